//! Real-sensor readers (issue 12): byte-exact fixtures written from known bits, converted and
//! read back bit for bit (SwissSPAD2 half and full array, colour SwissSPAD2 geometry,
//! SPAD512S variants, photon-cube .npy), natural order across nested directories, bad files
//! (clear error naming the file, nothing left behind), and fuzzing with random and mutated
//! inputs (no panic).

use ndarray::{Array2, Array3};
use proptest::prelude::*;
use quantacolor::capture::npy::encode_header;
use quantacolor::capture::readers::{
    open_npy, open_source, RawFormat, SourceSpec, Spad512sOptions, Spad512sOrientation,
};
use quantacolor::capture::{Capture, FrameWindow};
use quantacolor::cfa::{colorspad_cfa, colorspad_hot_pixel_mask, Cfa, Channel};
use quantacolor::convert::{convert_input, ConvertRequest, HotPixelChoice};
use quantacolor::progress::Silent;
use std::path::{Path, PathBuf};

/// The known bit of pixel (y, x) of frame t in fixture `seed`: a hash, so every frame differs.
fn bit(seed: u64, t: usize, y: usize, x: usize) -> bool {
    hash(seed, t, y, x) & 3 == 0
}

/// A uniform number in [0, 1) from the same hash.
fn uniform(seed: u64, t: usize, y: usize, x: usize) -> f64 {
    (hash(seed, t, y, x) >> 11) as f64 / (1u64 << 53) as f64
}

fn hash(seed: u64, t: usize, y: usize, x: usize) -> u64 {
    let mut z = seed ^ ((t as u64) << 40) ^ ((y as u64) << 20) ^ x as u64;
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A SwissSPAD2 half-array file: frames t0.. of 256x512, 64 bytes a row, LSB first.
fn swissspad2_half_file(seed: u64, t0: usize, frames: usize) -> Vec<u8> {
    let mut out = vec![0u8; frames * 256 * 64];
    for t in 0..frames {
        for y in 0..256 {
            for x in 0..512 {
                if bit(seed, t0 + t, y, x) {
                    out[(t * 256 + y) * 64 + x / 8] |= 1 << (x % 8);
                }
            }
        }
    }
    out
}

/// A SwissSPAD2 full-array file: 256 frames of 512x512; stored row r holds zones
/// T0 B0 T1 B1 T2 B2 T3 B3 (16 bytes each), Tk = top row r, Bk = row 511 - r, LSB first.
fn swissspad2_full_file(seed: u64, frames: usize) -> Vec<u8> {
    let mut out = vec![0u8; frames * 512 * 64];
    for t in 0..frames {
        for y in 0..512 {
            let (stored_row, bottom) = if y < 256 { (y, 0) } else { (511 - y, 1) };
            for x in 0..512 {
                if bit(seed, t, y, x) {
                    let zone = 2 * (x / 128) + bottom;
                    let byte = t * 32768 + stored_row * 128 + zone * 16 + (x % 128) / 8;
                    out[byte] |= 1 << (x % 8);
                }
            }
        }
    }
    out
}

/// A SPAD512S file: `frames` stored frames of 512x512 MSB first, then `trailer` bytes.
fn spad512s_file(seed: u64, t0: usize, frames: usize, trailer: usize) -> Vec<u8> {
    let mut out = vec![0u8; frames * 32768];
    for t in 0..frames {
        for y in 0..512 {
            for x in 0..512 {
                if bit(seed, t0 + t, y, x) {
                    out[(t * 512 + y) * 64 + x / 8] |= 0x80 >> (x % 8);
                }
            }
        }
    }
    out.extend(std::iter::repeat_n(0xA5, trailer));
    out
}

/// Which stored pixel an output pixel (y, x) comes from.
type PixelMap = fn(usize, usize) -> (usize, usize);
/// Files of a fixture: (relative path, bytes).
type Files<'a> = Vec<(&'a str, Vec<u8>)>;

fn write(path: &Path, bytes: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, bytes).unwrap();
}

