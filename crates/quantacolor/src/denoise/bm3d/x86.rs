//! The AVX2 kernels of BM3D, each beside the dispatch that chooses it over its portable
//! reference (in `transforms`, `grouping`, `filtering`): every kernel does the operations of
//! the reference in the same order (no fused multiply-add), so both give the same bits.
//!
//! The instruction set is a [`crate::cpu::Isa`] taken once at the entry and carried by
//! [`Transforms`]: [`matmul8`] and [`block_coeffs_row`] look at it, and [`process_row`] chooses
//! the AVX2 build of a row of reference blocks, in which the const generic `AVX2` is true and
//! the other dispatches here take their kernels. This file holds all of BM3D's `unsafe`.

#![allow(unsafe_code)]

use super::filtering::{hard_threshold, wiener_shrink};
#[cfg(target_arch = "x86_64")]
use super::filtering::{lane_total, SHRINK_LANES};
#[cfg(target_arch = "x86_64")]
use super::grouping::LOW_COEFFS;
use super::grouping::{distance_at_most, low_check, LowPlanes, LANES8};
use super::steps::process_row_generic;
use super::transforms::{matmul8_portable, BlockCoeffs};
use super::{aggregation::Strip, Geometry, Scratch, StepParams, Transforms};
use crate::cpu::Isa;

/// `out = a · b` for row-major 8 x 8 matrices, each row of `out` accumulated as
/// `0 + a[r][0]·b[0][·] + a[r][1]·b[1][·] + …` (the order of `axpy` in the general path),
/// through [`matmul8_avx2`] when `isa` has AVX2 (the same bits).
#[inline(always)]
pub(super) fn matmul8(isa: Isa, a: &[f32; 64], b: &[f32; 64], out: &mut [f32; 64]) {
    #[cfg(target_arch = "x86_64")]
    {
        if isa.avx2() {
            // SAFETY: an `Isa` with AVX2 exists only on a CPU that has it.
            unsafe { matmul8_avx2(a, b, out) };
            return;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = isa;
    matmul8_portable(a, b, out)
}

/// [`matmul8`] with every row of `out` one register: `a[r][i]` broadcast from memory times row
/// `i` of `b`, added in order of `i` to a sum that starts at +0 (a multiply, then an add, never
/// fused), which is what each lane of the portable loop does. Written out because the compiler
/// vectorised the portable loop's second product of a 2D transform (`a` the first product's
/// result) across rows, with a transpose's worth of shuffles per product; the transforms
/// also pass the first product through `black_box`, so that its elements are broadcast from
/// memory rather than shuffled out of registers.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn matmul8_avx2(a: &[f32; 64], b: &[f32; 64], out: &mut [f32; 64]) {
    use std::arch::x86_64::*;
    let rows: [__m256; 8] = std::array::from_fn(|i| _mm256_loadu_ps(b.as_ptr().add(8 * i)));
    for r in 0..8 {
        let mut sum = _mm256_setzero_ps();
        for (i, row) in rows.iter().enumerate() {
            let s = _mm256_broadcast_ss(&a[8 * r + i]);
            sum = _mm256_add_ps(sum, _mm256_mul_ps(s, *row));
        }
        _mm256_storeu_ps(out.as_mut_ptr().add(8 * r), sum);
    }
}

/// The 2D spectra of the blocks of position row `y` into `row` ([`BlockCoeffs::row`]), compiled
/// for AVX2 when `tr.isa` has it (no fused multiply-add: the same bits).
#[inline(always)]
pub(super) fn block_coeffs_row(
    plane: &[f32],
    y: usize,
    n: usize,
    w: usize,
    tr: &Transforms,
    row: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    {
        if tr.isa.avx2() {
            // SAFETY: an `Isa` with AVX2 exists only on a CPU that has it.
            return unsafe { block_coeffs_row_avx2(plane, y, n, w, tr, row) };
        }
    }
    BlockCoeffs::row(plane, y, n, w, tr, row)
}

/// [`BlockCoeffs::row`] compiled for AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn block_coeffs_row_avx2(
    plane: &[f32],
    y: usize,
    n: usize,
    w: usize,
    tr: &Transforms,
    row: &mut [f32],
) {
    BlockCoeffs::row(plane, y, n, w, tr, row)
}

