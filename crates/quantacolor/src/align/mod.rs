//! Alignment: from binary frames to block-level and frame-level motion (paper §4.1 and §4.3;
//! supplement §1.1 and §1.4; method of Quanta Burst Photography, Ma et al. 2020 §4).
//!
//! Stages, each callable on its own:
//! 1. [`hot_pixels`]: hot-pixel correction by random same-colour neighbours, dark-count map.
//! 2. [`blocks`]: temporal blocks of 100–1000 frames and the reference block.
//! 3. [`grey`]: grey block images (W interpolation, tile average or demosaic, by CFA class).
//! 4. [`patch`]: hierarchical tile alignment of each grey block image to the reference's.
//! 5. [`motion`]: frame-level flow by interpolation in time, per-pixel flow in space.
//! 6. [`refine`]: camera motion re-measured on short sub-blocks against the reference image
//!    (this project's own stage, run by [`crate::burst`] once the reference exists).
//!
//! [`align`] runs them in order with memory bounded in T: block sums are made one block at a
//! time (a few in parallel, the frames' mapped pages released behind them) and only the grey
//! images, `(H, W)` f32 per block, are kept.

pub mod blocks;
pub mod grey;
pub mod hot_pixels;
pub mod motion;
pub mod patch;
pub mod refine;
pub mod track;
pub mod trajectory;

pub use blocks::{BlockConfig, BlockPlan};
pub use grey::{grey_image, GreyChoice, GreyImager, GreyMethod};
pub use hot_pixels::{
    dark_count_rate_map, detect_hot_pixels, hot_pixel_mask, HotPixelConfig, HotPixelCorrector,
    HotPixelDetectConfig,
};
pub use motion::{block_centre_flow, flow_at, frame_flow};
pub use patch::{Norm, PatchConfig, ReferenceAligner, SecondMotionSearch, TileGrid};
pub use refine::{
    plan_sub_blocks, refine_camera_motion, shortest_sub_block, AffineMotion, FrameMotion,
    RefineConfig, RefineLevel,
};
pub use track::{
    fast_motion_spans, split_for_merge_in, steady_block_smear, track_fast_camera_motion,
    track_span, tracking_channel, TrackConfig,
};
pub use trajectory::{
    fit_photon_trajectory, fit_photon_trajectory_over, TrajectoryConfig, TrajectorySpan,
};

use crate::atomic::write_atomic_synced;
use crate::capture::BinaryFrames;
use crate::cfa::Cfa;
use crate::error::{Error, Result};
use crate::progress::Progress;
use ndarray::{s, Array2, Array3, Array4};
use ndarray_npy::WriteNpyExt;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Block-level flow `(n_blocks, tiles_y, tiles_x, 2)` of `(dy, dx)` in pixels: a scene point at
/// `p` in the reference frame is at `p + flow` in the block's centre frame.
pub type Flow = Array4<f32>;

/// Settings of the whole alignment stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AlignConfig {
    /// Hot-pixel correction (used when a hot-pixel mask is given).
    pub hot_pixels: HotPixelConfig,
    /// Block size.
    pub blocks: BlockConfig,
    /// Grey-image method.
    pub grey: GreyChoice,
    /// Hierarchical patch alignment.
    pub patch: PatchConfig,
    /// Radius (tiles) of the component-wise median filter applied to each block's tile flow:
    /// removes isolated mismatches (periodic texture, photon noise) that a single 16 px tile of
    /// a dark block cannot resolve. 0 disables it.
    pub median_radius: usize, // 1 tile (3x3)
    /// Replace each block's tile flow by the component-wise median of it and its two temporal
    /// neighbours (motion is smooth in time, isolated mismatches are not). Off: with few
    /// blocks it flattens real motion peaks (docs/tuning.md).
    pub temporal_median: bool, // false
    /// Tiles whose (median-filtered) flow lies within this distance of the block's robust
    /// affine fit take the fit (camera motion is affine to first order); tiles farther away
    /// keep their own flow (moving objects). 0 disables the fit.
    pub affine_tolerance_px: f32, // 2 px
    /// Convert the measured flows (between block-mean positions) to flows at the block centre
    /// frames relative to the reference frame ([`block_centre_flow`]), computed on each block's
    /// camera fit.
    pub centre_correction: bool, // true
    /// Search radius (px) of the second motion model that tiles rejected by the camera fit
    /// are given ([`ReferenceAligner::follow_second_motion`]); 0 disables it.
    pub second_motion_radius_px: usize, // 16
    /// Fewest rejected tiles for which the second motion model is fitted.
    pub second_motion_min_tiles: usize, // 16
}

