//! Naive reconstruction: the "naive average (long/short)" baseline of paper Table 2.
//!
//! Sums the binary frames of a window centred on the reference frame with no motion
//! compensation, inverts the Bernoulli response per pixel (MLE, paper Eq. 6), demosaics any
//! R/G/B/W arrangement by normalized convolution (Knutsson & Westin 1993), and applies the RGBW
//! combination of paper Eq. 8 ([`crate::rgbw`]). Every burst method must beat it.
#![forbid(unsafe_code)]

use crate::capture::Capture;
use crate::cfa::{Cfa, Channel};
use crate::error::{Error, Result};
use crate::filters::normalized_convolution_nan;
use crate::model::PixelModel;
use crate::rgbw::combine_rgbw;
use ndarray::{Array2, Array3, Axis, Zip};
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// Configuration of the naive baseline.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct NaiveConfig {
    /// Number of frames centred on the reference frame (default: all frames).
    pub window: Option<usize>,
}

/// The `window` frames centred on `reference` (clamped into `0..frame_count`).
pub fn centred_window(frame_count: usize, reference: usize, window: Option<usize>) -> Range<usize> {
    let n = window.unwrap_or(frame_count).clamp(1, frame_count);
    let start = reference.saturating_sub(n / 2).min(frame_count - n);
    start..start + n
}

/// Per-pixel flux map λ̂ (detections per frame, dark counts removed) from counts (sums of
/// samples) over `frames` frames by the pixel `model` (the MLE of Eq. 6 for binary frames; a
/// plain number is a binary pixel's dark counts per frame), NaN where `excluded` is set (hot
/// pixels).
pub fn flux_map(
    counts: &Array2<u32>,
    frames: usize,
    model: impl Into<PixelModel>,
    excluded: Option<&Array2<bool>>,
) -> Array2<f32> {
    let model: PixelModel = model.into();
    let n = frames as f64;
    let mut flux = counts.mapv(|s| model.flux(s as f64 / n, n) as f32);
    if let Some(mask) = excluded {
        Zip::from(&mut flux).and(mask).for_each(|f, &hot| {
            if hot {
                *f = f32::NAN;
            }
        });
    }
    flux
}

/// Gaussian width (pixels) used to interpolate a channel whose sites cover `fraction` of the
/// array: about 0.6 of the mean site spacing, so each output sees a handful of samples.
fn interpolation_sigma(fraction: f64) -> f64 {
    (0.6 / fraction.max(1e-6).sqrt()).max(0.5)
}

/// Demosaics a per-pixel flux map (NaN = excluded pixel) into full R, G, B, W planes by
/// normalized convolution of each channel's sites. Returns (4, H, W) in channel-code order;
/// channels absent from the CFA are NaN.
pub fn demosaic_normalized(flux: &Array2<f32>, cfa: &Cfa) -> Array3<f32> {
    let (h, w) = flux.dim();
    let fractions = cfa.fractions();
    let mut planes = Array3::<f32>::from_elem((4, h, w), f32::NAN);
    for channel in Channel::ALL {
        let fraction = fractions[channel.index()];
        if fraction == 0.0 {
            continue;
        }
        let samples = Zip::from(flux).and(cfa.codes()).map_collect(|&f, &c| {
            if c == channel.code() {
                f
            } else {
                f32::NAN
            }
        });
        let mut sigma = interpolation_sigma(fraction);
        let mut plane = normalized_convolution_nan(samples.view(), sigma);
        // Sparse channels near many excluded pixels may leave holes: widen until filled.
        for _ in 0..4 {
            if !plane.iter().any(|v| v.is_nan()) {
                break;
            }
            sigma *= 2.0;
            let wider = normalized_convolution_nan(samples.view(), sigma);
            Zip::from(&mut plane).and(&wider).for_each(|p, &q| {
                if p.is_nan() {
                    *p = q;
                }
            });
        }
        planes
            .index_axis_mut(Axis(0), channel.index())
            .assign(&plane);
    }
    planes
}

/// Result of the naive baseline.
#[derive(Debug, Clone)]
pub struct NaiveReconstruction {
    /// Linear RGB (H, W, 3), detections per frame of an R, G or B pixel, dark counts removed.
    pub linear: Array3<f32>,
    /// The frames that were summed.
    pub frames: Range<usize>,
}

/// Runs the naive baseline on `capture` around `reference_frame`.
pub fn reconstruct_naive(
    capture: &Capture,
    reference_frame: usize,
    config: &NaiveConfig,
) -> Result<NaiveReconstruction> {
    crate::cpu::on_pool(|| naive_on_pool(capture, reference_frame, config))
}

