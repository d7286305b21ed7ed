//! Diagnostic (ignored by default): alignment error per block split into mean bias and spread,
//! against three notions of the truth. Run with
//! `cargo test --release -p quantacolor --test align_diagnose -- --ignored --nocapture`.

use ndarray::{s, Array3, Axis};
use quantacolor::align::{
    affine_fit_field, align, median_filter_flow, median_filter_valid_flow, snap_to_affine_fit,
    AlignConfig, ReferenceAligner,
};
use quantacolor::capture::BinaryFrames;
use quantacolor::cfa::colorspad_cfa;
use quantacolor::progress::Silent;
use quantacolor::simulate::{simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulationConfig};

fn med(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[test]
#[ignore]
fn diagnose() {
    let motion = std::env::var("MOTION").unwrap_or("handheld".into());
    let cfa = colorspad_cfa();
    let config = SimulationConfig {
        height: cfa.height(),
        width: cfa.width(),
        frames: 512,
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: motion.parse::<MotionConfig>().unwrap(),
        hot_fraction: std::env::var("HOT")
            .map(|v| v.parse().unwrap())
            .unwrap_or(0.02),
        seed: 7,
        ..SimulationConfig::default()
    };
    let sim = simulate_with_cfa(
        &config,
        &Scene::from_spec("builtin:chart").unwrap(),
        &cfa,
        &Silent,
    )
    .unwrap();
    let bits = BinaryFrames::from_packed(sim.packed_frames.clone(), sim.width).unwrap();
    let mut cfg = AlignConfig::default();
    if let Ok(sig) = std::env::var("SIGMA") {
        cfg.patch.presmooth_sigma = sig.parse().unwrap();
    }
    if let Ok(it) = std::env::var("LKIT") {
        cfg.patch.lk_iterations = it.parse().unwrap();
    }
    if std::env::var("GREY").is_ok() {
        cfg.grey = quantacolor::align::GreyChoice::Demosaic;
    }
    let al = align(&bits, &sim.cfa, Some(&sim.hot_pixels), 256, &cfg, &Silent).unwrap();
    let grid = &al.grid;
    let truth_w = sim.ground_truth.sum_axis(Axis(2));
    let half = grid.tile_size as f64 / 2.0;
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
            let tile = truth_w.slice(s![y0..y1, x0..x1]);
            let m = tile.mean().unwrap();
            if m > 0.0 && tile.std(0.0) / m > 0.1 {
                textured.push((ty, tx, cy as f64, cx as f64));
            }
        }
    }
    let aligner = ReferenceAligner::new(&al.grey[al.plan.reference_block], &cfg.patch).unwrap();
    let m = &sim.motion;
    let mean_disp = |r: std::ops::Range<usize>, y: f64, x: f64| {
        let n = r.len() as f64;
        let (mut a, mut b) = (0.0, 0.0);
        for t in r {
            let d = m.true_displacement(t, y, x);
            a += d.0;
            b += d.1;
        }
        (a / n, b / n)
    };
    let refr = al.plan.blocks[al.plan.reference_block].clone();
    println!(
        "motion {motion} ref block {:?} ref frame {}",
        refr, al.plan.reference_frame
    );
    for (b, range) in al.plan.blocks.iter().enumerate() {
        let c = al.plan.center_frames()[b];
        let raw = aligner.align(&al.grey[b]).unwrap();
        let medf = median_filter_flow(&raw, 1);
        let ints = raw.iter().filter(|v| v.fract() == 0.0).count() as f64 / raw.len() as f64;
        let ints_tex = textured
            .iter()
            .filter(|&&(ty, tx, ..)| {
                raw[[ty, tx, 0]].fract() == 0.0 && raw[[ty, tx, 1]].fract() == 0.0
            })
            .count() as f64
            / textured.len() as f64;
        println!(
            "b{b}: integer components {ints:.2}, integer textured tiles {ints_tex:.2} of {}",
            textured.len()
        );
        let fit = snap_to_affine_fit(&medf, grid, 1e6);
        let stages: [(&str, &Array3<f32>); 4] = [
            ("raw", &raw),
            ("median", &medf),
            ("fit", &fit),
            ("final", &al.flow.slice(s![b, .., .., ..]).to_owned()),
        ];
        for (name, f) in stages {
            let mut line = format!("b{b} {:?} c={c:.1} {name:>6}:", range);
            for truth in 0..3 {
                let (mut by, mut bx, mut es) = (0.0, 0.0, Vec::new());
                let (mut sy, mut sx, mut et, mut tt) = (Vec::new(), Vec::new(), 0.0, 0.0);
                for &(ty, tx, cy, cx) in &textured {
                    let t = match truth {
                        0 => {
                            let (f0, f1) = (c.floor() as usize, c.ceil() as usize);
                            let (a, bb) = (
                                m.true_displacement(f0, cy, cx),
                                m.true_displacement(f1, cy, cx),
                            );
                            ((a.0 + bb.0) / 2.0, (a.1 + bb.1) / 2.0)
                        }
                        1 => mean_disp(range.clone(), cy, cx),
                        _ => {
                            let a = mean_disp(range.clone(), cy, cx);
                            let r = mean_disp(refr.clone(), cy, cx);
                            // position in block mean of point at p in ref-block mean
                            (a.0 - r.0, a.1 - r.1)
                        }
                    };
                    let ey = f[[ty, tx, 0]] as f64 - t.0;
                    let ex = f[[ty, tx, 1]] as f64 - t.1;
                    by += ey;
                    bx += ex;
                    sy.push(ey);
                    sx.push(ex);
                    if (ey * ey + ex * ex) < 1.0 {
                        et += ey * t.0 + ex * t.1;
                        tt += t.0 * t.0 + t.1 * t.1;
                    }
                    es.push((ey * ey + ex * ex).sqrt());
                }
                let n = textured.len() as f64;
                let (by, bx) = (by / n, bx / n);
                if truth == 0 {
                    line += &format!(
                        " medsigned ({:+.3},{:+.3}) slope {:+.4}",
                        med(&mut sy),
                        med(&mut sx),
                        et / tt.max(1e-9)
                    );
                }
                line += &format!(
                    "  [{truth}] bias ({by:+.3},{bx:+.3}) med {:.3}",
                    med(&mut es)
                );
            }
            if let Some(object) = &m.object {
                let mut on = Vec::new();
                let mut fl = Vec::new();
                for &(ty, tx, cy, cx) in &textured {
                    if m.on_object([cy, cx])
                        && m.on_object([cy - half, cx - half])
                        && m.on_object([cy + half, cx + half])
                    {
                        let (f0, f1) = (c.floor() as usize, c.ceil() as usize);
                        let (a, bb) = (
                            m.true_displacement(f0, cy, cx),
                            m.true_displacement(f1, cy, cx),
                        );
                        let t = ((a.0 + bb.0) / 2.0, (a.1 + bb.1) / 2.0);
                        let (ey, ex) = (f[[ty, tx, 0]] as f64 - t.0, f[[ty, tx, 1]] as f64 - t.1);
                        on.push((ey * ey + ex * ex).sqrt());
                        fl.push(format!("{:.1}", f[[ty, tx, 1]]));
                    }
                }
                let n_on = on.len();
                println!(
                    "  object {name}: median EPE {:.3} over {n_on} tiles, truth dx {:.2}; dx {}",
                    med(&mut on),
                    object.dx[c as usize],
                    fl[..fl.len().min(30)].join(" ")
                );
            }
            if std::env::var("ALL").is_ok() || name == "final" {
                println!("{}", &line[..line.len().min(110)]);
            }
        }
    }
}

