//! Joint demosaic-merge (supplement Eq. 1–3) and the whole merge on synthetic bursts through a
//! 75 % W CFA with known truth.
mod merge_support;

use merge_support::*;
use ndarray::{Array2, Array3, Axis};
use quantacolor::cfa::{generate, Pattern};
use quantacolor::merge::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

const DARK: f64 = 0.002;

/// Runs `merge_burst` with every sub-block also acting as its own alignment block.
fn merge_all(
    cfa: &quantacolor::Cfa,
    subs: &[SubBlock],
    flows: Option<&[Array3<f32>]>,
    config: &MergeConfig,
) -> MergedBurst {
    let (h, w) = (cfa.height(), cfa.width());
    let zero = vec![Array3::<f32>::zeros((h, w, 2)); subs.len()];
    let flows: Vec<Array3<f32>> = flows.map_or(zero, |f| f.to_vec());
    let subs: Vec<SubBlock> = subs
        .iter()
        .zip(&flows)
        .map(|(s, f)| SubBlock {
            flow: f.clone().into(),
            ..s.clone()
        })
        .collect();
    let grey: Vec<Array2<f32>> = subs.iter().map(|s| grey_block(s, cfa)).collect();
    let input = BurstInput {
        grey_blocks: &grey,
        block_flows: &flows,
        reference_block: 0,
        grey_trials: subs[0].frames as f32,
        sub_blocks: &subs,
        cfa,
        w_weights: W_WEIGHTS,
        model: DARK.into(),
    };
    merge_burst(&input, config).unwrap()
}

#[test]
fn static_scene_recovers_the_flux_of_every_channel() {
    let (h, w) = (32, 40);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let truth_rgb = [0.10f64, 0.25, 0.15];
    let scene = move |_: f64, _: f64| truth_rgb;
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    let motions = vec![
        Motion {
            dy: 0.0,
            dx: 0.0,
            theta: 0.0
        };
        20
    ];
    let subs = sub_blocks(&scene, &cfa, &motions, 50, DARK, &mut rng);
    let kernels = kernel_field(&Array2::from_elem((h, w), 0.4), &KernelConfig::default()).unwrap();
    let planes = demosaic_merge(
        &subs,
        &[],
        &cfa,
        &kernels,
        DARK,
        W_WEIGHTS,
        &AccumulateConfig::default(),
    );
    let subs_full: Vec<_> = subs
        .into_iter()
        .map(|s| SubBlock {
            robustness: SubBlockRobustness::Full,
            ..s
        })
        .collect();
    let planes_full = demosaic_merge(
        &subs_full,
        &[],
        &cfa,
        &kernels,
        DARK,
        W_WEIGHTS,
        &AccumulateConfig::default(),
    );
    // `Block(k)` without maps is an error; `Full` works.
    assert!(planes.is_err());
    let planes = planes_full.unwrap();
    let lambda_w: f64 = truth_rgb.iter().sum();
    for (c, &t) in truth_rgb.iter().chain([lambda_w].iter()).enumerate() {
        let plane = planes.flux.index_axis(Axis(0), c);
        let mean = plane.mean().unwrap() as f64;
        println!("channel {c}: merged mean {mean:.4}, truth {t:.4}");
        assert!((mean - t).abs() < 0.03 * t, "channel {c}: {mean} vs {t}");
        assert!(plane.iter().all(|v| v.is_finite()));
    }
    assert!(!planes.w_fallback.iter().any(|&f| f));
}

/// The chromaticity r / (r + g + b) of every channel of the merged image, after Eq. 8.
fn chromaticity(planes: &MergedPlanes) -> Array3<f32> {
    let mut rgb = quantacolor::rgbw::combine_rgbw(&planes.flux, W_WEIGHTS);
    for mut px in rgb.lanes_mut(Axis(2)) {
        let sum: f32 = px.iter().sum();
        px.mapv_inplace(|v| v / sum);
    }
    rgb
}

