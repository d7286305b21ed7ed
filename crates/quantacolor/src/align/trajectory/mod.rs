//! The camera trajectory at single-frame resolution, fitted to every detected photon: this
//! project's own stage, not the paper's — a piecewise-linear camera trajectory fitted to the
//! individual photons by maximum likelihood, with a smoothness prior on its acceleration.
//!
//! The paper (§4.1) and Quanta Burst Photography (Ma et al. 2020, §4.2) align block sums and
//! interpolate their motion in time; [`super::track`] measures fast motion on sub-blocks of
//! ~10 frames. Both see a sub-block as one image, so under fast shake (1–2 px per frame) a
//! sub-block is a streak, and its fit lands anywhere along it: the quality suite measured a
//! median end-point error of 2–3 px on fast handheld captures after tracking.
//!
//! Here the inverse camera map of every frame (frame → reference, affine about the image
//! centre) is a piecewise-linear function of time through *knots* every few frames, and the
//! knots are fitted jointly to the binary frames themselves by maximum likelihood:
//!
//! - each site of the tracking channel (W, or G of a Bayer CFA: `super::track::tracking_channel`;
//!   not hot) of frame `f` is a Bernoulli trial whose success probability is
//!   the template `p` (the mean bit rate per frame at that scene point, built from all frames
//!   at the current trajectory) at the site's reference position; the log-likelihood is
//!   `Σ_detections log p + Σ_no-detection log(1 − p)`, the single-photon form of the paper's
//!   binomial model (Eq. 2–3);
//! - Fisher scoring (Gauss–Newton for this likelihood) on the knot parameters, coarse to fine
//!   over template blur σ, the template rebuilt from the updated trajectory every iteration;
//! - a Gaussian prior on the trajectory's acceleration (second differences of the knots) keeps
//!   knots whose frames hold few photons or little texture on the path of their neighbours.
//!
//! The normal equations are banded (a knot couples to two neighbours on each side), so one
//! iteration costs one pass over the frames' sites plus a banded Cholesky solve; memory is
//! O(number of knots), not O(T · H · W).
//!
//! The steps, one file each: `config` (the settings), `knots` (the piecewise-linear
//! trajectory), `sites` (the grey sites and their detections), `template` (the template from
//! all frames along the trajectory), `likelihood` (each frame's score and information),
//! `solve` (the banded scoring step with the prior); `x86` holds their AVX2 kernels.

// Index loops mirror the matrix algebra (band offsets, symmetric fills).
#![allow(clippy::needless_range_loop)]

mod config;
mod knots;
mod likelihood;
mod sites;
mod solve;
mod template;
#[cfg(target_arch = "x86_64")]
mod x86;

pub use config::TrajectoryConfig;

use super::grey::GreyMethod;
use super::refine::{template_level, AffineMotion, FrameMotion};
use super::track::tracking_channel;
use crate::capture::{BinaryFrames, Capture};
use crate::cpu::Isa;
use crate::error::Result;
use crate::progress::Progress;
use knots::Trajectory;
use likelihood::ScoreTemplate;
use sites::Sites;
use solve::scoring_step;
use std::ops::Range;
use template::build_template;

/// Fits the camera trajectory of every frame to the photons (see the module documentation),
/// starting from `motion`'s camera, and replaces `motion`'s sub-blocks by runs of frames within
/// one block over which the fitted camera moves at most `max_sub_block_motion_px`. Runs only
/// on binary frames of a CFA with a tracking channel (W, or G of Bayer); returns whether it ran. The stage's entry: the
/// instruction set of its kernels is taken here ([`Isa::current`]).
pub fn fit_photon_trajectory(
    capture: &Capture,
    grey_method: GreyMethod,
    motion: &mut FrameMotion,
    config: &TrajectoryConfig,
    max_sub_block_motion_px: f64,
    progress: &dyn Progress,
) -> Result<bool> {
    let span = TrajectorySpan {
        sub_blocks: 0..motion.sub_blocks.len(),
        anchor_frame: motion.plan.reference_frame,
    };
    fit_photon_trajectory_over(
        capture,
        grey_method,
        motion,
        &span,
        config,
        max_sub_block_motion_px,
        progress,
    )
}

/// The consecutive sub-blocks of a [`FrameMotion`] whose frames a trajectory is fitted to, and
/// the frame whose camera it keeps: a fit sees only its own frames, so where it is placed as a
/// whole (its gauge) is fixed from outside. At the reference frame the camera is zero (the
/// convention of the flows); elsewhere it is the camera `motion` holds there before the fit
/// (tracked from a slow block next to the span).
#[derive(Debug, Clone, PartialEq)]
pub struct TrajectorySpan {
    pub sub_blocks: Range<usize>,
    pub anchor_frame: usize,
}

