//! The affine camera map of one sub-block, d(x) = b + m·(x − c), and its algebra (inverse,
//! composition, distances, interpolation in time).
#![forbid(unsafe_code)]

/// Affine displacement field d(x) = b + m·(x − c) about the image centre c, in (y, x) order.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct AffineMotion {
    pub b: [f64; 2],
    pub m: [[f64; 2]; 2],
}

impl AffineMotion {
    /// d(x) for a position x given relative to the centre.
    #[inline]
    pub fn at(&self, rel: [f64; 2]) -> [f64; 2] {
        [
            self.b[0] + self.m[0][0] * rel[0] + self.m[0][1] * rel[1],
            self.b[1] + self.m[1][0] * rel[0] + self.m[1][1] * rel[1],
        ]
    }

    /// The displacement e of the inverse map: if x ↦ x + d(x), then y ↦ y + e(y) undoes it.
    pub fn inverse(&self) -> Option<AffineMotion> {
        let a = [
            [1.0 + self.m[0][0], self.m[0][1]],
            [self.m[1][0], 1.0 + self.m[1][1]],
        ];
        let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
        if det.abs() < 1e-9 {
            return None;
        }
        let inv = [
            [a[1][1] / det, -a[0][1] / det],
            [-a[1][0] / det, a[0][0] / det],
        ];
        Some(AffineMotion {
            b: [
                -(inv[0][0] * self.b[0] + inv[0][1] * self.b[1]),
                -(inv[1][0] * self.b[0] + inv[1][1] * self.b[1]),
            ],
            m: [[inv[0][0] - 1.0, inv[0][1]], [inv[1][0], inv[1][1] - 1.0]],
        })
    }

    pub(in crate::align) fn params(&self) -> [f64; 6] {
        [
            self.b[0],
            self.b[1],
            self.m[0][0],
            self.m[0][1],
            self.m[1][0],
            self.m[1][1],
        ]
    }

    pub(in crate::align) fn from_params(p: [f64; 6]) -> AffineMotion {
        AffineMotion {
            b: [p[0], p[1]],
            m: [[p[2], p[3]], [p[4], p[5]]],
        }
    }

    /// Largest displacement difference to `other` over the corners of a `half` = (H/2, W/2)
    /// image (px).
    pub(in crate::align) fn distance(&self, other: &AffineMotion, half: [f64; 2]) -> f64 {
        let mut worst = 0.0f64;
        for sy in [-1.0, 1.0] {
            for sx in [-1.0, 1.0] {
                let rel = [sy * half[0], sx * half[1]];
                let (a, b) = (self.at(rel), other.at(rel));
                worst = worst.max(((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt());
            }
        }
        worst
    }

    /// Root-mean-square displacement difference to `other` over a `half` = (H/2, W/2) image
    /// (px): the difference Δb + Δm·x averaged over the image rectangle, whose coordinates are
    /// uniform with variance h²/3 and uncorrelated, so |Δb|² + Σ Δm_rc²·half_c²/3.
    pub(in crate::align) fn rms_distance(&self, other: &AffineMotion, half: [f64; 2]) -> f64 {
        let mut mean_square = (0..2)
            .map(|r| (self.b[r] - other.b[r]).powi(2))
            .sum::<f64>();
        for (row, other_row) in self.m.iter().zip(&other.m) {
            for ((m, o), h) in row.iter().zip(other_row).zip(half) {
                mean_square += (m - o).powi(2) * h * h / 3.0;
            }
        }
        mean_square.sqrt()
    }

    /// The displacement of the map x ↦ self(other(x)) (both as maps x ↦ x + d(x)).
    pub fn after(&self, other: &AffineMotion) -> AffineMotion {
        let a = [
            [1.0 + self.m[0][0], self.m[0][1]],
            [self.m[1][0], 1.0 + self.m[1][1]],
        ];
        let o = [
            [1.0 + other.m[0][0], other.m[0][1]],
            [other.m[1][0], 1.0 + other.m[1][1]],
        ];
        let prod = |i: usize, j: usize| a[i][0] * o[0][j] + a[i][1] * o[1][j];
        AffineMotion {
            b: [
                a[0][0] * other.b[0] + a[0][1] * other.b[1] + self.b[0],
                a[1][0] * other.b[0] + a[1][1] * other.b[1] + self.b[1],
            ],
            m: [
                [prod(0, 0) - 1.0, prod(0, 1)],
                [prod(1, 0), prod(1, 1) - 1.0],
            ],
        }
    }

    pub(in crate::align) fn lerp(&self, other: &AffineMotion, a: f64) -> AffineMotion {
        let (p, q) = (self.params(), other.params());
        AffineMotion::from_params(std::array::from_fn(|i| p[i] * (1.0 - a) + q[i] * a))
    }
}

/// Value at time `t` of a piecewise-linear function through `(times[i], values[i])`,
/// extrapolated linearly beyond the ends.
pub(super) fn interpolate(times: &[f64], values: &[AffineMotion], t: f64) -> AffineMotion {
    if values.len() == 1 {
        return values[0];
    }
    let k = times
        .windows(2)
        .position(|w| t < w[1])
        .unwrap_or(times.len() - 2);
    let a = (t - times[k]) / (times[k + 1] - times[k]);
    values[k].lerp(&values[k + 1], a)
}
