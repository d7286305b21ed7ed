//! LPIPS-Alex v0.1 (`quantacolor::metrics::lpips`): the reference values of the shared data
//! (`tests/data/lpips/`, copied from `shared/data/lpips/`: 256x192 crops of Kodak images and
//! their LPIPS from an implementation that matches the `lpips` Python package to 4 decimals),
//! identity, symmetry, monotonicity in noise, input checks, and the evaluation protocol.

#[path = "common/skip.rs"]
mod skip;

use std::path::{Path, PathBuf};
use std::time::Instant;

use ndarray::{s, Array3};
use quantacolor::color::srgb::linear_to_srgb;
use quantacolor::metrics::{evaluate_lpips, lpips, EvalOptions, Lpips, LPIPS_MIN_SIZE};

fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/lpips")
}

/// An 8-bit sRGB PNG as (H, W, 3) f32 in [0, 1] (value / 255, as the reference computation).
fn read_png(name: &str) -> Array3<f32> {
    let img = image::open(data_dir().join(name))
        .unwrap_or_else(|e| panic!("{name}: {e}"))
        .to_rgb8();
    let (w, h) = img.dimensions();
    Array3::from_shape_vec((h as usize, w as usize, 3), img.into_raw())
        .unwrap()
        .mapv(|v| f32::from(v) / 255.0)
}

/// `"a.png vs b.png": value` pairs of reference_values.json (flat object, no nesting).
fn reference_values() -> Vec<(String, String, f64)> {
    let text = std::fs::read_to_string(data_dir().join("reference_values.json")).unwrap();
    let body = text.trim().trim_start_matches('{').trim_end_matches('}');
    body.split(',')
        .filter(|e| !e.trim().is_empty())
        .map(|entry| {
            let (key, value) = entry.rsplit_once(':').expect("key: value");
            let key = key.trim().trim_matches('"');
            let (a, b) = key.split_once(" vs ").expect("'a vs b'");
            (a.to_string(), b.to_string(), value.trim().parse().unwrap())
        })
        .collect()
}

#[test]
fn reproduces_the_reference_values() {
    let refs = reference_values();
    assert_eq!(refs.len(), 3);
    for (a, b, want) in refs {
        let got = lpips(read_png(&a).view(), read_png(&b).view()).unwrap();
        println!("{a} vs {b}: {got:.5} (reference {want})");
        // The reference is rounded to 4 decimals.
        assert!((got - want).abs() < 1e-3, "{a} vs {b}: {got} vs {want}");
    }
}

/// A smooth synthetic sRGB image with edges and texture, (h, w, 3) in [0, 1].
fn synthetic(h: usize, w: usize) -> Array3<f32> {
    Array3::from_shape_fn((h, w, 3), |(y, x, c)| {
        let (yf, xf) = (y as f32 / h as f32, x as f32 / w as f32);
        let stripes = if (x / 9 + y / 13) % 2 == 0 { 0.2 } else { 0.0 };
        let wave = 0.15 * ((xf * 17.0 + c as f32).sin() * (yf * 11.0).cos());
        (0.3 + 0.3 * xf * (c as f32 + 1.0) / 3.0 + 0.2 * yf + stripes + wave).clamp(0.0, 1.0)
    })
}

/// Deterministic zero-mean noise in [−1, 1] (integer hash, no RNG dependence).
fn noise(h: usize, w: usize) -> Array3<f32> {
    Array3::from_shape_fn((h, w, 3), |(y, x, c)| {
        let mut v = (y * 7919 + x * 104_729 + c * 15_485_863) as u64;
        v ^= v >> 13;
        v = v.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        v ^= v >> 29;
        (v % 2001) as f32 / 1000.0 - 1.0
    })
}

#[test]
fn identity_is_zero_and_distance_is_symmetric() {
    let a = synthetic(64, 80);
    assert_eq!(lpips(a.view(), a.view()).unwrap(), 0.0);
    let b = (&a + &(noise(64, 80) * 0.1)).mapv(|v| v.clamp(0.0, 1.0));
    let ab = lpips(a.view(), b.view()).unwrap();
    let ba = lpips(b.view(), a.view()).unwrap();
    assert!(ab > 0.01, "noise must register: {ab}");
    assert!((ab - ba).abs() < 1e-6, "{ab} vs {ba}");
}

#[test]
fn grows_with_the_noise_level() {
    let a = synthetic(96, 128);
    let n = noise(96, 128);
    let scores: Vec<f64> = [0.0f32, 0.02, 0.05, 0.1, 0.2, 0.4]
        .iter()
        .map(|&sigma| {
            let b = (&a + &(&n * sigma)).mapv(|v| v.clamp(0.0, 1.0));
            lpips(a.view(), b.view()).unwrap()
        })
        .collect();
    println!("LPIPS by noise amplitude: {scores:?}");
    assert_eq!(scores[0], 0.0);
    for pair in scores.windows(2) {
        assert!(pair[1] > pair[0], "not increasing: {scores:?}");
    }
}

