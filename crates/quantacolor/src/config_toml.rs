//! Configuration tables as TOML text (`reconstruct --config`, the benchmarks' config files, the
//! Python `config=` dicts): missing keys take their defaults, unknown keys are an error, so that
//! a misspelt key cannot silently leave a default in place.
#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use serde::de::DeserializeOwned;

/// The configuration `T` in TOML `text`; the error names a key `T` does not have by its dotted
/// path.
pub fn parse<T: DeserializeOwned>(text: &str) -> Result<T> {
    let mut unknown = Vec::new();
    let value: T = serde_ignored::deserialize(toml::Deserializer::new(text), |key| {
        unknown.push(key.to_string())
    })
    .map_err(|e| Error::invalid(e.to_string().trim_end().to_string()))?;
    match unknown.as_slice() {
        [] => Ok(value),
        keys => Err(Error::invalid(format!(
            "unknown key{} {} (report.toml lists every key under [config])",
            if keys.len() > 1 { "s" } else { "" },
            keys.iter()
                .map(|k| format!("`{k}`"))
                .collect::<Vec<_>>()
                .join(", ")
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::ReconstructConfig;

    #[test]
    fn a_partial_config_keeps_the_other_defaults() {
        let config: ReconstructConfig = parse("[burst.refine]\npasses = 1\n").unwrap();
        let mut expected = ReconstructConfig::default();
        expected.burst.refine.passes = 1;
        assert_eq!(
            toml::to_string(&config).unwrap(),
            toml::to_string(&expected).unwrap()
        );
    }

    #[test]
    fn a_misspelt_key_is_named() {
        let err = parse::<ReconstructConfig>("[burst.align.blocks]\nmin_block = 0\n")
            .unwrap_err()
            .to_string();
        assert!(err.contains("`burst.align.blocks.min_block`"), "{err}");
    }

    #[test]
    fn a_value_of_the_wrong_type_is_shown_with_its_key() {
        let err = parse::<ReconstructConfig>("[denoise]\nluma_gain = \"x\"\n")
            .unwrap_err()
            .to_string();
        assert!(err.contains("luma_gain"), "{err}");
    }

    #[test]
    fn the_full_default_config_reads_back() {
        let text = toml::to_string(&ReconstructConfig::default()).unwrap();
        let config: ReconstructConfig = parse(&text).unwrap();
        assert_eq!(toml::to_string(&config).unwrap(), text);
    }
}
