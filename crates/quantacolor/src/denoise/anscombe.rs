//! Binomial Anscombe transform and its exact unbiased inverse (paper §4.3, supplement §1.5).
//!
//! A merged pixel is a count X ~ Binomial(n, p) of detections in n binary frames. Its variance
//! np(1 − p) depends on the signal, which Gaussian denoisers such as BM3D do not expect. The
//! binomial Anscombe transform (Anscombe 1948)
//!
//! A(X) = 2·√(n + ½)·asin(√((X + ⅜)/(n + ¾)))
//!
//! makes the variance close to 1 for every p not too near 0 or 1. After denoising, the
//! algebraic inverse sin²(A/(2√(n + ½)))·(n + ¾) − ⅜ is biased at low counts, because the
//! denoised value estimates E[A(X)], not A(E[X]). The exact unbiased inverse (Mäkitalo & Foi,
//! IEEE TIP 2011, for the Poisson case; the same construction for the binomial) maps a value a
//! to the p with E[A(X) | p] = a, computed here from the binomial distribution on a table.
#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use crate::model::{detection_probability, detection_probability_slope, PixelModel, Readout};
use rayon::prelude::*;

/// Number of table points in p (uniform in asin √p, so uniform in the transformed domain).
const TABLE_POINTS: usize = 4097;

/// The binomial Anscombe transform for a fixed number of trials, with its exact unbiased
/// inverse tabulated.
#[derive(Debug, Clone)]
pub struct BinomialAnscombe {
    trials: f64,
    /// Bit rates p of the table, increasing from 0 to 1.
    table_p: Vec<f64>,
    /// E[A(X) | p] for X ~ Binomial(trials, p), increasing.
    table_expected: Vec<f64>,
    /// Where [`BinomialAnscombe::inverse_exact`] searches `table_expected`: the range of E[A]
    /// cut into [`SEARCH_BUCKETS`] equal buckets, `bucket_start[k]` the lowest value of bucket
    /// k and `bucket_first[k]` the first table index whose E[A] exceeds it (one more entry,
    /// the table's length, ends the last bucket), so that a value's table interval lies
    /// between the firsts of its bucket and the next (usually a step or two, instead of a
    /// binary search over the whole table).
    bucket_start: Vec<f64>,
    bucket_first: Vec<usize>,
}

/// Buckets of the search index of [`BinomialAnscombe::inverse_exact`].
const SEARCH_BUCKETS: usize = 4096;

impl BinomialAnscombe {
    /// The transform for `trials` binary frames (rounded to the nearest integer, at least 1).
    pub fn new(trials: f64) -> Result<Self> {
        if !trials.is_finite() || trials < 0.5 {
            return Err(Error::invalid(format!(
                "binomial Anscombe transform: number of trials must be at least 1, got {trials}"
            )));
        }
        let trials = trials.round();
        let mut transform = BinomialAnscombe {
            trials,
            table_p: Vec::with_capacity(TABLE_POINTS),
            table_expected: Vec::with_capacity(TABLE_POINTS),
            bucket_start: Vec::with_capacity(SEARCH_BUCKETS + 1),
            bucket_first: Vec::with_capacity(SEARCH_BUCKETS + 1),
        };
        // A(k) of every count k, made once (the expectations below visit each many times);
        // beyond `MAX_COUNT_TABLE` trials each is computed where it is needed.
        const MAX_COUNT_TABLE: f64 = 4_194_304.0;
        // With them, the ratios P(k+1)/P(k) and P(k−1)/P(k) of the binomial distribution
        // without their p factor, the same for every p (no divisions in the sums).
        let counts: Option<CountTables> =
            (trials <= MAX_COUNT_TABLE).then(|| CountTables::new(&transform));
        let points: Vec<(f64, f64)> = (0..TABLE_POINTS)
            .into_par_iter()
            .map(|i| {
                let theta = std::f64::consts::FRAC_PI_2 * i as f64 / (TABLE_POINTS - 1) as f64;
                let p = theta.sin().powi(2).clamp(0.0, 1.0);
                let expected = match &counts {
                    Some(t) => transform.expected_with(
                        p,
                        |k| t.forward[k as usize],
                        |k| t.up[k as usize],
                        |k| t.down[k as usize],
                    ),
                    None => transform.expected(p),
                };
                (p, expected)
            })
            .collect();
        for (p, expected) in points {
            transform.table_p.push(p);
            transform.table_expected.push(expected);
        }
        // E[A | p] is increasing in p; rounding can leave ties at the ends.
        for i in 1..TABLE_POINTS {
            if transform.table_expected[i] < transform.table_expected[i - 1] {
                transform.table_expected[i] = transform.table_expected[i - 1];
            }
        }
        let table = &transform.table_expected;
        let (lo, hi) = (table[0], table[TABLE_POINTS - 1]);
        for k in 0..SEARCH_BUCKETS {
            let start = lo + (hi - lo) * (k as f64 / SEARCH_BUCKETS as f64);
            transform.bucket_start.push(start);
            transform
                .bucket_first
                .push(table.partition_point(|&e| e <= start));
        }
        // The last bucket reaches to the end of the table.
        transform.bucket_first.push(TABLE_POINTS);
        Ok(transform)
    }

