//! Frames: binary, bit-packed uint8 (T, H, ceil(W/8)), MSB first as `np.packbits` writes them, or
//! unpacked bool/uint8 0/1 (T, H, W); or multi-bit, uint16 (T, H, W) digital numbers of a
//! conventional sensor. Files are memory-mapped, never copied whole into memory, and the passes
//! over them release the pages behind them ([`BinaryFrames::release`]); block sums are
//! computed straight from the stored bytes (for binary frames, from the packed words). A sum is
//! the number of ones (binary) or the sum of digital numbers (multi-bit): the merge's "counts".

use super::npy::{NpyDtype, NpyHeader};
use crate::cpu::Isa;
use crate::error::{Error, Result};
use memmap2::Mmap;
use ndarray::{Array2, Array3};
use rayon::prelude::*;
use std::collections::HashMap;
use std::fs::File;
use std::ops::Range;
use std::path::Path;
use std::sync::{Arc, Mutex};

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
    /// Shared, so that a view of some frames ([`BinaryFrames::view`]) maps nothing again.
    Mapped {
        map: Arc<Mmap>,
        offset: usize,
    },
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
                map: Arc::new(map),
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
    #[inline]
    pub fn raw_row(&self, t: usize, y: usize) -> &[u8] {
        let rb = self.row_bytes();
        let start = (t * self.height + y) * rb;
        &self.data()[start..start + rb]
    }

    /// The stored bytes of frame `t`: its H rows of [`Self::raw_row`] one after another.
    #[inline]
    pub fn raw_frame(&self, t: usize) -> &[u8] {
        let frame_bytes = self.height * self.row_bytes();
        &self.data()[t * frame_bytes..(t + 1) * frame_bytes]
    }

    /// The bit of pixel `(y, x)` in frame `t` (for multi-bit frames: whether the sample is
    /// nonzero).
    pub fn bit(&self, t: usize, y: usize, x: usize) -> bool {
        self.sample(t, y, x) != 0
    }

    /// The sample of pixel `(y, x)` in frame `t`: its bit (0 or 1) or its digital number.
    #[inline]
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
    /// full scale). Packed frames are summed on the process's instruction set
    /// ([`Isa::current`]).
    pub fn sum_range(&self, frames: Range<usize>) -> Array2<u32> {
        self.sum_range_on(frames, Isa::current())
    }

    /// [`Self::sum_range`] on `isa` (every instruction set gives the same sums).
    fn sum_range_on(&self, frames: Range<usize>, isa: Isa) -> Array2<u32> {
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
            if self.layout == FrameLayout::Packed {
                out.par_chunks_mut(SUM_BAND_ROWS * w)
                    .enumerate()
                    .for_each(|(band, out)| {
                        let y0 = band * SUM_BAND_ROWS;
                        self.sum_band_packed(start..end, y0..y0 + out.len() / w, out, isa)
                    });
            } else {
                out.par_chunks_mut(w)
                    .enumerate()
                    .for_each(|(y, out)| self.sum_row(start..end, y, out, isa));
            }
            self.release(start..end);
            start = end;
        }
        counts
    }

    /// Adds the counts of packed `frames` over `rows` to `out` (those rows' pixels,
    /// row-major), bit-sliced: the rows' bytes of every frame are read as 64-bit words (64
    /// pixels each), eight frames are added by a carry-save adder tree into a 4-bit count per
    /// pixel held in four words, and that count into eight bit-plane words (a count below 256
    /// per pixel), which are spread into `out` every [`PLANE_FLUSH`] frames. A few logic
    /// operations per word of eight frames instead of a table look-up per byte of every frame;
    /// the counts are the same integers (compiled for AVX2 where `isa` has it).
    fn sum_band_packed(&self, frames: Range<usize>, rows: Range<usize>, out: &mut [u32], isa: Isa) {
        #[cfg(target_arch = "x86_64")]
        {
            if isa.avx2() {
                // SAFETY: `isa` has AVX2, so the CPU has (an `Isa` never holds a feature the
                // CPU lacks).
                return unsafe { self.sum_band_packed_avx2(frames, rows, out) };
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = isa;
        self.sum_band_packed_generic(frames, rows, out)
    }

    /// [`Self::sum_band_packed_generic`] compiled for AVX2 (its word loops vectorise four
    /// words at a time).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn sum_band_packed_avx2(
        &self,
        frames: Range<usize>,
        rows: Range<usize>,
        out: &mut [u32],
    ) {
        self.sum_band_packed_generic(frames, rows, out)
    }

    #[inline(always)]
    fn sum_band_packed_generic(&self, frames: Range<usize>, rows: Range<usize>, out: &mut [u32]) {
        let rb = self.row_bytes();
        let frame_bytes = self.height * rb;
        let band_start = rows.start * rb;
        let nbytes = rows.len() * rb;
        let words = nbytes.div_ceil(8);
        let data = self.data();
        // The band of frame t as whole words (the last one zero-padded).
        let band_words = |t: usize, buf: &mut Vec<u64>| {
            let bytes = &data[t * frame_bytes + band_start..t * frame_bytes + band_start + nbytes];
            buf.clear();
            let chunks = bytes.chunks_exact(8);
            let tail = chunks.remainder();
            buf.extend(chunks.map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes"))));
            if !tail.is_empty() {
                let mut last = [0u8; 8];
                last[..tail.len()].copy_from_slice(tail);
                buf.push(u64::from_le_bytes(last));
            }
        };
        // planes[k * words + j]: bit k of the count of every pixel of word j.
        let mut planes = vec![0u64; 8 * words];
        let mut group: [Vec<u64>; 8] = std::array::from_fn(|_| Vec::with_capacity(words));
        let mut start = frames.start;
        while start < frames.end {
            let end = (start + PLANE_FLUSH).min(frames.end);
            let mut t = start;
            while t + 8 <= end {
                for (i, buf) in group.iter_mut().enumerate() {
                    band_words(t + i, buf);
                }
                add_eight(&mut planes, &group, words);
                t += 8;
            }
            while t < end {
                band_words(t, &mut group[0]);
                add_one(&mut planes, &group[0], words);
                t += 1;
            }
            flush_planes(&mut planes, words, nbytes, rb, self.width, out);
            start = end;
        }
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

    /// Adds row `y`'s samples over `frames` to `out` (unpacked and multi-bit frames; packed
    /// ones are summed by [`Self::sum_band_packed`], on `isa`).
    fn sum_row(&self, frames: Range<usize>, y: usize, out: &mut [u32], isa: Isa) {
        match self.layout {
            FrameLayout::Packed => self.sum_band_packed(frames, y..y + 1, out, isa),
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
        let bytes = self.window_bytes(&window)?;
        let storage = match self.storage {
            Storage::Owned(mut v) => {
                v.truncate(bytes.end);
                v.drain(..bytes.start);
                Storage::Owned(v)
            }
            Storage::Mapped { map, offset } => Storage::Mapped {
                map,
                offset: offset + bytes.start,
            },
        };
        Ok(BinaryFrames {
            storage,
            frame_count: window.len(),
            shared: Mutex::default(),
            ..self
        })
    }

    /// The frames in `window` (indices into this stack) as a stack of their own, frames
    /// `0..window.len()`, leaving `self` as it is: a memory map is shared (nothing is read),
    /// frames held in memory are copied. For reconstructions of parts of one capture (the
    /// windows of a video).
    pub fn view(&self, window: Range<usize>) -> Result<BinaryFrames> {
        let bytes = self.window_bytes(&window)?;
        let storage = match &self.storage {
            Storage::Owned(v) => Storage::Owned(v[bytes].to_vec()),
            Storage::Mapped { map, offset } => Storage::Mapped {
                map: Arc::clone(map),
                offset: offset + bytes.start,
            },
        };
        Ok(BinaryFrames {
            storage,
            layout: self.layout,
            frame_count: window.len(),
            height: self.height,
            width: self.width,
            shared: Mutex::default(),
        })
    }

    /// The byte range (from the first frame) of the frames in `window`; errors when it is
    /// empty or outside the stack.
    fn window_bytes(&self, window: &Range<usize>) -> Result<Range<usize>> {
        if window.start >= window.end || window.end > self.frame_count {
            return Err(Error::invalid(format!(
                "frame window {}:{} is empty or outside the capture's {} frames",
                window.start, window.end, self.frame_count
            )));
        }
        let frame_bytes = self.height * self.row_bytes();
        Ok(window.start * frame_bytes..window.end * frame_bytes)
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

/// Frames of eight bit-planes before their counts could overflow (a multiple of 8 below 256).
const PLANE_FLUSH: usize = 248;

/// Rows summed by one task of [`BinaryFrames::sum_range`] (packed frames).
const SUM_BAND_ROWS: usize = 16;

/// Full adder of three bit vectors: (sum, carry).
#[inline(always)]
fn full_add(a: u64, b: u64, c: u64) -> (u64, u64) {
    let u = a ^ b;
    (u ^ c, (a & b) | (u & c))
}

/// Adds the bits of eight frames (`frames[i][j]`: word j of frame i) to the bit-planes
/// (`planes[k * words + j]`): a carry-save tree makes each pixel's 4-bit count of ones of the
/// eight, added to the 8-bit plane count with carries.
#[inline(always)]
fn add_eight(planes: &mut [u64], frames: &[Vec<u64>; 8], words: usize) {
    let (p0, rest) = planes.split_at_mut(words);
    let (p1, rest) = rest.split_at_mut(words);
    let (p2, rest) = rest.split_at_mut(words);
    let (p3, rest) = rest.split_at_mut(words);
    let (p4, rest) = rest.split_at_mut(words);
    let (p5, rest) = rest.split_at_mut(words);
    let (p6, p7) = rest.split_at_mut(words);
    let f: [&[u64]; 8] = std::array::from_fn(|i| &frames[i][..words]);
    for j in 0..words {
        let (s1, c1) = full_add(f[0][j], f[1][j], f[2][j]);
        let (s2, c2) = full_add(f[3][j], f[4][j], f[5][j]);
        let (s3, c3) = (f[6][j] ^ f[7][j], f[6][j] & f[7][j]);
        let (ones, c4) = full_add(s1, s2, s3);
        let (t1, d1) = full_add(c1, c2, c3);
        let (twos, d2) = (t1 ^ c4, t1 & c4);
        let (fours, eights) = (d1 ^ d2, d1 & d2);
        // The plane count plus (eights, fours, twos, ones).
        let (b0, carry) = (p0[j] ^ ones, p0[j] & ones);
        let (b1, carry) = full_add(p1[j], twos, carry);
        let (b2, carry) = full_add(p2[j], fours, carry);
        let (b3, carry) = full_add(p3[j], eights, carry);
        let (b4, carry) = (p4[j] ^ carry, p4[j] & carry);
        let (b5, carry) = (p5[j] ^ carry, p5[j] & carry);
        let (b6, carry) = (p6[j] ^ carry, p6[j] & carry);
        let b7 = p7[j] ^ carry;
        (p0[j], p1[j], p2[j], p3[j]) = (b0, b1, b2, b3);
        (p4[j], p5[j], p6[j], p7[j]) = (b4, b5, b6, b7);
    }
}

/// Adds the bits of one frame (`frame[j]`: word j) to the bit-planes of [`add_eight`].
#[inline(always)]
fn add_one(planes: &mut [u64], frame: &[u64], words: usize) {
    for (j, &bits) in frame[..words].iter().enumerate() {
        let mut carry = bits;
        for k in 0..8 {
            let p = &mut planes[k * words + j];
            let next = *p & carry;
            *p ^= carry;
            carry = next;
        }
    }
}

/// Adds the counts held in the bit-planes of [`add_eight`] (words of `nbytes` packed bytes of
/// rows of `row_bytes` bytes, `width` pixels) to `out` (those rows' pixels) and clears them.
fn flush_planes(
    planes: &mut [u64],
    words: usize,
    nbytes: usize,
    row_bytes: usize,
    width: usize,
    out: &mut [u32],
) {
    for byte in 0..nbytes {
        let (j, shift) = (byte / 8, 8 * (byte % 8));
        // Eight byte lanes, lane i the count of pixel 8·column + i.
        let mut lanes = 0u64;
        for k in 0..8 {
            lanes += SPREAD[((planes[k * words + j] >> shift) & 0xFF) as usize] << k;
        }
        let (row, column) = (byte / row_bytes, byte % row_bytes);
        let first = row * width + 8 * column;
        let pixels = (width - 8 * column).min(8);
        for (o, count) in out[first..first + pixels]
            .iter_mut()
            .zip(lanes.to_le_bytes())
        {
            *o += count as u32;
        }
    }
    planes.fill(0);
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
    fn bit_sliced_sums_match_plain_counts() {
        // Widths with and without a partial byte, bands whose bytes end inside a word, ranges
        // crossing the plane flush and leaving odd frames beside the groups of eight.
        for (t, h, w) in [(530, 37, 61), (70, 3, 64), (9, 40, 5)] {
            let bits = random_bits(t, h, w, (t + w) as u64);
            let frames = BinaryFrames::from_packed(pack_bits(&bits), w).unwrap();
            for range in [0..t, 1..t.min(260), 3..4, 2..2] {
                let expected = Array2::from_shape_fn((h, w), |(y, x)| {
                    range.clone().map(|f| bits[[f, y, x]] as u32).sum::<u32>()
                });
                assert_eq!(
                    frames.sum_range(range.clone()),
                    expected,
                    "{t} {h} {w} {range:?}"
                );
                // The AVX2 build of the bit-sliced sums (where the CPU has it) and the
                // portable one agree exactly.
                for isa in [Isa::generic(), Isa::current()] {
                    assert_eq!(
                        frames.sum_range_on(range.clone(), isa),
                        expected,
                        "{isa:?}: {t} {h} {w} {range:?}"
                    );
                }
            }
        }
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
    fn views_hold_their_frames_and_leave_the_stack_whole() {
        let (t, h, w) = (40, 3, 13);
        let bits = random_bits(t, h, w, 5);
        let packed = pack_bits(&bits);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frames.npy");
        ndarray_npy::write_npy(&path, &packed).unwrap();
        let mapped = BinaryFrames::open(&path, w).unwrap();
        let owned = BinaryFrames::from_packed(packed, w).unwrap();
        for stack in [&mapped, &owned] {
            let view = stack.view(10..25).unwrap();
            assert_eq!(view.frame_count(), 15);
            for f in 0..15 {
                for y in 0..h {
                    for x in 0..w {
                        assert_eq!(view.sample(f, y, x), bits[[10 + f, y, x]] as u32);
                    }
                }
            }
            // A view of a view counts from the view's first frame; the stack is unchanged.
            let inner = view.view(5..6).unwrap();
            assert_eq!(inner.sum_range(0..1), stack.sum_range(15..16));
            assert_eq!(stack.frame_count(), t);
            assert!(stack.view(30..41).is_err());
            assert!(stack.view(5..5).is_err());
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
