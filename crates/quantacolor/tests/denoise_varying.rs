//! BM3D with a per-pixel noise variance map and the multi-scale chroma denoising of
//! `denoise::chroma::bm3d_multiscale`, against known truth (seeded Gaussian noise on a
//! synthetic image).

use ndarray::{s, Array2, Array3, Axis};
use quantacolor::denoise::bm3d::{bm3d_multichannel, bm3d_multichannel_varying, Bm3dConfig};
use quantacolor::denoise::chroma::bm3d_multiscale;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

mod bm3d_support;
use bm3d_support::synthetic;

fn rmse(a: ndarray::ArrayView2<f32>, b: ndarray::ArrayView2<f32>) -> f64 {
    let n = a.len() as f64;
    (a.iter()
        .zip(b.iter())
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / n)
        .sqrt()
}

/// Noise of σ 5 on the left half and σ 30 on the right: with the true variance map each half
/// is filtered at its own σ and both halves come out closer to the truth than with the one σ
/// (the RMS σ) that plain BM3D must use; a map of ones gives plain BM3D bit for bit.
#[test]
fn variance_map_denoises_dim_and_bright_noise_alike() {
    let clean = synthetic(96, 128);
    let (h, w) = clean.dim();
    let sigma_of = |x: usize| if x < w / 2 { 5.0f32 } else { 30.0 };
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let unit = Normal::new(0.0f32, 1.0).unwrap();
    let noisy = Array2::from_shape_fn((h, w), |(y, x)| {
        clean[[y, x]] + sigma_of(x) * unit.sample(&mut rng)
    });
    let noisy3 = noisy.clone().insert_axis(Axis(0));
    let rms_sigma = ((5.0f32 * 5.0 + 30.0 * 30.0) / 2.0).sqrt();
    let config = Bm3dConfig::default();
    let uniform = bm3d_multichannel(noisy3.view(), &[rms_sigma], &config).unwrap();
    let map = Array3::from_shape_fn((1, h, w), |(_, _, x)| (sigma_of(x) / rms_sigma).powi(2));
    let varying =
        bm3d_multichannel_varying(noisy3.view(), &[rms_sigma], Some(map.view()), &config).unwrap();
    // Away from the seam, where blocks mix both halves.
    let (left, right) = (s![.., 8..w / 2 - 16], s![.., w / 2 + 16..w - 8]);
    for (name, half) in [("left (σ 5)", left), ("right (σ 30)", right)] {
        let e_uniform = rmse(
            uniform.index_axis(Axis(0), 0).slice(half),
            clean.slice(half),
        );
        let e_varying = rmse(
            varying.index_axis(Axis(0), 0).slice(half),
            clean.slice(half),
        );
        let e_noisy = rmse(noisy.slice(half), clean.slice(half));
        println!("{name}: noisy {e_noisy:.2}, one σ {e_uniform:.2}, σ map {e_varying:.2}");
        assert!(
            e_varying < e_noisy * 0.7,
            "{name}: the map must still denoise"
        );
        assert!(
            e_varying < e_uniform * 0.95,
            "{name}: σ map {e_varying:.2} not better than one σ {e_uniform:.2}"
        );
    }
    let ones = Array3::from_elem((1, h, w), 1.0f32);
    let same =
        bm3d_multichannel_varying(noisy3.view(), &[rms_sigma], Some(ones.view()), &config).unwrap();
    let plain = bm3d_multichannel(noisy3.view(), &[rms_sigma], &config).unwrap();
    assert_eq!(same, plain);
    // Bad maps are errors, not panics.
    let bad = Array3::from_elem((1, h, w), 0.0f32);
    assert!(bm3d_multichannel_varying(noisy3.view(), &[5.0], Some(bad.view()), &config).is_err());
    let wrong = Array3::from_elem((1, h, w - 1), 1.0f32);
    assert!(bm3d_multichannel_varying(noisy3.view(), &[5.0], Some(wrong.view()), &config).is_err());
}

/// Chroma noise correlated over about 4 px (white noise blurred by a 4×4 box, as the merge's
/// wide colour kernels make it): denoising the chroma planes again at 1/2 and 1/4 scale removes
/// more of it than 8×8 blocks alone, and leaves the luma plane as the single-scale result.
#[test]
fn coarse_scales_remove_coarse_grained_chroma_noise() {
    let (h, w) = (128, 160);
    let luma = synthetic(h, w);
    let chroma = Array2::from_shape_fn((h, w), |(y, x)| {
        20.0 * ((y as f32 / 37.0).sin() + (x as f32 / 23.0).cos())
    });
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let unit = Normal::new(0.0f32, 1.0).unwrap();
    let white = Array2::from_shape_fn((h + 3, w + 3), |_| unit.sample(&mut rng));
    // 4×4 box blur of white noise: σ 1/4 per unit; scale to σ 6 (luma: white, σ 3).
    let coarse_noise = Array2::from_shape_fn((h, w), |(y, x)| {
        white.slice(s![y..y + 4, x..x + 4]).sum() * 1.5
    });
    let mut planes = Array3::<f32>::zeros((3, h, w));
    for y in 0..h {
        for x in 0..w {
            planes[[0, y, x]] = luma[[y, x]] + 3.0 * unit.sample(&mut rng);
            planes[[1, y, x]] = chroma[[y, x]] + coarse_noise[[y, x]];
            planes[[2, y, x]] = -chroma[[y, x]] + coarse_noise[[(y + 64) % h, x]];
        }
    }
    let config = Bm3dConfig::default();
    let sigmas = [3.0, 6.0, 6.0];
    let single = bm3d_multiscale(planes.view(), sigmas, None, 0, 0.7, &config).unwrap();
    let multi = bm3d_multiscale(planes.view(), sigmas, None, 2, 0.7, &config).unwrap();
    assert_eq!(
        single.index_axis(Axis(0), 0),
        multi.index_axis(Axis(0), 0),
        "luma keeps its full-scale result"
    );
    for (ch, truth) in [(1usize, chroma.clone()), (2, chroma.mapv(|v| -v))] {
        let e_single = rmse(single.index_axis(Axis(0), ch), truth.view());
        let e_multi = rmse(multi.index_axis(Axis(0), ch), truth.view());
        let e_noisy = rmse(planes.index_axis(Axis(0), ch), truth.view());
        println!("chroma {ch}: noisy {e_noisy:.2}, one scale {e_single:.2}, 3 scales {e_multi:.2}");
        assert!(
            e_multi < e_single * 0.9,
            "chroma {ch}: coarse scales {e_multi:.2} vs one scale {e_single:.2}"
        );
    }
}
