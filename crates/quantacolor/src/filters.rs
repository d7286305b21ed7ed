//! Low-level image filters shared by every stage: Gaussian kernels, zero-padded separable
//! convolution, Gaussian blur, normalized convolution (Knutsson & Westin 1993), bilinear
//! sampling, bicubic upsampling and box downsampling.
//!
//! One home for these ideas. Two kernel conventions exist on purpose and give different numbers,
//! so both are kept under distinct names rather than merged:
//! - [`gaussian_taps`] (f32 arithmetic, unnormalised taps, radius `max(1, ⌈3σ⌉)`) feeds the
//!   alignment filters ([`gaussian_blur`], [`normalized_convolution_masked`]); their result is
//!   divided by the convolved weights, so the taps need no normalisation.
//! - [`gaussian_kernel_unit_sum`] (taps computed in f64 and normalised to sum 1 before rounding
//!   to f32, radius `⌈3σ⌉`) feeds the demosaicking/hole-filling normalized convolution
//!   [`normalized_convolution_nan`] of the naive baseline and the merge.
//! - [`gaussian_taps_f64`] (f64, unnormalised, radius given by the caller) and
//!   [`gaussian_of_squared_distance`] (one f64 weight of an integer squared distance) are the
//!   f64 Gaussians both of the above builds on or that the blue-noise CFA uses directly.
//!
//! None of this is from the paper (which demosaics by normalized convolution without giving a
//! kernel); the widths are this project's choices and live with the callers.

use crate::cpu::Isa;
use ndarray::{Array2, Array3, ArrayView2, ArrayView3, Axis, Zip};
use rayon::prelude::*;

/// Unnormalised Gaussian taps `exp(−d²/2σ²)` in f32 for `d = −r..=r`, `r = max(1, ⌈3σ⌉)`
/// (σ in pixels). Used where the result is divided by the convolved weights.
pub fn gaussian_taps(sigma: f32) -> Vec<f32> {
    let radius = (3.0 * sigma).ceil().max(1.0) as usize;
    (0..=2 * radius)
        .map(|i| {
            let d = i as f32 - radius as f32;
            (-0.5 * d * d / (sigma * sigma)).exp()
        })
        .collect()
}

/// Gaussian taps computed in f64 for `d = −r..=r`, `r = ⌈3σ⌉` (σ in pixels), normalised to
/// sum 1 and then rounded to f32. Differs from [`gaussian_taps`] in precision, normalisation and
/// the minimum radius (0 here, 1 there).
pub fn gaussian_kernel_unit_sum(sigma: f64) -> Vec<f32> {
    let radius = (3.0 * sigma).ceil() as i64;
    let k = gaussian_taps_f64(sigma, radius);
    let sum: f64 = k.iter().sum();
    k.iter().map(|v| (v / sum) as f32).collect()
}

/// Unnormalised Gaussian taps `exp(−d²/2σ²)` in f64 for `d = −radius..=radius` (σ and the
/// radius in grid steps, chosen by the caller): each tap is [`gaussian_of_squared_distance`]
/// of `d²`. The factors of the blue-noise CFA's separable kernel, and (normalised) of
/// [`gaussian_kernel_unit_sum`].
pub fn gaussian_taps_f64(sigma: f64, radius: i64) -> Vec<f64> {
    (-radius..=radius)
        .map(|d| gaussian_of_squared_distance(d * d, sigma))
        .collect()
}

/// `exp(−d²/2σ²)` in f64 for an integer squared distance `d²` (a 2-D one `di² + dj²` too,
/// which is not the product of two 1-D taps bit for bit).
#[inline]
pub fn gaussian_of_squared_distance(d2: i64, sigma: f64) -> f64 {
    (-(d2 as f64) / (2.0 * sigma * sigma)).exp()
}

