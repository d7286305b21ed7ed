//! CPU hints and parallel helpers shared by the hot kernels (this project's own engineering,
//! not a paper stage), and the one place the instruction set is chosen ([`Isa`]).

use std::sync::OnceLock;

/// The instruction set the hot kernels run on: detected once per process (as rav1e's
/// `cpu_features`) and passed down as a value, so every kernel takes the same decision.
/// `QUANTACOLOR_ISA=generic` forces the portable paths (so CI runs them too); `native` or
/// unset takes what the CPU offers. A level the CPU lacks can never be constructed, which is
/// what makes the `unsafe` calls of the AVX2 kernels sound.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Isa(Level);

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
enum Level {
    Generic,
    /// AVX2 without FMA (rare: some early or emulated CPUs).
    Avx2,
    /// AVX2 and FMA (every x86-64 CPU with AVX2 since 2013 in practice).
    Avx2Fma,
}

/// The environment variable that lowers the instruction set ([`Isa::current`]).
pub const ISA_ENV: &str = "QUANTACOLOR_ISA";

impl Isa {
    /// The portable paths: plain Rust that any CPU runs.
    pub const fn generic() -> Self {
        Isa(Level::Generic)
    }

    /// What this CPU offers, ignoring the environment.
    pub fn native() -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                return if std::arch::is_x86_feature_detected!("fma") {
                    Isa(Level::Avx2Fma)
                } else {
                    Isa(Level::Avx2)
                };
            }
        }
        Isa(Level::Generic)
    }

    /// The instruction set of this process: [`Isa::native`] lowered by `QUANTACOLOR_ISA`,
    /// decided on the first call and the same ever after. An unknown value of the variable is
    /// ignored here (the command line rejects it up front with [`Isa::from_env_value`]).
    pub fn current() -> Self {
        static CURRENT: OnceLock<Isa> = OnceLock::new();
        *CURRENT.get_or_init(|| {
            let native = Isa::native();
            match std::env::var(ISA_ENV) {
                Ok(value) => {
                    Isa::from_env_value(&value).map_or(native, |wanted| wanted.min(native))
                }
                Err(_) => native,
            }
        })
    }

    /// The level a value of `QUANTACOLOR_ISA` asks for (before it is capped at what the CPU
    /// offers): `generic`, `avx2` or `native`, in any case. `None` for anything else.
    pub fn from_env_value(value: &str) -> Option<Self> {
        match value.trim().to_ascii_lowercase().as_str() {
            "generic" => Some(Isa(Level::Generic)),
            "avx2" => Some(Isa(Level::Avx2Fma)),
            "native" | "" => Some(Isa::native()),
            _ => None,
        }
    }

    /// Whether the AVX2 kernels may run.
    #[inline]
    pub fn avx2(self) -> bool {
        self.0 >= Level::Avx2
    }

    /// Whether the AVX2 kernels that also use FMA may run.
    #[inline]
    pub fn avx2_fma(self) -> bool {
        self.0 >= Level::Avx2Fma
    }

    /// A short name for reports: `generic`, `avx2` or `avx2+fma`.
    pub fn name(self) -> &'static str {
        match self.0 {
            Level::Generic => "generic",
            Level::Avx2 => "avx2",
            Level::Avx2Fma => "avx2+fma",
        }
    }
}

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
/// merge's 35 MB of phase bins, is one thread's memset). The same values as `vec!`.
pub fn zeroed_par<T: Default + Clone + Send + Sync>(len: usize) -> Vec<T> {
    let mut out = Vec::new();
    resize_par(&mut out, len, T::default());
    out
}

/// [`Vec::resize`] with the new values written by all threads at once (as [`zeroed_par`]).
pub fn resize_par<T: Clone + Send + Sync>(buffer: &mut Vec<T>, len: usize, value: T) {
    use rayon::prelude::*;
    if len <= buffer.len() {
        buffer.truncate(len);
        return;
    }
    let missing = len - buffer.len();
    buffer.par_extend(rayon::iter::repeat_n(value, missing).with_min_len(PAR_FILL_ITEMS));
}

