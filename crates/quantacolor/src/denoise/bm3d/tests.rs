//! The tests of BM3D: its transforms, matching, filtering and steps against their formulas and
//! plain references, and every AVX2 kernel against its portable reference (`Isa::generic()`
//! against `Isa::current()`, bit for bit).

#![forbid(unsafe_code)]

use super::filtering::{filter_group, hard_threshold, wiener_shrink};
use super::grouping::{
    centre_out, distance_at_most, find_group, low_check, low_partial_distances, low_planes,
    prev_power_of_two, squared_distance, squared_distance_at_most,
};
use super::transforms::{
    axpy, bessel_i0, haar_forward, haar_forward_general, haar_inverse, haar_inverse_general,
    kaiser_1d, matmul8_portable,
};
use super::x86::{
    distance_at_most_dispatch, hard_threshold_dispatch, low_check_dispatch, matmul8,
    wiener_shrink_dispatch,
};
use super::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// [`distance_at_most_dispatch`] of 8 × 8 blocks on `isa` (AVX2 kernel when it has AVX2).
fn distance_on(
    isa: Isa,
    a: &[f32; 64],
    b: &[f32; 64],
    limit: f32,
    two_rows: Option<f32>,
) -> Option<f32> {
    if isa.avx2() {
        distance_at_most_dispatch::<true>(a, b, limit, two_rows)
    } else {
        distance_at_most_dispatch::<false>(a, b, limit, two_rows)
    }
}

/// [`low_check_dispatch`] on `isa`.
fn low_check_on(
    isa: Isa,
    low: &LowPlanes,
    reference: &[f32],
    (y, x): (usize, usize),
    bound: f32,
) -> (u32, [f32; 8]) {
    if isa.avx2() {
        low_check_dispatch::<true>(low, reference, y, x, bound)
    } else {
        low_check_dispatch::<false>(low, reference, y, x, bound)
    }
}

/// [`hard_threshold_dispatch`] on `isa`.
fn hard_threshold_on(isa: Isa, group: &mut [f32], profile: &[f32], threshold: f32) -> f32 {
    if isa.avx2() {
        hard_threshold_dispatch::<true>(group, profile, threshold)
    } else {
        hard_threshold_dispatch::<false>(group, profile, threshold)
    }
}

/// [`wiener_shrink_dispatch`] on `isa`.
fn wiener_shrink_on(isa: Isa, group: &mut [f32], basic: &[f32], profile: &[f32], s2: f32) -> f32 {
    if isa.avx2() {
        wiener_shrink_dispatch::<true>(group, basic, profile, s2)
    } else {
        wiener_shrink_dispatch::<false>(group, basic, profile, s2)
    }
}

/// [`find_group`] on `isa`.
fn find_group_on(
    isa: Isa,
    p: &StepParams,
    geo: &Geometry,
    (yr, xr): (usize, usize),
    s: &mut Scratch,
) {
    if isa.avx2() {
        find_group::<true>(p, geo, yr, xr, s)
    } else {
        find_group::<false>(p, geo, yr, xr, s)
    }
}

fn random(len: usize, seed: u64) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..len).map(|_| rng.gen_range(-1.0..1.0)).collect()
}

/// White Gaussian noise of unit variance smoothed by a Gaussian of std `s` px and scaled
/// back to unit per-pixel variance.
fn correlated_noise(h: usize, w: usize, s: f32, seed: u64) -> ndarray::Array2<f32> {
    use rand_distr::{Distribution, StandardNormal};
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let white = ndarray::Array2::from_shape_fn((h, w), |_| StandardNormal.sample(&mut rng));
    let smooth = crate::filters::gaussian_blur(&white, s);
    let var = smooth.iter().map(|v| v * v).sum::<f32>() / smooth.len() as f32;
    smooth / var.sqrt()
}

