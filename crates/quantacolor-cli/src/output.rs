//! Output directories that never hold partial results (the library's [`StagedDir`]).

#![forbid(unsafe_code)]

pub use quantacolor::output::StagedDir;

use anyhow::{anyhow, Result};
use std::path::Path;

/// Refuses the output directory `out` (given as `flag`) when it already holds files, unless
/// `overwrite` (`--overwrite`): the library's [`quantacolor::output::check_out_dir`], with the
/// flag in front of the message.
pub fn check_out_dir(out: &Path, flag: &str, overwrite: bool) -> Result<()> {
    quantacolor::output::check_out_dir(out, flag, "give --overwrite", overwrite)
        .map_err(|e| anyhow!("{flag} {e}"))
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
