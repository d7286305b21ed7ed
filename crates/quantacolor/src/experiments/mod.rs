//! The paper's experiments as functions that return their files: a CSV table, a plot (PNG),
//! images where the experiment has them, and a `summary.md` that states whether the paper's claim
//! is reproduced, with the numbers.
//!
//! | experiment       | paper                      | module              |
//! |------------------|----------------------------|---------------------|
//! | `dynamic-range`  | §7, Eq. 9–10, Fig. 19      | [`dynamic_range`]   |
//! | `motion`         | Fig. 10                    | [`motion`]          |
//! | `w-fraction`     | supplement Fig. 3          | [`w_fraction`]      |
//! | `cfa`            | Fig. 7                     | [`cfa`]             |
//! | `sensors`        | Fig. 11–12, suppl. Fig. 4  | [`sensors`]         |
//!
//! Every experiment takes the sensor of paper Table 1 ([`crate::simulate::SensorModel::table1`]).
//! The simulated ones run the simulator ([`crate::simulate`]) and the reconstruction pipeline
//! ([`crate::pipeline::reconstruct`]) and score against the simulator's ground truth
//! ([`crate::metrics::evaluate`]); `quick` shrinks them to seconds (used by the tests), the
//! default runs in minutes. The claims' pass criteria (which differences count as reproduced)
//! are this project's reading of the paper's figures, stated in each summary.
//!
//! Nothing is written here: the caller (the `quantacolor experiment` command) writes the returned
//! [`Artifact`]s atomically. The same options and seed give identical bytes.
#![deny(unsafe_code)]

pub mod cfa;
pub mod dynamic_range;
pub mod motion;
pub mod plot;
pub mod sensors;
pub mod w_fraction;

mod common;

use crate::error::{Error, Result};
use crate::progress::Progress;
use ndarray::Array3;

/// The experiments, by command-line name ([`Experiment::NAMES`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Experiment {
    DynamicRange,
    Motion,
    WFraction,
    Cfa,
    Sensors,
}

impl Experiment {
    /// Command-line names, in the order of [`Experiment::all`].
    pub const NAMES: [&'static str; 5] =
        ["dynamic-range", "motion", "w-fraction", "cfa", "sensors"];

    /// Every experiment.
    pub fn all() -> [Experiment; 5] {
        [
            Experiment::DynamicRange,
            Experiment::Motion,
            Experiment::WFraction,
            Experiment::Cfa,
            Experiment::Sensors,
        ]
    }

    /// The command-line name.
    pub fn name(self) -> &'static str {
        match self {
            Experiment::DynamicRange => "dynamic-range",
            Experiment::Motion => "motion",
            Experiment::WFraction => "w-fraction",
            Experiment::Cfa => "cfa",
            Experiment::Sensors => "sensors",
        }
    }
}

impl std::str::FromStr for Experiment {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Experiment::all()
            .into_iter()
            .find(|e| e.name() == s)
            .ok_or_else(|| {
                Error::invalid(format!(
                    "unknown experiment '{s}' (expected one of: {})",
                    Experiment::NAMES.join(", ")
                ))
            })
    }
}

/// Options shared by every experiment.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ExperimentOptions {
    /// Small sizes and few settings: seconds instead of minutes (for tests and smoke runs).
    pub quick: bool,
    /// Scene of the simulated experiments (a `Scene::from_spec` string); `None` takes each
    /// experiment's own default. The analytic `dynamic-range` refuses a scene.
    pub scene: Option<String>,
    /// Seed of the simulations (scene noise, motion, pseudorandom CFAs).
    pub seed: u64,
}

/// One output file of an experiment.
#[derive(Debug, Clone, PartialEq)]
pub enum Artifact {
    /// A text file (CSV, Markdown).
    Text(String),
    /// An 8-bit sRGB image (H, W, 3), written as PNG.
    Png(Array3<u8>),
}

/// The files of one experiment run, in writing order, plus whether every claim was reproduced.
#[derive(Debug, Clone, PartialEq)]
pub struct ExperimentOutput {
    /// `(file name, contents)`.
    pub files: Vec<(String, Artifact)>,
    /// Each claim of the paper tested, with its verdict (also in `summary.md`).
    pub claims: Vec<Claim>,
}

/// A claim of the paper and what this run found.
#[derive(Debug, Clone, PartialEq)]
pub struct Claim {
    /// The claim, as the paper makes it.
    pub statement: String,
    pub reproduced: bool,
    /// The numbers behind the verdict.
    pub evidence: String,
}

impl ExperimentOutput {
    /// The text of file `name`, if it is a text artifact.
    pub fn text(&self, name: &str) -> Option<&str> {
        self.files.iter().find_map(|(n, a)| match a {
            Artifact::Text(t) if n == name => Some(t.as_str()),
            _ => None,
        })
    }
}

/// Runs `experiment` with `options`.
pub fn run(
    experiment: Experiment,
    options: &ExperimentOptions,
    progress: &dyn Progress,
) -> Result<ExperimentOutput> {
    match experiment {
        Experiment::DynamicRange => dynamic_range::run(options),
        Experiment::Motion => motion::run(options, progress),
        Experiment::WFraction => w_fraction::run(options, progress),
        Experiment::Cfa => cfa::run(options, progress),
        Experiment::Sensors => sensors::run(options, progress),
    }
}

/// `summary.md`: title, the setting, one section per claim (verdict and numbers), notes.
pub fn summary_markdown(title: &str, setting: &str, claims: &[Claim], notes: &str) -> String {
    let mut s = format!("# {title}\n\n{setting}\n\n## Claims\n\n");
    for c in claims {
        let verdict = if c.reproduced {
            "REPRODUCED"
        } else {
            "NOT REPRODUCED"
        };
        s.push_str(&format!(
            "- **{verdict}**: {}\n  - {}\n",
            c.statement, c.evidence
        ));
    }
    if !notes.is_empty() {
        s.push_str(&format!("\n## Notes\n\n{notes}\n"));
    }
    s
}
