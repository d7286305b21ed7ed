//! Comparison pages over reconstruction output folders (`quantacolor report`), the user-study
//! variant of supplement §4 (Fig. 11–12) and the labelled comparison strip of the demo.
//!
//! The page is static and self-contained: `index.html` with `report.css`, `render.js`,
//! `report.js` and `report-data.js` beside it, opened from disk, no server, no network. The
//! linear reconstructions travel as binary16 ([`encode`]) and are rendered in the browser by
//! `render.js`, a port of the display pipeline ([`crate::display`]: noise-aware low-light blend
//! of supplement Eq. 9–10, exposure, the `global` and `none` tone maps, sRGB, 8 bits) that
//! matches `quantacolor display` to within one 8-bit level (tests/report_render.rs runs it
//! under node; the CLI's browser test compares screenshots). Mantiuk06 (paper §7's HDR
//! figures) is a multi-scale solver too large to port: the page shows it pre-rendered by
//! [`crate::display::render_srgb8`] at automatic exposure without the low-light view, and says
//! so. The page layout, the binary16 format and the study protocol's file format are the
//! project's own; the questions are the paper's (supplement §4).
#![forbid(unsafe_code)]

pub mod encode;
pub mod label;
pub mod study;

use crate::capture::io;
use crate::display::{render_srgb8, ColorMatrix, Mantiuk06Config, RenderOptions, ToneMap};
use crate::error::{Error, Result};
use crate::metrics::{evaluate, EvalOptions, Scores};
use crate::output::{report_frames, report_w_weights, StagedDir};
use crate::progress::Progress;
use ndarray::{Array3, ArrayView3};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub use encode::{decode_half, encode_half, HalfImage};
pub use label::labelled_hstack;
pub use study::{read_votes, tally, write_study, StudyConfig, Tally, VotesFile};

/// The page's HTML template (placeholders `{{name}}`).
const REPORT_HTML: &str = include_str!("assets/report.html");
/// Styles of the report and study pages.
pub const REPORT_CSS: &str = include_str!("assets/report.css");
/// The display pipeline in JavaScript (see the module doc).
pub const RENDER_JS: &str = include_str!("assets/render.js");
/// The page's user interface: panels, synchronised zoom and pan, controls.
const REPORT_JS: &str = include_str!("assets/report.js");

/// The files of a report page, as written into its directory.
pub const REPORT_FILES: [&str; 5] = [
    "index.html",
    "report.css",
    "render.js",
    "report.js",
    "report-data.js",
];

/// A reconstruction output folder: `linear.npy` (float32 (H, W, 3)) and `report.toml`.
#[derive(Debug, Clone)]
pub struct ResultDir {
    pub dir: PathBuf,
    /// The folder's name (how the page and the votes name the result).
    pub label: String,
    pub linear: Array3<f32>,
    pub report: toml::Table,
    /// `report.toml` as written.
    pub report_text: String,
}

impl ResultDir {
    /// Reads `dir/linear.npy` and `dir/report.toml`; errors name the folder and what is missing.
    pub fn open(dir: &Path) -> Result<Self> {
        if !dir.is_dir() {
            return Err(Error::format(
                dir,
                "not a directory (expected a reconstruction output folder with linear.npy and report.toml)",
            ));
        }
        let report_path = dir.join("report.toml");
        let linear_path = dir.join("linear.npy");
        for p in [&linear_path, &report_path] {
            if !p.is_file() {
                return Err(Error::format(
                    dir,
                    format!(
                        "no {} (expected a reconstruction output folder with linear.npy and report.toml)",
                        p.file_name().unwrap_or_default().to_string_lossy()
                    ),
                ));
            }
        }
        let report_text =
            std::fs::read_to_string(&report_path).map_err(|e| Error::io(&report_path, e))?;
        let report: toml::Table = toml::from_str(&report_text)
            .map_err(|e| Error::format(&report_path, format!("not valid TOML: {e}")))?;
        let linear = io::read_npy_3d::<f32>(&linear_path)?;
        if linear.dim().2 != 3 || linear.is_empty() {
            return Err(Error::format(
                &linear_path,
                format!("expected linear RGB (H, W, 3), got {:?}", linear.dim()),
            ));
        }
        let label = std::path::absolute(dir)
            .ok()
            .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
            .unwrap_or_else(|| dir.display().to_string());
        Ok(ResultDir {
            dir: dir.to_path_buf(),
            label,
            linear,
            report,
            report_text,
        })
    }

