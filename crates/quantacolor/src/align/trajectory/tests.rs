//! Tests of the photon-trajectory fit: the row-factorised score against a site-by-site
//! oracle, the AVX2 kernels against the portable paths, the banded solver, the knots.

use super::config::TrajectoryConfig;
use super::knots::Trajectory;
use super::likelihood::{
    frame_score, frame_score_by_rows, group_end_positions, row_sums_scalar, InformativeBlocks,
    RowSampling, RowSums, ScoreTemplate, TemplatePlanes, P_MIN,
};
use super::sites::{chunk_bits, site_bit, RowMap, Sites};
use super::solve::BandedSpd;
use super::template::Splats;
use crate::align::refine::{sample_template, template_level, AffineMotion, TemplateLevel};
use crate::capture::frames::FrameLayout;
use crate::capture::BinaryFrames;
use crate::cpu::Isa;
use ndarray::Array2;

/// Calls `visit(y, x, detected)` for every grey site of frame `t` (the site-by-site
/// reference).
fn for_each_site(
    frames: &BinaryFrames,
    sites: &Sites,
    t: usize,
    mut visit: impl FnMut(usize, usize, bool),
) {
    let packed = matches!(frames.layout(), FrameLayout::Packed);
    for (y, columns) in sites.columns.iter().enumerate() {
        let row = frames.raw_row(t, y);
        for &x in columns {
            let x = x as usize;
            visit(y, x, site_bit(row, x, packed));
        }
    }
}

/// [`frame_score`] site by site, each site's 6 + 21 products summed directly (the reference
/// of the test).
fn frame_score_reference(
    frames: &BinaryFrames,
    sites: &Sites,
    t: usize,
    camera: &AffineMotion,
    level: &TemplateLevel,
    margin: f64,
) -> ([f64; 6], [[f64; 6]; 6]) {
    let mut g = [0.0f64; 6];
    let mut info = [[0.0f64; 6]; 6];
    for_each_site(frames, sites, t, |y, x, bit| {
        let rel = [y as f64 - sites.centre[0], x as f64 - sites.centre[1]];
        let d = camera.at(rel);
        let Some([v, gy, gx]) =
            sample_template(level, y as f64 + d[0] + margin, x as f64 + d[1] + margin)
        else {
            return;
        };
        let p = v.clamp(P_MIN, 1.0 - P_MIN);
        // ∂p/∂θ for θ = (b_y, b_x, m_yy, m_yx, m_xy, m_xx).
        let j = [gy, gx, gy * rel[0], gy * rel[1], gx * rel[0], gx * rel[1]];
        let weight = 1.0 / (p * (1.0 - p));
        let score = if bit { 1.0 / p } else { -1.0 / (1.0 - p) };
        for a in 0..6 {
            g[a] += score * j[a];
            let wa = weight * j[a];
            for b in a..6 {
                info[a][b] += wa * j[b];
            }
        }
    });
    for a in 0..6 {
        for b in 0..a {
            info[a][b] = info[b][a];
        }
    }
    (g, info)
}

/// Random packed binary frames of shape `[frames, h, w]` (each bit set with probability
/// `p`, seeded), as bits and as frames, and the sites where `is_site(y, x)`.
fn random_capture(
    [n, h, w]: [usize; 3],
    p: f64,
    seed: u64,
    is_site: impl Fn(usize, usize) -> bool,
) -> (ndarray::Array3<u8>, BinaryFrames, Sites) {
    use crate::capture::frames::pack_bits;
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let bits = ndarray::Array3::from_shape_fn((n, h, w), |_| rng.gen_bool(p) as u8);
    let frames = BinaryFrames::from_packed(pack_bits(&bits), w).unwrap();
    let columns = (0..h)
        .map(|y| {
            (0..w)
                .filter(|&x| is_site(y, x))
                .map(|x| x as u16)
                .collect()
        })
        .collect();
    let sites = Sites::new(w, columns, [(h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0]);
    (bits, frames, sites)
}

#[test]
fn banded_cholesky_solves_a_known_system() {
    // Pentadiagonal SPD matrix, checked against A x.
    let n = 12;
    let mut a = BandedSpd::zeros(n, 2);
    let mut dense = vec![vec![0.0f64; n]; n];
    for i in 0..n {
        for (d, v) in [(0usize, 6.0), (1, -1.5), (2, 0.5)] {
            if i + d < n {
                a.add(i, i + d, v);
                dense[i][i + d] += v;
                if d > 0 {
                    dense[i + d][i] += v;
                }
            }
        }
    }
    let x: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).sin()).collect();
    let rhs: Vec<f64> = (0..n)
        .map(|i| (0..n).map(|j| dense[i][j] * x[j]).sum())
        .collect();
    let solved = a.solve(&rhs).expect("positive definite");
    for (s, e) in solved.iter().zip(&x) {
        assert!((s - e).abs() < 1e-12, "{s} vs {e}");
    }
}

