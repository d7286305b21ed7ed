//! Motion-compensated merge of a colour quanta burst (paper §4.2, Fig. 4; supplement §1.2–1.3).
//!
//! Stages, each a public function with its own config struct (paper defaults):
//! 1. [`reference_image`]: warp grey block images to the reference grid and merge them by a
//!    Wiener filter over DFT tiles (supplement §1.2; HDR+).
//! 2. [`kernel_field`]: anisotropic kernel covariances from the reference's structure tensor
//!    (Wronski et al. 2019).
//! 3. [`robustness`]: per-block weights that reject content the reference does not confirm
//!    (supplement Eq. 4–6).
//!    [`merge_guide`] runs stages 1–3.
//! 4. [`demosaic_merge`] / [`MergeAccumulator`]: joint demosaic and merge of sub-block counts
//!    by kernel regression (supplement Eq. 1–3) over sub-pixel phase bins, MLE flux per channel
//!    (paper Eq. 6), optional super-resolution grid, W-saturation fallback (supplement §7).
//! 5. [`merge_burst`]: all of the above, then the RGBW combination of paper Eq. 8
//!    ([`crate::rgbw::combine_rgbw`]). [`crate::burst`] runs the same functions, streaming
//!    the sub-blocks through the accumulator.
//!
//! Alignment is not part of this module: every stage takes dense per-pixel flows (dy, dx),
//! where the scene point at p in the reference is at p + flow(p) in the (sub-)block.

pub mod accumulate;
pub mod kernels;
pub mod reference;
pub mod robustness;
pub mod warp;

pub use accumulate::{
    demosaic_merge, reference_position, AccumulateConfig, MergeAccumulator, MergedPlanes, SubBlock,
    SubBlockMotion, SubBlockRobustness,
};
pub use kernels::{
    kernel_field, kernel_field_with_noise, KernelConfig, KernelField, ReferenceNoise,
};
pub use reference::{reference_image, reference_image_streamed, WienerConfig};
pub use robustness::{robustness, robustness_against, ReferenceStats, RobustnessConfig};
pub use warp::warp_to_reference;

use crate::cfa::Cfa;
use crate::error::{Error, Result};
use crate::model::PixelModel;
use crate::rgbw::combine_rgbw;
use ndarray::{Array2, Array3};
use serde::{Deserialize, Serialize};

/// The noise of a grey block value (the mean sample per frame over `trials` frames, see
/// [`crate::align::grey_image`]): Var = v(μ)/trials with v the pixel model's per-frame sample variance
/// ([`PixelModel::sample_variance`]: binomial μ(1 − μ) for binary frames, Gaussian–Poisson for
/// multi-bit ones). The Wiener reference and the robustness weights ask it. A plain number is
/// that many Bernoulli trials of a binary pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GreyNoise {
    /// Frames averaged into one grey value (times pixels binned, where binned).
    pub trials: f32,
    pub model: PixelModel,
}

impl From<f32> for GreyNoise {
    fn from(trials: f32) -> Self {
        GreyNoise {
            trials,
            model: PixelModel::binary(0.0),
        }
    }
}

impl GreyNoise {
    /// Variance of a grey value whose mean is `mean`.
    pub fn variance(&self, mean: f32) -> f32 {
        (self.model.sample_variance(mean as f64) / self.trials as f64) as f32
    }
}

/// Configuration of the whole merge.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MergeConfig {
    /// A grey block image whose sub-block cameras lie more than this far from the block's
    /// camera (px at the image corners) is smeared by its own frames' motion; the burst remakes
    /// it from its sub-blocks, each at its own motion, before the merge guide (this project's
    /// step: `crate::burst`'s `sharpen_grey_blocks`). 0 remakes every block of two or more
    /// sub-blocks; `inf` none. Tuning: docs/tuning.md ("Sharp grey blocks for the merge guide").
    pub sharpen_blocks_px: f64, // 1 px
    pub wiener: WienerConfig,
    pub kernels: KernelConfig,
    pub robustness: RobustnessConfig,
    pub accumulate: AccumulateConfig,
}

