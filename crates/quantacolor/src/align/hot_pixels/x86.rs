//! The AVX2 kernels of hot-pixel correction: eight ChaCha8 blocks side by side (portable
//! reference [`super::chacha::chacha8_block`]) and the fused draws and reads of eight hot
//! pixels at a time ([`HotSites`]; reference: the scalar loop of the packed draws).

use super::chacha::CHACHA_CONSTANTS;
use super::{BLOCK_WORDS, HOT_GROUP};
use crate::capture::BinaryFrames;
use crate::cpu::Isa;
use std::ops::Range;

/// [`chacha8_blocks_avx2`]: the ChaCha8 blocks of eight `jobs` into `out`.
///
/// # Panics
/// If `isa` lacks AVX2, or `jobs` and `out` are not eight long.
pub(super) fn chacha8_blocks8(
    isa: Isa,
    key: &[u32; 8],
    jobs: &[(u64, u64)],
    out: &mut [[u32; BLOCK_WORDS]],
) {
    assert!(isa.avx2() && jobs.len() == 8 && out.len() == 8);
    // SAFETY: an `Isa` never holds a feature the CPU lacks, so the CPU has AVX2 (asserted).
    unsafe { chacha8_blocks_avx2(key, jobs, out) };
}

/// The candidates of a group of hot pixels (each its bit positions in a frame, at most eight)
/// for the AVX2 path of [`super::HotPixelCorrector::corrected_block_sum`]: the draws of eight pixels
/// are made side by side (the same ChaCha block of each pixel's stream, one per 32-bit lane),
/// so that each of the block's sixteen words is one frame's draws of the eight pixels, used
/// where it is made (no transposes, no stores of draws or positions): a draw `r` picks
/// candidate `(r · n) >> 32` of its pixel's table (one gather of eight table entries), and the
/// frame's bits at those positions are read by another gather. The same picks and bits as the
/// scalar path, so the same counts (integer sums).
#[derive(Debug)]
pub(super) struct HotSites {
    /// Each pixel's eight candidate positions (padded with its first), end to end; the group
    /// padded to whole vectors of eight pixels by repeating its last pixel (whose counts are
    /// dropped).
    tables: Vec<u32>,
    /// Each (padded) pixel's candidate count.
    counts: Vec<u32>,
    /// Each (padded) pixel's ChaCha stream (its flat index).
    streams: Vec<u64>,
}

impl HotSites {
    /// `None` when `isa` lacks AVX2, when a pixel has more than eight candidates, or when the
    /// 4-byte gathers from the group's bytes (`span`) would reach past a frame of `frame_bytes`.
    pub(super) fn new(
        sites: &[u32],
        spans: &[(usize, u64)],
        hot: &[usize],
        frame_bytes: usize,
        span: &Range<usize>,
        isa: Isa,
    ) -> Option<HotSites> {
        {
            let fits = isa.avx2()
                && !spans.is_empty()
                && spans.len() == hot.len()
                && spans.iter().all(|&(_, n)| (1..=8).contains(&n))
                && span.end + 3 <= frame_bytes
                && frame_bytes <= i32::MAX as usize;
            if !fits {
                return None;
            }
            let padded = spans.len().div_ceil(8) * 8;
            let pixel = |i: usize| i.min(spans.len() - 1);
            let tables = (0..padded)
                .flat_map(|i| {
                    let (start, n) = spans[pixel(i)];
                    let own = &sites[start..start + n as usize];
                    (0..8).map(|l| own.get(l).copied().unwrap_or(own[0]))
                })
                .collect();
            Some(HotSites {
                tables,
                counts: (0..padded).map(|i| spans[pixel(i)].1 as u32).collect(),
                streams: (0..padded).map(|i| hot[pixel(i)] as u64).collect(),
            })
        }
    }

    /// Adds to `counts` (one per pixel of the group) the bit of each pixel's drawn candidate
    /// in every frame of `range`, prefetching the group's bytes (`span`) of the next ChaCha
    /// block's frames.
    pub(super) fn count_drawn(
        &self,
        key: &[u32; 8],
        frames: &BinaryFrames,
        range: Range<usize>,
        span: &Range<usize>,
        counts: &mut [u32],
    ) {
        // SAFETY: `new` checked that its `Isa` has AVX2 (an `Isa` never holds a feature the
        // CPU lacks) and that the gathers stay inside a frame.
        unsafe { self.count_drawn_avx2(key, frames, range, span, counts) };
    }

