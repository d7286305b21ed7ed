use quantacolor::cfa::colorspad_cfa;
use quantacolor::denoise::chroma::DenoiseMethod;
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::pipeline::{reconstruct, ReconstructConfig};
use quantacolor::progress::Silent;
use quantacolor::simulate::*;
use quantacolor::video::VideoReconstructor;

fn epe(sim: &SimulatedCapture, b: &quantacolor::burst::BurstReconstruction, r: usize) -> f64 {
    let n = sim.motion.frames;
    let ts: Vec<usize> = (0..16).map(|k| ((k as f64 + 0.5) / 16.0 * n as f64) as usize).collect();
    epe_at(sim, b, r, &ts)
}
fn epe_at(sim: &SimulatedCapture, b: &quantacolor::burst::BurstReconstruction, r: usize, ts: &[usize]) -> f64 {
    let (h, w) = (sim.cfa.height(), sim.cfa.width());
    let mut e = Vec::new();
    for &t in ts {
        let est = b.merge_flow(t as f64);
        for y in (16..h - 16).step_by(8) {
            for x in (16..w - 16).step_by(8) {
                let p = sim.motion.inverse(r, [y as f64, x as f64]);
                let q = sim.motion.forward(t, p);
                let dy = est[[y, x, 0]] as f64 - (q[0] - y as f64);
                let dx = est[[y, x, 1]] as f64 - (q[1] - x as f64);
                e.push((dy * dy + dx * dx).sqrt());
            }
        }
    }
    e.sort_by(f64::total_cmp);
    e[e.len() / 2]
}

fn main() {
    let frames: usize = std::env::args().nth(1).map_or(2000, |v| v.parse().unwrap());
    let refs: Vec<usize> = std::env::args().nth(2).unwrap().split(',').map(|v| v.parse().unwrap()).collect();
    let config = SimulationConfig { frames, flux: FluxSpec::Mean { flux: 0.1 }, motion: "handheld".parse().unwrap(), hot_fraction: 0.02, seed: 1, ..SimulationConfig::default() };
    let scene = Scene::from_spec("builtin:chart").unwrap();
    let cfa = colorspad_cfa();
    let sim = simulate_with_cfa(&config, &scene, &cfa, &Silent).unwrap();
    let cap = sim.to_capture().unwrap();
    let truths = ground_truth_at(&config, &scene, &cfa, &refs).unwrap();
    let mut rc = ReconstructConfig::default();
    rc.denoise.method = DenoiseMethod::None;
    let opts = EvalOptions { border: 16, normalize_percentile: Some(99.5) };
    let video = VideoReconstructor::new(&cap, &rc, &Silent).unwrap();
    let a = video.frame(video.anchor_frame(), &Silent).unwrap();
    for &r in &refs { println!("anchor motion error at frame {r}: {:.3}", epe_at(&sim, a.burst.as_ref().unwrap(), video.anchor_frame(), &[r])); }
    for (i, &r) in refs.iter().enumerate() {
        let old = reconstruct(&cap, &ReconstructConfig { reference_frame: Some(r), ..rc.clone() }, &Silent).unwrap();
        let new = video.frame(r, &Silent).unwrap();
        let (bo, bn) = (old.burst.as_ref().unwrap(), new.burst.as_ref().unwrap());
        let local = |b: &quantacolor::burst::BurstReconstruction| b.motion.local.iter().filter(|v| **v != 0.0).count();
        println!("r {r}: EPE old {:.3} new {:.3}; local old {} new {}; subblocks {} {}; psnr old {:.2} new {:.2}",
            epe(&sim, bo, r), epe(&sim, bn, r), local(bo), local(bn), bo.sub_blocks.len(), bn.sub_blocks.len(),
            evaluate(old.linear.view(), truths[i].view(), &opts).unwrap().psnr_srgb,
            evaluate(new.linear.view(), truths[i].view(), &opts).unwrap().psnr_srgb);
        let curve = |b| (0..10).map(|k| format!("{:.2}", epe_at(&sim, b, r, &[k * frames / 10 + 50]))).collect::<Vec<_>>().join(" ");
        println!("  old {}\n  new {}", curve(bo), curve(bn));
    }
}
