//! Frames: binary, bit-packed uint8 (T, H, ceil(W/8)), MSB first as `np.packbits` writes them, or
//! unpacked bool/uint8 0/1 (T, H, W); or multi-bit, uint16 (T, H, W) digital numbers of a
//! conventional sensor. Files are memory-mapped, never copied whole into memory, and the passes
//! over them release the pages behind them ([`BinaryFrames::release`]); block sums are
//! computed straight from the stored bytes (for binary frames, from the packed words). A sum is
//! the number of ones (binary) or the sum of digital numbers (multi-bit): the merge's "counts".

use super::npy::{NpyDtype, NpyHeader};
use crate::error::{Error, Result};
use memmap2::Mmap;
use ndarray::{Array2, Array3};
use rayon::prelude::*;
use std::collections::HashMap;
use std::fs::File;
use std::ops::Range;
use std::path::Path;
use std::sync::Mutex;

/// How the bits of one frame row are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameLayout {
    /// ceil(W/8) bytes per row, MSB first.
    Packed,
    /// W bytes per row, each 0 or 1 (nonzero counts as 1).
    Unpacked,
    /// 2·W bytes per row: little-endian uint16 digital numbers (multi-bit frames).
    MultiBit,
}

#[derive(Debug)]
enum Storage {
    Owned(Vec<u8>),
    Mapped { map: Mmap, offset: usize },
}

/// A stack of T frames of H x W pixels: binary (the paper's SPAD and jot frames) or multi-bit
/// ([`FrameLayout::MultiBit`], a conventional sensor's digital numbers). [`Self::sum_range`]
/// and [`Self::sample`] work for both; the bit accessors are for binary frames.
#[derive(Debug)]
pub struct BinaryFrames {
    storage: Storage,
    layout: FrameLayout,
    frame_count: usize,
    height: usize,
    width: usize,
    /// Sums kept by [`Self::shared_sum`].
    shared: Mutex<SharedSums>,
}

/// Budget of the sums [`BinaryFrames::shared_sum`] keeps, bytes: 256 sums of 496x254 as u16
/// (the blocks of about 100,000 frames at 0.1 photons per frame), so that a reconstruction
/// stays within its memory bound for any T (sums beyond it are made again when asked again).
const SHARED_SUM_BYTES: usize = 64 << 20;

/// Per-pixel sums over frame ranges, as u16 (a binary sum over fewer than 65,536 frames fits),
/// within [`SHARED_SUM_BYTES`].
#[derive(Debug, Default)]
struct SharedSums {
    sums: HashMap<(usize, usize), Vec<u16>>,
    bytes: usize,
}

/// Byte `v` spread into eight byte lanes of a u64, MSB of `v` in the lowest lane, so that lane
/// `i` holds bit `7 - i` (pixel `8·k + i` of the row).
const fn spread_table() -> [u64; 256] {
    let mut table = [0u64; 256];
    let mut v = 0;
    while v < 256 {
        let mut lanes = 0u64;
        let mut i = 0;
        while i < 8 {
            if (v >> (7 - i)) & 1 == 1 {
                lanes |= 1u64 << (8 * i);
            }
            i += 1;
        }
        table[v] = lanes;
        v += 1;
    }
    table
}
static SPREAD: [u64; 256] = spread_table();

/// Frames summed at a time by [`BinaryFrames::sum_range`] before their mapped pages are
/// released (16 MB of 496x254 packed frames).
const SUM_CHUNK_FRAMES: usize = 1024;

/// Frames added into the byte lanes of one u64 before they could overflow (255 max per lane).
const LANE_FLUSH: usize = 255;