/// Linear motion passes `block_centre_flow` unchanged but for the shift that makes the flow at
/// the reference frame zero (the function's contract in `align::motion`).
#[test]
fn centre_flow_keeps_linear_motion_up_to_the_reference_shift() {
    use quantacolor::align::{block_centre_flow, BlockPlan};
    let plan = BlockPlan::new(512, 64, 256).unwrap();
    let n = plan.len();
    let centres = plan.center_frames();
    // dy moves 1/64 px per frame (linear in time, so a block's mean is its centre frame's
    // position; the first block is shorter than the others), dx is constant.
    let per_frame = 1.0 / 64.0;
    let mut f = ndarray::Array4::<f32>::zeros((n, 1, 1, 2));
    for k in 0..n {
        f[[k, 0, 0, 0]] = (centres[k] * per_frame) as f32;
        f[[k, 0, 0, 1]] = 1.0;
    }
    let o = block_centre_flow(&f, &plan);
    for k in 0..n {
        let dy = ((centres[k] - plan.reference_frame as f64) * per_frame) as f32;
        assert!(
            (o[[k, 0, 0, 0]] - dy).abs() < 1e-4,
            "block {k}: dy {} want {dy}",
            o[[k, 0, 0, 0]]
        );
        assert!(
            o[[k, 0, 0, 1]].abs() < 1e-5,
            "block {k}: dx {}",
            o[[k, 0, 0, 1]]
        );
    }
}

