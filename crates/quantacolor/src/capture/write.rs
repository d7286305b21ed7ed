//! Writing a capture directory ([`write_capture`]): the parts checked for consistency, every
//! file written into a temporary sibling that replaces the target only when complete.

#![forbid(unsafe_code)]

use super::{
    npy, CaptureMeta, CFA_NPY_FILE, CFA_PNG_FILE, FRAMES_FILE, GROUND_TRUTH_FILE, HOT_PIXELS_FILE,
    META_FILE,
};
use crate::atomic::{temp_sibling, TempGuard};
use crate::cfa::Cfa;
use crate::error::{Error, Result};
use ndarray::{Array2, Array3};
use ndarray_npy::WriteNpyExt;
use std::fs::{self, File};
use std::io::{BufWriter, Write};
use std::path::Path;

/// The frames of a capture to write.
#[derive(Debug, Clone, Copy)]
pub enum FrameData<'a> {
    /// Binary frames, bit-packed uint8 (T, H, ceil(W/8)), MSB first.
    Packed(&'a Array3<u8>),
    /// Multi-bit frames, uint16 (T, H, W) digital numbers (the metadata must say `bit_depth`).
    MultiBit(&'a Array3<u16>),
}

impl FrameData<'_> {
    /// (T, H, last dimension) of the stored array.
    fn dim(&self) -> (usize, usize, usize) {
        match self {
            FrameData::Packed(a) => a.dim(),
            FrameData::MultiBit(a) => a.dim(),
        }
    }
}

/// Everything needed to write a capture directory.
#[derive(Debug, Clone)]
pub struct CaptureParts<'a> {
    /// The frames: packed binary or multi-bit.
    pub frames: FrameData<'a>,
    /// Width W in pixels (a packed array pads it to a multiple of 8).
    pub width: usize,
    pub cfa: &'a Cfa,
    pub meta: &'a CaptureMeta,
    /// Written as `hot_pixels.npy` (and named in `capture.toml`) when given.
    pub hot_pixels: Option<&'a Array2<bool>>,
    /// Written as `ground_truth.npy`, float32 (H, W, 3), when given.
    pub ground_truth: Option<&'a Array3<f32>>,
    /// Further files `(name, bytes)` written into the same atomic directory (e.g. the
    /// simulator's motion truth). Plain file names only, not one of the standard names.
    pub extra_files: Vec<(String, Vec<u8>)>,
    /// Extra tables merged into `capture.toml` (e.g. `[simulation]`); every value must be a table.
    pub extra_toml: Option<toml::Table>,
}

/// Names reserved for the standard files of a capture.
const RESERVED: [&str; 6] = [
    FRAMES_FILE,
    CFA_NPY_FILE,
    CFA_PNG_FILE,
    META_FILE,
    HOT_PIXELS_FILE,
    GROUND_TRUTH_FILE,
];

