//! Tests of the benchmarks' pure parts: the denoising grid and bicubic upsampling.

#![forbid(unsafe_code)]

use super::common::{bicubic_upsample, keys};
use super::denoise::DenoiseGrid;
use ndarray::Array3;

#[test]
fn a_denoise_grid_tries_coarse_factors_only_with_coarse_scales() {
    let grid = DenoiseGrid {
        luma_gains: vec![1.0, 1.5],
        chroma_gains: vec![2.0],
        merge_k_denoise: vec![None],
        chroma_scales: vec![0, 1],
        coarse_sigma_factors: vec![0.5, 0.7],
    };
    let settings = grid.settings();
    // Per luma gain: scales 0 once, scales 1 with each factor.
    assert_eq!(settings.len(), 2 * (1 + 2));
    let factors: Vec<(usize, f32)> = settings[..3]
        .iter()
        .map(|s| (s.chroma_scales, s.coarse_sigma_factor))
        .collect();
    assert_eq!(factors, vec![(0, 0.5), (1, 0.5), (1, 0.7)]);
    assert!(settings[3..].iter().all(|s| s.luma_gain == 1.5));
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
    let image = Array3::from_shape_fn((12, 14, 2), |(y, x, c)| f(y as f32, x as f32) + c as f32);
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
