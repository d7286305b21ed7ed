//! `bench speed`: align + merge (and the whole pipeline with denoising) of a simulated capture
//! against the naive sum of the same frames, in interleaved rounds in the same process, on the
//! built-in chart and photographs; with each capture's real-time factor at the colour
//! SwissSPAD2's 16,000 frames per second; and both as whole `quantacolor reconstruct`
//! processes, reading and writing included (the speed issue's measure).

#![forbid(unsafe_code)]

use super::{suite, SuiteSet};
use anyhow::{Context, Result};
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
use std::ffi::OsString;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

/// Naive sums timed in each round of [`speed`]: it takes tens of milliseconds against about a
/// second for the pipeline, so more samples of it cost little and steady its median.
const NAIVE_RUNS_PER_ROUND: usize = 3;

/// Frame rate of the colour SwissSPAD2 at 496x254: the real-time factor's clock.
const SENSOR_FPS: f64 = 16_000.0;

/// Mean light of every capture, photons per pixel per frame.
const FLUX: f64 = 0.1;

/// Where the quality suite's scenes are by default (as `bench quality --scenes`).
const DEFAULT_SCENES: &str = "../shared/data/scenes";

/// One scene of `bench speed`: its label in the report and the scene to simulate.
pub(super) struct SpeedScene {
    pub(super) label: String,
    pub(super) scene: Scene,
}

/// The scenes to time: the `--scene` specs (files `Scene::load` reads, or `builtin:…`) when
/// given, loaded here so that a bad one fails before anything is simulated; otherwise the
/// built-in chart, then the quality suite's validation photographs from `scenes` (default
/// [`DEFAULT_SCENES`]; without that folder a note and the chart only, unless the folder was
/// named explicitly).
pub(super) fn speed_scenes(specs: &[String], scenes: Option<&Path>) -> Result<Vec<SpeedScene>> {
    if !specs.is_empty() {
        return specs
            .iter()
            .map(|spec| {
                let scene = Scene::from_spec(spec).with_context(|| format!("--scene {spec}"))?;
                Ok(SpeedScene {
                    label: scene_label(spec),
                    scene,
                })
            })
            .collect();
    }
    let mut out = vec![SpeedScene {
        label: "chart".into(),
        scene: Scene::from_spec("builtin:chart")?,
    }];
    let dir = scenes.map_or_else(|| PathBuf::from(DEFAULT_SCENES), Path::to_path_buf);
    if !dir.is_dir() {
        anyhow::ensure!(
            scenes.is_none(),
            "{}: scene folder not found (--scenes)",
            dir.display()
        );
        eprintln!(
            "{}: no scene folder (the quality suite's photographs); timing the built-in chart only",
            dir.display()
        );
        return Ok(out);
    }
    for name in validation_photographs() {
        let path = dir.join(name);
        let scene = Scene::load(&path).with_context(|| format!("{}", path.display()))?;
        out.push(SpeedScene {
            label: scene_label(name),
            scene,
        });
    }
    Ok(out)
}

/// The distinct photographs (PNG) of the quality suite's validation set, in its order.
fn validation_photographs() -> Vec<&'static str> {
    let mut names: Vec<&'static str> = Vec::new();
    for case in suite::suite() {
        if case.set == SuiteSet::Validation
            && case.scene.ends_with(".png")
            && !names.contains(&case.scene)
        {
            names.push(case.scene);
        }
    }
    names
}

/// A scene's label: a file's stem, or the built-in name without `builtin:`.
fn scene_label(spec: &str) -> String {
    if let Some(name) = spec.strip_prefix("builtin:") {
        return name.to_string();
    }
    Path::new(spec)
        .file_stem()
        .map_or_else(|| spec.to_string(), |s| s.to_string_lossy().into_owned())
}

/// One timed run of the default pipeline in [`speed`].
struct WholeRun {
    whole_s: f64,
    burst_s: f64,
    denoise_s: f64,
    blocks: usize,
    sub_blocks: usize,
    timings: Vec<StageTiming>,
}