#[test]
fn coefficient_profile_matches_the_dct_spectrum_of_smoothed_noise() {
    assert!(coefficient_profile(8, 0.0).iter().all(|&q| q == 1.0));
    let tr = Transforms::new(8, 2.0, Isa::current());
    for s in [0.5f32, 0.8, 1.2] {
        let noise = correlated_noise(256, 256, s, 11);
        // Variance of every DCT coefficient over the non-overlapping 8x8 blocks.
        let mut power = [0.0f64; 64];
        let (mut tmp, mut out) = (vec![0.0f32; 64], vec![0.0f32; 64]);
        let mut blocks = 0;
        for by in (0..256).step_by(8) {
            for bx in (0..256).step_by(8) {
                let block: Vec<f32> = (0..64).map(|k| noise[[by + k / 8, bx + k % 8]]).collect();
                tr.forward(&block, &mut tmp, &mut out);
                for (p, v) in power.iter_mut().zip(&out) {
                    *p += (*v as f64).powi(2);
                }
                blocks += 1;
            }
        }
        let profile = coefficient_profile(8, s);
        let mean_square = profile.iter().map(|q| (q * q) as f64).sum::<f64>() / 64.0;
        assert!((mean_square - 1.0).abs() < 1e-5, "{mean_square}");
        // The model against the measured σ of the coefficients that hold most of the noise
        // (within 25 %), and of the first three frequencies along each axis.
        for k in [0usize, 1, 2, 8, 9, 16, 18] {
            let measured = (power[k] / blocks as f64).sqrt();
            let ratio = profile[k] as f64 / measured;
            assert!(
                (0.75..1.33).contains(&ratio),
                "s {s}, coefficient {k}: model {} vs measured {measured}",
                profile[k]
            );
        }
        // High frequencies hold far less noise than the low ones.
        assert!(profile[63] < 0.2 * profile[0], "{profile:?}");
    }
}

#[test]
fn correlated_noise_is_removed_better_with_its_profile() {
    // A smooth ramp with a step, plus noise correlated over 0.8 px of known per-pixel σ.
    let (h, w, sigma) = (96usize, 96usize, 20.0f32);
    let clean = ndarray::Array2::from_shape_fn((h, w), |(y, x)| {
        100.0 + x as f32 + if y > 48 { 60.0 } else { 0.0 }
    });
    let noisy = &clean + &(correlated_noise(h, w, 0.8, 5) * sigma);
    let mse = |correlation: f32| {
        let config = Bm3dConfig {
            noise_correlation_px: [correlation, correlation],
            ..Bm3dConfig::default()
        };
        let out = bm3d_grey(noisy.view(), sigma, &config).unwrap();
        (&out - &clean).mapv(|v| v * v).mean().unwrap()
    };
    let (white, matched) = (mse(0.0), mse(0.8));
    assert!(
        matched < 0.8 * white,
        "white-noise model {white}, correlated {matched}"
    );
}

#[test]
fn bounded_distance_is_the_full_distance_or_none() {
    for (len, seed) in [(64usize, 1u64), (16, 2), (9, 3), (1, 4)] {
        for k in 0..50u64 {
            let a = random(len, seed * 100 + k);
            let b = random(len, seed * 1000 + k);
            let full = squared_distance(&a, &b);
            for limit in [0.0, full * 0.5, full, full * 1.0001, full * 2.0] {
                let bounded = squared_distance_at_most(&a, &b, limit);
                if full <= limit {
                    assert_eq!(bounded.map(f32::to_bits), Some(full.to_bits()));
                } else {
                    assert_eq!(bounded, None);
                }
                // The 8 x 8 kernels: the portable one and the AVX2 one, the same bits and
                // the same `None`s (also for limits between the early checks' sums).
                if len == 64 {
                    let (a8, b8): (&[f32; 64], &[f32; 64]) =
                        (a[..].try_into().unwrap(), b[..].try_into().unwrap());
                    let portable = distance_at_most(&a, &b, limit, None);
                    assert_eq!(portable.map(f32::to_bits), bounded.map(f32::to_bits));
                    // Given the sum after two rows (as `low_partial_distances` makes
                    // it), the same answer.
                    let two_rows = (0..8).fold(0.0f32, |sum, j| {
                        let (d0, d1) = (a[j] - b[j], a[j + 8] - b[j + 8]);
                        let acc = d0 * d0 + d1 * d1;
                        if j == 0 {
                            acc
                        } else {
                            sum + acc
                        }
                    });
                    for l in [limit, two_rows, two_rows * 0.999, full * 0.3] {
                        let given = distance_at_most(&a, &b, l, Some(two_rows));
                        let own = distance_at_most(&a, &b, l, None);
                        assert_eq!(given.map(f32::to_bits), own.map(f32::to_bits));
                    }
                    for isa in [Isa::generic(), Isa::current()] {
                        for l in [limit, full * 0.1, full * 0.3, full * 0.6] {
                            let wide = distance_on(isa, a8, b8, l, None);
                            let portable = distance_at_most(&a, &b, l, None);
                            assert_eq!(wide.map(f32::to_bits), portable.map(f32::to_bits));
                            let given = distance_on(isa, a8, b8, l, Some(two_rows));
                            assert_eq!(given.map(f32::to_bits), portable.map(f32::to_bits));
                        }
                    }
                }
            }
        }
    }
}

