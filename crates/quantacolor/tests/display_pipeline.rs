//! The display pipeline (paper §7, Fig. 14, Fig. 20; supplement §4 Eq. 9–10): colour-matrix fit
//! against a known mixing, tone-mapping properties, the noise-aware low-light blend and render.

use ndarray::{Array3, ArrayView3};
use quantacolor::display::mantiuk::process_log_luminance;
use quantacolor::display::{
    ccm::{chart_patch_means, colorchecker_linear, ColorMatrix},
    mesopic_blend, mesopic_weight, render, tone_map, GlobalConfig, Mantiuk06Config, MesopicConfig,
    MesopicOffset, MesopicParams, RenderOptions, ToneMap,
};
use quantacolor::simulate::chart::chart_value;
use rand::Rng;
use rand_chacha::rand_core::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const LUMA: [f32; 3] = [0.2126, 0.7152, 0.0722];

fn luma(img: &Array3<f32>, y: usize, x: usize) -> f32 {
    (0..3).map(|c| LUMA[c] * img[[y, x, c]]).sum()
}

fn chart(h: usize, w: usize) -> Array3<f32> {
    Array3::from_shape_fn((h, w, 3), |(y, x, c)| {
        chart_value(y as f64, x as f64, h, w, false)[c]
    })
}

/// The chart seen through a camera with mixing `k` and gain `gain`, plus Gaussian noise.
fn mixed_chart(k: &[[f64; 3]; 3], gain: f64, noise: f64, seed: u64) -> Array3<f32> {
    let truth = chart(127, 248);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let n = Normal::new(0.0, noise).unwrap();
    let mut out = truth.clone();
    for ((y, x), _) in truth.slice(ndarray::s![.., .., 0]).indexed_iter() {
        let t = [0, 1, 2].map(|c| truth[[y, x, c]] as f64);
        for c in 0..3 {
            let v = gain * (k[c][0] * t[0] + k[c][1] * t[1] + k[c][2] * t[2]);
            out[[y, x, c]] = (v + n.sample(&mut rng)) as f32;
        }
    }
    out
}

fn random_mixing(seed: u64) -> [[f64; 3]; 3] {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    std::array::from_fn(|i| {
        std::array::from_fn(|j| {
            (i == j) as u8 as f64 * 0.7 + rng.gen_range(0.0..0.3) // crosstalk as in CFA dyes
        })
    })
}

#[test]
#[allow(clippy::needless_range_loop)] // matrix products read clearer with indices
fn colour_fit_recovers_the_inverse_of_a_known_mixing() {
    let k = random_mixing(7);
    let gain = 0.05; // detections per frame for reflectance 1
    let img = mixed_chart(&k, gain, 0.001, 1);
    let means = chart_patch_means(img.view()).unwrap();
    for affine in [false, true] {
        let fit = ColorMatrix::fit(&means, affine).unwrap();
        let m = &fit.matrix;
        let g = m.gain.unwrap();
        // g · M · gain · K should be the identity.
        for i in 0..3 {
            for j in 0..3 {
                let v: f64 = (0..3).map(|l| m.rows[i][l] * k[l][j]).sum::<f64>() * gain * g;
                let want = (i == j) as u8 as f64;
                assert!((v - want).abs() < 0.02, "affine {affine}: ({i},{j}) = {v}");
            }
        }
        if affine {
            for r in &m.rows {
                assert!(r[3].abs() * g < 0.01, "offset {}", r[3]);
            }
        }
        let r = fit.residual;
        assert!(r.delta_e_before > 5.0, "{r:?}");
        assert!(
            r.delta_e_after < 0.25 * r.delta_e_before && r.delta_e_after < 2.0,
            "{r:?}"
        );
        assert!(r.rms_after < 0.5 * r.rms_before, "{r:?}");
        // Applied to the image, the matrix brings the patches to the chart (up to the gain).
        let corrected = m.apply(img.view()).unwrap();
        let cm = chart_patch_means(corrected.view()).unwrap();
        let truth = colorchecker_linear();
        let worst = cm
            .iter()
            .zip(&truth)
            .flat_map(|(p, t)| (0..3).map(move |c| (p[c] * g - t[c]).abs()))
            .fold(0.0f64, f64::max);
        assert!(worst < 0.02, "worst patch error {worst}");
    }
}

