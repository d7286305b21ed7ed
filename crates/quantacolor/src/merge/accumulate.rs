//! Joint demosaic and merge by kernel regression (paper §4.2, Fig. 4; supplement Eq. 1–3;
//! Wronski et al. 2019 Eq. 1; Takeda et al. 2007): every output pixel gathers, per channel, the
//! CFA sites of every sub-block that land near it after motion compensation, weighted by the
//! anisotropic kernel and the sub-block's robustness, then inverts the pixel's response on the
//! accumulated counts: the Bernoulli MLE of paper Eq. 6 for binary frames, the Gaussian–Poisson
//! inversion for multi-bit frames (§6.1; [`crate::model::PixelModel`]). Samples are first splatted into sub-pixel phase bins
//! on the reference grid, so the regression runs once whatever the number of sub-blocks
//! (this project's implementation choice; the sum it computes is the paper's).

use super::kernels::KernelField;
use crate::cfa::{Cfa, Channel};
use crate::cpu;
use crate::error::{Error, Result};
use crate::fastmath;
use crate::filters::bilinear;
use crate::filters::normalized_convolution_nan as normalized_convolution;
use crate::model::PixelModel;
use ndarray::{Array2, Array3, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Which robustness weights apply to a sub-block's samples.
#[derive(Debug, Clone, PartialEq)]
pub enum SubBlockRobustness {
    /// Weight 1 everywhere (e.g. the reference sub-block).
    Full,
    /// The (H, W) map of block `i` in the `block_robustness` list (sub-blocks share their
    /// block's map).
    Block(usize),
    /// Its own (H, W) map on the reference grid.
    Map(Array2<f32>),
}

/// A group of consecutive frames summed into one multi-bit image whose motion relative
/// to the reference agrees to a fraction of a pixel over its frames (for multi-bit frames of a
/// conventional sensor, one frame: paper §6.1).
#[derive(Debug, Clone)]
pub struct SubBlock {
    /// (H, W) sum of the samples over `frames` frames per pixel: the number of ones of binary
    /// frames, the sum of digital numbers of multi-bit frames.
    pub counts: Array2<u32>,
    /// Frames summed into `counts`.
    pub frames: u32,
    /// Where each site's scene point sits in the reference.
    pub flow: SubBlockMotion,
    pub robustness: SubBlockRobustness,
}

/// The motion of a sub-block, as the merge needs it: the reference position of every site.
#[derive(Debug, Clone)]
pub enum SubBlockMotion {
    /// (H, W, 2) dense flow (dy, dx): the scene point at p in the reference is at p + flow(p);
    /// inverted per site by fixed-point iteration ([`reference_position`]).
    Dense(Array3<f32>),
    /// A global affine map from sensor site q to reference position p = `matrix`·q + `offset`
    /// ((y, x) order): a camera motion with no local motion, inverted once for all sites.
    Affine {
        matrix: [[f64; 2]; 2],
        offset: [f64; 2],
    },
    /// A camera motion (the affine map of [`SubBlockMotion::Affine`]) plus a local residual
    /// (moving objects): `flow` is the dense flow of both, and `local` (H, W) marks the
    /// reference pixels where the residual may be non-zero. A site whose affine reference
    /// position lies inside the image on an unmarked pixel takes that position (there the
    /// dense flow is the camera's, whose inverse the affine map is exactly); the others invert
    /// `flow` as [`SubBlockMotion::Dense`] does.
    CameraAndLocal {
        matrix: [[f64; 2]; 2],
        offset: [f64; 2],
        flow: Array3<f32>,
        local: Array2<bool>,
    },
}

impl From<Array3<f32>> for SubBlockMotion {
    fn from(flow: Array3<f32>) -> Self {
        SubBlockMotion::Dense(flow)
    }
}

impl SubBlockMotion {
    /// The dense flow, if this motion is one.
    pub fn dense(&self) -> Option<&Array3<f32>> {
        match self {
            SubBlockMotion::Dense(flow) => Some(flow),
            SubBlockMotion::CameraAndLocal { flow, .. } => Some(flow),
            SubBlockMotion::Affine { .. } => None,
        }
    }

    /// Checks a dense flow's shape and values, or an affine map's values.
    fn check(&self, h: usize, w: usize, what: &str) -> Result<()> {
        match self {
            SubBlockMotion::Dense(flow) => super::warp::check_flow(flow, h, w, what),
            SubBlockMotion::Affine { matrix, offset } => check_affine(matrix, offset, what),
            SubBlockMotion::CameraAndLocal {
                matrix,
                offset,
                flow,
                local,
            } => {
                check_affine(matrix, offset, what)?;
                super::warp::check_flow(flow, h, w, what)?;
                if local.dim() != (h, w) {
                    return Err(Error::invalid(format!(
                        "{what}: local-motion mask has shape {:?}, expected ({h}, {w})",
                        local.dim()
                    )));
                }
                Ok(())
            }
        }
    }
}

fn check_affine(matrix: &[[f64; 2]; 2], offset: &[f64; 2], what: &str) -> Result<()> {
    if matrix.iter().flatten().chain(offset).all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(Error::invalid(format!(
            "{what}: affine motion has non-finite values"
        )))
    }
}

/// Reference position p = `matrix`·q + `offset` of site q.
#[inline(always)]
fn affine_position(matrix: &[[f64; 2]; 2], offset: &[f64; 2], q: [f32; 2]) -> [f32; 2] {
    let (y, x) = (q[0] as f64, q[1] as f64);
    [
        (matrix[0][0] * y + matrix[0][1] * x + offset[0]) as f32,
        (matrix[1][0] * y + matrix[1][1] * x + offset[1]) as f32,
    ]
}

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

/// Output of [`demosaic_merge`], on the output grid (H·scale, W·scale).
#[derive(Debug, Clone)]
pub struct MergedPlanes {
    /// (4, H·s, W·s) flux λ per channel in code order R, G, B, W: mean detections per binary
    /// frame, dark counts removed. W is replaced by wR·R + wG·G + wB·B where it saturates.
    /// Channels absent from the CFA are NaN.
    pub flux: Array3<f32>,
    /// (4, H·s, W·s) merged mean sample per frame p̂ = Σ w·counts / Σ w·frames per channel: the
    /// bit rate of binary frames, the mean digital number of multi-bit frames.
    pub bit_rate: Array3<f32>,
    /// (4, H·s, W·s) effective number of frames behind each mean, (Σ w·F)² / Σ w²·F (Kish):
    /// with the pixel model, the noise model of the merge (binomial Var(p̂) = p(1 − p)/N for
    /// binary frames; [`PixelModel::flux_variance`]). NaN where no sample reached the pixel
    /// (filled pixels).
    pub effective_frames: Array3<f32>,
    /// (H·s, W·s) pixels where the saturated W was replaced by the RGB estimate.
    pub w_fallback: Array2<bool>,
}

/// Streaming form of [`demosaic_merge`] whose cost does not grow with the number of sub-blocks
/// times the kernel footprint (DESIGN "Motion at the sensor's time resolution").
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
/// Memory: 12 f32 per bin, about 26 MB for 496x254 at scale 1 and 100 MB at scale 2,
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
    /// bins[((by·4 + c)·3 + k)·stride + bx] with k = {0: Σ r·counts, 1: Σ r·F, 2: Σ r²·F}
    /// (padding columns stay 0); bin (by, bx) sits at reference position
    /// (by/u − margin, bx/u − margin).
    bins: Vec<f32>,
    /// Scratch of [`MergeAccumulator::add`], kept between calls: the target of every site of
    /// a group of sub-blocks, and the range of targets of each of their rows.
    targets: Vec<(u32, f32)>,
    row_bins: Vec<(u32, u32)>,
}

/// Sub-blocks whose site targets are made before their samples are splatted together
/// ([`MergeAccumulator::add`]): 8 MB of targets for 496x254 sites.
const SPLAT_GROUP: usize = 8;
/// Bin rows per band of the splat: 16 rows of 12 planes of 1016 bins (496 px wide at 2 bins per
/// px) are 0.8 MB, within a core's L2 cache.
const SPLAT_BAND_ROWS: usize = 16;
/// Lanes of the vectorised kernel regression (eight f32: one AVX2 register).
const LANES: usize = 8;
/// Sums per bin: 4 channels × (Σ r·counts, Σ r·F, Σ r²·F).
const SUMS: usize = 12;
/// A channel's own ellipse bounds its bins in the regression ([`gather_row_generic`]) when its
/// limit is below this fraction of the widest channel's (this project's heuristic: it changes
/// only the work, not the result).
const OWN_ELLIPSE_RATIO: f64 = 0.8;

/// Kernel scale (covariance factor), relative to the densest channel's, from which a channel
/// counts as sparse and takes the coarser phase bins of
/// `AccumulateConfig::sparse_bins_per_output_px` (its kernel std is then at least 1.5 times the
/// densest channel's). On the colour-SPAD CFA at spacing exponent 0.5 (the default pipeline with
/// denoising) G, B and R have 2.4, 3.5 and 3.5 times W's scale; Bayer's R and B have at most
/// twice G's, and stay on the phase bins: with them on coarser bins (ratio 2) the quality
/// suite's Bayer capture lost 0.11 dB (burst) and 0.14 dB (true motion).
const SPARSE_SCALE_RATIO: f32 = 2.25;

/// Without W, the colour ratios' guide is a colour (G of Bayer) whose pixel noise the ratio
/// would carry into the other colours (Eq. 8 cancels W's, not G's): the factor's departure
/// from 1 is shrunk by the non-negative garrote (Breiman 1995) at this many standard deviations
/// of the guide's flux at the pixel (relative to the guide seen by the colour), so flat areas
/// keep their colour noise and
/// edges get the correction ([`MergeAccumulator::colour_from_ratios`]). Measured on Bayer
/// captures (default pipeline, sRGB PSNR against no ratios): kodim07 static 2,000 frames +1.74
/// / +1.72 / +1.41 dB at 0 / 1 / 2 standard deviations, kodim12 static +0.57 / +0.72 / +0.54,
/// kodim22 static 512 +0.55 / +0.70 / +0.53, kodim04 handheld 512 −0.54 / +0.12 / +0.01.
const COLOUR_GUIDE_NOISE_GATE: f32 = 1.0;

/// The non-negative garrote of `value` at `threshold`: `value·(1 − threshold²/value²)` beyond
/// the threshold, 0 within it.
fn garrote(value: f32, threshold: f32) -> f32 {
    if value * value > threshold * threshold {
        value - threshold * threshold / value
    } else {
        0.0
    }
}

/// Relative difference between a channel's kernel factor and a whole multiple of the sparsest
/// channel's within which the channel takes that multiple ([`snap_scales`]).
const SNAP_SCALE_TOLERANCE: f32 = 0.02;
/// Largest multiple of the sparsest channel's kernel factor that a channel is snapped to: its
/// weights are that power of the sparsest channel's ([`lane_power`], one multiplication per bit
/// of the multiple and one per set bit after the first).
const MAX_SNAP_MULTIPLE: u32 = 32;

/// `scales` (the kernel scale of R, G, B, W, [`KernelField::channel_scale`] to the power α;
/// 0: absent) with the scale of every channel whose kernel factor 1/scale is within
/// [`SNAP_SCALE_TOLERANCE`] of a whole multiple k of the sparsest channel's (the largest
/// scale, the first of equal ones) set to that channel's scale / k, and each channel's k (0:
/// not snapped, and the sparsest channel itself). The kernel weight exp(−½·k·q) of a snapped
/// channel is then the k-th power of the sparsest channel's exp(−½·q), a few multiplications
/// instead of an exponential ([`gather_row_generic`]); k = 1 (a pattern with as many sites of
/// two colours give or take a few) shares the weights. On /tmp/cap10k's CFA (7,936 R, 15,748 G,
/// 7,812 B, 94,488 W sites) R, G and W take 1, 2 and 12 times B's factor: one exponential per
/// bin instead of four. This project's heuristic: it changes those kernels' widths by at most
/// 1 % (at most 2 % of their factors).
fn snap_scales(mut scales: [f32; 4]) -> ([f32; 4], [u32; 4]) {
    let mut multiples = [0u32; 4];
    let Some(base) = (0..4)
        .filter(|&ch| scales[ch] > 0.0)
        .fold(None, |best: Option<usize>, ch| match best {
            Some(b) if scales[b] >= scales[ch] => Some(b),
            _ => Some(ch),
        })
    else {
        return (scales, multiples);
    };
    let sparsest = scales[base];
    for ch in 0..4 {
        if ch == base || scales[ch] <= 0.0 {
            continue;
        }
        let ratio = sparsest / scales[ch];
        let k = ratio.round();
        if (1.0..=MAX_SNAP_MULTIPLE as f32).contains(&k)
            && (ratio - k).abs() <= SNAP_SCALE_TOLERANCE * k
        {
            scales[ch] = sparsest / k;
            multiples[ch] = k as u32;
        }
    }
    (scales, multiples)
}

/// `w`^`k` lane-wise, by squaring (`k` ≥ 1): the kernel weights of a channel whose factor is k
/// times that of the channel with weights `w` ([`snap_scales`]).
#[inline(always)]
fn lane_power(w: [f32; LANES], k: u32) -> [f32; LANES] {
    let mut result: Option<[f32; LANES]> = None;
    let (mut square, mut k) = (w, k);
    loop {
        if k & 1 == 1 {
            result = Some(match result {
                None => square,
                Some(r) => std::array::from_fn(|i| r[i] * square[i]),
            });
        }
        k >>= 1;
        if k == 0 {
            break;
        }
        square = std::array::from_fn(|i| square[i] * square[i]);
    }
    result.unwrap_or([1.0; LANES])
}

/// Bilinear sample of the interleaved (H, W, 2) `flow` at real position (y, x), clamped.
#[inline]
fn flow_bilinear(flow: &[f32], h: usize, w: usize, y: f32, x: f32) -> [f32; 2] {
    let y = y.clamp(0.0, (h - 1) as f32);
    let x = x.clamp(0.0, (w - 1) as f32);
    // Truncation is the floor of a non-negative value (and 0 for NaN, as `floor` then a cast
    // gives): no libm call in the hot loop.
    let y0 = (y as usize).min(h.saturating_sub(2));
    let x0 = (x as usize).min(w.saturating_sub(2));
    let (y1, x1) = ((y0 + 1).min(h - 1), (x0 + 1).min(w - 1));
    let (fy, fx) = (y - y0 as f32, x - x0 as f32);
    let mut out = [0.0; 2];
    for (c, o) in out.iter_mut().enumerate() {
        let at = |yy: usize, xx: usize| flow[(yy * w + xx) * 2 + c];
        let top = at(y0, x0) * (1.0 - fx) + at(y0, x1) * fx;
        let bottom = at(y1, x0) * (1.0 - fx) + at(y1, x1) * fx;
        *o = top * (1.0 - fy) + bottom * fy;
    }
    out
}

