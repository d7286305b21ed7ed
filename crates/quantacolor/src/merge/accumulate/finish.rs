//! The merge's last steps: per-channel mean samples and fluxes from the regression sums (the
//! MLE of paper Eq. 6, or the Gaussian–Poisson inversion, §6.1), hole filling, and the W
//! saturation fallback (supplement §7, generalised to censoring: this project's own) that lets
//! paper Eq. 8's RGBW combination ([`crate::rgbw`]) keep the RGB estimate where W saturates.
#![forbid(unsafe_code)]

use super::*;

/// Output of [`demosaic_merge`], on the output grid (H·scale, W·scale).
#[derive(Debug, Clone)]
pub struct MergedPlanes {
    /// (4, H·s, W·s) flux λ per channel in code order R, G, B, W: mean detections per binary
    /// frame, dark counts removed. W is replaced by wR·R + wG·G + wB·B where it saturates.
    /// Channels absent from the CFA are NaN.
    pub flux: Array3<f32>,
    /// (4, H·s, W·s) merged mean sample per frame p̂ = Σ w·counts / Σ w·frames per channel: the
    /// bit rate of binary frames, the mean digital number of multi-bit frames.
    pub bit_rate: Array3<f32>,
    /// (4, H·s, W·s) effective number of frames behind each mean, (Σ w·F)² / Σ w²·F (Kish):
    /// with the pixel model, the noise model of the merge (binomial Var(p̂) = p(1 − p)/N for
    /// binary frames; [`PixelModel::flux_variance`]). NaN where no sample reached the pixel
    /// (filled pixels).
    pub effective_frames: Array3<f32>,
    /// (H·s, W·s) pixels where the saturated W was replaced by the RGB estimate.
    pub w_fallback: Array2<bool>,
}

impl MergeAccumulator<'_> {
    /// Kernel regression over the bins (supplement Eq. 1–3), then per-channel mean samples and
    /// fluxes (the MLE of paper Eq. 6, or the Gaussian–Poisson inversion: [`PixelModel::flux`]),
    /// holes filled, W saturation fallback applied.
    pub fn finish(mut self, w_weights: [f64; 3]) -> MergedPlanes {
        let scale = self.config.scale;
        let channel_scale = self.channel_scale;
        let with_flux = self.fill_flux_planes();
        let sums = self.regression([true; 4], with_flux);
        let (bit_rate, mut flux, effective_frames) = self.fluxes(&sums);
        if with_flux {
            self.flux_domain_floor(&mut flux, &sums);
        }
        drop(sums);
        fill_holes(&mut flux, channel_scale, scale);
        let w_fallback = self.w_fallback(w_weights, &mut flux, &bit_rate, &effective_frames);
        if self.config.colour_ratios && channel_scale[..3].iter().all(|&s| s > 0.0) {
            let guide = colour_guide(channel_scale);
            self.colour_from_ratios(guide, &mut flux, &effective_frames);
        }
        MergedPlanes {
            flux,
            bit_rate,
            effective_frames,
            w_fallback,
        }
    }

    /// (bit rate, flux, effective frames), each (4, H·s, W·s), from the regression `sums`: the
    /// mean sample p̂ = Σ g·S0 / Σ g·S1, the effective frames (Σ g·S1)² / Σ g²·S2 and the flux
    /// of the pixel model; NaN where no sample reached the pixel.
    fn fluxes(&self, sums: &[[f32; SUMS]]) -> (Array3<f32>, Array3<f32>, Array3<f32>) {
        let model = self.model;
        let scale = self.config.scale;
        let (h, w) = (self.cfa.height(), self.cfa.width());
        let (hs, ws) = (h * scale, w * scale);
        let mut bit_rate = Array3::<f32>::from_elem((4, hs, ws), f32::NAN);
        let mut flux = Array3::<f32>::from_elem((4, hs, ws), f32::NAN);
        let mut effective_frames = Array3::<f32>::from_elem((4, hs, ws), f32::NAN);
        // Per channel plane, in parallel by output rows.
        for ch in 0..4 {
            let mut rate_plane = bit_rate.index_axis_mut(Axis(0), ch);
            let mut frames_plane = effective_frames.index_axis_mut(Axis(0), ch);
            let mut flux_plane = flux.index_axis_mut(Axis(0), ch);
            rate_plane
                .axis_iter_mut(Axis(0))
                .into_par_iter()
                .zip(frames_plane.axis_iter_mut(Axis(0)))
                .zip(flux_plane.axis_iter_mut(Axis(0)))
                .zip(sums.par_chunks(ws))
                .for_each(|(((mut rate, mut frames), mut flux), row)| {
                    for (ox, s) in row.iter().enumerate() {
                        let s = &s[ch * PLANES..ch * PLANES + 3];
                        if s[1] > 1e-6 && s[2] > 0.0 {
                            let p = s[0] / s[1];
                            let n_eff = s[1] as f64 * s[1] as f64 / s[2] as f64;
                            rate[ox] = p;
                            frames[ox] = n_eff as f32;
                            flux[ox] = model.flux(p as f64, n_eff) as f32;
                        }
                    }
                });
        }
        (bit_rate, flux, effective_frames)
    }

    /// W saturation fallback (supplement §7), generalised to censoring: where W is censored
    /// (binary frames, [`w_trust`]) or saturated (multi-bit frames), W of `flux` is blended
    /// towards or replaced by wR·R + wG·G + wB·B; the (H·s, W·s) pixels where it was.
    fn w_fallback(
        &self,
        w_weights: [f64; 3],
        flux: &mut Array3<f32>,
        bit_rate: &Array3<f32>,
        effective_frames: &Array3<f32>,
    ) -> Array2<bool> {
        let model = self.model;
        let w_saturation = self.config.w_saturation * model.max_sample() as f32;
        let scale = self.config.scale;
        let (h, w) = (self.cfa.height(), self.cfa.width());
        let (hs, ws) = (h * scale, w * scale);
        let channel_scale = self.channel_scale;
        // W saturation fallback (supplement §7), generalised to censoring.
        // Pixel by pixel, in parallel by output rows.
        let mut w_fallback = Array2::<bool>::from_elem((hs, ws), false);
        if channel_scale[..3].iter().all(|&s| s > 0.0) && channel_scale[3] > 0.0 {
            let censoring_zeros = self.config.w_censoring_zeros;
            let (rgb, mut white) = flux.view_mut().split_at(Axis(0), 3);
            white
                .index_axis_mut(Axis(0), 0)
                .axis_iter_mut(Axis(0))
                .into_par_iter()
                .zip(w_fallback.axis_iter_mut(Axis(0)))
                .enumerate()
                .for_each(|(oy, (mut white, mut fallback))| {
                    for ox in 0..ws {
                        let sat = |ch: usize| bit_rate[[ch, oy, ox]] > w_saturation;
                        let lum = || -> f32 {
                            (0..3)
                                .map(|ch| rgb[[ch, oy, ox]] as f64 * w_weights[ch])
                                .sum::<f64>() as f32
                        };
                        if model.is_binary() && censoring_zeros > 0.0 {
                            let trust = w_trust(
                                bit_rate[[3, oy, ox]],
                                effective_frames[[3, oy, ox]],
                                censoring_zeros,
                            );
                            let (censored, lum) = (white[ox], lum());
                            if trust < 1.0 && lum.is_finite() && lum > censored {
                                white[ox] = trust * censored + (1.0 - trust) * lum;
                                fallback[ox] = true;
                            }
                        } else if sat(3) && !(sat(0) || sat(1) || sat(2)) {
                            white[ox] = lum();
                            fallback[ox] = true;
                        }
                    }
                });
        }
        w_fallback
    }
}

