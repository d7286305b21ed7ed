//! Parameters of the joint demosaic-merge (supplement §1.3, §7) and the checks made on them
//! and on the inputs before any sample is read.
#![forbid(unsafe_code)]

use super::*;
use serde::{Deserialize, Serialize};

/// Parameters of the joint demosaic-merge (supplement §1.3, §7).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AccumulateConfig {
    /// Output grid upsampling (1 = reference grid; 2 = super-resolution, supplement Fig. 6).
    pub scale: usize, // output px per reference px, per axis
    /// Largest gather radius (reference px): bounds the work per output pixel; wider kernels
    /// (sparse colour channels in flat areas) are truncated to this square.
    pub max_radius: usize, // 5 px
    /// Kernel truncation: samples with dᵀΩ⁻¹d above this are skipped (9 = 3 std).
    pub cutoff: f32, // 9 (squared Mahalanobis distance)
    /// Mean sample of W, as a fraction of the largest sample (1 for binary frames, full scale
    /// for multi-bit ones), above which W counts as saturated and the RGB estimate replaces it
    /// (supplement §7), provided R, G and B are below it.
    pub w_saturation: f32, // 0.98 (bit rate of binary frames)
    /// Binary frames: fewest frames without a detection (effective frames × (1 − p̂)) behind W's
    /// mean for its flux to be used as it is; below, W is blended towards wR·R + wG·G + wB·B
    /// where that is larger (`w_trust`). 0: supplement §7's rule (`w_saturation`).
    pub w_censoring_zeros: f32, // 100 frames
    /// Exponent α of the per-channel kernel widening Ω_c = Ω·scale_c^α, scale_c the area per
    /// site ([`KernelField::channel_scale`]): 1 widens a kernel by its channel's mean site
    /// spacing; sub-blocks at sub-pixel offsets sample sparse channels densely and need less.
    pub spacing_exponent: f32, // 1 (dimensionless)
    /// Phase bins per output pixel along each axis: sample positions are rounded to a grid this
    /// much finer than the output before the kernel regression ([`MergeAccumulator`]).
    pub bins_per_output_px: usize, // 2
    /// Phase bins per output pixel of the sparse channels (kernel scale at least
    /// `SPARSE_SCALE_RATIO` times the densest channel's: R, G, B of a W-rich CFA, none of
    /// Bayer); must divide `bins_per_output_px`. This project's speed trade-off.
    pub sparse_bins_per_output_px: usize, // 1
    /// Colour from ratios to the merged W, or to G without W (this project's own step,
    /// [`MergeAccumulator::colour_from_ratios`]): cancels the luminance edges that the wide
    /// kernels of the sparse colours smear into colour fringes.
    pub colour_ratios: bool, // true
}

impl Default for AccumulateConfig {
    fn default() -> Self {
        AccumulateConfig {
            scale: 1,
            max_radius: 5,
            cutoff: 9.0,
            w_saturation: 0.98,
            w_censoring_zeros: 100.0,
            spacing_exponent: 1.0,
            bins_per_output_px: 2,
            sparse_bins_per_output_px: 1,
            colour_ratios: true,
        }
    }
}

/// The checks of [`MergeAccumulator::new`] (without sub-blocks) and [`MergeAccumulator::add`]:
/// the configuration, the shapes of the kernel field and robustness maps, every sub-block.
pub(super) fn validate(
    sub_blocks: &[SubBlock],
    block_robustness: &[Array2<f32>],
    kernels: &KernelField,
    h: usize,
    w: usize,
    config: &AccumulateConfig,
    max_sample: f64,
) -> Result<()> {
    validate_config(config)?;
    if kernels.inv_cov.dim() != (h, w, 3) {
        return Err(Error::invalid(format!(
            "merge: kernel field has shape {:?}, expected ({h}, {w}, 3)",
            kernels.inv_cov.dim()
        )));
    }
    for (i, m) in block_robustness.iter().enumerate() {
        if m.dim() != (h, w) {
            return Err(Error::invalid(format!(
                "merge: robustness map of block {i} has shape {:?}, expected ({h}, {w})",
                m.dim()
            )));
        }
    }
    check_sub_blocks(sub_blocks, block_robustness.len(), h, w, max_sample)
}

