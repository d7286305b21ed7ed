//! Branch-free elementary functions for hot loops that the compiler vectorises: the same
//! operations in the same order whatever the instruction set (no fused multiply-add, no table,
//! no libm call), so a loop over 8 lanes gives the same bits compiled for AVX2 as for plain
//! x86-64 or another architecture.
//!
//! Not from the paper: a numerical tool of this project (the kernel regression of
//! [`crate::merge::MergeAccumulator`] evaluates one Gaussian weight per phase bin).
#![forbid(unsafe_code)]

/// ln 2 split into a part with few mantissa bits (exact in products with small integers) and
/// the rest (Cody–Waite reduction, as in Cephes `expf`).
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// 1.5·2²³: adding it rounds an f32 of magnitude below 2²² to the nearest integer (ties to
/// even), which then sits in the low mantissa bits.
const ROUND_MAGIC: f32 = 12_582_912.0;

/// e^x with a relative error below 2·10⁻⁷ (about 2 ulp) for x in [−87, 88]; inputs outside are
/// clamped there (so e^x of a large negative x is about 1.6·10⁻³⁸ instead of 0); NaN gives NaN.
/// Cephes `expf`: x = n·ln 2 + r with |r| ≤ ½ ln 2, e^r by its degree-7 minimax polynomial,
/// 2ⁿ by writing the exponent bits.
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    let x = x.clamp(-87.0, 88.0);
    // n = round(x / ln 2) and its bits, without a float-to-int conversion.
    let t = x * std::f32::consts::LOG2_E + ROUND_MAGIC;
    let n = t - ROUND_MAGIC;
    let n_int = t.to_bits().wrapping_sub(ROUND_MAGIC.to_bits()) as i32;
    let r = x - n * LN2_HI - n * LN2_LO;
    let mut p = 1.987_569_1e-4;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 0.166_666_65;
    p = p * r + 0.5;
    let er = p * (r * r) + r + 1.0;
    er * f32::from_bits((n_int.wrapping_add(127) as u32) << 23)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rel_err(x: f32) -> f64 {
        let want = (x as f64).exp();
        ((exp(x) as f64 - want) / want).abs()
    }

    #[test]
    fn exp_matches_the_exact_exponential_over_the_kernel_range() {
        // The merge evaluates e^(−q/2) for q in [0, cutoff) (cutoff 9 by default): x in
        // (−4.5, 0], densely, then the rest of the unclamped negative range.
        let mut worst = 0.0f64;
        for i in 0..=1_000_000 {
            let x = -4.5 * i as f32 / 1_000_000.0;
            worst = worst.max(rel_err(x));
        }
        for i in 0..=1_000_000 {
            let x = -87.0 * i as f32 / 1_000_000.0;
            worst = worst.max(rel_err(x));
        }
        assert!(worst < 2e-7, "worst relative error {worst}");
        assert_eq!(exp(0.0), 1.0);
    }

    #[test]
    fn exp_is_close_to_libm_over_its_whole_range() {
        let mut worst = 0.0f64;
        for i in -870_000..=880_000 {
            let x = i as f32 * 1e-4;
            worst = worst.max(rel_err(x));
            let libm = x.exp();
            assert!(((exp(x) - libm) / libm).abs() < 3e-7, "{x}");
        }
        assert!(worst < 2e-7, "worst relative error {worst}");
    }

    #[test]
    fn exp_clamps_out_of_range_inputs() {
        assert!(exp(-1000.0) > 0.0 && exp(-1000.0) < 1e-37);
        assert!(exp(1000.0).is_finite() && exp(1000.0) > 1e38);
        assert!(exp(f32::NAN).is_nan());
        assert!(exp(f32::NEG_INFINITY) < 1e-37);
    }
}
