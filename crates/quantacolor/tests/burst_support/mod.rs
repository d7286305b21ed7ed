//! Shared by the burst tests: scoring the motion a burst reconstruction used against the
//! simulator's, and its image against the ground truth.

use ndarray::Array3;
use quantacolor::burst::BurstReconstruction;
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::simulate::SimulatedCapture;

/// sRGB PSNR (dB) of the linear image `linear` against `sim`'s ground truth by the quality
/// suite's protocol: a 16-pixel border left out, both scaled so that the truth's 99.5th
/// percentile is 1.
pub fn psnr_srgb(sim: &SimulatedCapture, linear: &Array3<f32>) -> f64 {
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };
    evaluate(linear.view(), sim.ground_truth.view(), &opts)
        .unwrap()
        .psnr_srgb
}

/// Median end-point error (px) of the merge's motion at 16 frames spread over the burst.
pub fn median_epe(sim: &SimulatedCapture, burst: &BurstReconstruction) -> f64 {
    let (h, w) = (sim.cfa.height(), sim.cfa.width());
    let frames = sim.motion.frames;
    let mut errors = Vec::new();
    for k in 0..16 {
        let t = (k as f64 + 0.5) / 16.0 * frames as f64;
        let est = burst.merge_flow(t);
        let truth = sim.motion.dense_flow(t, h, w);
        for y in (16..h - 16).step_by(4) {
            for x in (16..w - 16).step_by(4) {
                let dy = (est[[y, x, 0]] - truth[[y, x, 0]]) as f64;
                let dx = (est[[y, x, 1]] - truth[[y, x, 1]]) as f64;
                errors.push((dy * dy + dx * dx).sqrt());
            }
        }
    }
    errors.sort_by(f64::total_cmp);
    errors[errors.len() / 2]
}
