//! Aggregation (Dabov et al., TIP 2007, §III-A.3 / §III-B.3, Eq. 10 / Eq. 12): every block
//! estimate of a group, weighted and Kaiser-windowed, into its reference row's strip; then the
//! strips into the image in reference-row order, so the sums are the same for any thread count.

#![forbid(unsafe_code)]

use super::{Geometry, Scratch, Transforms};
use rayon::prelude::*;

/// Numerator and denominator of the aggregation for image rows `y0..y0+rows`, every channel.
pub(super) struct Strip<'b> {
    pub(super) y0: usize,
    pub(super) rows: usize,
    pub(super) num: &'b mut [f32],
    pub(super) den: &'b mut [f32],
}

/// Adds the block estimates of the group in `s` (its members' filtered 2D spectra in
/// `s.noisy_group`), channel `c`, into `strip`: `num += weight·kaiser·pixels`, `den +=
/// weight·kaiser`, after the inverse 2D DCT of each.
#[inline(always)]
pub(super) fn aggregate_group(
    geo: &Geometry,
    tr: &Transforms,
    c: usize,
    weight: f32,
    s: &mut Scratch,
    strip: &mut Strip<'_>,
) {
    let n = geo.n;
    let n2 = n * n;
    let m = s.group.len();
    let w = geo.w;
    let group = &s.noisy_group[..m * n2];
    let len = strip.rows * w;
    let num = &mut strip.num[c * len..(c + 1) * len];
    let den = &mut strip.den[c * len..(c + 1) * len];
    for (g, &pos) in s.group.iter().enumerate() {
        let (by, bx) = (pos / geo.pw, pos % geo.pw);
        tr.inverse(&group[g * n2..(g + 1) * n2], &mut s.tmp, &mut s.pixels);
        for i in 0..n {
            let row = (by + i - strip.y0) * w + bx;
            let kai = &tr.kaiser[i * n..(i + 1) * n];
            let px = &s.pixels[i * n..(i + 1) * n];
            let (num, den) = (&mut num[row..row + n], &mut den[row..row + n]);
            if n == 8 {
                // Fixed length: unrolled and vectorised.
                let num: &mut [f32; 8] = num.try_into().expect("8 wide");
                let den: &mut [f32; 8] = den.try_into().expect("8 wide");
                let kai: &[f32; 8] = kai.try_into().expect("8 wide");
                let px: &[f32; 8] = px.try_into().expect("8 wide");
                aggregate_row8(num, den, kai, px, weight);
            } else {
                aggregate_row(num, den, kai, px, weight);
            }
        }
    }
}

/// Adds the strips of one batch of reference rows (`strips[k]` = (first image row, rows) of
/// `buffers[k]`, numerator and denominator, every channel) into the image sums `num` and `den`
/// (`(C, h, w)`). Image rows are independent, so they are split among the threads; each row
/// still adds the strips that cover it in reference-row order.
pub(super) fn sum_strips(
    num: &mut [f32],
    den: &mut [f32],
    strips: &[(usize, usize)],
    buffers: &[(Vec<f32>, Vec<f32>)],
    (h, w): (usize, usize),
) {
    let add_rows = |acc: &mut [f32], first: usize, numerator: bool| {
        for (k, dst) in acc.chunks_exact_mut(w).enumerate() {
            let (c, y) = ((first + k) / h, (first + k) % h);
            for (&(y0, rows), buffer) in strips.iter().zip(buffers) {
                if (y0..y0 + rows).contains(&y) {
                    let strip = if numerator { &buffer.0 } else { &buffer.1 };
                    let src = &strip[(c * rows + y - y0) * w..][..w];
                    for (d, s) in dst.iter_mut().zip(src) {
                        *d += s;
                    }
                }
            }
        }
    };
    const SUM_ROWS: usize = 16;
    num.par_chunks_mut(SUM_ROWS * w)
        .zip(den.par_chunks_mut(SUM_ROWS * w))
        .enumerate()
        .for_each(|(i, (num, den))| {
            add_rows(num, i * SUM_ROWS, true);
            add_rows(den, i * SUM_ROWS, false);
        });
}

/// `num += weight·kai·px`, `den += weight·kai` along one block row (aggregation, TIP 2007
/// Eq. 10 / Eq. 12).
#[inline(always)]
fn aggregate_row(num: &mut [f32], den: &mut [f32], kai: &[f32], px: &[f32], weight: f32) {
    for (((num, den), &k), &v) in num.iter_mut().zip(den.iter_mut()).zip(kai).zip(px) {
        let wk = weight * k;
        *num += wk * v;
        *den += wk;
    }
}

/// [`aggregate_row`] of an 8-pixel row, through local copies so that it compiles to a few
/// vector instructions: the same operations, so the same bits.
#[inline(always)]
fn aggregate_row8(
    num: &mut [f32; 8],
    den: &mut [f32; 8],
    kai: &[f32; 8],
    px: &[f32; 8],
    weight: f32,
) {
    let (mut n8, mut d8) = (*num, *den);
    for j in 0..8 {
        let wk = weight * kai[j];
        n8[j] += wk * px[j];
        d8[j] += wk;
    }
    *num = n8;
    *den = d8;
}
