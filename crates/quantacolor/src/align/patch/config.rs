//! Settings of the hierarchical alignment ([`PatchConfig`]) and the patch distance of each
//! pyramid level ([`Norm`]): HDR+ (Hasinoff et al. 2016 §4) and Ma et al. 2020 §4 style levels.
#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Patch distance used by the integer search on one pyramid level.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Norm {
    /// Sum of absolute differences: robust to the few outliers of fine, noisy levels.
    L1,
    /// Sum of squared differences: smoother cost on the coarse, averaged levels.
    L2,
}

/// Settings of the hierarchical patch alignment. Level 0 is the finest (the grey image itself);
/// the vectors are indexed by level and must have equal lengths.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PatchConfig {
    /// Box-aggregation factor of each level relative to the previous one (level 0: 1).
    pub downsample_factors: Vec<usize>,
    /// Tile size of each level, px of that level; tiles overlap by half (stride = size / 2).
    pub tile_sizes: Vec<usize>,
    /// Search radius of each level, px of that level: offsets in [−r, r]² around the seed.
    pub search_radii: Vec<usize>,
    /// Patch distance of each level.
    pub norms: Vec<Norm>,
    /// Lucas–Kanade iterations on level 0 (0 keeps integer offsets).
    pub lk_iterations: usize,
    /// Gaussian σ (px) smoothing the grey images before the pyramid is built; reduces the
    /// photon noise of low-light blocks in the gradients Lucas–Kanade uses (0 disables).
    pub presmooth_sigma: f32,
}

impl Default for PatchConfig {
    fn default() -> Self {
        // HDR+ / QBP 2020 style: factors [1, 2, 4, 4] (total 32), 16 px tiles on the finest level
        // and 8 px on the coarse ones, radii growing toward the coarse levels (±297 px in all).
        PatchConfig {
            downsample_factors: vec![1, 2, 4, 4],
            tile_sizes: vec![16, 8, 8, 8],
            search_radii: vec![1, 4, 4, 8],
            norms: vec![Norm::L1, Norm::L2, Norm::L2, Norm::L2],
            lk_iterations: 5,
            presmooth_sigma: 1.0,
        }
    }
}

impl PatchConfig {
    /// Checks that the per-level vectors agree and hold usable values.
    pub fn validate(&self) -> Result<()> {
        let n = self.downsample_factors.len();
        if n == 0 {
            return Err(Error::invalid(
                "patch alignment needs at least one pyramid level",
            ));
        }
        if self.tile_sizes.len() != n || self.search_radii.len() != n || self.norms.len() != n {
            return Err(Error::invalid(format!(
                "pyramid settings disagree in length: {} factors, {} tile sizes, {} radii, {} norms",
                n,
                self.tile_sizes.len(),
                self.search_radii.len(),
                self.norms.len()
            )));
        }
        if self.downsample_factors.contains(&0) {
            return Err(Error::invalid("downsample factors must be at least 1"));
        }
        if self.tile_sizes.iter().any(|&t| t < 2) {
            return Err(Error::invalid("tile sizes must be at least 2 px"));
        }
        if self.presmooth_sigma.is_nan() || self.presmooth_sigma < 0.0 {
            return Err(Error::invalid("presmooth sigma must be >= 0"));
        }
        Ok(())
    }
}
