//! Colour from ratios to W, or to G without W (`AccumulateConfig::colour_ratios`): this
//! project's own step, not the paper's (the principle of colour-ratio demosaicking, Kimmel
//! 1999, and of guided filtering, He et al. 2013). Where the CFA has W and R, G, B, each
//! colour's flux is divided by the merged W seen through that colour's own kernel and sample
//! weights (the same regression over the same bins with every sample's counts replaced by the
//! merged W at its position), and multiplied by the merged W at the pixel. A colour kernel is
//! several pixels wide (its sites are sparse), so at a luminance edge it averages samples from
//! both sides and the brighter side's colour bleeds into the darker (fringes, strongest in
//! static captures where the sites never move); the ratio to W over the same samples cancels
//! that luminance step. In flat regions the factor is 1. Without W (Bayer) the densest colour,
//! G, guides R and B, its noise gated ([`COLOUR_GUIDE_NOISE_GATE`]). Measured gains and cost:
//! docs/tuning.md.
#![forbid(unsafe_code)]

use super::*;

/// Without W, the colour ratios' guide is a colour (G of Bayer) whose pixel noise the ratio
/// would carry into the other colours (Eq. 8 cancels W's, not G's): the factor's departure
/// from 1 is shrunk by the non-negative garrote (Breiman 1995) at this many standard deviations
/// of the guide's flux at the pixel (relative to the guide seen by the colour), so flat areas
/// keep their colour noise and edges get the correction
/// ([`MergeAccumulator::colour_from_ratios`]; 0, 1 and 2 measured: docs/tuning.md).
const COLOUR_GUIDE_NOISE_GATE: f32 = 1.0;

/// The non-negative garrote of `value` at `threshold`: `value·(1 − threshold²/value²)` beyond
/// the threshold, 0 within it.
pub(super) fn garrote(value: f32, threshold: f32) -> f32 {
    if value * value > threshold * threshold {
        value - threshold * threshold / value
    } else {
        0.0
    }
}

impl MergeAccumulator<'_> {
    /// `AccumulateConfig::colour_ratios`: every colour c of `flux` but the `guide` (W, or the
    /// densest colour without W) times G / Ḡ_c, G the guide's merged flux (`flux`'s plane,
    /// after hole filling and the saturation fallback) and Ḡ_c the guide at the positions of
    /// channel c's samples, regressed with c's kernel and weights. The phase bins already hold
    /// each bin's Σ r·F per channel; a bin's samples all lie within half a bin of it, so the
    /// guide at the bin stands for the guide at each of them, and Σ g·G(bin)·Σ r·F over the
    /// bins, divided by Σ g·Σ r·F, is Ḡ_c. Both G and Ḡ_c are floored at one detection over
    /// the pixel's effective guide frames: where the guide says nothing (the dark), the factor
    /// is 1. A colour guide's pixel noise would enter c (Eq. 8 cancels W's, not G's), so there
    /// the factor's departure from 1 is shrunk by [`COLOUR_GUIDE_NOISE_GATE`].
    pub(super) fn colour_from_ratios(
        &mut self,
        guide: usize,
        flux: &mut Array3<f32>,
        effective_frames: &Array3<f32>,
    ) {
        let scale = self.config.scale as f32;
        let model = self.model;
        let gate = (guide != Channel::W.index()).then_some(COLOUR_GUIDE_NOISE_GATE);
        let guided: [bool; 4] = std::array::from_fn(|ch| ch < 3 && ch != guide);
        let guide_flux = flux.index_axis(Axis(0), guide).to_owned();
        let (u, margin, stride, bins_w) = (
            self.bins_per_px as f32,
            self.margin as f32,
            self.stride,
            self.bins_w,
        );
        // Output pixel (oy, ox) sits at reference position (oy + 0.5) / scale − 0.5.
        let output_position = |bin: usize| ((bin as f32 / u - margin) + 0.5) * scale - 0.5;
        self.bins
            .par_chunks_mut(SUMS * stride)
            .enumerate()
            .for_each(|(by, row)| {
                let oy = output_position(by);
                for bx in 0..bins_w {
                    let at_bin = bilinear(guide_flux.view(), oy, output_position(bx));
                    let at_bin = if at_bin.is_finite() { at_bin } else { 0.0 };
                    for ch in (0..3).filter(|&ch| guided[ch]) {
                        let frames = row[(ch * PLANES + 1) * stride + bx];
                        row[ch * PLANES * stride + bx] = at_bin * frames;
                    }
                }
            });
        let sums = self.regression(guided, false);
        let guide_frames = effective_frames.index_axis(Axis(0), guide);
        let ws = guide_flux.ncols();
        for ch in (0..3).filter(|&ch| guided[ch]) {
            flux.index_axis_mut(Axis(0), ch)
                .axis_iter_mut(Axis(0))
                .into_par_iter()
                .zip(sums.par_chunks(ws))
                .enumerate()
                .for_each(|(oy, (mut plane_row, sums_row))| {
                    for (ox, (value, s)) in plane_row.iter_mut().zip(sums_row).enumerate() {
                        let n = guide_frames[[oy, ox]];
                        let s = &s[ch * PLANES..ch * PLANES + 2];
                        if n.is_finite() && n > 0.0 && s[1] > 1e-6 {
                            let floor = 1.0 / n;
                            let guide_seen_by_colour = (s[0] / s[1]).max(floor);
                            let guide_here = guide_flux[[oy, ox]];
                            let factor = guide_here.max(floor) / guide_seen_by_colour;
                            *value *= match gate {
                                None => factor,
                                Some(sigmas) => {
                                    let variance =
                                        model.flux_variance(guide_here.max(0.0) as f64, n as f64);
                                    let noise =
                                        sigmas * (variance as f32).sqrt() / guide_seen_by_colour;
                                    1.0 + garrote(factor - 1.0, noise)
                                }
                            };
                        }
                    }
                });
        }
    }
}
