//! The kernel weights of the regression: exponentials of the sparsest channel's quadratic
//! form, shared or raised to a whole power by the channels whose factor is a multiple of it
//! (this project's speed heuristic, [`snap_scales`]).
#![forbid(unsafe_code)]

use super::*;

/// Relative difference between a channel's kernel factor and a whole multiple of the sparsest
/// channel's within which the channel takes that multiple ([`snap_scales`]).
const SNAP_SCALE_TOLERANCE: f32 = 0.02;
/// Largest multiple of the sparsest channel's kernel factor that a channel is snapped to: its
/// weights are that power of the sparsest channel's ([`lane_power`], one multiplication per bit
/// of the multiple and one per set bit after the first).
pub(super) const MAX_SNAP_MULTIPLE: u32 = 32;

/// `scales` (the kernel scale of R, G, B, W, [`KernelField::channel_scale`] to the power α;
/// 0: absent) with the scale of every channel whose kernel factor 1/scale is within
/// [`SNAP_SCALE_TOLERANCE`] of a whole multiple k of the sparsest channel's (the largest
/// scale, the first of equal ones) set to that channel's scale / k, and each channel's k (0:
/// not snapped, and the sparsest channel itself). The kernel weight exp(−½·k·q) of a snapped
/// channel is then the k-th power of the sparsest channel's exp(−½·q), a few multiplications
/// instead of an exponential ([`gather_row_generic`]); k = 1 (a pattern with as many sites of
/// two colours give or take a few) shares the weights. On /tmp/cap10k's CFA (7,936 R, 15,748 G,
/// 7,812 B, 94,488 W sites) R, G and W take 1, 2 and 12 times B's factor: one exponential per
/// bin instead of four. This project's heuristic: it changes those kernels' widths by at most
/// 1 % (at most 2 % of their factors).
pub(super) fn snap_scales(mut scales: [f32; 4]) -> ([f32; 4], [u32; 4]) {
    let mut multiples = [0u32; 4];
    let Some(base) = (0..4)
        .filter(|&ch| scales[ch] > 0.0)
        .fold(None, |best: Option<usize>, ch| match best {
            Some(b) if scales[b] >= scales[ch] => Some(b),
            _ => Some(ch),
        })
    else {
        return (scales, multiples);
    };
    let sparsest = scales[base];
    for ch in 0..4 {
        if ch == base || scales[ch] <= 0.0 {
            continue;
        }
        let ratio = sparsest / scales[ch];
        let k = ratio.round();
        if (1.0..=MAX_SNAP_MULTIPLE as f32).contains(&k)
            && (ratio - k).abs() <= SNAP_SCALE_TOLERANCE * k
        {
            scales[ch] = sparsest / k;
            multiples[ch] = k as u32;
        }
    }
    (scales, multiples)
}

/// `w`^`k` lane-wise, by squaring (`k` ≥ 1): the kernel weights of a channel whose factor is k
/// times that of the channel with weights `w` ([`snap_scales`]).
#[inline(always)]
pub(super) fn lane_power(w: [f32; LANES], k: u32) -> [f32; LANES] {
    let mut result: Option<[f32; LANES]> = None;
    let (mut square, mut k) = (w, k);
    loop {
        if k & 1 == 1 {
            result = Some(match result {
                None => square,
                Some(r) => std::array::from_fn(|i| r[i] * square[i]),
            });
        }
        k >>= 1;
        if k == 0 {
            break;
        }
        square = std::array::from_fn(|i| square[i] * square[i]);
    }
    result.unwrap_or([1.0; LANES])
}

