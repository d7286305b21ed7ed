//! Tests of the joint demosaic-merge's internals (bins, targets, regression, weights).
#![forbid(unsafe_code)]

use super::colour_ratios::garrote;
use super::regression::{ellipse_spans, gather_row};
use super::test_oracle::{ellipse_span, gather_row_reference};
use super::weights::{lane_power, MAX_SNAP_MULTIPLE};
use super::*;
use crate::cpu::Isa;

#[test]
fn coarse_bins_share_each_fine_bin_between_the_nearest_coarse_bins() {
    // A sparse channel's coarse bins keep every plane's total, put a fine bin on a coarse
    // bin's centre wholly there and one halfway between two (f = 2) half in each; the
    // other channels' planes stay 0. R, G and B of the 75 % W pattern are sparse, W is not.
    use crate::cfa::{generate, Pattern};
    use crate::merge::kernels::{kernel_field, KernelConfig};
    let (h, w) = (12usize, 20usize);
    let reference = Array2::from_elem((h, w), 0.3f32);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let kernels = kernel_field(&reference, &KernelConfig::default()).unwrap();
    let mut acc = MergeAccumulator::new(
        &cfa,
        &kernels,
        &AccumulateConfig::default(),
        PixelModel::binary(0.0),
    )
    .unwrap();
    let sparse = acc.sparse_channels();
    assert_eq!(sparse, [true, true, true, false]);
    let (stride, fine_w) = (acc.stride, acc.bins_w);
    let at = |by: usize, plane: usize, bx: usize| (by * SUMS + plane) * stride + bx;
    // G's Σ r·counts: a sample on coarse bin (3, 4), one between (3, 5) and (4, 5)
    // vertically, one between (4, 6), (4, 7), (5, 6) and (5, 7); W's plane too.
    let plane = PLANES;
    acc.bins[at(6, plane, 8)] = 8.0;
    acc.bins[at(7, plane, 10)] = 4.0;
    acc.bins[at(9, plane, 13)] = 16.0;
    acc.bins[at(6, 3 * PLANES, 8)] = 5.0;
    let coarse = acc.coarse_bins(sparse, PLANES);
    let get = |cy: usize, p: usize, cx: usize| coarse.bins[(cy * SUMS + p) * coarse.stride + cx];
    assert_eq!(get(3, plane, 4), 8.0);
    assert_eq!((get(3, plane, 5), get(4, plane, 5)), (2.0, 2.0));
    for (cy, cx) in [(4, 6), (4, 7), (5, 6), (5, 7)] {
        assert_eq!(get(cy, plane, cx), 4.0);
    }
    let total: f32 = (0..coarse.bins_h)
        .flat_map(|cy| (0..coarse.bins_w).map(move |cx| (cy, cx)))
        .map(|(cy, cx)| get(cy, plane, cx))
        .sum();
    assert_eq!(total, 28.0);
    assert!(coarse.bins.iter().enumerate().all(|(i, &v)| {
        let p = (i / coarse.stride) % SUMS;
        v == 0.0 || p == plane
    }));
    assert_eq!(
        (coarse.bins_h, coarse.bins_w),
        ((acc.bins_h - 1) / 2 + 1, (fine_w - 1) / 2 + 1)
    );
    assert_eq!((coarse.u, coarse.margin), (1.0, acc.margin as f32));
}

