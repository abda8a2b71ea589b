//! Every config shipped in `configs/` parses as the job it is for.

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
