//! Unit tests of the patch alignment: every AVX2 kernel against its portable reference
//! (`Isa::current()` against `Isa::generic()`, bit for bit) and the second motion's steps.
#![forbid(unsafe_code)]

use super::cost::{seed_costs, tile_cost, window_costs, window_row_costs, Tile};
use super::lucas_kanade::{lk_gradient_dot_error, lk_gradient_dot_error_generic, LkScratch};
use super::search::best_offset;
use super::second_motion::{fill_ambiguous_labels, rejected_components, TileMask};
use super::Norm;
use crate::cpu::Isa;
use ndarray::{Array2, Array3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::ops::Range;

/// The tile at `origin` of `ts` px, the block image `alternate` against `reference`.
fn tile<'a>(
    reference: &'a Array2<f32>,
    alternate: &'a Array2<f32>,
    origin: (usize, usize),
    ts: usize,
    norm: Norm,
    isa: Isa,
) -> Tile<'a> {
    Tile {
        reference,
        alternate,
        origin,
        ts,
        norm,
        isa,
    }
}

#[test]
fn rejected_components_are_the_large_sets_far_from_the_camera() {
    // 4x6 tiles, camera flow zero; a 2x2 set 3 px off (rejected), one tile 3 px off
    // elsewhere (too small), one tile 1 px off (within the tolerance).
    let camera = Array3::<f32>::zeros((4, 6, 2));
    let mut flow = camera.clone();
    for (i, j) in [(0, 0), (0, 1), (1, 0), (1, 1), (3, 5)] {
        flow[[i, j, 1]] = 3.0;
    }
    flow[[2, 3, 0]] = 1.0;
    let components = rejected_components(&flow, &camera, 2.0, 2);
    assert_eq!(components.len(), 1);
    let mut tiles = components[0].clone();
    tiles.sort();
    assert_eq!(tiles, vec![(0, 0), (0, 1), (1, 0), (1, 1)]);
    // min_tiles 0 counts as 1: the lone tile is a component too.
    assert_eq!(rejected_components(&flow, &camera, 2.0, 0).len(), 2);
}

#[test]
fn ambiguous_tiles_take_their_decided_neighbours_majority_inside_the_region() {
    // One row of five tiles, all in the region: decided ends, ambiguous middle.
    let region = TileMask(Array2::from_elem((1, 5), true));
    let mut label =
        Array2::from_shape_vec((1, 5), vec![Some(true), None, None, None, Some(false)]).unwrap();
    fill_ambiguous_labels(&mut label, &region);
    // Round 1: tile 1 sees one `true`, tile 3 one `false`, tile 2 none (it waits);
    // round 2: tile 2 sees one of each, a tie, which goes to the camera.
    assert_eq!(
        label.into_raw_vec_and_offset().0,
        vec![
            Some(true),
            Some(true),
            Some(false),
            Some(false),
            Some(false)
        ]
    );
    // Neighbours outside the region do not vote, and tiles outside it are left alone.
    let region = TileMask(Array2::from_shape_vec((1, 3), vec![false, true, true]).unwrap());
    let mut label = Array2::from_shape_vec((1, 3), vec![Some(true), None, None]).unwrap();
    fill_ambiguous_labels(&mut label, &region);
    assert_eq!(
        label.into_raw_vec_and_offset().0,
        vec![Some(true), None, None]
    );
}

