//! Atomic file output, the one home for it: every output goes to a temporary file in the
//! destination's directory (a name unique across threads and processes) and is renamed into
//! place only when complete, so a reader never sees half a file and a failed write leaves any
//! previous file untouched. Every error names the file and the problem.
#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use std::fs::{self, OpenOptions};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// A fresh name `.{name}.{pid}-{n}.tmp` beside `path`, unique within this process and across
/// concurrent processes.
pub(crate) fn temp_sibling(path: &Path) -> Result<PathBuf> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let name = path
        .file_name()
        .ok_or_else(|| Error::invalid(format!("{} has no file name", path.display())))?;
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let tmp = format!(".{}.{}-{n}.tmp", name.to_string_lossy(), std::process::id());
    Ok(path.with_file_name(tmp))
}

/// Removes a temporary file or directory when dropped, unless [`TempGuard::keep`] was called:
/// an error (or a panic) half-way through a write leaves nothing behind.
pub(crate) struct TempGuard {
    path: PathBuf,
    is_dir: bool,
    armed: bool,
}

impl TempGuard {
    pub(crate) fn file(path: PathBuf) -> Self {
        TempGuard {
            path,
            is_dir: false,
            armed: true,
        }
    }

    pub(crate) fn dir(path: PathBuf) -> Self {
        TempGuard {
            path,
            is_dir: true,
            armed: true,
        }
    }

    pub(crate) fn path(&self) -> &Path {
        &self.path
    }

    /// The temporary has been renamed into place: do not delete it.
    pub(crate) fn keep(mut self) {
        self.armed = false;
    }
}

impl Drop for TempGuard {
    fn drop(&mut self) {
        if self.armed {
            // Best effort: the original error is what the caller needs to see.
            let _ = if self.is_dir {
                fs::remove_dir_all(&self.path)
            } else {
                fs::remove_file(&self.path)
            };
        }
    }
}

/// Writes `path` atomically: `write` fills a temporary file in the same directory, which is then
/// renamed over `path`. On any error the temporary file is removed and an existing `path` is left
/// untouched. No fsync (see [`write_atomic_synced`]).
pub fn write_atomic<F>(path: impl AsRef<Path>, write: F) -> Result<()>
where
    F: FnOnce(&mut dyn Write) -> io::Result<()>,
{
    write_atomic_with(path.as_ref(), false, write)
}

/// [`write_atomic`], and the file's data is flushed to the disk (fsync) before the rename, so a
/// crash cannot leave an empty file under the final name.
pub fn write_atomic_synced<F>(path: impl AsRef<Path>, write: F) -> Result<()>
where
    F: FnOnce(&mut dyn Write) -> io::Result<()>,
{
    write_atomic_with(path.as_ref(), true, write)
}

fn write_atomic_with<F>(path: &Path, fsync: bool, write: F) -> Result<()>
where
    F: FnOnce(&mut dyn Write) -> io::Result<()>,
{
    let tmp = temp_sibling(path)?;
    let file = OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&tmp)
        .map_err(|e| Error::io(path, e))?;
    let guard = TempGuard::file(tmp);
    let mut out = BufWriter::with_capacity(1 << 20, file);
    write(&mut out).map_err(|e| Error::io(path, e))?;
    let file = out
        .into_inner()
        .map_err(|e| Error::io(path, e.into_error()))?;
    if fsync {
        file.sync_all().map_err(|e| Error::io(path, e))?;
    }
    drop(file);
    fs::rename(guard.path(), path).map_err(|e| Error::io(path, e))?;
    guard.keep();
    Ok(())
}