impl Default for AlignConfig {
    fn default() -> Self {
        AlignConfig {
            hot_pixels: HotPixelConfig::default(),
            blocks: BlockConfig::default(),
            grey: GreyChoice::default(),
            patch: PatchConfig::default(),
            median_radius: 1,
            temporal_median: false,
            affine_tolerance_px: 2.0,
            centre_correction: true,
            second_motion_radius_px: 16,
            second_motion_min_tiles: 16,
        }
    }
}

/// Scale (px) of the Tukey biweight of the final iterations of [`affine_fit_field`].
const TUKEY_SCALE_PX: f64 = 1.5;

/// Robust affine fit of the tile flows (dy, dx) = A·(y, x) + b by iteratively reweighted least
/// squares (Huber weights with 1 px scale, zero weight beyond 2 × `tolerance`, for 5
/// iterations; then 5 with Tukey's biweight of scale 1.5 px, zero beyond it); tiles within
/// `tolerance` px of the fit are replaced by it.
pub fn snap_to_affine_fit(tile_flow: &Array3<f32>, grid: &TileGrid, tolerance: f32) -> Array3<f32> {
    let Some(fit) = affine_fit_field(tile_flow, grid, tolerance) else {
        return tile_flow.clone();
    };
    let (ty, tx, _) = tile_flow.dim();
    let mut out = tile_flow.clone();
    for i in 0..ty {
        for j in 0..tx {
            let (dy, dx) = (
                tile_flow[[i, j, 0]] - fit[[i, j, 0]],
                tile_flow[[i, j, 1]] - fit[[i, j, 1]],
            );
            if (dy * dy + dx * dx).sqrt() <= tolerance {
                out[[i, j, 0]] = fit[[i, j, 0]];
                out[[i, j, 1]] = fit[[i, j, 1]];
            }
        }
    }
    out
}

