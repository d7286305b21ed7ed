//! Flux conservation in HDR scenes (issue 45): a synthetic step wedge over five decades of
//! light plus small bright points on a dark background, captured static and handheld; the
//! burst merge must keep the light of every patch it can measure.

use ndarray::{s, Array3};
use quantacolor::burst::{reconstruct_burst, BurstConfig};
use quantacolor::cfa::colorspad_cfa;
use quantacolor::metrics::MEASURABLE_DARK_FRAMES;
use quantacolor::pipeline::{reconstruct, ReconstructConfig};
use quantacolor::progress::Silent;
use quantacolor::simulate::{
    simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulatedCapture, SimulationConfig,
};

const H: usize = 254;
const W: usize = 496;
/// Patch side (px) of the wedge.
const PATCH: usize = 60;
/// Px left out at every side of a patch when it is measured.
const INSET: usize = 14;
/// Colours of the three rows of the wedge (fractions of W).
const COLOURS: [[f32; 3]; 3] = [
    [1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0],
    [0.6, 0.3, 0.1],
    [0.1, 0.3, 0.6],
];
/// Flux λ_W (scene units, close to detections per frame) of the dark background.
const BACKGROUND: f32 = 0.01;
/// Point sizes (px) and fluxes λ_W of the bright points.
const POINT_SIZES: [usize; 3] = [1, 2, 3];
const POINT_FLUX: [f32; 6] = [0.3, 1.0, 2.0, 3.0, 10.0, 30.0];

/// λ_W of wedge patch (row, col): eight steps of 10^(4/7) per row, rows interleaved, from
/// 0.001 to 25.
fn wedge_flux(row: usize, col: usize) -> f32 {
    10f32.powf(-3.0 + (col as f32 + row as f32 / 3.0) * 4.0 / 7.0)
}

/// Patch (row, col) as (y0, x0) of its top-left corner.
fn patch_origin(row: usize, col: usize) -> (usize, usize) {
    (8 + row * PATCH, 8 + col * PATCH)
}

/// Centre (y, x) of point (size index, flux index).
fn point_centre(size: usize, flux: usize) -> (usize, usize) {
    (192 + 20 * size, 30 + 75 * flux)
}

/// The wedge scene (H, W, 3), linear, W = R + G + B in the units of the flux.
fn wedge_scene() -> Array3<f32> {
    let mut image = Array3::<f32>::zeros((H, W, 3));
    for c in 0..3 {
        image.slice_mut(s![.., .., c]).fill(BACKGROUND / 3.0);
    }
    for (row, colour) in COLOURS.iter().enumerate() {
        for col in 0..8 {
            let (y0, x0) = patch_origin(row, col);
            for (c, &share) in colour.iter().enumerate() {
                image
                    .slice_mut(s![y0..y0 + PATCH, x0..x0 + PATCH, c])
                    .fill(wedge_flux(row, col) * share);
            }
        }
    }
    for (si, &size) in POINT_SIZES.iter().enumerate() {
        for (fi, &flux) in POINT_FLUX.iter().enumerate() {
            let (cy, cx) = point_centre(si, fi);
            let (y0, x0) = (cy - (size - 1) / 2, cx - (size - 1) / 2);
            for c in 0..3 {
                image
                    .slice_mut(s![y0..y0 + size, x0..x0 + size, c])
                    .fill(flux / 3.0);
            }
        }
    }
    image
}

fn simulate_wedge(motion: &str, frames: usize, seed: u64) -> SimulatedCapture {
    let image = wedge_scene();
    let mean_w = image.sum() as f64 / (H * W) as f64;
    let config = SimulationConfig {
        frames,
        flux: FluxSpec::Mean { flux: mean_w },
        motion: motion.parse::<MotionConfig>().unwrap(),
        seed,
        ..SimulationConfig::default()
    };
    let scene = Scene::from_linear(image, "wedge").unwrap();
    simulate_with_cfa(&config, &scene, &colorspad_cfa(), &Silent).unwrap()
}

/// Sum over R, G, B of `image` in the rectangle.
fn rect_sum(image: &Array3<f32>, y: std::ops::Range<usize>, x: std::ops::Range<usize>) -> f64 {
    image
        .slice(s![y, x, ..])
        .iter()
        .map(|&v| v as f64)
        .sum::<f64>()
}

fn max_w(truth: &Array3<f32>, y: std::ops::Range<usize>, x: std::ops::Range<usize>) -> f64 {
    let t = truth.slice(s![y, x, ..]);
    t.outer_iter()
        .flat_map(|row| {
            row.outer_iter()
                .map(|px| px.iter().map(|&v| v as f64).sum::<f64>())
                .collect::<Vec<_>>()
        })
        .fold(0.0, f64::max)
}

