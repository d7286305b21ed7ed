//! Configuration files (`reconstruct --config`, the benchmarks' `--burst-config` and
//! `--denoise-config`), read by [`quantacolor::config_toml::parse`]: unknown keys are an error.

#![forbid(unsafe_code)]

use anyhow::{anyhow, Context, Result};
use serde::de::DeserializeOwned;
use std::path::Path;

/// The configuration in the TOML file `path`; the error names the file (and a key the
/// configuration does not have).
pub fn read<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    quantacolor::config_toml::parse(&text).map_err(|e| anyhow!("{}: {e}", path.display()))
}
