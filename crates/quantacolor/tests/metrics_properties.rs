//! Properties of PSNR, SSIM and the evaluation protocol: identities, symmetry, closed forms,
//! a brute-force SSIM, and errors on bad input.

use ndarray::{s, Array2, Array3, Axis};
use quantacolor::color::srgb::linear_to_srgb;
use quantacolor::metrics::{evaluate, psnr, ssim, ssim_color, ssim_gray, EvalOptions};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_image(rng: &mut ChaCha8Rng, h: usize, w: usize, c: usize) -> Array3<f32> {
    Array3::from_shape_fn((h, w, c), |_| rng.gen::<f32>())
}

/// Reflect (half-sample symmetric) index, written independently of the library.
fn refl(i: isize, n: usize) -> usize {
    let n = n as isize;
    let mut i = i;
    while i < 0 || i >= n {
        i = if i < 0 { -i - 1 } else { 2 * n - 1 - i };
    }
    i as usize
}

/// Textbook SSIM with explicit 7×7 window sums: slow but obviously right.
fn ssim_brute(x: &Array2<f32>, y: &Array2<f32>, data_range: f64) -> f64 {
    let (h, w) = x.dim();
    let (c1, c2) = ((0.01 * data_range).powi(2), (0.03 * data_range).powi(2));
    let mut total = 0.0;
    let mut count = 0.0;
    for i in 3..h - 3 {
        for j in 3..w - 3 {
            let (mut sx, mut sy, mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for di in -3isize..=3 {
                for dj in -3isize..=3 {
                    let (ii, jj) = (refl(i as isize + di, h), refl(j as isize + dj, w));
                    let (a, b) = (f64::from(x[[ii, jj]]), f64::from(y[[ii, jj]]));
                    sx += a;
                    sy += b;
                    sxx += a * a;
                    syy += b * b;
                    sxy += a * b;
                }
            }
            let n = 49.0;
            let (mx, my) = (sx / n, sy / n);
            // Sample (co)variances, normalised by n − 1.
            let vx = (sxx - n * mx * mx) / (n - 1.0);
            let vy = (syy - n * my * my) / (n - 1.0);
            let vxy = (sxy - n * mx * my) / (n - 1.0);
            total += ((2.0 * mx * my + c1) * (2.0 * vxy + c2))
                / ((mx * mx + my * my + c1) * (vx + vy + c2));
            count += 1.0;
        }
    }
    total / count
}

#[test]
fn ssim_matches_brute_force_including_strided_views() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let a = random_image(&mut rng, 41, 37, 2);
    let b = a.mapv(|v| (v + 0.2 * (v * 7.0).sin()).clamp(0.0, 1.0));
    for ch in 0..2 {
        let (x, y) = (a.index_axis(Axis(2), ch), b.index_axis(Axis(2), ch));
        let brute = ssim_brute(&x.to_owned(), &y.to_owned(), 1.0);
        let fast = ssim_gray(x, y, 1.0).unwrap();
        assert!((fast - brute).abs() < 1e-12, "{fast} vs {brute}");
        // Transposed and stepped (non-contiguous) views.
        let (xt, yt) = (x.t(), y.t());
        let brute_t = ssim_brute(&xt.to_owned(), &yt.to_owned(), 1.0);
        assert!((ssim_gray(xt, yt, 1.0).unwrap() - brute_t).abs() < 1e-12);
        let (xs, ys) = (x.slice(s![..;2, ..]), y.slice(s![..;2, ..]));
        let brute_s = ssim_brute(&xs.to_owned(), &ys.to_owned(), 1.0);
        assert!((ssim_gray(xs, ys, 1.0).unwrap() - brute_s).abs() < 1e-12);
    }
    // Colour = mean of channels.
    let mean = (0..2)
        .map(|ch| ssim_gray(a.index_axis(Axis(2), ch), b.index_axis(Axis(2), ch), 1.0).unwrap())
        .sum::<f64>()
        / 2.0;
    assert!((ssim_color(a.view(), b.view(), 1.0).unwrap() - mean).abs() < 1e-15);
}

#[test]
fn identical_images_and_symmetry() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let a = random_image(&mut rng, 20, 24, 3);
    let b = random_image(&mut rng, 20, 24, 3);
    assert_eq!(psnr(a.view(), a.view(), 1.0).unwrap(), f64::INFINITY);
    assert!((ssim_color(a.view(), a.view(), 1.0).unwrap() - 1.0).abs() < 1e-12);
    assert_eq!(
        psnr(a.view(), b.view(), 1.0).unwrap(),
        psnr(b.view(), a.view(), 1.0).unwrap()
    );
    let (sab, sba) = (
        ssim_color(a.view(), b.view(), 1.0).unwrap(),
        ssim_color(b.view(), a.view(), 1.0).unwrap(),
    );
    assert!((sab - sba).abs() < 1e-14);
    // Independent noise images are nearly uncorrelated.
    assert!(sab.abs() < 0.1, "{sab}");
}

