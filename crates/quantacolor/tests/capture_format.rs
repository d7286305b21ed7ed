//! Capture directories: write/open round trips, one test per malformed input, atomic
//! replacement, and the real colour-SPAD CFA image.

#[path = "common/skip.rs"]
mod skip;

use ndarray::{s, Array2, Array3, Axis};
use ndarray_npy::write_npy;
use quantacolor::capture::frames::{pack_bits, FrameLayout};
use quantacolor::capture::{io, write_capture, Capture, CaptureMeta, CaptureParts, FrameData};
use quantacolor::cfa::{Cfa, Channel};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::fs;
use std::path::{Path, PathBuf};

const T: usize = 9;
const H: usize = 5;
const W: usize = 13; // not a multiple of 8: the last packed byte has padding bits

fn random_bits(t: usize, h: usize, w: usize, seed: u64) -> Array3<u8> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    Array3::from_shape_fn((t, h, w), |_| rng.gen_bool(0.4) as u8)
}

/// A CFA using all four codes.
fn sample_cfa(h: usize, w: usize) -> Cfa {
    Cfa::new(Array2::from_shape_fn((h, w), |(y, x)| {
        ((y * 7 + x * 3) % 4) as u8
    }))
    .unwrap()
}

fn sample_meta() -> CaptureMeta {
    CaptureMeta {
        exposure_s: 1e-5,
        dark_count_rate_hz: 7.5,
        w_weights: [0.5, 1.0, 0.25],
        hot_pixels: None,
        reference_frame: Some(3),
        ..CaptureMeta::new(1e-5)
    }
}

/// Writes a small valid capture at `dir` and returns its unpacked bits.
fn write_valid(dir: &Path) -> Array3<u8> {
    let bits = random_bits(T, H, W, 1);
    let packed = pack_bits(&bits);
    let cfa = sample_cfa(H, W);
    let meta = sample_meta();
    write_capture(
        dir,
        &CaptureParts {
            frames: FrameData::Packed(&packed),
            width: W,
            cfa: &cfa,
            meta: &meta,
            hot_pixels: None,
            ground_truth: None,
            extra_files: vec![],
            extra_toml: None,
        },
    )
    .unwrap();
    bits
}

fn valid_capture() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("cap");
    write_valid(&dir);
    (tmp, dir)
}

/// Opening `dir` fails with a message naming `file` and containing every phrase.
fn expect_error(dir: &Path, file: &str, phrases: &[&str]) {
    let err = Capture::open(dir).expect_err("malformed capture must not open");
    let msg = err.to_string();
    eprintln!("{msg}");
    assert!(msg.contains(file), "error {msg:?} does not name {file}");
    for p in phrases {
        assert!(msg.contains(p), "error {msg:?} does not mention {p:?}");
    }
}

fn set_toml(dir: &Path, text: &str) {
    fs::write(dir.join("capture.toml"), text).unwrap();
}

fn leftovers(parent: &Path) -> Vec<String> {
    fs::read_dir(parent)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".tmp"))
        .collect()
}