    /// # Safety
    /// The CPU must support AVX2; every position of the tables must lie in a frame's first
    /// `frame bytes − 3` bytes.
    #[target_feature(enable = "avx2")]
    unsafe fn count_drawn_avx2(
        &self,
        key: &[u32; 8],
        frames: &BinaryFrames,
        range: Range<usize>,
        span: &Range<usize>,
        counts: &mut [u32],
    ) {
        use std::arch::x86_64::*;
        const VECTORS: usize = HOT_GROUP / 8;
        let vectors = self.streams.len() / 8;
        debug_assert!(vectors <= VECTORS && counts.len() <= 8 * vectors);
        let (seven, one) = (_mm256_set1_epi32(7), _mm256_set1_epi32(1));
        // Lane l's table starts at entry 8·l of its vector's tables.
        let lane_tables = _mm256_setr_epi32(0, 8, 16, 24, 32, 40, 48, 56);
        let mut sums = [_mm256_setzero_si256(); VECTORS];
        if range.is_empty() {
            return;
        }
        for block in range.start / BLOCK_WORDS..=(range.end - 1) / BLOCK_WORDS {
            let t0 = block * BLOCK_WORDS;
            // The block's words that are frames of `range`.
            let words = range.start.max(t0) - t0..range.end.min(t0 + BLOCK_WORDS) - t0;
            // The next block's frames, prefetched a few per vector of pixels.
            let next = (t0 + BLOCK_WORDS).min(range.end)..(t0 + 2 * BLOCK_WORDS).min(range.end);
            let per_vector = next.len().div_ceil(vectors);
            for (v, sum) in sums[..vectors].iter_mut().enumerate() {
                let ahead = (next.start + v * per_vector).min(next.end);
                for t in ahead..(ahead + per_vector).min(next.end) {
                    crate::cpu::prefetch(&frames.raw_frame(t)[span.clone()]);
                }
                let jobs: [(u64, u64); 8] =
                    std::array::from_fn(|l| (self.streams[8 * v + l], block as u64));
                let draws = chacha8_words_avx2(key, &jobs);
                let n = _mm256_loadu_si256(self.counts[8 * v..].as_ptr().cast());
                let tables = self.tables[64 * v..][..64].as_ptr();
                for w in words.clone() {
                    let r = draws[w];
                    // (r · n) >> 32 per lane: even lanes from one 32x32 -> 64-bit product, odd
                    // lanes from another.
                    let even = _mm256_srli_epi64::<32>(_mm256_mul_epu32(r, n));
                    let odd = _mm256_mul_epu32(_mm256_srli_epi64::<32>(r), n);
                    let pick = _mm256_blend_epi32::<0b1010_1010>(even, odd);
                    let position = _mm256_i32gather_epi32::<4>(
                        tables.cast(),
                        _mm256_add_epi32(lane_tables, pick),
                    );
                    // The four bytes from the candidate's byte (little-endian: that byte
                    // lowest), shifted by the bit's place in it.
                    let frame = frames.raw_frame(t0 + w);
                    let word = _mm256_i32gather_epi32::<1>(
                        frame.as_ptr().cast(),
                        _mm256_srli_epi32::<3>(position),
                    );
                    let bit = _mm256_and_si256(
                        _mm256_srlv_epi32(word, _mm256_and_si256(position, seven)),
                        one,
                    );
                    *sum = _mm256_add_epi32(*sum, bit);
                }
            }
        }
        let mut lanes = [0u32; HOT_GROUP];
        for (v, sum) in sums[..vectors].iter().enumerate() {
            _mm256_storeu_si256(lanes[8 * v..].as_mut_ptr().cast(), *sum);
        }
        for (count, lane) in counts.iter_mut().zip(lanes) {
            *count += lane;
        }
    }
}

