//! `quantacolor bench speed` end to end at a tiny size (`--frames 200 --runs 1`): each capture
//! reports every stage, its blocks, the naive sum, the whole pipeline, both again as whole
//! `reconstruct` processes, and a real-time factor, and the summary has a row per capture; bad
//! scenes exit with status 2 before anything is simulated, and a missing default scene folder
//! only narrows the run to the chart. No wall-clock value is asserted, only that the numbers
//! are there and parse.

mod cli_support;
use cli_support::{ok, quantacolor, table_cells};
use std::path::Path;
use std::process::Command;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A small sRGB photograph-like PNG: a colour gradient with a few hard edges.
fn write_png(path: &Path) {
    let img = image::RgbImage::from_fn(96, 64, |x, y| {
        let edge = if (x / 16 + y / 16) % 2 == 0 { 60 } else { 0 };
        image::Rgb([
            (x * 2 + edge) as u8,
            (y * 3 + edge) as u8,
            (200 - x - y + edge) as u8,
        ])
    });
    img.save(path).unwrap();
}

/// The number before `unit` at the end of `text` (after trimming), e.g. "0.123" of "0.123 s".
fn number_before(text: &str, unit: &str) -> f64 {
    let text = text.trim();
    let value = text
        .strip_suffix(unit)
        .unwrap_or_else(|| panic!("{text:?} does not end with {unit:?}"))
        .trim()
        .rsplit(' ')
        .next()
        .unwrap();
    value
        .parse()
        .unwrap_or_else(|_| panic!("{value:?} (of {text:?}) is not a number"))
}

/// The lines of the report of the capture labelled `label`, from its `== label:` header to
/// the next blank line.
fn capture_lines<'a>(stdout: &'a str, label: &str) -> Vec<&'a str> {
    let header = format!("== {label}: handheld, 0.1 photons/pixel/frame");
    let start = stdout
        .lines()
        .position(|l| l.starts_with(&header))
        .unwrap_or_else(|| panic!("no report of {label} in {stdout}"));
    stdout
        .lines()
        .skip(start + 1)
        .take_while(|l| !l.is_empty())
        .collect()
}

/// Checks the report of one capture: stage lines with seconds, the blocks line, the naive sum,
/// the whole pipeline and the real-time factor.
fn check_capture(stdout: &str, label: &str) {
    let lines = capture_lines(stdout, label);
    let first = lines[0];
    assert!(
        first.starts_with("200 frames 496x254, ") && first.contains(" threads, "),
        "{first}"
    );
    let naive = first
        .split("naive ")
        .nth(1)
        .and_then(|r| r.split(" s ").next())
        .unwrap();
    assert!(naive.parse::<f64>().unwrap() > 0.0, "{first}");
    let blocks = lines
        .iter()
        .find(|l| l.contains("alignment blocks"))
        .unwrap_or_else(|| panic!("no blocks line in {lines:?}"));
    let words: Vec<&str> = blocks.split_whitespace().collect();
    assert!(words[0].parse::<usize>().unwrap() >= 1, "{blocks}");
    assert_eq!(words[1..3], ["alignment", "blocks,"], "{blocks}");
    assert!(words[3].parse::<usize>().is_ok(), "{blocks}");
    assert_eq!(words[4..], ["sub-blocks", "merged"], "{blocks}");
    for stage in [
        "align",
        "motion refinement",
        "merge guide",
        "demosaic-merge",
        "denoise",
    ] {
        let line = lines
            .iter()
            .find(|l| l.trim_start().starts_with(stage) && l.starts_with("  "))
            .unwrap_or_else(|| panic!("no stage line {stage:?} in {lines:?}"));
        let seconds = line.split(" s").next().unwrap();
        assert!(number_before(seconds, "") >= 0.0, "{line}");
    }
    let whole = lines
        .iter()
        .find(|l| l.starts_with("whole default pipeline"))
        .unwrap_or_else(|| panic!("no whole-pipeline line in {lines:?}"));
    assert!(
        number_before(whole, "x the naive sum") > 0.0,
        "{whole}: no ratio"
    );
    let process = lines
        .iter()
        .find(|l| l.starts_with("whole process (`quantacolor reconstruct`"))
        .unwrap_or_else(|| panic!("no whole-process line in {lines:?}"));
    assert!(
        number_before(process, "x the naive process") > 0.0,
        "{process}: no ratio"
    );
    let factor_line = lines
        .iter()
        .find(|l| l.starts_with("real-time factor at 16 kfps: "))
        .unwrap_or_else(|| panic!("no real-time factor in {lines:?}"));
    let factor: f64 = factor_line["real-time factor at 16 kfps: ".len()..]
        .split('x')
        .next()
        .unwrap()
        .parse()
        .unwrap_or_else(|_| panic!("{factor_line}: factor is not a number"));
    assert!(factor > 0.0, "{factor_line}");
    // 200 frames at 16,000 frames per second.
    let duration = factor_line
        .split("(200 frames = ")
        .nth(1)
        .and_then(|r| r.split(" s of capture").next())
        .unwrap_or_else(|| panic!("{factor_line}: no capture duration"));
    let duration: f64 = duration.parse().unwrap();
    assert!((duration - 0.0125).abs() < 0.001, "{factor_line}");
    assert!(
        factor_line.ends_with("slower than real time)")
            || factor_line.ends_with("faster than real time)"),
        "{factor_line}"
    );
}

