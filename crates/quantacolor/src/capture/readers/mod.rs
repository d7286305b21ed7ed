//! Readers of real single-photon recordings and their conversion into a capture directory
//! (`quantacolor convert`; formats in `docs/real-sensors.md`).
//!
//! Every reader is a [`FrameSource`]: it knows its frame count and size up front (from file
//! sizes or the `.npy` header, after checking every file) and hands out one frame at a time,
//! already packed the capture format's way, so [`crate::convert`] streams any number of
//! frames through one frame of memory into a [`super::CaptureWriter`].

pub mod files;
pub mod layouts;
pub mod npy_cube;

pub use files::{list_files, natural_cmp, natural_path_cmp, FileLayout, RawFileSet};
pub use layouts::{colorspad_crop, RawLayout, Spad512sOrientation};
pub use npy_cube::open_npy;

use crate::cfa::Cfa;
use crate::error::{Error, Result};
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// A recording read one frame at a time.
pub trait FrameSource {
    /// What is being read, for messages.
    fn describe(&self) -> String;
    /// Number of frames T.
    fn frame_count(&self) -> usize;
    /// Frame height H.
    fn height(&self) -> usize;
    /// Frame width W.
    fn width(&self) -> usize;
    /// Frame `t`, packed MSB first: H rows of `ceil(W/8)` bytes into `out`. Reading frames in
    /// increasing order is the fast path.
    fn read_frame(&mut self, t: usize, out: &mut [u8]) -> Result<()>;
}

/// The input formats of `quantacolor convert --from`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RawFormat {
    /// SwissSPAD2 half array `.bin` files.
    SwissSpad2,
    /// SwissSPAD2 full array `.bin` files.
    SwissSpad2Full,
    /// Pi Imaging SPAD512S `.bin` files.
    Spad512s,
    /// A photon-cube `.npy` (binary frames or a visionsim RGB cube).
    Npy,
}

impl RawFormat {
    /// The command-line name.
    pub fn name(&self) -> &'static str {
        match self {
            RawFormat::SwissSpad2 => "swissspad2",
            RawFormat::SwissSpad2Full => "swissspad2-full",
            RawFormat::Spad512s => "spad512s",
            RawFormat::Npy => "npy",
        }
    }
}

impl FromStr for RawFormat {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "swissspad2" => RawFormat::SwissSpad2,
            "swissspad2-full" => RawFormat::SwissSpad2Full,
            "spad512s" => RawFormat::Spad512s,
            "npy" => RawFormat::Npy,
            _ => {
                return Err(Error::invalid(format!(
                    "unknown input format {s:?} (swissspad2, swissspad2-full, spad512s, npy)"
                )))
            }
        })
    }
}

/// SPAD512S options: public readers disagree on both (see [`layouts`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Spad512sOptions {
    /// Bytes after the frames of every file, ignored (default 4, as the MATLAB reader drops).
    pub trailer_bytes: usize,
    /// How frames are oriented in the capture (default as stored).
    pub orientation: Spad512sOrientation,
}

impl Default for Spad512sOptions {
    fn default() -> Self {
        Spad512sOptions {
            trailer_bytes: 4,
            orientation: Spad512sOrientation::Stored,
        }
    }
}

/// Frames in one SwissSPAD2 half-array file.
pub const SWISSSPAD2_HALF_FRAMES_PER_FILE: usize = 512;
/// Frames in one SwissSPAD2 full-array file.
pub const SWISSSPAD2_FULL_FRAMES_PER_FILE: usize = 256;

/// Raw `.bin` files decoded by a [`RawLayout`], optionally cropped to the colour SwissSPAD2
/// geometry.
pub struct RawBinSource {
    input: PathBuf,
    files: RawFileSet,
    layout: RawLayout,
    colorspad: bool,
    raw: Vec<u8>,
    decoded: Vec<u8>,
}

