//! LPIPS (Zhang, Isola, Efros, Shechtman, Wang: "The Unreasonable Effectiveness of Deep
//! Features as a Perceptual Metric", CVPR 2018), the third metric of the paper's Table 2
//! (§6), with the AlexNet backbone and the v0.1 linear weights — the `lpips` Python package's
//! default `LPIPS(net='alex', version='0.1')`.
//!
//! Network (as published; nothing here is our own heuristic): an sRGB image in [0, 1] is
//! mapped to [−1, 1], then normalised per channel by `(x − shift) / scale` with shift
//! (−0.030, −0.088, −0.188) and scale (0.458, 0.448, 0.450). The five convolutions of
//! torchvision's AlexNet `features` follow: conv0 11×11 stride 4 pad 2 (3→64), ReLU, max-pool
//! 3×3 stride 2; conv1 5×5 pad 2 (64→192), ReLU, max-pool 3×3 stride 2; conv2 3×3 pad 1
//! (192→384), conv3 (384→256), conv4 (256→256), each followed by a ReLU. The five ReLU outputs
//! are the features. Per layer: unit-normalise each pixel's feature vector over channels
//! (`f / (‖f‖ + 1e−10)`), square the difference of the two images' normalised features,
//! weight the channels by the learned non-negative `lin` weights, sum over channels and
//! average over pixels. LPIPS is the sum over the five layers; 0 for identical images, larger
//! for more different ones (about 0.1–0.6 for typical distortions).
//!
//! Weights: torchvision's pretrained AlexNet (BSD-3-Clause) and the LPIPS v0.1 linear layers
//! (richzhang/PerceptualSimilarity, BSD-2-Clause) are embedded in the library
//! (`data/lpips/`, notices in `data/lpips/NOTICE`), so nothing is downloaded.
//!
//! Implementation: feature maps are channel-last `(H, W, C)` f32; each convolution is an
//! im2col (the patch of every output pixel as one row, built band by band of output rows)
//! times the `(k·k·C_in, C_out)` weight matrix (`ndarray`'s `matrixmultiply` GEMM), bands in
//! parallel with rayon, and the two images in parallel.
#![deny(unsafe_code)]

use std::io::Cursor;
use std::sync::OnceLock;

use ndarray::linalg::general_mat_mul;
use ndarray::{Array, Array1, Array2, Array3, Array4, ArrayView3, Axis, Dimension, OwnedRepr};
use ndarray_npy::NpzReader;
use rayon::prelude::*;

use crate::error::{Error, Result};

/// The embedded weights: an `.npz` (stored, not compressed) holding `conv{i}.weight`
/// (out, in, kh, kw), `conv{i}.bias` (out,) and `lin{i}.weight` (channels,), i = 0..4, as
/// IEEE binary16 values stored as their uint16 bit patterns (numpy:
/// `np.load(f)[name].view(np.float16)`). They are the published float32 weights
/// (`shared/data/lpips/lpips_alex_v0.1_oihw.npz`) rounded to the nearest binary16 by
/// `examples/lpips_weights_f16.rs`, which halves the library (4.9 MB instead of 9.9 MB) and
/// moves LPIPS by at most 1.5e−4 on the reference pairs (0.39316 / 0.17024 / 0.50190 against
/// 0.39326 / 0.17027 / 0.50196 with float32; the published values are 0.3933 / 0.1703 /
/// 0.502).
pub const LPIPS_ALEX_NPZ: &[u8] = include_bytes!("../../data/lpips/lpips_alex_v0.1_f16.npz");

/// Name under which errors in the embedded weights are reported.
const EMBEDDED_NAME: &str = "<embedded>/data/lpips/lpips_alex_v0.1_f16.npz";

/// Smallest image side LPIPS-Alex accepts: the second max-pool needs a 3×3 input, i.e. conv0
/// must give at least 7 rows, `(n + 4 − 11) / 4 + 1 ≥ 7` ⇔ `n ≥ 31`.
pub const LPIPS_MIN_SIZE: usize = 31;

