//! Memory bounded in T (issue 15): the default reconstruction (burst alignment, refinement,
//! merge, chroma-BM3D) of 100,000 frames of 496x254 peaks at no more than 600 MB of resident
//! memory, and its time grows about linearly with T (printed, not asserted).
//!
//! Ignored by default (Linux only): it needs a 100,000-frame capture, 1.6 GB on disk.
//! `QUANTACOLOR_100K_CAPTURE=DIR` names one, e.g. made by
//! `quantacolor simulate --frames 100000 --cfa rgbw-75-bluenoise --out DIR`; without it the
//! test simulates one into a temporary directory first (about ten minutes on two cores):
//!
//! ```sh
//! QUANTACOLOR_100K_CAPTURE=/tmp/cap100k cargo test --release -p quantacolor \
//!     --test memory_100k -- --ignored --nocapture
//! ```
//!
//! The peak is the process's VmHWM from `/proc/self/status`, reset (`/proc/self/clear_refs`)
//! after the capture is opened, so a simulation in the same process does not count.

#![cfg(target_os = "linux")]

use quantacolor::capture::{Capture, FrameWindow};
use quantacolor::pipeline::{reconstruct, ReconstructConfig};
use quantacolor::progress::Silent;
use quantacolor::simulate::{simulate, SimulationConfig};
use std::path::PathBuf;
use std::time::Instant;

const FRAMES: usize = 100_000;
const LIMIT_MB: f64 = 600.0;

/// A field of `/proc/self/status` in kB.
fn status_kb(field: &str) -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    status
        .lines()
        .find_map(|l| l.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or_else(|| panic!("{field} missing from /proc/self/status"))
}

/// Resets the peak resident set (VmHWM) to the current one.
fn reset_peak() {
    std::fs::write("/proc/self/clear_refs", "5").expect("cannot reset VmHWM");
}

#[test]
#[ignore]
fn reconstruct_100k_frames_within_600_mb() {
    let mut _simulated = None;
    let dir = match std::env::var_os("QUANTACOLOR_100K_CAPTURE") {
        Some(dir) => PathBuf::from(dir),
        None => {
            let tmp = tempfile::tempdir().unwrap();
            let config = SimulationConfig {
                frames: FRAMES,
                cfa: "rgbw-75-bluenoise".into(),
                ..SimulationConfig::default()
            };
            let scene = quantacolor::simulate::Scene::from_spec("builtin:chart").unwrap();
            let t0 = Instant::now();
            simulate(&config, &scene, &Silent)
                .unwrap()
                .write(tmp.path().join("cap"))
                .unwrap();
            println!(
                "simulated {FRAMES} frames in {:.0} s",
                t0.elapsed().as_secs_f64()
            );
            let dir = tmp.path().join("cap");
            _simulated = Some(tmp);
            dir
        }
    };
    let config = ReconstructConfig::default();

    let capture = Capture::open(&dir).unwrap();
    let t = capture.frames.frame_count();
    assert!(
        t >= FRAMES,
        "{} holds {t} frames, need {FRAMES}",
        dir.display()
    );
    let capture = capture
        .window(&format!("0:{FRAMES}").parse::<FrameWindow>().unwrap())
        .unwrap();
    reset_peak();
    let before_kb = status_kb("VmHWM");
    let start = Instant::now();
    let rec = reconstruct(&capture, &config, &Silent).unwrap();
    let large_s = start.elapsed().as_secs_f64();
    let peak_mb = status_kb("VmHWM") as f64 / 1024.0;
    assert!(rec.linear.iter().all(|v| v.is_finite()));
    drop((rec, capture));

    // The same reconstruction on the middle tenth, for the time's growth with T.
    let small = Capture::open(&dir)
        .unwrap()
        .window(
            &format!("{}:{}", 9 * FRAMES / 20, 11 * FRAMES / 20)
                .parse::<FrameWindow>()
                .unwrap(),
        )
        .unwrap();
    let start = Instant::now();
    reconstruct(&small, &config, &Silent).unwrap();
    let small_s = start.elapsed().as_secs_f64();

    println!(
        "{FRAMES} frames: {large_s:.1} s, peak resident {peak_mb:.0} MB (limit {LIMIT_MB:.0} MB; \
         {:.0} MB before the reconstruction); {} frames: {small_s:.1} s; time ratio {:.1} for \
         10x the frames",
        before_kb as f64 / 1024.0,
        FRAMES / 10,
        large_s / small_s
    );
    assert!(
        peak_mb <= LIMIT_MB,
        "peak resident memory {peak_mb:.0} MB exceeds {LIMIT_MB:.0} MB"
    );
}
