//! Streaming capture output: frames are appended one at a time to `frames.npy` inside a
//! temporary directory, so converting 10^6 raw frames (or simulating them) needs memory for a
//! few frames only. Frames are bit-packed binary ([`CaptureWriter::create`]) or uint16 multi-bit
//! ([`CaptureWriter::create_multibit`]); the ground truth and further files (a simulation's
//! motion truth) may be added before the directory is renamed into place by
//! [`CaptureWriter::finish`]. Dropping the writer (an error, a panic) removes the temporary
//! directory, leaving nothing behind and any previous capture untouched.
#![forbid(unsafe_code)]

use super::write::check_extra_name;
use super::{
    commit_dir, npy, npy_writer, prepare_target, write_member, BinaryFrames, CaptureMeta,
    CFA_NPY_FILE, FRAMES_FILE, GROUND_TRUTH_FILE, HOT_PIXELS_FILE, META_FILE,
};
use crate::atomic::{temp_sibling, TempGuard};
use crate::cfa::Cfa;
use crate::error::{Error, Result};
use ndarray::{Array2, Array3, Dim};
use ndarray_npy::write_zeroed_npy;
use std::fs::{self, File};
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// Writes a capture directory whose frames arrive one by one (see the module documentation).
pub struct CaptureWriter {
    dir: PathBuf,
    existing: bool,
    // Declared before `tmp` so that the file is closed before the guard removes the directory.
    frames: Option<BufWriter<File>>,
    tmp: TempGuard,
    frame_count: usize,
    height: usize,
    width: usize,
    written: usize,
    /// Multi-bit (uint16) frames instead of bit-packed binary ones.
    multibit: bool,
    /// Files added besides the standard ones (their names, to refuse duplicates).
    extra_names: Vec<String>,
}

impl CaptureWriter {
    /// Starts a capture of `frame_count` frames of `height` x `width` pixels at `dir`: checks
    /// that `dir` may be written (absent, empty, or a capture to replace), creates the temporary
    /// directory and writes the `frames.npy` header.
    pub fn create(
        dir: impl AsRef<Path>,
        frame_count: usize,
        height: usize,
        width: usize,
    ) -> Result<CaptureWriter> {
        Self::start(dir.as_ref(), frame_count, height, width, false)
    }

    /// As [`Self::create`] for multi-bit frames: `frames.npy` holds little-endian uint16
    /// (T, H, W) digital numbers, and [`Self::finish`] needs metadata with a bit depth
    /// ([`CaptureMeta::multibit`]).
    pub fn create_multibit(
        dir: impl AsRef<Path>,
        frame_count: usize,
        height: usize,
        width: usize,
    ) -> Result<CaptureWriter> {
        Self::start(dir.as_ref(), frame_count, height, width, true)
    }

    fn start(
        dir: &Path,
        frame_count: usize,
        height: usize,
        width: usize,
        multibit: bool,
    ) -> Result<CaptureWriter> {
        if frame_count == 0 || height == 0 || width == 0 {
            return Err(Error::invalid(format!(
                "a capture needs at least one non-empty frame, got T={frame_count}, \
                 H={height}, W={width}"
            )));
        }
        let existing = prepare_target(dir)?;
        let tmp = TempGuard::dir(temp_sibling(dir)?);
        fs::create_dir(tmp.path()).map_err(|e| Error::io(dir, e))?;
        let shown = dir.join(FRAMES_FILE);
        let mut file =
            File::create(tmp.path().join(FRAMES_FILE)).map_err(|e| Error::io(&shown, e))?;
        if multibit {
            // The header exactly as `write_capture` writes multi-bit frames (ndarray-npy's), with
            // the file extended (sparsely) to its full size; the frames then overwrite the zeros.
            let data = frame_count
                .checked_mul(height * width * 2)
                .ok_or_else(|| Error::invalid(format!("{frame_count} frames overflow")))?;
            write_zeroed_npy::<u16, _>(&file, Dim([frame_count, height, width]))
                .map_err(|e| Error::io(&shown, std::io::Error::other(e)))?;
            let len = file.metadata().map_err(|e| Error::io(&shown, e))?.len();
            file.seek(SeekFrom::Start(len - data as u64))
                .map_err(|e| Error::io(&shown, e))?;
        } else {
            let header = npy::encode_header("|u1", &[frame_count, height, width.div_ceil(8)]);
            file.write_all(&header).map_err(|e| Error::io(&shown, e))?;
        }
        let out = BufWriter::with_capacity(1 << 22, file);
        Ok(CaptureWriter {
            dir: dir.to_path_buf(),
            existing,
            tmp,
            frames: Some(out),
            frame_count,
            height,
            width,
            written: 0,
            multibit,
            extra_names: Vec::new(),
        })
    }

    /// Bytes of one frame as stored: `H · ceil(W/8)` packed, `2 · H · W` multi-bit.
    pub fn frame_bytes(&self) -> usize {
        if self.multibit {
            2 * self.height * self.width
        } else {
            self.height * self.width.div_ceil(8)
        }
    }

    /// Frames written so far.
    pub fn written(&self) -> usize {
        self.written
    }