#[test]
fn packed_capture_round_trips_with_every_optional_part() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("nested").join("cap");
    let bits = random_bits(T, H, W, 2);
    let packed = pack_bits(&bits);
    let cfa = sample_cfa(H, W);
    let meta = sample_meta();
    let hot = Array2::from_shape_fn((H, W), |(y, x)| (y + x) % 5 == 0);
    let truth = Array3::from_shape_fn((H, W, 3), |(y, x, c)| (y * 100 + x * 10 + c) as f32 * 0.01);
    let mut extra_toml = toml::Table::new();
    extra_toml.insert(
        "simulation".into(),
        toml::Value::Table(toml::toml! { seed = 42 scene = "kodim01" }),
    );
    write_capture(
        &dir,
        &CaptureParts {
            frames: FrameData::Packed(&packed),
            width: W,
            cfa: &cfa,
            meta: &meta,
            hot_pixels: Some(&hot),
            ground_truth: Some(&truth),
            extra_files: vec![("motion_truth.npy".into(), b"motion bytes".to_vec())],
            extra_toml: Some(extra_toml),
        },
    )
    .unwrap();

    let cap = Capture::open(&dir).unwrap();
    assert_eq!(cap.frames.frame_count(), T);
    assert_eq!((cap.frames.height(), cap.frames.width()), (H, W));
    assert_eq!(cap.frames.layout(), FrameLayout::Packed);
    let expected_sums = bits.map(|&b| b as u32).sum_axis(Axis(0));
    assert_eq!(cap.frames.sum_range(0..T), expected_sums);
    assert_eq!(cap.frames.frame(4), bits.index_axis(Axis(0), 4));
    assert_eq!(cap.cfa, cfa);
    let mut expected_meta = meta.clone();
    expected_meta.hot_pixels = Some("hot_pixels.npy".into());
    assert_eq!(cap.meta, expected_meta);
    assert_eq!(cap.hot_pixels.as_ref(), Some(&hot));
    assert_eq!(cap.ground_truth().unwrap(), Some(truth));
    assert_eq!(cap.reference_frame(), 3);
    assert_eq!(
        fs::read(dir.join("motion_truth.npy")).unwrap(),
        b"motion bytes"
    );
    let text = fs::read_to_string(dir.join("capture.toml")).unwrap();
    let table: toml::Table = text.parse().unwrap();
    assert_eq!(table["simulation"]["seed"].as_integer(), Some(42));
    assert!((cap.meta.dark_counts_per_frame() - 7.5e-5).abs() < 1e-15);
    assert!(leftovers(dir.parent().unwrap()).is_empty());
}

#[test]
fn defaults_apply_when_keys_are_absent() {
    let (_tmp, dir) = valid_capture();
    set_toml(&dir, "exposure_s = 2\n");
    let cap = Capture::open(&dir).unwrap();
    assert_eq!(cap.meta, CaptureMeta::new(2.0));
    assert_eq!(cap.reference_frame(), T / 2);
    assert!(cap.hot_pixels.is_none());
    assert_eq!(cap.ground_truth().unwrap(), None);
}

#[test]
fn unpacked_u8_and_bool_frames_open_with_the_same_sums() {
    let (_tmp, dir) = valid_capture();
    let bits = random_bits(T, H, W, 3);
    let expected = bits.map(|&b| b as u32).sum_axis(Axis(0));
    write_npy(dir.join("frames.npy"), &bits).unwrap();
    let cap = Capture::open(&dir).unwrap();
    assert_eq!(cap.frames.layout(), FrameLayout::Unpacked);
    assert_eq!(cap.frames.sum_range(0..T), expected);

    write_npy(dir.join("frames.npy"), &bits.map(|&b| b != 0)).unwrap();
    let cap = Capture::open(&dir).unwrap();
    assert_eq!(cap.frames.layout(), FrameLayout::Unpacked);
    assert_eq!(
        cap.frames.sum_range(2..7),
        bits.slice(s![2..7, .., ..])
            .map(|&b| b as u32)
            .sum_axis(Axis(0))
    );
}

// ---- malformed inputs: each names the file and the problem ----

#[test]
fn missing_directory() {
    let tmp = tempfile::tempdir().unwrap();
    expect_error(&tmp.path().join("nope"), "nope", &["No such file"]);
}

#[test]
fn path_is_a_file_not_a_directory() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("plain.txt");
    fs::write(&file, "x").unwrap();
    expect_error(&file, "plain.txt", &["directory"]);
}

#[test]
fn missing_frames() {
    let (_tmp, dir) = valid_capture();
    fs::remove_file(dir.join("frames.npy")).unwrap();
    expect_error(&dir, "frames.npy", &["No such file"]);
}

#[test]
fn missing_toml() {
    let (_tmp, dir) = valid_capture();
    fs::remove_file(dir.join("capture.toml")).unwrap();
    expect_error(&dir, "capture.toml", &["No such file"]);
}

#[test]
fn missing_cfa() {
    let (_tmp, dir) = valid_capture();
    fs::remove_file(dir.join("cfa.npy")).unwrap();
    expect_error(&dir, "cfa.npy", &["No such file"]);
}