impl BinaryFrames {
    /// Memory-maps `path` (a `.npy`) holding frames `width` pixels wide: uint8 (T, H, ceil(W/8))
    /// packed, or bool/uint8 (T, H, W) unpacked.
    pub fn open(path: &Path, width: usize) -> Result<BinaryFrames> {
        let file = File::open(path).map_err(|e| Error::io(path, e))?;
        // SAFETY: the file is opened read-only; the capture format treats inputs as immutable.
        let map = unsafe { Mmap::map(&file) }.map_err(|e| Error::io(path, e))?;
        let header = NpyHeader::parse(&map).map_err(|m| Error::format(path, m))?;
        if header.fortran_order {
            return Err(Error::format(
                path,
                "Fortran-ordered arrays are not supported",
            ));
        }
        let shape = &header.shape;
        if shape.len() != 3 {
            return Err(Error::format(
                path,
                format!("expected a 3-D array (T, H, W or W/8), found shape {shape:?}"),
            ));
        }
        let (t, h, last) = (shape[0], shape[1], shape[2]);
        let layout = match header.dtype {
            NpyDtype::Bool => FrameLayout::Unpacked,
            NpyDtype::U16 if last == width => FrameLayout::MultiBit,
            NpyDtype::U16 => {
                return Err(Error::format(
                    path,
                    format!("uint16 frames have width {last}, the CFA has width {width}"),
                ))
            }
            NpyDtype::U8 if last == width.div_ceil(8) && last != width => FrameLayout::Packed,
            NpyDtype::U8 if last == width => FrameLayout::Unpacked,
            NpyDtype::U8 => {
                return Err(Error::format(
                    path,
                    format!(
                        "last dimension {last} matches neither the CFA width {width} (unpacked) \
                         nor ceil({width}/8) = {} (bit-packed)",
                        width.div_ceil(8)
                    ),
                ))
            }
            _ => {
                return Err(Error::format(
                    path,
                    format!(
                        "dtype '{}' is not supported for frames (need uint8 or bool for binary \
                         frames, little-endian uint16 for multi-bit frames)",
                        header.descr
                    ),
                ))
            }
        };
        if layout == FrameLayout::Unpacked && last != width {
            return Err(Error::format(
                path,
                format!("bool frames have width {last}, the CFA has width {width}"),
            ));
        }
        if t == 0 {
            return Err(Error::format(path, "the capture holds no frames (T = 0)"));
        }
        if h == 0 || width == 0 {
            return Err(Error::format(path, "frames have zero height or width"));
        }
        let item = if layout == FrameLayout::MultiBit {
            2
        } else {
            1
        };
        let expected = t
            .checked_mul(h)
            .and_then(|n| n.checked_mul(last))
            .and_then(|n| n.checked_mul(item))
            .and_then(|n| n.checked_add(header.data_offset));
        let Some(_end) = expected.filter(|&e| e <= map.len()) else {
            return Err(Error::format(
                path,
                format!(
                    "file is truncated: {} bytes, shape {shape:?} needs {}",
                    map.len(),
                    expected.map_or("more than usize::MAX".to_string(), |e| e.to_string())
                ),
            ));
        };
        Ok(BinaryFrames {
            storage: Storage::Mapped {
                map,
                offset: header.data_offset,
            },
            layout,
            frame_count: t,
            height: h,
            width,
            shared: Mutex::default(),
        })
    }

    /// Wraps packed frames held in memory, uint8 (T, H, ceil(width/8)).
    pub fn from_packed(packed: Array3<u8>, width: usize) -> Result<BinaryFrames> {
        let (t, h, bytes) = packed.dim();
        if bytes != width.div_ceil(8) {
            return Err(Error::invalid(format!(
                "packed frames have {bytes} bytes per row, width {width} needs {}",
                width.div_ceil(8)
            )));
        }
        if t == 0 || h == 0 || width == 0 {
            return Err(Error::invalid("packed frames are empty"));
        }
        let data = if packed.is_standard_layout() {
            packed.into_raw_vec_and_offset().0
        } else {
            packed.iter().copied().collect()
        };
        Ok(BinaryFrames {
            storage: Storage::Owned(data),
            layout: FrameLayout::Packed,
            frame_count: t,
            height: h,
            width,
            shared: Mutex::default(),
        })
    }

