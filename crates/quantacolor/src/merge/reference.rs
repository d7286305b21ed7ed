//! Reference image (paper §4.2, Fig. 4; supplement §1.2): every block's grey image is warped to
//! the reference grid and merged with the reference block by a per-frequency Wiener filter over
//! overlapping DFT tiles (HDR+, Hasinoff et al. 2016, §5). The result is a low-noise grey image
//! registered to the reference block; it steers the merge kernels and the robustness weights.
#![forbid(unsafe_code)]

use super::warp::{positive, warp_to_reference};
use super::GreyNoise;
use crate::error::{Error, Result};
use ndarray::{Array2, Array3, Axis};
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

    /// The 2-D DFT of `data` (rows, then columns) left transposed in `scratch`: entry
    /// (kx, ky) at kx·n + ky. The Wiener merge works frequency by frequency, so its spectra
    /// stay in this layout and one transpose per tile is saved; [`Fft2::inverse`] takes it.
    /// `data` is overwritten.
    fn forward_transposed(&self, data: &mut [Complex32], scratch: &mut [Complex32]) {
        self.forward.process(data); // every row (the buffer is n rows of n)
        transpose(data, scratch, self.n);
        self.forward.process(scratch); // every column
    }

    /// In-place inverse 2-D DFT (unnormalised) of a spectrum `data` in the transposed layout of
    /// [`Fft2::forward_transposed`]: back to row-major (rows over kx first, then columns, as
    /// a plain 2-D inverse transform), then rows, then columns; `scratch` is overwritten.
    fn inverse(&self, data: &mut [Complex32], scratch: &mut [Complex32]) {
        let n = self.n;
        transpose(data, scratch, n);
        self.inverse.process(scratch); // every row
        transpose(scratch, data, n);
        self.inverse.process(data); // every column
        transpose(data, scratch, n);
        data.copy_from_slice(scratch);
    }
}

fn transpose(src: &[Complex32], dst: &mut [Complex32], n: usize) {
    for (y, row) in src.chunks_exact(n).enumerate() {
        for (x, &v) in row.iter().enumerate() {
            dst[x * n + y] = v;
        }
    }
}

/// One tile of the Wiener merge while the blocks stream past: its origin, the DFT of the
/// reference block's tile, that tile's mean and the running sum over blocks.
struct TileState {
    y0: isize,
    x0: isize,
    reference: Vec<Complex32>,
    mean_ref: f32,
    acc: Vec<Complex32>,
}

/// Blocks warped at a time (in parallel) by [`reference_image_streamed`]: bounds its memory to
/// this many (H, W) images, whatever the number of blocks.
const WARP_GROUP: usize = 8;

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
    if flows_dense.len() != grey_blocks.len() {
        return Err(Error::invalid(format!(
            "reference image: {} grey blocks but {} flows",
            grey_blocks.len(),
            flows_dense.len()
        )));
    }
    reference_image_streamed(
        grey_blocks,
        &|k| flows_dense[k].clone(),
        ref_index,
        noise,
        config,
    )
}

/// [`reference_image`] with block k's dense flow made by `block_flow(k)` when it is needed:
/// blocks are warped a few at a time and merged into every tile's running sum, in block order
/// (the same sums, in the same order, as with all warped blocks at hand), so memory is a few
/// (H, W) images and one set of tile spectra whatever the number of blocks.
pub fn reference_image_streamed(
    grey_blocks: &[Array2<f32>],
    block_flow: &(dyn Fn(usize) -> Array3<f32> + Sync),
    ref_index: usize,
    noise: impl Into<GreyNoise>,
    config: &WienerConfig,
) -> Result<Array2<f32>> {
    let noise: GreyNoise = noise.into();
    let (h, w) = check_reference_input(grey_blocks, ref_index, noise, config)?;
    let warp = |k: usize| warp_to_reference(&grey_blocks[k], &block_flow(k));
    let reference_warped = warp(ref_index)?;
    if grey_blocks.len() == 1 {
        return Ok(reference_warped);
    }
    let layout = TileLayout::new(config.tile, h, w);
    let mut tiles = layout.reference_tiles(&reference_warped);
    drop(reference_warped);

    // The other blocks, a group warped in parallel, each merged into every tile in block order.
    let others: Vec<usize> = (0..grey_blocks.len()).filter(|&k| k != ref_index).collect();
    for group in others.chunks(WARP_GROUP) {
        let warped: Vec<Array2<f32>> = group.par_iter().map(|&k| warp(k)).collect::<Result<_>>()?;
        for img in &warped {
            layout.merge_block(&mut tiles, img, noise, config.c);
        }
    }
    Ok(layout.blend(tiles, grey_blocks.len()))
}

