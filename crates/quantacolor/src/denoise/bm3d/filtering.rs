//! Collaborative filtering of a group (Dabov et al., TIP 2007): the 3D transform (the blocks'
//! 2D DCT spectra, then 1D Haar along the group), hard thresholding (Step 1, §III-A, Eq. 5) or
//! empirical Wiener shrinkage (Step 2, §III-B, Eq. 7–8), the inverse, and the aggregation weight.

#![forbid(unsafe_code)]

use super::transforms::{
    haar_forward, haar_forward_lanes, haar_inverse, haar_inverse_lanes, MAX_LANE_GROUP,
};
use super::x86::{hard_threshold_dispatch, wiener_shrink_dispatch};
use super::{Geometry, Scratch, StepParams, Transforms};

/// Relative σ of every 2D DCT coefficient (row-major `n × n`) of white noise smoothed by a
/// Gaussian of std `correlation_px`: |K̂(ω_u, ω_v)| = exp(−(ω_u² + ω_v²)·s²/2) at the basis
/// frequencies ω_k = πk/n, scaled so that the mean square is 1 (Parseval: the per-pixel
/// variance is unchanged). All ones for white noise.
pub(super) fn coefficient_profile(n: usize, correlation_px: f32) -> Vec<f32> {
    let s2 = (correlation_px as f64).powi(2);
    let omega2 = |k: usize| (std::f64::consts::PI * k as f64 / n as f64).powi(2);
    let power: Vec<f64> = (0..n * n)
        .map(|k| (-(omega2(k / n) + omega2(k % n)) * s2).exp())
        .collect();
    let mean = power.iter().sum::<f64>() / power.len() as f64;
    power.iter().map(|p| (p / mean).sqrt() as f32).collect()
}

/// Filters channel `c` of the group in `s` (found by [`super::grouping::find_group`]) with
/// noise σ `sigma`: its members' 2D spectra into `s.noisy_group`, the shrinkage of Step 1 or,
/// when `p.basic` is given, Step 2 ([`filter_group`]), and returns the group's aggregation
/// weight.
#[inline(always)]
pub(super) fn filter_channel<const AVX2: bool>(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    c: usize,
    sigma: f32,
    s: &mut Scratch,
) -> f32 {
    let n = geo.n;
    let n2 = n * n;
    let m = s.group.len();
    for (g, &pos) in s.group.iter().enumerate() {
        p.noisy[c].block_into(
            pos,
            geo,
            tr,
            (&mut s.pixels, &mut s.tmp),
            &mut s.noisy_group[g * n2..(g + 1) * n2],
        );
    }
    let group = &mut s.noisy_group[..m * n2];
    let profile = &p.profiles[c];
    match p.basic {
        None => {
            // Step 1: hard thresholding of the 3D spectrum (TIP 2007 §III-A, Eq. 5) and
            // weight 1/(σ²·N_har) (Eq. 10).
            // With correlated noise each 2D coefficient k has its own σ·profile[k], and
            // N_har becomes the retained coefficients' summed relative variance.
            let threshold = p.lambda_3d * sigma;
            let retained =
                filter_group::<AVX2, false>(group, &mut [], m, profile, threshold, &mut s.haar_tmp);
            if retained > 0.0 {
                1.0 / (sigma * sigma * retained)
            } else {
                1.0
            }
        }
        Some(basic) => {
            // Step 2: empirical Wiener shrinkage W = |B|²/(|B|² + σ²) (§III-B, Eq. 7–8) and
            // weight 1/(σ²·‖W‖²) (Eq. 12).
            for (g, &pos) in s.group.iter().enumerate() {
                basic[c].block_into(
                    pos,
                    geo,
                    tr,
                    (&mut s.pixels, &mut s.tmp),
                    &mut s.basic_group[g * n2..(g + 1) * n2],
                );
            }
            let bgroup = &mut s.basic_group[..m * n2];
            let s2 = sigma * sigma;
            let w_norm = filter_group::<AVX2, true>(group, bgroup, m, profile, s2, &mut s.haar_tmp);
            if w_norm > 0.0 {
                1.0 / (s2 * w_norm)
            } else {
                1.0 / s2
            }
        }
    }
}