#[test]
fn frames_wrong_dtype() {
    let (_tmp, dir) = valid_capture();
    write_npy(dir.join("frames.npy"), &Array3::<f32>::zeros((T, H, W))).unwrap();
    expect_error(&dir, "frames.npy", &["dtype"]);
}

#[test]
fn frames_wrong_rank() {
    let (_tmp, dir) = valid_capture();
    write_npy(dir.join("frames.npy"), &Array2::<u8>::zeros((H, 2))).unwrap();
    expect_error(&dir, "frames.npy", &["3-D"]);
}

#[test]
fn frames_zero_count() {
    let (_tmp, dir) = valid_capture();
    write_npy(dir.join("frames.npy"), &Array3::<u8>::zeros((0, H, 2))).unwrap();
    expect_error(&dir, "frames.npy", &["T = 0"]);
}

#[test]
fn frames_truncated() {
    let (_tmp, dir) = valid_capture();
    let path = dir.join("frames.npy");
    let bytes = fs::read(&path).unwrap();
    fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
    expect_error(&dir, "frames.npy", &["truncated"]);
}

#[test]
fn frames_corrupt() {
    let (_tmp, dir) = valid_capture();
    fs::write(dir.join("frames.npy"), b"this is not numpy data at all").unwrap();
    expect_error(&dir, "frames.npy", &["not a .npy"]);
}

#[test]
fn frames_height_differs_from_cfa() {
    let (_tmp, dir) = valid_capture();
    write_npy(dir.join("cfa.npy"), sample_cfa(H + 1, W).codes()).unwrap();
    expect_error(&dir, "frames.npy", &["height"]);
}

#[test]
fn frames_width_differs_from_cfa() {
    let (_tmp, dir) = valid_capture();
    write_npy(dir.join("cfa.npy"), sample_cfa(H, W + 8).codes()).unwrap();
    expect_error(&dir, "frames.npy", &["CFA width"]);
}

#[test]
fn cfa_code_out_of_range() {
    let (_tmp, dir) = valid_capture();
    let mut codes = sample_cfa(H, W).codes().clone();
    codes[[2, 4]] = 7;
    write_npy(dir.join("cfa.npy"), &codes).unwrap();
    expect_error(&dir, "cfa.npy", &["code 7", "y=2", "x=4"]);
}

#[test]
fn cfa_wrong_dtype() {
    let (_tmp, dir) = valid_capture();
    write_npy(dir.join("cfa.npy"), &Array2::<u16>::zeros((H, W))).unwrap();
    expect_error(&dir, "cfa.npy", &["dtype", "uint8"]);
}

#[test]
fn cfa_wrong_rank() {
    let (_tmp, dir) = valid_capture();
    write_npy(dir.join("cfa.npy"), &Array3::<u8>::zeros((H, W, 1))).unwrap();
    expect_error(&dir, "cfa.npy", &["2-D"]);
}

#[test]
fn cfa_truncated() {
    let (_tmp, dir) = valid_capture();
    let path = dir.join("cfa.npy");
    let bytes = fs::read(&path).unwrap();
    fs::write(&path, &bytes[..bytes.len() - 1]).unwrap();
    expect_error(&dir, "cfa.npy", &["truncated"]);
}

#[test]
fn cfa_png_corrupt() {
    let (_tmp, dir) = valid_capture();
    fs::remove_file(dir.join("cfa.npy")).unwrap();
    fs::write(dir.join("cfa.png"), b"\x89PNG\r\n\x1a\n garbage").unwrap();
    expect_error(&dir, "cfa.png", &["corrupt"]);
}

#[test]
fn cfa_png_with_a_colour_that_is_no_filter() {
    let (_tmp, dir) = valid_capture();
    fs::remove_file(dir.join("cfa.npy")).unwrap();
    let mut img = Array3::<u8>::from_elem((H, W, 3), 255);
    img[[1, 6, 0]] = 128;
    io::write_png_rgb8(dir.join("cfa.png"), &img).unwrap();
    expect_error(&dir, "cfa.png", &["y=1", "x=6", "(128, 255, 255)"]);
}

