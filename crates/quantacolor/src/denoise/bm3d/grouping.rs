//! Block matching (Dabov et al., TIP 2007, §III-A.1 / §III-B.1, Eq. 3 / Eq. 6): the squared
//! distance of 2D spectra within the search window, with bounds that skip work but never change
//! a group (the group of a full search, first check eight positions at a time).

#![forbid(unsafe_code)]

use super::transforms::BlockCoeffs;
use super::x86::{distance_at_most_dispatch, low_check_dispatch};
use super::{recycled, Geometry, Scratch, StepParams};
use rayon::prelude::*;

/// Squared L2 distance with eight partial sums (vectorises; fixed order, so deterministic).
#[cfg(test)]
pub(super) fn squared_distance(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for j in 0..8 {
            let d = x[j] - y[j];
            acc[j] += d * d;
        }
    }
    let mut tail = 0.0f32;
    for (x, y) in ra.iter().zip(rb) {
        tail += (x - y) * (x - y);
    }
    acc.iter().sum::<f32>() + tail
}

/// [`squared_distance`] when it is at most `limit`, else `None`, possibly without summing
/// every coefficient: the eight partial sums only grow (non-negative terms, and rounding is
/// monotone), so once their total over the first half of the chunks exceeds `limit`, so does
/// the full distance. Distances at or below `limit` are the same bits as [`squared_distance`].
#[inline(always)]
pub(super) fn squared_distance_at_most(a: &[f32], b: &[f32], limit: f32) -> Option<f32> {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    let check_after = a.len() / 16;
    for (chunk, (x, y)) in ca.zip(cb).enumerate() {
        if chunk == check_after && check_after > 0 && acc.iter().sum::<f32>() > limit {
            return None;
        }
        for j in 0..8 {
            let d = x[j] - y[j];
            acc[j] += d * d;
        }
    }
    let mut tail = 0.0f32;
    for (x, y) in ra.iter().zip(rb) {
        tail += (x - y) * (x - y);
    }
    let d = acc.iter().sum::<f32>() + tail;
    (d <= limit).then_some(d)
}

/// [`squared_distance_at_most`], with 8 × 8 blocks (64 coefficients, the default) unrolled
/// and checked against `limit` after the first two rows of coefficients as well (the low
/// vertical frequencies, where most of a mismatch shows): the same bits, or `None` under the
/// same condition (a partial sum of non-negative terms, summed over the lanes in the same
/// order as the full one, only grows).
///
/// `two_rows`: the sum after the first two rows when the caller has it already (the
/// [`low_partial_distances`] lane of this candidate: the same bits), so that the check
/// after two rows compares it instead of totalling the lanes again.
#[inline(always)]
pub(super) fn distance_at_most(
    a: &[f32],
    b: &[f32],
    limit: f32,
    two_rows: Option<f32>,
) -> Option<f32> {
    if let (Ok(a), Ok(b)) = (<&[f32; 64]>::try_from(a), <&[f32; 64]>::try_from(b)) {
        let mut acc = [0.0f32; 8];
        for chunk in 0..8 {
            let early = match chunk {
                2 => Some(two_rows.unwrap_or_else(|| acc.iter().sum::<f32>())),
                4 => Some(acc.iter().sum::<f32>()),
                _ => None,
            };
            if early.is_some_and(|e| e > limit) {
                return None;
            }
            for j in 0..8 {
                let d = a[chunk * 8 + j] - b[chunk * 8 + j];
                acc[j] += d * d;
            }
        }
        // `+ 0.0`: the empty tail of the general path.
        let d = acc.iter().sum::<f32>() + 0.0;
        return (d <= limit).then_some(d);
    }
    squared_distance_at_most(a, b, limit)
}

/// Coefficients per block in [`LowPlanes`]: the first two rows of an 8 × 8 block's DCT.
pub(super) const LOW_COEFFS: usize = 16;

