//! `quantacolor experiment NAME --out DIR`: runs one of the paper's experiments (library module
//! `quantacolor::experiments`) and writes its CSV, plots and `summary.md` atomically into DIR.

#![forbid(unsafe_code)]

use crate::output::StagedDir;
use anyhow::Result;
use clap::Args;
use quantacolor::capture::io;
use quantacolor::experiments::{self, Artifact, Experiment, ExperimentOptions};
use quantacolor::progress::Progress;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct ExperimentArgs {
    /// Experiment: dynamic-range (§7, Fig. 19), motion (Fig. 10), w-fraction (supplement
    /// Fig. 3), cfa (Fig. 7) or sensors (Fig. 11-12, supplement Fig. 4).
    pub name: String,
    /// Output directory (CSV, PNG plots, summary.md).
    #[arg(long)]
    pub out: PathBuf,
    /// Replace the files of an existing, non-empty output directory (refused otherwise).
    #[arg(long)]
    pub overwrite: bool,
    /// Small sizes and few settings: seconds instead of minutes.
    #[arg(long)]
    pub quick: bool,
    /// Scene of the simulated experiments: builtin:chart, builtin:chart-hdr, builtin:flat or an
    /// image file (default: each experiment's own; dynamic-range takes none).
    #[arg(long)]
    pub scene: Option<String>,
    /// Seed of the simulations.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

pub fn run(args: &ExperimentArgs, progress: &dyn Progress) -> Result<()> {
    crate::output::check_out_dir(&args.out, "--out", args.overwrite)?;
    let experiment: Experiment = args.name.parse()?;
    let options = ExperimentOptions {
        quick: args.quick,
        scene: args.scene.clone(),
        seed: args.seed,
    };
    let output = experiments::run(experiment, &options, progress)?;
    let staged = StagedDir::new(&args.out)?;
    for (name, artifact) in &output.files {
        match artifact {
            Artifact::Text(text) => quantacolor::atomic::write_atomic(staged.path(name), |w| {
                std::io::Write::write_all(w, text.as_bytes())
            })?,
            Artifact::Png(image) => io::write_png_rgb8(staged.path(name), image)?,
        }
    }
    staged.commit()?;
    for c in &output.claims {
        let verdict = if c.reproduced {
            "reproduced"
        } else {
            "NOT reproduced"
        };
        println!("{verdict}: {}\n    {}", c.statement, c.evidence);
    }
    crate::output::say(&format!("wrote {}", args.out.display()));
    Ok(())
}