#[test]
fn cfa_png_is_used_when_npy_is_absent() {
    let (_tmp, dir) = valid_capture();
    let cfa = sample_cfa(H, W);
    fs::remove_file(dir.join("cfa.npy")).unwrap();
    let colours = [[255u8, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]];
    let img = Array3::from_shape_fn((H, W, 3), |(y, x, c)| {
        colours[cfa.codes()[[y, x]] as usize][c]
    });
    io::write_png_rgb8(dir.join("cfa.png"), &img).unwrap();
    assert_eq!(Capture::open(&dir).unwrap().cfa, cfa);
}

#[test]
fn toml_syntax_error() {
    let (_tmp, dir) = valid_capture();
    set_toml(&dir, "exposure_s = = 1\n");
    expect_error(&dir, "capture.toml", &["invalid TOML"]);
}

#[test]
fn toml_missing_exposure() {
    let (_tmp, dir) = valid_capture();
    set_toml(&dir, "dark_count_rate_hz = 1.0\n");
    expect_error(&dir, "capture.toml", &["missing", "exposure_s"]);
}

#[test]
fn toml_wrong_types() {
    let (_tmp, dir) = valid_capture();
    for (text, key, want) in [
        ("exposure_s = \"fast\"", "exposure_s", "number"),
        (
            "exposure_s = 1\ndark_count_rate_hz = true",
            "dark_count_rate_hz",
            "number",
        ),
        ("exposure_s = 1\nw_weights = 1.0", "w_weights", "array"),
        (
            "exposure_s = 1\nw_weights = [1, \"g\", 1]",
            "w_weights",
            "a string",
        ),
        ("exposure_s = 1\nhot_pixels = 3", "hot_pixels", "string"),
        (
            "exposure_s = 1\nreference_frame = 1.5",
            "reference_frame",
            "integer",
        ),
    ] {
        set_toml(&dir, text);
        expect_error(&dir, "capture.toml", &[key, want]);
    }
}

#[test]
fn toml_invalid_values() {
    let (_tmp, dir) = valid_capture();
    for (text, key) in [
        ("exposure_s = 0", "exposure_s"),
        ("exposure_s = -1e-5", "exposure_s"),
        ("exposure_s = nan", "exposure_s"),
        ("exposure_s = inf", "exposure_s"),
        (
            "exposure_s = 1\ndark_count_rate_hz = -3",
            "dark_count_rate_hz",
        ),
        ("exposure_s = 1\nw_weights = [0, 0, 0]", "w_weights"),
        ("exposure_s = 1\nw_weights = [1, -1, 1]", "w_weights"),
        ("exposure_s = 1\nw_weights = [1, 1]", "w_weights"),
        ("exposure_s = 1\nreference_frame = -1", "reference_frame"),
        ("exposure_s = 1\nhot_pixels = \"\"", "hot_pixels"),
    ] {
        set_toml(&dir, text);
        expect_error(&dir, "capture.toml", &[key]);
    }
}

#[test]
fn toml_reference_frame_past_the_end() {
    let (_tmp, dir) = valid_capture();
    set_toml(&dir, &format!("exposure_s = 1\nreference_frame = {T}\n"));
    expect_error(&dir, "capture.toml", &["reference_frame", "< T = 9"]);
    set_toml(
        &dir,
        &format!("exposure_s = 1\nreference_frame = {}\n", T - 1),
    );
    assert_eq!(Capture::open(&dir).unwrap().reference_frame(), T - 1);
}

#[test]
fn toml_unknown_key_is_rejected_but_tables_are_tolerated() {
    let (_tmp, dir) = valid_capture();
    set_toml(&dir, "exposre_s = 1e-5\nexposure_s = 1e-5\n");
    expect_error(&dir, "capture.toml", &["unknown key `exposre_s`"]);
    set_toml(
        &dir,
        "exposure_s = 1e-5\n[simulation]\nseed = 1\nmotion = { kind = \"pan\" }\n[[runs]]\nid = 1\n",
    );
    assert_eq!(Capture::open(&dir).unwrap().meta, CaptureMeta::new(1e-5));
}

