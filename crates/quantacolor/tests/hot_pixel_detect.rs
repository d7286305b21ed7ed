//! Hot-pixel self-calibration (issue 12) on simulated captures with known injected hot pixels:
//! it must find the hot pixels that matter and flag almost no scene pixels (sharp chart
//! edges, colour patches), with and without camera motion. Run with `--nocapture` for the
//! numbers.

use quantacolor::align::hot_pixels::{detect_hot_pixels, HotPixelDetectConfig};
use quantacolor::cfa::{generate, Cfa, Pattern};
use quantacolor::progress::Silent;
use quantacolor::simulate::{
    simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulatedCapture, SimulationConfig,
};

fn simulate(cfa: &Cfa, motion: &str, hot_fraction: f64, hot_rate_hz: [f64; 2]) -> SimulatedCapture {
    let config = SimulationConfig {
        height: cfa.height(),
        width: cfa.width(),
        frames: 1000,
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: motion.parse::<MotionConfig>().unwrap(),
        hot_fraction,
        hot_rate_hz,
        seed: 5,
        ..SimulationConfig::default()
    };
    simulate_with_cfa(
        &config,
        &Scene::from_spec("builtin:chart").unwrap(),
        cfa,
        &Silent,
    )
    .unwrap()
}

/// (hot pixels found / hot pixels whose dark counts at least double their light, false
/// positives, normal pixels).
fn score(sim: &SimulatedCapture) -> (usize, usize, usize, usize) {
    let capture = sim.to_capture().unwrap();
    let mask = detect_hot_pixels(
        &capture.frames,
        &capture.cfa,
        capture.meta.w_weights,
        &HotPixelDetectConfig::default(),
    )
    .unwrap();
    let exposure = capture.meta.exposure_s;
    let (mut found, mut strong, mut false_pos, mut normal) = (0, 0, 0, 0);
    for ((pos, &hot), &flagged) in sim.hot_pixels.indexed_iter().zip(mask.iter()) {
        if hot {
            // Light at this pixel: its channel's flux at the reference frame.
            let (y, x) = pos;
            let c = capture.cfa.codes()[pos] as usize;
            let light: f32 = if c == 3 {
                (0..3).map(|k| sim.ground_truth[[y, x, k]]).sum()
            } else {
                sim.ground_truth[[y, x, c]]
            };
            let dark = sim.dark_count_rates_hz[pos] * exposure;
            if dark >= light.max(0.01) as f64 {
                strong += 1;
                found += flagged as usize;
            }
        } else {
            normal += 1;
            false_pos += flagged as usize;
        }
    }
    (found, strong, false_pos, normal)
}

#[test]
fn finds_injected_hot_pixels_with_few_false_positives() {
    let cfa = generate(&"rgbw-75-bluenoise".parse::<Pattern>().unwrap(), 96, 128, 0).unwrap();
    for motion in ["static", "handheld"] {
        let sim = simulate(&cfa, motion, 0.02, [2e3, 2e4]);
        let (found, strong, false_pos, normal) = score(&sim);
        let recall = found as f64 / strong as f64;
        let fp_rate = false_pos as f64 / normal as f64;
        println!(
            "{motion}: found {found} of {strong} strong hot pixels ({:.1} %), {false_pos} false \
             positives of {normal} ({:.3} %)",
            100.0 * recall,
            100.0 * fp_rate
        );
        assert!(
            strong > 100,
            "{motion}: too few strong hot pixels to score ({strong})"
        );
        let min_recall = if motion == "static" { 0.85 } else { 0.95 };
        assert!(recall > min_recall, "{motion}: recall {recall}");
        assert!(fp_rate < 0.001, "{motion}: false-positive rate {fp_rate}");
    }
}

#[test]
fn a_clean_capture_gets_almost_no_hot_pixels() {
    let cfa = generate(&"rgbw-75-bluenoise".parse::<Pattern>().unwrap(), 96, 128, 0).unwrap();
    for motion in ["static", "handheld"] {
        let sim = simulate(&cfa, motion, 0.0, [2e3, 2e4]);
        let (_, _, false_pos, normal) = score(&sim);
        println!("{motion}, no hot pixels: {false_pos} flagged of {normal}");
        assert!(
            (false_pos as f64) < 0.001 * normal as f64,
            "{motion}: {false_pos} scene pixels flagged"
        );
    }
}
