//! Frame-level motion from block-level flow (paper §4.1; Ma et al. 2020 §4.2): the block flows,
//! measured at the blocks' centre frames, are interpolated linearly in time to every binary
//! frame (extrapolated before the first and after the last centre), and bilinearly in space
//! from tile centres to any pixel.
#![deny(unsafe_code)]

use super::blocks::BlockPlan;
use super::patch::TileGrid;
use ndarray::{s, Array3, Array4, Axis};
use rayon::prelude::*;

/// Flow of frame `t`, `(tiles_y, tiles_x, 2)`, from the block flows `flow`
/// (`(n_blocks, tiles_y, tiles_x, 2)`) by linear interpolation between the two block centres
/// around `t`; outside the first/last centre the nearest two blocks' line is extrapolated. With
/// one block its flow is returned.
pub fn frame_flow(flow: &Array4<f32>, plan: &BlockPlan, t: f64) -> Array3<f32> {
    let centers = plan.center_frames();
    assert_eq!(flow.dim().0, centers.len(), "flow and block plan disagree");
    if centers.len() == 1 {
        return flow.slice(s![0, .., .., ..]).to_owned();
    }
    // Segment [k, k + 1] containing t, or the end segments for extrapolation.
    let k = centers
        .windows(2)
        .position(|w| t < w[1])
        .unwrap_or(centers.len() - 2);
    let (c0, c1) = (centers[k], centers[k + 1]);
    let a = ((t - c0) / (c1 - c0)) as f32;
    let f0 = flow.slice(s![k, .., .., ..]);
    let f1 = flow.slice(s![k + 1, .., .., ..]);
    &f0 * (1.0 - a) + &f1 * a
}

/// Flow `(dy, dx)` at pixel `(y, x)` (reference-frame coordinates) by bilinear interpolation of
/// the tile flows `tile_flow` (`(tiles_y, tiles_x, 2)`) between tile centres of `grid`; beyond
/// the outermost centres the edge tiles' values are held.
pub fn flow_at(tile_flow: &Array3<f32>, grid: &TileGrid, y: f32, x: f32) -> [f32; 2] {
    let locate = |v: f32, centers: &[f32]| -> (usize, usize, f32) {
        let n = centers.len();
        if n == 1 || v <= centers[0] {
            return (0, 0, 0.0);
        }
        if v >= centers[n - 1] {
            return (n - 1, n - 1, 0.0);
        }
        let step = centers[1] - centers[0];
        // v lies past the first centre: the quotient is positive, where truncation (`as`) is
        // the floor (and no libm call).
        let i = (((v - centers[0]) / step) as usize).min(n - 2);
        (i, i + 1, (v - centers[i]) / step)
    };
    let (y0, y1, fy) = locate(y, &grid.tile_centers_y);
    let (x0, x1, fx) = locate(x, &grid.tile_centers_x);
    let mut out = [0.0; 2];
    for (c, o) in out.iter_mut().enumerate() {
        let top = tile_flow[[y0, x0, c]] * (1.0 - fx) + tile_flow[[y0, x1, c]] * fx;
        let bottom = tile_flow[[y1, x0, c]] * (1.0 - fx) + tile_flow[[y1, x1, c]] * fx;
        *o = top * (1.0 - fy) + bottom * fy;
    }
    out
}

/// Weights `(block, weight)` giving the trajectory's value at frame `t` from the block means
/// of the (up to) three blocks nearest block `k`: the quadratic in time whose means over those
/// blocks' frames equal the block means, evaluated at `t` (a line with two blocks).
fn quadratic_weights(plan: &BlockPlan, k: usize, t: f64) -> Vec<(usize, f64)> {
    let n = plan.len();
    let order = n.min(3);
    let first = k.saturating_sub(1).min(n - order);
    let scale = plan.block_size.max(1) as f64;
    // moments[j][p] = mean over block j's frames of ((frame − t) / B)^p.
    let moments: Vec<Vec<f64>> = (first..first + order)
        .map(|j| {
            let range = plan.blocks[j].clone();
            let len = range.len().max(1) as f64;
            (0..order)
                .map(|p| {
                    range
                        .clone()
                        .map(|f| ((f as f64 - t) / scale).powi(p as i32))
                        .sum::<f64>()
                        / len
                })
                .collect()
        })
        .collect();
    match invert(moments) {
        // value(t) = coefficient 0 = row 0 of the inverse applied to the block means.
        Some(inv) => (0..order).map(|j| (first + j, inv[0][j])).collect(),
        None => vec![(k, 1.0)],
    }
}

/// Converts block flows measured between block images into flows at the blocks' centre frames
/// relative to the reference frame, the convention of `flow.toml`.
///
/// A block image is the sum of its frames (supplement §1.1), so patch alignment measures the
/// displacement between the *time averages* of the trajectory over the block and over the
/// reference block. Along a curved trajectory (hand shake, circular motion) a block's mean
/// differs from the position at its centre frame, and the reference block's mean from the
/// reference frame's position, by a few tenths of a pixel. Per tile, the quadratic in time
/// whose block means match the measured flows of a block and its two neighbours gives the flow
/// at the block's centre frame; all flows are then shifted so that the flow at the reference
/// frame (same construction around the reference block) is zero. Constant and linear motion
/// pass unchanged (but for that shift).
pub fn block_centre_flow(flow: &Array4<f32>, plan: &BlockPlan) -> Array4<f32> {
    let centers = plan.center_frames();
    let n = centers.len();
    assert_eq!(flow.dim().0, n, "flow and block plan disagree");
    let rows: Vec<Vec<(usize, f64)>> = (0..n)
        .map(|k| quadratic_weights(plan, k, centers[k]))
        .collect();
    let anchor_row = quadratic_weights(plan, plan.reference_block, plan.reference_frame as f64);
    let (_, _, tx, _) = flow.dim();
    let mut out = flow.clone();
    // Tile rows in parallel: every value depends on its own tile alone.
    out.axis_iter_mut(Axis(1))
        .into_par_iter()
        .enumerate()
        .for_each(|(i, mut out)| {
            for j in 0..tx {
                for c in 0..2 {
                    let value = |row: &[(usize, f64)]| -> f64 {
                        row.iter()
                            .map(|&(b, w)| w * flow[[b, i, j, c]] as f64)
                            .sum()
                    };
                    let anchor = value(&anchor_row);
                    for (k, row) in rows.iter().enumerate() {
                        out[[k, j, c]] = (value(row) - anchor) as f32;
                    }
                }
            }
        });
    out
}

/// Inverse of a square matrix by Gauss–Jordan elimination with partial pivoting.
pub(super) fn invert(mut m: Vec<Vec<f64>>) -> Option<Vec<Vec<f64>>> {
    let n = m.len();
    let mut inv: Vec<Vec<f64>> = (0..n)
        .map(|i| (0..n).map(|j| if i == j { 1.0 } else { 0.0 }).collect())
        .collect();
    for col in 0..n {
        let pivot = (col..n).max_by(|&a, &b| m[a][col].abs().total_cmp(&m[b][col].abs()))?;
        if m[pivot][col].abs() < 1e-12 {
            return None;
        }
        m.swap(col, pivot);
        inv.swap(col, pivot);
        let p = m[col][col];
        for v in m[col].iter_mut() {
            *v /= p;
        }
        for v in inv[col].iter_mut() {
            *v /= p;
        }
        for row in 0..n {
            if row != col && m[row][col] != 0.0 {
                let f = m[row][col];
                for k in 0..n {
                    m[row][k] -= f * m[col][k];
                    inv[row][k] -= f * inv[col][k];
                }
            }
        }
    }
    Some(inv)
}
