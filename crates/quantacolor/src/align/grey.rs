//! Grey block images for alignment (supplement §1.1).
//!
//! Block sums are mosaicked: neighbouring pixels sit behind different filters and see different
//! fractions of the light. Patch matching needs a single-channel image in which a moving scene
//! moves and nothing else, so each block sum is first turned into a grey image, normalised by
//! the block length (mean detections per frame) so that blocks of different lengths compare.
//! How depends on the CFA (see [`GreyMethod::detect`]).
#![forbid(unsafe_code)]

use crate::cfa::{Cfa, Channel};
use crate::error::{Error, Result};
use crate::filters::{normalized_convolution_masked_with, normalized_convolution_weights};
use ndarray::{Array2, Zip};
use serde::{Deserialize, Serialize};

/// How a mosaicked block sum becomes a grey image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GreyMethod {
    /// Dense W lattice (≥ 50 % W): W pixels keep their value, colour sites get W by normalized
    /// convolution over their W neighbours (Gaussian σ = 0.75 px). W carries luminance at full
    /// resolution and the highest photon rate (paper §4.1), so this wins over tile averaging.
    InterpolateW,
    /// Periodic CFA with period `py` x `px` ≤ 4 (e.g. Bayer): every pixel takes the mean of the
    /// `py` x `px` window starting at it, which holds each filter of the period exactly once, so
    /// the filters' different sensitivities cancel. The window's half-period offset is the same
    /// in every block and does not bias relative motion.
    TileAverage { py: usize, px: usize },
    /// Anything else (sparse or aperiodic colour CFAs): each channel is interpolated by
    /// normalized convolution (Gaussian σ = 0.6 / √fraction px, about half the channel's
    /// lattice spacing) and the grey image is the mean of the channel planes present.
    Demosaic,
}

/// Which grey method to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GreyChoice {
    /// [`GreyMethod::detect`] decides.
    #[default]
    Auto,
    /// Force [`GreyMethod::InterpolateW`].
    InterpolateW,
    /// Force [`GreyMethod::TileAverage`] (fails for CFAs not periodic within 4 x 4).
    TileAverage,
    /// Force [`GreyMethod::Demosaic`].
    Demosaic,
}

/// Smallest period ≤ 4 of `codes` along rows (`axis_y`) or columns, if any.
fn period(codes: &Array2<u8>, along_y: bool) -> Option<usize> {
    let (h, w) = codes.dim();
    let n = if along_y { h } else { w };
    (1..=4.min(n)).find(|&p| {
        codes.indexed_iter().all(|((y, x), &c)| {
            let (yy, xx) = if along_y { (y + p, x) } else { (y, x + p) };
            yy >= h || xx >= w || codes[[yy, xx]] == c
        })
    })
}

impl GreyMethod {
    /// Detects the class of `cfa`: W fraction ≥ 50 % → [`GreyMethod::InterpolateW`]; else the
    /// smallest periods along y and x, tested by comparing the code array with itself shifted
    /// by 1..=4 pixels, both found → [`GreyMethod::TileAverage`]; else
    /// [`GreyMethod::Demosaic`]. A uniform CFA (monochrome) is a 1 x 1 tile average.
    pub fn detect(cfa: &Cfa) -> GreyMethod {
        let frac = cfa.fractions();
        if frac[Channel::W.index()] >= 0.5 && frac[Channel::W.index()] < 1.0 {
            return GreyMethod::InterpolateW;
        }
        match (period(cfa.codes(), true), period(cfa.codes(), false)) {
            (Some(py), Some(px)) => GreyMethod::TileAverage { py, px },
            _ => GreyMethod::Demosaic,
        }
    }

