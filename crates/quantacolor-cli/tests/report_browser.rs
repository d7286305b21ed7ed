//! The pages of `quantacolor report` in headless Chromium: the comparison page opened from
//! disk, its exposure slider moved with the keyboard, zoomed with the wheel and panned by
//! dragging, low-light view and tone maps switched, every screenshot checked pixel by pixel
//! against `quantacolor display` for the same settings (within one 8-bit level); and the study
//! page: votes cast with keys and clicks, downloaded as JSON, read back and tallied.
//!
//! Skips with a message when Chromium is not installed. `QC_SCREENSHOT_DIR=DIR` keeps the
//! screenshots.

use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

mod browser_support;
mod cli_support;
mod report_support;
use browser_support::{browser_or_skip, Browser};
use cli_support::ok;
use report_support::{result_dir, scene};

const WAIT: Duration = Duration::from_secs(20);

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `quantacolor display INPUT --out tmp.png EXTRA...`, decoded.
fn display(tmp: &Path, input: &Path, extra: &[String]) -> image::RgbImage {
    let out = tmp.join(format!(
        "display-{}.png",
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos()
    ));
    let mut args = vec!["display".to_string(), s(input).into(), "--out".into()];
    args.push(s(&out).into());
    args.extend(extra.iter().cloned());
    let a: Vec<&str> = args.iter().map(String::as_str).collect();
    ok(&a);
    image::open(&out).unwrap().to_rgb8()
}

fn keep_screenshot(shot: &image::RgbImage, name: &str) {
    if let Some(dir) = std::env::var_os("QC_SCREENSHOT_DIR") {
        std::fs::create_dir_all(&dir).unwrap();
        shot.save(Path::new(&dir).join(name)).unwrap();
    }
}

/// The page's view and where its canvases are.
struct Layout {
    w: f64,
    h: f64,
    zoom: f64,
    cx: f64,
    cy: f64,
    origins: Vec<(f64, f64)>,
}

fn layout(b: &mut Browser) -> Layout {
    let v = b.eval(
        "({w: QC.size.w, h: QC.size.h, zoom: QC.view.zoom, cx: QC.view.cx, cy: QC.view.cy, \
          origins: QC.panels.map(p => { const r = p.canvas.getBoundingClientRect(); return [r.left, r.top]; })})",
    );
    let f = |k: &str| v[k].as_f64().unwrap();
    Layout {
        w: f("w"),
        h: f("h"),
        zoom: f("zoom"),
        cx: f("cx"),
        cy: f("cy"),
        origins: v["origins"]
            .as_array()
            .unwrap()
            .iter()
            .map(|o| (o[0].as_f64().unwrap(), o[1].as_f64().unwrap()))
            .collect(),
    }
}

/// Compares every screen pixel of every panel whose centre falls well inside an image pixel
/// (not within 15 % of its edge) with that pixel of `expected[panel]`. Returns the number of
/// pixels compared; panics on a difference above one level.
fn check_panels(b: &mut Browser, expected: &[image::RgbImage], name: &str) -> usize {
    let shot = b.screenshot();
    keep_screenshot(&shot, name);
    let l = layout(b);
    let mut compared = 0;
    for (i, want) in expected.iter().enumerate() {
        let (ox, oy) = l.origins[i];
        let (ox, oy) = (ox.round() as i64, oy.round() as i64);
        let mut worst = 0u8;
        let (mut same, mut n) = (0usize, 0usize);
        for sy in 0..l.h as i64 {
            for sx in 0..l.w as i64 {
                let ix = l.cx + (sx as f64 + 0.5 - l.w / 2.0) / l.zoom;
                let iy = l.cy + (sy as f64 + 0.5 - l.h / 2.0) / l.zoom;
                let (fx, fy) = (ix - ix.floor(), iy - iy.floor());
                if !(0.15..0.85).contains(&fx) || !(0.15..0.85).contains(&fy) {
                    continue;
                }
                let (px, py) = (ix.floor() as i64, iy.floor() as i64);
                if px < 0 || py < 0 || px >= want.width() as i64 || py >= want.height() as i64 {
                    continue;
                }
                let got = shot.get_pixel((ox + sx) as u32, (oy + sy) as u32).0;
                let exp = want.get_pixel(px as u32, py as u32).0;
                for c in 0..3 {
                    let d = got[c].abs_diff(exp[c]);
                    assert!(
                        d <= 1,
                        "{name}: panel {i}, screen ({sx}, {sy}) = image ({px}, {py}): page {got:?}, display {exp:?}"
                    );
                    worst = worst.max(d);
                    same += (d == 0) as usize;
                    n += 1;
                }
                compared += 1;
            }
        }
        eprintln!(
            "{name}: panel {i}: max difference {worst} level(s), {same} of {n} samples identical"
        );
    }
    assert!(compared > 1000, "{name}: only {compared} pixels compared");
    compared
}

