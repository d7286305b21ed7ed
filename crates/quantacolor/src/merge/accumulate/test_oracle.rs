//! Reference implementations used only by the tests: the regression as it was before its
//! weights were made a bin row at a time, and the per-row ellipse span.
#![forbid(unsafe_code)]

use super::regression::{ellipse_spans, lane_sum, BinSpan};
use super::weights::power_weights;
use super::*;

impl MergeAccumulator<'_> {
    /// Runs `f` with what the regression of every channel over the phase bins reads
    /// ([`Gather`]).
    pub(super) fn with_gather<R>(&self, f: impl FnOnce(&Gather) -> R) -> R {
        let inv_cov = self.kernels.inv_cov.as_standard_layout();
        let gather = self.gather(
            self.fine_grid(),
            [true; 4],
            inv_cov.as_slice().expect("standard layout"),
            true,
        );
        f(&gather)
    }
}

/// The regression of [`gather_row_generic`] as it was before its weights were made a bin row
/// at a time (the channels taking turns per group of eight bins, the partial sums in memory):
/// the reference of `gather_row_matches_the_group_by_group_reference`.
pub(super) fn gather_row_reference(g: &Gather, oy: usize, row: &mut [[f32; SUMS]]) {
    let stride = g.stride;
    let (u, inv_u, margin, radius) = (g.u, g.inv_u, g.margin, g.radius);
    let py = oy as f32 * g.inv_s + g.offset;
    let iy = (py.round().max(0.0) as usize).min(g.h - 1);
    let by0 = (((py - radius + margin) * u).ceil() as isize).max(0);
    let by1 = (((py + radius + margin) * u).floor() as isize).min(g.bins_h - 1);
    // Row offsets of the bin rows from the pixel row, and each pixel's dx interval of every
    // ellipse in each bin row (the main one, then each channel's own), made for all rows at
    // once ([`ellipse_spans`]).
    let dys: Vec<f32> = (by0..=by1)
        .map(|by| by as f32 * inv_u - margin - py)
        .collect();
    let rows = dys.len();
    let mut main_span = vec![[0.0f64; 2]; rows];
    let mut channel_span: [Vec<[f64; 2]>; 4] = std::array::from_fn(|ch| {
        if g.channel_limit[ch].is_some() {
            vec![[0.0f64; 2]; rows]
        } else {
            Vec::new()
        }
    });
    for (ox, out) in row.iter_mut().enumerate() {
        let px = ox as f32 * g.inv_s + g.offset;
        let ix = (px.round().max(0.0) as usize).min(g.w - 1);
        let k = 3 * (iy * g.w + ix);
        let (a, b2, c) = (g.inv_cov[k], 2.0 * g.inv_cov[k + 1], g.inv_cov[k + 2]);
        let bx0 = (((px - radius + margin) * u).ceil() as isize).max(0);
        let bx1 = (((px + radius + margin) * u).floor() as isize).min(g.bins_w - 1);
        if let Some(limit) = g.ellipse_limit {
            ellipse_spans(a, b2, c, &dys, limit, &mut main_span);
        }
        for (ch, spans) in channel_span.iter_mut().enumerate() {
            if let Some(limit) = g.channel_limit[ch] {
                ellipse_spans(a, b2, c, &dys, limit, spans);
            }
        }
        // acc[channel][sum][lane]
        let mut acc = [[[0.0f32; LANES]; PLANES]; 4];
        for (row, by) in (by0..=by1).enumerate() {
            let dy = dys[row];
            let ady2 = a * dy * dy;
            let bdy = b2 * dy;
            // The bins of the row inside an ellipse's dx interval, widened by a bin each side.
            let cols = BinSpan {
                bx0,
                bx1,
                inv_u: inv_u as f64,
                centre: (margin + px) as f64,
                u: u as f64,
            };
            let (lo, hi) = match g.ellipse_limit {
                Some(_) => cols.of(main_span[row]),
                None => (bx0, bx1),
            };
            // Each channel's own bins (a narrower ellipse: fewer); a group of lanes outside them
            // would add exact zeros to the channel's sums, so it is skipped. Channels that
            // share weights share the factor, hence the span. (Plain functions, not closures,
            // so that they are compiled with the caller's instruction set: no libm calls for
            // `floor` and `ceil`.)
            let mut span = [(lo, hi); 4];
            for (ch, span) in span.iter_mut().enumerate() {
                if g.channel_limit[ch].is_some() {
                    let (l, h) = cols.of(channel_span[ch][row]);
                    *span = (l.max(lo), h.min(hi));
                }
            }
            let row_start = by as usize * SUMS * stride;
            reference_groups(g, row_start, (lo, hi), &span, (ady2, bdy, c), px, &mut acc);
        }
        for (ch, acc) in acc.iter().enumerate() {
            for (sum, lanes) in acc.iter().enumerate() {
                out[ch * PLANES + sum] = lane_sum(lanes);
            }
        }
    }
}

