//! Cross-check of our Mantiuk 2006 tone map (`display::mantiuk`, written from the paper) against
//! `pfstmo_mantiuk06` of the pfstools package (GPL; only invoked as a program, nothing of it is
//! copied; see tools/mantiuk_crosscheck/README.md). Ignored by default:
//!
//! `cargo test --release -p quantacolor --test mantiuk_crosscheck -- --ignored --nocapture`
//!
//! Inputs: the OpenEXR photographs of `../shared/data/scenes/` (when present), simulated HDR
//! reconstructions of them (colour-SPAD CFA, 2000 frames, median W pixel at 0.1 detections per
//! frame, as `bench quality`'s HDR captures) and the built-in HDR chart. Both operators run on
//! the same linear RGB; their display-referred outputs are sRGB-encoded by the same code and
//! compared (PSNR and SSIM of the 8-bit images), with per-stage statistics: the dynamic range of
//! the display luminance (log10 of its 99th over 1st percentile), the mean log-luminance
//! gradient magnitude at the finest scale (detail, where noise shows) and at 1/8 scale (global
//! contrast), and the chroma saturation. Installs pfstools with apt-get when it can and is
//! allowed (`MANTIUK_CROSSCHECK_INSTALL=0` forbids); otherwise prints why and passes.
//!
//! `MANTIUK_CROSSCHECK_OUT=DIR` also writes side-by-side PNGs (ours | pfstools | global) there.

use ndarray::{s, Array2, Array3, ArrayView3, Axis};
use quantacolor::capture::io;
use quantacolor::display::{hstack, quantise8, tone_map, Mantiuk06Config, ToneMap};
use quantacolor::metrics::{psnr, ssim_color};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

const REC709: [f32; 3] = [0.2126, 0.7152, 0.0722];

fn scenes_dir() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/scenes");
    dir.is_dir().then_some(dir)
}

fn have(program: &str) -> bool {
    Command::new(program)
        .arg("--help")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok()
}

/// pfstools on the PATH, installing it with apt-get when that is possible and allowed.
fn pfstools() -> Result<(), String> {
    let tools = ["pfsinpfm", "pfsoutpfm", "pfstmo_mantiuk06"];
    if tools.iter().all(|t| have(t)) {
        return Ok(());
    }
    if std::env::var("MANTIUK_CROSSCHECK_INSTALL").as_deref() == Ok("0") {
        return Err("pfstools not installed (MANTIUK_CROSSCHECK_INSTALL=0)".into());
    }
    if !have("apt-get") {
        return Err("pfstools not installed and no apt-get".into());
    }
    let run = |args: &[&str]| {
        Command::new("apt-get")
            .args(args)
            .env("DEBIAN_FRONTEND", "noninteractive")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .map(|s| s.success())
            .unwrap_or(false)
    };
    if !(run(&["update"]) && run(&["install", "-y", "pfstools"])) {
        return Err("apt-get install pfstools failed (no root or no network?)".into());
    }
    if tools.iter().all(|t| have(t)) {
        Ok(())
    } else {
        Err("pfstools installed but its programs are not on the PATH".into())
    }
}

/// Portable float map, colour ("PF"), little endian, rows stored bottom to top.
fn write_pfm(path: &Path, img: ArrayView3<f32>) {
    let (h, w, _) = img.dim();
    let mut bytes = format!("PF\n{w} {h}\n-1.0\n").into_bytes();
    for y in (0..h).rev() {
        for x in 0..w {
            for c in 0..3 {
                bytes.extend_from_slice(&img[[y, x, c]].to_le_bytes());
            }
        }
    }
    std::fs::write(path, bytes).expect("write pfm");
}

fn read_pfm(bytes: &[u8]) -> Array3<f32> {
    // Header: three whitespace-separated tokens lines.
    let mut fields = Vec::new();
    let mut pos = 0;
    while fields.len() < 4 {
        while bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        let start = pos;
        while !bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        fields.push(String::from_utf8_lossy(&bytes[start..pos]).to_string());
    }
    pos += 1; // the single whitespace after the scale
    assert_eq!(fields[0], "PF", "colour PFM expected");
    let w: usize = fields[1].parse().unwrap();
    let h: usize = fields[2].parse().unwrap();
    let scale: f32 = fields[3].parse().unwrap();
    let data = &bytes[pos..];
    assert_eq!(data.len(), w * h * 12, "PFM data size");
    let get = |i: usize| {
        let b = [
            data[4 * i],
            data[4 * i + 1],
            data[4 * i + 2],
            data[4 * i + 3],
        ];
        if scale < 0.0 {
            f32::from_le_bytes(b)
        } else {
            f32::from_be_bytes(b)
        }
    };
    Array3::from_shape_fn((h, w, 3), |(y, x, c)| get(((h - 1 - y) * w + x) * 3 + c))
}

