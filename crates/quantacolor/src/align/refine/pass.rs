//! The stage: passes of templates from the current block motion, a fit per sub-block and
//! smoothing in time, each followed by the similarity prior (see the module documentation).
#![forbid(unsafe_code)]

use super::affine::AffineMotion;
use super::bins::{bin_layout, BinLayout};
use super::config::RefineConfig;
use super::fit::{fit_sub_block_with_information, FitSettings, Information, SubBlockFit};
use super::frame_motion::FrameMotion;
use super::prior::similarity_posterior;
use super::template::{
    leave_one_out_templates, template_level, warp_blocks_to_reference, TemplateLevel, WarpedBlocks,
    TEMPLATE_GROUP,
};
use crate::align::grey::GreyMethod;
use crate::align::motion::invert;
use crate::capture::{BinaryFrames, Capture};
use crate::cpu::{self, Isa};
use crate::error::{Error, Result};
use crate::progress::Progress;
use ndarray::Array2;
use rayon::prelude::*;

/// Re-measures the camera motion of every sub-block of `motion` against a template made of the
/// other blocks and smooths it in time; see the module documentation. The stage's entry: the
/// instruction set of its fits ([`Isa::current`]) is taken here.
///
/// The template of the sub-blocks of block k is the mean of every *other* block's grey image
/// (`grey_blocks`, mean bit rate per frame) warped to the reference by the current block motion
/// ([`FrameMotion::block_flow`]): a template that holds the sub-block's own photon noise pulls the
/// fit toward that noise. The coarse level uses the mean of all blocks. Sub-blocks are summed from
/// the packed frames; the capture's hot pixels are left out of the bins.
pub fn refine_camera_motion(
    capture: &Capture,
    grey_method: GreyMethod,
    grey_blocks: &[Array2<f32>],
    motion: &mut FrameMotion,
    config: &RefineConfig,
    progress: &dyn Progress,
) -> Result<()> {
    if !config.enabled || matches!(grey_method, GreyMethod::Demosaic) {
        return Ok(());
    }
    config.validate()?;
    if grey_blocks.len() != motion.plan.len() {
        return Err(Error::invalid(format!(
            "motion refinement: {} grey blocks for {} planned blocks",
            grey_blocks.len(),
            motion.plan.len()
        )));
    }
    let layouts: Vec<BinLayout> = config
        .levels
        .par_iter()
        .map(|l| {
            bin_layout(
                &capture.cfa,
                grey_method,
                capture.hot_pixels.as_ref(),
                l.bin,
            )
        })
        .collect();
    let inputs = PassInputs {
        frames: &capture.frames,
        layouts: &layouts,
        grey_blocks,
        config,
        progress,
        isa: Isa::current(),
    };
    for _ in 0..config.passes.max(1) {
        let before = motion.camera.clone();
        let information = refine_pass(&inputs, motion)?;
        // The templates are registered wherever the block motion put them; the convention is
        // zero motion at the reference frame.
        motion.anchor_at_reference();
        // Whether to run another pass is decided on the fits themselves: how far the photons
        // moved the cameras from the motion the templates were registered by (the prior's own
        // move is not evidence of misregistered templates).
        let half = motion.half_size();
        let mut changes: Vec<f64> = before
            .iter()
            .zip(&motion.camera)
            .map(|(a, b)| a.distance(b, half))
            .collect();
        changes.sort_by(f64::total_cmp);
        let median_change = changes.get(changes.len() / 2).copied().unwrap_or(0.0);
        if config.similarity_prior_px > 0.0 {
            let radius = motion.centre()[0].max(motion.centre()[1]).max(1.0);
            for (camera, info) in motion.camera.iter_mut().zip(&information) {
                if let Some(info) = info {
                    *camera =
                        similarity_posterior(camera, info, config.similarity_prior_px, radius);
                }
            }
            motion.anchor_at_reference();
        }
        if median_change <= config.repeat_above_px {
            break;
        }
    }
    Ok(())
}

