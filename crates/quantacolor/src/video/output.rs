//! A video's frames, the frames each is made from, and its output directory, streamed: this
//! project's own packaging of the paper's supplementary videos (one reconstruction per
//! reference frame).
//!
//! [`VideoPlan`] places a reference frame every `stride` frames and, with a window, gives each
//! one the `window` frames centred on it ([`crate::naive::centred_window`]), so a video of a
//! long recording costs time linear in its length (each frame reads its own window, not the
//! whole recording). [`reconstruct_frame`] reconstructs one video frame from its window alone.
//! [`VideoWriter`] writes `frame_NNNNN.png` (one exposure for all, from the first frame),
//! `linear.npy` (float32 (N, H, W, 3)) and `video.toml` as the frames arrive, holding one frame
//! in memory: a video of 10^6 frames needs the memory of one reconstruction. The CLI's
//! `reconstruct --video` and the Python package's `batch.reconstruct_video` (frames made on a
//! Dask cluster, then streamed in order through the same writer) write the same bytes.
#![forbid(unsafe_code)]

use super::video_reference_frames;
use crate::capture::{io, Capture};
use crate::display::{auto_exposure_scale, encode_srgb8};
use crate::error::{Error, Result};
use crate::naive::centred_window;
use crate::output::{StagedDir, LINEAR_UNITS};
use crate::pipeline::{reconstruct, ReconstructConfig, Reconstruction};
use crate::progress::Progress;
use ndarray::{ArrayView3, Dim};
use serde::Serialize;
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::ops::Range;
use std::path::{Path, PathBuf};

/// One frame of a video: its number, its reference frame and the capture frames it is
/// reconstructed from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VideoFrame {
    pub index: usize,
    pub reference_frame: usize,
    pub frames: Range<usize>,
}

/// The frames of a video over a capture of `frame_count` frames: a reference frame every
/// `stride` frames from `stride / 2` (each centred in its stretch), each reconstructed from
/// the `window` frames centred on it (clamped into the capture), or from every frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VideoPlan {
    pub frame_count: usize,
    pub stride: usize,
    pub window: Option<usize>,
    pub frames: Vec<VideoFrame>,
}

impl VideoPlan {
    /// The plan; errors name the option at fault (`--stride`, `--window`) and when no
    /// reference frame falls inside the capture.
    pub fn new(frame_count: usize, stride: usize, window: Option<usize>) -> Result<VideoPlan> {
        if stride == 0 {
            return Err(Error::invalid("--stride must be at least 1 frame"));
        }
        if window == Some(0) {
            return Err(Error::invalid("--window must hold at least 1 frame"));
        }
        let frames: Vec<VideoFrame> = video_reference_frames(frame_count, stride)?
            .into_iter()
            .enumerate()
            .map(|(index, reference_frame)| VideoFrame {
                index,
                reference_frame,
                frames: centred_window(frame_count, reference_frame, window),
            })
            .collect();
        if frames.is_empty() {
            return Err(Error::invalid(format!(
                "--stride {stride} leaves no reference frame in the capture's {frame_count} frames"
            )));
        }
        Ok(VideoPlan {
            frame_count,
            stride,
            window,
            frames,
        })
    }

    /// The reference frames, in video order.
    pub fn reference_frames(&self) -> Vec<usize> {
        self.frames.iter().map(|f| f.reference_frame).collect()
    }

    /// Whether every video frame is made from the whole capture.
    pub fn whole_capture(&self) -> bool {
        self.frames
            .iter()
            .all(|f| f.frames == (0..self.frame_count))
    }
}

/// The file name of video frame `index` (`frame_00042.png`).
pub fn frame_file_name(index: usize) -> String {
    format!("frame_{index:05}.png")
}