/// Presses `key` `n` times with the element `id` focused.
fn press(b: &mut Browser, id: &str, key: &str, key_code: u32, n: usize) {
    b.eval(&format!("document.getElementById('{id}').focus()"));
    for _ in 0..n {
        b.key(key, key, key_code);
    }
}

fn exposures(b: &mut Browser, n: usize) -> Vec<String> {
    (0..n)
        .map(|i| {
            let v = b.eval(&format!("QC.exposureOf({i})"));
            // Exact f32 values printed in full: `display --exposure` parses the same f32.
            format!("{}", v.as_f64().expect("an explicit exposure"))
        })
        .collect()
}

#[test]
fn report_page_renders_like_display_and_zooms_pixel_exact() {
    let Some(mut b) = browser_or_skip("report_page_renders_like_display", 1000, 760) else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let smooth = result_dir(d, "smooth", "capA", &scene(48, 64, 0.0));
    let noisy = result_dir(d, "noisy", "capA", &scene(48, 64, 0.4));
    let gt = d.join("gt.npy");
    quantacolor::capture::io::write_npy(&gt, &scene(48, 64, 0.0).mapv(|v| v * 1.1)).unwrap();
    let page = d.join("page");
    ok(&[
        "report",
        s(&smooth),
        s(&noisy),
        "--ground-truth",
        s(&gt),
        "--out",
        s(&page),
    ]);
    let inputs: Vec<PathBuf> = vec![
        gt.clone(),
        smooth.join("linear.npy"),
        noisy.join("linear.npy"),
    ];
    // The ground truth has no report.toml beside it: the page uses the first result's frames.
    let frames_for = |i: usize| -> Vec<String> {
        if i == 0 {
            vec!["--frames".into(), "1000".into()]
        } else {
            vec![]
        }
    };
    let start = Instant::now();
    b.navigate(&page.join("index.html"));
    b.wait_for("window.QC !== undefined && QC.ready === true", WAIT);

    // 1. As opened: automatic exposure, global tone map = `display` defaults.
    let expected: Vec<_> = inputs.iter().map(|p| display(d, p, &[])).collect();
    let l = layout(&mut b);
    assert_eq!(l.origins.len(), 3);
    assert!(l.zoom > 1.0, "fit zoom {}", l.zoom);
    check_panels(&mut b, &expected, "1-default.png");

    // 2. Exposure slider +1.3 EV with the arrow key (0.1 EV a step).
    press(&mut b, "ev", "ArrowRight", 39, 13);
    b.wait_for("QC.state.ev === 1.3", WAIT);
    let e = exposures(&mut b, 3);
    let expected: Vec<_> = inputs
        .iter()
        .zip(&e)
        .map(|(p, e)| display(d, p, &["--exposure".into(), e.clone()]))
        .collect();
    check_panels(&mut b, &expected, "2-exposure.png");

    // 3. Three wheel notches on the middle panel: zoom about the pointer, all panels follow.
    let l = layout(&mut b);
    // Whole page pixels (mouse events carry integer client coordinates).
    let (px, py) = (
        (l.origins[1].0 + 120.0).round(),
        (l.origins[1].1 + 90.0).round(),
    );
    let (sx, sy) = (px - l.origins[1].0, py - l.origins[1].1);
    let before = (
        l.cx + (sx - l.w / 2.0) / l.zoom,
        l.cy + (sy - l.h / 2.0) / l.zoom,
    );
    for _ in 0..3 {
        b.wheel(px, py, -100.0);
    }
    b.wait_for("QC.view.zoom === 12", WAIT);
    let l = layout(&mut b);
    let after = (
        l.cx + (sx - l.w / 2.0) / l.zoom,
        l.cy + (sy - l.h / 2.0) / l.zoom,
    );
    assert!(
        (before.0 - after.0).abs() < 1e-9 && (before.1 - after.1).abs() < 1e-9,
        "the point under the pointer moved: {before:?} -> {after:?}"
    );
    check_panels(&mut b, &expected, "3-zoom.png");

    // 4. Drag the first panel 60 px left and 36 px up: the view moves 5 and 3 image pixels.
    let (cx0, cy0) = (l.cx, l.cy);
    let o = l.origins[0];
    b.drag((o.0 + 200.0, o.1 + 150.0), (o.0 + 140.0, o.1 + 114.0), 6);
    let l = layout(&mut b);
    assert!((l.cx - cx0 - 5.0).abs() < 1e-9 && (l.cy - cy0 - 3.0).abs() < 1e-9);
    check_panels(&mut b, &expected, "4-pan.png");

    // 5. Low-light view on, L0 -0.5 (slider, arrow keys).
    let (mx, my) = b.centre_of("#mesopic");
    b.click(mx, my);
    b.wait_for("QC.state.l0 === 0", WAIT);
    press(&mut b, "l0", "ArrowLeft", 37, 5);
    b.wait_for("QC.state.l0 === -0.5", WAIT);
    let e = exposures(&mut b, 3);
    let expected: Vec<_> = (0..3)
        .map(|i| {
            let mut extra = vec![
                "--mesopic".into(),
                "-0.5".into(),
                "--exposure".into(),
                e[i].clone(),
            ];
            extra.extend(frames_for(i));
            display(d, &inputs[i], &extra)
        })
        .collect();
    check_panels(&mut b, &expected, "5-low-light.png");

    // 6. Tone map `none` (exposure and clip), same exposure for all panels.
    b.eval("(() => { const t = document.getElementById('tonemap'); t.value = 'none'; t.dispatchEvent(new Event('change')); })()");
    let (lx, ly) = b.centre_of("#lock");
    b.click(lx, ly);
    b.wait_for(
        "QC.state.tonemap === 'none' && QC.state.lock === true",
        WAIT,
    );
    let e = exposures(&mut b, 3);
    assert!(e[0] == e[1] && e[1] == e[2], "{e:?}");
    let expected: Vec<_> = (0..3)
        .map(|i| {
            let mut extra = vec![
                "--tonemap".into(),
                "none".into(),
                "--mesopic".into(),
                "-0.5".into(),
                "--exposure".into(),
                e[i].clone(),
            ];
            extra.extend(frames_for(i));
            display(d, &inputs[i], &extra)
        })
        .collect();
    check_panels(&mut b, &expected, "6-none-locked.png");

    // 7. Mantiuk06, pre-rendered: `display --tonemap mantiuk06`.
    b.eval("(() => { const t = document.getElementById('tonemap'); t.value = 'mantiuk06'; t.dispatchEvent(new Event('change')); })()");
    b.wait_for("QC.state.tonemap === 'mantiuk06'", WAIT);
    let expected: Vec<_> = inputs
        .iter()
        .map(|p| display(d, p, &["--tonemap".into(), "mantiuk06".into()]))
        .collect();
    check_panels(&mut b, &expected, "7-mantiuk06.png");

    // The settings are in the URL: reopening it restores the view.
    let hash = b.eval("location.hash");
    let hash = hash.as_str().unwrap();
    assert!(
        hash.contains("tm=mantiuk06") && hash.contains("z=12"),
        "{hash}"
    );
    eprintln!("browser steps took {:.1} s", start.elapsed().as_secs_f64());
}

