//! Pixel supersampling in the simulator (`SimulationConfig::pixel_supersampling`): a scene with
//! detail finer than a pixel, each pixel integrating it over its s x s sub-pixel area, and the
//! high-resolution ground truth on the merge's scale-s grid.
//!
//! The known truth: a static sensor of H x W viewing an image of exactly 2(H + 6) x 2(W + 6)
//! pixels (the static motion's 3-pixel scene margin on every side) maps image pixel
//! (6 + 2Y + i, 6 + 2X + j) onto sub-pixel (i, j) of sensor pixel (Y, X), with a footprint of one
//! image pixel (no pre-filtering). So the high-resolution truth is the image crop times the
//! quantum efficiency and the flux gain, and every pixel's detection rate is the 2x2 mean of
//! its four image pixels.

use ndarray::{s, Array3};
use quantacolor::capture::BinaryFrames;
use quantacolor::progress::Silent;
use quantacolor::simulate::{simulate, FluxSpec, Scene, SimulatedCapture, SimulationConfig};

const H: usize = 24;
const W: usize = 32;

/// Deterministic pseudorandom value in [0.1, 1.0] per (y, x, c).
fn pseudo_random(y: usize, x: usize, c: usize) -> f32 {
    let mut z = (y as u64) << 32 ^ (x as u64) << 8 ^ c as u64 ^ 0x5eed;
    z = z.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z ^= z >> 29;
    z = z.wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z ^= z >> 32;
    0.1 + 0.9 * (z % 10_000) as f32 / 10_000.0
}

/// The 2(H + 6) x 2(W + 6) linear image: independent random values per image pixel, so a sensor
/// pixel's four sub-pixels differ.
fn fine_image() -> Array3<f32> {
    Array3::from_shape_fn((2 * (H + 6), 2 * (W + 6), 3), |(y, x, c)| {
        pseudo_random(y, x, c)
    })
}

fn config(frames: usize, supersampling: usize) -> SimulationConfig {
    SimulationConfig {
        height: H,
        width: W,
        frames,
        cfa: "bayer".into(),
        flux: FluxSpec::Mean { flux: 1.0 },
        hot_fraction: 0.0,
        seed: 11,
        pixel_supersampling: supersampling,
        ..SimulationConfig::default()
    }
}

fn simulate_fine(frames: usize, supersampling: usize) -> SimulatedCapture {
    let scene = Scene::from_linear(fine_image(), "fine").unwrap();
    simulate(&config(frames, supersampling), &scene, &Silent).unwrap()
}

/// λ of channel c at sensor pixel (y, x) before the flux gain: the quantum efficiency times the
/// 2x2 mean of the pixel's four image pixels (`corner` = Some((i, j)): that sub-pixel alone).
fn expected_unscaled(
    image: &Array3<f32>,
    qe: [f64; 3],
    y: usize,
    x: usize,
    c: usize,
    corner: Option<(usize, usize)>,
) -> f64 {
    let v = match corner {
        Some((i, j)) => image[[6 + 2 * y + i, 6 + 2 * x + j, c]] as f64,
        None => {
            image
                .slice(s![6 + 2 * y..8 + 2 * y, 6 + 2 * x..8 + 2 * x, c])
                .sum() as f64
                / 4.0
        }
    };
    v * qe[c]
}

/// The flux gain of `FluxSpec::Mean { flux: 1 }`: mean W (= R + G + B) detections are 1.
fn gain(image: &Array3<f32>, qe: [f64; 3]) -> f64 {
    let mut w_sum = 0.0;
    for y in 0..H {
        for x in 0..W {
            w_sum += (0..3)
                .map(|c| expected_unscaled(image, qe, y, x, c, None))
                .sum::<f64>();
        }
    }
    1.0 / (w_sum / (H * W) as f64)
}

#[test]
fn ground_truths_are_the_sub_pixel_scene_and_its_pixel_area_mean() {
    let sim = simulate_fine(4, 2);
    let image = fine_image();
    let qe = sim.sensor.quantum_efficiency;
    let g = gain(&image, qe);
    let hr = sim
        .ground_truth_hr
        .as_ref()
        .expect("supersampling 2 gives a high-resolution ground truth");
    assert_eq!(hr.dim(), (2 * H, 2 * W, 3));
    assert_eq!(sim.ground_truth.dim(), (H, W, 3));
    let mut worst_hr = 0.0f64;
    let mut worst_1x = 0.0f64;
    for y in 0..H {
        for x in 0..W {
            for c in 0..3 {
                let want = g * expected_unscaled(&image, qe, y, x, c, None);
                let got = sim.ground_truth[[y, x, c]] as f64;
                worst_1x = worst_1x.max((got / want - 1.0).abs());
                for (i, j) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    let want = g * expected_unscaled(&image, qe, y, x, c, Some((i, j)));
                    let got = hr[[2 * y + i, 2 * x + j, c]] as f64;
                    worst_hr = worst_hr.max((got / want - 1.0).abs());
                }
            }
        }
    }
    assert!(worst_hr < 1e-4, "hr truth off the image by {worst_hr:.2e}");
    assert!(
        worst_1x < 1e-4,
        "1x truth off the 2x2 area mean by {worst_1x:.2e}"
    );
}