    /// The number of trials n.
    pub fn trials(&self) -> f64 {
        self.trials
    }

    /// A(X) for a count X (any real value in [0, n]; clamped to it).
    pub fn forward(&self, count: f64) -> f64 {
        let n = self.trials;
        let ratio = ((count.clamp(0.0, n) + 0.375) / (n + 0.75)).clamp(0.0, 1.0);
        2.0 * (n + 0.5).sqrt() * ratio.sqrt().asin()
    }

    /// A(n·p) for a bit rate p.
    pub fn forward_rate(&self, p: f64) -> f64 {
        self.forward(p * self.trials)
    }

    /// dA/dp at bit rate p: the factor that carries a bit-rate standard deviation into the
    /// transformed domain (delta method).
    pub fn derivative_rate(&self, p: f64) -> f64 {
        let n = self.trials;
        let u = ((p.clamp(0.0, 1.0) * n + 0.375) / (n + 0.75)).clamp(1e-12, 1.0 - 1e-12);
        // d/dp asin(√u) = (du/dp) / (2√(u(1 − u))), du/dp = n/(n + ¾).
        2.0 * (n + 0.5).sqrt() * (n / (n + 0.75)) / (2.0 * (u * (1.0 - u)).sqrt())
    }

    /// Algebraic inverse: the bit rate p with A(n·p) = `value`.
    pub fn inverse_algebraic(&self, value: f64) -> f64 {
        let n = self.trials;
        let s = (value / (2.0 * (n + 0.5).sqrt())).clamp(0.0, std::f64::consts::FRAC_PI_2);
        ((s.sin().powi(2) * (n + 0.75) - 0.375) / n).clamp(0.0, 1.0)
    }

    /// E[A(X) | p] for X ~ Binomial(n, p), summed over the binomial distribution.
    pub fn expected(&self, p: f64) -> f64 {
        let n = self.trials;
        self.expected_with(
            p,
            |k| self.forward(k as f64),
            |k| ratio_up(n, k),
            |k| ratio_down(n, k),
        )
    }

    /// [`BinomialAnscombe::expected`] with A(k) of count k given by `forward_count`, and
    /// [`ratio_up`] and [`ratio_down`] of count k by `up` and `down`.
    fn expected_with(
        &self,
        p: f64,
        forward_count: impl Fn(u64) -> f64,
        up: impl Fn(u64) -> f64,
        down: impl Fn(u64) -> f64,
    ) -> f64 {
        let n = self.trials;
        if p <= 0.0 {
            return forward_count(0);
        }
        if p >= 1.0 {
            return forward_count(n as u64);
        }
        // Probabilities relative to the mode by the ratio P(k+1)/P(k) = (n−k)/(k+1) · p/(1−p),
        // walking out until they are negligible; then normalised.
        let n_int = n as u64;
        let mode = (((n + 1.0) * p).floor() as u64).min(n_int);
        let odds = p / (1.0 - p);
        let (mut weight_sum, mut value_sum) = (1.0, forward_count(mode));
        let mut weight = 1.0f64;
        for k in mode..n_int {
            weight *= up(k) * odds;
            if weight < 1e-17 {
                break;
            }
            weight_sum += weight;
            value_sum += weight * forward_count(k + 1);
        }
        weight = 1.0;
        for k in (1..=mode).rev() {
            // P(k−1)/P(k) = k/(n−k+1) · (1−p)/p
            weight *= down(k) / odds;
            if weight < 1e-17 {
                break;
            }
            weight_sum += weight;
            value_sum += weight * forward_count(k - 1);
        }
        value_sum / weight_sum
    }

