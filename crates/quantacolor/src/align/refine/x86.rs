//! AVX2 kernels of the sub-block fit, beside their portable references in fit.rs: the same
//! operations in the same order (no fused multiply-add), so bit-identical results.

use super::affine::AffineMotion;
use super::bins::GROUP_LANES;
use super::fit::{fit_sub_block_generic, run_frame, GroupedRuns, Information, SubBlockFit};
use super::template::group_lanes_fit;
use crate::cpu::Isa;
use std::arch::x86_64::*;

/// All ones in the lanes where 0 ≤ y and 0 ≤ x and y `UPPER` `y_end` and x `UPPER` `x_end`
/// (`UPPER` a comparison predicate: `_CMP_LE_OQ` for a template sample, `_CMP_LT_OQ` for a
/// bilinear splat); NaN lanes are outside.
///
/// # Safety
/// The CPU must support AVX.
#[target_feature(enable = "avx")]
#[inline]
pub(in crate::align) unsafe fn inside_avx2<const UPPER: i32>(
    y: __m256,
    x: __m256,
    y_end: __m256,
    x_end: __m256,
) -> __m256 {
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

/// [`fit_sub_block_generic`] compiled for AVX2, with the per-run sums of
/// [`run_sums_group_avx2`]: the same operations in the same order (no fused multiply-add), so
/// the same result. `fit.isa` must offer AVX2.
pub(super) fn fit_sub_block(
    fit: &SubBlockFit,
    start: AffineMotion,
) -> Option<(AffineMotion, Information)> {
    assert!(fit.isa.avx2(), "the AVX2 fit on {}", fit.isa.name());
    // SAFETY: an `Isa` offers AVX2 only on a CPU that supports it.
    unsafe { fit_sub_block_avx2(fit, start) }
}

/// [`fit_sub_block_generic`] compiled for AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2")]
unsafe fn fit_sub_block_avx2(
    fit: &SubBlockFit,
    start: AffineMotion,
) -> Option<(AffineMotion, Information)> {
    fit_sub_block_generic(fit, start)
}

/// [`run_sums_group_avx2`] where `isa` offers AVX2 (as it must).
#[inline(always)]
pub(super) fn run_sums_groups(
    isa: Isa,
    runs: &GroupedRuns,
    motion: &AffineMotion,
    centre: [f64; 2],
    group_step: usize,
    out: &mut [[f64; 13]],
) {
    assert!(isa.avx2(), "the AVX2 run sums on {}", isa.name());
    // SAFETY: an `Isa` offers AVX2 only on a CPU that supports it.
    unsafe { run_sums_group_avx2(runs, motion, centre, group_step, out) }
}

/// [`run_sums`](super::fit::run_sums) of every run of `runs.groups`, [`GROUP_LANES`] runs at a
/// time in the f32 lanes of AVX2 registers (observations laid out as the groups' slots,
/// [`RunGroups::observations`](super::bins::RunGroups::observations)), of every
/// `group_step`-th group; run r's sums go to `out[r]`. Every lane does the scalar operations of
/// its own run's bins in order (no fused multiply-add, the same rounding), and a bin outside
/// the template (or a padding slot) adds weight zero, so ±0 terms: a sum that starts at +0 is
/// never −0, so adding ±0 leaves it unchanged, as skipping the bin does. The sums are
/// bit-identical to [`run_sums`](super::fit::run_sums) (checked by a test). The template must
/// pass [`group_lanes_fit`].
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn run_sums_group_avx2(
    runs: &GroupedRuns,
    motion: &AffineMotion,
    centre: [f64; 2],
    group_step: usize,
    out: &mut [[f64; 13]],
) {
    let (template, groups) = (runs.template, runs.groups);
    let (observed, trials) = (&runs.slots.observed, &runs.slots.trials);
    let (h, w) = (template.height, template.width);
    // The lane arithmetic indexes pixels in i32.
    assert!(group_lanes_fit(template), "template of {h}x{w} pixels");
    assert!(observed.len() == groups.bin.len() && trials.len() == groups.bin.len());
    let kernel = SlotKernel::new(runs, motion, centre);
    for (g, members) in groups.runs.iter().enumerate().step_by(group_step.max(1)) {
        let frames = groups.row[g].map(|r| run_frame(motion, centre, r).0);
        let rows = RowLanes {
            row_y: _mm256_loadu_ps(frames.map(|f| f[0]).as_ptr()),
            base_y: _mm256_loadu_ps(frames.map(|f| f[1]).as_ptr()),
            base_x: _mm256_loadu_ps(frames.map(|f| f[2]).as_ptr()),
        };
        let mut acc = [_mm256_setzero_ps(); 13];
        for s in groups.slot_start[g]..groups.slot_start[g + 1] {
            let slot = SlotLanes {
                x: _mm256_loadu_ps(groups.x.get_unchecked(s).as_ptr()),
                x2: _mm256_loadu_ps(groups.x2.get_unchecked(s).as_ptr()),
                observed: _mm256_loadu_ps(observed.get_unchecked(s).as_ptr()),
                trials: _mm256_loadu_ps(trials.get_unchecked(s).as_ptr()),
            };
            kernel.add_slot(&rows, &slot, &mut acc);
        }
        store_run_sums(&acc, members, out);
    }
}

/// The parts of a group's sample positions that do not change along its runs, one run per lane
/// ([`run_frame`]).
struct RowLanes {
    row_y: __m256,
    base_y: __m256,
    base_x: __m256,
}

/// One slot of a group: the centroid column of every lane's bin and its square, and the bin's
/// observation.
struct SlotLanes {
    x: __m256,
    x2: __m256,
    observed: __m256,
    trials: __m256,
}

/// What [`run_sums_group_avx2`] holds fixed over its groups: the template's samples and size,
/// the motion's column parts, and constants, each in every lane.
struct SlotKernel {
    samples: *const f32,
    /// Floats per template row.
    row_stride: usize,
    m_yx: __m256,
    m_xx: __m256,
    centre_x: __m256,
    y_max: __m256,
    x_max: __m256,
    y_last: __m256i,
    x_last: __m256i,
    width: __m256i,
    one: __m256,
    floor: __m256,
    nine: __m256,
    three: __m256,
    sign: __m256,
    /// Lanes k and k + 4 of a vector, each repeated over one half of a register.
    pair_lanes: [__m256i; 4],
}

impl SlotKernel {
    /// The kernel of `runs.template` at `motion`.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn new(runs: &GroupedRuns, motion: &AffineMotion, centre: [f64; 2]) -> Self {
        let (h, w) = (runs.template.height, runs.template.width);
        let (_, [m_yx, m_xx, centre_x]) = run_frame(motion, centre, 0.0);
        SlotKernel {
            samples: runs.template.samples.as_ptr() as *const f32,
            row_stride: 4 * w,
            m_yx: _mm256_set1_ps(m_yx),
            m_xx: _mm256_set1_ps(m_xx),
            centre_x: _mm256_set1_ps(centre_x),
            y_max: _mm256_set1_ps((h - 1) as f32),
            x_max: _mm256_set1_ps((w - 1) as f32),
            y_last: _mm256_set1_epi32((h - 2) as i32),
            x_last: _mm256_set1_epi32((w - 2) as i32),
            width: _mm256_set1_epi32(w as i32),
            one: _mm256_set1_ps(1.0),
            floor: _mm256_set1_ps(0.01),
            nine: _mm256_set1_ps(9.0),
            three: _mm256_set1_ps(3.0),
            sign: _mm256_set1_ps(-0.0),
            pair_lanes: [
                _mm256_setr_epi32(0, 0, 0, 0, 4, 4, 4, 4),
                _mm256_setr_epi32(1, 1, 1, 1, 5, 5, 5, 5),
                _mm256_setr_epi32(2, 2, 2, 2, 6, 6, 6, 6),
                _mm256_setr_epi32(3, 3, 3, 3, 7, 7, 7, 7),
            ],
        }
    }

    /// Adds the terms of `slot`'s bins (runs at `rows`) to the 13 sums `acc` of
    /// [`run_sums`](super::fit::run_sums), lane by lane.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn add_slot(&self, rows: &RowLanes, slot: &SlotLanes, acc: &mut [__m256; 13]) {
        let x = slot.x;
        let py = _mm256_add_ps(
            rows.row_y,
            _mm256_add_ps(rows.base_y, _mm256_mul_ps(self.m_yx, x)),
        );
        let px = _mm256_add_ps(
            _mm256_add_ps(x, self.centre_x),
            _mm256_add_ps(rows.base_x, _mm256_mul_ps(self.m_xx, x)),
        );
        // Inside the template's interior (as `run_sums`; NaN is outside).
        let inside = inside_avx2::<_CMP_LE_OQ>(py, px, self.y_max, self.x_max);
        let all_inside = _mm256_movemask_ps(inside) == 0xFF;
        // Lanes outside sample pixel (0, 0) and get weight zero below.
        let (py, px) = if all_inside {
            (py, px)
        } else {
            (_mm256_and_ps(py, inside), _mm256_and_ps(px, inside))
        };
        let [t, gy, gx] = self.sample(py, px);
        let residual = _mm256_sub_ps(slot.observed, t);
        let weight = self.weight(residual, slot.trials, t);
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
            acc[6 + k] = _mm256_add_ps(acc[6 + k], _mm256_mul_ps(v, slot.x2));
        }
        let (ry, rx) = (_mm256_mul_ps(wgy, residual), _mm256_mul_ps(wgx, residual));
        acc[9] = _mm256_add_ps(acc[9], ry);
        acc[10] = _mm256_add_ps(acc[10], rx);
        acc[11] = _mm256_add_ps(acc[11], _mm256_mul_ps(ry, x));
        acc[12] = _mm256_add_ps(acc[12], _mm256_mul_ps(rx, x));
    }

    /// The template's bilinear value, ∂/∂y and ∂/∂x at (`py`, `px`) of every lane (inside the
    /// template, as [`inside_avx2`] finds it).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn sample(&self, py: __m256, px: __m256) -> [__m256; 3] {
        let y0 = _mm256_min_epi32(_mm256_cvttps_epi32(py), self.y_last);
        let x0 = _mm256_min_epi32(_mm256_cvttps_epi32(px), self.x_last);
        let fy = _mm256_sub_ps(py, _mm256_cvtepi32_ps(y0));
        let fx = _mm256_sub_ps(px, _mm256_cvtepi32_ps(x0));
        let mut index = [0i32; GROUP_LANES];
        _mm256_storeu_si256(
            index.as_mut_ptr() as *mut __m256i,
            _mm256_add_epi32(_mm256_mullo_epi32(y0, self.width), x0),
        );
        let (s0, s1, s2, s3) = (
            self.pair(&index, 0, fx, fy),
            self.pair(&index, 1, fx, fy),
            self.pair(&index, 2, fx, fy),
            self.pair(&index, 3, fx, fy),
        );
        // Transposed to value, ∂y and ∂x across the lanes, in lane order.
        let (low01, low23) = (_mm256_unpacklo_ps(s0, s1), _mm256_unpacklo_ps(s2, s3));
        let (high01, high23) = (_mm256_unpackhi_ps(s0, s1), _mm256_unpackhi_ps(s2, s3));
        [
            _mm256_shuffle_ps::<0x44>(low01, low23),
            _mm256_shuffle_ps::<0xEE>(low01, low23),
            _mm256_shuffle_ps::<0x44>(high01, high23),
        ]
    }

    /// (value, ∂y, ∂x, 0) of lanes k (low half) and k + 4 (high half), interpolated at
    /// fractions `fx`, `fy` from the pixels at `index` and their neighbours: each corner pixel
    /// of the two lanes in one register.
    ///
    /// # Safety
    /// The CPU must support AVX2; `index` must hold pixels of the template's interior.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn pair(&self, index: &[i32; GROUP_LANES], k: usize, fx: __m256, fy: __m256) -> __m256 {
        let pa = self.samples.add(4 * *index.get_unchecked(k) as usize);
        let pb = self.samples.add(4 * *index.get_unchecked(k + 4) as usize);
        let both = |offset: usize| {
            _mm256_insertf128_ps::<1>(
                _mm256_castps128_ps256(_mm_loadu_ps(pa.add(offset))),
                _mm_loadu_ps(pb.add(offset)),
            )
        };
        let (a, b) = (both(0), both(4));
        let (c, d) = (both(self.row_stride), both(self.row_stride + 4));
        let fxl = _mm256_permutevar8x32_ps(fx, self.pair_lanes[k]);
        let fyl = _mm256_permutevar8x32_ps(fy, self.pair_lanes[k]);
        let (gxl, gyl) = (_mm256_sub_ps(self.one, fxl), _mm256_sub_ps(self.one, fyl));
        let top = _mm256_add_ps(_mm256_mul_ps(a, gxl), _mm256_mul_ps(b, fxl));
        let bottom = _mm256_add_ps(_mm256_mul_ps(c, gxl), _mm256_mul_ps(d, fxl));
        _mm256_add_ps(_mm256_mul_ps(top, gyl), _mm256_mul_ps(bottom, fyl))
    }

    /// The fit's weight of every lane: the inverse binomial variance of the bin mean, times
    /// the Huber factor 3/z past 3 std (as [`run_sums`](super::fit::run_sums)).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn weight(&self, residual: __m256, trials: __m256, t: __m256) -> __m256 {
        let inv_variance = _mm256_div_ps(
            trials,
            _mm256_max_ps(_mm256_mul_ps(t, _mm256_sub_ps(self.one, t)), self.floor),
        );
        let z2 = _mm256_mul_ps(_mm256_mul_ps(residual, residual), inv_variance);
        let far = _mm256_cmp_ps::<_CMP_GT_OQ>(z2, self.nine);
        if _mm256_movemask_ps(far) == 0 {
            inv_variance
        } else {
            let huber = _mm256_div_ps(
                _mm256_mul_ps(self.three, _mm256_sqrt_ps(inv_variance)),
                _mm256_andnot_ps(self.sign, residual),
            );
            _mm256_blendv_ps(inv_variance, huber, far)
        }
    }
}

/// The 13 sums `acc` of the runs `members` (one per lane, `usize::MAX`: none) to `out`, in
/// double precision.
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn store_run_sums(
    acc: &[__m256; 13],
    members: &[usize; GROUP_LANES],
    out: &mut [[f64; 13]],
) {
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
