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

use burst_support::{median_epe, psnr_srgb};
use quantacolor::align::AffineMotion;
use quantacolor::burst::{reconstruct_burst, reconstruct_burst_with_motion, BurstConfig};
use quantacolor::cfa::colorspad_cfa;
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
        let score = |l: &ndarray::Array3<f32>| psnr_srgb(&sim, l);
        let epe = |b: &quantacolor::burst::BurstReconstruction| median_epe(&sim, b);
        let mut variants: Vec<(String, BurstConfig)> =
            vec![("refined".into(), BurstConfig::default())];
        let mut off = BurstConfig::default();
        off.refine.enabled = false;
        if std::env::var("QC_SKIP_INTERPOLATED").is_err() {
            variants.push(("interpolated".into(), off));
        }
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
            } else if std::env::var("QC_DEBUG").is_ok_and(|v| v == "decompose") {
                decompose(&sim.motion, &b, h, w);
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

/// The true camera (affine about the centre, forward displacement) at fractional frame `t`,
/// interpolated between frames as [`quantacolor::simulate::Motion::dense_flow`] does.
fn true_camera(m: &quantacolor::simulate::Motion, t: f64) -> AffineMotion {
    let last = m.frames - 1;
    let t = t.clamp(0.0, last as f64);
    let (f0, f1) = (t.floor() as usize, (t.ceil() as usize).min(last));
    let a = t - f0 as f64;
    let at = |f: usize| {
        let (s, c) = m.theta_rad[f].sin_cos();
        [m.dy[f], m.dx[f], c - 1.0, s, -s, c - 1.0]
    };
    let (p, q) = (at(f0), at(f1));
    let v: [f64; 6] = std::array::from_fn(|i| p[i] * (1.0 - a) + q[i] * a);
    AffineMotion {
        b: [v[0], v[1]],
        m: [[v[2], v[3]], [v[4], v[5]]],
    }
}

fn params(a: &AffineMotion) -> [f64; 6] {
    [a.b[0], a.b[1], a.m[0][0], a.m[0][1], a.m[1][0], a.m[1][1]]
}

fn from_params(v: [f64; 6]) -> AffineMotion {
    AffineMotion {
        b: [v[0], v[1]],
        m: [[v[2], v[3]], [v[4], v[5]]],
    }
}

/// Median EPE over the 16 sample times and the pixel grid of `median_epe`, of the camera
/// `est(t)` against the true camera.
fn camera_epe(
    m: &quantacolor::simulate::Motion,
    h: usize,
    w: usize,
    est: impl Fn(f64) -> AffineMotion,
) -> f64 {
    let c = [(h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0];
    let mut e = Vec::new();
    for k in 0..16 {
        let t = (k as f64 + 0.5) / 16.0 * m.frames as f64;
        let (a, b) = (est(t), true_camera(m, t));
        for y in (16..h - 16).step_by(4) {
            for x in (16..w - 16).step_by(4) {
                let rel = [y as f64 - c[0], x as f64 - c[1]];
                let (p, q) = (a.at(rel), b.at(rel));
                e.push((p[0] - q[0]).hypot(p[1] - q[1]));
            }
        }
    }
    e.sort_by(f64::total_cmp);
    e[e.len() / 2]
}

/// Piecewise-linear interpolation through (times, cameras), extrapolated at the ends (as
/// `FrameMotion::camera_at`).
fn interp(times: &[f64], cams: &[AffineMotion], t: f64) -> AffineMotion {
    if cams.len() == 1 {
        return cams[0];
    }
    let k = times
        .windows(2)
        .position(|w| t < w[1])
        .unwrap_or(times.len() - 2);
    let a = (t - times[k]) / (times[k + 1] - times[k]);
    let (p, q) = (params(&cams[k]), params(&cams[k + 1]));
    from_params(std::array::from_fn(|i| p[i] * (1.0 - a) + q[i] * a))
}

/// Decomposition of the end-point error: camera parameters per sub-block, temporal
/// interpolation, local motion, bias (QC_DEBUG=decompose).
// Sub-block indices run over several parallel arrays (cameras, true means, errors).
#[allow(clippy::needless_range_loop)]
fn decompose(
    m: &quantacolor::simulate::Motion,
    b: &quantacolor::burst::BurstReconstruction,
    h: usize,
    w: usize,
) {
    let fm = &b.motion;
    let times = fm.sub_block_centres();
    let n = fm.sub_blocks.len();
    let truth_centre: Vec<AffineMotion> = times.iter().map(|&t| true_camera(m, t)).collect();
    let truth_mean: Vec<AffineMotion> = fm
        .sub_blocks
        .iter()
        .map(|r| {
            let mut s = [0.0; 6];
            for f in r.clone() {
                let p = params(&true_camera(m, f as f64));
                s.iter_mut().zip(p).for_each(|(a, v)| *a += v);
            }
            from_params(s.map(|v| v / r.len() as f64))
        })
        .collect();
    let lens: Vec<usize> = fm.sub_blocks.iter().map(|r| r.len()).collect();
    println!(
        "  {n} sub-blocks (len min {} max {}), {} blocks, reference frame {}",
        lens.iter().min().unwrap(),
        lens.iter().max().unwrap(),
        fm.plan.len(),
        fm.plan.reference_frame
    );
    println!(
        "  camera only (camera_at)             : {:.3}",
        camera_epe(m, h, w, |t| fm.camera_at(t))
    );
    println!(
        "  floor: truth at centres, interpolated: {:.3}",
        camera_epe(m, h, w, |t| interp(&times, &truth_centre, t))
    );
    println!(
        "  floor: true means, interpolated      : {:.3}",
        camera_epe(m, h, w, |t| interp(&times, &truth_mean, t))
    );
    // Parameter errors per sub-block against the true mean over its frames, in px at the
    // corners for the linear part.
    let scale = [
        1.0,
        1.0,
        h as f64 / 2.0,
        w as f64 / 2.0,
        h as f64 / 2.0,
        w as f64 / 2.0,
    ];
    let names = ["b_y", "b_x", "m_yy", "m_yx", "m_xy", "m_xx"];
    let errs: Vec<[f64; 6]> = (0..n)
        .map(|k| {
            let (p, q) = (params(&fm.camera[k]), params(&truth_mean[k]));
            std::array::from_fn(|i| (p[i] - q[i]) * scale[i])
        })
        .collect();
    for i in 0..6 {
        let mean = errs.iter().map(|e| e[i]).sum::<f64>() / n as f64;
        let rms = (errs.iter().map(|e| e[i] * e[i]).sum::<f64>() / n as f64).sqrt();
        let d = (errs
            .windows(2)
            .map(|e| (e[1][i] - e[0][i]).powi(2))
            .sum::<f64>()
            / (n - 1).max(1) as f64)
            .sqrt();
        println!(
            "  param {:<5} error (px at corner): mean {mean:+.3} rms {rms:.3} rms of step {d:.3}",
            names[i]
        );
    }
    if std::env::var("QC_SERIES").is_ok() {
        for k in 0..n {
            println!(
                "  sb {k:3} block {} frames {:?}: b_x {:+.2} m_xy {:+.2} m_yx {:+.2} b_y {:+.2} | true m_yx {:+.2}",
                fm.block_of[k],
                fm.sub_blocks[k],
                errs[k][1],
                errs[k][4],
                errs[k][3],
                errs[k][0],
                params(&truth_mean[k])[3] * scale[3]
            );
        }
    }
    // EPE of the sub-block cameras against the true means (at their own frames).
    let c = [(h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0];
    let mut e = Vec::new();
    for k in 0..n {
        for y in (16..h - 16).step_by(8) {
            for x in (16..w - 16).step_by(8) {
                let rel = [y as f64 - c[0], x as f64 - c[1]];
                let (p, q) = (fm.camera[k].at(rel), truth_mean[k].at(rel));
                e.push((p[0] - q[0]).hypot(p[1] - q[1]));
            }
        }
    }
    e.sort_by(f64::total_cmp);
    println!(
        "  sub-block cameras vs true means     : median {:.3}",
        e[e.len() / 2]
    );
    // Smoothing of the fitted cameras in time (moving average over +-r sub-blocks).
    for r in [2usize, 5, 10, 20] {
        let sm: Vec<AffineMotion> = (0..n)
            .map(|k| {
                let (lo, hi) = (k.saturating_sub(r), (k + r + 1).min(n));
                // local linear fit
                let (mut s0, mut s1, mut s2) = (0.0, 0.0, 0.0);
                let mut r0 = [0.0; 6];
                let mut r1 = [0.0; 6];
                for j in lo..hi {
                    let u = times[j] - times[k];
                    s0 += 1.0;
                    s1 += u;
                    s2 += u * u;
                    let p = params(&fm.camera[j]);
                    for i in 0..6 {
                        r0[i] += p[i];
                        r1[i] += u * p[i];
                    }
                }
                let det = s0 * s2 - s1 * s1;
                from_params(std::array::from_fn(|i| {
                    if det.abs() > 1e-9 {
                        (s2 * r0[i] - s1 * r1[i]) / det
                    } else {
                        r0[i] / s0
                    }
                }))
            })
            .collect();
        println!(
            "  cameras smoothed (local line +-{r:2})  : {:.3}",
            camera_epe(m, h, w, |t| interp(&times, &sm, t))
        );
    }
    // Rigid projection (similarity without scale) of each sub-block camera.
    let rigid: Vec<AffineMotion> = fm
        .camera
        .iter()
        .map(|a| {
            let r = (a.m[0][1] - a.m[1][0]) / 2.0;
            let s = (a.m[0][0] + a.m[1][1]) / 2.0;
            AffineMotion {
                b: a.b,
                m: [[s, r], [-r, s]],
            }
        })
        .collect();
    println!(
        "  cameras projected to similarity      : {:.3}",
        camera_epe(m, h, w, |t| interp(&times, &rigid, t))
    );
    // Per-parameter substitution: the true mean for one parameter at a time.
    for i in 0..6 {
        let sub: Vec<AffineMotion> = (0..n)
            .map(|k| {
                let mut p = params(&fm.camera[k]);
                p[i] = params(&truth_mean[k])[i];
                from_params(p)
            })
            .collect();
        println!(
            "  true {:<5} substituted             : {:.3}",
            names[i],
            camera_epe(m, h, w, |t| interp(&times, &sub, t))
        );
    }
    // Local motion: the samples where the merge flow leaves the camera's.
    let c = [(h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0];
    let (mut moved, mut all, mut frames_with) = (0usize, 0usize, 0usize);
    let (mut with_local, mut camera_there) = (Vec::new(), Vec::new());
    for k in 0..16 {
        let t = (k as f64 + 0.5) / 16.0 * m.frames as f64;
        let flow = b.merge_flow(t);
        let (cam, tru) = (fm.camera_at(t), true_camera(m, t));
        let before = moved;
        for y in (16..h - 16).step_by(4) {
            for x in (16..w - 16).step_by(4) {
                let rel = [y as f64 - c[0], x as f64 - c[1]];
                let (p, q) = (cam.at(rel), tru.at(rel));
                let f = [flow[[y, x, 0]] as f64, flow[[y, x, 1]] as f64];
                all += 1;
                if (f[0] - p[0]).hypot(f[1] - p[1]) > 0.01 {
                    moved += 1;
                    with_local.push((f[0] - q[0]).hypot(f[1] - q[1]));
                    camera_there.push((p[0] - q[0]).hypot(p[1] - q[1]));
                }
            }
        }
        frames_with += (moved > before) as usize;
    }
    with_local.sort_by(f64::total_cmp);
    camera_there.sort_by(f64::total_cmp);
    if !with_local.is_empty() {
        println!(
            "  local motion on {:.1} % of the samples ({frames_with} of 16 times): median EPE there {:.3} (camera alone {:.3})",
            100.0 * moved as f64 / all as f64,
            with_local[with_local.len() / 2],
            camera_there[camera_there.len() / 2]
        );
    } else {
        println!("  no local motion at the 16 times");
    }
    // Error over time (16 samples), px at corner.
    for k in 0..16 {
        let t = (k as f64 + 0.5) / 16.0 * m.frames as f64;
        let (p, q) = (params(&fm.camera_at(t)), params(&true_camera(m, t)));
        let d: Vec<String> = (0..6)
            .map(|i| format!("{:+.2}", (p[i] - q[i]) * scale[i]))
            .collect();
        println!("  t {t:7.1}: err {}", d.join(" "));
    }
}
