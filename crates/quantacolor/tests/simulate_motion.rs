//! Simulator motion tests: identity at the reference frame, inverse consistency, known
//! displacements per model, a pan moving the rendered frames by the expected amount, and the
//! serialised description.

use ndarray::Array3;
use quantacolor::capture::BinaryFrames;
use quantacolor::cfa::{Cfa, Channel};
use quantacolor::progress::Silent;
use quantacolor::simulate::{
    simulate_with_cfa, FluxSpec, Motion, MotionConfig, Scene, SimulationConfig,
};

const NAMES: [&str; 6] = [
    "static",
    "pan",
    "handheld",
    "fast-handheld",
    "circular",
    "object",
];

fn generate(name: &str) -> Motion {
    Motion::generate(&name.parse().unwrap(), 300, 120, 60, 80, 5).unwrap()
}

#[test]
fn identity_at_reference_and_inverse_consistent() {
    for name in NAMES {
        let m = generate(name);
        assert_eq!(m.model, name);
        for &(y, x) in &[(0.0, 0.0), (30.0, 40.0), (59.0, 3.5), (12.25, 79.0)] {
            assert_eq!(m.true_displacement(120, y, x), (0.0, 0.0), "{name}");
            for t in [0, 7, 119, 121, 299] {
                let q = m.forward(t, [y, x]);
                let p = m.inverse(t, q);
                assert!(
                    (p[0] - y).abs() < 1e-9 && (p[1] - x).abs() < 1e-9,
                    "{name} t={t}"
                );
            }
        }
    }
}

#[test]
fn model_displacements_match_their_definition() {
    let pan = Motion::generate(
        &MotionConfig::Pan {
            velocity: [0.01, -0.03],
        },
        300,
        120,
        60,
        80,
        0,
    )
    .unwrap();
    let (dy, dx) = pan.true_displacement(220, 10.0, 10.0);
    assert!((dy - 1.0).abs() < 1e-12 && (dx + 3.0).abs() < 1e-12);

    // Handheld: peaks equal the configured amplitude and rotation (0.5 degrees by default).
    let hh = generate("handheld");
    let peak = |v: &[f64]| v.iter().fold(0.0f64, |m, a| m.max(a.abs()));
    assert!((peak(&hh.dy) - 4.0).abs() < 1e-9 && (peak(&hh.dx) - 4.0).abs() < 1e-9);
    assert!((peak(&hh.theta_rad) - 0.5f64.to_radians()).abs() < 1e-12);
    // Smooth: no frame-to-frame jump above the peak speed of the sinusoid sum.
    let max_step = hh
        .dx
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .fold(0.0, f64::max);
    assert!(
        max_step < 0.2,
        "handheld jumps {max_step} px between frames"
    );
    let fast = generate("fast-handheld");
    assert!(peak(&fast.dx) > 3.0 * peak(&hh.dx));

    // Circular: every displacement lies on the circle of radius 8 through the origin.
    let c = generate("circular");
    for t in 0..300 {
        let (dy, dx) = c.true_displacement(t, 20.0, 20.0);
        assert!((dy.hypot(dx + 8.0) - 8.0).abs() < 1e-9);
    }

    // Object: points on the disc move with it, the background stays.
    let o = generate("object");
    let track = o.object.clone().unwrap();
    let (cy, cx) = (track.center[0], track.center[1]);
    let (dy, dx) = o.true_displacement(220, cy + 1.0, cx - 2.0);
    assert!((dy - 0.0).abs() < 1e-12 && (dx - 0.05 * 100.0).abs() < 1e-9);
    assert_eq!(o.true_displacement(220, 0.0, 0.0), (0.0, 0.0));
}

#[test]
fn rotation_moves_corners_more_than_the_centre() {
    let m = Motion::generate(
        &MotionConfig::Handheld {
            amplitude_px: 0.0,
            rotation_deg: 2.0,
            cycles: 1.0,
        },
        100,
        50,
        101,
        101,
        3,
    )
    .unwrap();
    let t = (0..100)
        .max_by(|&a, &b| m.theta_rad[a].abs().total_cmp(&m.theta_rad[b].abs()))
        .unwrap();
    let (cy, cx) = m.true_displacement(t, 50.0, 50.0);
    assert!(cy.abs() < 1e-9 && cx.abs() < 1e-9);
    let (dy, dx) = m.true_displacement(t, 0.0, 100.0);
    // Chord of a 2 degree turn at radius 50·√2.
    let expected = 2.0 * 50.0 * 2f64.sqrt() * (1f64.to_radians()).sin();
    assert!((dy.hypot(dx) - expected).abs() < 1e-6);
}

