//! Hot-pixel correction and dark-count calibration (supplement §1.4, Fig. 2; paper Fig. 5).
//!
//! A hot pixel fires far more often than its neighbours even in the dark. Left alone, hot pixels
//! form a static pattern that every block image shares, so block matching is pulled toward zero
//! motion (paper Fig. 5). Following supplement §1.4, each hot pixel takes, in every binary frame,
//! the bit of one of its `k` nearest non-hot neighbours behind the same colour filter, drawn at
//! random. The draw is a function of `(seed, pixel, frame)` only, so block sums do not depend on
//! block boundaries or thread count.

use crate::capture::frames::FrameLayout;
use crate::capture::BinaryFrames;
use crate::cfa::Cfa;
use crate::cpu::Isa;
use crate::error::{Error, Result};
use crate::model::{
    detection_probability, mle_flux, mle_variance_from_probability, SATURATION_MARGIN,
};
use ndarray::Array2;
use rand::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// Settings of hot-pixel correction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct HotPixelConfig {
    /// Number of nearest same-colour, non-hot pixels a hot pixel draws from (default 8).
    ///
    /// Eight is the ring of nearest sites on any regular colour lattice (the 8-neighbourhood
    /// on the sub-lattice of one colour), so replacements stay within about one lattice spacing
    /// while drawing from enough pixels that the replacement is not a copy of a single neighbour
    /// (a copied neighbour would duplicate its noise and texture at a fixed offset).
    pub k: usize,
    /// Seed of the per-(pixel, frame) draws.
    pub seed: u64,
}

impl Default for HotPixelConfig {
    fn default() -> Self {
        HotPixelConfig { k: 8, seed: 0 }
    }
}

/// Hot pixels whose replacements [`HotPixelCorrector::corrected_block_sum`] draws frame by
/// frame together.
const HOT_GROUP: usize = 64;

/// Frames whose draws [`HotPixelCorrector::corrected_block_sum`] makes at a time (per hot pixel
/// of a group): chunks end at multiples of it, so that a chunk's draws lie in at most
/// `DRAW_CHUNK / 16` ChaCha blocks of each pixel's stream.
const DRAW_CHUNK: usize = 64;

/// 32-bit words of one ChaCha block.
const BLOCK_WORDS: usize = 16;

/// Frames ahead of the one being read whose candidate bytes the scalar path of
/// [`HotPixelCorrector::corrected_block_sum`] asks the cache for (frames lie a frame's size
/// apart, a stride the hardware prefetchers do not follow).
const PREFETCH_FRAMES: usize = 8;

/// Precomputed replacement candidates of every hot pixel.
#[derive(Debug, Clone)]
pub struct HotPixelCorrector {
    height: usize,
    width: usize,
    seed: u64,
    /// The ChaCha key that `ChaCha8Rng::seed_from_u64(seed)` uses, as little-endian words.
    key: [u32; 8],
    /// Flat pixel index `y * W + x` of each hot pixel.
    hot: Vec<usize>,
    /// For each hot pixel, its candidates' `(y, x)`, nearest first.
    candidates: Vec<Vec<(u32, u32)>>,
}