#[test]
fn rejects_bad_input() {
    let a = synthetic(40, 40);
    let err = |r: quantacolor::Result<f64>| r.unwrap_err().to_string();
    // Shape mismatch.
    let b = synthetic(40, 41);
    assert!(err(lpips(a.view(), b.view())).contains("differs"));
    // Too small.
    let small = synthetic(LPIPS_MIN_SIZE - 1, 50);
    let e = err(lpips(small.view(), small.view()));
    assert!(e.contains("at least 31x31"), "{e}");
    let ok = synthetic(LPIPS_MIN_SIZE, LPIPS_MIN_SIZE);
    assert!(lpips(ok.view(), ok.view()).is_ok());
    // Not RGB.
    let grey = Array3::<f32>::zeros((40, 40, 1));
    assert!(err(lpips(grey.view(), grey.view())).contains("channels"));
    // Out of range (0..255 data) and NaN.
    let big = a.mapv(|v| v * 255.0);
    assert!(err(lpips(big.view(), a.view())).contains("[0, 1]"));
    let mut nan = a.clone();
    nan[[3, 4, 1]] = f32::NAN;
    assert!(err(lpips(a.view(), nan.view())).contains("NaN"));
    // Garbage weights.
    assert!(Lpips::from_npz_bytes(b"not a zip").is_err());
}

#[test]
fn evaluate_lpips_scores_the_protocol_images() {
    // evaluate_lpips = LPIPS of the cropped, normalised, clipped, sRGB-encoded images.
    let truth = synthetic(72, 90).mapv(|v| v * v * 3.0); // linear, arbitrary exposure
    let est = (&truth + &(noise(72, 90) * 0.2)).mapv(|v| v.max(0.0));
    let opts = EvalOptions {
        border: 4,
        normalize_percentile: Some(99.5),
    };
    let got = evaluate_lpips(est.view(), truth.view(), &opts).unwrap();
    // The same by hand: crop, scale by the truth's 99.5th percentile, clip, sRGB.
    let crop = |a: &Array3<f32>| a.slice(s![4..68, 4..86, ..]).to_owned();
    let (e, t) = (crop(&est), crop(&truth));
    let mut v: Vec<f32> = t.iter().copied().collect();
    v.sort_by(f32::total_cmp);
    let pos = 0.995 * (v.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let q = f64::from(v[lo]) + (pos - lo as f64) * f64::from(v[lo + 1] - v[lo]);
    let enc =
        |a: &Array3<f32>| a.mapv(|x| linear_to_srgb((f64::from(x) / q).clamp(0.0, 1.0) as f32));
    let want = lpips(enc(&e).view(), enc(&t).view()).unwrap();
    assert!((got - want).abs() < 1e-9, "{got} vs {want}");
    // Exposure-invariant like the other scores.
    let scaled = evaluate_lpips(
        est.mapv(|x| x * 7.0).view(),
        truth.mapv(|x| x * 7.0).view(),
        &opts,
    )
    .unwrap();
    assert!((scaled - got).abs() < 1e-4, "{scaled} vs {got}");
    assert_eq!(
        evaluate_lpips(truth.view(), truth.view(), &opts).unwrap(),
        0.0
    );
}

/// Speed diagnostic (run with `--ignored --nocapture`): LPIPS on a 496x254 image pair.
#[test]
#[ignore]
fn speed_496x254() {
    let a = synthetic(254, 496);
    let b = (&a + &(noise(254, 496) * 0.1)).mapv(|v| v.clamp(0.0, 1.0));
    Lpips::alex().unwrap(); // weights parsed outside the timing
    let runs = 5;
    let start = Instant::now();
    let mut d = 0.0;
    for _ in 0..runs {
        d = lpips(a.view(), b.view()).unwrap();
    }
    let per = start.elapsed().as_secs_f64() / runs as f64;
    println!(
        "LPIPS 496x254: {:.3} s per pair ({} threads), distance {d:.4}",
        per,
        rayon::current_num_threads()
    );
}

/// The embedded binary16 weights against the published float32 ones, when the project's shared
/// data folder is present (skipped otherwise; CI requires it).
#[test]
fn embedded_f16_weights_agree_with_the_published_f32_weights() {
    let rel = "shared/data/lpips/lpips_alex_v0.1_oihw.npz";
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    let Some(path) = manifest
        .ancestors()
        .map(|d| d.join(rel))
        .find(|p| p.is_file())
    else {
        skip::skip(rel, "not found beside any parent of the project");
        return;
    };
    let bytes = std::fs::read(&path).unwrap();
    let full = Lpips::from_npz_bytes(&bytes).unwrap();
    let embedded = Lpips::alex().unwrap();
    for (a, b, want) in reference_values() {
        let (x, y) = (read_png(&a), read_png(&b));
        let f32_value = full.distance(x.view(), y.view()).unwrap();
        let f16_value = embedded.distance(x.view(), y.view()).unwrap();
        println!("{a} vs {b}: float32 {f32_value:.5}, binary16 {f16_value:.5}, reference {want}");
        assert!((f32_value - want).abs() < 1e-3);
        assert!(
            (f16_value - f32_value).abs() < 3e-4,
            "{f16_value} vs {f32_value}"
        );
    }
}
