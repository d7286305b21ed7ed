//! Image quality metrics used in the paper's evaluation (§6, Fig. 8–10, Table 2): PSNR and SSIM,
//! computed exactly as scikit-image computes them, plus an [`evaluate`] helper that applies the
//! paper-style protocol (border crop, exposure normalisation, clipping, linear and sRGB scores).
//! The table's third metric, LPIPS (AlexNet, v0.1), lives in [`lpips`](mod@lpips);
//! [`evaluate_lpips`] applies it to the same sRGB images the protocol scores.
//!
//! [`ssim`] reproduces `skimage.metrics.structural_similarity` with its defaults and
//! `data_range` given: a 7×7 uniform window (`scipy.ndimage.uniform_filter`, `mode='reflect'`,
//! i.e. half-sample symmetric extension `d c b a | a b c d | d c b a`), K1 = 0.01, K2 = 0.03,
//! sample covariances (normalised by 49/48), and the mean of the SSIM map after cropping
//! `(7 − 1) / 2 = 3` pixels from every side. Colour images `(H, W, C)` give the mean of the
//! per-channel SSIMs (`channel_axis=-1`). Arithmetic is in f64; scikit-image computes in the
//! input's float type, so the two agree to ~1e-12 for float64 input (the reference test) and to
//! float32 rounding for float32 input. [`psnr`] is `peak_signal_noise_ratio`:
//! `10·log10(data_range² / MSE)`, `+∞` for identical images.
#![deny(unsafe_code)]

pub mod lpips;

pub use lpips::{lpips, Lpips, LPIPS_MIN_SIZE};

use ndarray::{
    s, Array3, ArrayView, ArrayView2, ArrayView3, ArrayViewD, Axis, Dimension, Ix2, Ix3,
};
use rayon::prelude::*;

use crate::color::srgb::linear_to_srgb;
use crate::error::{Error, Result};
use crate::stats::percentile_linear;

/// SSIM window side (pixels): scikit-image's default for uniform weights.
pub const SSIM_WIN_SIZE: usize = 7;
/// SSIM luminance stabiliser: C1 = (K1·data_range)².
pub const SSIM_K1: f64 = 0.01;
/// SSIM contrast stabiliser: C2 = (K2·data_range)².
pub const SSIM_K2: f64 = 0.03;

/// Rows per parallel task in the vertical box-filter pass.
const ROW_BLOCK: usize = 32;

fn check_data_range(data_range: f64) -> Result<()> {
    if data_range.is_finite() && data_range > 0.0 {
        Ok(())
    } else {
        Err(Error::invalid(format!(
            "data_range must be positive and finite, got {data_range}"
        )))
    }
}

fn check_same_shape(a: &[usize], b: &[usize]) -> Result<()> {
    if a == b {
        Ok(())
    } else {
        Err(Error::invalid(format!(
            "estimate shape {a:?} differs from truth shape {b:?}"
        )))
    }
}

/// Peak signal-to-noise ratio in dB, `10·log10(data_range² / MSE)`, over arrays of any shape
/// (as `skimage.metrics.peak_signal_noise_ratio`). Identical images give `+∞`.
///
/// Errors on a shape mismatch, empty arrays or a non-positive `data_range`.
pub fn psnr<D: Dimension>(
    estimate: ArrayView<f32, D>,
    truth: ArrayView<f32, D>,
    data_range: f64,
) -> Result<f64> {
    check_same_shape(estimate.shape(), truth.shape())?;
    check_data_range(data_range)?;
    if estimate.is_empty() {
        return Err(Error::invalid("PSNR of empty images"));
    }
    let sse: f64 = estimate
        .iter()
        .zip(truth.iter())
        .map(|(&a, &b)| {
            let d = f64::from(a) - f64::from(b);
            d * d
        })
        .sum();
    let mse = sse / estimate.len() as f64;
    Ok(10.0 * (data_range * data_range / mse).log10())
}

/// Index into `0..n` of position `i` under scipy's `mode='reflect'` (half-sample symmetric,
/// periodic with period 2n for offsets beyond one reflection).
fn reflect_index(i: isize, n: usize) -> usize {
    let n = n as isize;
    let m = i.rem_euclid(2 * n);
    (if m < n { m } else { 2 * n - 1 - m }) as usize
}