/// `planes[(y·LOW_COEFFS + k)·stride + x]`: coefficient k < [`LOW_COEFFS`] of the block at
/// position (y, x) (`stride` = positions per row + 8, the padding zero), so that eight
/// consecutive positions of a row are read as lanes.
pub(super) struct LowPlanes {
    pub(super) planes: Vec<f32>,
    pub(super) stride: usize,
}

/// The [`LowPlanes`] of `coeffs` for 8 × 8 blocks, `None` for other sizes.
#[cfg(test)]
pub(super) fn low_planes(coeffs: &BlockCoeffs, geo: &Geometry) -> Option<LowPlanes> {
    low_planes_in(Vec::new(), coeffs, geo)
}

/// [`low_planes`] in `buffer`'s allocation ([`super::Bm3dBuffers`]).
pub(super) fn low_planes_in(
    buffer: Vec<f32>,
    coeffs: &BlockCoeffs,
    geo: &Geometry,
) -> Option<LowPlanes> {
    if coeffs.n2 != 64 {
        return None;
    }
    let pw = geo.pw;
    let stride = pw + LANES8;
    let mut planes = recycled(buffer, geo.ph * LOW_COEFFS * stride, false);
    planes
        .par_chunks_mut(LOW_COEFFS * stride)
        .zip(coeffs.coefficients().par_chunks(pw * 64))
        .for_each(|(rows, blocks)| {
            for (x, block) in blocks.chunks_exact(64).enumerate() {
                for (k, &v) in block[..LOW_COEFFS].iter().enumerate() {
                    rows[k * stride + x] = v;
                }
            }
            // The padding (a recycled buffer holds old values there).
            for row in rows.chunks_exact_mut(stride) {
                row[pw..].fill(0.0);
            }
        });
    Some(LowPlanes { planes, stride })
}

/// Lanes of the first matching check (eight f32: one AVX2 register).
pub(super) const LANES8: usize = 8;

/// For the eight block positions (y, x..x + 8), the partial distance to `reference` that
/// [`distance_at_most`] compares with its limit after two rows of coefficients: per lane,
/// `acc[j] = (r[j] − c[j])² + (r[j+8] − c[j+8])²`, summed over j in order. The same operations
/// on the same values, so the same bits, with the positions as vector lanes.
#[inline(always)]
pub(super) fn low_partial_distances(
    low: &LowPlanes,
    reference: &[f32],
    y: usize,
    x: usize,
) -> [f32; LANES8] {
    let mut sum = [0.0f32; LANES8];
    let row = y * LOW_COEFFS * low.stride + x;
    for j in 0..8 {
        let at = row + j * low.stride;
        let c0: &[f32; LANES8] = low.planes[at..at + LANES8].try_into().expect("lanes");
        let at = row + (j + 8) * low.stride;
        let c1: &[f32; LANES8] = low.planes[at..at + LANES8].try_into().expect("lanes");
        let (r0, r1) = (reference[j], reference[j + 8]);
        for l in 0..LANES8 {
            let d0 = r0 - c0[l];
            let d1 = r1 - c1[l];
            let acc = d0 * d0 + d1 * d1;
            sum[l] = if j == 0 { acc } else { sum[l] + acc };
        }
    }
    sum
}

