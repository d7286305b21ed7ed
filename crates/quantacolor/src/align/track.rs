//! Fast camera motion tracked sub-block by sub-block: this project's own stage, not the
//! paper's.
//!
//! Under fast shake (tens of pixels over a few hundred frames) a block of 50–100 frames is a
//! streak, tile alignment of blocks fails, and so does the refinement against block images
//! ([`super::refine`]). Here the burst is instead tracked outward from the reference sub-block:
//! each sub-block's affine camera motion is predicted from its neighbours' (constant velocity),
//! fitted by the Gauss–Newton of [`super::refine`] with a wide coarse level against a template
//! built from the sub-blocks already tracked, and then added to that template. Every fit is to
//! the same growing template, so errors do not compound from one sub-block to the next.
//! (Refitting every sub-block against the finished mosaic measured no better; docs/tuning.md.)
//!
//! Tracking runs only when the block motion says the camera moves fast (see
//! [`TrackConfig::trigger_px`]) and only on CFAs with a tracking channel ([`tracking_channel`]:
//! W, or G of a Bayer CFA); afterwards the merge
//! uses sub-blocks short enough for the tracked motion ([`split_for_merge_in`]).
#![forbid(unsafe_code)]

use super::grey::GreyMethod;
use super::refine::{
    channel_bin_layout, fit_sub_block, template_level, validate_levels, AffineMotion, BinLayout,
    FitSettings, FrameMotion, RefineLevel, TemplateLevel,
};
use crate::capture::Capture;
use crate::cfa::Channel;
use crate::error::{Error, Result};
use crate::filters::gaussian_blur;
use crate::progress::Progress;
use ndarray::Array2;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Settings of [`track_fast_camera_motion`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrackConfig {
    /// Track when two consecutive blocks' cameras differ by more than this (px, at the image
    /// corners) and by more than [`MIN_RMS_SHARE`] of it as an RMS over the image
    /// ([`moves_fast`]): blocks that long are streaks. Infinite disables tracking.
    pub trigger_px: f64, // 6 px
    /// A steady camera (both block cameras within this distance, px at the corners, of the
    /// constant-velocity path, [`off_constant_velocity`], and slow enough for the refinement's
    /// shortest sub-blocks) is not tracked: the refinement follows it. Ours; 0 = off.
    pub steady_px: f64, // 1 px
    /// Coarse-to-fine levels of each sub-block's fit (the coarse level sets the capture range
    /// around the constant-velocity prediction).
    pub levels: Vec<RefineLevel>,
    /// Gauss–Newton iterations per level.
    pub iterations: usize, // 8
    /// Largest linear part (largest |m| entry; 0.1 ≈ 6° or 10 %) of the median tracked camera;
    /// a tracking that needs more has failed and the burst goes through the refinement
    /// instead. Ours: a handheld camera turns a few degrees and does not zoom.
    pub max_linear: f64, // 0.25
    /// The template (blurred levels of the mosaic tracked so far) is made again only once the
    /// mosaic holds this fraction more frames than when last made; 0 = every sub-block. Ours:
    /// a speed setting (making the levels was half of the stage's time).
    pub template_growth: f64, // 0.05
}

impl Default for TrackConfig {
    fn default() -> Self {
        TrackConfig {
            trigger_px: 6.0,
            steady_px: 1.0,
            levels: vec![
                RefineLevel {
                    bin: 8,
                    sigma_px: 4.0,
                },
                RefineLevel {
                    bin: 4,
                    sigma_px: 2.0,
                },
                RefineLevel {
                    bin: 1,
                    sigma_px: 0.7,
                },
            ],
            iterations: 8,
            max_linear: 0.25,
            template_growth: 0.05,
        }
    }
}

impl TrackConfig {
    /// Checks that the thresholds and levels hold usable values (the error names the key).
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, what: &str, value: f64| {
            Err(Error::invalid(format!(
                "fast-motion tracking: [burst.track] {key} must be {what}, got {value}"
            )))
        };
        if self.trigger_px.is_nan() || self.trigger_px < 0.0 {
            return bad(
                "trigger_px",
                "a non-negative number of pixels (inf turns tracking off)",
                self.trigger_px,
            );
        }
        for (key, value) in [
            ("steady_px", self.steady_px),
            ("max_linear", self.max_linear),
            ("template_growth", self.template_growth),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(key, "a non-negative number", value);
            }
        }
        if self.iterations == 0 {
            return bad("iterations", "at least 1", 0.0);
        }
        validate_levels(&self.levels, "fast-motion tracking: [burst.track] levels")
    }
}

/// Share of [`TrackConfig::trigger_px`] that the root-mean-square camera difference of two
/// consecutive blocks must exceed, besides the difference at the corners, for the blocks to
/// count as moving fast.
const MIN_RMS_SHARE: f64 = 0.65;

