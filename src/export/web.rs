//! `springtime export RUN --format web`: a folder that opens offline in a browser and simulates
//! the surrogate live. The page and its scripts live in the repository's `web/` folder (see
//! `web/README.md`) and are embedded in the binary; the exporter writes them beside the run's
//! `surrogate.json` and `surrogate.js` (the same JSON as a script, since browsers refuse to
//! `fetch()` a `file://` URL).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// The page's files: path in the export, contents.
const ASSETS: &[(&str, &[u8])] = &[
    (
        "index.html",
        include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/web/index.html")),
    ),
    (
        "src/sim.js",
        include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/web/src/sim.js")),
    ),
    (
        "src/app.js",
        include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/web/src/app.js")),
    ),
    (
        "vendor/three.min.js",
        include_bytes!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/web/vendor/three.min.js"
        )),
    ),
    (
        "vendor/three.LICENSE",
        include_bytes!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/web/vendor/three.LICENSE"
        )),
    ),
];

/// `surrogate.js`, the script that hands `surrogate.json` to the page.
pub const SCRIPT: &str = "surrogate.js";

/// Every file the page adds to `out` (besides `surrogate.json` and `surrogate.npz`).
pub fn files(out: &Path) -> Vec<PathBuf> {
    ASSETS
        .iter()
        .map(|(name, _)| out.join(name))
        .chain(std::iter::once(out.join(SCRIPT)))
        .collect()
}

/// Writes the page's files and `surrogate.js` (from the text of `surrogate.json`) into `out`.
pub fn write(out: &Path, surrogate_json: &str) -> Result<Vec<PathBuf>> {
    let mut written = Vec::new();
    for (name, bytes) in ASSETS {
        let path = out.join(name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        crate::io::write_atomic(&path, |mut f| {
            use std::io::Write;
            f.write_all(bytes)?;
            Ok(())
        })?;
        written.push(path);
    }
    let script = out.join(SCRIPT);
    crate::io::write_text(
        &script,
        &format!(
            "window.SPRINGTIME_SURROGATE = {};\n",
            surrogate_json.trim_end()
        ),
    )?;
    written.push(script);
    Ok(written)
}