/// The first check of [`find_group`] for the eight block positions (y, x..x + 8): a mask of
/// the lanes whose [`low_partial_distances`] are at most `bound` (bit l for position x + l),
/// and those partials. The portable reference of `x86::low_check_avx2` (chosen by
/// `x86::low_check_dispatch`).
///
/// The first row of coefficients is checked before the second: per lane, Σ_j (r[j] − c[j])²
/// summed over j in order is the same sum with smaller terms (each lane's two-row term is the
/// one-row square plus a non-negative one, and rounding is monotone), so it is at most the
/// two-row partial, which is at most the full distance. When no lane passes it, the chunk is
/// done after eight coefficients instead of sixteen (mask 0; the partials are then unused
/// zeros). The mask is the same either way.
#[inline(always)]
pub(super) fn low_check(
    low: &LowPlanes,
    reference: &[f32],
    y: usize,
    x: usize,
    bound: f32,
) -> (u32, [f32; LANES8]) {
    let row = y * LOW_COEFFS * low.stride + x;
    let mut first = [0.0f32; LANES8];
    for (j, &r) in reference[..8].iter().enumerate() {
        let at = row + j * low.stride;
        let c0: &[f32; LANES8] = low.planes[at..at + LANES8].try_into().expect("lanes");
        for l in 0..LANES8 {
            let d0 = r - c0[l];
            first[l] = if j == 0 { d0 * d0 } else { first[l] + d0 * d0 };
        }
    }
    if !first.iter().any(|&f| f <= bound) {
        return (0, [0.0; LANES8]);
    }
    let partial = low_partial_distances(low, reference, y, x);
    let mut mask = 0u32;
    for (l, &part) in partial.iter().enumerate() {
        mask |= ((part <= bound) as u32) << l;
    }
    (mask, partial)
}

/// Fills `s.group` with the reference position followed by its best matches (distance ≤ τ,
/// ascending distance, ties by position), truncated to a power of two ≤ `max_group`
/// (the grouping of TIP 2007 §III-A.1 / §III-B.1, Eq. 3 / Eq. 6).
///
/// Only the best `max_group − 1` matches can enter the group, so a candidate farther than the
/// `(max_group − 1)`-th best distance known so far need not be summed to the end: the scan
/// keeps that bound (from the previous reference's group members, which mostly lie in this
/// window too ([`warm_bound`]), and then from the matches found), and [`distance_at_most`]
/// stops once a partial sum exceeds it. The bound is always the distance of an actual
/// candidate, so every candidate the group can take is still summed in full: the group is the
/// one of a full scan (the test `bounded_search_finds_the_full_search_group` compares them).
#[inline(always)]
pub(super) fn find_group<const AVX2: bool>(
    p: &StepParams,
    geo: &Geometry,
    yr: usize,
    xr: usize,
    s: &mut Scratch,
) {
    let hw = geo.half_window;
    let pw = geo.pw;
    let ref_pos = yr * pw + xr;
    let reference = p.matching.block(ref_pos);
    s.candidates.clear();
    let window = Window {
        ref_pos,
        pw,
        ys: (yr.saturating_sub(hw), (yr + hw).min(geo.ph - 1)),
        xs: (xr.saturating_sub(hw), (xr + hw).min(pw - 1)),
    };
    let keep = p.max_group - 1;
    s.group.clear();
    s.group.push(ref_pos);
    if keep == 0 {
        return;
    }
    let mut bound = warm_bound::<AVX2>(p, reference, &window, keep, s);
    // Every position of the window; the list is cut back to the best `keep` (and the bound
    // lowered to the last of them) whenever it reaches `cap`.
    let search = Search {
        reference,
        matching: p.matching,
        keep,
        cap: 2 * keep.max(8),
    };
    // Rows from the reference's out: its best matches usually lie near it, so the bound falls
    // early and fewer candidates are summed in full (any order gives the same group).
    match p.low {
        Some(low) => scan_checked::<AVX2>(&search, low, &window, yr, &mut bound, s),
        None => {
            let ((y0, y1), (x0, x1)) = (window.ys, window.xs);
            for y in centre_out(yr, y0, y1) {
                for x in x0..=x1 {
                    let pos = y * pw + x;
                    if pos != ref_pos {
                        search.consider::<AVX2>(pos, None, &mut bound, &mut s.candidates);
                    }
                }
            }
        }
    }
    take_best(p.max_group, keep, s);
}

/// The search window of one reference block: its position, the positions per row, and the
/// rows `ys` and columns `xs` of block positions it spans (inclusive).
struct Window {
    ref_pos: usize,
    pw: usize,
    ys: (usize, usize),
    xs: (usize, usize),
}