    /// `frames_used` of the report (the `T` of the low-light view).
    pub fn frames(&self) -> Option<f64> {
        report_frames(&self.report)
    }

    /// `w_weights` of the report (`[1, 1, 1]` when absent).
    pub fn w_weights(&self) -> [f64; 3] {
        report_w_weights(&self.report).unwrap_or([1.0, 1.0, 1.0])
    }

    /// The capture the result was reconstructed from (report.toml's `capture`), which groups
    /// results into scenes in the study.
    pub fn capture(&self) -> Option<&str> {
        self.report.get("capture").and_then(|v| v.as_str())
    }

    fn str_key(&self, key: &str) -> Option<String> {
        self.report.get(key).map(|v| match v {
            toml::Value::String(s) => s.clone(),
            other => other.to_string(),
        })
    }

    /// `(stage, seconds)` of the report's `[[timings]]`.
    pub fn timings(&self) -> Vec<(String, f64)> {
        let Some(list) = self.report.get("timings").and_then(|t| t.as_array()) else {
            return Vec::new();
        };
        list.iter()
            .filter_map(|t| {
                let stage = t.get("stage")?.as_str()?.to_string();
                let s = t.get("seconds")?;
                Some((stage, s.as_float().or(s.as_integer().map(|i| i as f64))?))
            })
            .collect()
    }

    /// The denoiser of the report (`[denoise] method`).
    pub fn denoise(&self) -> Option<String> {
        let d = self.report.get("denoise")?.as_table()?;
        d.get("method")?.as_str().map(str::to_string)
    }
}

/// Settings of [`write_report`].
#[derive(Debug, Clone)]
pub struct ReportConfig {
    pub title: String,
    /// Tone map the page opens with: `global`, `none` or `mantiuk06`.
    pub tonemap: String,
    /// Border excluded from the scores, px.
    pub border: usize,
    /// Colour matrix applied (in Rust, before export) to every panel, as `display --ccm`.
    pub color_matrix: Option<ColorMatrix>,
}

impl Default for ReportConfig {
    fn default() -> Self {
        ReportConfig {
            title: "quantacolor report".into(),
            tonemap: "global".into(),
            border: 0,
            color_matrix: None,
        }
    }
}

/// One row of the page's table.
#[derive(Debug, Clone, Serialize)]
pub struct ReportRow {
    pub label: String,
    pub scores: Option<Scores>,
}

#[derive(Serialize)]
struct PanelData {
    label: String,
    kind: &'static str,
    width: usize,
    height: usize,
    scale_log2: i32,
    /// base64 of the little-endian binary16 samples.
    half: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    frames: Option<f64>,
    w_weights: [f64; 3],
    /// data: URL of the Mantiuk06 rendering (PNG).
    mantiuk06: String,
}

#[derive(Serialize)]
struct PageData<'a> {
    title: &'a str,
    tonemap: &'a str,
    /// Index of the panel whose exposure "same exposure for all" uses.
    reference: usize,
    panels: Vec<PanelData>,
}

