//! Configuration files (`reconstruct --config`, the benchmarks' `--burst-config` and
//! `--denoise-config`), read by [`quantacolor::config_toml::parse`]: unknown keys are an error.

#![forbid(unsafe_code)]

use anyhow::{anyhow, Context, Result};
use serde::de::DeserializeOwned;
use std::path::Path;

/// The configuration in the TOML file `path`; the error names the file (and a key the
/// configuration does not have).
pub fn read<T: DeserializeOwned>(path: &Path) -> Result<T> {
    quantacolor::config_toml::parse(&text(path)?).map_err(|e| anyhow!("{}: {e}", path.display()))
}

/// The text of the configuration file `path`.
fn text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).with_context(|| format!("{}: cannot read", path.display()))
}

/// The configuration in the TOML file `path` laid over the TOML `base` (a profile's settings,
/// [`quantacolor::config_toml::parse_over`]); the error names the file.
pub fn read_over<T: DeserializeOwned>(base: &str, path: &Path) -> Result<T> {
    quantacolor::config_toml::parse_over(base, &text(path)?)
        .map_err(|e| anyhow!("{}: {e}", path.display()))
}