/// `v.round()` (half away from zero) without the libm call that a target without SSE4.1
/// makes of it: the same value for every finite `v` (up to the sign of a zero result). The
/// step away from the truncation is taken without a branch: sub-pixel positions make it a coin
/// toss that a branch predictor misses half of the time.
#[inline]
fn round_half_away(v: f32) -> f32 {
    if v.is_nan() || v.abs() >= 8_388_608.0 {
        // NaN, infinite or already integral (|v| >= 2^23).
        return v.round();
    }
    let t = (v as i32) as f32;
    let frac = v - t; // exact
    t + ((frac >= 0.5) as i32 - (frac <= -0.5) as i32) as f32
}

/// `v.max(0.0).min(hi) as i32` (NaN gives 0, as `as` does) for a finite `hi` in [0, 2³¹):
/// without the saturation checks of `as`, which keep the compiler from converting eight lanes
/// with one vector instruction. The same value as `v as i32` for every `v` in [0, hi] and NaN.
#[inline(always)]
fn index_in(v: f32, hi: f32) -> i32 {
    debug_assert!((0.0..2_147_483_648.0).contains(&hi));
    // `max` returns 0 for NaN: the value is finite and in [0, hi] here.
    let v = v.max(0.0).min(hi);
    // SAFETY: v is finite, non-negative and below 2³¹, so its truncation is an i32.
    unsafe { v.to_int_unchecked::<i32>() }
}

/// [`round_half_away`] from the truncation `v.trunc()` (one vector instruction where the CPU
/// has SSE4.1, e.g. in the AVX2 code; a libm call elsewhere): the same value for every `v`
/// up to the sign of a zero result (NaN and infinities included: their truncation is
/// themselves and their fraction NaN).
#[inline(always)]
fn round_half_away_trunc(v: f32) -> f32 {
    let t = v.trunc();
    let frac = v - t;
    t + ((frac >= 0.5) as i32 - (frac <= -0.5) as i32) as f32
}

/// Reference-grid position of the sensor site `q` of a (sub-)block with forward `flow` (the
/// scene point at p is at p + flow(p) in the block): the p with p + flow(p) = q, by two
/// fixed-point steps p ← q − flow(p) from p = q − flow(q) (exact for translations; the error
/// shrinks by |∇flow| per step, 10⁻² for hand shake, so ~10⁻⁶·|flow| after three).
#[inline]
pub fn reference_position(flow: &[f32], h: usize, w: usize, q: [f32; 2]) -> [f32; 2] {
    let mut p = q;
    for _ in 0..3 {
        let f = flow_bilinear(flow, h, w, p[0], p[1]);
        p = [q[0] - f[0], q[1] - f[1]];
    }
    p
}

/// [`reference_position`] of the eight sites (`y`, `x0` + i), i < 8, lane by lane with the
/// same operations (32-bit indices: vector instructions where the CPU has them): positions
/// (y, x) per lane.
#[inline(always)]
fn reference_positions(flow: &[f32], h: usize, w: usize, y: f32, x0: f32) -> [[f32; LANES]; 2] {
    let (hf, wf) = ((h - 1) as f32, (w - 1) as f32);
    let (ylast, xlast) = (h.saturating_sub(2) as u32, w.saturating_sub(2) as u32);
    let (hl, wl) = ((h - 1) as u32, (w - 1) as u32);
    let w32 = w as u32;
    let q: [[f32; LANES]; 2] = [[y; LANES], std::array::from_fn(|i| x0 + i as u32 as f32)];
    let mut p = q;
    for _ in 0..3 {
        let mut f = [[0.0f32; LANES]; 2];
        for i in 0..LANES {
            // `flow_bilinear` lane-wise: the clamp passes NaN, which truncates to 0.
            let y = p[0][i].clamp(0.0, hf);
            let x = p[1][i].clamp(0.0, wf);
            let y0 = (index_in(y, hf) as u32).min(ylast);
            let x0 = (index_in(x, wf) as u32).min(xlast);
            let (y1, x1) = ((y0 + 1).min(hl), (x0 + 1).min(wl));
            let (fy, fx) = (y - y0 as f32, x - x0 as f32);
            for (c, o) in f.iter_mut().enumerate() {
                let at = |yy: u32, xx: u32| flow[((yy * w32 + xx) * 2) as usize + c];
                let top = at(y0, x0) * (1.0 - fx) + at(y0, x1) * fx;
                let bottom = at(y1, x0) * (1.0 - fx) + at(y1, x1) * fx;
                o[i] = top * (1.0 - fy) + bottom * fy;
            }
        }
        for a in 0..2 {
            for i in 0..LANES {
                p[a][i] = q[a][i] - f[a][i];
            }
        }
    }
    p
}

/// The range (lowest, highest) of the target bins of a row of sites, `(u32::MAX, 0)` when no
/// site of the row lands in the bins: [`MergeAccumulator::add`]'s bands skip the rows that
/// cannot reach them. Made while the row is still in cache from its targets.
#[inline(always)]
fn row_span(row: &[(u32, f32)]) -> (u32, u32) {
    row.iter()
        .filter(|&&(bin, _)| bin != u32::MAX)
        .fold((u32::MAX, 0), |(lo, hi), &(bin, _)| {
            (lo.min(bin), hi.max(bin))
        })
}

/// What [`MergeAccumulator::add`] needs to find the target bin of every site.
struct TargetGrid<'s> {
    h: usize,
    w: usize,
    /// Bins per reference px.
    u: f32,
    /// Margin of the bin grid (reference px).
    margin: f32,
    bins_h: usize,
    bins_w: usize,
    /// Floats per plane row of the bins ([`MergeAccumulator`]'s `stride`).
    stride: usize,
    excluded: Option<&'s [bool]>,
    /// Robustness map on the reference grid (`None`: weight 1).
    robust: Option<&'s [f32]>,
}