/// Reconstructs video frame `frame` of `capture` from its own frames alone (the full pipeline
/// at its reference frame; `--video-motion per-frame`). The result's `reference_frame` and
/// `frames_used` count within the window.
pub fn reconstruct_frame(
    capture: &Capture,
    config: &ReconstructConfig,
    frame: &VideoFrame,
    progress: &dyn Progress,
) -> Result<Reconstruction> {
    let whole = 0..capture.frames.frame_count();
    let windowed;
    let (capture, reference_frame) = if frame.frames == whole {
        (capture, frame.reference_frame)
    } else {
        windowed = capture.view(frame.frames.clone())?;
        (&windowed, frame.reference_frame - frame.frames.start)
    };
    let config = ReconstructConfig {
        reference_frame: Some(reference_frame),
        ..config.clone()
    };
    reconstruct(capture, &config, progress)
}

/// A video frame's stage progress, each stage labelled with the frame (`frame 3/40: merge`),
/// so that a long video shows how far it is.
pub struct FrameProgress<'a> {
    inner: &'a dyn Progress,
    prefix: String,
}

impl<'a> FrameProgress<'a> {
    /// Progress of video frame `frame` of `plan`, reported to `inner`.
    pub fn new(inner: &'a dyn Progress, frame: &VideoFrame, plan: &VideoPlan) -> Self {
        FrameProgress {
            inner,
            prefix: format!("frame {}/{}", frame.index + 1, plan.frames.len()),
        }
    }
}

impl Progress for FrameProgress<'_> {
    fn start(&self, label: &str, total: u64) {
        self.inner
            .start(&format!("{}: {label}", self.prefix), total);
    }
    fn advance(&self, n: u64) {
        self.inner.advance(n);
    }
    fn finish(&self) {
        self.inner.finish();
    }
}

/// What `video.toml` records.
#[derive(Debug, Serialize)]
pub struct VideoReport<'a> {
    pub capture: String,
    pub method: String,
    pub reference_frames: Vec<usize>,
    /// Frames each video frame is reconstructed from, centred on its reference frame (absent:
    /// every frame).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub window: Option<usize>,
    /// The frame whose motion every frame reuses, composed to its own reference frame.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub motion_anchor_frame: Option<usize>,
    /// Why every frame was reconstructed on its own instead.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub per_frame_reason: Option<String>,
    pub preview_exposure_scale: f32,
    pub units: &'static str,
    pub config: &'a ReconstructConfig,
}

impl<'a> VideoReport<'a> {
    /// The report of a video of `plan` made from `capture` (as the user named it) with
    /// `config`, every frame on its own; the writer fills in the exposure scale.
    pub fn new(capture: String, config: &'a ReconstructConfig, plan: &VideoPlan) -> Self {
        VideoReport {
            capture,
            method: config.method.to_string(),
            reference_frames: plan.reference_frames(),
            window: plan.window,
            motion_anchor_frame: None,
            per_frame_reason: None,
            preview_exposure_scale: 1.0,
            units: LINEAR_UNITS,
            config,
        }
    }
}

/// The files of a video directory, written as the frames arrive (see the module
/// documentation): staged beside `out` and moved into place by [`Self::finish`]; dropped
/// before that (an error, Ctrl-C), it leaves nothing behind and an earlier `out` untouched.
pub struct VideoWriter {
    // Declared before `staged` so that the file is closed before the directory is removed.
    linear: Option<BufWriter<File>>,
    staged: StagedDir,
    frame_count: usize,
    written: usize,
    shape: Option<(usize, usize, usize)>,
    exposure_scale: Option<f32>,
}

impl VideoWriter {
    /// A video of `frame_count` frames to be written into `out`.
    pub fn create(out: &Path, frame_count: usize) -> Result<VideoWriter> {
        Ok(VideoWriter {
            linear: None,
            staged: StagedDir::new(out)?,
            frame_count,
            written: 0,
            shape: None,
            exposure_scale: None,
        })
    }

    /// The exposure scale of the PNGs (set by the first frame).
    pub fn exposure_scale(&self) -> Option<f32> {
        self.exposure_scale
    }