impl HotPixelCorrector {
    /// Finds, for each pixel set in `mask` (`(H, W)`, same shape as `cfa`), its `k` nearest
    /// (Euclidean) non-hot pixels behind the same colour filter; ties break in row-major order.
    /// Fewer than `k` are kept when the sensor has fewer. Errors when shapes differ, `k` is 0, or
    /// a hot pixel has no usable same-colour pixel at all.
    pub fn new(cfa: &Cfa, mask: &Array2<bool>, k: usize, seed: u64) -> Result<Self> {
        let (h, w) = (cfa.height(), cfa.width());
        if mask.dim() != (h, w) {
            return Err(Error::invalid(format!(
                "hot-pixel mask is {:?}, the CFA is ({h}, {w})",
                mask.dim()
            )));
        }
        if k == 0 {
            return Err(Error::invalid(
                "hot-pixel neighbour count k must be at least 1",
            ));
        }
        let hot: Vec<usize> = mask
            .indexed_iter()
            .filter(|(_, &m)| m)
            .map(|((y, x), _)| y * w + x)
            .collect();
        let codes = cfa.codes();
        let candidates = hot
            .par_iter()
            .map(|&idx| {
                let (y0, x0) = (idx / w, idx % w);
                let code = codes[[y0, x0]];
                nearest_where((h, w), (y0, x0), k, |y, x| {
                    codes[[y, x]] == code && !mask[[y, x]]
                })
                .into_iter()
                .map(|(y, x)| (y as u32, x as u32))
                .collect::<Vec<_>>()
            })
            .collect::<Vec<_>>();
        if let Some(i) = candidates.iter().position(|c| c.is_empty()) {
            let (y, x) = (hot[i] / w, hot[i] % w);
            return Err(Error::invalid(format!(
                "hot pixel (y={y}, x={x}) has no non-hot pixel of the same colour to borrow from"
            )));
        }
        let key_bytes = ChaCha8Rng::seed_from_u64(seed).get_seed();
        let key = std::array::from_fn(|i| {
            u32::from_le_bytes(key_bytes[4 * i..4 * i + 4].try_into().expect("4 bytes"))
        });
        Ok(HotPixelCorrector {
            height: h,
            width: w,
            seed,
            key,
            hot,
            candidates,
        })
    }

    /// Number of hot pixels.
    pub fn hot_count(&self) -> usize {
        self.hot.len()
    }

    /// The replacement candidates of hot pixel `(y, x)`, nearest first (`None` if not hot).
    pub fn candidates(&self, y: usize, x: usize) -> Option<&[(u32, u32)]> {
        let idx = y * self.width + x;
        self.hot
            .binary_search(&idx)
            .ok()
            .map(|i| self.candidates[i].as_slice())
    }

    /// Per-pixel count of ones (sum of samples, for multi-bit frames) over `range` (`(H, W)`),
    /// with each hot pixel's sample in frame `t` replaced by the sample of candidate number `draw(seed, pixel, t) mod k` (supplement §1.4).
    /// The draws run on the process's instruction set ([`Isa::current`]).
    pub fn corrected_block_sum(&self, frames: &BinaryFrames, range: Range<usize>) -> Array2<u32> {
        self.corrected_block_sum_on(frames, range, Isa::current())
    }

    /// [`Self::corrected_block_sum`] with the draws on `isa` (every instruction set gives the
    /// same sums).
    fn corrected_block_sum_on(
        &self,
        frames: &BinaryFrames,
        range: Range<usize>,
        isa: Isa,
    ) -> Array2<u32> {
        assert_eq!(
            (frames.height(), frames.width()),
            (self.height, self.width),
            "frames and hot-pixel corrector disagree in size"
        );
        // Hot pixels a few dozen at a time (neighbours in row-major order), frame by frame: the
        // group's reads of one frame stay within a few rows (one pixel at a time through all
        // frames would touch a new page and cache line at every read). The draws come before
        // the block sum, which then finds the frames' pages mapped and partly cached (summed
        // first, they would be released and faulted in again for these few reads).
        let packed = frames.layout() == FrameLayout::Packed;
        let replaced: Vec<Vec<u32>> = self
            .hot
            .par_chunks(HOT_GROUP)
            .zip(self.candidates.par_chunks(HOT_GROUP))
            .map(|(hot, candidates)| {
                if packed {
                    self.drawn_counts_packed(frames, range.clone(), hot, candidates, isa)
                } else {
                    self.drawn_counts_unpacked(frames, range.clone(), hot, candidates)
                }
            })
            .collect();
        let mut sums = frames.shared_sum(range.clone());
        frames.release(range);
        for (&idx, &c) in self.hot.iter().zip(replaced.iter().flatten()) {
            sums[[idx / self.width, idx % self.width]] = c;
        }
        sums
    }