/// The robust affine fit of [`snap_to_affine_fit`] evaluated at every tile, `(tiles_y,
/// tiles_x, 2)`; `None` when `tolerance` is not positive, there are fewer than 6 tiles or the
/// normal equations are singular.
pub fn affine_fit_field(
    tile_flow: &Array3<f32>,
    grid: &TileGrid,
    tolerance: f32,
) -> Option<Array3<f32>> {
    let (ty, tx, _) = tile_flow.dim();
    if tolerance <= 0.0 || ty * tx < 6 {
        return None;
    }
    let (cy, cx) = (
        grid.tile_centers_y.iter().sum::<f32>() / ty as f32,
        grid.tile_centers_x.iter().sum::<f32>() / tx as f32,
    );
    let mut weights = vec![1.0f64; ty * tx];
    let mut params = [[0.0f64; 3]; 2];
    for it in 0..10 {
        let mut normal = [[0.0f64; 3]; 3];
        let mut rhs = [[0.0f64; 3]; 2];
        for i in 0..ty {
            for j in 0..tx {
                let wgt = weights[i * tx + j];
                let basis = [
                    1.0,
                    (grid.tile_centers_y[i] - cy) as f64,
                    (grid.tile_centers_x[j] - cx) as f64,
                ];
                for r in 0..3 {
                    for c in 0..3 {
                        normal[r][c] += wgt * basis[r] * basis[c];
                    }
                    for (k, rhs_k) in rhs.iter_mut().enumerate() {
                        rhs_k[r] += wgt * basis[r] * tile_flow[[i, j, k]] as f64;
                    }
                }
            }
        }
        for k in 0..2 {
            params[k] = solve3(normal, rhs[k])?;
        }
        for i in 0..ty {
            for j in 0..tx {
                let r = residual(tile_flow, grid, &params, (cy, cx), i, j);
                // Huber near the fit, zero beyond 2x the tolerance (other motions, mismatches);
                // then Tukey: mismatched tiles 1-4 px off (at 0.1 photons, B = 64, most tiles)
                // lie mostly toward zero motion, and Huber's 1/r weight let them pull the fit
                // short of the true motion (gain 0.97 -> 0.99, handheld EPE 0.18 -> 0.11 px).
                weights[i * tx + j] = if it >= 4 {
                    if r < TUKEY_SCALE_PX {
                        (1.0 - (r / TUKEY_SCALE_PX).powi(2)).powi(2)
                    } else {
                        0.0
                    }
                } else if r <= 1.0 {
                    1.0
                } else if r <= 2.0 * tolerance as f64 {
                    1.0 / r
                } else {
                    0.0
                };
            }
        }
    }
    Some(Array3::from_shape_fn((ty, tx, 2), |(i, j, k)| {
        affine_at(&params[k], grid, (cy, cx), i, j) as f32
    }))
}

fn affine_at(p: &[f64; 3], grid: &TileGrid, centre: (f32, f32), i: usize, j: usize) -> f64 {
    p[0] + p[1] * (grid.tile_centers_y[i] - centre.0) as f64
        + p[2] * (grid.tile_centers_x[j] - centre.1) as f64
}

fn residual(
    flow: &Array3<f32>,
    grid: &TileGrid,
    params: &[[f64; 3]; 2],
    centre: (f32, f32),
    i: usize,
    j: usize,
) -> f64 {
    let dy = flow[[i, j, 0]] as f64 - affine_at(&params[0], grid, centre, i, j);
    let dx = flow[[i, j, 1]] as f64 - affine_at(&params[1], grid, centre, i, j);
    (dy * dy + dx * dx).sqrt()
}

/// Solves the 3x3 system `m·x = b` by Cramer's rule; `None` if singular.
fn solve3(m: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(&m);
    if d.abs() < 1e-12 {
        return None;
    }
    let mut x = [0.0; 3];
    for (c, xc) in x.iter_mut().enumerate() {
        let mut mc = m;
        for r in 0..3 {
            mc[r][c] = b[r];
        }
        *xc = det(&mc) / d;
    }
    Some(x)
}

/// Component-wise median over (previous, this, next) block of every tile flow; the first, last
/// and reference blocks are kept.
pub fn temporal_median_flow(flow: &Flow, reference_block: usize) -> Flow {
    let n = flow.dim().0;
    let mut out = flow.clone();
    for b in 1..n.saturating_sub(1) {
        if b == reference_block {
            continue;
        }
        ndarray::Zip::from(out.slice_mut(s![b, .., .., ..]))
            .and(flow.slice(s![b - 1, .., .., ..]))
            .and(flow.slice(s![b, .., .., ..]))
            .and(flow.slice(s![b + 1, .., .., ..]))
            .for_each(|o, &a, &m, &c| *o = a.max(m).min(a.min(m).max(c)));
    }
    out
}

/// Component-wise median of `tile_flow` (tiles_y, tiles_x, 2) over a (2r+1)² window of tiles
/// (clipped at the grid edges).
pub fn median_filter_flow(tile_flow: &Array3<f32>, radius: usize) -> Array3<f32> {
    let (ty, tx, _) = tile_flow.dim();
    median_filter_valid_flow(tile_flow, &Array2::from_elem((ty, tx), true), radius)
}

