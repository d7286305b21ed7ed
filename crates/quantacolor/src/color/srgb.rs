//! The sRGB transfer function (IEC 61966-2-1).
#![forbid(unsafe_code)]

/// sRGB-encoded value in [0, 1] to linear.
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear value to sRGB encoding; input is clamped to [0, 1].
pub fn linear_to_srgb(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0);
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_known_points() {
        for i in 0..=100 {
            let v = i as f32 / 100.0;
            assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 1e-5);
        }
        // 18 % grey encodes to about 0.4613.
        assert!((linear_to_srgb(0.18) - 0.4613).abs() < 1e-3);
        assert!((linear_to_srgb(2.0) - 1.0).abs() < 1e-6);
    }
}