    /// Exact unbiased inverse: the bit rate p with E[A(X) | p] = `value` (clamped to [0, 1]
    /// outside the range of E[A]).
    pub fn inverse_exact(&self, value: f64) -> f64 {
        let table = &self.table_expected;
        if !value.is_finite() {
            return f64::NAN;
        }
        if value <= table[0] {
            return 0.0;
        }
        if value >= table[TABLE_POINTS - 1] {
            return 1.0;
        }
        let hi = self.first_above(value).min(TABLE_POINTS - 1);
        let lo = hi - 1;
        let span = table[hi] - table[lo];
        let t = if span > 0.0 {
            (value - table[lo]) / span
        } else {
            0.0
        };
        self.table_p[lo] + t * (self.table_p[hi] - self.table_p[lo])
    }
}

impl BinomialAnscombe {
    /// The first table index whose E[A] exceeds `value` (`table_expected.partition_point(|&e|
    /// e <= value)`, found within the value's bucket of the search index), for `value` within
    /// the table's range.
    fn first_above(&self, value: f64) -> usize {
        let (starts, table) = (&self.bucket_start, &self.table_expected);
        let (lo, hi) = (table[0], table[TABLE_POINTS - 1]);
        let guess = if hi > lo {
            ((value - lo) / (hi - lo) * SEARCH_BUCKETS as f64) as usize
        } else {
            0
        };
        // The bucket k with start[k] ≤ value < start[k + 1] (the last bucket has no end; the
        // guess is at most one off by rounding).
        let mut k = guess.min(SEARCH_BUCKETS - 1);
        while k > 0 && value < starts[k] {
            k -= 1;
        }
        while k + 1 < SEARCH_BUCKETS && value >= starts[k + 1] {
            k += 1;
        }
        // E[A] > start[k + 1] > value from `first[k + 1]` on, and E[A] ≤ start[k] ≤ value
        // before `first[k]`.
        let (from, to) = (self.bucket_first[k], self.bucket_first[k + 1]);
        from + table[from..to].partition_point(|&e| e <= value)
    }
}

/// P(k+1)/P(k) of Binomial(n, p) without its factor p/(1 − p): (n − k)/(k + 1).
fn ratio_up(n: f64, k: u64) -> f64 {
    (n - k as f64) / (k as f64 + 1.0)
}

/// P(k−1)/P(k) of Binomial(n, p) without its factor (1 − p)/p: k/(n − k + 1).
fn ratio_down(n: f64, k: u64) -> f64 {
    k as f64 / (n - k as f64 + 1.0)
}

/// A(k), [`ratio_up`] and [`ratio_down`] of every count k of a [`BinomialAnscombe`], made once
/// for its table (each expectation visits them many times).
struct CountTables {
    forward: Vec<f64>,
    up: Vec<f64>,
    down: Vec<f64>,
}

impl CountTables {
    fn new(transform: &BinomialAnscombe) -> Self {
        let n = transform.trials;
        let counts = 0..=n as u64;
        CountTables {
            forward: counts
                .clone()
                .map(|k| transform.forward(k as f64))
                .collect(),
            up: counts.clone().map(|k| ratio_up(n, k)).collect(),
            down: counts.map(|k| ratio_down(n, k)).collect(),
        }
    }
}

/// Variance stabilisation of a merged flux λ (detections per frame) from `trials` frames, by
/// the capture's pixel model ([`PixelModel`]):
///
/// - binary frames: the bit rate p = 1 − exp(−(λ + d)) (paper Eq. 2–3), then the binomial
///   Anscombe transform A(n·p) with its exact unbiased inverse ([`BinomialAnscombe`], paper
///   §4.3);
/// - multi-bit frames (Gaussian–Poisson, §6.1): the generalized Anscombe transform (Murtagh,
///   Starck & Bijaoui 1995) of the equivalent count Y = n·(λ + c), c = d + σ_r² + gain²/12
///   (shot noise plus read and quantisation noise as a Poisson count of the same variance):
///   a = 2·√(Y + ⅜), inverted by the asymptotically unbiased Y = (a/2)² − ⅛ (Mäkitalo & Foi
///   2013 in the regime where n·c is large: a conventional burst has n·σ_r² of hundreds).
#[derive(Debug, Clone)]
pub enum Stabiliser {
    Binomial {
        anscombe: BinomialAnscombe,
        model: PixelModel,
    },
    GaussianPoisson {
        trials: f64,
        /// c = d + σ_r² + gain²/12, electrons per frame.
        floor: f64,
        model: PixelModel,
    },
}