/// What [`speed`] reports of one capture: the medians of its rounds and their ranges.
struct Measured {
    label: String,
    /// Every naive sum's seconds.
    naive_times: Vec<f64>,
    naive_s: f64,
    /// The fastest and slowest whole pipeline.
    whole_range: (f64, f64),
    /// The pipeline's run of median whole time.
    median: WholeRun,
    /// The same as whole processes.
    process: Option<ProcessTimes>,
}

/// Seconds of one timed call of `f`, with its result.
fn timed<T>(f: impl FnOnce() -> Result<T>) -> Result<(f64, T)> {
    let start = Instant::now();
    let out = f()?;
    Ok((start.elapsed().as_secs_f64(), out))
}

/// The pipeline's seconds over the capture's own duration at [`SENSOR_FPS`]: above 1, the
/// reconstruction takes longer than the sensor took to record the frames.
fn real_time_factor(whole_s: f64, frames: usize) -> f64 {
    whole_s / (frames as f64 / SENSOR_FPS)
}

/// `pipeline_args`: the `reconstruct` options that select `pipeline` (`--profile`, `--config`),
/// for the whole-process timings.
pub(super) fn speed(
    scenes: &[SpeedScene],
    frames: usize,
    runs: usize,
    (pipeline, name, pipeline_args): (&ReconstructConfig, &str, &[OsString]),
    progress: &dyn Progress,
) -> Result<()> {
    let exe = std::env::current_exe().context("cannot find the quantacolor executable")?;
    let work = WorkDir::new()?;
    let config = SimulationConfig {
        frames,
        flux: FluxSpec::Mean { flux: FLUX },
        motion: "handheld".parse::<MotionConfig>()?,
        ..SimulationConfig::default()
    };
    let mut results = Vec::with_capacity(scenes.len());
    for (i, scene) in scenes.iter().enumerate() {
        eprintln!(
            "simulating {frames} frames of {}x{} of {} (not timed)",
            config.width, config.height, scene.label
        );
        let capture_dir = work.path.join("capture");
        let capture = simulate_with_cfa(&config, &scene.scene, &colorspad_cfa(), progress)
            .and_then(|sim| {
                sim.write(&capture_dir)?;
                sim.to_capture()
            })
            .with_context(|| format!("simulating {}", scene.label))?;
        eprintln!("timing {} ({runs} rounds)", scene.label);
        let mut measured = measure(&scene.label, &capture, pipeline, frames, runs)?;
        drop(capture);
        eprintln!(
            "timing {} as whole reconstruct processes ({runs} rounds)",
            scene.label
        );
        measured.process = Some(time_processes(
            &exe,
            &capture_dir,
            &work.path,
            pipeline_args,
            runs,
        )?);
        std::fs::remove_dir_all(&capture_dir)
            .with_context(|| format!("cannot remove {}", capture_dir.display()))?;
        if i > 0 {
            println!();
        }
        println!(
            "== {}: handheld, {FLUX} photons/pixel/frame, colour-SPAD CFA, seed {}",
            scene.label, config.seed
        );
        print!(
            "{}",
            capture_report(&measured, frames, runs, (pipeline, name), &config)
        );
        results.push(measured);
    }
    println!();
    print!("{}", summary_table(&results, frames, name));
    Ok(())
}

/// Times `runs` rounds on `capture` and keeps the medians.
fn measure(
    label: &str,
    capture: &Capture,
    pipeline: &ReconstructConfig,
    frames: usize,
    runs: usize,
) -> Result<Measured> {
    let (mut naive_times, mut whole_runs) = time_rounds(capture, pipeline, frames, runs)?;
    let naive_s = median_f64(&mut naive_times);
    whole_runs.sort_by(|a, b| a.whole_s.total_cmp(&b.whole_s));
    let whole_range = (
        whole_runs[0].whole_s,
        whole_runs[whole_runs.len() - 1].whole_s,
    );
    let median = whole_runs.swap_remove(whole_runs.len() / 2);
    Ok(Measured {
        label: label.to_string(),
        naive_times,
        naive_s,
        whole_range,
        median,
        process: None,
    })
}

