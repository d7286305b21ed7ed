//! Helpers shared by the simulated experiments: simulate a capture, reconstruct it (burst or
//! naive, no denoising), score it, and build CSV text and contact sheets.
#![deny(unsafe_code)]

use crate::cfa::Cfa;
use crate::denoise::chroma::DenoiseMethod;
use crate::display::{
    auto_exposure_scale, encode_srgb8, global_exposure, global_white, hstack, tone_map_global,
    vstack, GlobalConfig,
};
use crate::error::Result;
use crate::metrics::{evaluate, EvalOptions, Scores};
use crate::pipeline::{reconstruct, Method, ReconstructConfig};
use crate::progress::Progress;
use crate::simulate::{self, Scene, SensorKind, SimulationConfig};
use ndarray::{s, Array3, ArrayView3};

/// CSV text: `header`, then one line per row, each line ending in `\n`.
pub(super) fn csv(header: &str, rows: impl Iterator<Item = String>) -> String {
    let mut out = format!("{header}\n");
    for r in rows {
        out.push_str(&r);
        out.push('\n');
    }
    out
}

/// The scene of `options`, or `default`.
pub(super) fn scene_or(spec: Option<&str>, default: &str) -> Result<Scene> {
    Scene::from_spec(spec.unwrap_or(default))
}

/// A simulated capture reconstructed by the burst method and by naive averaging.
pub(super) struct Trial {
    pub truth: Array3<f32>,
    pub burst: Array3<f32>,
    /// Naive sum of all frames (only when asked for).
    pub naive: Option<Array3<f32>>,
}

/// Simulates `config` (behind `cfa` when given; a binary sensor, or the multi-bit CMOS sensor)
/// and reconstructs it; both reconstructions run
/// without denoising, so that the experiments measure alignment and merge, as the paper's
/// figures compare them.
pub(super) fn trial(
    config: &SimulationConfig,
    scene: &Scene,
    cfa: Option<&Cfa>,
    with_naive: bool,
    progress: &dyn Progress,
) -> Result<Trial> {
    let cfa = match cfa {
        Some(c) => c.clone(),
        None => simulate::config_cfa(config)?,
    };
    // Conventional sensors run through the same pipeline with multi-bit frames (paper §6.1).
    let (capture, truth) = if config.sensor == SensorKind::Cmos {
        let sim = simulate::simulate_cmos_with_cfa(config, scene, &cfa, progress)?;
        (sim.to_capture()?, sim.ground_truth)
    } else {
        let sim = simulate::simulate_with_cfa(config, scene, &cfa, progress)?;
        (sim.to_capture()?, sim.ground_truth)
    };
    let run = |method: Method| -> Result<Array3<f32>> {
        let mut rc = ReconstructConfig {
            method,
            ..Default::default()
        };
        rc.denoise.method = DenoiseMethod::None;
        Ok(reconstruct(&capture, &rc, progress)?.linear)
    };
    let burst = run(Method::Burst)?;
    let naive = if with_naive {
        Some(run(Method::Naive)?)
    } else {
        None
    };
    Ok(Trial {
        truth,
        burst,
        naive,
    })
}

/// Scores under the paper's protocol (§6): border crop, truth's 99.5th percentile -> 1, clip.
pub(super) fn score(estimate: &Array3<f32>, truth: &Array3<f32>, border: usize) -> Result<Scores> {
    evaluate(
        estimate.view(),
        truth.view(),
        &EvalOptions {
            border,
            normalize_percentile: Some(99.5),
        },
    )
}

