//! The integer tile search of one pyramid level: seeds from the coarser level's offsets
//! (Hasinoff et al. 2016 §4.1: the nearest parent tile and its two neighbours toward the tile,
//! plus zero motion, this project's addition), then the least-cost offset of a window around
//! the best seed, and on level 0 the Lucas–Kanade refinement.
#![forbid(unsafe_code)]

use super::cost::{seed_costs, window_costs, Tile};
use super::lucas_kanade::LkScratch;
use super::{ReferenceAligner, TileGrid};
use ndarray::{Array2, Array3};

/// The offsets of the next coarser pyramid level that seed a level's tile search
/// ([`parent_candidates`]): per tile of `grid`, in that level's pixels, `factor` times coarser.
pub(super) struct ParentLevel<'a> {
    pub(super) offsets: &'a Array3<f32>,
    pub(super) grid: &'a TileGrid,
    pub(super) factor: f32,
}

/// The seed of lowest patch cost among `seeds` rounded to whole pixels, each distinct offset
/// scored once (the parent tiles often agree, and equal offsets cost the same); the first of
/// equal minima wins (as `min_by`).
fn best_seed(tile: &Tile<'_>, seeds: &[(f32, f32)]) -> (isize, isize) {
    let mut rounded = [(0isize, 0isize); 4];
    let mut distinct = 0;
    for &(dy, dx) in seeds {
        let d = (dy.round() as isize, dx.round() as isize);
        if !rounded[..distinct].contains(&d) {
            rounded[distinct] = d;
            distinct += 1;
        }
    }
    let mut seed_cost = [0.0f32; 4];
    seed_costs(tile, &rounded[..distinct], &mut seed_cost[..distinct]);
    *seed_cost[..distinct]
        .iter()
        .zip(&rounded[..distinct])
        .min_by(|a, b| a.0.total_cmp(b.0))
        .expect("at least one seed")
        .1
}

/// The offset of the least cost of a search window (`costs`, row-major, `side` offsets a row,
/// centred on `seed`, ±`radius`), ties going to the smaller displacement (L1 norm) and then to
/// the first in row-major order; NaN costs never win. When every cost is infinite (or NaN),
/// the seed unless an offset is strictly closer to zero motion.
///
/// The result of a scan that keeps the best so far, starting from (∞, seed), and replaces it
/// by a cost that is smaller, or equal and strictly closer. Where the least cost is finite that
/// scan ends at the first closest offset among those of the least cost: found here by the
/// minimum (eight independent running minima, no branch per offset), then one pass for the
/// offsets equal to it.
pub(super) fn best_offset(
    costs: &[f32],
    side: usize,
    seed: (isize, isize),
    radius: isize,
) -> (isize, isize) {
    let offset = |k: usize| {
        (
            seed.0 - radius + (k / side) as isize,
            seed.1 - radius + (k % side) as isize,
        )
    };
    let norm = |d: (isize, isize)| d.0.abs() + d.1.abs();
    let mut minima = [f32::INFINITY; 8];
    let chunks = costs.chunks_exact(8);
    let rest = chunks.remainder();
    for chunk in chunks {
        for (m, &c) in minima.iter_mut().zip(chunk) {
            *m = m.min(c);
        }
    }
    let least = minima
        .iter()
        .chain(rest)
        .fold(f32::INFINITY, |m, &c| m.min(c));
    if least < f32::INFINITY {
        let mut best: Option<(isize, (isize, isize))> = None;
        for (k, _) in costs.iter().enumerate().filter(|&(_, &c)| c == least) {
            let d = offset(k);
            let closer = match best {
                None => true,
                Some((n, _)) => norm(d) < n,
            };
            if closer {
                best = Some((norm(d), d));
            }
        }
        return best.expect("the least cost is one of the costs").1;
    }
    // No finite cost: only strictly closer offsets replace the seed.
    let mut best = seed;
    for (k, &c) in costs.iter().enumerate() {
        if c == f32::INFINITY && norm(offset(k)) < norm(best) {
            best = offset(k);
        }
    }
    best
}