/// Lucas–Kanade's Σ g·e equals a plain f64 sum of the bilinear samples' errors, for an
/// interior tile (contiguous taps), tiles clamped at the left and right edges, and a tile
/// narrower than the eight lanes.
#[test]
fn lucas_kanade_sums_match_the_direct_sum() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (h, w) = (40usize, 50usize);
    let alt = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0));
    let reference = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0));
    let cases = [
        (10..26, 12..28, (0.3f32, -0.7f32)),
        (5..21, 0..16, (-0.4, -1.6)),
        (20..36, 34..50, (0.9, 1.2)),
        (3..8, 44..50, (0.2, 0.45)),
        (0..8, 20..28, (-0.6, 0.1)),
        (30..40, 4..28, (0.5, -0.3)),
    ];
    for (ys, xs, u) in cases {
        let grad: Vec<(f32, f32)> = (0..ys.len() * xs.len())
            .map(|_| (rng.gen_range(-1.0f32..1.0), rng.gen_range(-1.0f32..1.0)))
            .collect();
        let grad_y: Vec<f32> = grad.iter().map(|g| g.0).collect();
        let grad_x: Vec<f32> = grad.iter().map(|g| g.1).collect();
        // A scratch left over from a wider tile: its contents must not leak in.
        let mut scratch = LkScratch {
            fxs: vec![9.0; 40],
            errors: vec![9.0; 40],
            ..LkScratch::default()
        };
        scratch.rows = ys
            .clone()
            .map(|y| crate::filters::bilinear_taps(y as f32 + u.0, h))
            .collect();
        scratch.cols = xs
            .clone()
            .map(|x| crate::filters::bilinear_taps(x as f32 + u.1, w))
            .collect();
        let (sy, sx) = lk_gradient_dot_error(
            Isa::current(),
            &alt,
            &reference,
            (&grad_y, &grad_x),
            &mut scratch,
            (ys.clone(), xs.clone()),
        );
        // The portable path, by `Isa::generic()` and called directly: the same numbers bit
        // for bit.
        let generic = lk_gradient_dot_error(
            Isa::generic(),
            &alt,
            &reference,
            (&grad_y, &grad_x),
            &mut scratch,
            (ys.clone(), xs.clone()),
        );
        let direct = lk_gradient_dot_error_generic(
            &alt,
            &reference,
            (&grad_y, &grad_x),
            &mut scratch,
            (ys.clone(), xs.clone()),
        );
        for portable in [generic, direct] {
            assert_eq!(
                (sy.to_bits(), sx.to_bits()),
                (portable.0.to_bits(), portable.1.to_bits())
            );
        }
        // And the sum as it was made before the scratch buffers and split gradients.
        let before = lk_gradient_dot_error_before(
            &alt,
            &reference,
            &grad,
            &scratch.rows,
            &scratch.cols,
            (ys.clone(), xs.clone()),
        );
        assert_eq!(
            (sy.to_bits(), sx.to_bits()),
            (before.0.to_bits(), before.1.to_bits())
        );
        let (mut ey, mut ex) = (0.0f64, 0.0f64);
        for (j, y) in ys.clone().enumerate() {
            for (i, x) in xs.clone().enumerate() {
                let sample = crate::filters::bilinear(alt.view(), y as f32 + u.0, x as f32 + u.1);
                let e = (sample - reference[[y, x]]) as f64;
                let g = grad[j * xs.len() + i];
                ey += g.0 as f64 * e;
                ex += g.1 as f64 * e;
            }
        }
        assert!(
            (sy as f64 - ey).abs() < 1e-4 * (1.0 + ey.abs()),
            "{ys:?} {xs:?}: {sy} vs {ey}"
        );
        assert!(
            (sx as f64 - ex).abs() < 1e-4 * (1.0 + ex.abs()),
            "{ys:?} {xs:?}: {sx} vs {ex}"
        );
    }
}