#[test]
fn motion_description_round_trips_through_toml() {
    for name in NAMES {
        let m = generate(name);
        let text = m.to_toml().unwrap();
        let back: Motion = toml::from_str(&text).unwrap();
        assert_eq!(back, m, "{name}");
    }
    let cfg: MotionConfig = toml::from_str("model = \"circular\"\nradius_px = 3.0").unwrap();
    assert_eq!(
        cfg,
        MotionConfig::Circular {
            radius_px: 3.0,
            revolutions: 1.0
        }
    );
    assert!("wobble".parse::<MotionConfig>().is_err());
    assert!(Motion::generate(&MotionConfig::Static, 10, 10, 4, 4, 0).is_err());
}

/// Centroid (y, x) of counts above a threshold halfway between the median and the maximum.
fn centroid(sum: &ndarray::Array2<u32>) -> (f64, f64) {
    let mut sorted: Vec<u32> = sum.iter().copied().collect();
    sorted.sort_unstable();
    let (median, max) = (
        sorted[sorted.len() / 2] as f64,
        *sorted.last().unwrap() as f64,
    );
    let bg = 0.5 * (median + max);
    let (mut m, mut my, mut mx) = (0.0, 0.0, 0.0);
    for ((y, x), &c) in sum.indexed_iter() {
        let v = (c as f64 - bg).max(0.0);
        m += v;
        my += v * y as f64;
        mx += v * x as f64;
    }
    (my / m, mx / m)
}

#[test]
fn pan_moves_a_bright_dot_by_the_expected_amount() {
    // A Gaussian dot on a dark background, seen by an all-W sensor.
    let (hs, ws) = (80, 100);
    let image = Array3::from_shape_fn((hs, ws, 3), |(y, x, _)| {
        let r2 = (y as f32 - 40.0).powi(2) + (x as f32 - 50.0).powi(2);
        0.01 + (-r2 / 18.0).exp()
    });
    let scene = Scene::from_linear(image, "dot").unwrap();
    let config = SimulationConfig {
        height: 40,
        width: 56,
        frames: 400,
        motion: MotionConfig::Pan {
            velocity: [0.01, 0.03],
        },
        reference_frame: Some(0),
        flux: FluxSpec::Mean { flux: 0.2 },
        hot_fraction: 0.0,
        ..SimulationConfig::default()
    };
    let cfa = Cfa::uniform(40, 56, Channel::W);
    let sim = simulate_with_cfa(&config, &scene, &cfa, &Silent).unwrap();
    let frames = BinaryFrames::from_packed(sim.packed_frames.clone(), 56).unwrap();
    let (a, b) = (
        centroid(&frames.sum_range(0..100)),
        centroid(&frames.sum_range(300..400)),
    );
    // Mean frame 49.5 vs 349.5: 300 frames apart.
    let (dy, dx) = (b.0 - a.0, b.1 - a.1);
    assert!(
        (dy - 3.0).abs() < 0.3 && (dx - 9.0).abs() < 0.3,
        "shift ({dy}, {dx})"
    );
    // The ground truth is the reference frame (0): its centroid matches the first block's.
    let gt = sim
        .ground_truth
        .map_axis(ndarray::Axis(2), |v| (v.sum() * 1e4) as u32);
    let g = centroid(&gt);
    assert!((g.0 - (a.0 - 0.495)).abs() < 0.3 && (g.1 - (a.1 - 1.485)).abs() < 0.3);
}

#[test]
fn object_moves_over_a_static_background() {
    let config = SimulationConfig {
        height: 48,
        width: 64,
        frames: 200,
        motion: MotionConfig::Object {
            radius_frac: 0.2,
            velocity: [0.0, 0.08],
        },
        reference_frame: Some(0),
        flux: FluxSpec::Mean { flux: 0.5 },
        hot_fraction: 0.0,
        ..SimulationConfig::default()
    };
    let cfa = Cfa::uniform(48, 64, Channel::W);
    let scene = Scene::Constant([0.05; 3]);
    let sim = simulate_with_cfa(&config, &scene, &cfa, &Silent).unwrap();
    let frames = BinaryFrames::from_packed(sim.packed_frames.clone(), 64).unwrap();
    let (a, b) = (
        centroid(&frames.sum_range(0..50)),
        centroid(&frames.sum_range(150..200)),
    );
    // The bright object moves 150 frames · 0.08 px = 12 px to the right.
    assert!((b.1 - a.1 - 12.0).abs() < 0.8, "object moved {}", b.1 - a.1);
    assert!((b.0 - a.0).abs() < 0.5);
}