/// Input shift of the LPIPS scaling layer, per RGB channel (inputs in [−1, 1]).
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
/// Input scale of the LPIPS scaling layer, per RGB channel.
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// Stabiliser of the per-pixel unit normalisation (`lpips.normalize_tensor`).
const NORM_EPS: f32 = 1e-10;
/// Tolerance on the [0, 1] input range (sRGB encoding may round a hair past 1).
const RANGE_TOL: f32 = 1e-4;

/// Output pixels per im2col band: large enough for an efficient GEMM, small enough that a
/// band's patch matrix (pixels × k·k·C_in floats, ≤ 1.7 MB for conv3) stays in cache-sized
/// pieces and there are many bands to share among threads.
const BAND_PIXELS: usize = 256;

/// One convolution layer (square kernel), weights reshaped for im2col.
#[derive(Debug, Clone)]
struct Conv {
    cin: usize,
    cout: usize,
    k: usize,
    stride: usize,
    pad: usize,
    /// `(k·k·cin, cout)`; row index `(ky·k + kx)·cin + ci`, matching the patch layout.
    weight: Array2<f32>,
    bias: Array1<f32>,
}

/// (kernel, stride, padding, max-pool after) of AlexNet's five feature convolutions.
const LAYERS: [(usize, usize, usize, bool); 5] = [
    (11, 4, 2, true),
    (5, 1, 2, true),
    (3, 1, 1, false),
    (3, 1, 1, false),
    (3, 1, 1, false),
];

/// The LPIPS-Alex v0.1 network: five convolutions and five linear channel weightings.
#[derive(Debug, Clone)]
pub struct Lpips {
    convs: Vec<Conv>,
    lins: Vec<Array1<f32>>,
}

impl Lpips {
    /// The network with the embedded weights, parsed once per process.
    pub fn alex() -> Result<&'static Lpips> {
        static MODEL: OnceLock<std::result::Result<Lpips, String>> = OnceLock::new();
        MODEL
            .get_or_init(|| Lpips::from_npz_bytes(LPIPS_ALEX_NPZ).map_err(|e| e.to_string()))
            .as_ref()
            .map_err(|e| Error::format(EMBEDDED_NAME, e.clone()))
    }

    /// Parses weights laid out as the embedded file (see [`LPIPS_ALEX_NPZ`]): float32 arrays
    /// (e.g. the published `lpips_alex_v0.1_oihw.npz`) or binary16 bits as uint16.
    pub fn from_npz_bytes(bytes: &[u8]) -> Result<Lpips> {
        let mut npz = NpzReader::new(Cursor::new(bytes))
            .map_err(|e| Error::invalid(format!("LPIPS weights: not an npz archive: {e}")))?;
        let mut convs = Vec::with_capacity(LAYERS.len());
        let mut lins = Vec::with_capacity(LAYERS.len());
        let mut cin = 3;
        for (i, &(k, stride, pad, _)) in LAYERS.iter().enumerate() {
            let w: Array4<f32> = read_weights(&mut npz, &format!("conv{i}.weight"))?;
            let bias: Array1<f32> = read_weights(&mut npz, &format!("conv{i}.bias"))?;
            let lin: Array1<f32> = read_weights(&mut npz, &format!("lin{i}.weight"))?;
            let (cout, wcin, kh, kw) = w.dim();
            if wcin != cin || kh != k || kw != k || bias.len() != cout || lin.len() != cout {
                return Err(Error::invalid(format!(
                    "LPIPS weights: layer {i} has weight {:?}, bias {}, lin {}; expected \
                     (_, {cin}, {k}, {k}) with matching bias and lin",
                    w.dim(),
                    bias.len(),
                    lin.len()
                )));
            }
            let weight = Array2::from_shape_fn((k * k * cin, cout), |(r, co)| {
                let ci = r % cin;
                let kx = (r / cin) % k;
                let ky = r / (cin * k);
                w[[co, ci, ky, kx]]
            });
            convs.push(Conv {
                cin,
                cout,
                k,
                stride,
                pad,
                weight,
                bias,
            });
            lins.push(lin);
            cin = cout;
        }
        Ok(Lpips { convs, lins })
    }

    /// The five ReLU feature maps `(H_l, W_l, C_l)` of an sRGB image `(H, W, 3)` in [0, 1].
    /// Errors as [`Lpips::distance`].
    pub fn features(&self, image: ArrayView3<f32>) -> Result<Vec<Array3<f32>>> {
        check_image(image, "image")?;
        Ok(self.features_unchecked(image))
    }

    fn features_unchecked(&self, image: ArrayView3<f32>) -> Vec<Array3<f32>> {
        let mut x = image.mapv(|v| v * 2.0 - 1.0);
        for mut px in x.lanes_mut(Axis(2)) {
            for c in 0..3 {
                px[c] = (px[c] - SHIFT[c]) / SCALE[c];
            }
        }
        let mut feats: Vec<Array3<f32>> = Vec::with_capacity(self.convs.len());
        // The next layer's input: the pooled map, or (no pool) the previous feature map itself.
        let mut pooled = Some(x);
        for (conv, &(_, _, _, pool)) in self.convs.iter().zip(&LAYERS) {
            let f = match &pooled {
                Some(input) => conv_relu(input, conv),
                None => conv_relu(feats.last().expect("a previous layer"), conv),
            };
            pooled = pool.then(|| max_pool_3x3_s2(&f));
            feats.push(f);
        }
        feats
    }

    /// LPIPS distance between two sRGB images `(H, W, 3)` with values in [0, 1] (see the
    /// module documentation). Symmetric, 0 for identical images.
    ///
    /// Errors on a shape mismatch, a channel count other than 3, a side shorter than
    /// [`LPIPS_MIN_SIZE`], or values that are not finite or outside [0, 1].
    pub fn distance(&self, a: ArrayView3<f32>, b: ArrayView3<f32>) -> Result<f64> {
        if a.shape() != b.shape() {
            return Err(Error::invalid(format!(
                "LPIPS: estimate shape {:?} differs from truth shape {:?}",
                a.shape(),
                b.shape()
            )));
        }
        check_image(a, "estimate")?;
        check_image(b, "truth")?;
        let (fa, fb) = rayon::join(|| self.features_unchecked(a), || self.features_unchecked(b));
        Ok(fa
            .iter()
            .zip(&fb)
            .zip(&self.lins)
            .map(|((x, y), lin)| layer_distance(x, y, lin))
            .sum())
    }
}

