mod cmd_cfa;

use clap::{Parser, Subcommand};

/// quantacolor: colour burst photography for single-photon cameras.
#[derive(Debug, Parser)]
#[command(name = "quantacolor", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Colour filter arrays (paper §5).
    Cfa(cmd_cfa::CfaArgs),
}

fn main() {
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Cfa(args) => cmd_cfa::run(args),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(2);
    }
}