/// [`median_filter_flow`] over the tiles of each window marked `valid` (sub-pixel refined; see
/// [`ReferenceAligner::align_with_validity`]), or over all of them where none is: the integer
/// flows of tiles where Lucas–Kanade failed would pull the median toward whole pixels.
pub fn median_filter_valid_flow(
    tile_flow: &Array3<f32>,
    valid: &Array2<bool>,
    radius: usize,
) -> Array3<f32> {
    let (ty, tx, _) = tile_flow.dim();
    assert_eq!(valid.dim(), (ty, tx), "flow and validity disagree");
    if radius == 0 {
        return tile_flow.clone();
    }
    let mut out = tile_flow.clone();
    let mut window = Vec::with_capacity((2 * radius + 1).pow(2));
    for y in 0..ty {
        for x in 0..tx {
            for c in 0..2 {
                window.clear();
                for only_valid in [true, false] {
                    for yy in y.saturating_sub(radius)..(y + radius + 1).min(ty) {
                        for xx in x.saturating_sub(radius)..(x + radius + 1).min(tx) {
                            if valid[[yy, xx]] || !only_valid {
                                window.push(tile_flow[[yy, xx, c]]);
                            }
                        }
                    }
                    if !window.is_empty() {
                        break;
                    }
                }
                // The middle of the window in `total_cmp` order, by selection instead of a
                // full sort: the same values (elements equal in that order are the same bits).
                let n = window.len();
                let (below, &mut upper, _) = window.select_nth_unstable_by(n / 2, f32::total_cmp);
                out[[y, x, c]] = if n % 2 == 1 {
                    upper
                } else {
                    let lower = below
                        .iter()
                        .copied()
                        .max_by(f32::total_cmp)
                        .expect("an even, nonempty window");
                    0.5 * (lower + upper)
                };
            }
        }
    }
    out
}

/// Result of [`align`].
#[derive(Debug, Clone)]
pub struct Alignment {
    /// The blocks.
    pub plan: BlockPlan,
    /// The tile grid of the flow (finest level, reference-frame pixel coordinates).
    pub grid: TileGrid,
    /// Block-level flow.
    pub flow: Flow,
    /// How grey images were made.
    pub grey_method: GreyMethod,
    /// Grey image `(H, W)` of every block, mean detections per frame (not smoothed; hot pixels
    /// corrected when a mask was given). The reference image stage warps these. One image per
    /// block, 4·H·W bytes (0.5 MB at 496x254): the only per-block images the burst keeps.
    pub grey: Vec<Array2<f32>>,
}

impl Alignment {
    /// The blocks and tile grid of the flow, as `flow.toml` holds them.
    pub fn flow_meta(&self) -> FlowMeta {
        FlowMeta {
            block_size: self.plan.block_size,
            block_start_frames: self.plan.start_frames(),
            block_center_frames: self.plan.center_frames(),
            tile_size: self.grid.tile_size,
            tile_stride: self.grid.tile_stride,
            tile_centers_y: self.grid.tile_centers_y.clone(),
            tile_centers_x: self.grid.tile_centers_x.clone(),
        }
    }

    /// Flow of frame `t`, `(tiles_y, tiles_x, 2)` (see [`frame_flow`]).
    pub fn frame_flow(&self, t: usize) -> Array3<f32> {
        frame_flow(&self.flow, &self.plan, t as f64)
    }
}

