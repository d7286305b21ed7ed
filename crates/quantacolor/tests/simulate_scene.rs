//! Simulator scene tests: image files (PNG sRGB, EXR linear) from the shared data folder (skipped
//! when absent), errors naming the file, and the built-in chart's patch values.

#[path = "common/skip.rs"]
mod skip;

use quantacolor::color::colorchecker::{srgb8_to_linear, COLORCHECKER_SRGB};
use quantacolor::color::srgb::srgb_to_linear;
use quantacolor::progress::Silent;
use quantacolor::simulate::chart::white_patch;
use quantacolor::simulate::{simulate, FluxSpec, Scene, SimulationConfig};
use std::path::{Path, PathBuf};

fn shared(name: &str) -> Option<PathBuf> {
    // The shared data folder sits beside the project root (or beside a parent of a worktree).
    let rel = Path::new("shared/data/scenes").join(name);
    let found = Path::new(env!("CARGO_MANIFEST_DIR"))
        .ancestors()
        .map(|a| a.join(&rel))
        .find(|p| p.exists());
    if found.is_none() {
        skip::skip(
            name,
            "the shared scene is not beside any parent of the project",
        );
    }
    found
}

#[test]
fn png_scene_is_decoded_to_linear() {
    let Some(path) = shared("kodim02.png") else {
        return;
    };
    let Scene::Image { image, .. } = Scene::from_spec(path.to_str().unwrap()).unwrap() else {
        panic!("expected an image scene");
    };
    let raw = image::open(&path).unwrap().to_rgb8();
    assert_eq!(
        image.dim(),
        (raw.height() as usize, raw.width() as usize, 3)
    );
    for &(y, x) in &[
        (0u32, 0u32),
        (100, 200),
        (raw.height() - 1, raw.width() - 1),
    ] {
        let px = raw.get_pixel(x, y).0;
        for k in 0..3 {
            let expected = srgb_to_linear(px[k] as f32 / 255.0);
            assert!((image[[y as usize, x as usize, k]] - expected).abs() < 1e-6);
        }
    }
    // A small capture of it: the mean W detections equal the requested flux.
    let config = SimulationConfig {
        height: 30,
        width: 50,
        frames: 4,
        flux: FluxSpec::Mean { flux: 0.3 },
        ..SimulationConfig::default()
    };
    let scene = Scene::from_spec(path.to_str().unwrap()).unwrap();
    let sim = simulate(&config, &scene, &Silent).unwrap();
    let mean_w = sim.ground_truth.sum() as f64 / (30.0 * 50.0);
    assert!((mean_w - 0.3).abs() < 1e-4, "mean W {mean_w}");
}

#[test]
fn exr_scene_is_linear_hdr() {
    let Some(path) = shared("ScanLines_StillLife.exr") else {
        return;
    };
    let Scene::Image { image, .. } = Scene::load(&path).unwrap() else {
        panic!("expected an image scene");
    };
    assert!(image.iter().all(|v| v.is_finite() && *v >= 0.0));
    let max = image.iter().cloned().fold(0.0f32, f32::max);
    let mut sorted: Vec<f32> = image.iter().cloned().collect();
    sorted.sort_by(f32::total_cmp);
    let median = sorted[sorted.len() / 2];
    assert!(
        max > 1.0 && max > 50.0 * median,
        "max {max}, median {median}"
    );
}

#[test]
fn bad_scene_paths_name_the_file() {
    let err = Scene::from_spec("/nonexistent/scene.png")
        .unwrap_err()
        .to_string();
    assert!(err.contains("/nonexistent/scene.png"), "{err}");
    let dir = tempfile::tempdir().unwrap();
    let junk = dir.path().join("junk.png");
    std::fs::write(&junk, b"not an image at all").unwrap();
    let err = Scene::load(&junk).unwrap_err().to_string();
    assert!(err.contains("junk.png"), "{err}");
    assert!(Scene::from_spec("builtin:nothing").is_err());
}

#[test]
fn chart_patches_keep_their_published_colours() {
    let (h, w) = (127, 248);
    let config = SimulationConfig {
        height: h,
        width: w,
        frames: 2,
        flux: FluxSpec::Mean { flux: 1.0 },
        ..SimulationConfig::default()
    };
    let sim = simulate(
        &config,
        &Scene::from_spec("builtin:chart").unwrap(),
        &Silent,
    )
    .unwrap();
    let qe = sim.sensor.quantum_efficiency;
    let centre = |i: usize| {
        let (row, col) = ((i / 6) as f64, (i % 6) as f64);
        let x = 0.02 * w as f64 + (col + 0.5) * 0.44 * w as f64 / 6.0;
        let y = 0.04 * h as f64 + (row + 0.5) * 0.52 * h as f64 / 4.0;
        (y.round() as usize, x.round() as usize)
    };
    // λ_c ∝ QE_c · linear sRGB value: ratios to the white patch hold per channel.
    let (wy, wx) = centre(18);
    let white = srgb8_to_linear(COLORCHECKER_SRGB[18]);
    for (i, &srgb) in COLORCHECKER_SRGB.iter().enumerate() {
        let (y, x) = centre(i);
        let lin = srgb8_to_linear(srgb);
        for k in 0..3 {
            let ratio = sim.ground_truth[[y, x, k]] / sim.ground_truth[[wy, wx, k]];
            assert!(
                (ratio - lin[k] / white[k]).abs() < 1e-3,
                "patch {i} channel {k}"
            );
        }
        // And the colour balance follows the quantum efficiencies.
        let g = sim.ground_truth[[y, x, 1]] / (lin[1] * qe[1] as f32);
        let r = sim.ground_truth[[y, x, 0]] / (lin[0] * qe[0] as f32);
        assert!((r / g - 1.0).abs() < 1e-3);
    }
    // The HDR chart's light is 1000x the white patch.
    let hdr = simulate(
        &config,
        &Scene::from_spec("builtin:chart-hdr").unwrap(),
        &Silent,
    )
    .unwrap();
    let (ly, lx) = ((0.75 * h as f64) as usize, (0.93 * w as f64) as usize);
    let ratio = hdr.ground_truth[[ly, lx, 1]] / hdr.ground_truth[[wy, wx, 1]];
    assert!((ratio - 1000.0).abs() < 1.0, "light / white = {ratio}");
    assert!((white_patch() - srgb_to_linear(243.0 / 255.0)).abs() < 1e-6);
}