/// [`fit_photon_trajectory`] over the frames of `span`'s sub-blocks only: they are replaced,
/// the others kept. Time and memory follow the span's frames, not the capture's.
pub fn fit_photon_trajectory_over(
    capture: &Capture,
    grey_method: GreyMethod,
    motion: &mut FrameMotion,
    span: &TrajectorySpan,
    config: &TrajectoryConfig,
    max_sub_block_motion_px: f64,
    progress: &dyn Progress,
) -> Result<bool> {
    let frames = &capture.frames;
    let isa = Isa::current();
    if config.enabled {
        config.validate()?;
    }
    let sub_blocks = &motion.sub_blocks;
    if span.sub_blocks.is_empty() || span.sub_blocks.end > sub_blocks.len() {
        return Err(crate::error::Error::invalid(format!(
            "photon trajectory: sub-blocks {:?} of {}",
            span.sub_blocks,
            sub_blocks.len()
        )));
    }
    let frame_span =
        sub_blocks[span.sub_blocks.start].start..sub_blocks[span.sub_blocks.end - 1].end;
    let Some(channel) = tracking_channel(&capture.cfa, grey_method) else {
        return Ok(false);
    };
    if !config.enabled || frames.is_multibit() || frame_span.len() < 2 {
        return Ok(false);
    }
    let (h, w) = (motion.height, motion.width);
    let hot = capture.hot_pixels.as_ref();
    let sites = Sites::new(
        w,
        (0..h)
            .map(|y| {
                (0..w)
                    .filter(|&x| {
                        capture.cfa.channel(y, x) == channel && !hot.is_some_and(|m| m[[y, x]])
                    })
                    .map(|x| x as u16)
                    .collect()
            })
            .collect(),
        motion.centre(),
    );
    if sites.count() == 0 {
        return Ok(false);
    }
    let half = motion.half_size();
    let margin = config.margin_px;
    // Zero motion at the reference frame, else the camera held at the anchor before the fit.
    let anchor_camera = (span.anchor_frame != motion.plan.reference_frame)
        .then(|| motion.camera_at(span.anchor_frame as f64));
    let mut trajectory = Trajectory::over(frame_span.clone(), config.knot_frames);
    for (k, &t) in trajectory.times.clone().iter().enumerate() {
        if let Some(inverse) = motion.camera_at(t as f64).inverse() {
            trajectory.knots[k] = inverse.params();
        }
    }
    progress.start(
        "photon trajectory",
        (config.sigmas_px.len() * config.iterations) as u64,
    );
    let early_sites =
        (config.early_row_step > 1).then(|| sites.every_nth_row(config.early_row_step));
    let last_iteration = config.sigmas_px.len() * config.iterations;
    let sites_of = |iteration: usize| match &early_sites {
        Some(early) if iteration + 1 < last_iteration => early,
        _ => &sites,
    };
    let span_frames = SpanFrames {
        frames,
        span: frame_span.clone(),
    };
    let iterations = config
        .sigmas_px
        .iter()
        .flat_map(|&sigma| std::iter::repeat_n(sigma, config.iterations))
        .enumerate();
    for (iteration, sigma) in iterations {
        let sites = sites_of(iteration);
        // The template is rebuilt every iteration: one template per level (rebuilt only when
        // the level starts) lost 0.40 dB on `bench quality`'s kodim22 fast capture
        // (docs/tuning.md).
        let template = build_template(&span_frames, sites, &trajectory, h, margin, isa);
        let level = template_level(&template, sigma);
        scoring_step(
            &span_frames,
            sites,
            &mut trajectory,
            &ScoreTemplate::informative(&level, isa, config.informative_fraction),
            config,
            half,
            margin as f64,
        );
        progress.advance(1);
    }
    progress.finish();
    let anchor = Anchor {
        frame: span.anchor_frame,
        camera: anchor_camera,
    };
    set_frame_camera(
        motion,
        span.sub_blocks.clone(),
        &trajectory,
        &anchor,
        max_sub_block_motion_px,
    );
    Ok(true)
}

/// The frames a trajectory is fitted to: `span` of `frames`.
struct SpanFrames<'a> {
    frames: &'a BinaryFrames,
    span: Range<usize>,
}

/// The frame whose camera a fitted trajectory is placed by, and that camera (`None`: zero).
struct Anchor {
    frame: usize,
    camera: Option<AffineMotion>,
}

/// Replaces the sub-blocks `replaced` of `motion` by runs of consecutive frames inside one
/// block over which `trajectory`'s camera moves at most `max_motion_px` (px at the image
/// corners), each at the camera of its centre, with the `anchor`'s camera at its frame.
fn set_frame_camera(
    motion: &mut FrameMotion,
    replaced: Range<usize>,
    trajectory: &Trajectory,
    anchor: &Anchor,
    max_motion_px: f64,
) {
    let half = motion.half_size();
    let forward = |t: f64| {
        trajectory
            .inverse_camera_at(t)
            .inverse()
            .unwrap_or_default()
    };
    let undo = forward(anchor.frame as f64).inverse().unwrap_or_default();
    let camera_at = |t: f64| match &anchor.camera {
        None => forward(t).after(&undo),
        Some(at_anchor) => forward(t).after(&undo).after(at_anchor),
    };
    let frames = motion.sub_blocks[replaced.start].start..motion.sub_blocks[replaced.end - 1].end;
    let mut sub_blocks: Vec<Range<usize>> = Vec::new();
    let mut block_of = Vec::new();
    let mut camera = Vec::new();
    for (b, block) in motion.plan.blocks.iter().enumerate() {
        let (mut start, end) = (block.start.max(frames.start), block.end.min(frames.end));
        while start < end {
            let first = camera_at(start as f64);
            let mut stop = start + 1;
            while stop < end && camera_at(stop as f64).distance(&first, half) <= max_motion_px {
                stop += 1;
            }
            camera.push(camera_at((start + stop - 1) as f64 / 2.0));
            sub_blocks.push(start..stop);
            block_of.push(b);
            start = stop;
        }
    }
    motion.sub_blocks.splice(replaced.clone(), sub_blocks);
    motion.block_of.splice(replaced.clone(), block_of);
    motion.camera.splice(replaced, camera);
}

#[cfg(test)]
mod tests;