#[test]
fn transforms_of_8x8_blocks_match_the_general_path() {
    // The unrolled 8 x 8 transforms against the general one, bit for bit.
    let tr = Transforms::new(8, 2.0, Isa::current());
    let general = |block: &[f32], inverse: bool| {
        let n = 8;
        let (m1, m2): (&[f32], &[f32]) = if inverse {
            (&tr.dct_t, &tr.dct)
        } else {
            (&tr.dct, &tr.dct_t)
        };
        let mut tmp = vec![0.0f32; 64];
        for k in 0..n {
            for i in 0..n {
                axpy(
                    &mut tmp[k * n..(k + 1) * n],
                    m1[k * n + i],
                    &block[i * n..(i + 1) * n],
                );
            }
        }
        let mut out = vec![0.0f32; 64];
        for k in 0..n {
            for j in 0..n {
                axpy(
                    &mut out[k * n..(k + 1) * n],
                    tmp[k * n + j],
                    &m2[j * n..(j + 1) * n],
                );
            }
        }
        out
    };
    for seed in 0..20 {
        let block = random(64, 700 + seed);
        // The dispatched product (generic, and AVX2 where present) against the portable loop.
        let (a, b): (&[f32; 64], &[f32; 64]) = (
            block[..].try_into().unwrap(),
            tr.dct[..].try_into().unwrap(),
        );
        for isa in [Isa::generic(), Isa::current()] {
            let (mut fast, mut portable) = ([0.0f32; 64], [0.0f32; 64]);
            matmul8(isa, a, b, &mut fast);
            matmul8_portable(a, b, &mut portable);
            assert_eq!(fast.map(f32::to_bits), portable.map(f32::to_bits));
            matmul8(isa, b, a, &mut fast);
            matmul8_portable(b, a, &mut portable);
            assert_eq!(fast.map(f32::to_bits), portable.map(f32::to_bits));
            let tr = Transforms::new(8, 2.0, isa);
            let (mut tmp, mut out) = (vec![0.0f32; 64], vec![0.0f32; 64]);
            tr.forward(&block, &mut tmp, &mut out);
            assert_eq!(out, general(&block, false));
            tr.inverse(&block, &mut tmp, &mut out);
            assert_eq!(out, general(&block, true));
        }
    }
}

#[test]
fn dct_is_orthonormal_round_trip_and_parseval() {
    for n in [4usize, 8, 11] {
        let tr = Transforms::new(n, 2.0, Isa::current());
        // D·Dᵀ = I.
        for a in 0..n {
            for b in 0..n {
                let dot: f32 = (0..n).map(|i| tr.dct[a * n + i] * tr.dct[b * n + i]).sum();
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((dot - want).abs() < 1e-5, "n {n} rows {a},{b}: {dot}");
            }
        }
        let block = random(n * n, n as u64);
        let (mut tmp, mut coeffs, mut back) =
            (vec![0.0; n * n], vec![0.0; n * n], vec![0.0; n * n]);
        tr.forward(&block, &mut tmp, &mut coeffs);
        tr.inverse(&coeffs, &mut tmp, &mut back);
        for (a, b) in block.iter().zip(&back) {
            assert!((a - b).abs() < 1e-5);
        }
        let e_pix: f32 = block.iter().map(|v| v * v).sum();
        let e_coef: f32 = coeffs.iter().map(|v| v * v).sum();
        assert!((e_pix - e_coef).abs() < 1e-4 * e_pix);
    }
}