/// Every reference block of row `yr` (`steps::process_reference`), in the AVX2 build where
/// `tr.isa` has AVX2 (the one choice of the instruction set for the grouping and filtering
/// kernels).
///
/// The AVX2 build of the same code is bit-identical: the kernels' sums are laid out lane by lane
/// in a fixed order (eight partial sums, rows of eight), wider registers only hold more lanes,
/// and no multiply-add is fused.
pub(super) fn process_row(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    yr: usize,
    s: &mut Scratch,
    strip: &mut Strip<'_>,
) {
    #[cfg(target_arch = "x86_64")]
    {
        if tr.isa.avx2() {
            // SAFETY: an `Isa` with AVX2 exists only on a CPU that has it.
            unsafe { process_row_avx2(p, geo, tr, yr, s, strip) };
            return;
        }
    }
    process_row_generic::<false>(p, geo, tr, yr, s, strip);
}

/// [`process_row_generic`] compiled for AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn process_row_avx2(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    yr: usize,
    s: &mut Scratch,
    strip: &mut Strip<'_>,
) {
    // `true`: this function is the AVX2 build, and its caller checked `isa.avx2()`.
    process_row_generic::<true>(p, geo, tr, yr, s, strip);
}

/// [`low_check`], through [`low_check_avx2`] when `AVX2`.
#[inline(always)]
pub(super) fn low_check_dispatch<const AVX2: bool>(
    low: &LowPlanes,
    reference: &[f32],
    y: usize,
    x: usize,
    bound: f32,
) -> (u32, [f32; LANES8]) {
    #[cfg(target_arch = "x86_64")]
    {
        if AVX2 {
            // SAFETY: `AVX2` is only true under `process_row_avx2`, which runs when `isa.avx2()`.
            return unsafe { low_check_avx2(low, reference, y, x, bound) };
        }
    }
    low_check(low, reference, y, x, bound)
}

/// [`low_check`] in AVX2 registers: the eight positions are the eight lanes of one register,
/// and every lane does the subtractions, products and sums of [`low_partial_distances`] in the
/// same order (no fused multiply-add), so the same bits; the first row's squares are kept for
/// the second row's sums, and each mask is one vector comparison (`≤`, false for NaN as the
/// portable `<=`). (The compiler did not vectorise the portable version well: it split the
/// lanes into 4 + 1 + 1 + 2.)
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn low_check_avx2(
    low: &LowPlanes,
    reference: &[f32],
    y: usize,
    x: usize,
    bound: f32,
) -> (u32, [f32; LANES8]) {
    use std::arch::x86_64::*;
    let stride = low.stride;
    let row = y * LOW_COEFFS * stride + x;
    // Every load below stays inside (`low.planes` is padded by eight lanes per row).
    assert!(
        reference.len() >= LOW_COEFFS
            && row + (LOW_COEFFS - 1) * stride + LANES8 <= low.planes.len()
    );
    let base = low.planes.as_ptr().add(row);
    let limit = _mm256_set1_ps(bound);
    let mut squares = [_mm256_setzero_ps(); 8];
    let mut first = _mm256_setzero_ps();
    for (j, square) in squares.iter_mut().enumerate() {
        let d0 = _mm256_sub_ps(
            _mm256_set1_ps(reference[j]),
            _mm256_loadu_ps(base.add(j * stride)),
        );
        *square = _mm256_mul_ps(d0, d0);
        first = if j == 0 {
            *square
        } else {
            _mm256_add_ps(first, *square)
        };
    }
    if _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(first, limit)) == 0 {
        return (0, [0.0; LANES8]);
    }
    let mut sum = _mm256_setzero_ps();
    for (j, &square) in squares.iter().enumerate() {
        let d1 = _mm256_sub_ps(
            _mm256_set1_ps(reference[j + 8]),
            _mm256_loadu_ps(base.add((j + 8) * stride)),
        );
        let acc = _mm256_add_ps(square, _mm256_mul_ps(d1, d1));
        sum = if j == 0 { acc } else { _mm256_add_ps(sum, acc) };
    }
    let mask = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(sum, limit)) as u32;
    let mut out = [0.0f32; LANES8];
    _mm256_storeu_ps(out.as_mut_ptr(), sum);
    (mask, out)
}

