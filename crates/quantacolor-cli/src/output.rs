//! Output directories that never hold partial results (the library's [`StagedDir`]).

#![forbid(unsafe_code)]

pub use quantacolor::output::StagedDir;

use anyhow::{bail, Context, Result};
use std::path::Path;

/// Refuses the output directory `out` (given as `flag`) when it already holds files, unless
/// `overwrite` (`--overwrite`): an earlier result is never replaced by accident. Checked before
/// any work, so a refused run costs nothing; the replacement itself stays atomic (files are
/// staged and moved into place when complete).
pub fn check_out_dir(out: &Path, flag: &str, overwrite: bool) -> Result<()> {
    if !out.exists() {
        return Ok(());
    }
    if !out.is_dir() {
        bail!("{flag} {}: exists and is not a directory", out.display());
    }
    let mut entries =
        std::fs::read_dir(out).with_context(|| format!("{flag} {}: cannot read", out.display()))?;
    if entries.next().is_some() && !overwrite {
        bail!(
            "{flag} {}: the directory already holds files (an earlier result?); choose another \
             {flag}, or give --overwrite to replace them",
            out.display()
        );
    }
    Ok(())
}

/// Set by `--quiet`: no success line.
static QUIET: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Silences [`say`] (`--quiet`).
pub fn set_quiet(quiet: bool) {
    QUIET.store(quiet, std::sync::atomic::Ordering::Relaxed);
}

/// A command's one line on success (what was written, where, how long), on stderr so that
/// stdout stays data; nothing with `--quiet`.
pub fn say(line: &str) {
    if !QUIET.load(std::sync::atomic::Ordering::Relaxed) {
        eprintln!("{line}");
    }
}
