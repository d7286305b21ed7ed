//! End-to-end tests of `quantacolor display` and `quantacolor calibrate-color`: one image per
//! option from a small synthetic linear.npy, the fitted matrix, and bad input (exit status 2, the
//! file named, nothing written).

use ndarray::Array3;
use quantacolor::capture::io::{read_rgb_image, write_npy};
use quantacolor::simulate::chart::chart_value;
use std::path::Path;

mod cli_support;
use cli_support::{ok, quantacolor};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Left half very dark (0.001 detections/frame), right half bright; reddish everywhere.
fn scene() -> Array3<f32> {
    Array3::from_shape_fn((24, 40, 3), |(y, x, c)| {
        let v = if x < 20 { 0.001 } else { 0.5 + 0.01 * y as f32 };
        v * [1.0, 0.4, 0.2][c]
    })
}

/// PNG bit depth from the IHDR chunk.
fn png_bit_depth(path: &Path) -> u8 {
    std::fs::read(path).unwrap()[24]
}

fn files_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn display_writes_one_image_per_option() {
    let tmp = tempfile::tempdir().unwrap();
    let lin = tmp.path().join("linear.npy");
    write_npy(&lin, &scene()).unwrap();
    for op in ["mantiuk06", "global", "none"] {
        let out = tmp.path().join(format!("{op}.png"));
        ok(&["display", s(&lin), "--out", s(&out), "--tonemap", op]);
        assert_eq!(png_bit_depth(&out), 8);
        let (img, _) = read_rgb_image(&out).unwrap();
        assert_eq!(img.dim(), (24, 40, 3));
        // Bright side: reddish and brighter than the dark side.
        let (r, g) = (img[[12, 30, 0]], img[[12, 30, 1]]);
        assert!(r > g && r > img[[12, 5, 0]], "{op}: {r} {g}");
    }
    // Mesopic: the dark half becomes grey, the bright half keeps its colour. Without a
    // report.toml a fixed L0 needs --frames (exit 2 otherwise); auto measures the noise.
    let out = tmp.path().join("meso.png");
    let failed = quantacolor(&["display", s(&lin), "--out", s(&out), "--mesopic", "0"]);
    assert_eq!(failed.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&failed.stderr).contains("--frames"));
    assert!(!out.exists());
    ok(&[
        "display",
        s(&lin),
        "--out",
        s(&out),
        "--tonemap",
        "none",
        "--mesopic",
        "0",
        "--frames",
        "100", // dark half: 0.16 W detections over the capture, bright half 80
    ]);
    let (img, _) = read_rgb_image(&out).unwrap();
    let dark = [img[[5, 5, 0]], img[[5, 5, 1]], img[[5, 5, 2]]];
    assert!(dark[0] == dark[1] && dark[1] == dark[2], "{dark:?}");
    assert!(img[[5, 30, 0]] > img[[5, 30, 1]] + 0.1);
    // 16-bit PNG and 16-bit TIFF (uncompressed: 6 bytes a pixel).
    let out = tmp.path().join("deep.png");
    ok(&[
        "display",
        s(&lin),
        "--out",
        s(&out),
        "--bits",
        "16",
        "--exposure",
        "1.5",
    ]);
    assert_eq!(png_bit_depth(&out), 16);
    let tif = tmp.path().join("deep.tif");
    ok(&["display", s(&lin), "--out", s(&tif), "--tonemap", "global"]);
    assert!(std::fs::metadata(&tif).unwrap().len() >= 24 * 40 * 6);
    assert_eq!(read_rgb_image(&tif).unwrap().0.dim(), (24, 40, 3));
}

