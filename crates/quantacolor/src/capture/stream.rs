//! Streaming capture output: frames are appended one at a time to `frames.npy` inside a
//! temporary directory, so converting 10^6 raw frames needs memory for one frame only. The
//! directory is renamed into place by [`CaptureWriter::finish`]; dropping the writer (an error,
//! a panic) removes it, leaving nothing behind and any previous capture untouched.
#![forbid(unsafe_code)]

use super::{
    commit_dir, npy, npy_writer, prepare_target, write_member, BinaryFrames, CaptureMeta,
    CFA_NPY_FILE, FRAMES_FILE, HOT_PIXELS_FILE, META_FILE,
};
use crate::atomic::{temp_sibling, TempGuard};
use crate::cfa::Cfa;
use crate::error::{Error, Result};
use ndarray::Array2;
use std::fs::{self, File};
use std::io::{BufWriter, Write};
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
        let dir = dir.as_ref();
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
        let file = File::create(tmp.path().join(FRAMES_FILE)).map_err(|e| Error::io(&shown, e))?;
        let mut out = BufWriter::with_capacity(1 << 22, file);
        out.write_all(&npy::encode_header(
            "|u1",
            &[frame_count, height, width.div_ceil(8)],
        ))
        .map_err(|e| Error::io(&shown, e))?;
        Ok(CaptureWriter {
            dir: dir.to_path_buf(),
            existing,
            tmp,
            frames: Some(out),
            frame_count,
            height,
            width,
            written: 0,
        })
    }

    /// Bytes of one packed frame, `H · ceil(W/8)`.
    pub fn frame_bytes(&self) -> usize {
        self.height * self.width.div_ceil(8)
    }

    /// Frames written so far.
    pub fn written(&self) -> usize {
        self.written
    }

    /// Appends one frame, packed MSB first, `H · ceil(W/8)` bytes.
    pub fn write_frame(&mut self, packed: &[u8]) -> Result<()> {
        if packed.len() != self.frame_bytes() {
            return Err(Error::invalid(format!(
                "a frame of {}x{} packs into {} bytes, got {}",
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