impl TargetGrid<'_> {
    /// Target bin (the index of its first sum in the bins, (by·12)·stride + bx) and robustness
    /// weight of every site (row-major), `(u32::MAX, 0)` for sites left out (excluded, zero
    /// weight, outside the bins); `position` maps a site to its reference-grid position. In
    /// parallel by rows; the range of target bins of every row into `spans` ([`row_span`]).
    fn fill(
        &self,
        targets: &mut [(u32, f32)],
        spans: &mut [(u32, u32)],
        position: impl Fn([f32; 2]) -> [f32; 2] + Sync,
    ) {
        let w = self.w;
        targets
            .par_chunks_mut(w)
            .zip(spans.par_iter_mut())
            .enumerate()
            .for_each(|(y, (row, span))| {
                for (x, target) in row.iter_mut().enumerate() {
                    *target = if self.excluded.is_some_and(|e| e[y * w + x]) {
                        (u32::MAX, 0.0)
                    } else {
                        let p = position([y as f32, x as f32]);
                        let rounded = [round_half_away(p[0]), round_half_away(p[1])];
                        let bin = [
                            round_half_away((p[0] + self.margin) * self.u),
                            round_half_away((p[1] + self.margin) * self.u),
                        ];
                        self.target(rounded, bin)
                    };
                }
                *span = row_span(row);
            });
    }

    /// The target of a site whose reference position p rounds to `rounded` and whose bin
    /// coordinates are `bin` (both rounded half away from zero): the robustness at the
    /// reference pixel nearest p (clamped to the image), the bin if inside the grid.
    #[inline(always)]
    fn target(&self, rounded: [f32; 2], bin: [f32; 2]) -> (u32, f32) {
        let (h, w) = (self.h, self.w);
        let r = self.robust.map_or(1.0, |m| {
            let ry = (rounded[0].max(0.0) as usize).min(h - 1);
            let rx = (rounded[1].max(0.0) as usize).min(w - 1);
            m[ry * w + rx]
        });
        let [by, bx] = bin;
        if r <= 0.0 || by < 0.0 || bx < 0.0 || by >= self.bins_h as f32 || bx >= self.bins_w as f32
        {
            (u32::MAX, 0.0)
        } else {
            ((by as usize * SUMS * self.stride + bx as usize) as u32, r)
        }
    }

    /// [`TargetGrid::fill`] for a sub-block whose sites move by the affine map
    /// (`matrix`, `offset`), where `local` (mask (H·W), dense flow (H, W, 2)) marks the reference
    /// pixels whose sites take the inverted dense flow instead ([`SubBlockMotion::
    /// CameraAndLocal`]). The positions and their roundings are computed eight sites at a time
    /// (vector instructions where the CPU has AVX2): the same operations per site, so the same
    /// targets as `fill` with the position closure of that motion.
    fn fill_affine(
        &self,
        targets: &mut [(u32, f32)],
        spans: &mut [(u32, u32)],
        matrix: &[[f64; 2]; 2],
        offset: &[f64; 2],
        local: Option<(&[bool], &[f32])>,
    ) {
        targets
            .par_chunks_mut(self.w)
            .zip(spans.par_iter_mut())
            .enumerate()
            .for_each(|(y, (row, span))| {
                #[cfg(target_arch = "x86_64")]
                {
                    if std::arch::is_x86_feature_detected!("avx2") {
                        // SAFETY: the CPU supports AVX2 (checked just above).
                        unsafe { self.affine_row_avx2(y, row, matrix, offset, local) };
                        *span = row_span(row);
                        return;
                    }
                }
                self.affine_row::<false>(y, row, matrix, offset, local);
                *span = row_span(row);
            });
    }

    /// [`TargetGrid::affine_row`] compiled for AVX2 (no fused multiply-add: the same bits).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn affine_row_avx2(
        &self,
        y: usize,
        row: &mut [(u32, f32)],
        matrix: &[[f64; 2]; 2],
        offset: &[f64; 2],
        local: Option<(&[bool], &[f32])>,
    ) {
        self.affine_row::<true>(y, row, matrix, offset, local)
    }

    /// Targets of the sites of row `y` ([`TargetGrid::fill_affine`]): lane-wise and without
    /// branches for the affine positions (whatever their robustness and whether they land in
    /// the bins), then the few sites that need more (local motion, excluded) one by one.
    /// `AVX2` (only from [`TargetGrid::affine_row_avx2`]): the affine lanes' targets by
    /// [`TargetGrid::lane_targets_avx2`], the same values as [`TargetGrid::lane_targets`].
    #[inline(always)]
    fn affine_row<const AVX2: bool>(
        &self,
        y: usize,
        row: &mut [(u32, f32)],
        matrix: &[[f64; 2]; 2],
        offset: &[f64; 2],
        local: Option<(&[bool], &[f32])>,
    ) {
        let (h, w, u, margin) = (self.h, self.w, self.u, self.margin);
        let (hf, wf) = ((h - 1) as f32, (w - 1) as f32);
        let excluded = self.excluded.map(|e| &e[y * w..(y + 1) * w]);
        // The vector reads of the robustness map stay inside it ([`TargetGrid::
        // lane_targets_avx2`]); a shorter map takes the checked reads (and their panic).
        let robust_covers = self.robust.is_none_or(|m| m.len() >= h * w);
        #[cfg(not(target_arch = "x86_64"))]
        let _ = robust_covers;
        for (chunk, out) in row.chunks_mut(LANES).enumerate() {
            let x0 = chunk * LANES;
            // Lane-wise: positions, their roundings and bin coordinates.
            let mut p = [[0.0f32; LANES]; 2];
            let mut rounded = [[0.0f32; LANES]; 2];
            let mut bin = [[0.0f32; LANES]; 2];
            let (yf, x0f) = (y as u32 as f32, x0 as u32 as f32);
            for i in 0..LANES {
                let q = affine_position(matrix, offset, [yf, x0f + i as u32 as f32]);
                for a in 0..2 {
                    p[a][i] = q[a];
                    rounded[a][i] = round_half_away_trunc(q[a]);
                    bin[a][i] = round_half_away_trunc((q[a] + margin) * u);
                }
            }
            // Excluded sites are left out lane-wise, as sites outside the bins are.
            let mut skip = [false; LANES];
            if let Some(e) = excluded {
                // Element by element: a fixed-length loop, no call to `memcpy`.
                for (s, &e) in skip.iter_mut().zip(&e[x0..x0 + out.len()]) {
                    *s = e;
                }
            }
            let mut lanes = match self.robust {
                #[cfg(target_arch = "x86_64")]
                _ if AVX2 && robust_covers => {
                    // SAFETY: `AVX2` is set only by `affine_row_avx2`, whose caller checked
                    // that the CPU supports AVX2; the robustness map (if any) holds the H·W
                    // pixels (`robust_covers`).
                    unsafe { self.lane_targets_avx2(&rounded, &bin, &skip) }
                }
                Some(m) => self.lane_targets(&rounded, &bin, &skip, |i| m[i]),
                None => self.lane_targets(&rounded, &bin, &skip, |_| 1.0),
            };
            if let Some((mask, flow)) = local {
                // Sites whose affine position is outside the image or on a marked pixel take
                // the inverted dense flow (all eight lanes computed when one needs it).
                let mut dense = [false; LANES];
                for i in 0..LANES {
                    let (py, px) = (p[0][i], p[1][i]);
                    let inside = (py >= 0.0) & (px >= 0.0) & (py <= hf) & (px <= wf);
                    // Inside, the clamps change nothing: the rounded position's pixel.
                    let ry = index_in(rounded[0][i], hf) as usize;
                    let rx = index_in(rounded[1][i], wf) as usize;
                    dense[i] = !inside || mask[ry * w + rx];
                }
                if dense[..out.len()].contains(&true) {
                    let q = reference_positions(flow, h, w, yf, x0f);
                    let mut rounded = [[0.0f32; LANES]; 2];
                    let mut bin = [[0.0f32; LANES]; 2];
                    for a in 0..2 {
                        for i in 0..LANES {
                            rounded[a][i] = round_half_away_trunc(q[a][i]);
                            bin[a][i] = round_half_away_trunc((q[a][i] + margin) * u);
                        }
                    }
                    let moved = match self.robust {
                        Some(m) => self.lane_targets(&rounded, &bin, &skip, |i| m[i]),
                        None => self.lane_targets(&rounded, &bin, &skip, |_| 1.0),
                    };
                    // A lane-wise select (no conditional stores of single lanes).
                    lanes = std::array::from_fn(|i| if dense[i] { moved[i] } else { lanes[i] });
                }
            }
            for (target, &lane) in out.iter_mut().zip(&lanes) {
                *target = lane;
            }
        }
    }

    /// [`TargetGrid::target`] of eight sites at once, without branches, lanes marked in `skip`
    /// (excluded sites) left out: `robust(i)` reads the robustness map at row-major index i
    /// (inside the image).
    #[inline(always)]
    fn lane_targets(
        &self,
        rounded: &[[f32; LANES]; 2],
        bin: &[[f32; LANES]; 2],
        skip: &[bool; LANES],
        robust: impl Fn(usize) -> f32,
    ) -> [(u32, f32); LANES] {
        // 32-bit integers throughout (vector conversions); the clamps are taken on the
        // integral floats, whose bounds (image sides) are exact in f32.
        let (hf, wf) = ((self.h - 1) as f32, (self.w - 1) as f32);
        let w = self.w as i32;
        let (bins_h, bins_w) = (self.bins_h as f32, self.bins_w as f32);
        let row_floats = (SUMS * self.stride) as i32;
        let mut index = [0i32; LANES];
        let mut outside = [false; LANES];
        let mut at = [0i32; LANES];
        for i in 0..LANES {
            let ry = index_in(rounded[0][i], hf);
            let rx = index_in(rounded[1][i], wf);
            at[i] = ry * w + rx;
            let (by, bx) = (bin[0][i], bin[1][i]);
            outside[i] = (by < 0.0) | (bx < 0.0) | (by >= bins_h) | (bx >= bins_w);
            // Wrapping: the index of a lane left out is discarded (and a lane is kept only
            // where 0 <= by < bins_h and 0 <= bx < bins_w, or NaN: there the clamped
            // conversion is `by as i32`).
            index[i] = index_in(by, bins_h)
                .wrapping_mul(row_floats)
                .wrapping_add(index_in(bx, bins_w));
        }
        // Selected lane-wise into two arrays, then interleaved: no conditional stores of
        // single lanes (which the vector reads of `out` then waited for: store forwarding
        // fails on a wide read of narrow writes). The same values as storing the kept lanes
        // into an array of `(u32::MAX, 0.0)`.
        let mut bins = [u32::MAX; LANES];
        let mut weights = [0.0f32; LANES];
        for i in 0..LANES {
            let r = robust(at[i] as usize);
            let keep = !(outside[i] | skip[i] | (r <= 0.0));
            bins[i] = if keep { index[i] as u32 } else { u32::MAX };
            weights[i] = if keep { r } else { 0.0 };
        }
        std::array::from_fn(|i| (bins[i], weights[i]))
    }

    /// [`TargetGrid::lane_targets`] with AVX2 instructions, the robustness (if any) read
    /// from `self.robust`: the same operations lane by lane, so the same targets. The
    /// clamped truncations of [`index_in`] are `max` with 0 second (NaN gives 0, as there),
    /// `min` with the bound and a truncating conversion; the comparisons are ordered (false
    /// for NaN, as Rust's); the index arithmetic wraps as there; the robustness is one
    /// gather; the kept lanes are selected with blends and the (bin, weight) pairs
    /// interleaved in registers and written with two full-width stores (no single-lane
    /// stores that a wide read of the result would wait for).
    ///
    /// # Safety
    /// The CPU must support AVX2, and `self.robust`, if any, must hold at least H·W values
    /// (every index read is a clamped pixel of the H×W image).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn lane_targets_avx2(
        &self,
        rounded: &[[f32; LANES]; 2],
        bin: &[[f32; LANES]; 2],
        skip: &[bool; LANES],
    ) -> [(u32, f32); LANES] {
        use std::arch::x86_64::*;
        let (hf, wf) = ((self.h - 1) as f32, (self.w - 1) as f32);
        let (bins_h, bins_w) = (self.bins_h as f32, self.bins_w as f32);
        let row_floats = (SUMS * self.stride) as i32;
        let zero = _mm256_setzero_ps();
        // `index_in` lane-wise: max(v, 0) returns its second operand 0 for NaN.
        let index = |v: __m256, hi: f32| {
            _mm256_cvttps_epi32(_mm256_min_ps(_mm256_max_ps(v, zero), _mm256_set1_ps(hi)))
        };
        // SAFETY: `rounded` and `bin` are arrays of eight f32 each (unaligned loads).
        let (ry, rx, by, bx) = unsafe {
            (
                _mm256_loadu_ps(rounded[0].as_ptr()),
                _mm256_loadu_ps(rounded[1].as_ptr()),
                _mm256_loadu_ps(bin[0].as_ptr()),
                _mm256_loadu_ps(bin[1].as_ptr()),
            )
        };
        let outside = _mm256_or_ps(
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_LT_OQ>(by, zero),
                _mm256_cmp_ps::<_CMP_LT_OQ>(bx, zero),
            ),
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_GE_OQ>(by, _mm256_set1_ps(bins_h)),
                _mm256_cmp_ps::<_CMP_GE_OQ>(bx, _mm256_set1_ps(bins_w)),
            ),
        );
        let target = _mm256_add_epi32(
            _mm256_mullo_epi32(index(by, bins_h), _mm256_set1_epi32(row_floats)),
            index(bx, bins_w),
        );
        let r = match self.robust {
            Some(m) => {
                let at = _mm256_add_epi32(
                    _mm256_mullo_epi32(index(ry, hf), _mm256_set1_epi32(self.w as i32)),
                    index(rx, wf),
                );
                // SAFETY: every lane of `at` is ry·W + rx with ry ≤ H − 1 and rx ≤ W − 1
                // (clamped above), below H·W ≤ m.len() (the caller's contract).
                unsafe { _mm256_i32gather_ps::<4>(m.as_ptr(), at) }
            }
            None => _mm256_set1_ps(1.0),
        };
        // The skipped lanes: bools are 0 or 1, widened to 32-bit lanes.
        let skipped = {
            let bytes = u64::from_le_bytes(std::array::from_fn(|i| skip[i] as u8));
            let wide = _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(bytes as i64));
            _mm256_castsi256_ps(_mm256_cmpgt_epi32(wide, _mm256_setzero_si256()))
        };
        let drop = _mm256_or_ps(
            _mm256_or_ps(outside, skipped),
            _mm256_cmp_ps::<_CMP_LE_OQ>(r, zero),
        );
        let bins = _mm256_blendv_ps(
            _mm256_castsi256_ps(target),
            _mm256_castsi256_ps(_mm256_set1_epi32(-1)),
            drop,
        );
        let weights = _mm256_blendv_ps(r, zero, drop);
        // (bin, weight) pairs in lane order: lanes 0, 1, 4, 5 and 2, 3, 6, 7, then halves.
        let (lo, hi) = (
            _mm256_unpacklo_ps(bins, weights),
            _mm256_unpackhi_ps(bins, weights),
        );
        // A tuple's layout is not guaranteed: the stores below need this one.
        const _: () = assert!(
            std::mem::size_of::<(u32, f32)>() == 8
                && std::mem::offset_of!((u32, f32), 0) == 0
                && std::mem::offset_of!((u32, f32), 1) == 4
        );
        let mut out = [(u32::MAX, 0.0f32); LANES];
        let at = out.as_mut_ptr() as *mut f32;
        // SAFETY: `out` is 64 bytes of eight (u32, f32) pairs, the u32 at offset 0 and the
        // f32 at offset 4 of each (asserted above); two unaligned 32-byte stores fill it.
        unsafe {
            _mm256_storeu_ps(at, _mm256_permute2f128_ps::<0x20>(lo, hi));
            _mm256_storeu_ps(at.add(LANES), _mm256_permute2f128_ps::<0x31>(lo, hi));
        }
        out
    }
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
            // Zeroed by all threads (26 MB for 496x254: ~10 ms of one thread's memset).
            bins: cpu::zeroed_par(len),
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

    /// Splats `sub_blocks` (whose `SubBlockRobustness::Block(i)` index `block_robustness`)
    /// into the phase bins.
    pub fn add(&mut self, sub_blocks: &[SubBlock], block_robustness: &[Array2<f32>]) -> Result<()> {
        let (h, w) = (self.cfa.height(), self.cfa.width());
        validate(
            sub_blocks,
            block_robustness,
            self.kernels,
            h,
            w,
            &self.config,
            self.model.max_sample(),
        )?;
        let block_maps: Vec<_> = block_robustness
            .iter()
            .map(|m| m.as_standard_layout())
            .collect();
        // The site targets and row spans of a group, kept from one call to the next (the
        // targets are 8 MB: fresh pages and their zeroing cost more than the splat of a small
        // group). Every entry a group uses is written before it is read.
        let group_len = SPLAT_GROUP.min(sub_blocks.len());
        let mut targets = std::mem::take(&mut self.targets);
        let mut row_bins = std::mem::take(&mut self.row_bins);
        if targets.len() < group_len * h * w {
            // Written by all threads: one thread's first touch of 8 MB left the other idle.
            targets = Vec::new();
            cpu::resize_par(&mut targets, group_len * h * w, (u32::MAX, 0.0f32));
            row_bins = vec![(u32::MAX, 0u32); group_len * h];
        }
        // Sub-blocks are splatted a group at a time: the target bins of all sites of the group
        // first, then the samples band of bin rows by band of bin rows ([`Self::splat_group`]).
        for group in sub_blocks.chunks(SPLAT_GROUP) {
            for (k, sub) in group.iter().enumerate() {
                let block_map = |i: usize| block_maps[i].as_slice();
                self.fill_targets(
                    sub,
                    block_map,
                    &mut targets[k * h * w..(k + 1) * h * w],
                    &mut row_bins[k * h..(k + 1) * h],
                );
            }
            self.splat_group(group, &targets, &row_bins);
        }
        self.targets = targets;
        self.row_bins = row_bins;
        Ok(())
    }

    /// The target bin and robustness weight of every site of sub-block `sub` (`block_map(i)`:
    /// block `i`'s robustness map, row-major), and in `spans` the range of target bins of
    /// every row of sites, so that a band skips the rows that cannot reach it.
    fn fill_targets<'m>(
        &self,
        sub: &SubBlock,
        block_map: impl Fn(usize) -> Option<&'m [f32]>,
        targets: &mut [(u32, f32)],
        spans: &mut [(u32, u32)],
    ) {
        let (h, w) = (self.cfa.height(), self.cfa.width());
        let own = match &sub.robustness {
            SubBlockRobustness::Map(m) => Some(m.as_standard_layout()),
            _ => None,
        };
        let robust: Option<&[f32]> = match &sub.robustness {
            SubBlockRobustness::Full => None,
            SubBlockRobustness::Block(i) => block_map(*i),
            SubBlockRobustness::Map(_) => own.as_ref().and_then(|m| m.as_slice()),
        };
        let grid = TargetGrid {
            h,
            w,
            u: self.bins_per_px as f32,
            margin: self.margin as f32,
            bins_h: self.bins_h,
            bins_w: self.bins_w,
            stride: self.stride,
            excluded: self.excluded.as_deref(),
            robust,
        };
        match &sub.flow {
            SubBlockMotion::Affine { matrix, offset } => {
                grid.fill_affine(targets, spans, matrix, offset, None)
            }
            SubBlockMotion::CameraAndLocal {
                matrix,
                offset,
                flow,
                local,
            } => {
                let flow = flow.as_standard_layout();
                let flow = flow.as_slice().expect("standard layout");
                let mask = local.as_standard_layout();
                let mask = mask.as_slice().expect("standard layout");
                grid.fill_affine(targets, spans, matrix, offset, Some((mask, flow)))
            }
            SubBlockMotion::Dense(flow) => {
                let flow = flow.as_standard_layout();
                let flow = flow.as_slice().expect("standard layout");
                grid.fill(targets, spans, |q: [f32; 2]| {
                    reference_position(flow, h, w, q)
                })
            }
        }
    }

    /// Adds the samples of the sub-blocks of `group` (their sites' `targets` and row spans
    /// `row_bins` from [`Self::fill_targets`], one `h·w` and one `h` slice per sub-block) to the
    /// bins, one band of bin rows per task (a band, ~1 MB, stays in cache while every
    /// sub-block of the group adds to it). Within a band, sub-blocks come in order and each
    /// scans its sites in order, so each bin receives its samples in (sub-block, site) order
    /// whatever the number of threads: the same sums as one serial pass.
    fn splat_group(&mut self, group: &[SubBlock], targets: &[(u32, f32)], row_bins: &[(u32, u32)]) {
        let (h, w) = (self.cfa.height(), self.cfa.width());
        let stride = self.stride;
        let band_floats = SPLAT_BAND_ROWS * SUMS * stride;
        let counts: Vec<_> = group
            .iter()
            .map(|sub| sub.counts.as_standard_layout())
            .collect();
        let codes = &self.codes;
        self.bins
            .par_chunks_mut(band_floats)
            .enumerate()
            .for_each(|(band, cells)| {
                // A local copy: read once, not after every store into the bins (the
                // closure otherwise reads the captured reference).
                #[allow(clippy::redundant_locals)]
                let stride = stride;
                let first = band * band_floats;
                let end = first + cells.len();
                for (k, sub) in group.iter().enumerate() {
                    let frames = sub.frames as f32;
                    let counts = counts[k].as_slice().expect("standard layout");
                    let targets = &targets[k * h * w..(k + 1) * h * w];
                    for (y, &(lo, hi)) in row_bins[k * h..(k + 1) * h].iter().enumerate() {
                        if lo == u32::MAX || (hi as usize) < first || lo as usize >= end {
                            continue;
                        }
                        let sites = y * w..(y + 1) * w;
                        for ((&(bin, r), &count), &code) in targets[sites.clone()]
                            .iter()
                            .zip(&counts[sites.clone()])
                            .zip(&codes[sites])
                        {
                            let bin = bin as usize;
                            if bin < first || bin >= end {
                                continue;
                            }
                            // The three sums of the site's channel in one sub-slice (one
                            // bounds check instead of three): the bins of a band are whole
                            // bin rows of SUMS planes, so the slice is inside the band.
                            let slot = bin - first + (code as usize & 3) * 3 * stride;
                            let cell = &mut cells[slot..slot + 2 * stride + 1];
                            cell[0] += r * count as f32;
                            cell[stride] += r * frames;
                            cell[2 * stride] += r * r * frames;
                        }
                    }
                }
            });
    }

    /// (Σ g·S0, Σ g·S1, Σ g²·S2) per channel (the sums of supplement Eq. 1–3 over the bins, g the
    /// kernel weight) of every output pixel, row-major, in parallel by output rows. The sparse
    /// channels ([`MergeAccumulator::sparse_channels`]), if any, gather from coarser bins
    /// ([`MergeAccumulator::coarse_bins`]), the others from the phase bins.
    fn regression(&self, channels: [bool; 4]) -> Vec<[f32; SUMS]> {
        let (hs, ws) = (
            self.cfa.height() * self.config.scale,
            self.cfa.width() * self.config.scale,
        );
        let inv_cov = self.kernels.inv_cov.as_standard_layout();
        let inv_cov = inv_cov.as_slice().expect("standard layout");
        let mut sums = cpu::zeroed_par::<[f32; SUMS]>(hs * ws);
        let gather_rows = |sums: &mut [[f32; SUMS]], gather: &Gather| {
            sums.par_chunks_mut(ws)
                .enumerate()
                .for_each(|(oy, row)| gather_row(gather, oy, row))
        };
        let all_sparse = self.sparse_channels();
        let sparse: [bool; 4] = std::array::from_fn(|ch| all_sparse[ch] && channels[ch]);
        if !sparse.contains(&true) {
            gather_rows(&mut sums, &self.gather(self.fine_grid(), channels, inv_cov));
            return sums;
        }
        let coarse = self.coarse_bins(sparse);
        let dense: [bool; 4] = std::array::from_fn(|ch| channels[ch] && !sparse[ch]);
        if !(0..4).any(|ch| dense[ch] && self.channel_scale[ch] > 0.0) {
            gather_rows(&mut sums, &self.gather(coarse.grid(), sparse, inv_cov));
            return sums;
        }
        let fine = self.gather(self.fine_grid(), dense, inv_cov);
        let coarse = self.gather(coarse.grid(), sparse, inv_cov);
        sums.par_chunks_mut(ws).enumerate().for_each_init(
            || vec![[0.0f32; SUMS]; ws],
            |sparse_row, (oy, row)| {
                gather_row(&fine, oy, row);
                gather_row(&coarse, oy, sparse_row);
                for (out, s) in row.iter_mut().zip(sparse_row.iter()) {
                    for ch in (0..4).filter(|&ch| sparse[ch]) {
                        out[ch * 3..ch * 3 + 3].copy_from_slice(&s[ch * 3..ch * 3 + 3]);
                    }
                }
            },
        );
        sums
    }

    /// The channels that gather from the coarser bins of `sparse_bins_per_output_px`: those
    /// present whose kernel scale is at least [`SPARSE_SCALE_RATIO`] times the densest
    /// channel's (none when the sparse bins are the phase bins).
    fn sparse_channels(&self) -> [bool; 4] {
        let densest = self
            .channel_scale
            .iter()
            .copied()
            .filter(|&s| s > 0.0)
            .fold(f32::INFINITY, f32::min);
        let coarser = self.config.sparse_bins_per_output_px < self.config.bins_per_output_px;
        self.channel_scale
            .map(|s| coarser && s > 0.0 && s >= SPARSE_SCALE_RATIO * densest)
    }

    /// The phase bins as the regression reads them.
    fn fine_grid(&self) -> BinGrid<'_> {
        BinGrid {
            bins: &self.bins,
            stride: self.stride,
            bins_h: self.bins_h,
            bins_w: self.bins_w,
            u: self.bins_per_px as f32,
            margin: self.margin as f32,
        }
    }

    /// The phase bins of the `sparse` channels on a grid f times coarser, f the ratio of
    /// `bins_per_output_px` to `sparse_bins_per_output_px`, in the same plane layout (the other
    /// channels' planes stay 0): coarse bin (k, j) sits on fine bin (f·k, f·j) and takes every
    /// fine bin within f − 1 of it along each axis with the tent weight (1 − |d|/f) per axis
    /// (all four sums: the fine bin's samples are shared between the nearest coarse bins, as
    /// when splatting with bilinear weights). Unlike rounding to the coarse grid it moves no
    /// sample on average: the positions of a static burst (every site on a whole reference
    /// pixel) stay where they are (rounding pairs of fine bins instead shifted the sparse
    /// channels by a quarter pixel: −0.17 dB on the quality suite's static capture). The
    /// splat itself stays one pass over the fine bins.
    fn coarse_bins(&self, sparse: [bool; 4]) -> CoarseBins {
        let f = self.config.bins_per_output_px / self.config.sparse_bins_per_output_px;
        // (bins − 1) is a multiple of the bins per reference px, hence of f.
        let (bins_h, bins_w) = ((self.bins_h - 1) / f + 1, (self.bins_w - 1) / f + 1);
        let stride = (bins_w + LANES - 1).next_multiple_of(LANES);
        let mut bins = cpu::zeroed_par::<f32>(bins_h * SUMS * stride);
        let (fine, fine_stride, fine_w) = (&self.bins, self.stride, self.bins_w);
        let fine_rows = self.bins_h as isize;
        let tent = |d: isize| (f as isize - d.abs()) as f32 / f as f32;
        let reach = f as isize - 1;
        bins.par_chunks_mut(SUMS * stride)
            .enumerate()
            .for_each_init(
                || vec![0.0f32; fine_w],
                |rows, (cy, row)| {
                    let centre = (cy * f) as isize;
                    for ch in (0..4).filter(|&ch| sparse[ch]) {
                        for k in 0..3 {
                            let plane = ch * 3 + k;
                            // The fine rows around the coarse row, tent-weighted...
                            rows.fill(0.0);
                            for by in (centre - reach).max(0)..=(centre + reach).min(fine_rows - 1)
                            {
                                let weight = tent(by - centre);
                                let at = (by as usize * SUMS + plane) * fine_stride;
                                for (r, &v) in rows.iter_mut().zip(&fine[at..at + fine_w]) {
                                    *r += weight * v;
                                }
                            }
                            // ...then the fine columns around each coarse column.
                            let out = &mut row[plane * stride..plane * stride + bins_w];
                            for (cx, o) in out.iter_mut().enumerate() {
                                let centre = (cx * f) as isize;
                                *o = ((centre - reach).max(0)
                                    ..=(centre + reach).min(fine_w as isize - 1))
                                    .map(|bx| tent(bx - centre) * rows[bx as usize])
                                    .sum();
                            }
                        }
                    }
                },
            );
        CoarseBins {
            bins,
            stride,
            bins_h,
            bins_w,
            u: (self.bins_per_px / f) as f32,
            margin: self.margin as f32,
        }
    }

    /// Runs `f` with what the regression of every channel over the phase bins reads
    /// ([`Gather`]).
    #[cfg(test)]
    fn with_gather<R>(&self, f: impl FnOnce(&Gather) -> R) -> R {
        let inv_cov = self.kernels.inv_cov.as_standard_layout();
        let gather = self.gather(
            self.fine_grid(),
            [true; 4],
            inv_cov.as_slice().expect("standard layout"),
        );
        f(&gather)
    }

    /// What the regression of `channels` over the bins of `grid` reads ([`Gather`]), with the
    /// (H, W, 3) inverse kernel covariances `inv_cov`.
    fn gather<'g>(&self, grid: BinGrid<'g>, channels: [bool; 4], inv_cov: &'g [f32]) -> Gather<'g> {
        let scale = self.config.scale;
        let (h, w) = (self.cfa.height(), self.cfa.width());
        let inv_scale = self.inv_scale;
        let cutoff = self.config.cutoff;
        let u = grid.u;
        let inv_s = 1.0 / scale as f32;
        // Every channel skips a bin whose quadratic form times the smallest channel factor is
        // at or above the cutoff (rounding is monotone and the form is then positive), so the
        // gather only visits the bins of each row inside that widest ellipse, widened by a bin
        // on each side against rounding ([`ellipse_span`]).
        let min_inv_scale = (0..4)
            .filter(|&ch| channels[ch])
            .map(|ch| inv_scale[ch])
            .fold(f32::INFINITY, f32::min);
        let present = std::array::from_fn(|ch| channels[ch] && self.channel_scale[ch] > 0.0);
        // The sparsest channel makes its weights with exponentials; a channel whose factor is
        // the same reuses them (R, G and B of most CFAs: the same values, computed once), one
        // whose factor is k times it takes their k-th power ([`snap_scales`]). Without the
        // sparsest channel among `channels`, each channel makes its own.
        let min_present = (0..4)
            .filter(|&ch| present[ch])
            .map(|ch| inv_scale[ch])
            .fold(f32::INFINITY, f32::min);
        let base = (0..4)
            .find(|&ch| present[ch] && self.multiples[ch] == 0 && inv_scale[ch] == min_present);
        let source = std::array::from_fn(|ch| match base {
            Some(base) if self.multiples[ch] == 1 => base,
            _ => ch,
        });
        let power = std::array::from_fn(|ch| match self.multiples[ch] {
            k if k >= 2 && base.is_some() => k,
            _ => 0,
        });
        Gather {
            bins: grid.bins,
            stride: grid.stride,
            bins_h: grid.bins_h as isize,
            bins_w: grid.bins_w as isize,
            inv_cov,
            h,
            w,
            u,
            inv_u: 1.0 / u,
            margin: grid.margin,
            radius: self.radius,
            inv_s,
            offset: 0.5 * inv_s - 0.5,
            cutoff,
            inv_scale,
            present,
            base: base.unwrap_or(0),
            source,
            power,
            ellipse_limit: (min_inv_scale > 0.0).then(|| cutoff as f64 / min_inv_scale as f64),
            // A channel with a larger factor (W of a W-rich CFA) has its own, narrower ellipse.
            channel_limit: std::array::from_fn(|ch| {
                (min_inv_scale > 0.0 && present[ch] && inv_scale[ch] > min_inv_scale)
                    .then(|| cutoff as f64 / inv_scale[ch] as f64)
            }),
        }
    }

    /// Kernel regression over the bins (supplement Eq. 1–3), then per-channel mean samples and
    /// fluxes (the MLE of paper Eq. 6, or the Gaussian–Poisson inversion: [`PixelModel::flux`]),
    /// holes filled, W saturation fallback applied.
    pub fn finish(mut self, w_weights: [f64; 3]) -> MergedPlanes {
        let model = self.model;
        let w_saturation = self.config.w_saturation * model.max_sample() as f32;
        let scale = self.config.scale;
        let (h, w) = (self.cfa.height(), self.cfa.width());
        let (hs, ws) = (h * scale, w * scale);
        let channel_scale = self.channel_scale;
        let sums = self.regression([true; 4]);
        let mut bit_rate = Array3::<f32>::from_elem((4, hs, ws), f32::NAN);
        let mut flux = Array3::<f32>::from_elem((4, hs, ws), f32::NAN);
        let mut effective_frames = Array3::<f32>::from_elem((4, hs, ws), f32::NAN);
        // Per channel plane, in parallel by output rows.
        for ch in 0..4 {
            let mut rate_plane = bit_rate.index_axis_mut(Axis(0), ch);
            let mut frames_plane = effective_frames.index_axis_mut(Axis(0), ch);
            let mut flux_plane = flux.index_axis_mut(Axis(0), ch);
            rate_plane
                .axis_iter_mut(Axis(0))
                .into_par_iter()
                .zip(frames_plane.axis_iter_mut(Axis(0)))
                .zip(flux_plane.axis_iter_mut(Axis(0)))
                .zip(sums.par_chunks(ws))
                .for_each(|(((mut rate, mut frames), mut flux), row)| {
                    for (ox, s) in row.iter().enumerate() {
                        let s = &s[ch * 3..ch * 3 + 3];
                        if s[1] > 1e-6 && s[2] > 0.0 {
                            let p = s[0] / s[1];
                            let n_eff = s[1] as f64 * s[1] as f64 / s[2] as f64;
                            rate[ox] = p;
                            frames[ox] = n_eff as f32;
                            flux[ox] = model.flux(p as f64, n_eff) as f32;
                        }
                    }
                });
        }
        drop(sums);
        // Fill pixels that no sample reached (sparse channels, image borders).
        for channel in Channel::ALL {
            let ch = channel.index();
            if channel_scale[ch] == 0.0 {
                continue;
            }
            let plane = flux.index_axis(Axis(0), ch);
            if plane.iter().any(|v| v.is_nan()) {
                let sigma = (channel_scale[ch] as f64).sqrt() * scale as f64;
                let filled = normalized_convolution(plane, sigma);
                let mut plane = flux.index_axis_mut(Axis(0), ch);
                plane.zip_mut_with(&filled, |v, &f| {
                    if v.is_nan() {
                        *v = f;
                    }
                });
            }
        }
        // W saturation fallback (supplement §7), generalised to censoring.
        // Pixel by pixel, in parallel by output rows.
        let mut w_fallback = Array2::<bool>::from_elem((hs, ws), false);
        if channel_scale[..3].iter().all(|&s| s > 0.0) && channel_scale[3] > 0.0 {
            let censoring_zeros = self.config.w_censoring_zeros;
            let (rgb, mut white) = flux.view_mut().split_at(Axis(0), 3);
            let (bit_rate, effective_frames) = (&bit_rate, &effective_frames);
            white
                .index_axis_mut(Axis(0), 0)
                .axis_iter_mut(Axis(0))
                .into_par_iter()
                .zip(w_fallback.axis_iter_mut(Axis(0)))
                .enumerate()
                .for_each(|(oy, (mut white, mut fallback))| {
                    for ox in 0..ws {
                        let sat = |ch: usize| bit_rate[[ch, oy, ox]] > w_saturation;
                        let lum = || -> f32 {
                            (0..3)
                                .map(|ch| rgb[[ch, oy, ox]] as f64 * w_weights[ch])
                                .sum::<f64>() as f32
                        };
                        if model.is_binary() && censoring_zeros > 0.0 {
                            let trust = w_trust(
                                bit_rate[[3, oy, ox]],
                                effective_frames[[3, oy, ox]],
                                censoring_zeros,
                            );
                            let (censored, lum) = (white[ox], lum());
                            if trust < 1.0 && lum.is_finite() && lum > censored {
                                white[ox] = trust * censored + (1.0 - trust) * lum;
                                fallback[ox] = true;
                            }
                        } else if sat(3) && !(sat(0) || sat(1) || sat(2)) {
                            white[ox] = lum();
                            fallback[ox] = true;
                        }
                    }
                });
        }
        if self.config.colour_ratios && channel_scale[..3].iter().all(|&s| s > 0.0) {
            // W guides where the CFA has it; otherwise the densest colour (G of Bayer).
            let guide = if channel_scale[3] > 0.0 {
                3
            } else {
                (0..3)
                    .min_by(|&a, &b| channel_scale[a].total_cmp(&channel_scale[b]))
                    .expect("three colours")
            };
            self.colour_from_ratios(guide, &mut flux, &effective_frames);
        }
        MergedPlanes {
            flux,
            bit_rate,
            effective_frames,
            w_fallback,
        }
    }

    /// `AccumulateConfig::colour_ratios`: every colour c of `flux` but the `guide` (W, or the
    /// densest colour without W) times G / Ḡ_c, G the guide's merged flux (`flux`'s plane,
    /// after hole filling and the saturation fallback) and Ḡ_c the guide at the positions of
    /// channel c's samples, regressed with c's kernel and weights. The phase bins already hold
    /// each bin's Σ r·F per channel; a bin's samples all lie within half a bin of it, so the
    /// guide at the bin stands for the guide at each of them, and Σ g·G(bin)·Σ r·F over the
    /// bins, divided by Σ g·Σ r·F, is Ḡ_c. Both G and Ḡ_c are floored at one detection over
    /// the pixel's effective guide frames: where the guide says nothing (the dark), the factor
    /// is 1. A colour guide's pixel noise would enter c (Eq. 8 cancels W's, not G's), so there
    /// the factor's departure from 1 is shrunk by [`COLOUR_GUIDE_NOISE_GATE`].
    fn colour_from_ratios(
        &mut self,
        guide: usize,
        flux: &mut Array3<f32>,
        effective_frames: &Array3<f32>,
    ) {
        let scale = self.config.scale as f32;
        let model = self.model;
        let gate = (guide != Channel::W.index()).then_some(COLOUR_GUIDE_NOISE_GATE);
        let guided: [bool; 4] = std::array::from_fn(|ch| ch < 3 && ch != guide);
        let guide_flux = flux.index_axis(Axis(0), guide).to_owned();
        let (u, margin, stride, bins_w) = (
            self.bins_per_px as f32,
            self.margin as f32,
            self.stride,
            self.bins_w,
        );
        // Output pixel (oy, ox) sits at reference position (oy + 0.5) / scale − 0.5.
        let output_position = |bin: usize| ((bin as f32 / u - margin) + 0.5) * scale - 0.5;
        self.bins
            .par_chunks_mut(SUMS * stride)
            .enumerate()
            .for_each(|(by, row)| {
                let oy = output_position(by);
                for bx in 0..bins_w {
                    let at_bin = bilinear(guide_flux.view(), oy, output_position(bx));
                    let at_bin = if at_bin.is_finite() { at_bin } else { 0.0 };
                    for ch in (0..3).filter(|&ch| guided[ch]) {
                        let frames = row[(ch * 3 + 1) * stride + bx];
                        row[ch * 3 * stride + bx] = at_bin * frames;
                    }
                }
            });
        let sums = self.regression(guided);
        let guide_frames = effective_frames.index_axis(Axis(0), guide);
        let ws = guide_flux.ncols();
        for ch in (0..3).filter(|&ch| guided[ch]) {
            flux.index_axis_mut(Axis(0), ch)
                .axis_iter_mut(Axis(0))
                .into_par_iter()
                .zip(sums.par_chunks(ws))
                .enumerate()
                .for_each(|(oy, (mut plane_row, sums_row))| {
                    for (ox, (value, s)) in plane_row.iter_mut().zip(sums_row).enumerate() {
                        let n = guide_frames[[oy, ox]];
                        let s = &s[ch * 3..ch * 3 + 2];
                        if n.is_finite() && n > 0.0 && s[1] > 1e-6 {
                            let floor = 1.0 / n;
                            let guide_seen_by_colour = (s[0] / s[1]).max(floor);
                            let guide_here = guide_flux[[oy, ox]];
                            let factor = guide_here.max(floor) / guide_seen_by_colour;
                            *value *= match gate {
                                None => factor,
                                Some(sigmas) => {
                                    let variance =
                                        model.flux_variance(guide_here.max(0.0) as f64, n as f64);
                                    let noise =
                                        sigmas * (variance as f32).sqrt() / guide_seen_by_colour;
                                    1.0 + garrote(factor - 1.0, noise)
                                }
                            };
                        }
                    }
                });
        }
    }
}