impl RawBinSource {
    /// Lists the `.bin` files under `input` (natural order) and checks their sizes.
    pub fn open(
        input: &Path,
        format: RawFormat,
        spad512s: Spad512sOptions,
        colorspad: bool,
    ) -> Result<RawBinSource> {
        let (layout, frames_per_file, trailer, name) = match format {
            RawFormat::SwissSpad2 => (
                RawLayout::SwissSpad2Half,
                Some(SWISSSPAD2_HALF_FRAMES_PER_FILE),
                0,
                "SwissSPAD2 half-array",
            ),
            RawFormat::SwissSpad2Full => (
                RawLayout::SwissSpad2Full,
                Some(SWISSSPAD2_FULL_FRAMES_PER_FILE),
                0,
                "SwissSPAD2 full-array",
            ),
            RawFormat::Spad512s => (
                RawLayout::Spad512s(spad512s.orientation),
                None,
                spad512s.trailer_bytes,
                "SPAD512S",
            ),
            RawFormat::Npy => return Err(Error::invalid("a .npy photon cube is not a .bin file")),
        };
        if colorspad && layout != RawLayout::SwissSpad2Half {
            return Err(Error::invalid(
                "--colorspad applies to SwissSPAD2 half-array recordings (--from swissspad2)",
            ));
        }
        let paths = list_files(input, "bin")?;
        let files = RawFileSet::new(
            paths,
            FileLayout {
                frame_bytes: layout.frame_bytes(),
                frames_per_file,
                trailer_bytes: trailer,
                format: name,
            },
        )?;
        Ok(RawBinSource {
            input: input.to_path_buf(),
            files,
            layout,
            colorspad,
            raw: vec![0; layout.frame_bytes()],
            decoded: vec![0; layout.frame_bytes()],
        })
    }

    /// The raw files, in reading order.
    pub fn files(&self) -> &RawFileSet {
        &self.files
    }
}

impl FrameSource for RawBinSource {
    fn describe(&self) -> String {
        format!(
            "{} ({} .bin file{})",
            self.input.display(),
            self.files.file_count(),
            if self.files.file_count() == 1 {
                ""
            } else {
                "s"
            }
        )
    }
    fn frame_count(&self) -> usize {
        self.files.frame_count()
    }
    fn height(&self) -> usize {
        if self.colorspad {
            layouts::COLORSPAD_ROWS.len()
        } else {
            self.layout.dims().0
        }
    }
    fn width(&self) -> usize {
        if self.colorspad {
            layouts::COLORSPAD_WIDTH
        } else {
            self.layout.dims().1
        }
    }
    fn read_frame(&mut self, t: usize, out: &mut [u8]) -> Result<()> {
        self.files.read_raw(t, &mut self.raw)?;
        if self.colorspad {
            self.layout.decode(&self.raw, &mut self.decoded);
            colorspad_crop(&self.decoded, out);
        } else {
            self.layout.decode(&self.raw, out);
        }
        Ok(())
    }
}

/// What to read: the format and its options.
#[derive(Debug, Clone, Default)]
pub struct SourceSpec {
    /// Input format (`None` is an error).
    pub format: Option<RawFormat>,
    /// Crop to the colour SwissSPAD2 geometry (SwissSPAD2 half array only).
    pub colorspad: bool,
    /// SPAD512S options.
    pub spad512s: Spad512sOptions,
}

/// Opens `input` as `spec` says. `cfa` is needed by RGB photon cubes and sets the width of
/// packed photon cubes.
pub fn open_source(
    input: &Path,
    spec: &SourceSpec,
    cfa: Option<&Cfa>,
) -> Result<Box<dyn FrameSource>> {
    match spec.format {
        None => Err(Error::invalid("no input format given")),
        Some(RawFormat::Npy) => {
            if spec.colorspad {
                return Err(Error::invalid(
                    "--colorspad applies to SwissSPAD2 half-array recordings (--from swissspad2)",
                ));
            }
            open_npy(input, cfa)
        }
        Some(f) => Ok(Box::new(RawBinSource::open(
            input,
            f,
            spec.spad512s,
            spec.colorspad,
        )?)),
    }
}
