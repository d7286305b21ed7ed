//! End-to-end tests of the `quantacolor` binary: the simulate -> reconstruct -> eval path,
//! determinism, and bad input (exit status 2, the file named, no panic, no partial output,
//! inputs untouched).

use std::path::Path;

mod cli_support;
use cli_support::{ok, quantacolor};

fn simulate(dir: &Path, seed: &str) {
    ok(&[
        "simulate",
        "--scene",
        "builtin:chart",
        "--motion",
        "handheld",
        "--frames",
        "96",
        "--flux",
        "0.2",
        "--size",
        "96x64",
        "--cfa",
        "rgbw-75-bluenoise",
        "--seed",
        seed,
        "--out",
        dir.to_str().unwrap(),
    ]);
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn simulate_reconstruct_eval_round_trip_is_deterministic() {
    let tmp = tempfile::tempdir().unwrap();
    let (cap, cap2) = (tmp.path().join("cap"), tmp.path().join("cap2"));
    simulate(&cap, "3");
    simulate(&cap2, "3");
    assert_eq!(
        read(&cap.join("frames.npy")),
        read(&cap2.join("frames.npy"))
    );
    for f in [
        "capture.toml",
        "cfa.npy",
        "ground_truth.npy",
        "hot_pixels.npy",
        "motion.toml",
    ] {
        assert!(cap.join(f).exists(), "{f} missing");
    }
    let frames_before = read(&cap.join("frames.npy"));
    for (name, method) in [("burst", "burst"), ("naive", "naive")] {
        let out = tmp.path().join(name);
        ok(&[
            "reconstruct",
            cap.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--method",
            method,
        ]);
        for f in ["linear.npy", "linear.exr", "preview.png", "report.toml"] {
            assert!(out.join(f).exists(), "{name}: {f} missing");
        }
        let again = tmp.path().join(format!("{name}-again"));
        ok(&[
            "reconstruct",
            cap.to_str().unwrap(),
            "--out",
            again.to_str().unwrap(),
            "--method",
            method,
        ]);
        assert_eq!(
            read(&out.join("linear.npy")),
            read(&again.join("linear.npy"))
        );
        let eval = ok(&[
            "eval",
            out.join("linear.npy").to_str().unwrap(),
            cap.join("ground_truth.npy").to_str().unwrap(),
            "--border",
            "8",
        ]);
        let text = String::from_utf8_lossy(&eval.stdout);
        let psnr: f64 = text
            .lines()
            .find_map(|l| l.strip_prefix("psnr_linear = "))
            .expect("psnr line")
            .parse()
            .unwrap();
        assert!(
            psnr > 10.0 && psnr < 60.0,
            "{name}: implausible PSNR {psnr}"
        );
        let lpips: f64 = text
            .lines()
            .find_map(|l| l.strip_prefix("lpips_srgb = "))
            .expect("lpips line")
            .parse()
            .unwrap();
        assert!(
            lpips > 0.0 && lpips < 1.0,
            "{name}: implausible LPIPS {lpips}"
        );
    }
    assert_eq!(
        frames_before,
        read(&cap.join("frames.npy")),
        "input modified"
    );
    // No staging directories are left behind.
    let leftovers: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains("partial"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

fn expect_failure(args: &[&str], names: &str) -> String {
    let out = quantacolor(args);
    assert_eq!(out.status.code(), Some(2), "{args:?} should exit with 2");
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    assert!(
        err.contains(names),
        "{args:?}: error {err:?} does not name {names}"
    );
    err
}

#[test]
fn bad_inputs_exit_2_name_the_file_and_leave_no_output() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let out_s = out.to_str().unwrap();
    expect_failure(
        &["reconstruct", "/no/such/capture", "--out", out_s],
        "/no/such/capture",
    );
    assert!(!out.exists());

    let cap = tmp.path().join("cap");
    simulate(&cap, "1");
    // Truncated frames.npy.
    let frames = read(&cap.join("frames.npy"));
    std::fs::write(cap.join("frames.npy"), &frames[..frames.len() / 2]).unwrap();
    let err = expect_failure(
        &["reconstruct", cap.to_str().unwrap(), "--out", out_s],
        "frames.npy",
    );
    assert!(err.contains("truncated"), "{err}");
    assert!(!out.exists(), "partial output left behind");
    assert_eq!(
        read(&cap.join("frames.npy")).len(),
        frames.len() / 2,
        "input modified"
    );
    std::fs::write(cap.join("frames.npy"), &frames).unwrap();

    // Bad TOML value.
    let toml = std::fs::read_to_string(cap.join("capture.toml")).unwrap();
    let broken = toml
        .lines()
        .map(|l| {
            if l.starts_with("exposure_s") {
                "exposure_s = -1.0"
            } else {
                l
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    std::fs::write(cap.join("capture.toml"), broken).unwrap();
    expect_failure(
        &["reconstruct", cap.to_str().unwrap(), "--out", out_s],
        "capture.toml",
    );
    std::fs::write(cap.join("capture.toml"), toml).unwrap();

    // A bad BM3D setting in --config: named with its file before any work.
    let bad_config = tmp.path().join("bad.toml");
    let reconstruct_with_config = |text: &str| {
        std::fs::write(&bad_config, text).unwrap();
        expect_failure(
            &[
                "reconstruct",
                cap.to_str().unwrap(),
                "--out",
                out_s,
                "--config",
                bad_config.to_str().unwrap(),
            ],
            "bad.toml",
        )
    };
    let err = reconstruct_with_config("[denoise.bm3d]\nstep = 0\n");
    assert!(err.contains("step"), "{err}");
    assert!(!out.exists(), "partial output left behind");
    // A misspelt key in --config is named, not silently left at its default.
    let err = reconstruct_with_config("[burst.refine]\nsimilarity_prior_px = -0.1\n");
    assert!(err.contains("similarity_prior_px"), "{err}");
    assert!(!out.exists(), "partial output left behind");
    let err = reconstruct_with_config("[burst.refine]\nmax_sub_block_motion_px = nan\n");
    assert!(err.contains("max_sub_block_motion_px"), "{err}");
    assert!(!out.exists(), "partial output left behind");
    let err = reconstruct_with_config("[burst.trajectory]\nearly_row_step = 0\n");
    assert!(err.contains("early_row_step"), "{err}");
    assert!(!out.exists(), "partial output left behind");
    let err = reconstruct_with_config("[burst.align.blocks]\nmax_steady_smear_px = -1\n");
    assert!(err.contains("max_steady_smear_px"), "{err}");
    assert!(!out.exists(), "partial output left behind");
    let err = reconstruct_with_config("[burst.merge]\nsharpen_blocks_px = -0.5\n");
    assert!(err.contains("sharpen_blocks_px"), "{err}");
    assert!(!out.exists(), "partial output left behind");
    let err = reconstruct_with_config("[burst.refine]\npases = 1\n");
    assert!(err.contains("`burst.refine.pases`"), "{err}");
    assert!(!out.exists(), "partial output left behind");
    // `bench speed --config` reads the same file the same way, before it simulates anything.
    std::fs::write(&bad_config, "[denoise.bm3d]\nsearch_window = 0\n").unwrap();
    let err = expect_failure(
        &["bench", "speed", "--config", bad_config.to_str().unwrap()],
        "bad.toml",
    );
    assert!(err.contains("search_window"), "{err}");

    // Reference frame outside the capture.
    expect_failure(
        &[
            "reconstruct",
            cap.to_str().unwrap(),
            "--out",
            out_s,
            "--reference-frame",
            "5000",
        ],
        "reference frame",
    );
    // Unknown scene file and unknown CFA pattern.
    expect_failure(
        &["simulate", "--scene", "/no/scene.png", "--out", out_s],
        "/no/scene.png",
    );
    expect_failure(
        &["simulate", "--cfa", "nonsense", "--out", out_s],
        "nonsense",
    );
    // eval with mismatched shapes.
    expect_failure(
        &[
            "eval",
            cap.join("ground_truth.npy").to_str().unwrap(),
            cap.join("hot_pixels.npy").to_str().unwrap(),
        ],
        "hot_pixels.npy",
    );
    assert!(!out.exists(), "partial output left behind");
}

#[test]
fn video_mode_writes_one_frame_per_reference() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    simulate(&cap, "4");
    let out = tmp.path().join("video");
    ok(&[
        "reconstruct",
        cap.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--video",
        "--stride",
        "32",
    ]);
    // 96 frames, stride 32: reference frames 16, 48, 80.
    for i in 0..3 {
        assert!(out.join(format!("frame_{i:05}.png")).exists(), "frame {i}");
    }
    assert!(!out.join("frame_00003.png").exists());
    let toml = std::fs::read_to_string(out.join("video.toml")).unwrap();
    assert!(
        toml.contains("16") && toml.contains("48") && toml.contains("80"),
        "{toml}"
    );
    // By default every frame is a full reconstruction.
    assert!(!toml.contains("motion_anchor_frame"), "{toml}");
    let linear = read(&out.join("linear.npy"));
    assert!(String::from_utf8_lossy(&linear[..128]).contains("(3, 64, 96, 3)"));

    // Shared motion: estimated once, at the capture's reference frame, and composed to each.
    let shared = tmp.path().join("shared");
    ok(&[
        "reconstruct",
        cap.to_str().unwrap(),
        "--out",
        shared.to_str().unwrap(),
        "--video",
        "--stride",
        "32",
        "--video-motion",
        "shared",
    ]);
    let toml = std::fs::read_to_string(shared.join("video.toml")).unwrap();
    assert!(toml.contains("motion_anchor_frame = 48"), "{toml}");
    let linear = read(&shared.join("linear.npy"));
    assert!(String::from_utf8_lossy(&linear[..128]).contains("(3, 64, 96, 3)"));

    // A stride that leaves no reference frame is refused, with no output.
    let none = tmp.path().join("none");
    expect_failure(
        &[
            "reconstruct",
            cap.to_str().unwrap(),
            "--out",
            none.to_str().unwrap(),
            "--video",
            "--stride",
            "1000",
        ],
        "--stride",
    );
    assert!(!none.exists(), "partial output left behind");
}

/// `--video --window N`: each frame is the reconstruction of the N frames centred on its
/// reference frame, byte for byte (checked against `--frames`), and shared motion, estimated
/// over the whole capture, is refused with a window.
#[test]
fn video_windows_are_reconstructions_of_their_own_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    simulate(&cap, "5");
    let out = tmp.path().join("video");
    let c = cap.to_str().unwrap();
    let video = ["reconstruct", c, "--out", out.to_str().unwrap(), "--video"];
    ok(&[&video[..], &["--stride", "32", "--window", "48"]].concat());
    // 96 frames: reference frames 16, 48, 80 with windows 0..48, 24..72, 48..96.
    let toml = std::fs::read_to_string(out.join("video.toml")).unwrap();
    assert!(toml.contains("window = 48"), "{toml}");
    let stack = read(&out.join("linear.npy"));
    for (i, frames, reference) in [(0, "0:48", "16"), (1, "24:72", "24"), (2, "48:96", "32")] {
        let single = tmp.path().join(format!("single{i}"));
        ok(&[
            "reconstruct",
            c,
            "--out",
            single.to_str().unwrap(),
            "--frames",
            frames,
            "--reference-frame",
            reference,
        ]);
        let one = read(&single.join("linear.npy"));
        let (header, frame_bytes) = (stack.len() - 3 * (one.len() - 128), one.len() - 128);
        assert_eq!(
            &stack[header + i * frame_bytes..header + (i + 1) * frame_bytes],
            &one[128..],
            "video frame {i} is not the reconstruction of frames {frames}"
        );
    }
    let shared = tmp.path().join("shared");
    expect_failure(
        &[
            "reconstruct",
            c,
            "--out",
            shared.to_str().unwrap(),
            "--video",
            "--video-motion",
            "shared",
            "--stride",
            "32",
            "--window",
            "48",
        ],
        "--window",
    );
    assert!(!shared.exists(), "partial output left behind");
}

#[test]
fn dump_stages_writes_every_intermediate() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    simulate(&cap, "6");
    let dump = tmp.path().join("stages");
    ok(&[
        "reconstruct",
        cap.to_str().unwrap(),
        "--out",
        tmp.path().join("out").to_str().unwrap(),
        "--dump-stages",
        dump.to_str().unwrap(),
    ]);
    for f in [
        "block_sums.npy",
        "grey_blocks.npy",
        "flow.npy",
        "flow.toml",
        "reference.npy",
        "robustness.npy",
        "merged_planes_rgbw.npy",
    ] {
        assert!(dump.join(f).exists(), "{f} missing");
    }
    let planes = read(&dump.join("merged_planes_rgbw.npy"));
    assert!(String::from_utf8_lossy(&planes[..128]).contains("(4, 64, 96)"));
}

/// `--denoise`, `--sigma-y/-c`, `--tonemap` and `--mesopic` of `reconstruct`: one run per
/// option; report.toml says what the denoiser did; the re-render reads the saved image.
#[test]
fn reconstruct_denoise_and_preview_options() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    simulate(&cap, "4");
    let run = |name: &str, extra: &[&str]| {
        let out = tmp.path().join(name);
        let mut args = vec![
            "reconstruct",
            cap.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        ok(&args);
        let report: toml::Table =
            toml::from_str(&std::fs::read_to_string(out.join("report.toml")).unwrap()).unwrap();
        (read(&out.join("linear.npy")), report)
    };
    let (none, report) = run("none", &["--denoise", "none"]);
    assert!(!report.contains_key("denoise"));
    let (chroma, report) = run("chroma", &[]);
    let denoise = report["denoise"].as_table().unwrap();
    assert_eq!(denoise["method"].as_str(), Some("chroma-bm3d"));
    assert_eq!(denoise["sigma_source"].as_str(), Some("binomial-model"));
    let (plain, report) = run("plain", &["--denoise", "bm3d", "--tonemap", "mantiuk06"]);
    assert_eq!(report["denoise"]["method"].as_str(), Some("bm3d"));
    assert_eq!(
        report["preview"]["tonemap"]["operator"].as_str(),
        Some("mantiuk06")
    );
    let (_, report) = run(
        "given",
        &["--sigma-y", "0.5", "--sigma-c", "3", "--mesopic", "-1"],
    );
    let sigmas = report["denoise"]["sigmas"].as_array().unwrap();
    assert_eq!(sigmas[0].as_float(), Some(0.5));
    assert_eq!(sigmas[1].as_float(), Some(3.0));
    assert_eq!(report["preview"]["mesopic"]["l0"].as_float(), Some(-1.0));
    assert!(report["preview"]["mesopic"]["frames"].as_float().unwrap() > 0.0);
    assert_ne!(none, chroma);
    assert_ne!(chroma, plain);
    // The fast profile (docs/speed.md) reaches the stages it names, and report.toml lists
    // its settings; a --config goes over it.
    let (fast, report) = run("fast", &["--profile", "fast"]);
    let config = &report["config"];
    assert_eq!(
        config["denoise"]["bm3d"]["search_window"].as_integer(),
        Some(25)
    );
    assert_eq!(config["denoise"]["bm3d"]["step"].as_integer(), Some(6));
    assert_eq!(config["burst"]["refine"]["passes"].as_integer(), Some(1));
    assert_eq!(
        config["burst"]["refine"]["max_sub_block_motion_px"].as_float(),
        Some(0.7)
    );
    let trajectory = &config["burst"]["trajectory"];
    assert_eq!(trajectory["early_row_step"].as_integer(), Some(2));
    assert_eq!(trajectory["informative_fraction"].as_float(), Some(0.9));
    assert_ne!(fast, chroma);
    let passes = tmp.path().join("passes.toml");
    std::fs::write(&passes, "[burst.refine]\npasses = 2\n").unwrap();
    let (_, report) = run(
        "fast-2",
        &["--profile", "fast", "--config", passes.to_str().unwrap()],
    );
    let config = &report["config"];
    assert_eq!(config["burst"]["refine"]["passes"].as_integer(), Some(2));
    assert_eq!(
        config["burst"]["refine"]["max_sub_block_motion_px"].as_float(),
        Some(0.7)
    );
    expect_failure(
        &[
            "reconstruct",
            cap.to_str().unwrap(),
            "--out",
            tmp.path().join("bad").to_str().unwrap(),
            "--profile",
            "turbo",
        ],
        "turbo",
    );
    expect_failure(
        &[
            "reconstruct",
            cap.to_str().unwrap(),
            "--out",
            tmp.path().join("bad").to_str().unwrap(),
            "--sigma-y=-1",
        ],
        "--sigma-y",
    );
    assert!(!tmp.path().join("bad").exists());
    ok(&[
        "display",
        tmp.path().join("chroma/linear.npy").to_str().unwrap(),
        "--out",
        tmp.path().join("view.tif").to_str().unwrap(),
        "--tonemap",
        "none",
    ]);
    assert!(tmp.path().join("view.tif").exists());
}

#[test]
fn experiment_writes_csv_plot_and_summary_and_rejects_bad_input() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("dr");
    let run = ok(&[
        "experiment",
        "dynamic-range",
        "--quick",
        "--out",
        out.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(stdout.contains("reproduced"), "{stdout}");
    for f in [
        "dynamic_range.csv",
        "snr.csv",
        "dynamic_range.png",
        "snr.png",
        "summary.md",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    let csv = String::from_utf8(read(&out.join("dynamic_range.csv"))).unwrap();
    assert!(csv.starts_with("w,best_performance_db,extended_db,conventional_db\n"));
    assert!(read(&out.join("dynamic_range.png")).starts_with(b"\x89PNG\r\n\x1a\n"));

    let bad = tmp.path().join("bad");
    let err = expect_failure(
        &[
            "experiment",
            "nope",
            "--quick",
            "--out",
            bad.to_str().unwrap(),
        ],
        "nope",
    );
    assert!(err.contains("dynamic-range"), "{err}");
    expect_failure(
        &[
            "experiment",
            "dynamic-range",
            "--scene",
            "builtin:chart",
            "--out",
            bad.to_str().unwrap(),
        ],
        "--scene",
    );
    expect_failure(
        &[
            "experiment",
            "motion",
            "--quick",
            "--scene",
            "/nonexistent/scene.png",
            "--out",
            bad.to_str().unwrap(),
        ],
        "/nonexistent/scene.png",
    );
    assert!(!bad.exists(), "a failed experiment left output");
    let leftovers: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains("partial"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn cmos_capture_reconstructs_and_bad_multibit_metadata_exits_2() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cmos");
    ok(&[
        "simulate",
        "--scene",
        "builtin:chart",
        "--motion",
        "static",
        "--frames",
        "12",
        "--flux",
        "100",
        "--size",
        "64x48",
        "--cfa",
        "bayer",
        "--sensor",
        "cmos",
        "--out",
        cap.to_str().unwrap(),
    ]);
    let rec = tmp.path().join("rec");
    ok(&[
        "reconstruct",
        cap.to_str().unwrap(),
        "--out",
        rec.to_str().unwrap(),
    ]);
    let scores = ok(&[
        "eval",
        rec.join("linear.npy").to_str().unwrap(),
        cap.join("ground_truth.npy").to_str().unwrap(),
        "--border",
        "6",
        "--no-lpips",
    ]);
    let text = String::from_utf8_lossy(&scores.stdout);
    let psnr: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("psnr_srgb = "))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no psnr_srgb in {text}"));
    assert!(psnr > 18.0, "{text}");

    let out = tmp.path().join("out");
    let out_s = out.to_str().unwrap();
    let toml = std::fs::read_to_string(cap.join("capture.toml")).unwrap();
    std::fs::write(
        cap.join("capture.toml"),
        toml.replace("bit_depth = 10", "bit_depth = 0"),
    )
    .unwrap();
    let err = expect_failure(
        &["reconstruct", cap.to_str().unwrap(), "--out", out_s],
        "capture.toml",
    );
    assert!(err.contains("`bit_depth`"), "{err}");
    let no_gain: String = toml
        .lines()
        .filter(|l| !l.starts_with("gain_e_per_dn"))
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(cap.join("capture.toml"), no_gain).unwrap();
    let err = expect_failure(
        &["reconstruct", cap.to_str().unwrap(), "--out", out_s],
        "capture.toml",
    );
    assert!(err.contains("missing `gain_e_per_dn`"), "{err}");
    assert!(!out.exists(), "partial output left behind");
}

#[test]
fn an_unknown_quantacolor_isa_exits_2_naming_the_variable_value_and_choices() {
    let run = |value: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_quantacolor"))
            .arg("--version")
            .env("QUANTACOLOR_ISA", value)
            .output()
            .expect("binary runs")
    };
    for good in ["generic", "AVX2", "native", ""] {
        let out = run(good);
        assert!(
            out.status.success(),
            "QUANTACOLOR_ISA={good:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let out = run("sse9");
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    for word in ["QUANTACOLOR_ISA", "sse9", "generic", "avx2", "native"] {
        assert!(err.contains(word), "error {err:?} does not name {word}");
    }
}

/// Negative numbers are option values (`--sigma-y -1` reaches the option's own check, not
/// clap's "unexpected argument"), and `eval` given a folder names the file that was meant.
#[test]
fn negative_values_reach_their_checks_and_eval_names_the_file_in_a_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    simulate(&cap, "1");
    let (cap_s, out) = (cap.to_str().unwrap(), tmp.path().join("out"));
    for (option, value, names) in [
        ("--sigma-y", "-1", "--sigma-y must be a non-negative number"),
        ("--block-size", "-3", "invalid value '-3' for '--block-size"),
        ("--frames", "-10:5", "frame window \"-10:5\""),
    ] {
        let args = [
            "reconstruct",
            cap_s,
            "--out",
            out.to_str().unwrap(),
            option,
            value,
        ];
        let err = expect_failure(&args, names);
        assert!(!err.contains("unexpected argument"), "{err}");
        assert!(!out.exists());
    }
    let truth = cap.join("ground_truth.npy");
    let err = expect_failure(&["eval", cap_s, truth.to_str().unwrap()], "is a directory");
    assert!(
        err.contains(&cap.join("linear.npy").display().to_string()),
        "{err}"
    );
}

/// Output into a pipe that closes early (`quantacolor eval … | head -1`) ends the program
/// quietly, by SIGPIPE as a C tool ends, not with a panic.
#[cfg(unix)]
#[test]
fn a_closed_stdout_pipe_ends_the_program_without_a_panic() {
    use std::os::unix::process::ExitStatusExt;
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    simulate(&cap, "1");
    let truth = cap.join("ground_truth.npy");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_quantacolor"))
        .args(["eval", truth.to_str().unwrap(), truth.to_str().unwrap()])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take()); // the reader goes away before the scores are printed
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(
        out.status.signal(),
        Some(libc::SIGPIPE),
        "{:?}: {err}",
        out.status
    );
}

/// An existing, non-empty output directory is refused before any work unless --overwrite, and
/// the earlier result is left as it was; the demo replaces only its own earlier output.
#[test]
fn existing_outputs_are_kept_unless_overwrite() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    simulate(&cap, "7");
    let c = cap.to_str().unwrap();
    let out = tmp.path().join("rec");
    let o = out.to_str().unwrap();
    ok(&["reconstruct", c, "--out", o]);
    let burst = read(&out.join("linear.npy"));
    let err = expect_failure(
        &["reconstruct", c, "--out", o, "--method", "naive"],
        "--overwrite",
    );
    assert!(err.contains(o), "{err}");
    assert_eq!(
        read(&out.join("linear.npy")),
        burst,
        "the earlier result changed"
    );
    ok(&[
        "reconstruct",
        c,
        "--out",
        o,
        "--method",
        "naive",
        "--overwrite",
    ]);
    assert_ne!(read(&out.join("linear.npy")), burst);
    // The same rule for a capture, a motion estimate and a file where a directory belongs.
    expect_failure(
        &["simulate", "--frames", "32", "--size", "32x32", "--out", c],
        "--overwrite",
    );
    let flow = tmp.path().join("flow");
    ok(&["align", c, "--out", flow.to_str().unwrap()]);
    expect_failure(
        &["align", c, "--out", flow.to_str().unwrap()],
        "--overwrite",
    );
    expect_failure(
        &["cfa", "compare", "--out", flow.to_str().unwrap()],
        "--overwrite",
    );
    let file = tmp.path().join("file");
    std::fs::write(&file, b"x").unwrap();
    expect_failure(
        &["reconstruct", c, "--out", file.to_str().unwrap()],
        "not a directory",
    );
}

/// A command that writes results says so in one line on stderr (what, where, how long), stdout
/// stays empty, and --quiet silences it.
#[test]
fn success_is_one_line_on_stderr_unless_quiet() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    simulate(&cap, "8");
    let out = tmp.path().join("rec");
    let run = quantacolor(&[
        "reconstruct",
        cap.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(
        stderr.starts_with("reconstruct: wrote ")
            && stderr.contains(out.to_str().unwrap())
            && stderr.trim_end().ends_with(" s"),
        "{stderr}"
    );
    assert!(run.stdout.is_empty());
    let quiet = tmp.path().join("quiet");
    let run = quantacolor(&[
        "reconstruct",
        cap.to_str().unwrap(),
        "--out",
        quiet.to_str().unwrap(),
        "--quiet",
    ]);
    assert!(run.status.success() && run.stderr.is_empty() && run.stdout.is_empty());
}

/// `--method naive` is the plain sum the README calls it: not denoised unless --denoise says so.
#[test]
fn the_naive_method_is_not_denoised_unless_asked() {
    let tmp = tempfile::tempdir().unwrap();
    let cap = tmp.path().join("cap");
    simulate(&cap, "9");
    let c = cap.to_str().unwrap();
    let run = |name: &str, extra: &[&str]| {
        let out = tmp.path().join(name);
        ok(&[
            &[
                "reconstruct",
                c,
                "--out",
                out.to_str().unwrap(),
                "--method",
                "naive",
            ],
            extra,
        ]
        .concat());
        (
            read(&out.join("linear.npy")),
            std::fs::read_to_string(out.join("report.toml")).unwrap(),
        )
    };
    let (plain, report) = run("plain", &[]);
    let (none, _) = run("none", &["--denoise", "none"]);
    let (denoised, denoised_report) = run("denoised", &["--denoise", "chroma-bm3d"]);
    assert_eq!(plain, none);
    assert_ne!(plain, denoised);
    assert!(
        !report.contains("[denoise]\nmethod = \"chroma-bm3d\""),
        "{report}"
    );
    assert!(denoised_report.contains("chroma-bm3d"), "{denoised_report}");
}