/// A grid of phase bins in [`MergeAccumulator`]'s plane layout: bin (by, bx) sits at reference
/// position (by/u − margin, bx/u − margin).
struct BinGrid<'b> {
    bins: &'b [f32],
    /// Floats per plane row.
    stride: usize,
    bins_h: usize,
    bins_w: usize,
    /// Bins per reference px.
    u: f32,
    /// Reference px of margin (not whole for coarse bins).
    margin: f32,
}

/// The coarser bins of the sparse channels ([`MergeAccumulator::coarse_bins`]).
struct CoarseBins {
    bins: Vec<f32>,
    stride: usize,
    bins_h: usize,
    bins_w: usize,
    u: f32,
    margin: f32,
}

impl CoarseBins {
    fn grid(&self) -> BinGrid<'_> {
        BinGrid {
            bins: &self.bins,
            stride: self.stride,
            bins_h: self.bins_h,
            bins_w: self.bins_w,
            u: self.u,
            margin: self.margin,
        }
    }
}

/// What the kernel regression ([`gather_row`]) reads: the phase bins and the kernels, with the
/// geometry of both grids (see [`MergeAccumulator`]).
struct Gather<'g> {
    /// The bins in [`MergeAccumulator`]'s plane layout.
    bins: &'g [f32],
    stride: usize,
    bins_h: isize,
    bins_w: isize,
    /// (H, W, 3) inverse kernel covariances (a, b, c), row-major.
    inv_cov: &'g [f32],
    h: usize,
    w: usize,
    /// Bins per reference px and its inverse.
    u: f32,
    inv_u: f32,
    /// Margin of the bin grid and gather radius (reference px).
    margin: f32,
    radius: f32,
    /// Reference px per output px, and the reference position of output pixel 0.
    inv_s: f32,
    offset: f32,
    cutoff: f32,
    /// Kernel factor 1/scale_c of every channel (Ω_c⁻¹ = Ω⁻¹/scale_c).
    inv_scale: [f32; 4],
    /// Channels with sites in the CFA.
    present: [bool; 4],
    /// The sparsest channel (the smallest factor), whose weights are exponentials.
    base: usize,
    /// The channel whose weights each channel uses (itself, or `base` for a channel of the
    /// same factor).
    source: [usize; 4],
    /// k ≥ 2: the channel's weights are the k-th power of `base`'s ([`lane_power`]); 0: its
    /// own (or its source's).
    power: [u32; 4],
    /// Bound of the quadratic form inside which some channel's weight is non-zero.
    ellipse_limit: Option<f64>,
    /// Bound of the quadratic form inside which channel c's weight is non-zero, for the
    /// channels whose ellipse is narrower than `ellipse_limit`'s (`None`: that one).
    channel_limit: [Option<f64>; 4],
}