/// The row-factorised score and information equal the site-by-site sums (to rounding) on a
/// random binary frame against a textured template, under an affine camera, with sites
/// that fall outside the template skipped alike.
#[test]
fn frame_score_equals_the_site_by_site_sums() {
    let (h, w, margin) = (40, 56, 6usize);
    let (_, frames, sites) = random_capture([2, h, w], 0.3, 5, |y, x| (x + 2 * y) % 3 != 0);
    let template = Array2::from_shape_fn((h + 2 * margin, w + 2 * margin), |(y, x)| {
        0.3 + 0.2 * ((y as f32 / 3.0).sin() * (x as f32 / 4.0).cos())
    });
    let level = template_level(&template, 0.8);
    // The last camera moves part of the image beyond the template's margin.
    for camera in [
        AffineMotion::default(),
        AffineMotion {
            b: [1.3, -2.1],
            m: [[0.01, -0.02], [0.015, -0.005]],
        },
        AffineMotion {
            b: [9.0, 4.5],
            m: [[0.0, 0.03], [-0.03, 0.0]],
        },
    ] {
        // The f64 row sums agree to rounding, as does `frame_score` on the generic paths; on
        // the current instruction set (f32 lanes where the CPU has AVX2 and FMA) to f32
        // rounding.
        for t in 0..2 {
            let (g_ref, info_ref) =
                frame_score_reference(&frames, &sites, t, &camera, &level, margin as f64);
            let scale = info_ref
                .iter()
                .flatten()
                .fold(0.0f64, |m, v| m.max(v.abs()));
            let g_scale = g_ref.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let scalar = frame_score_by_rows(
                &frames,
                &sites,
                t,
                &camera,
                margin as f64,
                |row, y, columns, d| row_sums_scalar(&level, None, row, y, columns, d),
            );
            let score_on = |isa: Isa| {
                let template = ScoreTemplate::new(&level, isa);
                frame_score(&frames, &sites, t, &camera, &template, margin as f64)
            };
            let (generic, current) = (score_on(Isa::generic()), score_on(Isa::current()));
            for ((g, info), tolerance) in [(scalar, 1e-10), (generic, 1e-10), (current, 1e-5)] {
                for a in 0..6 {
                    assert!(
                        (g[a] - g_ref[a]).abs() <= tolerance * g_scale,
                        "{g:?} vs {g_ref:?}"
                    );
                    for b in 0..6 {
                        assert!(
                            (info[a][b] - info_ref[a][b]).abs() <= tolerance * scale,
                            "{a} {b}: {} vs {}",
                            info[a][b],
                            info_ref[a][b]
                        );
                    }
                }
            }
        }
    }
}

/// The row runs' planar loads give the same bits as the transposed loads on every row,
/// under a still camera (every group a row run), a small turn and zoom (most groups), and a
/// camera that moves part of the image beyond the template (no run where a lane is outside).
#[cfg(target_arch = "x86_64")]
#[test]
fn row_runs_sum_the_same_bits_as_the_transposed_loads() {
    use super::x86::row_sums;
    let isa = Isa::current();
    if !isa.avx2_fma() {
        return;
    }
    let (h, w, margin) = (40, 67, 6usize);
    let (_, frames, sites) = random_capture([1, h, w], 0.3, 11, |y, x| (x + 2 * y) % 3 != 0);
    let template = Array2::from_shape_fn((h + 2 * margin, w + 2 * margin), |(y, x)| {
        0.3 + 0.2 * ((y as f32 / 3.0).sin() * (x as f32 / 4.0).cos())
    });
    let level = template_level(&template, 0.8);
    let planes = TemplatePlanes::new(&level);
    let packed = matches!(frames.layout(), FrameLayout::Packed);
    for camera in [
        AffineMotion::default(),
        AffineMotion {
            b: [0.4, -0.7],
            m: [[0.004, -0.006], [0.006, 0.003]],
        },
        AffineMotion {
            b: [9.0, 4.5],
            m: [[0.0, 0.03], [-0.03, 0.0]],
        },
    ] {
        for y in 0..h {
            let map = RowMap::new(&sites, &camera, y, packed, margin as f64);
            let row = frames.raw_row(0, y);
            let masks = &sites.masks[y];
            let (runs, transposed) = (
                row_sums(
                    isa,
                    &level,
                    &RowSampling {
                        planes: Some(&planes),
                        blocks: None,
                    },
                    row,
                    y,
                    masks,
                    &map,
                ),
                row_sums(isa, &level, &RowSampling::default(), row, y, masks, &map),
            );
            let bits = |r: &RowSums| {
                let mut v: Vec<u64> = r.score.iter().flatten().map(|x| x.to_bits()).collect();
                v.extend(r.weight.iter().flatten().map(|x| x.to_bits()));
                v
            };
            assert_eq!(bits(&runs), bits(&transposed), "row {y} under {camera:?}");
        }
    }
}

