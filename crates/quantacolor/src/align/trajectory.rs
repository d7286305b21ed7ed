//! The camera trajectory at single-frame resolution, fitted to every detected photon: this
//! project's own stage, not the paper's.
//!
//! The paper (§4.1) and Quanta Burst Photography (Ma et al. 2020, §4.2) align block sums and
//! interpolate their motion in time; [`super::track`] measures fast motion on sub-blocks of
//! ~10 frames. Both see a sub-block as one image, so under fast shake (1–2 px per frame) a
//! sub-block is a streak, and its fit lands anywhere along it: the quality suite measured a
//! median end-point error of 2–3 px on fast handheld captures after tracking.
//!
//! Here the inverse camera map of every frame (frame → reference, affine about the image
//! centre) is a piecewise-linear function of time through *knots* every few frames, and the
//! knots are fitted jointly to the binary frames themselves by maximum likelihood:
//!
//! - each grey site (W, not hot) of frame `f` is a Bernoulli trial whose success probability is
//!   the template `p` (the mean bit rate per frame at that scene point, built from all frames
//!   at the current trajectory) at the site's reference position; the log-likelihood is
//!   `Σ_detections log p + Σ_no-detection log(1 − p)`, the single-photon form of the paper's
//!   binomial model (Eq. 2–3);
//! - Fisher scoring (Gauss–Newton for this likelihood) on the knot parameters, coarse to fine
//!   over template blur σ, the template rebuilt from the updated trajectory every iteration;
//! - a Gaussian prior on the trajectory's acceleration (second differences of the knots) keeps
//!   knots whose frames hold few photons or little texture on the path of their neighbours.
//!
//! The normal equations are banded (a knot couples to two neighbours on each side), so one
//! iteration costs one pass over the frames' sites plus a banded Cholesky solve; memory is
//! O(number of knots), not O(T · H · W).

// Index loops mirror the matrix algebra (band offsets, symmetric fills).
#![allow(clippy::needless_range_loop)]

use super::grey::GreyMethod;
#[cfg(target_arch = "x86_64")]
use super::refine::inside_avx2;
use super::refine::{sample_template, template_level, AffineMotion, FrameMotion, TemplateLevel};
use crate::capture::frames::FrameLayout;
use crate::capture::{BinaryFrames, Capture};
use crate::cfa::Channel;
use crate::error::{Error, Result};
use crate::filters::gaussian_blur;
use crate::progress::Progress;
use ndarray::Array2;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// Settings of [`fit_photon_trajectory`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrajectoryConfig {
    /// Fit the trajectory to the photons after fast-motion tracking.
    pub enabled: bool, // true
    /// Frames between knots of the piecewise-linear trajectory.
    pub knot_frames: usize, // 4 frames
    /// Template blur of each coarse-to-fine level (px): the capture range of the fit.
    pub sigmas_px: Vec<f32>,
    /// Fisher-scoring iterations per level (the template is rebuilt before each).
    pub iterations: usize, // 2
    /// Prior standard deviation of the camera's acceleration (px per frame², at the image
    /// corners for the linear part): hand shake is smooth, photon noise is not.
    pub acceleration_px: f64, // 0.05 px/frame²
    /// Scene margin around the sensor kept in the template (px): content that leaves the
    /// sensor while the camera moves still aligns.
    pub margin_px: usize, // 48 px
    /// Every Fisher-scoring iteration but the last (template and score) uses the grey sites of
    /// every n-th sensor row only; the last uses every site. 1 (the default) uses every row
    /// throughout; 2 is a speed setting: the early iterations only bring the knots within the
    /// fine level's capture range, for which a fraction of the photons nearly suffices.
    /// Measured with 2 against 1 (`quantacolor simulate --cfa colorspad --motion
    /// fast-handheld`, sRGB PSNR without denoising, border 16): the stage takes 0.68 of the
    /// time (10,000-frame kodim15, seed 204: 13.96 → 9.44 s) at 33.945 → 33.957 dB, and
    /// 29.765 → 29.758 dB on 10,000-frame kodim22 (seed 303); 3,000-frame captures of kodim02,
    /// kodim04, kodim12, the chart and ScanLines_Cannon −0.009 to +0.16 dB; `bench quality`'s
    /// fast handheld captures (512 frames, 40 px, 2°) 32.02 → 31.99 and 29.52 → 29.56 dB with
    /// chroma-BM3D; `experiment sensors`' night fast-shake SPAD capture (0.04 detections per
    /// frame) 19.15 → 19.12 dB. But on MultiResolution_Bonita under fast shake (HDR, 3,000
    /// frames, seeds 311–313), whose tracked cameras carry a shear that the trajectory must
    /// remove ([`super::TrackConfig::max_linear`]), it lost 0.04–0.15 dB, so it is not the
    /// default. Skipping iterations instead (the coarse level, or one iteration of each
    /// level) lost 0.19–0.42 dB on `bench quality`'s kodim22 fast capture.
    pub early_row_step: usize, // 1
}

impl Default for TrajectoryConfig {
    fn default() -> Self {
        TrajectoryConfig {
            enabled: true,
            knot_frames: 4,
            sigmas_px: vec![1.5, 0.6],
            iterations: 2,
            acceleration_px: 0.05,
            margin_px: 48,
            early_row_step: 1,
        }
    }
}

impl TrajectoryConfig {
    /// Checks that the settings hold usable values (the error names the key).
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, what: &str, value: String| {
            Err(Error::invalid(format!(
                "photon trajectory: [burst.trajectory] {key} must be {what}, got {value}"
            )))
        };
        for (key, value) in [
            ("knot_frames", self.knot_frames),
            ("iterations", self.iterations),
            ("early_row_step", self.early_row_step),
        ] {
            if value == 0 {
                return bad(key, "at least 1", value.to_string());
            }
        }
        if self.sigmas_px.is_empty() || self.sigmas_px.iter().any(|&s| !(s > 0.0 && s.is_finite()))
        {
            return bad(
                "sigmas_px",
                "a non-empty list of positive pixel sizes",
                format!("{:?}", self.sigmas_px),
            );
        }
        if !(self.acceleration_px > 0.0 && self.acceleration_px.is_finite()) {
            return bad(
                "acceleration_px",
                "a positive number",
                self.acceleration_px.to_string(),
            );
        }
        Ok(())
    }
}

/// Bernoulli probabilities are kept inside [P_MIN, 1 − P_MIN].
const P_MIN: f64 = 1e-4;

/// A piecewise-linear inverse camera trajectory (frame → reference displacement about the image
/// centre) through knots at `times`.
#[derive(Debug, Clone)]
struct Trajectory {
    times: Vec<usize>,
    knots: Vec<[f64; 6]>,
}

impl Trajectory {
    fn new(frames: usize, knot_frames: usize) -> Trajectory {
        let last = frames.saturating_sub(1);
        let step = knot_frames.max(1);
        let mut times: Vec<usize> = (0..=last).step_by(step).collect();
        if *times.last().expect("at least one knot") != last {
            times.push(last);
        }
        let knots = vec![[0.0; 6]; times.len()];
        Trajectory { times, knots }
    }

    /// The knot interval holding frame `t` and the weight of its right knot.
    fn locate(&self, t: f64) -> (usize, f64) {
        if self.times.len() == 1 {
            return (0, 0.0);
        }
        let k = (self
            .times
            .partition_point(|&s| (s as f64) <= t)
            .saturating_sub(1))
        .min(self.times.len() - 2);
        let (t0, t1) = (self.times[k] as f64, self.times[k + 1] as f64);
        (k, ((t - t0) / (t1 - t0)).clamp(0.0, 1.0))
    }

    fn params_at(&self, t: f64) -> [f64; 6] {
        let (k, a) = self.locate(t);
        if self.times.len() == 1 {
            return self.knots[0];
        }
        std::array::from_fn(|i| self.knots[k][i] * (1.0 - a) + self.knots[k + 1][i] * a)
    }

    fn inverse_camera_at(&self, t: f64) -> AffineMotion {
        AffineMotion::from_params(self.params_at(t))
    }
}