/// (λ_W of the truth, estimate / truth) of every wedge patch's interior, row-major.
fn patch_ratios(image: &Array3<f32>, truth: &Array3<f32>) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    for row in 0..3 {
        for col in 0..8 {
            let (y0, x0) = patch_origin(row, col);
            let (y, x) = (
                y0 + INSET..y0 + PATCH - INSET,
                x0 + INSET..x0 + PATCH - INSET,
            );
            let n = (y.len() * x.len()) as f64;
            let t = rect_sum(truth, y.clone(), x.clone());
            out.push((t / n, rect_sum(image, y, x) / t));
        }
    }
    out
}

/// (largest λ_W of the truth in the window, estimate / truth) of the 15x15 window around every
/// bright point.
fn point_ratios(image: &Array3<f32>, truth: &Array3<f32>) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    for si in 0..POINT_SIZES.len() {
        for fi in 0..POINT_FLUX.len() {
            let (cy, cx) = brightest_near(truth, point_centre(si, fi));
            let (y, x) = (cy - 7..cy + 8, cx - 7..cx + 8);
            let t = rect_sum(truth, y.clone(), x.clone());
            out.push((
                max_w(truth, y.clone(), x.clone()),
                rect_sum(image, y, x) / t,
            ));
        }
    }
    out
}

/// The pixel of largest λ_W of `truth` within 9 px of `at` (the scene is fitted to the sensor
/// plus the motion's margin, so a handheld capture's points sit a few pixels off the layout).
fn brightest_near(truth: &Array3<f32>, at: (usize, usize)) -> (usize, usize) {
    let w = |y: usize, x: usize| truth[[y, x, 0]] + truth[[y, x, 1]] + truth[[y, x, 2]];
    (at.0 - 9..=at.0 + 9)
        .flat_map(|y| (at.1 - 9..=at.1 + 9).map(move |x| (y, x)))
        .max_by(|a, b| w(a.0, a.1).total_cmp(&w(b.0, b.1)))
        .unwrap()
}

fn measurable(lambda_w: f64, frames: usize) -> bool {
    frames as f64 * (-lambda_w).exp() >= MEASURABLE_DARK_FRAMES
}