/// What every pass of [`refine_camera_motion`] reads: the capture's frames, every level's bins,
/// the grey blocks, the settings, the progress report and the instruction set of the fits.
struct PassInputs<'a> {
    frames: &'a BinaryFrames,
    layouts: &'a [BinLayout],
    grey_blocks: &'a [Array2<f32>],
    config: &'a RefineConfig,
    progress: &'a dyn Progress,
    isa: Isa,
}

/// One pass of [`refine_camera_motion`]: templates from the current block motion, a fit per
/// sub-block, smoothing in time. Returns the [`Information`] of every sub-block's fit (`None`
/// where it failed and kept its starting motion).
fn refine_pass(inputs: &PassInputs, motion: &mut FrameMotion) -> Result<Vec<Option<Information>>> {
    let (grey_blocks, config, progress) = (inputs.grey_blocks, inputs.config, inputs.progress);
    let n_blocks = grey_blocks.len();
    let WarpedBlocks { total, mut kept } = warp_blocks_to_reference(grey_blocks, motion)?;
    let all = &total / n_blocks as f32;
    let last = config.levels.len() - 1;
    // Every level but the finest is made from the mean of all blocks; the finest from the
    // other blocks' mean, per block (one block alone: its own).
    let shared: Vec<Option<TemplateLevel>> = config
        .levels
        .iter()
        .enumerate()
        .map(|(i, l)| (i < last || n_blocks == 1).then(|| template_level(&all, l.sigma_px)))
        .collect();
    progress.start("motion refinement", motion.sub_blocks.len() as u64);
    let mut fitted: Vec<Option<(AffineMotion, Information)>> = vec![None; motion.sub_blocks.len()];
    let busy: Vec<usize> = (0..n_blocks)
        .filter(|b| motion.block_of.contains(b))
        .collect();
    // A few blocks at a time: their own templates in parallel, then all their sub-blocks' fits
    // in one parallel loop (one block's few sub-blocks leave cores idle); memory stays bounded
    // by the group, not the number of blocks.
    for group in busy.chunks(cpu::balanced_chunk_len(busy.len(), TEMPLATE_GROUP)) {
        let own_images: Vec<Option<Array2<f32>>> = group.iter().map(|&b| kept[b].take()).collect();
        let own_templates = leave_one_out_templates(
            group,
            own_images,
            &total,
            grey_blocks,
            motion,
            config.levels[last].sigma_px,
        )?;
        let templates: Vec<Vec<&TemplateLevel>> = own_templates
            .iter()
            .map(|own| match own {
                Some(own) => shared.iter().map(|t| t.as_ref().unwrap_or(own)).collect(),
                None => shared.iter().flatten().collect(),
            })
            .collect();
        for (k, result) in fit_group_sub_blocks(inputs, motion, group, &templates) {
            fitted[k] = result;
        }
        // The sums hand back the pages they read, but not those the kernel mapped around them
        // (fault-around): the group's frames are handed back whole, or a long recording's
        // resident memory grows with its sub-blocks.
        if let (Some(&first), Some(&last)) = (group.first(), group.last()) {
            let blocks = &motion.plan.blocks;
            inputs.frames.release(blocks[first].start..blocks[last].end);
        }
    }
    progress.finish();
    motion.camera = refined_camera(&fitted, motion, config);
    Ok(fitted
        .into_iter()
        .map(|f| f.map(|(_, info)| info))
        .collect())
}

