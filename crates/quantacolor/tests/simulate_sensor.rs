//! Simulator sensor tests: bit densities against paper Eq. 2, ground truth against the flux
//! definition, dark counts and hot pixels, determinism, the CMOS output range.

use ndarray::Array2;
use quantacolor::capture::BinaryFrames;
use quantacolor::cfa::{self, Cfa, Channel, Pattern};
use quantacolor::progress::Silent;
use quantacolor::simulate::{
    simulate, simulate_cmos, simulate_with_cfa, FluxSpec, Scene, SensorKind, SimulationConfig,
};

fn flat_config(sensor: SensorKind, flux: f64, frames: usize) -> SimulationConfig {
    SimulationConfig {
        height: 32,
        width: 48,
        frames,
        cfa: "rgbw-75-regular".into(),
        sensor,
        flux: FluxSpec::Mean { flux },
        hot_fraction: 0.0,
        seed: 7,
        ..SimulationConfig::default()
    }
}

/// Per-pixel fraction of ones over all frames.
fn densities(sim: &quantacolor::simulate::SimulatedCapture) -> Array2<f64> {
    let frames = BinaryFrames::from_packed(sim.packed_frames.clone(), sim.width).unwrap();
    let t = frames.frame_count() as f64;
    frames
        .sum_range(0..frames.frame_count())
        .mapv(|c| c as f64 / t)
}

/// Expected λ per channel on a flat grey scene: W = flux, split by the Table 1 efficiencies.
fn flat_lambda(qe: [f64; 3], flux: f64) -> [f64; 4] {
    let s: f64 = qe.iter().sum();
    [qe[0] / s * flux, qe[1] / s * flux, qe[2] / s * flux, flux]
}

#[test]
fn spad_bit_density_follows_eq2_per_channel() {
    let flux = 0.5;
    let config = flat_config(SensorKind::Spad, flux, 400);
    let sim = simulate(&config, &Scene::Constant([0.5; 3]), &Silent).unwrap();
    let dens = densities(&sim);
    let lambda = flat_lambda([0.09, 0.14, 0.13], flux);
    for ch in Channel::ALL {
        let mask = sim.cfa.mask(ch);
        let (mut measured, mut expected, mut n) = (0.0, 0.0, 0.0);
        for ((y, x), &m) in mask.indexed_iter() {
            if m {
                let d = sim.dark_count_rates_hz[[y, x]] * sim.meta.exposure_s;
                measured += dens[[y, x]];
                expected += 1.0 - (-(lambda[ch.index()] + d)).exp();
                n += 1.0;
            }
        }
        let (measured, expected) = (measured / n, expected / n);
        let sigma = (expected * (1.0 - expected) / (n * 400.0)).sqrt();
        assert!(
            (measured - expected).abs() < 5.0 * sigma,
            "{ch:?}: density {measured} vs 1 - exp(-(λ + d)) = {expected} (σ {sigma})"
        );
    }
}

#[test]
fn ground_truth_equals_the_flux_definition() {
    let flux = 0.25;
    let sim = simulate(
        &flat_config(SensorKind::Spad, flux, 2),
        &Scene::Constant([0.5; 3]),
        &Silent,
    )
    .unwrap();
    let lambda = flat_lambda([0.09, 0.14, 0.13], flux);
    for ((y, x, k), &v) in sim.ground_truth.indexed_iter() {
        let l = lambda[k];
        assert!(
            (v as f64 - l).abs() < 1e-5 * l,
            "({y}, {x}, {k}): {v} vs {l}"
        );
    }
    assert_eq!(sim.meta.w_weights, [1.0, 1.0, 1.0]);
    assert_eq!(sim.meta.reference_frame, Some(1));
    assert!((sim.meta.exposure_s - 1.0 / 24_000.0).abs() < 1e-15);
}

