//! Statistical tests of the Bernoulli imaging model (paper §3, Eq. 1–6, Eq. 9): the MLE is
//! unbiased to first order, its exact expectation matches the known O(1/n) bias, and the SNR
//! formula matches Monte Carlo.

use ndarray::{Array2, Array3};
use quantacolor::model::{
    detection_probability, mle_flux, mle_flux_array, mle_flux_nonneg, mle_flux_nonneg_array,
    mle_flux_per_pixel, mle_std, saturation_flux, snr,
};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Binomial, Distribution};

const FRAMES: u64 = 2000;
const DRAWS: usize = 4000;

/// log grid over 1e-3..3 photons per frame.
fn flux_grid() -> Vec<f64> {
    let k = 13;
    (0..k)
        .map(|i| 1e-3 * (3.0f64 / 1e-3).powf(i as f64 / (k - 1) as f64))
        .collect()
}

/// Binomial(n, p) pmf for k = 0..=n, via log-factorials (exact to ~1e-12 relative).
fn binomial_pmf(n: u64, p: f64) -> Vec<f64> {
    let n_us = n as usize;
    let mut ln_fact = vec![0.0f64; n_us + 1];
    for k in 1..=n_us {
        ln_fact[k] = ln_fact[k - 1] + (k as f64).ln();
    }
    (0..=n_us)
        .map(|k| {
            let ln_c = ln_fact[n_us] - ln_fact[k] - ln_fact[n_us - k];
            (ln_c + k as f64 * p.ln() + (n_us - k) as f64 * (-p).ln_1p()).exp()
        })
        .collect()
}

/// Exact mean and standard deviation of λ̂ over the binomial distribution of S.
fn exact_moments(lambda: f64, dark: f64, n: u64) -> (f64, f64, f64) {
    let pmf = binomial_pmf(n, detection_probability(lambda, dark));
    let nf = n as f64;
    let (mut m1, mut m2, mut total) = (0.0, 0.0, 0.0);
    for (k, &w) in pmf.iter().enumerate() {
        let e = mle_flux(k as f64, nf, dark);
        m1 += w * e;
        m2 += w * e * e;
        total += w;
    }
    (m1, (m2 - m1 * m1).max(0.0).sqrt(), total)
}

fn sample_estimates(rng: &mut ChaCha8Rng, lambda: f64, dark: f64) -> Vec<f64> {
    let p = detection_probability(lambda, dark);
    let bin = Binomial::new(FRAMES, p).unwrap();
    (0..DRAWS)
        .map(|_| mle_flux(bin.sample(rng) as f64, FRAMES as f64, dark))
        .collect()
}

fn mean_std(v: &[f64]) -> (f64, f64) {
    let m = v.iter().sum::<f64>() / v.len() as f64;
    let var = v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (v.len() - 1) as f64;
    (m, var.sqrt())
}

#[test]
fn saturation_is_negligible_on_the_grid() {
    // At λ = 3 (the top of the grid) P(S = n) = p^n must be tiny for n = 2000.
    let p = detection_probability(3.0, 1e-3);
    let log10_p_sat = FRAMES as f64 * p.log10();
    assert!(log10_p_sat < -40.0, "log10 P(S=n) = {log10_p_sat}");
}

#[test]
fn mle_is_unbiased_within_standard_error() {
    let mut rng = ChaCha8Rng::seed_from_u64(0x5eed_0001);
    let n = FRAMES as f64;
    for &dark in &[0.0, 1e-3] {
        for lambda in flux_grid() {
            let (exact_mean, exact_std, total) = exact_moments(lambda, dark, FRAMES);
            assert!((total - 1.0).abs() < 1e-9, "pmf sums to {total}");

            // Exact bias agrees with the second-order delta-method term (e^{λ+d} − 1)/(2n), to
            // within 10 % of that term (the next order is O(1/n²)); it is below 0.3 % of λ.
            let bias = exact_mean - lambda;
            let predicted = (lambda + dark).exp_m1() / (2.0 * n);
            assert!(
                (bias - predicted).abs() <= 0.1 * predicted + 1e-12,
                "λ={lambda} d={dark}: exact bias {bias:e}, predicted {predicted:e}"
            );
            assert!(bias.abs() <= 3e-3 * lambda, "λ={lambda}: bias {bias:e}");

            // Monte Carlo mean agrees with λ + exact bias within 4 standard errors; the bias
            // itself is below one standard error of this experiment except near λ = 3.
            let est = sample_estimates(&mut rng, lambda, dark);
            let (mc_mean, mc_std) = mean_std(&est);
            let stderr = mc_std / (DRAWS as f64).sqrt();
            assert!(
                (mc_mean - exact_mean).abs() <= 4.0 * stderr,
                "λ={lambda} d={dark}: MC mean {mc_mean}, exact {exact_mean}, stderr {stderr}"
            );
            assert!(
                (mc_mean - lambda).abs() <= 4.0 * stderr + bias.abs(),
                "λ={lambda} d={dark}: MC mean {mc_mean}"
            );
            // The asymptotic std is within 2 % of the exact one on this grid.
            let asym = mle_std(lambda, n, dark);
            assert!(
                (asym / exact_std - 1.0).abs() < 0.02,
                "λ={lambda} d={dark}: asymptotic std {asym}, exact {exact_std}"
            );
        }
    }
}

