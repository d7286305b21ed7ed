//! Cross-check of `bm3d_grey` against the reference `bm3d` Python package (non-commercial
//! licence; only invoked, see tools/bm3d_crosscheck/README.md). Ignored by default:
//! `cargo test --release -p quantacolor --test bm3d_crosscheck -- --ignored --nocapture`.
//! Skips (prints why, passes) when python3, venv creation or pip fails.

use ndarray::Array2;
use ndarray_npy::{read_npy, write_npy};
use quantacolor::denoise::bm3d::{bm3d_grey, Bm3dConfig};
use quantacolor::metrics::psnr;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

mod bm3d_support;
use bm3d_support::{scenes_dir, synthetic};

/// 256x256 centre crops of the scene photographs on 0..255: Kodak PNGs by Rec. 601 luma, EXRs
/// by luma normalised at its 99th percentile, gamma 1/2.2 and clipped.
fn scene_crops() -> Vec<(String, Array2<f32>)> {
    let Some(dir) = scenes_dir() else {
        println!("no shared/data/scenes folder: synthetic image only");
        return Vec::new();
    };
    let mut names: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map(|rd| rd.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    names.sort();
    let mut out = Vec::new();
    for path in names {
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        let is_kodim = name.starts_with("kodim") && name.ends_with(".png");
        let is_exr = name.ends_with(".exr");
        if !is_kodim && !is_exr {
            continue;
        }
        let Ok(img) = image::open(&path) else {
            println!("{name}: cannot read, skipped");
            continue;
        };
        let rgb = img.to_rgb32f();
        let (w, h) = (rgb.width() as usize, rgb.height() as usize);
        if w < 256 || h < 256 {
            continue;
        }
        let (y0, x0) = ((h - 256) / 2, (w - 256) / 2);
        let mut crop = Array2::from_shape_fn((256, 256), |(y, x)| {
            let p = rgb.get_pixel((x0 + x) as u32, (y0 + y) as u32);
            0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2]
        });
        if is_exr {
            let mut v: Vec<f32> = crop.iter().map(|v| v.max(0.0)).collect();
            v.sort_by(f32::total_cmp);
            let p99 = v[v.len() * 99 / 100].max(1e-12);
            crop.mapv_inplace(|l| (l.max(0.0) / p99).min(1.0).powf(1.0 / 2.2) * 255.0);
        } else {
            crop.mapv_inplace(|l| l * 255.0);
        }
        out.push((name, crop));
    }
    out
}

/// A venv with bm3d and numpy under the target folder, or why there is none.
fn python_with_bm3d() -> Result<PathBuf, String> {
    let target = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .expect("target dir")
        .to_path_buf();
    let venv = target.join("bm3d-crosscheck-venv");
    let python = venv.join("bin/python");
    let has_bm3d = |py: &Path| {
        Command::new(py)
            .args(["-c", "import bm3d, numpy"])
            .status()
            .map(|s| s.success())
            .unwrap_or(false)
    };
    if python.exists() && has_bm3d(&python) {
        return Ok(python);
    }
    let status = Command::new("python3")
        .args(["-m", "venv"])
        .arg(&venv)
        .status()
        .map_err(|e| format!("python3 not runnable: {e}"))?;
    if !status.success() {
        return Err(format!("python3 -m venv failed ({status})"));
    }
    let status = Command::new(venv.join("bin/pip"))
        .args(["install", "--quiet", "bm3d", "numpy"])
        .status()
        .map_err(|e| format!("pip not runnable: {e}"))?;
    if !status.success() || !has_bm3d(&python) {
        return Err(format!("pip install bm3d numpy failed ({status})"));
    }
    Ok(python)
}