#[test]
fn affine_targets_match_the_per_site_positions() {
    // `fill_affine` (eight sites at a time, the local mask's rounding reused) against
    // `fill` with the position closures of SubBlockMotion::Affine and ::CameraAndLocal.
    use rand::{Rng, SeedableRng};
    let (h, w) = (23usize, 37usize);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let robust: Vec<f32> = (0..h * w).map(|_| rng.gen_range(-0.2..1.0)).collect();
    let excluded: Vec<bool> = (0..h * w).map(|_| rng.gen_bool(0.05)).collect();
    let mask: Vec<bool> = (0..h * w).map(|i| (i / w) % 7 < 2 || i % w > 30).collect();
    let flow: Vec<f32> = (0..h * w * 2).map(|_| rng.gen_range(-2.5..2.5)).collect();
    let (u, margin) = (2.0f32, 3.0f32);
    let bins_h = (h - 1 + 6) * 2 + 1;
    let bins_w = (w - 1 + 6) * 2 + 1;
    let grid = TargetGrid {
        h,
        w,
        u,
        margin,
        bins_h,
        bins_w,
        stride: (bins_w + LANES - 1).next_multiple_of(LANES),
        excluded: Some(&excluded),
        robust: Some(&robust),
    };
    for (matrix, offset) in [
        ([[1.0, 0.0], [0.0, 1.0]], [0.5, -0.5]),
        ([[1.001, 0.01], [-0.012, 0.998]], [-1.37, 2.61]),
        ([[0.97, 0.2], [-0.2, 0.97]], [4.2, -7.9]),
    ] {
        let mut fast = vec![(0u32, 0.0f32); h * w];
        let mut plain = vec![(1u32, 1.0f32); h * w];
        let mut fast_spans = vec![(0u32, 0u32); h];
        let mut plain_spans = vec![(1u32, 1u32); h];
        // Every row's span is its lowest and highest target bin of a site kept.
        let spans_of = |targets: &[(u32, f32)]| -> Vec<(u32, u32)> {
            targets
                .chunks(w)
                .map(|row| {
                    let kept: Vec<u32> = row
                        .iter()
                        .map(|&(bin, _)| bin)
                        .filter(|&bin| bin != u32::MAX)
                        .collect();
                    match (kept.iter().min(), kept.iter().max()) {
                        (Some(&lo), Some(&hi)) => (lo, hi),
                        _ => (u32::MAX, 0),
                    }
                })
                .collect()
        };
        // Both fills agree, excluded sites have no target, and the spans are the targets'.
        let check = |fast: &[(u32, f32)],
                     fast_spans: &[(u32, u32)],
                     plain: &[(u32, f32)],
                     plain_spans: &[(u32, u32)],
                     case: &str| {
            assert_eq!(fast, plain, "{case} {matrix:?} {offset:?}");
            assert!(excluded
                .iter()
                .zip(fast)
                .all(|(&e, &(bin, _))| !e || bin == u32::MAX));
            assert_eq!(fast_spans, spans_of(fast));
            assert_eq!(plain_spans, spans_of(plain));
        };
        // The portable lanes and, where the CPU has them, the AVX2 ones.
        for isa in [Isa::generic(), Isa::current()] {
            grid.fill_affine(isa, &mut fast, &mut fast_spans, &matrix, &offset, None);
            grid.fill(&mut plain, &mut plain_spans, |q| {
                affine_position(&matrix, &offset, q)
            });
            check(&fast, &fast_spans, &plain, &plain_spans, "affine");
        }

        let (hf, wf) = ((h - 1) as f32, (w - 1) as f32);
        grid.fill(&mut plain, &mut plain_spans, |q| {
            let p = affine_position(&matrix, &offset, q);
            let inside = p[0] >= 0.0 && p[1] >= 0.0 && p[0] <= hf && p[1] <= wf;
            if inside && !mask[round_half_away(p[0]) as usize * w + round_half_away(p[1]) as usize]
            {
                p
            } else {
                reference_position(&flow, h, w, q)
            }
        });
        for isa in [Isa::generic(), Isa::current()] {
            grid.fill_affine(
                isa,
                &mut fast,
                &mut fast_spans,
                &matrix,
                &offset,
                Some((&mask, &flow)),
            );
            check(&fast, &fast_spans, &plain, &plain_spans, "camera and local");
        }
    }
}

