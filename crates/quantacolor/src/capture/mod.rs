//! Capture format: a directory with `frames.npy`, `cfa.npy` (or a CFA PNG) and `capture.toml`.
//! See `docs/capture-format.md`.
//!
//! A capture is the raw data of the paper's pipeline (§3 imaging model, §4 burst
//! reconstruction): T binary frames of a colour SPAD sensor, the colour filter array in front of
//! it (§5) and the exposure and dark-count rate that turn detection counts into flux (Eq. 2–3).
//! Binary frames stay bit-packed and memory-mapped; block sums come straight from the packed
//! bytes.

pub mod frames;
pub mod io;
pub mod npy;
pub mod readers;
pub mod stream;
pub mod window;
mod write;

pub use frames::BinaryFrames;
pub use stream::CaptureWriter;
pub use window::FrameWindow;
pub(crate) use write::{commit_dir, prepare_target};
use write::{npy_writer, write_member};
pub use write::{write_capture, CaptureParts, FrameData};

use crate::cfa::Cfa;
use crate::error::{Error, Result};
use ndarray::{Array2, Array3};
use serde::{Deserialize, Serialize};
use std::fs;
use std::ops::Range;
use std::path::{Path, PathBuf};

/// The bit-packed binary frames.
pub const FRAMES_FILE: &str = "frames.npy";
/// The colour filter array as uint8 codes.
pub const CFA_NPY_FILE: &str = "cfa.npy";
/// The colour filter array as a colour image (used when `cfa.npy` is absent).
pub const CFA_PNG_FILE: &str = "cfa.png";
/// The metadata.
pub const META_FILE: &str = "capture.toml";
/// The hot-pixel mask written by [`write_capture`].
pub const HOT_PIXELS_FILE: &str = "hot_pixels.npy";
/// The linear ground truth of simulated captures.
pub const GROUND_TRUTH_FILE: &str = "ground_truth.npy";

const META_KEYS: [&str; 11] = [
    "exposure_s",
    "dark_count_rate_hz",
    "dark_current_e_per_s",
    "w_weights",
    "hot_pixels",
    "reference_frame",
    "bit_depth",
    "read_noise_e",
    "gain_e_per_dn",
    "full_well_e",
    "black_level_dn",
];

/// Keys that only multi-bit captures (`bit_depth` >= 2) may carry.
const MULTIBIT_KEYS: [&str; 3] = ["gain_e_per_dn", "full_well_e", "black_level_dn"];

/// The readout of a multi-bit (conventional sensor) capture: `frames.npy` holds uint16
/// digital numbers (T, H, W), reconstructed with the Gaussian–Poisson model
/// ([`crate::model::GaussianPoisson`], paper §6.1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MultiBitReadout {
    /// Bits per sample, 2..=16; samples lie in `0..=2^bit_depth − 1`, and a sample at full
    /// scale is saturated.
    pub bit_depth: u32,
    /// Electrons per digital number (`full_well_e` in `capture.toml` sets it to
    /// full_well / (2^bit_depth − 1 − black_level_dn)).
    pub gain_e_per_dn: f64,
    /// Digital number of zero electrons (default 0).
    pub black_level_dn: f64,
}

impl MultiBitReadout {
    /// The largest digital number, `2^bit_depth − 1`.
    pub fn saturation_dn(&self) -> u32 {
        ((1u64 << self.bit_depth.min(16)) - 1) as u32
    }
}

/// Contents of `capture.toml`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaptureMeta {
    /// Exposure time of one binary frame, seconds.
    pub exposure_s: f64,
    /// Mean dark count rate, counts per second (default 0).
    #[serde(default)]
    pub dark_count_rate_hz: f64,
    /// W = wR·R + wG·G + wB·B (default [1, 1, 1]).
    #[serde(default = "default_w_weights")]
    pub w_weights: [f64; 3],
    /// Optional file name (relative to the capture directory) of a bool (H, W) hot-pixel mask.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hot_pixels: Option<String>,
    /// Reference frame index (default T/2 rounded down).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference_frame: Option<usize>,
    /// Read noise, electrons RMS (default 0): the Gaussian read noise of a multi-bit capture,
    /// or a binary jot's read noise, whose false positives count as dark counts
    /// ([`crate::model::read_noise_false_positive_dark`]).
    #[serde(skip)]
    pub read_noise_e: f64,
    /// `Some` for multi-bit frames (`bit_depth` >= 2), `None` for binary frames.
    #[serde(skip)]
    pub multibit: Option<MultiBitReadout>,
}