#[test]
#[ignore = "needs Python and network: cargo test --release --test bm3d_crosscheck -- --ignored --nocapture"]
fn psnr_matches_reference_package() {
    let python = match python_with_bm3d() {
        Ok(p) => p,
        Err(why) => {
            println!("SKIPPED bm3d cross-check: {why}");
            return;
        }
    };
    let script =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tools/bm3d_crosscheck/denoise.py");
    let tmp = tempfile::tempdir().unwrap();
    let mut images = vec![("synthetic".to_string(), synthetic(256, 256))];
    images.extend(scene_crops());
    // Optional narrowing for quick runs: BM3D_CROSSCHECK_IMAGES=<count>, BM3D_CROSSCHECK_SIGMA=<σ>.
    if let Some(k) = std::env::var("BM3D_CROSSCHECK_IMAGES")
        .ok()
        .and_then(|v| v.parse().ok())
    {
        images.truncate(k);
    }
    let sigmas: Vec<f32> = match std::env::var("BM3D_CROSSCHECK_SIGMA") {
        Ok(v) => vec![v.parse().expect("BM3D_CROSSCHECK_SIGMA is a number")],
        Err(_) => vec![15.0, 25.0, 50.0],
    };
    // BM3D_CROSSCHECK_CONFIG="<toml>" overrides parameters, for tuning experiments.
    let config: Bm3dConfig = match std::env::var("BM3D_CROSSCHECK_CONFIG") {
        Ok(text) => toml::from_str(&text).expect("BM3D_CROSSCHECK_CONFIG is a Bm3dConfig in TOML"),
        // The package's normal profile: reference blocks every 3 px (ours defaults to 5).
        Err(_) => Bm3dConfig {
            step: 3,
            ..Bm3dConfig::default()
        },
    };
    let mut failures = Vec::new();
    println!(
        "{:<28} {:>5} {:>8} {:>8} {:>8} {:>8} {:>8} {:>7}",
        "image", "sigma", "noisy", "ours", "package", "ours s", "pkg s", "speedup"
    );
    for (i, (name, clean)) in images.iter().enumerate() {
        for &sigma in &sigmas {
            let j = [15.0f32, 25.0, 50.0]
                .iter()
                .position(|&v| v == sigma)
                .unwrap_or(3);
            let mut rng = ChaCha8Rng::seed_from_u64(1000 + 10 * i as u64 + j as u64);
            let normal = Normal::new(0.0f32, sigma).unwrap();
            let noisy = clean.mapv(|v| v + normal.sample(&mut rng));
            let t0 = Instant::now();
            let ours = bm3d_grey(noisy.view(), sigma, &config).unwrap();
            let ours_s = t0.elapsed().as_secs_f64();

            let noisy_path = tmp.path().join("noisy.npy");
            let out_path = tmp.path().join("out.npy");
            write_npy(&noisy_path, &noisy).unwrap();
            let output = Command::new(&python)
                .arg(&script)
                .arg(&noisy_path)
                .arg(sigma.to_string())
                .arg(&out_path)
                .output()
                .unwrap();
            assert!(
                output.status.success(),
                "denoise.py failed: {}",
                String::from_utf8_lossy(&output.stderr)
            );
            let stdout = String::from_utf8_lossy(&output.stdout);
            let pkg_s: f64 = stdout
                .lines()
                .find_map(|l| l.strip_prefix("seconds="))
                .and_then(|v| v.trim().parse().ok())
                .expect("denoise.py prints seconds=");
            let theirs: Array2<f32> = read_npy(&out_path).unwrap();

            let p_noisy = psnr(noisy.view(), clean.view(), 255.0).unwrap();
            let p_ours = psnr(ours.view(), clean.view(), 255.0).unwrap();
            let p_theirs = psnr(theirs.view(), clean.view(), 255.0).unwrap();
            println!(
                "{:<28} {:>5} {:>8.2} {:>8.2} {:>8.2} {:>8.3} {:>8.3} {:>7.2}",
                name,
                sigma,
                p_noisy,
                p_ours,
                p_theirs,
                ours_s,
                pkg_s,
                pkg_s / ours_s
            );
            if p_ours < p_theirs - 0.3 {
                failures.push(format!(
                    "{name} sigma {sigma}: ours {p_ours:.2} dB vs package {p_theirs:.2} dB"
                ));
            }
        }
    }
    assert!(failures.is_empty(), "more than 0.3 dB worse: {failures:?}");
}
