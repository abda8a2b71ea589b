//! Records the git commit of a build from a checkout as `SPRINGTIME_GIT_COMMIT` ("unknown"
//! outside one, or without git). Never fails the build.

use std::path::Path;
use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git")
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
        .filter(|s| !s.is_empty())
}

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    let checkout = Path::new(env!("CARGO_MANIFEST_DIR")).join(".git").exists();
    let commit = checkout
        .then(|| git(&["rev-parse", "HEAD"]))
        .flatten()
        .unwrap_or_else(|| "unknown".into());
    if checkout {
        // Rebuild the value when HEAD moves (a commit, a checkout); paths from git itself, as a
        // worktree's `.git` is a file pointing elsewhere.
        for what in ["HEAD", "packed-refs"] {
            if let Some(p) = git(&["rev-parse", "--git-path", what]) {
                println!("cargo:rerun-if-changed={p}");
            }
        }
        if let Some(r) =
            git(&["symbolic-ref", "-q", "HEAD"]).and_then(|r| git(&["rev-parse", "--git-path", &r]))
        {
            println!("cargo:rerun-if-changed={r}");
        }
    }
    println!("cargo:rustc-env=SPRINGTIME_GIT_COMMIT={commit}");
}