/// Mean over a `(2r+1)×(2r+1)` window with reflect boundaries, i.e.
/// `scipy.ndimage.uniform_filter(src, size=2r+1, mode='reflect')` on an `h×w` row-major plane.
/// Separable: running sums along rows, then running sums down columns, both parallel over rows.
fn box_filter_reflect(src: &[f64], h: usize, w: usize, r: usize) -> Vec<f64> {
    let ri = r as isize;
    let norm = 1.0 / (2 * r + 1) as f64;
    // Horizontal pass: one running sum per row.
    let mut tmp = vec![0.0f64; h * w];
    tmp.par_chunks_mut(w).zip(src.par_chunks(w)).for_each_init(
        || vec![0.0f64; w + 2 * r],
        |ext, (out, row)| {
            // The row with r reflected samples on each side; avoids a modulo per sample.
            for (k, e) in ext.iter_mut().enumerate() {
                *e = row[reflect_index(k as isize - ri, w)];
            }
            let mut acc: f64 = ext[..2 * r + 1].iter().sum();
            out[0] = acc * norm;
            for x in 1..w {
                acc += ext[x + 2 * r] - ext[x - 1];
                out[x] = acc * norm;
            }
        },
    );
    // Vertical pass: a running row-vector sum, restarted at each block of rows.
    let mut dst = vec![0.0f64; h * w];
    dst.par_chunks_mut(ROW_BLOCK * w)
        .enumerate()
        .for_each(|(b, block)| {
            let y0 = b * ROW_BLOCK;
            let row = |i: isize| {
                let y = reflect_index(i, h);
                &tmp[y * w..(y + 1) * w]
            };
            let mut acc = vec![0.0f64; w];
            for k in -ri..=ri {
                for (a, &v) in acc.iter_mut().zip(row(y0 as isize + k)) {
                    *a += v;
                }
            }
            for (j, out) in block.chunks_mut(w).enumerate() {
                let y = (y0 + j) as isize;
                if j > 0 {
                    let (add, sub) = (row(y + ri), row(y - ri - 1));
                    for ((a, &p), &m) in acc.iter_mut().zip(add).zip(sub) {
                        *a += p - m;
                    }
                }
                for (o, &a) in out.iter_mut().zip(&acc) {
                    *o = a * norm;
                }
            }
        });
    dst
}

/// Mean SSIM of one `h×w` plane pair (f64, row-major), skimage defaults.
fn ssim_plane(x: &[f64], y: &[f64], h: usize, w: usize, data_range: f64) -> f64 {
    let r = (SSIM_WIN_SIZE - 1) / 2;
    let np = (SSIM_WIN_SIZE * SSIM_WIN_SIZE) as f64;
    let cov_norm = np / (np - 1.0); // sample covariance
    let c1 = (SSIM_K1 * data_range).powi(2);
    let c2 = (SSIM_K2 * data_range).powi(2);

    let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
    let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
    let xy: Vec<f64> = x.iter().zip(y).map(|(a, b)| a * b).collect();
    let inputs = [x, y, &xx[..], &yy[..], &xy[..]];
    let filtered: Vec<Vec<f64>> = inputs
        .par_iter()
        .map(|p| box_filter_reflect(p, h, w, r))
        .collect();
    let (ux, uy, uxx, uyy, uxy) = (
        &filtered[0],
        &filtered[1],
        &filtered[2],
        &filtered[3],
        &filtered[4],
    );

    // Sum of the SSIM map over the interior (crop r pixels from each side), row by row.
    let row_sums: Vec<f64> = (r..h - r)
        .into_par_iter()
        .map(|yi| {
            let mut acc = 0.0;
            for xi in r..w - r {
                let i = yi * w + xi;
                let (mx, my) = (ux[i], uy[i]);
                let vx = cov_norm * (uxx[i] - mx * mx);
                let vy = cov_norm * (uyy[i] - my * my);
                let vxy = cov_norm * (uxy[i] - mx * my);
                let a1 = 2.0 * mx * my + c1;
                let a2 = 2.0 * vxy + c2;
                let b1 = mx * mx + my * my + c1;
                let b2 = vx + vy + c2;
                acc += (a1 * a2) / (b1 * b2);
            }
            acc
        })
        .collect();
    let count = ((h - 2 * r) * (w - 2 * r)) as f64;
    row_sums.iter().sum::<f64>() / count
}

fn plane_to_f64(v: ArrayView2<f32>) -> Vec<f64> {
    v.iter().map(|&a| f64::from(a)).collect()
}

fn check_ssim_size(h: usize, w: usize) -> Result<()> {
    if h < SSIM_WIN_SIZE || w < SSIM_WIN_SIZE {
        Err(Error::invalid(format!(
            "SSIM needs images of at least {SSIM_WIN_SIZE}x{SSIM_WIN_SIZE} pixels, got {h}x{w}"
        )))
    } else {
        Ok(())
    }
}