#[test]
fn block_coefficients_are_each_blocks_own_transform_bit_for_bit() {
    // The separable all-positions transform (8 x 8) and the general path (5 x 5) against
    // `forward` of every block cut out of the plane.
    for n in [8usize, 5] {
        let (h, w) = (13, 29);
        let plane = random(h * w, 11 + n as u64);
        let config = Bm3dConfig {
            block_size: n,
            ..Bm3dConfig::default()
        };
        let geo = Geometry::new(h, w, n, &config);
        let tr = Transforms::new(n, 2.0, Isa::current());
        let coeffs = BlockCoeffs::compute(&plane, &geo, &tr);
        // And computed in a given buffer, and hard-thresholded (a copy): other allocations.
        let t = 0.3;
        let recycled = BlockCoeffs::compute_in(vec![1.0; 5], &plane, &geo, &tr);
        let thresholded = coeffs.hard_thresholded(t);
        assert_eq!(coeffs.coefficients().len(), geo.ph * geo.pw * n * n);
        let (mut block, mut tmp, mut expected) =
            (vec![0.0; n * n], vec![0.0; n * n], vec![0.0; n * n]);
        for y in 0..geo.ph {
            for x in 0..geo.pw {
                let pos = y * geo.pw + x;
                for stored in [&coeffs, &recycled, &thresholded] {
                    // Whole cache lines from the first block on.
                    assert_eq!(
                        stored.block(pos).as_ptr() as usize % 64,
                        (pos * n * n * 4) % 64
                    );
                }
                let kept = coeffs
                    .block(pos)
                    .iter()
                    .map(|&v| if v.abs() > t { v } else { 0.0 });
                assert!(kept.eq(thresholded.block(pos).iter().copied()));
                assert_eq!(coeffs.block(pos), recycled.block(pos));
                for i in 0..n {
                    block[i * n..(i + 1) * n]
                        .copy_from_slice(&plane[(y + i) * w + x..(y + i) * w + x + n]);
                }
                tr.forward(&block, &mut tmp, &mut expected);
                let got = coeffs.block(y * geo.pw + x);
                let same = got
                    .iter()
                    .zip(&expected)
                    .all(|(a, b)| a.to_bits() == b.to_bits());
                assert!(same, "n = {n}, block ({y}, {x}): {got:?} != {expected:?}");
            }
        }
    }
}

#[test]
fn dct_of_constant_block_is_dc_only() {
    let tr = Transforms::new(8, 2.0, Isa::current());
    let block = vec![3.0f32; 64];
    let (mut tmp, mut coeffs) = (vec![0.0; 64], vec![0.0; 64]);
    tr.forward(&block, &mut tmp, &mut coeffs);
    assert!(
        (coeffs[0] - 24.0).abs() < 1e-4,
        "DC = 3·8 = 24, got {}",
        coeffs[0]
    );
    assert!(coeffs[1..].iter().all(|v| v.abs() < 1e-4));
}

#[test]
fn haar_is_orthonormal_round_trip_and_parseval() {
    let n2 = 5;
    for m in [1usize, 2, 4, 16, 32] {
        let orig = random(m * n2, m as u64 + 100);
        let mut g = orig.clone();
        let mut tmp = vec![0.0; m * n2];
        haar_forward(&mut g, m, n2, &mut tmp);
        let e0: f32 = orig.iter().map(|v| v * v).sum();
        let e1: f32 = g.iter().map(|v| v * v).sum();
        assert!((e0 - e1).abs() < 1e-4 * e0.max(1.0), "m {m}");
        // The first coefficient of each column is the scaled group mean.
        let mean0: f32 = (0..m).map(|b| orig[b * n2]).sum::<f32>() / m as f32;
        assert!((g[0] - mean0 * (m as f32).sqrt()).abs() < 1e-4);
        haar_inverse(&mut g, m, n2, &mut tmp);
        for (a, b) in orig.iter().zip(&g) {
            assert!((a - b).abs() < 1e-5);
        }
    }
}

#[test]
fn haar_of_eight_lanes_matches_the_general_path() {
    for n2 in [8usize, 64] {
        for m in [1usize, 2, 4, 8, 16, 32] {
            let orig = random(m * n2, (m * n2) as u64 + 7);
            let mut tmp = vec![0.0; m * n2];
            let (mut fast, mut general) = (orig.clone(), orig.clone());
            haar_forward(&mut fast, m, n2, &mut tmp);
            haar_forward_general(&mut general, m, n2, &mut tmp);
            assert_eq!(fast, general, "forward, m {m}, n2 {n2}");
            haar_inverse(&mut fast, m, n2, &mut tmp);
            haar_inverse_general(&mut general, m, n2, &mut tmp);
            assert_eq!(fast, general, "inverse, m {m}, n2 {n2}");
        }
    }
}