#[test]
fn constant_offset_closed_forms() {
    let (a, delta) = (0.4f32, 0.05f32);
    let truth = Array3::from_elem((16, 16, 3), a);
    let est = truth.mapv(|v| v + delta);
    // MSE = δ² -> PSNR = −20·log10(δ) for data range 1, +20·log10(R) for range R.
    let d = f64::from(est[[0, 0, 0]]) - f64::from(a);
    let p = psnr(est.view(), truth.view(), 1.0).unwrap();
    assert!((p + 20.0 * d.log10()).abs() < 1e-9, "{p}");
    let p2 = psnr(est.view(), truth.view(), 2.0).unwrap();
    assert!((p2 - p - 20.0 * 2f64.log10()).abs() < 1e-9);
    // Flat images: no variance, SSIM = luminance term (2μxμy + C1)/(μx² + μy² + C1).
    let (mx, my, c1) = (f64::from(est[[0, 0, 0]]), f64::from(a), 1e-4);
    let want = (2.0 * mx * my + c1) / (mx * mx + my * my + c1);
    let got = ssim_color(est.view(), truth.view(), 1.0).unwrap();
    assert!((got - want).abs() < 1e-12, "{got} vs {want}");
    // PSNR over any dimensionality.
    let flat = truth.view().into_shape_with_order(768).unwrap();
    let flat_e = est.view().into_shape_with_order(768).unwrap();
    assert_eq!(psnr(flat_e, flat, 1.0).unwrap(), p);
}

#[test]
fn metric_errors_are_reported() {
    let a = Array3::<f32>::zeros((8, 8, 3));
    let b = Array3::<f32>::zeros((8, 9, 3));
    assert!(psnr(a.view(), b.view(), 1.0).is_err());
    assert!(psnr(a.view(), a.view(), 0.0).is_err());
    assert!(psnr(a.view(), a.view(), f64::NAN).is_err());
    assert!(ssim_color(a.view(), b.view(), 1.0).is_err());
    let small = Array3::<f32>::zeros((6, 8, 3));
    assert!(ssim_color(small.view(), small.view(), 1.0).is_err());
    let v4 = ndarray::Array4::<f32>::zeros((8, 8, 3, 1)).into_dyn();
    assert!(ssim(v4.view(), v4.view(), 1.0).is_err());
    let empty = Array2::<f32>::zeros((0, 5));
    assert!(psnr(empty.view(), empty.view(), 1.0).is_err());
}

#[test]
fn evaluate_protocol() {
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let truth = random_image(&mut rng, 30, 28, 3).mapv(|v| 4.0 * v);
    let est = truth.mapv(|v| v * 1.05 + 0.01);
    let opts = EvalOptions {
        border: 3,
        normalize_percentile: Some(99.5),
    };
    // Identity.
    let sc = evaluate(truth.view(), truth.view(), &opts).unwrap();
    assert_eq!(sc.psnr_linear, f64::INFINITY);
    assert!((sc.ssim_srgb - 1.0).abs() < 1e-12);
    // Normalisation makes the scores independent of the exposure unit.
    let base = evaluate(est.view(), truth.view(), &opts).unwrap();
    let scaled = evaluate(
        est.mapv(|v| v * 8.0).view(),
        truth.mapv(|v| v * 8.0).view(),
        &opts,
    )
    .unwrap();
    assert!((base.psnr_linear - scaled.psnr_linear).abs() < 1e-4);
    assert!((base.ssim_srgb - scaled.ssim_srgb).abs() < 1e-5);
    // Without normalisation, values are clipped to [0, 1]: by hand on the cropped images.
    let plain = EvalOptions {
        border: 3,
        normalize_percentile: None,
    };
    let sc = evaluate(est.view(), truth.view(), &plain).unwrap();
    let crop = |a: &Array3<f32>| a.slice(s![3..27, 3..25, ..]).mapv(|v| v.clamp(0.0, 1.0));
    let (e, t) = (crop(&est), crop(&truth));
    assert_eq!(sc.psnr_linear, psnr(e.view(), t.view(), 1.0).unwrap());
    assert_eq!(sc.ssim_linear, ssim_color(e.view(), t.view(), 1.0).unwrap());
    let (es, ts) = (e.mapv(linear_to_srgb), t.mapv(linear_to_srgb));
    assert_eq!(sc.psnr_srgb, psnr(es.view(), ts.view(), 1.0).unwrap());
    assert_eq!(sc.ssim_srgb, ssim_color(es.view(), ts.view(), 1.0).unwrap());
}

#[test]
fn evaluate_errors() {
    let a = Array3::<f32>::ones((20, 20, 3));
    let opt = |border, p| EvalOptions {
        border,
        normalize_percentile: p,
    };
    assert!(evaluate(a.view(), a.view(), &opt(10, None)).is_err()); // nothing left
    assert!(evaluate(a.view(), a.view(), &opt(7, None)).is_err()); // 6x6 < SSIM window
    assert!(evaluate(a.view(), a.view(), &opt(6, None)).is_ok());
    let b = Array3::<f32>::ones((20, 21, 3));
    assert!(evaluate(a.view(), b.view(), &opt(0, None)).is_err());
    assert!(evaluate(a.view(), a.view(), &opt(0, Some(0.0))).is_err());
    assert!(evaluate(a.view(), a.view(), &opt(0, Some(101.0))).is_err());
    let zeros = Array3::<f32>::zeros((20, 20, 3));
    assert!(evaluate(a.view(), zeros.view(), &opt(0, Some(99.5))).is_err());
    let mut nan = a.clone();
    nan[[5, 5, 1]] = f32::NAN;
    assert!(evaluate(nan.view(), a.view(), &opt(0, None)).is_err());
}