/// `pfsinpfm IN | pfstmo_mantiuk06 ARGS | pfsoutpfm -`: display-referred linear RGB.
fn run_pfstools(img: ArrayView3<f32>, args: &[&str], dir: &Path) -> Array3<f32> {
    let input = dir.join("in.pfm");
    write_pfm(&input, img);
    let script = format!(
        "pfsinpfm '{}' | pfstmo_mantiuk06 -q {} | pfsoutpfm -",
        input.display(),
        args.join(" ")
    );
    let mut child = Command::new("sh")
        .args(["-c", &script])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("sh");
    let mut out = Vec::new();
    child.stdout.take().unwrap().read_to_end(&mut out).unwrap();
    assert!(child.wait().unwrap().success(), "{script} failed");
    read_pfm(&out)
}

fn luminance(img: ArrayView3<f32>) -> Array2<f32> {
    img.map_axis(Axis(2), |p| {
        REC709[0] * p[0] + REC709[1] * p[1] + REC709[2] * p[2]
    })
}

fn percentile(v: impl Iterator<Item = f32>, p: f64) -> f32 {
    let mut v: Vec<f32> = v.filter(|x| x.is_finite()).collect();
    v.sort_by(f32::total_cmp);
    v[((p / 100.0) * (v.len() - 1) as f64).round() as usize]
}

/// Per-stage statistics of a display-referred image.
#[derive(Debug)]
struct Stats {
    /// log10 of the 99th over the 1st percentile of display luminance.
    range: f32,
    /// Mean |∇ log10 L| at full resolution.
    detail: f32,
    /// Mean |∇ log10 L| of the 8x8 box-averaged image.
    global: f32,
    /// Mean of (max − min)/max channel over lit pixels.
    saturation: f32,
}

fn box_down(x: &Array2<f32>, f: usize) -> Array2<f32> {
    let (h, w) = (x.dim().0 / f, x.dim().1 / f);
    Array2::from_shape_fn((h, w), |(y, xx)| {
        x.slice(s![y * f..(y + 1) * f, xx * f..(xx + 1) * f])
            .mean()
            .unwrap()
    })
}

fn mean_grad(x: &Array2<f32>) -> f32 {
    let (h, w) = x.dim();
    let mut acc = 0.0f64;
    let mut n = 0usize;
    for y in 0..h - 1 {
        for xx in 0..w - 1 {
            acc +=
                ((x[[y, xx + 1]] - x[[y, xx]]).abs() + (x[[y + 1, xx]] - x[[y, xx]]).abs()) as f64;
            n += 2;
        }
    }
    (acc / n as f64) as f32
}

fn stats(display: ArrayView3<f32>) -> Stats {
    let lum = luminance(display);
    let lo = percentile(lum.iter().copied(), 1.0).max(1e-4);
    let hi = percentile(lum.iter().copied(), 99.0).max(1e-4);
    let floor = 1e-4;
    let log = lum.mapv(|l| l.max(floor).log10());
    let log8 = box_down(&lum, 8).mapv(|l| l.max(floor).log10());
    let mut sat = 0.0f64;
    let mut n = 0usize;
    for p in display.lanes(Axis(2)) {
        let mx = p.iter().copied().fold(0.0f32, f32::max);
        let mn = p.iter().copied().fold(f32::INFINITY, f32::min);
        if mx > 0.02 {
            sat += ((mx - mn) / mx) as f64;
            n += 1;
        }
    }
    Stats {
        range: (hi / lo).log10(),
        detail: mean_grad(&log),
        global: mean_grad(&log8),
        saturation: (sat / n.max(1) as f64) as f32,
    }
}

fn to_f32(img: &Array3<u8>) -> Array3<f32> {
    img.mapv(|v| v as f32)
}

/// The HDR inputs: (name, linear RGB).
fn inputs() -> Vec<(String, Array3<f32>)> {
    let mut out = vec![(
        "builtin:chart-hdr".to_string(),
        Array3::from_shape_fn((254, 496, 3), |(y, x, c)| {
            quantacolor::simulate::chart::chart_value(y as f64, x as f64, 254, 496, true)[c]
        }),
    )];
    let Some(dir) = scenes_dir() else {
        println!("no shared/data/scenes folder: built-in HDR chart only");
        return out;
    };
    for name in [
        "ScanLines_StillLife.exr",
        "MultiResolution_Bonita.exr",
        "ScanLines_Cannon.exr",
    ] {
        let path = dir.join(name);
        match io::read_rgb_image(&path) {
            Ok((img, _)) => out.push((name.to_string(), img)),
            Err(e) => println!("{name}: {e}, skipped"),
        }
        if let Some(rec) = reconstruction(&path) {
            out.push((format!("{name} reconstruction"), rec));
        }
    }
    if let Ok(extra) = std::env::var("MANTIUK_CROSSCHECK_NPY") {
        for p in extra.split(',').filter(|p| !p.is_empty()) {
            out.push((p.to_string(), io::read_npy_3d::<f32>(p).expect("npy")));
        }
    }
    out
}