impl Stabiliser {
    /// The stabiliser of `model` for `trials` frames (at least 1).
    pub fn new(model: PixelModel, trials: f64) -> Result<Self> {
        Ok(match model.readout {
            Readout::Binary => Stabiliser::Binomial {
                anscombe: BinomialAnscombe::new(trials)?,
                model,
            },
            Readout::GaussianPoisson(g) => {
                if !trials.is_finite() || trials < 0.5 {
                    return Err(Error::invalid(format!(
                        "Gaussian–Poisson Anscombe transform: number of frames must be at \
                         least 1, got {trials}"
                    )));
                }
                Stabiliser::GaussianPoisson {
                    trials,
                    floor: model.dark_per_frame + g.floor_variance_e2(),
                    model,
                }
            }
        })
    }

    /// The pixel model.
    pub fn model(&self) -> &PixelModel {
        match self {
            Stabiliser::Binomial { model, .. } | Stabiliser::GaussianPoisson { model, .. } => model,
        }
    }

    /// The number of frames n.
    pub fn trials(&self) -> f64 {
        match self {
            Stabiliser::Binomial { anscombe, .. } => anscombe.trials(),
            Stabiliser::GaussianPoisson { trials, .. } => *trials,
        }
    }

    /// The flux kept where the Poisson rate λ + d is not negative (NaN is read as −d): a merged
    /// flux estimate is unbiased, not non-negative, and can lie slightly below −d.
    fn physical_flux(lambda: f64, dark: f64) -> f64 {
        lambda.max(-dark)
    }

    /// Bit rate of binary frames, p = 1 − exp(−(λ + d)) in [0, 1] ([`detection_probability`],
    /// paper Eq. 1–4).
    fn bit_rate(lambda: f64, dark: f64) -> f64 {
        detection_probability(Self::physical_flux(lambda, dark), dark)
    }

    /// The stabilised value of flux `lambda`.
    pub fn forward(&self, lambda: f64) -> f64 {
        match self {
            Stabiliser::Binomial { anscombe, model } => {
                anscombe.forward_rate(Self::bit_rate(lambda, model.dark_per_frame))
            }
            Stabiliser::GaussianPoisson { trials, floor, .. } => {
                2.0 * (trials * (lambda + floor) + 0.375).max(0.0).sqrt()
            }
        }
    }

    /// d(forward)/dλ at `lambda` (delta method).
    pub fn derivative(&self, lambda: f64) -> f64 {
        match self {
            Stabiliser::Binomial { anscombe, model } => {
                let dark = model.dark_per_frame;
                let p = Self::bit_rate(lambda, dark);
                anscombe.derivative_rate(p)
                    * detection_probability_slope(Self::physical_flux(lambda, dark), dark)
            }
            Stabiliser::GaussianPoisson { trials, floor, .. } => {
                trials / (trials * (lambda + floor) + 0.375).max(1e-12).sqrt()
            }
        }
    }

    /// `(forward(lambda), derivative(lambda))`, the same bits, with the bit rate (binary
    /// frames) computed once for both: the denoiser needs both at every pixel (the stabilised
    /// image and the delta method of its noise model).
    pub fn forward_and_derivative(&self, lambda: f64) -> (f64, f64) {
        match self {
            Stabiliser::Binomial { anscombe, model } => {
                let dark = model.dark_per_frame;
                let p = Self::bit_rate(lambda, dark);
                let slope = detection_probability_slope(Self::physical_flux(lambda, dark), dark);
                (
                    anscombe.forward_rate(p),
                    anscombe.derivative_rate(p) * slope,
                )
            }
            Stabiliser::GaussianPoisson { .. } => (self.forward(lambda), self.derivative(lambda)),
        }
    }