/// [`lk_gradient_dot_error`] as it was before [`LkScratch`] (interleaved gradients, buffers
/// allocated per call, no AVX2 path): the reference of the bit-for-bit test above.
fn lk_gradient_dot_error_before(
    alt: &Array2<f32>,
    reference: &Array2<f32>,
    grad: &[(f32, f32)],
    rows: &[(usize, usize, f32)],
    cols: &[(usize, usize, f32)],
    (ys, xs): (Range<usize>, Range<usize>),
) -> (f32, f32) {
    const LANES: usize = 8;
    let (mut sum_y, mut sum_x) = ([0.0f32; LANES], [0.0f32; LANES]);
    let width = xs.len();
    let fxs: Vec<f32> = cols.iter().map(|c| c.2).collect();
    let mut errors = vec![0.0f32; width];
    for ((y, &(y0, y1, fy)), grad) in ys.zip(rows).zip(grad.chunks_exact(width)) {
        for (i, &(x0, x1, _)) in cols.iter().enumerate() {
            let fx = fxs[i];
            let top = alt[[y0, x0]] * (1.0 - fx) + alt[[y0, x1]] * fx;
            let bottom = alt[[y1, x0]] * (1.0 - fx) + alt[[y1, x1]] * fx;
            errors[i] = (top * (1.0 - fy) + bottom * fy) - reference[[y, xs.start + i]];
        }
        for (i, (e, g)) in errors.iter().zip(grad).enumerate() {
            sum_y[i % LANES] += g.0 * e;
            sum_x[i % LANES] += g.1 * e;
        }
    }
    let total = |lanes: [f32; LANES]| lanes.iter().sum::<f32>();
    (total(sum_y), total(sum_x))
}

/// A reference and an alternate image of uniform random values in [0, 1), drawn in that
/// order from `rng`.
fn random_image_pair(rng: &mut ChaCha8Rng, h: usize, w: usize) -> (Array2<f32>, Array2<f32>) {
    let reference = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0));
    let alternate = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0));
    (reference, alternate)
}

/// Every cost of a window row equals [`tile_cost`] bit for bit: interior tiles, tiles at
/// every border, offsets reaching past the image, both norms.
#[test]
fn window_row_costs_equal_tile_cost() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (h, w) = (29usize, 41usize);
    let (reference, alternate) = random_image_pair(&mut rng, h, w);
    let mut finite = 0;
    for norm in [Norm::L1, Norm::L2] {
        for ts in [8usize, 16] {
            for oy in (0..h).step_by(5) {
                for ox in (0..w).step_by(3) {
                    for radius in [1isize, 4, 8] {
                        let dy = rng.gen_range(-6isize..=6);
                        let dx0 = rng.gen_range(-12isize..=6);
                        for isa in [Isa::generic(), Isa::current()] {
                            let t = tile(&reference, &alternate, (oy, ox), ts, norm, isa);
                            let mut costs = vec![0.0f32; (2 * radius + 1) as usize];
                            window_row_costs(&t, (dy, dx0), &mut costs);
                            for (i, &c) in costs.iter().enumerate() {
                                let d = (dy, dx0 + i as isize);
                                let expected = tile_cost(&t, d);
                                assert_eq!(c.to_bits(), expected.to_bits(), "{oy} {ox} {d:?}");
                                finite += c.is_finite() as usize;
                            }
                        }
                    }
                }
            }
        }
    }
    assert!(finite > 1000, "{finite}");
}

