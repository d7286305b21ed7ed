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
        }
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
    centre: [f64; 2],
}

impl Sites {
    fn count(&self) -> usize {
        self.columns.iter().map(Vec::len).sum()
    }
}

/// Calls `visit(y, x, detected)` for every grey site of frame `t`.
#[inline]
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
    let (sum, exposure) = starts
        .par_iter()
        .map(|&start| {
            let mut sum = Array2::<f32>::zeros((th, tw));
            let mut exposure = Array2::<f32>::zeros((th, tw));
            for t in start..(start + chunk).min(n) {
                let e = trajectory.inverse_camera_at(t as f64);
                for_each_site(frames, sites, t, |y, x, bit| {
                    let rel = [y as f64 - sites.centre[0], x as f64 - sites.centre[1]];
                    let d = e.at(rel);
                    let py = y as f64 + d[0] + margin as f64;
                    let px = x as f64 + d[1] + margin as f64;
                    splat(&mut exposure, py, px, 1.0);
                    if bit {
                        splat(&mut sum, py, px, 1.0);
                    }
                });
            }
            (sum, exposure)
        })
        .reduce(
            || (Array2::zeros((th, tw)), Array2::zeros((th, tw))),
            |(a, b), (c, d)| (a + c, b + d),
        );
    let num = gaussian_blur(&sum, 0.7);
    let den = gaussian_blur(&exposure, 0.7);
    let mean = sum.sum() / exposure.sum().max(1.0);
    let floor = 1e-3 * den.iter().copied().fold(0.0f32, f32::max);
    ndarray::Zip::from(&num)
        .and(&den)
        .map_collect(|&n, &d| if d > floor { n / d } else { mean })
}

/// Adds `v` at (y, x) with bilinear weights; outside the image it is dropped.
#[inline]
fn splat(img: &mut Array2<f32>, y: f64, x: f64, v: f32) {
    let (h, w) = img.dim();
    if !(y >= 0.0 && x >= 0.0 && y < (h - 1) as f64 && x < (w - 1) as f64) {
        return;
    }
    let (y0, x0) = (y as usize, x as usize);
    let (fy, fx) = ((y - y0 as f64) as f32, (x - x0 as f64) as f32);
    img[[y0, x0]] += v * (1.0 - fy) * (1.0 - fx);
    img[[y0, x0 + 1]] += v * (1.0 - fy) * fx;
    img[[y0 + 1, x0]] += v * fy * (1.0 - fx);
    img[[y0 + 1, x0 + 1]] += v * fy * fx;
}

/// Score (gradient of the log-likelihood) and Fisher information of one frame's inverse camera
/// parameters at `camera`, against the template `level`.
///
/// A site's Jacobian ∂p/∂θ for θ = (b_y, b_x, m_yy, m_yx, m_xy, m_xx) is the template gradient
/// (g_y, g_x) times (1, r_y, r_x), its position about the centre: each entry is g_a·r_y^i·r_x^j.
/// Along a row r_y is fixed, so the row sums Σ s·g_a·r_x^j (score, j ≤ 1) and Σ w·g_a·g_b·r_x^j
/// (information, j ≤ 2) give every entry once multiplied by the row's power of r_y: 13 sums per
/// site instead of the 27 of the 6 + 21 entries (the same terms, grouped by row).
fn frame_score(
    frames: &BinaryFrames,
    sites: &Sites,
    t: usize,
    camera: &AffineMotion,
    level: &TemplateLevel,
    margin: f64,
) -> ([f64; 6], [[f64; 6]; 6]) {
    let packed = matches!(frames.layout(), FrameLayout::Packed);
    let mut g = [0.0f64; 6];
    let mut info = [[0.0f64; 6]; 6];
    for (y, columns) in sites.columns.iter().enumerate() {
        if columns.is_empty() {
            continue;
        }
        let row = frames.raw_row(t, y);
        let ry = y as f64 - sites.centre[0];
        // The displacement at r_x = 0 of this row; d = base + m[.][1]·r_x.
        let base = camera.at([ry, 0.0]);
        // score[a][j] = Σ s·g_a·r_x^j; weight[k][j] = Σ w·g_a·g_b·r_x^j for (a, b) = (y, y),
        // (y, x), (x, x).
        let mut score = [[0.0f64; 2]; 2];
        let mut weight = [[0.0f64; 3]; 3];
        for &x in columns {
            let x = x as usize;
            let bit = site_bit(row, x, packed);
            let rx = x as f64 - sites.centre[1];
            let d = [base[0] + camera.m[0][1] * rx, base[1] + camera.m[1][1] * rx];
            let Some([v, gy, gx]) =
                sample_template(level, y as f64 + d[0] + margin, x as f64 + d[1] + margin)
            else {
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
    let scores: Vec<([f64; 6], [[f64; 6]; 6])> = (0..n_frames)
        .into_par_iter()
        .map(|t| {
            let camera = trajectory.inverse_camera_at(t as f64);
            frame_score(frames, sites, t, &camera, level, margin)
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
    if config.enabled
        && (config.knot_frames == 0
            || config
                .sigmas_px
                .iter()
                .any(|&s| !(s > 0.0 && s.is_finite()))
            || !(config.acceleration_px > 0.0 && config.acceleration_px.is_finite()))
    {
        return Err(Error::invalid(
            "photon trajectory: knot_frames must be at least 1, and sigmas_px and \
             acceleration_px positive",
        ));
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
    let sites = Sites {
        width: w,
        columns: (0..h)
            .map(|y| {
                (0..w)
                    .filter(|&x| {
                        capture.cfa.channel(y, x) == Channel::W && !hot.is_some_and(|m| m[[y, x]])
                    })
                    .map(|x| x as u16)
                    .collect()
            })
            .collect(),
        centre: motion.centre(),
    };
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
    for &sigma in &config.sigmas_px {
        for _ in 0..config.iterations {
            let template = build_template(frames, &sites, &trajectory, h, margin);
            let level = template_level(&template, sigma);
            scoring_step(
                frames,
                &sites,
                &mut trajectory,
                &level,
                config,
                half,
                margin as f64,
            );
            progress.advance(1);
        }
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
        use crate::capture::frames::pack_bits;
        use rand::{Rng, SeedableRng};
        let (h, w, margin) = (40, 56, 6usize);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let bits = ndarray::Array3::from_shape_fn((2, h, w), |_| rng.gen_bool(0.3) as u8);
        let frames = BinaryFrames::from_packed(pack_bits(&bits), w).unwrap();
        let sites = Sites {
            width: w,
            columns: (0..h)
                .map(|y| {
                    (0..w)
                        .filter(|x| (x + 2 * y) % 3 != 0)
                        .map(|x| x as u16)
                        .collect()
                })
                .collect(),
            centre: [(h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0],
        };
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
            for t in 0..2 {
                let (g, info) = frame_score(&frames, &sites, t, &camera, &level, margin as f64);
                let (g_ref, info_ref) =
                    frame_score_reference(&frames, &sites, t, &camera, &level, margin as f64);
                let scale = info_ref
                    .iter()
                    .flatten()
                    .fold(0.0f64, |m, v| m.max(v.abs()));
                for a in 0..6 {
                    let g_scale = g_ref.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                    assert!(
                        (g[a] - g_ref[a]).abs() <= 1e-10 * g_scale,
                        "{g:?} vs {g_ref:?}"
                    );
                    for b in 0..6 {
                        assert!(
                            (info[a][b] - info_ref[a][b]).abs() <= 1e-10 * scale,
                            "{a} {b}: {} vs {}",
                            info[a][b],
                            info_ref[a][b]
                        );
                    }
                }
            }
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
