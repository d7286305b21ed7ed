//! Noise-aware low-light visualisation (supplement §4, Eq. 9–10): in the dark, colour vision
//! fades (mesopic/scotopic vision), and the chrominance of a photon-starved reconstruction is
//! mostly noise. Each pixel's colour is blended toward the neutral grey of the same luminance
//! with weight
//!
//! `p(x, y) = clamp((log10 W(x, y) + L0 − C2) / (C1 − C2), 0, 1)`, `C1 = 0`, `C2 = −2`  (Eq. 9)
//!
//! `out = p · RGB + (1 − p) · grey`, `grey = W / (wR + wG + wB)` in every channel  (Eq. 10)
//!
//! where `W = wR·R + wG·G + wB·B` is the flux a W (clear) pixel would see and `L0` a user offset.
//! The log is base 10: C1 and C2 are two decades apart, so colour fades in over W from 0.01 to 1
//! detections per frame (times 10^−L0). The grey keeps `W` unchanged, so the blend preserves the
//! luminance used to compute `p`.

use crate::error::{Error, Result};
use ndarray::{Array3, ArrayView3, Axis, Zip};

/// `C1` of Eq. 9: log10 luminance (plus `L0`) at and above which colour is kept in full.
pub const MESOPIC_C1: f64 = 0.0;
/// `C2` of Eq. 9: log10 luminance (plus `L0`) at and below which the pixel is grey.
pub const MESOPIC_C2: f64 = -2.0;

/// Colour weight `p` of Eq. 9 for luminance `w` and offset `l0`; 0 for `w <= 0` or non-finite.
pub fn mesopic_weight(w: f64, l0: f64) -> f64 {
    if w == f64::INFINITY {
        return 1.0;
    }
    if w.is_nan() || w <= 0.0 {
        return 0.0;
    }
    ((w.log10() + l0 - MESOPIC_C2) / (MESOPIC_C1 - MESOPIC_C2)).clamp(0.0, 1.0)
}

/// Applies Eq. 9–10 to a linear (H, W, 3) image in detections per frame, with luminance
/// weights `w_weights` (the W pixel's response to R, G, B; `[1, 1, 1]` for simulated captures).
pub fn mesopic_blend(linear: ArrayView3<f32>, l0: f64, w_weights: [f64; 3]) -> Result<Array3<f32>> {
    if linear.dim().2 != 3 {
        return Err(Error::invalid(format!(
            "expected an (H, W, 3) RGB image, got shape {:?}",
            linear.dim()
        )));
    }
    let sum: f64 = w_weights.iter().sum();
    if !l0.is_finite()
        || w_weights.iter().any(|w| !(w.is_finite() && *w >= 0.0))
        || sum.is_nan()
        || sum <= 0.0
    {
        return Err(Error::invalid(format!(
            "mesopic blend needs a finite L0 and non-negative luminance weights with a positive sum, got L0 = {l0}, w = {w_weights:?}"
        )));
    }
    let mut out = Array3::<f32>::zeros(linear.dim());
    Zip::from(out.lanes_mut(Axis(2)))
        .and(linear.lanes(Axis(2)))
        .par_for_each(|mut o, px| {
            let rgb = [px[0] as f64, px[1] as f64, px[2] as f64];
            let w: f64 = (0..3).map(|c| w_weights[c] * rgb[c]).sum();
            let p = mesopic_weight(w, l0);
            let grey = w / sum;
            for c in 0..3 {
                o[c] = (p * rgb[c] + (1.0 - p) * grey) as f32;
            }
        });
    Ok(out)
}