impl Default for MergeConfig {
    fn default() -> Self {
        MergeConfig {
            sharpen_blocks_px: 1.0,
            wiener: WienerConfig::default(),
            kernels: KernelConfig::default(),
            robustness: RobustnessConfig::default(),
            accumulate: AccumulateConfig::default(),
        }
    }
}

/// Everything [`merge_burst`] needs besides its config.
#[derive(Debug, Clone, Copy)]
pub struct BurstInput<'a> {
    /// (H, W) grey image per block ([`crate::align::grey_image`]), comparable across blocks.
    pub grey_blocks: &'a [Array2<f32>],
    /// (H, W, 2) dense flow per block, reference grid -> block.
    pub block_flows: &'a [Array3<f32>],
    /// Index of the reference block.
    pub reference_block: usize,
    /// Frames averaged into one grey value (frames per block x pixels binned).
    pub grey_trials: f32,
    /// Sub-blocks to merge; `SubBlockRobustness::Block(i)` refers to block i above.
    pub sub_blocks: &'a [SubBlock],
    pub cfa: &'a Cfa,
    /// W = wR·R + wG·G + wB·B.
    pub w_weights: [f64; 3],
    /// The pixel model (binary with its dark counts per frame, or Gaussian–Poisson).
    pub model: PixelModel,
}

/// Result of [`merge_burst`], with the intermediate stages for inspection.
#[derive(Debug, Clone)]
pub struct MergedBurst {
    /// (H·s, W·s, 3) linear RGB: detections per frame of an R, G or B pixel, dark removed.
    pub linear: Array3<f32>,
    /// Per-channel merged planes before Eq. 8.
    pub planes: MergedPlanes,
    /// (H, W) Wiener-merged grey reference.
    pub reference: Array2<f32>,
    /// (H, W) robustness map per block (the reference block's is all ones); empty from
    /// [`crate::burst`], which makes each map while it merges that block and drops it
    /// (`BurstReconstruction::robustness_maps` remakes them).
    pub robustness: Vec<Array2<f32>>,
    pub kernels: KernelField,
}

/// What steers the joint demosaic-merge: the reference image, its kernels and every block's
/// robustness map (stages 1–3 above).
#[derive(Debug, Clone)]
pub struct MergeGuide {
    /// (H, W) Wiener-merged grey reference.
    pub reference: Array2<f32>,
    pub kernels: KernelField,
    /// (H, W) robustness map per block (the reference block's is all ones); empty from
    /// [`merge_guide_streamed`].
    pub robustness: Vec<Array2<f32>>,
}

