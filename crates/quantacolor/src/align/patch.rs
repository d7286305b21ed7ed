//! Hierarchical tile alignment of grey block images (paper §4.1; Ma et al. 2020 §4; the HDR+
//! coarse-to-fine scheme of Hasinoff et al. 2016 §4).
//!
//! Each block image is aligned to the reference block image tile by tile: an image pyramid by
//! box aggregation, an exhaustive L1/L2 search in a small window on every level seeded by three
//! candidates from the coarser level, and Lucas–Kanade iterations on the finest level for
//! sub-pixel accuracy. The result for a tile is the displacement `(dy, dx)` such that the
//! scene point at `p` in the reference image is at `p + (dy, dx)` in the block image.

use crate::error::{Error, Result};
use crate::filters::gaussian_blur;
use ndarray::{Array2, Array3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;
use std::ops::Range;

/// Patch distance used by the integer search on one pyramid level.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Norm {
    /// Sum of absolute differences: robust to the few outliers of fine, noisy levels.
    L1,
    /// Sum of squared differences: smoother cost on the coarse, averaged levels.
    L2,
}

/// Settings of the hierarchical patch alignment. Level 0 is the finest (the grey image itself);
/// the vectors are indexed by level and must have equal lengths.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PatchConfig {
    /// Box-aggregation factor of each level relative to the previous one (level 0: 1).
    pub downsample_factors: Vec<usize>,
    /// Tile size of each level, px of that level; tiles overlap by half (stride = size / 2).
    pub tile_sizes: Vec<usize>,
    /// Search radius of each level, px of that level: offsets in [−r, r]² around the seed.
    pub search_radii: Vec<usize>,
    /// Patch distance of each level.
    pub norms: Vec<Norm>,
    /// Lucas–Kanade iterations on level 0 (0 keeps integer offsets).
    pub lk_iterations: usize,
    /// Gaussian σ (px) smoothing the grey images before the pyramid is built; reduces the
    /// photon noise of low-light blocks in the gradients Lucas–Kanade uses (0 disables).
    pub presmooth_sigma: f32,
}

impl Default for PatchConfig {
    fn default() -> Self {
        // HDR+ / QBP 2020 style: factors [1, 2, 4, 4] (total 32), 16 px tiles on the finest level
        // and 8 px on the coarse ones, radii growing toward the coarse levels (±297 px in all).
        PatchConfig {
            downsample_factors: vec![1, 2, 4, 4],
            tile_sizes: vec![16, 8, 8, 8],
            search_radii: vec![1, 4, 4, 8],
            norms: vec![Norm::L1, Norm::L2, Norm::L2, Norm::L2],
            lk_iterations: 5,
            presmooth_sigma: 1.0,
        }
    }
}

impl PatchConfig {
    /// Checks that the per-level vectors agree and hold usable values.
    pub fn validate(&self) -> Result<()> {
        let n = self.downsample_factors.len();
        if n == 0 {
            return Err(Error::invalid(
                "patch alignment needs at least one pyramid level",
            ));
        }
        if self.tile_sizes.len() != n || self.search_radii.len() != n || self.norms.len() != n {
            return Err(Error::invalid(format!(
                "pyramid settings disagree in length: {} factors, {} tile sizes, {} radii, {} norms",
                n,
                self.tile_sizes.len(),
                self.search_radii.len(),
                self.norms.len()
            )));
        }
        if self.downsample_factors.contains(&0) {
            return Err(Error::invalid("downsample factors must be at least 1"));
        }
        if self.tile_sizes.iter().any(|&t| t < 2) {
            return Err(Error::invalid("tile sizes must be at least 2 px"));
        }
        if self.presmooth_sigma.is_nan() || self.presmooth_sigma < 0.0 {
            return Err(Error::invalid("presmooth sigma must be >= 0"));
        }
        Ok(())
    }
}

/// A regular grid of square tiles overlapping by `tile_size - tile_stride`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileGrid {
    /// Tile side, px.
    pub tile_size: usize,
    /// Distance between tile origins, px.
    pub tile_stride: usize,
    /// Number of tile rows.
    pub tiles_y: usize,
    /// Number of tile columns.
    pub tiles_x: usize,
    /// Centre row of each tile row, px (`i · stride + (size − 1) / 2`).
    pub tile_centers_y: Vec<f32>,
    /// Centre column of each tile column, px.
    pub tile_centers_x: Vec<f32>,
}

impl TileGrid {
    /// Tiles covering an `height` x `width` image: `ceil((H − size) / stride) + 1` rows (at least
    /// one), the last tiles reaching past the image where the size does not divide evenly.
    pub fn new(height: usize, width: usize, tile_size: usize, tile_stride: usize) -> TileGrid {
        let count = |n: usize| {
            if n <= tile_size {
                1
            } else {
                (n - tile_size).div_ceil(tile_stride) + 1
            }
        };
        let (ty, tx) = (count(height), count(width));
        let centre = |i: usize| (i * tile_stride) as f32 + (tile_size as f32 - 1.0) / 2.0;
        TileGrid {
            tile_size,
            tile_stride,
            tiles_y: ty,
            tiles_x: tx,
            tile_centers_y: (0..ty).map(centre).collect(),
            tile_centers_x: (0..tx).map(centre).collect(),
        }
    }
}

/// Image pyramid: level 0 the (smoothed) grey image, each next level a box aggregate (mean).
#[derive(Debug, Clone)]
pub struct Pyramid {
    /// Levels, finest first.
    pub levels: Vec<Array2<f32>>,
}

impl Pyramid {
    /// Builds the pyramid of `grey` per `config` (factors and pre-smoothing).
    pub fn new(grey: &Array2<f32>, config: &PatchConfig) -> Pyramid {
        let base = if config.presmooth_sigma > 0.0 {
            gaussian_blur(grey, config.presmooth_sigma)
        } else {
            grey.clone()
        };
        let mut levels: Vec<Array2<f32>> = Vec::with_capacity(config.downsample_factors.len());
        let mut base = Some(base);
        for &f in &config.downsample_factors {
            // Each level from the one before (the base for the first); a factor of 1 is a copy,
            // so the first level takes the base itself when it is not downsampled.
            let next = match (levels.last(), base.take()) {
                (None, Some(b)) if f == 1 => b,
                (None, Some(b)) => crate::filters::box_downsample(&b, f),
                (Some(prev), _) => crate::filters::box_downsample(prev, f),
                (None, None) => unreachable!("the base is taken by the first level"),
            };
            levels.push(next);
        }
        Pyramid { levels }
    }
}

/// The offsets of the next coarser pyramid level that seed a level's tile search
/// ([`parent_candidates`]): per tile of `grid`, in that level's pixels, `factor` times coarser.
struct ParentLevel<'a> {
    offsets: &'a Array3<f32>,
    grid: &'a TileGrid,
    factor: f32,
}

/// The seed of lowest patch cost among `seeds` rounded to whole pixels, each distinct offset
/// scored once (the parent tiles often agree, and equal offsets cost the same); the first of
/// equal minima wins (as `min_by`).
fn best_seed(
    reference: &Array2<f32>,
    alternate: &Array2<f32>,
    origin: (usize, usize),
    ts: usize,
    seeds: &[(f32, f32)],
    norm: Norm,
) -> (isize, isize) {
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
    seed_costs(
        reference,
        alternate,
        origin,
        ts,
        &rounded[..distinct],
        norm,
        &mut seed_cost[..distinct],
    );
    *seed_cost[..distinct]
        .iter()
        .zip(&rounded[..distinct])
        .min_by(|a, b| a.0.total_cmp(b.0))
        .expect("at least one seed")
        .1
}