/// Mean SSIM of two grey images `(H, W)`, as `skimage.metrics.structural_similarity(estimate,
/// truth, data_range=data_range)` (see the module documentation for the exact definition).
///
/// Errors on a shape mismatch, images smaller than 7×7 or a non-positive `data_range`.
pub fn ssim_gray(
    estimate: ArrayView2<f32>,
    truth: ArrayView2<f32>,
    data_range: f64,
) -> Result<f64> {
    check_same_shape(estimate.shape(), truth.shape())?;
    check_data_range(data_range)?;
    let (h, w) = estimate.dim();
    check_ssim_size(h, w)?;
    Ok(ssim_plane(
        &plane_to_f64(estimate),
        &plane_to_f64(truth),
        h,
        w,
        data_range,
    ))
}

/// Mean SSIM of two channel-last images `(H, W, C)`: the mean over channels of the per-channel
/// SSIM, as scikit-image with `channel_axis=-1`. Channels are computed in parallel.
pub fn ssim_color(
    estimate: ArrayView3<f32>,
    truth: ArrayView3<f32>,
    data_range: f64,
) -> Result<f64> {
    check_same_shape(estimate.shape(), truth.shape())?;
    check_data_range(data_range)?;
    let (h, w, c) = estimate.dim();
    check_ssim_size(h, w)?;
    if c == 0 {
        return Err(Error::invalid("SSIM of an image with no channels"));
    }
    let per_channel: Vec<f64> = (0..c)
        .into_par_iter()
        .map(|ch| {
            let x = plane_to_f64(estimate.index_axis(Axis(2), ch));
            let y = plane_to_f64(truth.index_axis(Axis(2), ch));
            ssim_plane(&x, &y, h, w, data_range)
        })
        .collect();
    Ok(per_channel.iter().sum::<f64>() / c as f64)
}

/// Mean SSIM of a grey `(H, W)` or channel-last colour `(H, W, C)` image pair; dispatches to
/// [`ssim_gray`] or [`ssim_color`]. Other dimensionalities are an error.
pub fn ssim(estimate: ArrayViewD<f32>, truth: ArrayViewD<f32>, data_range: f64) -> Result<f64> {
    check_same_shape(estimate.shape(), truth.shape())?;
    match estimate.ndim() {
        2 => ssim_gray(
            estimate.into_dimensionality::<Ix2>().expect("ndim checked"),
            truth.into_dimensionality::<Ix2>().expect("ndim checked"),
            data_range,
        ),
        3 => ssim_color(
            estimate.into_dimensionality::<Ix3>().expect("ndim checked"),
            truth.into_dimensionality::<Ix3>().expect("ndim checked"),
            data_range,
        ),
        n => Err(Error::invalid(format!(
            "SSIM expects (H, W) or (H, W, C) images, got {n} dimensions"
        ))),
    }
}

/// Evaluation protocol for [`evaluate`].
/// The default scores the whole image as given (no crop, no normalisation).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EvalOptions {
    /// Pixels cropped from every side before scoring (alignment and filter borders).
    pub border: usize,
    /// If set, both images are multiplied by the same factor so that this percentile (0–100,
    /// numpy's default linear interpolation, over all pixels and channels) of the cropped truth
    /// becomes 1, e.g. 99.5. Without it the images are scored as given.
    pub normalize_percentile: Option<f64>,
}

/// Scores of one reconstruction against its ground truth (dB for PSNR).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Scores {
    /// PSNR of the linear images (data range 1 after normalisation and clipping).
    pub psnr_linear: f64,
    /// SSIM of the linear images.
    pub ssim_linear: f64,
    /// PSNR after sRGB encoding of both images.
    pub psnr_srgb: f64,
    /// SSIM after sRGB encoding of both images.
    pub ssim_srgb: f64,
}