/// The summary table's data rows, as cells.
fn summary_rows(stdout: &str) -> Vec<Vec<String>> {
    let start = stdout
        .lines()
        .position(|l| l.starts_with("summary: "))
        .unwrap_or_else(|| panic!("no summary in {stdout}"));
    let lines: Vec<&str> = stdout.lines().skip(start + 1).collect();
    assert!(lines[0].starts_with("| scene | blocks | sub-blocks | naive |"));
    assert!(lines[0].ends_with(
        "| denoise | whole | x naive | x real time | process | naive process | x naive process |"
    ));
    lines[2..]
        .iter()
        .take_while(|l| l.starts_with("| "))
        .map(|l| table_cells(l))
        .collect()
}

#[test]
fn bench_speed_reports_stages_blocks_and_the_real_time_factor_of_each_scene() {
    let tmp = tempfile::tempdir().unwrap();
    let png = tmp.path().join("photo.png");
    write_png(&png);
    let spec = format!("builtin:chart,{}", s(&png));
    let out = ok(&[
        "bench", "speed", "--frames", "200", "--runs", "1", "--scene", &spec,
    ]);
    let stdout = String::from_utf8(out.stdout).unwrap();
    check_capture(&stdout, "chart");
    check_capture(&stdout, "photo");
    let rows = summary_rows(&stdout);
    let labels: Vec<&str> = rows.iter().map(|r| r[0].as_str()).collect();
    assert_eq!(labels, ["chart", "photo"], "{stdout}");
    assert!(rows
        .iter()
        .all(|r| !r[r.len() - 1].is_empty() && !r[3].is_empty()));
    for row in &rows {
        // A stage that one capture's pipeline skipped is blank in its row.
        for cell in row[1..].iter().filter(|c| !c.is_empty()) {
            let value = cell.trim_end_matches('x');
            assert!(
                value.parse::<f64>().is_ok_and(|v| v >= 0.0),
                "{cell:?} of {row:?} is not a number"
            );
        }
    }
}

#[test]
fn bench_speed_without_the_scene_folder_times_the_chart_and_says_so() {
    // The default folder is ../shared/data/scenes from the working directory: a fresh
    // temporary folder has none.
    let tmp = tempfile::tempdir().unwrap();
    let cwd = tmp.path().join("a").join("b");
    std::fs::create_dir_all(&cwd).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_quantacolor"))
        .args(["bench", "speed", "--frames", "200", "--runs", "1"])
        .current_dir(&cwd)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("no scene folder"), "{stderr}");
    let stdout = String::from_utf8(out.stdout).unwrap();
    check_capture(&stdout, "chart");
    let rows = summary_rows(&stdout);
    assert_eq!(rows.len(), 1, "{stdout}");
}

#[test]
fn bench_speed_refuses_a_missing_scene_before_simulating() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("missing.png");
    let png = tmp.path().join("photo.png");
    write_png(&png);
    // The bad scene is second: nothing is simulated for the first either.
    let spec = format!("{},{}", s(&png), s(&missing));
    for args in [
        vec!["bench", "speed", "--scene", s(&missing)],
        vec!["bench", "speed", "--frames", "200", "--scene", &spec],
        vec!["bench", "speed", "--scene", s(&png), "--scene", s(&missing)],
    ] {
        let out = quantacolor(&args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains("missing.png"), "{args:?}: {stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
        assert!(!stderr.contains("simulating"), "{stderr}");
        assert!(out.stdout.is_empty(), "{args:?} printed a report");
    }
    // An explicit --scenes folder must exist.
    let out = quantacolor(&["bench", "speed", "--scenes", "/no/such/scenes"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/no/such/scenes"));
}