/// Whether the block motion of `motion` moves faster than `config.trigger_px` between blocks:
/// two consecutive blocks' cameras differ by more than `trigger_px` at an image corner and by
/// more than [`MIN_RMS_SHARE`] of it as a root mean square over the image
/// ([`AffineMotion::rms_distance`]), unless the camera is steady there (both cameras within
/// `config.steady_px` of a constant-velocity path, [`TrackConfig::steady_px`]) and no faster
/// than `followable_px_per_frame` at the corners. This project's heuristic. The corner
/// difference is the streak at the corners; the RMS guard rejects a corner difference made by
/// a shear that moves the image little on average, which is what a block fit leaves unobserved
/// on a scene that constrains one direction only (sky and sea, MultiResolution_Bonita). The
/// margins on both sides of the guard are thin (measurements in docs/tuning.md); a fit of the
/// camera's linear part that knows what the photons left unobserved (as the similarity prior
/// of [`super::refine`] does) would be the better fix.
fn moves_fast(motion: &FrameMotion, config: &TrackConfig, followable_px_per_frame: f64) -> bool {
    fast_block_pairs(motion, config, followable_px_per_frame)
        .iter()
        .any(|&fast| fast)
}

/// For every two consecutive blocks `i`, `i + 1` of `motion`'s plan, whether the camera moves
/// fast between them (the test of [`moves_fast`]).
fn fast_block_pairs(
    motion: &FrameMotion,
    config: &TrackConfig,
    followable_px_per_frame: f64,
) -> Vec<bool> {
    let half = motion.half_size();
    let times = motion.plan.center_frames();
    let cameras: Vec<AffineMotion> = times.iter().map(|&t| motion.camera_at(t)).collect();
    let off_path = off_constant_velocity(&cameras, &times, half);
    let trigger = config.trigger_px;
    (0..cameras.len().saturating_sub(1))
        .map(|i| {
            let (a, b) = (&cameras[i], &cameras[i + 1]);
            let streak = a.distance(b, half);
            let streaks = streak > trigger && a.rms_distance(b, half) > MIN_RMS_SHARE * trigger;
            let offs = [off_path[i], off_path[i + 1]];
            let steady = offs.iter().any(Option::is_some)
                && offs.iter().flatten().all(|&off| off <= config.steady_px);
            let followable = streak / (times[i + 1] - times[i]).max(1.0) <= followable_px_per_frame;
            streaks && !(steady && followable)
        })
        .collect()
}

/// Blocks on each side of two fast-moving blocks that are tracked with them: the slow block
/// the tracking of a span starts from.
const SPAN_MARGIN_BLOCKS: usize = 1;

/// Slow stretches shorter than this many blocks, between two spans or at an end of the
/// capture, are tracked with their spans rather than left to the refinement.
const MIN_SLOW_BLOCKS: usize = 4;

/// The spans of consecutive blocks of `motion`'s plan that fast-motion tracking and the photon
/// trajectory must follow, in time order: every two blocks between which the camera moves fast
/// ([`moves_fast`]) with [`SPAN_MARGIN_BLOCKS`] on each side, spans that meet merged, and slow
/// stretches shorter than [`MIN_SLOW_BLOCKS`] absorbed. Empty when nothing moves fast; one span
/// of every block when the capture moves fast throughout. This project's heuristic: motion is
/// handled locally in time, so a recording that is jolted once is tracked around the jolt
/// only, and the rest keeps the block and sub-block refinement.
pub fn fast_motion_spans(
    motion: &FrameMotion,
    config: &TrackConfig,
    followable_px_per_frame: f64,
) -> Vec<std::ops::Range<usize>> {
    let pairs = fast_block_pairs(motion, config, followable_px_per_frame);
    spans_of_fast_pairs(&pairs, motion.plan.len())
}

/// [`fast_motion_spans`] of the fast pairs `pairs` (pair `i` = blocks `i`, `i + 1`) of
/// `n_blocks` blocks.
fn spans_of_fast_pairs(pairs: &[bool], n_blocks: usize) -> Vec<std::ops::Range<usize>> {
    let mut spans: Vec<std::ops::Range<usize>> = Vec::new();
    for (i, _) in pairs.iter().enumerate().filter(|(_, &fast)| fast) {
        let span = i.saturating_sub(SPAN_MARGIN_BLOCKS)..(i + 2 + SPAN_MARGIN_BLOCKS).min(n_blocks);
        match spans.last_mut() {
            Some(last) if span.start < last.end + MIN_SLOW_BLOCKS => last.end = span.end,
            _ => spans.push(span),
        }
    }
    if let Some(first) = spans.first_mut() {
        if first.start < MIN_SLOW_BLOCKS {
            first.start = 0;
        }
    }
    if let Some(last) = spans.last_mut() {
        if last.end + MIN_SLOW_BLOCKS > n_blocks {
            last.end = n_blocks;
        }
    }
    spans
}