#[test]
fn hot_pixel_mask_problems() {
    let (_tmp, dir) = valid_capture();
    set_toml(&dir, "exposure_s = 1\nhot_pixels = \"hot.npy\"\n");
    expect_error(&dir, "hot.npy", &["No such file"]);
    write_npy(
        dir.join("hot.npy"),
        &Array2::<bool>::from_elem((H, W + 1), false),
    )
    .unwrap();
    expect_error(&dir, "hot.npy", &["shape", "(5, 14)"]);
    write_npy(dir.join("hot.npy"), &Array2::<u8>::zeros((H, W))).unwrap();
    expect_error(&dir, "hot.npy", &["dtype", "bool"]);
    let mut mask = Array2::<bool>::from_elem((H, W), false);
    mask[[0, 1]] = true;
    write_npy(dir.join("hot.npy"), &mask).unwrap();
    assert_eq!(Capture::open(&dir).unwrap().hot_pixels, Some(mask));
}

#[test]
fn random_and_mutated_files_never_panic() {
    let (_tmp, dir) = valid_capture();
    let originals: Vec<(String, Vec<u8>)> = ["frames.npy", "cfa.npy", "capture.toml"]
        .iter()
        .map(|n| (n.to_string(), fs::read(dir.join(n)).unwrap()))
        .collect();
    let mut rng = ChaCha8Rng::seed_from_u64(99);
    let mut opened = 0;
    for round in 0..300 {
        let (name, original) = &originals[round % originals.len()];
        let bytes = if round % 2 == 0 {
            // Pure noise of a random length.
            let len = rng.gen_range(0..400);
            (0..len).map(|_| rng.gen()).collect::<Vec<u8>>()
        } else {
            // A valid file with a few bytes of its first 128 changed, or cut short.
            let mut b = original.clone();
            for _ in 0..rng.gen_range(1..4) {
                let i = rng.gen_range(0..b.len().min(128));
                b[i] = rng.gen();
            }
            if rng.gen_bool(0.3) {
                b.truncate(rng.gen_range(0..b.len()));
            }
            b
        };
        fs::write(dir.join(name), &bytes).unwrap();
        if let Ok(cap) = Capture::open(&dir) {
            opened += 1;
            let t = cap.frames.frame_count();
            let _ = cap.frames.sum_range(0..t);
        }
        fs::write(dir.join(name), original).unwrap();
    }
    eprintln!("{opened} of 300 corrupted captures opened");
    // Most mutations must be caught; a few (e.g. in header padding) are harmless.
    assert!(opened < 150, "{opened} of 300 corrupted captures opened");
    // png noise too
    fs::remove_file(dir.join("cfa.npy")).unwrap();
    for _ in 0..50 {
        let len = rng.gen_range(0..300);
        let mut bytes: Vec<u8> = b"\x89PNG\r\n\x1a\n".to_vec();
        bytes.extend((0..len).map(|_| rng.gen::<u8>()));
        fs::write(dir.join("cfa.png"), &bytes).unwrap();
        assert!(Capture::open(&dir).is_err());
    }
}

// ---- atomic writes ----

#[test]
fn rewriting_replaces_the_capture_and_leaves_no_temporaries() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("cap");
    write_valid(&dir);
    let bits = random_bits(4, 3, 20, 5);
    let packed = pack_bits(&bits);
    let cfa = Cfa::uniform(3, 20, Channel::W);
    let meta = CaptureMeta::new(1e-4);
    write_capture(
        &dir,
        &CaptureParts {
            frames: FrameData::Packed(&packed),
            width: 20,
            cfa: &cfa,
            meta: &meta,
            hot_pixels: None,
            ground_truth: None,
            extra_files: vec![],
            extra_toml: None,
        },
    )
    .unwrap();
    let cap = Capture::open(&dir).unwrap();
    assert_eq!((cap.frames.frame_count(), cap.frames.width()), (4, 20));
    assert_eq!(
        cap.frames.sum_range(0..4),
        bits.map(|&b| b as u32).sum_axis(Axis(0))
    );
    assert_eq!(leftovers(tmp.path()), Vec::<String>::new());
}

