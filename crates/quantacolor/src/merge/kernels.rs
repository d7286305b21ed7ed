//! Anisotropic merge kernels (Wronski et al. 2019, §5.1.2; paper §4.2): the local structure
//! tensor of the reference image decides, per pixel, how far a sample may sit from the output
//! position along and across the local edge.
#![deny(unsafe_code)]

use super::warp::positive;
use super::GreyNoise;
use crate::cfa::{Cfa, Channel};
use crate::error::{Error, Result};
use crate::stats;
use ndarray::{Array2, Array3, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Kernel-shape parameters (Wronski et al. 2019, "Handheld Multi-Frame Super-Resolution",
/// §5.1.2 and Eq. 4–5; the ranges that differ from theirs are this project's, as noted).
///
/// Kernel standard deviations are in reference pixels for a channel with one site per pixel;
/// [`KernelField::channel_scale`] widens them for sparse channels.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct KernelConfig {
    /// Base kernel std in detailed areas (px).
    pub k_detail: f32, // 0.3 px
    /// Isotropic kernel std that flat areas blend toward (px). Here an absolute std rather than
    /// Wronski's multiplier of k_detail, so that flat areas are actually denoised.
    pub k_denoise: f32, // 1.0 px
    /// Detail threshold D_th of D = clamp(1 − sqrt(λ1)/D_tr + D_th, 0, 1) (dimensionless).
    pub d_th: f32, // 0.005
    /// Detail transition D_tr, as a fraction of the reference's value range (1st to 99th
    /// percentile): Wronski's images span [0, 1], mean bit rates of dim scenes span far less.
    pub d_tr: f32, // 0.5 (of the range)
    /// Stretch along edges: k1 = k_detail·k_stretch·A. A spans [1, 5] here (Wronski: [1, 2]),
    /// so the default is 1 to keep the kernel within ~1.5 px along edges.
    pub k_stretch: f32, // 1
    /// Shrink across edges: k2 = k_detail/(k_shrink·A).
    pub k_shrink: f32, // 1
    /// Upper bound of the anisotropy A = min(sqrt(λ1/λ2), max_anisotropy).
    pub max_anisotropy: f32, // 5
    /// Detail transition in units of the reference's noise (this project's heuristic; 0 =
    /// off): D_tr = min(d_tr·range, detail_noise_sigmas·σ(p)), σ(p) the std of the reference
    /// at p ([`ReferenceNoise`]). Where photons are plenty a gradient far above the noise is
    /// detail even if it is small against the image's range; in the dark σ is large and
    /// `d_tr` decides. Measurements: docs/tuning.md.
    pub detail_noise_sigmas: f32, // 11 (noise stds; 0 = off)
    /// Signal-to-noise ratio of the reference above which the flat-area kernel narrows (this
    /// project's heuristic; 0 = off): k_denoise·min(1, flat_snr / SNR(p)), never below
    /// k_detail, so that where a pixel's own photons already give a clean value the merge does
    /// not blur it. Measurements: docs/tuning.md.
    pub flat_snr: f32, // 0 (dimensionless; 0 = off)
    /// Signal-to-noise ratio of the reference below which the flat-area kernel widens (this
    /// project's heuristic; 0 = off): k_denoise·min(2, dark_snr / SNR(p)), so that where a
    /// pixel's neighbourhood holds only a few detections more of them are pooled; the detail
    /// kernel widens by the same factor.
    pub dark_snr: f32, // 2 (dimensionless; 0 = off)
    /// Floor on every kernel std (px): narrower kernels than this underflow in f32 for samples
    /// one pixel away and leave holes.
    pub min_std: f32, // 0.25 px
    /// At output scale s > 1 the kernel stds are divided by s^exponent, as 1x kernels over-smooth
    /// the finer grid (this project's heuristic; Wronski et al. 2019 size kernels on the output
    /// grid). Measurements behind 0.5: docs/tuning.md.
    pub output_scale_exponent: f32, // 0.5 (dimensionless)
}

impl Default for KernelConfig {
    fn default() -> Self {
        KernelConfig {
            k_detail: 0.3,
            k_denoise: 1.0,
            d_th: 0.005,
            d_tr: 0.5,
            k_stretch: 1.0,
            k_shrink: 1.0,
            max_anisotropy: 5.0,
            detail_noise_sigmas: 11.0,
            flat_snr: 0.0,
            dark_snr: 2.0,
            min_std: 0.25,
            output_scale_exponent: 0.5,
        }
    }
}

impl KernelConfig {
    /// The kernel shapes for an output grid `scale` times finer than the reference: the three
    /// stds (`k_detail`, `k_denoise`, `min_std`, reference px) divided by
    /// scale^`output_scale_exponent` (see there).
    pub fn for_output_scale(&self, scale: usize) -> KernelConfig {
        let shrink = (scale.max(1) as f32).powf(-self.output_scale_exponent);
        KernelConfig {
            k_detail: self.k_detail * shrink,
            k_denoise: self.k_denoise * shrink,
            min_std: self.min_std * shrink,
            ..self.clone()
        }
    }
}

/// Per-pixel kernel shapes on the reference grid.
#[derive(Debug, Clone)]
pub struct KernelField {
    /// (H, W, 3): entries (a, b, c) of the inverse covariance Ω⁻¹ = [[a, b], [b, c]] in (y, x)
    /// order, for a channel with one site per pixel (px⁻²).
    pub inv_cov: Array3<f32>,
    /// (H, W): anisotropy A in [1, max_anisotropy].
    pub anisotropy: Array2<f32>,
    /// (H, W): D in [0, 1] (1 = flat, isotropic k_denoise kernel).
    pub flatness: Array2<f32>,
    /// Largest kernel std over the image (px, unit channel scale).
    pub max_std: f32,
}

impl KernelField {
    /// Covariance scale of each channel (code order): its mean site spacing squared, i.e. the
    /// area per site 1/fraction (W on a 75 % W CFA: 1.33; R on it: 16). A sparse channel's
    /// kernel is widened so that it reaches about as many sites as a dense one. Channels
    /// absent from `cfa` get 0.
    pub fn channel_scale(cfa: &Cfa) -> [f32; 4] {
        let fractions = cfa.fractions();
        Channel::ALL.map(|c| {
            let f = fractions[c.index()];
            if f > 0.0 {
                (1.0 / f) as f32
            } else {
                0.0
            }
        })
    }
}

/// The noise of the merged reference image: a grey value's noise ([`GreyNoise`]) averaged over
/// `blocks` blocks (the Wiener merge's flat-area limit, supplement §1.2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceNoise {
    pub grey: GreyNoise,
    /// Blocks merged into the reference.
    pub blocks: f32,
}