/// The first bound of [`find_group`]'s scan: `p.tau_sum`, or the keep-th smallest of the
/// previous reference's group members' distances to this reference when enough of them lie in
/// this window (their distances in `s.warm`).
#[inline(always)]
fn warm_bound<const AVX2: bool>(
    p: &StepParams,
    reference: &[f32],
    window: &Window,
    keep: usize,
    s: &mut Scratch,
) -> f32 {
    let (pw, ref_pos) = (window.pw, window.ref_pos);
    let ((y0, y1), (x0, x1)) = (window.ys, window.xs);
    let mut bound = p.tau_sum;
    let in_window = |pos: usize| {
        let (y, x) = (pos / pw, pos % pw);
        pos != ref_pos && (y0..=y1).contains(&y) && (x0..=x1).contains(&x)
    };
    s.warm.clear();
    for &pos in &s.previous_group {
        if in_window(pos) {
            if let Some(d) =
                distance_at_most_dispatch::<AVX2>(reference, p.matching.block(pos), bound, None)
            {
                s.warm.push(d);
            }
        }
    }
    if s.warm.len() >= keep {
        s.warm.select_nth_unstable_by(keep - 1, f32::total_cmp);
        bound = bound.min(s.warm[keep - 1]);
    }
    bound
}

/// [`find_group`]'s scan of the window with the first check on [`LowPlanes`] (8 × 8 blocks):
/// rows from the reference's out, eight positions at a time; the candidates that pass join
/// through [`Search::consider`].
///
/// Each row's first check runs before the candidates of the row checked before it are summed,
/// so that their blocks' prefetches have a row's work to arrive (summed right after their own
/// row's check, the first load of each stalled: about 10 % of the step's time, perf). The
/// check then uses an older bound, which lets more lanes pass, but `consider` compares every
/// one's two-row partial with the current bound first: the same candidates join in the same
/// order.
#[inline(always)]
fn scan_checked<const AVX2: bool>(
    search: &Search,
    low: &LowPlanes,
    window: &Window,
    yr: usize,
    bound: &mut f32,
    s: &mut Scratch,
) {
    let (pw, ref_pos) = (window.pw, window.ref_pos);
    let ((y0, y1), (x0, x1)) = (window.ys, window.xs);
    let reference = search.reference;
    s.pending.clear();
    for y in centre_out(yr, y0, y1) {
        s.checked.clear();
        // Eight positions at a time through the first check (the tail's extra lanes
        // read the next positions or the padding and are not used).
        let mut x = x0;
        while x <= x1 {
            // Lanes that pass the check, as bits.
            let (mut pass, partial) = low_check_dispatch::<AVX2>(low, reference, y, x, *bound);
            pass &= (1u32 << (x1 + 1 - x).min(LANES8)) - 1;
            if AVX2 {
                prefetch_blocks(search.matching, y * pw + x, pass);
            }
            while pass != 0 {
                let lane = pass.trailing_zeros() as usize;
                let pos = y * pw + x + lane;
                pass &= pass - 1;
                if pos != ref_pos {
                    // The lane's partial is the candidate's sum after two rows.
                    s.checked.push((pos as u32, partial[lane]));
                }
            }
            x += LANES8;
        }
        for &(pos, two_rows) in &s.pending {
            search.consider::<AVX2>(pos as usize, Some(two_rows), bound, &mut s.candidates);
        }
        std::mem::swap(&mut s.pending, &mut s.checked);
    }
    for &(pos, two_rows) in &s.pending {
        search.consider::<AVX2>(pos as usize, Some(two_rows), bound, &mut s.candidates);
    }
}

