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
