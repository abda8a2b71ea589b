//! Atomic file output: every artifact is written to a temporary file in its directory and
//! renamed into place, so a crash or a full disk never leaves a half-written file behind.

use std::fs::File;
use std::path::Path;

use anyhow::{Context, Result};

/// Refuses to overwrite an existing `path` unless `force`: the error names the file and
/// `--force`.
pub fn refuse_overwrite(path: &Path, force: bool) -> Result<()> {
    if path.exists() && !force {
        anyhow::bail!("{} exists; pass --force to overwrite it", path.display());
    }
    Ok(())
}

/// Writes `path` through `write`, atomically: into a uniquely named temporary file in the same
/// directory, renamed over `path` only when `write` succeeded; on any failure (or a panic) the
/// temporary file is removed and `path` is untouched.
pub fn write_atomic(path: &Path, write: impl FnOnce(File) -> Result<()>) -> Result<()> {
    let tmp = temp_beside(path)?;
    let file = tmp
        .as_file()
        .try_clone()
        .with_context(|| format!("cannot write {}", tmp.path().display()))?;
    write(file).with_context(|| format!("cannot write {}", path.display()))?;
    persist(tmp, path)
}

/// Writes a text file atomically.
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    use std::io::Write;
    write_atomic(path, |mut f| {
        f.write_all(text.as_bytes())?;
        f.sync_all()?;
        Ok(())
    })
}

/// Reads a JSON file, naming the file in any error.
pub fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{} is not valid", path.display()))
}

/// Writes a value as pretty JSON, atomically.
pub fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    write_text(path, &(serde_json::to_string_pretty(value)? + "\n"))
}

/// Writes through a temporary path that Burn's own writers fill, then renames it into place.
pub(crate) fn write_atomic_with_path(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<()>,
) -> Result<()> {
    let tmp = temp_beside(path)?;
    write(tmp.path()).with_context(|| format!("cannot write {}", path.display()))?;
    persist(tmp, path)
}

/// A new temporary file `.<name>.<random>.tmp` in `path`'s directory (created if needed),
/// readable like any other output (tempfile's default is owner-only).
fn temp_beside(path: &Path) -> Result<tempfile::NamedTempFile> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let prefix = format!(".{name}.");
    let mut builder = tempfile::Builder::new();
    builder.prefix(&prefix).suffix(".tmp");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o644));
    }
    builder.tempfile_in(dir).with_context(|| {
        format!(
            "cannot write {}: cannot create a file in {}",
            path.display(),
            dir.display()
        )
    })
}

/// Renames the finished temporary file over `path`.
fn persist(tmp: tempfile::NamedTempFile, path: &Path) -> Result<()> {
    tmp.persist(path)
        .map(|_| ())
        .map_err(|e| anyhow::Error::new(e.error))
        .with_context(|| format!("cannot move the new {} into place", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn listing(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn a_write_that_fails_midway_leaves_the_old_file_and_no_partial_one() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("eval.json");
        write_text(&path, "old\n").unwrap();
        // The disk fills after part of the file is written.
        let e = write_atomic(&path, |mut f| {
            use std::io::Write;
            f.write_all(b"{\"half\": ")?;
            Err(std::io::Error::from(std::io::ErrorKind::StorageFull).into())
        })
        .unwrap_err();
        assert!(format!("{e:#}").contains("eval.json"), "{e:#}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "old\n");
        assert_eq!(listing(dir.path()), ["eval.json"]);
        // The same through a path-taking writer (Burn's).
        let e = write_atomic_with_path(&path, |tmp| {
            std::fs::write(tmp, "partial")?;
            anyhow::bail!("no space left")
        })
        .unwrap_err();
        assert!(format!("{e:#}").contains("no space left"), "{e:#}");
        assert_eq!(listing(dir.path()), ["eval.json"]);
        // A panicking writer cleans up too.
        let caught = std::panic::catch_unwind(|| {
            let _ = write_atomic(&path, |_| panic!("writer panicked"));
        });
        assert!(caught.is_err());
        assert_eq!(listing(dir.path()), ["eval.json"]);
        write_text(&path, "new\n").unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "new\n");
    }

    #[test]
    fn a_write_into_a_read_only_directory_is_a_clear_error() {
        // sysfs refuses new files even to root; a directory without write permission refuses
        // everyone else.
        let mut targets = vec![Path::new("/sys/springtime-read-only-test.json").to_path_buf()];
        let dir = tempfile::tempdir().unwrap();
        let ro = dir.path().join("read-only");
        std::fs::create_dir(&ro).unwrap();
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
            if std::fs::write(ro.join("probe"), "x").is_err() {
                targets.push(ro.join("run.json"));
            }
        }
        let mut tried = 0;
        for path in targets {
            if !path.parent().is_some_and(Path::exists) {
                continue;
            }
            tried += 1;
            let e = write_text(&path, "{}\n").unwrap_err();
            let msg = format!("{e:#}");
            assert!(msg.contains(&path.display().to_string()), "{msg}");
            assert!(!path.exists());
        }
        assert!(tried > 0, "no read-only directory to test with");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o755)).unwrap();
        }
        let left: Vec<String> = listing(&ro).into_iter().filter(|n| n != "probe").collect();
        assert!(left.is_empty(), "{left:?}");
    }
}

/// `.<name>.<suffix>` in `dir`'s parent (`name` is `dir`'s last component, `fallback` without
/// one): where a lock guarding `dir` lives, so that `dir` itself may be cleared and recreated.
pub fn lock_path_beside(dir: &Path, suffix: &str, fallback: &str) -> std::path::PathBuf {
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| fallback.into());
    let parent = dir
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    parent.join(format!(".{name}.{suffix}"))
}

/// An exclusive operating-system lock on a file, held until dropped; the operating system
/// releases it when the process ends, however it ends.
#[derive(Debug)]
pub struct FileLock {
    _file: File,
}

impl FileLock {
    /// Opens (creating it and its folder) the lock file `path`.
    fn open(path: &Path) -> Result<File> {
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("cannot create {}", parent.display()))?;
        }
        std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(path)
            .with_context(|| format!("cannot open the lock {}", path.display()))
    }

    /// Takes the lock `path`, or `None` when another process holds it.
    pub fn try_take(path: &Path) -> Result<Option<Self>> {
        let file = Self::open(path)?;
        match file.try_lock() {
            Ok(()) => Ok(Some(Self { _file: file })),
            Err(std::fs::TryLockError::WouldBlock) => Ok(None),
            Err(std::fs::TryLockError::Error(e)) => {
                Err(e).with_context(|| format!("cannot lock {}", path.display()))
            }
        }
    }

    /// Takes the lock `path`, waiting while another process holds it.
    pub fn wait(path: &Path) -> Result<Self> {
        let file = Self::open(path)?;
        file.lock()
            .with_context(|| format!("cannot lock {}", path.display()))?;
        Ok(Self { _file: file })
    }
}