/// `buffer.fill(value)` by all threads at once (as [`zeroed_par`]).
pub fn fill_par<T: Clone + Send + Sync>(buffer: &mut [T], value: T) {
    use rayon::prelude::*;
    buffer
        .par_chunks_mut(PAR_FILL_ITEMS)
        .for_each(|chunk| chunk.fill(value.clone()));
}

/// The shortest chunk length that still splits `len` items into the fewest chunks of at most
/// `max` items (`max` 0 counts as 1): for loops that run chunk after chunk, each in parallel,
/// where every chunk waits for its slowest task. Chunks of `max` can leave a short last one (25
/// blocks in eights: 8, 8, 8, 1) whose few tasks leave cores idle; this gives 7, 7, 7, 4.
pub fn balanced_chunk_len(len: usize, max: usize) -> usize {
    let max = max.max(1);
    match len.div_ceil(max) {
        0 => max,
        chunks => len.div_ceil(chunks),
    }
}

/// Runs `f` on a thread of rayon's pool (the global one, or the caller's own pool when it
/// already runs on one of its threads: then in place) and returns what it returns: for the
/// library's entry points, whose stages run many short parallel loops in turn. From a thread
/// outside the pool each loop is a job sent into the pool while the caller sleeps until a
/// worker has finished it and woken it; on a worker, the caller works on its own loop and goes
/// on at once. Measured on `reconstruct` of the 10,000-frame chart (24 alternating pairs): the
/// merge 7.7 ms faster, the whole 6.3 ms; fast-motion tracking (a chain of small parallel
/// steps) 10 % faster. The same results: no value depends on which thread computes it.
pub fn on_pool<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| f())
}

/// Fewest values one task of the parallel fills writes.
const PAR_FILL_ITEMS: usize = 1 << 14;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn isa_is_never_above_the_cpu_and_the_variable_only_lowers_it() {
        let native = Isa::native();
        assert!(Isa::current() <= native);
        assert!(Isa::generic() <= native);
        assert!(!Isa::generic().avx2() && !Isa::generic().avx2_fma());
        assert_eq!(Isa::from_env_value(" Generic "), Some(Isa::generic()));
        assert_eq!(Isa::from_env_value("native"), Some(native));
        assert_eq!(Isa::from_env_value("sse9"), None);
        let avx2 = Isa::from_env_value("avx2").expect("a known level");
        assert!(avx2.avx2() && avx2.avx2_fma());
        if std::env::var(ISA_ENV).is_err() {
            assert_eq!(Isa::current(), native);
        } else if std::env::var(ISA_ENV).as_deref() == Ok("generic") {
            assert_eq!(Isa::current(), Isa::generic());
        }
        assert_eq!(Isa::generic().name(), "generic");
    }

    #[test]
    fn balanced_chunks_are_as_few_as_max_gives_and_as_short_as_that_allows() {
        assert_eq!(balanced_chunk_len(25, 8), 7);
        assert_eq!(balanced_chunk_len(99, 32), 25);
        for len in 1..300usize {
            for max in 0..40usize {
                let c = balanced_chunk_len(len, max);
                let fewest = len.div_ceil(max.max(1));
                assert!(c >= 1 && c <= max.max(1), "{len} {max}: {c}");
                assert_eq!(len.div_ceil(c), fewest, "{len} {max}: {c}");
                if c > 1 {
                    assert!(
                        len.div_ceil(c - 1) > fewest,
                        "{len} {max}: {c} is not the shortest"
                    );
                }
            }
        }
        assert!(
            balanced_chunk_len(0, 8) >= 1,
            "an empty slice still takes a chunk length"
        );
    }

    #[test]
    fn parallel_fills_write_what_the_serial_ones_do() {
        for (old, len) in [
            (0usize, 0usize),
            (0, 100_000),
            (5, 3),
            (70_000, 70_001),
            (10, 50_000),
        ] {
            let start: Vec<u32> = (0..old as u32).collect();
            let mut serial = start.clone();
            serial.resize(len, 7);
            let mut parallel = start.clone();
            resize_par(&mut parallel, len, 7);
            assert_eq!(parallel, serial, "resize {old} -> {len}");
            serial.fill(9);
            fill_par(&mut parallel, 9);
            assert_eq!(parallel, serial, "fill {len}");
        }
        assert_eq!(zeroed_par::<f32>(40_000), vec![0.0f32; 40_000]);
    }
}