#[test]
fn display_writes_a_video_stack_as_numbered_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let frames: Vec<Array3<f32>> = (0..3)
        .map(|i| scene().mapv(|v| v * (1.0 + i as f32)))
        .collect();
    let views: Vec<_> = frames.iter().map(|f| f.view()).collect();
    let stack = ndarray::stack(ndarray::Axis(0), &views).unwrap();
    let video = tmp.path().join("video");
    std::fs::create_dir(&video).unwrap();
    let lin = video.join("linear.npy");
    write_npy(&lin, &stack).unwrap();
    // report.toml as `reconstruct --video` does not write one: --frames for a fixed L0.
    let out_dir = tmp.path().join("frames");
    std::fs::create_dir(&out_dir).unwrap();
    let out = out_dir.join("clip.png");
    ok(&[
        "display",
        s(&lin),
        "--out",
        s(&out),
        "--mesopic",
        "0",
        "--frames",
        "1000",
    ]);
    assert_eq!(
        files_in(&out_dir),
        ["clip_00000.png", "clip_00001.png", "clip_00002.png"]
    );
    // One exposure for the whole clip: later frames (more light) are brighter.
    let mean = |i: usize| {
        let (img, _) = read_rgb_image(out_dir.join(format!("clip_{i:05}.png"))).unwrap();
        img.mean().unwrap()
    };
    assert!(mean(2) > mean(1) && mean(1) > mean(0));
    // Same bytes again (deterministic), 16-bit TIFF frames too.
    let first = std::fs::read(out_dir.join("clip_00001.png")).unwrap();
    ok(&[
        "display",
        s(&lin),
        "--out",
        s(&out),
        "--mesopic",
        "0",
        "--frames",
        "1000",
    ]);
    assert_eq!(
        std::fs::read(out_dir.join("clip_00001.png")).unwrap(),
        first
    );
    let tif_dir = tmp.path().join("tif");
    std::fs::create_dir(&tif_dir).unwrap();
    ok(&["display", s(&lin), "--out", s(&tif_dir.join("v.tif"))]);
    assert_eq!(
        files_in(&tif_dir),
        ["v_00000.tif", "v_00001.tif", "v_00002.tif"]
    );
    // Bad shapes: one error naming the file and the shape, exit 2, nothing written.
    let bad_dir = tmp.path().join("bad");
    std::fs::create_dir(&bad_dir).unwrap();
    type Writer = Box<dyn Fn(&Path)>;
    let bad: Vec<(&str, Writer)> = vec![
        (
            "four_channels.npy",
            Box::new(|p: &Path| {
                write_npy(p, &ndarray::Array4::<f32>::zeros((2, 4, 4, 4))).unwrap()
            }),
        ),
        (
            "empty.npy",
            Box::new(|p: &Path| {
                write_npy(p, &ndarray::Array4::<f32>::zeros((0, 4, 4, 3))).unwrap()
            }),
        ),
        (
            "five_d.npy",
            Box::new(|p: &Path| {
                write_npy(p, &ndarray::Array5::<f32>::zeros((1, 2, 4, 4, 3))).unwrap()
            }),
        ),
        (
            "two_d.npy",
            Box::new(|p: &Path| write_npy(p, &ndarray::Array2::<f32>::zeros((4, 3))).unwrap()),
        ),
        (
            "f64.npy",
            Box::new(|p: &Path| {
                write_npy(p, &ndarray::Array4::<f64>::zeros((2, 4, 4, 3))).unwrap()
            }),
        ),
    ];
    for (name, make) in bad {
        let path = tmp.path().join(name);
        make(&path);
        let out = quantacolor(&["display", s(&path), "--out", s(&bad_dir.join("x.png"))]);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{name}: {err}");
        assert!(
            err.contains(name) && err.contains("(N, H, W, 3)"),
            "{name}: {err}"
        );
        assert!(!err.contains("panicked"), "{err}");
        assert!(files_in(&bad_dir).is_empty(), "{name}");
    }
    // A truncated stack is named too.
    let trunc = tmp.path().join("trunc.npy");
    let bytes = std::fs::read(&lin).unwrap();
    std::fs::write(&trunc, &bytes[..bytes.len() - 100]).unwrap();
    let out = quantacolor(&["display", s(&trunc), "--out", s(&bad_dir.join("x.png"))]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("trunc.npy"));
    assert!(files_in(&bad_dir).is_empty());
}

