//! The target phase bin and robustness weight of every site of a sub-block (the first half of
//! the splat, [`MergeAccumulator::add`]): portable lanes here, their AVX2 form in `x86`.

#![forbid(unsafe_code)]

use super::*;
use crate::cpu::Isa;

/// The range (lowest, highest) of the target bins of a row of sites, `(u32::MAX, 0)` when no
/// site of the row lands in the bins: [`MergeAccumulator::add`]'s bands skip the rows that
/// cannot reach them. Made while the row is still in cache from its targets.
#[inline(always)]
pub(super) fn row_span(row: &[(u32, f32)]) -> (u32, u32) {
    row.iter()
        .filter(|&&(bin, _)| bin != u32::MAX)
        .fold((u32::MAX, 0), |(lo, hi), &(bin, _)| {
            (lo.min(bin), hi.max(bin))
        })
}

/// What [`MergeAccumulator::add`] needs to find the target bin of every site.
pub(super) struct TargetGrid<'s> {
    pub(super) h: usize,
    pub(super) w: usize,
    /// Bins per reference px.
    pub(super) u: f32,
    /// Margin of the bin grid (reference px).
    pub(super) margin: f32,
    pub(super) bins_h: usize,
    pub(super) bins_w: usize,
    /// Floats per plane row of the bins ([`MergeAccumulator`]'s `stride`).
    pub(super) stride: usize,
    pub(super) excluded: Option<&'s [bool]>,
    /// Robustness map on the reference grid (`None`: weight 1).
    pub(super) robust: Option<&'s [f32]>,
}