impl ReferenceNoise {
    /// Standard deviation of a reference pixel whose (local mean) value is `value`, the value
    /// floored at one detection over all the reference's frames: a dark pixel that saw nothing
    /// is not noise-free.
    pub fn std(&self, value: f32) -> f32 {
        let blocks = self.blocks.max(1.0);
        let one_detection = 1.0 / (self.grey.trials.max(1.0) * blocks);
        (self.grey.variance(value.max(one_detection)) / blocks).sqrt()
    }
}

/// The mean of each pixel's 3x3 window of `reference` (the structure tensor's window),
/// truncated at the image's edges; non-finite values count as 0.
fn local_mean_3x3(reference: &Array2<f32>) -> Array2<f32> {
    let taps = [1.0f32; 3];
    let values = reference.mapv(finite);
    let sums = crate::filters::separable_par(&values, &taps);
    let counts = crate::filters::separable_par(&Array2::ones(reference.dim()), &taps);
    sums / counts
}

/// Value at the `q`-quantile of `values` (finite values only, nearest rank; 0 if none).
fn quantile(values: &Array2<f32>, q: f64) -> f32 {
    stats::quantile(values.iter().copied(), q).unwrap_or(0.0)
}

/// Kernel covariances from the structure tensor of `reference` (Wronski et al. 2019, Eq. 4–5).
///
/// Gradients by central differences; the tensor is summed over 3x3 neighbourhoods; its
/// eigenvalues λ1 ≥ λ2 give A = min(sqrt(λ1/λ2), max_anisotropy) (A = max where λ2 = 0 < λ1,
/// 1 where both vanish) and D = clamp(1 − sqrt(λ1)/(D_tr·range) + D_th, 0, 1). Stds
/// k1 = k_detail·k_stretch·A along the edge and k2 = k_detail/(k_shrink·A) across it are blended
/// toward k_denoise as (1 − D)·k + D·k_denoise, floored at min_std, and
/// Ω = k1²·e_edge·e_edgeᵀ + k2²·e_grad·e_gradᵀ.
pub fn kernel_field(reference: &Array2<f32>, config: &KernelConfig) -> Result<KernelField> {
    kernel_field_with_noise(reference, None, config)
}