/// The configuration's own checks: scale, bins and cutoff.
fn validate_config(config: &AccumulateConfig) -> Result<()> {
    if !(1..=8).contains(&config.scale) {
        return Err(Error::invalid(format!(
            "merge: output scale {} must be between 1 and 8",
            config.scale
        )));
    }
    if !(1..=8).contains(&config.bins_per_output_px) {
        return Err(Error::invalid(format!(
            "merge: bins per output pixel {} must be between 1 and 8",
            config.bins_per_output_px
        )));
    }
    if config.sparse_bins_per_output_px == 0
        || !config
            .bins_per_output_px
            .is_multiple_of(config.sparse_bins_per_output_px)
    {
        return Err(Error::invalid(format!(
            "merge: sparse-channel bins per output pixel {} must divide the bins per output \
             pixel {}",
            config.sparse_bins_per_output_px, config.bins_per_output_px
        )));
    }
    if !crate::merge::warp::positive(config.cutoff) {
        return Err(Error::invalid("merge: the kernel cutoff must be positive"));
    }
    Ok(())
}

/// Every sub-block's counts (shape, at most `max_sample` per frame), frames, motion and
/// robustness (shape, or a block index below `block_maps`).
fn check_sub_blocks(
    sub_blocks: &[SubBlock],
    block_maps: usize,
    h: usize,
    w: usize,
    max_sample: f64,
) -> Result<()> {
    // Whether any count of each sub-block exceeds its most (the scans of all sub-blocks in
    // parallel: 124 x 126k counts for /tmp/cap10k; the messages below in sub-block order).
    let exceeding: Vec<bool> = sub_blocks
        .par_iter()
        .map(|b| {
            let most = b.frames as f64 * max_sample;
            // A count exceeds `most` exactly when it exceeds its floor (counts are integers):
            // a quick scan (the largest count: a fold without an early exit, which the compiler
            // vectorises, unlike `any`); the position is found only for the message.
            match b.counts.as_slice() {
                Some(counts) if most < u32::MAX as f64 => {
                    let floor = most.max(0.0).floor() as u32;
                    counts.iter().fold(0, |m: u32, &c| m.max(c)) > floor
                }
                _ => true,
            }
        })
        .collect();
    for (k, b) in sub_blocks.iter().enumerate() {
        if b.counts.dim() != (h, w) {
            return Err(Error::invalid(format!(
                "merge: sub-block {k} counts have shape {:?}, the CFA is ({h}, {w})",
                b.counts.dim()
            )));
        }
        if b.frames == 0 {
            return Err(Error::invalid(format!(
                "merge: sub-block {k} has zero frames"
            )));
        }
        let most = b.frames as f64 * max_sample;
        if exceeding[k] {
            if let Some(((y, x), c)) = b.counts.indexed_iter().find(|(_, &c)| c as f64 > most) {
                return Err(Error::invalid(format!(
                    "merge: sub-block {k} sums to {c} at (y={y}, x={x}), more than {} frames of \
                     at most {max_sample} each",
                    b.frames
                )));
            }
        }
        b.flow.check(h, w, &format!("merge: sub-block {k}"))?;
        match &b.robustness {
            SubBlockRobustness::Full => {}
            SubBlockRobustness::Block(i) if *i >= block_maps => {
                return Err(Error::invalid(format!(
                    "merge: sub-block {k} refers to block {i}, but only {} robustness maps exist",
                    block_maps
                )));
            }
            SubBlockRobustness::Block(_) => {}
            SubBlockRobustness::Map(m) if m.dim() != (h, w) => {
                return Err(Error::invalid(format!(
                    "merge: sub-block {k} robustness has shape {:?}, expected ({h}, {w})",
                    m.dim()
                )));
            }
            SubBlockRobustness::Map(_) => {}
        }
    }
    Ok(())
}
