//! The Python bindings end to end: `pip install ./python` into a fresh virtual environment,
//! then `pytest tests/python` (which trains, loads, simulates and evaluates through
//! `import springtime` and compares with this build's `springtime` binary).
//!
//! Needs `python3` with `venv` and a package index for maturin, NumPy and pytest. Where they are
//! missing the test says so and passes, unless `SPRINGTIME_REQUIRE_PYTHON=1` (CI sets it), which
//! makes a missing Python an error.

use std::path::Path;
use std::process::Command;

fn required() -> bool {
    std::env::var("SPRINGTIME_REQUIRE_PYTHON").is_ok_and(|v| v == "1")
}

/// Runs `cmd`, echoing its output; panics naming `what` when it fails.
fn run(what: &str, cmd: &mut Command) {
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("{what}: cannot start: {e}"));
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    println!("{text}");
    assert!(
        out.status.success(),
        "{what} failed ({}):\n{text}",
        out.status
    );
}

#[test]
fn python_bindings_install_and_pass_their_tests() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let venv = Path::new(env!("CARGO_TARGET_TMPDIR")).join("python-venv");
    let _ = std::fs::remove_dir_all(&venv);
    let made = Command::new("python3")
        .args(["-m", "venv"])
        .arg(&venv)
        .output();
    match made {
        Ok(out) if out.status.success() => {}
        other => {
            let why = match other {
                Ok(out) => String::from_utf8_lossy(&out.stderr).into_owned(),
                Err(e) => e.to_string(),
            };
            assert!(
                !required(),
                "SPRINGTIME_REQUIRE_PYTHON=1 but no Python virtual environment: {why}"
            );
            eprintln!("skipped: no `python3 -m venv` ({why})");
            return;
        }
    }
    let python = venv.join("bin/python");
    run(
        "pip install ./python pytest mujoco ray",
        Command::new(&python)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
            ])
            .arg(root.join("python"))
            .arg("pytest")
            // The cross-simulator case (tests/python/test_foreign.py): MuJoCo's flex cloth, the
            // bench's lightest simulator (a 6 MB wheel).
            .arg("mujoco==4.0.0")
            // `springtime.sweep` on a local Ray cluster (tests/python/test_sweep.py); the
            // package's optional `ray` extra, pinned here.
            .arg("ray==2.60.0")
            .current_dir(root),
    );
    run(
        "pytest tests/python",
        Command::new(&python)
            .args(["-m", "pytest", "-q", "-p", "no:cacheprovider"])
            .arg(root.join("tests/python"))
            .env("SPRINGTIME_BIN", env!("CARGO_BIN_EXE_springtime"))
            .current_dir(root),
    );
}
