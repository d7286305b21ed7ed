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
