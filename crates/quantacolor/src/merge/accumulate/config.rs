//! Parameters of the joint demosaic-merge (supplement §1.3, §7) and the checks made on them
//! and on the inputs before any sample is read.
#![forbid(unsafe_code)]

use super::*;
use serde::{Deserialize, Serialize};

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
    /// Binary frames: fewest frames without a detection that a W pixel's merged mean must be
    /// expected to hold (effective frames × (1 − p̂)) for its flux to be used as it is; below,
    /// W is a lower bound of the flux (censored by saturation) and is blended towards the R,
    /// G, B estimate wR·R + wG·G + wB·B where that is larger, fully where no zero frame is left
    /// (see `w_trust`). 0 keeps supplement §7's rule (`w_saturation`), which multi-bit frames
    /// always use. Tuned on the quality suite's tuning set: ScanLines_StillLife (HDR
    /// handheld) 21.97 → 22.86 dB without denoising at 100 zero frames, 22.75 at 3, 22.83 at 10.
    pub w_censoring_zeros: f32, // 100 frames
    /// Exponent α of the per-channel kernel widening: Ω_c = Ω·scale_c^α with scale_c the area
    /// per site ([`KernelField::channel_scale`]). 1 widens each channel's kernel by its mean
    /// site spacing (right for a single frame); many sub-blocks at sub-pixel offsets sample
    /// sparse channels densely and need less. Default 1 (with `max_radius` 5): on simulated
    /// SPAD captures at 0.1 photons/pixel/frame (kodim07 static, chart handheld 512 and 1024
    /// frames) it beat 0.5 (radius 3) by +2.3, +0.2 and +0.5 dB: those captures are
    /// photon-noise limited. A noiseless synthetic burst with true flows prefers 0.5.
    pub spacing_exponent: f32, // 1 (dimensionless)
    /// Phase bins per output pixel along each axis: sample positions are rounded to a grid this
    /// much finer than the output before the kernel regression ([`MergeAccumulator`]).
    pub bins_per_output_px: usize, // 2
    /// Phase bins per output pixel along each axis for the sparse channels: those whose kernel
    /// scale (area per site to the power `spacing_exponent`) is at least [`SPARSE_SCALE_RATIO`]
    /// times the densest channel's (R, G and B of a W-rich CFA; none of Bayer). Their kernels
    /// are at least 1.5 times as wide as the densest channel's, so a coarser rounding of their
    /// sample positions costs them little, and their regression (most of the merge's work: the
    /// widest kernels) visits that many times fewer bins per axis. Must divide
    /// `bins_per_output_px`; equal to it, every channel takes the same bins. This project's
    /// speed trade-off ([`MergeAccumulator::finish`]).
    pub sparse_bins_per_output_px: usize, // 1
    /// Colour from ratios to W, or to G without W (this project's own step, not the paper's;
    /// the principle of colour-ratio demosaicking, Kimmel 1999, and of guided filtering, He et
    /// al. 2013): where the CFA has W and R, G, B, each colour's flux is divided by the merged W seen through
    /// that colour's own kernel and sample weights (the same regression over the same bins with
    /// every sample's counts replaced by the merged W at its position), and multiplied by the
    /// merged W at the pixel. A colour kernel is several pixels wide (its sites are sparse), so
    /// at a luminance edge it averages samples from both sides and the brighter side's colour
    /// bleeds into the darker (fringes, strongest in static captures where the sites never
    /// move); the ratio to W over the same samples cancels that luminance step. In flat
    /// regions the factor is 1. Measured (sRGB PSNR, border 16): `bench quality` means burst
    /// 27.70 → 27.87 dB tuning, 29.64 → 29.67 validation, chroma-BM3D 29.65 → 29.70 and
    /// 31.64 → 31.64 (kodim07 static +0.94 burst, +0.28 chroma-BM3D; no capture lower by more
    /// than 0.01 dB; 2x super-resolution gain +1.25 → +1.34 and +1.31 → +1.36 dB). Static
    /// captures of other photographs and seeds (`simulate --cfa colorspad --motion static`,
    /// default `reconstruct`): kodim04 512 frames +0.12, kodim12 512 +0.09, kodim22 2,000
    /// +0.99, ScanLines_Cannon HDR 2,000 +1.10, MultiResolution_Bonita HDR 2,000 +0.57, kodim12
    /// 10,000 +2.21 dB (the fringes outlast the photon noise); handheld kodim04 +0.02, pan
    /// kodim22 0.00. Cost: a second regression of R, G and B, about 0.035 s on the 10,000-frame
    /// chart of `bench speed` (4 % of the pipeline). Without W (Bayer) the densest colour, G,
    /// guides R and B, its noise gated ([`COLOUR_GUIDE_NOISE_GATE`]): `bench quality`'s Bayer
    /// captures kodim07 handheld burst +1.29, chroma-BM3D +0.33 dB (tuning), kodim04 handheld
    /// +0.28 and +0.07 (validation); other Bayer captures, default pipeline: kodim02 static
    /// 2,000 frames +0.96, kodim15 handheld 2,000 +0.57, MultiResolution_Bonita HDR static
    /// +0.74, kodim22 fast handheld 512 +0.01, ScanLines_Cannon HDR pan +0.71 dB.
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

pub(super) fn validate(
    sub_blocks: &[SubBlock],
    block_robustness: &[Array2<f32>],
    kernels: &KernelField,
    h: usize,
    w: usize,
    config: &AccumulateConfig,
    max_sample: f64,
) -> Result<()> {
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
            SubBlockRobustness::Block(i) if *i >= block_robustness.len() => {
                return Err(Error::invalid(format!(
                    "merge: sub-block {k} refers to block {i}, but only {} robustness maps exist",
                    block_robustness.len()
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
