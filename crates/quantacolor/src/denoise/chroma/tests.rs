//! The tests of chroma-BM3D's settings, colour transforms and noise estimate.

#![forbid(unsafe_code)]

use super::*;
use ndarray::Array2;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

#[test]
fn channel_sigmas_take_the_gains_or_the_given_sigmas() {
    let modelled = [1.0, 2.0, 2.0];
    let chroma = DenoiseConfig {
        luma_gain: 1.5,
        chroma_gain: 3.0,
        ..DenoiseConfig::default()
    };
    assert_eq!(
        chroma.channel_sigmas(modelled, SigmaSource::BinomialModel),
        ([1.5, 6.0, 6.0], SigmaSource::BinomialModel)
    );
    // Plain BM3D: one σ, the RMS over the channels (√3 here) times the luma gain.
    let plain = DenoiseConfig {
        method: DenoiseMethod::Bm3d,
        ..chroma.clone()
    };
    let (sigmas, _) = plain.channel_sigmas(modelled, SigmaSource::BinomialModel);
    assert!(sigmas.iter().all(|&s| (s - 3f32.sqrt() * 1.5).abs() < 1e-6));
    // Given σs replace the modelled ones (σ_c only for chroma-BM3D), and say so.
    let given = DenoiseConfig {
        sigma_y: Some(0.5),
        sigma_c: Some(4.0),
        ..chroma
    };
    assert_eq!(
        given.channel_sigmas(modelled, SigmaSource::BinomialModel),
        ([0.5, 4.0, 4.0], SigmaSource::Given)
    );
    let given_plain = DenoiseConfig {
        method: DenoiseMethod::Bm3d,
        ..given
    };
    assert_eq!(
        given_plain
            .channel_sigmas(modelled, SigmaSource::BinomialModel)
            .0,
        [0.5; 3]
    );
}

#[test]
fn scale_to_255_maps_the_plane_range_and_leaves_a_constant_plane() {
    let ramp = Array2::from_shape_fn((2, 3), |(y, x)| 10.0 + (3 * y + x) as f32 * 2.0);
    assert_eq!(scale_to_255(ramp.view()), 25.5);
    assert_eq!(scale_to_255(Array2::from_elem((2, 2), 7.0f32).view()), 1.0);
}

#[test]
fn sigma_settings_are_checked_by_name() {
    for (config, name) in [
        (
            DenoiseConfig {
                chroma_gain: 0.0,
                ..DenoiseConfig::default()
            },
            "chroma_gain",
        ),
        (
            DenoiseConfig {
                sigma_y: Some(f32::NAN),
                ..DenoiseConfig::default()
            },
            "sigma_y",
        ),
    ] {
        let err = config.validate_sigmas().unwrap_err().to_string();
        assert!(err.contains(name), "{err}");
    }
    assert!(DenoiseConfig::default().validate_sigmas().is_ok());
}

fn matmul(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut out = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    out
}

#[test]
fn transforms_invert_and_luma_is_the_w_combination() {
    let w = [0.9, 1.1, 0.7];
    for t in [
        ColorTransform::w_weighted_ycbcr(w).unwrap(),
        ColorTransform::opponent(),
    ] {
        let id = matmul(&t.inverse, &t.forward);
        for (i, row) in id.iter().enumerate() {
            for (j, &v) in row.iter().enumerate() {
                assert!((v - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
    }
    let t = ColorTransform::w_weighted_ycbcr(w).unwrap();
    let rgb = [0.2, 0.5, 0.9];
    let ycc = ColorTransform::apply(&t.forward, rgb);
    let white: f64 = rgb.iter().zip(w).map(|(c, k)| c * k).sum();
    assert!((ycc[0] - white / w.iter().sum::<f64>()).abs() < 1e-12);
    // Grey has zero chroma.
    let grey = ColorTransform::apply(&t.forward, [0.4; 3]);
    assert!(grey[1].abs() < 1e-12 && grey[2].abs() < 1e-12);
    assert!(ColorTransform::w_weighted_ycbcr([1.0, 0.0, 1.0]).is_err());
}

#[test]
fn mad_sigma_recovers_gaussian_noise() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let normal = Normal::new(0.0f32, 2.5).unwrap();
    let plane = Array2::from_shape_fn((200, 200), |(y, x)| {
        (y as f32 * 0.1).sin() * 20.0 + x as f32 * 0.05 + normal.sample(&mut rng)
    });
    let s = mad_sigma(plane.view());
    assert!((s - 2.5).abs() < 0.15, "{s}");
}

#[test]
fn none_is_the_identity_and_bad_input_is_an_error() {
    let img = Array3::<f32>::from_shape_fn((16, 16, 3), |(y, x, c)| (y + x + c) as f32 * 0.01);
    let input = DenoiseInput {
        noise: None,
        frames: 100.0,
        model: PixelModel::binary(0.0),
        w_weights: [1.0; 3],
    };
    let config = DenoiseConfig {
        method: DenoiseMethod::None,
        ..Default::default()
    };
    let (out, report) = denoise_linear(img.view(), &input, &config).unwrap();
    assert_eq!(out, img);
    assert!(report.is_none());
    let bad = DenoiseConfig {
        sigma_y: Some(-1.0),
        ..Default::default()
    };
    assert!(denoise_linear(img.view(), &input, &bad).is_err());
    let two = Array3::<f32>::zeros((16, 16, 2));
    assert!(denoise_linear(two.view(), &input, &DenoiseConfig::default()).is_err());
}

/// The denoiser reports one stage, "denoise", whose advances add up to its total (each scale's
/// pixels), and the result is the silent run's.
#[test]
fn progress_reaches_the_total_of_every_scale() {
    use std::sync::Mutex;
    /// Stages started (label, total), units advanced, finishes.
    #[derive(Default)]
    struct Calls {
        starts: Vec<(String, u64)>,
        done: u64,
        finished: usize,
    }
    #[derive(Default)]
    struct Record(Mutex<Calls>);
    impl Progress for Record {
        fn start(&self, label: &str, total: u64) {
            self.0
                .lock()
                .unwrap()
                .starts
                .push((label.to_string(), total));
        }
        fn advance(&self, n: u64) {
            self.0.lock().unwrap().done += n;
        }
        fn finish(&self) {
            self.0.lock().unwrap().finished += 1;
        }
    }
    let img = Array3::<f32>::from_shape_fn((96, 128, 3), |(y, x, c)| {
        0.05 + 0.01 * ((y * 7 + x * 3 + c * 11) % 13) as f32
    });
    let input = DenoiseInput {
        noise: None,
        frames: 200.0,
        model: PixelModel::binary(0.0),
        w_weights: [1.0; 3],
    };
    let config = DenoiseConfig::default();
    let record = Record::default();
    let (out, _) = denoise_linear_with_progress(img.view(), &input, &config, &record).unwrap();
    let Calls {
        starts,
        done,
        finished,
    } = record.0.into_inner().unwrap();
    assert_eq!(starts.len(), 1, "{starts:?}");
    assert_eq!(starts[0].0, "denoise");
    assert_eq!(done, starts[0].1);
    // 96x128 with 8x8 blocks: the full scale and one 48x64 scale (24x32 is under 4 blocks).
    assert!(config.chroma_scales >= 1);
    assert_eq!(done, (96 * 128 + 48 * 64) as u64);
    assert_eq!(finished, 1);
    let (silent, _) = denoise_linear(img.view(), &input, &config).unwrap();
    assert_eq!(out, silent);
}