    /// Appends one frame as stored ([`Self::frame_bytes`] bytes): packed MSB first, or
    /// little-endian uint16 samples row by row for a multi-bit capture.
    pub fn write_frame(&mut self, packed: &[u8]) -> Result<()> {
        if packed.len() != self.frame_bytes() {
            return Err(Error::invalid(format!(
                "a frame of {}x{} is stored in {} bytes, got {}",
                self.height,
                self.width,
                self.frame_bytes(),
                packed.len()
            )));
        }
        if self.written >= self.frame_count {
            return Err(Error::invalid(format!(
                "the capture was declared with {} frames; cannot write more",
                self.frame_count
            )));
        }
        let shown = self.dir.join(FRAMES_FILE);
        let out = self
            .frames
            .as_mut()
            .ok_or_else(|| Error::invalid("frames.npy is already complete"))?;
        out.write_all(packed).map_err(|e| Error::io(&shown, e))?;
        self.written += 1;
        Ok(())
    }

    /// Appends one multi-bit frame, `H · W` samples row by row (a multi-bit capture only).
    pub fn write_frame_u16(&mut self, samples: &[u16]) -> Result<()> {
        if !self.multibit {
            return Err(Error::invalid(
                "the capture was created for binary frames; multi-bit frames need \
                 CaptureWriter::create_multibit",
            ));
        }
        let bytes: Vec<u8> = samples.iter().flat_map(|v| v.to_le_bytes()).collect();
        self.write_frame(&bytes)
    }

    /// Writes `ground_truth.npy`, float32 (H, W, 3), into the capture.
    pub fn write_ground_truth(&mut self, truth: &Array3<f32>) -> Result<()> {
        if truth.dim() != (self.height, self.width, 3) {
            return Err(Error::invalid(format!(
                "ground truth is {:?}, expected ({}, {}, 3)",
                truth.dim(),
                self.height,
                self.width
            )));
        }
        write_member(
            self.tmp.path(),
            &self.dir,
            GROUND_TRUTH_FILE,
            npy_writer(truth),
        )
    }

    /// Writes a further file `name` (a plain, non-standard file name, e.g. the simulator's
    /// `motion.toml`) into the capture.
    pub fn write_extra_file(&mut self, name: &str, bytes: &[u8]) -> Result<()> {
        check_extra_name(name, self.extra_names.iter().any(|n| n == name))?;
        write_member(self.tmp.path(), &self.dir, name, |w| w.write_all(bytes))?;
        self.extra_names.push(name.to_string());
        Ok(())
    }

    /// Completes `frames.npy` (every declared frame must have been written) and memory-maps
    /// it, e.g. to detect hot pixels before [`Self::finish`].
    pub fn frames(&mut self) -> Result<BinaryFrames> {
        let shown = self.dir.join(FRAMES_FILE);
        if let Some(out) = self.frames.take() {
            if self.written != self.frame_count {
                return Err(Error::invalid(format!(
                    "{} of {} declared frames were written",
                    self.written, self.frame_count
                )));
            }
            out.into_inner()
                .map_err(|e| Error::io(&shown, e.into_error()))?;
        }
        BinaryFrames::open(&self.tmp.path().join(FRAMES_FILE), self.width)
    }

    /// Writes `cfa.npy`, the optional `hot_pixels.npy` and `capture.toml` (with the `extra`
    /// tables) and moves the capture into place.
    pub fn finish(
        mut self,
        cfa: &Cfa,
        meta: &CaptureMeta,
        hot_pixels: Option<&Array2<bool>>,
        extra: Option<&toml::Table>,
    ) -> Result<()> {
        self.frames()?;
        if cfa.codes().dim() != (self.height, self.width) {
            return Err(Error::invalid(format!(
                "the CFA is {}x{}, the frames are {}x{}",
                cfa.height(),
                cfa.width(),
                self.height,
                self.width
            )));
        }
        match (self.multibit, meta.multibit) {
            (false, Some(m)) => {
                return Err(Error::invalid(format!(
                    "the metadata says bit_depth {}, but the frames are binary",
                    m.bit_depth
                )))
            }
            (true, None) => {
                return Err(Error::invalid(
                    "multi-bit frames need metadata with a bit depth and gain \
                     (CaptureMeta::multibit)",
                ))
            }
            _ => {}
        }
        let mut meta = meta.clone();
        meta.hot_pixels = None;
        if let Some(mask) = hot_pixels {
            if mask.dim() != (self.height, self.width) {
                return Err(Error::invalid(format!(
                    "hot-pixel mask is {:?}, the frames are ({}, {})",
                    mask.dim(),
                    self.height,
                    self.width
                )));
            }
            meta.hot_pixels = Some(HOT_PIXELS_FILE.to_string());
        }
        if let Some(r) = meta.reference_frame {
            if r >= self.frame_count {
                return Err(Error::invalid(format!(
                    "reference_frame {r} must be < T = {}",
                    self.frame_count
                )));
            }
        }
        let toml_text = meta.to_toml_string(extra)?;
        let t = self.tmp.path().to_path_buf();
        write_member(&t, &self.dir, CFA_NPY_FILE, npy_writer(cfa.codes()))?;
        if let Some(mask) = hot_pixels {
            write_member(&t, &self.dir, HOT_PIXELS_FILE, npy_writer(mask))?;
        }
        write_member(&t, &self.dir, META_FILE, |w| {
            w.write_all(toml_text.as_bytes())
        })?;
        commit_dir(self.tmp, &self.dir, self.existing)
    }
}