/// A row run is eight lanes at consecutive pixels of one row; any other layout is not.
#[cfg(target_arch = "x86_64")]
#[test]
fn row_runs_are_eight_consecutive_pixels_of_one_row() {
    if !Isa::current().avx2() {
        return;
    }
    use super::x86::row_run_start;
    use std::arch::x86_64::*;
    let start = |y: [i32; 8], x: [i32; 8]| {
        // SAFETY: the CPU has AVX2 (an `Isa` never holds a feature the CPU lacks).
        unsafe {
            row_run_start(
                _mm256_loadu_si256(y.as_ptr().cast()),
                _mm256_loadu_si256(x.as_ptr().cast()),
                100,
            )
        }
    };
    let run = [10, 11, 12, 13, 14, 15, 16, 17];
    assert_eq!(start([5; 8], run), Some(510));
    assert_eq!(start([5, 5, 5, 5, 5, 5, 5, 6], run), None);
    assert_eq!(start([5; 8], [10, 11, 12, 13, 15, 16, 17, 18]), None);
    assert_eq!(start([5; 8], [10; 8]), None);
}

#[test]
fn splats_agree_between_the_vector_and_scalar_paths() {
    let (h, w, margin) = (30, 45, 4usize);
    let (bits, frames, sites) = random_capture([1, h, w], 0.4, 9, |y, x| (x + y) % 4 != 1);
    let (th, tw) = (h + 2 * margin, w + 2 * margin);
    // A turn and a shift that carry part of the image beyond the margin (most groups of
    // eight sites splatted one by one), and a small shift (most groups as runs, carried).
    for camera in [
        AffineMotion {
            b: [5.3, -3.7],
            m: [[0.02, 0.05], [-0.05, 0.01]],
        },
        AffineMotion {
            b: [0.3, 4.6],
            m: [[0.0, 0.001], [-0.001, 0.0]],
        },
    ] {
        let maps: Vec<RowMap> = (0..h)
            .map(|y| RowMap::new(&sites, &camera, y, true, margin as f64))
            .collect();
        let splat_all = |isa: Isa| {
            let mut splats = Splats::zeros(th, tw, isa);
            for (y, map) in maps.iter().enumerate() {
                splats.add_row(frames.raw_row(0, y), y, &sites, map);
            }
            splats
        };
        let (scalar, vector) = (splat_all(Isa::generic()), splat_all(Isa::current()));
        // Every site inside adds weights summing to 1 (to the sum where it detected).
        let (mut inside, mut detected) = (0usize, 0usize);
        for (y, map) in maps.iter().enumerate() {
            for &x in &sites.columns[y] {
                let (py, px) = map.position(y, x as usize);
                if py >= 0.0 && px >= 0.0 && py < (th - 1) as f64 && px < (tw - 1) as f64 {
                    inside += 1;
                    detected += usize::from(bits[[0, y, x as usize]]);
                }
            }
        }
        assert!(inside > 0 && inside < sites.count());
        for splats in [&scalar, &vector] {
            assert!((splats.exposure.sum() - inside as f32).abs() < 1e-2);
            assert!((splats.sum.sum() - detected as f32).abs() < 1e-2);
        }
        for (a, b) in [
            (&scalar.sum, &vector.sum),
            (&scalar.exposure, &vector.exposure),
        ] {
            let largest = a
                .iter()
                .zip(b)
                .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(largest < 1e-4, "largest difference {largest}");
        }
    }
}

