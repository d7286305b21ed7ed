//! Video reconstruction with the motion estimated once (`quantacolor::video`): the composition
//! of camera maps against the simulator's true motion, and the frames against the full
//! per-reference reconstruction and the ground truth at each reference frame.

use ndarray::{Array2, Array4};
use quantacolor::align::{AffineMotion, Alignment, BlockPlan, FrameMotion, GreyMethod, TileGrid};
use quantacolor::cfa::colorspad_cfa;
use quantacolor::denoise::chroma::DenoiseMethod;
use quantacolor::metrics::{evaluate, psnr, EvalOptions};
use quantacolor::pipeline::{reconstruct, ReconstructConfig};
use quantacolor::progress::Silent;
use quantacolor::simulate::{
    ground_truth_at, simulate_with_cfa, FluxSpec, Motion, MotionConfig, Scene, SimulationConfig,
};
use quantacolor::video::{
    compose_cameras, frame_to_anchor_from_blocks, reanchor_cameras, VideoReconstructor,
};

const H: usize = 120;
const W: usize = 160;

/// The simulator's rigid map of frame `t` (reference → t) as an affine displacement about the
/// image centre.
fn true_camera(motion: &Motion, t: usize) -> AffineMotion {
    let c = [(H as f64 - 1.0) / 2.0, (W as f64 - 1.0) / 2.0];
    let f = |p: [f64; 2]| motion.forward(t, p);
    let o = f(c);
    let dy = f([c[0] + 1.0, c[1]]);
    let dx = f([c[0], c[1] + 1.0]);
    AffineMotion {
        b: [o[0] - c[0], o[1] - c[1]],
        m: [
            [dy[0] - o[0] - 1.0, dx[0] - o[0]],
            [dy[1] - o[1], dx[1] - o[1] - 1.0],
        ],
    }
}

/// Largest distance between two maps (as x ↦ x + d(x)) over the image corners and centre, px.
fn distance(a: &AffineMotion, b: &AffineMotion) -> f64 {
    let (hy, hx) = (H as f64 / 2.0, W as f64 / 2.0);
    [[0.0, 0.0], [-hy, -hx], [-hy, hx], [hy, -hx], [hy, hx]]
        .iter()
        .map(|&p| {
            let (u, v) = (a.at(p), b.at(p));
            (u[0] - v[0]).hypot(u[1] - v[1])
        })
        .fold(0.0, f64::max)
}

/// A burst motion of one-frame sub-blocks whose cameras are the simulator's true motion
/// relative to its reference frame (the anchor).
fn true_frame_motion(motion: &Motion) -> FrameMotion {
    let t = motion.frames;
    let plan = BlockPlan::new(t, 50, motion.reference_frame).unwrap();
    let grid = TileGrid::new(H, W, 16, 8);
    let alignment = Alignment {
        flow: Array4::zeros((plan.len(), grid.tiles_y, grid.tiles_x, 2)),
        grey: vec![Array2::zeros((H, W)); plan.len()],
        grey_method: GreyMethod::InterpolateW,
        plan,
        grid,
    };
    let mut frame_motion = FrameMotion::from_alignment(&alignment, 2.0, 80, 0.5);
    frame_motion.sub_blocks = (0..t).map(|f| f..f + 1).collect();
    frame_motion.block_of = (0..t)
        .map(|f| {
            alignment
                .plan
                .blocks
                .iter()
                .position(|b| b.contains(&f))
                .unwrap()
        })
        .collect();
    frame_motion.camera = (0..t).map(|f| true_camera(motion, f)).collect();
    frame_motion
}

#[test]
fn composed_camera_maps_match_the_true_motion_relative_to_any_reference_frame() {
    let config = MotionConfig::Handheld {
        amplitude_px: 6.0,
        rotation_deg: 2.0,
        cycles: 1.0,
    };
    let motion = Motion::generate(&config, 400, 200, H, W, 5).unwrap();
    let frame_motion = true_frame_motion(&motion);
    for r in [0, 37, 200, 311, 399] {
        // Truth relative to r: p_r ↦ forward(t, inverse(r, p_r)).
        let composed = reanchor_cameras(&frame_motion, r).unwrap();
        let mut worst = 0.0f64;
        for (t, camera) in composed.iter().enumerate() {
            let truth = true_camera(&motion, t).after(&true_camera(&motion, r).inverse().unwrap());
            for p in [[-50.0, -70.0], [40.0, 75.0], [0.0, 0.0]] {
                let c = [(H as f64 - 1.0) / 2.0, (W as f64 - 1.0) / 2.0];
                let q = motion.forward(t, motion.inverse(r, [p[0] + c[0], p[1] + c[1]]));
                let d = camera.at(p);
                let err = (p[0] + c[0] + d[0] - q[0]).hypot(p[1] + c[1] + d[1] - q[1]);
                worst = worst.max(err);
            }
            worst = worst.max(distance(camera, &truth));
        }
        println!("reference {r}: largest error of the composed maps {worst:.2e} px");
        assert!(worst < 1e-6, "reference {r}: {worst}");
        // The composed motion is zero at r itself.
        assert!(distance(&composed[r], &AffineMotion::default()) < 1e-9);
    }
    // The map to the anchor pooled from block cameras relative to r (their true values at the
    // block centres) is the true one, and composing with it gives the true motion again.
    let r = 311;
    let to_r = true_camera(&motion, r).inverse().unwrap();
    let centres = frame_motion.plan.center_frames();
    let block_cameras: Vec<AffineMotion> = centres
        .iter()
        .map(|&c| frame_motion.camera_at(c).after(&to_r))
        .collect();
    let w = frame_to_anchor_from_blocks(&frame_motion, &block_cameras).unwrap();
    assert!(distance(&w, &to_r) < 1e-6, "{:?} vs {to_r:?}", w);
    let pooled = compose_cameras(&frame_motion, &w);
    let direct = reanchor_cameras(&frame_motion, r).unwrap();
    let worst = pooled
        .iter()
        .zip(&direct)
        .map(|(a, b)| distance(a, b))
        .fold(0.0, f64::max);
    assert!(worst < 1e-6, "{worst}");
    // One block whose camera fit failed moves the median, not the map.
    let mut bad = block_cameras.clone();
    bad[0] = AffineMotion {
        b: [9.0, -7.0],
        ..AffineMotion::default()
    };
    let w = frame_to_anchor_from_blocks(&frame_motion, &bad).unwrap();
    assert!(distance(&w, &to_r) < 1e-6);
}