/// The filtering of 8 × 8 groups in eight-coefficient lanes gives the bits of the three
/// separate passes (Haar, shrinkage, inverse Haar), group and sum, for every group size,
/// both shrinkages, white and correlated noise, with and without the AVX2 kernels.
#[test]
fn group_filtering_in_lanes_matches_the_separate_passes() {
    let profiles = [vec![1.0f32; 64], coefficient_profile(8, 0.8)];
    for m in [1usize, 2, 4, 8, 16, 32] {
        for (p, profile) in profiles.iter().enumerate() {
            let seed = (m * 10 + p) as u64;
            let group: Vec<f32> = random(m * 64, seed).iter().map(|v| 40.0 * v).collect();
            let basic: Vec<f32> = random(m * 64, seed + 1).iter().map(|v| 40.0 * v).collect();
            for wiener in [false, true] {
                // Thresholds that keep about half of the coefficients.
                let param = if wiener { 300.0 } else { 10.0 };
                let mut tmp = vec![0.0; m * 64];
                let mut expected = group.clone();
                let mut b = basic.clone();
                haar_forward(&mut expected, m, 64, &mut tmp);
                let total = if wiener {
                    haar_forward(&mut b, m, 64, &mut tmp);
                    wiener_shrink(&mut expected, &b, profile, param)
                } else {
                    hard_threshold(&mut expected, profile, param)
                };
                haar_inverse(&mut expected, m, 64, &mut tmp);
                for isa in [Isa::generic(), Isa::current()] {
                    let (mut g, mut b) = (group.clone(), basic.clone());
                    let avx2 = isa.avx2();
                    let got = match (avx2, wiener) {
                        (false, false) => filter_group::<false, false>(
                            &mut g, &mut b, m, profile, param, &mut tmp,
                        ),
                        (false, true) => {
                            filter_group::<false, true>(&mut g, &mut b, m, profile, param, &mut tmp)
                        }
                        (true, false) => {
                            filter_group::<true, false>(&mut g, &mut b, m, profile, param, &mut tmp)
                        }
                        (true, true) => {
                            filter_group::<true, true>(&mut g, &mut b, m, profile, param, &mut tmp)
                        }
                    };
                    let what = format!("m {m}, profile {p}, wiener {wiener}, avx2 {avx2}");
                    assert_eq!(got.to_bits(), total.to_bits(), "{what}");
                    assert_eq!(g, expected, "{what}");
                    assert!(total > 0.0 && total < (m * 64) as f32, "{what}: {total}");
                }
            }
        }
    }
}

/// The shrinkages keep, zero and scale every coefficient as the formulas say, and their
/// lane sums equal the plain f64 sums, for 8x8 blocks and a length with a remainder (5x5).
#[test]
fn shrinkages_match_their_formulas() {
    for n2 in [64usize, 25] {
        let m = 5;
        let group = random(m * n2, 3);
        let basic = random(m * n2, 4);
        let profile: Vec<f32> = (0..n2).map(|k| 0.5 + (k % 7) as f32 * 0.2).collect();
        let (threshold, s2) = (0.9f32, 0.3f32);

        let mut thresholded = group.clone();
        let retained = hard_threshold(&mut thresholded, &profile, threshold);
        let mut expected = 0.0f64;
        for (i, (&v, &t)) in group.iter().zip(&thresholded).enumerate() {
            let q = profile[i % n2];
            if v.abs() > threshold * q {
                assert_eq!(t, v);
                expected += (q * q) as f64;
            } else {
                assert_eq!(t, 0.0);
            }
        }
        assert!(
            (retained as f64 - expected).abs() < 1e-5 * expected,
            "{retained} {expected}"
        );

        let mut shrunk = group.clone();
        let norm = wiener_shrink(&mut shrunk, &basic, &profile, s2);
        let mut expected = 0.0f64;
        for (i, (&v, &t)) in group.iter().zip(&shrunk).enumerate() {
            let (b2, q2) = (basic[i] * basic[i], profile[i % n2] * profile[i % n2]);
            let wc = b2 / (b2 + s2 * q2);
            assert_eq!(t, v * wc);
            expected += (wc * wc * q2) as f64;
        }
        assert!(
            (norm as f64 - expected).abs() < 1e-5 * expected,
            "{norm} {expected}"
        );
    }
}