    /// The counts over `range` of the hot pixels `hot` (one group) with each frame's sample
    /// drawn from the pixel's `candidates`, read from packed frames; the draws on `isa`.
    fn drawn_counts_packed(
        &self,
        frames: &BinaryFrames,
        range: Range<usize>,
        hot: &[usize],
        candidates: &[Vec<(u32, u32)>],
        isa: Isa,
    ) -> Vec<u32> {
        let row_bytes = frames.width().div_ceil(8);
        let mut counts = vec![0u32; hot.len()];
        // Packed frames: the bit read straight from the frame's bytes, each
        // candidate as its bit's position in a frame (byte · 8 + shift), the
        // group's candidates in one flat list (`spans`: each hot pixel's start and
        // count). The draws of a chunk of frames are the ChaCha blocks of every
        // pixel's stream that hold them (eight blocks at a time, [`chacha8_blocks`]:
        // the words `next_u32` would give one by one), turned into bit positions
        // frame-major, so the reads of a frame are independent loads with no
        // generator work between them.
        let mut sites: Vec<u32> = Vec::new();
        let mut spans: Vec<(usize, u64)> = Vec::with_capacity(hot.len());
        for cands in candidates {
            spans.push((sites.len(), cands.len() as u64));
            sites.extend(
                cands
                    .iter()
                    .map(|&(y, x)| (y * row_bytes as u32 + x / 8) * 8 + 7 - x % 8),
            );
        }
        let g = hot.len();
        // The bytes of a frame that the group's candidates lie in (a few rows).
        let span = match (sites.iter().min(), sites.iter().max()) {
            (Some(&lo), Some(&hi)) => (lo >> 3) as usize..(hi >> 3) as usize + 1,
            _ => 0..0,
        };
        // With AVX2, every hot pixel having at most eight candidates (its sites
        // one vector) and the 4-byte loads of the group's bytes ending inside a
        // frame: the draws and reads fused, eight pixels at a time ([`HotSites`]).
        let frame_bytes = frames.height() * row_bytes;
        if let Some(sites8) = HotSites::new(&sites, &spans, hot, frame_bytes, &span, isa) {
            sites8.count_drawn(&self.key, frames, range.clone(), &span, &mut counts);
            return counts;
        }
        // Per pixel, the DRAW_CHUNK / 16 blocks from the one holding the chunk's first
        // frame: pixel i's draw of frame t is word t − 16·(t0 / 16) of its run.
        let per_pixel = DRAW_CHUNK / BLOCK_WORDS;
        let mut blocks = vec![[0u32; BLOCK_WORDS]; per_pixel * g];
        let mut jobs: Vec<(u64, u64)> = Vec::with_capacity(per_pixel * g);
        let mut bits = vec![0u32; DRAW_CHUNK * g];
        let mut t0 = range.start;
        while t0 < range.end {
            let t1 = ((t0 / DRAW_CHUNK + 1) * DRAW_CHUNK).min(range.end);
            let c = t1 - t0;
            let first = t0 / BLOCK_WORDS;
            let count = (t1 - 1) / BLOCK_WORDS + 1 - first;
            jobs.clear();
            for &idx in hot {
                jobs.extend((first..first + count).map(|b| (idx as u64, b as u64)));
            }
            chacha8_blocks(&self.key, &jobs, &mut blocks[..count * g], isa);
            let offset = t0 - first * BLOCK_WORDS;
            for (i, (run, &(start, n))) in blocks[..count * g]
                .chunks_exact(count)
                .zip(&spans)
                .enumerate()
            {
                let words = &run.as_flattened()[offset..][..c];
                let sites = &sites[start..];
                for (f, &r) in words.iter().enumerate() {
                    bits[f * g + i] = sites[((r as u64 * n) >> 32) as usize];
                }
            }
            for (f, frame_bits) in bits.chunks_exact(g).take(c).enumerate() {
                let t = t0 + f;
                if t + PREFETCH_FRAMES < range.end {
                    crate::cpu::prefetch(&frames.raw_frame(t + PREFETCH_FRAMES)[span.clone()]);
                }
                let frame = frames.raw_frame(t);
                for (count, &b) in counts.iter_mut().zip(frame_bits) {
                    *count += ((frame[(b >> 3) as usize] >> (b & 7)) & 1) as u32;
                }
            }
            t0 = t1;
        }
        counts
    }

