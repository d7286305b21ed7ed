//! The AVX2 kernels of the patch costs ([`super::cost`]) and of Lucas–Kanade's Σ g·e
//! ([`super::lucas_kanade`]), each giving its portable reference's numbers bit for bit (the
//! same operations per lane in the same order, no fused multiply-add). Entered only through
//! the safe functions at the top, which check the [`Isa`] first.
#![allow(unsafe_code)]

use super::cost::{tile_cost, Tile};
use super::lucas_kanade::{lk_gradient_dot_error_generic, LkScratch};
use super::Norm;
use crate::cpu::Isa;
use ndarray::Array2;
use std::ops::Range;

/// The rows of offsets of [`super::cost::window_costs`] done with AVX2, into `out`: all of
/// them by [`interior_window_costs`] where no offset clips the tile; otherwise, for windows
/// of 2 to 24 offsets a row, up to three rows side by side by [`tile_costs_avx2`] while they
/// all overlap the image alike. Returns how many rows are done (0 without AVX2); the caller
/// takes the rest a row at a time.
pub(super) fn window_costs(
    tile: &Tile<'_>,
    (dy0, dx0): (isize, isize),
    side: usize,
    out: &mut [f32],
) -> usize {
    let rows = out.len() / side;
    if !tile.isa.avx2() {
        return 0;
    }
    if interior_window_costs(tile, (dy0, dx0), side, out) {
        return rows;
    }
    let mut done = 0;
    if (2..=24).contains(&side) {
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
            // SAFETY: AVX2 checked above (an `Isa` offers it only where the CPU has it).
            let ok = unsafe { kernel(tile, (dy, dx0), part) };
            if !ok {
                break;
            }
            done += batch;
        }
    }
    done
}

/// The offsets of [`super::cost::window_row_costs`] done with AVX2, into `out`: runs of up to
/// 24 offsets that clip the tile alike by [`tile_costs_avx2`] (a run of one by
/// [`tile_cost`]). Returns how many offsets are done (0 without AVX2); the caller takes the
/// rest one [`tile_cost`] each.
pub(super) fn window_row_costs(
    tile: &Tile<'_>,
    (dy, dx0): (isize, isize),
    out: &mut [f32],
) -> usize {
    let mut done = 0;
    if !tile.isa.avx2() {
        return done;
    }
    let (ox, w) = (tile.origin.1 as isize, tile.reference.ncols() as isize);
    let ts_i = tile.ts as isize;
    let clip_x = |dx: isize| (ox.max(-dx).max(0), (ox + ts_i).min(w).min(w - dx));
    while done + 1 < out.len() {
        let dx = dx0 + done as isize;
        // The offsets that clip the tile as the first does (a prefix: the bounds are
        // monotone in dx); one offset alone takes `tile_cost`.
        let lanes = (1..(out.len() - done).min(24))
            .find(|&l| clip_x(dx + l as isize) != clip_x(dx))
            .unwrap_or((out.len() - done).min(24));
        if lanes == 1 {
            out[done] = tile_cost(tile, (dy, dx));
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
        // SAFETY: AVX2 checked above (an `Isa` offers it only where the CPU has it).
        let ok = unsafe { kernel(tile, (dy, dx), part) };
        if !ok {
            break;
        }
        done += lanes;
    }
    done
}

/// [`super::cost::seed_costs`] with AVX2 where the tile and every seed's displaced copy lie
/// inside the images and the tile is 8 or 16 px: one [`interior_costs_avx2`] over the seeds
/// into `out`, `true`; otherwise `false` and nothing written.
pub(super) fn seed_costs(tile: &Tile<'_>, seeds: &[(isize, isize)], out: &mut [f32]) -> bool {
    let Tile {
        reference,
        alternate,
        origin: (oy, ox),
        ts,
        norm,
        isa,
    } = *tile;
    let (h, w) = reference.dim();
    let mut origins = [(0, 0); 8];
    let fits = |&(dy, dx): &(isize, isize)| {
        let (ay, ax) = (oy as isize + dy, ox as isize + dx);
        // The tile's whole-vector loads of its last row end inside the data.
        (ay >= 0 && ax >= 0 && ay as usize + ts <= h && ax as usize + ts <= w)
            .then_some((ay as usize, ax as usize))
    };
    if !(isa.avx2()
        && matches!(ts, 8 | 16)
        && seeds.len() <= origins.len()
        && oy + ts <= h
        && ox + ts <= w
        && alternate.dim() == (h, w))
    {
        return false;
    }
    let (Some(rs), Some(as_)) = (reference.as_slice(), alternate.as_slice()) else {
        return false;
    };
    let mut all = true;
    for (o, d) in origins.iter_mut().zip(seeds) {
        match fits(d) {
            Some(a) => *o = a,
            None => all = false,
        }
    }
    if !all {
        return false;
    }
    let interior = Interior {
        rs,
        as_,
        w,
        origin: (oy, ox),
        ts,
        norm,
    };
    // SAFETY: AVX2 checked above; every seed's copy lies inside the images (a strip of one
    // offset is the tile's width, a whole number of vectors).
    unsafe { interior_costs(&interior, &origins[..seeds.len()], 1, out) };
    true
}

/// [`super::lucas_kanade::lk_gradient_dot_error`] with AVX2 where `isa` has it (the portable
/// path otherwise).
pub(super) fn lk_gradient_dot_error(
    isa: Isa,
    alt: &Array2<f32>,
    reference: &Array2<f32>,
    grad: (&[f32], &[f32]),
    scratch: &mut LkScratch,
    tile: (Range<usize>, Range<usize>),
) -> (f32, f32) {
    if !isa.avx2() {
        return lk_gradient_dot_error_generic(alt, reference, grad, scratch, tile);
    }
    // SAFETY: the CPU supports AVX2 (an `Isa` offers it only where the CPU has it).
    unsafe { lk_gradient_dot_error_avx2(alt, reference, grad, scratch, tile) }
}

/// A tile of 8 or 16 px inside both images as the transposed kernels read it: the images'
/// data (row-major, rows of `w`), the tile's origin and side, and the patch distance.
struct Interior<'a> {
    rs: &'a [f32],
    as_: &'a [f32],
    w: usize,
    origin: (usize, usize),
    ts: usize,
    norm: Norm,
}