/// The regression sums of output row `oy` into `row` (W·scale pixels).
fn gather_row(g: &Gather, oy: usize, row: &mut [[f32; SUMS]]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            return unsafe { gather_row_avx2(g, oy, row) };
        }
    }
    gather_row_generic(g, oy, row)
}

/// [`gather_row_generic`] compiled for AVX2 (its eight-lane loops become vector instructions):
/// the same operations in the same order (no fused multiply-add), so the same result.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn gather_row_avx2(g: &Gather, oy: usize, row: &mut [[f32; SUMS]]) {
    gather_row_generic(g, oy, row)
}

/// Kernel regression of one output row over the phase bins (supplement Eq. 1–3): for every
/// output pixel p and every bin within the gather radius (and inside the widest channel's
/// ellipse), the weight g = exp(−½·dᵀΩ_c⁻¹d) of the bin's offset d for every channel c with
/// dᵀΩ_c⁻¹d below the cutoff, accumulated as Σ g·S0, Σ g·S1, Σ g²·S2 of the bin's sums.
///
/// Eight bins of a row at a time: the quadratic forms, the exponentials ([`fastmath::exp`])
/// and the products are lane-wise, with bins outside the row segment or the cutoff weighted 0
/// (empty bins hold zeros); each lane keeps its own partial sums, added in a fixed tree at
/// the end of the pixel. Deterministic and independent of the thread count; the order of the
/// additions differs from one sum over the bins in row order only by rounding.
///
/// Per bin row, the weights of every group of eight bins are made first (exponentials once per
/// distinct channel factor; a channel whose factor is k times the sparsest channel's takes the
/// k-th power of its weights, [`snap_scales`]), then each channel runs over the groups with its
/// three partial sums held in registers (three channels that share weights and groups in one
/// pass, [`RowPass::run3`]):
/// each partial sum receives the same products in the same order (rows, then groups) as when
/// the channels took turns per group, so the same bits
/// (`gather_row_matches_the_group_by_group_reference`).
#[inline(always)]
fn gather_row_generic(g: &Gather, oy: usize, row: &mut [[f32; SUMS]]) {
    let (bins, stride) = (g.bins, g.stride);
    let (u, inv_u, margin, radius) = (g.u, g.inv_u, g.margin, g.radius);
    let py = oy as f32 * g.inv_s + g.offset;
    let iy = (py.round().max(0.0) as usize).min(g.h - 1);
    let by0 = (((py - radius + margin) * u).ceil() as isize).max(0);
    let by1 = (((py + radius + margin) * u).floor() as isize).min(g.bins_h - 1);
    // Row offsets of the bin rows from the pixel row, and each pixel's dx interval of every
    // ellipse in each bin row (the main one, then each channel's own), made for all rows at
    // once ([`ellipse_spans`]).
    let dys: Vec<f32> = (by0..=by1)
        .map(|by| by as f32 * inv_u - margin - py)
        .collect();
    let rows = dys.len();
    let mut main_span = vec![[0.0f64; 2]; rows];
    let own = own_ellipses(g);
    let mut channel_span: [Vec<[f64; 2]>; 4] = std::array::from_fn(|ch| {
        if own[ch] == Some(ch) {
            vec![[0.0f64; 2]; rows]
        } else {
            Vec::new()
        }
    });
    let source = g.source;
    // Groups of eight bins of a bin row: at most the bins within the radius, plus one.
    let max_groups = ((2.0 * radius * u) as usize + 2).div_ceil(LANES) + 1;
    // weights[ch][group·8 + lane] of the channels that make their own weights.
    let mut quads = vec![0.0f32; max_groups * LANES];
    let mut weights: [Vec<f32>; 4] = std::array::from_fn(|ch| {
        vec![
            0.0f32;
            if g.present[ch] && g.source[ch] == ch {
                max_groups * LANES
            } else {
                0
            }
        ]
    });
    let plan = ChannelPlan::new(g, &own);
    // 0, 1, 2, … in f32 (exact): the bins' offsets from the first of a row segment.
    let lane_index: Vec<f32> = (0..max_groups * LANES).map(|k| k as f32).collect();
    for (ox, out) in row.iter_mut().enumerate() {
        let px = ox as f32 * g.inv_s + g.offset;
        let ix = (px.round().max(0.0) as usize).min(g.w - 1);
        let k = 3 * (iy * g.w + ix);
        let (a, b2, c) = (g.inv_cov[k], 2.0 * g.inv_cov[k + 1], g.inv_cov[k + 2]);
        let bx0 = (((px - radius + margin) * u).ceil() as isize).max(0);
        let bx1 = (((px + radius + margin) * u).floor() as isize).min(g.bins_w - 1);
        if let Some(limit) = g.ellipse_limit {
            ellipse_spans(a, b2, c, &dys, limit, &mut main_span);
        }
        for (ch, spans) in channel_span.iter_mut().enumerate() {
            if let (Some(limit), Some(true)) = (g.channel_limit[ch], own[ch].map(|o| o == ch)) {
                ellipse_spans(a, b2, c, &dys, limit, spans);
            }
        }
        // acc[channel][sum][lane]
        let mut acc = [[[0.0f32; LANES]; 3]; 4];
        for (row, by) in (by0..=by1).enumerate() {
            let dy = dys[row];
            let ady2 = a * dy * dy;
            let bdy = b2 * dy;
            // The bins of the row inside an ellipse's dx interval, widened by a bin each side.
            let cols = BinSpan {
                bx0,
                bx1,
                inv_u: inv_u as f64,
                centre: (margin + px) as f64,
                u: u as f64,
            };
            let (lo, hi) = match g.ellipse_limit {
                Some(_) => cols.of(main_span[row]),
                None => (bx0, bx1),
            };
            if lo > hi {
                continue;
            }
            let groups = ((hi - lo) as usize) / LANES + 1;
            debug_assert!(groups <= max_groups);
            // Per bin row: each channel's groups, the kernel's quadratic form of their bins,
            // the channels' weights, then the sums.
            let ranges =
                channel_group_ranges(&plan, &own, &cols, &channel_span, row, (lo, hi), groups);
            fill_quads(
                &mut quads[..groups * LANES],
                &lane_index[..groups * LANES],
                (lo, hi),
                (inv_u, margin, px),
                (ady2, bdy, c),
            );
            make_weights(g, &plan, &ranges, &quads, &mut weights);
            let row_start = by as usize * SUMS * stride;
            // The channels that share weights and groups (R, G and B of most CFAs) run over
            // the groups together: one pass with all their partial sums in registers (more
            // independent additions in flight), each partial sum receiving the same products
            // in the same order as in a pass of its own, so the same bits.
            for members in plan.passes() {
                let pass = RowPass {
                    bins,
                    weights: &weights[source[members[0]]],
                    start: row_start + lo as usize,
                    stride,
                    groups: ranges[members[0]],
                };
                if let &[c0, c1, c2] = members {
                    pass.run3(&mut acc, [c0, c1, c2]);
                } else {
                    for &ch in members {
                        pass.run1(&mut acc[ch], ch);
                    }
                }
            }
        }
        for (ch, acc) in acc.iter().enumerate() {
            for (sum, lanes) in acc.iter().enumerate() {
                out[ch * 3 + sum] = lane_sum(lanes);
            }
        }
    }
}