/// Mean patch distance between the reference tile at origin `(oy, ox)` (clipped to the image)
/// and the alternate image displaced by `(dy, dx)`, over the tile pixels whose displaced
/// position lies inside the image; infinite when fewer than a quarter of the tile's pixels
/// overlap, so that no offset wins by comparing against padding.
fn tile_cost(
    reference: &Array2<f32>,
    alternate: &Array2<f32>,
    (oy, ox): (usize, usize),
    ts: usize,
    (dy, dx): (isize, isize),
    norm: Norm,
) -> f32 {
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
#[allow(clippy::too_many_arguments)]
fn window_costs(
    reference: &Array2<f32>,
    alternate: &Array2<f32>,
    origin: (usize, usize),
    ts: usize,
    (dy0, dx0): (isize, isize),
    norm: Norm,
    side: usize,
    out: &mut [f32],
) {
    let rows = out.len() / side;
    debug_assert_eq!(rows * side, out.len());
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2")
            && interior_window_costs(
                reference,
                alternate,
                origin,
                ts,
                (dy0, dx0),
                norm,
                side,
                out,
            )
        {
            return;
        }
    }
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        if (2..=24).contains(&side) && std::arch::is_x86_feature_detected!("avx2") {
            while done < rows {
                let batch = (rows - done).min(3);
                let part = &mut out[done * side..(done + batch) * side];
                let kernel: CostKernel = match (side.div_ceil(8), batch) {
                    (1, 1) => tile_costs_avx2::<1, 1>,
                    (1, 2) => tile_costs_avx2::<1, 2>,
                    (1, _) => tile_costs_avx2::<1, 3>,
                    (2, 1) => tile_costs_avx2::<2, 1>,
                    (2, 2) => tile_costs_avx2::<2, 2>,
                    (2, _) => tile_costs_avx2::<2, 3>,
                    (_, 1) => tile_costs_avx2::<3, 1>,
                    (_, 2) => tile_costs_avx2::<3, 2>,
                    (_, _) => tile_costs_avx2::<3, 3>,
                };
                let dy = dy0 + done as isize;
                // SAFETY: AVX2 checked just above.
                let ok = unsafe { kernel(reference, alternate, origin, ts, (dy, dx0), norm, part) };
                if !ok {
                    break;
                }
                done += batch;
            }
        }
    }
    for (k, row) in out.chunks_mut(side).enumerate().skip(done) {
        window_row_costs(
            reference,
            alternate,
            origin,
            ts,
            (dy0 + k as isize, dx0),
            norm,
            row,
        );
    }
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
fn best_offset(costs: &[f32], side: usize, seed: (isize, isize), radius: isize) -> (isize, isize) {
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

/// [`tile_cost`] of one offset, by [`window_costs`] (a window of one): the same bits, computed
/// by the transposed AVX2 kernel where the tile and its displaced copy lie inside the images.
fn offset_cost(
    reference: &Array2<f32>,
    alternate: &Array2<f32>,
    origin: (usize, usize),
    ts: usize,
    d: (isize, isize),
    norm: Norm,
) -> f32 {
    let mut cost = [0.0f32];
    window_costs(reference, alternate, origin, ts, d, norm, 1, &mut cost);
    cost[0]
}

/// Most alternate columns that [`interior_costs_avx2`] holds transposed (the window's side − 1
/// plus the tile size, in whole vectors of eight).
#[cfg(target_arch = "x86_64")]
const STRIP_COLUMNS: usize = 64;

/// [`window_costs`] with AVX2 where no offset of the window clips the tile (the tile and every
/// displaced copy lie wholly inside the images, so every cost is the full tile's sum over its
/// area) and the tile is 8 or 16 px: [`interior_costs_avx2`] into `out`, `true`; otherwise
/// `false` and nothing written.
#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
fn interior_window_costs(
    reference: &Array2<f32>,
    alternate: &Array2<f32>,
    (oy, ox): (usize, usize),
    ts: usize,
    (dy0, dx0): (isize, isize),
    norm: Norm,
    side: usize,
    out: &mut [f32],
) -> bool {
    let rows = out.len() / side;
    let (h, w) = reference.dim();
    if !matches!(ts, 8 | 16) || rows == 0 || alternate.dim() != (h, w) {
        return false;
    }
    let (ay, ax) = (oy as isize + dy0, ox as isize + dx0);
    let columns = side + ts - 1;
    let strip = columns.div_ceil(8) * 8;
    let inside = oy + ts <= h
        && ox + ts <= w
        && ay >= 0
        && ax >= 0
        && ay as usize + rows + ts - 1 <= h
        && ax as usize + columns <= w
        && strip <= STRIP_COLUMNS
        && rows <= STRIP_COLUMNS
        // The strip's whole-vector loads of its last row end inside the data.
        && (ay as usize + rows + ts - 2) * w + ax as usize + strip <= h * w;
    let (Some(rs), Some(as_)) = (reference.as_slice(), alternate.as_slice()) else {
        return false;
    };
    if !inside {
        return false;
    }
    let (ay, ax) = (ay as usize, ax as usize);
    let mut origins = [(0, 0); STRIP_COLUMNS];
    for (k, o) in origins[..rows].iter_mut().enumerate() {
        *o = (ay + k, ax);
    }
    // SAFETY: the caller checked AVX2; the loads stay inside both slices (checked above; a
    // window fits the strip, so it has fewer rows than `STRIP_COLUMNS`).
    unsafe { interior_costs(rs, as_, w, (oy, ox), ts, &origins[..rows], norm, side, out) };
    true
}

/// [`interior_costs_avx2`] in the copy whose strip holds `side` offsets of a tile of `ts` px
/// (the smallest array that fits it, a fixed size per kernel: no allocation, and no more of it
/// cleared than a window of this side needs).
///
/// # Safety
/// As [`interior_costs_avx2`]; `ts` is 8 or 16 and the strip at most [`STRIP_COLUMNS`].
#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
unsafe fn interior_costs(
    rs: &[f32],
    as_: &[f32],
    w: usize,
    origin: (usize, usize),
    ts: usize,
    origins: &[(usize, usize)],
    norm: Norm,
    side: usize,
    out: &mut [f32],
) {
    let strip = (side + ts - 1).div_ceil(8) * 8;
    let kernel = match (ts, strip) {
        (8, ..=16) => interior_costs_avx2::<1, 16>,
        (8, ..=32) => interior_costs_avx2::<1, 32>,
        (8, _) => interior_costs_avx2::<1, STRIP_COLUMNS>,
        (_, ..=16) => interior_costs_avx2::<2, 16>,
        (_, ..=32) => interior_costs_avx2::<2, 32>,
        (_, _) => interior_costs_avx2::<2, STRIP_COLUMNS>,
    };
    kernel(rs, as_, w, origin, origins, norm, side, out)
}

/// The costs of the distinct `seeds` (offsets) of the tile at `origin` into `out` (one each,
/// the numbers of [`offset_cost`]): with AVX2, where the tile and every seed's displaced copy
/// lie inside the images and the tile is 8 or 16 px, by one [`interior_costs_avx2`] over the
/// seeds (the reference tile transposed once, the seeds' row sums transposed and added
/// together); otherwise one [`offset_cost`] each.
fn seed_costs(
    reference: &Array2<f32>,
    alternate: &Array2<f32>,
    (oy, ox): (usize, usize),
    ts: usize,
    seeds: &[(isize, isize)],
    norm: Norm,
    out: &mut [f32],
) {
    debug_assert_eq!(seeds.len(), out.len());
    #[cfg(target_arch = "x86_64")]
    {
        let (h, w) = reference.dim();
        let mut origins = [(0, 0); 8];
        let fits = |&(dy, dx): &(isize, isize)| {
            let (ay, ax) = (oy as isize + dy, ox as isize + dx);
            // The tile's whole-vector loads of its last row end inside the data.
            (ay >= 0 && ax >= 0 && ay as usize + ts <= h && ax as usize + ts <= w)
                .then_some((ay as usize, ax as usize))
        };
        if std::arch::is_x86_feature_detected!("avx2")
            && matches!(ts, 8 | 16)
            && seeds.len() <= origins.len()
            && oy + ts <= h
            && ox + ts <= w
            && alternate.dim() == (h, w)
        {
            if let (Some(rs), Some(as_)) = (reference.as_slice(), alternate.as_slice()) {
                let mut all = true;
                for (o, d) in origins.iter_mut().zip(seeds) {
                    match fits(d) {
                        Some(a) => *o = a,
                        None => all = false,
                    }
                }
                if all {
                    // SAFETY: AVX2 checked; every seed's copy lies inside the images (a strip
                    // of one offset is the tile's width, a whole number of vectors).
                    unsafe {
                        interior_costs(
                            rs,
                            as_,
                            w,
                            (oy, ox),
                            ts,
                            &origins[..seeds.len()],
                            norm,
                            1,
                            out,
                        )
                    };
                    return;
                }
            }
        }
    }
    for (c, &d) in out.iter_mut().zip(seeds) {
        *c = offset_cost(reference, alternate, (oy, ox), ts, d, norm);
    }
}

/// Eight rows of `img` (row length `w`) from `(y, x)`, eight columns each, transposed: vector
/// c holds column x + c, lane l row y + l.
///
/// # Safety
/// The CPU must support AVX2; the eight rows' eight columns must lie inside `img`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn load_transposed(
    img: &[f32],
    w: usize,
    y: usize,
    x: usize,
) -> [std::arch::x86_64::__m256; 8] {
    use std::arch::x86_64::*;
    debug_assert!((y + 7) * w + x + 8 <= img.len());
    let rows: [__m256i; 8] = std::array::from_fn(|l| {
        _mm256_castps_si256(_mm256_loadu_ps(img.as_ptr().add((y + l) * w + x)))
    });
    crate::cpu::transpose8x8(&rows).map(|v| _mm256_castsi256_ps(v))
}

/// The costs of [`interior_window_costs`] for tiles of `8·G` px (the strip at most `S`
/// columns), for rows of `side` offsets: row k's strip of the alternate starts at
/// `origins[k]` (a window's rows one below the other, or seeds anywhere, one a row), `out`
/// row-major. Lane l of a vector works on
/// tile row l (of a group of eight rows) instead of on an offset, so no lane idles whatever
/// the window's side (at level 1 a window row of nine offsets filled 9 of 16 lanes of
/// [`tile_costs_avx2`]). The reference tile is transposed once (vector c: column c of eight
/// rows) and each row of offsets' strip of the alternate likewise, so offset `(k, i)` of the
/// window is, per row, the sum over columns c in order from zero of the term of
/// `ref[c] − alt[i + c]`: the row sums of [`tile_cost`]. Eight offsets' row sums are then
/// transposed (lane: offset) and added row by row in order from zero, then divided by the
/// area: [`tile_cost`]'s operations in its order, so the same bits.
///
/// # Safety
/// The CPU must support AVX2; [`interior_window_costs`] checks the bounds.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(clippy::too_many_arguments)]
unsafe fn interior_costs_avx2<const G: usize, const S: usize>(
    rs: &[f32],
    as_: &[f32],
    w: usize,
    (oy, ox): (usize, usize),
    origins: &[(usize, usize)],
    norm: Norm,
    side: usize,
    out: &mut [f32],
) {
    use std::arch::x86_64::*;
    let ts = 8 * G;
    debug_assert_eq!(origins.len() * side, out.len());
    let strip_vectors = (side + ts - 1).div_ceil(8);
    let abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
    let area = _mm256_set1_ps((ts * ts) as f32);
    // rt[g][c]: column c of reference rows 8g..8g + 8 of the tile.
    let mut rt = [[_mm256_setzero_ps(); 16]; G];
    for (g, rt) in rt.iter_mut().enumerate() {
        for b in 0..G {
            let v = load_transposed(rs, w, oy + 8 * g, ox + 8 * b);
            rt[8 * b..8 * b + 8].copy_from_slice(&v);
        }
    }
    // at[g][c]: column ax + c of alternate rows 8g..8g + 8 of the current row of offsets.
    let mut at = [[_mm256_setzero_ps(); S]; G];
    // Row sums of up to eight offsets (vector g of offset n: tile rows 8g..8g + 8).
    let mut pending = [[_mm256_setzero_ps(); 8]; G];
    let mut filled = 0;
    let mut written = 0;
    // Offsets `written..written + filled`: rows added in order from zero, over the area.
    let flush = |pending: &[[__m256; 8]; G], filled: usize, out: &mut [f32]| {
        let mut cost = _mm256_setzero_ps();
        for group in pending {
            let sums: [__m256i; 8] = std::array::from_fn(|n| _mm256_castps_si256(group[n]));
            for row in crate::cpu::transpose8x8(&sums) {
                cost = _mm256_add_ps(cost, _mm256_castsi256_ps(row));
            }
        }
        let mut lanes = [0.0f32; 8];
        _mm256_storeu_ps(lanes.as_mut_ptr(), _mm256_div_ps(cost, area));
        out.copy_from_slice(&lanes[..filled]);
    };
    for &(ay, ax) in origins {
        for (g, at) in at.iter_mut().enumerate() {
            for b in 0..strip_vectors {
                let v = load_transposed(as_, w, ay + 8 * g, ax + 8 * b);
                at[8 * b..8 * b + 8].copy_from_slice(&v);
            }
        }
        for i in 0..side {
            for ((rt, at), pending) in rt.iter().zip(&at).zip(&mut pending) {
                let mut sum = _mm256_setzero_ps();
                for (&r, &a) in rt[..ts].iter().zip(&at[i..i + ts]) {
                    let diff = _mm256_sub_ps(r, a);
                    let term = match norm {
                        Norm::L1 => _mm256_and_ps(diff, abs_mask),
                        Norm::L2 => _mm256_mul_ps(diff, diff),
                    };
                    sum = _mm256_add_ps(sum, term);
                }
                pending[filled] = sum;
            }
            filled += 1;
            if filled == 8 {
                flush(&pending, filled, &mut out[written..written + filled]);
                written += filled;
                filled = 0;
            }
        }
    }
    if filled > 0 {
        flush(&pending, filled, &mut out[written..written + filled]);
    }
}

/// An AVX2 kernel of [`tile_costs_avx2`] (some number of vectors and rows).
#[cfg(target_arch = "x86_64")]
type CostKernel = unsafe fn(
    &Array2<f32>,
    &Array2<f32>,
    (usize, usize),
    usize,
    (isize, isize),
    Norm,
    &mut [f32],
) -> bool;