/// Prints patch and point ratios of the burst merge (and its planes) and the default output.
#[test]
#[ignore = "diagnostic: prints the light kept by every patch and point (--nocapture)"]
fn wedge_flux_diagnostic() {
    let frames: usize = std::env::var("WEDGE_FRAMES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2000);
    for motion in ["static", "handheld"] {
        let sim = simulate_wedge(motion, frames, 7);
        let capture = sim.to_capture().unwrap();
        let reference = capture.reference_frame();
        let truth = &sim.ground_truth;
        let burst =
            reconstruct_burst(&capture, reference, &BurstConfig::default(), &Silent).unwrap();
        let default = reconstruct(&capture, &ReconstructConfig::default(), &Silent).unwrap();
        let planes = &burst.merged.planes;
        println!("== {motion}, {frames} frames");
        let b = patch_ratios(&burst.merged.linear, truth);
        let d = patch_ratios(&default.linear, truth);
        for (i, ((lw, rb), (_, rd))) in b.iter().zip(&d).enumerate() {
            let (row, col) = (i / 8, i % 8);
            let (y0, x0) = patch_origin(row, col);
            let (y, x) = (
                y0 + INSET..y0 + PATCH - INSET,
                x0 + INSET..x0 + PATCH - INSET,
            );
            let plane_mean = |ch: usize| {
                planes
                    .flux
                    .slice(s![ch, y.clone(), x.clone()])
                    .mean()
                    .unwrap()
            };
            let tw = |ch: usize| truth.slice(s![y.clone(), x.clone(), ch]).mean().unwrap();
            let fallback = planes
                .w_fallback
                .slice(s![y.clone(), x.clone()])
                .iter()
                .filter(|&&f| f)
                .count();
            println!(
                "patch r{row} c{col} λW {lw:8.4} {} burst {:6.2} % default {:6.2} % | W plane {:6.2} % R {:6.2} G {:6.2} B {:6.2} fallback {fallback}",
                if measurable(*lw, frames) { "M" } else { "-" },
                100.0 * rb,
                100.0 * rd,
                100.0 * plane_mean(3) as f64 / (tw(0) + tw(1) + tw(2)) as f64,
                100.0 * plane_mean(0) / tw(0),
                100.0 * plane_mean(1) / tw(1),
                100.0 * plane_mean(2) / tw(2),
            );
        }
        let b = point_ratios(&burst.merged.linear, truth);
        let d = point_ratios(&default.linear, truth);
        for (i, ((lw, rb), (_, rd))) in b.iter().zip(&d).enumerate() {
            println!(
                "point size {} flux {:5.1} max λW {lw:7.3} {} burst {:6.2} % default {:6.2} %",
                POINT_SIZES[i / POINT_FLUX.len()],
                POINT_FLUX[i % POINT_FLUX.len()],
                if measurable(*lw, frames) { "M" } else { "-" },
                100.0 * rb,
                100.0 * rd
            );
        }
        for (name, image) in [
            ("burst", &burst.merged.linear),
            ("default", &default.linear),
        ] {
            let light = quantacolor::metrics::measurable_light_ratio(
                image.view(),
                truth.view(),
                capture.meta.w_weights,
                frames,
                16,
            )
            .unwrap()
            .unwrap();
            println!("{name}: measurable light {:.2} %", 100.0 * light);
        }
    }
}

/// Standard deviation of a patch interior's light ratio from photon and dark-count noise alone:
/// 1/√(expected detections), W at λ_W + d per frame over the patch's frames and pixels.
fn shot_noise(lambda_w: f64, dark: f64, frames: usize) -> f64 {
    let pixels = ((PATCH - 2 * INSET) * (PATCH - 2 * INSET)) as f64;
    let detections = (lambda_w + dark) * frames as f64 * pixels;
    (lambda_w + dark) / lambda_w / detections.sqrt()
}

/// Issue 45: over five decades of light, every wedge patch the capture can measure (at least
/// [`MEASURABLE_DARK_FRAMES`] expected frames without a W detection) keeps its light within
/// ±2 % (plus three standard deviations of its own photon noise, which reaches 2 % in the
/// darkest patches) in the burst merge and in the default output above λ_W = 0.01 (below it
/// the default output keeps 96–98 %: the denoiser's, not the merge's), and the 15x15 window
/// around every measurable bright point (1–3 px wide, up to λ_W ≈ 3) keeps at least 85 % of
/// its light in the burst merge (before the merge's flux-domain floor, 2x2 points at
/// λ_W = 3 kept 83 % static, 82.5 % handheld; after it the worst keeps 88 %) and 80 % in the
/// default output (worst 81.5 %: a 3x3 point at λ_W = 1.9, static, where chroma-BM3D shaves
/// what the merge kept). Per point, what is left is interpolation of W at the CFA's colour
/// sites (a point's light lands unevenly on a fixed CFA, 88–105 % static).
#[test]
fn wedge_patches_and_bright_points_keep_their_light() {
    let frames = 2000;
    let mut failures = Vec::new();
    for (motion, seed) in [("static", 7), ("handheld", 8)] {
        let sim = simulate_wedge(motion, frames, seed);
        let capture = sim.to_capture().unwrap();
        let dark = capture.meta.pixel_model().dark_per_frame;
        let reference = capture.reference_frame();
        let truth = &sim.ground_truth;
        let burst =
            reconstruct_burst(&capture, reference, &BurstConfig::default(), &Silent).unwrap();
        let default = reconstruct(&capture, &ReconstructConfig::default(), &Silent).unwrap();
        for (name, image, darkest, point_floor) in [
            ("burst", &burst.merged.linear, 0.0, 0.85),
            ("default", &default.linear, 0.01, 0.80),
        ] {
            for (i, &(lw, ratio)) in patch_ratios(image, truth).iter().enumerate() {
                let tolerance = 0.02 + 3.0 * shot_noise(lw, dark, frames);
                let checked = measurable(lw, frames) && lw >= darkest;
                println!(
                    "{motion} {name} patch {i:2} λ_W {lw:8.4}: {:6.2} % (±{:.1} %){}",
                    100.0 * ratio,
                    100.0 * tolerance,
                    if checked { "" } else { " not checked" }
                );
                if checked && (ratio - 1.0).abs() > tolerance {
                    failures.push(format!("{motion} {name} patch {i} λ_W {lw:.4}: {ratio:.4}"));
                }
            }
            for (i, &(lw, ratio)) in point_ratios(image, truth).iter().enumerate() {
                // A window whose peak is the background missed its point (handheld margin).
                let checked = measurable(lw, frames) && lw > 0.1;
                println!(
                    "{motion} {name} point {i:2} peak λ_W {lw:6.3}: {:6.2} %{}",
                    100.0 * ratio,
                    if checked { "" } else { " not checked" }
                );
                if checked && ratio < point_floor {
                    failures.push(format!(
                        "{motion} {name} point {i} peak λ_W {lw:.3}: {ratio:.4}"
                    ));
                }
            }
        }
    }
    assert!(failures.is_empty(), "light lost: {failures:#?}");
}