/// The collaborative filtering of a group in its blocks' 2D spectra (`m` stacked blocks of
/// `profile.len()` coefficients): the 1D Haar transform along the group, the shrinkage of the
/// 3D spectrum, hard thresholding at `param`·q ([`hard_threshold`]) or, when `WIENER`, the
/// empirical Wiener shrinkage with noise variance `param` and the basic estimate's group
/// `basic` in the same 2D spectra ([`wiener_shrink`]; `basic` is overwritten), and the inverse
/// Haar transform. Returns the shrinkage's sum (N_har or ‖W‖²). `tmp`: scratch of the group's
/// size.
///
/// For 8 × 8 blocks in groups of up to [`MAX_LANE_GROUP`] (the defaults) all three run on
/// eight coefficients of every member at a time ([`filter_group_lanes`]) instead of three
/// passes over the group: the same operations on the same values, and the shrinkage's terms
/// summed in the same order, so the same bits.
#[inline(always)]
pub(super) fn filter_group<const AVX2: bool, const WIENER: bool>(
    group: &mut [f32],
    basic: &mut [f32],
    m: usize,
    profile: &[f32],
    param: f32,
    tmp: &mut [f32],
) -> f32 {
    if let Ok(profile) = <&[f32; 64]>::try_from(profile) {
        // Sizes known to the compiler, as in `haar_lanes` (called directly: a closure here was
        // compiled on its own, without AVX2 and out of line).
        let (g, b, q, t) = (&mut *group, &*basic, profile, &mut *tmp);
        match m {
            1 => return filter_group_sized::<WIENER, 1>(g, b, q, param, t),
            2 => return filter_group_sized::<WIENER, 2>(g, b, q, param, t),
            4 => return filter_group_sized::<WIENER, 4>(g, b, q, param, t),
            8 => return filter_group_sized::<WIENER, 8>(g, b, q, param, t),
            16 => return filter_group_sized::<WIENER, 16>(g, b, q, param, t),
            32 => return filter_group_sized::<WIENER, 32>(g, b, q, param, t),
            _ => {}
        }
    }
    let n2 = profile.len();
    haar_forward(group, m, n2, tmp);
    let total = if WIENER {
        haar_forward(basic, m, n2, tmp);
        wiener_shrink_dispatch::<AVX2>(group, basic, profile, param)
    } else {
        hard_threshold_dispatch::<AVX2>(group, profile, param)
    };
    haar_inverse(group, m, n2, tmp);
    total
}

/// [`filter_group_lanes`] of `M` blocks.
#[inline(always)]
fn filter_group_sized<const WIENER: bool, const M: usize>(
    group: &mut [f32],
    basic: &[f32],
    profile: &[f32; 64],
    param: f32,
    terms: &mut [f32],
) -> f32 {
    let basic_rows = if WIENER { M * 64 } else { 0 };
    filter_group_lanes::<WIENER>(
        &mut group[..M * 64],
        &basic[..basic_rows],
        M,
        profile,
        param,
        &mut terms[..M * 64],
    )
}

/// [`filter_group`] of `m` ≤ [`MAX_LANE_GROUP`] blocks of 64 coefficients, eight
/// coefficients of every member at a time (as [`haar_lanes`]): their Haar transform, their
/// shrinkage (the formulas of [`hard_threshold`] / [`wiener_shrink`], lane by lane), and the
/// inverse transform, held in stack arrays between the three. Each coefficient's term of the
/// shrinkage's sum goes to `terms` (`m·64`, the group's layout), which is summed afterwards
/// in the order of the separate pass (member by member, lane `l` taking coefficients `l`
/// mod 8), so the sum has the same bits too.
#[inline(always)]
fn filter_group_lanes<const WIENER: bool>(
    group: &mut [f32],
    basic: &[f32],
    m: usize,
    profile: &[f32; 64],
    param: f32,
    terms: &mut [f32],
) -> f32 {
    let (mut x, mut y) = ([[0.0f32; 8]; MAX_LANE_GROUP], [[0.0f32; 8]; MAX_LANE_GROUP]);
    let (mut bx, mut by) = ([[0.0f32; 8]; MAX_LANE_GROUP], [[0.0f32; 8]; MAX_LANE_GROUP]);
    let mut work = [[[0.0f32; 8]; MAX_LANE_GROUP]; 2];
    for chunk in 0..8 {
        let lanes = chunk * 8..chunk * 8 + 8;
        for (x, row) in x[..m].iter_mut().zip(group.chunks_exact(64)) {
            *x = row[lanes.clone()].try_into().expect("eight lanes");
        }
        haar_forward_lanes(&mut x, &mut y, &mut work[0], m);
        if WIENER {
            for (x, row) in bx[..m].iter_mut().zip(basic.chunks_exact(64)) {
                *x = row[lanes.clone()].try_into().expect("eight lanes");
            }
            haar_forward_lanes(&mut bx, &mut by, &mut work[0], m);
        }
        let q: &[f32; 8] = profile[lanes.clone()].try_into().expect("eight lanes");
        for ((v, b), row) in y[..m].iter_mut().zip(&by).zip(terms.chunks_exact_mut(64)) {
            let term: &mut [f32; 8] = (&mut row[lanes.clone()]).try_into().expect("eight lanes");
            for l in 0..8 {
                if WIENER {
                    let (b2, q2) = (b[l] * b[l], q[l] * q[l]);
                    let wc = b2 / (b2 + param * q2);
                    v[l] *= wc;
                    term[l] = wc * wc * q2;
                } else {
                    let keep = v[l].abs() > param * q[l];
                    v[l] = if keep { v[l] } else { 0.0 };
                    term[l] = if keep { q[l] * q[l] } else { 0.0 };
                }
            }
        }
        haar_inverse_lanes(&mut y, &mut x, &mut work, m);
        for (x, row) in x[..m].iter().zip(group.chunks_exact_mut(64)) {
            row[lanes.clone()].copy_from_slice(x);
        }
    }
    let mut sum = [0.0f32; SHRINK_LANES];
    for term in terms.chunks_exact(SHRINK_LANES) {
        for l in 0..SHRINK_LANES {
            sum[l] += term[l];
        }
    }
    lane_total(sum)
}