/// Which channels of [`gather_row_generic`] take their own, narrower ellipse: only where it is
/// markedly narrower than the main one (a nearly equal one, e.g. R and G against B of a CFA
/// with one site fewer of B, would skip about no group for the cost of its spans), made once
/// per distinct limit: `own[ch]` is the channel whose spans channel `ch` uses. Groups outside
/// a channel's ellipse add exact zeros to its sums, so which ellipses are used changes no bit.
fn own_ellipses(g: &Gather) -> [Option<usize>; 4] {
    let mut own: [Option<usize>; 4] = [None; 4];
    for ch in 0..4 {
        if let (Some(limit), Some(main)) = (g.channel_limit[ch], g.ellipse_limit) {
            if limit < OWN_ELLIPSE_RATIO * main {
                let same =
                    (0..ch).find(|&l| own[l] == Some(l) && g.channel_limit[l] == Some(limit));
                own[ch] = Some(same.unwrap_or(ch));
            }
        }
    }
    own
}

/// The groups of eight bins of a bin row (from bin `lo`, `groups` of them) that each present
/// channel of `plan` runs over: those overlapping its own bins `(lo, hi)` or, for a channel
/// with its own ellipse ([`own_ellipses`]), those of that ellipse's dx interval in `row`
/// (`channel_span`); a group of lanes outside them would add exact zeros to the channel's
/// sums, so it is skipped. Channels that share weights share the factor, hence the span.
/// (Plain functions, not closures, so that they are compiled with the caller's instruction
/// set: no libm calls for `floor` and `ceil`.)
#[inline(always)]
fn channel_group_ranges(
    plan: &ChannelPlan,
    own: &[Option<usize>; 4],
    cols: &BinSpan,
    channel_span: &[Vec<[f64; 2]>; 4],
    row: usize,
    (lo, hi): (isize, isize),
    groups: usize,
) -> [(usize, usize); 4] {
    let mut span = [(lo, hi); 4];
    for ch in 0..4 {
        match own[ch] {
            Some(o) if o == ch => {
                let (l, h) = cols.of(channel_span[ch][row]);
                span[ch] = (l.max(lo), h.min(hi));
            }
            Some(o) => span[ch] = span[o],
            None => {}
        }
    }
    let mut ranges = [(0usize, 0usize); 4];
    for ch in plan.present() {
        let (l, h) = span[ch];
        // First group whose last lane reaches l, last group starting at or before h.
        let first = if l <= lo {
            0
        } else {
            ((l - lo) as usize)
                .saturating_sub(LANES - 1)
                .div_ceil(LANES)
        };
        let end = if h < lo {
            0
        } else {
            (((h - lo) as usize) / LANES + 1).min(groups)
        };
        ranges[ch] = (first, end);
    }
    ranges
}

/// The kernel's quadratic form a·dy² + dx·(2b·dy + c·dx) of every bin of a row segment's
/// groups (`quads`, whole groups of eight): bin lo + k at dx = (lo + k)/u − margin − px, with
/// lo + k made in f32 as the sum of two exact integers (below 2^24), so the same value as
/// converting the integer bin index; lanes past the segment's last bin `hi` get a form no
/// factor brings below the cutoff (weight 0).
#[inline(always)]
fn fill_quads(
    quads: &mut [f32],
    lane_index: &[f32],
    (lo, hi): (isize, isize),
    (inv_u, margin, px): (f32, f32, f32),
    (ady2, bdy, c): (f32, f32, f32),
) {
    let lo_f = lo as f32;
    for (quad, &k) in quads.iter_mut().zip(lane_index) {
        let dx = (lo_f + k) * inv_u - margin - px;
        *quad = ady2 + dx * (bdy + c * dx);
    }
    quads[(hi - lo) as usize + 1..].fill(f32::INFINITY);
}

/// The kernel weights of every channel that makes its own (`plan.makers()`: exp(−q·factor/2)
/// below the cutoff) over its groups `ranges`, then of the channels whose factor is a multiple
/// of the base's (powers of the base's weights, which cover every group: the base's ellipse is
/// the widest).
#[inline(always)]
fn make_weights(
    g: &Gather,
    plan: &ChannelPlan,
    ranges: &[(usize, usize); 4],
    quads: &[f32],
    weights: &mut [Vec<f32>; 4],
) {
    for &ch in plan.makers() {
        let (first, end) = ranges[ch];
        let factor = g.inv_scale[ch];
        let weights = &mut weights[ch];
        for group in first..end {
            let at = group * LANES;
            // Local lanes, so that the compiler sees eight independent values.
            let quad: [f32; LANES] = quads[at..at + LANES].try_into().expect("lanes");
            let mut lanes = [0.0f32; LANES];
            for i in 0..LANES {
                let q = quad[i] * factor;
                let e = fastmath::exp(-0.5 * q);
                lanes[i] = if q < g.cutoff { e } else { 0.0 };
            }
            weights[at..at + LANES].copy_from_slice(&lanes);
        }
    }
    for &(ch, k) in plan.powered() {
        let (first, end) = ranges[ch];
        let mut own = std::mem::take(&mut weights[ch]);
        let base = &weights[g.base];
        for group in first..end {
            let at = group * LANES;
            let quad: [f32; LANES] = quads[at..at + LANES].try_into().expect("lanes");
            let w: [f32; LANES] = base[at..at + LANES].try_into().expect("lanes");
            let lanes = power_weights(g, ch, &quad, w, k);
            own[at..at + LANES].copy_from_slice(&lanes);
        }
        weights[ch] = own;
    }
}

/// What the channels of a [`Gather`] do in every bin row of [`gather_row_generic`], the same
/// for every pixel: which channels make their weights with exponentials, which take powers of
/// the base's, and which run over the groups together (those that share weights and ellipse,
/// hence groups), each list in channel order.
struct ChannelPlan {
    present: [usize; 4],
    present_len: usize,
    makers: [usize; 4],
    makers_len: usize,
    powered: [(usize, u32); 4],
    powered_len: usize,
    /// Channels of pass i: `pass_members[pass_start[i]..pass_start[i + 1]]`.
    pass_members: [usize; 4],
    pass_start: [usize; 5],
    passes_len: usize,
}

impl ChannelPlan {
    /// The plan of `g` whose channels use the ellipses `own` ([`gather_row_generic`]).
    fn new(g: &Gather, own: &[Option<usize>; 4]) -> ChannelPlan {
        let mut plan = ChannelPlan {
            present: [0; 4],
            present_len: 0,
            makers: [0; 4],
            makers_len: 0,
            powered: [(0, 0); 4],
            powered_len: 0,
            pass_members: [0; 4],
            pass_start: [0; 5],
            passes_len: 0,
        };
        let mut placed = [false; 4];
        for ch in (0..4).filter(|&ch| g.present[ch]) {
            plan.present[plan.present_len] = ch;
            plan.present_len += 1;
            if g.source[ch] == ch && g.power[ch] == 0 {
                plan.makers[plan.makers_len] = ch;
                plan.makers_len += 1;
            }
            if g.power[ch] != 0 {
                plan.powered[plan.powered_len] = (ch, g.power[ch]);
                plan.powered_len += 1;
            }
            if placed[ch] {
                continue;
            }
            let mut n = plan.pass_start[plan.passes_len];
            for other in ch..4 {
                if g.present[other]
                    && !placed[other]
                    && g.source[other] == g.source[ch]
                    && own[other] == own[ch]
                {
                    plan.pass_members[n] = other;
                    n += 1;
                    placed[other] = true;
                }
            }
            plan.passes_len += 1;
            plan.pass_start[plan.passes_len] = n;
        }
        plan
    }

    fn present(&self) -> impl Iterator<Item = usize> + '_ {
        self.present[..self.present_len].iter().copied()
    }

    fn makers(&self) -> &[usize] {
        &self.makers[..self.makers_len]
    }

    fn powered(&self) -> &[(usize, u32)] {
        &self.powered[..self.powered_len]
    }

    fn passes(&self) -> impl Iterator<Item = &[usize]> + '_ {
        (0..self.passes_len).map(|i| &self.pass_members[self.pass_start[i]..self.pass_start[i + 1]])
    }
}

/// Weights of channel `ch` whose factor is `k` times the base channel's, from the base's
/// weights `w` of bins with quadratic forms `quad`: `w`^k inside the channel's cutoff, 0
/// outside ([`gather_row_generic`]).
#[inline(always)]
fn power_weights(
    g: &Gather,
    ch: usize,
    quad: &[f32; LANES],
    w: [f32; LANES],
    k: u32,
) -> [f32; LANES] {
    let powers = lane_power(w, k);
    let factor = g.inv_scale[ch];
    std::array::from_fn(|i| {
        if quad[i] * factor < g.cutoff {
            powers[i]
        } else {
            0.0
        }
    })
}

/// One bin row's pass of the regression ([`gather_row_generic`]) for channels that share
/// weights: groups `groups` (first, end) of eight bins from bin `start` (the row's first bin in
/// the channel-0 plane of the bins), with `weights` per group.
struct RowPass<'p> {
    bins: &'p [f32],
    weights: &'p [f32],
    start: usize,
    stride: usize,
    groups: (usize, usize),
}

impl RowPass<'_> {
    /// The three planes (S0, S1, S2) of channel `ch` over the pass's groups.
    #[inline(always)]
    fn planes(&self, ch: usize) -> [&[f32]; 3] {
        let len = self.groups.1 * LANES;
        let at = self.start + ch * 3 * self.stride;
        std::array::from_fn(|k| &self.bins[at + k * self.stride..at + k * self.stride + len])
    }

    /// Adds the pass's products to channel `ch`'s partial sums acc[sum][lane]: Σ g·S0, Σ g·S1
    /// and Σ g²·S2, group by group.
    #[inline(always)]
    fn run1(&self, acc: &mut [[f32; LANES]; 3], ch: usize) {
        let [p0, p1, p2] = self.planes(ch);
        let [mut s0acc, mut s1acc, mut s2acc] = *acc;
        for group in self.groups.0..self.groups.1 {
            let r = group * LANES..(group + 1) * LANES;
            let weight: &[f32; LANES] = self.weights[r.clone()].try_into().expect("lanes");
            let s0: &[f32; LANES] = p0[r.clone()].try_into().expect("lanes");
            let s1: &[f32; LANES] = p1[r.clone()].try_into().expect("lanes");
            let s2: &[f32; LANES] = p2[r].try_into().expect("lanes");
            for i in 0..LANES {
                s0acc[i] += weight[i] * s0[i];
                s1acc[i] += weight[i] * s1[i];
                s2acc[i] += weight[i] * weight[i] * s2[i];
            }
        }
        *acc = [s0acc, s1acc, s2acc];
    }

    /// [`RowPass::run1`] of three channels in one pass over the groups (nine independent
    /// partial sums in flight instead of three): the same products in the same order per
    /// partial sum.
    #[inline(always)]
    fn run3(&self, acc: &mut [[[f32; LANES]; 3]; 4], [c0, c1, c2]: [usize; 3]) {
        let [p00, p01, p02] = self.planes(c0);
        let [p10, p11, p12] = self.planes(c1);
        let [p20, p21, p22] = self.planes(c2);
        let [mut a0, mut a1, mut a2] = acc[c0];
        let [mut b0, mut b1, mut b2] = acc[c1];
        let [mut d0, mut d1, mut d2] = acc[c2];
        for group in self.groups.0..self.groups.1 {
            let r = group * LANES..(group + 1) * LANES;
            let w: &[f32; LANES] = self.weights[r.clone()].try_into().expect("lanes");
            let lanes = |p: &[f32]| -> [f32; LANES] { p[r.clone()].try_into().expect("lanes") };
            let (x00, x01, x02) = (lanes(p00), lanes(p01), lanes(p02));
            let (x10, x11, x12) = (lanes(p10), lanes(p11), lanes(p12));
            let (x20, x21, x22) = (lanes(p20), lanes(p21), lanes(p22));
            for i in 0..LANES {
                let sq = w[i] * w[i];
                a0[i] += w[i] * x00[i];
                a1[i] += w[i] * x01[i];
                a2[i] += sq * x02[i];
                b0[i] += w[i] * x10[i];
                b1[i] += w[i] * x11[i];
                b2[i] += sq * x12[i];
                d0[i] += w[i] * x20[i];
                d1[i] += w[i] * x21[i];
                d2[i] += sq * x22[i];
            }
        }
        acc[c0] = [a0, a1, a2];
        acc[c1] = [b0, b1, b2];
        acc[c2] = [d0, d1, d2];
    }
}

