//! `bench video`: `reconstruct --video` (motion estimated once, composed to every reference
//! frame) against a full reconstruction per reference frame, on a simulated chart capture.

#![forbid(unsafe_code)]

use anyhow::{bail, Result};
use ndarray::Array3;
use quantacolor::capture::Capture;
use quantacolor::cfa::colorspad_cfa;
use quantacolor::denoise::chroma::DenoiseMethod;
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::pipeline::{reconstruct, ReconstructConfig};
use quantacolor::progress::{Progress, Silent};
use quantacolor::simulate::{
    ground_truth_at, simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulationConfig,
};
use quantacolor::video::{video_reference_frames, VideoReconstructor};
use std::time::Instant;

pub(super) fn video(
    frames: usize,
    stride: usize,
    motion: &MotionConfig,
    denoise: Option<DenoiseMethod>,
    seed: u64,
    progress: &dyn Progress,
) -> Result<()> {
    let config = SimulationConfig {
        frames,
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: motion.clone(),
        hot_fraction: 0.02,
        seed,
        ..SimulationConfig::default()
    };
    let scene = Scene::from_spec("builtin:chart")?;
    let cfa = colorspad_cfa();
    eprintln!("simulating {frames} frames of 496x254 (not timed)");
    let sim = simulate_with_cfa(&config, &scene, &cfa, progress)?;
    let capture = sim.to_capture()?;
    let references = video_reference_frames(frames, stride)?;
    if references.is_empty() {
        bail!("--stride {stride} leaves no reference frame in {frames} frames");
    }
    let truths = ground_truth_at(&config, &scene, &cfa, &references)?;
    let mut rc = ReconstructConfig::default();
    if let Some(d) = denoise {
        rc.denoise.method = d;
    }
    let opts = EvalOptions {
        border: 16,
        normalize_percentile: Some(99.5),
    };

    let (old, old_s) = per_reference_path(&capture, &rc, &references)?;

    eprintln!("reuse path: motion once, then guide + merge + denoise per frame");
    let start = Instant::now();
    let reconstructor = VideoReconstructor::for_frames(&capture, &rc, &references, &Silent)?;
    let shared_s = start.elapsed().as_secs_f64();
    let mut new = Vec::new();
    let mut frame_stages: Vec<(String, f64)> = Vec::new();
    for &r in &references {
        let rec = reconstructor.frame(r, &Silent)?;
        for t in &rec.timings {
            match frame_stages.iter_mut().find(|(s, _)| *s == t.stage) {
                Some((_, total)) => *total += t.seconds,
                None => frame_stages.push((t.stage.clone(), t.seconds)),
            }
        }
        new.push(rec.linear);
    }
    let new_s = start.elapsed().as_secs_f64();
    let fallback = reconstructor.fallback_reason().map(str::to_string);
    let shared_stages = reconstructor.shared_timings().to_vec();
    drop(reconstructor);

    println!(
        "video: {frames} frames 496x254, {motion:?} motion, stride {stride} ({} reference \
         frames), denoise {}, {} threads",
        references.len(),
        rc.denoise.method,
        rayon::current_num_threads()
    );
    if let Some(reason) = &fallback {
        println!("  reuse path fell back to per-frame reconstruction: {reason}");
    }
    println!(
        "  per-reference path {old_s:.2} s ({:.2} s/frame); reuse path {new_s:.2} s \
         (shared motion {shared_s:.2} s + {:.2} s/frame): speed-up {:.2}x",
        old_s / references.len() as f64,
        (new_s - shared_s) / references.len() as f64,
        old_s / new_s
    );
    for t in &shared_stages {
        println!("    once:      {:<32} {:.3} s", t.stage, t.seconds);
    }
    for (stage, total) in &frame_stages {
        println!(
            "    per frame: {stage:<32} {:.3} s",
            total / references.len() as f64
        );
    }
    print_video_scores(&references, &old, &new, &truths, &opts)?;
    Ok(())
}

/// The per-reference path of [`video`]: one full reconstruction per reference frame; returns
/// the images and the seconds they took.
fn per_reference_path(
    capture: &Capture,
    rc: &ReconstructConfig,
    references: &[usize],
) -> Result<(Vec<Array3<f32>>, f64)> {
    eprintln!(
        "per-reference path: {} full reconstructions",
        references.len()
    );
    let start = Instant::now();
    let mut old = Vec::new();
    for &r in references {
        let cfg = ReconstructConfig {
            reference_frame: Some(r),
            ..rc.clone()
        };
        old.push(reconstruct(capture, &cfg, &Silent)?.linear);
    }
    let old_s = start.elapsed().as_secs_f64();
    Ok((old, old_s))
}

/// The table of [`video`]: PSNR / SSIM of both paths against the ground truth at each reference
/// frame and of one against the other, then the mean PSNRs.
fn print_video_scores(
    references: &[usize],
    old: &[Array3<f32>],
    new: &[Array3<f32>],
    truths: &[Array3<f32>],
    opts: &EvalOptions,
) -> Result<()> {
    println!("  reference   PSNR/SSIM vs truth: per-reference    reuse     reuse vs per-reference");
    let (mut sum_old, mut sum_new) = (0.0, 0.0);
    for (i, &r) in references.iter().enumerate() {
        let a = evaluate(old[i].view(), truths[i].view(), opts)?;
        let b = evaluate(new[i].view(), truths[i].view(), opts)?;
        let c = evaluate(new[i].view(), old[i].view(), opts)?;
        sum_old += a.psnr_srgb;
        sum_new += b.psnr_srgb;
        println!(
            "  {r:>9}   {:>24.2} dB {:.4}   {:.2} dB {:.4}   {:.2} dB",
            a.psnr_srgb, a.ssim_srgb, b.psnr_srgb, b.ssim_srgb, c.psnr_srgb
        );
    }
    let n = references.len() as f64;
    println!(
        "  mean PSNR (sRGB, border 16): per-reference {:.2} dB, reuse {:.2} dB ({:+.2} dB)",
        sum_old / n,
        sum_new / n,
        (sum_new - sum_old) / n
    );
    Ok(())
}