#[test]
fn peak_percentile_pins_the_hdr_highlights() {
    let config = SimulationConfig {
        height: 64,
        width: 96,
        frames: 2,
        flux: FluxSpec::Percentile {
            percentile: 50.0,
            peak: 0.3,
        },
        ..SimulationConfig::default()
    };
    let sim = simulate(&config, &Scene::Chart { hdr: true }, &Silent).unwrap();
    let mut w: Vec<f32> = sim
        .ground_truth
        .outer_iter()
        .flat_map(|r| r.outer_iter().map(|v| v.sum()).collect::<Vec<_>>())
        .collect();
    w.sort_by(f32::total_cmp);
    let median = w[((w.len() - 1) as f64 * 0.5).round() as usize];
    assert!((median - 0.3).abs() < 1e-5, "median W {median}");
    // The light source is about 1000x the white patch: far above the median.
    assert!(*w.last().unwrap() > 100.0 * median);
}

#[test]
fn jot_density_includes_read_noise_false_positives() {
    let flux = 0.5;
    let config = flat_config(SensorKind::Jot, flux, 300);
    let sim = simulate(&config, &Scene::Constant([0.5; 3]), &Silent).unwrap();
    let dens = densities(&sim);
    let lambda = flat_lambda([0.71, 0.79, 0.69], flux);
    // σ = 0.24 e-, threshold 0.5 e-: P(1 | n=0) = Q(0.5/0.24) = 0.018610, P(1 | n=1) = 0.981390.
    let (q0, q1) = (0.018_610, 0.981_390);
    for ch in Channel::ALL {
        let mask = sim.cfa.mask(ch);
        let l = lambda[ch.index()];
        let p = (-l).exp() * (q0 + l * q1) + (1.0 - (-l).exp() * (1.0 + l));
        let (sum, n) = mask
            .indexed_iter()
            .filter(|(_, &m)| m)
            .fold((0.0, 0.0), |(s, n), ((y, x), _)| {
                (s + dens[[y, x]], n + 1.0)
            });
        let sigma = (p * (1.0 - p) / (n * 300.0)).sqrt();
        assert!(
            (sum / n - p).abs() < 5.0 * sigma,
            "{ch:?}: {} vs {p}",
            sum / n
        );
    }
    assert!((sim.meta.exposure_s - 1e-3).abs() < 1e-15);
}

#[test]
fn hot_pixels_have_the_requested_fraction_and_rates() {
    let config = SimulationConfig {
        height: 40,
        width: 50,
        frames: 600,
        hot_fraction: 0.02,
        flux: FluxSpec::Mean { flux: 1e-6 },
        ..flat_config(SensorKind::Spad, 1e-6, 600)
    };
    let sim = simulate(&config, &Scene::Constant([0.5; 3]), &Silent).unwrap();
    let hot = sim.hot_pixels.iter().filter(|&&h| h).count();
    assert_eq!(hot, 40); // round(0.02 · 2000)
    let mut normal = Vec::new();
    for ((y, x), &h) in sim.hot_pixels.indexed_iter() {
        let r = sim.dark_count_rates_hz[[y, x]];
        if h {
            assert!((200.0..=2000.0).contains(&r), "hot rate {r}");
        } else {
            assert!(r < 50.0, "normal rate {r}");
            normal.push(r);
        }
    }
    let mean = normal.iter().sum::<f64>() / normal.len() as f64;
    assert!((sim.meta.dark_count_rate_hz - mean).abs() < 1e-12);
    assert!(
        (mean - 2.0).abs() < 0.1,
        "mean normal rate {mean} (Table 1: 2 cps)"
    );
    // In the dark, hot pixels fire at 1 − exp(−rate·τ) on average.
    let dens = densities(&sim);
    let (mut measured, mut expected) = (0.0, 0.0);
    for ((y, x), &h) in sim.hot_pixels.indexed_iter() {
        if h {
            measured += dens[[y, x]];
            expected += 1.0 - (-sim.dark_count_rates_hz[[y, x]] * sim.meta.exposure_s).exp();
        }
    }
    let sigma = (expected / 40.0 / (40.0 * 600.0)).sqrt() * 40.0;
    assert!(
        (measured - expected).abs() < 5.0 * sigma,
        "{measured} vs {expected}"
    );
}