fn request(format: RawFormat) -> ConvertRequest {
    ConvertRequest {
        source: SourceSpec {
            format: Some(format),
            ..SourceSpec::default()
        },
        hot_pixels: HotPixelChoice::None,
        ..ConvertRequest::default()
    }
}

fn convert(input: &Path, out: &Path, request: &ConvertRequest) -> quantacolor::Result<Capture> {
    convert_input(input, out, request, &Silent)?;
    Capture::open(out)
}

/// Every pixel of frame `t` of `capture` equals `expect(y, x)`.
fn assert_frame(capture: &Capture, t: usize, expect: impl Fn(usize, usize) -> bool) {
    let f = &capture.frames;
    for y in 0..f.height() {
        for x in 0..f.width() {
            assert_eq!(f.bit(t, y, x), expect(y, x), "frame {t} pixel ({y}, {x})");
        }
    }
}

#[test]
fn swissspad2_half_array_round_trips_in_natural_order_across_nested_directories() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("rec");
    // Natural order: 0/2.bin, 0/10.bin, 2/1.bin, 10/0.bin (lexicographic would differ twice).
    let order = ["0/2.bin", "0/10.bin", "2/1.bin", "10/0.bin"];
    for (i, name) in order.iter().enumerate() {
        write(&input.join(name), &swissspad2_half_file(1, 512 * i, 512));
    }
    write(&input.join("notes.txt"), b"ignored");
    let cap = convert(
        &input,
        &tmp.path().join("cap"),
        &request(RawFormat::SwissSpad2),
    )
    .unwrap();
    assert_eq!(cap.frames.frame_count(), 2048);
    assert_eq!((cap.frames.height(), cap.frames.width()), (256, 512));
    assert_eq!(cap.cfa.fractions()[Channel::W.index()], 1.0);
    for t in [0, 1, 511, 512, 1023, 1024, 1536, 2047] {
        assert_frame(&cap, t, |y, x| bit(1, t, y, x));
    }
    assert!(cap.hot_pixels.is_none());

    // A window converts only its frames, and they become frames 0..
    let mut req = request(RawFormat::SwissSpad2);
    req.window = "510:1030".parse().unwrap();
    let win = convert(&input, &tmp.path().join("win"), &req).unwrap();
    assert_eq!(win.frames.frame_count(), 520);
    for t in [0, 1, 2, 519] {
        assert_frame(&win, t, |y, x| bit(1, 510 + t, y, x));
    }
    let toml = std::fs::read_to_string(tmp.path().join("win/capture.toml")).unwrap();
    assert!(toml.contains("first_frame = 510"), "{toml}");
    assert!(toml.contains("format = \"swissspad2\""), "{toml}");
}

#[test]
fn swissspad2_full_array_restores_the_flipped_bottom_half() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("full.bin");
    write(&file, &swissspad2_full_file(2, 256));
    let cap = convert(
        &file,
        &tmp.path().join("cap"),
        &request(RawFormat::SwissSpad2Full),
    )
    .unwrap();
    assert_eq!(
        (
            cap.frames.frame_count(),
            cap.frames.height(),
            cap.frames.width()
        ),
        (256, 512, 512)
    );
    for t in [0, 100, 255] {
        assert_frame(&cap, t, |y, x| bit(2, t, y, x));
    }
}

#[test]
fn colorspad_geometry_crops_swaps_and_ships_the_calibration() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("a.bin");
    write(&file, &swissspad2_half_file(3, 0, 512));
    let mut req = request(RawFormat::SwissSpad2);
    req.source.colorspad = true;
    req.hot_pixels = HotPixelChoice::Auto;
    let cap = convert(&file, &tmp.path().join("cap"), &req).unwrap();
    assert_eq!((cap.frames.height(), cap.frames.width()), (254, 496));
    // Corrected pixel (y, x) is raw pixel (y + 2, x'), x' with blocks 252..256 and 260..264
    // swapped.
    let raw_col = |x: usize| match x {
        252..=255 => x + 8,
        260..=263 => x - 8,
        _ => x,
    };
    for t in [0, 511] {
        assert_frame(&cap, t, |y, x| bit(3, t, y + 2, raw_col(x)));
    }
    assert_eq!(cap.cfa, colorspad_cfa());
    assert_eq!(cap.hot_pixels.as_ref(), Some(&colorspad_hot_pixel_mask()));
    // --colorspad belongs to the half array only.
    let mut bad = request(RawFormat::SwissSpad2Full);
    bad.source.colorspad = true;
    assert!(convert(&file, &tmp.path().join("bad"), &bad).is_err());
    assert!(!tmp.path().join("bad").exists());
}