/// Array `name` of an LPIPS weight archive as f32: stored as float32 (the published weights)
/// or as uint16 holding IEEE binary16 bit patterns (the embedded copy, see [`LPIPS_ALEX_NPZ`]).
fn read_weights<D: Dimension>(
    npz: &mut NpzReader<Cursor<&[u8]>>,
    name: &str,
) -> Result<Array<f32, D>> {
    match npz.by_name::<OwnedRepr<f32>, D>(name) {
        Ok(a) => Ok(a),
        Err(f32_err) => match npz.by_name::<OwnedRepr<u16>, D>(name) {
            Ok(bits) => Ok(bits.mapv(|b| half::f16::from_bits(b).to_f32())),
            Err(_) => Err(Error::invalid(format!(
                "LPIPS weights: {name}: {f32_err} (expected float32, or float16 bits as uint16)"
            ))),
        },
    }
}

/// LPIPS-Alex v0.1 between two sRGB images `(H, W, 3)` in [0, 1], with the embedded weights
/// ([`Lpips::alex`], [`Lpips::distance`]).
pub fn lpips(a: ArrayView3<f32>, b: ArrayView3<f32>) -> Result<f64> {
    Lpips::alex()?.distance(a, b)
}

fn check_image(image: ArrayView3<f32>, what: &str) -> Result<()> {
    let (h, w, c) = image.dim();
    if c != 3 {
        return Err(Error::invalid(format!(
            "LPIPS: {what} must be an RGB image (H, W, 3), got {c} channels"
        )));
    }
    if h < LPIPS_MIN_SIZE || w < LPIPS_MIN_SIZE {
        return Err(Error::invalid(format!(
            "LPIPS: {what} is {h}x{w}; AlexNet needs at least {LPIPS_MIN_SIZE}x{LPIPS_MIN_SIZE} \
             pixels"
        )));
    }
    if let Some(((y, x, ch), v)) = image
        .indexed_iter()
        .find(|(_, &v)| !(-RANGE_TOL..=1.0 + RANGE_TOL).contains(&v))
    {
        return Err(Error::invalid(format!(
            "LPIPS: {what} has value {v} at ({y}, {x}, {ch}); expected sRGB values in [0, 1]"
        )));
    }
    Ok(())
}

