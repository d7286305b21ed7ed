//! Joint demosaic and merge by kernel regression (paper §4.2, Fig. 4; supplement Eq. 1–3;
//! Wronski et al. 2019 Eq. 1; Takeda et al. 2007): every output pixel gathers, per channel, the
//! CFA sites of every sub-block that land near it after motion compensation, weighted by the
//! anisotropic kernel and the sub-block's robustness, then inverts the pixel's response on the
//! accumulated counts: the Bernoulli MLE of paper Eq. 6 for binary frames, the Gaussian–Poisson
//! inversion for multi-bit frames (§6.1; [`crate::model::PixelModel`]). Samples are first
//! splatted into sub-pixel phase bins on the reference grid, so the regression runs once
//! whatever the number of sub-blocks (this project's implementation choice; the sum it
//! computes is the paper's).
//!
//! The steps, one file each: `sub_block` (the inputs: sub-block counts and motion), `config`
//! (parameters and their checks), `positions` and `targets` (where each site lands: the
//! inverse of its sub-block's flow, and its phase bin), `bins` (the splat into the phase
//! bins), `weights` and `regression` (the kernel regression of supplement Eq. 1–3 over the
//! bins), `finish` (per-channel fluxes, paper Eq. 6, hole filling and the W saturation
//! fallback of supplement §7, ahead of Eq. 8) and `colour_ratios` (this project's own colour
//! step); the AVX2 kernels in `x86` beside their portable reference.

mod bins;
mod colour_ratios;
mod config;
mod finish;
mod flux_domain;
mod positions;
mod regression;
mod sub_block;
mod targets;
mod weights;
#[cfg(target_arch = "x86_64")]
mod x86;

pub use config::AccumulateConfig;
pub use finish::MergedPlanes;
pub use positions::reference_position;
pub use sub_block::{SubBlock, SubBlockMotion, SubBlockRobustness};

use super::kernels::KernelField;
use crate::cfa::{Cfa, Channel};
use crate::cpu;
use crate::error::{Error, Result};
use crate::fastmath;
use crate::filters::bilinear;
use crate::filters::normalized_convolution_nan as normalized_convolution;
use crate::model::PixelModel;
use bins::BinGrid;
use config::validate;
use ndarray::{Array2, Array3, Axis};
use positions::{index_in, reference_positions, round_half_away, round_half_away_trunc};
use rayon::prelude::*;
use regression::Gather;
use sub_block::affine_position;
use targets::TargetGrid;
use weights::{make_weights, snap_scales, ChannelPlan};

/// Lanes of the vectorised kernel regression (eight f32: one AVX2 register).
const LANES: usize = 8;
/// Planes per channel: Σ r·counts, Σ r·F, Σ r²·F, and Σ r·F·λ_bin (each bin's own flux, filled
/// by [`MergeAccumulator::fill_flux_planes`] before the regression; `flux_domain`).
const PLANES: usize = 4;
/// The first [`PLANES`] that hold counts and trials (all but the flux plane): what a regression
/// without the flux-domain floor reads.
const RATE_PLANES: usize = 3;
/// Sums per bin: 4 channels × [`PLANES`].
const SUMS: usize = 4 * PLANES;