#[test]
fn spad512s_trailer_and_orientations() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("spad");
    // Files of different frame counts are fine for the SPAD512S (it fixes none).
    write(&input.join("RAW_9.bin"), &spad512s_file(4, 0, 3, 4));
    write(&input.join("RAW_10.bin"), &spad512s_file(4, 3, 2, 4));
    let views: [(Spad512sOrientation, PixelMap); 3] = [
        (Spad512sOrientation::Stored, |y, x| (y, x)),
        (Spad512sOrientation::FlipLr, |y, x| (y, 511 - x)),
        (Spad512sOrientation::Rot90, |y, x| (x, 511 - y)),
    ];
    for (i, (orientation, source_pixel)) in views.into_iter().enumerate() {
        let mut req = request(RawFormat::Spad512s);
        req.source.spad512s = Spad512sOptions {
            trailer_bytes: 4,
            orientation,
        };
        let cap = convert(&input, &tmp.path().join(format!("cap{i}")), &req).unwrap();
        assert_eq!(cap.frames.frame_count(), 5);
        for t in [0, 2, 3, 4] {
            assert_frame(&cap, t, |y, x| {
                let (sy, sx) = source_pixel(y, x);
                bit(4, t, sy, sx)
            });
        }
    }
    // Without the trailer option the sizes do not fit, and the error names the file.
    let mut req = request(RawFormat::Spad512s);
    req.source.spad512s.trailer_bytes = 0;
    let err = convert(&input, &tmp.path().join("bad"), &req)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("RAW_9.bin") && err.contains("98308 bytes"),
        "{err}"
    );
}

fn write_npy_u8(path: &Path, shape: &[usize], data: &[u8]) {
    let mut bytes = encode_header("|u1", shape);
    bytes.extend_from_slice(data);
    write(path, &bytes);
}

#[test]
fn photon_cubes_packed_and_rgb() {
    let tmp = tempfile::tempdir().unwrap();
    let (t, h, w) = (5, 6, 20);
    let bits = Array3::from_shape_fn((t, h, w), |(t, y, x)| bit(5, t, y, x) as u8);
    let packed = quantacolor::capture::frames::pack_bits(&bits);
    let path = tmp.path().join("cube.npy");
    write_npy_u8(&path, &[t, h, 3], packed.as_slice().unwrap());
    // With a CFA the width is the CFA's (20), without it 8 · 3 = 24.
    let cfa = Cfa::new(Array2::from_shape_fn((h, w), |(y, x)| ((y + x) % 4) as u8)).unwrap();
    let mut req = request(RawFormat::Npy);
    req.cfa = Some(cfa.clone());
    let cap = convert(&path, &tmp.path().join("cap"), &req).unwrap();
    assert_eq!(cap.frames.width(), 20);
    for ti in 0..t {
        assert_frame(&cap, ti, |y, x| bits[[ti, y, x]] == 1);
    }
    assert_eq!(open_npy(&path, None).unwrap().width(), 24);

    // RGB cube (T, H, W/8, 3): R, G, B pixels take their channel's bit, W the OR of all three.
    let rgb = Array3::from_shape_fn((t, h, w * 3), |(t, y, xc)| bit(6, t, y, xc) as u8);
    let mut cube = vec![0u8; t * h * 3 * 3];
    for ((ti, y, xc), &b) in rgb.indexed_iter() {
        let (x, c) = (xc / 3, xc % 3);
        if b == 1 {
            cube[((ti * h + y) * 3 + x / 8) * 3 + c] |= 0x80 >> (x % 8);
        }
    }
    let rgb_path = tmp.path().join("rgb.npy");
    write_npy_u8(&rgb_path, &[t, h, 3, 3], &cube);
    let cap = convert(&rgb_path, &tmp.path().join("rgbcap"), &req).unwrap();
    for ti in 0..t {
        assert_frame(&cap, ti, |y, x| match cfa.codes()[[y, x]] {
            c @ 0..=2 => rgb[[ti, y, 3 * x + c as usize]] == 1,
            _ => (0..3).any(|c| rgb[[ti, y, 3 * x + c]] == 1),
        });
    }
    // An RGB cube without a CFA is an error naming the file.
    let err = convert(&rgb_path, &tmp.path().join("x"), &request(RawFormat::Npy))
        .unwrap_err()
        .to_string();
    assert!(err.contains("rgb.npy") && err.contains("CFA"), "{err}");
}