/// Scores a linear colour reconstruction `(H, W, C)` against the ground truth the paper's way
/// (§6): crop `border` pixels from every side; optionally scale both images by the one factor
/// that maps the truth's `normalize_percentile` to 1 (so scores do not depend on the exposure
/// units); clip both to [0, 1] (a display cannot show more, and highlights beyond the range
/// would otherwise dominate the MSE); then PSNR and SSIM with `data_range = 1`, both on the linear
/// values and after sRGB encoding (`color::srgb::linear_to_srgb`), which weights shadows
/// closer to perception.
///
/// Errors on a shape mismatch, a border that leaves nothing (or less than SSIM's 7×7 window), a
/// percentile outside (0, 100] or a truth whose percentile is not positive, or non-finite values.
pub fn evaluate(
    estimate: ArrayView3<f32>,
    truth: ArrayView3<f32>,
    opts: &EvalOptions,
) -> Result<Scores> {
    let (est_lin, tru_lin) = protocol_linear(estimate, truth, opts)?;
    let (est_srgb, tru_srgb) = (encode_srgb(&est_lin), encode_srgb(&tru_lin));
    Ok(Scores {
        psnr_linear: psnr(est_lin.view(), tru_lin.view(), 1.0)?,
        ssim_linear: ssim_color(est_lin.view(), tru_lin.view(), 1.0)?,
        psnr_srgb: psnr(est_srgb.view(), tru_srgb.view(), 1.0)?,
        ssim_srgb: ssim_color(est_srgb.view(), tru_srgb.view(), 1.0)?,
    })
}

/// LPIPS (AlexNet v0.1, [`lpips()`]; paper Table 2) of a linear colour reconstruction against
/// the ground truth under the same protocol as [`evaluate`]: border crop, optional percentile
/// normalisation, clipping to [0, 1], then sRGB encoding (`color::srgb::linear_to_srgb`) —
/// LPIPS is defined on display-referred sRGB images, so it scores exactly the images whose
/// `psnr_srgb` / `ssim_srgb` [`evaluate`] reports. Kept apart from [`evaluate`] because a
/// network pass costs far more than PSNR and SSIM (about 0.1–0.3 s per 496x254 pair).
///
/// Errors as [`evaluate`], and on images smaller than [`LPIPS_MIN_SIZE`] after the crop or
/// with other than 3 channels.
pub fn evaluate_lpips(
    estimate: ArrayView3<f32>,
    truth: ArrayView3<f32>,
    opts: &EvalOptions,
) -> Result<f64> {
    let (est_lin, tru_lin) = protocol_linear(estimate, truth, opts)?;
    lpips(encode_srgb(&est_lin).view(), encode_srgb(&tru_lin).view())
}

/// Fewest expected frames without a detection for a pixel to count as measurable in
/// [`measurable_light_ratio`] (issue 45's protocol): brighter pixels are censored by
/// saturation (paper §3, Eq. 3) and no method can be held to their light.
pub const MEASURABLE_DARK_FRAMES: f64 = 100.0;

/// The light a linear reconstruction keeps: Σ estimate / Σ truth over the pixels (outside
/// `border`) that a binary capture of `frames` frames can measure, those whose true W flux
/// λ_W = Σ_c w_c·truth_c leaves at least [`MEASURABLE_DARK_FRAMES`] expected frames without a
/// detection (frames·e^(−λ_W)). Both images in the merge's units (detections per frame of an
/// R, G or B pixel); 1 = all the light. `None` where no pixel is measurable.
pub fn measurable_light_ratio(
    estimate: ArrayView3<f32>,
    truth: ArrayView3<f32>,
    w_weights: [f64; 3],
    frames: usize,
    border: usize,
) -> Result<Option<f64>> {
    check_same_shape(estimate.shape(), truth.shape())?;
    let (h, w, c) = truth.dim();
    if c != 3 || 2 * border >= h || 2 * border >= w {
        return Err(Error::invalid(format!(
            "light ratio: needs (H, W, 3) images larger than twice the border {border}, got \
             {h}x{w}x{c}"
        )));
    }
    let max_flux = (frames as f64 / MEASURABLE_DARK_FRAMES).ln();
    let (mut kept, mut total) = (0.0f64, 0.0f64);
    for y in border..h - border {
        for x in border..w - border {
            let t = [0, 1, 2].map(|ch| f64::from(truth[[y, x, ch]]));
            let w_flux: f64 = t.iter().zip(w_weights).map(|(v, k)| v * k).sum();
            if w_flux <= max_flux {
                total += t.iter().sum::<f64>();
                kept += (0..3)
                    .map(|ch| f64::from(estimate[[y, x, ch]]))
                    .sum::<f64>();
            }
        }
    }
    Ok((total > 0.0).then(|| kept / total))
}

/// sRGB encoding of clipped linear values, the display-referred images of the sRGB scores.
fn encode_srgb(linear: &Array3<f32>) -> Array3<f32> {
    linear.map(|&v| linear_to_srgb(v))
}

