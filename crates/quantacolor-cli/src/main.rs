//! `quantacolor`: command-line interface to the quantacolor library.

mod allocator;
mod closed_pipe;
mod cmd_align;
mod cmd_bench;
mod cmd_calibrate_color;
mod cmd_calibrate_dcr;
mod cmd_cfa;
mod cmd_convert;
mod cmd_demo;
mod cmd_display;
mod cmd_eval;
mod cmd_experiment;
mod cmd_inspect;
mod cmd_reconstruct;
mod cmd_report;
mod cmd_simulate;
mod config_file;
mod os_usage;
mod output;
mod progress;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};
use std::process::ExitCode;

/// Colour burst photography for single-photon cameras (Ma et al., "Seeing Photons in Color",
/// SIGGRAPH 2023).
#[derive(Debug, Parser)]
#[command(name = "quantacolor", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// No line on success (what was written, where, how long); errors are still reported.
    #[arg(long, global = true)]
    quiet: bool,
}

/// The success line of the commands that write results and say nothing else: what was
/// written, where, and how long it took.
fn success_line(command: &Command, seconds: f64) -> Option<String> {
    let (what, out, files) = match command {
        Command::Reconstruct(a) if a.video => (
            "reconstruct",
            &a.out,
            "frame_NNNNN.png, linear.npy, video.toml",
        ),
        Command::Reconstruct(a) => (
            "reconstruct",
            &a.out,
            "linear.npy, linear.exr, preview.png, report.toml",
        ),
        Command::Simulate(a) => ("simulate", &a.out, "a capture"),
        Command::Align(a) => ("align", &a.out, "flow.npy, flow.toml, camera.npy"),
        Command::Inspect(a) => ("inspect", a.preview.as_ref()?, "a preview"),
        _ => return None,
    };
    Some(format!(
        "{what}: wrote {} ({files}) in {seconds:.1} s",
        out.display()
    ))
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Simulate a capture of the built-in chart, reconstruct it (burst and naive baselines),
    /// write demo/ and print PSNR/SSIM.
    Demo(cmd_demo::DemoArgs),
    /// Simulate a colour single-photon capture (scenes, motion, sensors of paper Table 1).
    Simulate(cmd_simulate::SimulateArgs),
    /// Reconstruct a capture into linear.npy, linear.exr, preview.png and report.toml.
    Reconstruct(cmd_reconstruct::ReconstructArgs),
    /// PSNR, SSIM (scikit-image conventions) and LPIPS of an estimate against ground truth.
    Eval(cmd_eval::EvalArgs),
    /// Estimate the motion as `reconstruct` does; writes flow.npy, flow.toml and camera.npy.
    ///
    /// Runs the motion estimation of `quantacolor reconstruct --method burst` (block alignment,
    /// sub-block refinement, fast-motion tracking, photon trajectory) with the same settings
    /// and writes into --out: flow.npy and flow.toml, the block alignment's tile flow (float32
    /// (n_blocks, tiles_y, tiles_x, 2), (dy, dx) from the reference frame); camera.npy, float64
    /// (T, 2, 3): for every frame t the affine camera map M_t that takes a reference-frame pixel
    /// position (y, x, 1) (pixel centres at integers, y down, x right) to the position of the
    /// same scene point in frame t. camera.npy is the camera (global affine) motion only: moving
    /// objects' local motion is not in it. See docs/motion.md.
    Align(cmd_align::AlignArgs),
    /// Per-pixel dark count rates and a hot-pixel mask from a dark capture.
    CalibrateDcr(cmd_calibrate_dcr::CalibrateDcrArgs),
    /// Quality and speed benchmarks (ratios against baselines measured in the same run).
    Bench(cmd_bench::BenchArgs),
    /// Colour filter arrays: generate, analyse spectra, compare patterns (paper §5).
    Cfa(cmd_cfa::CfaArgs),
    /// Render a linear reconstruction to PNG/TIFF: colour matrix, low-light view, tone mapping.
    Display(cmd_display::DisplayArgs),
    /// Fit a colour-correction matrix from a reconstruction of the built-in chart.
    CalibrateColor(cmd_calibrate_color::CalibrateColorArgs),
    /// Convert a real recording (SwissSPAD2, SPAD512S .bin files, photon-cube .npy) into a
    /// capture directory.
    Convert(cmd_convert::ConvertArgs),
    /// Summarise a capture: size, CFA, light level per channel, hot pixels, block size.
    Inspect(cmd_inspect::InspectArgs),
    /// The paper's experiments (dynamic-range, sensors, motion, w-fraction, cfa): CSV, plots, summary.md.
    Experiment(cmd_experiment::ExperimentArgs),
    /// A static comparison page over reconstruction folders (exposure, tone map, low-light view,
    /// synchronised zoom; PSNR/SSIM), the user-study page (--study) and its tally (--tally).
    Report(cmd_report::ReportArgs),
}

/// Checks `QUANTACOLOR_ISA` ([`quantacolor::cpu::ISA_ENV`]) before any work: an unknown value
/// is an error here rather than silently ignored by the library.
fn check_isa_env() -> Result<(), String> {
    let name = quantacolor::cpu::ISA_ENV;
    match std::env::var_os(name) {
        None => Ok(()),
        Some(value) => match value.to_str() {
            Some(text) if quantacolor::cpu::Isa::from_env_value(text).is_some() => Ok(()),
            _ => Err(format!(
                "{name}={:?} is not a known instruction set (allowed values: generic, avx2, native)",
                value.to_string_lossy()
            )),
        },
    }
}

/// The command line, with negative numbers taken as option values in every subcommand, so that
/// `--sigma-y -1` reaches the option's own check instead of clap's "unexpected argument".
fn command() -> clap::Command {
    fn negative_numbers_are_values(command: clap::Command) -> clap::Command {
        command
            .allow_negative_numbers(true)
            .mut_subcommands(negative_numbers_are_values)
    }
    negative_numbers_are_values(Cli::command())
}

fn main() -> ExitCode {
    allocator::keep_freed_memory();
    closed_pipe::end_quietly_on_closed_pipe();
    if let Err(message) = check_isa_env() {
        eprintln!("error: {message}");
        return ExitCode::from(2);
    }
    let cli = Cli::from_arg_matches(&command().get_matches()).unwrap_or_else(|e| e.exit());
    output::set_quiet(cli.quiet);
    let started = std::time::Instant::now();
    let progress = progress::TerminalProgress::new();
    let result = match &cli.command {
        Command::Demo(args) => cmd_demo::run(args, &progress),
        Command::Simulate(args) => cmd_simulate::run(args, &progress),
        Command::Reconstruct(args) => cmd_reconstruct::run(args, &progress),
        Command::Eval(args) => cmd_eval::run(args),
        Command::Align(args) => cmd_align::run_align(args, &progress),
        Command::CalibrateDcr(args) => cmd_calibrate_dcr::run(args),
        Command::Cfa(args) => cmd_cfa::run(args),
        Command::Bench(args) => cmd_bench::run(args, &progress),
        Command::Display(args) => cmd_display::run(args),
        Command::CalibrateColor(args) => cmd_calibrate_color::run(args),
        Command::Convert(args) => cmd_convert::run_convert(args, &progress),
        Command::Inspect(args) => cmd_inspect::run(args),
        Command::Experiment(args) => cmd_experiment::run(args, &progress),
        Command::Report(args) => cmd_report::run(args, &progress),
    };
    match result {
        Ok(()) => {
            if let Some(line) = success_line(&cli.command, started.elapsed().as_secs_f64()) {
                output::say(&line);
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}