#[test]
fn study_page_records_key_and_click_votes_and_downloads_them() {
    let Some(mut b) = browser_or_skip("study_page_records_votes", 1000, 700) else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let mut dirs = Vec::new();
    for (scene_name, names) in [("capA", vec!["m1", "m2", "m3"]), ("capB", vec!["m1", "m2"])] {
        for (k, name) in names.iter().enumerate() {
            dirs.push(result_dir(
                &d.join(scene_name),
                name,
                scene_name,
                &scene(24, 32, 0.3 * k as f32),
            ));
        }
    }
    let study = d.join("study");
    let mut args: Vec<&str> = vec!["report", "--study", "--seed", "2", "--out", s(&study)];
    args.extend(dirs.iter().map(|p| s(p)));
    ok(&args);
    let downloads = d.join("downloads");
    std::fs::create_dir(&downloads).unwrap();
    b.call_browser(
        "Browser.setDownloadBehavior",
        json!({"behavior": "allow", "downloadPath": s(&downloads), "eventsEnabled": true}),
    );
    b.navigate(&study.join("index.html"));
    b.wait_for("window.QCStudy !== undefined", WAIT);
    let trials = b.eval("QC_STUDY.trials.map(t => [t.scene, t.labels])");
    let trials: Vec<(String, Vec<String>)> = serde_json::from_value(trials).unwrap();
    assert_eq!(trials.len(), 2);
    let mut expected = Vec::new();
    for (k, (scene_name, labels)) in trials.iter().enumerate() {
        b.wait_for(
            &format!("document.querySelectorAll('#choices img').length === {} && [...document.images].every(i => i.complete && i.naturalWidth > 0)", labels.len()),
            WAIT,
        );
        if k == 0 {
            keep_screenshot(&b.screenshot(), "study.png");
        }
        // "Which image looks cleanest?": m1, by its number key.
        let pos = labels.iter().position(|l| l == "m1").unwrap() + 1;
        let digit = pos.to_string();
        b.key(&digit, &format!("Digit{pos}"), 48 + pos as u32);
        expected.push((scene_name.clone(), "cleanest", "m1".to_string(), pos));
        b.wait_for(&format!("QCStudy.votes.length === {}", 2 * k + 1), WAIT);
        // "Which image do you like best?": the rightmost, by a click.
        let last = labels.len();
        let (x, y) = b.centre_of(&format!("#choice-{last}"));
        b.click(x, y);
        expected.push((scene_name.clone(), "best", labels[last - 1].clone(), last));
        b.wait_for(&format!("QCStudy.votes.length === {}", 2 * k + 2), WAIT);
    }
    b.wait_for(
        "QCStudy.finished() && !document.getElementById('done').hidden",
        WAIT,
    );
    let (x, y) = b.centre_of("#download");
    b.click(x, y);
    let file = downloads.join("votes.json");
    let start = Instant::now();
    while !file.is_file() {
        assert!(start.elapsed() < WAIT, "no votes.json downloaded");
        std::thread::sleep(Duration::from_millis(50));
    }
    // The download is complete when Chromium renames it into place.
    let votes: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    assert_eq!(votes["format"], "quantacolor-study-votes");
    assert_eq!(votes["seed"], 2);
    let got: Vec<(String, String, String, usize)> = votes["votes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| {
            (
                v["scene"].as_str().unwrap().to_string(),
                v["question"].as_str().unwrap().to_string(),
                v["choice"].as_str().unwrap().to_string(),
                v["position"].as_u64().unwrap() as usize,
            )
        })
        .collect();
    let expected: Vec<_> = expected
        .into_iter()
        .map(|(a, q, c, p)| (a, q.to_string(), c, p))
        .collect();
    assert_eq!(got, expected);
    let o = ok(&["report", "--tally", s(&file)]);
    let text = String::from_utf8_lossy(&o.stdout);
    let cleanest = &text[text.find("(cleanest)").unwrap()..text.find("(best)").unwrap()];
    let m1: Vec<&str> = cleanest
        .lines()
        .find(|l| l.trim_start().starts_with("m1"))
        .unwrap()
        .split_whitespace()
        .collect();
    assert_eq!(m1, ["m1", "2", "100.0%", "2"], "{text}");
}