/// Fills the pixels of `flux` that no sample reached (sparse channels, image borders) by
/// normalized convolution of their channel's plane, at the channel's site spacing.
fn fill_holes(flux: &mut Array3<f32>, channel_scale: [f32; 4], scale: usize) {
    for channel in Channel::ALL {
        let ch = channel.index();
        if channel_scale[ch] == 0.0 {
            continue;
        }
        let plane = flux.index_axis(Axis(0), ch);
        if plane.iter().any(|v| v.is_nan()) {
            let sigma = (channel_scale[ch] as f64).sqrt() * scale as f64;
            let filled = normalized_convolution(plane, sigma);
            let mut plane = flux.index_axis_mut(Axis(0), ch);
            plane.zip_mut_with(&filled, |v, &f| {
                if v.is_nan() {
                    *v = f;
                }
            });
        }
    }
}

/// The colour ratios' guide: W where the CFA has it, otherwise the densest colour (G of Bayer).
fn colour_guide(channel_scale: [f32; 4]) -> usize {
    if channel_scale[3] > 0.0 {
        3
    } else {
        (0..3)
            .min_by(|&a, &b| channel_scale[a].total_cmp(&channel_scale[b]))
            .expect("three colours")
    }
}

/// How far W's flux can be trusted at a pixel whose merged W bit rate is `bit_rate` over
/// `effective_frames` (binary frames): 1 while at least `censoring_zeros` frames are expected
/// without a detection, falling linearly to 0 when none are. With few zero frames left, W's
/// MLE is censored: the kernel mixes sites that saw a photon in every frame (whose MLE is
/// clamped) with nearly saturated ones, and the mean bit rate inverted through Eq. 6 is a lower
/// bound of the flux. This project's generalisation of supplement §7's fallback, which
/// replaces a saturated W only where R, G and B are not saturated themselves.
fn w_trust(bit_rate: f32, effective_frames: f32, censoring_zeros: f32) -> f32 {
    let zeros = effective_frames * (1.0 - bit_rate);
    if zeros.is_finite() {
        (zeros / censoring_zeros).clamp(0.0, 1.0)
    } else {
        1.0
    }
}
