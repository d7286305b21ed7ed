//! Flux-domain floor of the merged binary fluxes (issue 45, flux conservation): this project's
//! own step, not the paper's. The kernel regression of supplement Eq. 1–3 averages *bit rates*
//! over a kernel and only then inverts Eq. 6, λ̂ = f(p̄) with f(p) = −ln(1 − p). f is convex, so
//! where the kernel straddles samples of different flux (a bright point one or two pixels
//! wide, an edge, a pixel whose own site is another colour and whose W comes from its
//! neighbours) f(p̄) is below the kernel's mean flux Σ ω·f(p_b) (Jensen), and the light the
//! kernel spreads is not conserved: a 2x2 point at λ_W = 3 on a dark background kept 78–83 %
//! of its light (docs/tuning.md, "Flux conservation"). The mean *flux* of the bins instead
//! conserves light, as any normalised blur of the flux image does.
//!
//! Each phase bin's flux is its own inversion f(p_b) over its own (Kish) frames, less its
//! second-order bias ([`PixelModel::flux_bias`]: a bin holds few frames, and f(p̂_b) of a
//! noisy p̂_b is biased upward by the same convexity); the bins' fluxes, a fourth plane per
//! channel, are regressed in the same pass as the other sums, with the same kernels and
//! weights, and a pixel takes the larger of that and f(p̄). In a flat region
//! f(p̄) pools the frames before the inversion and is the better (maximum-likelihood)
//! estimate, and the bias-corrected flux mean falls below it on average, so f(p̄) stays;
//! across a step in flux the flux mean is larger by the Jensen gap and replaces it. Binary
//! frames only: the Gaussian–Poisson inversion of multi-bit frames is linear.
#![forbid(unsafe_code)]

use super::*;

impl MergeAccumulator<'_> {
    /// Fills each present channel's plane S3 of every phase bin with Σ r·F times the bin's own
    /// bias-corrected flux (0 where the bin holds no frames), for the regression to gather with
    /// the other sums; whether it did (binary frames only).
    pub(super) fn fill_flux_planes(&mut self) -> bool {
        let model = self.model;
        if !model.is_binary() {
            return false;
        }
        let present: [bool; 4] = std::array::from_fn(|ch| self.channel_scale[ch] > 0.0);
        let (stride, bins_w) = (self.stride, self.bins_w);
        self.bins.par_chunks_mut(SUMS * stride).for_each(|row| {
            for ch in (0..4).filter(|&ch| present[ch]) {
                let (sums, own_flux) =
                    row[ch * PLANES * stride..(ch + 1) * PLANES * stride].split_at_mut(3 * stride);
                let (counts, rest) = sums.split_at(stride);
                let (frames, squares) = rest.split_at(stride);
                for bx in 0..bins_w {
                    let (f, f2) = (frames[bx], squares[bx]);
                    own_flux[bx] = if f > 1e-6 && f2 > 0.0 {
                        let p = (counts[bx] / f) as f64;
                        let n = f as f64 * f as f64 / f2 as f64;
                        let lambda = model.flux(p, n) - model.flux_bias(p, n);
                        f * lambda as f32
                    } else {
                        0.0
                    };
                }
            }
        });
        true
    }

    /// Raises every present channel of `flux` (binary frames; dark removed) to the kernel mean
    /// of its phase bins' own bias-corrected fluxes, Σ g·S3 / Σ g·S1 of the regression `sums`
    /// made after [`Self::fill_flux_planes`], where that is larger.
    pub(super) fn flux_domain_floor(&self, flux: &mut Array3<f32>, sums: &[[f32; SUMS]]) {
        let present: [bool; 4] = std::array::from_fn(|ch| self.channel_scale[ch] > 0.0);
        let ws = flux.dim().2;
        for ch in (0..4).filter(|&ch| present[ch]) {
            flux.index_axis_mut(Axis(0), ch)
                .axis_iter_mut(Axis(0))
                .into_par_iter()
                .zip(sums.par_chunks(ws))
                .for_each(|(mut plane_row, sums_row)| {
                    for (value, s) in plane_row.iter_mut().zip(sums_row) {
                        let (frames, own_flux) = (s[ch * PLANES + 1], s[ch * PLANES + 3]);
                        if value.is_finite() && frames > 1e-6 {
                            *value = value.max(own_flux / frames);
                        }
                    }
                });
        }
    }
}