/// Camera motion (px at the image corners) that one block of `motion`'s plan collects when the
/// camera moves steadily: the largest displacement between consecutive block cameras, scaled
/// from the distance of their centre frames to the nominal block size, when every block
/// camera with two neighbours lies within `steady_px` of the constant-velocity path through
/// them; `None` for any other motion (hand shake, fast motion) or fewer than three blocks.
pub fn steady_block_smear(motion: &FrameMotion, steady_px: f64) -> Option<f64> {
    let half = motion.half_size();
    let times = motion.plan.center_frames();
    let cameras: Vec<AffineMotion> = times.iter().map(|&t| motion.camera_at(t)).collect();
    let off_path = off_constant_velocity(&cameras, &times, half);
    if cameras.len() < 3 || off_path.iter().flatten().any(|&off| off > steady_px) {
        return None;
    }
    let block = motion.plan.block_size as f64;
    (0..cameras.len() - 1)
        .map(|i| {
            cameras[i].distance(&cameras[i + 1], half) * block / (times[i + 1] - times[i]).max(1.0)
        })
        .reduce(f64::max)
}

/// How far each block camera lies from the constant-velocity path through its two neighbours
/// (px at the image corners: the camera against its neighbours' cameras interpolated linearly
/// in time to its centre frame); `None` for the first and the last block.
fn off_constant_velocity(
    cameras: &[AffineMotion],
    times: &[f64],
    half: [f64; 2],
) -> Vec<Option<f64>> {
    (0..cameras.len())
        .map(|j| {
            let (before, after) = (j.checked_sub(1)?, j + 1);
            let next = cameras.get(after)?;
            let a = (times[j] - times[before]) / (times[after] - times[before]);
            Some(cameras[j].distance(&cameras[before].lerp(next, a), half))
        })
        .collect()
}

/// The channel whose sites fast-motion tracking and the photon trajectory fit one template to
/// (this project's choice): W on a W-rich CFA (its grey image is W), G on a periodic CFA that
/// holds at least a quarter of G (Bayer: the densest channel, and every G site sees the same
/// filter, so one template fits them all); `None` (the refinement alone) otherwise.
pub fn tracking_channel(cfa: &crate::cfa::Cfa, grey_method: GreyMethod) -> Option<Channel> {
    match grey_method {
        GreyMethod::InterpolateW => Some(Channel::W),
        GreyMethod::TileAverage { .. } if cfa.fractions()[Channel::G.index()] >= 0.25 => {
            Some(Channel::G)
        }
        _ => None,
    }
}

/// The growing template: counts of the tracking channel's sites splatted to their reference
/// positions.
struct Mosaic {
    sum: Array2<f32>,
    frames: Array2<f32>,
    /// Frames of the sub-blocks added.
    frame_count: usize,
    /// Sites of the tracking channel that are not hot, row-major.
    sites: Vec<(usize, usize)>,
}

impl Mosaic {
    /// An empty mosaic of `(h, w)` over the capture's sites of `channel` that are not hot.
    fn of_sites(capture: &Capture, channel: Channel, (h, w): (usize, usize)) -> Self {
        let hot = capture.hot_pixels.as_ref();
        let sites = (0..h)
            .flat_map(|y| (0..w).map(move |x| (y, x)))
            .filter(|&(y, x)| {
                capture.cfa.channel(y, x) == channel && !hot.is_some_and(|m| m[[y, x]])
            })
            .collect();
        Mosaic {
            sum: Array2::zeros((h, w)),
            frames: Array2::zeros((h, w)),
            frame_count: 0,
            sites,
        }
    }

    fn add(
        &mut self,
        counts: &Array2<u32>,
        frames: usize,
        camera: &AffineMotion,
        centre: [f64; 2],
    ) {
        let Some(to_reference) = camera.inverse() else {
            return;
        };
        self.frame_count += frames;
        let (h, w) = self.sum.dim();
        for &(y, x) in &self.sites {
            let d = to_reference.at([y as f64 - centre[0], x as f64 - centre[1]]);
            let (py, px) = ((y as f64 + d[0]).round(), (x as f64 + d[1]).round());
            if py >= 0.0 && px >= 0.0 && (py as usize) < h && (px as usize) < w {
                self.sum[[py as usize, px as usize]] += counts[[y, x]] as f32;
                self.frames[[py as usize, px as usize]] += frames as f32;
            }
        }
    }