/// [`kernel_field`] with the reference's noise, which `detail_noise_sigmas` and `flat_snr`
/// need (without it, or with both 0, the two make no difference).
pub fn kernel_field_with_noise(
    reference: &Array2<f32>,
    noise: Option<ReferenceNoise>,
    config: &KernelConfig,
) -> Result<KernelField> {
    let (h, w) = reference.dim();
    if h == 0 || w == 0 {
        return Err(Error::invalid("kernels: the reference image is empty"));
    }
    let all_positive = [
        config.k_detail,
        config.k_denoise,
        config.min_std,
        config.d_tr,
        config.k_stretch,
        config.k_shrink,
    ]
    .into_iter()
    .all(positive);
    if !all_positive || config.max_anisotropy.is_nan() || config.max_anisotropy < 1.0 {
        return Err(Error::invalid(
            "kernels: k_detail, k_denoise, min_std, d_tr, k_stretch, k_shrink must be positive \
             and max_anisotropy at least 1",
        ));
    }
    let non_negative = |v: f32| v.is_finite() && v >= 0.0;
    let noise_settings = [config.detail_noise_sigmas, config.flat_snr, config.dark_snr];
    if !noise_settings.into_iter().all(non_negative) {
        return Err(Error::invalid(
            "kernels: detail_noise_sigmas, flat_snr and dark_snr must be finite and at least 0 \
             (0 = off)",
        ));
    }
    let range = (quantile(reference, 0.99) - quantile(reference, 0.01)).max(1e-6);
    let d_tr = config.d_tr * range;
    let products = gradient_products(reference);
    // The noise is judged at the window's mean: a single pixel's value is itself noisy.
    let local_mean = noise.map(|_| local_mean_3x3(reference));
    // Plain (y, x, product) slices for the 3x3 sums below.
    let products = products.as_slice().expect("fresh array is contiguous");
    let mut inv_cov = Array3::<f32>::zeros((h, w, 3));
    let mut anisotropy = Array2::<f32>::zeros((h, w));
    let mut flatness = Array2::<f32>::zeros((h, w));
    let max_std = inv_cov
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(anisotropy.axis_iter_mut(Axis(0)))
        .zip(flatness.axis_iter_mut(Axis(0)))
        .enumerate()
        .map(|(y, ((mut inv_row, mut a_row), mut d_row))| {
            let mut row_max = 0.0f32;
            for x in 0..w {
                let tensor = structure_tensor_3x3(products, (h, w), y, x);
                let (d_tr, k_flat) = match (noise, &local_mean) {
                    (Some(noise), Some(mean)) => noise_adapted(mean[[y, x]], noise, d_tr, config),
                    _ => (d_tr, config.k_denoise),
                };
                let kernel = PixelKernel::of(tensor, d_tr, k_flat, config);
                row_max = row_max.max(kernel.k_edge).max(kernel.k_grad);
                for (c, v) in kernel.inv_cov.into_iter().enumerate() {
                    inv_row[[x, c]] = v;
                }
                a_row[x] = kernel.anisotropy;
                d_row[x] = kernel.flatness;
            }
            row_max
        })
        .reduce(|| 0.0, f32::max);
    Ok(KernelField {
        inv_cov,
        anisotropy,
        flatness,
        max_std,
    })
}

/// The detail transition and the flat-area kernel std of a reference pixel of value `value`
/// (`detail_noise_sigmas`, `flat_snr`; `d_tr` the range-based transition).
fn noise_adapted(
    value: f32,
    noise: ReferenceNoise,
    d_tr: f32,
    config: &KernelConfig,
) -> (f32, f32) {
    let std = noise.std(value);
    if !(std.is_finite() && std > 0.0) {
        return (d_tr, config.k_denoise);
    }
    let d_tr = if config.detail_noise_sigmas > 0.0 {
        d_tr.min(config.detail_noise_sigmas * std)
    } else {
        d_tr
    };
    let snr = value.max(0.0) / std;
    let k_flat = if config.flat_snr > 0.0 && snr > config.flat_snr {
        (config.k_denoise * config.flat_snr / snr).max(config.k_detail.min(config.k_denoise))
    } else if config.dark_snr > 0.0 && snr < config.dark_snr {
        config.k_denoise * (config.dark_snr / snr.max(f32::MIN_POSITIVE)).min(2.0)
    } else {
        config.k_denoise
    };
    (d_tr.max(f32::MIN_POSITIVE), k_flat)
}