fn default_w_weights() -> [f64; 3] {
    [1.0, 1.0, 1.0]
}

/// A TOML value's type, for error messages.
fn toml_type(v: &toml::Value) -> &'static str {
    match v {
        toml::Value::String(_) => "a string",
        toml::Value::Integer(_) => "an integer",
        toml::Value::Float(_) => "a float",
        toml::Value::Boolean(_) => "a boolean",
        toml::Value::Datetime(_) => "a date-time",
        toml::Value::Array(_) => "an array",
        toml::Value::Table(_) => "a table",
    }
}

/// A TOML number (integer or float) as `f64`.
fn toml_number(v: &toml::Value) -> Option<f64> {
    match v {
        toml::Value::Float(f) => Some(*f),
        toml::Value::Integer(i) => Some(*i as f64),
        _ => None,
    }
}

/// The top-level keys of a `capture.toml` being read (`path` names it in errors).
struct MetaFields<'a> {
    table: &'a toml::Table,
    path: &'a Path,
}

impl MetaFields<'_> {
    fn bad_type(&self, key: &str, want: &str, v: &toml::Value) -> Error {
        Error::format(
            self.path,
            format!("`{key}` must be {want}, found {}", toml_type(v)),
        )
    }

    fn number(&self, key: &str) -> Result<Option<f64>> {
        self.table
            .get(key)
            .map(|v| toml_number(v).ok_or_else(|| self.bad_type(key, "a number", v)))
            .transpose()
    }

    /// `dark_count_rate_hz` or its synonym `dark_current_e_per_s` (not both), 0 without either.
    fn dark_count_rate_hz(&self) -> Result<f64> {
        match (
            self.number("dark_count_rate_hz")?,
            self.number("dark_current_e_per_s")?,
        ) {
            (Some(_), Some(_)) => Err(Error::format(
                self.path,
                "give `dark_count_rate_hz` or `dark_current_e_per_s`, not both (they are \
                 the same quantity: dark events per pixel per second)",
            )),
            (a, b) => Ok(a.or(b).unwrap_or(0.0)),
        }
    }

    /// The multi-bit readout of a `bit_depth` of 2..=16 (`None` for binary frames, whose
    /// capture must not give the multi-bit keys).
    fn multibit(&self, bit_depth: Option<i64>) -> Result<Option<MultiBitReadout>> {
        let path = self.path;
        match bit_depth {
            None | Some(1) => {
                if let Some(key) = MULTIBIT_KEYS.iter().find(|k| self.table.contains_key(**k)) {
                    return Err(Error::format(
                        path,
                        format!(
                            "`{key}` is only for multi-bit frames; set `bit_depth` (2..=16) for \
                             a conventional sensor's capture"
                        ),
                    ));
                }
                Ok(None)
            }
            Some(b) if !(2..=16).contains(&b) => Err(Error::format(
                path,
                format!(
                    "`bit_depth` must be 1 (binary frames) or 2..=16 (multi-bit uint16 \
                     frames), found {b}"
                ),
            )),
            Some(b) => {
                let bit_depth = b as u32;
                let black_level_dn = self.number("black_level_dn")?.unwrap_or(0.0);
                let full_scale = ((1u64 << bit_depth) - 1) as f64;
                if !(black_level_dn.is_finite()
                    && black_level_dn >= 0.0
                    && black_level_dn < full_scale)
                {
                    return Err(Error::format(
                        path,
                        format!(
                            "`black_level_dn` must be >= 0 and below full scale {full_scale}, \
                             found {black_level_dn}"
                        ),
                    ));
                }
                let gain_e_per_dn = self.gain_e_per_dn(bit_depth, full_scale - black_level_dn)?;
                Ok(Some(MultiBitReadout {
                    bit_depth,
                    gain_e_per_dn,
                    black_level_dn,
                }))
            }
        }
    }

    /// `gain_e_per_dn`, or `full_well_e` over the `range_dn` above the black level (one of
    /// the two, not both).
    fn gain_e_per_dn(&self, bit_depth: u32, range_dn: f64) -> Result<f64> {
        let path = self.path;
        match (self.number("gain_e_per_dn")?, self.number("full_well_e")?) {
            (Some(g), None) => Ok(g),
            (None, Some(fw)) => {
                if !(fw.is_finite() && fw > 0.0) {
                    return Err(Error::format(
                        path,
                        format!("`full_well_e` must be a finite number > 0, found {fw}"),
                    ));
                }
                Ok(fw / range_dn)
            }
            (Some(_), Some(_)) => Err(Error::format(
                path,
                "give `gain_e_per_dn` or `full_well_e`, not both",
            )),
            (None, None) => Err(Error::format(
                path,
                format!(
                    "missing `gain_e_per_dn` (electrons per digital number) or \
                     `full_well_e`: a {bit_depth}-bit capture needs one to turn \
                     digital numbers into photoelectrons"
                ),
            )),
        }
    }

    /// `w_weights` as three numbers.
    fn w_weights(&self, v: &toml::Value) -> Result<[f64; 3]> {
        let want = "an array of three numbers [wR, wG, wB]";
        let items = v
            .as_array()
            .ok_or_else(|| self.bad_type("w_weights", want, v))?;
        let nums: Vec<f64> = items
            .iter()
            .map(|x| {
                toml_number(x).ok_or_else(|| {
                    Error::format(
                        self.path,
                        format!(
                            "`w_weights` must hold numbers [wR, wG, wB], found {} in it",
                            toml_type(x)
                        ),
                    )
                })
            })
            .collect::<Result<_>>()?;
        <[f64; 3]>::try_from(nums).map_err(|n| {
            Error::format(
                self.path,
                format!(
                    "`w_weights` must hold 3 numbers [wR, wG, wB], found {}",
                    n.len()
                ),
            )
        })
    }
}