#[test]
fn calibrate_color_then_display_with_the_matrix() {
    let tmp = tempfile::tempdir().unwrap();
    let (h, w) = (127, 248);
    // The chart through a camera whose red leaks into green: a known mixing at 0.05 det/frame.
    let k = [[0.8, 0.15, 0.05], [0.25, 0.7, 0.05], [0.05, 0.1, 0.85]];
    let img = Array3::from_shape_fn((h, w, 3), |(y, x, c)| {
        let t = chart_value(y as f64, x as f64, h, w, false);
        0.05 * (k[c][0] * t[0] + k[c][1] * t[1] + k[c][2] * t[2])
    });
    let lin = tmp.path().join("chart.npy");
    write_npy(&lin, &img).unwrap();
    let ccm = tmp.path().join("ccm.toml");
    let out = ok(&["calibrate-color", s(&lin), "--out", s(&ccm)]);
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().find(|l| l.contains("delta E76")).unwrap();
    let nums: Vec<f64> = line
        .split(|c: char| !(c.is_ascii_digit() || c == '.'))
        .filter_map(|t| t.parse().ok())
        .filter(|v: &f64| *v != 76.0)
        .collect();
    assert!(nums[1] < 0.05 && nums[0] > 3.0, "{line}");
    let toml_text = std::fs::read_to_string(&ccm).unwrap();
    assert!(toml_text.contains("[color_matrix]"), "{toml_text}");
    // Displayed with the matrix, the red patch (15) is redder than without.
    let (with, without) = (tmp.path().join("with.png"), tmp.path().join("without.png"));
    ok(&[
        "display",
        s(&lin),
        "--out",
        s(&with),
        "--tonemap",
        "none",
        "--ccm",
        s(&ccm),
    ]);
    ok(&[
        "display",
        s(&lin),
        "--out",
        s(&without),
        "--tonemap",
        "none",
    ]);
    let red = |p: &Path| {
        let (im, _) = read_rgb_image(p).unwrap();
        let (y, x) = (
            (0.04 + 2.5 * 0.13) * h as f64,
            0.02 * w as f64 + 2.5 * 0.44 * w as f64 / 6.0,
        );
        let px = [0, 1, 2].map(|c| im[[y as usize, x as usize, c]]);
        px[0] - px[1]
    };
    assert!(red(&with) > red(&without) + 0.05);
    ok(&["calibrate-color", s(&lin), "--out", s(&ccm), "--affine"]);
    assert!(std::fs::read_to_string(&ccm)
        .unwrap()
        .contains("affine = true"));
}

#[test]
fn bad_input_exits_2_names_the_file_and_writes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let lin = tmp.path().join("linear.npy");
    write_npy(&lin, &scene()).unwrap();
    let wrong_shape = tmp.path().join("four.npy");
    write_npy(&wrong_shape, &Array3::<f32>::zeros((4, 4, 4))).unwrap();
    let wrong_dtype = tmp.path().join("f64.npy");
    write_npy(&wrong_dtype, &Array3::<f64>::zeros((4, 4, 3))).unwrap();
    let garbage = tmp.path().join("ccm.toml");
    std::fs::write(&garbage, "[color_matrix]\nrows = [[1, 2]]\n").unwrap();
    let out_dir = tmp.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let png = out_dir.join("x.png");
    let cases: Vec<(Vec<String>, String)> = vec![
        (
            vec![s(&wrong_shape).into(), "--out".into(), s(&png).into()],
            s(&wrong_shape).into(),
        ),
        (
            vec![s(&wrong_dtype).into(), "--out".into(), s(&png).into()],
            s(&wrong_dtype).into(),
        ),
        (
            vec![
                s(&lin).into(),
                "--out".into(),
                s(&out_dir.join("x.bmp")).into(),
            ],
            "x.bmp".into(),
        ),
        (
            vec![
                s(&lin).into(),
                "--out".into(),
                s(&png).into(),
                "--ccm".into(),
                s(&garbage).into(),
            ],
            s(&garbage).into(),
        ),
        (
            vec![
                s(&lin).into(),
                "--out".into(),
                s(&tmp.path().join("no/such/dir/x.png")).into(),
            ],
            "x.png".into(),
        ),
    ];
    for (args, named) in cases {
        let mut full = vec!["display".to_string()];
        full.extend(args);
        let refs: Vec<&str> = full.iter().map(|a| a.as_str()).collect();
        let out = quantacolor(&refs);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{full:?}: {err}");
        assert!(err.contains(&named), "{full:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
        assert!(files_in(&out_dir).is_empty(), "{:?}", files_in(&out_dir));
    }
    // calibrate-color on an image too small to hold the chart.
    let tiny = tmp.path().join("tiny.npy");
    write_npy(&tiny, &Array3::<f32>::zeros((3, 3, 3))).unwrap();
    let out = quantacolor(&[
        "calibrate-color",
        s(&tiny),
        "--out",
        s(&out_dir.join("c.toml")),
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("tiny.npy"));
    assert!(files_in(&out_dir).is_empty());
}