#[test]
fn lane_targets_avx2_match_the_scalar_lanes() {
    // `lane_targets_avx2` (where `Isa::current()` has AVX2) against `lane_targets` (the
    // portable path, which an AVX2 CPU otherwise never runs) on lanes inside and outside the image and the bins, at their
    // edges, NaN and infinite, with and without a robustness map, skipped or not.
    #[cfg(target_arch = "x86_64")]
    {
        use rand::{Rng, SeedableRng};
        let isa = Isa::current();
        if !isa.avx2() {
            return;
        }
        let (h, w) = (11usize, 13usize);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let robust: Vec<f32> = (0..h * w)
            .map(|i| match i % 9 {
                0 => 0.0,
                1 => f32::NAN,
                _ => rng.gen_range(-0.3..1.0),
            })
            .collect();
        let (bins_h, bins_w) = (27usize, 31usize);
        let specials = [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -0.0,
            -1.0,
            0.0,
            (h - 1) as f32,
            (w - 1) as f32,
            bins_h as f32,
            bins_w as f32,
            (bins_h - 1) as f32,
            1e10,
        ];
        let value = |rng: &mut rand_chacha::ChaCha8Rng, hi: f32| -> f32 {
            if rng.gen_bool(0.3) {
                specials[rng.gen_range(0..specials.len())]
            } else {
                rng.gen_range(-3.0..hi + 3.0f32).round()
            }
        };
        for map in [Some(&robust[..]), None] {
            let grid = TargetGrid {
                h,
                w,
                u: 2.0,
                margin: 1.0,
                bins_h,
                bins_w,
                stride: (bins_w + LANES - 1).next_multiple_of(LANES),
                excluded: None,
                robust: map,
            };
            for _ in 0..2000 {
                let rounded: [[f32; LANES]; 2] = [
                    std::array::from_fn(|_| value(&mut rng, h as f32)),
                    std::array::from_fn(|_| value(&mut rng, w as f32)),
                ];
                let bin: [[f32; LANES]; 2] = [
                    std::array::from_fn(|_| value(&mut rng, bins_h as f32)),
                    std::array::from_fn(|_| value(&mut rng, bins_w as f32)),
                ];
                let skip: [bool; LANES] = std::array::from_fn(|_| rng.gen_bool(0.2));
                let plain = match map {
                    Some(m) => grid.lane_targets(&rounded, &bin, &skip, |i| m[i]),
                    None => grid.lane_targets(&rounded, &bin, &skip, |_| 1.0),
                };
                let fast = grid
                    .lane_targets_x86(isa, &rounded, &bin, &skip)
                    .expect("AVX2, and a map of H·W values");
                let bits = |t: [(u32, f32); LANES]| t.map(|(b, r)| (b, r.to_bits()));
                assert_eq!(bits(fast), bits(plain), "{rounded:?} {bin:?} {skip:?}");
            }
        }
    }
}

#[test]
fn gather_row_matches_the_group_by_group_reference() {
    // The regression with its weights made a bin row at a time against the form where the
    // channels took turns per group of eight bins: bit for bit, with random bins and
    // kernels, for CFAs whose channels share weights (R, G, B), make their own (W) or have
    // a narrower ellipse of their own, at output scales 1 and 2 and a wide radius.
    use crate::cfa::{generate, Pattern};
    use crate::merge::kernels::{kernel_field, KernelConfig};
    use rand::{Rng, SeedableRng};
    let (h, w) = (13usize, 29usize);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let reference = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.05f32..0.95)).mapv(|v| v * v);
    let mut compared = 0;
    for pattern in [
        Pattern::Bayer,
        Pattern::Rgbw50,
        Pattern::Rgbw75Regular,
        Pattern::Colorspad,
    ] {
        let cfa = match generate(&pattern, h, w, 5) {
            Ok(cfa) => cfa,
            Err(_) => continue, // a pattern of fixed size
        };
        // And a W-rich CFA with exactly as many R, G and B sites, and /tmp/cap10k's pattern.
        let [equal, cap10k] = extra_cfas(h, w);
        let cfas = [cfa, equal, cap10k];
        for cfa in &cfas {
            for (scale, bins, max_radius, exponent) in [
                (1, 2, 5, 1.0),
                (2, 2, 5, 1.0),
                (1, 3, 8, 0.5),
                (2, 1, 3, 1.0),
            ] {
                let config = AccumulateConfig {
                    scale,
                    bins_per_output_px: bins,
                    max_radius,
                    spacing_exponent: exponent,
                    ..AccumulateConfig::default()
                };
                let kernels =
                    kernel_field(&reference, &KernelConfig::default().for_output_scale(scale))
                        .unwrap();
                let mut acc =
                    MergeAccumulator::new(cfa, &kernels, &config, PixelModel::binary(0.0)).unwrap();
                let stride = acc.stride;
                for (i, v) in acc.bins.iter_mut().enumerate() {
                    // Padding columns stay 0; some empty bins.
                    if i % stride < acc.bins_w && rng.gen_bool(0.8) {
                        *v = rng.gen_range(0.0f32..50.0);
                    }
                }
                assert_rows_match_the_reference(
                    &acc,
                    h * scale,
                    &format!("{pattern:?} {config:?}"),
                );
                compared += 1;
            }
        }
    }
    assert!(compared >= 24, "{compared}");
}