/// True for `[table]` and `[[array.of.tables]]` values, which `capture.toml` tolerates as
/// extra data (e.g. the simulator's `[simulation]` table).
fn is_table_like(v: &toml::Value) -> bool {
    match v {
        toml::Value::Table(_) => true,
        toml::Value::Array(a) => !a.is_empty() && a.iter().all(|x| x.is_table()),
        _ => false,
    }
}

impl CaptureMeta {
    /// Metadata with the given per-frame exposure and every other key at its default.
    pub fn new(exposure_s: f64) -> Self {
        CaptureMeta {
            exposure_s,
            dark_count_rate_hz: 0.0,
            w_weights: default_w_weights(),
            hot_pixels: None,
            reference_frame: None,
            read_noise_e: 0.0,
            multibit: None,
        }
    }

    /// Dark counts per frame, `d` of paper Eq. 3: dark count rate (dark current, for multi-bit
    /// frames) times exposure, plus, for a binary capture with read noise (a jot), its
    /// read-noise false positives as equivalent dark counts.
    pub fn dark_counts_per_frame(&self) -> f64 {
        let dark = self.dark_count_rate_hz * self.exposure_s;
        match self.multibit {
            Some(_) => dark,
            None => dark + crate::model::read_noise_false_positive_dark(self.read_noise_e),
        }
    }