fn naive_on_pool(
    capture: &Capture,
    reference_frame: usize,
    config: &NaiveConfig,
) -> Result<NaiveReconstruction> {
    let t = capture.frames.frame_count();
    if reference_frame >= t {
        return Err(Error::invalid(format!(
            "reference frame {reference_frame} is outside the capture's {t} frames"
        )));
    }
    if config.window == Some(0) {
        return Err(Error::invalid(
            "the naive window must hold at least one frame",
        ));
    }
    let frames = centred_window(t, reference_frame, config.window);
    let counts = capture.frames.sum_range(frames.clone());
    let flux = flux_map(
        &counts,
        frames.len(),
        capture.meta.pixel_model(),
        capture.hot_pixels.as_ref(),
    );
    let planes = demosaic_normalized(&flux, &capture.cfa);
    let linear = combine_rgbw(&planes, capture.meta.w_weights);
    Ok(NaiveReconstruction { linear, frames })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::{frames::pack_bits, BinaryFrames, CaptureMeta};
    use crate::cfa::{generate, Pattern};
    use rand::{Rng, SeedableRng};

    #[test]
    fn centred_window_stays_inside_the_capture() {
        assert_eq!(centred_window(100, 50, Some(10)), 45..55);
        assert_eq!(centred_window(100, 2, Some(10)), 0..10);
        assert_eq!(centred_window(100, 99, Some(10)), 90..100);
        assert_eq!(centred_window(100, 50, None), 0..100);
        assert_eq!(centred_window(100, 50, Some(1000)), 0..100);
    }

    #[test]
    fn normalized_convolution_reproduces_a_linear_ramp_from_sparse_samples() {
        let ramp =
            Array2::from_shape_fn((40, 40), |(y, x)| 1.0 + 0.01 * x as f32 + 0.02 * y as f32);
        let sparse = Array2::from_shape_fn((40, 40), |(y, x)| {
            if (y * 7 + x * 3) % 5 == 0 {
                ramp[[y, x]]
            } else {
                f32::NAN
            }
        });
        let dense = normalized_convolution_nan(sparse.view(), 1.5);
        // Away from the borders a symmetric kernel reproduces a linear function closely.
        for y in 8..32 {
            for x in 8..32 {
                assert!((dense[[y, x]] - ramp[[y, x]]).abs() < 0.02, "({y},{x})");
            }
        }
    }

    /// Bernoulli frames of a static flat scene with known per-channel flux, through a 75 % W
    /// CFA with hot pixels that fire often: the naive reconstruction must recover the flux.
    #[test]
    fn naive_recovers_known_flat_colour_with_hot_pixels_excluded() {
        let (h, w, t) = (32, 40, 400);
        let lambda_rgb = [0.02f64, 0.05, 0.03];
        let lambda_w: f64 = lambda_rgb.iter().sum();
        let dark = 0.001;
        let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let hot = Array2::from_shape_fn((h, w), |_| rng.gen_bool(0.03));
        let bits = Array3::from_shape_fn((t, h, w), |(_, y, x)| {
            let lambda = match cfa.channel(y, x) {
                Channel::W => lambda_w,
                c => lambda_rgb[c.index()],
            };
            let rate = if hot[[y, x]] { 0.5 } else { lambda + dark };
            rng.gen_bool(1.0 - (-rate).exp()) as u8
        });
        let capture = Capture {
            dir: "mem".into(),
            frames: BinaryFrames::from_packed(pack_bits(&bits), w).unwrap(),
            cfa,
            meta: CaptureMeta {
                dark_count_rate_hz: dark / 1e-4,
                ..CaptureMeta::new(1e-4)
            },
            hot_pixels: Some(hot),
        };
        let rec = reconstruct_naive(&capture, 200, &NaiveConfig::default()).unwrap();
        assert_eq!(rec.frames, 0..400);
        for (c, &truth) in lambda_rgb.iter().enumerate() {
            let plane = rec.linear.index_axis(Axis(2), c);
            let mean = plane.mean().unwrap() as f64;
            assert!(
                (mean - truth).abs() < 0.06 * truth,
                "channel {c}: mean {mean} vs truth {truth}"
            );
        }
        // Without excluding the hot pixels the estimate is biased upward.
        let mut biased = capture;
        biased.hot_pixels = None;
        let rec = reconstruct_naive(&biased, 200, &NaiveConfig::default()).unwrap();
        let total: f64 = (0..3)
            .map(|c| rec.linear.index_axis(Axis(2), c).mean().unwrap() as f64)
            .sum();
        assert!(
            total > 1.08 * lambda_w,
            "hot pixels should bias the sum: {total}"
        );
    }
}