/// [`super::chacha::chacha8_block`] of eight jobs at once, job l in 32-bit lane l of every state vector.
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2")]
unsafe fn chacha8_blocks_avx2(key: &[u32; 8], jobs: &[(u64, u64)], out: &mut [[u32; BLOCK_WORDS]]) {
    use std::arch::x86_64::*;
    debug_assert!(jobs.len() == 8 && out.len() == 8);
    let words = chacha8_words_avx2(key, jobs);
    // Vector j holds word j of the eight blocks: transposed, eight words of one block each.
    for (half, rows) in words.chunks_exact(8).enumerate() {
        let columns = crate::cpu::transpose8x8(rows.try_into().expect("eight rows"));
        for (block, column) in out.iter_mut().zip(columns) {
            _mm256_storeu_si256(block[8 * half..].as_mut_ptr().cast(), column);
        }
    }
}

/// The sixteen words of the ChaCha8 blocks of eight jobs `(stream, block)`: vector j holds
/// word j of every job's block, job l in lane l (the words of [`super::chacha::chacha8_block`]).
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn chacha8_words_avx2(
    key: &[u32; 8],
    jobs: &[(u64, u64)],
) -> [std::arch::x86_64::__m256i; BLOCK_WORDS] {
    use std::arch::x86_64::*;
    debug_assert!(jobs.len() == 8);
    let lanes = |word: fn(u64, u64) -> u32| {
        let w: [u32; 8] = std::array::from_fn(|l| word(jobs[l].0, jobs[l].1));
        _mm256_loadu_si256(w.as_ptr().cast())
    };
    let mut init = [_mm256_setzero_si256(); 16];
    for (v, &c) in init.iter_mut().zip(CHACHA_CONSTANTS.iter().chain(key)) {
        *v = _mm256_set1_epi32(c as i32);
    }
    init[12] = lanes(|_, b| b as u32);
    init[13] = lanes(|_, b| (b >> 32) as u32);
    init[14] = lanes(|s, _| s as u32);
    init[15] = lanes(|s, _| (s >> 32) as u32);
    // Byte shuffles rotating every 32-bit word left by 16 and by 8.
    let rot16 = _mm256_setr_epi8(
        2, 3, 0, 1, 6, 7, 4, 5, 10, 11, 8, 9, 14, 15, 12, 13, 2, 3, 0, 1, 6, 7, 4, 5, 10, 11, 8, 9,
        14, 15, 12, 13,
    );
    let rot8 = _mm256_setr_epi8(
        3, 0, 1, 2, 7, 4, 5, 6, 11, 8, 9, 10, 15, 12, 13, 14, 3, 0, 1, 2, 7, 4, 5, 6, 11, 8, 9, 10,
        15, 12, 13, 14,
    );
    let mut x = init;
    // Literal indices (a macro, not a loop over the index tables): the state then lives in
    // registers instead of being read and written through memory at computed offsets.
    macro_rules! quarter {
        ($a:literal, $b:literal, $c:literal, $d:literal) => {
            x[$a] = _mm256_add_epi32(x[$a], x[$b]);
            x[$d] = _mm256_shuffle_epi8(_mm256_xor_si256(x[$d], x[$a]), rot16);
            x[$c] = _mm256_add_epi32(x[$c], x[$d]);
            let t = _mm256_xor_si256(x[$b], x[$c]);
            x[$b] = _mm256_or_si256(_mm256_slli_epi32::<12>(t), _mm256_srli_epi32::<20>(t));
            x[$a] = _mm256_add_epi32(x[$a], x[$b]);
            x[$d] = _mm256_shuffle_epi8(_mm256_xor_si256(x[$d], x[$a]), rot8);
            x[$c] = _mm256_add_epi32(x[$c], x[$d]);
            let t = _mm256_xor_si256(x[$b], x[$c]);
            x[$b] = _mm256_or_si256(_mm256_slli_epi32::<7>(t), _mm256_srli_epi32::<25>(t));
        };
    }
    for _ in 0..4 {
        // The quarter rounds of CHACHA_COLUMNS, then of CHACHA_DIAGONALS.
        quarter!(0, 4, 8, 12);
        quarter!(1, 5, 9, 13);
        quarter!(2, 6, 10, 14);
        quarter!(3, 7, 11, 15);
        quarter!(0, 5, 10, 15);
        quarter!(1, 6, 11, 12);
        quarter!(2, 7, 8, 13);
        quarter!(3, 4, 9, 14);
    }
    std::array::from_fn(|j| _mm256_add_epi32(x[j], init[j]))
}