/// One row of the horizontal pass: `out[x] = Σ_k kernel[k]·inp[x + k − r]`, zero outside.
///
/// Every output starts at 0 and adds its taps in kernel order, skipping those outside the row.
/// Pixels whose taps all fall inside run tap by tap over the whole interior (a plain slice
/// loop that vectorises); the same additions in the same order per pixel as the border loop.
fn convolve_row(inp: &[f32], out: &mut [f32], kernel: &[f32]) {
    let w = inp.len();
    let r = kernel.len() / 2;
    let interior = r..w.saturating_sub(r).max(r);
    if !interior.is_empty() {
        let lane = &mut out[interior.clone()];
        lane.fill(0.0);
        for (k, &kv) in kernel.iter().enumerate() {
            let src = &inp[k..k + lane.len()];
            lane.iter_mut().zip(src).for_each(|(o, &s)| *o += kv * s);
        }
    }
    let border = (0..interior.start.min(w)).chain(interior.end.max(interior.start).min(w)..w);
    for x in border {
        let mut acc = 0.0;
        for (k, &kv) in kernel.iter().enumerate() {
            // x + k − r, when inside the row.
            if let Some(xx) = (x + k).checked_sub(r).filter(|&xx| xx < w) {
                acc += kv * inp[xx];
            }
        }
        out[x] = acc;
    }
}

/// One output row `y` of the vertical pass: `row = Σ_k kernel[k]·rows[y + k − r]` over the rows
/// inside the image, from 0 in kernel order (`rows` holds `row.len()`-wide rows).
fn accumulate_column(y: usize, row: &mut [f32], rows: &[f32], kernel: &[f32]) {
    let w = row.len();
    let h = rows.len().checked_div(w).unwrap_or(0);
    let r = kernel.len() / 2;
    row.fill(0.0);
    for (k, &kv) in kernel.iter().enumerate() {
        if let Some(yy) = (y + k).checked_sub(r).filter(|&yy| yy < h) {
            let src = &rows[yy * w..(yy + 1) * w];
            row.iter_mut().zip(src).for_each(|(d, &s)| *d += kv * s);
        }
    }
}

/// Zero-padded separable convolution with the odd-length `kernel`, along x then y, on the
/// calling thread (for callers that already run in parallel over many small images). Zero
/// padding is what normalized convolution needs: the weight image is padded the same way, so
/// borders stay unbiased.
pub fn separable(img: &Array2<f32>, kernel: &[f32]) -> Array2<f32> {
    let (h, w) = img.dim();
    let img = img.as_standard_layout();
    let src = img.as_slice().expect("standard layout");
    let mut rows = vec![0.0f32; h * w];
    let mut out = vec![0.0f32; h * w];
    if w > 0 {
        for (o, i) in rows.chunks_exact_mut(w).zip(src.chunks_exact(w)) {
            convolve_row(i, o, kernel);
        }
        for (y, row) in out.chunks_exact_mut(w).enumerate() {
            accumulate_column(y, row, &rows, kernel);
        }
    }
    Array2::from_shape_vec((h, w), out).expect("h x w")
}

/// [`separable`] with the rows spread over the rayon pool (same numbers, for full-size images).
pub fn separable_par(img: &Array2<f32>, kernel: &[f32]) -> Array2<f32> {
    let (h, w) = img.dim();
    let img = img.as_standard_layout();
    let src = img.as_slice().expect("standard layout");
    let mut rows = vec![0.0f32; h * w];
    let mut out = vec![0.0f32; h * w];
    if w > 0 {
        rows.par_chunks_exact_mut(w)
            .zip(src.par_chunks_exact(w))
            .for_each(|(o, i)| convolve_row(i, o, kernel));
        out.par_chunks_exact_mut(w)
            .enumerate()
            .for_each(|(y, row)| accumulate_column(y, row, &rows, kernel));
    }
    Array2::from_shape_vec((h, w), out).expect("h x w")
}

/// Gaussian blur with σ px ([`gaussian_taps`], radius 3σ), normalised near borders so edges do
/// not darken.
pub fn gaussian_blur(img: &Array2<f32>, sigma: f32) -> Array2<f32> {
    let kernel = gaussian_taps(sigma);
    let mut num = separable(img, &kernel);
    // The weights, `separable` of an all-ones image, row by row: every row of its horizontal
    // pass is the same, so output rows whose vertical taps all fall inside the image are the
    // same too and are made once (the same numbers as convolving the ones image).
    let (h, w) = img.dim();
    let mut ones = vec![0.0f32; w];
    convolve_row(&vec![1.0f32; w], &mut ones, &kernel);
    let r = kernel.len() / 2;
    let mut den = vec![0.0f32; w];
    let mut taps = None;
    for (y, mut row) in num.axis_iter_mut(Axis(0)).enumerate() {
        let span = (r.saturating_sub(y), (h - 1 - y + r).min(kernel.len() - 1));
        if taps != Some(span) {
            den.fill(0.0);
            for &kv in &kernel[span.0..=span.1] {
                den.iter_mut().zip(&ones).for_each(|(d, &s)| *d += kv * s);
            }
            taps = Some(span);
        }
        let row = row.as_slice_mut().expect("fresh array is contiguous");
        row.iter_mut().zip(&den).for_each(|(n, &d)| *n /= d);
    }
    num
}