/// The evaluation protocol's linear images (see [`evaluate`]): cropped by `opts.border`,
/// scaled by the truth's `opts.normalize_percentile`, clipped to [0, 1].
fn protocol_linear(
    estimate: ArrayView3<f32>,
    truth: ArrayView3<f32>,
    opts: &EvalOptions,
) -> Result<(Array3<f32>, Array3<f32>)> {
    check_same_shape(estimate.shape(), truth.shape())?;
    let (h, w, _) = estimate.dim();
    let b = opts.border;
    if 2 * b >= h || 2 * b >= w {
        return Err(Error::invalid(format!(
            "border {b} leaves nothing of a {h}x{w} image"
        )));
    }
    let est = estimate.slice(s![b..h - b, b..w - b, ..]);
    let tru = truth.slice(s![b..h - b, b..w - b, ..]);
    if est.iter().any(|v| !v.is_finite()) {
        return Err(Error::invalid("estimate contains non-finite values"));
    }
    if tru.iter().any(|v| !v.is_finite()) {
        return Err(Error::invalid("ground truth contains non-finite values"));
    }
    let scale = match opts.normalize_percentile {
        None => 1.0,
        Some(p) => {
            if !(p > 0.0 && p <= 100.0) {
                return Err(Error::invalid(format!(
                    "normalisation percentile must be in (0, 100], got {p}"
                )));
            }
            let mut values: Vec<f32> = tru.iter().copied().collect();
            let q = percentile_linear(&mut values, p);
            if q <= 0.0 {
                return Err(Error::invalid(format!(
                    "ground truth's {p}th percentile is {q}; cannot normalise"
                )));
            }
            1.0 / q
        }
    };
    let prepare = |v: &f32| (f64::from(*v) * scale).clamp(0.0, 1.0) as f32;
    Ok((est.map(prepare), tru.map(prepare)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_light_ratio_counts_measurable_pixels_only() {
        // 100 frames: only pixels with λ_W ≤ ln(1) = 0 count; 1,000 frames: λ_W ≤ ln 10.
        let truth = Array3::from_shape_fn((4, 4, 3), |(y, _, _)| if y < 2 { 0.1 } else { 2.0 });
        let mut estimate = truth.mapv(|v| 0.9 * v);
        // The bright rows (λ_W = 6 > ln 10) lose everything: not measurable, not counted.
        estimate.slice_mut(s![2.., .., ..]).fill(0.0);
        let ratio = |frames| {
            measurable_light_ratio(estimate.view(), truth.view(), [1.0; 3], frames, 0).unwrap()
        };
        assert!((ratio(1000).unwrap() - 0.9).abs() < 1e-6);
        assert_eq!(ratio(100), None);
        // Every pixel measurable: the bright rows' loss shows.
        let all = ratio(1_000_000).unwrap();
        assert!((all - 0.9 * 0.1 / 2.1).abs() < 1e-6, "{all}");
        assert!(measurable_light_ratio(estimate.view(), truth.view(), [1.0; 3], 1000, 2).is_err());
    }

    #[test]
    fn reflect_index_is_half_sample_symmetric() {
        // d c b a | a b c d | d c b a  for n = 4.
        let got: Vec<usize> = (-4..8).map(|i| reflect_index(i, 4)).collect();
        assert_eq!(got, vec![3, 2, 1, 0, 0, 1, 2, 3, 3, 2, 1, 0]);
        // Period 2n beyond one reflection.
        assert_eq!(reflect_index(-5, 4), 3);
        assert_eq!(reflect_index(-9, 4), 0);
        assert_eq!(reflect_index(12, 4), 3);
        assert_eq!(reflect_index(0, 1), 0);
        assert_eq!(reflect_index(-3, 1), 0);
    }

    #[test]
    fn box_filter_matches_direct_window_sum() {
        let (h, w, r) = (45, 11, 3); // h > ROW_BLOCK exercises the block restart
        let src: Vec<f64> = (0..h * w)
            .map(|i| ((i * 7919) % 97) as f64 / 97.0)
            .collect();
        let out = box_filter_reflect(&src, h, w, r);
        let ri = r as isize;
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for dy in -ri..=ri {
                    for dx in -ri..=ri {
                        let yy = reflect_index(y as isize + dy, h);
                        let xx = reflect_index(x as isize + dx, w);
                        acc += src[yy * w + xx];
                    }
                }
                let direct = acc / ((2 * r + 1) * (2 * r + 1)) as f64;
                assert!((out[y * w + x] - direct).abs() < 1e-13, "({y},{x})");
            }
        }
    }
}
