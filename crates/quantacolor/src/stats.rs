//! Order statistics, the one home for them: nearest-rank quantiles and percentiles, medians and
//! numpy's linearly interpolated percentile. Each selects in place (`select_nth_unstable`) under
//! `total_cmp`, so the value returned is unique whatever the selection's order of work.
#![forbid(unsafe_code)]

/// Value at the `q`-quantile (0–1) of the finite entries of `values`, nearest rank: the
/// `round(q·(n − 1))`-th smallest (clamped to the last). `None` when no entry is finite.
pub fn quantile(values: impl Iterator<Item = f32>, q: f64) -> Option<f32> {
    let mut v: Vec<f32> = values.filter(|x| x.is_finite()).collect();
    select_nearest_rank(&mut v, q)
}

/// Value at percentile `p` (0–100) of the finite entries of `values` (nearest rank): the
/// [`quantile`] at `p / 100`.
pub fn percentile(values: impl Iterator<Item = f32>, p: f64) -> Option<f32> {
    quantile(values, p / 100.0)
}

/// The `round(q·(n − 1))`-th smallest of `values` (clamped to the last; NaN `q` gives the
/// smallest), reordering them. `None` when empty.
pub fn select_nearest_rank(values: &mut [f32], q: f64) -> Option<f32> {
    if values.is_empty() {
        return None;
    }
    let k = ((q * (values.len() - 1) as f64).round() as usize).min(values.len() - 1);
    let (_, kth, _) = values.select_nth_unstable_by(k, f32::total_cmp);
    Some(*kth)
}

/// The `⌊q·n⌋`-th smallest of `values` (clamped to the last), reordering them: a quantile
/// that rounds down on the `n` entries rather than to the nearest of the `n − 1` gaps (as
/// [`select_nearest_rank`] does). `None` when empty.
pub fn select_floor_rank(values: &mut [f32], q: f64) -> Option<f32> {
    if values.is_empty() {
        return None;
    }
    let k = ((values.len() as f64 * q) as usize).min(values.len() - 1);
    let (_, kth, _) = values.select_nth_unstable_by(k, f32::total_cmp);
    Some(*kth)
}

/// Median of `values` (the upper one for an even count), reordering them. `None` when empty.
pub fn median(values: &mut [f32]) -> Option<f32> {
    if values.is_empty() {
        return None;
    }
    let k = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(k, f32::total_cmp);
    Some(*m)
}

/// Median of any values that widen to f64 (the upper one for an even count), compared as f64,
/// reordering them. NaN when empty.
pub fn median_f64<T: Copy + Into<f64>>(values: &mut [T]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mid = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(mid, |a, b| (*a).into().total_cmp(&(*b).into()));
    (*m).into()
}