    /// Mean bit rate per frame, normalised-convolution filled (σ 0.7 px); the global mean where
    /// nothing landed nearby.
    fn template(&self) -> Array2<f32> {
        let (num, den) = rayon::join(
            || gaussian_blur(&self.sum, 0.7),
            || gaussian_blur(&self.frames, 0.7),
        );
        let total: f32 = self.sum.sum();
        let mean = total / self.frames.sum().max(1.0);
        let floor = 1e-3 * den.iter().copied().fold(0.0f32, f32::max);
        ndarray::Zip::from(&num)
            .and(&den)
            .map_collect(|&n, &d| if d > floor { n / d } else { mean })
    }

    /// The template's fitting levels, made now.
    fn levels(&self, levels: &[RefineLevel]) -> TemplateLevels {
        let template = self.template();
        TemplateLevels {
            levels: levels
                .par_iter()
                .map(|l| template_level(&template, l.sigma_px))
                .collect(),
            frame_count: self.frame_count,
        }
    }
}

/// The fitting levels of a [`Mosaic`]'s template and the mosaic's frame count when they were
/// made.
struct TemplateLevels {
    levels: Vec<TemplateLevel>,
    frame_count: usize,
}

impl TemplateLevels {
    /// Whether `mosaic` has grown by more than `growth` of the frames these were made from.
    fn outgrown_by(&self, mosaic: &Mosaic, growth: f64) -> bool {
        mosaic.frame_count as f64 > self.frame_count as f64 * (1.0 + growth)
    }
}

/// The median over `cameras` of each one's largest linear entry |m| (NaN ranks above
/// everything); `None` without cameras.
fn median_linear_part(cameras: &[AffineMotion]) -> Option<f64> {
    let mut linear: Vec<f64> = cameras
        .iter()
        .map(|c| {
            c.m.iter()
                .flatten()
                .map(|v| if v.is_nan() { f64::INFINITY } else { v.abs() })
                .fold(0.0, f64::max)
        })
        .collect();
    linear.sort_by(f64::total_cmp);
    linear.get(linear.len() / 2).copied()
}

/// Tracks the camera of every sub-block of `motion` outward from the reference frame's
/// sub-block when the block motion says the camera moves fast ([`moves_fast`]; a steady camera
/// no faster than `followable_px_per_frame` at the image corners is left to the refinement);
/// returns whether it did.
pub fn track_fast_camera_motion(
    capture: &Capture,
    grey_method: GreyMethod,
    motion: &mut FrameMotion,
    config: &TrackConfig,
    followable_px_per_frame: f64,
    progress: &dyn Progress,
) -> Result<bool> {
    let Some(channel) = tracking_channel(&capture.cfa, grey_method) else {
        return Ok(false);
    };
    if !moves_fast(motion, config, followable_px_per_frame) {
        return Ok(false);
    }
    let n = motion.sub_blocks.len();
    let first = motion
        .sub_blocks
        .iter()
        .position(|r| r.contains(&motion.plan.reference_frame))
        .unwrap_or(0);
    let camera = vec![AffineMotion::default(); n];
    let tracker = Tracker::new(capture, channel, motion, config, 0..n);
    let Some(camera) = tracker.track_from(first, camera, progress) else {
        return Ok(false);
    };
    motion.camera = camera;
    motion.anchor_at_reference();
    Ok(true)
}

/// Tracks the sub-blocks of `motion` in the consecutive blocks `blocks` only (a span of
/// [`fast_motion_spans`]), outward from a seed sub-block whose camera is kept: the one holding
/// the reference frame when the span holds it (zero camera), else the middle sub-block of the
/// span's first block, or of its last when the span starts the capture (the slow margin
/// blocks, whose camera the refinement measured). The other sub-blocks are left as they are;
/// the span's local residual is dropped (streak matching, not motion). Returns the seed's
/// centre frame (where a trajectory fitted to the span keeps its camera), `None` when the
/// tracking failed ([`TrackConfig::max_linear`]) and nothing was changed.
pub fn track_span(
    capture: &Capture,
    grey_method: GreyMethod,
    motion: &mut FrameMotion,
    blocks: std::ops::Range<usize>,
    config: &TrackConfig,
    progress: &dyn Progress,
) -> Result<Option<usize>> {
    let Some(channel) = tracking_channel(&capture.cfa, grey_method) else {
        return Ok(None);
    };
    if blocks.is_empty() {
        return Ok(None);
    }
    let first = motion.block_of.partition_point(|&b| b < blocks.start);
    let last = motion.block_of.partition_point(|&b| b < blocks.end);
    if first >= last {
        return Ok(None);
    }
    let reference = motion.plan.reference_frame;
    let holds_reference = (first..last).find(|&k| motion.sub_blocks[k].contains(&reference));
    let mut camera = motion.camera.clone();
    let seed = match holds_reference {
        Some(k) => {
            camera[k] = AffineMotion::default();
            k
        }
        None => {
            let margin = if blocks.start > 0 {
                blocks.start
            } else {
                blocks.end - 1
            };
            let own: Vec<usize> = (first..last)
                .filter(|&k| motion.block_of[k] == margin)
                .collect();
            own[own.len() / 2]
        }
    };
    let seed_frame = {
        let r = &motion.sub_blocks[seed];
        (r.start + r.end - 1) / 2
    };
    let tracker = Tracker::new(capture, channel, motion, config, first..last);
    let Some(camera) = tracker.track_from(seed, camera, progress) else {
        return Ok(None);
    };
    motion.camera[first..last].copy_from_slice(&camera[first..last]);
    if holds_reference.is_some() {
        let undo = motion.camera_at(reference as f64).inverse();
        if let Some(undo) = undo {
            for c in &mut motion.camera[first..last] {
                *c = c.after(&undo);
            }
        }
    }
    motion.drop_local_motion_in(blocks);
    Ok(Some(match holds_reference {
        Some(_) => reference,
        None => seed_frame,
    }))
}

