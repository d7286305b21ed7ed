//! CPU hints shared by the hot kernels (this project's own engineering, not a paper stage).

/// Asks the CPU to bring every 64-byte cache line of `items` into cache. A hint only: no value
/// depends on it. Used where the next reads lie at strides the hardware prefetchers do not follow
/// (frame-major hot-pixel draws, BM3D candidate blocks).
#[inline(always)]
pub fn prefetch<T>(items: &[T]) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let line = (64 / std::mem::size_of::<T>().max(1)).max(1);
        for chunk in items.chunks(line) {
            // SAFETY: SSE is part of x86_64; prefetching a valid address reads nothing and
            // cannot fault.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(chunk.as_ptr().cast::<i8>()) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = items;
}

/// The 8x8 transpose of 32-bit words: lane l of output k is lane k of input l (shuffles only:
/// the words, f32 bits included, move unchanged). Used by the ChaCha draws of hot-pixel
/// correction and the transposed tile costs of patch alignment.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub unsafe fn transpose8x8(r: &[std::arch::x86_64::__m256i; 8]) -> [std::arch::x86_64::__m256i; 8] {
    use std::arch::x86_64::*;
    // Pairs of rows interleaved by word, then by word pair; 128-bit halves then swapped.
    let t: [__m256i; 8] = std::array::from_fn(|i| {
        let (a, b) = (r[i / 2 * 2], r[i / 2 * 2 + 1]);
        if i % 2 == 0 {
            _mm256_unpacklo_epi32(a, b)
        } else {
            _mm256_unpackhi_epi32(a, b)
        }
    });
    // u[k] (k < 4): words k and k + 4 of rows 0..4; u[4 + k]: of rows 4..8.
    let u: [__m256i; 8] = std::array::from_fn(|i| {
        let (base, k) = (i / 4 * 4, i % 4);
        let (a, b) = (t[base + k / 2], t[base + 2 + k / 2]);
        if k % 2 == 0 {
            _mm256_unpacklo_epi64(a, b)
        } else {
            _mm256_unpackhi_epi64(a, b)
        }
    });
    std::array::from_fn(|k| {
        if k < 4 {
            _mm256_permute2x128_si256::<0x20>(u[k], u[4 + k])
        } else {
            _mm256_permute2x128_si256::<0x31>(u[k - 4], u[k])
        }
    })
}

/// A vector of `len` default values (zeros for numbers) written by all threads at once: the
/// zeroing, and the first touch of fresh pages (their faults), shared between the cores
/// instead of taken by the calling thread alone (`vec![0.0; len]` of a large buffer, e.g. the
/// merge's 26 MB of phase bins, is one thread's memset). The same values as `vec!`.
pub fn zeroed_par<T: Default + Clone + Send + Sync>(len: usize) -> Vec<T> {
    use rayon::prelude::*;
    let mut out = Vec::new();
    rayon::iter::repeat_n(T::default(), len)
        .with_min_len(1 << 14)
        .collect_into_vec(&mut out);
    out
}
