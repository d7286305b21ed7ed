//! Videos of long recordings (`quantacolor::video::{VideoPlan, VideoWriter}`): each frame
//! reconstructed from the window of frames centred on its reference frame, registered there
//! (against the simulator's truth at that frame), and the streamed output files identical to
//! the stacked ones, whether written in one process or assembled from parts.

use ndarray::{Array3, Axis};
use quantacolor::capture::io;
use quantacolor::cfa::colorspad_cfa;
use quantacolor::denoise::chroma::DenoiseMethod;
use quantacolor::display::{auto_exposure_scale, encode_srgb8};
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::pipeline::ReconstructConfig;
use quantacolor::progress::Silent;
use quantacolor::simulate::{
    ground_truth_at, simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulationConfig,
};
use quantacolor::video::{
    assemble_parts, frame_file_name, part_path, reconstruct_frame, write_part, VideoPlan,
    VideoReport, VideoWriter,
};
use std::path::Path;

#[test]
fn plans_centre_a_window_on_every_reference_frame() {
    let plan = VideoPlan::new(1000, 250, Some(300)).unwrap();
    assert_eq!(plan.reference_frames(), [125, 375, 625, 875]);
    let windows: Vec<_> = plan.frames.iter().map(|f| f.frames.clone()).collect();
    // Clamped into the capture at both ends, 300 frames each.
    assert_eq!(windows, [0..300, 225..525, 475..775, 700..1000]);
    assert!(!plan.whole_capture());
    assert!(VideoPlan::new(1000, 250, None).unwrap().whole_capture());
    assert!(VideoPlan::new(1000, 250, Some(5000))
        .unwrap()
        .whole_capture());
    assert!(VideoPlan::new(1000, 0, None).is_err());
    assert!(VideoPlan::new(1000, 250, Some(0)).is_err());
    assert!(VideoPlan::new(10, 50, None).is_err());
}

/// A handheld capture whose camera moves by several pixels between the video's reference
/// frames: a frame made from its own window matches the truth at its own reference frame far
/// better than the truth at the others (a window placed or registered wrongly would not).
#[test]
fn windowed_frames_are_registered_at_their_own_reference_frame() {
    let config = SimulationConfig {
        frames: 1536,
        flux: FluxSpec::Mean { flux: 0.2 },
        motion: "handheld".parse::<MotionConfig>().unwrap(),
        seed: 41,
        ..SimulationConfig::default()
    };
    let scene = Scene::from_spec("builtin:chart").unwrap();
    let cfa = colorspad_cfa();
    let sim = simulate_with_cfa(&config, &scene, &cfa, &Silent).unwrap();
    let capture = sim.to_capture().unwrap();
    let plan = VideoPlan::new(1536, 512, Some(512)).unwrap();
    assert_eq!(plan.reference_frames(), [256, 768, 1280]);
    let truths = ground_truth_at(&config, &scene, &cfa, &plan.reference_frames()).unwrap();
    let mut rc = ReconstructConfig::default();
    rc.denoise.method = DenoiseMethod::None;
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };
    for frame in &plan.frames {
        let rec = reconstruct_frame(&capture, &rc, frame, &Silent).unwrap();
        assert_eq!(rec.frames_used, 512);
        let scores: Vec<f64> = truths
            .iter()
            .map(|t| {
                evaluate(rec.linear.view(), t.view(), &opts)
                    .unwrap()
                    .psnr_srgb
            })
            .collect();
        println!(
            "frame {}: PSNR against each truth {scores:.2?}",
            frame.index
        );
        let own = scores[frame.index];
        assert!(own > 24.0, "frame {}: {own:.2} dB", frame.index);
        for (i, &other) in scores.iter().enumerate() {
            if i != frame.index {
                assert!(own > other + 2.0, "frame {}: {scores:?}", frame.index);
            }
        }
    }
}

fn frames_of(n: usize) -> Vec<Array3<f32>> {
    (0..n)
        .map(|k| {
            Array3::from_shape_fn((5, 7, 3), |(y, x, c)| {
                0.01 * (k + 1) as f32 * (1 + y * 7 + x + 11 * c) as f32
            })
        })
        .collect()
}