    /// Wraps multi-bit frames held in memory, uint16 (T, H, W) digital numbers.
    pub fn from_multibit(frames: &Array3<u16>) -> Result<BinaryFrames> {
        let (t, h, w) = frames.dim();
        if t == 0 || h == 0 || w == 0 {
            return Err(Error::invalid("multi-bit frames are empty"));
        }
        let data: Vec<u8> = frames.iter().flat_map(|v| v.to_le_bytes()).collect();
        Ok(BinaryFrames {
            storage: Storage::Owned(data),
            layout: FrameLayout::MultiBit,
            frame_count: t,
            height: h,
            width: w,
            shared: Mutex::default(),
        })
    }

    /// Whether the frames are multi-bit digital numbers (not binary).
    pub fn is_multibit(&self) -> bool {
        self.layout == FrameLayout::MultiBit
    }

    /// The largest sample of any frame (0 or 1 for binary frames); parallel over frames.
    pub fn max_sample(&self) -> u32 {
        (0..self.frame_count)
            .into_par_iter()
            .map(|t| {
                (0..self.height)
                    .map(|y| self.row_samples(t, y).max().unwrap_or(0))
                    .max()
                    .unwrap_or(0)
            })
            .max()
            .unwrap_or(0)
    }

    /// The samples of row `y` of frame `t` (bits as 0/1, or digital numbers).
    fn row_samples(&self, t: usize, y: usize) -> impl Iterator<Item = u32> + '_ {
        (0..self.width).map(move |x| self.sample(t, y, x))
    }

    /// Number of frames T.
    pub fn frame_count(&self) -> usize {
        self.frame_count
    }

    /// Height H.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Width W.
    pub fn width(&self) -> usize {
        self.width
    }

    /// How rows are stored.
    pub fn layout(&self) -> FrameLayout {
        self.layout
    }

    fn row_bytes(&self) -> usize {
        match self.layout {
            FrameLayout::Packed => self.width.div_ceil(8),
            FrameLayout::Unpacked => self.width,
            FrameLayout::MultiBit => 2 * self.width,
        }
    }

    fn data(&self) -> &[u8] {
        match &self.storage {
            Storage::Owned(v) => v,
            Storage::Mapped { map, offset } => &map[*offset..],
        }
    }

    /// The stored bytes of row `y` of frame `t` (packed or unpacked, see [`Self::layout`]).
    pub fn raw_row(&self, t: usize, y: usize) -> &[u8] {
        let rb = self.row_bytes();
        let start = (t * self.height + y) * rb;
        &self.data()[start..start + rb]
    }

    /// The bit of pixel `(y, x)` in frame `t` (for multi-bit frames: whether the sample is
    /// nonzero).
    pub fn bit(&self, t: usize, y: usize, x: usize) -> bool {
        self.sample(t, y, x) != 0
    }

    /// The sample of pixel `(y, x)` in frame `t`: its bit (0 or 1) or its digital number.
    pub fn sample(&self, t: usize, y: usize, x: usize) -> u32 {
        let row = self.raw_row(t, y);
        match self.layout {
            FrameLayout::Packed => ((row[x / 8] >> (7 - x % 8)) & 1) as u32,
            FrameLayout::Unpacked => (row[x] != 0) as u32,
            FrameLayout::MultiBit => u16::from_le_bytes([row[2 * x], row[2 * x + 1]]) as u32,
        }
    }

    /// Per-pixel count of ones (binary) or sum of digital numbers (multi-bit) over `frames`,
    /// (H, W); parallel over rows. Multi-bit sums saturate at `u32::MAX` (2^16 frames of 16-bit
    /// full scale).
    pub fn sum_range(&self, frames: Range<usize>) -> Array2<u32> {
        assert!(
            frames.start <= frames.end && frames.end <= self.frame_count,
            "frame range {frames:?} outside 0..{}",
            self.frame_count
        );
        let (h, w) = (self.height, self.width);
        let mut counts = Array2::<u32>::zeros((h, w));
        let out = counts.as_slice_mut().expect("fresh array is contiguous");
        // In chunks of frames, each released once summed: a sum over a whole capture keeps a
        // bounded part of a memory-mapped file resident (the sums are integers, so chunking
        // does not change them).
        let mut start = frames.start;
        while start < frames.end {
            let end = (start + SUM_CHUNK_FRAMES).min(frames.end);
            out.par_chunks_mut(w)
                .enumerate()
                .for_each(|(y, out)| self.sum_row(start..end, y, out));
            self.release(start..end);
            start = end;
        }
        counts
    }

    /// [`Self::sum_range`] over `frames`, made once and shared by the stages that ask for the
    /// same range (alignment's block sums, the refinement's and the merge's sub-block sums:
    /// a sub-block that is a whole block is summed once for all three). Sums are kept as u16
    /// up to a fixed budget (64 MB; beyond it, and for sums that do not fit in u16, a sum is
    /// made again each time), until [`Self::forget_shared_sums`]. The values are those of
    /// [`Self::sum_range`] whichever way they come.
    pub fn shared_sum(&self, frames: Range<usize>) -> Array2<u32> {
        let key = (frames.start, frames.end);
        let (h, w) = (self.height, self.width);
        if let Some(kept) = self.lock_shared().sums.get(&key) {
            let values = kept.iter().map(|&v| v as u32).collect();
            return Array2::from_shape_vec((h, w), values).expect("kept sums match the shape");
        }
        let sums = self.sum_range(frames);
        let bytes = 2 * h * w;
        if let Some(narrow) = sums
            .iter()
            .map(|&v| u16::try_from(v).ok())
            .collect::<Option<Vec<u16>>>()
        {
            let mut shared = self.lock_shared();
            if shared.bytes + bytes <= SHARED_SUM_BYTES && !shared.sums.contains_key(&key) {
                shared.sums.insert(key, narrow);
                shared.bytes += bytes;
            }
        }
        sums
    }

    /// Drops the sums kept by [`Self::shared_sum`] (a reconstruction calls it when its merge is
    /// done).
    pub fn forget_shared_sums(&self) {
        *self.lock_shared() = SharedSums::default();
    }

    fn lock_shared(&self) -> std::sync::MutexGuard<'_, SharedSums> {
        // The kept sums are complete whenever the lock is released: a poisoned lock still
        // guards consistent data.
        self.shared.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Hands the memory-mapped pages of `frames` back to the operating system (`madvise`
    /// `MADV_DONTNEED`; Unix only, a no-op for frames held in memory). Passes over the frames
    /// call it behind them so that the resident memory of a capture larger than RAM stays
    /// bounded: the map is read-only, so a later read of the same frames faults the unchanged
    /// file pages back in (from the page cache, as a rule) and sees the same bytes.
    pub fn release(&self, frames: Range<usize>) {
        #[cfg(unix)]
        if let Storage::Mapped { map, offset } = &self.storage {
            let frame_bytes = self.height * self.row_bytes();
            let end = frames.end.min(self.frame_count);
            if frames.start >= end {
                return;
            }
            let start = offset + frames.start * frame_bytes;
            let len = (end - frames.start) * frame_bytes;
            // SAFETY: the map is a read-only file mapping that nothing in this process
            // writes; dropping its pages only makes the next access read the file again.
            // Advice is a hint: a failure changes nothing but memory use.
            let _ = unsafe {
                map.unchecked_advise_range(memmap2::UncheckedAdvice::DontNeed, start, len)
            };
        }
        #[cfg(not(unix))]
        let _ = frames;
    }

    fn sum_row(&self, frames: Range<usize>, y: usize, out: &mut [u32]) {
        match self.layout {
            FrameLayout::Packed => {
                let nbytes = self.row_bytes();
                let mut lanes = vec![0u64; nbytes];
                let mut pending = 0;
                for t in frames {
                    for (acc, &byte) in lanes.iter_mut().zip(self.raw_row(t, y)) {
                        *acc += SPREAD[byte as usize];
                    }
                    pending += 1;
                    if pending == LANE_FLUSH {
                        flush_lanes(&mut lanes, out);
                        pending = 0;
                    }
                }
                flush_lanes(&mut lanes, out);
            }
            FrameLayout::Unpacked => {
                for t in frames {
                    for (acc, &v) in out.iter_mut().zip(self.raw_row(t, y)) {
                        *acc += (v != 0) as u32;
                    }
                }
            }
            FrameLayout::MultiBit => {
                for t in frames {
                    for (acc, v) in out.iter_mut().zip(self.raw_row(t, y).chunks_exact(2)) {
                        *acc = acc.saturating_add(u16::from_le_bytes([v[0], v[1]]) as u32);
                    }
                }
            }
        }
    }

    /// Keeps only the frames in `window` (indices into this stack), which become frames
    /// `0..window.len()`; no data is copied (a memory map stays a memory map).
    pub fn window(self, window: Range<usize>) -> Result<BinaryFrames> {
        if window.start >= window.end || window.end > self.frame_count {
            return Err(Error::invalid(format!(
                "frame window {}:{} is empty or outside the capture's {} frames",
                window.start, window.end, self.frame_count
            )));
        }
        let frame_bytes = self.height * self.row_bytes();
        let skip = window.start * frame_bytes;
        let keep = window.len() * frame_bytes;
        let storage = match self.storage {
            Storage::Owned(mut v) => {
                v.truncate(skip + keep);
                v.drain(..skip);
                Storage::Owned(v)
            }
            Storage::Mapped { map, offset } => Storage::Mapped {
                map,
                offset: offset + skip,
            },
        };
        Ok(BinaryFrames {
            storage,
            frame_count: window.len(),
            shared: Mutex::default(),
            ..self
        })
    }

    /// Row `y` of frame `t` packed MSB first (`ceil(W/8)` bytes) into `out`, whatever the
    /// stored layout; padding bits of the last byte are zero.
    pub fn packed_row_into(&self, t: usize, y: usize, out: &mut [u8]) {
        let row = self.raw_row(t, y);
        match self.layout {
            FrameLayout::Packed => {
                out.copy_from_slice(row);
                if self.width & 7 != 0 {
                    let last = out.len() - 1;
                    out[last] &= 0xFFu8 << (8 - self.width % 8);
                }
            }
            FrameLayout::Unpacked | FrameLayout::MultiBit => {
                out.fill(0);
                for x in 0..self.width {
                    if self.sample(t, y, x) != 0 {
                        out[x / 8] |= 0x80 >> (x % 8);
                    }
                }
            }
        }
    }

    /// All frames bit-packed, uint8 (T, H, ceil(W/8)), MSB first (a copy; `frames.npy`'s layout
    /// for binary frames; multi-bit frames become "sample nonzero").
    pub fn to_packed(&self) -> Array3<u8> {
        let (t, h, w) = (self.frame_count, self.height, self.width);
        match self.layout {
            FrameLayout::Packed => {
                let bytes = t * h * w.div_ceil(8);
                Array3::from_shape_vec((t, h, w.div_ceil(8)), self.data()[..bytes].to_vec())
                    .expect("stored bytes match the shape")
            }
            FrameLayout::Unpacked | FrameLayout::MultiBit => {
                let bits = Array3::from_shape_fn((t, h, w), |(ti, y, x)| self.bit(ti, y, x) as u8);
                pack_bits(&bits)
            }
        }
    }

    /// All multi-bit frames as uint16 (T, H, W) (a copy; `frames.npy`'s layout); `None` for
    /// binary frames.
    pub fn to_multibit(&self) -> Option<Array3<u16>> {
        if self.layout != FrameLayout::MultiBit {
            return None;
        }
        let (t, h, w) = (self.frame_count, self.height, self.width);
        let values: Vec<u16> = self.data()[..2 * t * h * w]
            .chunks_exact(2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]))
            .collect();
        Some(Array3::from_shape_vec((t, h, w), values).expect("stored bytes match the shape"))
    }

    /// One frame unpacked to 0/1, (H, W).
    pub fn frame(&self, t: usize) -> Array2<u8> {
        Array2::from_shape_fn((self.height, self.width), |(y, x)| self.bit(t, y, x) as u8)
    }
}