/// The AVX2 shrinkages give the portable versions' bits: the shrunk coefficients and the
/// lane sums, for groups of 1 to 32 blocks of 8x8 and of 4x4 coefficients, with
/// coefficients exactly at the threshold, zeros (a zero basic coefficient with a zero
/// profile entry makes W = 0/0) and both signs.
#[test]
fn avx2_shrinkages_are_bit_identical_to_portable() {
    {
        let isa = Isa::current();
        for n2 in [64usize, 16] {
            for m in [1usize, 2, 4, 8, 16, 32] {
                let mut group = random(m * n2, 10 + m as u64);
                let mut basic = random(m * n2, 20 + m as u64);
                let mut profile: Vec<f32> = (0..n2).map(|k| 0.5 + (k % 7) as f32 * 0.2).collect();
                let threshold = 0.6f32;
                // On the threshold exactly (kept only if strictly above), zeros, -0.0.
                group[0] = threshold * profile[0];
                group[1] = -threshold * profile[1];
                group[2] = 0.0;
                group[3] = -0.0;
                basic[4] = 0.0;
                profile[4] = 0.0;
                basic[5] = -0.0;
                for s2 in [0.3f32, 0.0, 7.5] {
                    let (mut a, mut b) = (group.clone(), group.clone());
                    let ra = hard_threshold(&mut a, &profile, threshold);
                    let rb = hard_threshold_on(isa, &mut b, &profile, threshold);
                    assert_eq!(ra.to_bits(), rb.to_bits(), "n2 {n2} m {m}");
                    assert_eq!(
                        a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                        b.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                    );
                    let (mut a, mut b) = (group.clone(), group.clone());
                    let wa = wiener_shrink(&mut a, &basic, &profile, s2);
                    let wb = wiener_shrink_on(isa, &mut b, &basic, &profile, s2);
                    assert_eq!(wa.to_bits(), wb.to_bits(), "n2 {n2} m {m} s2 {s2}");
                    assert_eq!(
                        a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                        b.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                    );
                }
            }
        }
    }
}

/// A block's coefficients computed from the plane are the stored ones, bit for bit (8 x 8
/// and the general path).
#[test]
fn block_source_from_the_plane_is_the_stored_coefficients() {
    for n in [8usize, 5] {
        let (h, w) = (23usize, 31usize);
        let image = random(h * w, 40 + n as u64);
        let geo = Geometry::new(h, w, n, &Bm3dConfig::default());
        let tr = Transforms::new(n, 2.0, Isa::current());
        let coeffs = BlockCoeffs::compute(&image, &geo, &tr);
        let (stored, plane) = (BlockSource::Stored(&coeffs), BlockSource::Plane(&image));
        let (mut pixels, mut tmp) = (vec![0.0f32; n * n], vec![0.0f32; n * n]);
        let (mut a, mut b) = (vec![0.0f32; n * n], vec![0.0f32; n * n]);
        for pos in 0..geo.ph * geo.pw {
            stored.block_into(pos, &geo, &tr, (&mut pixels, &mut tmp), &mut a);
            plane.block_into(pos, &geo, &tr, (&mut pixels, &mut tmp), &mut b);
            assert_eq!(
                a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                b.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "n {n}, position {pos}"
            );
        }
    }
}

#[test]
fn kaiser_window_matches_closed_form() {
    // I0(0) = 1; I0(2) = 2.2795853023360673.
    assert!((bessel_i0(0.0) - 1.0).abs() < 1e-15);
    assert!((bessel_i0(2.0) - 2.279_585_302_336_067).abs() < 1e-12);
    let k = kaiser_1d(8, 2.0);
    assert!((k[0] - (1.0 / 2.279_585_3) as f32).abs() < 1e-6);
    for i in 0..4 {
        assert!((k[i] - k[7 - i]).abs() < 1e-7, "symmetric");
        assert!(k[i] < k[i + 1] || i == 3, "rising to the centre");
    }
}

#[test]
fn reference_grid_covers_last_position() {
    assert_eq!(reference_grid(10, 3), vec![0, 3, 6, 9]);
    assert_eq!(reference_grid(11, 3), vec![0, 3, 6, 9, 10]);
    assert_eq!(reference_grid(1, 3), vec![0]);
}