/// [`tile_cost`] of the offsets `(dy, dx0 + i)` for every `i < out.len()`, into `out`: with AVX2,
/// up to 24 offsets at a time that overlap the image alike (each lane sums its rows in the
/// scalar order, so every cost is bit-identical to [`tile_cost`]'s; at the image's left and
/// right edges the runs of equally clipped offsets); elsewhere one [`tile_cost`] each.
fn window_row_costs(
    reference: &Array2<f32>,
    alternate: &Array2<f32>,
    origin: (usize, usize),
    ts: usize,
    (dy, dx0): (isize, isize),
    norm: Norm,
    out: &mut [f32],
) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            let (ox, w) = (origin.1 as isize, reference.ncols() as isize);
            let ts_i = ts as isize;
            let clip_x = |dx: isize| (ox.max(-dx).max(0), (ox + ts_i).min(w).min(w - dx));
            while done + 1 < out.len() {
                let dx = dx0 + done as isize;
                // The offsets that clip the tile as the first does (a prefix: the bounds are
                // monotone in dx); one offset alone takes `tile_cost`.
                let lanes = (1..(out.len() - done).min(24))
                    .find(|&l| clip_x(dx + l as isize) != clip_x(dx))
                    .unwrap_or((out.len() - done).min(24));
                if lanes == 1 {
                    out[done] = tile_cost(reference, alternate, origin, ts, (dy, dx), norm);
                    done += 1;
                    continue;
                }
                let part = &mut out[done..done + lanes];
                // Vectors of 8 offsets: as many as the lanes need (up to 3).
                let kernel: CostKernel = match lanes.div_ceil(8) {
                    1 => tile_costs_avx2::<1, 1>,
                    2 => tile_costs_avx2::<2, 1>,
                    _ => tile_costs_avx2::<3, 1>,
                };
                // SAFETY: AVX2 checked just above.
                let ok = unsafe { kernel(reference, alternate, origin, ts, (dy, dx), norm, part) };
                if !ok {
                    break;
                }
                done += lanes;
            }
        }
    }
    for (i, c) in out.iter_mut().enumerate().skip(done) {
        *c = tile_cost(
            reference,
            alternate,
            origin,
            ts,
            (dy, dx0 + i as isize),
            norm,
        );
    }
}

/// [`tile_cost`] of the offsets `(dy + k, dx + i)`, `k < R`, `i < out.len() / R` (at most
/// `8·V`), into `out` (row-major), lane-parallel in `R·V` vectors of eight (independent sums,
/// so the vectors overlap in time); `false` (nothing written) when the offsets do not all clip
/// the tile alike or the wide loads would leave the image (the caller then takes them another
/// way).
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn tile_costs_avx2<const V: usize, const R: usize>(
    reference: &Array2<f32>,
    alternate: &Array2<f32>,
    (oy, ox): (usize, usize),
    ts: usize,
    (dy, dx): (isize, isize),
    norm: Norm,
    out: &mut [f32],
) -> bool {
    use std::arch::x86_64::*;
    let lanes = out.len() / R;
    debug_assert!(lanes > 8 * (V - 1) && lanes <= 8 * V && lanes * R == out.len());
    let (h, w) = (reference.nrows() as isize, reference.ncols() as isize);
    let (oy, ox) = (oy as isize, ox as isize);
    let ts = ts as isize;
    let clip_x = |dx: isize| (ox.max(-dx).max(0), (ox + ts).min(w).min(w - dx));
    let clip_y = |dy: isize| (oy.max(-dy).max(0), (oy + ts).min(h).min(h - dy));
    let (x0, x1) = clip_x(dx);
    let (y0, y1) = clip_y(dy);
    // Both ends clip alike, so every offset between does (the bounds are monotone in dx, dy).
    if clip_x(dx + lanes as isize - 1) != (x0, x1) || clip_y(dy + R as isize - 1) != (y0, y1) {
        return false;
    }
    if y1 <= y0 || x1 <= x0 || 4 * (y1 - y0) * (x1 - x0) < ts.min(h) * ts.min(w) {
        out.fill(f32::INFINITY);
        return true;
    }
    let rs = reference.as_slice().expect("standard layout");
    let as_ = alternate.as_slice().expect("standard layout");
    // Loads of `lanes` alternate values from column x + dx of rows y + dy + k (the last vector
    // masked to the lanes in use): the last must stay inside.
    let last = (y1 - 1 + dy + R as isize - 1) * w + (x1 - 1) + dx + lanes as isize - 1;
    if (y0 + dy) * w + x0 + dx < 0 || last >= as_.len() as isize {
        return false;
    }
    let n = (x1 - x0) as usize;
    let abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
    let tail = lanes - 8 * (V - 1);
    let tail_mask = _mm256_cmpgt_epi32(
        _mm256_set1_epi32(tail as i32),
        _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
    );
    let load = |p: *const f32, v: usize| {
        if v + 1 < V || tail == 8 {
            _mm256_loadu_ps(p)
        } else {
            // Lanes past `lanes` are not read (they may lie past the image's last pixel).
            _mm256_maskload_ps(p, tail_mask)
        }
    };
    let mut cost = [[_mm256_setzero_ps(); V]; R];
    for y in y0..y1 {
        let r = &rs[(y * w + x0) as usize..][..n];
        let a = as_.as_ptr().offset((y + dy) * w + x0 + dx);
        // Each lane sums its row in column order from zero, as `tile_cost`.
        let mut sum = [[_mm256_setzero_ps(); V]; R];
        for (i, &rv) in r.iter().enumerate() {
            let rv = _mm256_set1_ps(rv);
            for (k, row) in sum.iter_mut().enumerate() {
                let a = a.offset(k as isize * w + i as isize);
                for (v, s) in row.iter_mut().enumerate() {
                    let diff = _mm256_sub_ps(rv, load(a.add(8 * v), v));
                    let term = match norm {
                        Norm::L1 => _mm256_and_ps(diff, abs_mask),
                        Norm::L2 => _mm256_mul_ps(diff, diff),
                    };
                    *s = _mm256_add_ps(*s, term);
                }
            }
        }
        for (c, s) in cost.iter_mut().zip(sum) {
            for (c, s) in c.iter_mut().zip(s) {
                *c = _mm256_add_ps(*c, s);
            }
        }
    }
    let area = _mm256_set1_ps(((y1 - y0) * (x1 - x0)) as f32);
    for (o, c) in out.chunks_exact_mut(lanes).zip(cost) {
        let mut all = [[0.0f32; 8]; V];
        for (l, c) in all.iter_mut().zip(c) {
            _mm256_storeu_ps(l.as_mut_ptr(), _mm256_div_ps(c, area));
        }
        o.copy_from_slice(&all.as_flattened()[..lanes]);
    }
    true
}

/// Reference-side data of a Lucas–Kanade tile: gradients and the inverse of the 2x2 normal
/// matrix (inverse-compositional style: computed once, reused for every block).
#[derive(Debug, Clone)]
struct LkTile {
    /// ∂/∂y of the reference over the tile, row-major.
    grad_y: Vec<f32>,
    /// ∂/∂x, likewise.
    grad_x: Vec<f32>,
    inv: Option<[f32; 3]>, // (a, b, c) of the symmetric inverse [[a, b], [b, c]]
}

/// The reference block's pyramid, tile grids and Lucas–Kanade data, shared by all blocks.
#[derive(Debug, Clone)]
pub struct ReferenceAligner {
    config: PatchConfig,
    pyramid: Pyramid,
    grids: Vec<TileGrid>,
    lk: Vec<LkTile>,
}

impl ReferenceAligner {
    /// Prepares alignment against the reference grey image `reference` (`(H, W)`).
    pub fn new(reference: &Array2<f32>, config: &PatchConfig) -> Result<Self> {
        config.validate()?;
        if reference.is_empty() {
            return Err(Error::invalid("reference image is empty"));
        }
        let reference = reference.as_standard_layout().to_owned();
        let mut pyramid = Pyramid::new(&reference, config);
        // Levels smaller than their tile carry no usable patch: coarse-to-fine starts below them.
        let usable = (1..pyramid.levels.len())
            .find(|&l| {
                let (h, w) = pyramid.levels[l].dim();
                h < config.tile_sizes[l] || w < config.tile_sizes[l]
            })
            .unwrap_or(pyramid.levels.len());
        pyramid.levels.truncate(usable);
        let grids: Vec<TileGrid> = pyramid
            .levels
            .iter()
            .zip(&config.tile_sizes)
            .map(|(img, &ts)| TileGrid::new(img.nrows(), img.ncols(), ts, (ts / 2).max(1)))
            .collect();
        let fine = &pyramid.levels[0];
        let g0 = &grids[0];
        let lk = (0..g0.tiles_y * g0.tiles_x)
            .into_par_iter()
            .map(|k| {
                let (oy, ox) = (
                    (k / g0.tiles_x) * g0.tile_stride,
                    (k % g0.tiles_x) * g0.tile_stride,
                );
                lk_tile(fine, oy, ox, g0.tile_size)
            })
            .collect();
        Ok(ReferenceAligner {
            config: config.clone(),
            pyramid,
            grids,
            lk,
        })
    }

    /// Tile grid of the finest level (the grid of the output flow).
    pub fn grid(&self) -> &TileGrid {
        &self.grids[0]
    }

    /// Image size `(H, W)` of the finest level.
    pub fn dim(&self) -> (usize, usize) {
        self.pyramid.levels[0].dim()
    }

    /// Flow `(tiles_y, tiles_x, 2)` of `(dy, dx)` from the reference to the grey image `block`.
    pub fn align(&self, block: &Array2<f32>) -> Result<Array3<f32>> {
        Ok(self.align_with_validity(block)?.0)
    }

    /// [`ReferenceAligner::align`] and, per tile, whether Lucas–Kanade refined it to sub-pixel
    /// precision (`false`: flat or one-directional tile, or the iterations left the ±1 px
    /// window, and the flow is the integer search result).
    pub fn align_with_validity(&self, block: &Array2<f32>) -> Result<(Array3<f32>, Array2<bool>)> {
        let (flow, valid, _) = self.align_with_pyramid(block)?;
        Ok((flow, valid))
    }

    /// [`ReferenceAligner::align_with_validity`] and the block's pyramid it searched (for
    /// [`ReferenceAligner::follow_second_motion_in`], which then need not build it again).
    pub fn align_with_pyramid(
        &self,
        block: &Array2<f32>,
    ) -> Result<(Array3<f32>, Array2<bool>, Pyramid)> {
        if block.dim() != self.dim() {
            return Err(Error::invalid(format!(
                "block image is {:?}, the reference is {:?}",
                block.dim(),
                self.dim()
            )));
        }
        // A copy only where the block is not already row-major (the pyramid's filters read
        // rows as slices); grey block images always are.
        let owned;
        let block = if block.is_standard_layout() {
            block
        } else {
            owned = block.as_standard_layout().to_owned();
            &owned
        };
        let mut alt = Pyramid::new(block, &self.config);
        let n_levels = self.grids.len();
        alt.levels.truncate(n_levels);
        // Offsets of the coarser level, in that level's pixels.
        let mut coarse: Option<Array3<f32>> = None;
        let g0 = &self.grids[0];
        let mut valid = Array2::from_elem((g0.tiles_y, g0.tiles_x), false);
        for level in (0..n_levels).rev() {
            let grid = &self.grids[level];
            let parent = coarse.as_ref().map(|c| ParentLevel {
                offsets: c,
                grid: &self.grids[level + 1],
                factor: self.config.downsample_factors[level + 1] as f32,
            });
            let offsets: Vec<(f32, f32, bool)> = (0..grid.tiles_y * grid.tiles_x)
                .into_par_iter()
                .map_init(LkScratch::default, |scratch, k| {
                    self.align_tile(level, k, &alt.levels[level], parent.as_ref(), scratch)
                })
                .collect();
            let mut arr = Array3::<f32>::zeros((grid.tiles_y, grid.tiles_x, 2));
            for (k, (dy, dx, ok)) in offsets.into_iter().enumerate() {
                arr[[k / grid.tiles_x, k % grid.tiles_x, 0]] = dy;
                arr[[k / grid.tiles_x, k % grid.tiles_x, 1]] = dx;
                if level == 0 {
                    valid[[k / grid.tiles_x, k % grid.tiles_x]] = ok;
                }
            }
            coarse = Some(arr);
        }
        Ok((coarse.expect("at least one level"), valid, alt))
    }

