//! One Fisher-scoring step of every knot: the frames' scores and information spread onto
//! their two knots, the Gaussian acceleration prior (this project's smoothness prior) and
//! Levenberg damping added, the banded normal equations solved by Cholesky.

#![forbid(unsafe_code)]

use super::config::TrajectoryConfig;
use super::knots::Trajectory;
use super::likelihood::{frame_score, ScoreTemplate};
use super::sites::Sites;
use super::SpanFrames;
use crate::align::refine::AffineMotion;
use rayon::prelude::*;

/// A symmetric positive-definite banded matrix, upper band stored row by row:
/// `band[i * (bw + 1) + d] = A[i][i + d]`.
pub(super) struct BandedSpd {
    n: usize,
    bw: usize,
    band: Vec<f64>,
}

impl BandedSpd {
    /// The zero matrix of size `n` and half-bandwidth `bw`.
    pub(super) fn zeros(n: usize, bw: usize) -> BandedSpd {
        BandedSpd {
            n,
            bw,
            band: vec![0.0; n * (bw + 1)],
        }
    }

    /// Adds `v` to A[i][j] (and A[j][i]); |i − j| must be within the band.
    pub(super) fn add(&mut self, i: usize, j: usize, v: f64) {
        let (i, j) = if i <= j { (i, j) } else { (j, i) };
        debug_assert!(j - i <= self.bw);
        self.band[i * (self.bw + 1) + (j - i)] += v;
    }

    /// A[i][j] for i ≤ j within the band.
    fn get(&self, i: usize, j: usize) -> f64 {
        self.band[i * (self.bw + 1) + (j - i)]
    }

    /// Solves A x = rhs by banded Cholesky (A = Uᵀ U); `None` if A is not positive definite.
    pub(super) fn solve(mut self, rhs: &[f64]) -> Option<Vec<f64>> {
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

/// One Fisher-scoring step of every knot against `template`, from the frames of `frames`;
/// returns the largest knot update (px at the image corners).
pub(super) fn scoring_step(
    frames: &SpanFrames<'_>,
    sites: &Sites,
    trajectory: &mut Trajectory,
    template: &ScoreTemplate<'_>,
    config: &TrajectoryConfig,
    half: [f64; 2],
    margin: f64,
) -> f64 {
    let first = frames.span.start;
    let scores: Vec<([f64; 6], [[f64; 6]; 6])> = frames
        .span
        .clone()
        .into_par_iter()
        .map(|t| {
            let camera = trajectory.inverse_camera_at(t as f64);
            frame_score(frames.frames, sites, t, &camera, template, margin)
        })
        .collect();
    let n_knots = trajectory.knots.len();
    let dim = 6 * n_knots;
    let mut system = BandedSpd::zeros(dim, 6 * 2 + 5);
    let mut rhs = vec![0.0f64; dim];
    for (i, (g, info)) in scores.iter().enumerate() {
        let (k, a) = trajectory.locate((first + i) as f64);
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