    /// The photon model of the capture's pixels (binary, paper Eq. 2–6, or Gaussian–Poisson
    /// for multi-bit frames, §6.1) with [`CaptureMeta::dark_counts_per_frame`].
    pub fn pixel_model(&self) -> crate::model::PixelModel {
        use crate::model::{GaussianPoisson, PixelModel, Readout};
        PixelModel {
            dark_per_frame: self.dark_counts_per_frame(),
            readout: match self.multibit {
                None => Readout::Binary,
                Some(m) => Readout::GaussianPoisson(GaussianPoisson {
                    gain_e_per_dn: m.gain_e_per_dn,
                    read_noise_e: self.read_noise_e,
                    black_level_dn: m.black_level_dn,
                    saturation_dn: m.saturation_dn() as f64,
                }),
            },
        }
    }

    /// Parses the text of a `capture.toml`; `path` names it in errors. Unknown top-level keys
    /// are rejected (typo protection) unless they are tables, which are left for other tools.
    pub fn from_toml_str(text: &str, path: impl AsRef<Path>) -> Result<CaptureMeta> {
        let path = path.as_ref();
        let table: toml::Table = text
            .parse()
            .map_err(|e| Error::format(path, format!("invalid TOML: {e}")))?;
        for (key, value) in &table {
            if !META_KEYS.contains(&key.as_str()) && !is_table_like(value) {
                return Err(Error::format(
                    path,
                    format!(
                        "unknown key `{key}` (known keys: {}; extra data belongs in a [table])",
                        META_KEYS.join(", ")
                    ),
                ));
            }
        }
        let fields = MetaFields {
            table: &table,
            path,
        };
        let exposure_s = fields.number("exposure_s")?.ok_or_else(|| {
            Error::format(
                path,
                "missing required key `exposure_s` (exposure of one binary frame, seconds)",
            )
        })?;
        let dark_count_rate_hz = fields.dark_count_rate_hz()?;
        let bit_depth = match table.get("bit_depth") {
            None => None,
            Some(toml::Value::Integer(i)) => Some(*i),
            Some(v) => return Err(fields.bad_type("bit_depth", "an integer", v)),
        };
        let read_noise_e = fields.number("read_noise_e")?.unwrap_or(0.0);
        let multibit = fields.multibit(bit_depth)?;
        let w_weights = match table.get("w_weights") {
            None => default_w_weights(),
            Some(v) => fields.w_weights(v)?,
        };
        let hot_pixels = match table.get("hot_pixels") {
            None => None,
            Some(toml::Value::String(s)) => Some(s.clone()),
            Some(v) => return Err(fields.bad_type("hot_pixels", "a file name (string)", v)),
        };
        let reference_frame = match table.get("reference_frame") {
            None => None,
            Some(toml::Value::Integer(i)) => Some(usize::try_from(*i).map_err(|_| {
                Error::format(path, format!("`reference_frame` must be >= 0, found {i}"))
            })?),
            Some(v) => return Err(fields.bad_type("reference_frame", "an integer", v)),
        };
        let meta = CaptureMeta {
            exposure_s,
            dark_count_rate_hz,
            w_weights,
            hot_pixels,
            reference_frame,
            read_noise_e,
            multibit,
        };
        meta.check().map_err(|m| Error::format(path, m))?;
        Ok(meta)
    }

    /// The metadata as `capture.toml` text, with `extra` tables appended (e.g. `[simulation]`).
    pub fn to_toml_string(&self, extra: Option<&toml::Table>) -> Result<String> {
        self.check().map_err(Error::invalid)?;
        let mut table = toml::Table::try_from(self)
            .map_err(|e| Error::invalid(format!("cannot serialise capture metadata: {e}")))?;
        if self.read_noise_e != 0.0 {
            table.insert("read_noise_e".into(), self.read_noise_e.into());
        }
        if let Some(m) = self.multibit {
            // A conventional sensor's dark events are dark current.
            if let Some(dark) = table.remove("dark_count_rate_hz") {
                table.insert("dark_current_e_per_s".into(), dark);
            }
            table.insert("bit_depth".into(), i64::from(m.bit_depth).into());
            table.insert("gain_e_per_dn".into(), m.gain_e_per_dn.into());
            table.insert("black_level_dn".into(), m.black_level_dn.into());
        }
        for (key, value) in extra.into_iter().flatten() {
            if META_KEYS.contains(&key.as_str()) || !is_table_like(value) {
                return Err(Error::invalid(format!(
                    "extra capture.toml entry `{key}` must be a table and not a metadata key"
                )));
            }
            table.insert(key.clone(), value.clone());
        }
        toml::to_string(&table)
            .map_err(|e| Error::invalid(format!("cannot serialise capture metadata: {e}")))
    }