#[test]
fn failed_write_leaves_the_existing_capture_untouched() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("cap");
    let old_bits = write_valid(&dir);
    let before: Vec<Vec<u8>> = ["frames.npy", "cfa.npy", "capture.toml"]
        .iter()
        .map(|n| fs::read(dir.join(n)).unwrap())
        .collect();

    let packed = pack_bits(&random_bits(2, H, W, 8));
    let cfa = sample_cfa(H, W);
    let meta = CaptureMeta::new(1e-5);
    // Fails half-way: frames and CFA are already written when the over-long file name
    // (beyond the 255-byte limit of common file systems) cannot be created.
    let failing = CaptureParts {
        frames: FrameData::Packed(&packed),
        width: W,
        cfa: &cfa,
        meta: &meta,
        hot_pixels: None,
        ground_truth: None,
        extra_files: vec![("x".repeat(300), vec![1, 2, 3])],
        extra_toml: None,
    };
    let err = write_capture(&dir, &failing).unwrap_err();
    assert!(err.to_string().contains("cap"), "{err}");
    // Fails validation before touching the disk.
    let wrong_cfa = sample_cfa(H + 1, W);
    let invalid = CaptureParts {
        cfa: &wrong_cfa,
        extra_files: vec![],
        ..failing.clone()
    };
    assert!(write_capture(&dir, &invalid).is_err());

    let after: Vec<Vec<u8>> = ["frames.npy", "cfa.npy", "capture.toml"]
        .iter()
        .map(|n| fs::read(dir.join(n)).unwrap())
        .collect();
    assert_eq!(before, after);
    let cap = Capture::open(&dir).unwrap();
    assert_eq!(
        cap.frames.sum_range(0..T),
        old_bits.map(|&b| b as u32).sum_axis(Axis(0))
    );
    assert_eq!(leftovers(tmp.path()), Vec::<String>::new());
    // A failed first write leaves no directory at all.
    let fresh = tmp.path().join("fresh");
    assert!(write_capture(&fresh, &failing).is_err());
    assert!(!fresh.exists());
    assert_eq!(leftovers(tmp.path()), Vec::<String>::new());
}

#[test]
fn refuses_to_replace_a_directory_that_is_not_a_capture() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("documents");
    fs::create_dir(&dir).unwrap();
    fs::write(dir.join("thesis.tex"), "precious").unwrap();
    let packed = pack_bits(&random_bits(1, H, W, 1));
    let cfa = sample_cfa(H, W);
    let meta = CaptureMeta::new(1e-5);
    let err = write_capture(
        &dir,
        &CaptureParts {
            frames: FrameData::Packed(&packed),
            width: W,
            cfa: &cfa,
            meta: &meta,
            hot_pixels: None,
            ground_truth: None,
            extra_files: vec![],
            extra_toml: None,
        },
    )
    .unwrap_err();
    assert!(err.to_string().contains("not a capture directory"), "{err}");
    assert_eq!(
        fs::read_to_string(dir.join("thesis.tex")).unwrap(),
        "precious"
    );
}

