//! AVX2 kernels of the sub-block fit, beside their portable references in fit.rs: the same
//! operations in the same order (no fused multiply-add), so bit-identical results.

use super::affine::AffineMotion;
use super::bins::{BinLayout, RunGroups, GROUP_LANES};
use super::fit::{fit_sub_block_generic, run_frame, FitSettings, Information};
use super::template::{group_lanes_fit, TemplateLevel};

/// All ones in the lanes where 0 ≤ y and 0 ≤ x and y `UPPER` `y_end` and x `UPPER` `x_end`
/// (`UPPER` a comparison predicate: `_CMP_LE_OQ` for a template sample, `_CMP_LT_OQ` for a
/// bilinear splat); NaN lanes are outside.
///
/// # Safety
/// The CPU must support AVX.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
#[inline]
pub(in crate::align) unsafe fn inside_avx2<const UPPER: i32>(
    y: std::arch::x86_64::__m256,
    x: std::arch::x86_64::__m256,
    y_end: std::arch::x86_64::__m256,
    x_end: std::arch::x86_64::__m256,
) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    let zero = _mm256_setzero_ps();
    _mm256_and_ps(
        _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_GE_OQ>(y, zero),
            _mm256_cmp_ps::<_CMP_GE_OQ>(x, zero),
        ),
        _mm256_and_ps(
            _mm256_cmp_ps::<UPPER>(y, y_end),
            _mm256_cmp_ps::<UPPER>(x, x_end),
        ),
    )
}

/// [`fit_sub_block_generic`](super::fit::fit_sub_block_generic) compiled for AVX2, with the per-run
/// sums of [`run_sums_group_avx2`]: the same operations in the same order (no fused multiply-add),
/// so the same result.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn fit_sub_block_avx2(
    counts: &[u32],
    frames: usize,
    layouts: &[BinLayout],
    templates: &[&TemplateLevel],
    start: AffineMotion,
    centre: [f64; 2],
    settings: FitSettings,
) -> Option<(AffineMotion, Information)> {
    fit_sub_block_generic(
        counts, frames, layouts, templates, start, centre, settings, true,
    )
}

