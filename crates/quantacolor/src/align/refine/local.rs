//! The tile flow that a block's camera fit does not explain (moving objects), kept only where
//! it covers a connected group and recurs in time: this project's heuristics, not the paper's.
#![forbid(unsafe_code)]

use crate::align::blocks::BlockPlan;
use crate::align::Flow;
use ndarray::{Array2, Array3, Axis};

/// Smallest tile residual from a block's camera fit that counts as local motion (px; this
/// project's heuristic). Below it the tile follows the camera: a residual of hundredths of a
/// pixel is the difference between two robust fits, not a moving object, and on the chart
/// (handheld, 10,000 frames) such residuals covered whole blocks, which sent their sub-blocks
/// through the dense flow inversion of the merge instead of the camera's affine map.
const MIN_LOCAL_RESIDUAL_PX: f32 = 0.25;

/// `tiles − fit` (tiles_y, tiles_x, 2), zero on the tiles whose residual is under
/// [`MIN_LOCAL_RESIDUAL_PX`].
pub(super) fn unexplained_residual(tiles: &Array3<f32>, fit: &Array3<f32>) -> Array3<f32> {
    let mut residual = tiles - fit;
    for mut tile in residual.lanes_mut(Axis(2)) {
        if tile[0].hypot(tile[1]) < MIN_LOCAL_RESIDUAL_PX {
            tile.fill(0.0);
        }
    }
    residual
}

/// Tiles of `residual` (tiles_y, tiles_x, 2) that the camera does not explain, kept only in
/// connected groups of at least `min_tiles` tiles (4-neighbours whose residuals differ by at
/// most 1 px): a moving object moves many neighbouring tiles alike, while tiles matched a
/// texture period off, or lost in photon noise, stand alone or in small groups.
pub(super) fn coherent_residual(residual: &Array3<f32>, min_tiles: usize) -> Array3<f32> {
    let mut out = Array3::<f32>::zeros(residual.dim());
    for group in residual_groups(residual) {
        if group.len() >= min_tiles {
            for (gi, gj) in group {
                out[[gi, gj, 0]] = residual[[gi, gj, 0]];
                out[[gi, gj, 1]] = residual[[gi, gj, 1]];
            }
        }
    }
    out
}

/// The groups of nonzero tiles of `residual` (tiles_y, tiles_x, 2) that move alike: connected
/// through 4-neighbours whose residuals differ by at most 1 px, each as its (row, column) list.
fn residual_groups(residual: &Array3<f32>) -> Vec<Vec<(usize, usize)>> {
    let (ty, tx, _) = residual.dim();
    let moving = |i: usize, j: usize| residual[[i, j, 0]] != 0.0 || residual[[i, j, 1]] != 0.0;
    let close = |a: (usize, usize), b: (usize, usize)| {
        let dy = residual[[a.0, a.1, 0]] - residual[[b.0, b.1, 0]];
        let dx = residual[[a.0, a.1, 1]] - residual[[b.0, b.1, 1]];
        dy * dy + dx * dx <= 1.0
    };
    let mut groups = Vec::new();
    let mut seen = Array2::<bool>::from_elem((ty, tx), false);
    for i in 0..ty {
        for j in 0..tx {
            if seen[[i, j]] || !moving(i, j) {
                continue;
            }
            // Flood fill of the group of (i, j).
            let mut group = vec![(i, j)];
            seen[[i, j]] = true;
            let mut next = 0;
            while next < group.len() {
                let (ci, cj) = group[next];
                next += 1;
                let neighbours = [
                    (ci.wrapping_sub(1), cj),
                    (ci + 1, cj),
                    (ci, cj.wrapping_sub(1)),
                    (ci, cj + 1),
                ];
                for (ni, nj) in neighbours {
                    if ni < ty
                        && nj < tx
                        && !seen[[ni, nj]]
                        && moving(ni, nj)
                        && close((ci, cj), (ni, nj))
                    {
                        seen[[ni, nj]] = true;
                        group.push((ni, nj));
                    }
                }
            }
            groups.push(group);
        }
    }
    groups
}

