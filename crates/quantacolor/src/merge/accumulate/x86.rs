//! The merge's AVX2 kernels, beside their portable references: the targets of eight sites at
//! once ([`TargetGrid::lane_targets`]) and the rows of the splat's targets and of the
//! regression compiled for AVX2. The safe entries take the [`Isa`] that allows them.

use super::regression::gather_row_generic;
use super::*;
use crate::cpu::Isa;

impl TargetGrid<'_> {
    /// [`TargetGrid::affine_row`] compiled for AVX2 (no fused multiply-add: the same bits).
    ///
    /// # Panics
    /// If `isa` lacks AVX2 ([`TargetGrid::fill_affine`] asks it first).
    pub(super) fn affine_row_avx2(
        &self,
        isa: Isa,
        y: usize,
        row: &mut [(u32, f32)],
        matrix: &[[f64; 2]; 2],
        offset: &[f64; 2],
        local: Option<(&[bool], &[f32])>,
    ) {
        assert!(isa.avx2(), "the AVX2 targets need an AVX2 instruction set");
        // SAFETY: an `Isa` with AVX2 exists only on a CPU that supports it.
        unsafe { self.affine_row_avx2_unchecked(isa, y, row, matrix, offset, local) }
    }

    /// [`TargetGrid::affine_row_avx2`] without the check.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    unsafe fn affine_row_avx2_unchecked(
        &self,
        isa: Isa,
        y: usize,
        row: &mut [(u32, f32)],
        matrix: &[[f64; 2]; 2],
        offset: &[f64; 2],
        local: Option<(&[bool], &[f32])>,
    ) {
        self.affine_row(isa, y, row, matrix, offset, local)
    }

    /// [`TargetGrid::lane_targets_avx2`] where `isa` has AVX2 and the robustness map (if any)
    /// covers the H×W image; `None` otherwise (then the portable [`TargetGrid::lane_targets`]
    /// make them, and a shorter map takes their checked reads and their panic).
    #[inline(always)]
    pub(super) fn lane_targets_x86(
        &self,
        isa: Isa,
        rounded: &[[f32; LANES]; 2],
        bin: &[[f32; LANES]; 2],
        skip: &[bool; LANES],
    ) -> Option<[(u32, f32); LANES]> {
        if isa.avx2() && self.robust.is_none_or(|m| m.len() >= self.h * self.w) {
            // SAFETY: an `Isa` with AVX2 exists only on a CPU that supports it; the map holds
            // the H·W pixels (checked just above).
            Some(unsafe { self.lane_targets_avx2(rounded, bin, skip) })
        } else {
            None
        }
    }

    /// [`TargetGrid::lane_targets`] with AVX2 instructions, the robustness (if any) read
    /// from `self.robust`: the same operations lane by lane, so the same targets. The
    /// clamped truncations of [`index_in`] are `max` with 0 second (NaN gives 0, as there),
    /// `min` with the bound and a truncating conversion; the comparisons are ordered (false
    /// for NaN, as Rust's); the index arithmetic wraps as there; the robustness is one
    /// gather; the kept lanes are selected with blends and the (bin, weight) pairs
    /// interleaved in registers and written with two full-width stores (no single-lane
    /// stores that a wide read of the result would wait for).
    ///
    /// # Safety
    /// The CPU must support AVX2, and `self.robust`, if any, must hold at least H·W values
    /// (every index read is a clamped pixel of the H×W image).
    #[target_feature(enable = "avx2")]
    unsafe fn lane_targets_avx2(
        &self,
        rounded: &[[f32; LANES]; 2],
        bin: &[[f32; LANES]; 2],
        skip: &[bool; LANES],
    ) -> [(u32, f32); LANES] {
        use std::arch::x86_64::*;
        let (hf, wf) = ((self.h - 1) as f32, (self.w - 1) as f32);
        let (bins_h, bins_w) = (self.bins_h as f32, self.bins_w as f32);
        let row_floats = (SUMS * self.stride) as i32;
        let zero = _mm256_setzero_ps();
        // `index_in` lane-wise: max(v, 0) returns its second operand 0 for NaN.
        let index = |v: __m256, hi: f32| {
            _mm256_cvttps_epi32(_mm256_min_ps(_mm256_max_ps(v, zero), _mm256_set1_ps(hi)))
        };
        // SAFETY: `rounded` and `bin` are arrays of eight f32 each (unaligned loads).
        let (ry, rx, by, bx) = unsafe {
            (
                _mm256_loadu_ps(rounded[0].as_ptr()),
                _mm256_loadu_ps(rounded[1].as_ptr()),
                _mm256_loadu_ps(bin[0].as_ptr()),
                _mm256_loadu_ps(bin[1].as_ptr()),
            )
        };
        let outside = _mm256_or_ps(
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_LT_OQ>(by, zero),
                _mm256_cmp_ps::<_CMP_LT_OQ>(bx, zero),
            ),
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_GE_OQ>(by, _mm256_set1_ps(bins_h)),
                _mm256_cmp_ps::<_CMP_GE_OQ>(bx, _mm256_set1_ps(bins_w)),
            ),
        );
        let target = _mm256_add_epi32(
            _mm256_mullo_epi32(index(by, bins_h), _mm256_set1_epi32(row_floats)),
            index(bx, bins_w),
        );
        let r = match self.robust {
            Some(m) => {
                let at = _mm256_add_epi32(
                    _mm256_mullo_epi32(index(ry, hf), _mm256_set1_epi32(self.w as i32)),
                    index(rx, wf),
                );
                // SAFETY: every lane of `at` is ry·W + rx with ry ≤ H − 1 and rx ≤ W − 1
                // (clamped above), below H·W ≤ m.len() (the caller's contract).
                unsafe { _mm256_i32gather_ps::<4>(m.as_ptr(), at) }
            }
            None => _mm256_set1_ps(1.0),
        };
        // The skipped lanes: bools are 0 or 1, widened to 32-bit lanes.
        let skipped = {
            let bytes = u64::from_le_bytes(std::array::from_fn(|i| skip[i] as u8));
            let wide = _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(bytes as i64));
            _mm256_castsi256_ps(_mm256_cmpgt_epi32(wide, _mm256_setzero_si256()))
        };
        let drop = _mm256_or_ps(
            _mm256_or_ps(outside, skipped),
            _mm256_cmp_ps::<_CMP_LE_OQ>(r, zero),
        );
        let bins = _mm256_blendv_ps(
            _mm256_castsi256_ps(target),
            _mm256_castsi256_ps(_mm256_set1_epi32(-1)),
            drop,
        );
        let weights = _mm256_blendv_ps(r, zero, drop);
        // (bin, weight) pairs in lane order: lanes 0, 1, 4, 5 and 2, 3, 6, 7, then halves.
        let (lo, hi) = (
            _mm256_unpacklo_ps(bins, weights),
            _mm256_unpackhi_ps(bins, weights),
        );
        // A tuple's layout is not guaranteed: the stores below need this one.
        const _: () = assert!(
            std::mem::size_of::<(u32, f32)>() == 8
                && std::mem::offset_of!((u32, f32), 0) == 0
                && std::mem::offset_of!((u32, f32), 1) == 4
        );
        let mut out = [(u32::MAX, 0.0f32); LANES];
        let at = out.as_mut_ptr() as *mut f32;
        // SAFETY: `out` is 64 bytes of eight (u32, f32) pairs, the u32 at offset 0 and the
        // f32 at offset 4 of each (asserted above); two unaligned 32-byte stores fill it.
        unsafe {
            _mm256_storeu_ps(at, _mm256_permute2f128_ps::<0x20>(lo, hi));
            _mm256_storeu_ps(at.add(LANES), _mm256_permute2f128_ps::<0x31>(lo, hi));
        }
        out
    }
}

/// [`gather_row_generic`] compiled for AVX2 (its eight-lane loops become vector instructions):
/// the same operations in the same order (no fused multiply-add), so the same result.
///
/// # Panics
/// If `isa` lacks AVX2 ([`gather_row`] asks it first).
pub(super) fn gather_row_avx2(isa: Isa, g: &Gather, oy: usize, row: &mut [[f32; SUMS]]) {
    assert!(
        isa.avx2(),
        "the AVX2 regression needs an AVX2 instruction set"
    );
    // SAFETY: an `Isa` with AVX2 exists only on a CPU that supports it.
    unsafe { gather_row_avx2_unchecked(g, oy, row) }
}

/// [`gather_row_avx2`] without the check.
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2")]
unsafe fn gather_row_avx2_unchecked(g: &Gather, oy: usize, row: &mut [[f32; SUMS]]) {
    gather_row_generic(g, oy, row)
}
