//! Sub-pixel refinement on level 0: Lucas–Kanade (inverse-compositional Gauss–Newton) steps
//! from the integer search's offset, with the reference tile's gradients and normal matrix
//! computed once per reference. This project's choice for the sub-pixel step (HDR+,
//! Hasinoff et al. 2016 §4.1, fits a quadratic to the L2 costs instead).
#![forbid(unsafe_code)]

use super::ReferenceAligner;
use crate::cpu::Isa;
use ndarray::Array2;
use std::ops::Range;

/// Reference-side data of a Lucas–Kanade tile: gradients and the inverse of the 2x2 normal
/// matrix (inverse-compositional style: computed once, reused for every block).
#[derive(Debug, Clone)]
pub(super) struct LkTile {
    /// ∂/∂y of the reference over the tile, row-major.
    grad_y: Vec<f32>,
    /// ∂/∂x, likewise.
    grad_x: Vec<f32>,
    inv: Option<[f32; 3]>, // (a, b, c) of the symmetric inverse [[a, b], [b, c]]
}

impl ReferenceAligner {
    /// Lucas–Kanade refinement of tile `k` from the integer offset `start`: minimises
    /// Σ (alt(p + u) − ref(p))² by Gauss–Newton steps with the reference gradients; `None`
    /// when the tile lacks texture in some direction or the steps leave ±1 px.
    pub(super) fn refine(
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
                self.isa,
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
pub(super) struct LkScratch {
    /// The bilinear taps `(y0, y1, fy)` of the tile's rows.
    pub(super) rows: Vec<(usize, usize, f32)>,
    /// The bilinear taps `(x0, x1, fx)` of the tile's columns.
    pub(super) cols: Vec<(usize, usize, f32)>,
    /// The column weights `fx` of `cols`.
    pub(super) fxs: Vec<f32>,
    /// The errors of one row of the tile.
    pub(super) errors: Vec<f32>,
    /// The costs of a tile's search window, row-major (used by the integer search of
    /// [`ReferenceAligner::align_with_pyramid`], which shares the per-thread scratch).
    pub(super) window: Vec<f32>,
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
/// samples are read as slices. `isa` picks the AVX2 kernel or [`lk_gradient_dot_error_generic`].
pub(super) fn lk_gradient_dot_error(
    isa: Isa,
    alt: &Array2<f32>,
    reference: &Array2<f32>,
    grad: (&[f32], &[f32]),
    scratch: &mut LkScratch,
    tile: (Range<usize>, Range<usize>),
) -> (f32, f32) {
    #[cfg(target_arch = "x86_64")]
    {
        if isa.avx2() {
            return super::x86::lk_gradient_dot_error(isa, alt, reference, grad, scratch, tile);
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = isa;
    lk_gradient_dot_error_generic(alt, reference, grad, scratch, tile)
}

/// The portable [`lk_gradient_dot_error`] (also the AVX2 kernel's path for tiles it does not
/// take, compiled there for AVX2).
#[inline(always)]
pub(super) fn lk_gradient_dot_error_generic(
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
pub(super) fn lk_tile(img: &Array2<f32>, oy: usize, ox: usize, ts: usize) -> LkTile {
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
