//! Multi-bit (conventional CMOS) captures through the reconstruction pipeline (paper §6.1):
//! format round trip, metadata errors, a static capture against its ground truth, saturation,
//! and the Gaussian–Poisson model of `model.rs` against the simulator.

use ndarray::{Array2, Array3};
use quantacolor::capture::{write_capture, Capture, CaptureMeta, CaptureParts, FrameData};
use quantacolor::denoise::anscombe::Stabiliser;
use quantacolor::denoise::chroma::DenoiseMethod;
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::model::{read_noise_false_positive_dark, GaussianPoisson, PixelModel, Readout};
use quantacolor::pipeline::{reconstruct, Method, ReconstructConfig};
use quantacolor::progress::Silent;
use quantacolor::simulate::{
    simulate, simulate_cmos, FluxSpec, MotionConfig, Scene, SensorKind, SimulationConfig,
};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal, Poisson};

fn cmos_config(flux: f64, frames: usize) -> SimulationConfig {
    SimulationConfig {
        height: 48,
        width: 64,
        frames,
        cfa: "bayer".into(),
        sensor: SensorKind::Cmos,
        flux: FluxSpec::Mean { flux },
        motion: MotionConfig::Static,
        hot_fraction: 0.0,
        seed: 3,
        ..SimulationConfig::default()
    }
}

fn no_denoise(method: Method) -> ReconstructConfig {
    let mut rc = ReconstructConfig {
        method,
        ..Default::default()
    };
    rc.denoise.method = DenoiseMethod::None;
    rc
}

/// Mean of channel `c` of an (H, W, 3) image inside `border`.
fn channel_mean(img: &Array3<f32>, c: usize, border: usize) -> f64 {
    let (h, w, _) = img.dim();
    let mut sum = 0.0;
    let mut n = 0.0;
    for y in border..h - border {
        for x in border..w - border {
            sum += img[[y, x, c]] as f64;
            n += 1.0;
        }
    }
    sum / n
}

#[test]
fn cmos_capture_round_trips_through_the_format() {
    let sim = simulate_cmos(&cmos_config(40.0, 6), &Scene::Constant([0.5; 3]), &Silent).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cmos");
    sim.write(&path).unwrap();
    let text = std::fs::read_to_string(path.join("capture.toml")).unwrap();
    for key in [
        "bit_depth = 10",
        "read_noise_e = 2.4",
        "gain_e_per_dn = 1.0",
        "black_level_dn = 16.0",
        "dark_current_e_per_s",
    ] {
        assert!(text.contains(key), "{key} missing from\n{text}");
    }
    assert!(!text.contains("dark_count_rate_hz"), "{text}");
    let cap = Capture::open(&path).unwrap();
    assert_eq!(cap.meta, sim.meta);
    assert!(cap.frames.is_multibit());
    assert_eq!(cap.frames.to_multibit().unwrap(), sim.frames);
    let sums = cap.frames.sum_range(1..5);
    let expected = Array2::from_shape_fn((48, 64), |(y, x)| {
        (1..5).map(|t| sim.frames[[t, y, x]] as u32).sum::<u32>()
    });
    assert_eq!(sums, expected);
    assert_eq!(cap.frames.sample(2, 3, 4), sim.frames[[2, 3, 4]] as u32);
    // Metadata text round trip, and `full_well_e` as the alternative to the gain.
    let again = CaptureMeta::from_toml_str(&sim.meta.to_toml_string(None).unwrap(), "x").unwrap();
    assert_eq!(again, sim.meta);
    let fw = CaptureMeta::from_toml_str(
        "exposure_s = 0.01\nbit_depth = 12\nfull_well_e = 8000\nblack_level_dn = 95\n",
        "x",
    )
    .unwrap();
    let m = fw.multibit.unwrap();
    assert!((m.gain_e_per_dn - 8000.0 / (4095.0 - 95.0)).abs() < 1e-12);
    match fw.pixel_model().readout {
        Readout::GaussianPoisson(g) => assert!((g.full_well_e() - 8000.0).abs() < 1e-9),
        Readout::Binary => panic!("a 12-bit capture is not binary"),
    }
}