    /// [`Self::drawn_counts_packed`] for frames that are not packed: one ChaCha8 stream per
    /// pixel, a sample at a time.
    fn drawn_counts_unpacked(
        &self,
        frames: &BinaryFrames,
        range: Range<usize>,
        hot: &[usize],
        candidates: &[Vec<(u32, u32)>],
    ) -> Vec<u32> {
        let mut counts = vec![0u32; hot.len()];
        let mut rngs: Vec<ChaCha8Rng> = hot
            .iter()
            .map(|&idx| self.stream(idx, range.start))
            .collect();
        for t in range.clone() {
            for ((rng, cands), count) in rngs.iter_mut().zip(candidates).zip(counts.iter_mut()) {
                let n = cands.len() as u64;
                let pick = ((rng.next_u32() as u64 * n) >> 32) as usize;
                let (y, x) = (cands[pick].0 as usize, cands[pick].1 as usize);
                *count += frames.sample(t, y, x);
            }
        }
        counts
    }

    /// The random stream of pixel `idx`, positioned so that its next 32-bit word is the draw of
    /// frame `t`: word `t` of ChaCha8 stream `idx` under the corrector's seed.
    fn stream(&self, idx: usize, t: usize) -> ChaCha8Rng {
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        rng.set_stream(idx as u64);
        rng.set_word_pos(t as u128);
        rng
    }
}