/// Normalized convolution (Knutsson & Westin 1993): `G * (m·v) / G * m` with a separable
/// Gaussian of standard deviation `sigma` px ([`gaussian_taps`], radius 3σ), i.e. a
/// Gaussian-weighted mean of the values where `mask` holds. Pixels with no masked neighbour
/// within the radius get 0. Runs on the calling thread.
pub fn normalized_convolution_masked(
    values: &Array2<f32>,
    mask: &Array2<bool>,
    sigma: f32,
) -> Array2<f32> {
    let den = normalized_convolution_weights(mask, sigma);
    normalized_convolution_masked_with(values, mask, sigma, &den)
}

/// The denominator `G * m` of [`normalized_convolution_masked`] for `mask` and `sigma`: it
/// depends on the mask alone, so images sharing a mask (every block of a burst) make it once.
pub fn normalized_convolution_weights(mask: &Array2<bool>, sigma: f32) -> Array2<f32> {
    let weights = mask.mapv(|m| m as u8 as f32);
    separable(&weights, &gaussian_taps(sigma))
}

/// [`normalized_convolution_masked`] with its denominator `den` made beforehand by
/// [`normalized_convolution_weights`] for the same `mask` and `sigma` (the same numbers).
pub fn normalized_convolution_masked_with(
    values: &Array2<f32>,
    mask: &Array2<bool>,
    sigma: f32,
    den: &Array2<f32>,
) -> Array2<f32> {
    assert_eq!(
        den.dim(),
        mask.dim(),
        "normalized convolution: denominator shape"
    );
    let kernel = gaussian_taps(sigma);
    let weighted = Zip::from(values)
        .and(mask)
        .map_collect(|&v, &m| if m { v } else { 0.0 });
    let num = separable(&weighted, &kernel);
    Zip::from(&num)
        .and(den)
        .map_collect(|&n, &d| if d > 1e-6 { n / d } else { 0.0 })
}

/// Normalized convolution of the samples in `values` (NaN = no sample) with a Gaussian of
/// width `sigma` ([`gaussian_kernel_unit_sum`]): Σ g·v / Σ g over the valid samples. Pixels
/// without any sample within 3σ get NaN (where [`normalized_convolution_masked`] gives 0).
/// Rows run in parallel.
pub fn normalized_convolution_nan(values: ArrayView2<f32>, sigma: f64) -> Array2<f32> {
    let weights = values.mapv(|v| if v.is_nan() { 0.0 } else { 1.0 });
    let data = values.mapv(|v| if v.is_nan() { 0.0 } else { v });
    let kernel = gaussian_kernel_unit_sum(sigma);
    let num = separable_par(&data, &kernel);
    let den = separable_par(&weights, &kernel);
    Zip::from(&num)
        .and(&den)
        .map_collect(|&n, &d| if d > 1e-6 { n / d } else { f32::NAN })
}

/// The two taps and the weight of the second along one axis of length `n` of [`bilinear`] at
/// coordinate `v` (clamped to the axis).
#[inline]
pub fn bilinear_taps(v: f32, n: usize) -> (usize, usize, f32) {
    let v = v.clamp(0.0, (n - 1) as f32);
    // Truncation is the floor of a non-negative value (and 0 for NaN, as `floor` then a cast
    // gives): no libm call.
    let v0 = v as usize;
    (v0, (v0 + 1).min(n - 1), v - v0 as f32)
}