/// The grey sites of a capture, row by row, relative to the image centre.
struct Sites {
    width: usize,
    /// For every row, the columns of its grey sites.
    columns: Vec<Vec<u16>>,
    /// For every row, one mask per eight columns 8k..8k + 8: bit l set where column 8k + l is
    /// a grey site.
    masks: Vec<Vec<u8>>,
    centre: [f64; 2],
}

impl Sites {
    /// The sites in `columns` (row by row, increasing) of an image `width` wide.
    fn new(width: usize, columns: Vec<Vec<u16>>, centre: [f64; 2]) -> Sites {
        let masks = columns
            .iter()
            .map(|row| {
                let mut masks = vec![0u8; width.div_ceil(8)];
                for &x in row {
                    masks[x as usize / 8] |= 1 << (x % 8);
                }
                masks
            })
            .collect();
        Sites {
            width,
            columns,
            masks,
            centre,
        }
    }

    fn count(&self) -> usize {
        self.columns.iter().map(Vec::len).sum()
    }

    /// The sites of every `step`-th row (0, step, 2·step, …); the other rows keep none.
    fn every_nth_row(&self, step: usize) -> Sites {
        let step = step.max(1);
        Sites::new(
            self.width,
            self.columns
                .iter()
                .enumerate()
                .map(|(y, row)| {
                    if y % step == 0 {
                        row.clone()
                    } else {
                        Vec::new()
                    }
                })
                .collect(),
            self.centre,
        )
    }
}

/// Calls `visit(y, x, detected)` for every grey site of frame `t` (the tests' site-by-site
/// reference).
#[cfg(test)]
fn for_each_site(
    frames: &BinaryFrames,
    sites: &Sites,
    t: usize,
    mut visit: impl FnMut(usize, usize, bool),
) {
    let packed = matches!(frames.layout(), FrameLayout::Packed);
    for (y, columns) in sites.columns.iter().enumerate() {
        let row = frames.raw_row(t, y);
        for &x in columns {
            let x = x as usize;
            visit(y, x, site_bit(row, x, packed));
        }
    }
}

/// Whether the site in column `x` of a frame's raw row detected a photon.
#[inline(always)]
fn site_bit(row: &[u8], x: usize, packed: bool) -> bool {
    if packed {
        (row[x / 8] >> (7 - x % 8)) & 1 == 1
    } else {
        row[x] != 0
    }
}

/// The mean bit rate per frame at every scene point of the reference frame (with a margin),
/// from all frames splatted bilinearly to their reference positions along `trajectory`;
/// normalized convolution at σ 0.7 px, the global mean where nothing landed nearby.
fn build_template(
    frames: &BinaryFrames,
    sites: &Sites,
    trajectory: &Trajectory,
    height: usize,
    margin: usize,
) -> Array2<f32> {
    let (th, tw) = (height + 2 * margin, sites.width + 2 * margin);
    let n = frames.frame_count();
    let chunk = n.div_ceil(rayon::current_num_threads().max(1) * 4).max(1);
    let starts: Vec<usize> = (0..n).step_by(chunk).collect();
    let packed = matches!(frames.layout(), FrameLayout::Packed);
    let (sum, exposure) = starts
        .par_iter()
        .map(|&start| {
            let mut splats = Splats::zeros(th, tw);
            for t in start..(start + chunk).min(n) {
                let camera = trajectory.inverse_camera_at(t as f64);
                for (y, columns) in sites.columns.iter().enumerate() {
                    if columns.is_empty() {
                        continue;
                    }
                    let map = RowMap::new(sites, &camera, y, packed, margin as f64);
                    splats.add_row(frames.raw_row(t, y), y, sites, &map);
                }
            }
            (splats.sum, splats.exposure)
        })
        .reduce(
            || (Array2::zeros((th, tw)), Array2::zeros((th, tw))),
            |(a, b), (c, d)| (a + c, b + d),
        );
    let (num, den) = rayon::join(
        || gaussian_blur(&sum, 0.7),
        || gaussian_blur(&exposure, 0.7),
    );
    let mean = sum.sum() / exposure.sum().max(1.0);
    let floor = 1e-3 * den.iter().copied().fold(0.0f32, f32::max);
    ndarray::Zip::from(&num)
        .and(&den)
        .map_collect(|&n, &d| if d > floor { n / d } else { mean })
}

/// The template's two splat images: detections (`sum`) and trials (`exposure`).
struct Splats {
    sum: Array2<f32>,
    exposure: Array2<f32>,
    /// Whether [`splat_row_avx2`] can run: AVX2 and FMA, and flat indices fit an i32.
    #[cfg(target_arch = "x86_64")]
    avx2: bool,
}

impl Splats {
    fn zeros(height: usize, width: usize) -> Splats {
        Splats {
            sum: Array2::zeros((height, width)),
            exposure: Array2::zeros((height, width)),
            #[cfg(target_arch = "x86_64")]
            avx2: has_avx2_and_fma() && height * width < i32::MAX as usize,
        }
    }