/// [`distance_at_most`], through [`distance_at_most_avx2`] when `AVX2` and the blocks are
/// 8 × 8.
#[inline(always)]
pub(super) fn distance_at_most_dispatch<const AVX2: bool>(
    a: &[f32],
    b: &[f32],
    limit: f32,
    two_rows: Option<f32>,
) -> Option<f32> {
    #[cfg(target_arch = "x86_64")]
    {
        if AVX2 {
            if let (Ok(a), Ok(b)) = (<&[f32; 64]>::try_from(a), <&[f32; 64]>::try_from(b)) {
                // SAFETY: `AVX2` is only true under `process_row_avx2`, which runs when
                // `isa.avx2()`.
                return unsafe { distance_at_most_avx2(a, b, limit, two_rows) };
            }
        }
    }
    distance_at_most(a, b, limit, two_rows)
}

/// [`distance_at_most`] of 8 × 8 blocks with its eight partial sums as the lanes of one AVX2
/// register: the same differences, squares and sums in the same order, and the lanes totalled
/// by the same in-order sum, so the same bits and the same early exits.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn distance_at_most_avx2(
    a: &[f32; 64],
    b: &[f32; 64],
    limit: f32,
    two_rows: Option<f32>,
) -> Option<f32> {
    use std::arch::x86_64::*;
    let total = |acc: __m256| {
        let mut lanes = [0.0f32; 8];
        _mm256_storeu_ps(lanes.as_mut_ptr(), acc);
        lanes.iter().sum::<f32>()
    };
    let mut acc = _mm256_setzero_ps();
    for chunk in 0..8 {
        let early = match chunk {
            2 => Some(two_rows.unwrap_or_else(|| total(acc))),
            4 => Some(total(acc)),
            _ => None,
        };
        if early.is_some_and(|e| e > limit) {
            return None;
        }
        let d = _mm256_sub_ps(
            _mm256_loadu_ps(a.as_ptr().add(chunk * 8)),
            _mm256_loadu_ps(b.as_ptr().add(chunk * 8)),
        );
        acc = _mm256_add_ps(acc, _mm256_mul_ps(d, d));
    }
    // `+ 0.0`: as in `distance_at_most`.
    let d = total(acc) + 0.0;
    (d <= limit).then_some(d)
}

/// [`hard_threshold`], through [`hard_threshold_avx2`] when `AVX2` and the rows are whole
/// lane chunks.
#[inline(always)]
pub(super) fn hard_threshold_dispatch<const AVX2: bool>(
    group: &mut [f32],
    profile: &[f32],
    threshold: f32,
) -> f32 {
    #[cfg(target_arch = "x86_64")]
    {
        let rem = profile.len() % SHRINK_LANES; // not is_multiple_of: rust-version is 1.80
        if AVX2 && rem == 0 {
            // SAFETY: `AVX2` is only true under `process_row_avx2`, which runs when `isa.avx2()`.
            return unsafe { hard_threshold_avx2(group, profile, threshold) };
        }
    }
    hard_threshold(group, profile, threshold)
}