/// [`bilinear_taps`] of the coordinates `start + i + offset` for every `i < len` (`i` converted
/// to `f32` with the start, then the offset added: the values a caller mapping
/// `bilinear_taps(p as f32 + offset, n)` over `start..start + len` gets), appended to `out`.
/// With AVX2, eight coordinates at a time by the same operations (exact integer conversions,
/// the same clamp, truncation and subtraction), so the same taps bit for bit; where the offset
/// is not finite or the coordinates exceed `i32`, one at a time. Runs on [`Isa::current`]
/// (see [`bilinear_taps_into_with`] for a caller that holds its own).
pub fn bilinear_taps_into(
    start: usize,
    len: usize,
    offset: f32,
    n: usize,
    out: &mut Vec<(usize, usize, f32)>,
) {
    bilinear_taps_into_with(Isa::current(), start, len, offset, n, out);
}

/// [`bilinear_taps_into`] on the instruction set `isa` (the same taps on every one).
pub fn bilinear_taps_into_with(
    isa: Isa,
    start: usize,
    len: usize,
    offset: f32,
    n: usize,
    out: &mut Vec<(usize, usize, f32)>,
) {
    #[cfg(target_arch = "x86_64")]
    {
        if offset.is_finite()
            && start + len <= i32::MAX as usize
            && n <= i32::MAX as usize
            && isa.avx2()
        {
            // SAFETY: an `Isa` with AVX2 exists only on a CPU that has it.
            unsafe { bilinear_taps_into_avx2(start, len, offset, n, out) };
            return;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = isa;
    out.extend((start..start + len).map(|p| bilinear_taps(p as f32 + offset, n)));
}

/// [`bilinear_taps_into`] eight coordinates at a time. `f32::clamp` keeps the value when it is
/// not below the low end nor above the high end (a −0.0 stays −0.0): `max(0, v)` and
/// `min(n − 1, v)` with `v` second, whose instructions return the second operand of equal
/// zeros, do the same (`v` is finite: no NaN to order).
///
/// # Safety
/// The CPU must support AVX2; `offset` must be finite, `start + len` and `n` at most
/// `i32::MAX`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn bilinear_taps_into_avx2(
    start: usize,
    len: usize,
    offset: f32,
    n: usize,
    out: &mut Vec<(usize, usize, f32)>,
) {
    use std::arch::x86_64::*;
    let zero = _mm256_setzero_ps();
    let high = _mm256_set1_ps((n - 1) as f32);
    let last = _mm256_set1_epi32((n - 1) as i32);
    let offset_v = _mm256_set1_ps(offset);
    let lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    out.reserve(len);
    let mut done = 0;
    while done < len {
        let p = _mm256_add_epi32(_mm256_set1_epi32((start + done) as i32), lanes);
        let v = _mm256_add_ps(_mm256_cvtepi32_ps(p), offset_v);
        let v = _mm256_min_ps(high, _mm256_max_ps(zero, v));
        let v0 = _mm256_cvttps_epi32(v);
        let v1 = _mm256_min_epi32(_mm256_add_epi32(v0, _mm256_set1_epi32(1)), last);
        let frac = _mm256_sub_ps(v, _mm256_cvtepi32_ps(v0));
        let (mut t0, mut t1, mut f) = ([0i32; 8], [0i32; 8], [0.0f32; 8]);
        _mm256_storeu_si256(t0.as_mut_ptr().cast(), v0);
        _mm256_storeu_si256(t1.as_mut_ptr().cast(), v1);
        _mm256_storeu_ps(f.as_mut_ptr(), frac);
        let count = (len - done).min(8);
        out.extend((0..count).map(|l| (t0[l] as usize, t1[l] as usize, f[l])));
        done += count;
    }
}

/// Bilinear sample of `image` at the real position `(y, x)`, clamped to the image edges.
#[inline]
pub fn bilinear(image: ArrayView2<f32>, y: f32, x: f32) -> f32 {
    let (h, w) = image.dim();
    let (y0, y1, fy) = bilinear_taps(y, h);
    let (x0, x1, fx) = bilinear_taps(x, w);
    let top = image[[y0, x0]] * (1.0 - fx) + image[[y0, x1]] * fx;
    let bottom = image[[y1, x0]] * (1.0 - fx) + image[[y1, x1]] * fx;
    top * (1.0 - fy) + bottom * fy
}

/// Mean over `f` x `f` cells (partial cells at the far edges average what they hold).
pub fn box_downsample(img: &Array2<f32>, f: usize) -> Array2<f32> {
    if f == 1 {
        return img.clone();
    }
    let (h, w) = img.dim();
    let (oh, ow) = (h.div_ceil(f), w.div_ceil(f));
    Array2::from_shape_fn((oh, ow), |(y, x)| {
        let (y1, x1) = (((y + 1) * f).min(h), ((x + 1) * f).min(w));
        let mut s = 0.0;
        for yy in y * f..y1 {
            for xx in x * f..x1 {
                s += img[[yy, xx]];
            }
        }
        s / ((y1 - y * f) * (x1 - x * f)) as f32
    })
}

/// Keys cubic convolution weight (a = −0.5) at distance `d`.
fn keys(d: f32) -> f32 {
    const A: f32 = -0.5;
    let d = d.abs();
    if d <= 1.0 {
        ((A + 2.0) * d - (A + 3.0)) * d * d + 1.0
    } else if d < 2.0 {
        ((A * d - 5.0 * A) * d + 8.0 * A) * d - 4.0 * A
    } else {
        0.0
    }
}

/// Bicubic (Keys, a = −0.5) upsampling of an (H, W, C) image by `scale` on the merge's scale-s
/// grid: output pixel (Y, X) interpolates the input at ((Y + ½)/s − ½, (X + ½)/s − ½); edges
/// are clamped.
pub fn bicubic_upsample(image: ArrayView3<f32>, scale: usize) -> Array3<f32> {
    // Taps (4 clamped source indices and weights) of every output coordinate along one axis.
    let taps = |n: usize| -> Vec<([usize; 4], [f32; 4])> {
        (0..n * scale)
            .map(|o| {
                let p = (o as f32 + 0.5) / scale as f32 - 0.5;
                let base = p.floor();
                let f = p - base;
                let mut idx = [0usize; 4];
                let mut wts = [0.0f32; 4];
                for k in 0..4 {
                    let i = base as isize - 1 + k as isize;
                    idx[k] = i.clamp(0, n as isize - 1) as usize;
                    wts[k] = keys(f - (k as f32 - 1.0));
                }
                (idx, wts)
            })
            .collect()
    };
    let (h, w, c) = image.dim();
    let (ty, tx) = (taps(h), taps(w));
    // Along x, then along y.
    let mut rows = Array3::<f32>::zeros((h, w * scale, c));
    for y in 0..h {
        for (xo, (idx, wts)) in tx.iter().enumerate() {
            for ch in 0..c {
                rows[[y, xo, ch]] = (0..4).map(|k| wts[k] * image[[y, idx[k], ch]]).sum();
            }
        }
    }
    let mut out = Array3::<f32>::zeros((h * scale, w * scale, c));
    for (yo, (idx, wts)) in ty.iter().enumerate() {
        for xo in 0..w * scale {
            for ch in 0..c {
                out[[yo, xo, ch]] = (0..4).map(|k| wts[k] * rows[[idx[k], xo, ch]]).sum();
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The batched taps equal [`bilinear_taps`] one coordinate at a time, bit for bit, on the
    /// portable path and on this CPU's (AVX2 where it has it): offsets
    /// below, inside and past the axis (clamped at both ends), negative zero, fractions next to
    /// whole pixels, lengths off the vector width, a one-pixel axis, and non-finite offsets.
    #[test]
    fn batched_bilinear_taps_match_one_at_a_time() {
        let offsets = [
            0.0f32,
            -0.0,
            0.3,
            -0.7,
            -1.6,
            2.45,
            -1e-8,
            0.999_999_9,
            -40.0,
            40.0,
            f32::NAN,
            f32::INFINITY,
        ];
        for n in [1usize, 9, 50] {
            for start in [0usize, 3, 20, 45] {
                for len in [0usize, 1, 7, 8, 13, 16, 17] {
                    for (&offset, isa) in offsets
                        .iter()
                        .flat_map(|o| [(o, Isa::generic()), (o, Isa::current())])
                    {
                        let mut got = vec![(7, 7, 7.0)];
                        bilinear_taps_into_with(isa, start, len, offset, n, &mut got);
                        let expected: Vec<(usize, usize, f32)> = std::iter::once((7, 7, 7.0))
                            .chain(
                                (start..start + len).map(|p| bilinear_taps(p as f32 + offset, n)),
                            )
                            .collect();
                        assert_eq!(got.len(), expected.len());
                        for (g, e) in got.iter().zip(&expected) {
                            assert_eq!(
                                (g.0, g.1, g.2.to_bits()),
                                (e.0, e.1, e.2.to_bits()),
                                "n {n} start {start} len {len} offset {offset} {}",
                                isa.name()
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn serial_and_parallel_separable_agree_bit_for_bit() {
        let img = Array2::from_shape_fn((23, 31), |(y, x)| ((y * 7 + x * 13) % 17) as f32 * 0.37);
        for kernel in [gaussian_taps(1.3), gaussian_kernel_unit_sum(2.1)] {
            let a = separable(&img, &kernel);
            let b = separable_par(&img, &kernel);
            assert!(a.iter().zip(&b).all(|(p, q)| p.to_bits() == q.to_bits()));
        }
    }

    /// Zero-padded separable convolution as a direct sum over every tap that falls inside
    /// (taps in kernel order from 0, rows first): what [`separable`] must equal bit for bit.
    fn direct_separable(img: &Array2<f32>, kernel: &[f32]) -> Array2<f32> {
        let (h, w) = img.dim();
        let r = (kernel.len() / 2) as isize;
        let taps = |n: usize, i: usize| {
            kernel.iter().enumerate().filter_map(move |(k, &kv)| {
                let j = i as isize + k as isize - r;
                (j >= 0 && j < n as isize).then_some((j as usize, kv))
            })
        };
        let rows = Array2::from_shape_fn((h, w), |(y, x)| {
            taps(w, x).fold(0.0f32, |acc, (xx, kv)| acc + kv * img[[y, xx]])
        });
        Array2::from_shape_fn((h, w), |(y, x)| {
            taps(h, y).fold(0.0f32, |acc, (yy, kv)| acc + kv * rows[[yy, x]])
        })
    }

    /// Images narrower, as wide as and wider than the kernel; values with negative zeros.
    #[test]
    fn separable_equals_the_direct_tap_sum_bit_for_bit() {
        for (h, w) in [(23, 31), (3, 17), (1, 5), (40, 2), (7, 7), (5, 13), (1, 1)] {
            let img = Array2::from_shape_fn((h, w), |(y, x)| {
                let v = ((y * 7 + x * 13) % 17) as f32 * 0.37 - 2.0;
                if (y + x) % 5 == 0 {
                    -0.0
                } else {
                    v
                }
            });
            for kernel in [
                gaussian_taps(0.75),
                gaussian_taps(2.0),
                gaussian_kernel_unit_sum(1.1),
            ] {
                let expected = direct_separable(&img, &kernel);
                for got in [separable(&img, &kernel), separable_par(&img, &kernel)] {
                    assert!(
                        got.iter()
                            .zip(&expected)
                            .all(|(p, q)| p.to_bits() == q.to_bits()),
                        "{h}x{w} kernel of {}",
                        kernel.len()
                    );
                }
            }
        }
    }

    /// The blur's weights made row by row equal convolving an all-ones image, bit for bit:
    /// images taller and shorter than the kernel.
    #[test]
    fn gaussian_blur_equals_the_normalised_separable_convolution() {
        for (h, w) in [(23, 31), (3, 17), (1, 5), (40, 2)] {
            let img = Array2::from_shape_fn((h, w), |(y, x)| ((y * 7 + x * 13) % 17) as f32 * 0.37);
            for sigma in [0.4, 1.0, 2.0, 4.0] {
                let kernel = gaussian_taps(sigma);
                let expected =
                    separable(&img, &kernel) / separable(&Array2::from_elem((h, w), 1.0), &kernel);
                let blurred = gaussian_blur(&img, sigma);
                assert!(
                    blurred
                        .iter()
                        .zip(&expected)
                        .all(|(p, q)| p.to_bits() == q.to_bits()),
                    "{h}x{w} sigma {sigma}"
                );
            }
        }
    }

    #[test]
    fn unit_sum_kernel_sums_to_one_and_blur_keeps_a_constant() {
        let k = gaussian_kernel_unit_sum(1.7);
        assert_eq!(k.len(), 2 * 6 + 1);
        assert!((k.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        let flat = Array2::from_elem((9, 12), 3.5f32);
        assert!(gaussian_blur(&flat, 1.2)
            .iter()
            .all(|&v| (v - 3.5).abs() < 1e-5));
    }

    /// The f64 Gaussians equal, bit for bit, the expressions they replaced: the normalised
    /// kernel's old isize taps, the blue-noise kernel's 1-D taps and its 2-D causal weights.
    #[test]
    fn f64_gaussians_match_the_expressions_they_replaced_bit_for_bit() {
        let old_unit_sum = |sigma: f64| -> Vec<f32> {
            let radius = (3.0 * sigma).ceil() as isize;
            let k: Vec<f64> = (-radius..=radius)
                .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp())
                .collect();
            let sum: f64 = k.iter().sum();
            k.iter().map(|v| (v / sum) as f32).collect()
        };
        let old_taps = |sigma: f64, radius: i64| -> Vec<f64> {
            (-radius..=radius)
                .map(|d| (-(d * d) as f64 / (2.0 * sigma * sigma)).exp())
                .collect()
        };
        let old_weight = |di: i64, dj: i64, sigma: f64| {
            (-((di * di + dj * dj) as f64) / (2.0 * sigma * sigma)).exp()
        };
        let bits32 = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let bits64 = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for sigma in [0.3, 0.5, 0.75, 1.0, 1.1, 1.5, 1.7, 2.1, 3.3, 7.9] {
            assert_eq!(
                bits32(&gaussian_kernel_unit_sum(sigma)),
                bits32(&old_unit_sum(sigma)),
                "sigma {sigma}"
            );
            for radius in [0i64, 1, 2, 5, 24] {
                assert_eq!(
                    bits64(&gaussian_taps_f64(sigma, radius)),
                    bits64(&old_taps(sigma, radius)),
                    "sigma {sigma} radius {radius}"
                );
            }
            for di in -6i64..=0 {
                for dj in -6i64..=6 {
                    assert_eq!(
                        gaussian_of_squared_distance(di * di + dj * dj, sigma).to_bits(),
                        old_weight(di, dj, sigma).to_bits(),
                        "sigma {sigma} ({di}, {dj})"
                    );
                }
            }
        }
    }

    #[test]
    fn keys_weights_interpolate_and_sum_to_one() {
        assert_eq!(keys(0.0), 1.0);
        assert_eq!(keys(1.0), 0.0);
        assert_eq!(keys(2.0), 0.0);
        for f in [0.1f32, 0.25, 0.5, 0.75] {
            let sum: f32 = (0..4).map(|k| keys(f - (k as f32 - 1.0))).sum();
            assert!((sum - 1.0).abs() < 1e-6, "{f}: {sum}");
        }
    }

    #[test]
    fn bicubic_reproduces_a_quadratic_away_from_the_edges() {
        // Keys' a = −0.5 kernel reproduces polynomials up to degree 2.
        let f = |y: f32, x: f32| 0.3 + 0.02 * y - 0.01 * x + 0.001 * x * x + 0.002 * x * y;
        let image =
            Array3::from_shape_fn((12, 14, 2), |(y, x, c)| f(y as f32, x as f32) + c as f32);
        let up = bicubic_upsample(image.view(), 2);
        assert_eq!(up.dim(), (24, 28, 2));
        for yo in 4..20 {
            for xo in 4..24 {
                let (y, x) = ((yo as f32 + 0.5) / 2.0 - 0.5, (xo as f32 + 0.5) / 2.0 - 0.5);
                for c in 0..2 {
                    let want = f(y, x) + c as f32;
                    assert!((up[[yo, xo, c]] - want).abs() < 1e-4, "({yo}, {xo}, {c})");
                }
            }
        }
        // Constants everywhere, edges included.
        let flat = Array3::from_elem((5, 7, 3), 0.7f32);
        assert!(bicubic_upsample(flat.view(), 2)
            .iter()
            .all(|v| (v - 0.7).abs() < 1e-6));
    }

    #[test]
    fn masked_and_nan_variants_mark_empty_neighbourhoods_differently() {
        let mut values = Array2::<f32>::from_elem((5, 40), f32::NAN);
        values[[2, 1]] = 4.0;
        let mask = values.mapv(|v| !v.is_nan());
        let masked = normalized_convolution_masked(&values, &mask, 1.0);
        let nan = normalized_convolution_nan(values.view(), 1.0);
        assert_eq!(masked[[2, 1]], 4.0);
        assert_eq!(nan[[2, 1]], 4.0);
        assert_eq!(masked[[2, 39]], 0.0);
        assert!(nan[[2, 39]].is_nan());
    }
}