#[test]
fn bad_multibit_metadata_is_a_clear_error() {
    let cases = [
        (
            "exposure_s = 0.01\nbit_depth = 0\ngain_e_per_dn = 1\n",
            "`bit_depth`",
        ),
        (
            "exposure_s = 0.01\nbit_depth = 17\ngain_e_per_dn = 1\n",
            "`bit_depth`",
        ),
        (
            "exposure_s = 0.01\nbit_depth = 10\n",
            "missing `gain_e_per_dn`",
        ),
        (
            "exposure_s = 0.01\nbit_depth = 10\ngain_e_per_dn = -1\n",
            "`gain_e_per_dn`",
        ),
        (
            "exposure_s = 0.01\nbit_depth = 10\ngain_e_per_dn = 1\nfull_well_e = 1000\n",
            "not both",
        ),
        (
            "exposure_s = 0.01\nbit_depth = 10\ngain_e_per_dn = 1\nblack_level_dn = 2000\n",
            "`black_level_dn`",
        ),
        (
            "exposure_s = 0.01\ngain_e_per_dn = 1\n",
            "only for multi-bit",
        ),
        (
            "exposure_s = 0.01\nbit_depth = \"ten\"\n",
            "`bit_depth` must be an integer",
        ),
        (
            "exposure_s = 0.01\ndark_count_rate_hz = 1\ndark_current_e_per_s = 1\n",
            "not both",
        ),
        ("exposure_s = 0.01\nread_noise_e = -0.5\n", "`read_noise_e`"),
    ];
    for (text, want) in cases {
        let err = CaptureMeta::from_toml_str(text, "cap/capture.toml")
            .unwrap_err()
            .to_string();
        assert!(err.contains(want), "{text:?}: {err}");
        assert!(err.contains("cap/capture.toml"), "{err}");
    }
}

#[test]
fn frames_and_metadata_must_agree() {
    let sim = simulate_cmos(&cmos_config(40.0, 3), &Scene::Constant([0.5; 3]), &Silent).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cmos");
    sim.write(&path).unwrap();
    let toml_path = path.join("capture.toml");
    let text = std::fs::read_to_string(&toml_path).unwrap();
    // uint16 frames without a bit depth.
    let binary: String = text
        .lines()
        .filter(|l| {
            !["bit_depth", "gain_e_per_dn", "black_level_dn"]
                .iter()
                .any(|k| l.starts_with(k))
        })
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(&toml_path, &binary).unwrap();
    let err = Capture::open(&path).unwrap_err().to_string();
    assert!(
        err.contains("frames.npy") && err.contains("no `bit_depth`"),
        "{err}"
    );
    // A sample above full scale.
    let four_bits = text
        .replace("bit_depth = 10", "bit_depth = 4")
        .replace("black_level_dn = 16.0", "black_level_dn = 0.0");
    std::fs::write(&toml_path, four_bits).unwrap();
    let err = Capture::open(&path).unwrap_err().to_string();
    assert!(err.contains("above the full scale 15"), "{err}");
    // A bit depth on binary frames.
    let spad = simulate(
        &SimulationConfig {
            sensor: SensorKind::Spad,
            ..cmos_config(0.5, 8)
        },
        &Scene::Constant([0.5; 3]),
        &Silent,
    )
    .unwrap();
    let spad_path = dir.path().join("spad");
    spad.write(&spad_path).unwrap();
    let meta = spad_path.join("capture.toml");
    let t = std::fs::read_to_string(&meta).unwrap();
    std::fs::write(&meta, format!("bit_depth = 10\ngain_e_per_dn = 1\n{t}")).unwrap();
    let err = Capture::open(&spad_path).unwrap_err().to_string();
    assert!(err.contains("frames are binary"), "{err}");
    // The writer refuses the same mismatches before touching the disk.
    let parts = CaptureParts {
        frames: FrameData::MultiBit(&sim.frames),
        meta: &spad.meta,
        ..sim.capture_parts().unwrap()
    };
    assert!(write_capture(dir.path().join("bad"), &parts).is_err());
    assert!(!dir.path().join("bad").exists());
}

