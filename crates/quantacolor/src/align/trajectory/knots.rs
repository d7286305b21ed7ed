//! The model being fitted: the inverse camera map of every frame as a piecewise-linear
//! function of time through knots every few frames (this project's own parametrisation).

#![forbid(unsafe_code)]

use crate::align::refine::AffineMotion;

/// A piecewise-linear inverse camera trajectory (frame → reference displacement about the image
/// centre) through knots at `times`.
#[derive(Debug, Clone)]
pub(super) struct Trajectory {
    /// The frames of the knots: every `knot_frames`-th, and the last.
    pub(super) times: Vec<usize>,
    /// The inverse camera parameters at each knot ([`AffineMotion::params`]).
    pub(super) knots: Vec<[f64; 6]>,
}

impl Trajectory {
    /// Knots every `knot_frames` frames from frame 0, and one at the last frame, all at zero.
    #[cfg(test)]
    pub(super) fn new(frames: usize, knot_frames: usize) -> Trajectory {
        Trajectory::over(0..frames, knot_frames)
    }

    /// Knots every `knot_frames` frames of `frames` from its first, and one at its last, all at
    /// zero.
    pub(super) fn over(frames: std::ops::Range<usize>, knot_frames: usize) -> Trajectory {
        let last = frames.end.saturating_sub(1).max(frames.start);
        let step = knot_frames.max(1);
        let mut times: Vec<usize> = (frames.start..=last).step_by(step).collect();
        if *times.last().expect("at least one knot") != last {
            times.push(last);
        }
        let knots = vec![[0.0; 6]; times.len()];
        Trajectory { times, knots }
    }

    /// The knot interval holding frame `t` and the weight of its right knot.
    pub(super) fn locate(&self, t: f64) -> (usize, f64) {
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

    /// The parameters at frame `t`, interpolated linearly between its knots.
    pub(super) fn params_at(&self, t: f64) -> [f64; 6] {
        let (k, a) = self.locate(t);
        if self.times.len() == 1 {
            return self.knots[0];
        }
        std::array::from_fn(|i| self.knots[k][i] * (1.0 - a) + self.knots[k + 1][i] * a)
    }

    /// The inverse camera map of frame `t`.
    pub(super) fn inverse_camera_at(&self, t: f64) -> AffineMotion {
        AffineMotion::from_params(self.params_at(t))
    }
}