/// The dx interval of row offset `dy` where the kernel's quadratic form
/// a·dy² + 2b·dy·dx + c·dx² (`b2` = 2b) is below `limit`, widened by 0.1 % and 10⁻³ px against
/// rounding; `None` when the whole row is at least 0.1 % above it. Not positive definite:
/// an unbounded interval. The reference of [`ellipse_spans`].
pub(super) fn ellipse_span(a: f32, b2: f32, c: f32, dy: f32, limit: f64) -> Option<(f64, f64)> {
    let (a, b, c, dy) = (a as f64, b2 as f64 / 2.0, c as f64, dy as f64);
    let det = a * c - b * b;
    if !(c > 0.0 && det > 0.0) {
        return Some((f64::NEG_INFINITY, f64::INFINITY));
    }
    // Minimum over dx at dx* = −b·dy/c, of value dy²·det/c.
    let min = dy * dy * det / c;
    let slack = limit * 1e-3 + 1e-6;
    if min > limit + slack {
        return None;
    }
    let half = ((limit + slack - min).max(0.0) / c).sqrt() * 1.001 + 1e-3;
    let centre = -b * dy / c;
    Some((centre - half, centre + half))
}

/// The groups of eight bins from `lo` to `hi` of the bin row whose first bin is `row_start`
/// ([`gather_row_reference`]), the channels taking turns per group, each within its `span`.
fn reference_groups(
    g: &Gather,
    row_start: usize,
    (lo, hi): (isize, isize),
    span: &[(isize, isize); 4],
    (ady2, bdy, c): (f32, f32, f32),
    px: f32,
    acc: &mut [[[f32; LANES]; PLANES]; 4],
) {
    let (bins, stride) = (g.bins, g.stride);
    let (inv_u, margin) = (g.inv_u, g.margin);
    let mut bx = lo;
    while bx <= hi {
        let mut quad = [0.0f32; LANES];
        let mut inside = [false; LANES];
        for i in 0..LANES {
            let dx = (bx + i as isize) as f32 * inv_u - margin - px;
            quad[i] = ady2 + dx * (bdy + c * dx);
            inside[i] = bx + (i as isize) <= hi;
        }
        let first = row_start + bx as usize;
        for (ch, acc) in acc.iter_mut().enumerate() {
            if !g.present[ch] || bx + (LANES as isize - 1) < span[ch].0 || bx > span[ch].1 {
                continue;
            }
            let exps = |ch: usize| -> [f32; LANES] {
                std::array::from_fn(|i| {
                    let q = quad[i] * g.inv_scale[ch];
                    let e = fastmath::exp(-0.5 * q);
                    if inside[i] && q < g.cutoff {
                        e
                    } else {
                        0.0
                    }
                })
            };
            let weight = match g.power[ch] {
                0 => exps(ch),
                k => power_weights(g, ch, &quad, exps(g.base), k),
            };
            let at = first + ch * PLANES * stride;
            let s0: &[f32; LANES] = bins[at..at + LANES].try_into().expect("lanes");
            let at = at + stride;
            let s1: &[f32; LANES] = bins[at..at + LANES].try_into().expect("lanes");
            let at = at + stride;
            let s2: &[f32; LANES] = bins[at..at + LANES].try_into().expect("lanes");
            let at = at + stride;
            let s3: &[f32; LANES] = bins[at..at + LANES].try_into().expect("lanes");
            for i in 0..LANES {
                acc[0][i] += weight[i] * s0[i];
                acc[1][i] += weight[i] * s1[i];
                acc[2][i] += weight[i] * weight[i] * s2[i];
                if g.with_flux {
                    acc[3][i] += weight[i] * s3[i];
                }
            }
        }
        bx += LANES as isize;
    }
}
