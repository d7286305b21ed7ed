//! The motion of every frame of a burst: an affine camera motion per sub-block plus, per
//! block, the tile flow the camera does not explain; dense flows and warps made from them.
#![forbid(unsafe_code)]

use super::affine::{interpolate, AffineMotion};
use super::local::{coherent_residual, confirmed_in_time, near_local_tiles, unexplained_residual};
use crate::align::blocks::BlockPlan;
use crate::align::motion::{flow_at, frame_flow};
use crate::align::patch::TileGrid;
use crate::align::{affine_fit_field, solve3, Alignment, Flow};
use crate::error::{Error, Result};
use crate::merge::warp::{relative_flow, warp_rows_to_reference};
use crate::merge::SubBlockMotion;
use ndarray::{Array2, Array3, Axis};
use rayon::prelude::*;
use std::ops::Range;

/// Motion of every frame of a burst: an affine camera motion per sub-block plus, per block, the
/// tile flow the camera does not explain (moving objects).
#[derive(Debug, Clone)]
pub struct FrameMotion {
    pub height: usize,
    pub width: usize,
    /// The blocks the local residual is given for.
    pub plan: BlockPlan,
    pub grid: TileGrid,
    /// Frames of each sub-block, in time order, covering the burst.
    pub sub_blocks: Vec<Range<usize>>,
    /// Block holding each sub-block.
    pub block_of: Vec<usize>,
    /// Forward camera displacement of each sub-block (reference → sub-block), about the image
    /// centre.
    pub camera: Vec<AffineMotion>,
    /// (n_blocks, tiles_y, tiles_x, 2) tile flow minus the block's camera motion; zero where
    /// the camera explains the tile.
    pub local: Flow,
    /// Whether any tile has a local residual.
    pub(super) has_local: bool,
}

/// The frame-weighted mean of sub-block cameras given with their frame counts (a block
/// image is the time average of its frames).
fn mean_camera<'a>(cameras: impl Iterator<Item = (&'a AffineMotion, usize)>) -> AffineMotion {
    let mut sum = [0.0f64; 6];
    let mut n = 0.0;
    for (camera, frames) in cameras {
        let f = frames as f64;
        sum.iter_mut()
            .zip(camera.params())
            .for_each(|(s, v)| *s += f * v);
        n += f;
    }
    AffineMotion::from_params(sum.map(|s| s / n.max(1.0)))
}

/// Least-squares affine displacement through the tile flows `field` (tiles_y, tiles_x, 2).
fn affine_from_tiles(field: &Array3<f32>, grid: &TileGrid, centre: [f64; 2]) -> AffineMotion {
    let mut params = [[0.0f64; 3]; 2];
    let mut normal = [[0.0f64; 3]; 3];
    let mut rhs = [[0.0f64; 3]; 2];
    for (i, &cy) in grid.tile_centers_y.iter().enumerate() {
        for (j, &cx) in grid.tile_centers_x.iter().enumerate() {
            let basis = [1.0, cy as f64 - centre[0], cx as f64 - centre[1]];
            for r in 0..3 {
                for c in 0..3 {
                    normal[r][c] += basis[r] * basis[c];
                }
                for (k, rhs_k) in rhs.iter_mut().enumerate() {
                    rhs_k[r] += basis[r] * field[[i, j, k]] as f64;
                }
            }
        }
    }
    for k in 0..2 {
        match solve3(normal, rhs[k]) {
            Some(p) => params[k] = p,
            None => {
                // One row or column of tiles: translation only.
                let n = (grid.tiles_y * grid.tiles_x) as f64;
                params[k] = [rhs[k][0] / n, 0.0, 0.0];
            }
        }
    }
    AffineMotion {
        b: [params[0][0], params[1][0]],
        m: [[params[0][1], params[0][2]], [params[1][1], params[1][2]]],
    }
}

impl FrameMotion {
    /// One sub-block per block of `plan`, each with its camera and no local motion (tests).
    #[cfg(test)]
    pub(in crate::align) fn of_block_cameras(
        height: usize,
        width: usize,
        plan: BlockPlan,
        camera: Vec<AffineMotion>,
    ) -> FrameMotion {
        let grid = TileGrid::new(height, width, 16, 8);
        FrameMotion {
            height,
            width,
            sub_blocks: plan.blocks.clone(),
            block_of: (0..plan.len()).collect(),
            local: Flow::zeros((plan.len(), grid.tiles_y, grid.tiles_x, 2)),
            plan,
            grid,
            camera,
            has_local: false,
        }
    }

