//! The user-study page (supplement §4, Fig. 11) and the tally of its votes (supplement Fig. 12).
//!
//! The paper showed participants four renderings of a scene side by side, in random order, and
//! asked two questions: "Which image looks cleanest?" and "Which image do you like best?".
//! [`write_study`] writes that page: the results are grouped into scenes by the capture they
//! were reconstructed from (report.toml's `capture`), the scenes and the renderings of every
//! scene are shuffled with a seeded generator (the same seed gives the same page, byte for
//! byte), each rendering is pre-rendered in Rust by the display pipeline (so participants see
//! exactly `quantacolor display` output), and votes are cast by clicking an image or pressing
//! its number. The page offers the votes as a JSON file ([`VotesFile`], project format);
//! [`tally`] adds up any number of them.
#![forbid(unsafe_code)]

use super::{html_escape, js_assignment, png_data_url, write_text, ResultDir, REPORT_CSS};
use crate::display::{render_srgb8, ColorMatrix, RenderOptions, ToneMap};
use crate::error::{Error, Result};
use crate::output::StagedDir;
use crate::progress::Progress;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The study's questions (supplement §4): identifier in the votes file, text shown.
pub const QUESTIONS: [(&str, &str); 2] = [
    ("cleanest", "Which image looks cleanest?"),
    ("best", "Which image do you like best?"),
];

/// `format` of a votes file.
pub const VOTES_FORMAT: &str = "quantacolor-study-votes";

const STUDY_HTML: &str = include_str!("assets/study.html");
const STUDY_JS: &str = include_str!("assets/study.js");

/// The files of a study page.
pub const STUDY_FILES: [&str; 4] = ["index.html", "report.css", "study.js", "study-data.js"];

/// Settings of [`write_study`].
#[derive(Debug, Clone)]
pub struct StudyConfig {
    pub title: String,
    /// Seed of the random order of scenes and renderings.
    pub seed: u64,
    /// Tone map of the renderings (automatic exposure).
    pub tonemap: ToneMap,
    /// Colour matrix applied before rendering, as `display --ccm`.
    pub color_matrix: Option<ColorMatrix>,
}