#[test]
fn detection_rates_are_the_pixel_area_mean() {
    let frames = 4000;
    let sim = simulate_fine(frames, 2);
    let image = fine_image();
    let qe = sim.sensor.quantum_efficiency;
    let g = gain(&image, qe);
    let packed = BinaryFrames::from_packed(sim.packed_frames.clone(), sim.width).unwrap();
    let counts = packed.sum_range(0..frames);
    let t = frames as f64;
    // Mean of z² = ((λ̂ − λ) / σ)² over the pixels, with λ̂ = −ln(1 − p̂) − d from the bit
    // density and σ² = p / ((1 − p) T) its binomial variance; ~1 for the right λ.
    let chi2 = |corner: Option<(usize, usize)>| -> f64 {
        let mut sum = 0.0;
        for y in 0..H {
            for x in 0..W {
                let c = sim.cfa.channel(y, x).index();
                let d = sim.dark_count_rates_hz[[y, x]] * sim.meta.exposure_s;
                let lambda = g * expected_unscaled(&image, qe, y, x, c, corner);
                let p = 1.0 - (-(lambda + d)).exp();
                let p_hat = counts[[y, x]] as f64 / t;
                let lambda_hat = -(1.0 - p_hat).ln() - d;
                let var = p / ((1.0 - p) * t);
                sum += (lambda_hat - lambda).powi(2) / var;
            }
        }
        sum / (H * W) as f64
    };
    let area = chi2(None);
    assert!(
        (0.8..1.25).contains(&area),
        "detection rates against the 2x2 area mean: mean z² {area:.3} (expected ~1)"
    );
    // Sanity of the test's power: one sub-pixel alone is far off.
    let corner = chi2(Some((0, 0)));
    assert!(corner > 5.0, "mean z² against one sub-pixel {corner:.3}");
}

/// 2x2 box mean of an (2H, 2W, 3) image.
fn box2(hr: &Array3<f32>) -> Array3<f32> {
    let (h2, w2, c) = hr.dim();
    Array3::from_shape_fn((h2 / 2, w2 / 2, c), |(y, x, k)| {
        hr.slice(s![2 * y..2 * y + 2, 2 * x..2 * x + 2, k]).sum() / 4.0
    })
}

#[test]
fn hr_truth_box_downsampled_is_the_1x_truth_under_motion() {
    // A photograph-like scene at a non-integer scale, handheld motion and a moving object:
    // the reference frame's truths still agree.
    for motion in ["handheld", "object"] {
        let image = Array3::from_shape_fn((150, 200, 3), |(y, x, c)| {
            0.3 + 0.2 * ((y as f32 * 0.7 + c as f32).sin() * (x as f32 * 0.45).cos())
                + 0.2 * pseudo_random(y, x, c)
        });
        let scene = Scene::from_linear(image, "synthetic").unwrap();
        let config = SimulationConfig {
            height: 40,
            width: 56,
            frames: 64,
            motion: motion.parse().unwrap(),
            pixel_supersampling: 2,
            ..SimulationConfig::default()
        };
        let sim = simulate(&config, &scene, &Silent).unwrap();
        let hr = sim.ground_truth_hr.as_ref().unwrap();
        assert_eq!(hr.dim(), (80, 112, 3));
        let down = box2(hr);
        let scale = sim.ground_truth.iter().fold(0.0f32, |m, &v| m.max(v));
        let worst = down
            .iter()
            .zip(sim.ground_truth.iter())
            .map(|(a, b)| (a - b).abs() / scale)
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-5, "{motion}: box(hr) − 1x truth {worst:.2e}");
        // The high-resolution truth holds detail the 1x truth averages away.
        let residual: f32 = (0..80)
            .flat_map(|y| (0..112).map(move |x| (y, x)))
            .map(|(y, x)| (hr[[y, x, 1]] - down[[y / 2, x / 2, 1]]).abs())
            .sum::<f32>()
            / (80.0 * 112.0);
        assert!(
            residual > 0.01 * scale,
            "{motion}: no sub-pixel detail (mean |hr − box| {residual:.2e})"
        );
    }
}

#[test]
fn supersampling_defaults_to_one_and_old_configs_parse() {
    let config: SimulationConfig = toml::from_str("frames = 10\nheight = 8\nwidth = 16\n").unwrap();
    assert_eq!(config.pixel_supersampling, 1);
    let sim = simulate(&config, &Scene::Constant([0.5; 3]), &Silent).unwrap();
    assert!(sim.ground_truth_hr.is_none());
    let bad = SimulationConfig {
        pixel_supersampling: 0,
        ..config
    };
    assert!(simulate(&bad, &Scene::Constant([0.5; 3]), &Silent).is_err());
}