#[test]
fn previous_power_of_two() {
    let got: Vec<usize> = (1..=9).map(prev_power_of_two).collect();
    assert_eq!(got, vec![1, 2, 2, 4, 4, 4, 4, 8, 8]);
}

/// The group of a plain full search: every window position within τ, sorted by
/// (distance, position), the best `max_group − 1` kept, cut to a power of two.
fn full_search_group(p: &StepParams, geo: &Geometry, yr: usize, xr: usize) -> Vec<usize> {
    let hw = geo.half_window;
    let ref_pos = yr * geo.pw + xr;
    let reference = p.matching.block(ref_pos);
    let mut found: Vec<(f32, usize)> = Vec::new();
    for y in yr.saturating_sub(hw)..=(yr + hw).min(geo.ph - 1) {
        for x in xr.saturating_sub(hw)..=(xr + hw).min(geo.pw - 1) {
            let pos = y * geo.pw + x;
            let d = squared_distance(reference, p.matching.block(pos));
            if pos != ref_pos && d <= p.tau_sum {
                found.push((d, pos));
            }
        }
    }
    found.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    found.truncate(p.max_group - 1);
    let size = prev_power_of_two(1 + found.len()).min(prev_power_of_two(p.max_group));
    std::iter::once(ref_pos)
        .chain(found[..size - 1].iter().map(|&(_, pos)| pos))
        .collect()
}

#[test]
fn bounded_search_finds_the_full_search_group() {
    // A smooth image with repeated texture and noise, so that many blocks are near each
    // other and near the thresholds.
    let (h, w) = (48usize, 56usize);
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let image: Vec<f32> = (0..h * w)
        .map(|i| {
            let (y, x) = ((i / w) as f32, (i % w) as f32);
            100.0 + 40.0 * (x * 0.7).sin() * (y * 0.3).cos() + rng.gen_range(-20.0..20.0)
        })
        .collect();
    let config = Bm3dConfig {
        search_window: 21,
        ..Bm3dConfig::default()
    };
    let geo = Geometry::new(h, w, 8, &config);
    let tr = Transforms::new(8, 2.0, Isa::current());
    let coeffs = [BlockCoeffs::compute(&image, &geo, &tr)];
    let low = low_planes(&coeffs[0], &geo).expect("8 x 8 blocks");
    for (tau_sum, max_group) in [(64.0 * 400.0, 16), (64.0 * 3000.0, 32), (64.0 * 50.0, 8)] {
        for with_low in [true, false] {
            let p = StepParams {
                matching: &coeffs[0],
                low: with_low.then_some(&low),
                tau_sum,
                max_group,
                noisy: &[BlockSource::Stored(&coeffs[0])],
                basic: None,
                sigmas: &[20.0],
                block_variance: None,
                lambda_3d: 2.7,
                profiles: &[vec![1.0; 64]],
            };
            // One worker's scratch across many references, so that the bound from the
            // previous group is used (and sometimes from another row).
            // The portable kernels and those of `Isa::current()` (AVX2 where present), each
            // with its worker's own scratch.
            let mut s = Scratch::new(64, max_group);
            let mut s_current = Scratch::new(64, max_group);
            for &yr in &geo.ref_ys {
                for &xr in &geo.ref_xs {
                    let full = full_search_group(&p, &geo, yr, xr);
                    find_group_on(Isa::generic(), &p, &geo, (yr, xr), &mut s);
                    assert_eq!(
                        s.group, full,
                        "tau {tau_sum}, group {max_group}, low {with_low}, ({yr}, {xr})"
                    );
                    find_group_on(Isa::current(), &p, &geo, (yr, xr), &mut s_current);
                    assert_eq!(
                        s_current.group,
                        full,
                        "{} ({yr}, {xr})",
                        Isa::current().name()
                    );
                }
            }
        }
    }
}