/// Streaming form of [`demosaic_merge`] whose cost does not grow with the number of sub-blocks
/// times the kernel footprint, so motion at (close to) frame granularity costs about as much as
/// motion per block.
///
/// [`MergeAccumulator::add`] only *splats*: every CFA site of a sub-block is moved to its
/// reference-grid position p (the inverse of the sub-block's flow, by fixed-point iteration)
/// and its robustness-weighted count and frames are added to the phase bin nearest p, per
/// channel, on a grid `bins_per_output_px` times finer than the output grid. That is O(H·W) per
/// sub-block, so frame-granular motion (many short sub-blocks) is cheap.
/// [`MergeAccumulator::finish`] then runs the kernel regression of supplement Eq. 1–3 once,
/// over the bins instead of the samples. A sample's position is rounded to its bin centre
/// (at most 1/(2·bins) output px away: a uniform error of std 0.14 px for 2 bins, small
/// against the kernels' ≥ 0.25 px std); the test `fast_merge_matches_the_per_sample_merge`
/// compares it with the direct per-sample sum.
///
/// Memory: 16 f32 per bin, about 35 MB for 496x254 at scale 1 and 133 MB at scale 2,
/// whatever the number of frames. The bins are stored as planes (structure of arrays: one row
/// of bins per channel and sum), so the regression reads a row segment of bins as contiguous
/// lanes and evaluates eight kernel weights at once ([`gather_row`]).
pub struct MergeAccumulator<'a> {
    cfa: &'a Cfa,
    kernels: &'a KernelField,
    config: AccumulateConfig,
    model: PixelModel,
    codes: Vec<u8>,
    /// Sites never splatted (hot pixels), row-major (H·W).
    excluded: Option<Vec<bool>>,
    channel_scale: [f32; 4],
    /// Each channel's kernel factor as a multiple of the sparsest channel's (0: its own;
    /// [`snap_scales`]).
    multiples: [u32; 4],
    inv_scale: [f32; 4],
    /// Gather radius of the regression (reference px).
    radius: f32,
    /// Bins per reference px along each axis.
    bins_per_px: usize,
    /// Reference px of margin around the image covered by bins (samples landing outside the
    /// image still reach border pixels).
    margin: usize,
    bins_h: usize,
    bins_w: usize,
    /// Floats per plane row: `bins_w` padded so that eight lanes read from any bin of a row
    /// stay inside the row ([`LANES`]).
    stride: usize,
    /// bins[((by·4 + c)·PLANES + k)·stride + bx] with k = {0: Σ r·counts, 1: Σ r·F, 2: Σ r²·F,
    /// 3: Σ r·F·λ_bin} (padding columns stay 0); bin (by, bx) sits at reference position
    /// (by/u − margin, bx/u − margin).
    bins: Vec<f32>,
    /// The instruction set of the splat's targets and of the regression, taken once by
    /// [`MergeAccumulator::new`] ([`cpu::Isa::current`]).
    isa: cpu::Isa,
    /// Scratch of [`MergeAccumulator::add`], kept between calls: the target of every site of
    /// a group of sub-blocks, and the range of targets of each of their rows.
    targets: Vec<(u32, f32)>,
    row_bins: Vec<(u32, u32)>,
}

impl<'a> MergeAccumulator<'a> {
    /// Empty accumulators for `cfa` with the kernels of the reference, for frames whose
    /// samples follow `model` (a plain number: binary frames with that many dark counts per
    /// frame).
    pub fn new(
        cfa: &'a Cfa,
        kernels: &'a KernelField,
        config: &AccumulateConfig,
        model: impl Into<PixelModel>,
    ) -> Result<Self> {
        let (h, w) = (cfa.height(), cfa.width());
        let model: PixelModel = model.into();
        validate(&[], &[], kernels, h, w, config, model.max_sample())?;
        let (channel_scale, multiples) = snap_scales(KernelField::channel_scale(cfa).map(|s| {
            if s > 0.0 {
                s.powf(config.spacing_exponent)
            } else {
                0.0
            }
        }));
        let inv_scale: [f32; 4] = channel_scale.map(|s| if s > 0.0 { 1.0 / s } else { 0.0 });
        let max_scale = channel_scale.iter().copied().fold(0.0f32, f32::max);
        let radius = (3.0 * kernels.max_std * max_scale.sqrt())
            .ceil()
            .clamp(1.0, config.max_radius.max(1) as f32);
        let bins_per_px = config.scale * config.bins_per_output_px;
        let margin = radius as usize;
        let bins_h = (h - 1 + 2 * margin) * bins_per_px + 1;
        let bins_w = (w - 1 + 2 * margin) * bins_per_px + 1;
        let stride = (bins_w + LANES - 1).next_multiple_of(LANES);
        let len = bins_h
            .checked_mul(SUMS * stride)
            .filter(|&n| n < u32::MAX as usize)
            .ok_or_else(|| {
                Error::invalid(format!(
                    "merge: a {h}x{w} image at scale {} with {} bins per output pixel needs \
                     more phase bins than the merge can index; lower the scale or the bins",
                    config.scale, config.bins_per_output_px
                ))
            })?;
        Ok(MergeAccumulator {
            cfa,
            kernels,
            config: config.clone(),
            model,
            codes: cfa.codes().iter().copied().collect(),
            excluded: None,
            channel_scale,
            multiples,
            inv_scale,
            radius,
            bins_per_px,
            margin,
            bins_h,
            bins_w,
            stride,
            // Zeroed by all threads (35 MB for 496x254: ~13 ms of one thread's memset).
            bins: cpu::zeroed_par(len),
            isa: cpu::Isa::current(),
            targets: Vec::new(),
            row_bins: Vec::new(),
        })
    }