    /// Range checks shared by the reader and the writer; the message names the key.
    fn check(&self) -> std::result::Result<(), String> {
        if !(self.exposure_s.is_finite() && self.exposure_s > 0.0) {
            return Err(format!(
                "`exposure_s` must be a finite number > 0, found {}",
                self.exposure_s
            ));
        }
        if !(self.dark_count_rate_hz.is_finite() && self.dark_count_rate_hz >= 0.0) {
            return Err(format!(
                "`dark_count_rate_hz` must be a finite number >= 0, found {}",
                self.dark_count_rate_hz
            ));
        }
        let w = self.w_weights;
        if w.iter().any(|v| !(v.is_finite() && *v >= 0.0)) || w.iter().all(|&v| v == 0.0) {
            return Err(format!(
                "`w_weights` must be finite, >= 0 and not all zero, found {w:?}"
            ));
        }
        if !(self.read_noise_e.is_finite() && self.read_noise_e >= 0.0) {
            return Err(format!(
                "`read_noise_e` must be a finite number >= 0, found {}",
                self.read_noise_e
            ));
        }
        if let Some(m) = self.multibit {
            if !(2..=16).contains(&m.bit_depth) {
                return Err(format!(
                    "`bit_depth` must be 1 (binary frames) or 2..=16 (multi-bit uint16 \
                     frames), found {}",
                    m.bit_depth
                ));
            }
            if !(m.gain_e_per_dn.is_finite() && m.gain_e_per_dn > 0.0) {
                return Err(format!(
                    "`gain_e_per_dn` must be a finite number > 0, found {}",
                    m.gain_e_per_dn
                ));
            }
            let full_scale = m.saturation_dn() as f64;
            if !(m.black_level_dn.is_finite()
                && m.black_level_dn >= 0.0
                && m.black_level_dn < full_scale)
            {
                return Err(format!(
                    "`black_level_dn` must be >= 0 and below full scale {full_scale}, found {}",
                    m.black_level_dn
                ));
            }
        }
        if let Some(name) = &self.hot_pixels {
            if name.is_empty() || Path::new(name).is_absolute() {
                return Err(format!(
                    "`hot_pixels` must be a file name relative to the capture directory, \
                     found {name:?}"
                ));
            }
        }
        Ok(())
    }
}

/// An opened capture.
#[derive(Debug)]
pub struct Capture {
    /// The capture directory.
    pub dir: PathBuf,
    /// Binary frames (memory-mapped).
    pub frames: BinaryFrames,
    /// Colour filter array, same (H, W) as the frames.
    pub cfa: Cfa,
    /// Metadata from `capture.toml`.
    pub meta: CaptureMeta,
    /// Hot-pixel mask (true = hot or dead), if the capture names one.
    pub hot_pixels: Option<Array2<bool>>,
}

/// Checks that binary frames come with binary metadata and multi-bit frames with a
/// `bit_depth` >= 2 whose full scale holds every sample; the message says what disagrees.
fn check_frame_kind(frames: &BinaryFrames, meta: &CaptureMeta) -> std::result::Result<(), String> {
    match (frames.is_multibit(), meta.multibit) {
        (false, None) => Ok(()),
        (false, Some(m)) => Err(format!(
            "capture.toml says `bit_depth` = {}, but the frames are binary (uint8 or bool); \
             multi-bit frames are uint16 (T, H, W)",
            m.bit_depth
        )),
        (true, None) => Err(
            "the frames are uint16 (multi-bit), but capture.toml has no `bit_depth` (2..=16) \
             and `gain_e_per_dn` or `full_well_e`"
                .into(),
        ),
        (true, Some(m)) => {
            let max = frames.max_sample();
            if max > m.saturation_dn() {
                Err(format!(
                    "a sample is {max}, above the full scale {} of `bit_depth` = {}",
                    m.saturation_dn(),
                    m.bit_depth
                ))
            } else {
                Ok(())
            }
        }
    }
}