/// The fit of every sub-block of the blocks of `group` (`templates[g]` are the levels of
/// `group[g]`'s), in one parallel loop: `(sub-block, fitted motion and its information)`,
/// `None` where the fit failed or moved farther than `max_correction_px` from its start.
fn fit_group_sub_blocks(
    inputs: &PassInputs,
    motion: &FrameMotion,
    group: &[usize],
    templates: &[Vec<&TemplateLevel>],
) -> Vec<(usize, Option<(AffineMotion, Information)>)> {
    let (config, progress) = (inputs.config, inputs.progress);
    let settings = FitSettings {
        fine_iterations: config.fine_iterations,
        fine_information: config.fine_information,
        fine_thinning: config.fine_thinning,
        iterations: config.iterations,
    };
    let (centre, half) = (motion.centre(), motion.half_size());
    let members: Vec<(usize, usize)> = (0..motion.sub_blocks.len())
        .filter_map(|k| {
            group
                .iter()
                .position(|&b| b == motion.block_of[k])
                .map(|g| (k, g))
        })
        .collect();
    members
        .par_iter()
        .with_max_len(1)
        .map(|&(k, g)| {
            let range = motion.sub_blocks[k].clone();
            let start = motion.camera[k];
            let counts = inputs.frames.shared_sum(range.clone());
            let result = start.inverse().and_then(|inverse_start| {
                let fit = SubBlockFit {
                    counts: counts.as_slice()?,
                    frames: range.len(),
                    layouts: inputs.layouts,
                    templates: &templates[g],
                    centre,
                    settings,
                    isa: inputs.isa,
                };
                fit_sub_block_with_information(&fit, inverse_start)
                    .and_then(|(inv, info)| inv.inverse().map(|fit| (fit, info)))
                    .filter(|(fit, _)| fit.distance(&start, half) <= config.max_correction_px)
            });
            progress.advance(1);
            (k, result)
        })
        .collect()
}

/// Every sub-block's camera motion after the fits: the fit where there is one, the motion it
/// started from otherwise, then smoothed in time when `config.smooth_radius` > 0.
fn refined_camera(
    fitted: &[Option<(AffineMotion, Information)>],
    motion: &FrameMotion,
    config: &RefineConfig,
) -> Vec<AffineMotion> {
    let valid: Vec<bool> = fitted.iter().map(|f| f.is_some()).collect();
    let camera: Vec<AffineMotion> = fitted
        .iter()
        .zip(&motion.camera)
        .map(|(f, start)| f.map_or(*start, |(fit, _)| fit))
        .collect();
    if config.smooth_radius > 0 {
        smooth_in_time(
            &camera,
            &valid,
            &motion.sub_block_centres(),
            config.smooth_radius,
        )
    } else {
        camera
    }
}

/// Local quadratic fit along time of every parameter of `camera` (sub-block centres `times`)
/// over `radius` neighbours each side, from the sub-blocks marked `valid`.
fn smooth_in_time(
    camera: &[AffineMotion],
    valid: &[bool],
    times: &[f64],
    radius: usize,
) -> Vec<AffineMotion> {
    let n = camera.len();
    (0..n)
        .map(|k| {
            let lo = k.saturating_sub(radius);
            let hi = (k + radius + 1).min(n);
            let idx: Vec<usize> = (lo..hi).filter(|&j| valid[j]).collect();
            if idx.is_empty() {
                return camera[k];
            }
            let order = idx.len().min(3);
            let scale = (times[hi - 1] - times[lo]).max(1.0);
            let mut normal = vec![vec![0.0f64; order]; order];
            let mut rhs = vec![[0.0f64; 6]; order];
            for &j in &idx {
                let u = (times[j] - times[k]) / scale;
                let basis: Vec<f64> = (0..order).map(|p| u.powi(p as i32)).collect();
                let p = camera[j].params();
                for r in 0..order {
                    for c in 0..order {
                        normal[r][c] += basis[r] * basis[c];
                    }
                    for (i, v) in p.iter().enumerate() {
                        rhs[r][i] += basis[r] * v;
                    }
                }
            }
            match invert(normal) {
                Some(inv) => AffineMotion::from_params(std::array::from_fn(|i| {
                    (0..order).map(|c| inv[0][c] * rhs[c][i]).sum()
                })),
                None => camera[k],
            }
        })
        .collect()
}
