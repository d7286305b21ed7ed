//! `quantacolor report` without a browser: the files of the page and the study, determinism
//! (same inputs and seed, same bytes), the seeded order, the tally, and bad input (exit 2, the
//! file named, nothing written).

use ndarray::Array3;
use quantacolor::capture::io::write_npy;
use std::path::Path;

mod cli_support;
mod report_support;
use cli_support::{ok, quantacolor};
use report_support::{result_dir, scene};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn files(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn report_writes_a_deterministic_self_contained_page() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let a = result_dir(d, "smooth", "capA", &scene(20, 30, 0.0));
    let b = result_dir(d, "noisy", "capA", &scene(20, 30, 0.5));
    let gt = d.join("gt.npy");
    write_npy(&gt, &scene(20, 30, 0.0)).unwrap();
    let out = d.join("page");
    let run = |out: &Path| {
        ok(&[
            "report",
            s(&a),
            s(&b),
            "--ground-truth",
            s(&gt),
            "--out",
            s(out),
            "--title",
            "A <test> & page",
        ])
    };
    let o = run(&out);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("wrote"), "{stderr}");
    assert_eq!(
        files(&out),
        [
            "index.html",
            "render.js",
            "report-data.js",
            "report.css",
            "report.js"
        ]
    );
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    assert!(html.contains("<title>A &lt;test&gt; &amp; page</title>"));
    // No network: every script and stylesheet is a file beside the page.
    for needle in ["http://", "https://", "//cdn"] {
        assert!(!html.contains(needle), "{needle}");
    }
    assert!(html.contains("<td>smooth</td>") && html.contains("<td>noisy</td>"));
    // PSNR of the identical image is infinite, the noisy one finite.
    assert!(html.contains("PSNR sRGB"));
    let data = std::fs::read_to_string(out.join("report-data.js")).unwrap();
    assert!(data.starts_with("window.QC_DATA = {"));
    assert!(data.contains("\"label\":\"ground truth\""));
    assert!(data.contains("data:image/png;base64,"));
    // Same inputs, same bytes.
    let again = d.join("page2");
    run(&again);
    for f in files(&out) {
        assert_eq!(
            std::fs::read(out.join(&f)).unwrap(),
            std::fs::read(again.join(&f)).unwrap(),
            "{f}"
        );
    }
}

#[test]
fn study_order_is_seeded_and_tally_reads_votes() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let mut dirs = Vec::new();
    for (scene, names) in [("capA", ["m1", "m2", "m3"]), ("capB", ["m1", "m2", "m3"])] {
        for (k, name) in names.iter().enumerate() {
            let sub = d.join(scene);
            dirs.push(result_dir(
                &sub,
                name,
                scene,
                &scene_image(k as f32 * 0.3, scene == "capB"),
            ));
        }
    }
    let args = |out: &Path, seed: &str| -> Vec<String> {
        let mut v: Vec<String> = vec!["report".into(), "--study".into()];
        v.extend(dirs.iter().map(|p| s(p).to_string()));
        v.extend(["--out".into(), s(out).into(), "--seed".into(), seed.into()]);
        v
    };
    let run = |out: &Path, seed: &str| {
        let a = args(out, seed);
        let a: Vec<&str> = a.iter().map(String::as_str).collect();
        ok(&a);
        std::fs::read_to_string(out.join("study-data.js")).unwrap()
    };
    let first = run(&d.join("s1"), "5");
    assert_eq!(first, run(&d.join("s2"), "5"));
    assert_eq!(
        files(&d.join("s1")),
        ["index.html", "report.css", "study-data.js", "study.js"]
    );
    // Some seed gives another order (each of 2 scenes x 3! arrangements).
    let orders: std::collections::BTreeSet<String> = ["1", "2", "3", "4"]
        .iter()
        .map(|seed| {
            let text = run(&d.join(format!("seed{seed}")), seed);
            let v: serde_json::Value = serde_json::from_str(
                text.trim_start_matches("window.QC_STUDY = ")
                    .trim_end_matches(";\n"),
            )
            .unwrap();
            v["trials"]
                .as_array()
                .unwrap()
                .iter()
                .map(|t| format!("{}:{}", t["scene"], t["labels"]))
                .collect::<Vec<_>>()
                .join("|")
        })
        .collect();
    assert!(orders.len() > 1, "{orders:?}");

    // Tally of two votes files.
    let position = |c: &str| ["m1", "m2", "m3"].iter().position(|x| *x == c).unwrap() + 1;
    let votes = |choices: &[(&str, &str)]| {
        serde_json::json!({
            "format": "quantacolor-study-votes", "version": 1,
            "questions": [{"id": "cleanest", "text": "Which image looks cleanest?"},
                          {"id": "best", "text": "Which image do you like best?"}],
            "votes": choices.iter().map(|(q, c)| serde_json::json!({
                "scene": "capA", "question": q, "choice": c,
                "position": position(c),
                "order": ["m1", "m2", "m3"]})).collect::<Vec<_>>()
        })
        .to_string()
    };
    let v1 = d.join("v1.json");
    let v2 = d.join("v2.json");
    std::fs::write(&v1, votes(&[("cleanest", "m1"), ("best", "m2")])).unwrap();
    std::fs::write(&v2, votes(&[("cleanest", "m1"), ("best", "m1")])).unwrap();
    let o = ok(&["report", "--tally", s(&v1), s(&v2)]);
    let text = String::from_utf8_lossy(&o.stdout);
    let line = |q: &str, label: &str| -> String {
        let section = &text[text.find(q).unwrap()..];
        section
            .lines()
            .find(|l| l.trim_start().starts_with(label))
            .unwrap()
            .split_whitespace()
            .collect::<Vec<_>>()
            .join(" ")
    };
    assert_eq!(line("(cleanest)", "m1"), "m1 2 100.0% 2", "{text}");
    assert_eq!(line("(best)", "m1"), "m1 1 50.0% 2", "{text}");
    assert_eq!(line("(best)", "m3"), "m3 0 0.0% 2", "{text}");
}