/// A simulated HDR capture of `scene` (as `bench quality`'s HDR cases) reconstructed with the
/// default pipeline.
fn reconstruction(scene: &Path) -> Option<Array3<f32>> {
    use quantacolor::cfa::{generate, Pattern};
    use quantacolor::pipeline::{reconstruct, ReconstructConfig};
    use quantacolor::progress::Silent;
    use quantacolor::simulate::{simulate_with_cfa, FluxSpec, Scene, SimulationConfig};
    if std::env::var("MANTIUK_CROSSCHECK_RECONSTRUCT").as_deref() == Ok("0") {
        return None;
    }
    let scene = Scene::load(scene).ok()?;
    let config = SimulationConfig {
        height: 254,
        width: 496,
        frames: 2000,
        flux: FluxSpec::Percentile {
            percentile: 50.0,
            peak: 0.1,
        },
        motion: "handheld".parse().ok()?,
        hot_fraction: 0.02,
        seed: 11,
        ..SimulationConfig::default()
    };
    let cfa = generate(&Pattern::Colorspad, 254, 496, 0).ok()?;
    let sim = simulate_with_cfa(&config, &scene, &cfa, &Silent).ok()?;
    let rec = reconstruct(
        &sim.to_capture().ok()?,
        &ReconstructConfig::default(),
        &Silent,
    )
    .ok()?;
    Some(rec.linear)
}

#[test]
#[ignore = "needs pfstools (installs it with apt-get when possible); run with --ignored"]
fn mantiuk06_matches_pfstmo_mantiuk06() {
    if let Err(why) = pfstools() {
        println!("skipped: {why}");
        return;
    }
    let work = Path::new(env!("CARGO_TARGET_TMPDIR")).join("mantiuk-crosscheck");
    std::fs::create_dir_all(&work).unwrap();
    let out_dir = std::env::var("MANTIUK_CROSSCHECK_OUT")
        .ok()
        .map(PathBuf::from);
    let ours_op = ToneMap::Mantiuk06(Mantiuk06Config::default());
    let (mut worst_psnr, mut worst_ssim) = (f64::INFINITY, f64::INFINITY);
    println!(
        "{:<40} {:>7} {:>6} | {:>28} | {:>28}",
        "input", "PSNR", "SSIM", "ours range/detail/global/sat", "pfs range/detail/global/sat"
    );
    for (name, img) in inputs() {
        let clean = img.mapv(|v| if v.is_finite() { v.max(0.0) } else { 0.0 });
        let ours = tone_map(clean.view(), None, &ours_op).expect("ours");
        let theirs = run_pfstools(clean.view(), &[], &work).mapv(|v| v.clamp(0.0, 1.0));
        let (o8, t8) = (quantise8(ours.view()), quantise8(theirs.view()));
        let p = psnr(to_f32(&o8).view(), to_f32(&t8).view(), 255.0).unwrap();
        let q = ssim_color(to_f32(&o8).view(), to_f32(&t8).view(), 255.0).unwrap();
        let (so, st) = (stats(ours.view()), stats(theirs.view()));
        println!(
            "{name:<40} {p:>7.2} {q:>6.3} | {:>6.2} {:>6.3} {:>6.3} {:>6.3} | {:>6.2} {:>6.3} {:>6.3} {:>6.3}",
            so.range, so.detail, so.global, so.saturation, st.range, st.detail, st.global, st.saturation
        );
        worst_psnr = worst_psnr.min(p);
        worst_ssim = worst_ssim.min(q);
        if let Some(dir) = &out_dir {
            std::fs::create_dir_all(dir).unwrap();
            let global = tone_map(clean.view(), None, &ToneMap::default()).unwrap();
            let g8 = quantise8(global.view());
            let sheet = hstack(&[o8.view(), t8.view(), g8.view()], 8, 255u8);
            let file = name.replace([':', ' ', '.'], "_") + ".png";
            io::write_png_rgb8(dir.join(file), &sheet).unwrap();
        }
    }
    let _ = std::io::stdout().flush();
    println!("worst PSNR {worst_psnr:.2} dB, worst SSIM {worst_ssim:.3}");
    // The agreement `display::mantiuk`'s module doc states: 20–32 dB PSNR, SSIM 0.79–0.98.
    assert!(
        worst_psnr >= 20.0,
        "worst PSNR against pfstmo_mantiuk06 {worst_psnr:.2} dB, stated at least 20 dB"
    );
    assert!(
        worst_ssim >= 0.79,
        "worst SSIM against pfstmo_mantiuk06 {worst_ssim:.3}, stated at least 0.79"
    );
}