/// Checks the inputs of [`reference_image_streamed`]; returns the image shape (H, W).
fn check_reference_input(
    grey_blocks: &[Array2<f32>],
    ref_index: usize,
    noise: GreyNoise,
    config: &WienerConfig,
) -> Result<(usize, usize)> {
    let k_count = grey_blocks.len();
    if k_count == 0 {
        return Err(Error::invalid("reference image: no grey blocks given"));
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
    Ok((h, w))
}

/// The overlapping DFT tiles of the Wiener merge over an (H, W) image: `n` x `n` tiles at stride
/// n/2, origins from −n/2 so that every pixel is covered by two tiles per axis, blended with a
/// raised-cosine window.
struct TileLayout {
    n: usize,
    h: usize,
    w: usize,
    fft: Fft2,
    /// 1/n², the DFT's normalisation (and the tile mean's).
    norm: f32,
}

impl TileLayout {
    fn new(n: usize, h: usize, w: usize) -> Self {
        TileLayout {
            n,
            h,
            w,
            fft: Fft2::new(n),
            norm: 1.0 / (n * n) as f32,
        }
    }

    /// Tile origins (y0, x0), row-major.
    fn origins(&self) -> Vec<(isize, isize)> {
        let stride = self.n / 2;
        let origins = |len: usize| -> Vec<isize> {
            (0..)
                .map(|i| -(stride as isize) + (i * stride) as isize)
                .take_while(|&o| o < len as isize)
                .collect()
        };
        let (oy, ox) = (origins(self.h), origins(self.w));
        oy.iter()
            .flat_map(|&y0| ox.iter().map(move |&x0| (y0, x0)))
            .collect()
    }

    /// Tile (y0, x0) of the row-major (H, W) image `img` into `buf` (edges clamped); returns
    /// the tile mean (the pixels summed row by row, left to right).
    fn load(&self, img: &[f32], y0: isize, x0: isize, buf: &mut [Complex32]) -> f32 {
        let (n, h, w) = (self.n, self.h, self.w);
        let mut sum = 0.0;
        // Tiles clear of the left and right edges copy a plain run of each row.
        let inside = (x0 >= 0 && x0 as usize + n <= w).then_some(x0 as usize);
        for (i, out) in buf.chunks_exact_mut(n).take(n).enumerate() {
            let y = (y0 + i as isize).clamp(0, h as isize - 1) as usize;
            let row = &img[y * w..(y + 1) * w];
            match inside {
                Some(x0) => {
                    for (o, &v) in out.iter_mut().zip(&row[x0..x0 + n]) {
                        sum += v;
                        *o = Complex32::new(v, 0.0);
                    }
                }
                None => {
                    for (j, o) in out.iter_mut().enumerate() {
                        let v = row[(x0 + j as isize).clamp(0, w as isize - 1) as usize];
                        sum += v;
                        *o = Complex32::new(v, 0.0);
                    }
                }
            }
        }
        sum * self.norm
    }

    /// Every tile's reference spectrum (in the layout of [`Fft2::forward_transposed`]), its
    /// mean, and the running sum started with it.
    fn reference_tiles(&self, reference_warped: &Array2<f32>) -> Vec<TileState> {
        let n = self.n;
        let image = reference_warped.as_standard_layout();
        let image = image.as_slice().expect("standard layout");
        self.origins()
            .par_iter()
            .map(|&(y0, x0)| {
                let mut tile = vec![Complex32::default(); n * n];
                let mut reference = vec![Complex32::default(); n * n];
                let mean_ref = self.load(image, y0, x0, &mut tile);
                self.fft.forward_transposed(&mut tile, &mut reference);
                let acc = reference.clone();
                TileState {
                    y0,
                    x0,
                    reference,
                    mean_ref,
                    acc,
                }
            })
            .collect()
    }

    /// Adds one warped block `img` to every tile's running sum, per frequency
    /// T_k + A_k (T_ref − T_k) with A_k = |D_k|² / (|D_k|² + c·σ²), D_k = T_ref − T_k.
    /// Spectra in the layout of [`Fft2::forward_transposed`], as the tiles hold them.
    fn merge_block(&self, tiles: &mut [TileState], img: &Array2<f32>, noise: GreyNoise, c: f32) {
        let n = self.n;
        let image = img.as_standard_layout();
        let image = image.as_slice().expect("standard layout");
        tiles.par_iter_mut().for_each_init(
            || {
                (
                    vec![Complex32::default(); n * n],
                    vec![Complex32::default(); n * n],
                )
            },
            |(pixels, other), tile| {
                let mean_k = self.load(image, tile.y0, tile.x0, pixels);
                self.fft.forward_transposed(pixels, other);
                let sigma2 =
                    (n * n) as f32 * (noise.variance(tile.mean_ref) + noise.variance(mean_k));
                let noise = c * sigma2.max(f32::MIN_POSITIVE);
                for ((a, &t_ref), &t_k) in
                    tile.acc.iter_mut().zip(&tile.reference).zip(other.iter())
                {
                    let d = t_ref - t_k;
                    let d2 = d.norm_sqr();
                    let shrink = d2 / (d2 + noise);
                    *a += t_k + d * shrink;
                }
            },
        );
    }

    /// The merged image: each tile's sum over `k_count` blocks back from the DFT and divided by
    /// `k_count`, the tiles blended with the raised-cosine window (weights normalised).
    fn blend(&self, mut tiles: Vec<TileState>, k_count: usize) -> Array2<f32> {
        let (n, h, w) = (self.n, self.h, self.w);
        let scale = self.norm / k_count as f32;
        tiles.par_iter_mut().for_each_init(
            || vec![Complex32::default(); n * n],
            |scratch, tile| {
                self.fft.inverse(&mut tile.acc, scratch);
                for v in tile.acc.iter_mut() {
                    *v = Complex32::new(v.re * scale, 0.0);
                }
            },
        );
        let window = raised_cosine(n);
        let mut num = Array2::<f32>::zeros((h, w));
        let mut den = Array2::<f32>::zeros((h, w));
        // Bands of rows in parallel; every pixel still adds its tiles in tile order.
        const BAND_ROWS: usize = 8;
        num.axis_chunks_iter_mut(Axis(0), BAND_ROWS)
            .into_par_iter()
            .zip(den.axis_chunks_iter_mut(Axis(0), BAND_ROWS))
            .enumerate()
            .for_each(|(band, (mut num, mut den))| {
                let first = (band * BAND_ROWS) as isize;
                let rows = first..first + num.nrows() as isize;
                for tile in &tiles {
                    for i in 0..n {
                        let y = tile.y0 + i as isize;
                        if !rows.contains(&y) {
                            continue;
                        }
                        let y = (y - first) as usize;
                        for j in 0..n {
                            let x = tile.x0 + j as isize;
                            if x < 0 || x >= w as isize {
                                continue;
                            }
                            let wt = window[i] * window[j];
                            num[[y, x as usize]] += wt * tile.acc[i * n + j].re;
                            den[[y, x as usize]] += wt;
                        }
                    }
                }
                num.zip_mut_with(&den, |v, &d| *v /= d);
            });
        num
    }
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