/// Checks `parts` for consistency before anything touches the disk.
fn check_parts(parts: &CaptureParts<'_>) -> Result<()> {
    let (t, h, row_len) = parts.frames.dim();
    let (ch, cw) = parts.cfa.codes().dim();
    if t == 0 || h == 0 || parts.width == 0 {
        return Err(Error::invalid(format!(
            "a capture needs at least one non-empty frame, got T={t}, H={h}, W={}",
            parts.width
        )));
    }
    if (h, parts.width) != (ch, cw) {
        return Err(Error::invalid(format!(
            "frames are {h}x{} (H x W), the CFA is {ch}x{cw}",
            parts.width
        )));
    }
    match (parts.frames, parts.meta.multibit) {
        (FrameData::Packed(_), None) => {
            if row_len != parts.width.div_ceil(8) {
                return Err(Error::invalid(format!(
                    "packed frames have {row_len} bytes per row, width {} needs {}",
                    parts.width,
                    parts.width.div_ceil(8)
                )));
            }
        }
        (FrameData::MultiBit(frames), Some(m)) => {
            if row_len != parts.width {
                return Err(Error::invalid(format!(
                    "multi-bit frames are {row_len} wide, the width is {}",
                    parts.width
                )));
            }
            if let Some(&max) = frames.iter().max() {
                if u32::from(max) > m.saturation_dn() {
                    return Err(Error::invalid(format!(
                        "a frame sample is {max}, above the full scale {} of bit_depth {}",
                        m.saturation_dn(),
                        m.bit_depth
                    )));
                }
            }
        }
        (FrameData::Packed(_), Some(m)) => {
            return Err(Error::invalid(format!(
                "the metadata says bit_depth {}, but the frames are binary",
                m.bit_depth
            )))
        }
        (FrameData::MultiBit(_), None) => {
            return Err(Error::invalid(
                "multi-bit frames need metadata with a bit depth and gain (CaptureMeta::multibit)",
            ))
        }
    }
    if let Some(r) = parts.meta.reference_frame {
        if r >= t {
            return Err(Error::invalid(format!(
                "reference_frame {r} must be < T = {t}"
            )));
        }
    }
    if let Some(mask) = parts.hot_pixels {
        if mask.dim() != (h, parts.width) {
            return Err(Error::invalid(format!(
                "hot-pixel mask is {:?}, the frames are ({h}, {})",
                mask.dim(),
                parts.width
            )));
        }
    } else if let Some(name) = &parts.meta.hot_pixels {
        return Err(Error::invalid(format!(
            "the metadata names hot-pixel mask {name:?} but no mask was given to write"
        )));
    }
    if let Some(truth) = parts.ground_truth {
        if truth.dim() != (h, parts.width, 3) {
            return Err(Error::invalid(format!(
                "ground truth is {:?}, expected ({h}, {}, 3)",
                truth.dim(),
                parts.width
            )));
        }
    }
    let mut names = std::collections::HashSet::new();
    for (name, _) in &parts.extra_files {
        check_extra_name(name, !names.insert(name.as_str()))?;
    }
    Ok(())
}

/// Checks the name of a further file of a capture: plain, not one of the standard names, and
/// not `duplicate` (already given).
pub(super) fn check_extra_name(name: &str, duplicate: bool) -> Result<()> {
    let plain = !name.is_empty()
        && name != "."
        && name != ".."
        && !name.contains(['/', '\\'])
        && !RESERVED.contains(&name);
    if !plain || duplicate {
        return Err(Error::invalid(format!(
            "extra capture file name {name:?} must be a plain, unique, non-standard file name"
        )));
    }
    Ok(())
}

/// Writes `name` inside the (temporary) directory `dir`; errors name the final location.
pub(super) fn write_member(
    dir: &Path,
    final_dir: &Path,
    name: &str,
    write: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<()> {
    let shown = final_dir.join(name);
    let file = File::create(dir.join(name)).map_err(|e| Error::io(&shown, e))?;
    let mut out = BufWriter::with_capacity(1 << 20, file);
    write(&mut out)
        .and_then(|_| out.flush())
        .map_err(|e| Error::io(&shown, e))
}

/// Streams packed frames to `w`: the `.npy` header, then the raw bytes (no copy when the array
/// is contiguous).
fn write_frames(w: &mut dyn Write, packed: &Array3<u8>) -> std::io::Result<()> {
    let (t, h, b) = packed.dim();
    w.write_all(&npy::encode_header("|u1", &[t, h, b]))?;
    match packed.as_slice() {
        Some(bytes) => w.write_all(bytes),
        None => packed.rows().into_iter().try_for_each(|row| {
            let bytes: Vec<u8> = row.iter().copied().collect();
            w.write_all(&bytes)
        }),
    }
}

/// Writes `array` as a `.npy` file to the writer [`write_member`] gives.
pub(super) fn npy_writer<'b, A, S, D>(
    array: &'b ndarray::ArrayBase<S, D>,
) -> impl FnOnce(&mut dyn Write) -> std::io::Result<()> + 'b
where
    A: ndarray_npy::WritableElement,
    S: ndarray::Data<Elem = A>,
    D: ndarray::Dimension,
{
    move |w| array.write_npy(w).map_err(std::io::Error::other)
}

