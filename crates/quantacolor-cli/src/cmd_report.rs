//! `quantacolor report`: a static comparison page over reconstruction output folders, the
//! user-study variant (supplement §4, Fig. 11) and the tally of its votes (Fig. 12). The page
//! and the study are written by `quantacolor::report`.

#![forbid(unsafe_code)]

use crate::cmd_display::ToneMapArg;
use anyhow::{bail, Result};
use clap::Args;
use quantacolor::display::ColorMatrix;
use quantacolor::progress::Progress;
use quantacolor::report::{
    read_ground_truth, read_votes, tally, write_report, write_study, ReportConfig, ResultDir,
    StudyConfig,
};
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct ReportArgs {
    /// Reconstruction output folders (each with linear.npy and report.toml); with --tally, the
    /// votes files downloaded from study pages.
    #[arg(required = true, value_name = "RESULT|VOTES.json")]
    pub inputs: Vec<PathBuf>,
    /// Output directory: index.html and its assets (report.css, render.js, ...) are written
    /// there; other files in it are kept.
    #[arg(long, required_unless_present = "tally")]
    pub out: Option<PathBuf>,
    /// Page title.
    #[arg(long)]
    pub title: Option<String>,
    /// Ground truth, float32 (H, W, 3) .npy: shown first and scored against (PSNR/SSIM).
    #[arg(long, conflicts_with_all = ["study", "tally"])]
    pub ground_truth: Option<PathBuf>,
    /// Pixels cropped from every border before scoring (as `quantacolor eval --border`).
    #[arg(long, default_value_t = 0)]
    pub border: usize,
    /// Tone map the page opens with (the study's renderings use it).
    #[arg(long, value_enum, default_value_t = ToneMapArg::Global)]
    pub tonemap: ToneMapArg,
    /// Colour matrix from `quantacolor calibrate-color`, applied to every image.
    #[arg(long)]
    pub ccm: Option<PathBuf>,
    /// Write the user-study page instead: scenes (results grouped by their capture) with their
    /// renderings in seeded random order, two questions, keyboard and click voting.
    #[arg(long, conflicts_with = "tally")]
    pub study: bool,
    /// Seed of the study's random order.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Print the vote shares per rendering of the given votes files (supplement Fig. 12).
    #[arg(long, conflicts_with_all = ["out", "title", "ccm"])]
    pub tally: bool,
}

fn tonemap_name(t: ToneMapArg) -> &'static str {
    match t {
        ToneMapArg::Mantiuk06 => "mantiuk06",
        ToneMapArg::Global => "global",
        ToneMapArg::None => "none",
    }
}

pub fn run(args: &ReportArgs, progress: &dyn Progress) -> Result<()> {
    if args.tally {
        let files = args
            .inputs
            .iter()
            .map(|p| read_votes(p))
            .collect::<Result<Vec<_>, _>>()?;
        print!("{}", tally(&files));
        return Ok(());
    }
    let Some(out) = &args.out else {
        bail!("--out is required");
    };
    let results = args
        .inputs
        .iter()
        .map(|p| ResultDir::open(p))
        .collect::<Result<Vec<_>, _>>()?;
    let color_matrix = match &args.ccm {
        Some(p) => Some(ColorMatrix::read(p)?),
        None => None,
    };
    if args.study {
        let config = StudyConfig {
            title: args
                .title
                .clone()
                .unwrap_or_else(|| StudyConfig::default().title),
            seed: args.seed,
            tonemap: args.tonemap.to_tone_map(),
            color_matrix,
        };
        let scenes = write_study(out, &results, &config, progress)?;
        let count = |n: usize, one: &str| format!("{n} {one}{}", if n == 1 { "" } else { "s" });
        crate::output::say(&format!(
            "wrote {} ({}, {}, seed {})",
            out.join("index.html").display(),
            count(scenes.len(), "scene"),
            count(results.len(), "rendering"),
            args.seed
        ));
        return Ok(());
    }
    let truth = match &args.ground_truth {
        Some(p) => Some(read_ground_truth(p, &results)?),
        None => None,
    };
    let config = ReportConfig {
        title: args
            .title
            .clone()
            .unwrap_or_else(|| ReportConfig::default().title),
        tonemap: tonemap_name(args.tonemap).into(),
        border: args.border,
        color_matrix,
    };
    let rows = write_report(
        out,
        &results,
        truth.as_ref().map(|t| t.view()),
        &config,
        progress,
    )?;
    for row in &rows {
        if let Some(s) = &row.scores {
            println!(
                "{:<24} PSNR sRGB {:>6.2}  SSIM sRGB {:.4}",
                row.label, s.psnr_srgb, s.ssim_srgb
            );
        }
    }
    crate::output::say(&format!("wrote {}", out.join("index.html").display()));
    Ok(())
}