/// The regression of [`gather_row_generic`] as it was before its weights were made a bin row
/// at a time (the channels taking turns per group of eight bins, the partial sums in memory):
/// the reference of `gather_row_matches_the_group_by_group_reference`.
#[cfg(test)]
fn gather_row_reference(g: &Gather, oy: usize, row: &mut [[f32; SUMS]]) {
    let (bins, stride) = (g.bins, g.stride);
    let (u, inv_u, margin, radius) = (g.u, g.inv_u, g.margin, g.radius);
    let py = oy as f32 * g.inv_s + g.offset;
    let iy = (py.round().max(0.0) as usize).min(g.h - 1);
    let by0 = (((py - radius + margin) * u).ceil() as isize).max(0);
    let by1 = (((py + radius + margin) * u).floor() as isize).min(g.bins_h - 1);
    // Row offsets of the bin rows from the pixel row, and each pixel's dx interval of every
    // ellipse in each bin row (the main one, then each channel's own), made for all rows at
    // once ([`ellipse_spans`]).
    let dys: Vec<f32> = (by0..=by1)
        .map(|by| by as f32 * inv_u - margin - py)
        .collect();
    let rows = dys.len();
    let mut main_span = vec![[0.0f64; 2]; rows];
    let mut channel_span: [Vec<[f64; 2]>; 4] = std::array::from_fn(|ch| {
        if g.channel_limit[ch].is_some() {
            vec![[0.0f64; 2]; rows]
        } else {
            Vec::new()
        }
    });
    for (ox, out) in row.iter_mut().enumerate() {
        let px = ox as f32 * g.inv_s + g.offset;
        let ix = (px.round().max(0.0) as usize).min(g.w - 1);
        let k = 3 * (iy * g.w + ix);
        let (a, b2, c) = (g.inv_cov[k], 2.0 * g.inv_cov[k + 1], g.inv_cov[k + 2]);
        let bx0 = (((px - radius + margin) * u).ceil() as isize).max(0);
        let bx1 = (((px + radius + margin) * u).floor() as isize).min(g.bins_w - 1);
        if let Some(limit) = g.ellipse_limit {
            ellipse_spans(a, b2, c, &dys, limit, &mut main_span);
        }
        for (ch, spans) in channel_span.iter_mut().enumerate() {
            if let Some(limit) = g.channel_limit[ch] {
                ellipse_spans(a, b2, c, &dys, limit, spans);
            }
        }
        // acc[channel][sum][lane]
        let mut acc = [[[0.0f32; LANES]; 3]; 4];
        for (row, by) in (by0..=by1).enumerate() {
            let dy = dys[row];
            let ady2 = a * dy * dy;
            let bdy = b2 * dy;
            // The bins of the row inside an ellipse's dx interval, widened by a bin each side.
            let cols = BinSpan {
                bx0,
                bx1,
                inv_u: inv_u as f64,
                centre: (margin + px) as f64,
                u: u as f64,
            };
            let (lo, hi) = match g.ellipse_limit {
                Some(_) => cols.of(main_span[row]),
                None => (bx0, bx1),
            };
            // Each channel's own bins (a narrower ellipse: fewer); a group of lanes outside them
            // would add exact zeros to the channel's sums, so it is skipped. Channels that
            // share weights share the factor, hence the span. (Plain functions, not closures,
            // so that they are compiled with the caller's instruction set: no libm calls for
            // `floor` and `ceil`.)
            let mut span = [(lo, hi); 4];
            for (ch, span) in span.iter_mut().enumerate() {
                if g.channel_limit[ch].is_some() {
                    let (l, h) = cols.of(channel_span[ch][row]);
                    *span = (l.max(lo), h.min(hi));
                }
            }
            let row_start = by as usize * SUMS * stride;
            let mut bx = lo;
            while bx <= hi {
                let mut quad = [0.0f32; LANES];
                let mut inside = [false; LANES];
                for i in 0..LANES {
                    let dx = (bx + i as isize) as f32 * inv_u - margin - px;
                    quad[i] = ady2 + dx * (bdy + c * dx);
                    inside[i] = bx + (i as isize) <= hi;
                }
                let first = row_start + bx as usize;
                for (ch, acc) in acc.iter_mut().enumerate() {
                    if !g.present[ch] || bx + (LANES as isize - 1) < span[ch].0 || bx > span[ch].1 {
                        continue;
                    }
                    let exps = |ch: usize| -> [f32; LANES] {
                        std::array::from_fn(|i| {
                            let q = quad[i] * g.inv_scale[ch];
                            let e = fastmath::exp(-0.5 * q);
                            if inside[i] && q < g.cutoff {
                                e
                            } else {
                                0.0
                            }
                        })
                    };
                    let weight = match g.power[ch] {
                        0 => exps(ch),
                        k => power_weights(g, ch, &quad, exps(g.base), k),
                    };
                    let at = first + ch * 3 * stride;
                    let s0: &[f32; LANES] = bins[at..at + LANES].try_into().expect("lanes");
                    let at = at + stride;
                    let s1: &[f32; LANES] = bins[at..at + LANES].try_into().expect("lanes");
                    let at = at + stride;
                    let s2: &[f32; LANES] = bins[at..at + LANES].try_into().expect("lanes");
                    for i in 0..LANES {
                        acc[0][i] += weight[i] * s0[i];
                        acc[1][i] += weight[i] * s1[i];
                        acc[2][i] += weight[i] * weight[i] * s2[i];
                    }
                }
                bx += LANES as isize;
            }
        }
        for (ch, acc) in acc.iter().enumerate() {
            for (sum, lanes) in acc.iter().enumerate() {
                out[ch * 3 + sum] = lane_sum(lanes);
            }
        }
    }
}

/// The bins of a row of the regression between `bx0` and `bx1` inside a dx interval of an
/// ellipse, widened by a bin each side ([`gather_row_generic`]).
struct BinSpan {
    bx0: isize,
    bx1: isize,
    inv_u: f64,
    /// Margin plus the output pixel's reference x.
    centre: f64,
    u: f64,
}

impl BinSpan {
    #[inline(always)]
    fn of(&self, [dx_lo, dx_hi]: [f64; 2]) -> (isize, isize) {
        (
            self.bx0
                .max(((dx_lo - self.inv_u + self.centre) * self.u).floor() as isize),
            self.bx1
                .min(((dx_hi + self.inv_u + self.centre) * self.u).ceil() as isize),
        )
    }
}

/// The sum of eight lanes in a fixed order (pairs of halves, then of quarters, then the two).
#[inline(always)]
fn lane_sum(l: &[f32; LANES]) -> f32 {
    let (a0, a1, a2, a3) = (l[0] + l[4], l[1] + l[5], l[2] + l[6], l[3] + l[7]);
    let (b0, b1) = (a0 + a2, a1 + a3);
    b0 + b1
}

/// How far W's flux can be trusted at a pixel whose merged W bit rate is `bit_rate` over
/// `effective_frames` (binary frames): 1 while at least `censoring_zeros` frames are expected
/// without a detection, falling linearly to 0 when none are. With few zero frames left, W's
/// MLE is censored: the kernel mixes sites that saw a photon in every frame (whose MLE is
/// clamped) with nearly saturated ones, and the mean bit rate inverted through Eq. 6 is a lower
/// bound of the flux. This project's generalisation of supplement §7's fallback, which
/// replaces a saturated W only where R, G and B are not saturated themselves.
fn w_trust(bit_rate: f32, effective_frames: f32, censoring_zeros: f32) -> f32 {
    let zeros = effective_frames * (1.0 - bit_rate);
    if zeros.is_finite() {
        (zeros / censoring_zeros).clamp(0.0, 1.0)
    } else {
        1.0
    }
}

/// [`ellipse_span`] of every row offset of `dys` into `spans`, a row where the whole row is
/// above the limit getting (+∞, −∞) (whose bins, [`BinSpan::of`], are an empty range). The same
/// operations per row in a loop without branches, which the compiler vectorises (four rows
/// per instruction with AVX2: divisions and square roots were most of the regression's
/// per-row cost), so the same values.
#[inline(always)]
fn ellipse_spans(a: f32, b2: f32, c: f32, dys: &[f32], limit: f64, spans: &mut [[f64; 2]]) {
    let (a, b, c) = (a as f64, b2 as f64 / 2.0, c as f64);
    let det = a * c - b * b;
    if !(c > 0.0 && det > 0.0) {
        spans.fill([f64::NEG_INFINITY, f64::INFINITY]);
        return;
    }
    let slack = limit * 1e-3 + 1e-6;
    for (&dy, span) in dys.iter().zip(spans) {
        let dy = dy as f64;
        let min = dy * dy * det / c;
        let half = ((limit + slack - min).max(0.0) / c).sqrt() * 1.001 + 1e-3;
        let centre = -b * dy / c;
        *span = if min > limit + slack {
            [f64::INFINITY, f64::NEG_INFINITY]
        } else {
            [centre - half, centre + half]
        };
    }
}

