//! The comparison page's rendering module (report/assets/render.js) against the Rust display
//! pipeline on sample pixels: the page must match `quantacolor display` to within one 8-bit
//! level. Runs render.js under node; skips with a message when node is not installed.

#[path = "common/skip.rs"]
mod skip;

use ndarray::Array3;
use quantacolor::display::{render_srgb8, MesopicConfig, MesopicOffset, RenderOptions, ToneMap};
use quantacolor::report::encode::{base64, half_bytes};
use quantacolor::report::{decode_half, encode_half, RENDER_JS};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::process::Command;

/// Sample pixels over seven decades, every hue, with zeros, negatives and non-finite values.
fn samples() -> Array3<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut img = Array3::from_shape_fn((24, 40, 3), |_| {
        let decade: f32 = rng.gen_range(-6.0..1.0);
        10f32.powf(decade) * rng.gen_range(0.2..1.0)
    });
    img[[0, 0, 0]] = 0.0;
    img[[0, 1, 1]] = -0.01;
    img[[0, 2, 2]] = f32::NAN;
    img[[0, 3, 0]] = f32::INFINITY;
    img[[1, 0, 0]] = 0.0;
    img[[1, 0, 1]] = 0.0;
    img[[1, 0, 2]] = 0.0;
    img
}

struct Case {
    tonemap: &'static str,
    exposure: Option<f32>,
    l0: Option<f32>,
    w_weights: [f64; 3],
}

const FRAMES: f64 = 2000.0;

fn cases() -> Vec<Case> {
    let mut out = Vec::new();
    for tonemap in ["global", "none"] {
        for exposure in [None, Some(0.37f32), Some(12.5)] {
            for l0 in [None, Some(0.0f32), Some(-1.3), Some(0.8)] {
                for w_weights in [[1.0, 1.0, 1.0], [0.9, 1.1, 0.8]] {
                    out.push(Case {
                        tonemap,
                        exposure,
                        l0,
                        w_weights,
                    });
                }
            }
        }
    }
    out
}

fn rust_render(img: &Array3<f32>, c: &Case) -> Vec<u8> {
    let options = RenderOptions {
        exposure: c.exposure,
        tonemap: c.tonemap.parse::<ToneMap>().unwrap(),
        mesopic: c.l0.map(|l0| MesopicConfig {
            l0: MesopicOffset::Fixed(l0),
            frames: Some(FRAMES),
        }),
        w_weights: c.w_weights,
        ..RenderOptions::default()
    };
    render_srgb8(img.view(), &options)
        .unwrap()
        .into_raw_vec_and_offset()
        .0
}

const HARNESS: &str = r#"
const R = require(process.argv[2]);
const input = JSON.parse(require("fs").readFileSync(process.argv[3], "utf8"));
const linear = R.decodeHalf(input.half, input.scale_log2);
const out = input.cases.map((c) => {
  const prep = R.prepare(linear, c.l0 === null ? null : { l0: c.l0, frames: input.frames }, c.w_weights);
  const rgba = R.render(prep, c.tonemap, c.exposure);
  const rgb = [];
  for (let i = 0; i < rgba.length; i += 4) rgb.push(rgba[i], rgba[i + 1], rgba[i + 2]);
  return rgb;
});
process.stdout.write(JSON.stringify(out));
"#;

#[test]
fn render_js_matches_the_rust_display_pipeline_within_one_level() {
    if Command::new("node").arg("--version").output().is_err() {
        skip::skip(
            "render_js_matches_the_rust_display_pipeline_within_one_level",
            "node is not installed (the browser test in quantacolor-cli checks the page in Chromium)",
        );
        return;
    }
    let img = samples();
    let half = encode_half(img.view());
    let decoded = decode_half(&half);
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("render.js"), RENDER_JS).unwrap();
    std::fs::write(dir.path().join("harness.js"), HARNESS).unwrap();
    let cases = cases();
    let input = serde_json::json!({
        "half": base64(&half_bytes(&half)),
        "scale_log2": half.scale_log2,
        "frames": FRAMES,
        "cases": cases.iter().map(|c| serde_json::json!({
            "tonemap": c.tonemap,
            "exposure": c.exposure,
            "l0": c.l0,
            "w_weights": c.w_weights,
        })).collect::<Vec<_>>(),
    });
    std::fs::write(dir.path().join("input.json"), input.to_string()).unwrap();
    let out = Command::new("node")
        .arg(dir.path().join("harness.js"))
        .arg(dir.path().join("render.js"))
        .arg(dir.path().join("input.json"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let js: Vec<Vec<u8>> = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(js.len(), cases.len());
    let mut exact = 0usize;
    let mut total = 0usize;
    for (c, got) in cases.iter().zip(&js) {
        let label = format!(
            "{} exposure {:?} L0 {:?} w {:?}",
            c.tonemap, c.exposure, c.l0, c.w_weights
        );
        // Same data as the page decodes: the port itself.
        let want = rust_render(&decoded, c);
        assert_eq!(got.len(), want.len(), "{label}");
        for (i, (&g, &w)) in got.iter().zip(&want).enumerate() {
            assert!(
                g.abs_diff(w) <= 1,
                "{label}: sample {i}: page {g}, display {w}"
            );
        }
        exact += got.iter().zip(&want).filter(|(g, w)| g == w).count();
        total += got.len();
        // The original float32 image, as `quantacolor display` renders linear.npy: the
        // binary16 export costs at most one level.
        let original = rust_render(&img, c);
        let worst = got
            .iter()
            .zip(&original)
            .map(|(g, w)| g.abs_diff(*w))
            .max()
            .unwrap();
        assert!(
            worst <= 1,
            "{label}: page vs float32 display differ by {worst}"
        );
        // The cases are not all alike (a broken port could not pass by rendering black).
        assert!(got.iter().any(|&v| v > 50), "{label}");
    }
    eprintln!("render.js vs display on the decoded data: {exact} of {total} samples identical");
    // Bit-exact f32 emulation: differences come only from libm-level rounding.
    assert!(
        exact as f64 >= 0.999 * total as f64,
        "{exact} of {total} samples identical"
    );
}

#[test]
fn low_light_cases_differ_from_plain_ones() {
    // The harness's L0 cases must exercise the blend (otherwise the test above could not see a
    // wrong Eq. 9-10): the sample image spans the fade.
    let img = samples();
    let plain = rust_render(
        &img,
        &Case {
            tonemap: "global",
            exposure: None,
            l0: None,
            w_weights: [1.0; 3],
        },
    );
    for l0 in [0.0, -1.3, 0.8] {
        let blended = rust_render(
            &img,
            &Case {
                tonemap: "global",
                exposure: None,
                l0: Some(l0),
                w_weights: [1.0; 3],
            },
        );
        let changed = plain
            .iter()
            .zip(&blended)
            .filter(|(a, b)| a.abs_diff(**b) > 2)
            .count();
        assert!(changed > 100, "L0 {l0}: {changed} samples changed");
    }
}