/// [`run_sums`](super::fit::run_sums) of every run of `groups`, [`GROUP_LANES`] runs at a time in
/// the f32 lanes of AVX2 registers (`observed` and `trials` laid out as the groups' slots,
/// [`RunGroups::observations`]); run r's sums go to `out[r]`. Every lane does the scalar operations
/// of its own run's bins in order (no fused multiply-add, the same rounding), and a bin outside the
/// template (or a padding slot) adds weight zero, so ±0 terms: a sum that starts at +0 is never −0,
/// so adding ±0 leaves it unchanged, as skipping the bin does. The sums are bit-identical to
/// [`run_sums`](super::fit::run_sums) (checked by a test). The template must pass
/// [`group_lanes_fit`].
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(clippy::too_many_arguments)]
pub(super) unsafe fn run_sums_group_avx2(
    template: &TemplateLevel,
    motion: &AffineMotion,
    centre: [f64; 2],
    groups: &RunGroups,
    observed: &[[f32; GROUP_LANES]],
    trials: &[[f32; GROUP_LANES]],
    group_step: usize,
    out: &mut [[f64; 13]],
) {
    use std::arch::x86_64::*;
    let (h, w) = (template.height, template.width);
    // The lane arithmetic indexes pixels in i32.
    assert!(group_lanes_fit(template), "template of {h}x{w} pixels");
    assert!(observed.len() == groups.bin.len() && trials.len() == groups.bin.len());
    let samples = template.samples.as_ptr() as *const f32;
    let (_, [m_yx, m_xx, centre_x]) = run_frame(motion, centre, 0.0);
    let (m_yx, m_xx, centre_x) = (
        _mm256_set1_ps(m_yx),
        _mm256_set1_ps(m_xx),
        _mm256_set1_ps(centre_x),
    );
    let zero = _mm256_setzero_ps();
    let (y_max, x_max) = (
        _mm256_set1_ps((h - 1) as f32),
        _mm256_set1_ps((w - 1) as f32),
    );
    let (y_last, x_last) = (
        _mm256_set1_epi32((h - 2) as i32),
        _mm256_set1_epi32((w - 2) as i32),
    );
    let width = _mm256_set1_epi32(w as i32);
    let one = _mm256_set1_ps(1.0);
    let (floor, nine, three) = (
        _mm256_set1_ps(0.01),
        _mm256_set1_ps(9.0),
        _mm256_set1_ps(3.0),
    );
    let sign = _mm256_set1_ps(-0.0);
    // Lanes k and k + 4 of a vector, each repeated over one half of a register.
    let pair_lanes = [
        _mm256_setr_epi32(0, 0, 0, 0, 4, 4, 4, 4),
        _mm256_setr_epi32(1, 1, 1, 1, 5, 5, 5, 5),
        _mm256_setr_epi32(2, 2, 2, 2, 6, 6, 6, 6),
        _mm256_setr_epi32(3, 3, 3, 3, 7, 7, 7, 7),
    ];
    let row_stride = 4 * w;
    for (g, members) in groups.runs.iter().enumerate().step_by(group_step.max(1)) {
        let frames = groups.row[g].map(|r| run_frame(motion, centre, r).0);
        let row_y = _mm256_loadu_ps(frames.map(|f| f[0]).as_ptr());
        let base_y = _mm256_loadu_ps(frames.map(|f| f[1]).as_ptr());
        let base_x = _mm256_loadu_ps(frames.map(|f| f[2]).as_ptr());
        let mut acc = [zero; 13];
        for s in groups.slot_start[g]..groups.slot_start[g + 1] {
            let x = _mm256_loadu_ps(groups.x.get_unchecked(s).as_ptr());
            let x2 = _mm256_loadu_ps(groups.x2.get_unchecked(s).as_ptr());
            let observed = _mm256_loadu_ps(observed.get_unchecked(s).as_ptr());
            let trials = _mm256_loadu_ps(trials.get_unchecked(s).as_ptr());
            let py = _mm256_add_ps(row_y, _mm256_add_ps(base_y, _mm256_mul_ps(m_yx, x)));
            let px = _mm256_add_ps(
                _mm256_add_ps(x, centre_x),
                _mm256_add_ps(base_x, _mm256_mul_ps(m_xx, x)),
            );
            // Inside the template's interior (as `run_sums`; NaN is outside).
            let inside = inside_avx2::<_CMP_LE_OQ>(py, px, y_max, x_max);
            let all_inside = _mm256_movemask_ps(inside) == 0xFF;
            // Lanes outside sample pixel (0, 0) and get weight zero below.
            let (py, px) = if all_inside {
                (py, px)
            } else {
                (_mm256_and_ps(py, inside), _mm256_and_ps(px, inside))
            };
            let y0 = _mm256_min_epi32(_mm256_cvttps_epi32(py), y_last);
            let x0 = _mm256_min_epi32(_mm256_cvttps_epi32(px), x_last);
            let fy = _mm256_sub_ps(py, _mm256_cvtepi32_ps(y0));
            let fx = _mm256_sub_ps(px, _mm256_cvtepi32_ps(x0));
            let mut index = [0i32; GROUP_LANES];
            _mm256_storeu_si256(
                index.as_mut_ptr() as *mut __m256i,
                _mm256_add_epi32(_mm256_mullo_epi32(y0, width), x0),
            );
            // (value, ∂y, ∂x, 0) of lanes k (low half) and k + 4 (high half): each corner pixel
            // of the two lanes in one register.
            let pair = |k: usize| {
                let pa = samples.add(4 * *index.get_unchecked(k) as usize);
                let pb = samples.add(4 * *index.get_unchecked(k + 4) as usize);
                let both = |offset: usize| {
                    _mm256_insertf128_ps::<1>(
                        _mm256_castps128_ps256(_mm_loadu_ps(pa.add(offset))),
                        _mm_loadu_ps(pb.add(offset)),
                    )
                };
                let (a, b) = (both(0), both(4));
                let (c, d) = (both(row_stride), both(row_stride + 4));
                let fxl = _mm256_permutevar8x32_ps(fx, pair_lanes[k]);
                let fyl = _mm256_permutevar8x32_ps(fy, pair_lanes[k]);
                let (gxl, gyl) = (_mm256_sub_ps(one, fxl), _mm256_sub_ps(one, fyl));
                let top = _mm256_add_ps(_mm256_mul_ps(a, gxl), _mm256_mul_ps(b, fxl));
                let bottom = _mm256_add_ps(_mm256_mul_ps(c, gxl), _mm256_mul_ps(d, fxl));
                _mm256_add_ps(_mm256_mul_ps(top, gyl), _mm256_mul_ps(bottom, fyl))
            };
            let (s0, s1, s2, s3) = (pair(0), pair(1), pair(2), pair(3));
            // Transposed to value, ∂y and ∂x across the lanes, in lane order.
            let (low01, low23) = (_mm256_unpacklo_ps(s0, s1), _mm256_unpacklo_ps(s2, s3));
            let (high01, high23) = (_mm256_unpackhi_ps(s0, s1), _mm256_unpackhi_ps(s2, s3));
            let t = _mm256_shuffle_ps::<0x44>(low01, low23);
            let gy = _mm256_shuffle_ps::<0xEE>(low01, low23);
            let gx = _mm256_shuffle_ps::<0x44>(high01, high23);
            let residual = _mm256_sub_ps(observed, t);
            let inv_variance = _mm256_div_ps(
                trials,
                _mm256_max_ps(_mm256_mul_ps(t, _mm256_sub_ps(one, t)), floor),
            );
            let z2 = _mm256_mul_ps(_mm256_mul_ps(residual, residual), inv_variance);
            let far = _mm256_cmp_ps::<_CMP_GT_OQ>(z2, nine);
            let weight = if _mm256_movemask_ps(far) == 0 {
                inv_variance
            } else {
                let huber = _mm256_div_ps(
                    _mm256_mul_ps(three, _mm256_sqrt_ps(inv_variance)),
                    _mm256_andnot_ps(sign, residual),
                );
                _mm256_blendv_ps(inv_variance, huber, far)
            };
            let weight = if all_inside {
                weight
            } else {
                _mm256_and_ps(weight, inside)
            };
            let (wgy, wgx) = (_mm256_mul_ps(weight, gy), _mm256_mul_ps(weight, gx));
            let pairs = [
                _mm256_mul_ps(wgy, gy),
                _mm256_mul_ps(wgy, gx),
                _mm256_mul_ps(wgx, gx),
            ];
            for (k, &v) in pairs.iter().enumerate() {
                acc[k] = _mm256_add_ps(acc[k], v);
                acc[3 + k] = _mm256_add_ps(acc[3 + k], _mm256_mul_ps(v, x));
                acc[6 + k] = _mm256_add_ps(acc[6 + k], _mm256_mul_ps(v, x2));
            }
            let (ry, rx) = (_mm256_mul_ps(wgy, residual), _mm256_mul_ps(wgx, residual));
            acc[9] = _mm256_add_ps(acc[9], ry);
            acc[10] = _mm256_add_ps(acc[10], rx);
            acc[11] = _mm256_add_ps(acc[11], _mm256_mul_ps(ry, x));
            acc[12] = _mm256_add_ps(acc[12], _mm256_mul_ps(rx, x));
        }
        let mut lanes = [[0.0f32; GROUP_LANES]; 13];
        for (k, a) in acc.iter().enumerate() {
            _mm256_storeu_ps(lanes[k].as_mut_ptr(), *a);
        }
        for (lane, &r) in members.iter().enumerate() {
            if r != usize::MAX {
                out[r] = std::array::from_fn(|k| lanes[k][lane] as f64);
            }
        }
    }
}
