//! Photon cubes stored as `.npy`: bit-packed binary frames `(T, H, ceil(W/8))` (MSB first, the
//! capture format's own packing; bool or 0/1 `uint8` `(T, H, W)` also accepted), and
//! visionsim-style colour cubes `(T, H, ceil(W/8), 3)`: one bit-packed binary frame per R, G
//! and B channel (`np.packbits(bits, axis=2)` of a `(T, H, W, 3)` stack), which a chosen CFA
//! turns into one mosaicked frame.

use super::FrameSource;
use crate::capture::npy::{NpyDtype, NpyHeader};
use crate::capture::BinaryFrames;
use crate::cfa::Cfa;
use crate::error::{Error, Result};
use memmap2::Mmap;
use std::fs::File;
use std::path::{Path, PathBuf};

/// Opens a photon-cube `.npy`. A 3-D array is a stack of binary frames; its width is the CFA's
/// when `cfa` is given, else `8 · ceil(W/8)` for packed `uint8` (the packing cannot say how
/// many padding bits the last byte holds) and `W` for bool. A 4-D `(T, H, ceil(W/8), 3)` array
/// is an RGB cube and needs `cfa`.
pub fn open_npy(path: &Path, cfa: Option<&Cfa>) -> Result<Box<dyn FrameSource>> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    // SAFETY: read-only map of an input file the converter never writes.
    let map = unsafe { Mmap::map(&file) }.map_err(|e| Error::io(path, e))?;
    let header = NpyHeader::parse(&map).map_err(|m| Error::format(path, m))?;
    match header.shape.len() {
        3 => {
            let last = header.shape[2];
            let width = match (cfa, header.dtype) {
                (Some(c), _) => c.width(),
                (None, NpyDtype::U8) => last.checked_mul(8).ok_or_else(|| {
                    Error::format(path, format!("shape {:?} is too large", header.shape))
                })?,
                (None, _) => last,
            };
            drop(map);
            let frames = BinaryFrames::open(path, width)?;
            Ok(Box::new(NpyFrames {
                path: path.to_path_buf(),
                frames,
            }))
        }
        4 => {
            let cfa = cfa.ok_or_else(|| {
                Error::format(
                    path,
                    format!(
                        "an RGB photon cube {:?} needs a CFA (--cfa) to choose each pixel's \
                         channel",
                        header.shape
                    ),
                )
            })?;
            RgbCube::new(path, map, header, cfa.clone()).map(|c| Box::new(c) as _)
        }
        _ => Err(Error::format(
            path,
            format!(
                "expected a photon cube (T, H, W/8) or an RGB cube (T, H, W/8, 3), found shape \
                 {:?}",
                header.shape
            ),
        )),
    }
}

/// A 3-D `.npy` of binary frames.
struct NpyFrames {
    path: PathBuf,
    frames: BinaryFrames,
}

impl FrameSource for NpyFrames {
    fn describe(&self) -> String {
        format!("photon cube {}", self.path.display())
    }
    fn frame_count(&self) -> usize {
        self.frames.frame_count()
    }
    fn height(&self) -> usize {
        self.frames.height()
    }
    fn width(&self) -> usize {
        self.frames.width()
    }
    fn read_frame(&mut self, t: usize, out: &mut [u8]) -> Result<()> {
        let rb = self.frames.width().div_ceil(8);
        for (y, row) in out.chunks_exact_mut(rb).enumerate() {
            self.frames.packed_row_into(t, y, row);
        }
        Ok(())
    }
}

/// A visionsim-style `(T, H, ceil(W/8), 3)` cube seen through a CFA: an R, G or B pixel takes
/// its channel's bit; a W pixel fires when any channel fired, which is exact for a clear
/// filter with W = R + G + B and independent Poisson arrivals (P(no photon) is the product of
/// the channels' P(no photon), paper Eq. 2–4).
struct RgbCube {
    path: PathBuf,
    map: Mmap,
    offset: usize,
    shape: [usize; 4],
    cfa: Cfa,
}

impl RgbCube {
    fn new(path: &Path, map: Mmap, header: NpyHeader, cfa: Cfa) -> Result<RgbCube> {
        let s = &header.shape;
        let (t, h, b, c) = (s[0], s[1], s[2], s[3]);
        if header.dtype != NpyDtype::U8 {
            return Err(Error::format(
                path,
                format!("an RGB photon cube must be uint8, found '{}'", header.descr),
            ));
        }
        if header.fortran_order {
            return Err(Error::format(
                path,
                "Fortran-ordered arrays are not supported",
            ));
        }
        if c != 3 {
            return Err(Error::format(
                path,
                format!("an RGB photon cube has 3 channels last, found shape {s:?}"),
            ));
        }
        if t == 0 || h == 0 {
            return Err(Error::format(path, "the photon cube holds no frames"));
        }
        if (h, b) != (cfa.height(), cfa.width().div_ceil(8)) {
            return Err(Error::format(
                path,
                format!(
                    "cube frames are {h} rows of {b} packed bytes; the {}x{} CFA needs {} rows \
                     of {} bytes",
                    cfa.height(),
                    cfa.width(),
                    cfa.height(),
                    cfa.width().div_ceil(8)
                ),
            ));
        }
        let need = t
            .checked_mul(h)
            .and_then(|n| n.checked_mul(b * 3))
            .and_then(|n| n.checked_add(header.data_offset));
        if !matches!(need, Some(n) if n <= map.len()) {
            return Err(Error::format(
                path,
                format!("file is truncated: {} bytes, shape {s:?}", map.len()),
            ));
        }
        Ok(RgbCube {
            path: path.to_path_buf(),
            offset: header.data_offset,
            map,
            shape: [t, h, b, c],
            cfa,
        })
    }
}

impl FrameSource for RgbCube {
    fn describe(&self) -> String {
        format!("RGB photon cube {}", self.path.display())
    }
    fn frame_count(&self) -> usize {
        self.shape[0]
    }
    fn height(&self) -> usize {
        self.shape[1]
    }
    fn width(&self) -> usize {
        self.cfa.width()
    }
    fn read_frame(&mut self, t: usize, out: &mut [u8]) -> Result<()> {
        let [_, h, b, _] = self.shape;
        let frame = &self.map[self.offset + t * h * b * 3..][..h * b * 3];
        out.fill(0);
        let codes = self.cfa.codes();
        for y in 0..h {
            let row = &frame[y * b * 3..][..b * 3];
            for x in 0..self.cfa.width() {
                let (byte, mask) = (x / 8, 0x80u8 >> (x % 8));
                let bit = |c: usize| row[byte * 3 + c] & mask != 0;
                let fired = match codes[[y, x]] {
                    c @ 0..=2 => bit(c as usize),
                    _ => bit(0) || bit(1) || bit(2),
                };
                if fired {
                    out[y * b + byte] |= mask;
                }
            }
        }
        Ok(())
    }
}