#[test]
fn colour_fit_of_an_exact_chart_is_the_identity_and_errors_are_reported() {
    let img = chart(127, 248);
    let fit = ColorMatrix::fit(&chart_patch_means(img.view()).unwrap(), false).unwrap();
    assert!(fit.residual.delta_e_after < 1e-6 && fit.residual.delta_e_before < 1e-6);
    for (i, r) in fit.matrix.rows.iter().enumerate() {
        for (j, v) in r.iter().enumerate() {
            assert!((v - (i == j) as u8 as f64).abs() < 1e-6);
        }
    }
    assert!(ColorMatrix::fit(&[[0.0; 3]; 24], false).is_err());
    assert!(chart_patch_means(Array3::<f32>::zeros((4, 4, 3)).view()).is_err());
}

#[test]
fn identity_matrix_is_bitwise_a_no_op_and_toml_round_trips() {
    let img = mixed_chart(&random_mixing(3), 0.1, 0.01, 2);
    let out = ColorMatrix::identity().apply(img.view()).unwrap();
    assert!(out
        .iter()
        .zip(img.iter())
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    let fit = ColorMatrix::fit(&chart_patch_means(img.view()).unwrap(), true).unwrap();
    let text = fit.matrix.to_toml();
    assert!(
        text.contains("[color_matrix]") && text.contains("rows"),
        "{text}"
    );
    assert_eq!(ColorMatrix::from_toml(&text, "x.toml").unwrap(), fit.matrix);
    let bad = "[color_matrix]\nrows = [[1.0, 0.0], [0.0, 1.0], [0.0, 0.0, 1.0]]\n";
    let err = ColorMatrix::from_toml(bad, "bad.toml")
        .unwrap_err()
        .to_string();
    assert!(err.contains("bad.toml"), "{err}");
}

/// A horizontal log ramp: luminance from 1e-3 to 1e3, grey.
fn log_ramp(h: usize, w: usize) -> Array3<f32> {
    Array3::from_shape_fn((h, w, 3), |(_, x, _)| {
        10f32.powf(-3.0 + 6.0 * x as f32 / (w - 1) as f32)
    })
}

fn row_is_non_decreasing(img: &Array3<f32>, y: usize) -> bool {
    let w = img.dim().1;
    (1..w).all(|x| luma(img, y, x) >= luma(img, y, x - 1) - 1e-6)
}

fn operators() -> [ToneMap; 3] {
    [
        ToneMap::Mantiuk06(Mantiuk06Config::default()),
        ToneMap::Global(GlobalConfig::default()),
        ToneMap::None,
    ]
}

#[test]
fn tone_maps_are_monotonic_bounded_grey_preserving_and_deterministic() {
    let ramp = log_ramp(16, 200);
    for op in operators() {
        let out = tone_map(ramp.view(), None, &op).unwrap();
        assert!(out.iter().all(|v| (0.0..=1.0).contains(v)), "{op:?}");
        for y in [0, 8, 15] {
            assert!(row_is_non_decreasing(&out, y), "{op:?} row {y}");
        }
        // Grey in, grey out (bitwise equal channels).
        assert!(out
            .outer_iter()
            .flat_map(|r| r
                .outer_iter()
                .map(|p| (p[0], p[1], p[2]))
                .collect::<Vec<_>>())
            .all(|(r, g, b)| r == g && g == b));
        // The ramp spans the display: dark at the left, white at the right.
        assert!(
            luma(&out, 8, 0) < 0.05 && luma(&out, 8, 199) > 0.95,
            "{op:?}"
        );
        let again = tone_map(ramp.view(), None, &op).unwrap();
        assert!(out
            .iter()
            .zip(again.iter())
            .all(|(a, b)| a.to_bits() == b.to_bits()));
    }
}

#[test]
fn mantiuk06_keeps_the_order_of_an_hdr_step_and_is_scale_invariant() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    // Left: dim textured room (0.01 +- 20 %), right: a window 1000x brighter.
    let img = Array3::from_shape_fn((40, 60, 3), |(_, x, c)| {
        let base = if x < 30 { 0.01 } else { 10.0 };
        base * (1.0 + 0.2 * rng.gen_range(-1.0f32..1.0)) * [1.0, 0.8, 0.6][c]
    });
    let op = ToneMap::Mantiuk06(Mantiuk06Config::default());
    let out = tone_map(img.view(), None, &op).unwrap();
    let mean = |x0: usize, x1: usize| {
        let mut s = 0.0;
        for y in 0..40 {
            for x in x0..x1 {
                s += luma(&out, y, x);
            }
        }
        s / (40 * (x1 - x0)) as f32
    };
    let (dark, bright) = (mean(0, 28), mean(32, 60));
    assert!(bright > dark + 0.2, "{dark} {bright}");
    // Contrast compression: the dark side stays above the display's black level 10^-2.3 (a
    // global clip at the window's exposure would show it at 0.001).
    assert!(dark > 0.006, "{dark}");
    // Colour kept: red > green > blue as in the input.
    assert!(out[[20, 45, 0]] > out[[20, 45, 1]] && out[[20, 45, 1]] > out[[20, 45, 2]]);
    // x10 exposure: the output barely changes.
    let brighter = img.mapv(|v| v * 10.0);
    let out10 = tone_map(brighter.view(), None, &op).unwrap();
    let max_diff = out
        .iter()
        .zip(out10.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(max_diff < 0.01, "{max_diff}");
    // A smooth ramp stays monotonic.
    let ramp = Array3::from_shape_fn((30, 80, 3), |(y, x, _)| {
        0.1 + x as f32 / 80.0 + 0.01 * y as f32
    });
    let r = tone_map(ramp.view(), None, &op).unwrap();
    for y in 0..30 {
        assert!(row_is_non_decreasing(&r, y));
    }
}

#[test]
fn mantiuk06_converges_on_a_chart_sized_image() {
    let img = Array3::from_shape_fn((254, 496, 3), |(y, x, c)| {
        chart_value(y as f64, x as f64, 254, 496, true)[c] * 0.02
    });
    let config = Mantiuk06Config::default();
    let out = tone_map(img.view(), None, &ToneMap::Mantiuk06(config)).unwrap();
    let log_lum = ndarray::Array2::from_shape_fn((254, 496), |(y, x)| {
        (0..3)
            .map(|c| LUMA[c] * img[[y, x, c]])
            .sum::<f32>()
            .max(1e-6)
            .log10()
    });
    let sol = process_log_luminance(log_lum.view(), &config);
    // At the sensor's size conjugate gradients end near the tolerance (at or close to the
    // iteration cap), and what the cap leaves unsolved moves the display by under two 8-bit
    // levels (1.3 measured).
    assert!(
        sol.relative_residual <= 2.0 * config.tolerance as f64,
        "relative residual {:.2e} after {} iterations, tolerance {:.0e}",
        sol.relative_residual,
        sol.iterations,
        config.tolerance
    );
    let converged = Mantiuk06Config {
        max_iterations: 1500,
        tolerance: 1e-4,
        ..config
    };
    let reference = tone_map(img.view(), None, &ToneMap::Mantiuk06(converged)).unwrap();
    let worst = out
        .iter()
        .zip(reference.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 2.0 / 255.0, "capped vs converged solve: {worst}");
    // A display image: every value in [0, 1], and the HDR chart's range is not collapsed.
    assert!(out.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)));
    let (lo, hi) = out
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    assert!(hi - lo > 0.5, "display range {lo}..{hi}");
}

