//! `quantacolor`: command-line interface to the quantacolor library.

mod cmd_eval;
mod cmd_reconstruct;
mod output;
mod progress;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// Colour burst photography for single-photon cameras (Ma et al., "Seeing Photons in Color",
/// SIGGRAPH 2023).
#[derive(Debug, Parser)]
#[command(name = "quantacolor", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Reconstruct a capture into linear.npy, linear.exr, preview.png and report.toml.
    Reconstruct(cmd_reconstruct::ReconstructArgs),
    /// PSNR and SSIM of an estimate against ground truth (scikit-image conventions).
    Eval(cmd_eval::EvalArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let progress = progress::TerminalProgress::new();
    let result = match &cli.command {
        Command::Reconstruct(args) => cmd_reconstruct::run(args, &progress),
        Command::Eval(args) => cmd_eval::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}