/// Black-box measurement of the reference's display mapping (step 6 of `display::mantiuk`):
/// with contrast factor 1 (no compression) a three-level image shows where the 0.1st and 99.9th
/// percentiles of log luminance land: 2.3 decades apart, the top at 1, nothing clamped below.
#[test]
#[ignore = "needs pfstools (installs it with apt-get when possible); run with --ignored"]
fn reference_display_mapping_spans_2_3_decades_between_percentiles() {
    if let Err(why) = pfstools() {
        println!("skipped: {why}");
        return;
    }
    let work = Path::new(env!("CARGO_TARGET_TMPDIR")).join("mantiuk-display-mapping");
    std::fs::create_dir_all(&work).unwrap();
    let (h, w) = (100usize, 200usize);
    for (q, outlier, inside) in [
        (0.0005f32, 1000.0f32, false),
        (0.002, 1000.0, true),
        (0.0005, 0.001, false),
        (0.002, 0.001, true),
    ] {
        // A fraction q of outlier pixels, the rest half 1, half 10 (log10: 0 and 1).
        let nb = (q * (h * w) as f32).round() as usize;
        let img = Array3::from_shape_fn((h, w, 3), |(y, x, _)| {
            if y * w + x < nb {
                outlier
            } else if x < w / 2 {
                1.0
            } else {
                10.0
            }
        });
        let lum = luminance(run_pfstools(img.view(), &["-f", "1"], &work).view());
        let (lo_px, hi_px) = (lum[[h / 2, 10]], lum[[h / 2, w - 10]]);
        // Expected: log10 L' = 2.3 (x − x_hi) / (x_hi − x_lo) with the percentile range
        // including the outliers only when they exceed 0.1 % of the pixels.
        let (x_lo, x_hi) = match (inside, outlier > 1.0) {
            (false, _) => (0.0, 1.0),
            (true, true) => (0.0, 3.0),
            (true, false) => (-3.0, 1.0),
        };
        let expect = |x: f32| 10f32.powf(2.3 * (x - x_hi) / (x_hi - x_lo));
        println!("q {q} outlier {outlier}: 1 -> {lo_px:.4} (expect {:.4}), 10 -> {hi_px:.4} (expect {:.4})", expect(0.0), expect(1.0));
        assert!((lo_px / expect(0.0)).log10().abs() < 0.02);
        assert!((hi_px / expect(1.0)).log10().abs() < 0.02);
    }
}

/// Per-scale behaviour of the contrast mapping, printed for both operators: a step of `D`
/// decades with a fine grating of `g` decades on it. After the display mapping, the ratio of the
/// grating to the step shows how much more large contrasts are compressed than small ones.
#[test]
#[ignore = "needs pfstools (installs it with apt-get when possible); run with --ignored"]
fn contrast_mapping_of_steps_and_gratings() {
    if let Err(why) = pfstools() {
        println!("skipped: {why}");
        return;
    }
    let work = Path::new(env!("CARGO_TARGET_TMPDIR")).join("mantiuk-gratings");
    std::fs::create_dir_all(&work).unwrap();
    let (h, w) = (128usize, 256usize);
    for big in [0.5f32, 1.0, 2.0, 4.0] {
        for g in [0.01f32, 0.05, 0.2] {
            let img = Array3::from_shape_fn((h, w, 3), |(y, x, _)| {
                let step = if x < w / 2 { 0.0 } else { big };
                let grating = if (y / 2) % 2 == 0 { g / 2.0 } else { -g / 2.0 };
                10f32.powf(step + grating)
            });
            let theirs = run_pfstools(img.view(), &[], &work);
            let ours = tone_map(
                img.view(),
                None,
                &ToneMap::Mantiuk06(Mantiuk06Config::default()),
            )
            .unwrap();
            let measure = |o: &Array3<f32>| {
                let l = luminance(o.view()).mapv(|v| v.max(1e-6).log10());
                let left = l.slice(s![.., w / 8..w * 3 / 8]);
                let right = l.slice(s![.., w * 5 / 8..w * 7 / 8]);
                let step = right.mean().unwrap() - left.mean().unwrap();
                let mut acc = 0.0;
                let mut n = 0;
                for y in 0..h - 2 {
                    for x in w / 8..w * 3 / 8 {
                        acc += (l[[y, x]] - l[[y + 2, x]]).abs();
                        n += 1;
                    }
                }
                (step, acc / n as f32)
            };
            let (so, go) = measure(&ours);
            let (st, gt) = measure(&theirs);
            println!(
                "step {big} grating {g}: ours step {so:.3} grating {go:.4} (ratio {:.4}) | pfstmo step {st:.3} grating {gt:.4} (ratio {:.4})",
                go / so,
                gt / st
            );
        }
    }
}
