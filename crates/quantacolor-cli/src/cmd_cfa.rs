//! `quantacolor cfa`: generate, analyse and compare colour filter arrays (paper §5, Fig. 7–9).
//! Parses arguments and calls `quantacolor::cfa`; all algorithms live in the library.

#![forbid(unsafe_code)]

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use quantacolor::cfa::analysis::{write_analysis, AnalysisConfig};
use quantacolor::cfa::sheet::{write_compare, SheetConfig};
use quantacolor::cfa::{self, Pattern};
use std::path::PathBuf;

/// Colour filter arrays: generate, spectral analysis, comparison sheet.
#[derive(Debug, Args)]
pub struct CfaArgs {
    #[command(subcommand)]
    pub command: CfaCommand,
}

#[derive(Debug, Subcommand)]
pub enum CfaCommand {
    /// Write a CFA as .npy codes (0=R 1=G 2=B 3=W) or a colour .png (by extension).
    Generate(GenerateArgs),
    /// Luminance/chrominance spectra and aliasing scores of one CFA (Fig. 9).
    Analyze(AnalyzeArgs),
    /// Side-by-side sheet of every pattern with its spectrum and scores (Fig. 8/9). The
    /// scores, all of the chrominance spectrum: baseband = share of chroma
    /// energy below 1/8 cycle/pixel (overlaps the image's luminance); peak = share in the top
    /// 0.1 % of frequency bins (1 for periodic patterns: moiré); max/mean = largest bin over
    /// the mean bin; chroma = mean chrominance power per pixel (how much colour is sampled).
    /// Lower baseband, peak and max/mean alias less; higher chroma samples more colour.
    Compare(CompareArgs),
}

/// Pattern selection shared by `generate` and `analyze`.
#[derive(Debug, Args)]
pub struct PatternArgs {
    /// Pattern name: bayer, rgbw-25, rgbw-50, rgbw-75-regular, rgbw-75-random,
    /// rgbw-75-bluenoise (also rgbw-50/87.5/93.75-bluenoise), colorspad.
    #[arg(long)]
    pub pattern: String,
    /// Size as WIDTHxHEIGHT (default 512x512; colorspad: 496x254 or a smaller top-left crop).
    #[arg(long)]
    pub size: Option<String>,
    /// Seed of the pseudorandom patterns.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// W fraction of the blue-noise family: 0.5, 0.75, 0.875 or 0.9375.
    #[arg(long)]
    pub w_fraction: Option<f64>,
}

#[derive(Debug, Args)]
pub struct GenerateArgs {
    #[command(flatten)]
    pub pattern: PatternArgs,
    /// Output file, .npy or .png.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct AnalyzeArgs {
    #[command(flatten)]
    pub pattern: PatternArgs,
    /// Output directory (spectra PNGs, analysis.toml, radial.csv).
    #[arg(long)]
    pub out: PathBuf,
    /// Replace the files of an existing, non-empty output directory (refused otherwise).
    #[arg(long)]
    pub overwrite: bool,
}

#[derive(Debug, Args)]
pub struct CompareArgs {
    /// Output directory (compare.png, compare.csv).
    #[arg(long)]
    pub out: PathBuf,
    /// Replace the files of an existing, non-empty output directory (refused otherwise).
    #[arg(long)]
    pub overwrite: bool,
    /// Analysis size of the generated patterns, WIDTHxHEIGHT.
    #[arg(long, default_value = "256x256")]
    pub size: String,
    /// Seed of the pseudorandom patterns.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Runs `quantacolor cfa ...`.
pub fn run(args: &CfaArgs) -> Result<()> {
    match &args.command {
        CfaCommand::Generate(g) => {
            let (label, cfa) = build(&g.pattern)?;
            cfa::save(&cfa, &g.out)?;
            let f = cfa.fractions();
            println!(
                "{label}: {}x{} written to {} (R {:.4}, G {:.4}, B {:.4}, W {:.4})",
                cfa.width(),
                cfa.height(),
                g.out.display(),
                f[0],
                f[1],
                f[2],
                f[3]
            );
        }
        CfaCommand::Analyze(a) => {
            crate::output::check_out_dir(&a.out, "--out", a.overwrite)?;
            let (label, cfa) = build(&a.pattern)?;
            let analysis = write_analysis(&a.out, &label, &cfa, &AnalysisConfig::default())?;
            let s = analysis.scores;
            println!(
                "{label}: baseband {:.4}, peak {:.4}, max/mean {:.1}, chroma power {:.4} -> {}",
                s.baseband_fraction,
                s.peak_fraction,
                s.peak_to_mean,
                s.chroma_power,
                a.out.display()
            );
        }
        CfaCommand::Compare(c) => {
            crate::output::check_out_dir(&c.out, "--out", c.overwrite)?;
            let (width, height) = parse_size(&c.size)?;
            let config = SheetConfig {
                size: (height, width),
                seed: c.seed,
                ..SheetConfig::default()
            };
            let entries = write_compare(&c.out, &config)?;
            println!(
                "{:<22} {:>9} {:>9} {:>10} {:>8}",
                "pattern", "baseband", "peak", "max/mean", "chroma"
            );
            for e in &entries {
                let s = &e.scores;
                println!(
                    "{:<22} {:>9.4} {:>9.4} {:>10.1} {:>8.4}",
                    e.name, s.baseband_fraction, s.peak_fraction, s.peak_to_mean, s.chroma_power
                );
            }
            crate::output::say(
                "columns (chrominance spectrum): baseband = energy share below 1/8 cycle/pixel, \
                 peak = share in the top 0.1 % of bins (1 = periodic, moiré), max/mean = largest \
                 bin over the mean, chroma = mean chrominance power per pixel; see `cfa compare \
                 --help`",
            );
            crate::output::say(&format!("wrote {}", c.out.join("compare.png").display()));
        }
    }
    Ok(())
}

/// The requested pattern at the requested size.
fn build(p: &PatternArgs) -> Result<(String, cfa::Cfa)> {
    let mut pattern: Pattern = p.pattern.parse()?;
    if let Some(w) = p.w_fraction {
        pattern = pattern.with_w_fraction(w)?;
    }
    let (width, height) = match (&p.size, &pattern) {
        (Some(s), _) => parse_size(s)?,
        (None, Pattern::Colorspad) => (
            cfa::colorspad::COLORSPAD_WIDTH,
            cfa::colorspad::COLORSPAD_HEIGHT,
        ),
        (None, _) => (512, 512),
    };
    let cfa = cfa::generate(&pattern, height, width, p.seed)?;
    Ok((pattern.to_string(), cfa))
}

/// Parses `WIDTHxHEIGHT`.
fn parse_size(s: &str) -> Result<(usize, usize)> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("size '{s}' is not WIDTHxHEIGHT"))?;
    let w: usize = w
        .trim()
        .parse()
        .with_context(|| format!("bad width in size '{s}'"))?;
    let h: usize = h
        .trim()
        .parse()
        .with_context(|| format!("bad height in size '{s}'"))?;
    if w == 0 || h == 0 {
        bail!("size '{s}' is empty");
    }
    Ok((w, h))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse() {
        assert_eq!(parse_size("512x256").unwrap(), (512, 256));
        assert!(parse_size("512").is_err());
        assert!(parse_size("0x4").is_err());
    }
}