/// The kernel weights of every channel that makes its own (`plan.makers()`: exp(−q·factor/2)
/// below the cutoff) over its groups `ranges`, then of the channels whose factor is a multiple
/// of the base's (powers of the base's weights, which cover every group: the base's ellipse is
/// the widest).
#[inline(always)]
pub(super) fn make_weights(
    g: &Gather,
    plan: &ChannelPlan,
    ranges: &[(usize, usize); 4],
    quads: &[f32],
    weights: &mut [Vec<f32>; 4],
) {
    for &ch in plan.makers() {
        let (first, end) = ranges[ch];
        let factor = g.inv_scale[ch];
        let weights = &mut weights[ch];
        for group in first..end {
            let at = group * LANES;
            // Local lanes, so that the compiler sees eight independent values.
            let quad: [f32; LANES] = quads[at..at + LANES].try_into().expect("lanes");
            let mut lanes = [0.0f32; LANES];
            for i in 0..LANES {
                let q = quad[i] * factor;
                let e = fastmath::exp(-0.5 * q);
                lanes[i] = if q < g.cutoff { e } else { 0.0 };
            }
            weights[at..at + LANES].copy_from_slice(&lanes);
        }
    }
    for &(ch, k) in plan.powered() {
        let (first, end) = ranges[ch];
        let mut own = std::mem::take(&mut weights[ch]);
        let base = &weights[g.base];
        for group in first..end {
            let at = group * LANES;
            let quad: [f32; LANES] = quads[at..at + LANES].try_into().expect("lanes");
            let w: [f32; LANES] = base[at..at + LANES].try_into().expect("lanes");
            let lanes = power_weights(g, ch, &quad, w, k);
            own[at..at + LANES].copy_from_slice(&lanes);
        }
        weights[ch] = own;
    }
}

/// What the channels of a [`Gather`] do in every bin row of [`gather_row_generic`], the same
/// for every pixel: which channels make their weights with exponentials, which take powers of
/// the base's, and which run over the groups together (those that share weights and ellipse,
/// hence groups), each list in channel order.
pub(super) struct ChannelPlan {
    present: [usize; 4],
    present_len: usize,
    makers: [usize; 4],
    makers_len: usize,
    powered: [(usize, u32); 4],
    powered_len: usize,
    /// Channels of pass i: `pass_members[pass_start[i]..pass_start[i + 1]]`.
    pass_members: [usize; 4],
    pass_start: [usize; 5],
    passes_len: usize,
}

impl ChannelPlan {
    /// The plan of `g` whose channels use the ellipses `own` ([`gather_row_generic`]).
    pub(super) fn new(g: &Gather, own: &[Option<usize>; 4]) -> ChannelPlan {
        let mut plan = ChannelPlan {
            present: [0; 4],
            present_len: 0,
            makers: [0; 4],
            makers_len: 0,
            powered: [(0, 0); 4],
            powered_len: 0,
            pass_members: [0; 4],
            pass_start: [0; 5],
            passes_len: 0,
        };
        let mut placed = [false; 4];
        for ch in (0..4).filter(|&ch| g.present[ch]) {
            plan.present[plan.present_len] = ch;
            plan.present_len += 1;
            if g.source[ch] == ch && g.power[ch] == 0 {
                plan.makers[plan.makers_len] = ch;
                plan.makers_len += 1;
            }
            if g.power[ch] != 0 {
                plan.powered[plan.powered_len] = (ch, g.power[ch]);
                plan.powered_len += 1;
            }
            if placed[ch] {
                continue;
            }
            let mut n = plan.pass_start[plan.passes_len];
            for other in ch..4 {
                if g.present[other]
                    && !placed[other]
                    && g.source[other] == g.source[ch]
                    && own[other] == own[ch]
                {
                    plan.pass_members[n] = other;
                    n += 1;
                    placed[other] = true;
                }
            }
            plan.passes_len += 1;
            plan.pass_start[plan.passes_len] = n;
        }
        plan
    }

    pub(super) fn present(&self) -> impl Iterator<Item = usize> + '_ {
        self.present[..self.present_len].iter().copied()
    }

    pub(super) fn makers(&self) -> &[usize] {
        &self.makers[..self.makers_len]
    }

    pub(super) fn powered(&self) -> &[(usize, u32)] {
        &self.powered[..self.powered_len]
    }

    pub(super) fn passes(&self) -> impl Iterator<Item = &[usize]> + '_ {
        (0..self.passes_len).map(|i| &self.pass_members[self.pass_start[i]..self.pass_start[i + 1]])
    }
}

/// Weights of channel `ch` whose factor is `k` times the base channel's, from the base's
/// weights `w` of bins with quadratic forms `quad`: `w`^k inside the channel's cutoff, 0
/// outside ([`gather_row_generic`]).
#[inline(always)]
pub(super) fn power_weights(
    g: &Gather,
    ch: usize,
    quad: &[f32; LANES],
    w: [f32; LANES],
    k: u32,
) -> [f32; LANES] {
    let powers = lane_power(w, k);
    let factor = g.inv_scale[ch];
    std::array::from_fn(|i| {
        if quad[i] * factor < g.cutoff {
            powers[i]
        } else {
            0.0
        }
    })
}