/// Reads the CFA of a capture: `cfa.npy` (uint8 (H, W) codes) if present, else `cfa.png`.
fn read_cfa(dir: &Path) -> Result<Cfa> {
    let npy = dir.join(CFA_NPY_FILE);
    let png = dir.join(CFA_PNG_FILE);
    let (path, codes) = if npy.exists() || !png.exists() {
        (npy.clone(), io::read_npy_2d::<u8>(&npy)?)
    } else {
        (png.clone(), io::read_cfa_png(&png)?)
    };
    if codes.is_empty() {
        return Err(Error::format(&path, "CFA is empty"));
    }
    if let Some(((y, x), &c)) = codes.indexed_iter().find(|(_, &c)| c > 3) {
        return Err(Error::format(
            &path,
            format!("CFA code {c} at (y={y}, x={x}) is not one of 0=R 1=G 2=B 3=W"),
        ));
    }
    Cfa::new(codes).map_err(|e| Error::format(&path, e.to_string()))
}

impl Capture {
    /// Opens and validates the capture in `dir`: reads `capture.toml`, the CFA and the optional
    /// hot-pixel mask, memory-maps `frames.npy`, and checks that every shape agrees. Any
    /// problem is an [`Error`] naming the file at fault.
    pub fn open(dir: impl AsRef<Path>) -> Result<Capture> {
        let dir = dir.as_ref();
        let info = fs::metadata(dir).map_err(|e| Error::io(dir, e))?;
        if !info.is_dir() {
            return Err(Error::format(
                dir,
                "a capture must be a directory holding frames.npy, cfa.npy and capture.toml",
            ));
        }
        let meta_path = dir.join(META_FILE);
        let text = fs::read(&meta_path).map_err(|e| Error::io(&meta_path, e))?;
        let text =
            String::from_utf8(text).map_err(|_| Error::format(&meta_path, "not UTF-8 text"))?;
        let meta = CaptureMeta::from_toml_str(&text, &meta_path)?;

        let cfa = read_cfa(dir)?;
        let frames_path = dir.join(FRAMES_FILE);
        let frames = BinaryFrames::open(&frames_path, cfa.width())?;
        if frames.height() != cfa.height() {
            return Err(Error::format(
                &frames_path,
                format!(
                    "frames have height {}, the CFA has height {} (shape {:?})",
                    frames.height(),
                    cfa.height(),
                    cfa.codes().dim()
                ),
            ));
        }
        check_frame_kind(&frames, &meta).map_err(|m| Error::format(&frames_path, m))?;
        let t = frames.frame_count();
        if let Some(r) = meta.reference_frame {
            if r >= t {
                return Err(Error::format(
                    &meta_path,
                    format!("`reference_frame` = {r} must be < T = {t} (the number of frames)"),
                ));
            }
        }

        let hot_pixels = match &meta.hot_pixels {
            None => None,
            Some(name) => {
                let path = dir.join(name);
                let mask = io::read_npy_2d::<bool>(&path)?;
                if mask.dim() != cfa.codes().dim() {
                    return Err(Error::format(
                        &path,
                        format!(
                            "hot-pixel mask has shape {:?}, the frames are {:?} (H, W)",
                            mask.dim(),
                            cfa.codes().dim()
                        ),
                    ));
                }
                Some(mask)
            }
        };
        Ok(Capture {
            dir: dir.to_path_buf(),
            frames,
            cfa,
            meta,
            hot_pixels,
        })
    }