#[test]
fn snr_formula_matches_monte_carlo() {
    let mut rng = ChaCha8Rng::seed_from_u64(0x5eed_0002);
    let n = FRAMES as f64;
    for &dark in &[0.0, 1e-3] {
        for lambda in flux_grid() {
            let est = sample_estimates(&mut rng, lambda, dark);
            let (m, s) = mean_std(&est);
            let mc_snr = m / s;
            let formula = snr(lambda, n, dark);
            assert!(
                (mc_snr / formula - 1.0).abs() < 0.05,
                "λ={lambda} d={dark}: MC SNR {mc_snr}, formula {formula}"
            );
            // SNR is λ over the asymptotic std by definition of Eq. 9.
            assert!((formula - lambda / mle_std(lambda, n, dark)).abs() < 1e-9 * formula);
        }
    }
}

#[test]
fn snr_known_limits() {
    // Low flux, no dark counts: SNR -> sqrt(n λ) (photon shot noise).
    let (n, l) = (1000.0, 1e-6);
    assert!((snr(l, n, 0.0) / (n * l).sqrt() - 1.0).abs() < 1e-6);
    // Low flux with dark counts: SNR -> λ sqrt(n) / sqrt(λ + d).
    let d = 1e-3;
    assert!((snr(l, n, d) / (l * n.sqrt() / (l + d).sqrt()) - 1.0).abs() < 1e-3);
    assert_eq!(snr(0.0, n, 0.0), 0.0);
    // Very high flux: the exponential term drives the SNR to zero.
    assert!(snr(60.0, n, 0.0) < 1e-9);
}

#[test]
fn mle_edge_cases_are_finite_and_monotone() {
    let n = 100.0;
    let d = 0.01;
    // S = 0 gives −d unclamped, 0 clamped.
    assert_eq!(mle_flux(0.0, n, d), -d);
    assert_eq!(mle_flux_nonneg(0.0, n, d), 0.0);
    // S = n is replaced by n − 0.5: ln(2n) − d.
    let sat = mle_flux(n, n, d);
    assert!((sat - ((2.0 * n).ln() - d)).abs() < 1e-12);
    assert_eq!(saturation_flux(n, d), sat);
    // Out-of-range counts clamp to the valid range instead of producing NaN/inf.
    assert_eq!(mle_flux(n + 7.0, n, d), sat);
    assert_eq!(mle_flux(-3.0, n, d), -d);
    assert!(mle_flux(1.0, 0.0, d).is_nan());
    // Strictly increasing for 0 <= S <= n − 0.5, non-decreasing up to n.
    let mut prev = f64::NEG_INFINITY;
    for k in 0..=200 {
        let s = k as f64 * 0.5;
        let v = mle_flux(s, n, d);
        assert!(v.is_finite());
        if s <= n - 0.5 {
            assert!(v > prev, "not increasing at S={s}");
        } else {
            assert!(v >= prev);
        }
        prev = v;
    }
}

#[test]
fn array_versions_match_scalar() {
    let (n, d) = (255.0, 2e-3);
    // Small (sequential path) and large (rayon path) arrays, 2-D and 3-D.
    let small = Array2::from_shape_fn((7, 9), |(y, x)| ((y * 9 + x) * 4 % 256) as f32);
    let large = Array3::from_shape_fn((3, 200, 160), |(c, y, x)| {
        ((c * 7919 + y * 160 + x) % 256) as f32
    });
    let out = mle_flux_array(small.view(), n, d).unwrap();
    for (o, &s) in out.iter().zip(small.iter()) {
        assert_eq!(*o, mle_flux(f64::from(s), n, d) as f32);
    }
    let out = mle_flux_array(large.view(), n, d).unwrap();
    assert_eq!(out.shape(), large.shape());
    for (o, &s) in out.iter().zip(large.iter()) {
        assert_eq!(*o, mle_flux(f64::from(s), n, d) as f32);
    }
    let out = mle_flux_nonneg_array(large.view(), n, d).unwrap();
    for (o, &s) in out.iter().zip(large.iter()) {
        assert_eq!(*o, mle_flux_nonneg(f64::from(s), n, d) as f32);
        assert!(*o >= 0.0);
    }
    // Per-pixel frame counts.
    let frames = Array2::from_shape_fn((7, 9), |(y, x)| 250.0 + (y + x) as f32);
    let out = mle_flux_per_pixel(small.view(), frames.view(), d).unwrap();
    for ((o, &s), &f) in out.iter().zip(small.iter()).zip(frames.iter()) {
        assert_eq!(*o, mle_flux(f64::from(s), f64::from(f), d) as f32);
    }
    // Invalid parameters are errors, not panics.
    assert!(mle_flux_array(small.view(), 0.0, d).is_err());
    assert!(mle_flux_array(small.view(), n, -1.0).is_err());
    assert!(mle_flux_array(small.view(), f64::NAN, d).is_err());
    let wrong = Array2::<f32>::ones((9, 7));
    assert!(mle_flux_per_pixel(small.view(), wrong.view(), d).is_err());
}