/// Convolution + bias + ReLU of a channel-last map, zero padding, by im2col and GEMM.
fn conv_relu(x: &Array3<f32>, conv: &Conv) -> Array3<f32> {
    let (h, w, cin) = x.dim();
    debug_assert_eq!(cin, conv.cin);
    let (k, s, p) = (conv.k, conv.stride, conv.pad);
    let ho = (h + 2 * p - k) / s + 1;
    let wo = (w + 2 * p - k) / s + 1;
    let kk = k * k * cin;
    let src = x.as_standard_layout();
    let src = src.as_slice().expect("standard layout");
    let band_rows = BAND_PIXELS.div_ceil(wo).max(1);
    let mut out = Array2::<f32>::zeros((ho * wo, conv.cout));
    out.axis_chunks_iter_mut(Axis(0), band_rows * wo)
        .into_par_iter()
        .enumerate()
        .for_each(|(band, mut chunk)| {
            let y0 = band * band_rows;
            let n = chunk.nrows();
            // im2col: row i = the zero-padded k×k×cin patch of output pixel (y0 + i / wo, i % wo).
            let mut patches = Array2::<f32>::zeros((n, kk));
            let pm = patches.as_slice_mut().expect("fresh array");
            for (i, row) in pm.chunks_mut(kk).enumerate() {
                let (yo, xo) = (y0 + i / wo, i % wo);
                for ky in 0..k {
                    let iy = (yo * s + ky) as isize - p as isize;
                    if iy < 0 || iy >= h as isize {
                        continue;
                    }
                    // Columns ix = xo·s + kx − p inside [0, w): a contiguous run of pixels.
                    let kx_lo = p.saturating_sub(xo * s);
                    let kx_hi = (w + p).saturating_sub(xo * s).min(k);
                    if kx_lo >= kx_hi {
                        continue;
                    }
                    let ix_lo = xo * s + kx_lo - p;
                    let len = (kx_hi - kx_lo) * cin;
                    let from = (iy as usize * w + ix_lo) * cin;
                    let to = (ky * k + kx_lo) * cin;
                    row[to..to + len].copy_from_slice(&src[from..from + len]);
                }
            }
            general_mat_mul(1.0, &patches, &conv.weight, 0.0, &mut chunk);
            for mut px in chunk.rows_mut() {
                for (v, &b) in px.iter_mut().zip(&conv.bias) {
                    *v = (*v + b).max(0.0);
                }
            }
        });
    out.into_shape_with_order((ho, wo, conv.cout))
        .expect("ho·wo rows")
}

/// 3×3 max-pool, stride 2, no padding (floor), of a channel-last map.
fn max_pool_3x3_s2(x: &Array3<f32>) -> Array3<f32> {
    let (h, w, c) = x.dim();
    let (ho, wo) = ((h - 3) / 2 + 1, (w - 3) / 2 + 1);
    let mut out = Array3::<f32>::from_elem((ho, wo, c), f32::NEG_INFINITY);
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(yo, mut row)| {
            for xo in 0..wo {
                let mut o = row.index_axis_mut(Axis(0), xo);
                for dy in 0..3 {
                    for dx in 0..3 {
                        let src = x.slice(ndarray::s![2 * yo + dy, 2 * xo + dx, ..]);
                        o.zip_mut_with(&src, |a, &b| *a = a.max(b));
                    }
                }
            }
        });
    out
}