impl Default for StudyConfig {
    fn default() -> Self {
        StudyConfig {
            title: "quantacolor user study".into(),
            seed: 1,
            tonemap: ToneMap::default(),
            color_matrix: None,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Question {
    pub id: String,
    pub text: String,
}

#[derive(Serialize)]
struct Trial {
    scene: String,
    /// Rendering names in the order shown (left to right, keys 1, 2, ...).
    labels: Vec<String>,
    /// data: URLs of the renderings, same order.
    images: Vec<String>,
}

#[derive(Serialize)]
struct StudyData<'a> {
    title: &'a str,
    seed: u64,
    questions: Vec<Question>,
    trials: Vec<Trial>,
}

/// One scene of the study and its renderings, in the order shown.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyScene {
    pub scene: String,
    pub labels: Vec<String>,
}

/// The scene a result belongs to: its capture, or (without one) the folder above it.
fn scene_of(r: &ResultDir) -> String {
    r.capture().map(str::to_string).unwrap_or_else(|| {
        std::path::absolute(&r.dir)
            .ok()
            .and_then(|p| p.parent().map(Path::to_path_buf))
            .unwrap_or_else(|| PathBuf::from("."))
            .display()
            .to_string()
    })
}

/// Groups `results` into scenes and shuffles them (see the module doc): indices into
/// `results`, scenes in the order shown.
fn plan(results: &[ResultDir], seed: u64) -> Result<Vec<(String, Vec<usize>)>> {
    let mut scenes: Vec<(String, Vec<usize>)> = Vec::new();
    for (i, r) in results.iter().enumerate() {
        let key = scene_of(r);
        match scenes.iter_mut().find(|(k, _)| *k == key) {
            Some((_, members)) => {
                if let Some(&j) = members.iter().find(|&&j| results[j].label == r.label) {
                    return Err(Error::format(
                        &r.dir,
                        format!(
                            "two renderings of scene {key} are named '{}' (the other is {}); rename a folder",
                            r.label,
                            results[j].dir.display()
                        ),
                    ));
                }
                members.push(i);
            }
            None => scenes.push((key, vec![i])),
        }
    }
    if let Some((key, m)) = scenes.iter().find(|(_, m)| m.len() < 2) {
        return Err(Error::format(
            &results[m[0]].dir,
            format!("the only rendering of scene {key}: a study scene needs at least two"),
        ));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    scenes.shuffle(&mut rng);
    for (_, members) in scenes.iter_mut() {
        members.shuffle(&mut rng);
    }
    Ok(scenes)
}

/// Writes the study page into `out` (staged; see the module doc) and returns the scenes in the
/// order shown.
pub fn write_study(
    out: &Path,
    results: &[ResultDir],
    config: &StudyConfig,
    progress: &dyn Progress,
) -> Result<Vec<StudyScene>> {
    if results.len() < 2 {
        return Err(Error::invalid(
            "study: give at least two result folders (renderings of one scene)",
        ));
    }
    let scenes = plan(results, config.seed)?;
    progress.start("study", results.len() as u64);
    let mut trials = Vec::new();
    for (scene, members) in &scenes {
        let mut images = Vec::new();
        for &i in members {
            let r = &results[i];
            let options = RenderOptions {
                tonemap: config.tonemap,
                color_matrix: config.color_matrix.clone(),
                w_weights: r.w_weights(),
                ..RenderOptions::default()
            };
            images.push(png_data_url(&render_srgb8(r.linear.view(), &options)?)?);
            progress.advance(1);
        }
        trials.push(Trial {
            scene: scene.clone(),
            labels: members.iter().map(|&i| results[i].label.clone()).collect(),
            images,
        });
    }
    progress.finish();
    let data = StudyData {
        title: &config.title,
        seed: config.seed,
        questions: QUESTIONS
            .iter()
            .map(|(id, text)| Question {
                id: id.to_string(),
                text: text.to_string(),
            })
            .collect(),
        trials,
    };
    let staged = StagedDir::new(out)?;
    let dir = staged.dir();
    write_text(dir, "study-data.js", &js_assignment("QC_STUDY", &data)?)?;
    write_text(dir, "study.js", STUDY_JS)?;
    write_text(dir, "report.css", REPORT_CSS)?;
    write_text(
        dir,
        "index.html",
        &STUDY_HTML.replace("{{title}}", &html_escape(&config.title)),
    )?;
    staged.commit()?;
    Ok(data
        .trials
        .iter()
        .map(|t| StudyScene {
            scene: t.scene.clone(),
            labels: t.labels.clone(),
        })
        .collect())
}

/// One vote as the study page records it.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Vote {
    pub scene: String,
    /// A question id of [`QUESTIONS`].
    pub question: String,
    /// The rendering chosen.
    pub choice: String,
    /// Its position on screen, 1-based.
    pub position: usize,
    /// The renderings in the order shown.
    pub order: Vec<String>,
    /// Milliseconds from the question appearing to the vote.
    #[serde(default)]
    pub ms: Option<f64>,
}

/// A votes file downloaded from the study page.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct VotesFile {
    /// [`VOTES_FORMAT`].
    pub format: String,
    pub version: u32,
    #[serde(default)]
    pub title: Option<String>,
    #[serde(default)]
    pub seed: Option<u64>,
    pub questions: Vec<Question>,
    pub votes: Vec<Vote>,
}

/// Reads and checks a votes file; errors name the file and the problem.
pub fn read_votes(path: &Path) -> Result<VotesFile> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let file: VotesFile = serde_json::from_str(&text).map_err(|e| {
        Error::format(
            path,
            format!("not a votes file of the study page (JSON: {e})"),
        )
    })?;
    if file.format != VOTES_FORMAT || file.version != 1 {
        return Err(Error::format(
            path,
            format!(
                "format '{}' version {}, expected '{VOTES_FORMAT}' version 1",
                file.format, file.version
            ),
        ));
    }
    for (i, v) in file.votes.iter().enumerate() {
        if !file.questions.iter().any(|q| q.id == v.question) {
            return Err(Error::format(
                path,
                format!("vote {i}: unknown question '{}'", v.question),
            ));
        }
        if v.order.get(v.position.wrapping_sub(1)) != Some(&v.choice) {
            return Err(Error::format(
                path,
                format!(
                    "vote {i}: choice '{}' is not at position {} of {:?}",
                    v.choice, v.position, v.order
                ),
            ));
        }
    }
    Ok(file)
}

/// Votes of one rendering for one question.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Share {
    pub label: String,
    pub votes: usize,
    /// Questions in which it was among the choices.
    pub shown: usize,
    /// `votes` over all votes of the question.
    pub share: f64,
}

/// The vote shares of one question.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct QuestionTally {
    pub id: String,
    pub text: String,
    pub total: usize,
    /// Most votes first, then by name.
    pub shares: Vec<Share>,
}

/// Vote shares per rendering and question (supplement Fig. 12).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Tally {
    pub files: usize,
    pub questions: Vec<QuestionTally>,
}