/// The transposed kernel of windows that no offset clips ([`interior_window_costs`]) gives
/// the plain loop's bits for both tile sizes, both norms and window sides of one to the
/// largest strip; it declines windows that clip the tile or would read past the image.
#[cfg(target_arch = "x86_64")]
#[test]
fn interior_window_costs_equal_the_plain_tile_cost() {
    let isa = Isa::current();
    if !isa.avx2() {
        return;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (h, w) = (70usize, 83usize);
    let (reference, alternate) = random_image_pair(&mut rng, h, w);
    let (mut taken, mut declined) = (0, 0);
    for norm in [Norm::L1, Norm::L2] {
        for ts in [8usize, 16] {
            for side in [1usize, 2, 3, 7, 9, 17, 33, 49] {
                for _ in 0..40 {
                    let rows = rng.gen_range(1..=side.min(9));
                    let (oy, ox) = (rng.gen_range(0..h - 4), rng.gen_range(0..w - 4));
                    let dy0 = rng.gen_range(-(oy as isize) - 3..8);
                    let dx0 = rng.gen_range(-(ox as isize) - 3..8);
                    let mut costs = vec![f32::NAN; rows * side];
                    let t = tile(&reference, &alternate, (oy, ox), ts, norm, isa);
                    let ok = super::x86::interior_window_costs(&t, (dy0, dx0), side, &mut costs);
                    let clipped = oy + ts > h
                        || ox + ts > w
                        || oy as isize + dy0 < 0
                        || ox as isize + dx0 < 0
                        || oy as isize + dy0 + (rows + ts - 1) as isize > h as isize
                        || ox as isize + dx0 + (side + ts - 1) as isize > w as isize;
                    if clipped {
                        assert!(!ok, "{oy} {ox} {dy0} {dx0} {side} {rows}");
                    }
                    if !ok {
                        assert!(costs.iter().all(|c| c.is_nan()), "wrote while declining");
                        declined += 1;
                        continue;
                    }
                    taken += 1;
                    for (k, &c) in costs.iter().enumerate() {
                        let d = (dy0 + (k / side) as isize, dx0 + (k % side) as isize);
                        let plain = tile_cost_plain(&reference, &alternate, (oy, ox), ts, d, norm);
                        assert!(plain.is_finite());
                        assert_eq!(c.to_bits(), plain.to_bits(), "{oy} {ox} {d:?} {side}");
                    }
                }
            }
        }
    }
    assert!(taken > 100 && declined > 100, "{taken} {declined}");
}

/// The seeds' costs ([`seed_costs`], all of a tile's seeds in one kernel where they lie
/// inside the images) equal the plain loop bit for bit, for one to four seeds, both tile
/// sizes and norms, tiles inside and at the edges, seeds inside and reaching past the image.
#[test]
fn seed_costs_equal_the_plain_tile_cost() {
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let (h, w) = (57usize, 66usize);
    let (reference, alternate) = random_image_pair(&mut rng, h, w);
    let mut finite = 0;
    for norm in [Norm::L1, Norm::L2] {
        for ts in [8usize, 16] {
            for _ in 0..300 {
                let (oy, ox) = (rng.gen_range(0..h - 4), rng.gen_range(0..w - 4));
                let n = rng.gen_range(1..=4);
                let seeds: Vec<(isize, isize)> = (0..n)
                    .map(|_| (rng.gen_range(-12isize..=12), rng.gen_range(-12isize..=12)))
                    .collect();
                for isa in [Isa::generic(), Isa::current()] {
                    let t = tile(&reference, &alternate, (oy, ox), ts, norm, isa);
                    let mut costs = vec![f32::NAN; n];
                    seed_costs(&t, &seeds, &mut costs);
                    for (&c, &d) in costs.iter().zip(&seeds) {
                        let plain = tile_cost_plain(&reference, &alternate, (oy, ox), ts, d, norm);
                        assert_eq!(c.to_bits(), plain.to_bits(), "{oy} {ox} {d:?} {ts}");
                        finite += c.is_finite() as usize;
                    }
                }
            }
        }
    }
    assert!(finite > 1000, "{finite}");
}

/// [`best_offset`] is the sequential scan it replaces (keep the best so far from (∞, seed);
/// take a smaller cost, or an equal one strictly closer to zero motion): windows with ties
/// among few distinct costs, infinite and NaN costs, all infinite, seeds on either side.
#[test]
fn best_offset_equals_the_sequential_scan() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let values = [0.25f32, 0.5, 0.75, f32::INFINITY, f32::NAN];
    let mut finite_ties = 0;
    for case in 0..4000 {
        let radius = [1isize, 2, 4, 8][case % 4];
        let side = (2 * radius + 1) as usize;
        let seed = (rng.gen_range(-5isize..=5), rng.gen_range(-5isize..=5));
        let all_infinite = case % 7 == 0;
        let costs: Vec<f32> = (0..side * side)
            .map(|_| {
                if all_infinite {
                    [f32::INFINITY, f32::NAN][rng.gen_range(0..2)]
                } else {
                    values[rng.gen_range(0..values.len())]
                }
            })
            .collect();
        let mut best = (f32::INFINITY, seed);
        for (dy, row) in (-radius..=radius).zip(costs.chunks_exact(side)) {
            for (dx, &c) in (-radius..=radius).zip(row) {
                let d = (seed.0 + dy, seed.1 + dx);
                let closer = (d.0.abs() + d.1.abs()) < (best.1 .0.abs() + best.1 .1.abs());
                if c < best.0 || (c == best.0 && closer) {
                    best = (c, d);
                }
            }
        }
        let least = costs.iter().filter(|&&c| c == best.0).count();
        finite_ties += (best.0.is_finite() && least > 1) as usize;
        assert_eq!(
            best_offset(&costs, side, seed, radius),
            best.1,
            "case {case}"
        );
    }
    assert!(finite_ties > 1000, "{finite_ties}");
}