/// Most alternate columns that [`interior_costs_avx2`] holds transposed (the window's side − 1
/// plus the tile size, in whole vectors of eight).
const STRIP_COLUMNS: usize = 64;

/// [`super::cost::window_costs`] with AVX2 where no offset of the window clips the tile (the tile and every
/// displaced copy lie wholly inside the images, so every cost is the full tile's sum over its
/// area) and the tile is 8 or 16 px: [`interior_costs_avx2`] into `out`, `true`; otherwise
/// `false` and nothing written.
pub(super) fn interior_window_costs(
    tile: &Tile<'_>,
    (dy0, dx0): (isize, isize),
    side: usize,
    out: &mut [f32],
) -> bool {
    let Tile {
        reference,
        alternate,
        origin: (oy, ox),
        ts,
        norm,
        isa,
    } = *tile;
    if !isa.avx2() {
        return false;
    }
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
    let interior = Interior {
        rs,
        as_,
        w,
        origin: (oy, ox),
        ts,
        norm,
    };
    // SAFETY: AVX2 checked above (an `Isa` offers it only where the CPU has it); the loads
    // stay inside both slices (checked above; a window fits the strip, so it has fewer rows
    // than `STRIP_COLUMNS`).
    unsafe { interior_costs(&interior, &origins[..rows], side, out) };
    true
}

/// [`interior_costs_avx2`] in the copy whose strip holds `side` offsets of a tile of `ts` px
/// (the smallest array that fits it, a fixed size per kernel: no allocation, and no more of it
/// cleared than a window of this side needs).
///
/// # Safety
/// As [`interior_costs_avx2`]; `ts` is 8 or 16 and the strip at most [`STRIP_COLUMNS`].
unsafe fn interior_costs(
    interior: &Interior<'_>,
    origins: &[(usize, usize)],
    side: usize,
    out: &mut [f32],
) {
    let ts = interior.ts;
    let strip = (side + ts - 1).div_ceil(8) * 8;
    let kernel = match (ts, strip) {
        (8, ..=16) => interior_costs_avx2::<1, 16>,
        (8, ..=32) => interior_costs_avx2::<1, 32>,
        (8, _) => interior_costs_avx2::<1, STRIP_COLUMNS>,
        (_, ..=16) => interior_costs_avx2::<2, 16>,
        (_, ..=32) => interior_costs_avx2::<2, 32>,
        (_, _) => interior_costs_avx2::<2, STRIP_COLUMNS>,
    };
    kernel(interior, origins, side, out)
}

/// Eight rows of `img` (row length `w`) from `(y, x)`, eight columns each, transposed: vector
/// c holds column x + c, lane l row y + l.
///
/// # Safety
/// The CPU must support AVX2; the eight rows' eight columns must lie inside `img`.
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
#[target_feature(enable = "avx2")]
unsafe fn interior_costs_avx2<const G: usize, const S: usize>(
    interior: &Interior<'_>,
    origins: &[(usize, usize)],
    side: usize,
    out: &mut [f32],
) {
    use std::arch::x86_64::*;
    let Interior {
        rs,
        as_,
        w,
        origin: (oy, ox),
        norm,
        ..
    } = *interior;
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
type CostKernel = unsafe fn(&Tile<'_>, (isize, isize), &mut [f32]) -> bool;

/// [`tile_cost`] of the offsets `(dy + k, dx + i)`, `k < R`, `i < out.len() / R` (at most
/// `8·V`), into `out` (row-major), lane-parallel in `R·V` vectors of eight (independent sums,
/// so the vectors overlap in time); `false` (nothing written) when the offsets do not all clip
/// the tile alike or the wide loads would leave the image (the caller then takes them another
/// way).
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2")]
unsafe fn tile_costs_avx2<const V: usize, const R: usize>(
    tile: &Tile<'_>,
    (dy, dx): (isize, isize),
    out: &mut [f32],
) -> bool {
    use std::arch::x86_64::*;
    let Tile {
        reference,
        alternate,
        origin: (oy, ox),
        ts,
        norm,
        ..
    } = *tile;
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

/// [`lk_gradient_dot_error_generic`] with AVX2: where the column taps are contiguous and the
/// tile's width a multiple of eight (every interior tile), eight columns at a time with each
/// lane doing the generic path's operations in its order (multiplies and adds, no fused
/// multiply-add), so the same numbers bit for bit; otherwise the generic path compiled for
/// AVX2.
///
/// # Safety
/// The CPU must support AVX2.
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
