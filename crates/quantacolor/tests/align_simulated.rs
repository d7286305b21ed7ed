//! Alignment accuracy on simulated captures with known motion (issue: alignment accuracy).
//! Median end-point error at block centres, over textured tiles, against the simulator's true
//! motion. Run with `--nocapture` to see the numbers.

use ndarray::Axis;
use quantacolor::align::{align, AlignConfig, Alignment};
use quantacolor::capture::BinaryFrames;
use quantacolor::cfa::{colorspad_cfa, generate, Cfa, Pattern};
use quantacolor::progress::Silent;
use quantacolor::simulate::{
    simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulatedCapture, SimulationConfig,
};

fn simulate(cfa: &Cfa, motion: &str, frames: usize, flux: f64, seed: u64) -> SimulatedCapture {
    let config = SimulationConfig {
        height: cfa.height(),
        width: cfa.width(),
        frames,
        flux: FluxSpec::Mean { flux },
        motion: motion.parse::<MotionConfig>().unwrap(),
        hot_fraction: 0.02,
        seed,
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

/// (median EPE over textured tiles, median EPE over tiles on the moving object if any,
/// median EPE over static tiles off the object) at block centres.
fn errors(sim: &SimulatedCapture, alignment: &Alignment) -> (f64, f64, f64) {
    let truth_w = sim.ground_truth.sum_axis(Axis(2));
    let grid = &alignment.grid;
    let half = grid.tile_size as f64 / 2.0;
    // Texture: std of the true W luminance in the tile relative to its mean.
    let mut textured = Vec::new();
    for (ty, &cy) in grid.tile_centers_y.iter().enumerate() {
        for (tx, &cx) in grid.tile_centers_x.iter().enumerate() {
            let (y0, x0) = (
                (cy as f64 - half).max(0.0) as usize,
                (cx as f64 - half).max(0.0) as usize,
            );
            let (y1, x1) = (
                ((cy as f64 + half) as usize).min(truth_w.nrows()),
                ((cx as f64 + half) as usize).min(truth_w.ncols()),
            );
            let tile = truth_w.slice(ndarray::s![y0..y1, x0..x1]);
            let mean = tile.mean().unwrap();
            let std = tile.std(0.0);
            if mean > 0.0 && std / mean > 0.1 {
                textured.push((ty, tx, cy as f64, cx as f64));
            }
        }
    }
    let (mut all, mut on, mut off) = (Vec::new(), Vec::new(), Vec::new());
    for (b, &centre) in alignment.plan.center_frames().iter().enumerate() {
        let (f0, f1) = (centre.floor() as usize, centre.ceil() as usize);
        for &(ty, tx, cy, cx) in &textured {
            let (a0, a1) = sim.motion.true_displacement(f0, cy, cx);
            let (b0, b1) = sim.motion.true_displacement(f1, cy, cx);
            let (ty_, tx_) = ((a0 + b0) / 2.0, (a1 + b1) / 2.0);
            let ey = alignment.flow[[b, ty, tx, 0]] as f64 - ty_;
            let ex = alignment.flow[[b, ty, tx, 1]] as f64 - tx_;
            let e = (ey * ey + ex * ex).sqrt();
            all.push(e);
            if sim.motion.object.is_some() {
                // Tiles fully inside or fully outside the object disc.
                let inside = sim.motion.on_object([cy, cx])
                    && sim.motion.on_object([cy - half, cx - half])
                    && sim.motion.on_object([cy + half, cx + half]);
                let outside = !sim.motion.on_object([cy, cx])
                    && !sim.motion.on_object([cy - 2.0 * half, cx])
                    && !sim.motion.on_object([cy + 2.0 * half, cx])
                    && !sim.motion.on_object([cy, cx - 2.0 * half])
                    && !sim.motion.on_object([cy, cx + 2.0 * half]);
                if inside {
                    on.push(e);
                } else if outside {
                    off.push(e);
                }
            }
        }
    }
    (median(&mut all), median(&mut on), median(&mut off))
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn run(cfa: &Cfa, motion: &str, frames: usize, flux: f64) -> (f64, f64, f64) {
    let sim = simulate(cfa, motion, frames, flux, 7);
    let bits = BinaryFrames::from_packed(sim.packed_frames.clone(), sim.width).unwrap();
    let reference = sim.meta.reference_frame.unwrap_or(frames / 2);
    let alignment = align(
        &bits,
        &sim.cfa,
        Some(&sim.hot_pixels),
        reference,
        &AlignConfig::default(),
        &Silent,
    )
    .unwrap();
    let e = errors(&sim, &alignment);
    println!(
        "{motion:>14} T={frames:>5} flux={flux:<5} B={:>4} blocks={:>2}: median EPE {:.3} px (object {:.3}, background {:.3})",
        alignment.plan.block_size,
        alignment.plan.len(),
        e.0,
        e.1,
        e.2
    );
    e
}

// Thresholds are regression guards at about 1.3x the errors measured when they were set
// (0.1 photons/pixel/frame, 512 frames: handheld 0.106 (blue noise 0.106), pan 0.058, circular
// 0.110, object 0.15 and its background 0.044 px; 0.02 photons and 2000 frames: 0.129 px). The
// project's targets are 0.15 px and 0.3 px: all rows meet them. Before the Tukey stage of the
// camera fit (mismatched tiles pulled the fit toward zero motion: gain 0.97) handheld was at
// 0.18 px. Before the block-centre correction (block images measure the trajectory's mean over a
// block, not its centre-frame position) handheld and circular were at 0.33 px.

#[test]
fn colorspad_cfa_handheld_pan_and_circular_at_0_1_photons() {
    let cfa = colorspad_cfa();
    let mut worst: f64 = 0.0;
    for motion in ["handheld", "pan", "circular"] {
        let (e, _, _) = run(&cfa, motion, 512, 0.1);
        worst = worst.max(e);
    }
    assert!(worst <= 0.15, "worst median EPE {worst:.3} px");
}

#[test]
fn blue_noise_cfa_handheld_at_0_1_photons() {
    let cfa = generate(&Pattern::BlueNoise { w_fraction: 0.75 }, 254, 496, 0).unwrap();
    let (e, _, _) = run(&cfa, "handheld", 512, 0.1);
    assert!(e <= 0.15, "median EPE {e:.3} px");
}

#[test]
fn low_light_0_02_photons_2000_frames() {
    let cfa = colorspad_cfa();
    let (e, _, _) = run(&cfa, "handheld", 2000, 0.02);
    assert!(e <= 0.17, "median EPE {e:.3} px");
}

#[test]
fn moving_object_is_followed_and_background_stays_still() {
    let cfa = colorspad_cfa();
    let (_, on, off) = run(&cfa, "object", 512, 0.1);
    // The object's texture is periodic (6 px): its tiles follow it through the second motion
    // model fitted to the tiles the camera fit rejects.
    assert!(on <= 0.2, "object tiles: median EPE {on:.3} px");
    assert!(off <= 0.06, "background tiles: median EPE {off:.3} px");
}