#[test]
fn low_coefficient_partials_are_the_bounded_distance_checks() {
    // Eight lanes of the first check equal the partial sum that `distance_at_most` compares
    // after two rows of coefficients (bit for bit), and never exceed the full distance.
    let (h, w) = (20usize, 30usize);
    let image = random(h * w, 77);
    let geo = Geometry::new(h, w, 8, &Bm3dConfig::default());
    let tr = Transforms::new(8, 2.0, Isa::current());
    let coeffs = BlockCoeffs::compute(&image, &geo, &tr);
    let low = low_planes(&coeffs, &geo).expect("8 x 8 blocks");
    let reference = coeffs.block(5 * geo.pw + 4);
    for y in 0..geo.ph {
        for x0 in (0..geo.pw).step_by(8) {
            let lanes = low_partial_distances(&low, reference, y, x0);
            // With no bound every lane passes and the check returns the partials.
            let (mask, partial) = low_check(&low, reference, y, x0, f32::INFINITY);
            assert_eq!(mask, 0xff);
            assert_eq!(partial.map(f32::to_bits), lanes.map(f32::to_bits));
            for isa in [Isa::generic(), Isa::current()] {
                let (mask, wide) = low_check_on(isa, &low, reference, (y, x0), f32::INFINITY);
                assert_eq!(mask, 0xff);
                assert_eq!(
                    wide.map(f32::to_bits),
                    lanes.map(f32::to_bits),
                    "({y}, {x0})"
                );
            }
            // With bounds around the lanes' partials (and below all of them, where the
            // first row alone rejects the chunk), the mask is the lanes at most the bound.
            let mut bounds: Vec<f32> = lanes.to_vec();
            bounds.extend([
                0.0,
                lanes.iter().copied().fold(f32::INFINITY, f32::min) * 0.5,
            ]);
            for bound in bounds {
                let want = lanes
                    .iter()
                    .enumerate()
                    .fold(0u32, |m, (l, &v)| m | (((v <= bound) as u32) << l));
                assert_eq!(low_check(&low, reference, y, x0, bound).0, want);
                for isa in [Isa::generic(), Isa::current()] {
                    let (mask, _) = low_check_on(isa, &low, reference, (y, x0), bound);
                    assert_eq!(mask, want, "({y}, {x0}) bound {bound}");
                }
            }
            for (l, &got) in lanes.iter().enumerate().take(geo.pw - x0) {
                let block = coeffs.block(y * geo.pw + x0 + l);
                let mut acc = [0.0f32; 8];
                for chunk in 0..2 {
                    for j in 0..8 {
                        let d = reference[chunk * 8 + j] - block[chunk * 8 + j];
                        acc[j] += d * d;
                    }
                }
                let want = acc.iter().sum::<f32>();
                assert_eq!(got.to_bits(), want.to_bits(), "({y}, {})", x0 + l);
                assert!(got <= squared_distance(reference, block));
            }
        }
    }
}

#[test]
fn centre_out_visits_every_row_once_nearest_first() {
    assert_eq!(
        centre_out(5, 3, 9).collect::<Vec<_>>(),
        [5, 6, 4, 7, 3, 8, 9]
    );
    assert_eq!(centre_out(0, 0, 2).collect::<Vec<_>>(), [0, 1, 2]);
    assert_eq!(centre_out(4, 0, 4).collect::<Vec<_>>(), [4, 3, 2, 1, 0]);
    assert_eq!(centre_out(7, 7, 7).collect::<Vec<_>>(), [7]);
}

#[test]
fn group_starts_with_reference_even_among_identical_blocks() {
    // Constant image: every block is at distance 0; the reference must still be first.
    let (h, w) = (20usize, 20usize);
    let config = Bm3dConfig::default();
    let geo = Geometry::new(h, w, 8, &config);
    let tr = Transforms::new(8, 2.0, Isa::current());
    let coeffs = BlockCoeffs::compute(&vec![1.0; h * w], &geo, &tr);
    let noisy = [coeffs];
    let p = StepParams {
        matching: &noisy[0],
        low: None,
        tau_sum: 1.0,
        max_group: 16,
        noisy: &[BlockSource::Stored(&noisy[0])],
        basic: None,
        sigmas: &[1.0],
        block_variance: None,
        lambda_3d: 2.7,
        profiles: &[vec![1.0; 64]],
    };
    let mut s = Scratch::new(64, 16);
    find_group::<false>(&p, &geo, 6, 6, &mut s);
    assert_eq!(s.group.len(), 16);
    assert_eq!(s.group[0], 6 * geo.pw + 6);
    let mut unique = s.group.clone();
    unique.sort_unstable();
    unique.dedup();
    assert_eq!(unique.len(), 16);
}