/// [`hard_threshold`] for rows of whole lane chunks, lane `l` of [`SHRINK_LANES`] in lane `l`
/// of an AVX2 register: the same comparison, the same products added in the same order (a
/// zeroed coefficient adds `+0.0`, as in the portable version), so the same bits.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn hard_threshold_avx2(group: &mut [f32], profile: &[f32], threshold: f32) -> f32 {
    use std::arch::x86_64::*;
    let n2 = profile.len();
    let (rem, rows_rem) = (n2 % SHRINK_LANES, group.len() % n2.max(1)); // rust-version 1.80
    assert!(rem == 0 && rows_rem == 0);
    let t = _mm256_set1_ps(threshold);
    let abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
    let mut lanes = _mm256_setzero_ps();
    for row in group.chunks_exact_mut(n2) {
        for k in (0..n2).step_by(SHRINK_LANES) {
            let v = _mm256_loadu_ps(row.as_ptr().add(k));
            let q = _mm256_loadu_ps(profile.as_ptr().add(k));
            let keep = _mm256_cmp_ps::<_CMP_GT_OQ>(_mm256_and_ps(v, abs_mask), _mm256_mul_ps(t, q));
            _mm256_storeu_ps(row.as_mut_ptr().add(k), _mm256_and_ps(v, keep));
            lanes = _mm256_add_ps(lanes, _mm256_and_ps(_mm256_mul_ps(q, q), keep));
        }
    }
    let mut out = [0.0f32; SHRINK_LANES];
    _mm256_storeu_ps(out.as_mut_ptr(), lanes);
    lane_total(out)
}

/// [`wiener_shrink`], through [`wiener_shrink_avx2`] when `AVX2` and the rows are whole lane
/// chunks.
#[inline(always)]
pub(super) fn wiener_shrink_dispatch<const AVX2: bool>(
    group: &mut [f32],
    basic: &[f32],
    profile: &[f32],
    s2: f32,
) -> f32 {
    #[cfg(target_arch = "x86_64")]
    {
        let rem = profile.len() % SHRINK_LANES; // not is_multiple_of: rust-version is 1.80
        if AVX2 && rem == 0 {
            // SAFETY: `AVX2` is only true under `process_row_avx2`, which runs when `isa.avx2()`.
            return unsafe { wiener_shrink_avx2(group, basic, profile, s2) };
        }
    }
    wiener_shrink(group, basic, profile, s2)
}

/// [`wiener_shrink`] for rows of whole lane chunks in AVX2 registers: the same operations in
/// the same order per lane (IEEE division, no fused multiply-add), so the same bits.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn wiener_shrink_avx2(group: &mut [f32], basic: &[f32], profile: &[f32], s2: f32) -> f32 {
    use std::arch::x86_64::*;
    let n2 = profile.len();
    let (rem, rows_rem) = (n2 % SHRINK_LANES, group.len() % n2.max(1)); // rust-version 1.80
    assert!(rem == 0 && rows_rem == 0 && basic.len() >= group.len());
    let s2v = _mm256_set1_ps(s2);
    let mut lanes = _mm256_setzero_ps();
    for (r, row) in group.chunks_exact_mut(n2).enumerate() {
        let brow = basic.as_ptr().add(r * n2);
        for k in (0..n2).step_by(SHRINK_LANES) {
            let v = _mm256_loadu_ps(row.as_ptr().add(k));
            let b = _mm256_loadu_ps(brow.add(k));
            let q = _mm256_loadu_ps(profile.as_ptr().add(k));
            let b2 = _mm256_mul_ps(b, b);
            let q2 = _mm256_mul_ps(q, q);
            let wc = _mm256_div_ps(b2, _mm256_add_ps(b2, _mm256_mul_ps(s2v, q2)));
            _mm256_storeu_ps(row.as_mut_ptr().add(k), _mm256_mul_ps(v, wc));
            lanes = _mm256_add_ps(lanes, _mm256_mul_ps(_mm256_mul_ps(wc, wc), q2));
        }
    }
    let mut out = [0.0f32; SHRINK_LANES];
    _mm256_storeu_ps(out.as_mut_ptr(), lanes);
    lane_total(out)
}