    /// Keeps only the frames of `window`, which become frames `0..B-A` (no data is copied).
    /// The capture's `reference_frame` is shifted with them when it lies inside the window and
    /// dropped (the window's centre is used) otherwise.
    pub fn window(mut self, window: &FrameWindow) -> Result<Capture> {
        let range = window
            .resolve(self.frames.frame_count())
            .map_err(|e| Error::format(self.dir.join(FRAMES_FILE), e.to_string()))?;
        self.meta.reference_frame = self
            .meta
            .reference_frame
            .filter(|r| range.contains(r))
            .map(|r| r - range.start);
        self.frames = self.frames.window(range)?;
        Ok(self)
    }

    /// The frames in `range` as a capture of their own (frames `0..range.len()`), leaving
    /// `self` as it is; the CFA, hot-pixel mask and metadata are shared, the reference frame
    /// shifted with the frames as [`Self::window`] does. A memory map is not read again
    /// ([`BinaryFrames::view`]).
    pub fn view(&self, range: Range<usize>) -> Result<Capture> {
        let mut meta = self.meta.clone();
        meta.reference_frame = meta
            .reference_frame
            .filter(|r| range.contains(r))
            .map(|r| r - range.start);
        Ok(Capture {
            dir: self.dir.clone(),
            frames: self.frames.view(range)?,
            cfa: self.cfa.clone(),
            meta,
            hot_pixels: self.hot_pixels.clone(),
        })
    }

    /// A capture held in memory (the Python package's `Capture.from_arrays`): checks what
    /// [`Capture::open`] checks, with errors naming the part at fault (`frames`, `cfa`,
    /// `hot_pixels`, `reference_frame` or a metadata key). `meta.hot_pixels` is ignored: the
    /// mask is `hot_pixels` itself.
    pub fn from_memory(
        frames: BinaryFrames,
        cfa: Cfa,
        mut meta: CaptureMeta,
        hot_pixels: Option<Array2<bool>>,
    ) -> Result<Capture> {
        let (h, w) = (frames.height(), frames.width());
        if (cfa.height(), cfa.width()) != (h, w) {
            return Err(Error::invalid(format!(
                "cfa has shape ({}, {}), the frames are (H, W) = ({h}, {w})",
                cfa.height(),
                cfa.width()
            )));
        }
        meta.hot_pixels = None;
        meta.check().map_err(Error::invalid)?;
        check_frame_kind(&frames, &meta).map_err(|m| Error::invalid(format!("frames: {m}")))?;
        let t = frames.frame_count();
        if let Some(r) = meta.reference_frame {
            if r >= t {
                return Err(Error::invalid(format!(
                    "reference_frame = {r} must be < T = {t} (the number of frames)"
                )));
            }
        }
        if let Some(mask) = &hot_pixels {
            if mask.dim() != (h, w) {
                return Err(Error::invalid(format!(
                    "hot_pixels has shape {:?}, the frames are (H, W) = ({h}, {w})",
                    mask.dim()
                )));
            }
        }
        Ok(Capture {
            dir: PathBuf::from("<memory>"),
            frames,
            cfa,
            meta,
            hot_pixels,
        })
    }

    /// The reference frame: `meta.reference_frame` or T/2 rounded down.
    pub fn reference_frame(&self) -> usize {
        self.meta
            .reference_frame
            .unwrap_or(self.frames.frame_count() / 2)
    }

    /// The linear ground truth `ground_truth.npy`, float32 (H, W, 3), of a simulated capture;
    /// `None` when the file is absent.
    pub fn ground_truth(&self) -> Result<Option<Array3<f32>>> {
        let path = self.dir.join(GROUND_TRUTH_FILE);
        if !path.exists() {
            return Ok(None);
        }
        let truth = io::read_npy_3d::<f32>(&path)?;
        let want = (self.frames.height(), self.frames.width(), 3);
        if truth.dim() != want {
            return Err(Error::format(
                &path,
                format!(
                    "ground truth has shape {:?}, expected {want:?}",
                    truth.dim()
                ),
            ));
        }
        Ok(Some(truth))
    }
}