    /// Block-level motion of `alignment`: each block's robust affine fit (tolerance as in
    /// [`super::AlignConfig::affine_tolerance_px`]) as its camera motion, the rest as local
    /// residual where it covers at least `min_local_tiles` connected tiles (see
    /// [`RefineConfig::min_local_tiles`]) and, where `local_consistency` > 0, recurs in a
    /// neighbouring block ([`RefineConfig::local_consistency`]); one sub-block per block.
    pub fn from_alignment(
        alignment: &Alignment,
        tolerance_px: f32,
        min_local_tiles: usize,
        local_consistency: f32,
    ) -> FrameMotion {
        let (h, w) = alignment.grey[alignment.plan.reference_block].dim();
        let centre = [(h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0];
        let grid = alignment.grid.clone();
        // Each block's fit and kept residual depend on that block's tiles only.
        let per_block: Vec<(AffineMotion, Array3<f32>)> = (0..alignment.plan.len())
            .into_par_iter()
            .map(|b| {
                let tiles = alignment.flow.index_axis(Axis(0), b).to_owned();
                let (camera, residual) =
                    match affine_fit_field(&tiles, &grid, tolerance_px.max(1.0)) {
                        Some(fit) => (
                            affine_from_tiles(&fit, &grid, centre),
                            unexplained_residual(&tiles, &fit),
                        ),
                        None => (AffineMotion::default(), tiles),
                    };
                (camera, coherent_residual(&residual, min_local_tiles))
            })
            .collect();
        let mut local = alignment.flow.clone();
        let mut camera = Vec::with_capacity(per_block.len());
        for (b, (block_camera, kept)) in per_block.into_iter().enumerate() {
            camera.push(block_camera);
            local.index_axis_mut(Axis(0), b).assign(&kept);
        }
        if local_consistency > 0.0 {
            local = confirmed_in_time(&local, &alignment.plan, local_consistency);
        }
        let has_local = local.iter().any(|&v| v != 0.0);
        FrameMotion {
            height: h,
            width: w,
            plan: alignment.plan.clone(),
            grid,
            sub_blocks: alignment.plan.blocks.clone(),
            block_of: (0..alignment.plan.len()).collect(),
            camera,
            local,
            has_local,
        }
    }

    /// Forgets the local residual: every pixel follows the camera.
    pub fn drop_local_motion(&mut self) {
        self.local.fill(0.0);
        self.has_local = false;
    }

    /// Forgets the local residual of the blocks `blocks`.
    pub fn drop_local_motion_in(&mut self, blocks: Range<usize>) {
        for b in blocks {
            self.local.index_axis_mut(Axis(0), b).fill(0.0);
        }
        self.has_local = self.local.iter().any(|&v| v != 0.0);
    }

    pub(in crate::align) fn centre(&self) -> [f64; 2] {
        [
            (self.height as f64 - 1.0) / 2.0,
            (self.width as f64 - 1.0) / 2.0,
        ]
    }

    pub(in crate::align) fn half_size(&self) -> [f64; 2] {
        [self.height as f64 / 2.0, self.width as f64 / 2.0]
    }

    /// Centre frame of each sub-block.
    pub fn sub_block_centres(&self) -> Vec<f64> {
        self.sub_blocks
            .iter()
            .map(|r| (r.start + r.end - 1) as f64 / 2.0)
            .collect()
    }

    /// Composes every sub-block camera with the inverse of the camera at the reference frame,
    /// so that the motion there is zero (the convention of the flows); unchanged where that
    /// camera cannot be inverted.
    pub(crate) fn anchor_at_reference(&mut self) {
        let anchor = self.camera_at(self.plan.reference_frame as f64);
        if let Some(undo) = anchor.inverse() {
            for camera in self.camera.iter_mut() {
                *camera = camera.after(&undo);
            }
        }
    }

    /// How far the camera moves inside sub-block `k` (px at the image corners, first frame to
    /// last, at [`Self::camera_at`]).
    pub fn sub_block_travel(&self, k: usize) -> f64 {
        let r = &self.sub_blocks[k];
        self.camera_at(r.start as f64)
            .distance(&self.camera_at((r.end - 1) as f64), self.half_size())
    }

    /// Camera motion at (fractional) frame `t`, linear between sub-block centres.
    pub fn camera_at(&self, t: f64) -> AffineMotion {
        interpolate(&self.sub_block_centres(), &self.camera, t)
    }

    /// Dense (H, W, 2) flow of camera motion `camera` plus the local residual at frame `t`.
    pub(super) fn dense(&self, camera: &AffineMotion, t: f64) -> Array3<f32> {
        self.dense_with(camera, self.local_at(t).as_ref())
    }

    /// The local residual's tile flow at frame `t` and its tiles near a residual
    /// ([`near_local_tiles`]), when there is a residual.
    fn local_at(&self, t: f64) -> Option<(Array3<f32>, Array2<bool>)> {
        self.has_local.then(|| {
            let local = frame_flow(&self.local, &self.plan, t);
            let near = near_local_tiles(&local);
            (local, near)
        })
    }

    /// [`Self::dense`] with the residual of [`Self::local_at`] given.
    fn dense_with(
        &self,
        camera: &AffineMotion,
        local: Option<&(Array3<f32>, Array2<bool>)>,
    ) -> Array3<f32> {
        let mut out = Array3::<f32>::zeros((self.height, self.width, 2));
        out.outer_iter_mut()
            .into_par_iter()
            .enumerate()
            .for_each(|(y, mut row)| {
                let row = row.as_slice_mut().expect("fresh array is contiguous");
                self.dense_row(camera, local, y, row);
            });
        out
    }

    /// Row `y` of [`Self::dense_with`] into `row` ((dy, dx) pairs, 2·W values).
    fn dense_row(
        &self,
        camera: &AffineMotion,
        local: Option<&(Array3<f32>, Array2<bool>)>,
        y: usize,
        row: &mut [f32],
    ) {
        let centre = self.centre();
        let stride = self.grid.tile_stride.max(1);
        // `AffineMotion::at` with its row part added once: (b + m·ry) + m'·rx.
        let ry = y as f64 - centre[0];
        let base = [
            camera.b[0] + camera.m[0][0] * ry,
            camera.b[1] + camera.m[1][0] * ry,
        ];
        let near_row = local
            .map(|(l, near)| {
                let (ty, _) = near.dim();
                (l, near.row((y / stride).min(ty - 1)))
            })
            .filter(|(_, near)| near.iter().any(|&n| n));
        if near_row.is_none() {
            // The camera alone (the loop below with a zero residual, in a form that
            // vectorises).
            for (x, out) in row.chunks_exact_mut(2).enumerate() {
                let rx = x as f64 - centre[1];
                out[0] = (base[0] + camera.m[0][1] * rx) as f32 + 0.0;
                out[1] = (base[1] + camera.m[1][1] * rx) as f32 + 0.0;
            }
            return;
        }
        for (x, out) in row.chunks_exact_mut(2).enumerate() {
            let rx = x as f64 - centre[1];
            let d = [base[0] + camera.m[0][1] * rx, base[1] + camera.m[1][1] * rx];
            let l = match &near_row {
                Some((l, near)) if near[(x / stride).min(near.len() - 1)] => {
                    flow_at(l, &self.grid, y as f32, x as f32)
                }
                _ => [0.0; 2],
            };
            out[0] = d[0] as f32 + l[0];
            out[1] = d[1] as f32 + l[1];
        }
    }

    /// Sub-block `k`'s motion as the merge takes it: its affine reference map
    /// ([`FrameMotion::sub_block_reference_map`]) without a local residual (in the capture, or
    /// at the sub-block's time), else that map with
    /// the dense flow and the pixels where the residual may act
    /// ([`SubBlockMotion::CameraAndLocal`]: most sites skip the dense flow's inversion); the
    /// dense flow alone when the camera motion cannot be inverted.
    pub fn sub_block_motion(&self, k: usize) -> SubBlockMotion {
        if let Some((matrix, offset)) = self.sub_block_reference_map(k) {
            return SubBlockMotion::Affine { matrix, offset };
        }
        let r = &self.sub_blocks[k];
        let local = self.local_at((r.start + r.end - 1) as f64 / 2.0);
        if let Some((_, near)) = &local {
            if !near.iter().any(|&n| n) {
                // No residual at this sub-block's time (other blocks have one): the camera
                // alone, whose affine map places even the sites that leave the image exactly.
                if let Some((matrix, offset)) = self.camera_reference_map(k) {
                    return SubBlockMotion::Affine { matrix, offset };
                }
            }
        }
        let flow = self.dense_with(&self.camera[k], local.as_ref());
        match (self.camera_reference_map(k), local) {
            (Some((matrix, offset)), Some((_, near))) => {
                let (ty, tx) = near.dim();
                let stride = self.grid.tile_stride.max(1);
                let columns: Vec<usize> =
                    (0..self.width).map(|x| (x / stride).min(tx - 1)).collect();
                let mut local = Array2::from_elem((self.height, self.width), false);
                for (y, mut row) in local.outer_iter_mut().enumerate() {
                    let near = near.row((y / stride).min(ty - 1));
                    for (m, &c) in row.iter_mut().zip(&columns) {
                        *m = near[c];
                    }
                }
                SubBlockMotion::CameraAndLocal {
                    matrix,
                    offset,
                    flow,
                    local,
                }
            }
            _ => SubBlockMotion::Dense(flow),
        }
    }

    /// Dense (H, W, 2) flow of sub-block `k` (reference → sub-block).
    pub fn sub_block_flow(&self, k: usize) -> Array3<f32> {
        let r = &self.sub_blocks[k];
        self.dense(&self.camera[k], (r.start + r.end - 1) as f64 / 2.0)
    }

    /// Cuts every sub-block `k` into `pieces(k, range)` equal runs of frames (at least one, at
    /// most one per frame); each piece stays in its block and takes the camera
    /// `camera(self, k, piece)`.
    pub fn split_sub_blocks(
        &mut self,
        pieces: impl Fn(usize, &Range<usize>) -> usize,
        camera: impl Fn(&FrameMotion, usize, &Range<usize>) -> AffineMotion,
    ) {
        let mut sub_blocks = Vec::new();
        let mut block_of = Vec::new();
        let mut cameras = Vec::new();
        for (k, range) in self.sub_blocks.iter().enumerate() {
            let len = range.len();
            let n = pieces(k, range).clamp(1, len.max(1));
            for i in 0..n {
                let r = range.start + i * len / n..range.start + (i + 1) * len / n;
                if !r.is_empty() {
                    cameras.push(camera(self, k, &r));
                    sub_blocks.push(r);
                    block_of.push(self.block_of[k]);
                }
            }
        }
        self.sub_blocks = sub_blocks;
        self.block_of = block_of;
        self.camera = cameras;
    }

    /// Sub-block `k`'s map from sensor site q to reference position p = matrix·q + offset
    /// ((y, x) order), when the camera explains all motion (no local residual): the merge then
    /// needs no dense flow.
    pub fn sub_block_reference_map(&self, k: usize) -> Option<([[f64; 2]; 2], [f64; 2])> {
        if self.has_local {
            return None;
        }
        self.camera_reference_map(k)
    }

    /// The map of [`FrameMotion::sub_block_reference_map`] of the camera motion alone.
    pub(super) fn camera_reference_map(&self, k: usize) -> Option<([[f64; 2]; 2], [f64; 2])> {
        let e = self.camera[k].inverse()?;
        let c = self.centre();
        let matrix = [[1.0 + e.m[0][0], e.m[0][1]], [e.m[1][0], 1.0 + e.m[1][1]]];
        let offset = [
            e.b[0] - e.m[0][0] * c[0] - e.m[0][1] * c[1],
            e.b[1] - e.m[1][0] * c[0] - e.m[1][1] * c[1],
        ];
        Some((matrix, offset))
    }

    /// The camera motion at (fractional) frame `t` ([`Self::camera_at`]) as a 2×3 matrix
    /// `M` in pixel coordinates, (y, x) order: the scene point at reference-frame position
    /// `(y, x)` (pixel centres at integers) is at `M·(y, x, 1)` in frame `t`. The camera alone:
    /// [`Self::flow_at_frame`] without a local residual is `M·(y, x, 1) − (y, x)`. The
    /// displacement `b + m·(p − c)` about the image centre `c` of [`AffineMotion`] is rewritten
    /// about the origin: `M = [I + m | b − m·c]` (this project's own export, `camera.npy`, see
    /// docs/motion.md).
    pub fn camera_matrix(&self, t: f64) -> [[f64; 3]; 2] {
        let AffineMotion { b, m } = self.camera_at(t);
        let c = self.centre();
        [
            [
                1.0 + m[0][0],
                m[0][1],
                b[0] - m[0][0] * c[0] - m[0][1] * c[1],
            ],
            [
                m[1][0],
                1.0 + m[1][1],
                b[1] - m[1][0] * c[0] - m[1][1] * c[1],
            ],
        ]
    }

    /// [`Self::camera_matrix`] of every frame `0..frames`: float64 (frames, 2, 3), the array
    /// of `camera.npy`.
    pub fn camera_matrices(&self, frames: usize) -> Array3<f64> {
        let mut out = Array3::<f64>::zeros((frames, 2, 3));
        for (t, mut matrix) in out.outer_iter_mut().enumerate() {
            let m = self.camera_matrix(t as f64);
            for (r, row) in m.iter().enumerate() {
                for (c, &v) in row.iter().enumerate() {
                    matrix[[r, c]] = v;
                }
            }
        }
        out
    }

    /// Dense (H, W, 2) flow at (fractional) frame `t`.
    pub fn flow_at_frame(&self, t: f64) -> Array3<f32> {
        self.dense(&self.camera_at(t), t)
    }

    /// Dense (H, W, 2) flow of block `b`: the frame-weighted mean camera motion of its
    /// sub-blocks (a block image is the time average of its frames) plus its local residual.
    pub fn block_flow(&self, b: usize) -> Array3<f32> {
        self.dense(&self.block_camera(b), self.plan.center_frames()[b])
    }

    /// Block `b`'s frames in runs of consecutive sub-blocks whose cameras lie within
    /// `tolerance_px` of the run's first (px at the image corners): each run's frames, its
    /// frame-weighted mean camera and its centre frame. One image per run then stands for its
    /// sub-blocks, smeared by at most about `tolerance_px` more than a sub-block.
    pub fn block_runs(
        &self,
        b: usize,
        tolerance_px: f64,
    ) -> Vec<(Range<usize>, AffineMotion, f64)> {
        let half = self.half_size();
        let members: Vec<usize> = (0..self.sub_blocks.len())
            .filter(|&k| self.block_of[k] == b)
            .collect();
        let mut runs = Vec::new();
        let mut i = 0;
        while i < members.len() {
            let first = self.camera[members[i]];
            let mut j = i + 1;
            while j < members.len()
                && self.sub_blocks[members[j]].start == self.sub_blocks[members[j - 1]].end
                && self.camera[members[j]].distance(&first, half) <= tolerance_px
            {
                j += 1;
            }
            let run = &members[i..j];
            let frames = self.sub_blocks[run[0]].start..self.sub_blocks[run[run.len() - 1]].end;
            runs.push((
                frames.clone(),
                mean_camera(
                    run.iter()
                        .map(|&k| (&self.camera[k], self.sub_blocks[k].len())),
                ),
                (frames.start + frames.end - 1) as f64 / 2.0,
            ));
            i = j;
        }
        runs
    }

    /// Dense (H, W, 2) flow from block `b`'s grid (its grey image, which [`Self::block_flow`]
    /// takes to the reference) to frames at camera `camera` and time `t`: a pixel q of the
    /// block image shows the scene point at q + flow(q) there. The camera composition K ∘ B⁻¹
    /// without a local residual; else [`relative_flow`] of the two dense flows (the residual
    /// at `t`).
    pub fn flow_from_block(&self, b: usize, camera: &AffineMotion, t: f64) -> Result<Array3<f32>> {
        if !self.has_local {
            if let Some(undo) = self.block_camera(b).inverse() {
                return Ok(self.dense_with(&camera.after(&undo), None));
            }
        }
        relative_flow(&self.block_flow(b), &self.dense(camera, t))
    }

    /// How far the cameras of block `b`'s sub-blocks lie from the block's camera (the largest,
    /// px at the image corners): how much its frames smear its grey image.
    pub fn block_spread(&self, b: usize) -> f64 {
        let block = self.block_camera(b);
        let half = self.half_size();
        (0..self.sub_blocks.len())
            .filter(|&k| self.block_of[k] == b)
            .map(|k| self.camera[k].distance(&block, half))
            .fold(0.0, f64::max)
    }

    /// The camera part of [`Self::block_flow`]: the frame-weighted mean camera motion of block
    /// `b`'s sub-blocks.
    fn block_camera(&self, b: usize) -> AffineMotion {
        mean_camera(
            (0..self.sub_blocks.len())
                .filter(|&k| self.block_of[k] == b)
                .map(|k| (&self.camera[k], self.sub_blocks[k].len())),
        )
    }

    /// `image` (block `b`'s) warped onto the reference grid by [`Self::block_flow`]: the same
    /// numbers as [`warp_to_reference`] of that flow, made a row at a time without the dense
    /// (H, W, 2) flow ([`warp_rows_to_reference`]).
    pub fn warp_block(&self, b: usize, image: &Array2<f32>) -> Result<Array2<f32>> {
        if image.dim() != (self.height, self.width) {
            return Err(Error::invalid(format!(
                "warp: block image of {:?} for a motion of {}x{}",
                image.dim(),
                self.height,
                self.width
            )));
        }
        let camera = self.block_camera(b);
        let local = self.local_at(self.plan.center_frames()[b]);
        warp_rows_to_reference(image, |y, row| {
            self.dense_row(&camera, local.as_ref(), y, row)
        })
    }
}