    /// Resolves `choice` for `cfa`.
    pub fn resolve(choice: GreyChoice, cfa: &Cfa) -> Result<GreyMethod> {
        Ok(match choice {
            GreyChoice::Auto => GreyMethod::detect(cfa),
            GreyChoice::InterpolateW => {
                if cfa.fractions()[Channel::W.index()] == 0.0 {
                    return Err(Error::invalid("W interpolation needs a CFA with W pixels"));
                }
                GreyMethod::InterpolateW
            }
            GreyChoice::Demosaic => GreyMethod::Demosaic,
            GreyChoice::TileAverage => {
                match (period(cfa.codes(), true), period(cfa.codes(), false)) {
                    (Some(py), Some(px)) => GreyMethod::TileAverage { py, px },
                    _ => {
                        return Err(Error::invalid(
                            "tile averaging needs a CFA periodic within 4 x 4 pixels",
                        ))
                    }
                }
            }
        })
    }
}

/// Grey image `(H, W)` of one block sum `counts` over `frames` frames, in mean detections per
/// frame (the mean sample per frame: bit rate, or digital number of multi-bit frames), by
/// `method` for `cfa`. The one grey image of the crate: alignment blocks, the Wiener reference
/// and the robustness weights all compare these. Many blocks of one CFA: [`GreyImager`].
///
/// Errors if `counts` and the CFA differ in shape or `frames` is 0.
pub fn grey_image(
    counts: &Array2<u32>,
    frames: usize,
    cfa: &Cfa,
    method: GreyMethod,
) -> Result<Array2<f32>> {
    GreyImager::new(cfa, method).image(counts, frames)
}

/// [`grey_image`] for many block sums of one CFA: the CFA masks and the normalized
/// convolutions' denominators (which depend on the masks alone) are made once, not per block.
/// The same numbers as [`grey_image`].
#[derive(Debug, Clone)]
pub struct GreyImager {
    codes_dim: (usize, usize),
    method: GreyMethod,
    /// Per plane: mask, Gaussian σ (px) and denominator `G * mask`.
    planes: Vec<(Array2<bool>, f32, Array2<f32>)>,
}

impl GreyImager {
    /// Masks and denominators of `method` on `cfa`.
    pub fn new(cfa: &Cfa, method: GreyMethod) -> GreyImager {
        let mut planes = Vec::new();
        let mut plane = |mask: Array2<bool>, sigma: f32| {
            let den = normalized_convolution_weights(&mask, sigma);
            planes.push((mask, sigma, den));
        };
        match method {
            GreyMethod::TileAverage { .. } => {}
            GreyMethod::InterpolateW => plane(cfa.mask(Channel::W), 0.75),
            GreyMethod::Demosaic => {
                let frac = cfa.fractions();
                for ch in Channel::ALL {
                    let f = frac[ch.index()];
                    if f == 0.0 {
                        continue;
                    }
                    plane(cfa.mask(ch), (0.6 / f.sqrt()) as f32);
                }
            }
        }
        GreyImager {
            codes_dim: cfa.codes().dim(),
            method,
            planes,
        }
    }

    /// Grey image of one block sum (see [`grey_image`]).
    pub fn image(&self, counts: &Array2<u32>, frames: usize) -> Result<Array2<f32>> {
        if counts.dim() != self.codes_dim {
            return Err(Error::invalid(format!(
                "grey image: counts have shape {:?}, the CFA is {:?}",
                counts.dim(),
                self.codes_dim
            )));
        }
        if frames == 0 {
            return Err(Error::invalid("grey image: zero frames"));
        }
        let scale = 1.0 / frames as f32;
        let values = counts.mapv(|c| c as f32 * scale);
        Ok(match self.method {
            GreyMethod::TileAverage { py, px } => tile_average(&values, py, px),
            GreyMethod::InterpolateW => {
                let (w_mask, sigma, den) = &self.planes[0];
                let smooth = normalized_convolution_masked_with(&values, w_mask, *sigma, den);
                let mut out = values;
                Zip::from(&mut out)
                    .and(w_mask)
                    .and(&smooth)
                    .for_each(|o, &m, &s| {
                        if !m {
                            *o = s;
                        }
                    });
                out
            }
            GreyMethod::Demosaic => {
                let mut out = Array2::<f32>::zeros(values.dim());
                let mut planes = 0.0f32;
                for (mask, sigma, den) in &self.planes {
                    let plane = normalized_convolution_masked_with(&values, mask, *sigma, den);
                    out += &plane;
                    planes += 1.0;
                }
                out / planes
            }
        })
    }
}