/// Per pixel of `reference`, the products (gy², gy·gx, gx²) of its central-difference
/// gradient (edges replicated; non-finite differences count as 0), `(H, W, 3)`.
fn gradient_products(reference: &Array2<f32>) -> Array3<f32> {
    let (h, w) = reference.dim();
    let at = |y: isize, x: isize| -> f32 {
        reference[[
            y.clamp(0, h as isize - 1) as usize,
            x.clamp(0, w as isize - 1) as usize,
        ]]
    };
    let mut products = Array3::<f32>::zeros((h, w, 3));
    products
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut row)| {
            let y = y as isize;
            for x in 0..w as isize {
                let gy = 0.5 * (at(y + 1, x) - at(y - 1, x));
                let gx = 0.5 * (at(y, x + 1) - at(y, x - 1));
                let (gy, gx) = (finite(gy), finite(gx));
                row[[x as usize, 0]] = gy * gy;
                row[[x as usize, 1]] = gy * gx;
                row[[x as usize, 2]] = gx * gx;
            }
        });
    products
}

/// The structure tensor (Σ gy², Σ gy·gx, Σ gx²) over the 3x3 window of pixel (y, x),
/// truncated at the image's edges, from the `(H, W, 3)` row-major `products`.
fn structure_tensor_3x3(products: &[f32], (h, w): (usize, usize), y: usize, x: usize) -> [f32; 3] {
    let mut t = [0.0f32; 3];
    for yy in y.saturating_sub(1)..(y + 2).min(h) {
        let row = &products[yy * w * 3..(yy + 1) * w * 3];
        let window = &row[x.saturating_sub(1) * 3..(x + 2).min(w) * 3];
        for p in window.chunks_exact(3) {
            t[0] += p[0];
            t[1] += p[1];
            t[2] += p[2];
        }
    }
    t
}

/// One pixel's merge kernel from its structure tensor (Wronski et al. 2019 §5.1.2, see
/// [`KernelConfig`]).
struct PixelKernel {
    /// Ω⁻¹ as (yy, yx, xx).
    inv_cov: [f32; 3],
    /// Std along the edge and along the gradient, px.
    k_edge: f32,
    k_grad: f32,
    anisotropy: f32,
    flatness: f32,
}

impl PixelKernel {
    /// The kernel of a pixel whose 3x3 structure tensor is `[syy, syx, sxx]`: anisotropy
    /// A = √(λ1/λ2) (capped at `max_anisotropy`), flatness D = clamp(1 − √λ1 / `d_tr` + D_th),
    /// stds k_detail·k_stretch·A along the edge and k_detail / (k_shrink·A) along the
    /// gradient, each blended with the flat-area std `k_flat` (k_denoise, or its noise-adapted
    /// value) by D and floored at `min_std`. Where `dark_snr` widens `k_flat` beyond k_denoise,
    /// the detail stds and their floor widen by the same factor (this project's heuristic): at a
    /// fraction of a detection per pixel a thin dark line's own pixel holds no photon, and the
    /// detail kernel must pool along and across it too (issue 45's isolated dark pixels).
    fn of([syy, syx, sxx]: [f32; 3], d_tr: f32, k_flat: f32, config: &KernelConfig) -> Self {
        let half_trace = 0.5 * (syy + sxx);
        let disc = (0.25 * (syy - sxx) * (syy - sxx) + syx * syx).sqrt();
        let l1 = (half_trace + disc).max(0.0);
        let l2 = (half_trace - disc).max(0.0);
        let a = if l1 <= f32::MIN_POSITIVE {
            1.0
        } else if l2 <= l1 / (config.max_anisotropy * config.max_anisotropy) {
            config.max_anisotropy
        } else {
            (l1 / l2).sqrt().min(config.max_anisotropy)
        };
        let d = (1.0 - l1.sqrt() / d_tr + config.d_th).clamp(0.0, 1.0);
        // Gradient direction e_grad (eigenvector of λ1), in (y, x).
        let (mut ey, mut ex) = (l1 - sxx, syx);
        let norm = (ey * ey + ex * ex).sqrt();
        if norm > 1e-12 {
            ey /= norm;
            ex /= norm;
        } else if syy >= sxx {
            (ey, ex) = (1.0, 0.0);
        } else {
            (ey, ex) = (0.0, 1.0);
        }
        let dark_widening = (k_flat / config.k_denoise).max(1.0);
        let k_edge = config.k_detail * config.k_stretch * a * dark_widening;
        let k_grad = config.k_detail / (config.k_shrink * a) * dark_widening;
        let floor = config.min_std * dark_widening;
        let k_edge = ((1.0 - d) * k_edge + d * k_flat).max(floor);
        let k_grad = ((1.0 - d) * k_grad + d * k_flat).max(floor);
        // Ω⁻¹ = e_grad e_gradᵀ / k_grad² + e_edge e_edgeᵀ / k_edge², e_edge = (−ex, ey).
        let (ig, ie) = (1.0 / (k_grad * k_grad), 1.0 / (k_edge * k_edge));
        PixelKernel {
            inv_cov: [
                ig * ey * ey + ie * ex * ex,
                ig * ey * ex - ie * ex * ey,
                ig * ex * ex + ie * ey * ey,
            ],
            k_edge,
            k_grad,
            anisotropy: a,
            flatness: d,
        }
    }
}