fn flush_lanes(lanes: &mut [u64], out: &mut [u32]) {
    for (k, acc) in lanes.iter_mut().enumerate() {
        let bytes = acc.to_le_bytes();
        for (i, &b) in bytes.iter().enumerate() {
            if let Some(o) = out.get_mut(8 * k + i) {
                *o += b as u32;
            }
        }
        *acc = 0;
    }
}

/// Packs 0/1 frames (T, H, W) into uint8 (T, H, ceil(W/8)), MSB first (`np.packbits` order).
pub fn pack_bits(bits: &Array3<u8>) -> Array3<u8> {
    let (t, h, w) = bits.dim();
    let mut packed = Array3::<u8>::zeros((t, h, w.div_ceil(8)));
    for ((ti, y, x), &b) in bits.indexed_iter() {
        if b != 0 {
            packed[[ti, y, x / 8]] |= 0x80 >> (x % 8);
        }
    }
    packed
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_bits(t: usize, h: usize, w: usize, seed: u64) -> Array3<u8> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        Array3::from_shape_fn((t, h, w), |_| rng.gen_bool(0.3) as u8)
    }

    #[test]
    fn packed_sums_match_unpacked_counts_across_lane_flushes() {
        // 600 frames crosses the 255-frame lane flush twice; width 13 leaves a partial byte.
        let bits = random_bits(600, 5, 13, 7);
        let frames = BinaryFrames::from_packed(pack_bits(&bits), 13).unwrap();
        for range in [0..600, 17..300, 5..5] {
            let sums = frames.sum_range(range.clone());
            for y in 0..5 {
                for x in 0..13 {
                    let expected: u32 = range.clone().map(|t| bits[[t, y, x]] as u32).sum();
                    assert_eq!(sums[[y, x]], expected, "({y},{x}) over {range:?}");
                }
            }
        }
        assert_eq!(frames.frame(42), bits.index_axis(ndarray::Axis(0), 42));
    }

    #[test]
    fn shared_and_released_sums_match_plain_counts() {
        // 1300 frames cross the 1024-frame chunk of a sum; the file is memory-mapped.
        let (t, h, w) = (1300, 4, 21);
        let bits = random_bits(t, h, w, 3);
        let packed = pack_bits(&bits);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frames.npy");
        ndarray_npy::write_npy(&path, &packed).unwrap();
        let mapped = BinaryFrames::open(&path, w).unwrap();
        let owned = BinaryFrames::from_packed(packed, w).unwrap();
        for range in [0..t, 100..1200, 7..40, 7..40, 3..3] {
            let expected = Array2::from_shape_fn((h, w), |(y, x)| {
                range.clone().map(|f| bits[[f, y, x]] as u32).sum::<u32>()
            });
            assert_eq!(mapped.sum_range(range.clone()), expected, "{range:?}");
            for _ in 0..2 {
                assert_eq!(mapped.shared_sum(range.clone()), expected, "{range:?}");
                assert_eq!(owned.shared_sum(range.clone()), expected, "{range:?}");
            }
            mapped.release(range.clone());
            owned.release(range.clone());
            assert_eq!(mapped.sum_range(range.clone()), expected, "{range:?}");
            mapped.forget_shared_sums();
            assert_eq!(mapped.shared_sum(range.clone()), expected, "{range:?}");
        }
    }

    #[test]
    fn msb_first_bit_order() {
        let mut bits = Array3::<u8>::zeros((1, 1, 10));
        bits[[0, 0, 0]] = 1;
        bits[[0, 0, 9]] = 1;
        let packed = pack_bits(&bits);
        assert_eq!(packed.as_slice().unwrap(), &[0x80, 0x40]);
        let frames = BinaryFrames::from_packed(packed, 10).unwrap();
        assert!(frames.bit(0, 0, 0) && frames.bit(0, 0, 9) && !frames.bit(0, 0, 1));
    }
}
