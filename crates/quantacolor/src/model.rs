//! TODO (placeholder until the model branch lands)

/// MLE of photon detections per frame from `ones` detections in `frames` frames (paper Eq. 6).
pub fn mle_flux(ones: f64, frames: f64, dark: f64) -> f64 {
    let s = ones.min(frames - 0.5);
    -(1.0 - s / frames).ln() - dark
}
