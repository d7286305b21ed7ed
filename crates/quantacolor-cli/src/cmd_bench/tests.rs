//! Tests of the benchmarks' pure parts: the denoising grid.

#![forbid(unsafe_code)]

use super::denoise::DenoiseGrid;

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