/// Aligns a burst: plans blocks around `reference_frame`, makes every block's (hot-pixel
/// corrected) sum and grey image, and aligns each grey image to the reference block's.
pub fn align(
    frames: &BinaryFrames,
    cfa: &Cfa,
    hot: Option<&Array2<bool>>,
    reference_frame: usize,
    config: &AlignConfig,
    progress: &dyn Progress,
) -> Result<Alignment> {
    let (h, w) = (frames.height(), frames.width());
    if (cfa.height(), cfa.width()) != (h, w) {
        return Err(Error::invalid(format!(
            "frames are {h}x{w} but the CFA is {}x{}",
            cfa.height(),
            cfa.width()
        )));
    }
    config.patch.validate()?;
    let plan = BlockPlan::choose(frames, reference_frame, &config.blocks)?;
    let grey_method = GreyMethod::resolve(config.grey, cfa)?;
    let corrector = hot
        .map(|m| HotPixelCorrector::new(cfa, m, config.hot_pixels.k, config.hot_pixels.seed))
        .transpose()?;

    let imager = GreyImager::new(cfa, grey_method);
    progress.start("block sums", plan.len() as u64);
    let grey: Vec<Array2<f32>> = plan
        .blocks
        .par_iter()
        .with_max_len(1)
        .map(|range| {
            let sums = match &corrector {
                Some(c) => c.corrected_block_sum(frames, range.clone()),
                None => frames.shared_sum(range.clone()),
            };
            let image = imager.image(&sums, range.len());
            progress.advance(1);
            image
        })
        .collect::<Result<_>>()?;
    progress.finish();
    let (grid, flow) = align_grey_blocks(&grey, &plan, config, progress)?;
    Ok(Alignment {
        plan,
        grid,
        flow,
        grey_method,
        grey,
    })
}

/// The tile alignment of [`align`] on its own: every grey block image of `plan` aligned to its
/// reference block's (hierarchical tile search, median filter, robust camera fit, second
/// motion, centre-frame correction). Returns the tile grid and the block-level flow.
pub fn align_grey_blocks(
    grey: &[Array2<f32>],
    plan: &BlockPlan,
    config: &AlignConfig,
    progress: &dyn Progress,
) -> Result<(TileGrid, Flow)> {
    config.patch.validate()?;
    if grey.len() != plan.len() || plan.reference_block >= plan.len() {
        return Err(Error::invalid(format!(
            "alignment: {} grey blocks for {} planned blocks (reference block {})",
            grey.len(),
            plan.len(),
            plan.reference_block
        )));
    }
    let aligner = ReferenceAligner::new(&grey[plan.reference_block], &config.patch)?;
    let grid = aligner.grid().clone();
    let mut flow = Flow::zeros((plan.len(), grid.tiles_y, grid.tiles_x, 2));
    // Each block's robust affine fit (camera motion), for the centre-frame correction.
    let mut camera = Flow::zeros(flow.dim());
    progress.start("patch alignment", plan.len() as u64);
    // Blocks in parallel (each block's pyramid, filters and fits are serial work; the tile
    // searches inside run in parallel too): every block's result depends on that block alone.
    type BlockFlow = Option<(Array3<f32>, Option<Array3<f32>>)>;
    let results: Vec<BlockFlow> = grey
        .par_iter()
        .enumerate()
        .with_max_len(1)
        .map(|(b, block)| -> Result<BlockFlow> {
            if b == plan.reference_block {
                progress.advance(1);
                return Ok(None);
            }
            let (f, valid, alt) = aligner.align_with_pyramid(block)?;
            let f = median_filter_valid_flow(&f, &valid, config.median_radius);
            let mut f = snap_to_affine_fit(&f, &grid, config.affine_tolerance_px);
            let fit = affine_fit_field(&f, &grid, config.affine_tolerance_px);
            if let Some(fit) = &fit {
                if config.second_motion_radius_px > 0 {
                    f = aligner.follow_second_motion_in(
                        block,
                        &alt,
                        &f,
                        fit,
                        SecondMotionSearch {
                            tolerance_px: config.affine_tolerance_px,
                            radius_px: config.second_motion_radius_px,
                            min_tiles: config.second_motion_min_tiles,
                        },
                    );
                }
            }
            progress.advance(1);
            Ok(Some((f, fit)))
        })
        .collect::<Result<_>>()?;
    for (b, result) in results.into_iter().enumerate() {
        if let Some((f, fit)) = result {
            if let Some(fit) = fit {
                camera.slice_mut(s![b, .., .., ..]).assign(&fit);
            }
            flow.slice_mut(s![b, .., .., ..]).assign(&f);
        }
    }
    progress.finish();
    if config.temporal_median {
        flow = temporal_median_flow(&flow, plan.reference_block);
    }
    if config.centre_correction {
        // The correction is a temporal sharpening filter: computed on the smooth camera fits
        // so that a mismatched tile does not leak into its temporal neighbours.
        flow += &(block_centre_flow(&camera, plan) - &camera);
    }
    Ok((grid, flow))
}