    /// Tile `k` of pyramid `level` aligned to the block's level image `a_img`: the best of the
    /// seeds from the `parent` level's offsets (zero on the coarsest level), the best offset in
    /// the level's search window around it, and on level 0 the Lucas–Kanade refinement
    /// ([`ReferenceAligner::refine`]). Returns `(dy, dx, refined)` in the level's pixels.
    fn align_tile(
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
        let seed = best_seed(r_img, a_img, origin, ts, seeds, norm);
        let side = (2 * radius + 1) as usize;
        scratch.window.clear();
        scratch.window.resize(side * side, 0.0);
        let costs = &mut scratch.window;
        // The whole window: the same numbers as `cost` for each offset.
        window_costs(
            r_img,
            a_img,
            origin,
            ts,
            (seed.0 - radius, seed.1 - radius),
            norm,
            side,
            costs,
        );
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

    /// Lucas–Kanade refinement of tile `k` from the integer offset `start`: minimises
    /// Σ (alt(p + u) − ref(p))² by Gauss–Newton steps with the reference gradients; `None`
    /// when the tile lacks texture in some direction or the steps leave ±1 px.
    fn refine(
        &self,
        k: usize,
        alt: &Array2<f32>,
        (oy, ox): (usize, usize),
        start: (f32, f32),
        scratch: &mut LkScratch,
    ) -> Option<(f32, f32)> {
        let tile = &self.lk[k];
        let [a, b, c] = tile.inv?;
        let reference = &self.pyramid.levels[0];
        let (h, w) = reference.dim();
        let ts = self.grids[0].tile_size;
        let mut u = start;
        let (ys, xs) = (oy..(oy + ts).min(h), ox..(ox + ts).min(w));
        for _ in 0..self.config.lk_iterations {
            // The taps of `bilinear` at (y + u.0, x + u.1) depend on the row or the column
            // alone: computed once per row and column (the same values), eight at a time.
            scratch.rows.clear();
            crate::filters::bilinear_taps_into(
                ys.start,
                ys.len(),
                u.0,
                alt.nrows(),
                &mut scratch.rows,
            );
            scratch.cols.clear();
            crate::filters::bilinear_taps_into(
                xs.start,
                xs.len(),
                u.1,
                alt.ncols(),
                &mut scratch.cols,
            );
            let (by, bx) = lk_gradient_dot_error(
                alt,
                reference,
                (&tile.grad_y, &tile.grad_x),
                scratch,
                (ys.clone(), xs.clone()),
            );
            let step = (-(a * by + b * bx), -(b * by + c * bx));
            u = (u.0 + step.0, u.1 + step.1);
            if (u.0 - start.0).abs() > 1.0 || (u.1 - start.1).abs() > 1.0 {
                return None;
            }
            if step.0.abs() < 1e-3 && step.1.abs() < 1e-3 {
                break;
            }
        }
        Some(u)
    }
}

/// Per-thread buffers of [`ReferenceAligner::refine`]: the bilinear taps of the tile's rows and
/// columns, their column weights and the errors of one row (reused from tile to tile instead
/// of allocated per Lucas–Kanade iteration).
#[derive(Debug, Default)]
struct LkScratch {
    rows: Vec<(usize, usize, f32)>,
    cols: Vec<(usize, usize, f32)>,
    fxs: Vec<f32>,
    errors: Vec<f32>,
    /// The costs of a tile's search window, row-major (used by the integer search of
    /// [`ReferenceAligner::align_with_pyramid`], which shares the per-thread scratch).
    window: Vec<f32>,
}

/// Σ g·e over a tile for Lucas–Kanade: `e` the bilinear sample of `alt` at the taps
/// `scratch.rows` x `scratch.cols` minus the reference over rows `ys` and columns `xs`, `g` =
/// (∂/∂y, ∂/∂x) of the reference (`grad`, row-major over the tile).
///
/// Column i of the tile adds into lane i mod 8 and the lanes are summed at the end in a fixed
/// order: eight independent sums instead of one chain of dependent additions, which vectorises,
/// and the same numbers for any tile whatever path computes them (with AVX2 the same loop
/// compiled eight lanes wide: the same operations per lane, no fused multiply-add). Where the
/// column taps are contiguous (the tile does not touch the image's right or left edge) the
/// samples are read as slices.
fn lk_gradient_dot_error(
    alt: &Array2<f32>,
    reference: &Array2<f32>,
    grad: (&[f32], &[f32]),
    scratch: &mut LkScratch,
    tile: (Range<usize>, Range<usize>),
) -> (f32, f32) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            return unsafe { lk_gradient_dot_error_avx2(alt, reference, grad, scratch, tile) };
        }
    }
    lk_gradient_dot_error_generic(alt, reference, grad, scratch, tile)
}

/// [`lk_gradient_dot_error_generic`] with AVX2: where the column taps are contiguous and the
/// tile's width a multiple of eight (every interior tile), eight columns at a time with each
/// lane doing the generic path's operations in its order (multiplies and adds, no fused
/// multiply-add), so the same numbers bit for bit; otherwise the generic path compiled for
/// AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn lk_gradient_dot_error_avx2(
    alt: &Array2<f32>,
    reference: &Array2<f32>,
    (grad_y, grad_x): (&[f32], &[f32]),
    scratch: &mut LkScratch,
    (ys, xs): (Range<usize>, Range<usize>),
) -> (f32, f32) {
    use std::arch::x86_64::*;
    let width = xs.len();
    let cols = &scratch.cols;
    let first = cols.first().map_or(0, |c| c.0);
    let contiguous = cols.len() == width
        && cols
            .iter()
            .enumerate()
            .all(|(i, &(x0, x1, _))| x0 == first + i && x1 == x0 + 1);
    if !contiguous || width == 0 || width % 8 != 0 || width > 32 {
        return lk_gradient_dot_error_generic(alt, reference, (grad_y, grad_x), scratch, (ys, xs));
    }
    let vectors = width / 8;
    let one = _mm256_set1_ps(1.0);
    // Column weights fx and 1 − fx, eight columns a vector.
    let mut fx = [_mm256_setzero_ps(); 4];
    let mut one_fx = [_mm256_setzero_ps(); 4];
    for v in 0..vectors {
        let mut lanes = [0.0f32; 8];
        for (l, c) in lanes.iter_mut().zip(&cols[8 * v..8 * v + 8]) {
            *l = c.2;
        }
        fx[v] = _mm256_loadu_ps(lanes.as_ptr());
        one_fx[v] = _mm256_sub_ps(one, fx[v]);
    }
    let (mut sum_y, mut sum_x) = (_mm256_setzero_ps(), _mm256_setzero_ps());
    let alt_s = alt.as_slice().expect("standard layout");
    let ref_s = reference.as_slice().expect("standard layout");
    let (w_alt, w_ref) = (alt.ncols(), reference.ncols());
    // The alternate row whose column interpolation `carried` holds (the previous tile row's
    // bottom tap): where it is this row's top tap (rows one apart, as in the interior) it is
    // not made again; the same operations on the same values, so the same bits.
    let mut carried_row = None;
    let mut carried = [_mm256_setzero_ps(); 4];
    for (j, (y, &(y0, y1, fy))) in ys.zip(&scratch.rows).enumerate() {
        // Bounds: the taps' rows hold columns first..first + width + 1.
        let top = &alt_s[y0 * w_alt + first..][..width + 1];
        let bottom = &alt_s[y1 * w_alt + first..][..width + 1];
        let r = &ref_s[y * w_ref + xs.start..][..width];
        let gy = &grad_y[j * width..][..width];
        let gx = &grad_x[j * width..][..width];
        let (fy_v, one_fy) = (_mm256_set1_ps(fy), _mm256_set1_ps(1.0 - fy));
        let reuse = carried_row == Some(y0);
        for v in 0..vectors {
            let i = 8 * v;
            let t = if reuse {
                carried[v]
            } else {
                _mm256_add_ps(
                    _mm256_mul_ps(_mm256_loadu_ps(top.as_ptr().add(i)), one_fx[v]),
                    _mm256_mul_ps(_mm256_loadu_ps(top.as_ptr().add(i + 1)), fx[v]),
                )
            };
            let b = _mm256_add_ps(
                _mm256_mul_ps(_mm256_loadu_ps(bottom.as_ptr().add(i)), one_fx[v]),
                _mm256_mul_ps(_mm256_loadu_ps(bottom.as_ptr().add(i + 1)), fx[v]),
            );
            carried[v] = b;
            let e = _mm256_sub_ps(
                _mm256_add_ps(_mm256_mul_ps(t, one_fy), _mm256_mul_ps(b, fy_v)),
                _mm256_loadu_ps(r.as_ptr().add(i)),
            );
            sum_y = _mm256_add_ps(sum_y, _mm256_mul_ps(_mm256_loadu_ps(gy.as_ptr().add(i)), e));
            sum_x = _mm256_add_ps(sum_x, _mm256_mul_ps(_mm256_loadu_ps(gx.as_ptr().add(i)), e));
        }
        carried_row = Some(y1);
    }
    let (mut ly, mut lx) = ([0.0f32; 8], [0.0f32; 8]);
    _mm256_storeu_ps(ly.as_mut_ptr(), sum_y);
    _mm256_storeu_ps(lx.as_mut_ptr(), sum_x);
    (ly.iter().sum::<f32>(), lx.iter().sum::<f32>())
}