/// One layer's term: mean over pixels of Σ_c lin_c·(â_c − b̂_c)², with â, b̂ the feature
/// vectors divided by (their norm + 1e−10).
fn layer_distance(a: &Array3<f32>, b: &Array3<f32>, lin: &Array1<f32>) -> f64 {
    let (h, w, _) = a.dim();
    let sum: f64 = a
        .lanes(Axis(2))
        .into_iter()
        .zip(b.lanes(Axis(2)))
        .map(|(fa, fb)| {
            let na = fa.iter().map(|v| v * v).sum::<f32>().sqrt() + NORM_EPS;
            let nb = fb.iter().map(|v| v * v).sum::<f32>().sqrt() + NORM_EPS;
            let d: f32 = fa
                .iter()
                .zip(fb.iter())
                .zip(lin.iter())
                .map(|((&x, &y), &l)| {
                    let e = x / na - y / nb;
                    l * e * e
                })
                .sum();
            f64::from(d)
        })
        .sum();
    sum / (h * w) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array4;

    /// Direct convolution (no im2col) for checking the fast path.
    fn conv_direct(x: &Array3<f32>, w: &Array4<f32>, b: &[f32], s: usize, p: usize) -> Array3<f32> {
        let (h, wd, cin) = x.dim();
        let (cout, _, k, _) = w.dim();
        let ho = (h + 2 * p - k) / s + 1;
        let wo = (wd + 2 * p - k) / s + 1;
        Array3::from_shape_fn((ho, wo, cout), |(yo, xo, co)| {
            let mut acc = b[co];
            for ci in 0..cin {
                for ky in 0..k {
                    for kx in 0..k {
                        let iy = (yo * s + ky) as isize - p as isize;
                        let ix = (xo * s + kx) as isize - p as isize;
                        if iy >= 0 && ix >= 0 && (iy as usize) < h && (ix as usize) < wd {
                            acc += w[[co, ci, ky, kx]] * x[[iy as usize, ix as usize, ci]];
                        }
                    }
                }
            }
            acc.max(0.0)
        })
    }

    fn pseudo(i: usize) -> f32 {
        ((i.wrapping_mul(2_654_435_761) >> 7) % 1000) as f32 / 1000.0 - 0.5
    }

    #[test]
    fn im2col_conv_matches_direct_convolution() {
        for &(k, s, p, cin, cout, h, w) in &[
            (11, 4, 2, 3, 5, 37, 45),
            (5, 1, 2, 4, 3, 9, 13),
            (3, 1, 1, 6, 7, 30, 11), // several bands (BAND_PIXELS / 11 rows each)
        ] {
            let x = Array3::from_shape_fn((h, w, cin), |(y, xx, c)| pseudo(y * 1000 + xx * 10 + c));
            let wt = Array4::from_shape_fn((cout, cin, k, k), |(a, b, c, d)| {
                pseudo(a * 7919 + b * 613 + c * 31 + d + 5)
            });
            let bias: Vec<f32> = (0..cout).map(|i| pseudo(i + 99) * 0.1).collect();
            let weight = Array2::from_shape_fn((k * k * cin, cout), |(r, co)| {
                wt[[co, r % cin, r / (cin * k), (r / cin) % k]]
            });
            let conv = Conv {
                cin,
                cout,
                k,
                stride: s,
                pad: p,
                weight,
                bias: Array1::from(bias.clone()),
            };
            let fast = conv_relu(&x, &conv);
            let slow = conv_direct(&x, &wt, &bias, s, p);
            assert_eq!(fast.dim(), slow.dim());
            for (a, b) in fast.iter().zip(slow.iter()) {
                assert!((a - b).abs() < 1e-4, "k={k}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn max_pool_takes_the_window_maximum() {
        let x = Array3::from_shape_fn((7, 8, 2), |(y, xx, c)| pseudo(y * 100 + xx * 3 + c));
        let out = max_pool_3x3_s2(&x);
        assert_eq!(out.dim(), (3, 3, 2));
        for ((yo, xo, c), &v) in out.indexed_iter() {
            let mut m = f32::NEG_INFINITY;
            for dy in 0..3 {
                for dx in 0..3 {
                    m = m.max(x[[2 * yo + dy, 2 * xo + dx, c]]);
                }
            }
            assert_eq!(v, m);
        }
    }
}
