//! Anisotropic kernels (Wronski et al. 2019) on images with known structure.
use ndarray::Array2;
use quantacolor::cfa::{generate, Pattern};
use quantacolor::merge::{kernel_field, KernelConfig, KernelField};

/// Squared Mahalanobis distance of the offset (dy, dx) under the kernel at (y, x).
fn quad(k: &KernelField, y: usize, x: usize, dy: f32, dx: f32) -> f32 {
    let (a, b, c) = (
        k.inv_cov[[y, x, 0]],
        k.inv_cov[[y, x, 1]],
        k.inv_cov[[y, x, 2]],
    );
    a * dy * dy + 2.0 * b * dy * dx + c * dx * dx
}

#[test]
fn kernels_stretch_along_edges_and_are_isotropic_in_flat_areas() {
    // Vertical step edge at x = 20 (bit rates 0.2 | 0.6), flat elsewhere.
    let img = Array2::from_shape_fn((32, 40), |(_, x)| if x < 20 { 0.2f32 } else { 0.6 });
    let config = KernelConfig::default();
    let k = kernel_field(&img, &config).unwrap();
    // On the edge: λ2 = 0 < λ1, so A is maximal, D = 0, and the kernel is long along y.
    assert_eq!(k.anisotropy[[16, 20]], config.max_anisotropy);
    assert_eq!(k.flatness[[16, 20]], 0.0);
    let along = quad(&k, 16, 20, 1.0, 0.0);
    let across = quad(&k, 16, 20, 0.0, 1.0);
    let k_edge = config.k_detail * config.k_stretch * config.max_anisotropy;
    assert!(
        (along - 1.0 / (k_edge * k_edge)).abs() < 1e-3,
        "along {along}"
    );
    let k_grad = (config.k_detail / (config.k_shrink * config.max_anisotropy)).max(config.min_std);
    assert!(
        (across - 1.0 / (k_grad * k_grad)).abs() < 1e-2,
        "across {across}"
    );
    // Far from the edge: flat, isotropic k_denoise kernel.
    assert_eq!(k.flatness[[16, 5]], 1.0);
    assert_eq!(k.anisotropy[[16, 5]], 1.0);
    let iso = 1.0 / (config.k_denoise * config.k_denoise);
    assert!((quad(&k, 16, 5, 1.0, 0.0) - iso).abs() < 1e-5);
    assert!((quad(&k, 16, 5, 0.0, 1.0) - iso).abs() < 1e-5);
    assert!(k.inv_cov[[16, 5, 1]].abs() < 1e-6);
    assert!((k.max_std - k_edge.max(config.k_denoise)).abs() < 1e-5);
}

#[test]
fn diagonal_edge_kernel_follows_the_edge_direction() {
    // Edge along the direction (1, 1): intensity depends on x − y.
    let img = Array2::from_shape_fn((32, 32), |(y, x)| {
        if (x as i32 - y as i32) < 0 {
            0.1f32
        } else {
            0.5
        }
    });
    let k = kernel_field(&img, &KernelConfig::default()).unwrap();
    let along = quad(&k, 16, 16, 1.0, 1.0);
    let across = quad(&k, 16, 16, 1.0, -1.0);
    assert!(along * 10.0 < across, "along {along}, across {across}");
}

#[test]
fn channel_scale_is_the_area_per_site() {
    let cfa = generate(&Pattern::Rgbw75Regular, 16, 16, 0).unwrap();
    let s = KernelField::channel_scale(&cfa);
    assert!((s[0] - 16.0).abs() < 1e-5 && (s[2] - 16.0).abs() < 1e-5);
    assert!((s[1] - 8.0).abs() < 1e-5);
    assert!((s[3] - 4.0 / 3.0).abs() < 1e-5);
    let bayer = generate(&Pattern::Bayer, 16, 16, 0).unwrap();
    assert_eq!(KernelField::channel_scale(&bayer)[3], 0.0);
}

#[test]
fn bad_kernel_config_is_an_error() {
    let img = Array2::<f32>::zeros((8, 8));
    let config = KernelConfig {
        k_detail: 0.0,
        ..KernelConfig::default()
    };
    assert!(kernel_field(&img, &config).is_err());
    assert!(kernel_field(&Array2::zeros((0, 4)), &KernelConfig::default()).is_err());
}

#[test]
fn kernels_shrink_on_a_finer_output_grid() {
    let config = KernelConfig::default();
    assert_eq!(config.for_output_scale(1), config);
    let four = config.for_output_scale(4);
    let shrink = 4f32.powf(-config.output_scale_exponent);
    assert!((four.k_detail - config.k_detail * shrink).abs() < 1e-6);
    assert!((four.k_denoise - config.k_denoise * shrink).abs() < 1e-6);
    assert!((four.min_std - config.min_std * shrink).abs() < 1e-6);
    assert!(four.k_denoise < config.k_denoise);
    assert_eq!(four.max_anisotropy, config.max_anisotropy);
}