#[test]
fn mesopic_weight_limits_and_clamp() {
    assert_eq!(mesopic_weight(1.0, 0.0), 1.0); // log10 W = C1
    assert_eq!(mesopic_weight(0.01, 0.0), 0.0); // log10 W = C2
    assert!((mesopic_weight(0.1, 0.0) - 0.5).abs() < 1e-12);
    assert_eq!(mesopic_weight(100.0, 0.0), 1.0);
    assert_eq!(mesopic_weight(1e-4, 0.0), 0.0);
    assert_eq!(mesopic_weight(0.0, 0.0), 0.0);
    // L0 shifts the thresholds by decades.
    assert!((mesopic_weight(0.01, 1.0) - 0.5).abs() < 1e-12);
}

/// Blend parameters with `W` in detections per frame (T = 100 frames, so `T/100 = 1`).
fn per_frame(l0: f64) -> MesopicParams {
    MesopicParams {
        l0,
        frames: 100.0,
        effective_frames: None,
    }
}

/// The noise-aware view at L0 = 0 with `W` in detections per frame (T = 100).
fn meso0() -> Option<MesopicConfig> {
    Some(MesopicConfig {
        l0: MesopicOffset::Fixed(0.0),
        frames: Some(100.0),
    })
}

#[test]
fn mesopic_blend_keeps_bright_colour_and_greys_dark_pixels() {
    let w = [0.9, 1.1, 0.7];
    let bright = Array3::from_shape_fn((4, 5, 3), |(y, x, c)| {
        2.0 + (y + x) as f32 * 0.1 + [0.5, 0.0, -0.7][c]
    });
    let out = mesopic_blend(bright.view(), &per_frame(0.0), w).unwrap();
    assert!(out
        .iter()
        .zip(bright.iter())
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    let dark = bright.mapv(|v| v * 1e-3);
    let out = mesopic_blend(dark.view(), &per_frame(0.0), w).unwrap();
    for y in 0..4 {
        for x in 0..5 {
            let (p, q) = (
                out.slice(ndarray::s![y, x, ..]),
                dark.slice(ndarray::s![y, x, ..]),
            );
            assert!((p[0] - p[1]).abs() < 1e-9 && (p[1] - p[2]).abs() < 1e-9);
            let wl = |v: ArrayView1| (0..3).map(|c| w[c] * v[c] as f64).sum::<f64>();
            assert!((wl(p) - wl(q)).abs() < 1e-6 * wl(q));
        }
    }
    assert!(mesopic_blend(dark.view(), &per_frame(f64::NAN), w).is_err());
}

type ArrayView1<'a> = ndarray::ArrayView1<'a, f32>;

fn dark_colourful(h: usize, w: usize) -> Array3<f32> {
    Array3::from_shape_fn((h, w, 3), |(y, x, c)| {
        let v = if x < w / 2 { 0.001 } else { 5.0 };
        v * [1.0, 0.3, 0.1][c] * (1.0 + 0.01 * y as f32)
    })
}

#[test]
fn render_chains_the_stages_in_order() {
    let img = dark_colourful(8, 12);
    let base = RenderOptions {
        tonemap: ToneMap::None,
        exposure: Some(0.1),
        ..Default::default()
    };
    let plain = render(img.view(), &base).unwrap();
    // Exposure only: values scale and clip.
    assert!((plain[[0, 0, 0]] - 0.0001).abs() < 1e-9);
    assert_eq!(plain[[0, 11, 0]], 0.5);
    let meso = render(
        img.view(),
        &RenderOptions {
            mesopic: meso0(),
            ..base.clone()
        },
    )
    .unwrap();
    let px = |a: &Array3<f32>, x: usize| [a[[0, x, 0]], a[[0, x, 1]], a[[0, x, 2]]];
    let d = px(&meso, 0);
    assert!(d[0] == d[1] && d[1] == d[2], "dark side grey: {d:?}");
    assert_eq!(
        px(&meso, 11),
        px(&plain, 11),
        "bright side keeps its colour"
    );
    // The colour matrix runs before the blend: swapping R and B changes the bright pixel only.
    let swap = ColorMatrix {
        rows: vec![
            vec![0.0, 0.0, 1.0],
            vec![0.0, 1.0, 0.0],
            vec![1.0, 0.0, 0.0],
        ],
        affine: false,
        gain: None,
    };
    let sw = render(
        img.view(),
        &RenderOptions {
            mesopic: meso0(),
            color_matrix: Some(swap),
            ..base.clone()
        },
    )
    .unwrap();
    assert_eq!(
        px(&sw, 11),
        [px(&plain, 11)[2], px(&plain, 11)[1], px(&plain, 11)[0]]
    );
    assert!(render(Array3::<f32>::zeros((2, 2, 4)).view(), &base).is_err());
    let _: ArrayView3<f32> = img.view();
}

#[test]
fn render_options_default_and_toml_round_trip() {
    let d = RenderOptions::default();
    assert_eq!(d.tonemap, ToneMap::Global(GlobalConfig::default()));
    assert_eq!((d.exposure, d.mesopic, d.w_weights), (None, None, [1.0; 3]));
    for tonemap in operators() {
        let o = RenderOptions {
            tonemap,
            mesopic: Some(MesopicConfig {
                l0: MesopicOffset::Fixed(0.5),
                frames: Some(2000.0),
            }),
            color_matrix: Some(ColorMatrix::identity()),
            ..Default::default()
        };
        let text = toml::to_string(&o).unwrap();
        assert_eq!(toml::from_str::<RenderOptions>(&text).unwrap(), o, "{text}");
    }
    let auto = RenderOptions {
        mesopic: Some(MesopicConfig {
            l0: MesopicOffset::Auto,
            frames: None,
        }),
        ..Default::default()
    };
    let text = toml::to_string(&auto).unwrap();
    assert!(text.contains("l0 = \"auto\""), "{text}");
    assert_eq!(toml::from_str::<RenderOptions>(&text).unwrap(), auto);
}