/// The report of one capture: every stage, the blocks, the naive sum, the whole pipeline, its
/// ratio to the naive sum and its real-time factor.
fn capture_report(
    m: &Measured,
    frames: usize,
    runs: usize,
    (pipeline, name): (&ReconstructConfig, &str),
    config: &SimulationConfig,
) -> String {
    let WholeRun {
        whole_s,
        burst_s,
        denoise_s,
        blocks,
        sub_blocks,
        ref timings,
    } = m.median;
    let naive_s = m.naive_s;
    let mut out = String::new();
    writeln!(
        out,
        "{frames} frames {}x{}, {} threads, medians of {runs} rounds: naive {naive_s:.3} s \
         ({} runs, {:.3}-{:.3} s), burst (align + merge) {burst_s:.3} s, ratio {:.1}x",
        config.width,
        config.height,
        rayon::current_num_threads(),
        m.naive_times.len(),
        m.naive_times.iter().copied().fold(f64::INFINITY, f64::min),
        m.naive_times.iter().copied().fold(0.0, f64::max),
        burst_s / naive_s
    )
    .ok();
    writeln!(
        out,
        "  {blocks} alignment blocks, {sub_blocks} sub-blocks merged"
    )
    .ok();
    for t in timings {
        writeln!(out, "  {:<32} {:.3} s", t.stage, t.seconds).ok();
    }
    writeln!(
        out,
        "  {:<32} {denoise_s:.3} s ({:.1}x the naive sum)",
        format!("denoise ({})", pipeline.denoise.method),
        denoise_s / naive_s
    )
    .ok();
    writeln!(
        out,
        "whole {name} (align, merge, denoise): {whole_s:.3} s ({:.3}-{:.3} s), ratio \
         {:.1}x the naive sum",
        m.whole_range.0,
        m.whole_range.1,
        whole_s / naive_s
    )
    .ok();
    if let Some(p) = &m.process {
        writeln!(
            out,
            "whole process (`quantacolor reconstruct`, reading and writing included): {:.3} s \
             ({:.3}-{:.3} s), naive process (`--method naive --denoise none`) {:.3} s ({:.3}-{:.3} \
             s), ratio {:.1}x the naive process",
            p.pipeline_s,
            p.pipeline_range.0,
            p.pipeline_range.1,
            p.naive_s,
            p.naive_range.0,
            p.naive_range.1,
            p.pipeline_s / p.naive_s
        )
        .ok();
    }
    let factor = real_time_factor(whole_s, frames);
    writeln!(
        out,
        "real-time factor at 16 kfps: {factor:.2}x ({frames} frames = {:.3} s of capture, \
         {whole_s:.3} s to reconstruct: {})",
        frames as f64 / SENSOR_FPS,
        if factor > 1.0 {
            "slower than real time"
        } else {
            "faster than real time"
        }
    )
    .ok();
    out
}

/// A stage's column header: its name without the parenthesised detail.
fn short_stage(stage: &str) -> &str {
    stage.split_once(" (").map_or(stage, |(a, _)| a)
}