#[inline(always)]
fn lk_gradient_dot_error_generic(
    alt: &Array2<f32>,
    reference: &Array2<f32>,
    (grad_y, grad_x): (&[f32], &[f32]),
    scratch: &mut LkScratch,
    (ys, xs): (Range<usize>, Range<usize>),
) -> (f32, f32) {
    const LANES: usize = 8;
    let (mut sum_y, mut sum_x) = ([0.0f32; LANES], [0.0f32; LANES]);
    let LkScratch {
        rows,
        cols,
        fxs,
        errors,
        ..
    } = scratch;
    let width = xs.len();
    let first = cols.first().map_or(0, |c| c.0);
    let contiguous = cols
        .iter()
        .enumerate()
        .all(|(i, &(x0, x1, _))| x0 == first + i && x1 == x0 + 1);
    fxs.clear();
    fxs.extend(cols.iter().map(|c| c.2));
    errors.clear();
    errors.resize(width, 0.0);
    let (fxs, errors) = (&fxs[..width], &mut errors[..width]);
    let full = width - width % LANES;
    for (((y, &(y0, y1, fy)), gy), gx) in ys
        .zip(rows.iter())
        .zip(grad_y.chunks_exact(width))
        .zip(grad_x.chunks_exact(width))
    {
        let (top_row, bottom_row) = (alt.row(y0), alt.row(y1));
        let (top_row, bottom_row) = (
            top_row.as_slice().expect("standard layout"),
            bottom_row.as_slice().expect("standard layout"),
        );
        let reference_row = reference.row(y);
        let reference_row = &reference_row.as_slice().expect("standard layout")[xs.clone()];
        let error = |top: f32, bottom: f32, r: f32| (top * (1.0 - fy) + bottom * fy) - r;
        if contiguous {
            let (top, bottom) = (
                &top_row[first..first + width + 1],
                &bottom_row[first..first + width + 1],
            );
            for i in 0..width {
                let fx = fxs[i];
                errors[i] = error(
                    top[i] * (1.0 - fx) + top[i + 1] * fx,
                    bottom[i] * (1.0 - fx) + bottom[i + 1] * fx,
                    reference_row[i],
                );
            }
        } else {
            for (i, &(x0, x1, fx)) in cols.iter().enumerate() {
                errors[i] = error(
                    top_row[x0] * (1.0 - fx) + top_row[x1] * fx,
                    bottom_row[x0] * (1.0 - fx) + bottom_row[x1] * fx,
                    reference_row[i],
                );
            }
        }
        for ((e, gy), gx) in errors[..full]
            .chunks_exact(LANES)
            .zip(gy[..full].chunks_exact(LANES))
            .zip(gx[..full].chunks_exact(LANES))
        {
            for l in 0..LANES {
                sum_y[l] += gy[l] * e[l];
                sum_x[l] += gx[l] * e[l];
            }
        }
        for (l, ((e, gy), gx)) in errors[full..]
            .iter()
            .zip(&gy[full..])
            .zip(&gx[full..])
            .enumerate()
        {
            sum_y[l] += gy * e;
            sum_x[l] += gx * e;
        }
    }
    let total = |lanes: [f32; LANES]| lanes.iter().sum::<f32>();
    (total(sum_y), total(sum_x))
}

/// Gradients (central differences, one-sided at borders) and inverse normal matrix of the
/// reference tile at `(oy, ox)`; no inverse when the smaller eigenvalue is under 1e-3 of the
/// larger (an edge or flat tile, where sub-pixel motion is not determined in 2-D).
fn lk_tile(img: &Array2<f32>, oy: usize, ox: usize, ts: usize) -> LkTile {
    let (h, w) = img.dim();
    let (mut grad_y, mut grad_x) = (Vec::with_capacity(ts * ts), Vec::with_capacity(ts * ts));
    let (mut syy, mut syx, mut sxx) = (0.0f64, 0.0f64, 0.0f64);
    for y in oy..(oy + ts).min(h) {
        for x in ox..(ox + ts).min(w) {
            let (ym, yp) = (y.saturating_sub(1), (y + 1).min(h - 1));
            let (xm, xp) = (x.saturating_sub(1), (x + 1).min(w - 1));
            let gy = if yp > ym {
                (img[[yp, x]] - img[[ym, x]]) / (yp - ym) as f32
            } else {
                0.0
            };
            let gx = if xp > xm {
                (img[[y, xp]] - img[[y, xm]]) / (xp - xm) as f32
            } else {
                0.0
            };
            grad_y.push(gy);
            grad_x.push(gx);
            syy += (gy * gy) as f64;
            syx += (gy * gx) as f64;
            sxx += (gx * gx) as f64;
        }
    }
    let det = syy * sxx - syx * syx;
    let tr = syy + sxx;
    let disc = ((syy - sxx).powi(2) + 4.0 * syx * syx).sqrt();
    let (l_max, l_min) = ((tr + disc) / 2.0, (tr - disc) / 2.0);
    let inv = (l_max > 0.0 && l_min > 1e-3 * l_max && det > 0.0)
        .then(|| [(sxx / det) as f32, (-syx / det) as f32, (syy / det) as f32]);
    LkTile {
        grad_y,
        grad_x,
        inv,
    }
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
    /// Second motion model for tiles the camera model rejects (paper §4.1: patch-wise alignment
    /// must follow independently moving objects; the robust affine camera fit leaves them out).
    ///
    /// `flow` is a block's tile flow after the camera fit, `camera` the fit itself. Tiles whose
    /// flow lies more than `tolerance` px from the fit are rejected; each 8-connected set of at
    /// least `min_tiles` rejected tiles gets one common translation: every integer offset within
    /// ±`radius` px of the set's median flow is scored by the summed L1 patch cost over the set
    /// and its neighbouring tiles (whose edge against the rest of the scene resolves periodic
    /// texture that a single tile cannot), on pyramid level 1 and then within ±f px on level 0,
    /// and refined to sub-pixel as the median of the tiles' Lucas–Kanade results. Every tile
    /// within two tiles of the set then takes that translation where its own patch cost there
    /// is lower than at the camera flow, and the camera flow otherwise; the whole set keeps the
    /// camera flow when the translation's offset from the camera is a period of the reference's
    /// own texture ([`is_texture_period`]): a grating matched a whole number of periods off, which
    /// long blocks (whose camera fit can sit half a pixel off the best integer match) otherwise
    /// sent a period away (10,000-frame chart, seed 2: groups of 115–231 tiles at 8, 16 and 24 px
    /// that the merge kept as local motion, −0.83 dB).
    pub fn follow_second_motion(
        &self,
        block: &Array2<f32>,
        flow: &Array3<f32>,
        camera: &Array3<f32>,
        tolerance: f32,
        radius: usize,
        min_tiles: usize,
    ) -> Array3<f32> {
        self.second_motion(block, None, flow, camera, tolerance, radius, min_tiles)
    }

    /// [`ReferenceAligner::follow_second_motion`] with the block's pyramid `alt` from
    /// [`ReferenceAligner::align_with_pyramid`]: its levels 0 and 1 are the smoothed block and
    /// its level-1 downsampling that the second motion scores, so they are not made again
    /// (where the finest level is not downsampled; otherwise they are made from `block`).
    /// The same numbers as [`ReferenceAligner::follow_second_motion`].
    #[allow(clippy::too_many_arguments)]
    pub fn follow_second_motion_in(
        &self,
        block: &Array2<f32>,
        alt: &Pyramid,
        flow: &Array3<f32>,
        camera: &Array3<f32>,
        tolerance: f32,
        radius: usize,
        min_tiles: usize,
    ) -> Array3<f32> {
        self.second_motion(block, Some(alt), flow, camera, tolerance, radius, min_tiles)
    }

    #[allow(clippy::too_many_arguments)]
    fn second_motion(
        &self,
        block: &Array2<f32>,
        alt: Option<&Pyramid>,
        flow: &Array3<f32>,
        camera: &Array3<f32>,
        tolerance: f32,
        radius: usize,
        min_tiles: usize,
    ) -> Array3<f32> {
        let grid = &self.grids[0];
        if block.dim() != self.dim()
            || flow.dim() != (grid.tiles_y, grid.tiles_x, 2)
            || camera.dim() != flow.dim()
        {
            return flow.clone();
        }
        let components = rejected_components(flow, camera, tolerance, min_tiles);
        if components.is_empty() {
            return flow.clone();
        }
        let levels = self.second_motion_levels(block, alt);
        let scorer = levels.scorer(self, camera);
        let mut out = flow.clone();
        for component in &components {
            let support = scorer.dilate(component, 1).tiles();
            let f = scorer.factor;
            let median = (
                tile_median(flow, component, 0),
                tile_median(flow, component, 1),
            );
            let coarse = scorer.common_offset(
                &support,
                ScoredLevel::Coarse,
                (
                    (median.0 / f as f32).round() as isize,
                    (median.1 / f as f32).round() as isize,
                ),
                (radius / f) as isize,
            );
            let best = scorer.common_offset(
                &support,
                ScoredLevel::Fine,
                (coarse.0 * f as isize, coarse.1 * f as isize),
                f as isize,
            );
            let translation = self.sub_pixel_translation(component, scorer.alt0, best);
            let region = scorer.dilate(component, 2);
            let mut label = scorer.label_tiles(component, &region, best);
            fill_ambiguous_labels(&mut label, &region);
            let followers: Vec<(usize, usize)> = label
                .indexed_iter()
                .filter(|&((i, j), l)| region.0[[i, j]] && *l == Some(true))
                .map(|(p, _)| p)
                .collect();
            let offset_from_camera = |(i, j): (usize, usize)| {
                (
                    (translation.0 - camera[[i, j, 0]]).round() as isize,
                    (translation.1 - camera[[i, j, 1]]).round() as isize,
                )
            };
            if is_texture_period(scorer.ref0, grid, &followers, offset_from_camera) {
                label.fill(Some(false));
            }
            for ((i, j), &near) in region.0.indexed_iter() {
                if !near {
                    continue;
                }
                let source = if label[[i, j]] == Some(true) {
                    [translation.0, translation.1]
                } else {
                    [camera[[i, j, 0]], camera[[i, j, 1]]]
                };
                out[[i, j, 0]] = source[0];
                out[[i, j, 1]] = source[1];
            }
        }
        out
    }

    /// The smoothed block and its downsampling to pyramid level 1 (level 0 alone when the
    /// pyramid has one level) that the second motion scores: the block pyramid's levels 0 and 1
    /// where `alt` is given and level 0 is not downsampled (`box_downsample` by 1 is a copy),
    /// made from `block` otherwise.
    fn second_motion_levels<'a>(
        &self,
        block: &Array2<f32>,
        alt: Option<&'a Pyramid>,
    ) -> SecondMotionLevels<'a> {
        let factor = if self.grids.len() > 1 {
            self.config.downsample_factors[1]
        } else {
            1
        };
        let (alt0, alt1) = match alt {
            Some(p)
                if self.config.downsample_factors[0] == 1
                    && p.levels.len() >= self.grids.len()
                    && p.levels[0].dim() == block.dim() =>
            {
                let alt1 = &p.levels[if factor > 1 { 1 } else { 0 }];
                (Cow::Borrowed(&p.levels[0]), Cow::Borrowed(alt1))
            }
            _ => {
                let alt0 = if self.config.presmooth_sigma > 0.0 {
                    gaussian_blur(
                        &block.as_standard_layout().to_owned(),
                        self.config.presmooth_sigma,
                    )
                } else {
                    block.as_standard_layout().to_owned()
                };
                let alt1 = crate::filters::box_downsample(&alt0, factor);
                (Cow::Owned(alt0), Cow::Owned(alt1))
            }
        };
        SecondMotionLevels { alt0, alt1, factor }
    }

    /// The second motion's translation to sub-pixel precision: the median of the Lucas–Kanade
    /// results of the `component`'s tiles started at the integer offset `start` (`start` when
    /// none converges).
    fn sub_pixel_translation(
        &self,
        component: &[(usize, usize)],
        alt0: &Array2<f32>,
        start: (isize, isize),
    ) -> (f32, f32) {
        let grid = &self.grids[0];
        let start = (start.0 as f32, start.1 as f32);
        let mut scratch = LkScratch::default();
        let refined: Vec<(f32, f32)> = component
            .iter()
            .filter_map(|&(i, j)| {
                let origin = (i * grid.tile_stride, j * grid.tile_stride);
                self.refine(i * grid.tiles_x + j, alt0, origin, start, &mut scratch)
            })
            .collect();
        if refined.is_empty() {
            return start;
        }
        let mut ys: Vec<f32> = refined.iter().map(|r| r.0).collect();
        let mut xs: Vec<f32> = refined.iter().map(|r| r.1).collect();
        ys.sort_by(f32::total_cmp);
        xs.sort_by(f32::total_cmp);
        (ys[ys.len() / 2], xs[xs.len() / 2])
    }
}