/// Escapes text for HTML content and attribute values.
pub fn html_escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for ch in s.chars() {
        match ch {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// `data:image/png;base64,...` of an 8-bit sRGB image.
pub fn png_data_url(image: &Array3<u8>) -> Result<String> {
    Ok(format!(
        "data:image/png;base64,{}",
        encode::base64(&io::encode_png_rgb8(image)?)
    ))
}

/// Writes `text` to `dir/name` atomically.
pub(crate) fn write_text(dir: &Path, name: &str, text: &str) -> Result<()> {
    crate::atomic::write_atomic(dir.join(name), |w| w.write_all(text.as_bytes()))
}

/// A JavaScript file that sets `window.NAME` to `value` (JSON is valid JavaScript).
pub(crate) fn js_assignment(name: &str, value: &impl Serialize) -> Result<String> {
    let json = serde_json::to_string(value)
        .map_err(|e| Error::invalid(format!("cannot serialise the page data: {e}")))?;
    Ok(format!("window.{name} = {json};\n"))
}

fn panel(
    label: &str,
    kind: &'static str,
    linear: ArrayView3<f32>,
    frames: Option<f64>,
    w_weights: [f64; 3],
) -> Result<PanelData> {
    let half = encode_half(linear);
    let mantiuk = render_srgb8(
        linear,
        &RenderOptions {
            tonemap: ToneMap::Mantiuk06(Mantiuk06Config::default()),
            w_weights,
            ..RenderOptions::default()
        },
    )?;
    Ok(PanelData {
        label: label.to_string(),
        kind,
        width: half.width,
        height: half.height,
        scale_log2: half.scale_log2,
        half: encode::base64(&encode::half_bytes(&half)),
        frames,
        w_weights,
        mantiuk06: png_data_url(&mantiuk)?,
    })
}

fn fmt_score(v: Option<f64>, digits: usize) -> String {
    v.map(|v| format!("{v:.digits$}")).unwrap_or_default()
}

/// The page's table: parameters, timings and (with a ground truth) PSNR/SSIM.
fn table_html(results: &[ResultDir], rows: &[ReportRow]) -> String {
    let scored = rows.iter().any(|r| r.scores.is_some());
    let mut t = String::from("<table id=\"results\">\n<tr><th>result</th><th>method</th><th>denoise</th><th>frames</th><th>size</th><th>time s</th><th>stages (s)</th>");
    if scored {
        t.push_str("<th>PSNR sRGB</th><th>SSIM sRGB</th><th>PSNR linear</th><th>SSIM linear</th>");
    }
    t.push_str("</tr>\n");
    for (r, row) in results.iter().zip(rows) {
        let timings = r.timings();
        let total: f64 = timings.iter().map(|(_, s)| s).sum();
        let stages: Vec<String> = timings
            .iter()
            .map(|(n, s)| format!("{} {s:.2}", html_escape(n)))
            .collect();
        let (h, w, _) = r.linear.dim();
        let _ = write!(
            t,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td class=\"num\">{}</td><td>{w}&times;{h}</td><td class=\"num\">{}</td><td>{}</td>",
            html_escape(&r.label),
            html_escape(&r.str_key("method").unwrap_or_default()),
            html_escape(&r.denoise().unwrap_or_else(|| "none".into())),
            r.frames().map(|f| format!("{f}")).unwrap_or_default(),
            if timings.is_empty() { String::new() } else { format!("{total:.2}") },
            stages.join(", "),
        );
        if scored {
            let s = row.scores.as_ref();
            let _ = write!(
                t,
                "<td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td>",
                fmt_score(s.map(|s| s.psnr_srgb), 2),
                fmt_score(s.map(|s| s.ssim_srgb), 4),
                fmt_score(s.map(|s| s.psnr_linear), 2),
                fmt_score(s.map(|s| s.ssim_linear), 4),
            );
        }
        t.push_str("</tr>\n");
    }
    t.push_str("</table>");
    t
}

/// Writes the page files ([`REPORT_FILES`]) into `dir` (which must exist), each atomically;
/// [`write_report`] stages them. `truth` is a linear ground truth shown first and scored
/// against (PSNR/SSIM as `quantacolor eval`, normalised at its 99.5th percentile). Returns the
/// table's rows.
pub fn write_report_files(
    dir: &Path,
    results: &[ResultDir],
    truth: Option<ArrayView3<f32>>,
    config: &ReportConfig,
    progress: &dyn Progress,
) -> Result<Vec<ReportRow>> {
    if results.is_empty() {
        return Err(Error::invalid("report: no result folders given"));
    }
    if !["global", "none", "mantiuk06"].contains(&config.tonemap.as_str()) {
        return Err(Error::invalid(format!(
            "report: unknown tone map '{}' (available: global, none, mantiuk06)",
            config.tonemap
        )));
    }
    let rows = score_rows(results, truth, config.border)?;
    let panels = report_panels(results, truth, config, progress)?;
    let data = PageData {
        title: &config.title,
        tonemap: &config.tonemap,
        reference: 0,
        panels,
    };
    let html = page_html(results, &rows, truth.is_some(), config);
    write_text(dir, "report-data.js", &js_assignment("QC_DATA", &data)?)?;
    write_text(dir, "render.js", RENDER_JS)?;
    write_text(dir, "report.js", REPORT_JS)?;
    write_text(dir, "report.css", REPORT_CSS)?;
    write_text(dir, "index.html", &html)?;
    Ok(rows)
}

/// Each result's label and, with a `truth`, its scores as `quantacolor eval --border`.
fn score_rows(
    results: &[ResultDir],
    truth: Option<ArrayView3<f32>>,
    border: usize,
) -> Result<Vec<ReportRow>> {
    let opts = EvalOptions {
        border,
        normalize_percentile: Some(99.5),
    };
    results
        .iter()
        .map(|r| {
            let scores = match truth {
                Some(t) => Some(
                    evaluate(r.linear.view(), t, &opts)
                        .map_err(|e| Error::format(r.dir.join("linear.npy"), format!("{e}")))?,
                ),
                None => None,
            };
            Ok(ReportRow {
                label: r.label.clone(),
                scores,
            })
        })
        .collect()
}

/// The page's panels: the ground truth first where given (at the first result's frames and W
/// weights), then every result, each through the configured colour matrix.
fn report_panels(
    results: &[ResultDir],
    truth: Option<ArrayView3<f32>>,
    config: &ReportConfig,
    progress: &dyn Progress,
) -> Result<Vec<PanelData>> {
    let corrected = |linear: ArrayView3<f32>| -> Result<Array3<f32>> {
        match &config.color_matrix {
            Some(m) => m.apply(linear),
            None => Ok(linear.to_owned()),
        }
    };
    progress.start("report", (results.len() + truth.is_some() as usize) as u64);
    let mut panels = Vec::new();
    if let Some(t) = truth {
        let first = &results[0];
        panels.push(panel(
            "ground truth",
            "truth",
            corrected(t)?.view(),
            first.frames(),
            first.w_weights(),
        )?);
        progress.advance(1);
    }
    for r in results {
        panels.push(panel(
            &r.label,
            "result",
            corrected(r.linear.view())?.view(),
            r.frames(),
            r.w_weights(),
        )?);
        progress.advance(1);
    }
    progress.finish();
    Ok(panels)
}

/// `index.html`: the page template with the title, the score table, the notes on exposure and
/// scoring, and every result's `report.toml`.
fn page_html(
    results: &[ResultDir],
    rows: &[ReportRow],
    with_truth: bool,
    config: &ReportConfig,
) -> String {
    let mut notes = String::from(
        "Exposure: 0 EV is the automatic exposure of <code>quantacolor display</code> for each panel; the caption gives the scale to pass to <code>display --exposure</code>. \
         The low-light view is the noise-aware blend of supplement Eq. 9&ndash;10 (L0 as <code>display --mesopic L0</code>, T = frames_used of each report). \
         Mantiuk06 is pre-rendered (automatic exposure, no low-light view); exposure and L0 do not apply to it.",
    );
    if with_truth {
        let _ = write!(
            notes,
            " Scores as <code>quantacolor eval --border {}</code>: both images scaled so that the ground truth&rsquo;s 99.5th percentile is 1, clipped to [0, 1]. The ground truth panel&rsquo;s low-light view uses the first result&rsquo;s frame count.",
            config.border
        );
    }
    let mut details = String::new();
    for r in results {
        let _ = writeln!(
            details,
            "<details><summary>{}: report.toml</summary><pre>{}</pre></details>",
            html_escape(&r.label),
            html_escape(&r.report_text)
        );
    }
    REPORT_HTML
        .replace("{{title}}", &html_escape(&config.title))
        .replace(
            "{{reference}}",
            if with_truth {
                "ground truth"
            } else {
                "first panel"
            },
        )
        .replace("{{table}}", &table_html(results, rows))
        .replace("{{notes}}", &notes)
        .replace("{{details}}", &details)
}

/// Writes the comparison page into `out` (staged: nothing is left on error; other files in
/// `out` are kept). See [`write_report_files`].
pub fn write_report(
    out: &Path,
    results: &[ResultDir],
    truth: Option<ArrayView3<f32>>,
    config: &ReportConfig,
    progress: &dyn Progress,
) -> Result<Vec<ReportRow>> {
    let staged = StagedDir::new(out)?;
    let rows = write_report_files(staged.dir(), results, truth, config, progress)?;
    staged.commit()?;
    Ok(rows)
}

/// Reads a ground truth (float32 (H, W, 3) .npy) and checks it against the results' shape.
pub fn read_ground_truth(path: &Path, results: &[ResultDir]) -> Result<Array3<f32>> {
    let truth = io::read_npy_3d::<f32>(path)?;
    for r in results {
        if r.linear.dim() != truth.dim() {
            return Err(Error::format(
                path,
                format!(
                    "ground truth has shape {:?} but {} has {:?}",
                    truth.dim(),
                    r.dir.join("linear.npy").display(),
                    r.linear.dim()
                ),
            ));
        }
    }
    Ok(truth)
}