/// Adds up the votes of `files` (see [`read_votes`]).
pub fn tally(files: &[VotesFile]) -> Tally {
    let mut questions: Vec<Question> = Vec::new();
    for f in files {
        for q in &f.questions {
            if !questions.iter().any(|k| k.id == q.id) {
                questions.push(q.clone());
            }
        }
    }
    let questions = questions
        .into_iter()
        .map(|q| {
            let mut counts: BTreeMap<&str, (usize, usize)> = BTreeMap::new();
            let mut total = 0;
            for v in files.iter().flat_map(|f| &f.votes) {
                if v.question != q.id {
                    continue;
                }
                total += 1;
                for l in &v.order {
                    counts.entry(l).or_default().1 += 1;
                }
                counts.entry(&v.choice).or_default().0 += 1;
            }
            let mut shares: Vec<Share> = counts
                .into_iter()
                .map(|(label, (votes, shown))| Share {
                    label: label.to_string(),
                    votes,
                    shown,
                    share: if total > 0 {
                        votes as f64 / total as f64
                    } else {
                        0.0
                    },
                })
                .collect();
            shares.sort_by(|a, b| b.votes.cmp(&a.votes).then(a.label.cmp(&b.label)));
            QuestionTally {
                id: q.id,
                text: q.text,
                total,
                shares,
            }
        })
        .collect();
    Tally {
        files: files.len(),
        questions,
    }
}

impl std::fmt::Display for Tally {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "{} votes file(s)", self.files)?;
        for q in &self.questions {
            writeln!(f, "\n{} ({}): {} votes", q.text, q.id, q.total)?;
            writeln!(
                f,
                "  {:<24} {:>6} {:>7} {:>6}",
                "rendering", "votes", "share", "shown"
            )?;
            for s in &q.shares {
                writeln!(
                    f,
                    "  {:<24} {:>6} {:>6.1}% {:>6}",
                    s.label,
                    s.votes,
                    100.0 * s.share,
                    s.shown
                )?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vote(q: &str, choice: &str, order: &[&str]) -> Vote {
        Vote {
            scene: "s".into(),
            question: q.into(),
            choice: choice.into(),
            position: order.iter().position(|o| *o == choice).unwrap() + 1,
            order: order.iter().map(|s| s.to_string()).collect(),
            ms: None,
        }
    }

    fn file(votes: Vec<Vote>) -> VotesFile {
        VotesFile {
            format: VOTES_FORMAT.into(),
            version: 1,
            title: None,
            seed: Some(1),
            questions: QUESTIONS
                .iter()
                .map(|(id, text)| Question {
                    id: id.to_string(),
                    text: text.to_string(),
                })
                .collect(),
            votes,
        }
    }

    #[test]
    fn tally_counts_shares_per_question() {
        let order = ["a", "b", "c"];
        let t = tally(&[
            file(vec![
                vote("cleanest", "a", &order),
                vote("best", "b", &order),
            ]),
            file(vec![
                vote("cleanest", "a", &order),
                vote("cleanest", "c", &order),
                vote("best", "b", &order),
            ]),
        ]);
        assert_eq!(t.files, 2);
        let c = &t.questions[0];
        assert_eq!((c.id.as_str(), c.total), ("cleanest", 3));
        assert_eq!(c.shares[0].label, "a");
        assert_eq!(c.shares[0].votes, 2);
        assert!((c.shares[0].share - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(c.shares[1].label, "c");
        assert_eq!((c.shares[2].label.as_str(), c.shares[2].votes), ("b", 0));
        assert_eq!(c.shares[2].shown, 3);
        let b = &t.questions[1];
        assert_eq!(b.total, 2);
        assert_eq!((b.shares[0].label.as_str(), b.shares[0].share), ("b", 1.0));
        let text = t.to_string();
        assert!(text.contains("Which image looks cleanest?"), "{text}");
        assert!(text.contains("66.7%"), "{text}");
    }

    #[test]
    fn bad_votes_files_are_rejected_with_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("v.json");
        std::fs::write(&p, "{not json").unwrap();
        let e = read_votes(&p).unwrap_err().to_string();
        assert!(
            e.contains("v.json") && e.contains("not a votes file"),
            "{e}"
        );
        let mut f = file(vec![vote("cleanest", "a", &["a", "b"])]);
        f.votes[0].position = 2;
        std::fs::write(&p, serde_json::to_string(&f).unwrap()).unwrap();
        let e = read_votes(&p).unwrap_err().to_string();
        assert!(e.contains("not at position 2"), "{e}");
        let mut f = file(vec![vote("prettiest", "a", &["a", "b"])]);
        f.votes[0].question = "prettiest".into();
        std::fs::write(&p, serde_json::to_string(&f).unwrap()).unwrap();
        assert!(read_votes(&p)
            .unwrap_err()
            .to_string()
            .contains("unknown question"));
        let f = file(vec![vote("best", "b", &["a", "b"])]);
        std::fs::write(&p, serde_json::to_string(&f).unwrap()).unwrap();
        assert_eq!(read_votes(&p).unwrap(), f);
    }
}
