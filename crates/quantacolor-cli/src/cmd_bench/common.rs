//! Helpers shared by the benchmarks: the median of a sample and bicubic (Keys) upsampling, the
//! baseline the scale-2 merge is scored against.

#![forbid(unsafe_code)]

use ndarray::{Array3, ArrayView3};

/// Median (upper median for an even count); NaN for no values.
pub(super) fn median<T: Copy + Into<f64>>(values: &mut [T]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mid = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(mid, |a, b| (*a).into().total_cmp(&(*b).into()));
    (*m).into()
}

/// Keys cubic convolution weight (a = −0.5) at distance `d`.
pub(super) fn keys(d: f32) -> f32 {
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
pub(super) fn bicubic_upsample(image: ArrayView3<f32>, scale: usize) -> Array3<f32> {
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