    /// Appends the next frame (linear RGB (H, W, 3), the shape of the first): its PNG, at the
    /// first frame's automatic exposure, and its slice of `linear.npy`.
    pub fn push(&mut self, linear: ArrayView3<f32>) -> Result<()> {
        let index = self.written;
        if index == self.frame_count {
            return Err(Error::invalid(format!(
                "video: frame {index} is one more than the {} planned",
                self.frame_count
            )));
        }
        let path = self.staged.path("linear.npy");
        let shape = *self.shape.get_or_insert(linear.dim());
        if linear.dim() != shape {
            return Err(Error::invalid(format!(
                "video frame {index} has shape {:?}, the first {shape:?}",
                linear.dim()
            )));
        }
        let scale = *self
            .exposure_scale
            .get_or_insert_with(|| auto_exposure_scale(linear));
        io::write_png_rgb8(
            self.staged.path(&frame_file_name(index)),
            &encode_srgb8(linear, scale),
        )?;
        if self.linear.is_none() {
            self.linear = Some(start_stack(&path, self.frame_count, shape)?);
        }
        let out = self.linear.as_mut().expect("opened above");
        let bytes: Vec<u8> = linear.iter().flat_map(|v| v.to_le_bytes()).collect();
        out.write_all(&bytes).map_err(|e| Error::io(&path, e))?;
        self.written += 1;
        Ok(())
    }

    /// Writes `video.toml` (`report`, with the exposure scale filled in) and moves the video
    /// into place; errors unless every planned frame was pushed.
    pub fn finish(mut self, mut report: VideoReport<'_>) -> Result<PathBuf> {
        if self.written != self.frame_count {
            return Err(Error::invalid(format!(
                "video: {} of {} frames were written",
                self.written, self.frame_count
            )));
        }
        let path = self.staged.path("linear.npy");
        if let Some(mut out) = self.linear.take() {
            out.flush().map_err(|e| Error::io(&path, e))?;
        }
        report.preview_exposure_scale = self.exposure_scale.unwrap_or(1.0);
        let report_path = self.staged.path("video.toml");
        let text = toml::to_string_pretty(&report)
            .map_err(|e| Error::format(&report_path, format!("cannot serialise: {e}")))?;
        std::fs::write(&report_path, text).map_err(|e| Error::io(&report_path, e))?;
        self.staged.commit()
    }
}

/// Creates `path` as a float32 `.npy` of `frame_count` frames of `shape` and returns a writer
/// at its first element (the header as `ndarray-npy` writes it, so the file is the one
/// [`io::write_npy`] writes for the stacked frames).
fn start_stack(
    path: &Path,
    frame_count: usize,
    (h, w, c): (usize, usize, usize),
) -> Result<BufWriter<File>> {
    let mut file = File::create(path).map_err(|e| Error::io(path, e))?;
    ndarray_npy::write_zeroed_npy::<f32, _>(&file, Dim([frame_count, h, w, c]))
        .map_err(|e| Error::io(path, std::io::Error::other(e)))?;
    let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let data = (frame_count * h * w * c * 4) as u64;
    file.seek(SeekFrom::Start(len - data))
        .map_err(|e| Error::io(path, e))?;
    Ok(BufWriter::with_capacity(1 << 22, file))
}

/// Writes one video frame's linear RGB as `part` (a `.npy`), atomically: a finished part of a
/// video made in pieces ([`assemble_parts`]).
pub fn write_part(part: &Path, linear: ArrayView3<f32>) -> Result<()> {
    io::write_npy(part, &linear)
}

/// The part file of video frame `index` inside a parts directory.
pub fn part_path(parts_dir: &Path, index: usize) -> PathBuf {
    parts_dir.join(format!("linear_{index:05}.npy"))
}

/// Streams the finished parts of every frame of `plan` from `parts_dir` ([`write_part`], named
/// by [`part_path`]) through a [`VideoWriter`] into `out`: the same files as a video written
/// in one process. Errors name the first missing or malformed part.
pub fn assemble_parts(
    parts_dir: &Path,
    out: &Path,
    plan: &VideoPlan,
    report: VideoReport<'_>,
) -> Result<PathBuf> {
    let mut writer = VideoWriter::create(out, plan.frames.len())?;
    for frame in &plan.frames {
        let part = part_path(parts_dir, frame.index);
        let linear = io::read_npy_3d::<f32>(&part)?;
        writer.push(linear.view())?;
    }
    writer.finish(report)
}