/// The summary: a Markdown table with a row per capture (every stage of any capture as a
/// column, blank where a capture's pipeline did not run it).
fn summary_table(results: &[Measured], frames: usize, name: &str) -> String {
    let mut stages: Vec<&str> = Vec::new();
    for m in results {
        for t in &m.median.timings {
            if !stages.contains(&t.stage.as_str()) {
                stages.push(&t.stage);
            }
        }
    }
    let mut out = String::new();
    writeln!(
        out,
        "summary: {name}, {frames} frames ({:.3} s at 16 kfps), {} threads, medians (s)",
        frames as f64 / SENSOR_FPS,
        rayon::current_num_threads()
    )
    .ok();
    let mut header = "| scene | blocks | sub-blocks | naive |".to_string();
    for stage in &stages {
        write!(header, " {} |", short_stage(stage)).ok();
    }
    header.push_str(
        " denoise | whole | x naive | x real time | process | naive process | x naive process |",
    );
    writeln!(out, "{header}").ok();
    writeln!(out, "{}", "|---".repeat(stages.len() + 11) + "|").ok();
    for m in results {
        let w = &m.median;
        let mut row = format!(
            "| {} | {} | {} | {:.3} |",
            m.label, w.blocks, w.sub_blocks, m.naive_s
        );
        for stage in &stages {
            match w.timings.iter().find(|t| t.stage == *stage) {
                Some(t) => write!(row, " {:.3} |", t.seconds).ok(),
                None => write!(row, " |").ok(),
            };
        }
        write!(
            row,
            " {:.3} | {:.3} | {:.1}x | {:.2}x |",
            w.denoise_s,
            w.whole_s,
            w.whole_s / m.naive_s,
            real_time_factor(w.whole_s, frames)
        )
        .ok();
        match &m.process {
            Some(p) => write!(
                row,
                " {:.3} | {:.3} | {:.1}x |",
                p.pipeline_s,
                p.naive_s,
                p.pipeline_s / p.naive_s
            )
            .ok(),
            None => write!(row, " | | |").ok(),
        };
        writeln!(out, "{row}").ok();
    }
    out
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

/// A folder of its own in the system's temporary folder for [`speed`]'s captures and outputs,
/// removed when dropped (also when the benchmark fails).
struct WorkDir {
    path: PathBuf,
}

impl WorkDir {
    fn new() -> Result<WorkDir> {
        let path =
            std::env::temp_dir().join(format!("quantacolor-bench-speed-{}", std::process::id()));
        if path.exists() {
            std::fs::remove_dir_all(&path)
                .with_context(|| format!("cannot clear {}", path.display()))?;
        }
        std::fs::create_dir_all(&path)
            .with_context(|| format!("cannot create {}", path.display()))?;
        Ok(WorkDir { path })
    }
}

impl Drop for WorkDir {
    fn drop(&mut self) {
        // Best effort: a leftover folder in the temporary folder is harmless.
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

/// Medians (and ranges) of whole `quantacolor reconstruct` processes: the pipeline timed, and
/// the naive sum (`--method naive --denoise none`).
struct ProcessTimes {
    pipeline_s: f64,
    pipeline_range: (f64, f64),
    naive_s: f64,
    naive_range: (f64, f64),
}

/// Times `runs` rounds of whole processes on the capture folder `capture`, each
/// [`NAIVE_RUNS_PER_ROUND`] naive processes then one of the pipeline (`pipeline_args`), as a
/// user runs them in a shell: start-up, reading the capture and writing every output included.
fn time_processes(
    exe: &Path,
    capture: &Path,
    work: &Path,
    pipeline_args: &[OsString],
    runs: usize,
) -> Result<ProcessTimes> {
    let naive_args: Vec<OsString> = ["--method", "naive", "--denoise", "none"]
        .into_iter()
        .map(OsString::from)
        .collect();
    let (mut naive, mut pipeline) = (Vec::new(), Vec::new());
    for _ in 0..runs.max(1) {
        for _ in 0..NAIVE_RUNS_PER_ROUND {
            naive.push(process_seconds(
                exe,
                capture,
                &work.join("naive"),
                &naive_args,
            )?);
        }
        pipeline.push(process_seconds(
            exe,
            capture,
            &work.join("pipeline"),
            pipeline_args,
        )?);
    }
    let range = |v: &[f64]| {
        (
            v.iter().copied().fold(f64::INFINITY, f64::min),
            v.iter().copied().fold(0.0, f64::max),
        )
    };
    Ok(ProcessTimes {
        pipeline_range: range(&pipeline),
        naive_range: range(&naive),
        pipeline_s: median_f64(&mut pipeline),
        naive_s: median_f64(&mut naive),
    })
}

/// Wall-clock seconds of one `quantacolor reconstruct CAPTURE --out OUT --overwrite ARGS`
/// child process; its error output in the error if it fails.
fn process_seconds(exe: &Path, capture: &Path, out: &Path, args: &[OsString]) -> Result<f64> {
    let start = Instant::now();
    let output = Command::new(exe)
        .arg("reconstruct")
        .arg(capture)
        .arg("--out")
        .arg(out)
        .arg("--overwrite") // the benchmark's own output folder, run again
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .output()
        .with_context(|| format!("cannot run {}", exe.display()))?;
    let seconds = start.elapsed().as_secs_f64();
    anyhow::ensure!(
        output.status.success(),
        "quantacolor reconstruct {} failed ({}): {}",
        capture.display(),
        output.status,
        String::from_utf8_lossy(&output.stderr).trim()
    );
    Ok(seconds)
}
