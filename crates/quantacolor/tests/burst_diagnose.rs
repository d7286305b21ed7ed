//! Hand-run diagnostic of the frame-granular motion (prints, asserts nothing, so ignored):
//! burst with and without motion refinement against the true-motion merge, and the median
//! end-point error of the merge's motion, on tuning captures.
//! `cargo test --release -p quantacolor --test burst_diagnose -- --ignored --nocapture`
//! (QC_CASES="scene:motion:frames:flux;..." overrides the captures; scenes from ../shared/data;
//! QC_SEED sets the seed of the first capture, 900 by default, the next ones count up;
//! QC_DEBUG=epe prints the flow error at the centre and corners over time, QC_DEBUG=rigid the
//! camera's error as fitted and projected to a similarity or rigid map, QC_DEBUG=local the local
//! residual of every block (QC_MAP=1 also maps its tiles), any other value the
//! motion of every sub-block).

mod burst_support;

use burst_support::median_epe;
use quantacolor::burst::{reconstruct_burst, reconstruct_burst_with_motion, BurstConfig};
use quantacolor::cfa::colorspad_cfa;
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::progress::Silent;
use quantacolor::simulate::{simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulationConfig};
use std::time::Instant;

#[test]
#[ignore]
fn diagnose_frame_motion() {
    let cases = std::env::var("QC_CASES").unwrap_or_else(|_| {
        "kodim02.png:handheld:512:0.1;builtin:chart:handheld:1024:0.1;kodim15.png:fast-handheld:512:0.1;ScanLines_StillLife.exr:handheld:2000:hdr".into()
    });
    let scenes =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/scenes");
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };
    for (i, case) in cases.split(';').enumerate() {
        let parts: Vec<&str> = case.rsplitn(4, ':').collect();
        let (flux, frames, motion, scene) = (parts[0], parts[1], parts[2], parts[3]);
        let scene = if scene.starts_with("builtin:") {
            Scene::from_spec(scene).unwrap()
        } else {
            Scene::load(scenes.join(scene)).unwrap()
        };
        let flux = if flux == "hdr" {
            FluxSpec::Percentile {
                percentile: 50.0,
                peak: 0.1,
            }
        } else {
            FluxSpec::Mean {
                flux: flux.parse().unwrap(),
            }
        };
        let motion_config: MotionConfig = match motion {
            "fast40" => MotionConfig::FastHandheld {
                amplitude_px: 40.0,
                rotation_deg: 2.0,
                cycles: 3.0,
            },
            m => m.parse().unwrap(),
        };
        let config = SimulationConfig {
            frames: frames.parse().unwrap(),
            flux,
            motion: motion_config,
            hot_fraction: 0.02,
            seed: std::env::var("QC_SEED").map_or(900, |s| s.parse().unwrap()) + i as u64,
            ..SimulationConfig::default()
        };
        let sim = simulate_with_cfa(&config, &scene, &colorspad_cfa(), &Silent).unwrap();
        let capture = sim.to_capture().unwrap();
        let reference = capture.reference_frame();
        let (h, w) = (capture.cfa.height(), capture.cfa.width());
        let oracle = |t: f64| sim.motion.dense_flow(t, h, w);
        let score = |l: &ndarray::Array3<f32>| {
            evaluate(l.view(), sim.ground_truth.view(), &opts)
                .unwrap()
                .psnr_srgb
        };
        let epe = |b: &quantacolor::burst::BurstReconstruction| median_epe(&sim, b);
        let mut variants: Vec<(String, BurstConfig)> =
            vec![("refined".into(), BurstConfig::default())];
        let mut off = BurstConfig::default();
        off.refine.enabled = false;
        variants.push(("interpolated".into(), off));
        if let Ok(extra) = std::env::var("QC_VARIANT") {
            let cfg: BurstConfig = toml::from_str(&extra).unwrap();
            variants.push(("variant".into(), cfg));
        }
        let truth = reconstruct_burst_with_motion(
            &capture,
            reference,
            &BurstConfig::default(),
            Some(&oracle),
            &Silent,
        )
        .unwrap();
        let t_psnr = score(&truth.merged.linear);
        for (name, cfg) in &variants {
            let start = Instant::now();
            let b = reconstruct_burst(&capture, reference, cfg, &Silent).unwrap();
            let secs = start.elapsed().as_secs_f64();
            let p = score(&b.merged.linear);
            if std::env::var("QC_DEBUG").is_ok_and(|v| v == "epe") {
                for k in 0..16 {
                    let t = (k as f64 + 0.5) / 16.0 * sim.motion.frames as f64;
                    let est = b.merge_flow(t);
                    let tru = sim.motion.dense_flow(t, h, w);
                    let at = |y: usize, x: usize| {
                        (
                            est[[y, x, 0]] - tru[[y, x, 0]],
                            est[[y, x, 1]] - tru[[y, x, 1]],
                        )
                    };
                    let pts = [
                        (h / 2, w / 2),
                        (20, 20),
                        (20, w - 20),
                        (h - 20, 20),
                        (h - 20, w - 20),
                    ];
                    let errs: Vec<String> = pts
                        .iter()
                        .map(|&(y, x)| {
                            let (dy, dx) = at(y, x);
                            format!("({dy:+.2},{dx:+.2})")
                        })
                        .collect();
                    println!(
                        "  t {t:7.1}: true centre ({:+.2},{:+.2}) err centre/corners {}",
                        tru[[h / 2, w / 2, 0]],
                        tru[[h / 2, w / 2, 1]],
                        errs.join(" ")
                    );
                }
            } else if std::env::var("QC_DEBUG").is_ok_and(|v| v == "rigid") {
                // EPE of the camera alone, as fitted and projected to a similarity or a rigid map.
                let c = [(h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0];
                let mut errs = [Vec::new(), Vec::new(), Vec::new()];
                for k in 0..16 {
                    let t = (k as f64 + 0.5) / 16.0 * sim.motion.frames as f64;
                    let cam = b.motion.camera_at(t);
                    let tru = sim.motion.dense_flow(t, h, w);
                    let a = (cam.m[0][0] + cam.m[1][1]) / 2.0;
                    let r = (cam.m[1][0] - cam.m[0][1]) / 2.0;
                    let mut sim_cam = cam;
                    sim_cam.m = [[a, -r], [r, a]];
                    let mut rigid = cam;
                    rigid.m = [[0.0, -r], [r, 0.0]];
                    for y in (16..h - 16).step_by(4) {
                        for x in (16..w - 16).step_by(4) {
                            let rel = [y as f64 - c[0], x as f64 - c[1]];
                            for (e, m) in errs.iter_mut().zip([cam, sim_cam, rigid]) {
                                let d = m.at(rel);
                                e.push(
                                    (d[0] - tru[[y, x, 0]] as f64)
                                        .hypot(d[1] - tru[[y, x, 1]] as f64),
                                );
                            }
                        }
                    }
                }
                for (name, e) in ["affine", "similarity", "rigid"]
                    .iter()
                    .zip(errs.iter_mut())
                {
                    e.sort_by(f64::total_cmp);
                    println!("  camera {name}: median EPE {:.3}", e[e.len() / 2]);
                }
            } else if std::env::var("QC_DEBUG").is_ok_and(|v| v == "local") {
                // Local residual of every block: tiles kept, mean and spread of the residual.
                if let Ok(dir) = std::env::var("QC_DUMP") {
                    let path = format!("{dir}/local-{name}.npy");
                    ndarray_npy::write_npy(&path, &b.motion.local).unwrap();
                    let path = format!("{dir}/flow-{name}.npy");
                    ndarray_npy::write_npy(&path, &b.alignment.flow).unwrap();
                }
                for bl in 0..b.motion.plan.len() {
                    let l = b.motion.local.slice(ndarray::s![bl, .., .., ..]);
                    let (ty, tx, _) = l.dim();
                    let mut n = 0usize;
                    let (mut sy, mut sx) = (0.0f64, 0.0f64);
                    let mut rows = Vec::new();
                    for i in 0..ty {
                        let mut row = String::new();
                        for j in 0..tx {
                            let (a, c) = (l[[i, j, 0]], l[[i, j, 1]]);
                            if a != 0.0 || c != 0.0 {
                                n += 1;
                                sy += a as f64;
                                sx += c as f64;
                                row.push(if c.abs() > a.abs() { 'x' } else { 'y' });
                            } else {
                                row.push('.');
                            }
                        }
                        rows.push(row);
                    }
                    let r = &b.motion.plan.blocks[bl];
                    println!(
                        "  block {bl} {r:?}: {n} local tiles, mean ({:+.2}, {:+.2})",
                        sy / n.max(1) as f64,
                        sx / n.max(1) as f64
                    );
                    if n > 0 && std::env::var("QC_MAP").is_ok() {
                        for row in rows.iter().step_by(2) {
                            println!("    {row}");
                        }
                    }
                }
            } else if std::env::var("QC_DEBUG").is_ok() {
                for (k, r) in b.motion.sub_blocks.iter().enumerate() {
                    let c = (r.start + r.end - 1) as f64 / 2.0;
                    let tru = sim.motion.dense_flow(c, h, w);
                    let est = b.motion.sub_block_flow(k);
                    println!(
                        "  sub-block {k} {r:?}: camera b {:?}; centre flow est ({:.2}, {:.2}) true ({:.2}, {:.2}); corner est ({:.2}, {:.2}) true ({:.2}, {:.2})",
                        b.motion.camera[k].b,
                        est[[h / 2, w / 2, 0]], est[[h / 2, w / 2, 1]],
                        tru[[h / 2, w / 2, 0]], tru[[h / 2, w / 2, 1]],
                        est[[20, 20, 0]], est[[20, 20, 1]],
                        tru[[20, 20, 0]], tru[[20, 20, 1]]
                    );
                }
            }
            println!(
                "{case}: {name:<12} {p:.2} dB (true motion {t_psnr:.2}, {:+.2}), EPE {:.3} px, {} sub-blocks, {secs:.1} s {:?}",
                p - t_psnr,
                epe(&b),
                b.sub_blocks.len(),
                b.timings.iter().map(|t| format!("{} {:.2}", t.stage, t.seconds)).collect::<Vec<_>>()
            );
        }
    }
}