fn scene_image(noise: f32, other: bool) -> Array3<f32> {
    let img = scene(12, 16, noise);
    if other {
        img.mapv(|v| v * 2.0)
    } else {
        img
    }
}

fn expect_exit_2(args: &[&str], names: &str) -> String {
    let o = quantacolor(args);
    assert_eq!(o.status.code(), Some(2), "{args:?}");
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(err.contains(names), "{args:?}: {err}");
    err
}

#[test]
fn bad_input_exits_2_names_the_file_and_writes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let a = result_dir(d, "a", "capA", &scene(8, 10, 0.0));
    let out = d.join("out");
    // A folder without report.toml.
    let bare = d.join("bare");
    std::fs::create_dir(&bare).unwrap();
    write_npy(bare.join("linear.npy"), &scene(8, 10, 0.0)).unwrap();
    let e = expect_exit_2(&["report", s(&a), s(&bare), "--out", s(&out)], "bare");
    assert!(e.contains("no report.toml"), "{e}");
    // A ground truth of another size.
    let gt = d.join("gt.npy");
    write_npy(&gt, &scene(9, 10, 0.0)).unwrap();
    let e = expect_exit_2(
        &["report", s(&a), "--ground-truth", s(&gt), "--out", s(&out)],
        "gt.npy",
    );
    assert!(e.contains("shape"), "{e}");
    // A broken report.toml.
    let broken = result_dir(d, "broken", "capA", &scene(8, 10, 0.0));
    std::fs::write(broken.join("report.toml"), "frames_used = [").unwrap();
    expect_exit_2(&["report", s(&broken), "--out", s(&out)], "report.toml");
    // A study scene with one rendering.
    expect_exit_2(
        &["report", "--study", s(&a), "--out", s(&out)],
        "at least two",
    );
    let b = result_dir(&d.join("other"), "b", "capB", &scene(8, 10, 0.0));
    let a2 = result_dir(&d.join("x"), "a2", "capA", &scene(8, 10, 0.0));
    let e = expect_exit_2(
        &["report", "--study", s(&a), s(&a2), s(&b), "--out", s(&out)],
        "capB",
    );
    assert!(e.contains("at least two"), "{e}");
    // A votes file that is not one.
    let v = d.join("votes.json");
    std::fs::write(&v, "[1, 2]").unwrap();
    expect_exit_2(&["report", "--tally", s(&v)], "votes.json");
    assert!(!out.exists(), "no partial output");
    let leftovers: Vec<String> = files(d)
        .into_iter()
        .filter(|f| f.starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}