/// What `flow.toml` holds beside `flow.npy`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FlowMeta {
    /// Nominal block size, frames.
    pub block_size: usize,
    /// First frame of each block.
    pub block_start_frames: Vec<usize>,
    /// Centre frame of each block.
    pub block_center_frames: Vec<f64>,
    /// Tile side, px.
    pub tile_size: usize,
    /// Tile stride, px.
    pub tile_stride: usize,
    /// Tile centre rows, px (reference frame).
    pub tile_centers_y: Vec<f32>,
    /// Tile centre columns, px.
    pub tile_centers_x: Vec<f32>,
}

/// Writes `flow.npy` (float32 `(n_blocks, tiles_y, tiles_x, 2)`) and `flow.toml` (see
/// [`FlowMeta`]) into `dir` (created if missing), each through a temporary file renamed into
/// place, so readers never see a half-written file.
pub fn write_alignment(dir: impl AsRef<Path>, alignment: &Alignment) -> Result<()> {
    let dir = dir.as_ref();
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let meta = alignment.flow_meta();
    let text = toml::to_string(&meta)
        .map_err(|e| Error::invalid(format!("cannot serialise flow metadata: {e}")))?;
    write_atomic_synced(dir.join("flow.npy"), |f| {
        alignment
            .flow
            .as_standard_layout()
            .write_npy(f)
            .map_err(|e| std::io::Error::other(e.to_string()))
    })?;
    write_atomic_synced(dir.join("flow.toml"), |f| f.write_all(text.as_bytes()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The selected median equals the middle of the sorted window (odd windows, and even ones
    /// at the grid's edges and where validity leaves an even count), with repeated values.
    #[test]
    fn median_filter_takes_the_middle_of_the_sorted_window() {
        let (ty, tx) = (7, 9);
        let flow = Array3::from_shape_fn((ty, tx, 2), |(i, j, c)| {
            ((i * 5 + j * 3 + c * 7) % 6) as f32 * 0.25 - 0.5
        });
        let valid = Array2::from_shape_fn((ty, tx), |(i, j)| (i * 3 + j) % 4 != 0);
        for radius in [1, 2] {
            let got = median_filter_valid_flow(&flow, &valid, radius);
            let mut saw_even = false;
            for ((i, j, c), &value) in got.indexed_iter() {
                let window = |only_valid: bool| {
                    let mut v = Vec::new();
                    for y in i.saturating_sub(radius)..(i + radius + 1).min(ty) {
                        for x in j.saturating_sub(radius)..(j + radius + 1).min(tx) {
                            if valid[[y, x]] || !only_valid {
                                v.push(flow[[y, x, c]]);
                            }
                        }
                    }
                    v
                };
                let mut v = window(true);
                if v.is_empty() {
                    v = window(false);
                }
                v.sort_by(f32::total_cmp);
                let n = v.len();
                saw_even |= n % 2 == 0;
                let expected = if n % 2 == 1 {
                    v[n / 2]
                } else {
                    0.5 * (v[n / 2 - 1] + v[n / 2])
                };
                assert_eq!(value.to_bits(), expected.to_bits(), "tile ({i}, {j}) {c}");
            }
            assert!(saw_even);
        }
    }
}
