//! Shared by the burst tests: scoring the motion a burst reconstruction used against the
//! simulator's.

use quantacolor::burst::BurstReconstruction;
use quantacolor::simulate::SimulatedCapture;

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
