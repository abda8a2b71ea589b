//! Every config shipped in `configs/` parses as the job it is for.

use springtime::settings::Job;
use std::path::Path;

#[test]
fn shipped_configs_parse() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            // A fold job (`springtime fold`) embeds a training config under [surrogate]; an
            // `xpbd estimate` job has a [truth] material; a `latent` job an [autoencoder].
            let text = std::fs::read_to_string(&path).unwrap();
            let table = text.parse::<toml::Table>().unwrap();
            let parsed = if table.contains_key("surrogate") {
                springtime::fold::FoldConfig::load(&path, &[]).map(|_| ())
            } else if table.contains_key("truth") {
                springtime::xpbd::estimate::XpbdConfig::load(&path, &[]).map(|_| ())
            } else if table.contains_key("autoencoder") {
                springtime::latent::LatentConfig::load(&path, &[]).map(|_| ())
            } else {
                springtime::config::Config::load(&path, &[]).map(|_| ())
            };
            parsed.unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
        }
    }
}

/// Every schema's `config --defaults KIND` text parses back to its template, which validates
/// (a template a user copies must be a working job), and the book's copy of it is current.
fn schema_holds<J: Job + PartialEq + std::fmt::Debug>() {
    let text = J::defaults_toml();
    let parsed = J::parse(&text, &[]).unwrap_or_else(|e| panic!("{}: {e:#}", J::KIND));
    assert_eq!(
        parsed,
        J::template(),
        "{}: the printed defaults differ",
        J::KIND
    );
    let book = format!("docs/src/reference/defaults/{}.toml", J::KIND);
    let shown = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(&book))
        .unwrap_or_default();
    assert!(
        shown == text,
        "{book} is not what the code prints; regenerate it with `springtime config --defaults {} > {book}`",
        J::KIND
    );
}

#[test]
fn every_schema_prints_defaults_that_load_back_and_the_book_shows_them() {
    schema_holds::<springtime::config::Config>();
    schema_holds::<springtime::fold::FoldConfig>();
    schema_holds::<springtime::xpbd::estimate::XpbdConfig>();
    schema_holds::<springtime::latent::LatentConfig>();
    schema_holds::<springtime::drape::scene::SceneFile>();
}

#[test]
fn the_command_line_prints_each_schema_and_refuses_an_unknown_kind() {
    let bin = env!("CARGO_BIN_EXE_springtime");
    let out = std::process::Command::new(bin)
        .args(["config", "--defaults", "xpbd"])
        .output()
        .unwrap();
    assert!(out.status.success());
    assert_eq!(
        String::from_utf8(out.stdout).unwrap(),
        <springtime::xpbd::estimate::XpbdConfig as Job>::defaults_toml()
    );
    let out = std::process::Command::new(bin)
        .args(["config", "--defaults", "cloth"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains("invalid value 'cloth'") && err.contains("fold"),
        "{err}"
    );
}