/// What [`track_fast_camera_motion`] fits each sub-block with.
struct Tracker<'a> {
    capture: &'a Capture,
    /// The channel whose sites are tracked ([`tracking_channel`]).
    channel: Channel,
    motion: &'a FrameMotion,
    config: &'a TrackConfig,
    layouts: Vec<BinLayout>,
    centres: Vec<f64>,
    centre: [f64; 2],
    /// The sub-blocks tracked.
    range: std::ops::Range<usize>,
}

impl<'a> Tracker<'a> {
    fn new(
        capture: &'a Capture,
        channel: Channel,
        motion: &'a FrameMotion,
        config: &'a TrackConfig,
        range: std::ops::Range<usize>,
    ) -> Self {
        let hot = capture.hot_pixels.as_ref();
        let layouts = config
            .levels
            .par_iter()
            .map(|l| channel_bin_layout(&capture.cfa, channel, hot, l.bin))
            .collect();
        Tracker {
            capture,
            channel,
            motion,
            config,
            layouts,
            centres: motion.sub_block_centres(),
            centre: motion.centre(),
            range,
        }
    }

    /// The cameras of the tracker's sub-blocks tracked outward from sub-block `seed` (forward
    /// in time, then backward, each direction fitted to the mosaic of every sub-block tracked
    /// before it), starting from `camera` (of every sub-block; `camera[seed]` is kept); `None`
    /// when the tracked cameras' median linear part exceeds [`TrackConfig::max_linear`].
    fn track_from(
        &self,
        seed: usize,
        mut camera: Vec<AffineMotion>,
        progress: &dyn Progress,
    ) -> Option<Vec<AffineMotion>> {
        let motion = self.motion;
        let mut mosaic =
            Mosaic::of_sites(self.capture, self.channel, (motion.height, motion.width));
        progress.start("fast motion tracking", self.range.len() as u64);
        self.add_sub_block(&mut mosaic, seed, &self.counts(seed), &camera[seed]);
        progress.advance(1);
        for forward in [true, false] {
            self.track_outward(seed, forward, &mut camera, &mut mosaic, progress);
        }
        progress.finish();
        if median_linear_part(&camera[self.range.clone()])
            .is_some_and(|v| v > self.config.max_linear)
        {
            return None;
        }
        Some(camera)
    }

    fn counts(&self, k: usize) -> Array2<u32> {
        self.capture
            .frames
            .sum_range(self.motion.sub_blocks[k].clone())
    }

    fn add_sub_block(
        &self,
        mosaic: &mut Mosaic,
        k: usize,
        counts: &Array2<u32>,
        camera: &AffineMotion,
    ) {
        mosaic.add(counts, self.motion.sub_blocks[k].len(), camera, self.centre);
    }

    /// Tracks the sub-blocks of the tracker's range after `first` (`forward`) or before it, one at a time, each from
    /// the motion extrapolated from the two tracked before it, fitted to the mosaic, then added
    /// to it.
    fn track_outward(
        &self,
        first: usize,
        forward: bool,
        camera: &mut [AffineMotion],
        mosaic: &mut Mosaic,
        progress: &dyn Progress,
    ) {
        let mut templates: Option<TemplateLevels> = None;
        let (mut k, mut previous) = (first, None::<usize>);
        loop {
            let next = if forward { k + 1 } else { k.wrapping_sub(1) };
            if !self.range.contains(&next) {
                break;
            }
            let prediction = match previous {
                Some(p) => {
                    let a = (self.centres[next] - self.centres[p])
                        / (self.centres[k] - self.centres[p]);
                    camera[p].lerp(&camera[k], a)
                }
                None => camera[k],
            };
            // The template's levels (made again once the mosaic has outgrown them) and the next
            // sub-block's counts, side by side (each fit needs the template of the sub-blocks
            // before it, so the fits are in turn).
            let outgrown = templates
                .as_ref()
                .is_none_or(|t| t.outgrown_by(mosaic, self.config.template_growth));
            let (fresh, counts) = rayon::join(
                || outgrown.then(|| mosaic.levels(&self.config.levels)),
                || self.counts(next),
            );
            if fresh.is_some() {
                templates = fresh;
            }
            let templates = templates
                .as_ref()
                .expect("made on the first step of each direction");
            camera[next] = self.fit(next, &counts, templates, prediction);
            self.add_sub_block(mosaic, next, &counts, &camera[next]);
            progress.advance(1);
            previous = Some(k);
            k = next;
        }
    }