/// The candidates of a group of hot pixels (each its bit positions in a frame, at most eight)
/// for the AVX2 path of [`HotPixelCorrector::corrected_block_sum`]: the draws of eight pixels
/// are made side by side (the same ChaCha block of each pixel's stream, one per 32-bit lane),
/// so that each of the block's sixteen words is one frame's draws of the eight pixels, used
/// where it is made (no transposes, no stores of draws or positions): a draw `r` picks
/// candidate `(r · n) >> 32` of its pixel's table (one gather of eight table entries), and the
/// frame's bits at those positions are read by another gather. The same picks and bits as the
/// scalar path, so the same counts (integer sums).
#[derive(Debug)]
struct HotSites {
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
    fn new(
        sites: &[u32],
        spans: &[(usize, u64)],
        hot: &[usize],
        frame_bytes: usize,
        span: &Range<usize>,
        isa: Isa,
    ) -> Option<HotSites> {
        #[cfg(target_arch = "x86_64")]
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
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (sites, spans, hot, frame_bytes, span, isa);
            None
        }
    }

    /// Adds to `counts` (one per pixel of the group) the bit of each pixel's drawn candidate
    /// in every frame of `range`, prefetching the group's bytes (`span`) of the next ChaCha
    /// block's frames.
    fn count_drawn(
        &self,
        key: &[u32; 8],
        frames: &BinaryFrames,
        range: Range<usize>,
        span: &Range<usize>,
        counts: &mut [u32],
    ) {
        #[cfg(target_arch = "x86_64")]
        {
            // SAFETY: `new` checked that its `Isa` has AVX2 (an `Isa` never holds a feature the
            // CPU lacks) and that the gathers stay inside a frame.
            unsafe { self.count_drawn_avx2(key, frames, range, span, counts) };
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (key, frames, range, span, counts);
    }

    /// # Safety
    /// The CPU must support AVX2; every position of the tables must lie in a frame's first
    /// `frame bytes − 3` bytes.
    #[cfg(target_arch = "x86_64")]
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

/// The ChaCha constant words ("expand 32-byte k").
const CHACHA_CONSTANTS: [u32; 4] = [0x6170_7865, 0x3320_646e, 0x7962_2d32, 0x6b20_6574];

/// The ChaCha8 blocks `(stream, block)` of `jobs` under `key` into `out` (one per job): the
/// words `ChaCha8Rng` (rand_chacha) gives, word `16·block + j` of stream `stream` being word j
/// of that block. The generator's own refill makes four consecutive blocks of one stream at a
/// time; here any eight blocks go side by side, one per 32-bit lane (AVX2), so that the few
/// blocks each hot pixel needs per chunk of frames are made at full width. Integer arithmetic:
/// every path gives the same words (eight lanes where `isa` has AVX2).
fn chacha8_blocks(key: &[u32; 8], jobs: &[(u64, u64)], out: &mut [[u32; BLOCK_WORDS]], isa: Isa) {
    assert_eq!(jobs.len(), out.len(), "one output block per job");
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        if isa.avx2() {
            for (jobs, out) in jobs.chunks_exact(8).zip(out.chunks_exact_mut(8)) {
                // SAFETY: `isa` has AVX2, so the CPU has (an `Isa` never exceeds it).
                unsafe { chacha8_blocks_avx2(key, jobs, out) };
                done += 8;
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = isa;
    for (&(stream, block), out) in jobs[done..].iter().zip(&mut out[done..]) {
        *out = chacha8_block(key, stream, block);
    }
}

/// The initial ChaCha state of block `block` of stream `stream`: constants, key, 64-bit block
/// counter, 64-bit stream number (rand_chacha's layout).
fn chacha_state(key: &[u32; 8], stream: u64, block: u64) -> [u32; 16] {
    let mut state = [0u32; 16];
    state[..4].copy_from_slice(&CHACHA_CONSTANTS);
    state[4..12].copy_from_slice(key);
    state[12..].copy_from_slice(&[
        block as u32,
        (block >> 32) as u32,
        stream as u32,
        (stream >> 32) as u32,
    ]);
    state
}

/// One ChaCha8 block (4 double rounds, then the initial state added), scalar.
fn chacha8_block(key: &[u32; 8], stream: u64, block: u64) -> [u32; 16] {
    let init = chacha_state(key, stream, block);
    let mut x = init;
    let quarter = |x: &mut [u32; 16], a: usize, b: usize, c: usize, d: usize| {
        x[a] = x[a].wrapping_add(x[b]);
        x[d] = (x[d] ^ x[a]).rotate_left(16);
        x[c] = x[c].wrapping_add(x[d]);
        x[b] = (x[b] ^ x[c]).rotate_left(12);
        x[a] = x[a].wrapping_add(x[b]);
        x[d] = (x[d] ^ x[a]).rotate_left(8);
        x[c] = x[c].wrapping_add(x[d]);
        x[b] = (x[b] ^ x[c]).rotate_left(7);
    };
    for _ in 0..4 {
        for (a, b, c, d) in CHACHA_COLUMNS.into_iter().chain(CHACHA_DIAGONALS) {
            quarter(&mut x, a, b, c, d);
        }
    }
    for (x, i) in x.iter_mut().zip(init) {
        *x = x.wrapping_add(i);
    }
    x
}

/// The quarter rounds of a ChaCha column round and diagonal round (state word indices).
const CHACHA_COLUMNS: [(usize, usize, usize, usize); 4] =
    [(0, 4, 8, 12), (1, 5, 9, 13), (2, 6, 10, 14), (3, 7, 11, 15)];
const CHACHA_DIAGONALS: [(usize, usize, usize, usize); 4] =
    [(0, 5, 10, 15), (1, 6, 11, 12), (2, 7, 8, 13), (3, 4, 9, 14)];

/// [`chacha8_block`] of eight jobs at once, job l in 32-bit lane l of every state vector.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
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
/// word j of every job's block, job l in lane l (the words of [`chacha8_block`]).
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
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

/// Dark-count rate of every pixel (counts per second, `(H, W)`) from frames captured in the dark:
/// the Bernoulli maximum-likelihood estimate λ = −ln(1 − k/T) / τ (paper Eq. 6 with no light),
/// where `k` is the pixel's count over all T frames and τ = `exposure_s` the exposure of one
/// binary frame in seconds. A pixel that fired in every frame gets the rate of k = T − ½.
pub fn dark_count_rate_map(frames: &BinaryFrames, exposure_s: f64) -> Result<Array2<f32>> {
    if exposure_s.is_nan() || exposure_s <= 0.0 || exposure_s.is_infinite() {
        return Err(Error::invalid(format!(
            "binary-frame exposure must be a positive number of seconds, got {exposure_s}"
        )));
    }
    let t = frames.frame_count() as f64;
    let sums = frames.sum_range(0..frames.frame_count());
    Ok(sums.mapv(|k| (mle_flux(k as f64, t, 0.0) / exposure_s) as f32))
}

/// Pixels whose dark-count rate exceeds `threshold_cps` (counts per second).
pub fn hot_pixel_mask(rate_map: &Array2<f32>, threshold_cps: f32) -> Array2<bool> {
    rate_map.mapv(|r| r > threshold_cps)
}

/// Settings of hot-pixel self-calibration ([`detect_hot_pixels`]). This detector is the
/// project's own heuristic (the paper calibrates hot pixels from dark frames, supplement §1.4).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct HotPixelDetectConfig {
    /// Nearest same-colour pixels a pixel is compared with (default 24: about the first three
    /// rings of a colour's sites, so that detail at the pixel pitch (gratings, dot patterns)
    /// has bright sites among them; with 8 the built-in chart's finest gratings were flagged).
    pub neighbours: usize,
    /// The pixel is compared with the `rank`-th brightest of those neighbours (default 3): a
    /// few neighbours on the same bright line, edge, grating or highlight keep a scene feature
    /// from being flagged, and one or two hot neighbours cannot hide a hot pixel.
    pub rank: usize,
    /// A hot pixel's flux exceeds the reference by at least this factor (default 1.5).
    pub min_ratio: f64,
    /// ... and by at least this many binomial standard deviations of the reference's estimate
    /// over the whole burst (default 6: about one false alarm per 10^9 pixels by noise alone).
    pub z: f64,
}

impl Default for HotPixelDetectConfig {
    fn default() -> Self {
        HotPixelDetectConfig {
            neighbours: 24,
            rank: 3,
            min_ratio: 1.5,
            z: 6.0,
        }
    }
}

/// The `k` nearest pixels (Euclidean, ties in row-major order) of `(y0, x0)` for which
/// `accept(y, x)` holds, excluding `(y0, x0)` itself.
fn nearest_where(
    (h, w): (usize, usize),
    (y0, x0): (usize, usize),
    k: usize,
    accept: impl Fn(usize, usize) -> bool,
) -> Vec<(usize, usize)> {
    let (y0, x0) = (y0 as isize, x0 as isize);
    let max_r = h.max(w) as isize;
    let mut r: isize = 2;
    loop {
        let mut found: Vec<(isize, usize, usize)> = Vec::new();
        for y in (y0 - r).max(0)..=(y0 + r).min(h as isize - 1) {
            for x in (x0 - r).max(0)..=(x0 + r).min(w as isize - 1) {
                if (y, x) != (y0, x0) && accept(y as usize, x as usize) {
                    found.push(((y - y0).pow(2) + (x - x0).pow(2), y as usize, x as usize));
                }
            }
        }
        found.sort_unstable();
        if (found.len() >= k && found[k - 1].0 <= r * r) || r >= max_r {
            found.truncate(k);
            return found.into_iter().map(|(_, y, x)| (y, x)).collect();
        }
        r *= 2;
    }
}

/// Hot pixels found in an ordinary capture (no dark frames): pixels whose flux over the whole
/// burst is far above their same-colour neighbourhood. This is the project's own heuristic;
/// the paper's hot pixels come from a dark calibration ([`dark_count_rate_map`]).
///
/// Each pixel's flux λ̂ is the MLE of paper Eq. 6 from its count over all T frames. Its
/// reference is the `rank`-th largest λ̂ among its `neighbours` nearest same-colour pixels.
/// The pixel is hot when λ̂ > max(`min_ratio` · ref, ref + `z` · σ), σ being the binomial
/// standard deviation of the MLE at the reference flux over T frames (firing probability
/// floored at 2/T so that an all-dark neighbourhood does not make a handful of counts
/// significant). An R, G or B pixel must also exceed the physical bound set by its W
/// neighbours: behind filter c a pixel sees at most W / w_c, since W = wR·R + wG·G + wB·B
/// (the second largest W of its 3x3 neighbourhood is used).
///
/// Scene features are protected by the rank (a bright line or edge through the pixel also
/// lights at least two same-colour neighbours or the W neighbours) and by motion (a moving
/// camera smears them over the burst); a static single-pixel point of light cannot be told
/// from a hot pixel and is flagged, which costs only that pixel's own samples.
pub fn detect_hot_pixels(
    frames: &BinaryFrames,
    cfa: &Cfa,
    w_weights: [f64; 3],
    config: &HotPixelDetectConfig,
) -> Result<Array2<bool>> {
    let (h, w) = (cfa.height(), cfa.width());
    if (frames.height(), frames.width()) != (h, w) {
        return Err(Error::invalid(format!(
            "frames are {}x{}, the CFA is {h}x{w}",
            frames.height(),
            frames.width()
        )));
    }
    if config.neighbours == 0 || config.rank == 0 || config.rank > config.neighbours {
        return Err(Error::invalid(format!(
            "hot-pixel detection needs 1 <= rank ({}) <= neighbours ({})",
            config.rank, config.neighbours
        )));
    }
    if !(config.min_ratio.is_finite() && config.min_ratio >= 1.0 && config.z.is_finite()) {
        return Err(Error::invalid(format!(
            "hot-pixel detection needs min_ratio >= 1 and a finite z, got {} and {}",
            config.min_ratio, config.z
        )));
    }
    let t = frames.frame_count() as f64;
    let counts = frames.sum_range(0..frames.frame_count());
    let flux = counts.mapv(|k| mle_flux(k as f64, t, 0.0));
    let codes = cfa.codes();
    let w_code = crate::cfa::Channel::W.code();
    let p_floor = (2.0 / t).min(0.5);
    let mut mask = Array2::<bool>::from_elem((h, w), false);
    mask.axis_iter_mut(ndarray::Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut row)| {
            for x in 0..w {
                let code = codes[[y, x]];
                let same = nearest_where((h, w), (y, x), config.neighbours, |yy, xx| {
                    codes[[yy, xx]] == code
                });
                if same.len() < config.rank {
                    continue;
                }
                let mut values: Vec<f64> = same.iter().map(|&p| flux[p]).collect();
                values.sort_unstable_by(|a, b| b.total_cmp(a));
                let reference = values[config.rank - 1].max(0.0);
                let p = detection_probability(reference, 0.0)
                    .max(p_floor)
                    .min(1.0 - SATURATION_MARGIN / t);
                let sigma = mle_variance_from_probability(p, t).sqrt();
                let mut threshold =
                    (config.min_ratio * reference).max(reference + config.z * sigma);
                if code != w_code {
                    let weight = w_weights[code as usize];
                    let mut whites: Vec<f64> = (y.saturating_sub(1)..(y + 2).min(h))
                        .flat_map(|yy| {
                            (x.saturating_sub(1)..(x + 2).min(w)).map(move |xx| (yy, xx))
                        })
                        .filter(|&p| codes[p] == w_code)
                        .map(|p| flux[p])
                        .collect();
                    whites.sort_unstable_by(|a, b| b.total_cmp(a));
                    if weight > 0.0 && whites.len() >= 2 {
                        threshold = threshold.max(whites[1] / weight);
                    }
                }
                row[x] = flux[[y, x]] > threshold;
            }
        });
    Ok(mask)
}

/// Gives `capture` a hot-pixel mask detected from its own frames ([`detect_hot_pixels`]) when
/// it names none; returns how many were found, or `None` when the capture had a mask.
pub fn self_calibrate(
    capture: &mut crate::capture::Capture,
    config: &HotPixelDetectConfig,
) -> Result<Option<usize>> {
    if capture.hot_pixels.is_some() {
        return Ok(None);
    }
    let mask = detect_hot_pixels(
        &capture.frames,
        &capture.cfa,
        capture.meta.w_weights,
        config,
    )?;
    let n = mask.iter().filter(|&&m| m).count();
    capture.hot_pixels = Some(mask);
    Ok(Some(n))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::frames::pack_bits;
    use crate::cfa::colorspad_cfa;
    use ndarray::Array3;
    use rand::Rng;

    /// The ChaCha8 blocks of `chacha8_blocks` (eight-lane and scalar paths) are the words of
    /// rand_chacha's `ChaCha8Rng` for the same seed, stream and position, for streams and block
    /// counters that use their high words too.
    #[test]
    fn chacha8_blocks_equal_the_generator_words() {
        let cfa = colorspad_cfa();
        let mask = Array2::from_elem((cfa.height(), cfa.width()), false);
        let corrector = HotPixelCorrector::new(&cfa, &mask, 8, 77).unwrap();
        let jobs: Vec<(u64, u64)> = (0..21u64)
            .map(|i| {
                let stream = i.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> ((i % 3) * 20);
                (stream, i * 7 + ((i % 4) << 33))
            })
            .collect();
        for isa in [Isa::generic(), Isa::current()] {
            let mut got = vec![[0u32; BLOCK_WORDS]; jobs.len()];
            chacha8_blocks(&corrector.key, &jobs, &mut got, isa);
            for (&(stream, block), got) in jobs.iter().zip(&got) {
                let mut rng = ChaCha8Rng::seed_from_u64(77);
                rng.set_stream(stream);
                rng.set_word_pos(block as u128 * BLOCK_WORDS as u128);
                let expected: [u32; BLOCK_WORDS] = std::array::from_fn(|_| rng.next_u32());
                assert_eq!(*got, expected, "{isa:?}: stream {stream} block {block}");
                assert_eq!(chacha8_block(&corrector.key, stream, block), expected);
            }
        }
    }

    /// The grouped, frame-by-frame draws of `corrected_block_sum` are the per-pixel draws of
    /// supplement §1.4 as a plain loop makes them (more hot pixels than one group holds, a
    /// last group of fewer than eight times a whole number, chunks of frames not multiples of
    /// eight): eight candidates and five (the AVX2 paths of [`HotSites`], five not a power of
    /// two) and twelve (the scalar path).
    #[test]
    fn grouped_correction_matches_per_pixel_draws() {
        for k in [8, 5, 12] {
            grouped_correction_matches_per_pixel_draws_with(k);
        }
    }

    fn grouped_correction_matches_per_pixel_draws_with(k: usize) {
        let cfa = colorspad_cfa();
        let (h, w) = (cfa.height(), cfa.width());
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut mask = Array2::from_shape_fn((h, w), |_| rng.gen_bool(0.02));
        if mask.iter().filter(|&&m| m).count() % 8 == 0 {
            mask[[h / 2, w / 2]] ^= true;
        }
        let t = 157;
        let bits = Array3::from_shape_fn((t, h, w), |_| rng.gen_bool(0.3) as u8);
        let frames = BinaryFrames::from_packed(pack_bits(&bits), w).unwrap();
        let corrector = HotPixelCorrector::new(&cfa, &mask, k, 9).unwrap();
        assert!(corrector.hot_count() > 3 * HOT_GROUP);
        assert_ne!(corrector.hot_count() % 8, 0, "a padded last group");
        #[cfg(target_arch = "x86_64")]
        if Isa::current().avx2() {
            // The vector path takes groups of up to eight candidates a pixel, not more.
            let spans = [(0, k.min(corrector.candidates[0].len()) as u64)];
            let sites: Vec<u32> = (0..k as u32).collect();
            assert_eq!(
                HotSites::new(&sites, &spans, &[0], 64, &(0..8), Isa::current()).is_some(),
                k <= 8
            );
        }
        let range = 5..t - 3;
        let got = corrector.corrected_block_sum(&frames, range.clone());
        // The AVX2 paths (where the CPU has them) and the portable ones give the same sums.
        assert_eq!(
            corrector.corrected_block_sum_on(&frames, range.clone(), Isa::current()),
            got
        );
        assert_eq!(
            corrector.corrected_block_sum_on(&frames, range.clone(), Isa::generic()),
            got
        );
        let mut expected = frames.sum_range(range.clone());
        for (&idx, cands) in corrector.hot.iter().zip(&corrector.candidates) {
            let mut stream = corrector.stream(idx, range.start);
            let mut count = 0;
            for f in range.clone() {
                let pick = ((stream.next_u32() as u64 * cands.len() as u64) >> 32) as usize;
                let (y, x) = cands[pick];
                count += bits[[f, y as usize, x as usize]] as u32;
            }
            expected[[idx / w, idx % w]] = count;
        }
        assert_eq!(got, expected);
    }
}