/// The seeds from the coarser level for a tile centred at `(cy, cx)` (this level's px): the
/// nearest parent tile and its neighbours toward the tile in y and in x, each offset scaled by
/// the factor `f` between the levels (Hasinoff et al. 2016 §4.1), plus zero motion.
fn parent_candidates(
    coarse: &Array3<f32>,
    pgrid: &TileGrid,
    f: f32,
    cy: f32,
    cx: f32,
) -> [(f32, f32); 4] {
    // Position in parent tile-index units.
    let index = |c: f32, centers: &[f32], stride: usize| {
        let pc = (c + 0.5) / f - 0.5;
        let t = (pc - centers[0]) / stride as f32;
        let n = centers.len() as isize;
        let near = (t.round() as isize).clamp(0, n - 1);
        let other = if t > near as f32 { near + 1 } else { near - 1 };
        (near as usize, other.clamp(0, n - 1) as usize)
    };
    let (iy, oy) = index(cy, &pgrid.tile_centers_y, pgrid.tile_stride);
    let (ix, ox) = index(cx, &pgrid.tile_centers_x, pgrid.tile_stride);
    let seed = |(a, b): (usize, usize)| (coarse[[a, b, 0]] * f, coarse[[a, b, 1]] * f);
    // Zero motion as a fourth seed: a coarse level that is ambiguous (aperture problem on a
    // heavily averaged, nearly one-directional texture) cannot then drag a tile far away.
    [seed((iy, ix)), seed((oy, ix)), seed((iy, ox)), (0.0, 0.0)]
}

impl ReferenceAligner {
    /// Tile `k` of pyramid `level` aligned to the block's level image `a_img`: the best of the
    /// seeds from the `parent` level's offsets (zero on the coarsest level), the best offset in
    /// the level's search window around it, and on level 0 the Lucas–Kanade refinement
    /// ([`ReferenceAligner::refine`]). Returns `(dy, dx, refined)` in the level's pixels.
    pub(super) fn align_tile(
        &self,
        level: usize,
        k: usize,
        a_img: &Array2<f32>,
        parent: Option<&ParentLevel<'_>>,
        scratch: &mut LkScratch,
    ) -> (f32, f32, bool) {
        let grid = &self.grids[level];
        let r_img = &self.pyramid.levels[level];
        let norm = self.config.norms[level];
        let radius = self.config.search_radii[level] as isize;
        let ts = grid.tile_size;
        let (i, j) = (k / grid.tiles_x, k % grid.tiles_x);
        let origin = (i * grid.tile_stride, j * grid.tile_stride);
        let parent_seeds;
        let seeds: &[(f32, f32)] = match parent {
            None => &[(0.0, 0.0)],
            Some(p) => {
                parent_seeds = parent_candidates(
                    p.offsets,
                    p.grid,
                    p.factor,
                    grid.tile_centers_y[i],
                    grid.tile_centers_x[j],
                );
                &parent_seeds
            }
        };
        let tile = Tile {
            reference: r_img,
            alternate: a_img,
            origin,
            ts,
            norm,
            isa: self.isa,
        };
        let seed = best_seed(&tile, seeds);
        let side = (2 * radius + 1) as usize;
        scratch.window.clear();
        scratch.window.resize(side * side, 0.0);
        let costs = &mut scratch.window;
        // The whole window: the same numbers as `cost` for each offset.
        window_costs(&tile, (seed.0 - radius, seed.1 - radius), side, costs);
        let best = best_offset(costs, side, seed, radius);
        let flow = (best.0 as f32, best.1 as f32);
        if level > 0 {
            return (flow.0, flow.1, false);
        }
        match self.refine(k, a_img, origin, flow, scratch) {
            Some(f) => (f.0, f.1, true),
            None => (flow.0, flow.1, false),
        }
    }
}