/// The 8-connected sets of at least `min_tiles` (at least one) tiles whose `flow` lies more
/// than `tolerance` px from the `camera` fit.
fn rejected_components(
    flow: &Array3<f32>,
    camera: &Array3<f32>,
    tolerance: f32,
    min_tiles: usize,
) -> Vec<Vec<(usize, usize)>> {
    let (ty, tx, _) = flow.dim();
    let rejected = Array2::from_shape_fn((ty, tx), |(i, j)| {
        let dy = flow[[i, j, 0]] - camera[[i, j, 0]];
        let dx = flow[[i, j, 1]] - camera[[i, j, 1]];
        (dy * dy + dx * dx).sqrt() > tolerance
    });
    connected_components(&rejected)
        .into_iter()
        .filter(|c| c.len() >= min_tiles.max(1))
        .collect()
}

/// The median (upper, of an even count) of flow component `c` over `tiles`.
fn tile_median(flow: &Array3<f32>, tiles: &[(usize, usize)], c: usize) -> f32 {
    let mut v: Vec<f32> = tiles.iter().map(|&(i, j)| flow[[i, j, c]]).collect();
    v.sort_by(f32::total_cmp);
    v[v.len() / 2]
}

/// The block's two levels that [`ReferenceAligner::second_motion`] scores, and the
/// downsampling `factor` from the first to the second.
struct SecondMotionLevels<'a> {
    alt0: Cow<'a, Array2<f32>>,
    alt1: Cow<'a, Array2<f32>>,
    factor: usize,
}

impl SecondMotionLevels<'_> {
    fn scorer<'s>(&'s self, aligner: &'s ReferenceAligner, camera: &'s Array3<f32>) -> Scorer<'s> {
        let ref0 = &aligner.pyramid.levels[0];
        Scorer {
            grid: &aligner.grids[0],
            ref0,
            ref1: if self.factor > 1 {
                &aligner.pyramid.levels[1]
            } else {
                ref0
            },
            alt0: &self.alt0,
            alt1: &self.alt1,
            factor: self.factor,
            camera,
        }
    }
}

/// Which of the two levels of [`SecondMotionLevels`] a cost is taken on.
#[derive(Clone, Copy)]
enum ScoredLevel {
    /// Level 0 (the block's resolution).
    Fine,
    /// Level 1 (downsampled by the factor).
    Coarse,
}

/// A set of tiles of the finest grid as a mask.
struct TileMask(Array2<bool>);

impl TileMask {
    fn tiles(&self) -> Vec<(usize, usize)> {
        self.0
            .indexed_iter()
            .filter(|(_, &m)| m)
            .map(|(p, _)| p)
            .collect()
    }
}

/// L1 patch costs of the second motion's tiles between the reference's and the block's levels
/// ([`offset_cost`], [`window_costs`]), and the camera flow they are compared against.
struct Scorer<'a> {
    grid: &'a TileGrid,
    ref0: &'a Array2<f32>,
    ref1: &'a Array2<f32>,
    alt0: &'a Array2<f32>,
    alt1: &'a Array2<f32>,
    factor: usize,
    camera: &'a Array3<f32>,
}

impl Scorer<'_> {
    /// The level's images, the tile's origin and the tile size there.
    fn tile_at(
        &self,
        level: ScoredLevel,
        i: usize,
        j: usize,
    ) -> (&Array2<f32>, &Array2<f32>, (usize, usize), usize) {
        let (oy, ox) = (i * self.grid.tile_stride, j * self.grid.tile_stride);
        let (ts, f) = (self.grid.tile_size, self.factor);
        match level {
            ScoredLevel::Fine => (self.ref0, self.alt0, (oy, ox), ts),
            ScoredLevel::Coarse => (self.ref1, self.alt1, (oy / f, ox / f), (ts / f).max(2)),
        }
    }

    fn cost(&self, level: ScoredLevel, i: usize, j: usize, d: (isize, isize)) -> f32 {
        let (reference, alternate, origin, ts) = self.tile_at(level, i, j);
        offset_cost(reference, alternate, origin, ts, d, Norm::L1)
    }

    /// The costs of the `side × side` offsets from `corner` (row-major) at once.
    fn window(
        &self,
        level: ScoredLevel,
        (i, j): (usize, usize),
        corner: (isize, isize),
        side: usize,
        out: &mut [f32],
    ) {
        let (reference, alternate, origin, ts) = self.tile_at(level, i, j);
        window_costs(
            reference,
            alternate,
            origin,
            ts,
            corner,
            Norm::L1,
            side,
            out,
        )
    }

    /// The cost at the camera flow (rounded to the level's pixels).
    fn camera_cost(&self, level: ScoredLevel, i: usize, j: usize) -> f32 {
        let scale = match level {
            ScoredLevel::Fine => 1.0,
            ScoredLevel::Coarse => self.factor as f32,
        };
        let d = (
            (self.camera[[i, j, 0]] / scale).round() as isize,
            (self.camera[[i, j, 1]] / scale).round() as isize,
        );
        self.cost(level, i, j, d)
    }

    /// The tiles within `dist` tiles (Chebyshev) of `tiles`.
    fn dilate(&self, tiles: &[(usize, usize)], dist: usize) -> TileMask {
        let (ty, tx) = (self.grid.tiles_y, self.grid.tiles_x);
        let mut mask = Array2::from_elem((ty, tx), false);
        for &(i, j) in tiles {
            for y in i.saturating_sub(dist)..(i + dist + 1).min(ty) {
                for x in j.saturating_sub(dist)..(j + dist + 1).min(tx) {
                    mask[[y, x]] = true;
                }
            }
        }
        TileMask(mask)
    }

    /// The offset within ±`r` of `centre` (px of `level`) that minimises the total cost when
    /// every tile takes the better of the camera flow and the offset: tiles of the camera's
    /// motion score the same for every offset, so the minimum is the motion of the others
    /// (ties: the offset nearest zero, then the first in row-major order).
    fn common_offset(
        &self,
        tiles: &[(usize, usize)],
        level: ScoredLevel,
        centre: (isize, isize),
        r: isize,
    ) -> (isize, isize) {
        let cam: Vec<f32> = tiles
            .iter()
            .map(|&(i, j)| self.camera_cost(level, i, j))
            .collect();
        let side = (2 * r + 1) as usize;
        // Per tile, its cost at every offset, in the order of `offsets`.
        let table: Vec<Vec<f32>> = tiles
            .par_iter()
            .map(|&tile| {
                let mut costs = vec![0.0f32; side * side];
                self.window(level, tile, (centre.0 - r, centre.1 - r), side, &mut costs);
                costs
            })
            .collect();
        let offsets: Vec<(isize, isize)> = (-r..=r)
            .flat_map(|dy| (-r..=r).map(move |dx| (centre.0 + dy, centre.1 + dx)))
            .collect();
        offsets
            .par_iter()
            .enumerate()
            .map(|(o, &d)| {
                let total: f32 = table
                    .iter()
                    .zip(&cam)
                    .map(|(costs, &c)| (costs[o] / SWITCH_MARGIN).min(c))
                    .filter(|c| c.is_finite())
                    .sum();
                (total, d)
            })
            .min_by(|a, b| {
                a.0.total_cmp(&b.0)
                    .then((a.1 .0.abs() + a.1 .1.abs()).cmp(&(b.1 .0.abs() + b.1 .1.abs())))
            })
            .map(|(_, d)| d)
            .expect("at least one offset")
    }

    /// Each tile of `region`: `Some(true)` where its 3x3 window of tiles costs markedly less
    /// at the offset `best` than at the camera flow ([`SWITCH_MARGIN`]), `Some(false)` where
    /// markedly more, `None` where ambiguous (one tile's costs are too noisy at low light; a
    /// periodic texture whose period is the motion between the two is ambiguous too).
    fn label_tiles(
        &self,
        component: &[(usize, usize)],
        region: &TileMask,
        best: (isize, isize),
    ) -> Array2<Option<bool>> {
        let (ty, tx) = (self.grid.tiles_y, self.grid.tiles_x);
        // Per tile: its costs at the offset and at the camera.
        let mut costs = Array2::<(f32, f32)>::from_elem((ty, tx), (0.0, 0.0));
        for ((i, j), &near) in self.dilate(component, 3).0.indexed_iter() {
            if near {
                let (c_obj, c_cam) = (
                    self.cost(ScoredLevel::Fine, i, j, best),
                    self.camera_cost(ScoredLevel::Fine, i, j),
                );
                if c_obj.is_finite() && c_cam.is_finite() {
                    costs[[i, j]] = (c_obj, c_cam);
                }
            }
        }
        let mut label = Array2::<Option<bool>>::from_elem((ty, tx), None);
        for ((i, j), &near) in region.0.indexed_iter() {
            if !near {
                continue;
            }
            let (mut o, mut c) = (0.0, 0.0);
            for y in i.saturating_sub(1)..(i + 2).min(ty) {
                for x in j.saturating_sub(1)..(j + 2).min(tx) {
                    o += costs[[y, x]].0;
                    c += costs[[y, x]].1;
                }
            }
            label[[i, j]] = if o < SWITCH_MARGIN * c {
                Some(true)
            } else if c < SWITCH_MARGIN * o {
                Some(false)
            } else {
                None
            };
        }
        label
    }
}