    /// Splats every site of one row of a frame: a trial at each, a detection where its bit is
    /// set; bilinearly, sites outside the images' interior dropped.
    fn add_row(&mut self, row: &[u8], y: usize, sites: &Sites, map: &RowMap) {
        let (h, w) = self.sum.dim();
        let sum = self.sum.as_slice_mut().expect("standard layout");
        let exposure = self.exposure.as_slice_mut().expect("standard layout");
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` holds the CPU's features and that indices fit an i32.
            unsafe { splat_row_avx2(exposure, sum, (h, w), row, y, &sites.masks[y], map) };
            return;
        }
        for &x in &sites.columns[y] {
            let (py, px) = map.position(y, x as usize);
            if !(py >= 0.0 && px >= 0.0 && py < (h - 1) as f64 && px < (w - 1) as f64) {
                continue;
            }
            let (y0, x0) = (py as usize, px as usize);
            let (fy, fx) = ((py - y0 as f64) as f32, (px - x0 as f64) as f32);
            let weights = [
                (1.0 - fy) * (1.0 - fx),
                (1.0 - fy) * fx,
                fy * (1.0 - fx),
                fy * fx,
            ];
            let bit = site_bit(row, x as usize, map.packed);
            splat_at(exposure, sum, w, y0 * w + x0, weights, bit);
        }
    }
}

/// Adds the bilinear `weights` of one site at the pixels (i, i + 1, i + w, i + w + 1) of
/// `exposure`, and of `sum` if it detected a photon.
#[inline(always)]
fn splat_at(
    exposure: &mut [f32],
    sum: &mut [f32],
    w: usize,
    i: usize,
    weights: [f32; 4],
    detected: bool,
) {
    let at = [i, i + 1, i + w, i + w + 1];
    for (&j, &v) in at.iter().zip(&weights) {
        exposure[j] += v;
    }
    if detected {
        for (&j, &v) in at.iter().zip(&weights) {
            sum[j] += v;
        }
    }
}

/// [`Splats::add_row`] eight columns at a time (`masks`: the row's [`Sites::masks`]).
///
/// Under small rotation and zoom, eight neighbouring columns land in one pair of template rows
/// at eight consecutive columns. Their bilinear splats then cover nine consecutive pixels of
/// each row: pixel l takes the left weight of site l and the right weight of site l − 1, so
/// each row is one vector addition; the ninth pixel's weight is carried into the next group
/// when that starts there (as it does along a row), else added alone. Other groups are
/// splatted site by site.
///
/// # Safety
/// The CPU must support AVX2 and FMA, and `h · w` must fit an i32.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn splat_row_avx2(
    exposure: &mut [f32],
    sum: &mut [f32],
    (h, w): (usize, usize),
    row: &[u8],
    y: usize,
    masks: &[u8],
    map: &RowMap,
) {
    use std::arch::x86_64::*;
    assert!(exposure.len() >= h * w && sum.len() >= h * w);
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let one = _mm256_set1_ps(1.0);
    let (y_end, x_end) = (
        _mm256_set1_ps((h - 1) as f32),
        _mm256_set1_ps((w - 1) as f32),
    );
    let previous = _mm256_setr_epi32(7, 0, 1, 2, 3, 4, 5, 6);
    // Adds the nine-pixel splat (left weights `a`, right weights `b`) of one row at `i`, with
    // `carry` (the previous group's ninth pixel) added to the first; returns the ninth.
    let add_run = |image: &mut [f32], i: usize, a: __m256, b: __m256, carry: f32| {
        let rotated = _mm256_permutevar8x32_ps(b, previous);
        let shifted = _mm256_blend_ps::<1>(rotated, _mm256_set1_ps(carry));
        let at = image[i..i + 8].as_mut_ptr();
        _mm256_storeu_ps(
            at,
            _mm256_add_ps(_mm256_loadu_ps(at), _mm256_add_ps(a, shifted)),
        );
        _mm256_cvtss_f32(rotated)
    };
    // The pending ninth pixels: (index of the top one, exposure top/bottom, sum top/bottom).
    let mut carry: Option<(usize, [f32; 4])> = None;
    let flush = |carry: &mut Option<(usize, [f32; 4])>, exposure: &mut [f32], sum: &mut [f32]| {
        if let Some((i, [e_top, e_bottom, s_top, s_bottom])) = carry.take() {
            exposure[i] += e_top;
            exposure[i + w] += e_bottom;
            sum[i] += s_top;
            sum[i + w] += s_bottom;
        }
    };
    for (k, &mask) in masks.iter().enumerate() {
        if mask == 0 {
            continue;
        }
        let detected = u32::from(mask) & chunk_bits(row, k, map.packed);
        let x = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(8 * k as i32), lane));
        let (_, py, px) = positions_avx2(y, x, map);
        let inside = inside_avx2::<_CMP_LT_OQ>(py, px, y_end, x_end);
        let inside_bits = _mm256_movemask_ps(inside) as u32;
        // Lanes outside take position 0 (in bounds); their weights are not used.
        let (py, px) = (_mm256_and_ps(py, inside), _mm256_and_ps(px, inside));
        let (y0, x0) = (_mm256_cvttps_epi32(py), _mm256_cvttps_epi32(px));
        let fy = _mm256_sub_ps(py, _mm256_cvtepi32_ps(y0));
        let fx = _mm256_sub_ps(px, _mm256_cvtepi32_ps(x0));
        let (gy, gx) = (_mm256_sub_ps(one, fy), _mm256_sub_ps(one, fx));
        let weights = [
            _mm256_mul_ps(gy, gx),
            _mm256_mul_ps(gy, fx),
            _mm256_mul_ps(fy, gx),
            _mm256_mul_ps(fy, fx),
        ];
        let first_y = _mm256_permutevar8x32_epi32(y0, _mm256_setzero_si256());
        let first_x = _mm256_permutevar8x32_epi32(x0, _mm256_setzero_si256());
        let consecutive = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_and_si256(
            _mm256_cmpeq_epi32(y0, first_y),
            _mm256_cmpeq_epi32(x0, _mm256_add_epi32(first_x, lane)),
        ))) == 0xFF;
        if inside_bits == 0xFF && consecutive {
            // All eight lanes inside: the last one's top-left pixel is at most (h − 2, w − 2),
            // so both nine-pixel runs lie inside the images.
            let i = (_mm256_cvtsi256_si32(first_y) as usize) * w
                + _mm256_cvtsi256_si32(first_x) as usize;
            let mut pending = [0.0f32; 4];
            match carry {
                // Taken up here; `carry` is replaced below.
                Some((at, values)) if at == i => pending = values,
                _ => flush(&mut carry, exposure, sum),
            }
            let sites = lane_mask_avx2(u32::from(mask));
            let [a, b, c, d] = weights.map(|v| _mm256_and_ps(v, sites));
            let mut next = [
                add_run(exposure, i, a, b, pending[0]),
                add_run(exposure, i + w, c, d, pending[1]),
                0.0,
                0.0,
            ];
            if detected != 0 {
                let photons = lane_mask_avx2(detected);
                let [a, b, c, d] = weights.map(|v| _mm256_and_ps(v, photons));
                next[2] = add_run(sum, i, a, b, pending[2]);
                next[3] = add_run(sum, i + w, c, d, pending[3]);
            } else {
                sum[i] += pending[2];
                sum[i + w] += pending[3];
            }
            carry = Some((i + 8, next));
            continue;
        }
        let mut index = [0i32; 8];
        _mm256_storeu_si256(
            index.as_mut_ptr().cast(),
            _mm256_add_epi32(_mm256_mullo_epi32(y0, _mm256_set1_epi32(w as i32)), x0),
        );
        let mut lanes = [[0.0f32; 8]; 4];
        for (out, v) in lanes.iter_mut().zip(weights) {
            _mm256_storeu_ps(out.as_mut_ptr(), v);
        }
        let mut todo = inside_bits & u32::from(mask);
        while todo != 0 {
            let l = todo.trailing_zeros() as usize;
            todo &= todo - 1;
            let site_weights = lanes.map(|v| v[l]);
            let photon = detected >> l & 1 == 1;
            splat_at(exposure, sum, w, index[l] as usize, site_weights, photon);
        }
    }
    flush(&mut carry, exposure, sum);
}

/// All ones in lane l where bit l of `bits` is set, zeros elsewhere.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn lane_mask_avx2(bits: u32) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
    _mm256_castsi256_ps(_mm256_cmpeq_epi32(
        _mm256_and_si256(_mm256_set1_epi32(bits as i32), lane_bits),
        lane_bits,
    ))
}

/// The detections of columns 8k..8k + 8 of a frame's raw row: bit l for column 8k + l.
#[inline(always)]
fn chunk_bits(row: &[u8], k: usize, packed: bool) -> u32 {
    if packed {
        // Packed rows hold column 8k + l in bit 7 − l of byte k.
        u32::from(row[k].reverse_bits())
    } else {
        row[8 * k..(8 * k + 8).min(row.len())]
            .iter()
            .enumerate()
            .fold(0, |bits, (l, &v)| bits | (u32::from(v != 0) << l))
    }
}

/// For eight sites in columns `x` of row `y` under `map`: r_x (the column about the centre)
/// and the template positions y and x.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn positions_avx2(
    y: usize,
    x: std::arch::x86_64::__m256,
    map: &RowMap,
) -> (
    std::arch::x86_64::__m256,
    std::arch::x86_64::__m256,
    std::arch::x86_64::__m256,
) {
    use std::arch::x86_64::*;
    let splat = |v: f64| _mm256_set1_ps(v as f32);
    let rx = _mm256_sub_ps(x, splat(map.centre_x));
    let py = _mm256_fmadd_ps(
        splat(map.m_yx),
        rx,
        splat(y as f64 + map.base[0] + map.margin),
    );
    let px = _mm256_add_ps(
        _mm256_fmadd_ps(splat(map.m_xx), rx, splat(map.base[1] + map.margin)),
        x,
    );
    (rx, py, px)
}

/// Score (gradient of the log-likelihood) and Fisher information of one frame's inverse camera
/// parameters at `camera`, against the template `level`.
///
/// A site's Jacobian ∂p/∂θ for θ = (b_y, b_x, m_yy, m_yx, m_xy, m_xx) is the template gradient
/// (g_y, g_x) times (1, r_y, r_x), its position about the centre: each entry is g_a·r_y^i·r_x^j.
/// Along a row r_y is fixed, so the row sums Σ s·g_a·r_x^j (score, j ≤ 1) and Σ w·g_a·g_b·r_x^j
/// (information, j ≤ 2) give every entry once multiplied by the row's power of r_y: 13 sums per
/// site instead of the 27 of the 6 + 21 entries (the same terms, grouped by row).
///
/// With AVX2 and FMA the row sums are made eight sites at a time in f32 ([`row_sums_avx2`]);
/// otherwise site by site in f64 ([`row_sums_scalar`]). The two agree to f32 rounding.
fn frame_score(
    frames: &BinaryFrames,
    sites: &Sites,
    t: usize,
    camera: &AffineMotion,
    template: &ScoreTemplate<'_>,
    margin: f64,
) -> ([f64; 6], [[f64; 6]; 6]) {
    let level = template.level;
    #[cfg(target_arch = "x86_64")]
    if row_sums_avx2_fits(level) {
        return frame_score_by_rows(frames, sites, t, camera, margin, |row, y, _, d| {
            // SAFETY: `row_sums_avx2_fits` checked the CPU's features and the template's size;
            // the planes are the level's.
            unsafe { row_sums_avx2(level, Some(&template.planes), row, y, &sites.masks[y], d) }
        });
    }
    frame_score_by_rows(frames, sites, t, camera, margin, |row, y, columns, d| {
        row_sums_scalar(level, row, y, columns, d)
    })
}

/// The template that [`frame_score`] samples: its level, and the level's value and gradients
/// as three planes of their own ([`TemplatePlanes`]) for [`row_sums_avx2`]'s row runs.
struct ScoreTemplate<'a> {
    level: &'a TemplateLevel,
    planes: TemplatePlanes,
}

impl<'a> ScoreTemplate<'a> {
    fn new(level: &'a TemplateLevel) -> ScoreTemplate<'a> {
        ScoreTemplate {
            level,
            planes: TemplatePlanes::new(level),
        }
    }
}

/// A [`TemplateLevel`]'s value, ∂/∂y and ∂/∂x, each as a row-major plane of its own: eight
/// consecutive pixels of one are one load.
struct TemplatePlanes {
    width: usize,
    /// Value, ∂/∂y, ∂/∂x.
    planes: [Vec<f32>; 3],
}

impl TemplatePlanes {
    fn new(level: &TemplateLevel) -> TemplatePlanes {
        let floats = level.floats();
        TemplatePlanes {
            width: level.dims().1,
            planes: std::array::from_fn(|k| floats.iter().skip(k).step_by(4).copied().collect()),
        }
    }
}

/// How one row's sites map into the template: a site in column x (r_x = x − centre) sits at
/// (y + base_y + m_yx·r_x + margin, x + base_x + m_xx·r_x + margin).
#[derive(Clone, Copy)]
struct RowMap {
    packed: bool,
    centre_x: f64,
    base: [f64; 2],
    m_yx: f64,
    m_xx: f64,
    margin: f64,
}

impl RowMap {
    fn new(sites: &Sites, camera: &AffineMotion, y: usize, packed: bool, margin: f64) -> RowMap {
        let ry = y as f64 - sites.centre[0];
        RowMap {
            packed,
            centre_x: sites.centre[1],
            // The displacement at r_x = 0 of this row; d = base + m[.][1]·r_x.
            base: camera.at([ry, 0.0]),
            m_yx: camera.m[0][1],
            m_xx: camera.m[1][1],
            margin,
        }
    }

    /// The template position (y, x) of the site in column `x` of row `y`, in f64.
    #[inline(always)]
    fn position(&self, y: usize, x: usize) -> (f64, f64) {
        let rx = x as f64 - self.centre_x;
        (
            y as f64 + self.base[0] + self.m_yx * rx + self.margin,
            x as f64 + self.base[1] + self.m_xx * rx + self.margin,
        )
    }
}

/// The 13 row sums of [`frame_score`]: `score[a][j]` = Σ s·g_a·r_x^j; `weight[k][j]` =
/// Σ w·g_a·g_b·r_x^j for (a, b) = (y, y), (y, x), (x, x).
#[derive(Default)]
struct RowSums {
    score: [[f64; 2]; 2],
    weight: [[f64; 3]; 3],
}

/// [`frame_score`] from the row sums that `row_sums(raw row, y, columns, map)` makes.
fn frame_score_by_rows(
    frames: &BinaryFrames,
    sites: &Sites,
    t: usize,
    camera: &AffineMotion,
    margin: f64,
    mut row_sums: impl FnMut(&[u8], usize, &[u16], &RowMap) -> RowSums,
) -> ([f64; 6], [[f64; 6]; 6]) {
    let packed = matches!(frames.layout(), FrameLayout::Packed);
    let mut g = [0.0f64; 6];
    let mut info = [[0.0f64; 6]; 6];
    for (y, columns) in sites.columns.iter().enumerate() {
        if columns.is_empty() {
            continue;
        }
        let ry = y as f64 - sites.centre[0];
        let map = RowMap::new(sites, camera, y, packed, margin);
        let RowSums { score, weight } = row_sums(frames.raw_row(t, y), y, columns, &map);
        // Parameter p is g_{GRADIENT[p]}·r_y^{POWER_Y[p]}·r_x^{POWER_X[p]}.
        const GRADIENT: [usize; 6] = [0, 1, 0, 0, 1, 1];
        const POWER_Y: [usize; 6] = [0, 0, 1, 0, 1, 0];
        const POWER_X: [usize; 6] = [0, 0, 0, 1, 0, 1];
        let ry_power = [1.0, ry, ry * ry];
        for a in 0..6 {
            g[a] += ry_power[POWER_Y[a]] * score[GRADIENT[a]][POWER_X[a]];
            for b in a..6 {
                let pair = GRADIENT[a] + GRADIENT[b];
                info[a][b] +=
                    ry_power[POWER_Y[a] + POWER_Y[b]] * weight[pair][POWER_X[a] + POWER_X[b]];
            }
        }
    }
    for a in 0..6 {
        for b in 0..a {
            info[a][b] = info[b][a];
        }
    }
    (g, info)
}

/// One row's [`RowSums`], site by site in f64.
fn row_sums_scalar(
    level: &TemplateLevel,
    row: &[u8],
    y: usize,
    columns: &[u16],
    map: &RowMap,
) -> RowSums {
    let mut sums = RowSums::default();
    let (score, weight) = (&mut sums.score, &mut sums.weight);
    for &x in columns {
        let x = x as usize;
        let bit = site_bit(row, x, map.packed);
        let rx = x as f64 - map.centre_x;
        let (py, px) = map.position(y, x);
        let Some([v, gy, gx]) = sample_template(level, py, px) else {
            continue;
        };
        let p = v.clamp(P_MIN, 1.0 - P_MIN);
        let w = 1.0 / (p * (1.0 - p));
        let s = if bit { 1.0 / p } else { -1.0 / (1.0 - p) };
        let (sy, sx) = (s * gy, s * gx);
        score[0][0] += sy;
        score[0][1] += sy * rx;
        score[1][0] += sx;
        score[1][1] += sx * rx;
        let rx2 = rx * rx;
        for (k, wk) in [w * gy * gy, w * gy * gx, w * gx * gx]
            .into_iter()
            .enumerate()
        {
            weight[k][0] += wk;
            weight[k][1] += wk * rx;
            weight[k][2] += wk * rx2;
        }
    }
    sums
}

/// Whether [`row_sums_avx2`] can run: the CPU has AVX2 and FMA, and every float index of the
/// template fits an i32.
#[cfg(target_arch = "x86_64")]
fn row_sums_avx2_fits(level: &TemplateLevel) -> bool {
    has_avx2_and_fma() && level.float_len() < i32::MAX as usize
}

/// Whether the CPU has AVX2 and FMA (the trajectory's vector kernels).
#[cfg(target_arch = "x86_64")]
fn has_avx2_and_fma() -> bool {
    std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
}

/// One row's [`RowSums`], eight columns at a time (`masks`: the row's [`Sites::masks`]) in f32
/// (the template is f32 already; positions in f32 are within 4e-5 px below 1000 px), summed
/// per row in f64.
///
/// `planes`, when given, must be `level`'s ([`TemplatePlanes::new`]): groups of sites that
/// form a row run then sample them instead of `level` (the same floats, so the same sums).
///
/// # Safety
/// The CPU must support AVX2 and FMA, and the template's float indices must fit an i32
/// ([`row_sums_avx2_fits`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn row_sums_avx2(
    level: &TemplateLevel,
    planes: Option<&TemplatePlanes>,
    row: &[u8],
    y: usize,
    masks: &[u8],
    map: &RowMap,
) -> RowSums {
    use std::arch::x86_64::*;
    let (h, w) = level.dims();
    let samples = level.floats().as_ptr();
    let splat = |v: f64| _mm256_set1_ps(v as f32);
    let (zero, one) = (_mm256_setzero_ps(), _mm256_set1_ps(1.0));
    let (y_last, x_last) = (splat((h - 1) as f64), splat((w - 1) as f64));
    let (y0_last, x0_last) = (
        _mm256_set1_epi32(h as i32 - 2),
        _mm256_set1_epi32(w as i32 - 2),
    );
    let (p_min, p_max) = (splat(P_MIN), splat(1.0 - P_MIN));
    let row_floats = _mm256_set1_epi32(4 * w as i32);
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    // Accumulators: score (y, 1), (y, r_x), (x, 1), (x, r_x); weight (yy, yx, xx) × (1, r_x, r_x²).
    let mut acc = [zero; 13];
    for (k, &mask) in masks.iter().enumerate() {
        if mask == 0 {
            continue;
        }
        let valid = lane_mask_avx2(u32::from(mask));
        let bit = _mm256_and_ps(lane_mask_avx2(chunk_bits(row, k, map.packed)), one);
        let x = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(8 * k as i32), lane));
        let (rx, py, px) = positions_avx2(y, x, map);
        // Lanes inside the template (and holding a site), as in `sample_template`.
        let in_template = inside_avx2::<_CMP_LE_OQ>(py, px, y_last, x_last);
        let inside = _mm256_and_ps(in_template, valid);
        // Positions of lanes outside are replaced by 0 so that their loads stay in bounds.
        // When every lane is inside, a lane without a site keeps its position (in bounds too):
        // its weight is zero all the same, and a zero weight times a finite sample adds ±0,
        // which leaves every sum as it is.
        let all_in_template = _mm256_movemask_ps(in_template) == 0xFF;
        let (py, px) = if all_in_template {
            (py, px)
        } else {
            (_mm256_and_ps(py, inside), _mm256_and_ps(px, inside))
        };
        let y0 = _mm256_min_epi32(_mm256_cvttps_epi32(py), y0_last);
        let x0 = _mm256_min_epi32(_mm256_cvttps_epi32(px), x0_last);
        let fy = _mm256_sub_ps(py, _mm256_cvtepi32_ps(y0));
        let fx = _mm256_sub_ps(px, _mm256_cvtepi32_ps(x0));
        let (gx, gy) = (_mm256_sub_ps(one, fx), _mm256_sub_ps(one, fy));
        // Float k (value, ∂/∂y, ∂/∂x) of the bilinear interpolation, as `bilinear4`, from each
        // lane's top-left, top-right, bottom-left and bottom-right pixels' float k.
        let bilinear = |tl: __m256, tr: __m256, bl: __m256, br: __m256| {
            let t = _mm256_fmadd_ps(tl, gx, _mm256_mul_ps(tr, fx));
            let b = _mm256_fmadd_ps(bl, gx, _mm256_mul_ps(br, fx));
            _mm256_fmadd_ps(t, gy, _mm256_mul_ps(b, fy))
        };
        let run_start = if all_in_template && planes.is_some() {
            row_run_start(y0, x0, w)
        } else {
            None
        };
        let (v, grad_y, grad_x) = if let (Some(planes), Some(start)) = (planes, run_start) {
            // A row run (the lanes' top-left pixels are eight consecutive pixels of one row,
            // as under small rotation and zoom): each corner of every lane is one load from
            // each plane, the same floats as the transposed loads below. Lane 7's top-left
            // pixel is at most (h − 2, w − 2), so the nine pixels of both rows lie inside.
            let sample = |k: usize| {
                let p = planes.planes[k].as_ptr().add(start);
                let below = p.add(planes.width);
                bilinear(
                    _mm256_loadu_ps(p),
                    _mm256_loadu_ps(p.add(1)),
                    _mm256_loadu_ps(below),
                    _mm256_loadu_ps(below.add(1)),
                )
            };
            (sample(0), sample(1), sample(2))
        } else {
            // Each lane's two top pixels (8 floats) and two bottom pixels, transposed so that
            // vector k holds float k of every lane: (value, ∂/∂y, ∂/∂x, 0) left, then right
            // (eight loads and a transpose were faster than twelve gathers). A lane's top-left
            // pixel is at most (h − 2, w − 2), so both pairs lie inside the template.
            let mut top_left = [0i32; 8];
            _mm256_storeu_si256(
                top_left.as_mut_ptr().cast(),
                _mm256_add_epi32(
                    _mm256_mullo_epi32(y0, row_floats),
                    _mm256_slli_epi32::<2>(x0),
                ),
            );
            let pairs = |offset: usize| {
                let rows: [__m256i; 8] = std::array::from_fn(|l| {
                    _mm256_castps_si256(_mm256_loadu_ps(samples.add(top_left[l] as usize + offset)))
                });
                crate::cpu::transpose8x8(&rows).map(|r| _mm256_castsi256_ps(r))
            };
            let (top, bottom) = (pairs(0), pairs(4 * w));
            let sample = |k: usize| bilinear(top[k], top[4 + k], bottom[k], bottom[4 + k]);
            (sample(0), sample(1), sample(2))
        };
        let p = _mm256_min_ps(_mm256_max_ps(v, p_min), p_max);
        let q = _mm256_sub_ps(one, p);
        // w = 1 / (p (1 − p)); s = 1/p = q·w for a detection, −1/(1 − p) = −p·w otherwise.
        let weight = _mm256_and_ps(_mm256_div_ps(one, _mm256_mul_ps(p, q)), inside);
        let s = _mm256_mul_ps(
            weight,
            _mm256_sub_ps(
                _mm256_mul_ps(bit, q),
                _mm256_mul_ps(_mm256_sub_ps(one, bit), p),
            ),
        );
        let (sy, sx) = (_mm256_mul_ps(s, grad_y), _mm256_mul_ps(s, grad_x));
        acc[0] = _mm256_add_ps(acc[0], sy);
        acc[1] = _mm256_fmadd_ps(sy, rx, acc[1]);
        acc[2] = _mm256_add_ps(acc[2], sx);
        acc[3] = _mm256_fmadd_ps(sx, rx, acc[3]);
        let rx2 = _mm256_mul_ps(rx, rx);
        let wy = _mm256_mul_ps(weight, grad_y);
        for (k, wk) in [
            _mm256_mul_ps(wy, grad_y),
            _mm256_mul_ps(wy, grad_x),
            _mm256_mul_ps(_mm256_mul_ps(weight, grad_x), grad_x),
        ]
        .into_iter()
        .enumerate()
        {
            acc[4 + 3 * k] = _mm256_add_ps(acc[4 + 3 * k], wk);
            acc[5 + 3 * k] = _mm256_fmadd_ps(wk, rx, acc[5 + 3 * k]);
            acc[6 + 3 * k] = _mm256_fmadd_ps(wk, rx2, acc[6 + 3 * k]);
        }
    }
    let total = acc.map(|a| {
        let mut lanes = [0.0f32; 8];
        _mm256_storeu_ps(lanes.as_mut_ptr(), a);
        lanes.iter().map(|&l| l as f64).sum::<f64>()
    });
    RowSums {
        score: [[total[0], total[1]], [total[2], total[3]]],
        weight: std::array::from_fn(|k| std::array::from_fn(|j| total[4 + 3 * k + j])),
    }
}

/// The flat index `y0 · width + x0` of lane 0's pixel when the eight lanes' pixels `(y0, x0)`
/// are consecutive pixels of one row (lane l at `(y0[0], x0[0] + l)`), else `None`.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn row_run_start(
    y0: std::arch::x86_64::__m256i,
    x0: std::arch::x86_64::__m256i,
    width: usize,
) -> Option<usize> {
    use std::arch::x86_64::*;
    let first_y = _mm256_broadcastd_epi32(_mm256_castsi256_si128(y0));
    let first_x = _mm256_broadcastd_epi32(_mm256_castsi256_si128(x0));
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let same = _mm256_and_si256(
        _mm256_cmpeq_epi32(y0, first_y),
        _mm256_cmpeq_epi32(x0, _mm256_add_epi32(first_x, lane)),
    );
    if _mm256_movemask_epi8(same) != -1 {
        return None;
    }
    let (y, x) = (_mm256_cvtsi256_si32(first_y), _mm256_cvtsi256_si32(first_x));
    (y >= 0 && x >= 0).then(|| y as usize * width + x as usize)
}

/// A symmetric positive-definite banded matrix, upper band stored row by row:
/// `band[i * (bw + 1) + d] = A[i][i + d]`.
struct BandedSpd {
    n: usize,
    bw: usize,
    band: Vec<f64>,
}

impl BandedSpd {
    fn zeros(n: usize, bw: usize) -> BandedSpd {
        BandedSpd {
            n,
            bw,
            band: vec![0.0; n * (bw + 1)],
        }
    }

    /// Adds `v` to A[i][j] (and A[j][i]); |i − j| must be within the band.
    fn add(&mut self, i: usize, j: usize, v: f64) {
        let (i, j) = if i <= j { (i, j) } else { (j, i) };
        debug_assert!(j - i <= self.bw);
        self.band[i * (self.bw + 1) + (j - i)] += v;
    }

    fn get(&self, i: usize, j: usize) -> f64 {
        self.band[i * (self.bw + 1) + (j - i)]
    }

    /// Solves A x = rhs by banded Cholesky (A = Uᵀ U); `None` if A is not positive definite.
    fn solve(mut self, rhs: &[f64]) -> Option<Vec<f64>> {
        let (n, bw) = (self.n, self.bw);
        let stride = bw + 1;
        for i in 0..n {
            for d in 0..=bw.min(n - 1 - i) {
                let j = i + d;
                let mut s = self.get(i, j);
                for k in i.saturating_sub(bw)..i {
                    if j - k <= bw {
                        s -= self.band[k * stride + (i - k)] * self.band[k * stride + (j - k)];
                    }
                }
                if d == 0 {
                    if s <= 0.0 || !s.is_finite() {
                        return None;
                    }
                    self.band[i * stride] = s.sqrt();
                } else {
                    self.band[i * stride + d] = s / self.band[i * stride];
                }
            }
        }
        // Uᵀ y = rhs, then U x = y.
        let mut y = rhs.to_vec();
        for i in 0..n {
            let mut s = y[i];
            for k in i.saturating_sub(bw)..i {
                s -= self.band[k * stride + (i - k)] * y[k];
            }
            y[i] = s / self.band[i * stride];
        }
        for i in (0..n).rev() {
            let mut s = y[i];
            for j in i + 1..(i + bw + 1).min(n) {
                s -= self.band[i * stride + (j - i)] * y[j];
            }
            y[i] = s / self.band[i * stride];
        }
        Some(y)
    }
}

/// One Fisher-scoring step of every knot against `level`; returns the largest knot update (px
/// at the image corners).
fn scoring_step(
    frames: &BinaryFrames,
    sites: &Sites,
    trajectory: &mut Trajectory,
    level: &TemplateLevel,
    config: &TrajectoryConfig,
    half: [f64; 2],
    margin: f64,
) -> f64 {
    let n_frames = frames.frame_count();
    let template = ScoreTemplate::new(level);
    let scores: Vec<([f64; 6], [[f64; 6]; 6])> = (0..n_frames)
        .into_par_iter()
        .map(|t| {
            let camera = trajectory.inverse_camera_at(t as f64);
            frame_score(frames, sites, t, &camera, &template, margin)
        })
        .collect();
    let n_knots = trajectory.knots.len();
    let dim = 6 * n_knots;
    let mut system = BandedSpd::zeros(dim, 6 * 2 + 5);
    let mut rhs = vec![0.0f64; dim];
    for (t, (g, info)) in scores.iter().enumerate() {
        let (k, a) = trajectory.locate(t as f64);
        let weights: [(usize, f64); 2] = [(k, 1.0 - a), (k + 1, a)];
        for &(ki, wi) in &weights {
            if wi == 0.0 || ki >= n_knots {
                continue;
            }
            for p in 0..6 {
                rhs[6 * ki + p] += wi * g[p];
                for &(kj, wj) in &weights {
                    if wj == 0.0 || kj >= n_knots || kj < ki {
                        continue;
                    }
                    for q in 0..6 {
                        let (i, j) = (6 * ki + p, 6 * kj + q);
                        if kj > ki || q >= p {
                            system.add(i, j, wi * wj * info[p][q]);
                        }
                    }
                }
            }
        }
    }
    // Acceleration prior: second differences of the knots, in px at the image corners.
    let scale = [1.0, 1.0, half[0], half[1], half[0], half[1]];
    let spacing = config.knot_frames.max(1) as f64;
    let prior_weight = 1.0 / (config.acceleration_px * spacing * spacing).powi(2);
    for k in 1..n_knots.saturating_sub(1) {
        let taps = [(k - 1, 1.0), (k, -2.0), (k + 1, 1.0)];
        for p in 0..6 {
            let w = prior_weight * scale[p] * scale[p];
            let r: f64 = taps.iter().map(|&(i, c)| c * trajectory.knots[i][p]).sum();
            for &(i, ci) in &taps {
                rhs[6 * i + p] -= w * ci * r;
                for &(j, cj) in &taps {
                    if j >= i {
                        system.add(6 * i + p, 6 * j + p, w * ci * cj);
                    }
                }
            }
        }
    }
    // Levenberg damping on the diagonal, plus a floor for knots no photon constrains.
    for i in 0..dim {
        let d = system.get(i, i);
        let floor = 1e-6 * scale[i % 6] * scale[i % 6];
        system.add(i, i, 1e-3 * d + floor);
    }
    let Some(step) = system.solve(&rhs) else {
        return 0.0;
    };
    let mut largest = 0.0f64;
    for (k, knot) in trajectory.knots.iter_mut().enumerate() {
        let delta = AffineMotion::from_params(std::array::from_fn(|p| step[6 * k + p]));
        largest = largest.max(delta.distance(&AffineMotion::default(), half));
        for p in 0..6 {
            knot[p] += step[6 * k + p];
        }
    }
    largest
}

/// Fits the camera trajectory of every frame to the photons (see the module documentation),
/// starting from `motion`'s camera, and replaces `motion`'s sub-blocks by runs of frames within
/// one block over which the fitted camera moves at most `max_sub_block_motion_px`. Runs only
/// on binary frames whose grey channel is W; returns whether it ran.
pub fn fit_photon_trajectory(
    capture: &Capture,
    grey_method: GreyMethod,
    motion: &mut FrameMotion,
    config: &TrajectoryConfig,
    max_sub_block_motion_px: f64,
    progress: &dyn Progress,
) -> Result<bool> {
    let frames = &capture.frames;
    if config.enabled {
        config.validate()?;
    }
    if !config.enabled
        || frames.is_multibit()
        || !matches!(grey_method, GreyMethod::InterpolateW)
        || frames.frame_count() < 2
    {
        return Ok(false);
    }
    let (h, w) = (motion.height, motion.width);
    let hot = capture.hot_pixels.as_ref();
    let sites = Sites::new(
        w,
        (0..h)
            .map(|y| {
                (0..w)
                    .filter(|&x| {
                        capture.cfa.channel(y, x) == Channel::W && !hot.is_some_and(|m| m[[y, x]])
                    })
                    .map(|x| x as u16)
                    .collect()
            })
            .collect(),
        motion.centre(),
    );
    if sites.count() == 0 {
        return Ok(false);
    }
    let half = motion.half_size();
    let margin = config.margin_px;
    let mut trajectory = Trajectory::new(frames.frame_count(), config.knot_frames);
    for (k, &t) in trajectory.times.clone().iter().enumerate() {
        if let Some(inverse) = motion.camera_at(t as f64).inverse() {
            trajectory.knots[k] = inverse.params();
        }
    }
    progress.start(
        "photon trajectory",
        (config.sigmas_px.len() * config.iterations) as u64,
    );
    let early_sites =
        (config.early_row_step > 1).then(|| sites.every_nth_row(config.early_row_step));
    let last_iteration = config.sigmas_px.len() * config.iterations;
    let iterations = config
        .sigmas_px
        .iter()
        .flat_map(|&sigma| std::iter::repeat_n(sigma, config.iterations))
        .enumerate();
    for (iteration, sigma) in iterations {
        let sites = match &early_sites {
            Some(early) if iteration + 1 < last_iteration => early,
            _ => &sites,
        };
        let template = build_template(frames, sites, &trajectory, h, margin);
        let level = template_level(&template, sigma);
        scoring_step(
            frames,
            sites,
            &mut trajectory,
            &level,
            config,
            half,
            margin as f64,
        );
        progress.advance(1);
    }
    progress.finish();
    set_frame_camera(motion, &trajectory, max_sub_block_motion_px);
    Ok(true)
}

/// Replaces the sub-blocks of `motion` by runs of consecutive frames inside one block over
/// which `trajectory`'s camera moves at most `max_motion_px` (px at the image corners), each at
/// the camera of its centre, with zero motion at the reference frame.
fn set_frame_camera(motion: &mut FrameMotion, trajectory: &Trajectory, max_motion_px: f64) {
    let half = motion.half_size();
    let forward = |t: f64| {
        trajectory
            .inverse_camera_at(t)
            .inverse()
            .unwrap_or_default()
    };
    let undo = forward(motion.plan.reference_frame as f64)
        .inverse()
        .unwrap_or_default();
    let camera_at = |t: f64| forward(t).after(&undo);
    let mut sub_blocks: Vec<Range<usize>> = Vec::new();
    let mut block_of = Vec::new();
    let mut camera = Vec::new();
    for (b, block) in motion.plan.blocks.iter().enumerate() {
        let mut start = block.start;
        while start < block.end {
            let first = camera_at(start as f64);
            let mut end = start + 1;
            while end < block.end && camera_at(end as f64).distance(&first, half) <= max_motion_px {
                end += 1;
            }
            camera.push(camera_at((start + end - 1) as f64 / 2.0));
            sub_blocks.push(start..end);
            block_of.push(b);
            start = end;
        }
    }
    motion.sub_blocks = sub_blocks;
    motion.block_of = block_of;
    motion.camera = camera;
}

#[cfg(test)]
mod tests {
    use super::*;

    /// [`frame_score`] site by site, each site's 6 + 21 products summed directly (the reference
    /// of the test).
    fn frame_score_reference(
        frames: &BinaryFrames,
        sites: &Sites,
        t: usize,
        camera: &AffineMotion,
        level: &TemplateLevel,
        margin: f64,
    ) -> ([f64; 6], [[f64; 6]; 6]) {
        let mut g = [0.0f64; 6];
        let mut info = [[0.0f64; 6]; 6];
        for_each_site(frames, sites, t, |y, x, bit| {
            let rel = [y as f64 - sites.centre[0], x as f64 - sites.centre[1]];
            let d = camera.at(rel);
            let Some([v, gy, gx]) =
                sample_template(level, y as f64 + d[0] + margin, x as f64 + d[1] + margin)
            else {
                return;
            };
            let p = v.clamp(P_MIN, 1.0 - P_MIN);
            // ∂p/∂θ for θ = (b_y, b_x, m_yy, m_yx, m_xy, m_xx).
            let j = [gy, gx, gy * rel[0], gy * rel[1], gx * rel[0], gx * rel[1]];
            let weight = 1.0 / (p * (1.0 - p));
            let score = if bit { 1.0 / p } else { -1.0 / (1.0 - p) };
            for a in 0..6 {
                g[a] += score * j[a];
                let wa = weight * j[a];
                for b in a..6 {
                    info[a][b] += wa * j[b];
                }
            }
        });
        for a in 0..6 {
            for b in 0..a {
                info[a][b] = info[b][a];
            }
        }
        (g, info)
    }

    /// Random packed binary frames of shape `[frames, h, w]` (each bit set with probability
    /// `p`, seeded), as bits and as frames, and the sites where `is_site(y, x)`.
    fn random_capture(
        [n, h, w]: [usize; 3],
        p: f64,
        seed: u64,
        is_site: impl Fn(usize, usize) -> bool,
    ) -> (ndarray::Array3<u8>, BinaryFrames, Sites) {
        use crate::capture::frames::pack_bits;
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let bits = ndarray::Array3::from_shape_fn((n, h, w), |_| rng.gen_bool(p) as u8);
        let frames = BinaryFrames::from_packed(pack_bits(&bits), w).unwrap();
        let columns = (0..h)
            .map(|y| {
                (0..w)
                    .filter(|&x| is_site(y, x))
                    .map(|x| x as u16)
                    .collect()
            })
            .collect();
        let sites = Sites::new(w, columns, [(h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0]);
        (bits, frames, sites)
    }

    #[test]
    fn banded_cholesky_solves_a_known_system() {
        // Pentadiagonal SPD matrix, checked against A x.
        let n = 12;
        let mut a = BandedSpd::zeros(n, 2);
        let mut dense = vec![vec![0.0f64; n]; n];
        for i in 0..n {
            for (d, v) in [(0usize, 6.0), (1, -1.5), (2, 0.5)] {
                if i + d < n {
                    a.add(i, i + d, v);
                    dense[i][i + d] += v;
                    if d > 0 {
                        dense[i + d][i] += v;
                    }
                }
            }
        }
        let x: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).sin()).collect();
        let rhs: Vec<f64> = (0..n)
            .map(|i| (0..n).map(|j| dense[i][j] * x[j]).sum())
            .collect();
        let solved = a.solve(&rhs).expect("positive definite");
        for (s, e) in solved.iter().zip(&x) {
            assert!((s - e).abs() < 1e-12, "{s} vs {e}");
        }
    }

    /// The row-factorised score and information equal the site-by-site sums (to rounding) on a
    /// random binary frame against a textured template, under an affine camera, with sites
    /// that fall outside the template skipped alike.
    #[test]
    fn frame_score_equals_the_site_by_site_sums() {
        let (h, w, margin) = (40, 56, 6usize);
        let (_, frames, sites) = random_capture([2, h, w], 0.3, 5, |y, x| (x + 2 * y) % 3 != 0);
        let template = Array2::from_shape_fn((h + 2 * margin, w + 2 * margin), |(y, x)| {
            0.3 + 0.2 * ((y as f32 / 3.0).sin() * (x as f32 / 4.0).cos())
        });
        let level = template_level(&template, 0.8);
        // The last camera moves part of the image beyond the template's margin.
        for camera in [
            AffineMotion::default(),
            AffineMotion {
                b: [1.3, -2.1],
                m: [[0.01, -0.02], [0.015, -0.005]],
            },
            AffineMotion {
                b: [9.0, 4.5],
                m: [[0.0, 0.03], [-0.03, 0.0]],
            },
        ] {
            // The f64 row sums agree to rounding; `frame_score` (f32 lanes where the CPU has
            // AVX2) to f32 rounding.
            for t in 0..2 {
                let (g_ref, info_ref) =
                    frame_score_reference(&frames, &sites, t, &camera, &level, margin as f64);
                let scale = info_ref
                    .iter()
                    .flatten()
                    .fold(0.0f64, |m, v| m.max(v.abs()));
                let g_scale = g_ref.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                let scalar = frame_score_by_rows(
                    &frames,
                    &sites,
                    t,
                    &camera,
                    margin as f64,
                    |row, y, columns, d| row_sums_scalar(&level, row, y, columns, d),
                );
                let template = ScoreTemplate::new(&level);
                let dispatched = frame_score(&frames, &sites, t, &camera, &template, margin as f64);
                for ((g, info), tolerance) in [(scalar, 1e-10), (dispatched, 1e-5)] {
                    for a in 0..6 {
                        assert!(
                            (g[a] - g_ref[a]).abs() <= tolerance * g_scale,
                            "{g:?} vs {g_ref:?}"
                        );
                        for b in 0..6 {
                            assert!(
                                (info[a][b] - info_ref[a][b]).abs() <= tolerance * scale,
                                "{a} {b}: {} vs {}",
                                info[a][b],
                                info_ref[a][b]
                            );
                        }
                    }
                }
            }
        }
    }

    /// The row runs' planar loads give the same bits as the transposed loads on every row,
    /// under a still camera (every group a row run), a small turn and zoom (most groups), and a
    /// camera that moves part of the image beyond the template (no run where a lane is outside).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn row_runs_sum_the_same_bits_as_the_transposed_loads() {
        if !has_avx2_and_fma() {
            return;
        }
        let (h, w, margin) = (40, 67, 6usize);
        let (_, frames, sites) = random_capture([1, h, w], 0.3, 11, |y, x| (x + 2 * y) % 3 != 0);
        let template = Array2::from_shape_fn((h + 2 * margin, w + 2 * margin), |(y, x)| {
            0.3 + 0.2 * ((y as f32 / 3.0).sin() * (x as f32 / 4.0).cos())
        });
        let level = template_level(&template, 0.8);
        let planes = TemplatePlanes::new(&level);
        let packed = matches!(frames.layout(), FrameLayout::Packed);
        for camera in [
            AffineMotion::default(),
            AffineMotion {
                b: [0.4, -0.7],
                m: [[0.004, -0.006], [0.006, 0.003]],
            },
            AffineMotion {
                b: [9.0, 4.5],
                m: [[0.0, 0.03], [-0.03, 0.0]],
            },
        ] {
            for y in 0..h {
                let map = RowMap::new(&sites, &camera, y, packed, margin as f64);
                let row = frames.raw_row(0, y);
                let masks = &sites.masks[y];
                // SAFETY: AVX2 and FMA checked above; a small template.
                let (runs, transposed) = unsafe {
                    (
                        row_sums_avx2(&level, Some(&planes), row, y, masks, &map),
                        row_sums_avx2(&level, None, row, y, masks, &map),
                    )
                };
                let bits = |r: &RowSums| {
                    let mut v: Vec<u64> = r.score.iter().flatten().map(|x| x.to_bits()).collect();
                    v.extend(r.weight.iter().flatten().map(|x| x.to_bits()));
                    v
                };
                assert_eq!(bits(&runs), bits(&transposed), "row {y} under {camera:?}");
            }
        }
    }

    /// A row run is eight lanes at consecutive pixels of one row; any other layout is not.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn row_runs_are_eight_consecutive_pixels_of_one_row() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        use std::arch::x86_64::*;
        let start = |y: [i32; 8], x: [i32; 8]| {
            // SAFETY: AVX2 checked above.
            unsafe {
                row_run_start(
                    _mm256_loadu_si256(y.as_ptr().cast()),
                    _mm256_loadu_si256(x.as_ptr().cast()),
                    100,
                )
            }
        };
        let run = [10, 11, 12, 13, 14, 15, 16, 17];
        assert_eq!(start([5; 8], run), Some(510));
        assert_eq!(start([5, 5, 5, 5, 5, 5, 5, 6], run), None);
        assert_eq!(start([5; 8], [10, 11, 12, 13, 15, 16, 17, 18]), None);
        assert_eq!(start([5; 8], [10; 8]), None);
    }

    #[test]
    fn splats_agree_between_the_vector_and_scalar_paths() {
        let (h, w, margin) = (30, 45, 4usize);
        let (bits, frames, sites) = random_capture([1, h, w], 0.4, 9, |y, x| (x + y) % 4 != 1);
        let (th, tw) = (h + 2 * margin, w + 2 * margin);
        // A turn and a shift that carry part of the image beyond the margin (most groups of
        // eight sites splatted one by one), and a small shift (most groups as runs, carried).
        for camera in [
            AffineMotion {
                b: [5.3, -3.7],
                m: [[0.02, 0.05], [-0.05, 0.01]],
            },
            AffineMotion {
                b: [0.3, 4.6],
                m: [[0.0, 0.001], [-0.001, 0.0]],
            },
        ] {
            let maps: Vec<RowMap> = (0..h)
                .map(|y| RowMap::new(&sites, &camera, y, true, margin as f64))
                .collect();
            let splat_all = |vector: bool| {
                let mut splats = Splats::zeros(th, tw);
                #[cfg(target_arch = "x86_64")]
                {
                    splats.avx2 &= vector;
                }
                #[cfg(not(target_arch = "x86_64"))]
                let _ = vector;
                for (y, map) in maps.iter().enumerate() {
                    splats.add_row(frames.raw_row(0, y), y, &sites, map);
                }
                splats
            };
            let (scalar, vector) = (splat_all(false), splat_all(true));
            // Every site inside adds weights summing to 1 (to the sum where it detected).
            let (mut inside, mut detected) = (0usize, 0usize);
            for (y, map) in maps.iter().enumerate() {
                for &x in &sites.columns[y] {
                    let (py, px) = map.position(y, x as usize);
                    if py >= 0.0 && px >= 0.0 && py < (th - 1) as f64 && px < (tw - 1) as f64 {
                        inside += 1;
                        detected += usize::from(bits[[0, y, x as usize]]);
                    }
                }
            }
            assert!(inside > 0 && inside < sites.count());
            for splats in [&scalar, &vector] {
                assert!((splats.exposure.sum() - inside as f32).abs() < 1e-2);
                assert!((splats.sum.sum() - detected as f32).abs() < 1e-2);
            }
            for (a, b) in [
                (&scalar.sum, &vector.sum),
                (&scalar.exposure, &vector.exposure),
            ] {
                let largest = a
                    .iter()
                    .zip(b)
                    .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
                assert!(largest < 1e-4, "largest difference {largest}");
            }
        }
    }

    #[test]
    fn validate_names_each_out_of_range_setting() {
        assert!(TrajectoryConfig::default().validate().is_ok());
        type Edit = fn(&mut TrajectoryConfig);
        let cases: [(&str, Edit); 7] = [
            ("knot_frames", |c| c.knot_frames = 0),
            ("iterations", |c| c.iterations = 0),
            ("early_row_step", |c| c.early_row_step = 0),
            ("sigmas_px", |c| c.sigmas_px.clear()),
            ("sigmas_px", |c| c.sigmas_px[1] = f32::NAN),
            ("acceleration_px", |c| c.acceleration_px = 0.0),
            ("acceleration_px", |c| c.acceleration_px = f64::INFINITY),
        ];
        for (key, edit) in cases {
            let mut config = TrajectoryConfig::default();
            edit(&mut config);
            let message = config.validate().expect_err(key).to_string();
            assert!(message.contains(key), "{key}: {message}");
        }
    }

    #[test]
    fn early_sites_keep_every_nth_row_and_empty_the_others() {
        let columns: Vec<Vec<u16>> = (0..7u16).map(|y| vec![y, y + 3, 20]).collect();
        let sites = Sites::new(24, columns.clone(), [3.0, 11.5]);
        let early = sites.every_nth_row(3);
        for (y, row) in early.columns.iter().enumerate() {
            let kept = if y % 3 == 0 {
                columns[y].clone()
            } else {
                vec![]
            };
            assert_eq!(row, &kept, "row {y}");
            let expected_masks = if y % 3 == 0 {
                &sites.masks[y]
            } else {
                &vec![0u8; 3]
            };
            assert_eq!(&early.masks[y], expected_masks, "row {y}");
        }
        assert_eq!(early.count(), 9);
        assert_eq!(early.centre, sites.centre);
        assert_eq!(sites.every_nth_row(1).columns, columns);
    }

    #[test]
    fn chunk_bits_read_packed_and_unpacked_rows_alike() {
        use crate::capture::frames::pack_bits;
        let row: Vec<u8> = (0..21u32).map(|x| u8::from(x % 3 == 0 || x == 7)).collect();
        let packed = pack_bits(&ndarray::Array3::from_shape_vec((1, 1, 21), row.clone()).unwrap());
        let packed = packed.as_slice().unwrap();
        for k in 0..3 {
            let expected = (0..8)
                .filter(|l| row.get(8 * k + l) == Some(&1))
                .fold(0u32, |bits, l| bits | 1 << l);
            assert_eq!(chunk_bits(packed, k, true), expected);
            assert_eq!(chunk_bits(&row, k, false), expected);
        }
    }

    #[test]
    fn banded_cholesky_rejects_an_indefinite_matrix() {
        let mut a = BandedSpd::zeros(3, 1);
        a.add(0, 0, 1.0);
        a.add(0, 1, 2.0);
        a.add(1, 1, 1.0);
        a.add(2, 2, 1.0);
        assert!(a.solve(&[1.0, 1.0, 1.0]).is_none());
    }

    #[test]
    fn knots_interpolate_linearly_and_end_at_the_last_frame() {
        let mut tr = Trajectory::new(10, 4);
        assert_eq!(tr.times, vec![0, 4, 8, 9]);
        for (k, &t) in tr.times.clone().iter().enumerate() {
            tr.knots[k][0] = 2.0 * t as f64;
        }
        for t in 0..10 {
            assert!((tr.params_at(t as f64)[0] - 2.0 * t as f64).abs() < 1e-12);
        }
        assert!((tr.params_at(5.5)[0] - 11.0).abs() < 1e-12);
    }
}
