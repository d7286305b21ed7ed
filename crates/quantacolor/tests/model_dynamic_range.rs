//! Dynamic-range helpers of the imaging model (paper §7), checked against a brute-force scan of
//! the SNR curve and closed-form limits.

use quantacolor::model::{
    db_to_ratio, dynamic_range, peak_snr_flux, ratio_to_db, saturation_flux, snr, UpperLimit,
};

/// Smallest and largest λ on a fine log grid with SNR >= thr (ignoring saturation).
fn scan(frames: f64, dark: f64, thr: f64) -> (f64, f64) {
    let (lo, hi, k) = (1e-9f64, 200.0f64, 200_000);
    let mut first = None;
    let mut last = None;
    for i in 0..=k {
        let l = lo * (hi / lo).powf(i as f64 / k as f64);
        if snr(l, frames, dark) >= thr {
            first.get_or_insert(l);
            last = Some(l);
        }
    }
    (first.unwrap(), last.unwrap())
}

#[test]
fn peak_flux_is_the_snr_maximum() {
    for &d in &[0.0, 1e-3, 0.1] {
        let p = peak_snr_flux(d);
        let s = snr(p, 1000.0, d);
        for &f in &[0.99, 0.999, 1.001, 1.01] {
            assert!(snr(p * f, 1000.0, d) < s, "d={d}: not a maximum at {p}");
        }
    }
    // d = 0: root of 2(1 − e^{−λ}) = λ, λ ≈ 1.5936.
    assert!((peak_snr_flux(0.0) - 1.593_624_260_6).abs() < 1e-9);
}

#[test]
fn bisection_matches_brute_force_scan() {
    for &(n, d, thr) in &[
        (2000.0, 0.0, 1.0),
        (2000.0, 1e-3, 10.0),
        (100.0, 0.0, 3.0),
        (1e5, 1e-2, 1.0),
    ] {
        let dr = dynamic_range(n, d, thr).unwrap();
        let (smin, smax) = scan(n, d, thr);
        let step = (200.0f64 / 1e-9).powf(1.0 / 200_000.0); // grid ratio
        assert!(
            dr.min_flux <= smin && dr.min_flux >= smin / step,
            "n={n} d={d}: min {} vs scan {smin}",
            dr.min_flux
        );
        assert!((snr(dr.min_flux, n, d) / thr - 1.0).abs() < 1e-9);
        let sat = saturation_flux(n, d);
        let expect_max = smax.min(sat);
        assert!(
            (dr.max_flux / expect_max - 1.0).abs() <= step - 1.0,
            "n={n} d={d}: max {} vs {expect_max}",
            dr.max_flux
        );
        assert!((dr.db - 20.0 * (dr.max_flux / dr.min_flux).log10()).abs() < 1e-12);
    }
}

#[test]
fn known_limits() {
    // No dark counts: SNR ≈ sqrt(nλ) at low flux, so λ_min ≈ thr²/n.
    let n = 1e6;
    let dr = dynamic_range(n, 0.0, 1.0).unwrap();
    assert!((dr.min_flux * n - 1.0).abs() < 1e-3, "{}", dr.min_flux * n);
    // With n = 2000 and SNR >= 1 the saturation limit ln(2n) − d binds (SNR is still ~7 there).
    let dr = dynamic_range(2000.0, 0.0, 1.0).unwrap();
    assert_eq!(dr.upper_limit, UpperLimit::Saturation);
    assert!((dr.max_flux - 4000f64.ln()).abs() < 1e-12);
    // A 20 dB criterion with few frames is SNR-limited on the high side.
    let dr = dynamic_range(2000.0, 0.0, db_to_ratio(20.0)).unwrap();
    assert_eq!(dr.upper_limit, UpperLimit::Snr);
    assert!((snr(dr.max_flux, 2000.0, 0.0) - 10.0).abs() < 1e-9);
    // Dark counts raise the floor.
    let clean = dynamic_range(2000.0, 0.0, 3.0).unwrap();
    let dark = dynamic_range(2000.0, 0.05, 3.0).unwrap();
    assert!(dark.min_flux > clean.min_flux && dark.db < clean.db);
}

#[test]
fn unreachable_threshold_and_bad_params_are_errors() {
    // Peak SNR for n = 100 is ~7.9; 20 dB (ratio 10) cannot be reached.
    assert!(snr(peak_snr_flux(0.0), 100.0, 0.0) < 10.0);
    assert!(dynamic_range(100.0, 0.0, 10.0).is_err());
    assert!(dynamic_range(0.0, 0.0, 1.0).is_err());
    assert!(dynamic_range(100.0, -0.1, 1.0).is_err());
    assert!(dynamic_range(100.0, 0.0, 0.0).is_err());
    assert!(dynamic_range(100.0, 0.0, f64::NAN).is_err());
}

#[test]
fn db_conversions() {
    assert!((db_to_ratio(20.0) - 10.0).abs() < 1e-12);
    assert!((ratio_to_db(1000.0) - 60.0).abs() < 1e-12);
    assert!((db_to_ratio(ratio_to_db(3.7)) - 3.7).abs() < 1e-12);
}