/// Writes a capture directory atomically: every file goes into a temporary sibling directory
/// that is renamed to `dir` only when complete. An existing `dir` is replaced only after the new
/// capture is complete, and only if it is empty or itself a capture (holds `capture.toml` or
/// `frames.npy`), so a mistyped path cannot wipe an unrelated directory. On error nothing is
/// left behind and an existing `dir` is untouched.
pub fn write_capture(dir: impl AsRef<Path>, parts: &CaptureParts<'_>) -> Result<()> {
    let dir = dir.as_ref();
    check_parts(parts)?;
    let mut meta = parts.meta.clone();
    if parts.hot_pixels.is_some() {
        meta.hot_pixels = Some(HOT_PIXELS_FILE.to_string());
    }
    let toml_text = meta.to_toml_string(parts.extra_toml.as_ref())?;

    let existing = prepare_target(dir)?;

    let tmp = TempGuard::dir(temp_sibling(dir)?);
    fs::create_dir(tmp.path()).map_err(|e| Error::io(dir, e))?;
    let t = tmp.path();
    match parts.frames {
        FrameData::Packed(packed) => {
            write_member(t, dir, FRAMES_FILE, |w| write_frames(w, packed))?
        }
        FrameData::MultiBit(frames) => write_member(t, dir, FRAMES_FILE, npy_writer(frames))?,
    }
    write_member(t, dir, CFA_NPY_FILE, npy_writer(parts.cfa.codes()))?;
    if let Some(mask) = parts.hot_pixels {
        write_member(t, dir, HOT_PIXELS_FILE, npy_writer(mask))?;
    }
    if let Some(truth) = parts.ground_truth {
        write_member(t, dir, GROUND_TRUTH_FILE, npy_writer(truth))?;
    }
    for (name, bytes) in &parts.extra_files {
        write_member(t, dir, name, |w| w.write_all(bytes))?;
    }
    write_member(t, dir, META_FILE, |w| w.write_all(toml_text.as_bytes()))?;

    commit_dir(tmp, dir, existing)
}

/// Checks that `dir` may receive a capture (absent, an empty directory, or a capture) and
/// creates its parent; returns whether `dir` exists (and will be replaced on commit).
pub(crate) fn prepare_target(dir: &Path) -> Result<bool> {
    let existing = match fs::symlink_metadata(dir) {
        Ok(info) if info.is_dir() => {
            let mut entries = fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
            let is_capture = dir.join(META_FILE).exists() || dir.join(FRAMES_FILE).exists();
            if !is_capture && entries.next().is_some() {
                return Err(Error::format(
                    dir,
                    "exists and is not a capture directory; refusing to replace it",
                ));
            }
            true
        }
        Ok(_) => {
            return Err(Error::format(
                dir,
                "exists and is not a directory; refusing to replace it",
            ))
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
        Err(e) => return Err(Error::io(dir, e)),
    };
    if let Some(parent) = dir.parent().filter(|p| !p.as_os_str().is_empty()) {
        fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
    }

    Ok(existing)
}

/// Moves the complete temporary capture `tmp` to `dir`, replacing an existing capture there
/// (see [`write_capture`]).
pub(crate) fn commit_dir(tmp: TempGuard, dir: &Path, existing: bool) -> Result<()> {
    let t = tmp.path();
    if existing {
        // Move the old capture aside, move the new one in, then delete the old one; if the
        // second rename fails, put the old capture back.
        let old = TempGuard::dir(temp_sibling(&dir.with_extension("old"))?);
        fs::rename(dir, old.path()).map_err(|e| Error::io(dir, e))?;
        if let Err(e) = fs::rename(t, dir) {
            let _ = fs::rename(old.path(), dir);
            old.keep();
            return Err(Error::io(dir, e));
        }
        tmp.keep();
        drop(old); // removes the previous capture
    } else {
        fs::rename(t, dir).map_err(|e| Error::io(dir, e))?;
        tmp.keep();
    }
    Ok(())
}