#[test]
fn static_cmos_capture_reconstructs_its_ground_truth() {
    let scene = Scene::from_spec("builtin:chart").unwrap();
    let sim = simulate_cmos(&cmos_config(150.0, 24), &scene, &Silent).unwrap();
    let cap = sim.to_capture().unwrap();
    let opts = EvalOptions {
        border: 6,
        normalize_percentile: Some(99.5),
    };
    let burst = reconstruct(&cap, &no_denoise(Method::Burst), &Silent).unwrap();
    let naive = reconstruct(&cap, &no_denoise(Method::Naive), &Silent).unwrap();
    let b = evaluate(burst.linear.view(), sim.ground_truth.view(), &opts).unwrap();
    let n = evaluate(naive.linear.view(), sim.ground_truth.view(), &opts).unwrap();
    // Each frame is its own block (paper §6.1).
    let rec = burst.burst.as_ref().unwrap();
    assert_eq!(rec.alignment.plan.block_size, 1);
    assert_eq!(rec.sub_blocks.len(), 24);
    // The static 64x48 chart behind Bayer is limited by demosaicing (a SPAD capture of 2000
    // frames scores about the same); a wrong black level or gain costs far more.
    assert!(b.psnr_srgb > 19.0, "burst {b:?}");
    assert!(n.psnr_srgb > 17.0, "naive {n:?}");
    // With denoising (the Gaussian–Poisson stabiliser) the result stays as good or better.
    let den = reconstruct(&cap, &ReconstructConfig::default(), &Silent).unwrap();
    let d = evaluate(den.linear.view(), sim.ground_truth.view(), &opts).unwrap();
    assert!(d.psnr_srgb > b.psnr_srgb - 0.5, "denoised {d:?} vs {b:?}");
    assert_eq!(
        den.denoise.unwrap().sigma_source,
        quantacolor::denoise::chroma::SigmaSource::GaussianPoissonModel
    );
}

#[test]
fn flat_cmos_capture_is_unbiased() {
    // A flat grey scene: the merged flux of every channel matches the truth to well under its
    // noise (a black level or dark current left in would be +16 e-, a wrong gain a factor).
    let sim = simulate_cmos(&cmos_config(30.0, 40), &Scene::Constant([0.5; 3]), &Silent).unwrap();
    let cap = sim.to_capture().unwrap();
    for method in [Method::Burst, Method::Naive] {
        let rec = reconstruct(&cap, &no_denoise(method), &Silent).unwrap();
        for c in 0..3 {
            let (est, truth) = (
                channel_mean(&rec.linear, c, 4),
                channel_mean(&sim.ground_truth, c, 4),
            );
            assert!(
                (est - truth).abs() < 0.02 * truth,
                "{method:?} channel {c}: {est} vs {truth}"
            );
        }
    }
}

#[test]
fn saturated_patch_reads_full_well_not_dark() {
    // A bright square 40x the background: above the 1007 e- full well of a 10-bit sensor with a
    // 16 DN black level, while the background is well exposed.
    let (h, w) = (48, 64);
    let image = Array3::from_shape_fn((h, w, 3), |(y, x, _)| {
        if (16..32).contains(&y) && (24..40).contains(&x) {
            4.0
        } else {
            0.1
        }
    });
    let scene = Scene::from_linear(image, "patch").unwrap();
    let config = SimulationConfig {
        flux: FluxSpec::Percentile {
            percentile: 10.0,
            peak: 150.0,
        },
        ..cmos_config(0.0, 12)
    };
    let sim = simulate_cmos(&config, &scene, &Silent).unwrap();
    assert_eq!(sim.frames.iter().max(), Some(&1023));
    let cap = sim.to_capture().unwrap();
    let full_well = match cap.meta.pixel_model().readout {
        Readout::GaussianPoisson(g) => g.full_well_e(),
        Readout::Binary => unreachable!(),
    };
    for method in [Method::Burst, Method::Naive] {
        let rec = reconstruct(&cap, &no_denoise(method), &Silent).unwrap();
        for c in 0..3 {
            let centre = rec.linear[[24, 32, c]] as f64;
            let truth = sim.ground_truth[[24, 32, c]] as f64;
            assert!(
                truth > full_well,
                "the patch must be above full well: {truth}"
            );
            assert!(
                centre.is_finite() && centre > 0.9 * full_well && centre <= full_well + 1.0,
                "{method:?} channel {c}: patch reads {centre}, full well {full_well}"
            );
            let bg = rec.linear[[4, 4, c]] as f64;
            let bg_truth = sim.ground_truth[[4, 4, c]] as f64;
            assert!(
                (bg - bg_truth).abs() < 0.25 * bg_truth,
                "{bg} vs {bg_truth}"
            );
        }
    }
}

