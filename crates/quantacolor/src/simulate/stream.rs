//! Streaming simulation ([`simulate_to_dir`]): the frames are rendered a chunk at a time (in
//! parallel within the chunk) and appended to the capture directory through a
//! [`CaptureWriter`], so memory holds the scene, the motion truth and one chunk of frames,
//! whatever the number of frames. Frame `t` draws from its own random stream, so the files are
//! byte for byte those of [`super::simulate`] followed by [`super::SimulatedCapture::write`]
//! (or the CMOS equivalents) for the same configuration, scene and seed.
#![forbid(unsafe_code)]

use super::render::{self, FrameJob};
use super::{binary_readout, config_cfa, prepare, Scene, SimulationConfig};
use super::{MOTION_FILE, PROGRESS_BINARY, PROGRESS_CMOS};
use crate::capture::CaptureWriter;
use crate::error::Result;
use crate::progress::Progress;
use ndarray::{Array3, Axis, Slice};
use std::path::Path;

/// Bytes of frames rendered before they are written (about 1,000 packed binary frames or 66
/// multi-bit frames of 496x254).
const CHUNK_BYTES: usize = 16 << 20;

/// Simulates the capture `config` describes (binary for SPAD and jot sensors, multi-bit for
/// CMOS; the CFA named by `config.cfa`) of `scene` and writes it atomically as the capture
/// directory `dir`: frames, CFA, metadata, hot pixels, ground truth and `motion.toml`, as
/// [`super::SimulatedCapture::write`] does. An error or an interruption leaves nothing behind
/// and an existing capture at `dir` untouched.
pub fn simulate_to_dir(
    config: &SimulationConfig,
    scene: &Scene,
    dir: impl AsRef<Path>,
    progress: &dyn Progress,
) -> Result<()> {
    simulate_in_chunks(config, scene, dir.as_ref(), None, progress)
}

