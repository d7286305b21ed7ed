//! Frame-level motion from block-level flow (paper §4.1; Ma et al. 2020 §4.2): the block flows,
//! measured at the blocks' centre frames, are interpolated linearly in time to every binary
//! frame (extrapolated before the first and after the last centre), and bilinearly in space
//! from tile centres to any pixel.

use super::blocks::BlockPlan;
use super::patch::TileGrid;
use ndarray::{s, Array3, Array4};

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
        let i = (((v - centers[0]) / step).floor() as usize).min(n - 2);
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