fn finite(v: f32) -> f32 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flat_pixel_gets_the_isotropic_denoising_kernel() {
        let config = KernelConfig::default();
        let kernel = PixelKernel::of([0.0; 3], 0.5, config.k_denoise, &config);
        // No gradient: flatness 1 (clamped from 1 + D_th), anisotropy 1, both stds k_denoise.
        assert_eq!((kernel.flatness, kernel.anisotropy), (1.0, 1.0));
        assert_eq!((kernel.k_edge, kernel.k_grad), (1.0, 1.0));
        assert_eq!(kernel.inv_cov, [1.0, 0.0, 1.0]);
    }

    /// Where `dark_snr` widens the flat kernel 2x, an edge's detail kernel widens 2x as well,
    /// along the edge, across it and at the floor.
    #[test]
    fn a_dark_edge_widens_like_the_flat_kernel() {
        let config = KernelConfig::default();
        let tensor = [100.0, 0.0, 0.0];
        let lit = PixelKernel::of(tensor, 0.5, config.k_denoise, &config);
        let dark = PixelKernel::of(tensor, 0.5, 2.0 * config.k_denoise, &config);
        assert_eq!(dark.flatness, 0.0);
        assert!((dark.k_edge - 2.0 * lit.k_edge).abs() < 1e-6);
        // Across the edge both sit at the floor: min_std and twice it.
        assert_eq!(lit.k_grad, config.min_std);
        assert_eq!(dark.k_grad, 2.0 * config.min_std);
    }

    #[test]
    fn a_strong_horizontal_edge_stretches_the_kernel_along_x() {
        // Gradient along y only (a horizontal edge), far above the flatness threshold.
        let config = KernelConfig::default();
        let kernel = PixelKernel::of([100.0, 0.0, 0.0], 0.5, config.k_denoise, &config);
        assert_eq!(kernel.flatness, 0.0);
        assert_eq!(kernel.anisotropy, config.max_anisotropy);
        // Along the edge (x): k_detail·k_stretch·A; across it (y): k_detail / (k_shrink·A),
        // floored at min_std.
        assert!(
            (kernel.k_edge - 0.3 * 5.0).abs() < 1e-6,
            "{}",
            kernel.k_edge
        );
        assert_eq!(kernel.k_grad, config.min_std);
        let [yy, yx, xx] = kernel.inv_cov;
        assert!((yy - 1.0 / (0.25 * 0.25)).abs() < 1e-3, "{yy}");
        assert!((xx - 1.0 / (1.5 * 1.5)).abs() < 1e-5, "{xx}");
        assert_eq!(yx, 0.0);
    }

    /// A reference merged from 100 blocks of 16 binary frames each.
    fn noise() -> ReferenceNoise {
        ReferenceNoise {
            grey: GreyNoise::from(16.0),
            blocks: 100.0,
        }
    }

    #[test]
    fn noise_adaptation_is_off_at_zero_and_in_the_dark() {
        let config = KernelConfig {
            detail_noise_sigmas: 0.0,
            flat_snr: 0.0,
            dark_snr: 0.0,
            ..KernelConfig::default()
        };
        assert_eq!(noise_adapted(0.5, noise(), 0.3, &config), (0.3, 1.0));
        // Both on, but a dim pixel: std of 0.001 over 1,600 frames is 7.9e-4, SNR 1.3, so
        // 8 σ = 6.3e-3 sits above a transition of 1e-3 and the SNR below 20.
        let on = KernelConfig {
            detail_noise_sigmas: 8.0,
            flat_snr: 20.0,
            ..config
        };
        assert_eq!(noise_adapted(0.001, noise(), 1e-3, &on), (1e-3, 1.0));
    }

    #[test]
    fn plenty_of_photons_narrow_the_transition_and_the_flat_kernel() {
        let config = KernelConfig {
            detail_noise_sigmas: 8.0,
            flat_snr: 20.0,
            ..KernelConfig::default()
        };
        // p = 0.5 over 1,600 frames: std 0.0125, SNR 40.
        let std = noise().std(0.5);
        assert!((std - 0.0125).abs() < 1e-6, "{std}");
        let (d_tr, k_flat) = noise_adapted(0.5, noise(), 0.3, &config);
        assert!((d_tr - 0.1).abs() < 1e-6, "{d_tr}");
        assert!((k_flat - 0.5).abs() < 1e-6, "{k_flat}");
        // SNR 400 (100x the frames): the flat kernel stops at k_detail.
        let many = ReferenceNoise {
            blocks: 10_000.0,
            ..noise()
        };
        assert_eq!(noise_adapted(0.5, many, 0.3, &config).1, config.k_detail);
        // A gradient of 0.05 per pixel: flat under the range-based transition, detail once
        // the transition follows the noise.
        let tensor = [9.0 * 0.05 * 0.05, 0.0, 0.0];
        let by_range = PixelKernel::of(tensor, 0.3, 1.0, &config);
        let by_noise = PixelKernel::of(tensor, d_tr, k_flat, &config);
        assert!(by_range.flatness > 0.45, "{}", by_range.flatness);
        assert_eq!(by_noise.flatness, 0.0);
        assert!(by_noise.k_grad < by_range.k_grad);
    }

    #[test]
    fn few_detections_widen_the_flat_kernel_up_to_twice() {
        let config = KernelConfig {
            dark_snr: 4.0,
            ..KernelConfig::default()
        };
        // p = 0.01 over 1,600 frames: std 0.00249, SNR 4.02: just above, unchanged.
        assert_eq!(
            noise_adapted(0.01, noise(), 0.3, &config).1,
            config.k_denoise
        );
        // p = 0.004: SNR 2.535, widened by 4 / 2.535 = 1.578.
        let k = noise_adapted(0.004, noise(), 0.3, &config).1;
        assert!((k - 1.578 * config.k_denoise).abs() < 0.002, "{k}");
        // Nothing seen: SNR 0 (the noise floored at one detection), widening capped at 2.
        assert_eq!(
            noise_adapted(0.0, noise(), 0.3, &config).1,
            2.0 * config.k_denoise
        );
    }

    #[test]
    fn the_structure_tensor_sums_the_window_inside_the_image() {
        // 3x4 image of products (p, 2p, 3p) with p = 1 + index.
        let (h, w) = (3, 4);
        let products: Vec<f32> = (0..h * w)
            .flat_map(|i| {
                let p = 1.0 + i as f32;
                [p, 2.0 * p, 3.0 * p]
            })
            .collect();
        // Corner (0, 0): pixels (0,0), (0,1), (1,0), (1,1) = 1 + 2 + 5 + 6.
        assert_eq!(
            structure_tensor_3x3(&products, (h, w), 0, 0),
            [14.0, 28.0, 42.0]
        );
        // Interior (1, 1): rows 0..3, columns 0..3: (1+2+3) + (5+6+7) + (9+10+11).
        assert_eq!(
            structure_tensor_3x3(&products, (h, w), 1, 1),
            [54.0, 108.0, 162.0]
        );
    }

    #[test]
    fn gradient_products_are_central_differences_with_replicated_edges() {
        // A ramp along x: gx = 1 inside, 0.5 at the replicated edges; gy = 0.
        let reference = Array2::from_shape_fn((2, 4), |(_, x)| x as f32);
        let products = gradient_products(&reference);
        let gx2: Vec<f32> = (0..4).map(|x| products[[0, x, 2]]).collect();
        assert_eq!(gx2, vec![0.25, 1.0, 1.0, 0.25]);
        assert!(products
            .slice(ndarray::s![.., .., 0..2])
            .iter()
            .all(|&v| v == 0.0));
    }
}