/// [`simulate_to_dir`], rendering `chunk_frames` frames at a time (default: [`CHUNK_BYTES`] of
/// frames, at least four per thread).
fn simulate_in_chunks(
    config: &SimulationConfig,
    scene: &Scene,
    dir: &Path,
    chunk_frames: Option<usize>,
    progress: &dyn Progress,
) -> Result<()> {
    let cfa = config_cfa(config)?;
    let readout = binary_readout(config.sensor);
    let prep = prepare(config, scene, &cfa)?;
    let (t, h, w) = (config.frames, config.height, config.width);
    let mut writer = match readout {
        Some(_) => CaptureWriter::create(dir, t, h, w)?,
        None => CaptureWriter::create_multibit(dir, t, h, w)?,
    };
    let field = prep.field();
    let job = FrameJob {
        field: &field,
        cfa: &cfa,
        dark_per_frame: &prep.dark_per_frame,
        frames: t,
        seed: config.seed,
    };
    let chunk = chunk_frames
        .unwrap_or_else(|| {
            (CHUNK_BYTES / writer.frame_bytes()).max(4 * rayon::current_num_threads())
        })
        .clamp(1, t);
    match readout {
        Some(readout) => {
            let mut buf = Array3::<u8>::zeros((chunk, h, w.div_ceil(8)));
            progress.start(PROGRESS_BINARY, t as u64);
            for first in (0..t).step_by(chunk) {
                let n = chunk.min(t - first);
                buf.fill(0);
                let mut frames = buf.slice_axis_mut(Axis(0), Slice::from(..n));
                render::render_binary_into(&job, readout, first, frames.view_mut(), progress);
                let bytes = frames.as_slice().expect("a leading slice is contiguous");
                for frame in bytes.chunks_exact(writer.frame_bytes()) {
                    writer.write_frame(frame)?;
                }
            }
        }
        None => {
            let mut buf = Array3::<u16>::zeros((chunk, h, w));
            progress.start(PROGRESS_CMOS, t as u64);
            for first in (0..t).step_by(chunk) {
                let n = chunk.min(t - first);
                let mut frames = buf.slice_axis_mut(Axis(0), Slice::from(..n));
                render::render_cmos_into(&job, &prep.sensor, first, frames.view_mut(), progress);
                let samples = frames.as_slice().expect("a leading slice is contiguous");
                for frame in samples.chunks_exact(h * w) {
                    writer.write_frame_u16(frame)?;
                }
            }
        }
    }
    progress.finish();
    writer.write_ground_truth(&prep.ground_truth)?;
    writer.write_extra_file(MOTION_FILE, prep.motion.to_toml()?.as_bytes())?;
    writer.finish(&cfa, &prep.meta, Some(&prep.dark.hot_pixels), None)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::Silent;
    use crate::simulate::{simulate, simulate_cmos, MotionConfig, SensorKind};

    /// Every file of the capture directory `dir`, by name.
    fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
        let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| {
                let e = e.unwrap();
                (
                    e.file_name().to_string_lossy().to_string(),
                    std::fs::read(e.path()).unwrap(),
                )
            })
            .collect();
        out.sort();
        out
    }

    /// The streamed capture, in uneven chunks and in one, is the in-memory capture's files byte
    /// for byte, for every sensor and for object motion (its own raster).
    #[test]
    fn streamed_captures_are_the_in_memory_ones_byte_for_byte() {
        let tmp = tempfile::tempdir().unwrap();
        let scene = Scene::from_spec("builtin:chart").unwrap();
        for (sensor, motion) in [
            (SensorKind::Spad, "handheld"),
            (SensorKind::Jot, "pan"),
            (SensorKind::Cmos, "object"),
        ] {
            let config = SimulationConfig {
                height: 24,
                width: 37,
                frames: 11,
                sensor,
                motion: motion.parse::<MotionConfig>().unwrap(),
                seed: 5,
                ..SimulationConfig::default()
            };
            let memory = tmp.path().join(format!("{sensor:?}-memory"));
            if sensor == SensorKind::Cmos {
                simulate_cmos(&config, &scene, &Silent)
                    .unwrap()
                    .write(&memory)
                    .unwrap();
            } else {
                simulate(&config, &scene, &Silent)
                    .unwrap()
                    .write(&memory)
                    .unwrap();
            }
            let expected = files(&memory);
            assert_eq!(expected.len(), 6, "{sensor:?}: {expected:?}");
            for chunk in [Some(4), Some(1), None] {
                let streamed = tmp.path().join(format!("{sensor:?}-{chunk:?}"));
                simulate_in_chunks(&config, &scene, &streamed, chunk, &Silent).unwrap();
                let got = files(&streamed);
                assert_eq!(got.len(), expected.len(), "{sensor:?} chunk {chunk:?}");
                for ((name, bytes), (want_name, want)) in got.iter().zip(&expected) {
                    assert_eq!(name, want_name, "{sensor:?} chunk {chunk:?}");
                    assert!(bytes == want, "{sensor:?} chunk {chunk:?}: {name} differs");
                }
            }
        }
    }

    /// A failed simulation (the target is a folder of other files) leaves that folder as it
    /// was and no temporary directory beside it.
    #[test]
    fn a_refused_target_is_left_untouched() {
        let tmp = tempfile::tempdir().unwrap();
        let target = tmp.path().join("notes");
        std::fs::create_dir(&target).unwrap();
        std::fs::write(target.join("keep.txt"), b"mine").unwrap();
        let config = SimulationConfig {
            height: 8,
            width: 8,
            frames: 3,
            ..SimulationConfig::default()
        };
        let scene = Scene::from_spec("builtin:flat").unwrap();
        let err = simulate_to_dir(&config, &scene, &target, &Silent).unwrap_err();
        assert!(err.to_string().contains("notes"), "{err}");
        assert_eq!(std::fs::read(target.join("keep.txt")).unwrap(), b"mine");
        let entries: Vec<_> = std::fs::read_dir(tmp.path()).unwrap().collect();
        assert_eq!(entries.len(), 1, "{entries:?}");
    }
}