impl TargetGrid<'_> {
    /// Target bin (the index of its first sum in the bins, (by·12)·stride + bx) and robustness
    /// weight of every site (row-major), `(u32::MAX, 0)` for sites left out (excluded, zero
    /// weight, outside the bins); `position` maps a site to its reference-grid position. In
    /// parallel by rows; the range of target bins of every row into `spans` ([`row_span`]).
    pub(super) fn fill(
        &self,
        targets: &mut [(u32, f32)],
        spans: &mut [(u32, u32)],
        position: impl Fn([f32; 2]) -> [f32; 2] + Sync,
    ) {
        let w = self.w;
        targets
            .par_chunks_mut(w)
            .zip(spans.par_iter_mut())
            .enumerate()
            .for_each(|(y, (row, span))| {
                for (x, target) in row.iter_mut().enumerate() {
                    *target = if self.excluded.is_some_and(|e| e[y * w + x]) {
                        (u32::MAX, 0.0)
                    } else {
                        let p = position([y as f32, x as f32]);
                        let rounded = [round_half_away(p[0]), round_half_away(p[1])];
                        let bin = [
                            round_half_away((p[0] + self.margin) * self.u),
                            round_half_away((p[1] + self.margin) * self.u),
                        ];
                        self.target(rounded, bin)
                    };
                }
                *span = row_span(row);
            });
    }

    /// The target of a site whose reference position p rounds to `rounded` and whose bin
    /// coordinates are `bin` (both rounded half away from zero): the robustness at the
    /// reference pixel nearest p (clamped to the image), the bin if inside the grid.
    #[inline(always)]
    fn target(&self, rounded: [f32; 2], bin: [f32; 2]) -> (u32, f32) {
        let (h, w) = (self.h, self.w);
        let r = self.robust.map_or(1.0, |m| {
            let ry = (rounded[0].max(0.0) as usize).min(h - 1);
            let rx = (rounded[1].max(0.0) as usize).min(w - 1);
            m[ry * w + rx]
        });
        let [by, bx] = bin;
        if r <= 0.0 || by < 0.0 || bx < 0.0 || by >= self.bins_h as f32 || bx >= self.bins_w as f32
        {
            (u32::MAX, 0.0)
        } else {
            ((by as usize * SUMS * self.stride + bx as usize) as u32, r)
        }
    }

    /// [`TargetGrid::fill`] for a sub-block whose sites move by the affine map
    /// (`matrix`, `offset`), where `local` (mask (H·W), dense flow (H, W, 2)) marks the reference
    /// pixels whose sites take the inverted dense flow instead ([`SubBlockMotion::
    /// CameraAndLocal`]). The positions and their roundings are computed eight sites at a time
    /// (vector instructions where `isa` has AVX2): the same operations per site, so the same
    /// targets as `fill` with the position closure of that motion.
    pub(super) fn fill_affine(
        &self,
        isa: Isa,
        targets: &mut [(u32, f32)],
        spans: &mut [(u32, u32)],
        matrix: &[[f64; 2]; 2],
        offset: &[f64; 2],
        local: Option<(&[bool], &[f32])>,
    ) {
        targets
            .par_chunks_mut(self.w)
            .zip(spans.par_iter_mut())
            .enumerate()
            .for_each(|(y, (row, span))| {
                #[cfg(target_arch = "x86_64")]
                {
                    if isa.avx2() {
                        self.affine_row_avx2(isa, y, row, matrix, offset, local);
                        *span = row_span(row);
                        return;
                    }
                }
                self.affine_row(isa, y, row, matrix, offset, local);
                *span = row_span(row);
            });
    }

    /// Targets of the sites of row `y` ([`TargetGrid::fill_affine`]): lane-wise and without
    /// branches for the affine positions (whatever their robustness and whether they land in
    /// the bins), then the few sites that need more (local motion, excluded) one by one.
    /// Where `isa` has AVX2 (and the robustness map covers the image), the affine lanes'
    /// targets by [`TargetGrid::lane_targets_avx2`], the same values as
    /// [`TargetGrid::lane_targets`].
    #[inline(always)]
    pub(super) fn affine_row(
        &self,
        isa: Isa,
        y: usize,
        row: &mut [(u32, f32)],
        matrix: &[[f64; 2]; 2],
        offset: &[f64; 2],
        local: Option<(&[bool], &[f32])>,
    ) {
        let (h, w, u, margin) = (self.h, self.w, self.u, self.margin);
        let (hf, wf) = ((h - 1) as f32, (w - 1) as f32);
        let excluded = self.excluded.map(|e| &e[y * w..(y + 1) * w]);
        for (chunk, out) in row.chunks_mut(LANES).enumerate() {
            let x0 = chunk * LANES;
            // Lane-wise: positions, their roundings and bin coordinates.
            let mut p = [[0.0f32; LANES]; 2];
            let mut rounded = [[0.0f32; LANES]; 2];
            let mut bin = [[0.0f32; LANES]; 2];
            let (yf, x0f) = (y as u32 as f32, x0 as u32 as f32);
            for i in 0..LANES {
                let q = affine_position(matrix, offset, [yf, x0f + i as u32 as f32]);
                for a in 0..2 {
                    p[a][i] = q[a];
                    rounded[a][i] = round_half_away_trunc(q[a]);
                    bin[a][i] = round_half_away_trunc((q[a] + margin) * u);
                }
            }
            // Excluded sites are left out lane-wise, as sites outside the bins are.
            let mut skip = [false; LANES];
            if let Some(e) = excluded {
                // Element by element: a fixed-length loop, no call to `memcpy`.
                for (s, &e) in skip.iter_mut().zip(&e[x0..x0 + out.len()]) {
                    *s = e;
                }
            }
            #[cfg(target_arch = "x86_64")]
            let simd = self.lane_targets_x86(isa, &rounded, &bin, &skip);
            #[cfg(not(target_arch = "x86_64"))]
            let simd = {
                let _ = isa;
                None
            };
            let mut lanes = match (simd, self.robust) {
                (Some(lanes), _) => lanes,
                (None, Some(m)) => self.lane_targets(&rounded, &bin, &skip, |i| m[i]),
                (None, None) => self.lane_targets(&rounded, &bin, &skip, |_| 1.0),
            };
            if let Some((mask, flow)) = local {
                // Sites whose affine position is outside the image or on a marked pixel take
                // the inverted dense flow (all eight lanes computed when one needs it).
                let mut dense = [false; LANES];
                for i in 0..LANES {
                    let (py, px) = (p[0][i], p[1][i]);
                    let inside = (py >= 0.0) & (px >= 0.0) & (py <= hf) & (px <= wf);
                    // Inside, the clamps change nothing: the rounded position's pixel.
                    let ry = index_in(rounded[0][i], hf) as usize;
                    let rx = index_in(rounded[1][i], wf) as usize;
                    dense[i] = !inside || mask[ry * w + rx];
                }
                if dense[..out.len()].contains(&true) {
                    let q = reference_positions(flow, h, w, yf, x0f);
                    let mut rounded = [[0.0f32; LANES]; 2];
                    let mut bin = [[0.0f32; LANES]; 2];
                    for a in 0..2 {
                        for i in 0..LANES {
                            rounded[a][i] = round_half_away_trunc(q[a][i]);
                            bin[a][i] = round_half_away_trunc((q[a][i] + margin) * u);
                        }
                    }
                    let moved = match self.robust {
                        Some(m) => self.lane_targets(&rounded, &bin, &skip, |i| m[i]),
                        None => self.lane_targets(&rounded, &bin, &skip, |_| 1.0),
                    };
                    // A lane-wise select (no conditional stores of single lanes).
                    lanes = std::array::from_fn(|i| if dense[i] { moved[i] } else { lanes[i] });
                }
            }
            for (target, &lane) in out.iter_mut().zip(&lanes) {
                *target = lane;
            }
        }
    }

    /// [`TargetGrid::target`] of eight sites at once, without branches, lanes marked in `skip`
    /// (excluded sites) left out: `robust(i)` reads the robustness map at row-major index i
    /// (inside the image).
    #[inline(always)]
    pub(super) fn lane_targets(
        &self,
        rounded: &[[f32; LANES]; 2],
        bin: &[[f32; LANES]; 2],
        skip: &[bool; LANES],
        robust: impl Fn(usize) -> f32,
    ) -> [(u32, f32); LANES] {
        // 32-bit integers throughout (vector conversions); the clamps are taken on the
        // integral floats, whose bounds (image sides) are exact in f32.
        let (hf, wf) = ((self.h - 1) as f32, (self.w - 1) as f32);
        let w = self.w as i32;
        let (bins_h, bins_w) = (self.bins_h as f32, self.bins_w as f32);
        let row_floats = (SUMS * self.stride) as i32;
        let mut index = [0i32; LANES];
        let mut outside = [false; LANES];
        let mut at = [0i32; LANES];
        for i in 0..LANES {
            let ry = index_in(rounded[0][i], hf);
            let rx = index_in(rounded[1][i], wf);
            at[i] = ry * w + rx;
            let (by, bx) = (bin[0][i], bin[1][i]);
            outside[i] = (by < 0.0) | (bx < 0.0) | (by >= bins_h) | (bx >= bins_w);
            // Wrapping: the index of a lane left out is discarded (and a lane is kept only
            // where 0 <= by < bins_h and 0 <= bx < bins_w, or NaN: there the clamped
            // conversion is `by as i32`).
            index[i] = index_in(by, bins_h)
                .wrapping_mul(row_floats)
                .wrapping_add(index_in(bx, bins_w));
        }
        // Selected lane-wise into two arrays, then interleaved: no conditional stores of
        // single lanes (which the vector reads of `out` then waited for: store forwarding
        // fails on a wide read of narrow writes). The same values as storing the kept lanes
        // into an array of `(u32::MAX, 0.0)`.
        let mut bins = [u32::MAX; LANES];
        let mut weights = [0.0f32; LANES];
        for i in 0..LANES {
            let r = robust(at[i] as usize);
            let keep = !(outside[i] | skip[i] | (r <= 0.0));
            bins[i] = if keep { index[i] as u32 } else { u32::MAX };
            weights[i] = if keep { r } else { 0.0 };
        }
        std::array::from_fn(|i| (bins[i], weights[i]))
    }
}