/// Stages 1–3 of the merge (supplement §1.2–1.3): the Wiener-merged reference of the grey
/// blocks warped by `block_flows`, its kernel field, and per-block robustness; `noise` is the
/// noise of a grey value ([`GreyNoise`]; a number: that many Bernoulli trials).
pub fn merge_guide(
    grey_blocks: &[Array2<f32>],
    block_flows: &[Array3<f32>],
    reference_block: usize,
    noise: impl Into<GreyNoise>,
    config: &MergeConfig,
) -> Result<MergeGuide> {
    let noise: GreyNoise = noise.into();
    let blocks = grey_blocks.len();
    if reference_block >= blocks {
        return Err(Error::invalid(format!(
            "merge: reference block {reference_block} is outside the {blocks} blocks"
        )));
    }
    if block_flows.len() != blocks {
        return Err(Error::invalid(format!(
            "reference image: {blocks} grey blocks but {} flows",
            block_flows.len()
        )));
    }
    let mut guide = merge_guide_streamed(
        grey_blocks,
        &|k| block_flows[k].clone(),
        reference_block,
        noise,
        config,
    )?;
    let stats = ReferenceStats::new(&guide.reference);
    guide.robustness = (0..blocks)
        .map(|k| {
            block_robustness(
                &stats,
                grey_blocks,
                &block_flows[k],
                k,
                reference_block,
                noise,
                &config.robustness,
            )
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(guide)
}

/// Stages 1–2 of [`merge_guide`] with block k's dense flow made by `block_flow(k)` when it is
/// needed ([`reference_image_streamed`]): the reference image and its kernels, with an empty
/// robustness list; the caller makes each block's map when it merges that block
/// ([`block_robustness`]), so that memory does not grow with the number of blocks.
pub fn merge_guide_streamed(
    grey_blocks: &[Array2<f32>],
    block_flow: &(dyn Fn(usize) -> Array3<f32> + Sync),
    reference_block: usize,
    noise: impl Into<GreyNoise>,
    config: &MergeConfig,
) -> Result<MergeGuide> {
    let noise: GreyNoise = noise.into();
    let reference = reference_image_streamed(
        grey_blocks,
        block_flow,
        reference_block,
        noise,
        &config.wiener,
    )?;
    let reference_noise = ReferenceNoise {
        grey: noise,
        blocks: grey_blocks.len() as f32,
    };
    let kernels = kernel_field_with_noise(
        &reference,
        Some(reference_noise),
        &config.kernels.for_output_scale(config.accumulate.scale),
    )?;
    Ok(MergeGuide {
        reference,
        kernels,
        robustness: Vec::new(),
    })
}

/// Robustness map of block `k` (stage 3 of [`merge_guide`]): all ones for the reference block,
/// else [`robustness`] of its grey image at `flow` against the reference of `reference`'s
/// statistics ([`ReferenceStats`], made once for all blocks).
pub fn block_robustness(
    reference: &ReferenceStats,
    grey_blocks: &[Array2<f32>],
    flow: &Array3<f32>,
    k: usize,
    reference_block: usize,
    noise: impl Into<GreyNoise>,
    config: &RobustnessConfig,
) -> Result<Array2<f32>> {
    if k == reference_block {
        Ok(Array2::ones(reference.dim()))
    } else {
        robustness_against(reference, &grey_blocks[k], flow, noise, config)
    }
}

/// Merges a burst (paper §4.2, Fig. 4): [`merge_guide`], joint demosaic-merge, RGBW
/// combination (Eq. 8). [`crate::burst`] runs the same stages, streaming the sub-blocks.
pub fn merge_burst(input: &BurstInput, config: &MergeConfig) -> Result<MergedBurst> {
    let blocks = input.grey_blocks.len();
    if input.reference_block >= blocks {
        return Err(Error::invalid(format!(
            "merge: reference block {} is outside the {blocks} blocks",
            input.reference_block
        )));
    }
    let (h, w) = (input.cfa.height(), input.cfa.width());
    if input.grey_blocks[input.reference_block].dim() != (h, w) {
        return Err(Error::invalid(format!(
            "merge: grey blocks have shape {:?}, the CFA is ({h}, {w})",
            input.grey_blocks[input.reference_block].dim()
        )));
    }
    let guide = merge_guide(
        input.grey_blocks,
        input.block_flows,
        input.reference_block,
        GreyNoise {
            trials: input.grey_trials,
            model: input.model,
        },
        config,
    )?;
    let planes = demosaic_merge(
        input.sub_blocks,
        &guide.robustness,
        input.cfa,
        &guide.kernels,
        input.model,
        input.w_weights,
        &config.accumulate,
    )?;
    Ok(MergedBurst::from_planes(planes, guide, input.w_weights))
}

impl MergedBurst {
    /// The RGBW combination of paper Eq. 8 over merged `planes`, with the guide kept for
    /// inspection.
    pub fn from_planes(planes: MergedPlanes, guide: MergeGuide, w_weights: [f64; 3]) -> Self {
        MergedBurst {
            linear: combine_rgbw(&planes.flux, w_weights),
            planes,
            reference: guide.reference,
            robustness: guide.robustness,
            kernels: guide.kernels,
        }
    }
}