/// Mean of the `py` x `px` window starting at each pixel (clamped at the far edges).
fn tile_average(values: &Array2<f32>, py: usize, px: usize) -> Array2<f32> {
    let (h, w) = values.dim();
    Array2::from_shape_fn((h, w), |(y, x)| {
        let y0 = y.min(h.saturating_sub(py));
        let x0 = x.min(w.saturating_sub(px));
        let mut s = 0.0;
        let mut n = 0.0;
        for yy in y0..(y0 + py).min(h) {
            for xx in x0..(x0 + px).min(w) {
                s += values[[yy, xx]];
                n += 1.0;
            }
        }
        s / n
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cfa::{generate, Pattern};
    use crate::filters::normalized_convolution_masked;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The grey image as it was made before [`GreyImager`]: every normalized convolution with
    /// its own denominator.
    fn grey_image_direct(
        counts: &Array2<u32>,
        frames: usize,
        cfa: &Cfa,
        method: GreyMethod,
    ) -> Array2<f32> {
        let scale = 1.0 / frames as f32;
        let values = counts.mapv(|c| c as f32 * scale);
        match method {
            GreyMethod::TileAverage { py, px } => tile_average(&values, py, px),
            GreyMethod::InterpolateW => {
                let w_mask = cfa.mask(Channel::W);
                let smooth = normalized_convolution_masked(&values, &w_mask, 0.75);
                let mut out = values;
                Zip::from(&mut out)
                    .and(&w_mask)
                    .and(&smooth)
                    .for_each(|o, &m, &s| {
                        if !m {
                            *o = s;
                        }
                    });
                out
            }
            GreyMethod::Demosaic => {
                let frac = cfa.fractions();
                let mut out = Array2::<f32>::zeros(values.dim());
                let mut planes = 0.0f32;
                for ch in Channel::ALL {
                    let f = frac[ch.index()];
                    if f == 0.0 {
                        continue;
                    }
                    let sigma = (0.6 / f.sqrt()) as f32;
                    out += &normalized_convolution_masked(&values, &cfa.mask(ch), sigma);
                    planes += 1.0;
                }
                out / planes
            }
        }
    }

    /// One [`GreyImager`] over many blocks gives every block the numbers of the per-block
    /// computation bit for bit, for every method on RGBW, Bayer and random CFAs.
    #[test]
    fn imager_equals_per_block_grey_image() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let random = Cfa::new(Array2::from_shape_fn((23, 31), |_| rng.gen_range(0..4u8))).unwrap();
        let cfas = [
            generate(&Pattern::Rgbw75Regular, 24, 40, 0).unwrap(),
            generate(&Pattern::Bayer, 18, 26, 0).unwrap(),
            random,
        ];
        for cfa in &cfas {
            for method in [
                GreyMethod::InterpolateW,
                GreyMethod::Demosaic,
                GreyMethod::TileAverage { py: 2, px: 2 },
            ] {
                let imager = GreyImager::new(cfa, method);
                for frames in [1usize, 7, 250] {
                    let counts = cfa.codes().mapv(|_| rng.gen_range(0..=frames as u32));
                    let got = imager.image(&counts, frames).unwrap();
                    let expected = grey_image_direct(&counts, frames, cfa, method);
                    assert_eq!(got.dim(), expected.dim());
                    for (g, e) in got.iter().zip(&expected) {
                        assert_eq!(g.to_bits(), e.to_bits(), "{method:?} {frames}");
                    }
                    // (W interpolation on a CFA without W has nothing to interpolate.)
                    let has_w = cfa.fractions()[Channel::W.index()] > 0.0;
                    if method != GreyMethod::InterpolateW || has_w {
                        assert!(got.iter().any(|&v| v > 0.0), "{method:?} {frames}");
                    }
                }
                assert!(imager.image(&cfa.codes().mapv(|_| 1u32), 0).is_err());
            }
        }
    }
}