/// Keeps of the local residual `local` (blocks, tiles_y, tiles_x, 2) of the blocks of `plan` only
/// the groups ([`residual_groups`]) that a temporally neighbouring block confirms (this project's
/// heuristic, [`RefineConfig::local_consistency`](super::RefineConfig::local_consistency)). A tile
/// of block b is confirmed by a neighbour n (b ± 1, not the reference block, whose residual is zero
/// by definition) when n's residual at a kept tile within one tile of it, scaled by the ratio of
/// the two blocks' centre-frame distances from the reference frame (constant velocity relative to
/// the camera), lies within `tolerance` × the change that this scaling predicts between the two
/// blocks (at least 1 px) of b's; a group stays when at least half of its tiles are confirmed, and
/// groups fall until all that are left are confirmed by each other. Tile-level work only: no image
/// is read.
///
/// The tolerance is a fraction of the predicted change, not of the residual itself: far from
/// the reference, neighbouring blocks' distances differ by a few per cent, and a residual that
/// stays put from block to block (no motion between them) would pass for one growing with the
/// distance. An object that moved and then stood still is left to the merge's robustness in
/// the blocks where it stands.
pub(super) fn confirmed_in_time(local: &Flow, plan: &BlockPlan, tolerance: f32) -> Flow {
    let (n, ty, tx, _) = local.dim();
    let centre_distance: Vec<f64> = plan
        .blocks
        .iter()
        .map(|r| (r.start + r.end - 1) as f64 / 2.0 - plan.reference_frame as f64)
        .collect();
    // Per block its groups; its temporal neighbours with the factor from their residuals to its.
    let groups: Vec<Vec<Vec<(usize, usize)>>> = (0..n)
        .map(|b| residual_groups(&local.index_axis(Axis(0), b).to_owned()))
        .collect();
    let neighbours = |b: usize| -> Vec<(usize, f32)> {
        [b.wrapping_sub(1), b + 1]
            .into_iter()
            .filter(|&m| m < n && m != plan.reference_block && b != plan.reference_block)
            .map(|m| (m, (centre_distance[b] / centre_distance[m]) as f32))
            .filter(|(_, scale)| scale.is_finite() && *scale > 0.0)
            .collect()
    };
    let mut out = local.clone();
    // Drop unconfirmed groups until every group left is confirmed by groups left: a group
    // confirmed only by one that falls does not stand on its own. Removal only shrinks what
    // confirms, so the result does not depend on the order.
    loop {
        let mut changed = false;
        for (b, block_groups) in groups.iter().enumerate() {
            let near = neighbours(b);
            // Tile (i, j) of block b is confirmed by a kept tile of a neighbour within one tile
            // (an object's outline shifts between blocks) at the residual the velocity predicts.
            let confirmed = |i: usize, j: usize| {
                let (ry, rx) = (local[[b, i, j, 0]], local[[b, i, j, 1]]);
                near.iter().any(|&(m, scale)| {
                    (i.saturating_sub(1)..(i + 2).min(ty)).any(|y| {
                        (j.saturating_sub(1)..(j + 2).min(tx)).any(|x| {
                            let (my, mx) = (out[[m, y, x, 0]], out[[m, y, x, 1]]);
                            let (py, px) = (my * scale, mx * scale);
                            let predicted_change = (py - my).hypot(px - mx);
                            (py != 0.0 || px != 0.0)
                                && (ry - py).hypot(rx - px)
                                    <= (tolerance * predicted_change).max(1.0)
                        })
                    })
                })
            };
            let falling: Vec<&Vec<(usize, usize)>> = block_groups
                .iter()
                .filter(|group| {
                    let (i0, j0) = group[0];
                    let standing = out[[b, i0, j0, 0]] != 0.0 || out[[b, i0, j0, 1]] != 0.0;
                    let kept = group.iter().filter(|&&(i, j)| confirmed(i, j)).count();
                    standing && 2 * kept < group.len()
                })
                .collect();
            for group in falling {
                for &(i, j) in group {
                    out[[b, i, j, 0]] = 0.0;
                    out[[b, i, j, 1]] = 0.0;
                }
                changed = true;
            }
        }
        if !changed {
            return out;
        }
    }
}

/// Tiles of the local flow `local` (tiles_y, tiles_x, 2) whose 3x3 neighbourhood holds a
/// local residual: elsewhere the bilinear interpolation between tile centres is zero.
pub(super) fn near_local_tiles(local: &Array3<f32>) -> Array2<bool> {
    let (ty, tx, _) = local.dim();
    Array2::from_shape_fn((ty, tx), |(i, j)| {
        (i.saturating_sub(1)..(i + 2).min(ty)).any(|a| {
            (j.saturating_sub(1)..(j + 2).min(tx))
                .any(|b| local[[a, b, 0]] != 0.0 || local[[a, b, 1]] != 0.0)
        })
    })
}
