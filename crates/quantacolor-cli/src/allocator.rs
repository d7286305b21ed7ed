//! Process-wide allocator settings for the command-line program.
//!
//! The pipeline allocates and frees image-sized buffers (up to a few tens of MB) for every
//! alignment block, sub-block and denoising pass. With glibc's defaults the larger ones are
//! mapped and unmapped, and freed heap tops are trimmed, so the same memory is handed back to
//! the kernel and faulted in (and zeroed) again many times per reconstruction: about 80,000
//! page faults and a tenth of the process's CPU time on 10,000 frames of 496x254. Keeping
//! freed memory in the process for reuse removes about 40 % of those faults. The price is a
//! little more resident memory: freed blocks stay in the heap and fragment it (100,000 frames:
//! peak 314 -> 339 MB).

/// glibc's largest mmap threshold (`HEAP_MAX_SIZE / 2` on 64-bit targets): blocks below it
/// come from the heap and are reused after they are freed.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD_BYTES: libc::c_int = 32 << 20;

/// Tells glibc to keep freed memory for reuse: the mmap threshold at its maximum, no
/// trimming of the heap top, and heap growth in 64 MiB steps. A no-op with other C libraries.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters; it is called before any thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES);
        libc::mallopt(libc::M_TRIM_THRESHOLD, libc::c_int::MAX);
        libc::mallopt(libc::M_TOP_PAD, 64 << 20);
    }
}
