//! RGBW combination, paper Eq. 8 (details in supplement §7): the merged W plane carries the
//! luminance (its SNR is far higher on RGBW sensors) and the merged R, G, B planes carry the
//! chromaticity. Used by the naive baseline ([`crate::naive`]) and by the burst merge
//! ([`crate::merge`]). The fallbacks where W is missing or the RGB luminance is not positive are
//! this project's own choices.

use ndarray::{Array3, Axis};
use rayon::prelude::*;

/// The RGBW combination of paper Eq. 8: scales R, G, B at each pixel so that
/// wR·R + wG·G + wB·B equals the merged W, keeping the chromaticity of RGB and the luminance of
/// W (whose SNR is far higher on RGBW sensors). Input (4, H, W) planes in code order; output
/// (H, W, 3). Where W is missing (no W sites) RGB are returned unchanged; where the RGB
/// luminance is not positive, W is spread as neutral grey.
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
                let lum: f64 = rgb
                    .iter()
                    .zip(w_weights)
                    .map(|(&v, wt)| v as f64 * wt)
                    .sum();
                for c in 0..3 {
                    row[[x, c]] = if white.is_nan() {
                        rgb[c]
                    } else if lum > 1e-9 && rgb.iter().all(|v| v.is_finite()) {
                        (rgb[c] as f64 * white as f64 / lum) as f32
                    } else {
                        (white as f64 / wsum) as f32
                    };
                }
            }
        });
    out
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
}
