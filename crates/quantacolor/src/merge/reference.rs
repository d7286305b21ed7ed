//! Reference image (paper §4.2, Fig. 4; supplement §1.2): every block's grey image is warped to
//! the reference grid and merged with the reference block by a per-frequency Wiener filter over
//! overlapping DFT tiles (HDR+, Hasinoff et al. 2016, §5). The result is a low-noise grey image
//! registered to the reference block; it steers the merge kernels and the robustness weights.

use super::warp::{positive, warp_to_reference};
use super::GreyNoise;
use crate::error::{Error, Result};
use ndarray::{Array2, Array3};
use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Wiener merge of the reference image (supplement §1.2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct WienerConfig {
    /// Tile side (px); tiles overlap by half and are blended with a raised cosine.
    pub tile: usize, // 16 px
    /// Noise-scaling constant c of A = |D|² / (|D|² + c·σ²) (HDR+ tuning, dimensionless).
    pub c: f32, // 8
}

impl Default for WienerConfig {
    fn default() -> Self {
        WienerConfig { tile: 16, c: 8.0 }
    }
}

/// Raised-cosine window of length `n`: w(i) = ½ − ½·cos(2π(i + ½)/n). Shifted by n/2 its copies
/// sum to one, and it is positive everywhere.
fn raised_cosine(n: usize) -> Vec<f32> {
    (0..n)
        .map(|i| {
            let t = (i as f32 + 0.5) / n as f32;
            0.5 - 0.5 * (2.0 * std::f32::consts::PI * t).cos()
        })
        .collect()
}

/// In-place 2-D DFT of a square `n`x`n` tile (row-major) with 1-D transforms of length `n`.
struct Fft2 {
    n: usize,
    forward: Arc<dyn Fft<f32>>,
    inverse: Arc<dyn Fft<f32>>,
}

impl Fft2 {
    fn new(n: usize) -> Self {
        let mut planner = FftPlanner::new();
        Fft2 {
            n,
            forward: planner.plan_fft_forward(n),
            inverse: planner.plan_fft_inverse(n),
        }
    }

    fn run(&self, data: &mut [Complex32], scratch: &mut [Complex32], inverse: bool) {
        let n = self.n;
        let fft = if inverse {
            &self.inverse
        } else {
            &self.forward
        };
        fft.process(data); // every row (the buffer is n rows of n)
        transpose(data, scratch, n);
        fft.process(scratch); // every column
        transpose(scratch, data, n);
    }
}

fn transpose(src: &[Complex32], dst: &mut [Complex32], n: usize) {
    for y in 0..n {
        for x in 0..n {
            dst[x * n + y] = src[y * n + x];
        }
    }
}

/// One row of merged tiles: its y origin and (x origin, n·n values) per tile.
type TileRow = (isize, Vec<(isize, Vec<f32>)>);

/// Merges grey block images into a reference image (supplement §1.2).
///
/// `grey_blocks[k]` are (H, W) block means (mean bit rate of a grey channel over the block's
/// frames, or mean digital number of multi-bit frames, comparable across blocks);
/// `flows_dense[k]` are (H, W, 2) dense flows (dy, dx) from the reference grid into block k;
/// `ref_index` names the reference block (its own flow should be zero); `noise` is the number
/// of frames averaged into one grey value with the pixel model ([`GreyNoise`]; a plain number
/// is that many Bernoulli trials). Each block is warped to the reference grid by bilinear sampling at p + flow(p);
/// then, in 16x16 tiles at stride 8, per DFT frequency
/// A_k = |D_k|² / (|D_k|² + c·σ²) with D_k = T_ref − T_k, and the merged tile is
/// Σ_k (T_k + A_k (T_ref − T_k)) / K. σ² is the variance of D_k per frequency for the pixel
/// noise v(μ) of the model at the tile mean μ (binomial μ(1−μ)/trials for binary frames,
/// Gaussian–Poisson for multi-bit ones): n²·(v_ref + v_k) for an n x n tile. Tiles are
/// blended with a raised-cosine window (weights normalised, so borders stay unbiased).
/// A misaligned block differs strongly from the reference, so A → 1 and it contributes the
/// reference's content instead of its own (no ghosting).
pub fn reference_image(
    grey_blocks: &[Array2<f32>],
    flows_dense: &[Array3<f32>],
    ref_index: usize,
    noise: impl Into<GreyNoise>,
    config: &WienerConfig,
) -> Result<Array2<f32>> {
    let noise: GreyNoise = noise.into();
    let k_count = grey_blocks.len();
    if k_count == 0 {
        return Err(Error::invalid("reference image: no grey blocks given"));
    }
    if flows_dense.len() != k_count {
        return Err(Error::invalid(format!(
            "reference image: {k_count} grey blocks but {} flows",
            flows_dense.len()
        )));
    }
    if ref_index >= k_count {
        return Err(Error::invalid(format!(
            "reference image: reference block {ref_index} is outside the {k_count} blocks"
        )));
    }
    if config.tile < 2 || config.tile & 1 == 1 {
        return Err(Error::invalid(format!(
            "reference image: tile size {} must be even and at least 2",
            config.tile
        )));
    }
    if !positive(noise.trials) || config.c.is_nan() || config.c < 0.0 {
        return Err(Error::invalid(
            "reference image: trials must be positive and c non-negative",
        ));
    }
    let (h, w) = grey_blocks[ref_index].dim();
    for (k, g) in grey_blocks.iter().enumerate() {
        if g.dim() != (h, w) {
            return Err(Error::invalid(format!(
                "reference image: grey block {k} has shape {:?}, block {ref_index} has ({h}, {w})",
                g.dim()
            )));
        }
    }
    let warped: Vec<Array2<f32>> = grey_blocks
        .iter()
        .zip(flows_dense)
        .map(|(g, f)| warp_to_reference(g, f))
        .collect::<Result<_>>()?;
    if k_count == 1 {
        return Ok(warped.into_iter().next().expect("one block"));
    }

    let n = config.tile;
    let stride = n / 2;
    let window = raised_cosine(n);
    let fft = Fft2::new(n);
    let norm = 1.0 / (n * n) as f32;
    // Tile origins from −stride so that every pixel is covered by two tiles per axis.
    let origins = |len: usize| -> Vec<isize> {
        (0..)
            .map(|i| -(stride as isize) + (i * stride) as isize)
            .take_while(|&o| o < len as isize)
            .collect()
    };
    let (oy, ox) = (origins(h), origins(w));
    let at = |img: &Array2<f32>, y: isize, x: isize| -> f32 {
        img[[
            y.clamp(0, h as isize - 1) as usize,
            x.clamp(0, w as isize - 1) as usize,
        ]]
    };

    // Each tile row in parallel: (origin_y, Vec<(origin_x, merged tile)>).
    let rows: Vec<TileRow> = oy
        .par_iter()
        .map(|&y0| {
            let mut tiles = Vec::with_capacity(ox.len());
            let mut reference = vec![Complex32::default(); n * n];
            let mut other = vec![Complex32::default(); n * n];
            let mut acc = vec![Complex32::default(); n * n];
            let mut scratch = vec![Complex32::default(); n * n];
            for &x0 in &ox {
                let load = |img: &Array2<f32>, buf: &mut [Complex32]| -> f32 {
                    let mut sum = 0.0;
                    for i in 0..n {
                        for j in 0..n {
                            let v = at(img, y0 + i as isize, x0 + j as isize);
                            sum += v;
                            buf[i * n + j] = Complex32::new(v, 0.0);
                        }
                    }
                    sum * norm
                };
                let mean_ref = load(&warped[ref_index], &mut reference);
                fft.run(&mut reference, &mut scratch, false);
                acc.copy_from_slice(&reference);
                for (k, img) in warped.iter().enumerate() {
                    if k == ref_index {
                        continue;
                    }
                    let mean_k = load(img, &mut other);
                    fft.run(&mut other, &mut scratch, false);
                    let sigma2 =
                        (n * n) as f32 * (noise.variance(mean_ref) + noise.variance(mean_k));
                    let noise = config.c * sigma2.max(f32::MIN_POSITIVE);
                    for ((a, &t_ref), &t_k) in acc.iter_mut().zip(&reference).zip(&other) {
                        let d = t_ref - t_k;
                        let d2 = d.norm_sqr();
                        let shrink = d2 / (d2 + noise);
                        *a += t_k + d * shrink;
                    }
                }
                fft.run(&mut acc, &mut scratch, true);
                let scale = norm / k_count as f32;
                tiles.push((x0, acc.iter().map(|v| v.re * scale).collect()));
            }
            (y0, tiles)
        })
        .collect();

    let mut num = Array2::<f32>::zeros((h, w));
    let mut den = Array2::<f32>::zeros((h, w));
    for (y0, tiles) in rows {
        for (x0, tile) in tiles {
            for i in 0..n {
                let y = y0 + i as isize;
                if y < 0 || y >= h as isize {
                    continue;
                }
                for j in 0..n {
                    let x = x0 + j as isize;
                    if x < 0 || x >= w as isize {
                        continue;
                    }
                    let wt = window[i] * window[j];
                    num[[y as usize, x as usize]] += wt * tile[i * n + j];
                    den[[y as usize, x as usize]] += wt;
                }
            }
        }
    }
    num.zip_mut_with(&den, |v, &d| *v /= d);
    Ok(num)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raised_cosine_halves_sum_to_one() {
        let w = raised_cosine(16);
        for i in 0..8 {
            assert!((w[i] + w[i + 8] - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn identical_blocks_merge_to_themselves() {
        let img = Array2::from_shape_fn((20, 27), |(y, x)| {
            0.1 + 0.01 * ((y * 3 + x * 7) % 11) as f32
        });
        let flows = vec![Array3::zeros((20, 27, 2)); 3];
        let out = reference_image(
            &vec![img.clone(); 3],
            &flows,
            1,
            100.0,
            &WienerConfig::default(),
        )
        .unwrap();
        for (a, b) in out.iter().zip(&img) {
            assert!((a - b).abs() < 1e-4);
        }
    }
}