/// Largest chromaticity error of the whole merge (plain, with colour ratios) near a static
/// vertical edge where the light of one hue drops twelvefold, and in the flat areas at least
/// eight columns away: `(near plain, near ratios, far plain, far ratios)`. The chromaticity is
/// (0.3, 0.5, 0.2) everywhere, so any other value near the edge is a fringe (a colour kernel
/// averaging bright and dark samples unequally).
fn edge_fringes(pattern: Pattern) -> (f32, f32, f32, f32) {
    let (h, w, edge) = (32, 48, 24.0);
    let hue = [0.3f64, 0.5, 0.2];
    let scene = move |_: f64, x: f64| {
        let light = if x < edge { 0.05 } else { 0.6 };
        hue.map(|c| c * light)
    };
    let cfa = generate(&pattern, h, w, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(47);
    let still = Motion {
        dy: 0.0,
        dx: 0.0,
        theta: 0.0,
    };
    let subs = sub_blocks(&scene, &cfa, &[still; 8], 2000, DARK, &mut rng);
    // The whole merge (reference, edge-aware kernels, robustness, regression, Eq. 8).
    let merge = |colour_ratios: bool| {
        let mut config = MergeConfig::default();
        config.accumulate.colour_ratios = colour_ratios;
        merge_all(&cfa, &subs, None, &config).planes
    };
    // Rows 4..h−4 and columns 4..w−4, against the image border.
    let errors = |planes: &MergedPlanes| {
        let chroma = chromaticity(planes);
        let (mut near, mut far) = (0.0f32, 0.0f32);
        for y in 4..h - 4 {
            for x in 4..w - 4 {
                let distance = (x as f64 + 0.5 - edge).abs();
                let error = (0..3)
                    .map(|c| (chroma[[y, x, c]] - hue[c] as f32).abs())
                    .fold(0.0, f32::max);
                if distance < 4.0 {
                    near = near.max(error);
                } else if distance > 8.0 {
                    far = far.max(error);
                }
            }
        }
        (near, far)
    };
    let (near_plain, far_plain) = errors(&merge(false));
    let (near_ratio, far_ratio) = errors(&merge(true));
    println!(
        "{pattern:?}: largest chromaticity error near the edge {near_plain:.4} plain, \
         {near_ratio:.4} with colour ratios; flat areas {far_plain:.4}, {far_ratio:.4}"
    );
    (near_plain, near_ratio, far_plain, far_ratio)
}

#[test]
fn colour_ratios_to_w_remove_the_colour_fringe_of_a_static_luminance_edge() {
    let (near_plain, near_ratio, far_plain, far_ratio) = edge_fringes(Pattern::Rgbw75Regular);
    // Measured: 0.42 plain, 0.022 with ratios (the photon noise of the flat areas, 0.023).
    assert!(
        near_plain > 0.2,
        "the plain merge shows a fringe: {near_plain}"
    );
    assert!(near_ratio < 0.05, "{near_ratio} vs {near_plain}");
    assert!(
        far_ratio < 0.04 && far_plain < 0.04,
        "{far_ratio}, {far_plain}"
    );
}

#[test]
fn colour_ratios_to_g_reduce_the_colour_fringe_of_bayer() {
    let (near_plain, near_ratio, far_plain, far_ratio) = edge_fringes(Pattern::Bayer);
    // Measured: 0.42 plain, 0.023 with ratios to G; flat areas 0.017 and 0.015.
    assert!(
        near_plain > 0.2,
        "the plain merge shows a fringe: {near_plain}"
    );
    assert!(near_ratio < 0.05, "{near_ratio} vs {near_plain}");
    // The noise gate leaves flat areas as they were.
    assert!(
        (far_ratio - far_plain).abs() < 0.005,
        "{far_ratio} vs {far_plain}"
    );
}

fn jitter_burst(
    seed: u64,
    h: usize,
    w: usize,
    count: usize,
    frames: u32,
) -> (quantacolor::Cfa, Vec<SubBlock>, Vec<Array3<f32>>) {
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut motions = vec![Motion {
        dy: 0.0,
        dx: 0.0,
        theta: 0.0,
    }];
    for _ in 1..count {
        motions.push(Motion::random(&mut rng, 3.0, 0.02));
    }
    let subs = sub_blocks(&textured, &cfa, &motions, frames, DARK, &mut rng);
    let flows = subs
        .iter()
        .map(|s| s.flow.dense().unwrap().clone())
        .collect();
    (cfa, subs, flows)
}

#[test]
fn true_flows_beat_a_zero_flow_merge() {
    let (h, w) = (48, 56);
    let (cfa, subs, flows) = jitter_burst(32, h, w, 24, 200);
    let config = high_snr_config();
    let aligned = merge_all(&cfa, &subs, Some(&flows), &config);
    let mut no_robust = config.clone();
    no_robust.robustness.t = -1.0; // R ≡ 1: the plain sum of the naive baseline
    let naive = merge_all(&cfa, &subs, None, &no_robust);
    let truth = truth(&textured, h, w, 1);
    let (p_aligned, p_naive) = (
        psnr(&aligned.linear, &truth, 4),
        psnr(&naive.linear, &truth, 4),
    );
    println!("PSNR vs truth: true flows {p_aligned:.2} dB, zero flow {p_naive:.2} dB");
    assert!(p_aligned > p_naive + 6.0, "{p_aligned} vs {p_naive}");
}

#[test]
fn super_resolution_beats_bilinear_upsampling() {
    let (h, w) = (32, 40);
    // Fine grating (period 2.6 px) in every channel.
    let fine = |y: f64, x: f64| {
        let t = (2.0 * std::f64::consts::PI * (x + 0.3 * y) / 2.6).sin();
        [
            0.15 * (1.0 + 0.5 * t),
            0.2 * (1.0 + 0.5 * t),
            0.15 * (1.0 + 0.5 * t),
        ]
    };
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(33);
    let mut motions = vec![Motion {
        dy: 0.0,
        dx: 0.0,
        theta: 0.0,
    }];
    for _ in 1..32 {
        motions.push(Motion::random(&mut rng, 2.0, 0.0));
    }
    let subs = sub_blocks(&fine, &cfa, &motions, 60, DARK, &mut rng);
    let flows: Vec<_> = subs
        .iter()
        .map(|s| s.flow.dense().unwrap().clone())
        .collect();
    let mut config = MergeConfig::default();
    let one = merge_all(&cfa, &subs, Some(&flows), &config);
    config.accumulate.scale = 2;
    let two = merge_all(&cfa, &subs, Some(&flows), &config);
    assert_eq!(two.linear.dim(), (2 * h, 2 * w, 3));
    assert_eq!(two.planes.flux.dim(), (4, 2 * h, 2 * w));
    let truth2 = truth(&fine, h, w, 2);
    let p_sr = psnr(&two.linear, &truth2, 8);
    let p_up = psnr(&upsample_bilinear(&one.linear, 2), &truth2, 8);
    println!("2x output PSNR: super-resolution {p_sr:.2} dB, bilinear upsampling {p_up:.2} dB");
    assert!(p_sr > p_up + 1.0, "{p_sr} vs {p_up}");
}

#[test]
fn robustness_suppresses_a_sub_block_with_wrong_content() {
    let (h, w) = (40, 48);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(34);
    let mut motions = vec![Motion {
        dy: 0.0,
        dx: 0.0,
        theta: 0.0,
    }];
    for _ in 1..16 {
        motions.push(Motion::random(&mut rng, 2.0, 0.0));
    }
    let mut subs = sub_blocks(&textured, &cfa, &motions, 50, DARK, &mut rng);
    // Sub-blocks 3, 7 and 11 see a bright object (absent from the reference) over a square.
    let object = |y: f64, x: f64| {
        if (10.0..24.0).contains(&y) && (14.0..28.0).contains(&x) {
            [1.2, 1.0, 0.3]
        } else {
            textured(y, x)
        }
    };
    for k in [3, 7, 11] {
        let m = motions[k];
        subs[k].counts = simulate_counts(
            &object,
            &cfa,
            50,
            DARK,
            |y, x| m.inverse(h, w, y, x),
            &mut rng,
        );
    }
    let flows: Vec<_> = subs
        .iter()
        .map(|s| s.flow.dense().unwrap().clone())
        .collect();
    let config = high_snr_config();
    let robust = merge_all(&cfa, &subs, Some(&flows), &config);
    let mut plain = config.clone();
    plain.robustness.t = -1.0;
    let ghosted = merge_all(&cfa, &subs, Some(&flows), &plain);
    let truth = truth(&textured, h, w, 1);
    let region = |img: &Array3<f32>| img.slice(ndarray::s![8..26, 12..30, ..]).to_owned();
    let (p_robust, p_plain) = (
        psnr(&region(&robust.linear), &region(&truth), 0),
        psnr(&region(&ghosted.linear), &region(&truth), 0),
    );
    let r_obj = robust.robustness[3]
        .slice(ndarray::s![12..22, 16..26])
        .mean()
        .unwrap();
    println!("object region PSNR: robust {p_robust:.2} dB, no robustness {p_plain:.2} dB; R in object {r_obj:.3}");
    assert!(r_obj < 0.1);
    assert!(p_robust > p_plain + 6.0, "{p_robust} vs {p_plain}");
}

/// Five still sub-blocks of `frames` frames each of a flat grey scene of flux `flux` per colour
/// (W sees the sum) through a 24 x 24 75 % W CFA, full robustness, with the kernels of a flat
/// area: the set-up of the W saturation tests.
fn flat_still_burst(
    flux: f64,
    frames: u32,
    seed: u64,
) -> (quantacolor::Cfa, Vec<SubBlock>, KernelField) {
    let (h, w) = (24, 24);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let scene = move |_: f64, _: f64| [flux; 3];
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let still = Motion {
        dy: 0.0,
        dx: 0.0,
        theta: 0.0,
    };
    let subs: Vec<_> = sub_blocks(&scene, &cfa, &[still; 5], frames, DARK, &mut rng)
        .into_iter()
        .map(|s| SubBlock {
            robustness: SubBlockRobustness::Full,
            ..s
        })
        .collect();
    let kernels = kernel_field(&Array2::from_elem((h, w), 0.9), &KernelConfig::default()).unwrap();
    (cfa, subs, kernels)
}

#[test]
fn saturated_w_falls_back_to_rgb() {
    // λ_W = 9 (bit rate 0.99988: every W frame fires), colours at 3 (bit rate 0.95); 50
    // frames, so the W estimate is clamped near −ln(0.5/N_eff) ≈ 6.3.
    let (cfa, subs, kernels) = flat_still_burst(3.0, 10, 35);
    let (h, w) = (cfa.height(), cfa.width());
    let config = AccumulateConfig::default();
    let with = demosaic_merge(&subs, &[], &cfa, &kernels, DARK, W_WEIGHTS, &config).unwrap();
    let off = AccumulateConfig {
        w_saturation: 1.5,
        w_censoring_zeros: 0.0,
        ..config
    };
    let without = demosaic_merge(&subs, &[], &cfa, &kernels, DARK, W_WEIGHTS, &off).unwrap();
    let share = with.w_fallback.iter().filter(|&&f| f).count() as f64 / (h * w) as f64;
    println!("W fallback on {:.1} % of pixels", 100.0 * share);
    assert!(share > 0.9, "{share}");
    assert!(!without.w_fallback.iter().any(|&f| f));
    let rgb_with = quantacolor::rgbw::combine_rgbw(&with.flux, W_WEIGHTS);
    let rgb_without = quantacolor::rgbw::combine_rgbw(&without.flux, W_WEIGHTS);
    for c in 0..3 {
        let m_with = rgb_with.index_axis(Axis(2), c).mean().unwrap() as f64;
        let m_without = rgb_without.index_axis(Axis(2), c).mean().unwrap() as f64;
        println!("channel {c}: fallback {m_with:.3}, saturated W {m_without:.3}, truth 3");
        assert!((m_with - 3.0).abs() < 0.1 * 3.0, "{m_with}");
        assert!(m_without < 0.85 * 3.0, "{m_without}");
    }
}

/// Mean of each RGB channel of Eq. 8 over merged planes.
fn rgb_means(planes: &MergedPlanes) -> Vec<f64> {
    let rgb = quantacolor::rgbw::combine_rgbw(&planes.flux, W_WEIGHTS);
    (0..3)
        .map(|c| rgb.index_axis(Axis(2), c).mean().unwrap() as f64)
        .collect()
}

#[test]
fn a_censored_w_gives_way_to_saturating_colours() {
    // λ = 4.5 per colour (bit rate 0.989, above `w_saturation`: supplement §7's rule keeps the
    // clamped W) and λ_W = 13.5, over 200 frames: W fires in every frame and its estimate is
    // clamped far below 13.5, so Eq. 8 darkens the colours; the colours still see zero frames.
    let truth = 4.5;
    let (cfa, subs, kernels) = flat_still_burst(truth, 40, 36);
    let (h, w) = (cfa.height(), cfa.width());
    let censoring = AccumulateConfig::default();
    let section7 = AccumulateConfig {
        w_censoring_zeros: 0.0,
        ..censoring.clone()
    };
    let merge = |config: &AccumulateConfig| {
        demosaic_merge(&subs, &[], &cfa, &kernels, DARK, W_WEIGHTS, config).unwrap()
    };
    let (new, old) = (merge(&censoring), merge(&section7));
    assert!(!old.w_fallback.iter().any(|&f| f), "§7 rule fell back");
    let share = new.w_fallback.iter().filter(|&&f| f).count() as f64 / (h * w) as f64;
    assert!(share > 0.9, "censored W replaced on {share} of pixels");
    for (c, (n, o)) in rgb_means(&new).into_iter().zip(rgb_means(&old)).enumerate() {
        println!("channel {c}: censoring {n:.3}, §7 rule {o:.3}, truth {truth}");
        assert!(o < 0.8 * truth, "{o}");
        assert!((n - truth).abs() < 0.1 * truth, "{n}");
    }
}

#[test]
fn unsaturated_w_is_used_as_it_is() {
    // λ_W = 1.5 over 200 frames: about 45 frames without a detection per W site, thousands
    // behind a merged W pixel, so censoring never applies and Eq. 8 keeps W.
    let (cfa, subs, kernels) = flat_still_burst(0.5, 40, 37);
    let merged = demosaic_merge(
        &subs,
        &[],
        &cfa,
        &kernels,
        DARK,
        W_WEIGHTS,
        &AccumulateConfig::default(),
    )
    .unwrap();
    assert!(!merged.w_fallback.iter().any(|&f| f));
}

#[test]
fn bad_sub_blocks_are_errors() {
    let (h, w) = (8, 8);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let kernels = kernel_field(&Array2::from_elem((h, w), 0.5), &KernelConfig::default()).unwrap();
    let good = SubBlock {
        counts: Array2::from_elem((h, w), 3),
        frames: 10,
        flow: Array3::zeros((h, w, 2)).into(),
        robustness: SubBlockRobustness::Full,
    };
    let c = AccumulateConfig::default();
    assert!(demosaic_merge(
        std::slice::from_ref(&good),
        &[],
        &cfa,
        &kernels,
        0.0,
        W_WEIGHTS,
        &c
    )
    .is_ok());
    let cases = [
        SubBlock {
            frames: 2,
            ..good.clone()
        },
        SubBlock {
            frames: 0,
            ..good.clone()
        },
        SubBlock {
            counts: Array2::zeros((h, w + 1)),
            ..good.clone()
        },
        SubBlock {
            flow: Array3::from_elem((h, w, 2), f32::NAN).into(),
            ..good.clone()
        },
        SubBlock {
            robustness: SubBlockRobustness::Map(Array2::zeros((2, 2))),
            ..good.clone()
        },
    ];
    for bad in cases {
        assert!(demosaic_merge(&[bad], &[], &cfa, &kernels, 0.0, W_WEIGHTS, &c).is_err());
    }
    assert!(demosaic_merge(&[], &[], &cfa, &kernels, 0.0, W_WEIGHTS, &c).is_err());
    let big = AccumulateConfig { scale: 0, ..c };
    assert!(demosaic_merge(&[good], &[], &cfa, &kernels, 0.0, W_WEIGHTS, &big).is_err());
}

#[test]
fn merge_burst_rejects_inconsistent_input() {
    let (h, w) = (16, 16);
    let (cfa, subs, flows) = jitter_burst(36, h, w, 2, 10);
    let grey: Vec<_> = subs.iter().map(|s| grey_block(s, &cfa)).collect();
    let input = BurstInput {
        grey_blocks: &grey,
        block_flows: &flows,
        reference_block: 2,
        grey_trials: 10.0,
        sub_blocks: &subs,
        cfa: &cfa,
        w_weights: W_WEIGHTS,
        model: DARK.into(),
    };
    assert!(merge_burst(&input, &MergeConfig::default()).is_err());
    let input = BurstInput {
        reference_block: 0,
        block_flows: &flows[..1],
        ..input
    };
    assert!(merge_burst(&input, &MergeConfig::default()).is_err());
    let input = BurstInput {
        block_flows: &flows,
        ..input
    };
    let out = merge_burst(&input, &MergeConfig::default()).unwrap();
    assert_eq!(out.linear.dim(), (h, w, 3));
    assert_eq!(out.robustness.len(), 2);
    assert!(out.robustness[0].iter().all(|&r| r == 1.0));
}

/// These synthetic bursts are bright and finely textured: narrow colour kernels (the
/// pre-default spacing exponent 0.5, radius 3) show the effect of flows and robustness best;
/// the photon-limited defaults widen colour kernels (see `AccumulateConfig::spacing_exponent`).
fn high_snr_config() -> MergeConfig {
    let mut config = MergeConfig::default();
    config.accumulate.spacing_exponent = 0.5;
    config.accumulate.max_radius = 3;
    config
}

/// Per-channel bit rates of the direct per-sample sum of supplement Eq. 1–3 (no bins): every
/// site of every sub-block at its exact reference position, weighted by the kernel of the
/// output pixel and truncated at the accumulator's radius and cutoff.
fn direct_bit_rates(
    subs: &[SubBlock],
    motions: &[Motion],
    cfa: &quantacolor::Cfa,
    kernels: &KernelField,
    config: &AccumulateConfig,
    radius: f64,
) -> Array3<f32> {
    let (h, w) = (cfa.height(), cfa.width());
    let inv_scale = KernelField::channel_scale(cfa).map(|s| {
        if s > 0.0 {
            1.0 / s.powf(config.spacing_exponent) as f64
        } else {
            0.0
        }
    });
    let mut out = Array3::<f32>::from_elem((4, h, w), f32::NAN);
    for y in 0..h {
        for x in 0..w {
            let k = &kernels.inv_cov;
            let (a, b, c) = (
                k[[y, x, 0]] as f64,
                k[[y, x, 1]] as f64,
                k[[y, x, 2]] as f64,
            );
            let mut num = [0.0f64; 4];
            let mut den = [0.0f64; 4];
            for (sub, m) in subs.iter().zip(motions) {
                for qy in 0..h {
                    for qx in 0..w {
                        let (py, px) = m.inverse(h, w, qy as f64, qx as f64);
                        let (dy, dx) = (py - y as f64, px - x as f64);
                        if dy.abs() > radius || dx.abs() > radius {
                            continue;
                        }
                        let ch = cfa.codes()[[qy, qx]] as usize;
                        let quad = (a * dy * dy + 2.0 * b * dy * dx + c * dx * dx) * inv_scale[ch];
                        if quad < config.cutoff as f64 {
                            let g = (-0.5 * quad).exp();
                            num[ch] += g * sub.counts[[qy, qx]] as f64;
                            den[ch] += g * sub.frames as f64;
                        }
                    }
                }
            }
            for ch in 0..4 {
                if den[ch] > 0.0 {
                    out[[ch, y, x]] = (num[ch] / den[ch]) as f32;
                }
            }
        }
    }
    out
}

#[test]
fn fast_merge_matches_the_per_sample_merge() {
    // Rotating, translating sub-blocks of a textured scene; the phase-bin accumulator against
    // the direct sum over samples at their exact reference positions. Many frames per
    // sub-block, so that photon noise (which any change of weights reshuffles) stays far below
    // the differences of interest.
    let (h, w) = (20, 24);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(35);
    let mut motions = vec![Motion {
        dy: 0.0,
        dx: 0.0,
        theta: 0.0,
    }];
    for _ in 1..6 {
        motions.push(Motion::random(&mut rng, 2.5, 0.03));
    }
    let subs: Vec<SubBlock> = sub_blocks(&textured, &cfa, &motions, 1_000_000, DARK, &mut rng)
        .into_iter()
        .map(|s| SubBlock {
            robustness: SubBlockRobustness::Full,
            ..s
        })
        .collect();
    let reference = Array2::from_shape_fn((h, w), |(y, x)| {
        bit_rate(
            textured(y as f64, x as f64),
            quantacolor::cfa::Channel::W,
            DARK,
        ) as f32
    });
    let kernels = kernel_field(&reference, &KernelConfig::default()).unwrap();
    // A radius wide enough that only the (smooth) kernel cutoff truncates: a hard square window
    // would let bin rounding move samples across its edge at full weight.
    let config = AccumulateConfig {
        max_radius: 12,
        bins_per_output_px: 4,
        ..AccumulateConfig::default()
    };
    let fast = demosaic_merge(&subs, &[], &cfa, &kernels, DARK, W_WEIGHTS, &config).unwrap();
    let radius = (3.0 * kernels.max_std as f64 * 16f64.sqrt())
        .ceil()
        .clamp(1.0, 12.0);
    let direct = direct_bit_rates(&subs, &motions, &cfa, &kernels, &config, radius);
    // The same sum with every sample left at its sensor position (motion ignored): what a
    // merge that dropped the flows would give, for scale.
    let still = vec![
        Motion {
            dy: 0.0,
            dx: 0.0,
            theta: 0.0
        };
        motions.len()
    ];
    let unaligned = direct_bit_rates(&subs, &still, &cfa, &kernels, &config, radius);
    let mean_abs = |a: &Array3<f32>, b: &Array3<f32>| {
        let mut s = 0.0f64;
        let mut n = 0.0;
        for ch in 0..4 {
            for y in 3..h - 3 {
                for x in 3..w - 3 {
                    let (u, v) = (a[[ch, y, x]] as f64, b[[ch, y, x]] as f64);
                    if u.is_finite() && v.is_finite() {
                        s += (u - v).abs() / v.max(1e-3);
                        n += 1.0;
                    }
                }
            }
        }
        s / n
    };
    let err = mean_abs(&fast.bit_rate, &direct);
    let err_unaligned = mean_abs(&unaligned, &direct);
    println!("mean relative difference: fast {err:.4}, unaligned {err_unaligned:.4}");
    assert!(err < 0.01, "{err}");
    assert!(err_unaligned > 5.0 * err, "{err_unaligned} vs {err}");
}

#[test]
fn an_affine_sub_block_motion_merges_like_its_dense_flow() {
    let (h, w) = (48, 56);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    let motions: Vec<Motion> = (0..6)
        .map(|_| Motion::random(&mut rng, 3.0, 0.03))
        .collect();
    let dense: Vec<SubBlock> = sub_blocks(&textured, &cfa, &motions, 40, DARK, &mut rng)
        .into_iter()
        .map(|s| SubBlock {
            robustness: SubBlockRobustness::Full,
            ..s
        })
        .collect();
    let affine: Vec<SubBlock> = dense
        .iter()
        .zip(&motions)
        .map(|(s, m)| SubBlock {
            flow: m.reference_map(h, w),
            ..s.clone()
        })
        .collect();
    let kernels = kernel_field(&Array2::from_elem((h, w), 0.5), &KernelConfig::default()).unwrap();
    let config = AccumulateConfig::default();
    let merge = |subs: &[SubBlock]| {
        demosaic_merge(subs, &[], &cfa, &kernels, DARK, W_WEIGHTS, &config).unwrap()
    };
    let (a, b) = (merge(&dense), merge(&affine));
    let (mut worst, mut total, mut n) = (0.0f64, 0.0f64, 0usize);
    for (x, y) in a.flux.iter().zip(b.flux.iter()) {
        if x.is_finite() && y.is_finite() && *x > 0.0 {
            let rel = ((x - y) / x).abs() as f64;
            worst = worst.max(rel);
            total += rel;
            n += 1;
        }
    }
    let mean = total / n as f64;
    println!("affine vs dense flow: mean relative flux difference {mean:.2e}, worst {worst:.2e}");
    assert!(n > 1000);
    // Positions agree to ~1e-5 px; only samples on a phase-bin boundary may move a bin.
    assert!(mean < 1e-3, "mean {mean}");
}

#[test]
fn a_camera_motion_with_a_local_residual_merges_like_its_dense_flow() {
    // A camera motion plus a moving square: sites whose affine position lies outside the
    // square's mask take the affine map, the others invert the dense flow.
    let (h, w) = (48, 56);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(78);
    let motions: Vec<Motion> = (0..6)
        .map(|_| Motion::random(&mut rng, 3.0, 0.03))
        .collect();
    let (square_y, square_x) = (10..26, 14..32);
    let local = Array2::from_shape_fn((h, w), |(y, x)| {
        // The square, widened by 2 px: the bilinear flow near its edge mixes both motions.
        (square_y.start - 2..square_y.end + 2).contains(&y)
            && (square_x.start - 2..square_x.end + 2).contains(&x)
    });
    let dense: Vec<SubBlock> = sub_blocks(&textured, &cfa, &motions, 40, DARK, &mut rng)
        .into_iter()
        .map(|s| {
            let mut flow = s.flow.dense().unwrap().clone();
            for y in square_y.clone() {
                for x in square_x.clone() {
                    flow[[y, x, 0]] += 1.5;
                    flow[[y, x, 1]] -= 2.0;
                }
            }
            SubBlock {
                flow: SubBlockMotion::Dense(flow),
                robustness: SubBlockRobustness::Full,
                ..s
            }
        })
        .collect();
    let hybrid: Vec<SubBlock> = dense
        .iter()
        .zip(&motions)
        .map(|(s, m)| {
            let SubBlockMotion::Affine { matrix, offset } = m.reference_map(h, w) else {
                unreachable!("an affine map")
            };
            SubBlock {
                flow: SubBlockMotion::CameraAndLocal {
                    matrix,
                    offset,
                    flow: s.flow.dense().unwrap().clone(),
                    local: local.clone(),
                },
                ..s.clone()
            }
        })
        .collect();
    let camera_only: Vec<SubBlock> = dense
        .iter()
        .zip(&motions)
        .map(|(s, m)| SubBlock {
            flow: m.reference_map(h, w),
            ..s.clone()
        })
        .collect();
    let kernels = kernel_field(&Array2::from_elem((h, w), 0.5), &KernelConfig::default()).unwrap();
    let config = AccumulateConfig::default();
    let merge = |subs: &[SubBlock]| {
        let mut acc = MergeAccumulator::new(&cfa, &kernels, &config, DARK).unwrap();
        acc.add(subs, &[]).unwrap();
        acc.finish(W_WEIGHTS)
    };
    let mean_difference = |a: &MergedPlanes, b: &MergedPlanes| {
        let (mut total, mut n) = (0.0f64, 0usize);
        for (x, y) in a.flux.iter().zip(b.flux.iter()) {
            if x.is_finite() && y.is_finite() && *x > 0.0 {
                total += ((x - y) / x).abs() as f64;
                n += 1;
            }
        }
        assert!(n > 1000);
        total / n as f64
    };
    let (a, b, c) = (merge(&dense), merge(&hybrid), merge(&camera_only));
    let (same, ignored) = (mean_difference(&a, &b), mean_difference(&a, &c));
    println!("hybrid vs dense: {same:.2e}; camera alone vs dense: {ignored:.2e}");
    // Positions agree to ~1e-5 px; only samples on a phase-bin boundary may move a bin. The
    // camera alone misplaces the square's samples.
    assert!(same < 1e-3, "hybrid {same}");
    assert!(
        ignored > 10.0 * same.max(1e-5),
        "camera alone {ignored}, hybrid {same}"
    );
}
