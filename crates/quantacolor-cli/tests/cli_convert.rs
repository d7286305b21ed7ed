//! `quantacolor convert`, `inspect` and `--frames` end to end (issue 12): a SwissSPAD2
//! recording written from known bits is converted, inspected and reconstructed; bad input
//! exits with status 2, names the file and leaves nothing behind.

use std::path::Path;

mod cli_support;
use cli_support::{ok, quantacolor};

/// A SwissSPAD2 half-array file (512 frames of 256x512, LSB first) of a flat scene firing
/// with probability 1/4, plus one pixel that fires in every frame.
fn swissspad2_file(path: &Path) {
    let mut bytes = vec![0u8; 512 * 256 * 64];
    let mut z: u64 = 1;
    for b in bytes.iter_mut() {
        z ^= z << 13;
        z ^= z >> 7;
        z ^= z << 17;
        *b = (z as u8) & ((z >> 8) as u8); // each bit set with probability 1/4
    }
    for t in 0..512 {
        bytes[(t * 256 + 100) * 64 + 200 / 8] |= 1 << (200 % 8);
    }
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, bytes).unwrap();
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn convert_inspect_reconstruct_a_swissspad2_recording() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    swissspad2_file(&rec.join("0/0.bin"));
    let cap = tmp.path().join("cap");
    let out = ok(&[
        "convert",
        s(&rec),
        "--from",
        "swissspad2",
        "--out",
        s(&cap),
        "--frames",
        "0:384",
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("384 frames of 256x512"), "{text}");
    assert!(text.contains("detected"), "{text}");
    let toml = std::fs::read_to_string(cap.join("capture.toml")).unwrap();
    assert!(toml.contains("hot_pixels = \"hot_pixels.npy\""), "{toml}");

    let preview = tmp.path().join("preview.png");
    let out = ok(&["inspect", s(&cap), "--preview", s(&preview)]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("384 of 256x512"), "{text}");
    // The always-on pixel is the capture's one hot pixel.
    assert!(text.contains("hot pixels    1 "), "{text}");
    // W detections per frame: 1/4.
    let w_line = text
        .lines()
        .find(|l| l.trim_start().starts_with('W'))
        .unwrap();
    let p: f64 = w_line.split_whitespace().nth(2).unwrap().parse().unwrap();
    assert!((p - 0.25).abs() < 0.005, "{w_line}");
    assert!(preview.exists());

    for extra in [&["--frames", "100:300"][..], &[][..]] {
        let dir = tmp.path().join(format!("naive{}", extra.len()));
        let mut args = vec![
            "reconstruct",
            s(&cap),
            "--out",
            s(&dir),
            "--method",
            "naive",
        ];
        args.extend_from_slice(extra);
        ok(&args);
        let report = std::fs::read_to_string(dir.join("report.toml")).unwrap();
        let want = if extra.is_empty() { 384 } else { 200 };
        assert!(
            report.contains(&format!("frames_used = {want}")),
            "{extra:?}: {report}"
        );
    }
    let flow = tmp.path().join("flow");
    ok(&[
        "align",
        s(&cap),
        "--out",
        s(&flow),
        "--frames",
        "0:256",
        "--block-size",
        "64",
    ]);
    assert!(flow.join("flow.npy").exists());
}

#[test]
fn bad_recordings_exit_2_name_the_file_and_leave_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    std::fs::create_dir_all(&rec).unwrap();
    std::fs::write(rec.join("7.bin"), vec![0u8; 12345]).unwrap();
    let cap = tmp.path().join("cap");
    let out = quantacolor(&["convert", s(&rec), "--from", "swissspad2", "--out", s(&cap)]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("7.bin") && err.contains("12345 bytes"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    assert!(!cap.exists());
    let names: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["rec"], "leftovers: {names:?}");

    let empty = tmp.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let out = quantacolor(&["convert", s(&empty), "--from", "spad512s", "--out", s(&cap)]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no .bin files"));

    let out = quantacolor(&[
        "convert",
        s(&rec),
        "--from",
        "swissspad2",
        "--out",
        s(&cap),
        "--frames",
        "9:3",
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("9:3"));
    assert!(!cap.exists());
}
