//! `bench speed`: align + merge (and the whole pipeline with denoising) of a simulated capture
//! against the naive sum of the same frames, in interleaved rounds in the same process.

#![forbid(unsafe_code)]

use anyhow::Result;
use quantacolor::burst::reconstruct_burst;
use quantacolor::capture::Capture;
use quantacolor::cfa::colorspad_cfa;
use quantacolor::denoise::chroma::denoise_linear;
use quantacolor::naive::{reconstruct_naive, NaiveConfig};
use quantacolor::pipeline::{burst_config_for, denoise_input, ReconstructConfig};
use quantacolor::progress::{Progress, Silent};
use quantacolor::simulate::{simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulationConfig};
use quantacolor::stats::median_f64;
use quantacolor::timing::StageTiming;
use std::time::Instant;

/// Naive sums timed in each round of [`speed`]: it takes tens of milliseconds against about a
/// second for the pipeline, so more samples of it cost little and steady its median.
const NAIVE_RUNS_PER_ROUND: usize = 3;

/// One timed run of the default pipeline in [`speed`].
struct WholeRun {
    whole_s: f64,
    burst_s: f64,
    denoise_s: f64,
    blocks: usize,
    sub_blocks: usize,
    timings: Vec<StageTiming>,
}

/// Seconds of one timed call of `f`, with its result.
fn timed<T>(f: impl FnOnce() -> Result<T>) -> Result<(f64, T)> {
    let start = Instant::now();
    let out = f()?;
    Ok((start.elapsed().as_secs_f64(), out))
}

pub(super) fn speed(
    frames: usize,
    runs: usize,
    (pipeline, name): (&ReconstructConfig, &str),
    progress: &dyn Progress,
) -> Result<()> {
    let config = SimulationConfig {
        frames,
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: "handheld".parse::<MotionConfig>()?,
        ..SimulationConfig::default()
    };
    eprintln!("simulating {frames} frames of 496x254 (not timed)");
    let sim = simulate_with_cfa(
        &config,
        &Scene::from_spec("builtin:chart")?,
        &colorspad_cfa(),
        progress,
    )?;
    let capture = sim.to_capture()?;
    let (mut naive_times, mut whole_runs) = time_rounds(&capture, pipeline, frames, runs)?;
    let naive_s = median_f64(&mut naive_times);
    whole_runs.sort_by(|a, b| a.whole_s.total_cmp(&b.whole_s));
    let whole_range = (
        whole_runs[0].whole_s,
        whole_runs[whole_runs.len() - 1].whole_s,
    );
    let WholeRun {
        whole_s,
        burst_s,
        denoise_s,
        blocks,
        sub_blocks,
        timings,
    } = whole_runs.swap_remove(whole_runs.len() / 2);
    println!(
        "{frames} frames 496x254, {} threads, medians of {runs} rounds: naive {naive_s:.3} s \
         ({} runs, {:.3}-{:.3} s), burst (align + merge) {burst_s:.3} s, ratio {:.1}x",
        rayon::current_num_threads(),
        naive_times.len(),
        naive_times.iter().copied().fold(f64::INFINITY, f64::min),
        naive_times.iter().copied().fold(0.0, f64::max),
        burst_s / naive_s
    );
    println!("  {blocks} alignment blocks, {sub_blocks} sub-blocks merged");
    for t in &timings {
        println!("  {:<32} {:.3} s", t.stage, t.seconds);
    }
    println!(
        "  {:<32} {denoise_s:.3} s ({:.1}x the naive sum)",
        format!("denoise ({})", pipeline.denoise.method),
        denoise_s / naive_s
    );
    println!(
        "whole {name} (align, merge, denoise): {whole_s:.3} s ({:.3}-{:.3} s), ratio \
         {:.1}x the naive sum",
        whole_range.0,
        whole_range.1,
        whole_s / naive_s
    );
    Ok(())
}

/// The timed rounds of [`speed`]: each runs the naive sum [`NAIVE_RUNS_PER_ROUND`] times, then
/// the pipeline once; returns the naive sums' seconds and the pipeline's runs.
fn time_rounds(
    capture: &Capture,
    pipeline: &ReconstructConfig,
    frames: usize,
    runs: usize,
) -> Result<(Vec<f64>, Vec<WholeRun>)> {
    let reference = capture.reference_frame();
    // Rounds of NAIVE_RUNS_PER_ROUND naive sums and one run of the default pipeline (its merge
    // takes the denoiser's kernel settings, as `reconstruct`), so that a slow spell of the
    // machine slows both sides of the ratio.
    let mut naive_times = Vec::with_capacity(runs * NAIVE_RUNS_PER_ROUND);
    let mut whole_runs = Vec::with_capacity(runs);
    for _ in 0..runs.max(1) {
        for _ in 0..NAIVE_RUNS_PER_ROUND {
            let (seconds, naive) = timed(|| {
                Ok(reconstruct_naive(
                    capture,
                    reference,
                    &NaiveConfig::default(),
                )?)
            })?;
            std::hint::black_box(&naive);
            naive_times.push(seconds);
        }
        let (whole_s, (burst_s, burst, denoise_s)) = timed(|| {
            let (burst_s, burst) = timed(|| {
                Ok(reconstruct_burst(
                    capture,
                    reference,
                    &burst_config_for(pipeline),
                    &Silent,
                )?)
            })?;
            let (denoise_s, denoised) = timed(|| {
                let input = denoise_input(capture, Some(&burst), frames);
                Ok(denoise_linear(
                    burst.merged.linear.view(),
                    &input,
                    &pipeline.denoise,
                )?)
            })?;
            std::hint::black_box(&denoised);
            Ok((burst_s, burst, denoise_s))
        })?;
        // What the report needs of the run; the reconstruction is dropped untimed.
        whole_runs.push(WholeRun {
            whole_s,
            burst_s,
            denoise_s,
            blocks: burst.alignment.plan.len(),
            sub_blocks: burst.sub_blocks.len(),
            timings: burst.timings.clone(),
        });
    }
    Ok((naive_times, whole_runs))
}