/// Ambiguous tiles of `region` take the majority label of their decided 8-neighbours in it
/// (ties: the camera), repeatedly (at most 16 rounds), so that labels grow inward from the
/// decided tiles.
fn fill_ambiguous_labels(label: &mut Array2<Option<bool>>, region: &TileMask) {
    let (ty, tx) = label.dim();
    let region = &region.0;
    for _ in 0..16 {
        let mut changed = false;
        let snapshot = label.clone();
        for ((i, j), &near) in region.indexed_iter() {
            if !near || snapshot[[i, j]].is_some() {
                continue;
            }
            let (mut yes, mut no) = (0, 0);
            for y in i.saturating_sub(1)..(i + 2).min(ty) {
                for x in j.saturating_sub(1)..(j + 2).min(tx) {
                    match snapshot[[y, x]] {
                        Some(true) if region[[y, x]] => yes += 1,
                        Some(false) if region[[y, x]] => no += 1,
                        _ => {}
                    }
                }
            }
            if yes + no > 0 {
                label[[i, j]] = Some(yes > no);
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }
}

/// A tile leaves the camera's motion for a second one only where its patch cost there is below
/// this fraction of its cost at the camera flow: periodic static texture, equally good at a
/// period's offset, then stays with the camera instead of following the photon noise.
const SWITCH_MARGIN: f32 = 0.9;

/// A second motion is taken for a texture period ([`is_texture_period`]) when the reference
/// matches itself at the motion's offset from the camera with a summed L1 cost below this
/// fraction of the mean cost at the four offsets [`PERIOD_PROBE_PX`] away. This project's
/// heuristic. Measured on the tile sets the second motion took on 10,000-frame captures
/// (`quantacolor simulate --frames 10000 --cfa colorspad`, 400-frame blocks): on the chart
/// (seeds 1–3) most sets lay at 0.22–0.55 (gratings matched a whole number of periods off) and
/// a few at 0.6–0.8; on the `object` captures (kodim15, kodim12, and at 512 frames) every set
/// lay at 0.84 or above; sets along the straight horizon of an HDR sea view (Bonita), matched
/// along the edge (the aperture problem), lay at 0.25–0.73 and fall under it too.
const PERIOD_RATIO: f32 = 0.75;

/// Distance (px) of the four offsets that [`is_texture_period`] compares the reference's
/// self-match against: a quarter of the chart's 8 px grating period, so the probes fall
/// between the grating's repeats.
const PERIOD_PROBE_PX: isize = 2;

/// Whether the reference shifted onto itself by each tile's `offset` (px, integer) matches
/// itself markedly better there than at the offsets [`PERIOD_PROBE_PX`] away in y and in x,
/// summed over `tiles` of `grid` (L1 patch costs; [`PERIOD_RATIO`]). A block that matches the
/// reference at the camera's motion plus such an offset matches it equally well at the camera's
/// motion: a static periodic texture (a grating matched a whole number of periods off), not a
/// second motion. A natural texture moved by an object matches itself no better at the object's
/// offset than beside it.
fn is_texture_period(
    reference: &Array2<f32>,
    grid: &TileGrid,
    tiles: &[(usize, usize)],
    offset: impl Fn((usize, usize)) -> (isize, isize),
) -> bool {
    let ts = grid.tile_size;
    let (mut at_offset, mut beside) = (0.0f32, 0.0f32);
    for &(i, j) in tiles {
        let origin = (i * grid.tile_stride, j * grid.tile_stride);
        let d = offset((i, j));
        let cost = |d: (isize, isize)| offset_cost(reference, reference, origin, ts, d, Norm::L1);
        let here = cost(d);
        let p = PERIOD_PROBE_PX;
        let around = [(p, 0), (-p, 0), (0, p), (0, -p)].map(|(a, b)| cost((d.0 + a, d.1 + b)));
        if here.is_finite() && around.iter().all(|c| c.is_finite()) {
            at_offset += here;
            beside += around.iter().sum::<f32>() / 4.0;
        }
    }
    beside > 0.0 && at_offset < PERIOD_RATIO * beside
}

/// 8-connected sets of `true` cells, each as its (row, column) list.
fn connected_components(mask: &Array2<bool>) -> Vec<Vec<(usize, usize)>> {
    let (h, w) = mask.dim();
    let mut seen = Array2::from_elem((h, w), false);
    let mut out = Vec::new();
    for start in mask.indexed_iter().filter(|(_, &m)| m).map(|(p, _)| p) {
        if seen[start] {
            continue;
        }
        seen[start] = true;
        let mut stack = vec![start];
        let mut component = Vec::new();
        while let Some((i, j)) = stack.pop() {
            component.push((i, j));
            for y in i.saturating_sub(1)..(i + 2).min(h) {
                for x in j.saturating_sub(1)..(j + 2).min(w) {
                    if mask[[y, x]] && !seen[[y, x]] {
                        seen[[y, x]] = true;
                        stack.push((y, x));
                    }
                }
            }
        }
        out.push(component);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn rejected_components_are_the_large_sets_far_from_the_camera() {
        // 4x6 tiles, camera flow zero; a 2x2 set 3 px off (rejected), one tile 3 px off
        // elsewhere (too small), one tile 1 px off (within the tolerance).
        let camera = Array3::<f32>::zeros((4, 6, 2));
        let mut flow = camera.clone();
        for (i, j) in [(0, 0), (0, 1), (1, 0), (1, 1), (3, 5)] {
            flow[[i, j, 1]] = 3.0;
        }
        flow[[2, 3, 0]] = 1.0;
        let components = rejected_components(&flow, &camera, 2.0, 2);
        assert_eq!(components.len(), 1);
        let mut tiles = components[0].clone();
        tiles.sort();
        assert_eq!(tiles, vec![(0, 0), (0, 1), (1, 0), (1, 1)]);
        // min_tiles 0 counts as 1: the lone tile is a component too.
        assert_eq!(rejected_components(&flow, &camera, 2.0, 0).len(), 2);
    }

    #[test]
    fn ambiguous_tiles_take_their_decided_neighbours_majority_inside_the_region() {
        // One row of five tiles, all in the region: decided ends, ambiguous middle.
        let region = TileMask(Array2::from_elem((1, 5), true));
        let mut label =
            Array2::from_shape_vec((1, 5), vec![Some(true), None, None, None, Some(false)])
                .unwrap();
        fill_ambiguous_labels(&mut label, &region);
        // Round 1: tile 1 sees one `true`, tile 3 one `false`, tile 2 none (it waits);
        // round 2: tile 2 sees one of each, a tie, which goes to the camera.
        assert_eq!(
            label.into_raw_vec_and_offset().0,
            vec![
                Some(true),
                Some(true),
                Some(false),
                Some(false),
                Some(false)
            ]
        );
        // Neighbours outside the region do not vote, and tiles outside it are left alone.
        let region = TileMask(Array2::from_shape_vec((1, 3), vec![false, true, true]).unwrap());
        let mut label = Array2::from_shape_vec((1, 3), vec![Some(true), None, None]).unwrap();
        fill_ambiguous_labels(&mut label, &region);
        assert_eq!(
            label.into_raw_vec_and_offset().0,
            vec![Some(true), None, None]
        );
    }

    /// Lucas–Kanade's Σ g·e equals a plain f64 sum of the bilinear samples' errors, for an
    /// interior tile (contiguous taps), tiles clamped at the left and right edges, and a tile
    /// narrower than the eight lanes.
    #[test]
    fn lucas_kanade_sums_match_the_direct_sum() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (h, w) = (40usize, 50usize);
        let alt = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0));
        let reference = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0));
        let cases = [
            (10..26, 12..28, (0.3f32, -0.7f32)),
            (5..21, 0..16, (-0.4, -1.6)),
            (20..36, 34..50, (0.9, 1.2)),
            (3..8, 44..50, (0.2, 0.45)),
            (0..8, 20..28, (-0.6, 0.1)),
            (30..40, 4..28, (0.5, -0.3)),
        ];
        for (ys, xs, u) in cases {
            let grad: Vec<(f32, f32)> = (0..ys.len() * xs.len())
                .map(|_| (rng.gen_range(-1.0f32..1.0), rng.gen_range(-1.0f32..1.0)))
                .collect();
            let grad_y: Vec<f32> = grad.iter().map(|g| g.0).collect();
            let grad_x: Vec<f32> = grad.iter().map(|g| g.1).collect();
            // A scratch left over from a wider tile: its contents must not leak in.
            let mut scratch = LkScratch {
                fxs: vec![9.0; 40],
                errors: vec![9.0; 40],
                ..LkScratch::default()
            };
            scratch.rows = ys
                .clone()
                .map(|y| crate::filters::bilinear_taps(y as f32 + u.0, h))
                .collect();
            scratch.cols = xs
                .clone()
                .map(|x| crate::filters::bilinear_taps(x as f32 + u.1, w))
                .collect();
            let (sy, sx) = lk_gradient_dot_error(
                &alt,
                &reference,
                (&grad_y, &grad_x),
                &mut scratch,
                (ys.clone(), xs.clone()),
            );
            // The portable path: the same numbers bit for bit.
            let generic = lk_gradient_dot_error_generic(
                &alt,
                &reference,
                (&grad_y, &grad_x),
                &mut scratch,
                (ys.clone(), xs.clone()),
            );
            assert_eq!(
                (sy.to_bits(), sx.to_bits()),
                (generic.0.to_bits(), generic.1.to_bits())
            );
            // And the sum as it was made before the scratch buffers and split gradients.
            let before = lk_gradient_dot_error_before(
                &alt,
                &reference,
                &grad,
                &scratch.rows,
                &scratch.cols,
                (ys.clone(), xs.clone()),
            );
            assert_eq!(
                (sy.to_bits(), sx.to_bits()),
                (before.0.to_bits(), before.1.to_bits())
            );
            let (mut ey, mut ex) = (0.0f64, 0.0f64);
            for (j, y) in ys.clone().enumerate() {
                for (i, x) in xs.clone().enumerate() {
                    let sample =
                        crate::filters::bilinear(alt.view(), y as f32 + u.0, x as f32 + u.1);
                    let e = (sample - reference[[y, x]]) as f64;
                    let g = grad[j * xs.len() + i];
                    ey += g.0 as f64 * e;
                    ex += g.1 as f64 * e;
                }
            }
            assert!(
                (sy as f64 - ey).abs() < 1e-4 * (1.0 + ey.abs()),
                "{ys:?} {xs:?}: {sy} vs {ey}"
            );
            assert!(
                (sx as f64 - ex).abs() < 1e-4 * (1.0 + ex.abs()),
                "{ys:?} {xs:?}: {sx} vs {ex}"
            );
        }
    }

    /// [`lk_gradient_dot_error`] as it was before [`LkScratch`] (interleaved gradients, buffers
    /// allocated per call, no AVX2 path): the reference of the bit-for-bit test above.
    fn lk_gradient_dot_error_before(
        alt: &Array2<f32>,
        reference: &Array2<f32>,
        grad: &[(f32, f32)],
        rows: &[(usize, usize, f32)],
        cols: &[(usize, usize, f32)],
        (ys, xs): (Range<usize>, Range<usize>),
    ) -> (f32, f32) {
        const LANES: usize = 8;
        let (mut sum_y, mut sum_x) = ([0.0f32; LANES], [0.0f32; LANES]);
        let width = xs.len();
        let fxs: Vec<f32> = cols.iter().map(|c| c.2).collect();
        let mut errors = vec![0.0f32; width];
        for ((y, &(y0, y1, fy)), grad) in ys.zip(rows).zip(grad.chunks_exact(width)) {
            for (i, &(x0, x1, _)) in cols.iter().enumerate() {
                let fx = fxs[i];
                let top = alt[[y0, x0]] * (1.0 - fx) + alt[[y0, x1]] * fx;
                let bottom = alt[[y1, x0]] * (1.0 - fx) + alt[[y1, x1]] * fx;
                errors[i] = (top * (1.0 - fy) + bottom * fy) - reference[[y, xs.start + i]];
            }
            for (i, (e, g)) in errors.iter().zip(grad).enumerate() {
                sum_y[i % LANES] += g.0 * e;
                sum_x[i % LANES] += g.1 * e;
            }
        }
        let total = |lanes: [f32; LANES]| lanes.iter().sum::<f32>();
        (total(sum_y), total(sum_x))
    }

    /// A reference and an alternate image of uniform random values in [0, 1), drawn in that
    /// order from `rng`.
    fn random_image_pair(rng: &mut ChaCha8Rng, h: usize, w: usize) -> (Array2<f32>, Array2<f32>) {
        let reference = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0));
        let alternate = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0));
        (reference, alternate)
    }

    /// Every cost of a window row equals [`tile_cost`] bit for bit: interior tiles, tiles at
    /// every border, offsets reaching past the image, both norms.
    #[test]
    fn window_row_costs_equal_tile_cost() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (h, w) = (29usize, 41usize);
        let (reference, alternate) = random_image_pair(&mut rng, h, w);
        let mut finite = 0;
        for norm in [Norm::L1, Norm::L2] {
            for ts in [8usize, 16] {
                for oy in (0..h).step_by(5) {
                    for ox in (0..w).step_by(3) {
                        for radius in [1isize, 4, 8] {
                            let dy = rng.gen_range(-6isize..=6);
                            let dx0 = rng.gen_range(-12isize..=6);
                            let mut costs = vec![0.0f32; (2 * radius + 1) as usize];
                            window_row_costs(
                                &reference,
                                &alternate,
                                (oy, ox),
                                ts,
                                (dy, dx0),
                                norm,
                                &mut costs,
                            );
                            for (i, &c) in costs.iter().enumerate() {
                                let d = (dy, dx0 + i as isize);
                                let expected =
                                    tile_cost(&reference, &alternate, (oy, ox), ts, d, norm);
                                assert_eq!(c.to_bits(), expected.to_bits(), "{oy} {ox} {d:?}");
                                finite += c.is_finite() as usize;
                            }
                        }
                    }
                }
            }
        }
        assert!(finite > 1000, "{finite}");
    }

    /// The transposed kernel of windows that no offset clips ([`interior_window_costs`]) gives
    /// the plain loop's bits for both tile sizes, both norms and window sides of one to the
    /// largest strip; it declines windows that clip the tile or would read past the image.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn interior_window_costs_equal_the_plain_tile_cost() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (h, w) = (70usize, 83usize);
        let (reference, alternate) = random_image_pair(&mut rng, h, w);
        let (mut taken, mut declined) = (0, 0);
        for norm in [Norm::L1, Norm::L2] {
            for ts in [8usize, 16] {
                for side in [1usize, 2, 3, 7, 9, 17, 33, 49] {
                    for _ in 0..40 {
                        let rows = rng.gen_range(1..=side.min(9));
                        let (oy, ox) = (rng.gen_range(0..h - 4), rng.gen_range(0..w - 4));
                        let dy0 = rng.gen_range(-(oy as isize) - 3..8);
                        let dx0 = rng.gen_range(-(ox as isize) - 3..8);
                        let mut costs = vec![f32::NAN; rows * side];
                        let ok = interior_window_costs(
                            &reference,
                            &alternate,
                            (oy, ox),
                            ts,
                            (dy0, dx0),
                            norm,
                            side,
                            &mut costs,
                        );
                        let clipped = oy + ts > h
                            || ox + ts > w
                            || oy as isize + dy0 < 0
                            || ox as isize + dx0 < 0
                            || oy as isize + dy0 + (rows + ts - 1) as isize > h as isize
                            || ox as isize + dx0 + (side + ts - 1) as isize > w as isize;
                        if clipped {
                            assert!(!ok, "{oy} {ox} {dy0} {dx0} {side} {rows}");
                        }
                        if !ok {
                            assert!(costs.iter().all(|c| c.is_nan()), "wrote while declining");
                            declined += 1;
                            continue;
                        }
                        taken += 1;
                        for (k, &c) in costs.iter().enumerate() {
                            let d = (dy0 + (k / side) as isize, dx0 + (k % side) as isize);
                            let plain =
                                tile_cost_plain(&reference, &alternate, (oy, ox), ts, d, norm);
                            assert!(plain.is_finite());
                            assert_eq!(c.to_bits(), plain.to_bits(), "{oy} {ox} {d:?} {side}");
                        }
                    }
                }
            }
        }
        assert!(taken > 100 && declined > 100, "{taken} {declined}");
    }

    /// The seeds' costs ([`seed_costs`], all of a tile's seeds in one kernel where they lie
    /// inside the images) equal the plain loop bit for bit, for one to four seeds, both tile
    /// sizes and norms, tiles inside and at the edges, seeds inside and reaching past the image.
    #[test]
    fn seed_costs_equal_the_plain_tile_cost() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let (h, w) = (57usize, 66usize);
        let (reference, alternate) = random_image_pair(&mut rng, h, w);
        let mut finite = 0;
        for norm in [Norm::L1, Norm::L2] {
            for ts in [8usize, 16] {
                for _ in 0..300 {
                    let (oy, ox) = (rng.gen_range(0..h - 4), rng.gen_range(0..w - 4));
                    let n = rng.gen_range(1..=4);
                    let seeds: Vec<(isize, isize)> = (0..n)
                        .map(|_| (rng.gen_range(-12isize..=12), rng.gen_range(-12isize..=12)))
                        .collect();
                    let mut costs = vec![f32::NAN; n];
                    seed_costs(
                        &reference,
                        &alternate,
                        (oy, ox),
                        ts,
                        &seeds,
                        norm,
                        &mut costs,
                    );
                    for (&c, &d) in costs.iter().zip(&seeds) {
                        let plain = tile_cost_plain(&reference, &alternate, (oy, ox), ts, d, norm);
                        assert_eq!(c.to_bits(), plain.to_bits(), "{oy} {ox} {d:?} {ts}");
                        finite += c.is_finite() as usize;
                    }
                }
            }
        }
        assert!(finite > 1000, "{finite}");
    }

    /// [`best_offset`] is the sequential scan it replaces (keep the best so far from (∞, seed);
    /// take a smaller cost, or an equal one strictly closer to zero motion): windows with ties
    /// among few distinct costs, infinite and NaN costs, all infinite, seeds on either side.
    #[test]
    fn best_offset_equals_the_sequential_scan() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let values = [0.25f32, 0.5, 0.75, f32::INFINITY, f32::NAN];
        let mut finite_ties = 0;
        for case in 0..4000 {
            let radius = [1isize, 2, 4, 8][case % 4];
            let side = (2 * radius + 1) as usize;
            let seed = (rng.gen_range(-5isize..=5), rng.gen_range(-5isize..=5));
            let all_infinite = case % 7 == 0;
            let costs: Vec<f32> = (0..side * side)
                .map(|_| {
                    if all_infinite {
                        [f32::INFINITY, f32::NAN][rng.gen_range(0..2)]
                    } else {
                        values[rng.gen_range(0..values.len())]
                    }
                })
                .collect();
            let mut best = (f32::INFINITY, seed);
            for (dy, row) in (-radius..=radius).zip(costs.chunks_exact(side)) {
                for (dx, &c) in (-radius..=radius).zip(row) {
                    let d = (seed.0 + dy, seed.1 + dx);
                    let closer = (d.0.abs() + d.1.abs()) < (best.1 .0.abs() + best.1 .1.abs());
                    if c < best.0 || (c == best.0 && closer) {
                        best = (c, d);
                    }
                }
            }
            let least = costs.iter().filter(|&&c| c == best.0).count();
            finite_ties += (best.0.is_finite() && least > 1) as usize;
            assert_eq!(
                best_offset(&costs, side, seed, radius),
                best.1,
                "case {case}"
            );
        }
        assert!(finite_ties > 1000, "{finite_ties}");
    }

    /// [`tile_cost`] as a plain loop: each row summed in column order from zero, the rows
    /// added in order (the four-row batches of `rows_cost` must give these numbers).
    fn tile_cost_plain(
        reference: &Array2<f32>,
        alternate: &Array2<f32>,
        (oy, ox): (usize, usize),
        ts: usize,
        (dy, dx): (isize, isize),
        norm: Norm,
    ) -> f32 {
        let (h, w) = (reference.nrows() as isize, reference.ncols() as isize);
        let (oy, ox, ts) = (oy as isize, ox as isize, ts as isize);
        let (y0, y1) = (oy.max(-dy).max(0), (oy + ts).min(h).min(h - dy));
        let (x0, x1) = (ox.max(-dx).max(0), (ox + ts).min(w).min(w - dx));
        if y1 <= y0 || x1 <= x0 || 4 * (y1 - y0) * (x1 - x0) < ts.min(h) * ts.min(w) {
            return f32::INFINITY;
        }
        let mut cost = 0.0f32;
        for y in y0..y1 {
            let mut row = 0.0f32;
            for x in x0..x1 {
                let d = reference[[y as usize, x as usize]]
                    - alternate[[(y + dy) as usize, (x + dx) as usize]];
                row += match norm {
                    Norm::L1 => d.abs(),
                    Norm::L2 => d * d,
                };
            }
            cost += row;
        }
        cost / ((y1 - y0) * (x1 - x0)) as f32
    }

    /// Whole windows of costs ([`window_costs`], rows of offsets side by side) and single
    /// costs ([`tile_cost`], rows four at a time) equal the plain loop bit for bit: interior
    /// tiles, tiles at every border, offsets reaching past the image, both norms, window sides
    /// of one to three vectors and wider.
    #[test]
    fn window_costs_equal_the_plain_tile_cost() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (h, w) = (31usize, 45usize);
        let (reference, alternate) = random_image_pair(&mut rng, h, w);
        let mut finite = 0;
        for norm in [Norm::L1, Norm::L2] {
            for ts in [4usize, 8, 16] {
                for oy in (0..h).step_by(6) {
                    for ox in (0..w).step_by(4) {
                        for side in [3usize, 5, 9, 17, 30] {
                            let dy0 = rng.gen_range(-20isize..=6);
                            let dx0 = rng.gen_range(-20isize..=6);
                            let mut costs = vec![0.0f32; side * side];
                            window_costs(
                                &reference,
                                &alternate,
                                (oy, ox),
                                ts,
                                (dy0, dx0),
                                norm,
                                side,
                                &mut costs,
                            );
                            for (k, &c) in costs.iter().enumerate() {
                                let d = (dy0 + (k / side) as isize, dx0 + (k % side) as isize);
                                let plain =
                                    tile_cost_plain(&reference, &alternate, (oy, ox), ts, d, norm);
                                let single =
                                    tile_cost(&reference, &alternate, (oy, ox), ts, d, norm);
                                assert_eq!(c.to_bits(), plain.to_bits(), "{oy} {ox} {d:?}");
                                assert_eq!(single.to_bits(), plain.to_bits(), "{oy} {ox} {d:?}");
                                finite += c.is_finite() as usize;
                            }
                        }
                    }
                }
            }
        }
        assert!(finite > 10000, "{finite}");
    }
}