#[test]
fn gaussian_poisson_model_matches_simulated_samples() {
    let g = GaussianPoisson {
        gain_e_per_dn: 2.0,
        read_noise_e: 3.0,
        black_level_dn: 64.0,
        saturation_dn: 4095.0,
    };
    let model = PixelModel {
        dark_per_frame: 0.5,
        readout: Readout::GaussianPoisson(g),
    };
    let lambda = 40.0;
    // The inversion undoes the mean.
    assert!((model.flux(model.mean_sample(lambda), 10.0) - lambda).abs() < 1e-9);
    // Full scale reads full well − dark.
    assert!((model.flux(5000.0, 3.0) - (g.full_well_e() - 0.5)).abs() < 1e-9);
    // Monte Carlo of the digitised samples: mean and variance of the estimate.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let poisson = Poisson::new(lambda + 0.5).unwrap();
    let normal = Normal::new(0.0, 3.0).unwrap();
    let n = 20.0;
    let estimates: Vec<f64> = (0..4000)
        .map(|_| {
            let sum: f64 = (0..n as usize)
                .map(|_| {
                    let e: f64 = poisson.sample(&mut rng) + normal.sample(&mut rng);
                    (64.0 + e / 2.0).round().clamp(0.0, 4095.0)
                })
                .sum();
            model.flux(sum / n, n)
        })
        .collect();
    let mean = estimates.iter().sum::<f64>() / estimates.len() as f64;
    let var =
        estimates.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / (estimates.len() - 1) as f64;
    let predicted = model.flux_variance(lambda, n);
    assert!(
        (mean - lambda).abs() < 4.0 * (predicted / 4000.0).sqrt(),
        "{mean}"
    );
    assert!((var / predicted - 1.0).abs() < 0.08, "{var} vs {predicted}");
    // Per-sample variance in DN² (grey-value noise of the merge).
    let dn_var = model.sample_variance(model.mean_sample(lambda));
    assert!((dn_var - predicted * n / 4.0).abs() < 1e-9);
    // The stabiliser gives unit variance and inverts.
    let stab = Stabiliser::new(model, n).unwrap();
    let a: Vec<f64> = estimates.iter().map(|&e| stab.forward(e)).collect();
    let am = a.iter().sum::<f64>() / a.len() as f64;
    let av = a.iter().map(|v| (v - am).powi(2)).sum::<f64>() / (a.len() - 1) as f64;
    assert!((av - 1.0).abs() < 0.08, "stabilised variance {av}");
    assert!(
        (stab.inverse(am) - lambda).abs() < 0.1,
        "{}",
        stab.inverse(am)
    );
}

#[test]
fn jot_read_noise_counts_as_dark() {
    // Q(0.5 / 0.24) = 0.01861: −ln(1 − Q) equivalent dark counts per frame.
    let d = read_noise_false_positive_dark(0.24);
    assert!((d - 0.018_786).abs() < 1e-5, "{d}");
    assert_eq!(read_noise_false_positive_dark(0.0), 0.0);
    let jot = simulate(
        &SimulationConfig {
            sensor: SensorKind::Jot,
            cfa: "rgbw-75-regular".into(),
            ..cmos_config(0.3, 400)
        },
        &Scene::Constant([0.5; 3]),
        &Silent,
    )
    .unwrap();
    assert_eq!(jot.meta.read_noise_e, 0.24);
    assert!(jot.meta.multibit.is_none());
    let dir = tempfile::tempdir().unwrap();
    jot.write(dir.path().join("jot")).unwrap();
    let cap = Capture::open(dir.path().join("jot")).unwrap();
    assert_eq!(cap.meta, jot.meta);
    let rec = reconstruct(&cap, &no_denoise(Method::Naive), &Silent).unwrap();
    // The flat W level is unbiased once the false positives are removed as dark counts.
    let truth = channel_mean(&jot.ground_truth, 1, 2);
    let est = channel_mean(&rec.linear, 1, 2);
    assert!((est - truth).abs() < 0.05 * truth, "{est} vs {truth}");
}