/// The dx interval of row offset `dy` where the kernel's quadratic form
/// a·dy² + 2b·dy·dx + c·dx² (`b2` = 2b) is below `limit`, widened by 0.1 % and 10⁻³ px against
/// rounding; `None` when the whole row is at least 0.1 % above it. Not positive definite:
/// an unbounded interval. The reference of [`ellipse_spans`].
#[cfg(test)]
fn ellipse_span(a: f32, b2: f32, c: f32, dy: f32, limit: f64) -> Option<(f64, f64)> {
    let (a, b, c, dy) = (a as f64, b2 as f64 / 2.0, c as f64, dy as f64);
    let det = a * c - b * b;
    if !(c > 0.0 && det > 0.0) {
        return Some((f64::NEG_INFINITY, f64::INFINITY));
    }
    // Minimum over dx at dx* = −b·dy/c, of value dy²·det/c.
    let min = dy * dy * det / c;
    let slack = limit * 1e-3 + 1e-6;
    if min > limit + slack {
        return None;
    }
    let half = ((limit + slack - min).max(0.0) / c).sqrt() * 1.001 + 1e-3;
    let centre = -b * dy / c;
    Some((centre - half, centre + half))
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

fn validate(
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
    if !super::warp::positive(config.cutoff) {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coarse_bins_share_each_fine_bin_between_the_nearest_coarse_bins() {
        // A sparse channel's coarse bins keep every plane's total, put a fine bin on a coarse
        // bin's centre wholly there and one halfway between two (f = 2) half in each; the
        // other channels' planes stay 0. R, G and B of the 75 % W pattern are sparse, W is not.
        use crate::cfa::{generate, Pattern};
        use crate::merge::kernels::{kernel_field, KernelConfig};
        let (h, w) = (12usize, 20usize);
        let reference = Array2::from_elem((h, w), 0.3f32);
        let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
        let kernels = kernel_field(&reference, &KernelConfig::default()).unwrap();
        let mut acc = MergeAccumulator::new(
            &cfa,
            &kernels,
            &AccumulateConfig::default(),
            PixelModel::binary(0.0),
        )
        .unwrap();
        let sparse = acc.sparse_channels();
        assert_eq!(sparse, [true, true, true, false]);
        let (stride, fine_w) = (acc.stride, acc.bins_w);
        let at = |by: usize, plane: usize, bx: usize| (by * SUMS + plane) * stride + bx;
        // Plane 3 (G's Σ r·counts): a sample on coarse bin (3, 4), one between (3, 5) and
        // (4, 5) vertically, one between (4, 6), (4, 7), (5, 6) and (5, 7); W's plane too.
        let plane = 3;
        acc.bins[at(6, plane, 8)] = 8.0;
        acc.bins[at(7, plane, 10)] = 4.0;
        acc.bins[at(9, plane, 13)] = 16.0;
        acc.bins[at(6, 9, 8)] = 5.0;
        let coarse = acc.coarse_bins(sparse);
        let get =
            |cy: usize, p: usize, cx: usize| coarse.bins[(cy * SUMS + p) * coarse.stride + cx];
        assert_eq!(get(3, plane, 4), 8.0);
        assert_eq!((get(3, plane, 5), get(4, plane, 5)), (2.0, 2.0));
        for (cy, cx) in [(4, 6), (4, 7), (5, 6), (5, 7)] {
            assert_eq!(get(cy, plane, cx), 4.0);
        }
        let total: f32 = (0..coarse.bins_h)
            .flat_map(|cy| (0..coarse.bins_w).map(move |cx| (cy, cx)))
            .map(|(cy, cx)| get(cy, plane, cx))
            .sum();
        assert_eq!(total, 28.0);
        assert!(coarse.bins.iter().enumerate().all(|(i, &v)| {
            let p = (i / coarse.stride) % SUMS;
            v == 0.0 || p == plane
        }));
        assert_eq!(
            (coarse.bins_h, coarse.bins_w),
            ((acc.bins_h - 1) / 2 + 1, (fine_w - 1) / 2 + 1)
        );
        assert_eq!((coarse.u, coarse.margin), (1.0, acc.margin as f32));
    }

    #[test]
    fn affine_targets_match_the_per_site_positions() {
        // `fill_affine` (eight sites at a time, the local mask's rounding reused) against
        // `fill` with the position closures of SubBlockMotion::Affine and ::CameraAndLocal.
        use rand::{Rng, SeedableRng};
        let (h, w) = (23usize, 37usize);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let robust: Vec<f32> = (0..h * w).map(|_| rng.gen_range(-0.2..1.0)).collect();
        let excluded: Vec<bool> = (0..h * w).map(|_| rng.gen_bool(0.05)).collect();
        let mask: Vec<bool> = (0..h * w).map(|i| (i / w) % 7 < 2 || i % w > 30).collect();
        let flow: Vec<f32> = (0..h * w * 2).map(|_| rng.gen_range(-2.5..2.5)).collect();
        let (u, margin) = (2.0f32, 3.0f32);
        let bins_h = (h - 1 + 6) * 2 + 1;
        let bins_w = (w - 1 + 6) * 2 + 1;
        let grid = TargetGrid {
            h,
            w,
            u,
            margin,
            bins_h,
            bins_w,
            stride: (bins_w + LANES - 1).next_multiple_of(LANES),
            excluded: Some(&excluded),
            robust: Some(&robust),
        };
        for (matrix, offset) in [
            ([[1.0, 0.0], [0.0, 1.0]], [0.5, -0.5]),
            ([[1.001, 0.01], [-0.012, 0.998]], [-1.37, 2.61]),
            ([[0.97, 0.2], [-0.2, 0.97]], [4.2, -7.9]),
        ] {
            let mut fast = vec![(0u32, 0.0f32); h * w];
            let mut plain = vec![(1u32, 1.0f32); h * w];
            let mut fast_spans = vec![(0u32, 0u32); h];
            let mut plain_spans = vec![(1u32, 1u32); h];
            // Every row's span is its lowest and highest target bin of a site kept.
            let spans_of = |targets: &[(u32, f32)]| -> Vec<(u32, u32)> {
                targets
                    .chunks(w)
                    .map(|row| {
                        let kept: Vec<u32> = row
                            .iter()
                            .map(|&(bin, _)| bin)
                            .filter(|&bin| bin != u32::MAX)
                            .collect();
                        match (kept.iter().min(), kept.iter().max()) {
                            (Some(&lo), Some(&hi)) => (lo, hi),
                            _ => (u32::MAX, 0),
                        }
                    })
                    .collect()
            };
            // Both fills agree, excluded sites have no target, and the spans are the targets'.
            let check = |fast: &[(u32, f32)],
                         fast_spans: &[(u32, u32)],
                         plain: &[(u32, f32)],
                         plain_spans: &[(u32, u32)],
                         case: &str| {
                assert_eq!(fast, plain, "{case} {matrix:?} {offset:?}");
                assert!(excluded
                    .iter()
                    .zip(fast)
                    .all(|(&e, &(bin, _))| !e || bin == u32::MAX));
                assert_eq!(fast_spans, spans_of(fast));
                assert_eq!(plain_spans, spans_of(plain));
            };
            grid.fill_affine(&mut fast, &mut fast_spans, &matrix, &offset, None);
            grid.fill(&mut plain, &mut plain_spans, |q| {
                affine_position(&matrix, &offset, q)
            });
            check(&fast, &fast_spans, &plain, &plain_spans, "affine");

            let (hf, wf) = ((h - 1) as f32, (w - 1) as f32);
            grid.fill_affine(
                &mut fast,
                &mut fast_spans,
                &matrix,
                &offset,
                Some((&mask, &flow)),
            );
            grid.fill(&mut plain, &mut plain_spans, |q| {
                let p = affine_position(&matrix, &offset, q);
                let inside = p[0] >= 0.0 && p[1] >= 0.0 && p[0] <= hf && p[1] <= wf;
                if inside
                    && !mask[round_half_away(p[0]) as usize * w + round_half_away(p[1]) as usize]
                {
                    p
                } else {
                    reference_position(&flow, h, w, q)
                }
            });
            check(&fast, &fast_spans, &plain, &plain_spans, "camera and local");
        }
    }

    #[test]
    fn lane_targets_avx2_match_the_scalar_lanes() {
        // `lane_targets_avx2` against `lane_targets` (the scalar path, which an AVX2 CPU
        // otherwise never runs) on lanes inside and outside the image and the bins, at their
        // edges, NaN and infinite, with and without a robustness map, skipped or not.
        #[cfg(target_arch = "x86_64")]
        {
            use rand::{Rng, SeedableRng};
            if !std::arch::is_x86_feature_detected!("avx2") {
                return;
            }
            let (h, w) = (11usize, 13usize);
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
            let robust: Vec<f32> = (0..h * w)
                .map(|i| match i % 9 {
                    0 => 0.0,
                    1 => f32::NAN,
                    _ => rng.gen_range(-0.3..1.0),
                })
                .collect();
            let (bins_h, bins_w) = (27usize, 31usize);
            let specials = [
                f32::NAN,
                f32::INFINITY,
                f32::NEG_INFINITY,
                -0.0,
                -1.0,
                0.0,
                (h - 1) as f32,
                (w - 1) as f32,
                bins_h as f32,
                bins_w as f32,
                (bins_h - 1) as f32,
                1e10,
            ];
            let value = |rng: &mut rand_chacha::ChaCha8Rng, hi: f32| -> f32 {
                if rng.gen_bool(0.3) {
                    specials[rng.gen_range(0..specials.len())]
                } else {
                    rng.gen_range(-3.0..hi + 3.0f32).round()
                }
            };
            for map in [Some(&robust[..]), None] {
                let grid = TargetGrid {
                    h,
                    w,
                    u: 2.0,
                    margin: 1.0,
                    bins_h,
                    bins_w,
                    stride: (bins_w + LANES - 1).next_multiple_of(LANES),
                    excluded: None,
                    robust: map,
                };
                for _ in 0..2000 {
                    let rounded: [[f32; LANES]; 2] = [
                        std::array::from_fn(|_| value(&mut rng, h as f32)),
                        std::array::from_fn(|_| value(&mut rng, w as f32)),
                    ];
                    let bin: [[f32; LANES]; 2] = [
                        std::array::from_fn(|_| value(&mut rng, bins_h as f32)),
                        std::array::from_fn(|_| value(&mut rng, bins_w as f32)),
                    ];
                    let skip: [bool; LANES] = std::array::from_fn(|_| rng.gen_bool(0.2));
                    let plain = match map {
                        Some(m) => grid.lane_targets(&rounded, &bin, &skip, |i| m[i]),
                        None => grid.lane_targets(&rounded, &bin, &skip, |_| 1.0),
                    };
                    // SAFETY: AVX2 is supported (checked above); the map holds H·W values.
                    let fast = unsafe { grid.lane_targets_avx2(&rounded, &bin, &skip) };
                    let bits = |t: [(u32, f32); LANES]| t.map(|(b, r)| (b, r.to_bits()));
                    assert_eq!(bits(fast), bits(plain), "{rounded:?} {bin:?} {skip:?}");
                }
            }
        }
    }

    #[test]
    fn gather_row_matches_the_group_by_group_reference() {
        // The regression with its weights made a bin row at a time against the form where the
        // channels took turns per group of eight bins: bit for bit, with random bins and
        // kernels, for CFAs whose channels share weights (R, G, B), make their own (W) or have
        // a narrower ellipse of their own, at output scales 1 and 2 and a wide radius.
        use crate::cfa::{generate, Pattern};
        use crate::merge::kernels::{kernel_field, KernelConfig};
        use rand::{Rng, SeedableRng};
        let (h, w) = (13usize, 29usize);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let reference =
            Array2::from_shape_fn((h, w), |_| rng.gen_range(0.05f32..0.95)).mapv(|v| v * v);
        let mut compared = 0;
        for pattern in [
            Pattern::Bayer,
            Pattern::Rgbw50,
            Pattern::Rgbw75Regular,
            Pattern::Colorspad,
        ] {
            let cfa = match generate(&pattern, h, w, 5) {
                Ok(cfa) => cfa,
                Err(_) => continue, // a pattern of fixed size
            };
            // And a W-rich CFA with exactly as many R, G and B sites (one pass of three
            // channels, `RowPass::run3`).
            let cfas = [
                cfa,
                {
                    let mut codes = Array2::from_elem((h, w), 3u8);
                    for (k, i) in (0..h * w).step_by(4).take(93).enumerate() {
                        codes[[i / w, i % w]] = (k % 3) as u8;
                    }
                    Cfa::new(codes).unwrap()
                },
                {
                    // /tmp/cap10k's pattern (W rows, then W with R and G, W with G and B): as
                    // many R as B sites, G twice and W about 14 times (weights as powers of
                    // R's, `snap_scales`), G's and W's ellipses their own.
                    let codes = Array2::from_shape_fn((h, w), |(y, x)| match (y % 4, x % 4) {
                        (1, 1) => 0,
                        (1, 3) | (3, 1) => 1,
                        (3, 3) => 2,
                        _ => 3,
                    });
                    Cfa::new(codes).unwrap()
                },
            ];
            for cfa in &cfas {
                for (scale, bins, max_radius, exponent) in [
                    (1, 2, 5, 1.0),
                    (2, 2, 5, 1.0),
                    (1, 3, 8, 0.5),
                    (2, 1, 3, 1.0),
                ] {
                    let config = AccumulateConfig {
                        scale,
                        bins_per_output_px: bins,
                        max_radius,
                        spacing_exponent: exponent,
                        ..AccumulateConfig::default()
                    };
                    let kernels =
                        kernel_field(&reference, &KernelConfig::default().for_output_scale(scale))
                            .unwrap();
                    let mut acc =
                        MergeAccumulator::new(cfa, &kernels, &config, PixelModel::binary(0.0))
                            .unwrap();
                    let stride = acc.stride;
                    for (i, v) in acc.bins.iter_mut().enumerate() {
                        // Padding columns stay 0; some empty bins.
                        if i % stride < acc.bins_w && rng.gen_bool(0.8) {
                            *v = rng.gen_range(0.0f32..50.0);
                        }
                    }
                    let ws = w * scale;
                    acc.with_gather(|g| {
                        for oy in 0..h * scale {
                            let mut fast = vec![[0.0f32; SUMS]; ws];
                            let mut generic = vec![[1.0f32; SUMS]; ws];
                            let mut reference = vec![[2.0f32; SUMS]; ws];
                            gather_row(g, oy, &mut fast);
                            gather_row_generic(g, oy, &mut generic);
                            gather_row_reference(g, oy, &mut reference);
                            let bits = |v: &Vec<[f32; SUMS]>| {
                                v.iter().map(|s| s.map(f32::to_bits)).collect::<Vec<_>>()
                            };
                            assert_eq!(
                                bits(&fast),
                                bits(&reference),
                                "{pattern:?} {config:?} {oy}"
                            );
                            assert_eq!(bits(&generic), bits(&reference), "{pattern:?} {config:?}");
                            assert!(reference.iter().flatten().any(|&v| v > 0.0));
                        }
                    });
                    compared += 1;
                }
            }
        }
        assert!(compared >= 24, "{compared}");
    }

    #[test]
    fn scales_near_a_multiple_of_the_sparsest_are_snapped_and_others_kept() {
        // /tmp/cap10k's CFA: 7,936 R, 15,748 G, 7,812 B and 94,488 W sites. B is the sparsest;
        // R is 1.6 % denser (its factor 1 times B's), G about twice and W about 12 times.
        let n = 125_984.0f32;
        let scales = [n / 7_936.0, n / 15_748.0, n / 7_812.0, n / 94_488.0];
        let (snapped, multiples) = snap_scales(scales);
        let b = scales[2];
        assert_eq!(multiples, [1, 2, 0, 12]);
        assert_eq!(snapped, [b, b / 2.0, b, b / 12.0]);
        // Bayer: R the sparsest (the first of equal ones), B shares it, G is half of it.
        assert_eq!(
            snap_scales([4.0, 2.0, 4.0, 0.0]),
            ([4.0, 2.0, 4.0, 0.0], [0, 2, 1, 0])
        );
        // 1 % apart: shared; 3 % apart, a ratio of 1.55, absent channels: kept.
        assert_eq!(
            snap_scales([12.0, 12.12, 0.0, 0.0]),
            ([12.12, 12.12, 0.0, 0.0], [1, 0, 0, 0])
        );
        assert_eq!(
            snap_scales([12.0, 12.4, 8.0, 0.0]),
            ([12.0, 12.4, 8.0, 0.0], [0, 0, 0, 0])
        );
        assert_eq!(snap_scales([0.0; 4]), ([0.0; 4], [0; 4]));
    }

    #[test]
    fn lane_power_is_the_power() {
        let w: [f32; LANES] = std::array::from_fn(|i| 0.05 + 0.13 * i as f32);
        for k in 1..=MAX_SNAP_MULTIPLE {
            let p = lane_power(w, k);
            for i in 0..LANES {
                let exact = (w[i] as f64).powi(k as i32);
                assert!(
                    (p[i] as f64 - exact).abs() <= 1e-6 * exact + 1e-30,
                    "{k} {i}: {} vs {exact}",
                    p[i]
                );
            }
        }
    }

    #[test]
    fn garrote_is_zero_within_the_threshold_and_shrinks_beyond_it() {
        assert_eq!(garrote(0.5, 1.0), 0.0);
        assert_eq!(garrote(-1.0, 1.0), 0.0);
        assert_eq!(garrote(2.0, 1.0), 1.5);
        assert_eq!(garrote(-4.0, 2.0), -3.0);
        assert_eq!(garrote(0.3, 0.0), 0.3);
    }

    #[test]
    fn index_in_is_the_saturating_cast_inside_its_range() {
        for hi in [0.0f32, 1.0, 253.0, 1015.0, 16_777_216.0, 2_147_483_520.0] {
            let mut values = vec![0.0, -0.0, hi, f32::NAN, 0.999_999_9];
            values.extend((0..1000).map(|i| hi * i as f32 / 999.0));
            values.extend((0..100).map(|i| (i as f32 * 0.37).min(hi)));
            for v in values {
                assert_eq!(index_in(v, hi), v as i32, "{v} in [0, {hi}]");
            }
            // Outside: clamped (the callers discard those lanes).
            assert_eq!(index_in(-5.0, hi), 0);
            assert_eq!(index_in(f32::INFINITY, hi), hi as i32);
            assert_eq!(index_in(f32::NEG_INFINITY, hi), 0);
        }
    }

    #[test]
    fn round_half_away_matches_f32_round() {
        let mut values = vec![
            0.0,
            0.5,
            -0.5,
            1.5,
            -1.5,
            2.5,
            0.49999997,
            -0.49999997,
            8_388_607.5,
            1e9,
            -1e9,
        ];
        values.extend((-4000..4000).map(|i| i as f32 * 0.013_7 + 0.25));
        values.extend([f32::INFINITY, f32::NEG_INFINITY, 3e9, -3e9, 2_147_483_520.0]);
        for v in values {
            assert_eq!(round_half_away(v), v.round(), "{v}");
            assert_eq!(round_half_away_trunc(v), v.round(), "{v}");
        }
        assert!(round_half_away(f32::NAN).is_nan());
        assert!(round_half_away_trunc(f32::NAN).is_nan());
    }

    #[test]
    fn ellipse_span_holds_every_dx_below_the_limit() {
        let limit = 20.0;
        for (a, b2, c) in [(1.0f32, 0.0f32, 1.0f32), (4.0, 3.0, 1.5), (0.3, -0.5, 2.0)] {
            for dy in [-3.0f32, -0.5, 0.0, 1.25, 4.0] {
                let span = ellipse_span(a, b2, c, dy, limit);
                for i in -400..=400 {
                    let dx = i as f32 * 0.025;
                    let quad = a * dy * dy + dx * (b2 * dy + c * dx);
                    if (quad as f64) < limit {
                        let (lo, hi) = span.expect("row with a point below the limit");
                        assert!(lo <= dx as f64 && dx as f64 <= hi, "{a} {b2} {c} {dy} {dx}");
                    }
                }
            }
        }
        // A row entirely outside the ellipse.
        assert_eq!(ellipse_span(1.0, 0.0, 1.0, 10.0, limit), None);
    }

    #[test]
    fn ellipse_spans_are_the_rows_ellipse_spans() {
        // The vectorised form against the per-row one, bit for bit, empty rows and
        // non-definite forms included.
        let dys: Vec<f32> = (0..41).map(|i| i as f32 * 0.25 - 5.1).collect();
        let mut spans = vec![[0.0f64; 2]; dys.len()];
        for limit in [9.0f64, 12.0, 108.0] {
            for (a, b2, c) in [
                (1.0f32, 0.0f32, 1.0f32),
                (4.0, 3.0, 1.5),
                (0.3, -0.5, 2.0),
                (16.0, 31.9, 16.0),
                (1.0, 4.0, 1.0),
                (1.0, 0.0, 0.0),
                (f32::NAN, 0.0, 1.0),
            ] {
                ellipse_spans(a, b2, c, &dys, limit, &mut spans);
                for (&dy, span) in dys.iter().zip(&spans) {
                    let want = ellipse_span(a, b2, c, dy, limit)
                        .map_or([f64::INFINITY, f64::NEG_INFINITY], |(l, h)| [l, h]);
                    assert_eq!(
                        span.map(f64::to_bits),
                        want.map(f64::to_bits),
                        "{a} {b2} {c} {dy} {limit}"
                    );
                }
            }
        }
    }
}