/// [`tile_cost`] as a plain loop: each row summed in column order from zero, the rows
/// added in order (the four-row batches of `rows_cost` must give these numbers).
fn tile_cost_plain(
    reference: &Array2<f32>,
    alternate: &Array2<f32>,
    (oy, ox): (usize, usize),
    ts: usize,
    (dy, dx): (isize, isize),
    norm: Norm,
) -> f32 {
    let (h, w) = (reference.nrows() as isize, reference.ncols() as isize);
    let (oy, ox, ts) = (oy as isize, ox as isize, ts as isize);
    let (y0, y1) = (oy.max(-dy).max(0), (oy + ts).min(h).min(h - dy));
    let (x0, x1) = (ox.max(-dx).max(0), (ox + ts).min(w).min(w - dx));
    if y1 <= y0 || x1 <= x0 || 4 * (y1 - y0) * (x1 - x0) < ts.min(h) * ts.min(w) {
        return f32::INFINITY;
    }
    let mut cost = 0.0f32;
    for y in y0..y1 {
        let mut row = 0.0f32;
        for x in x0..x1 {
            let d = reference[[y as usize, x as usize]]
                - alternate[[(y + dy) as usize, (x + dx) as usize]];
            row += match norm {
                Norm::L1 => d.abs(),
                Norm::L2 => d * d,
            };
        }
        cost += row;
    }
    cost / ((y1 - y0) * (x1 - x0)) as f32
}

/// Whole windows of costs ([`window_costs`], rows of offsets side by side) and single
/// costs ([`tile_cost`], rows four at a time) equal the plain loop bit for bit: interior
/// tiles, tiles at every border, offsets reaching past the image, both norms, window sides
/// of one to three vectors and wider.
#[test]
fn window_costs_equal_the_plain_tile_cost() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let (h, w) = (31usize, 45usize);
    let (reference, alternate) = random_image_pair(&mut rng, h, w);
    let mut finite = 0;
    for norm in [Norm::L1, Norm::L2] {
        for ts in [4usize, 8, 16] {
            for oy in (0..h).step_by(6) {
                for ox in (0..w).step_by(4) {
                    for side in [3usize, 5, 9, 17, 30] {
                        let dy0 = rng.gen_range(-20isize..=6);
                        let dx0 = rng.gen_range(-20isize..=6);
                        for isa in [Isa::generic(), Isa::current()] {
                            let t = tile(&reference, &alternate, (oy, ox), ts, norm, isa);
                            let mut costs = vec![0.0f32; side * side];
                            window_costs(&t, (dy0, dx0), side, &mut costs);
                            for (k, &c) in costs.iter().enumerate() {
                                let d = (dy0 + (k / side) as isize, dx0 + (k % side) as isize);
                                let plain =
                                    tile_cost_plain(&reference, &alternate, (oy, ox), ts, d, norm);
                                let single = tile_cost(&t, d);
                                assert_eq!(c.to_bits(), plain.to_bits(), "{oy} {ox} {d:?}");
                                assert_eq!(single.to_bits(), plain.to_bits(), "{oy} {ox} {d:?}");
                                finite += c.is_finite() as usize;
                            }
                        }
                    }
                }
            }
        }
    }
    assert!(finite > 10000, "{finite}");
}