#[test]
fn video_frames_match_the_per_reference_reconstruction() {
    let config = SimulationConfig {
        frames: 1024,
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: "handheld".parse::<MotionConfig>().unwrap(),
        hot_fraction: 0.02,
        seed: 31,
        ..SimulationConfig::default()
    };
    let scene = Scene::from_spec("builtin:chart").unwrap();
    let cfa = colorspad_cfa();
    let sim = simulate_with_cfa(&config, &scene, &cfa, &Silent).unwrap();
    let capture = sim.to_capture().unwrap();
    let references = [128, 512, 896];
    let truths = ground_truth_at(&config, &scene, &cfa, &references).unwrap();
    // The truth at the simulator's own reference frame is its ground truth.
    assert_eq!(truths[1], sim.ground_truth);
    let mut rc = ReconstructConfig::default();
    rc.denoise.method = DenoiseMethod::None;
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };
    let video = VideoReconstructor::new(&capture, &rc, &Silent).unwrap();
    assert_eq!(video.fallback_reason(), None);
    assert_eq!(video.anchor_frame(), 512);
    let (mut sum_old, mut sum_new) = (0.0, 0.0);
    for (i, &r) in references.iter().enumerate() {
        let per_reference = reconstruct(
            &capture,
            &ReconstructConfig {
                reference_frame: Some(r),
                ..rc.clone()
            },
            &Silent,
        )
        .unwrap();
        let frame = video.frame(r, &Silent).unwrap();
        assert_eq!(frame.reference_frame, r);
        if r == video.anchor_frame() {
            // At the anchor the reuse path is the per-reference path.
            assert_eq!(frame.linear, per_reference.linear);
        }
        let peak = per_reference.linear.fold(0.0f32, |a, &v| a.max(v)) as f64;
        let between = psnr(frame.linear.view(), per_reference.linear.view(), peak).unwrap();
        let old = evaluate(per_reference.linear.view(), truths[i].view(), &opts).unwrap();
        let new = evaluate(frame.linear.view(), truths[i].view(), &opts).unwrap();
        println!(
            "reference {r}: per-reference {:.2} dB, reuse {:.2} dB, reuse vs per-reference \
             {between:.2} dB",
            old.psnr_srgb, new.psnr_srgb
        );
        sum_old += old.psnr_srgb;
        sum_new += new.psnr_srgb;
        assert!(between > 30.0, "reference {r}: {between} dB");
        // A frame registered to another reference frame would be far off the truth.
        assert!(new.psnr_srgb > old.psnr_srgb - 0.5, "reference {r}");
    }
    let n = references.len() as f64;
    let (mean_old, mean_new) = (sum_old / n, sum_new / n);
    println!("mean: per-reference {mean_old:.2} dB, reuse {mean_new:.2} dB");
    assert!(mean_new > mean_old - 0.2, "{mean_new} vs {mean_old}");
}

/// `for_frames` moves the anchor to a video frame and keeps the block size when it divides the
/// spacing (every video frame is then a block centre of the anchor's grid, the one at the anchor
/// its reference block's), and keeps `new`'s grid when it does not.
#[test]
fn for_frames_centres_evenly_spaced_frames_in_their_blocks() {
    let config = SimulationConfig {
        frames: 1024,
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: "handheld".parse::<MotionConfig>().unwrap(),
        seed: 32,
        ..SimulationConfig::default()
    };
    let scene = Scene::from_spec("builtin:chart").unwrap();
    let sim = simulate_with_cfa(&config, &scene, &colorspad_cfa(), &Silent).unwrap();
    let capture = sim.to_capture().unwrap();
    let mut rc = ReconstructConfig::default();
    rc.burst.align.blocks.block_size = Some(101);
    // Spacing 202 = 2 B: frames 101 + 202 k are block centres; 505 is nearest the capture's 512.
    let centred = [101, 303, 505, 707, 909];
    let video = VideoReconstructor::for_frames(&capture, &rc, &centred, &Silent).unwrap();
    assert_eq!(video.anchor_frame(), 505);
    let plan = BlockPlan::new(1024, 101, 505).unwrap();
    let centres = plan.center_frames();
    for r in centred {
        assert!(centres.contains(&(r as f64)), "{r} is not a block centre");
    }
    // Spacing 150 is no multiple of B (within 2 %): the anchor stays.
    let other = [75, 225, 375, 525, 675, 825, 975];
    let video = VideoReconstructor::for_frames(&capture, &rc, &other, &Silent).unwrap();
    assert_eq!(video.anchor_frame(), 512);
}
