//! RGBW combination, paper Eq. 8 (details in supplement §7): the merged W plane carries the
//! luminance (its SNR is far higher on RGBW sensors) and the merged R, G, B planes carry the
//! chromaticity. Used by the naive baseline ([`crate::naive`]) and by the burst merge
//! ([`crate::merge`]). The fallbacks where W is missing or the RGB luminance is not positive are
//! this project's own choices.
#![forbid(unsafe_code)]

use ndarray::{Array3, Axis};
use rayon::prelude::*;

/// The RGBW combination of paper Eq. 8: scales R, G, B at each pixel so that
/// wR·R + wG·G + wB·B equals the merged W, keeping the chromaticity of RGB and the luminance of
/// W (whose SNR is far higher on RGBW sensors). Input (4, H, W) planes in code order; output
/// (H, W, 3). Where W is missing (no W sites) RGB are returned unchanged; where the RGB
/// luminance is not positive, W is spread as neutral grey.
///
/// Negative fluxes (the unclamped MLE of a channel with no detection, −d) enter the ratios as
/// zero, and so does a negative W: a ratio of noisy near-zero values of both signs would
/// otherwise scale one channel far below zero and the others far above W (measured on a
/// 256-frame HDR chart: values down to −0.064 where the truth is 0.0004). This project's own
/// guard; it changes nothing where the fluxes are positive.
pub fn combine_rgbw(planes: &Array3<f32>, w_weights: [f64; 3]) -> Array3<f32> {
    let (_, h, w) = planes.dim();
    let wsum: f64 = w_weights.iter().sum();
    let mut out = Array3::<f32>::zeros((h, w, 3));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut row)| {
            for x in 0..w {
                let rgb = [planes[[0, y, x]], planes[[1, y, x]], planes[[2, y, x]]];
                let white = planes[[3, y, x]];
                if white.is_nan() {
                    for c in 0..3 {
                        row[[x, c]] = rgb[c];
                    }
                    continue;
                }
                let white = white.max(0.0) as f64;
                let finite = rgb.iter().all(|v| v.is_finite());
                let chroma = rgb.map(|v| v.max(0.0) as f64);
                let lum: f64 = chroma.iter().zip(w_weights).map(|(&v, wt)| v * wt).sum();
                for c in 0..3 {
                    row[[x, c]] = if finite && lum > 1e-9 {
                        (chroma[c] * white / lum) as f32
                    } else {
                        (white / wsum) as f32
                    };
                }
            }
        });
    out
}

/// Jacobian of the RGBW combination of paper Eq. 8 at one pixel, `∂out_c/∂λ_k` for the outputs
/// c = R, G, B and the merged fluxes k = R, G, B, W (code order): with `out_c = λ_c·λ_W / L`,
/// `L = Σ w_k·λ_k`,
///
/// ```text
/// ∂out_c/∂λ_k = δ_ck·λ_W/L − λ_c·λ_W·w_k/L²   (k = R, G, B),     ∂out_c/∂λ_W = λ_c/L .
/// ```
///
/// Carries the merge's per-channel flux noise into the combined image (the denoiser's noise
/// model). Where there is no W (`has_w` false) or L ≤ 1e-9, the identity on R, G, B: the first is
/// what [`combine_rgbw`] does, the second is this project's simplification of the noise model
/// for the dark pixels where [`combine_rgbw`] spreads W as neutral grey.
pub fn combine_rgbw_jacobian(flux: [f64; 4], w_weights: [f64; 3], has_w: bool) -> [[f64; 4]; 3] {
    let mut jac = [[0.0f64; 4]; 3];
    let lum: f64 = (0..3).map(|k| w_weights[k] * flux[k]).sum();
    if has_w && lum > 1e-9 {
        for c in 0..3 {
            for k in 0..3 {
                let delta = if c == k { flux[3] / lum } else { 0.0 };
                jac[c][k] = delta - flux[c] * flux[3] * w_weights[k] / (lum * lum);
            }
            jac[c][3] = flux[c] / lum;
        }
    } else {
        for (c, row) in jac.iter_mut().enumerate() {
            row[c] = 1.0;
        }
    }
    jac
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rgbw_combination_matches_w_and_keeps_chromaticity() {
        let mut planes = Array3::<f32>::zeros((4, 1, 2));
        for (c, v) in [0.2f32, 0.5, 0.1, 1.6].iter().enumerate() {
            planes[[c, 0, 0]] = *v;
            planes[[c, 0, 1]] = *v;
        }
        planes[[3, 0, 1]] = f32::NAN; // no W: RGB pass through
        let weights = [1.0, 2.0, 0.5];
        let out = combine_rgbw(&planes, weights);
        let lum = 0.2 * 1.0 + 0.5 * 2.0 + 0.1 * 0.5;
        let s = 1.6 / lum;
        for (c, v) in [0.2f32, 0.5, 0.1].iter().enumerate() {
            assert!((out[[0, 0, c]] - v * s as f32).abs() < 1e-6);
            assert_eq!(out[[0, 1, c]], *v);
        }
    }

    /// Noisy near-zero fluxes of both signs give colours between zero and W, not ratios that
    /// run off far below zero and above W.
    #[test]
    fn negative_fluxes_never_make_negative_or_amplified_colours() {
        let weights = [1.0, 1.0, 1.0];
        for (r, g, b, white) in [
            (-0.0001f32, 0.0002, 0.0, 0.01),
            (-0.001, -0.002, 0.0005, 0.004),
            (-0.001, -0.002, -0.0005, 0.004),
            (0.001, 0.002, 0.0005, -0.0001),
        ] {
            let planes = Array3::from_shape_vec((4, 1, 1), vec![r, g, b, white]).unwrap();
            let out = combine_rgbw(&planes, weights);
            let sum: f32 = (0..3).map(|c| out[[0, 0, c]]).sum();
            for c in 0..3 {
                let v = out[[0, 0, c]];
                assert!(
                    v >= 0.0 && v <= white.max(0.0) + 1e-9,
                    "{:?}: {v}",
                    (r, g, b, white)
                );
            }
            assert!(
                (sum - white.max(0.0)).abs() < 1e-6,
                "luminance kept: {sum} vs {white}"
            );
        }
    }

    #[test]
    fn jacobian_matches_finite_differences_of_the_combination() {
        let weights = [1.0, 2.0, 0.5];
        let flux = [0.2f64, 0.5, 0.1, 1.6];
        let combine = |f: [f64; 4]| {
            let planes = Array3::from_shape_fn((4, 1, 1), |(c, _, _)| f[c] as f32);
            let out = combine_rgbw(&planes, weights);
            [0, 1, 2].map(|c| out[[0, 0, c]] as f64)
        };
        let jac = combine_rgbw_jacobian(flux, weights, true);
        let h = 1e-3;
        for k in 0..4 {
            let (mut up, mut down) = (flux, flux);
            up[k] += h;
            down[k] -= h;
            let (a, b) = (combine(up), combine(down));
            for c in 0..3 {
                let fd = (a[c] - b[c]) / (2.0 * h);
                assert!(
                    (jac[c][k] - fd).abs() < 1e-3,
                    "∂{c}/∂{k}: {} vs {fd}",
                    jac[c][k]
                );
            }
        }
        let identity = combine_rgbw_jacobian(flux, weights, false);
        for (c, row) in identity.iter().enumerate() {
            assert_eq!(row, &[0, 1, 2, 3].map(|k| if k == c { 1.0 } else { 0.0 }));
        }
    }
}
