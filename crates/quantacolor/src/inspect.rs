//! A capture at a glance (`quantacolor inspect`): size, CFA, light level per channel, hot
//! pixels and the block size alignment would choose.
#![forbid(unsafe_code)]

use crate::align::blocks::{BlockConfig, BlockPlan};
use crate::align::hot_pixels::{detect_hot_pixels, HotPixelDetectConfig};
use crate::capture::Capture;
use crate::cfa::Channel;
use crate::error::Result;
use crate::model::mle_flux;
use ndarray::Array2;
use serde::Serialize;

/// Where an inspected capture's hot-pixel mask came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum HotPixelOrigin {
    /// The mask named in `capture.toml`.
    Capture,
    /// Detected from the frames ([`detect_hot_pixels`]).
    Detected,
}

/// Per-channel statistics over the pixels of one colour (hot pixels excluded).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChannelSummary {
    /// `R`, `G`, `B` or `W`.
    pub channel: String,
    /// Fraction of the array behind this filter.
    pub fraction: f64,
    /// Mean detections per frame (the fraction of frames in which a pixel fired).
    pub detections_per_frame: f64,
    /// Mean flux λ̂ (photon detections per frame, dark counts removed): the MLE of paper
    /// Eq. 6 per pixel, averaged.
    pub flux: f64,
}

/// What [`summarize`] reports.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CaptureSummary {
    pub frames: usize,
    pub height: usize,
    pub width: usize,
    pub exposure_s: f64,
    /// Channels present in the CFA, in R, G, B, W order.
    pub channels: Vec<ChannelSummary>,
    pub hot_pixels: usize,
    pub hot_pixel_origin: HotPixelOrigin,
    /// The block size alignment chooses from the light level (paper §4.1, 100–1000 frames).
    pub suggested_block_size: usize,
}

/// Summarises `capture` with one pass over its frames. When the capture names no hot-pixel
/// mask, one is detected with `detect` and returned with the summary.
pub fn summarize(
    capture: &Capture,
    detect: &HotPixelDetectConfig,
) -> Result<(CaptureSummary, Array2<bool>)> {
    let frames = &capture.frames;
    let t = frames.frame_count();
    let (mask, origin) = match &capture.hot_pixels {
        Some(m) => (m.clone(), HotPixelOrigin::Capture),
        None => (
            detect_hot_pixels(frames, &capture.cfa, capture.meta.w_weights, detect)?,
            HotPixelOrigin::Detected,
        ),
    };
    let counts = frames.sum_range(0..t);
    let dark = capture.meta.dark_counts_per_frame();
    let fractions = capture.cfa.fractions();
    let mut channels = Vec::new();
    for channel in Channel::ALL {
        if fractions[channel.index()] == 0.0 {
            continue;
        }
        let (mut n, mut p_sum, mut flux_sum) = (0usize, 0.0, 0.0);
        for ((pos, &k), &code) in counts.indexed_iter().zip(capture.cfa.codes().iter()) {
            if code == channel.code() && !mask[pos] {
                n += 1;
                p_sum += k as f64 / t as f64;
                flux_sum += mle_flux(k as f64, t as f64, dark);
            }
        }
        let n = n.max(1) as f64;
        channels.push(ChannelSummary {
            channel: format!("{channel:?}"),
            fraction: fractions[channel.index()],
            detections_per_frame: p_sum / n,
            flux: flux_sum / n,
        });
    }
    let plan = BlockPlan::choose(frames, capture.reference_frame(), &BlockConfig::default())?;
    Ok((
        CaptureSummary {
            frames: t,
            height: frames.height(),
            width: frames.width(),
            exposure_s: capture.meta.exposure_s,
            channels,
            hot_pixels: mask.iter().filter(|&&m| m).count(),
            hot_pixel_origin: origin,
            suggested_block_size: plan.block_size,
        },
        mask,
    ))
}