#[test]
#[ignore]
fn centre_flow_on_truth() {
    use quantacolor::align::{block_centre_flow, BlockPlan, TileGrid};
    for motion in ["handheld", "circular", "pan"] {
        let m = quantacolor::simulate::Motion::generate(
            &motion.parse().unwrap(),
            512,
            256,
            254,
            496,
            7,
        )
        .unwrap();
        let plan = BlockPlan::new(512, 64, 256).unwrap();
        let grid = TileGrid::new(254, 496, 16, 8);
        let n = plan.len();
        let mean_disp = |r: std::ops::Range<usize>, y: f64, x: f64| {
            let k = r.len() as f64;
            let (mut a, mut b) = (0.0, 0.0);
            for t in r {
                let d = m.true_displacement(t, y, x);
                a += d.0;
                b += d.1;
            }
            (a / k, b / k)
        };
        let refr = plan.blocks[plan.reference_block].clone();
        let mut f = ndarray::Array4::<f32>::zeros((n, grid.tiles_y, grid.tiles_x, 2));
        let mut truth = f.clone();
        for (b, r) in plan.blocks.iter().enumerate() {
            let c = plan.center_frames()[b];
            for (i, &cy) in grid.tile_centers_y.iter().enumerate() {
                for (j, &cx) in grid.tile_centers_x.iter().enumerate() {
                    let (cy, cx) = (cy as f64, cx as f64);
                    let a = mean_disp(r.clone(), cy, cx);
                    let q = mean_disp(refr.clone(), cy, cx);
                    f[[b, i, j, 0]] = (a.0 - q.0) as f32;
                    f[[b, i, j, 1]] = (a.1 - q.1) as f32;
                    let (f0, f1) = (c.floor() as usize, c.ceil() as usize);
                    let (u, v) = (
                        m.true_displacement(f0, cy, cx),
                        m.true_displacement(f1, cy, cx),
                    );
                    truth[[b, i, j, 0]] = ((u.0 + v.0) / 2.0) as f32;
                    truth[[b, i, j, 1]] = ((u.1 + v.1) / 2.0) as f32;
                }
            }
        }
        let o = block_centre_flow(&f, &plan);
        let epe = |a: &ndarray::Array4<f32>| {
            let mut v: Vec<f64> = a
                .outer_iter()
                .zip(truth.outer_iter())
                .flat_map(|(x, t)| {
                    let d = &x - &t;
                    d.lanes(ndarray::Axis(2))
                        .into_iter()
                        .map(|l| ((l[0] * l[0] + l[1] * l[1]) as f64).sqrt())
                        .collect::<Vec<_>>()
                })
                .collect();
            med(&mut v)
        };
        for b in 0..n {
            println!(
                "b{b} dy m {:.3} o {:.3} t {:.3} | dx m {:.3} o {:.3} t {:.3}",
                f[[b, 10, 10, 0]],
                o[[b, 10, 10, 0]],
                truth[[b, 10, 10, 0]],
                f[[b, 10, 10, 1]],
                o[[b, 10, 10, 1]],
                truth[[b, 10, 10, 1]]
            );
        }
        println!(
            "{motion}: block means vs centre truth {:.3}, corrected {:.3}",
            epe(&f),
            epe(&o)
        );
    }
}