#[test]
fn same_seed_same_bytes_different_seed_different_bytes() {
    let config = SimulationConfig {
        height: 24,
        width: 37,
        frames: 40,
        motion: "handheld".parse().unwrap(),
        ..SimulationConfig::default()
    };
    let scene = Scene::Chart { hdr: false };
    let a = simulate(&config, &scene, &Silent).unwrap();
    // One worker thread must give the same bytes as the default pool.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let b = pool.install(|| simulate(&config, &scene, &Silent).unwrap());
    assert_eq!(a.packed_frames, b.packed_frames);
    assert_eq!(a.hot_pixels, b.hot_pixels);
    assert_eq!(a.ground_truth, b.ground_truth);
    assert_eq!(a.motion, b.motion);
    let c = simulate(
        &SimulationConfig {
            seed: 2,
            ..config.clone()
        },
        &scene,
        &Silent,
    )
    .unwrap();
    assert_ne!(a.packed_frames, c.packed_frames);
    assert_ne!(a.hot_pixels, c.hot_pixels);
    assert_ne!(a.motion, c.motion);
}

#[test]
fn cmos_frames_stay_in_ten_bits_and_average_the_flux() {
    let config = SimulationConfig {
        height: 16,
        width: 20,
        frames: 50,
        cfa: "bayer".into(),
        flux: FluxSpec::Mean { flux: 60.0 },
        hot_fraction: 0.0,
        ..SimulationConfig::default()
    };
    let sim = simulate_cmos(&config, &Scene::Constant([0.5; 3]), &Silent).unwrap();
    assert_eq!(sim.frames.dim(), (50, 16, 20));
    assert!(sim.frames.iter().all(|&v| v <= 1023));
    assert_eq!(sim.sensor.bit_depth, 10);
    let lambda = flat_lambda([0.59, 0.65, 0.48], 60.0);
    let g = sim.cfa.mask(Channel::G);
    let (sum, n) = sim
        .frames
        .indexed_iter()
        .filter(|((_, y, x), _)| g[[*y, *x]])
        .fold((0.0, 0.0), |(s, n), (_, &v)| (s + v as f64, n + 1.0));
    // black + Poisson(λ) + N(0, 2.4²): std of the mean ≈ sqrt((λ + 5.8) / n).
    let sigma = ((lambda[1] + 5.8) / n).sqrt();
    let black = sim.sensor.black_level_dn;
    assert_eq!(black, 16.0);
    assert!(
        (sum / n - black - lambda[1]).abs() < 5.0 * sigma,
        "{} vs {}",
        sum / n - black,
        lambda[1]
    );
    // Saturation clips at 1023.
    let bright = simulate_cmos(
        &SimulationConfig {
            flux: FluxSpec::Mean { flux: 5000.0 },
            frames: 2,
            ..config
        },
        &Scene::Constant([0.5; 3]),
        &Silent,
    )
    .unwrap();
    assert_eq!(bright.frames.iter().max(), Some(&1023));
    let dir = tempfile::tempdir().unwrap();
    bright.write(dir.path()).unwrap();
    let meta = std::fs::read_to_string(dir.path().join("capture.toml")).unwrap();
    assert!(meta.contains("bit_depth = 10"), "{meta}");
}

#[test]
fn explicit_cfa_and_bad_parameters() {
    let config = flat_config(SensorKind::Spad, 0.1, 4);
    let cfa = Cfa::uniform(32, 48, Channel::W);
    let sim = simulate_with_cfa(&config, &Scene::Constant([0.5; 3]), &cfa, &Silent).unwrap();
    assert_eq!(sim.cfa, cfa);
    let wrong = cfa::generate(&Pattern::Bayer, 10, 10, 0).unwrap();
    assert!(simulate_with_cfa(&config, &Scene::Constant([0.5; 3]), &wrong, &Silent).is_err());
    let bad = SimulationConfig {
        reference_frame: Some(4),
        ..config.clone()
    };
    assert!(simulate(&bad, &Scene::Constant([0.5; 3]), &Silent).is_err());
    let bad = SimulationConfig {
        hot_fraction: 1.5,
        ..config.clone()
    };
    assert!(simulate(&bad, &Scene::Constant([0.5; 3]), &Silent).is_err());
    let bad = SimulationConfig {
        sensor: SensorKind::Cmos,
        ..config
    };
    assert!(simulate(&bad, &Scene::Constant([0.5; 3]), &Silent).is_err());
}