#[test]
fn converted_hot_pixels_are_detected_when_no_mask_is_given() {
    let tmp = tempfile::tempdir().unwrap();
    // A flat dim scene (10 % firing) with three pixels firing 60 % of the time.
    let (t, h, w) = (400usize, 16usize, 24usize);
    let hot = [(3, 5), (10, 17), (12, 2)];
    let bits = Array3::from_shape_fn((t, h, w), |(ti, y, x)| {
        let p = if hot.contains(&(y, x)) { 0.6 } else { 0.1 };
        (uniform(7, ti, y, x) < p) as u8
    });
    let packed = quantacolor::capture::frames::pack_bits(&bits);
    let path = tmp.path().join("cube.npy");
    write_npy_u8(&path, &[t, h, 3], packed.as_slice().unwrap());
    let mut req = request(RawFormat::Npy);
    req.hot_pixels = HotPixelChoice::Auto;
    req.cfa = Some(Cfa::uniform(h, w, Channel::W));
    let cap = convert(&path, &tmp.path().join("cap"), &req).unwrap();
    let mask = cap.hot_pixels.expect("a detected mask is written");
    let flagged: Vec<_> = mask
        .indexed_iter()
        .filter(|(_, &m)| m)
        .map(|(p, _)| p)
        .collect();
    assert_eq!(flagged, hot.to_vec());
}

#[test]
fn bad_inputs_name_the_file_and_leave_nothing_behind() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let good = swissspad2_half_file(11, 0, 512);
    let cases: Vec<(&str, Files, &str)> = vec![
        (
            "truncated",
            vec![
                ("a/1.bin", good.clone()),
                ("a/2.bin", good[..1000].to_vec()),
            ],
            "2.bin",
        ),
        (
            "odd",
            vec![("1.bin", [good.clone(), vec![0; 7]].concat())],
            "1.bin",
        ),
        (
            "mixed",
            vec![
                ("1.bin", good.clone()),
                ("2.bin", good[..16384 * 256].to_vec()),
            ],
            "2.bin",
        ),
        ("empty-file", vec![("1.bin", Vec::new())], "1.bin"),
        ("empty-dir", vec![], "empty-dir"),
    ];
    for (name, files, named) in cases {
        let input = root.join(name);
        std::fs::create_dir_all(&input).unwrap();
        for (f, bytes) in &files {
            write(&input.join(f), bytes);
        }
        let out = root.join(format!("{name}-out"));
        let err = convert(&input, &out, &request(RawFormat::SwissSpad2))
            .unwrap_err()
            .to_string();
        assert!(err.contains(named), "{name}: {err}");
        assert!(!out.exists(), "{name}: output left behind");
    }
    let hidden: Vec<String> = std::fs::read_dir(root)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(hidden.is_empty(), "temporary files left: {hidden:?}");
    // A window past the end is refused before anything is written.
    write(&root.join("one/1.bin"), &good);
    let mut req = request(RawFormat::SwissSpad2);
    req.window = FrameWindow {
        start: Some(0),
        end: Some(513),
    };
    let err = convert(&root.join("one"), &root.join("w"), &req)
        .unwrap_err()
        .to_string();
    assert!(err.contains("512 frames"), "{err}");
    assert!(!root.join("w").exists());
}