/// Gain of the raw tile flow: the through-origin regression slope of estimated against true
/// displacement (block mean position relative to the reference block's mean position), per
/// component, over textured tiles within 1 px of the truth. Environment: MOTION, FLUX, HOT
/// (hot-pixel fraction), DARKVAR (`dark_variation`), SIGMA (pre-smoothing), BLOCK (frames),
/// PREFILTER=1 ([1,2,1]/4 binomial on the grey images before alignment), GREY=demosaic.
#[test]
#[ignore]
fn gain() {
    let env = |k: &str| std::env::var(k).ok();
    let motion = env("MOTION").unwrap_or("handheld".into());
    let cfa = colorspad_cfa();
    let config = SimulationConfig {
        height: cfa.height(),
        width: cfa.width(),
        frames: 512,
        flux: FluxSpec::Mean {
            flux: env("FLUX").map(|v| v.parse().unwrap()).unwrap_or(0.1),
        },
        motion: motion.parse::<MotionConfig>().unwrap(),
        hot_fraction: env("HOT").map(|v| v.parse().unwrap()).unwrap_or(0.02),
        dark_variation: env("DARKVAR").map(|v| v.parse().unwrap()).unwrap_or(0.3),
        seed: 7,
        ..SimulationConfig::default()
    };
    let sim = simulate_with_cfa(
        &config,
        &Scene::from_spec("builtin:chart").unwrap(),
        &cfa,
        &Silent,
    )
    .unwrap();
    let bits = BinaryFrames::from_packed(sim.packed_frames.clone(), sim.width).unwrap();
    let mut cfg = AlignConfig::default();
    if let Some(s) = env("SIGMA") {
        cfg.patch.presmooth_sigma = s.parse().unwrap();
    }
    if let Some(b) = env("BLOCK") {
        cfg.blocks.block_size = Some(b.parse().unwrap());
    }
    if env("GREY").as_deref() == Some("demosaic") {
        cfg.grey = quantacolor::align::GreyChoice::Demosaic;
    }
    let hot = (config.hot_fraction > 0.0).then_some(&sim.hot_pixels);
    let reference = sim.meta.reference_frame.unwrap_or(256);
    let al = align(&bits, &sim.cfa, hot, reference, &cfg, &Silent).unwrap();
    let mut grey = al.grey.clone();
    if env("PREFILTER").is_some() {
        for g in grey.iter_mut() {
            let (h, w) = g.dim();
            let src = g.to_owned();
            let at = |y: isize, x: isize| {
                src[[
                    y.clamp(0, h as isize - 1) as usize,
                    x.clamp(0, w as isize - 1) as usize,
                ]]
            };
            for y in 0..h as isize {
                for x in 0..w as isize {
                    let mut s = 0.0;
                    for (dy, a) in [(-1, 1.0), (0, 2.0), (1, 1.0)] {
                        for (dx, b) in [(-1, 1.0), (0, 2.0), (1, 1.0)] {
                            s += a * b * at(y + dy, x + dx);
                        }
                    }
                    g[[y as usize, x as usize]] = s / 16.0;
                }
            }
        }
    }
    let grid = &al.grid;
    let truth_w = sim.ground_truth.sum_axis(Axis(2));
    let half = grid.tile_size as f64 / 2.0;
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
            let tile = truth_w.slice(s![y0..y1, x0..x1]);
            let m = tile.mean().unwrap();
            if m > 0.0 && tile.std(0.0) / m > 0.1 {
                textured.push((ty, tx, cy as f64, cx as f64));
            }
        }
    }
    let aligner = ReferenceAligner::new(&grey[al.plan.reference_block], &cfg.patch).unwrap();
    let m = &sim.motion;
    let mean_disp = |r: std::ops::Range<usize>, y: f64, x: f64| {
        let n = r.len() as f64;
        let (mut a, mut b) = (0.0, 0.0);
        for t in r {
            let d = m.true_displacement(t, y, x);
            a += d.0;
            b += d.1;
        }
        (a / n, b / n)
    };
    let refr = al.plan.blocks[al.plan.reference_block].clone();
    // Per stage (raw, median, fit): sums [component][est·true, true²] over tiles within 1 px
    // of the truth (raw) or all textured tiles (median, fit), and the inlier count.
    let mut acc = [[[0.0f64; 2]; 2]; 3];
    let mut inliers = [0usize; 3];
    let mut errs = Vec::new();
    for (b, range) in al.plan.blocks.iter().enumerate() {
        if b == al.plan.reference_block {
            continue;
        }
        let (raw, valid) = aligner.align_with_validity(&grey[b]).unwrap();
        let medf = median_filter_valid_flow(&raw, &valid, cfg.median_radius);
        let fit = affine_fit_field(&medf, grid, cfg.affine_tolerance_px).unwrap();
        for &(ty, tx, cy, cx) in &textured {
            let a = mean_disp(range.clone(), cy, cx);
            let r = mean_disp(refr.clone(), cy, cx);
            let t = [a.0 - r.0, a.1 - r.1];
            for (stage, f) in [&raw, &medf, &fit].into_iter().enumerate() {
                let e = [f[[ty, tx, 0]] as f64, f[[ty, tx, 1]] as f64];
                let d = ((e[0] - t[0]).powi(2) + (e[1] - t[1]).powi(2)).sqrt();
                if stage == 0 {
                    errs.push(d);
                    if env("OUTLIERS").is_some() && d >= 1.0 && b == 7 {
                        println!(
                            "outlier b{b} tile ({ty},{tx}) est ({:+.2},{:+.2}) truth ({:+.2},{:+.2}) median ({:+.2},{:+.2})",
                            e[0], e[1], t[0], t[1], medf[[ty, tx, 0]], medf[[ty, tx, 1]]
                        );
                    }
                }
                if d < 1.0 {
                    inliers[stage] += 1;
                }
                if d < 1.0 || stage > 0 {
                    for c in 0..2 {
                        acc[stage][c][0] += e[c] * t[c];
                        acc[stage][c][1] += t[c] * t[c];
                    }
                }
            }
        }
    }
    let n = errs.len() as f64;
    let g = |st: usize, c: usize| acc[st][c][0] / acc[st][c][1];
    println!(
        "GAIN motion={motion} flux={:?} hot={} darkvar={} sigma={} B={} prefilter={} grey={:?}: \
         gain (y, x) raw-inliers ({:.4}, {:.4}) median ({:.4}, {:.4}) fit ({:.4}, {:.4}); \
         inliers raw {:.2} median {:.2} fit {:.2}; raw median EPE {:.3}; final median EPE {:.3}",
        config.flux,
        config.hot_fraction,
        config.dark_variation,
        cfg.patch.presmooth_sigma,
        al.plan.block_size,
        env("PREFILTER").is_some(),
        al.grey_method,
        g(0, 0),
        g(0, 1),
        g(1, 0),
        g(1, 1),
        g(2, 0),
        g(2, 1),
        inliers[0] as f64 / n,
        inliers[1] as f64 / n,
        inliers[2] as f64 / n,
        med(&mut errs),
        final_epe(&sim, &al, &textured),
    );
}

fn final_epe(
    sim: &quantacolor::simulate::SimulatedCapture,
    al: &quantacolor::align::Alignment,
    textured: &[(usize, usize, f64, f64)],
) -> f64 {
    let mut v = Vec::new();
    for (b, &c) in al.plan.center_frames().iter().enumerate() {
        let (f0, f1) = (c.floor() as usize, c.ceil() as usize);
        for &(ty, tx, cy, cx) in textured {
            let (a, bb) = (
                sim.motion.true_displacement(f0, cy, cx),
                sim.motion.true_displacement(f1, cy, cx),
            );
            let ey = al.flow[[b, ty, tx, 0]] as f64 - (a.0 + bb.0) / 2.0;
            let ex = al.flow[[b, ty, tx, 1]] as f64 - (a.1 + bb.1) / 2.0;
            v.push((ey * ey + ex * ex).sqrt());
        }
    }
    med(&mut v)
}