/// `p`-th percentile (0–100) of `values` with linear interpolation between order statistics
/// (numpy's default), in f64, reordering them. `values` must not be empty.
pub fn percentile_linear(values: &mut [f32], p: f64) -> f64 {
    let n = values.len();
    let pos = p / 100.0 * (n - 1) as f64;
    let lo = (pos.floor() as usize).min(n - 1);
    let frac = pos - lo as f64;
    let (_, &mut v_lo, upper) = values.select_nth_unstable_by(lo, f32::total_cmp);
    let v_lo = f64::from(v_lo);
    if frac == 0.0 || upper.is_empty() {
        return v_lo;
    }
    let v_hi = f64::from(upper.iter().copied().fold(f32::INFINITY, f32::min));
    v_lo + frac * (v_hi - v_lo)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values with duplicates, both zeros, infinities and NaN, in a scrambled order.
    fn awkward(n: usize) -> Vec<f32> {
        (0..n)
            .map(|i| match (i * 7919) % 23 {
                0 => f32::NAN,
                1 => f32::INFINITY,
                2 => f32::NEG_INFINITY,
                3 => -0.0,
                4 => 0.0,
                5 => 1.5,
                k => ((i * 104_729) % 1000) as f32 * 0.013 - 4.0 + k as f32,
            })
            .collect()
    }

    // The implementations this module replaced, verbatim: what the callers got before.
    fn old_exposure_percentile(values: impl Iterator<Item = f32>, p: f64) -> Option<f32> {
        let mut v: Vec<f32> = values.filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return None;
        }
        let k = (((p / 100.0) * (v.len() - 1) as f64).round() as usize).min(v.len() - 1);
        let (_, kth, _) = v.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
        Some(*kth)
    }
    fn old_kernels_quantile(values: &[f32], q: f64) -> f32 {
        let mut v: Vec<f32> = values.iter().copied().filter(|v| v.is_finite()).collect();
        if v.is_empty() {
            return 0.0;
        }
        let i = ((v.len() - 1) as f64 * q).round() as usize;
        let (_, x, _) = v.select_nth_unstable_by(i, f32::total_cmp);
        *x
    }
    fn old_mesopic_median(v: &mut [f32]) -> Option<f32> {
        if v.is_empty() {
            return None;
        }
        let k = v.len() / 2;
        let (_, m, _) = v.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
        Some(*m)
    }
    fn old_mesopic_noise_quantile(abs: &mut [f32], q: f64) -> f32 {
        let k = ((abs.len() as f64 * q) as usize).min(abs.len() - 1);
        let (_, q, _) = abs.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
        *q
    }

    fn bits(v: Option<f32>) -> Option<u32> {
        v.map(f32::to_bits)
    }

    #[test]
    fn nearest_rank_quantiles_match_the_code_they_replaced_bit_for_bit() {
        for n in [0usize, 1, 2, 3, 10, 57, 400] {
            let v = awkward(n);
            for p in [0.0, 1.0, 12.5, 30.0, 50.0, 99.0, 99.5, 100.0] {
                assert_eq!(
                    bits(percentile(v.iter().copied(), p)),
                    bits(old_exposure_percentile(v.iter().copied(), p)),
                    "n {n} p {p}"
                );
            }
            for q in [0.0, 0.01, 0.3, 0.5, 0.99, 1.0] {
                assert_eq!(
                    quantile(v.iter().copied(), q).unwrap_or(0.0).to_bits(),
                    old_kernels_quantile(&v, q).to_bits(),
                    "n {n} q {q}"
                );
            }
        }
        assert_eq!(percentile([f32::NAN].into_iter(), 50.0), None);
    }

    #[test]
    fn medians_and_floor_ranks_match_the_code_they_replaced_bit_for_bit() {
        for n in [0usize, 1, 2, 3, 10, 57, 400] {
            let v: Vec<f32> = awkward(n).into_iter().filter(|x| !x.is_nan()).collect();
            assert_eq!(
                bits(median(&mut v.clone())),
                bits(old_mesopic_median(&mut v.clone())),
                "n {n}"
            );
            let expected = if v.is_empty() {
                f64::NAN
            } else {
                f64::from(old_mesopic_median(&mut v.clone()).unwrap())
            };
            let got = median_f64(&mut v.clone());
            assert!(
                got.to_bits() == expected.to_bits(),
                "n {n}: {got} {expected}"
            );
            if !v.is_empty() {
                for q in [0.0, 0.3, 0.5, 0.999, 1.0] {
                    assert_eq!(
                        bits(select_floor_rank(&mut v.clone(), q)),
                        bits(Some(old_mesopic_noise_quantile(&mut v.clone(), q))),
                        "n {n} q {q}"
                    );
                }
            }
        }
        assert_eq!(median_f64(&mut [3u32, 1, 2, 9]), 3.0);
        assert!(median_f64::<f32>(&mut []).is_nan());
        assert_eq!(select_floor_rank(&mut [], 0.5), None);
    }

    #[test]
    fn percentile_linear_matches_numpy() {
        // np.percentile([1, 2, 3, 4], 50) = 2.5; 99.5 -> 3.985; 100 -> 4.
        let v = vec![4.0f32, 1.0, 3.0, 2.0];
        assert!((percentile_linear(&mut v.clone(), 50.0) - 2.5).abs() < 1e-12);
        assert!((percentile_linear(&mut v.clone(), 99.5) - 3.985).abs() < 1e-6);
        assert_eq!(percentile_linear(&mut v.clone(), 100.0), 4.0);
        assert_eq!(percentile_linear(&mut [7.0f32], 30.0), 7.0);
    }
}