/// The end of [`find_group`]: the best `keep` candidates in (distance, position) order after
/// the reference, cut to a power of two ≤ `max_group`; the group is kept as the next
/// reference's `previous_group`.
#[inline(always)]
fn take_best(max_group: usize, keep: usize, s: &mut Scratch) {
    let order = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
    if s.candidates.len() > keep {
        s.candidates.select_nth_unstable_by(keep - 1, order);
        s.candidates.truncate(keep);
    }
    s.candidates.sort_unstable_by(order);
    let size = prev_power_of_two(1 + s.candidates.len()).min(prev_power_of_two(max_group));
    s.group.extend(
        s.candidates[..size - 1]
            .iter()
            .map(|&(_, pos)| pos as usize),
    );
    s.previous_group.clear();
    s.previous_group.extend_from_slice(&s.group);
}

/// `y0..=y1` (which holds `centre`) in the order `centre, centre + 1, centre − 1, centre + 2,
/// …`, then the rest of the longer side.
pub(super) fn centre_out(centre: usize, y0: usize, y1: usize) -> impl Iterator<Item = usize> {
    let below = (centre + 1..=y1).map(Some).chain(std::iter::repeat(None));
    let above = (y0..centre).rev().map(Some).chain(std::iter::repeat(None));
    std::iter::once(centre).chain(
        below
            .zip(above)
            .take_while(|(b, a)| b.is_some() || a.is_some())
            .flat_map(|(b, a)| b.into_iter().chain(a)),
    )
}

/// Asks the CPU to start loading the coefficients of the positions `first + l` for every bit
/// `l` of `lanes` (all of them before any is summed, so that their cache misses overlap). A
/// hint only: no result depends on it.
#[inline(always)]
fn prefetch_blocks(coeffs: &BlockCoeffs, first: usize, lanes: u32) {
    let mut bits = lanes;
    while bits != 0 {
        let pos = first + bits.trailing_zeros() as usize;
        bits &= bits - 1;
        crate::cpu::prefetch(coeffs.block(pos));
    }
}

/// What [`find_group`]'s scan compares each candidate with: the reference's coefficients, the
/// matching coefficients of every position, the matches that can enter the group (`keep`),
/// and the length `cap` at which the candidate list is cut back to them.
struct Search<'a> {
    reference: &'a [f32],
    matching: &'a BlockCoeffs,
    keep: usize,
    cap: usize,
}

impl Search<'_> {
    /// One candidate of [`find_group`]'s scan: its distance to the reference when at most
    /// `bound` joins `candidates`, which are cut back to the best `keep` (and `bound` lowered
    /// to the last of them) whenever they reach `cap`. A function rather than a closure, so
    /// that it is inlined into the AVX2 build (the closure was compiled on its own, without
    /// AVX2). `two_rows`: the candidate's distance after two rows when known
    /// ([`distance_at_most`]).
    #[inline(always)]
    fn consider<const AVX2: bool>(
        &self,
        pos: usize,
        two_rows: Option<f32>,
        bound: &mut f32,
        candidates: &mut Vec<(f32, u32)>,
    ) {
        let block = self.matching.block(pos);
        if let Some(d) = distance_at_most_dispatch::<AVX2>(self.reference, block, *bound, two_rows)
        {
            candidates.push((d, pos as u32));
            if candidates.len() == self.cap {
                *bound = cut_candidates(candidates, self.keep);
            }
        }
    }
}

/// Keeps the best `keep` of `candidates` (ascending distance, ties by position: the order of
/// [`find_group`]) and returns the last one's distance.
#[inline(never)]
fn cut_candidates(candidates: &mut Vec<(f32, u32)>, keep: usize) -> f32 {
    let order = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
    candidates.select_nth_unstable_by(keep - 1, order);
    candidates.truncate(keep);
    candidates[keep - 1].0
}

/// Largest power of two ≤ `k` (`k ≥ 1`).
pub(super) fn prev_power_of_two(k: usize) -> usize {
    1 << (usize::BITS - 1 - k.leading_zeros())
}
