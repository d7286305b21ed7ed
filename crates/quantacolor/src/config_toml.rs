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

/// The configuration `T` of TOML `text` laid over TOML `base` (both partial configs): keys of
/// `text` replace those of `base`, tables merge key by key; unknown keys are an error as in
/// [`parse`].
pub fn parse_over<T: DeserializeOwned>(base: &str, text: &str) -> Result<T> {
    let table = |text: &str| -> Result<toml::Table> {
        text.parse::<toml::Table>()
            .map_err(|e| Error::invalid(e.to_string().trim_end().to_string()))
    };
    let mut merged = table(base)?;
    merge_into(&mut merged, table(text)?);
    parse(&merged.to_string())
}

/// Lays `over` onto `base`: tables merge recursively, any other value replaces.
fn merge_into(base: &mut toml::Table, over: toml::Table) {
    for (key, value) in over {
        match (base.get_mut(&key), value) {
            (Some(toml::Value::Table(inner)), toml::Value::Table(value)) => {
                merge_into(inner, value)
            }
            (_, value) => {
                base.insert(key, value);
            }
        }
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
    fn a_config_over_a_base_keeps_the_base_where_it_is_silent() {
        let base = "[burst.refine]\npasses = 1\nmax_sub_block_motion_px = 0.7\n";
        let over = "method = \"naive\"\n[burst.refine]\npasses = 3\n";
        let config: ReconstructConfig = parse_over(base, over).unwrap();
        assert_eq!(config.method, crate::pipeline::Method::Naive);
        assert_eq!(config.burst.refine.passes, 3);
        assert_eq!(config.burst.refine.max_sub_block_motion_px, 0.7);
        let err = parse_over::<ReconstructConfig>(base, "[burst.refine]\npases = 2\n");
        assert!(err.unwrap_err().to_string().contains("burst.refine.pases"));
    }

    #[test]
    fn the_fast_profile_changes_only_its_own_settings() {
        use crate::pipeline::Profile;
        assert_eq!(
            Profile::Default.config().unwrap(),
            ReconstructConfig::default()
        );
        let fast = Profile::Fast.config().unwrap();
        let default = ReconstructConfig::default();
        assert_eq!(fast.burst.align, default.burst.align);
        assert_eq!(fast.burst.refine.passes, 1);
        assert_eq!(fast.burst.refine.max_sub_block_motion_px, 0.7);
        assert_eq!(fast.burst.merge, default.burst.merge);
        let trajectory = crate::align::trajectory::TrajectoryConfig {
            early_row_step: 2,
            informative_fraction: 0.9,
            ..default.burst.trajectory.clone()
        };
        assert_eq!(fast.burst.trajectory, trajectory);
        assert_ne!(fast.denoise.bm3d, default.denoise.bm3d);
        assert_eq!(fast.method, default.method);
        // A user's config goes over the profile.
        let mine = Profile::Fast
            .config_with("[burst.refine]\npasses = 2\n")
            .unwrap();
        assert_eq!(mine.burst.refine.passes, 2);
        assert_eq!(mine.burst.refine.max_sub_block_motion_px, 0.7);
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