/// Mean angle (degrees) between the estimated and true RGB vectors over the pixels inside
/// `border` whose truth is not black: a chromaticity error blind to brightness (this project's
/// measure for the W-fraction experiment; the supplement reports colour fidelity visually).
pub(super) fn chroma_error_deg(estimate: &Array3<f32>, truth: &Array3<f32>, border: usize) -> f64 {
    let (h, w, _) = truth.dim();
    let (mut sum, mut n) = (0.0_f64, 0usize);
    for y in border..h.saturating_sub(border) {
        for x in border..w.saturating_sub(border) {
            let t = truth.slice(s![y, x, ..]);
            let e = estimate.slice(s![y, x, ..]);
            let (mut dot, mut nt, mut ne) = (0.0_f64, 0.0_f64, 0.0_f64);
            for c in 0..3 {
                let (tv, ev) = (f64::from(t[c]), f64::from(e[c]).max(0.0));
                dot += tv * ev;
                nt += tv * tv;
                ne += ev * ev;
            }
            if nt <= 0.0 || !ne.is_finite() {
                continue;
            }
            let cos = if ne > 0.0 {
                (dot / (nt.sqrt() * ne.sqrt())).clamp(-1.0, 1.0)
            } else {
                0.0 // a black estimate of a coloured pixel: 90 degrees
            };
            sum += cos.acos().to_degrees();
            n += 1;
        }
    }
    if n == 0 {
        0.0
    } else {
        sum / n as f64
    }
}

/// Side-by-side sRGB crops (centre `size` x `size`, or the whole image if smaller) of `images`,
/// all at the exposure that fits `truth`.
pub(super) fn contact_sheet(
    truth: &Array3<f32>,
    images: &[&Array3<f32>],
    size: usize,
) -> Array3<u8> {
    let scale = auto_exposure_scale(truth.view());
    let crop = |a: &Array3<f32>| -> Array3<u8> {
        let (h, w, _) = a.dim();
        let (ch, cw) = (size.min(h), size.min(w));
        let (y0, x0) = ((h - ch) / 2, (w - cw) / 2);
        let v: ArrayView3<f32> = a.slice(s![y0..y0 + ch, x0..x0 + cw, ..]);
        encode_srgb8(v, scale)
    };
    let crops: Vec<Array3<u8>> = std::iter::once(truth)
        .chain(images.iter().copied())
        .map(crop)
        .collect();
    let views: Vec<_> = crops.iter().map(|c| c.view()).collect();
    hstack(&views, 4, 255)
}

/// Contact sheet of tone-mapped results: one row per entry of `rows`, each the centre `size` x
/// `size` crop of the first pair's truth, then of every estimate. Each estimate is normalised like
/// the metric, by its own truth (the truth's 99.5th percentile to 1: sensors differ in units), and
/// all are rendered by the global operator (Reinhard 2002) at the exposure and white point it
/// picks for the row's first (normalised) truth, so that rows of HDR scenes with light sources
/// show their dark parts and every image of a row renders alike.
pub(super) fn tone_mapped_sheet(
    rows: &[Vec<(&Array3<f32>, &Array3<f32>)>],
    size: usize,
) -> Result<Array3<u8>> {
    let cfg = GlobalConfig::default();
    let normalised = |truth: &Array3<f32>, image: &Array3<f32>| {
        let norm = crate::display::exposure::percentile(truth.iter().copied(), 99.5)
            .filter(|p| *p > 0.0)
            .map_or(1.0, |p| 1.0 / p);
        image.mapv(|v| v * norm)
    };
    let mut rendered_rows = Vec::new();
    for pairs in rows {
        let Some(&(first_truth, _)) = pairs.first() else {
            continue;
        };
        let reference = normalised(first_truth, first_truth);
        let exposure = global_exposure(reference.view(), &cfg);
        let white = global_white(reference.view(), exposure, &cfg);
        let images: Vec<Array3<f32>> = std::iter::once(reference)
            .chain(pairs.iter().map(|(t, e)| normalised(t, e)))
            .collect();
        let crops = images
            .iter()
            .map(|a| {
                let (h, w, _) = a.dim();
                let (ch, cw) = (size.min(h), size.min(w));
                let (y0, x0) = ((h - ch) / 2, (w - cw) / 2);
                let crop = a.slice(s![y0..y0 + ch, x0..x0 + cw, ..]);
                let display = tone_map_global(crop, exposure, white, &cfg)?;
                Ok(encode_srgb8(display.view(), 1.0))
            })
            .collect::<Result<Vec<Array3<u8>>>>()?;
        let views: Vec<_> = crops.iter().map(|c| c.view()).collect();
        rendered_rows.push(hstack(&views, 4, 255));
    }
    let views: Vec<_> = rendered_rows.iter().map(|r| r.view()).collect();
    Ok(vstack(&views, 4, 255))
}
