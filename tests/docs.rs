//! The book's command reference (`docs/src/reference/commands.md`) is held to the clap tree:
//! every command has its section, every section a command, and every long option of a command
//! appears in its section.

use std::collections::BTreeMap;
use std::path::Path;

use clap::CommandFactory;

fn commands(cmd: &clap::Command, path: String, out: &mut BTreeMap<String, Vec<String>>) {
    let options = cmd
        .get_arguments()
        .filter_map(|a| a.get_long().map(|l| format!("--{l}")))
        .filter(|o| o != "--help" && o != "--version")
        .collect();
    out.insert(path.clone(), options);
    for sub in cmd.get_subcommands().filter(|s| s.get_name() != "help") {
        commands(sub, format!("{path} {}", sub.get_name()), out);
    }
}

#[test]
fn the_command_reference_covers_every_command_and_option() {
    let page = "docs/src/reference/commands.md";
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(page)).unwrap();
    let mut sections = BTreeMap::new();
    let mut current: Option<String> = None;
    for line in text.lines() {
        if let Some(name) = line.strip_prefix("## springtime") {
            current = Some(format!("springtime{name}").trim().to_string());
            sections.insert(current.clone().unwrap(), String::new());
        } else if line.starts_with("## ") {
            current = None;
        } else if let Some(c) = &current {
            let body: &mut String = sections.get_mut(c).unwrap();
            body.push_str(line);
            body.push('\n');
        }
    }
    let mut tree = BTreeMap::new();
    commands(
        &springtime::cli::Cli::command(),
        "springtime".into(),
        &mut tree,
    );
    for (command, options) in &tree {
        let body = sections
            .get(command)
            .unwrap_or_else(|| panic!("{page} has no section `## {command}`"));
        for o in options {
            assert!(
                body.contains(o.as_str()),
                "{page}: the section of `{command}` does not mention {o}; regenerate it from \
                 `{command} --help`"
            );
        }
    }
    for command in sections.keys() {
        assert!(
            tree.contains_key(command),
            "{page} documents `{command}`, which is no command"
        );
    }
}
