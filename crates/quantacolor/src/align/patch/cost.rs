//! Patch costs of a tile: the mean L1 or L2 distance between a reference tile and the block
//! image displaced by an offset (the distances of Hasinoff et al. 2016 §4.1), for one offset,
//! a window row, a whole window or a tile's seeds. The portable references; `x86` holds the
//! AVX2 kernels, each giving these numbers bit for bit.
#![forbid(unsafe_code)]

use super::Norm;
use crate::cpu::Isa;
use ndarray::Array2;

/// One tile of one pyramid level and what its costs compare: the reference image, the image
/// matched against it, the tile's origin and side, the patch distance and the instruction set.
#[derive(Clone, Copy)]
pub(super) struct Tile<'a> {
    /// The reference level image (row-major).
    pub(super) reference: &'a Array2<f32>,
    /// The block's level image (row-major), displaced by the offsets.
    pub(super) alternate: &'a Array2<f32>,
    /// The tile's top-left pixel `(oy, ox)`.
    pub(super) origin: (usize, usize),
    /// The tile's side, px.
    pub(super) ts: usize,
    /// The patch distance.
    pub(super) norm: Norm,
    /// Where the AVX2 kernels may run.
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    pub(super) isa: Isa,
}

/// Mean patch distance between the reference tile at origin `(oy, ox)` (clipped to the image)
/// and the alternate image displaced by `(dy, dx)`, over the tile pixels whose displaced
/// position lies inside the image; infinite when fewer than a quarter of the tile's pixels
/// overlap, so that no offset wins by comparing against padding.
pub(super) fn tile_cost(tile: &Tile<'_>, (dy, dx): (isize, isize)) -> f32 {
    let Tile {
        reference,
        alternate,
        origin: (oy, ox),
        ts,
        norm,
        ..
    } = *tile;
    let (h, w) = (reference.nrows() as isize, reference.ncols() as isize);
    let (oy, ox) = (oy as isize, ox as isize);
    let ts = ts as isize;
    // Rows/columns of the tile inside the image, then those whose displaced position is too.
    let (y0, y1) = (oy.max(-dy).max(0), (oy + ts).min(h).min(h - dy));
    let (x0, x1) = (ox.max(-dx).max(0), (ox + ts).min(w).min(w - dx));
    if y1 <= y0 || x1 <= x0 || 4 * (y1 - y0) * (x1 - x0) < ts.min(h) * ts.min(w) {
        return f32::INFINITY;
    }
    let rs = reference.as_slice().expect("standard layout");
    let as_ = alternate.as_slice().expect("standard layout");
    let rows = (y0..y1).map(|y| {
        let r0 = (y * w + x0) as usize;
        let a0 = ((y + dy) * w + x0 + dx) as usize;
        let n = (x1 - x0) as usize;
        (&rs[r0..r0 + n], &as_[a0..a0 + n])
    });
    let cost = match norm {
        Norm::L1 => rows_cost(rows, |d| d.abs()),
        Norm::L2 => rows_cost(rows, |d| d * d),
    };
    cost / ((y1 - y0) * (x1 - x0)) as f32
}

/// Σ over rows of (Σ over the row's columns, in order from zero, of `term(r − a)`), the rows
/// added in order: what one row at a time computes, with four rows summed side by side (four
/// independent chains of additions instead of one, the same numbers).
#[inline(always)]
fn rows_cost<'a>(
    rows: impl Iterator<Item = (&'a [f32], &'a [f32])>,
    term: impl Fn(f32) -> f32,
) -> f32 {
    let mut cost = 0.0f32;
    let mut batch: [(&[f32], &[f32]); 4] = [(&[], &[]); 4];
    let mut filled = 0;
    let flush = |batch: &[(&[f32], &[f32])], cost: &mut f32| {
        let n = batch[0].0.len();
        let mut sums = [0.0f32; 4];
        for i in 0..n {
            for (s, (r, a)) in sums.iter_mut().zip(batch) {
                *s += term(r[i] - a[i]);
            }
        }
        for s in &sums[..batch.len()] {
            *cost += s;
        }
    };
    for row in rows {
        batch[filled] = row;
        filled += 1;
        if filled == 4 {
            flush(&batch, &mut cost);
            filled = 0;
        }
    }
    if filled > 0 {
        flush(&batch[..filled], &mut cost);
    }
    cost
}

/// [`tile_cost`] of the offsets `(dy0 + k, dx0 + i)` for every `i < side` and `k <
/// out.len() / side` (a window of offsets, row-major), into `out`: with AVX2, up to three rows
/// of offsets side by side where they all overlap the image alike (independent sums, so that
/// they overlap in time; each cost bit-identical to [`tile_cost`]'s); otherwise a row at a
/// time by [`window_row_costs`].
pub(super) fn window_costs(
    tile: &Tile<'_>,
    (dy0, dx0): (isize, isize),
    side: usize,
    out: &mut [f32],
) {
    let rows = out.len() / side;
    debug_assert_eq!(rows * side, out.len());
    #[cfg(target_arch = "x86_64")]
    let done = super::x86::window_costs(tile, (dy0, dx0), side, out);
    #[cfg(not(target_arch = "x86_64"))]
    let done = 0;
    for (k, row) in out.chunks_mut(side).enumerate().skip(done) {
        window_row_costs(tile, (dy0 + k as isize, dx0), row);
    }
}

/// [`tile_cost`] of one offset, by [`window_costs`] (a window of one): the same bits, computed
/// by the transposed AVX2 kernel where the tile and its displaced copy lie inside the images.
pub(super) fn offset_cost(tile: &Tile<'_>, d: (isize, isize)) -> f32 {
    let mut cost = [0.0f32];
    window_costs(tile, d, 1, &mut cost);
    cost[0]
}

/// The costs of the distinct `seeds` (offsets) of the tile into `out` (one each, the numbers
/// of [`offset_cost`]): with AVX2, where the tile and every seed's displaced copy lie inside
/// the images and the tile is 8 or 16 px, by one transposed kernel over the seeds (the
/// reference tile transposed once, the seeds' row sums transposed and added together);
/// otherwise one [`offset_cost`] each.
pub(super) fn seed_costs(tile: &Tile<'_>, seeds: &[(isize, isize)], out: &mut [f32]) {
    debug_assert_eq!(seeds.len(), out.len());
    #[cfg(target_arch = "x86_64")]
    {
        if super::x86::seed_costs(tile, seeds, out) {
            return;
        }
    }
    for (c, &d) in out.iter_mut().zip(seeds) {
        *c = offset_cost(tile, d);
    }
}

/// [`tile_cost`] of the offsets `(dy, dx0 + i)` for every `i < out.len()`, into `out`: with AVX2,
/// up to 24 offsets at a time that overlap the image alike (each lane sums its rows in the
/// scalar order, so every cost is bit-identical to [`tile_cost`]'s; at the image's left and
/// right edges the runs of equally clipped offsets); elsewhere one [`tile_cost`] each.
pub(super) fn window_row_costs(tile: &Tile<'_>, (dy, dx0): (isize, isize), out: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    let done = super::x86::window_row_costs(tile, (dy, dx0), out);
    #[cfg(not(target_arch = "x86_64"))]
    let done = 0;
    for (i, c) in out.iter_mut().enumerate().skip(done) {
        *c = tile_cost(tile, (dy, dx0 + i as isize));
    }
}