#[test]
fn writer_rejects_inconsistent_parts() {
    let tmp = tempfile::tempdir().unwrap();
    let packed = pack_bits(&random_bits(2, H, W, 1));
    let cfa = sample_cfa(H, W);
    let meta = CaptureMeta::new(1e-5);
    let base = CaptureParts {
        frames: FrameData::Packed(&packed),
        width: W,
        cfa: &cfa,
        meta: &meta,
        hot_pixels: None,
        ground_truth: None,
        extra_files: vec![],
        extra_toml: None,
    };
    let bad_meta = CaptureMeta {
        reference_frame: Some(2),
        ..meta.clone()
    };
    let nan_meta = CaptureMeta::new(f64::NAN);
    let wrong_hot = Array2::from_elem((H, W + 1), false);
    let wrong_truth = Array3::<f32>::zeros((H, W, 4));
    let mut not_a_table = toml::Table::new();
    not_a_table.insert("seed".into(), toml::Value::Integer(1));
    let cases: Vec<(CaptureParts, &str)> = vec![
        (
            CaptureParts {
                width: W + 1,
                ..base.clone()
            },
            "CFA",
        ),
        (
            CaptureParts {
                meta: &bad_meta,
                ..base.clone()
            },
            "reference_frame",
        ),
        (
            CaptureParts {
                meta: &nan_meta,
                ..base.clone()
            },
            "exposure_s",
        ),
        (
            CaptureParts {
                hot_pixels: Some(&wrong_hot),
                ..base.clone()
            },
            "hot-pixel",
        ),
        (
            CaptureParts {
                ground_truth: Some(&wrong_truth),
                ..base.clone()
            },
            "ground truth",
        ),
        (
            CaptureParts {
                extra_files: vec![("frames.npy".into(), vec![])],
                ..base.clone()
            },
            "frames.npy",
        ),
        (
            CaptureParts {
                extra_files: vec![("../escape".into(), vec![])],
                ..base.clone()
            },
            "escape",
        ),
        (
            CaptureParts {
                extra_toml: Some(not_a_table),
                ..base.clone()
            },
            "seed",
        ),
    ];
    for (i, (parts, phrase)) in cases.iter().enumerate() {
        let dir = tmp.path().join(format!("c{i}"));
        let err = write_capture(&dir, parts).unwrap_err().to_string();
        assert!(err.contains(phrase), "case {i}: {err:?} lacks {phrase:?}");
        assert!(!dir.exists());
    }
    assert_eq!(leftovers(tmp.path()), Vec::<String>::new());
}

// ---- the real colour-SPAD CFA ----

fn colorspad_png() -> Option<PathBuf> {
    // The shared data folder sits beside the project root (or beside a parent of a worktree).
    let rel = "shared/data/colorspad/rgbw_oh_bn_color_ss2_corrected.png";
    let found = Path::new(env!("CARGO_MANIFEST_DIR"))
        .ancestors()
        .map(|a| a.join(rel))
        .find(|p| p.exists());
    if found.is_none() {
        skip::skip(rel, "not found beside any parent of the project");
    }
    found
}

#[test]
fn colorspad_png_loads_as_a_75_percent_w_cfa() {
    let Some(png) = colorspad_png() else { return };
    let codes = io::read_cfa_png(&png).unwrap();
    assert_eq!(codes.dim(), (256, 512));
    let cfa = Cfa::new(codes.clone()).unwrap();
    let f = cfa.fractions();
    assert!((f[3] - 0.758).abs() < 0.001, "W fraction {}", f[3]);
    for (c, fc) in f.iter().take(3).enumerate() {
        assert!((fc - 0.0807).abs() < 0.001, "channel {c} fraction {fc}");
    }
    // Colour filters sit only at (odd row, odd column) inside columns 0..496.
    for ((y, x), &c) in codes.indexed_iter() {
        if c != 3 {
            assert!(
                y % 2 == 1 && x % 2 == 1 && x < 496,
                "colour filter at ({y}, {x})"
            );
        }
    }

    // ... and serves as the CFA of a capture.
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("spad");
    let bits = random_bits(2, 256, 512, 4);
    let meta = CaptureMeta::new(1e-5);
    write_capture(
        &dir,
        &CaptureParts {
            frames: FrameData::Packed(&pack_bits(&bits)),
            width: 512,
            cfa: &cfa,
            meta: &meta,
            hot_pixels: None,
            ground_truth: None,
            extra_files: vec![],
            extra_toml: None,
        },
    )
    .unwrap();
    fs::remove_file(dir.join("cfa.npy")).unwrap();
    fs::copy(&png, dir.join("cfa.png")).unwrap();
    let cap = Capture::open(&dir).unwrap();
    assert_eq!(cap.cfa, cfa);
}
