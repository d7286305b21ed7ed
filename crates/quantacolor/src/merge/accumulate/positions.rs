//! Where a sensor site's scene point sits on the reference grid: the inverse of its
//! sub-block's dense flow by fixed-point iteration, and the roundings the phase bins take.

use super::*;

/// Bilinear sample of the interleaved (H, W, 2) `flow` at real position (y, x), clamped.
#[inline]
fn flow_bilinear(flow: &[f32], h: usize, w: usize, y: f32, x: f32) -> [f32; 2] {
    let y = y.clamp(0.0, (h - 1) as f32);
    let x = x.clamp(0.0, (w - 1) as f32);
    // Truncation is the floor of a non-negative value (and 0 for NaN, as `floor` then a cast
    // gives): no libm call in the hot loop.
    let y0 = (y as usize).min(h.saturating_sub(2));
    let x0 = (x as usize).min(w.saturating_sub(2));
    let (y1, x1) = ((y0 + 1).min(h - 1), (x0 + 1).min(w - 1));
    let (fy, fx) = (y - y0 as f32, x - x0 as f32);
    let mut out = [0.0; 2];
    for (c, o) in out.iter_mut().enumerate() {
        let at = |yy: usize, xx: usize| flow[(yy * w + xx) * 2 + c];
        let top = at(y0, x0) * (1.0 - fx) + at(y0, x1) * fx;
        let bottom = at(y1, x0) * (1.0 - fx) + at(y1, x1) * fx;
        *o = top * (1.0 - fy) + bottom * fy;
    }
    out
}

/// `v.round()` (half away from zero) without the libm call that a target without SSE4.1
/// makes of it: the same value for every finite `v` (up to the sign of a zero result). The
/// step away from the truncation is taken without a branch: sub-pixel positions make it a coin
/// toss that a branch predictor misses half of the time.
#[inline]
pub(super) fn round_half_away(v: f32) -> f32 {
    if v.is_nan() || v.abs() >= 8_388_608.0 {
        // NaN, infinite or already integral (|v| >= 2^23).
        return v.round();
    }
    let t = (v as i32) as f32;
    let frac = v - t; // exact
    t + ((frac >= 0.5) as i32 - (frac <= -0.5) as i32) as f32
}

/// `v.max(0.0).min(hi) as i32` (NaN gives 0, as `as` does) for a finite `hi` in [0, 2³¹):
/// without the saturation checks of `as`, which keep the compiler from converting eight lanes
/// with one vector instruction. The same value as `v as i32` for every `v` in [0, hi] and NaN.
#[inline(always)]
pub(super) fn index_in(v: f32, hi: f32) -> i32 {
    debug_assert!((0.0..2_147_483_648.0).contains(&hi));
    // `max` returns 0 for NaN: the value is finite and in [0, hi] here.
    let v = v.max(0.0).min(hi);
    // SAFETY: v is finite, non-negative and below 2³¹, so its truncation is an i32.
    unsafe { v.to_int_unchecked::<i32>() }
}

/// [`round_half_away`] from the truncation `v.trunc()` (one vector instruction where the CPU
/// has SSE4.1, e.g. in the AVX2 code; a libm call elsewhere): the same value for every `v`
/// up to the sign of a zero result (NaN and infinities included: their truncation is
/// themselves and their fraction NaN).
#[inline(always)]
pub(super) fn round_half_away_trunc(v: f32) -> f32 {
    let t = v.trunc();
    let frac = v - t;
    t + ((frac >= 0.5) as i32 - (frac <= -0.5) as i32) as f32
}

/// Reference-grid position of the sensor site `q` of a (sub-)block with forward `flow` (the
/// scene point at p is at p + flow(p) in the block): the p with p + flow(p) = q, by two
/// fixed-point steps p ← q − flow(p) from p = q − flow(q) (exact for translations; the error
/// shrinks by |∇flow| per step, 10⁻² for hand shake, so ~10⁻⁶·|flow| after three).
#[inline]
pub fn reference_position(flow: &[f32], h: usize, w: usize, q: [f32; 2]) -> [f32; 2] {
    let mut p = q;
    for _ in 0..3 {
        let f = flow_bilinear(flow, h, w, p[0], p[1]);
        p = [q[0] - f[0], q[1] - f[1]];
    }
    p
}

/// [`reference_position`] of the eight sites (`y`, `x0` + i), i < 8, lane by lane with the
/// same operations (32-bit indices: vector instructions where the CPU has them): positions
/// (y, x) per lane.
#[inline(always)]
pub(super) fn reference_positions(
    flow: &[f32],
    h: usize,
    w: usize,
    y: f32,
    x0: f32,
) -> [[f32; LANES]; 2] {
    let (hf, wf) = ((h - 1) as f32, (w - 1) as f32);
    let (ylast, xlast) = (h.saturating_sub(2) as u32, w.saturating_sub(2) as u32);
    let (hl, wl) = ((h - 1) as u32, (w - 1) as u32);
    let w32 = w as u32;
    let q: [[f32; LANES]; 2] = [[y; LANES], std::array::from_fn(|i| x0 + i as u32 as f32)];
    let mut p = q;
    for _ in 0..3 {
        let mut f = [[0.0f32; LANES]; 2];
        for i in 0..LANES {
            // `flow_bilinear` lane-wise: the clamp passes NaN, which truncates to 0.
            let y = p[0][i].clamp(0.0, hf);
            let x = p[1][i].clamp(0.0, wf);
            let y0 = (index_in(y, hf) as u32).min(ylast);
            let x0 = (index_in(x, wf) as u32).min(xlast);
            let (y1, x1) = ((y0 + 1).min(hl), (x0 + 1).min(wl));
            let (fy, fx) = (y - y0 as f32, x - x0 as f32);
            for (c, o) in f.iter_mut().enumerate() {
                let at = |yy: u32, xx: u32| flow[((yy * w32 + xx) * 2) as usize + c];
                let top = at(y0, x0) * (1.0 - fx) + at(y0, x1) * fx;
                let bottom = at(y1, x0) * (1.0 - fx) + at(y1, x1) * fx;
                o[i] = top * (1.0 - fy) + bottom * fy;
            }
        }
        for a in 0..2 {
            for i in 0..LANES {
                p[a][i] = q[a][i] - f[a][i];
            }
        }
    }
    p
}