#[test]
fn validate_names_each_out_of_range_setting() {
    assert!(TrajectoryConfig::default().validate().is_ok());
    type Edit = fn(&mut TrajectoryConfig);
    let cases: [(&str, Edit); 10] = [
        ("knot_frames", |c| c.knot_frames = 0),
        ("iterations", |c| c.iterations = 0),
        ("early_row_step", |c| c.early_row_step = 0),
        ("sigmas_px", |c| c.sigmas_px.clear()),
        ("sigmas_px", |c| c.sigmas_px[1] = f32::NAN),
        ("acceleration_px", |c| c.acceleration_px = 0.0),
        ("acceleration_px", |c| c.acceleration_px = f64::INFINITY),
        ("informative_fraction", |c| c.informative_fraction = 0.0),
        ("informative_fraction", |c| c.informative_fraction = 1.5),
        ("informative_fraction", |c| {
            c.informative_fraction = f64::NAN
        }),
    ];
    for (key, edit) in cases {
        let mut config = TrajectoryConfig::default();
        edit(&mut config);
        let message = config.validate().expect_err(key).to_string();
        assert!(message.contains(key), "{key}: {message}");
    }
}

#[test]
fn early_sites_keep_every_nth_row_and_empty_the_others() {
    let columns: Vec<Vec<u16>> = (0..7u16).map(|y| vec![y, y + 3, 20]).collect();
    let sites = Sites::new(24, columns.clone(), [3.0, 11.5]);
    let early = sites.every_nth_row(3);
    for (y, row) in early.columns.iter().enumerate() {
        let kept = if y % 3 == 0 {
            columns[y].clone()
        } else {
            vec![]
        };
        assert_eq!(row, &kept, "row {y}");
        let expected_masks = if y % 3 == 0 {
            &sites.masks[y]
        } else {
            &vec![0u8; 3]
        };
        assert_eq!(&early.masks[y], expected_masks, "row {y}");
    }
    assert_eq!(early.count(), 9);
    assert_eq!(early.centre, sites.centre);
    assert_eq!(sites.every_nth_row(1).columns, columns);
}

#[test]
fn chunk_bits_read_packed_and_unpacked_rows_alike() {
    use crate::capture::frames::pack_bits;
    let row: Vec<u8> = (0..21u32).map(|x| u8::from(x % 3 == 0 || x == 7)).collect();
    let packed = pack_bits(&ndarray::Array3::from_shape_vec((1, 1, 21), row.clone()).unwrap());
    let packed = packed.as_slice().unwrap();
    for k in 0..3 {
        let expected = (0..8)
            .filter(|l| row.get(8 * k + l) == Some(&1))
            .fold(0u32, |bits, l| bits | 1 << l);
        assert_eq!(chunk_bits(packed, k, true), expected);
        assert_eq!(chunk_bits(&row, k, false), expected);
    }
}

#[test]
fn banded_cholesky_rejects_an_indefinite_matrix() {
    let mut a = BandedSpd::zeros(3, 1);
    a.add(0, 0, 1.0);
    a.add(0, 1, 2.0);
    a.add(1, 1, 1.0);
    a.add(2, 2, 1.0);
    assert!(a.solve(&[1.0, 1.0, 1.0]).is_none());
}

#[test]
fn knots_interpolate_linearly_and_end_at_the_last_frame() {
    let mut tr = Trajectory::new(10, 4);
    assert_eq!(tr.times, vec![0, 4, 8, 9]);
    for (k, &t) in tr.times.clone().iter().enumerate() {
        tr.knots[k][0] = 2.0 * t as f64;
    }
    for t in 0..10 {
        assert!((tr.params_at(t as f64)[0] - 2.0 * t as f64).abs() < 1e-12);
    }
    assert!((tr.params_at(5.5)[0] - 11.0).abs() < 1e-12);
}

/// A template textured in its left half only: the informative blocks lie there, hold the
/// asked fraction of the information, and a fraction of 1 keeps every site.
#[test]
fn informative_blocks_hold_the_asked_fraction_where_the_texture_is() {
    let (h, w) = (48, 64);
    let template = Array2::from_shape_fn((h, w), |(y, x)| {
        let texture = if x < w / 2 {
            0.2 * ((y as f32 / 2.0).sin() * (x as f32 / 3.0).cos())
        } else {
            0.0
        };
        0.3 + texture
    });
    let level = template_level(&template, 0.8);
    assert!(InformativeBlocks::new(&level, 1.0).is_none());
    let blocks = InformativeBlocks::new(&level, 0.9).expect("a fraction below 1");
    let kept = blocks.kept_fraction();
    assert!(kept > 0.1 && kept <= 0.5 + 1e-9, "kept {kept}");
    // Blocks right of the texture (beyond the blur's reach) are dropped.
    for by in 0..blocks.height {
        for bx in (w / 2 + 8) / 8..blocks.width {
            assert_eq!(blocks.kept[by * blocks.width + bx], 0, "block ({by}, {bx})");
        }
    }
}

