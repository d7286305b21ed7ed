//! Hot-pixel correction and dark-count calibration (supplement §1.4, Fig. 2; paper Fig. 5).
//!
//! A hot pixel fires far more often than its neighbours even in the dark. Left alone, hot pixels
//! form a static pattern that every block image shares, so block matching is pulled toward zero
//! motion (paper Fig. 5). Following supplement §1.4, each hot pixel takes, in every binary frame,
//! the bit of one of its `k` nearest non-hot neighbours behind the same colour filter, drawn at
//! random. The draw is a function of `(seed, pixel, frame)` only, so block sums do not depend on
//! block boundaries or thread count.
//!
//! Files: this one the corrector (candidates and the grouped, frame-by-frame draws),
//! `chacha` the ChaCha8 blocks the draws are words of, `calibrate` the dark-frame rate map and
//! the self-calibration of captures without one, `x86` the AVX2 kernels of the draws.

mod calibrate;
mod chacha;
#[cfg(target_arch = "x86_64")]
mod x86;

pub use calibrate::{
    dark_count_rate_map, detect_hot_pixels, hot_pixel_mask, self_calibrate, HotPixelDetectConfig,
};

use crate::capture::frames::FrameLayout;
use crate::capture::BinaryFrames;
use crate::cfa::Cfa;
use crate::cpu::Isa;
use crate::error::{Error, Result};
use calibrate::nearest_where;
use chacha::chacha8_blocks;
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
    /// Number of nearest same-colour, non-hot pixels a hot pixel draws from (default 8: the
    /// ring of nearest sites of one colour's lattice, within about one lattice spacing, yet not
    /// a copy of a single neighbour's noise and texture; docs/tuning.md).
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
pub(super) const HOT_GROUP: usize = 64;

/// Frames whose draws [`HotPixelCorrector::corrected_block_sum`] makes at a time (per hot pixel
/// of a group): chunks end at multiples of it, so that a chunk's draws lie in at most
/// `DRAW_CHUNK / 16` ChaCha blocks of each pixel's stream.
const DRAW_CHUNK: usize = 64;

/// 32-bit words of one ChaCha block.
pub(super) const BLOCK_WORDS: usize = 16;

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
    pub(super) key: [u32; 8],
    /// Flat pixel index `y * W + x` of each hot pixel.
    pub(super) hot: Vec<usize>,
    /// For each hot pixel, its candidates' `(y, x)`, nearest first.
    pub(super) candidates: Vec<Vec<(u32, u32)>>,
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
        // frame: the draws and reads fused, eight pixels at a time ([`x86::HotSites`]).
        #[cfg(target_arch = "x86_64")]
        {
            let frame_bytes = frames.height() * row_bytes;
            if let Some(sites8) = x86::HotSites::new(&sites, &spans, hot, frame_bytes, &span, isa) {
                sites8.count_drawn(&self.key, frames, range.clone(), &span, &mut counts);
                return counts;
            }
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

#[cfg(test)]
mod tests;