    /// Sites (e.g. hot pixels) whose counts are never merged; their pixels are estimated from
    /// the other sites (and, under motion, from the other sub-blocks' sites landing there).
    pub fn exclude_sites(&mut self, mask: &Array2<bool>) -> Result<()> {
        if mask.dim() != self.cfa.codes().dim() {
            return Err(Error::invalid(format!(
                "merge: excluded-site mask has shape {:?}, the CFA is {:?}",
                mask.dim(),
                self.cfa.codes().dim()
            )));
        }
        self.excluded = Some(mask.iter().copied().collect());
        Ok(())
    }
}

/// Joint demosaic and merge of `sub_blocks` (supplement Eq. 1–3).
///
/// For output pixel p (reference coordinates; on a `scale` grid, pixel (Y, X) sits at
/// ((Y + ½)/s − ½, (X + ½)/s − ½)), every CFA site q of channel c of every sub-block k is
/// placed at its reference position p_q (the p' with p' + flow_k(p') = q) and contributes
/// weight w = exp(−½ dᵀ Ω_c⁻¹ d)·R_k(p_q) with d = p_q − p, Ω_c = Ω(p)·scale_c^α
/// ([`KernelField::channel_scale`], α = `spacing_exponent`), within `max_radius`:
/// num_c += w·counts_k(q), den_c += w·frames_k. Then p̂_c = num_c/den_c and
/// λ_c = mle_flux(p̂_c·N, N, dark) with the effective number of frames N = (Σ w·F)² / Σ w²·F
/// (Kish), so the saturation clamp of the MLE acts at the right count (multi-bit frames: the
/// Gaussian–Poisson inversion of `model`, [`PixelModel::flux`]). Kernels are read at
/// the nearest reference pixel of p, robustness at the nearest of p_q, and p_q is rounded to
/// the phase bins of [`MergeAccumulator`]. Pixels that no sample reaches are filled by
/// normalized convolution of their plane. Where W is censored by saturation (binary frames:
/// fewer than `w_censoring_zeros` frames without a detection behind its mean; multi-bit: p̂
/// above `w_saturation`) and wR·R + wG·G + wB·B is larger, W is blended towards that
/// (supplement §7, generalised), so Eq. 8 keeps the RGB estimate there.
pub fn demosaic_merge(
    sub_blocks: &[SubBlock],
    block_robustness: &[Array2<f32>],
    cfa: &Cfa,
    kernels: &KernelField,
    model: impl Into<PixelModel>,
    w_weights: [f64; 3],
    config: &AccumulateConfig,
) -> Result<MergedPlanes> {
    if sub_blocks.is_empty() {
        return Err(Error::invalid("merge: no sub-blocks given"));
    }
    let mut acc = MergeAccumulator::new(cfa, kernels, config, model)?;
    acc.add(sub_blocks, block_robustness)?;
    Ok(acc.finish(w_weights))
}

#[cfg(test)]
mod test_oracle;
#[cfg(test)]
mod tests;