/// With informative blocks, the generic and AVX2 scores both equal the site-by-site sums
/// over the groups that `keeps_group` keeps (from the f32 positions of their end columns),
/// under still, turned and far-moved cameras; and the AVX2 kernel's eight-group decisions are
/// `keeps_group`'s, bit for bit.
#[test]
fn informative_blocks_select_the_same_groups_on_every_path() {
    let (h, w, margin) = (40, 72, 6usize);
    let (_, frames, sites) = random_capture([2, h, w], 0.3, 9, |y, x| (x + 2 * y) % 3 != 0);
    let template = Array2::from_shape_fn((h + 2 * margin, w + 2 * margin), |(y, x)| {
        let bump = (-(((y as f32 - 20.0).powi(2) + (x as f32 - 30.0).powi(2)) / 60.0)).exp();
        0.3 + 0.25 * bump * (x as f32 / 2.0).sin()
    });
    let level = template_level(&template, 0.8);
    let packed = matches!(frames.layout(), FrameLayout::Packed);
    let blocks = InformativeBlocks::new(&level, 0.8).expect("a fraction below 1");
    for camera in [
        AffineMotion::default(),
        AffineMotion {
            b: [1.3, -2.1],
            m: [[0.01, -0.02], [0.015, -0.005]],
        },
        AffineMotion {
            b: [9.0, 4.5],
            m: [[0.0, 0.03], [-0.03, 0.0]],
        },
    ] {
        let (mut kept_groups, mut dropped_groups) = (0, 0);
        for y in 0..h {
            let map = RowMap::new(&sites, &camera, y, packed, margin as f64);
            let groups = w.div_ceil(8);
            let keeps: Vec<bool> = (0..groups)
                .map(|k| blocks.keeps_group(group_end_positions(&map, y, k)))
                .collect();
            kept_groups += keeps.iter().filter(|&&k| k).count();
            dropped_groups += keeps.iter().filter(|&&k| !k).count();
            #[cfg(target_arch = "x86_64")]
            if Isa::current().avx2_fma() {
                for k in (0..groups).step_by(8) {
                    // SAFETY: the CPU has AVX2 and FMA (checked above).
                    let bits = unsafe { super::x86::kept_groups8(&blocks, y, k, &map) };
                    for l in 0..8.min(groups - k) {
                        assert_eq!(bits >> l & 1 == 1, keeps[k + l], "row {y} group {}", k + l);
                    }
                }
            }
        }
        assert!(
            kept_groups > 0 && dropped_groups > 0,
            "{kept_groups} {dropped_groups}"
        );
        for t in 0..2 {
            // The reference: site by site over the kept groups only.
            let kept_sites = Sites::new(
                w,
                (0..h)
                    .map(|y| {
                        let map = RowMap::new(&sites, &camera, y, packed, margin as f64);
                        sites.columns[y]
                            .iter()
                            .copied()
                            .filter(|&x| {
                                let k = x as usize / 8;
                                blocks.keeps_group(group_end_positions(&map, y, k))
                            })
                            .collect()
                    })
                    .collect(),
                sites.centre,
            );
            let (g_ref, info_ref) =
                frame_score_reference(&frames, &kept_sites, t, &camera, &level, margin as f64);
            let scale = info_ref
                .iter()
                .flatten()
                .fold(0.0f64, |m, v| m.max(v.abs()));
            let g_scale = g_ref.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (isa, tolerance) in [(Isa::generic(), 1e-10), (Isa::current(), 1e-5)] {
                let template = ScoreTemplate::informative(&level, isa, 0.8);
                let (g, info) = frame_score(&frames, &sites, t, &camera, &template, margin as f64);
                for a in 0..6 {
                    assert!(
                        (g[a] - g_ref[a]).abs() <= tolerance * g_scale,
                        "{g:?} vs {g_ref:?}"
                    );
                    for b in 0..6 {
                        assert!(
                            (info[a][b] - info_ref[a][b]).abs() <= tolerance * scale,
                            "{a} {b}: {} vs {}",
                            info[a][b],
                            info_ref[a][b]
                        );
                    }
                }
            }
        }
    }
}