    /// The flux whose stabilised value has expectation `value` (exact unbiased inverse for
    /// binary frames, then the MLE of paper Eq. 6 with its saturation cap,
    /// [`PixelModel::flux`]; asymptotically unbiased for Gaussian–Poisson).
    pub fn inverse(&self, value: f64) -> f64 {
        match self {
            Stabiliser::Binomial { anscombe, model } => {
                model.flux(anscombe.inverse_exact(value), anscombe.trials())
            }
            Stabiliser::GaussianPoisson { trials, floor, .. } => {
                let y = 0.25 * value * value - 0.125;
                y / trials - floor
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Binomial, Distribution};

    #[test]
    fn variance_is_stabilised_near_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for &(n, p) in &[
            (100u64, 0.1),
            (100, 0.5),
            (1000, 0.02),
            (1000, 0.9),
            (50, 0.3),
        ] {
            let t = BinomialAnscombe::new(n as f64).unwrap();
            let dist = Binomial::new(n, p).unwrap();
            let samples: Vec<f64> = (0..20000)
                .map(|_| t.forward(dist.sample(&mut rng) as f64))
                .collect();
            let mean = samples.iter().sum::<f64>() / samples.len() as f64;
            let var =
                samples.iter().map(|a| (a - mean).powi(2)).sum::<f64>() / samples.len() as f64;
            assert!((var - 1.0).abs() < 0.08, "n {n} p {p}: variance {var}");
            // The table's expectation matches the sample mean.
            assert!((t.expected(p) - mean).abs() < 0.03, "n {n} p {p}");
        }
    }

    #[test]
    fn exact_inverse_is_unbiased_where_the_algebraic_one_is_not() {
        let n = 20.0;
        let t = BinomialAnscombe::new(n).unwrap();
        for &p in &[0.01, 0.05, 0.2, 0.5, 0.8, 0.97] {
            let e = t.expected(p);
            let exact = t.inverse_exact(e);
            assert!((exact - p).abs() < 1e-4, "p {p}: exact inverse {exact}");
        }
        // At 0.2 expected counts the algebraic inverse of E[A] is biased by about a quarter.
        let p = 0.01;
        let algebraic = t.inverse_algebraic(t.expected(p));
        assert!((algebraic - p).abs() / p > 0.2, "algebraic {algebraic}");
    }

    #[test]
    fn algebraic_inverse_inverts_forward_and_ends_clamp() {
        let t = BinomialAnscombe::new(500.0).unwrap();
        for i in 0..=50 {
            let p = i as f64 / 50.0;
            assert!((t.inverse_algebraic(t.forward_rate(p)) - p).abs() < 1e-9);
        }
        assert_eq!(t.inverse_exact(-5.0), 0.0);
        assert_eq!(t.inverse_exact(1e9), 1.0);
        assert!(t.inverse_exact(f64::NAN).is_nan());
        assert!(BinomialAnscombe::new(0.0).is_err());
        assert!(BinomialAnscombe::new(f64::NAN).is_err());
    }

    #[test]
    fn bucketed_search_is_the_binary_search() {
        for n in [1.0, 20.0, 700.0, 5000.0] {
            let t = BinomialAnscombe::new(n).unwrap();
            let (lo, hi) = (t.table_expected[0], t.table_expected[TABLE_POINTS - 1]);
            let mut values: Vec<f64> = (0..20_000)
                .map(|i| lo + (hi - lo) * (i as f64 + 0.5) / 20_000.0)
                .collect();
            // Every table value and its neighbours (ties are where the two could differ).
            for &e in t.table_expected.iter().step_by(7) {
                // E[A] ≥ 0: the neighbouring floats are one step of the bits away.
                let bits = e.to_bits();
                values.extend([
                    e,
                    f64::from_bits(bits.saturating_sub(1)),
                    f64::from_bits(bits + 1),
                ]);
            }
            values.extend(t.bucket_start.iter().copied());
            for v in values.into_iter().filter(|v| *v > lo && *v < hi) {
                let want = t.table_expected.partition_point(|&e| e <= v);
                assert_eq!(t.first_above(v), want, "n {n} value {v}");
            }
        }
    }

    #[test]
    fn forward_and_derivative_are_both_bit_for_bit() {
        let binary = Stabiliser::new(PixelModel::binary(0.003), 700.0).unwrap();
        let multibit = Stabiliser::new(
            PixelModel {
                dark_per_frame: 0.1,
                readout: Readout::GaussianPoisson(crate::model::GaussianPoisson {
                    gain_e_per_dn: 2.0,
                    read_noise_e: 1.5,
                    black_level_dn: 10.0,
                    saturation_dn: 1023.0,
                }),
            },
            40.0,
        )
        .unwrap();
        for s in [&binary, &multibit] {
            for lambda in [-0.01, 0.0, 1e-4, 0.02, 0.7, 3.0, 40.0, f64::NAN] {
                let (a, da) = s.forward_and_derivative(lambda);
                assert_eq!(a.to_bits(), s.forward(lambda).to_bits(), "{lambda}");
                assert_eq!(da.to_bits(), s.derivative(lambda).to_bits(), "{lambda}");
            }
        }
    }

    #[test]
    fn derivative_matches_finite_difference() {
        let t = BinomialAnscombe::new(300.0).unwrap();
        for &p in &[0.01, 0.3, 0.7] {
            let h = 1e-6;
            let fd = (t.forward_rate(p + h) - t.forward_rate(p - h)) / (2.0 * h);
            assert!((t.derivative_rate(p) - fd).abs() / fd < 1e-5, "p {p}");
        }
    }
}