/// Lanes of the sums in [`hard_threshold`] and [`wiener_shrink`]: coefficient i of a group row
/// adds into lane i mod 8, and the lanes are added in order at the end (independent sums that
/// vectorise; the same result on every CPU).
pub(super) const SHRINK_LANES: usize = 8;

/// Sum of the lanes of a [`SHRINK_LANES`] accumulator, in lane order.
#[inline(always)]
pub(super) fn lane_total(lanes: [f32; SHRINK_LANES]) -> f32 {
    lanes.iter().sum()
}

/// Zeroes the coefficients of `group` (rows of `profile.len()`) with |v| ≤ `threshold`·q (q the
/// coefficient's relative σ in `profile`) and returns the retained coefficients' Σ q² (N_har,
/// TIP 2007 Eq. 10, with correlated noise).
#[inline(always)]
pub(super) fn hard_threshold(group: &mut [f32], profile: &[f32], threshold: f32) -> f32 {
    let mut lanes = [0.0f32; SHRINK_LANES];
    let shrink = |v: &mut f32, q: f32, lane: &mut f32| {
        if v.abs() > threshold * q {
            *lane += q * q;
        } else {
            *v = 0.0;
        }
    };
    for row in group.chunks_exact_mut(profile.len()) {
        let whole = row.len() - row.len() % SHRINK_LANES;
        let (row_head, row_tail) = row.split_at_mut(whole);
        let (q_head, q_tail) = profile.split_at(whole);
        for (v, q) in row_head
            .chunks_exact_mut(SHRINK_LANES)
            .zip(q_head.chunks_exact(SHRINK_LANES))
        {
            let v: &mut [f32; SHRINK_LANES] = v.try_into().expect("lane chunk");
            let q: &[f32; SHRINK_LANES] = q.try_into().expect("lane chunk");
            for l in 0..SHRINK_LANES {
                let keep = v[l].abs() > threshold * q[l];
                v[l] = if keep { v[l] } else { 0.0 };
                lanes[l] += if keep { q[l] * q[l] } else { 0.0 };
            }
        }
        for (l, (v, &q)) in row_tail.iter_mut().zip(q_tail).enumerate() {
            shrink(v, q, &mut lanes[l]);
        }
    }
    lane_total(lanes)
}

/// Empirical Wiener shrinkage of `group` (rows of `profile.len()`) with the basic estimate's
/// spectrum `basic`: v ·= W, W = B²/(B² + σ²q²) (TIP 2007 Eq. 7–8, each coefficient's own
/// σ·q); returns Σ W²q² (‖W‖² of Eq. 12, with correlated noise).
#[inline(always)]
pub(super) fn wiener_shrink(group: &mut [f32], basic: &[f32], profile: &[f32], s2: f32) -> f32 {
    let mut lanes = [0.0f32; SHRINK_LANES];
    let shrink = |v: &mut f32, b: f32, q: f32, lane: &mut f32| {
        let (b2, q2) = (b * b, q * q);
        let wc = b2 / (b2 + s2 * q2);
        *v *= wc;
        *lane += wc * wc * q2;
    };
    let n2 = profile.len();
    for (row, brow) in group.chunks_exact_mut(n2).zip(basic.chunks_exact(n2)) {
        let whole = n2 - n2 % SHRINK_LANES;
        let (row_head, row_tail) = row.split_at_mut(whole);
        let (b_head, b_tail) = brow.split_at(whole);
        let (q_head, q_tail) = profile.split_at(whole);
        for ((v, b), q) in row_head
            .chunks_exact_mut(SHRINK_LANES)
            .zip(b_head.chunks_exact(SHRINK_LANES))
            .zip(q_head.chunks_exact(SHRINK_LANES))
        {
            let v: &mut [f32; SHRINK_LANES] = v.try_into().expect("lane chunk");
            let b: &[f32; SHRINK_LANES] = b.try_into().expect("lane chunk");
            let q: &[f32; SHRINK_LANES] = q.try_into().expect("lane chunk");
            let b2: [f32; SHRINK_LANES] = std::array::from_fn(|l| b[l] * b[l]);
            let q2: [f32; SHRINK_LANES] = std::array::from_fn(|l| q[l] * q[l]);
            let wc: [f32; SHRINK_LANES] = std::array::from_fn(|l| b2[l] / (b2[l] + s2 * q2[l]));
            for l in 0..SHRINK_LANES {
                v[l] *= wc[l];
                lanes[l] += wc[l] * wc[l] * q2[l];
            }
        }
        for (l, ((v, &b), &q)) in row_tail.iter_mut().zip(b_tail).zip(q_tail).enumerate() {
            shrink(v, b, q, &mut lanes[l]);
        }
    }
    lane_total(lanes)
}
