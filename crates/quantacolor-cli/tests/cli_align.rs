//! `quantacolor align` end to end (issue 44 item 4): camera.npy against the simulator's
//! motion.toml, the same array from `reconstruct --dump-stages`, and bad input exiting with
//! status 2 and leaving nothing behind.

use quantacolor::capture::io::read_npy_3d;
use quantacolor::simulate::Motion;
use std::path::Path;

mod cli_support;
use cli_support::{ok, quantacolor};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Median end-point error (px) of camera.npy against the simulator's camera map over a grid of
/// reference-frame points 16 px inside the image, every frame.
fn median_camera_epe(camera: &ndarray::Array3<f64>, truth: &Motion, h: usize, w: usize) -> f64 {
    let mut errors = Vec::new();
    for t in 0..truth.frames {
        for y in (16..h - 16).step_by(8) {
            for x in (16..w - 16).step_by(8) {
                let p = [y as f64, x as f64];
                let q = truth.forward(t, p);
                let e = [0, 1].map(|r| {
                    camera[[t, r, 0]] * p[0] + camera[[t, r, 1]] * p[1] + camera[[t, r, 2]] - q[r]
                });
                errors.push(e[0].hypot(e[1]));
            }
        }
    }
    errors.sort_by(f64::total_cmp);
    errors[errors.len() / 2]
}

#[test]
fn align_writes_the_camera_motion_reconstruct_uses() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    ok(&[
        "simulate",
        "--frames",
        "512",
        "--size",
        "192x128",
        "--motion",
        "handheld",
        "--seed",
        "3",
        "--out",
        s(&cap),
    ]);
    let al = tmp.path().join("al");
    ok(&["align", s(&cap), "--out", s(&al)]);
    for name in ["flow.npy", "flow.toml", "camera.npy"] {
        assert!(al.join(name).exists(), "{name} missing");
    }
    let camera = read_npy_3d::<f64>(al.join("camera.npy")).unwrap();
    assert_eq!(camera.dim(), (512, 2, 3));
    let truth: Motion =
        toml::from_str(&std::fs::read_to_string(cap.join("motion.toml")).unwrap()).unwrap();
    let epe = median_camera_epe(&camera, &truth, 128, 192);
    println!("handheld 192x128, 512 frames: camera.npy median EPE {epe:.3} px");
    assert!(epe <= 0.15, "camera.npy EPE {epe} px");

    // reconstruct --dump-stages writes the same motion.
    let stages = tmp.path().join("stages");
    ok(&[
        "reconstruct",
        s(&cap),
        "--out",
        s(&tmp.path().join("rec")),
        "--denoise",
        "none",
        "--dump-stages",
        s(&stages),
    ]);
    assert_eq!(
        std::fs::read(stages.join("camera.npy")).unwrap(),
        std::fs::read(al.join("camera.npy")).unwrap(),
        "reconstruct --dump-stages and align wrote different camera.npy"
    );

    // Bad input: status 2, a clear message, no output folder.
    let bad = tmp.path().join("bad");
    let out = quantacolor(&[
        "align",
        s(&cap),
        "--out",
        s(&bad),
        "--reference-frame",
        "512",
    ]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("reference frame 512"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert!(!bad.exists());
    let config = tmp.path().join("bad.toml");
    std::fs::write(&config, "[burst.refine]\nno_such_key = 1\n").unwrap();
    let out = quantacolor(&["align", s(&cap), "--out", s(&bad), "--config", s(&config)]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("bad.toml") && err.contains("no_such_key"),
        "{err}"
    );
    assert!(!bad.exists());
}
