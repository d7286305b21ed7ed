//! `quantacolor`: command-line interface (temporary wiring on the `sim` branch).

mod cmd_simulate;

use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use quantacolor::progress::Progress;

#[derive(Parser)]
#[command(
    name = "quantacolor",
    version,
    about = "Colour burst photography for single-photon cameras"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Simulate a capture.
    Simulate(cmd_simulate::SimulateArgs),
}

/// A progress bar on stderr.
struct Bar(std::sync::Mutex<Option<ProgressBar>>);

impl Progress for Bar {
    fn start(&self, label: &str, total: u64) {
        let bar = ProgressBar::new(total).with_message(label.to_string());
        bar.set_style(
            ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} {elapsed}").unwrap(),
        );
        *self.0.lock().unwrap() = Some(bar);
    }
    fn advance(&self, n: u64) {
        if let Some(b) = self.0.lock().unwrap().as_ref() {
            b.inc(n);
        }
    }
    fn finish(&self) {
        if let Some(b) = self.0.lock().unwrap().take() {
            b.finish();
        }
    }
}

fn main() {
    let cli = Cli::parse();
    let bar = Bar(std::sync::Mutex::new(None));
    let result = match &cli.command {
        Command::Simulate(args) => cmd_simulate::run(args, &bar),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(2);
    }
}