#[cfg(unix)]
#[test]
fn unreadable_file_is_named() {
    use std::os::unix::fs::PermissionsExt;
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("in/locked.bin");
    write(&file, &swissspad2_half_file(12, 0, 512));
    std::fs::set_permissions(&file, std::fs::Permissions::from_mode(0o000)).unwrap();
    if std::fs::File::open(&file).is_ok() {
        // Root reads mode-000 files (as CI does): a link to nowhere is a file nobody can open.
        std::fs::remove_file(&file).unwrap();
        std::os::unix::fs::symlink(tmp.path().join("gone.bin"), &file).unwrap();
    }
    let out = tmp.path().join("out");
    let err = convert(
        &tmp.path().join("in"),
        &out,
        &request(RawFormat::SwissSpad2),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("locked.bin"), "{err}");
    assert!(!out.exists());
}

/// Reads every frame of whatever `open_source` accepts; errors are fine, panics are not.
fn read_all(input: &Path, spec: &SourceSpec, cfa: Option<&Cfa>) {
    if let Ok(mut source) = open_source(input, spec, cfa) {
        let n = source.height() * source.width().div_ceil(8);
        let mut buf = vec![0u8; n];
        for t in 0..source.frame_count().min(8) {
            let _ = source.read_frame(t, &mut buf);
        }
    }
}

fn fuzz_dir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("qc-fuzz-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    /// Random .bin files of random sizes (around whole SPAD512S frames, with and without a
    /// trailer) through every raw format: no panic.
    #[test]
    fn random_bin_files_never_panic(
        sizes in proptest::collection::vec((0usize..3, 0usize..40), 1..3),
        fill in any::<u8>(),
        trailer in 0usize..6,
        colorspad in any::<bool>(),
    ) {
        let dir = fuzz_dir("bin");
        for (i, (frames, extra)) in sizes.iter().enumerate() {
            let len = frames * 32768 + extra;
            let bytes: Vec<u8> = (0..len).map(|k| (k as u8).wrapping_mul(31) ^ fill).collect();
            std::fs::write(dir.join(format!("{i}.bin")), bytes).unwrap();
        }
        for format in [RawFormat::SwissSpad2, RawFormat::SwissSpad2Full, RawFormat::Spad512s] {
            for orientation in [Spad512sOrientation::Stored, Spad512sOrientation::Rot90] {
                let spec = SourceSpec {
                    format: Some(format),
                    colorspad,
                    spad512s: Spad512sOptions { trailer_bytes: trailer, orientation },
                };
                read_all(&dir, &spec, None);
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Valid photon-cube .npy files with random bytes mutated (header included): no panic.
    #[test]
    fn mutated_npy_cubes_never_panic(
        t in 1usize..4, h in 1usize..5, b in 1usize..4, rgb in any::<bool>(),
        mutations in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..6),
        cut in proptest::option::of(any::<prop::sample::Index>()),
        with_cfa in any::<bool>(),
    ) {
        let shape: Vec<usize> = if rgb { vec![t, h, b, 3] } else { vec![t, h, b] };
        let n: usize = shape.iter().product();
        let mut bytes = encode_header("|u1", &shape);
        bytes.extend((0..n).map(|k| (k * 37) as u8));
        for (at, v) in mutations {
            let i = at.index(bytes.len());
            bytes[i] = v;
        }
        if let Some(c) = cut {
            bytes.truncate(c.index(bytes.len() + 1));
        }
        let dir = fuzz_dir("npy");
        let path = dir.join("cube.npy");
        std::fs::write(&path, &bytes).unwrap();
        let cfa = Cfa::new(Array2::from_shape_fn((h, 8 * b - 3), |(y, x)| ((y * 3 + x) % 4) as u8))
            .unwrap();
        let spec = SourceSpec { format: Some(RawFormat::Npy), ..SourceSpec::default() };
        read_all(&path, &spec, with_cfa.then_some(&cfa));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