#[test]
fn scales_near_a_multiple_of_the_sparsest_are_snapped_and_others_kept() {
    // /tmp/cap10k's CFA: 7,936 R, 15,748 G, 7,812 B and 94,488 W sites. B is the sparsest;
    // R is 1.6 % denser (its factor 1 times B's), G about twice and W about 12 times.
    let n = 125_984.0f32;
    let scales = [n / 7_936.0, n / 15_748.0, n / 7_812.0, n / 94_488.0];
    let (snapped, multiples) = snap_scales(scales);
    let b = scales[2];
    assert_eq!(multiples, [1, 2, 0, 12]);
    assert_eq!(snapped, [b, b / 2.0, b, b / 12.0]);
    // Bayer: R the sparsest (the first of equal ones), B shares it, G is half of it.
    assert_eq!(
        snap_scales([4.0, 2.0, 4.0, 0.0]),
        ([4.0, 2.0, 4.0, 0.0], [0, 2, 1, 0])
    );
    // 1 % apart: shared; 3 % apart, a ratio of 1.55, absent channels: kept.
    assert_eq!(
        snap_scales([12.0, 12.12, 0.0, 0.0]),
        ([12.12, 12.12, 0.0, 0.0], [1, 0, 0, 0])
    );
    assert_eq!(
        snap_scales([12.0, 12.4, 8.0, 0.0]),
        ([12.0, 12.4, 8.0, 0.0], [0, 0, 0, 0])
    );
    assert_eq!(snap_scales([0.0; 4]), ([0.0; 4], [0; 4]));
}

#[test]
fn lane_power_is_the_power() {
    let w: [f32; LANES] = std::array::from_fn(|i| 0.05 + 0.13 * i as f32);
    for k in 1..=MAX_SNAP_MULTIPLE {
        let p = lane_power(w, k);
        for i in 0..LANES {
            let exact = (w[i] as f64).powi(k as i32);
            assert!(
                (p[i] as f64 - exact).abs() <= 1e-6 * exact + 1e-30,
                "{k} {i}: {} vs {exact}",
                p[i]
            );
        }
    }
}

#[test]
fn garrote_is_zero_within_the_threshold_and_shrinks_beyond_it() {
    assert_eq!(garrote(0.5, 1.0), 0.0);
    assert_eq!(garrote(-1.0, 1.0), 0.0);
    assert_eq!(garrote(2.0, 1.0), 1.5);
    assert_eq!(garrote(-4.0, 2.0), -3.0);
    assert_eq!(garrote(0.3, 0.0), 0.3);
}

#[test]
fn index_in_is_the_saturating_cast_inside_its_range() {
    for hi in [0.0f32, 1.0, 253.0, 1015.0, 16_777_216.0, 2_147_483_520.0] {
        let mut values = vec![0.0, -0.0, hi, f32::NAN, 0.999_999_9];
        values.extend((0..1000).map(|i| hi * i as f32 / 999.0));
        values.extend((0..100).map(|i| (i as f32 * 0.37).min(hi)));
        for v in values {
            assert_eq!(index_in(v, hi), v as i32, "{v} in [0, {hi}]");
        }
        // Outside: clamped (the callers discard those lanes).
        assert_eq!(index_in(-5.0, hi), 0);
        assert_eq!(index_in(f32::INFINITY, hi), hi as i32);
        assert_eq!(index_in(f32::NEG_INFINITY, hi), 0);
    }
}

#[test]
fn round_half_away_matches_f32_round() {
    let mut values = vec![
        0.0,
        0.5,
        -0.5,
        1.5,
        -1.5,
        2.5,
        0.49999997,
        -0.49999997,
        8_388_607.5,
        1e9,
        -1e9,
    ];
    values.extend((-4000..4000).map(|i| i as f32 * 0.013_7 + 0.25));
    values.extend([f32::INFINITY, f32::NEG_INFINITY, 3e9, -3e9, 2_147_483_520.0]);
    for v in values {
        assert_eq!(round_half_away(v), v.round(), "{v}");
        assert_eq!(round_half_away_trunc(v), v.round(), "{v}");
    }
    assert!(round_half_away(f32::NAN).is_nan());
    assert!(round_half_away_trunc(f32::NAN).is_nan());
}