    /// Sub-block `k`'s camera fitted to `templates` from `prediction` (the prediction where
    /// the fit fails).
    fn fit(
        &self,
        k: usize,
        counts: &Array2<u32>,
        templates: &TemplateLevels,
        prediction: AffineMotion,
    ) -> AffineMotion {
        let levels: Vec<&TemplateLevel> = templates.levels.iter().collect();
        let settings = FitSettings {
            iterations: self.config.iterations,
            fine_iterations: self.config.iterations,
            fine_information: 1.0,
            fine_thinning: 0,
        };
        prediction
            .inverse()
            .and_then(|start| {
                fit_sub_block(
                    counts,
                    self.motion.sub_blocks[k].len(),
                    &self.layouts,
                    &levels,
                    start,
                    self.centre,
                    settings,
                )
            })
            .and_then(|inverse| inverse.inverse())
            .unwrap_or(prediction)
    }
}

/// Cuts every sub-block of `motion` in the blocks `blocks` (the others are kept) so that its
/// camera moves at most `max_motion_px` inside each piece (down to single frames), each piece
/// at the camera interpolated to its centre: once the motion is known at every few frames, the
/// merge need not blur it.
pub fn split_for_merge_in(
    motion: &mut FrameMotion,
    blocks: std::ops::Range<usize>,
    max_motion_px: f64,
) {
    let half = motion.half_size();
    let travel = |range: &std::ops::Range<usize>| {
        motion
            .camera_at(range.start as f64)
            .distance(&motion.camera_at((range.end - 1) as f64), half)
    };
    let inside: Vec<bool> = motion.block_of.iter().map(|b| blocks.contains(b)).collect();
    let pieces: Vec<usize> = motion
        .sub_blocks
        .iter()
        .zip(&inside)
        .map(|(r, &inside)| {
            if inside {
                (travel(r) / max_motion_px.max(1e-6)).ceil() as usize
            } else {
                1
            }
        })
        .collect();
    motion.split_sub_blocks(
        |k, _| pieces[k],
        |m, k, r| {
            if inside[k] {
                m.camera_at((r.start + r.end - 1) as f64 / 2.0)
            } else {
                m.camera[k]
            }
        },
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::align::BlockPlan;

    #[test]
    fn a_tracked_shear_like_bonitas_is_kept_and_runaway_fits_are_not() {
        let sheared = |shear: f64| AffineMotion {
            m: [[0.01, -0.01], [shear, -0.015]],
            ..AffineMotion::default()
        };
        let bound = TrackConfig::default().max_linear;
        // MultiResolution_Bonita under fast shake (seed 311): a shear of 0.09–0.13 that the
        // horizon does not constrain, and two outliers.
        let mut cameras: Vec<AffineMotion> =
            (0..9).map(|k| sheared(-0.09 - 0.005 * k as f64)).collect();
        cameras.push(sheared(f64::NAN));
        cameras.push(sheared(-0.9));
        let bonita = median_linear_part(&cameras).unwrap();
        assert!((bonita - 0.115).abs() < 1e-12, "{bonita}");
        assert!(bonita <= bound, "{bonita} over {bound}");
        // The dim static HDR capture of tests/denoise_chroma: fits escaping to ~80.
        let runaway: Vec<AffineMotion> = [81.6, 0.3, 120.0].into_iter().map(sheared).collect();
        assert!(median_linear_part(&runaway).unwrap() > bound);
        assert_eq!(median_linear_part(&[]), None);
    }

    #[test]
    fn templates_are_outgrown_once_the_mosaic_grows_by_more_than_the_fraction() {
        let mut mosaic = Mosaic {
            sum: Array2::zeros((4, 4)),
            frames: Array2::zeros((4, 4)),
            frame_count: 0,
            sites: vec![(1, 1), (2, 3)],
        };
        let counts = Array2::from_elem((4, 4), 1u32);
        mosaic.add(&counts, 100, &AffineMotion::default(), [1.5, 1.5]);
        assert_eq!(mosaic.frame_count, 100);
        assert_eq!(mosaic.frames[[1, 1]], 100.0);
        let made = mosaic.levels(&TrackConfig::default().levels);
        assert_eq!(made.frame_count, 100);
        assert_eq!(made.levels.len(), 3);
        mosaic.add(&counts, 5, &AffineMotion::default(), [1.5, 1.5]);
        assert!(
            !made.outgrown_by(&mosaic, 0.05),
            "105 frames of 100 is not over 5 %"
        );
        assert!(made.outgrown_by(&mosaic, 0.0));
        mosaic.add(&counts, 1, &AffineMotion::default(), [1.5, 1.5]);
        assert!(made.outgrown_by(&mosaic, 0.05), "106 frames of 100 is");
    }

    #[test]
    fn validate_names_each_out_of_range_setting() {
        assert!(TrackConfig::default().validate().is_ok());
        type Edit = fn(&mut TrackConfig);
        let cases: [(&str, Edit); 9] = [
            ("trigger_px", |c| c.trigger_px = -1.0),
            ("trigger_px", |c| c.trigger_px = f64::NAN),
            ("steady_px", |c| c.steady_px = -0.5),
            ("steady_px", |c| c.steady_px = f64::INFINITY),
            ("max_linear", |c| c.max_linear = f64::NAN),
            ("template_growth", |c| c.template_growth = -0.1),
            ("iterations", |c| c.iterations = 0),
            ("levels", |c| c.levels.clear()),
            ("levels", |c| c.levels[0].bin = 0),
        ];
        for (key, edit) in cases {
            let mut config = TrackConfig::default();
            edit(&mut config);
            let message = config.validate().expect_err(key).to_string();
            assert!(message.contains(key), "{key}: {message}");
        }
        // The edges are accepted: tracking off (inf) or always on (0), no steady exemption.
        for trigger_px in [0.0, f64::INFINITY] {
            let edges = TrackConfig {
                trigger_px,
                steady_px: 0.0,
                ..TrackConfig::default()
            };
            assert!(edges.validate().is_ok());
        }
    }

    /// A jolt between blocks 20 and 21 of 40 is tracked over blocks 19..23 only; spans that
    /// nearly meet are merged, short slow stretches at the ends absorbed, and a capture that
    /// moves fast throughout is one span of every block.
    #[test]
    fn fast_motion_is_followed_in_spans_around_the_fast_blocks() {
        let pairs = |fast: &[usize], n: usize| -> Vec<bool> {
            (0..n - 1).map(|i| fast.contains(&i)).collect()
        };
        assert_eq!(spans_of_fast_pairs(&pairs(&[], 40), 40), vec![]);
        assert_eq!(spans_of_fast_pairs(&pairs(&[20], 40), 40), vec![19..23]);
        // Two jolts with two slow blocks between their spans: one span.
        assert_eq!(spans_of_fast_pairs(&pairs(&[10, 16], 40), 40), vec![9..19]);
        // Three: still one; four: two spans.
        assert_eq!(spans_of_fast_pairs(&pairs(&[10, 17], 40), 40), vec![9..20]);
        assert_eq!(
            spans_of_fast_pairs(&pairs(&[10, 18], 40), 40),
            vec![9..13, 17..21]
        );
        // Near the ends: absorbed.
        assert_eq!(spans_of_fast_pairs(&pairs(&[3], 40), 40), vec![0..6]);
        assert_eq!(spans_of_fast_pairs(&pairs(&[35], 40), 40), vec![34..40]);
        assert_eq!(spans_of_fast_pairs(&pairs(&[4], 40), 40), vec![0..7]);
        assert_eq!(spans_of_fast_pairs(&pairs(&[5], 40), 40), vec![4..8]);
        let all: Vec<usize> = (0..39).collect();
        assert_eq!(spans_of_fast_pairs(&pairs(&all, 40), 40), vec![0..40]);
        assert_eq!(spans_of_fast_pairs(&pairs(&[2], 6), 6), vec![0..6]);
    }

    /// `moves_fast` with the default trigger (6 px) and no steady exemption.
    fn moves_fast_at_6_px(motion: &FrameMotion) -> bool {
        let config = TrackConfig {
            trigger_px: 6.0,
            ..TrackConfig::default()
        };
        moves_fast(motion, &config, 0.0)
    }

    /// Block cameras of a 2,000-frame burst in blocks of 200 frames (254 x 496 px), each the
    /// camera of its block's index and centre frame.
    fn block_motion(camera: &dyn Fn(usize, f64) -> AffineMotion) -> FrameMotion {
        let plan = BlockPlan::new(2000, 200, 1000).unwrap();
        let centres = plan.center_frames();
        let cameras = (0..plan.len()).map(|b| camera(b, centres[b])).collect();
        FrameMotion::of_block_cameras(254, 496, plan, cameras)
    }

    fn translation(dy: f64, dx: f64) -> AffineMotion {
        AffineMotion {
            b: [dy, dx],
            m: [[0.0; 2]; 2],
        }
    }

    /// Block cameras 1 px apart whose shear alternates by 0.045 (what a scene that constrains
    /// one direction only leaves unobserved: 5.7 px at the top and bottom edges of a 254-row
    /// image, 6.7 px at the corners with the translation, 3.5 px RMS) do not move fast; blocks
    /// 7 px apart do, and so do blocks turning by 3° at a time (14.6 px at the corners, 8.4 px
    /// RMS), but not blocks 5.9 px apart.
    #[test]
    fn an_unobserved_shear_is_not_fast_motion() {
        let sheared = block_motion(&|b, _| AffineMotion {
            b: [0.0, b as f64],
            m: [[0.0, 0.0], [0.045 * (b % 2) as f64, 0.0]],
        });
        let half = sheared.half_size();
        let corners = sheared.camera[0].distance(&sheared.camera[1], half);
        assert!(corners > 6.0, "the shear moves the corners by {corners} px");
        assert!(!moves_fast_at_6_px(&sheared));
        assert!(moves_fast_at_6_px(&block_motion(&|b, _| translation(
            0.0,
            7.0 * b as f64
        ))));
        let turning = block_motion(&|b, _| {
            let angle = (3.0 * b as f64).to_radians();
            AffineMotion {
                b: [0.0, 0.0],
                m: [
                    [angle.cos() - 1.0, -angle.sin()],
                    [angle.sin(), angle.cos() - 1.0],
                ],
            }
        });
        assert!(moves_fast_at_6_px(&turning));
        assert!(!moves_fast_at_6_px(&block_motion(&|b, _| translation(
            0.0,
            5.9 * b as f64
        ))));
    }

    /// A steady pan of 0.034 px per frame (6.8 px between 200-frame blocks) is left to the
    /// refinement when its sub-blocks can follow 0.035 px per frame, and tracked when they
    /// cannot (0.03); a camera at the same speed whose blocks lie 0.75 px (more than
    /// `steady_px`, 1 px, at the corners: 0.75 px each way is 1.5 px off its neighbours' path)
    /// alternately ahead and behind the pan is tracked, at 0.25 px not; so is a pan that turns
    /// by 90°; with `steady_px` 0 every streak is tracked.
    #[test]
    fn a_steady_pan_smears_each_block_by_its_speed_over_a_block() {
        let steady = TrackConfig::default().steady_px;
        // 0.02 px per frame over 200-frame blocks (the end blocks longer, scaled back).
        let pan = block_motion(&|_, t| translation(0.0, 0.02 * t));
        let smear = steady_block_smear(&pan, steady).expect("a steady pan");
        assert!((smear - 4.0).abs() < 1e-9, "{smear} px");
        // Block cameras alternately 0.75 px ahead and behind: not steady.
        let shaky = block_motion(&|b, t| {
            translation(0.0, 0.02 * t + if b % 2 == 0 { 0.75 } else { -0.75 })
        });
        assert_eq!(steady_block_smear(&shaky, steady), None);
        assert!(steady_block_smear(&shaky, 2.0).is_some());
        // Two blocks have no path to lie on.
        let plan = BlockPlan::new(400, 200, 100).unwrap();
        assert_eq!(plan.len(), 2);
        let two = FrameMotion::of_block_cameras(
            254,
            496,
            plan.clone(),
            plan.center_frames()
                .iter()
                .map(|&t| translation(0.0, 0.02 * t))
                .collect(),
        );
        assert_eq!(steady_block_smear(&two, steady), None);
    }

    #[test]
    fn a_steady_pan_is_left_to_the_refinement_when_its_sub_blocks_can_follow() {
        let config = TrackConfig::default();
        let pan = block_motion(&|_, t| translation(0.0, 0.034 * t));
        assert!(!moves_fast(&pan, &config, 0.035));
        assert!(moves_fast(&pan, &config, 0.03));
        let off = TrackConfig {
            steady_px: 0.0,
            ..config.clone()
        };
        assert!(moves_fast(&pan, &off, 0.035));
        let alternating = |shift: f64| {
            block_motion(&move |b, t| {
                translation(0.0, 0.034 * t + if b % 2 == 0 { shift } else { -shift })
            })
        };
        assert!(moves_fast(&alternating(0.75), &config, 0.05));
        assert!(!moves_fast(&alternating(0.25), &config, 0.05));
        // A diagonal pan (0.025 px per frame each way, 7.1 px between blocks) that turns by 90°
        // at frame 1000.
        let turning = block_motion(&|_, t| {
            let v = 0.025;
            translation(v * (1000.0 - (t - 1000.0).abs()), v * t)
        });
        assert!(moves_fast(&turning, &config, 0.05));
        let straight = block_motion(&|_, t| translation(0.025 * t, 0.025 * t));
        assert!(!moves_fast(&straight, &config, 0.05));
    }
}