fn entries(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn streamed_videos_are_the_stacked_files_and_parts_assemble_to_them() {
    let tmp = tempfile::tempdir().unwrap();
    let frames = frames_of(3);
    let plan = VideoPlan::new(300, 100, Some(100)).unwrap();
    let config = ReconstructConfig::default();
    let report = || VideoReport::new("cap".into(), &config, &plan);

    let out = tmp.path().join("video");
    let mut writer = VideoWriter::create(&out, 3).unwrap();
    for f in &frames {
        writer.push(f.view()).unwrap();
    }
    writer.finish(report()).unwrap();

    // linear.npy is the stack written at once; each PNG uses the first frame's exposure.
    let views: Vec<_> = frames.iter().map(|f| f.view()).collect();
    let stacked = tmp.path().join("stacked.npy");
    io::write_npy(&stacked, &ndarray::stack(Axis(0), &views).unwrap()).unwrap();
    let read = |p: &Path| std::fs::read(p).unwrap();
    assert_eq!(read(&out.join("linear.npy")), read(&stacked));
    let scale = auto_exposure_scale(frames[0].view());
    for (i, f) in frames.iter().enumerate() {
        let png = tmp.path().join("expected.png");
        io::write_png_rgb8(&png, &encode_srgb8(f.view(), scale)).unwrap();
        assert_eq!(read(&out.join(frame_file_name(i))), read(&png), "frame {i}");
    }
    let toml = std::fs::read_to_string(out.join("video.toml")).unwrap();
    assert!(toml.contains("window = 100"), "{toml}");
    let table: toml::Table = toml.parse().unwrap();
    let written = table["preview_exposure_scale"].as_float().unwrap();
    assert_eq!(written as f32, scale, "{toml}");

    // Parts written anywhere, in any order, assemble to the same files.
    let parts = tmp.path().join("parts");
    std::fs::create_dir(&parts).unwrap();
    for i in [2, 0, 1] {
        write_part(&part_path(&parts, i), frames[i].view()).unwrap();
    }
    let assembled = tmp.path().join("assembled");
    assemble_parts(&parts, &assembled, &plan, report()).unwrap();
    assert_eq!(entries(&out), entries(&assembled));
    for name in entries(&out) {
        assert_eq!(
            read(&out.join(&name)),
            read(&assembled.join(&name)),
            "{name}"
        );
    }

    // A missing part names itself and leaves nothing behind.
    std::fs::remove_file(part_path(&parts, 1)).unwrap();
    let incomplete = tmp.path().join("incomplete");
    let err = assemble_parts(&parts, &incomplete, &plan, report()).unwrap_err();
    assert!(err.to_string().contains("linear_00001.npy"), "{err}");
    assert!(!incomplete.exists());
}

#[test]
fn unfinished_or_inconsistent_videos_leave_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let frames = frames_of(2);
    let plan = VideoPlan::new(300, 100, None).unwrap();
    let config = ReconstructConfig::default();
    let out = tmp.path().join("video");

    // Dropped half-way (an error or Ctrl-C in the caller).
    let mut writer = VideoWriter::create(&out, 3).unwrap();
    writer.push(frames[0].view()).unwrap();
    drop(writer);
    assert_eq!(entries(tmp.path()), Vec::<String>::new());

    // Finished with a frame missing, or given a frame of another shape or one too many.
    let mut writer = VideoWriter::create(&out, 3).unwrap();
    writer.push(frames[0].view()).unwrap();
    assert!(writer.push(Array3::zeros((4, 7, 3)).view()).is_err());
    writer.push(frames[1].view()).unwrap();
    let report = VideoReport::new("cap".into(), &config, &plan);
    assert!(writer.finish(report).is_err());
    assert_eq!(entries(tmp.path()), Vec::<String>::new());

    let mut writer = VideoWriter::create(&out, 1).unwrap();
    writer.push(frames[0].view()).unwrap();
    assert!(writer.push(frames[1].view()).is_err());
}