#[test]
fn ellipse_span_holds_every_dx_below_the_limit() {
    let limit = 20.0;
    for (a, b2, c) in [(1.0f32, 0.0f32, 1.0f32), (4.0, 3.0, 1.5), (0.3, -0.5, 2.0)] {
        for dy in [-3.0f32, -0.5, 0.0, 1.25, 4.0] {
            let span = ellipse_span(a, b2, c, dy, limit);
            for i in -400..=400 {
                let dx = i as f32 * 0.025;
                let quad = a * dy * dy + dx * (b2 * dy + c * dx);
                if (quad as f64) < limit {
                    let (lo, hi) = span.expect("row with a point below the limit");
                    assert!(lo <= dx as f64 && dx as f64 <= hi, "{a} {b2} {c} {dy} {dx}");
                }
            }
        }
    }
    // A row entirely outside the ellipse.
    assert_eq!(ellipse_span(1.0, 0.0, 1.0, 10.0, limit), None);
}

#[test]
fn ellipse_spans_are_the_rows_ellipse_spans() {
    // The vectorised form against the per-row one, bit for bit, empty rows and
    // non-definite forms included.
    let dys: Vec<f32> = (0..41).map(|i| i as f32 * 0.25 - 5.1).collect();
    let mut spans = vec![[0.0f64; 2]; dys.len()];
    for limit in [9.0f64, 12.0, 108.0] {
        for (a, b2, c) in [
            (1.0f32, 0.0f32, 1.0f32),
            (4.0, 3.0, 1.5),
            (0.3, -0.5, 2.0),
            (16.0, 31.9, 16.0),
            (1.0, 4.0, 1.0),
            (1.0, 0.0, 0.0),
            (f32::NAN, 0.0, 1.0),
        ] {
            ellipse_spans(a, b2, c, &dys, limit, &mut spans);
            for (&dy, span) in dys.iter().zip(&spans) {
                let want = ellipse_span(a, b2, c, dy, limit)
                    .map_or([f64::INFINITY, f64::NEG_INFINITY], |(l, h)| [l, h]);
                assert_eq!(
                    span.map(f64::to_bits),
                    want.map(f64::to_bits),
                    "{a} {b2} {c} {dy} {limit}"
                );
            }
        }
    }
}

/// Two CFAs of `gather_row_matches_the_group_by_group_reference`: a W-rich one with exactly as
/// many R, G and B sites (one pass of three channels, `RowPass::run3`), and /tmp/cap10k's
/// pattern (W rows, then W with R and G, W with G and B): as many R as B sites, G twice and W
/// about 14 times (weights as powers of R's, `snap_scales`), G's and W's ellipses their own.
fn extra_cfas(h: usize, w: usize) -> [Cfa; 2] {
    [
        {
            let mut codes = Array2::from_elem((h, w), 3u8);
            for (k, i) in (0..h * w).step_by(4).take(93).enumerate() {
                codes[[i / w, i % w]] = (k % 3) as u8;
            }
            Cfa::new(codes).unwrap()
        },
        {
            let codes = Array2::from_shape_fn((h, w), |(y, x)| match (y % 4, x % 4) {
                (1, 1) => 0,
                (1, 3) | (3, 1) => 1,
                (3, 3) => 2,
                _ => 3,
            });
            Cfa::new(codes).unwrap()
        },
    ]
}

/// Every output row (`hs` of them) of `acc`'s regression over its bins, AVX2 (where the CPU has
/// it) and portable, against the group-by-group reference, bit for bit (the flux planes too).
fn assert_rows_match_the_reference(acc: &MergeAccumulator, hs: usize, what: &str) {
    let ws = acc.cfa.width() * acc.config.scale;
    acc.with_gather(|g| {
        for oy in 0..hs {
            let mut fast = vec![[0.0f32; SUMS]; ws];
            let mut generic = vec![[1.0f32; SUMS]; ws];
            let mut reference = vec![[2.0f32; SUMS]; ws];
            gather_row(g, Isa::current(), oy, &mut fast);
            gather_row(g, Isa::generic(), oy, &mut generic);
            gather_row_reference(g, oy, &mut reference);
            let bits =
                |v: &Vec<[f32; SUMS]>| v.iter().map(|s| s.map(f32::to_bits)).collect::<Vec<_>>();
            assert_eq!(bits(&fast), bits(&reference), "{what} {oy}");
            assert_eq!(bits(&generic), bits(&reference), "{what}");
            assert!(reference.iter().flatten().any(|&v| v > 0.0));
            // The bins' flux planes (S3) are gathered too.
            assert!(reference.iter().any(|s| s[PLANES - 1] > 0.0));
        }
    });
}
