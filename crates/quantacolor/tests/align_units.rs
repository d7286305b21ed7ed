//! Each alignment stage against known truth: hot-pixel neighbours and draws, dark-count MLE,
//! block plans, grey-image classes, exact integer and large shifts, time/space interpolation of
//! flow, and the flow files.

use ndarray::{Array2, Array3, Array4, Axis};
use ndarray_npy::ReadNpyExt;
use quantacolor::align::patch::TileGrid;
use quantacolor::align::*;
use quantacolor::capture::frames::pack_bits;
use quantacolor::capture::BinaryFrames;
use quantacolor::cfa::{generate, Cfa, Channel, Pattern};
use quantacolor::filters::box_downsample;
use quantacolor::progress::Silent;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn frames_from(bits: &Array3<u8>) -> BinaryFrames {
    BinaryFrames::from_packed(pack_bits(bits), bits.dim().2).unwrap()
}

#[test]
fn hot_pixel_candidates_are_the_nearest_same_colour_non_hot_pixels() {
    let cfa = generate(&Pattern::Rgbw75Regular, 24, 24, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mask = Array2::from_shape_fn((24, 24), |_| rng.gen_bool(0.1));
    let k = 8;
    let hp = HotPixelCorrector::new(&cfa, &mask, k, 1).unwrap();
    assert_eq!(hp.hot_count(), mask.iter().filter(|&&m| m).count());
    for ((y, x), _) in mask.indexed_iter().filter(|(_, &m)| m) {
        let cands = hp.candidates(y, x).unwrap();
        assert_eq!(cands.len(), k);
        // Brute force: the k-th smallest squared distance among eligible pixels.
        let mut d: Vec<i64> = mask
            .indexed_iter()
            .filter(|&((yy, xx), &m)| !m && cfa.channel(yy, xx) == cfa.channel(y, x))
            .map(|((yy, xx), _)| (yy as i64 - y as i64).pow(2) + (xx as i64 - x as i64).pow(2))
            .collect();
        d.sort();
        for &(cy, cx) in cands {
            let (cy, cx) = (cy as usize, cx as usize);
            assert!(!mask[[cy, cx]]);
            assert_eq!(cfa.channel(cy, cx), cfa.channel(y, x));
            let dist = (cy as i64 - y as i64).pow(2) + (cx as i64 - x as i64).pow(2);
            assert!(
                dist <= d[k - 1],
                "({y},{x}) took ({cy},{cx}) at d²={dist} > {}",
                d[k - 1]
            );
        }
    }
    assert!(hp.candidates(0, 0).is_none() || mask[[0, 0]]);
    // A colour with no usable pixel is an error, not a panic.
    let lone = Cfa::new(Array2::from_shape_fn((4, 4), |(y, x)| {
        if (y, x) == (1, 1) {
            0
        } else {
            3
        }
    }))
    .unwrap();
    let m = Array2::from_shape_fn((4, 4), |(y, x)| (y, x) == (1, 1));
    assert!(HotPixelCorrector::new(&lone, &m, 8, 0).is_err());
    assert!(HotPixelCorrector::new(&cfa, &Array2::from_elem((3, 3), false), 8, 0).is_err());
}

#[test]
fn corrected_sums_borrow_neighbour_bits_uniformly_and_independently_of_blocks() {
    // Bayer 8x8, hot pixel at G site (2, 3); its 4 nearest G neighbours fire in every frame
    // with distinct patterns, the hot pixel always.
    let (t, h, w) = (4000, 8, 8);
    let cfa = generate(&Pattern::Bayer, h, w, 0).unwrap();
    let mut mask = Array2::from_elem((h, w), false);
    mask[[2, 3]] = true;
    let hp = HotPixelCorrector::new(&cfa, &mask, 4, 42).unwrap();
    let cands: Vec<(usize, usize)> = hp
        .candidates(2, 3)
        .unwrap()
        .iter()
        .map(|&(y, x)| (y as usize, x as usize))
        .collect();
    assert_eq!(cands.len(), 4);
    for &(y, x) in &cands {
        assert_eq!(
            (y as i32 - 2).abs() + (x as i32 - 3).abs(),
            2,
            "diagonal G neighbours"
        );
    }
    let mut bits = Array3::<u8>::zeros((t, h, w));
    for ti in 0..t {
        bits[[ti, 2, 3]] = 1;
        // Only candidate 0 is ever on: the corrected count is how often it was drawn.
        bits[[ti, cands[0].0, cands[0].1]] = 1;
        bits[[ti, 0, 0]] = (ti % 3 == 0) as u8;
    }
    let frames = frames_from(&bits);
    let whole = hp.corrected_block_sum(&frames, 0..t);
    let drawn = whole[[2, 3]] as f64 / t as f64;
    assert!(
        (drawn - 0.25).abs() < 0.03,
        "candidate 0 drawn in {drawn} of frames"
    );
    // Other pixels untouched.
    assert_eq!(whole[[0, 0]], frames.sum_range(0..t)[[0, 0]]);
    // The draw of frame t does not depend on where blocks start.
    let split =
        &hp.corrected_block_sum(&frames, 0..1234) + &hp.corrected_block_sum(&frames, 1234..t);
    assert_eq!(split, whole);
    // Same seed, same result; another seed, other draws.
    let again = HotPixelCorrector::new(&cfa, &mask, 4, 42).unwrap();
    assert_eq!(again.corrected_block_sum(&frames, 0..t), whole);
    let other = HotPixelCorrector::new(&cfa, &mask, 4, 43).unwrap();
    assert_ne!(
        other.corrected_block_sum(&frames, 0..t)[[2, 3]],
        whole[[2, 3]]
    );
}

#[test]
fn dark_count_rates_are_the_bernoulli_mle() {
    let (t, h, w) = (20000, 2, 3);
    let tau = 10.24e-6; // s per binary frame
    let rates: [[f64; 3]; 2] = [[50.0, 500.0, 5000.0], [20000.0, 0.0, 1e9]]; // cps
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let bits = Array3::from_shape_fn((t, h, w), |(_, y, x)| {
        let p: f64 = 1.0 - (-rates[y][x] * tau).exp();
        rng.gen_bool(p) as u8
    });
    let map = dark_count_rate_map(&frames_from(&bits), tau).unwrap();
    for y in 0..h {
        for x in 0..w {
            let r = rates[y][x];
            let got = map[[y, x]] as f64;
            if r == 0.0 {
                assert_eq!(got, 0.0);
            } else if r < 1e8 {
                // Poisson error of the count, plus 3 sigma.
                let n = r * tau * t as f64;
                assert!(
                    (got - r).abs() <= 3.0 * r / n.sqrt() + 1.0,
                    "{r} cps estimated {got}"
                );
            } else {
                // Always on: finite, at the k = T − 1/2 cap.
                let cap = -(1.0 - (t as f64 - 0.5) / t as f64).ln() / tau;
                assert!((got - cap).abs() / cap < 1e-4);
            }
        }
    }
    let mask = hot_pixel_mask(&map, 1000.0);
    assert_eq!(
        mask,
        ndarray::arr2(&[[false, false, true], [true, false, true]])
    );
    assert!(dark_count_rate_map(&frames_from(&bits), 0.0).is_err());
}

#[test]
fn block_plans_centre_the_reference_and_cover_every_frame() {
    for (t, b, r) in [
        (10000, 300, 5000),
        (1000, 100, 0),
        (1000, 100, 999),
        (250, 100, 125),
        (50, 100, 20),
        (1234, 200, 617),
    ] {
        let plan = BlockPlan::new(t, b, r).unwrap();
        assert_eq!(plan.blocks[0].start, 0);
        assert_eq!(plan.blocks.last().unwrap().end, t);
        for w in plan.blocks.windows(2) {
            assert_eq!(w[0].end, w[1].start);
        }
        let rb = &plan.blocks[plan.reference_block];
        assert!(rb.contains(&r));
        let bb = plan.block_size;
        if r >= bb / 2 && r + bb / 2 <= t {
            assert_eq!(rb.len(), bb);
            assert!((plan.center_frames()[plan.reference_block] - r as f64).abs() <= 0.5);
        }
        for (i, blk) in plan.blocks.iter().enumerate() {
            if i != plan.reference_block {
                assert!(
                    blk.len() >= bb.div_ceil(2) && blk.len() < bb + bb.div_ceil(2),
                    "{plan:?}"
                );
            }
        }
    }
    let p = BlockPlan::new(1000, 100, 480).unwrap();
    assert_eq!(
        p.start_frames(),
        vec![0, 130, 230, 330, 430, 530, 630, 730, 830, 930]
    );
    assert_eq!(p.blocks[0], 0..130, "the 30-frame head joins its neighbour");
    assert_eq!(p.blocks[9], 930..1000, "a 70-frame tail stays a block");
    assert_eq!(p.reference_block, 4);
    assert_eq!(p.center_frames()[0], 64.5);
    assert!(BlockPlan::new(10, 5, 10).is_err());
    assert!(BlockPlan::new(10, 0, 1).is_err());
}

#[test]
fn automatic_block_size_follows_the_light_level() {
    let (h, w) = (4, 8);
    // Long captures: B follows 30 counts / rate, clamped to 100..=1000 (and to T / 8).
    for (p, expect) in [(0.3f64, 100usize), (0.1, 300), (0.01, 1000)] {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let bits = Array3::from_shape_fn((8000, h, w), |_| rng.gen_bool(p) as u8);
        let frames = frames_from(&bits);
        let plan = BlockPlan::choose(&frames, 4000, &BlockConfig::default()).unwrap();
        let b = plan.block_size as f64;
        assert!(
            (b - expect as f64).abs() / expect as f64 <= 0.15,
            "p = {p}: B = {b}, expected ~{expect}"
        );
    }
    // Shorter captures are cut into at least 8 blocks, never shorter than 32 frames.
    for (t, expect) in [(1200usize, 150usize), (512, 64), (200, 32)] {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let bits = Array3::from_shape_fn((t, h, w), |_| rng.gen_bool(0.1) as u8);
        let frames = frames_from(&bits);
        let plan = BlockPlan::choose(&frames, t / 2, &BlockConfig::default()).unwrap();
        assert_eq!(plan.block_size, expect, "T = {t}");
    }
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let bits = Array3::from_shape_fn((3000, h, w), |_| rng.gen_bool(0.1) as u8);
    let frames = frames_from(&bits);
    let plan = BlockPlan::choose(&frames, 1500, &BlockConfig::default()).unwrap();
    assert!(
        (270..=340).contains(&plan.block_size),
        "B = {}",
        plan.block_size
    );
    let fixed = BlockConfig {
        block_size: Some(123),
        ..Default::default()
    };
    assert_eq!(
        BlockPlan::choose(&frames, 1500, &fixed).unwrap().block_size,
        123
    );
    // Long recordings: at most `max_blocks` blocks (one grey image each is kept), even past
    // `max_block_size`; a bright 250,000-frame recording would otherwise have 2,500 blocks of
    // 100 frames.
    let bright = Array3::from_elem((250_000, 1, 8), 1u8);
    let frames = frames_from(&bright);
    let plan = BlockPlan::choose(&frames, 125_000, &BlockConfig::default()).unwrap();
    assert_eq!(plan.block_size, 251);
    assert!(plan.len() <= 1000, "{} blocks", plan.len());
    let few = BlockConfig {
        max_blocks: 100,
        ..Default::default()
    };
    let plan = BlockPlan::choose(&frames, 125_000, &few).unwrap();
    assert_eq!(plan.block_size, 2526, "past max_block_size");
    assert!(plan.len() <= 100, "{} blocks", plan.len());
}

#[test]
fn grey_method_follows_the_cfa_class() {
    let bayer = generate(&Pattern::Bayer, 16, 16, 0).unwrap();
    let rgbw = generate(&Pattern::Rgbw75Regular, 16, 16, 0).unwrap();
    let mono = Cfa::uniform(16, 16, Channel::W);
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let random = Cfa::new(Array2::from_shape_fn((16, 16), |_| rng.gen_range(0..3u8))).unwrap();
    assert_eq!(
        GreyMethod::detect(&bayer),
        GreyMethod::TileAverage { py: 2, px: 2 }
    );
    assert_eq!(GreyMethod::detect(&rgbw), GreyMethod::InterpolateW);
    assert_eq!(
        GreyMethod::detect(&mono),
        GreyMethod::TileAverage { py: 1, px: 1 }
    );
    assert_eq!(GreyMethod::detect(&random), GreyMethod::Demosaic);
    assert_eq!(
        GreyMethod::resolve(GreyChoice::TileAverage, &rgbw).unwrap(),
        GreyMethod::TileAverage { py: 4, px: 4 }
    );
    assert!(GreyMethod::resolve(GreyChoice::TileAverage, &random).is_err());
    assert!(GreyMethod::resolve(GreyChoice::InterpolateW, &bayer).is_err());
}

#[test]
fn grey_images_remove_the_mosaic() {
    // A flat grey scene: filters see different rates (R 2, G 5, B 1, W 8 counts per frame scale).
    let gain = [2u32, 5, 1, 8];
    let frames = 10;
    for (cfa, method) in [
        (
            generate(&Pattern::Bayer, 12, 12, 0).unwrap(),
            GreyMethod::TileAverage { py: 2, px: 2 },
        ),
        (
            generate(&Pattern::Rgbw75Regular, 12, 12, 0).unwrap(),
            GreyMethod::TileAverage { py: 4, px: 4 },
        ),
    ] {
        let counts = cfa.codes().mapv(|c| gain[c as usize] * frames as u32);
        let g = grey_image(&counts, frames, &cfa, method).unwrap();
        let first = g[[0, 0]];
        assert!(
            g.iter().all(|&v| (v - first).abs() < 1e-5),
            "{method:?} left a mosaic"
        );
    }
    // W interpolation reproduces a linear W ramp at the colour sites, keeps W pixels.
    let cfa = generate(&Pattern::Rgbw75Regular, 12, 12, 0).unwrap();
    let ramp = |y: usize, x: usize| 100 + 3 * y as u32 + 7 * x as u32;
    let counts = Array2::from_shape_fn((12, 12), |(y, x)| {
        if cfa.channel(y, x) == Channel::W {
            ramp(y, x)
        } else {
            1
        }
    });
    let g = grey_image(&counts, 4, &cfa, GreyMethod::InterpolateW).unwrap();
    // Interior, where the Gaussian's 3σ support (3 px) sees a symmetric W neighbourhood.
    for y in 3..9 {
        for x in 3..9 {
            assert!(
                (g[[y, x]] - ramp(y, x) as f32 / 4.0).abs() < 1e-3,
                "({y},{x}): {}",
                g[[y, x]]
            );
        }
    }
    // Demosaic: a flat scene with per-channel rates gives a flat grey image (mean of planes).
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let random = Cfa::new(Array2::from_shape_fn((20, 20), |_| rng.gen_range(0..3u8))).unwrap();
    let counts = random.codes().mapv(|c| gain[c as usize]);
    let g = grey_image(&counts, 1, &random, GreyMethod::Demosaic).unwrap();
    assert!(g.iter().all(|&v| (v - 8.0 / 3.0).abs() < 1e-4));
}

#[test]
fn w_interpolation_fills_colour_sites_with_the_w_bit_rate_and_bad_input_is_an_error() {
    let (h, w) = (16, 16);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    // W sites fire 30 of 100 frames, colour sites 5: the grey image is 0.3 everywhere.
    let counts = Array2::from_shape_fn((h, w), |(y, x)| {
        if cfa.channel(y, x) == Channel::W {
            30
        } else {
            5
        }
    });
    let grey = grey_image(&counts, 100, &cfa, GreyMethod::InterpolateW).unwrap();
    assert!(grey.iter().all(|&g| (g - 0.3).abs() < 1e-5));
    assert!(grey_image(&counts, 0, &cfa, GreyMethod::InterpolateW).is_err());
    let wider = Array2::zeros((h, w + 1));
    assert!(grey_image(&wider, 100, &cfa, GreyMethod::InterpolateW).is_err());
}

/// Smooth random texture (40 sinusoids of wavelength 8–40 px) shifted by `(dy, dx)`.
fn texture(h: usize, w: usize, dy: f32, dx: f32) -> Array2<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    let waves: Vec<(f32, f32, f32)> = (0..40)
        .map(|_| {
            let k = std::f32::consts::TAU / rng.gen_range(8.0..40.0f32);
            let th = rng.gen_range(0.0..std::f32::consts::TAU);
            (
                k * th.sin(),
                k * th.cos(),
                rng.gen_range(0.0..std::f32::consts::TAU),
            )
        })
        .collect();
    Array2::from_shape_fn((h, w), |(y, x)| {
        let (y, x) = (y as f32 - dy, x as f32 - dx);
        1.0 + 0.1
            * waves
                .iter()
                .map(|&(ky, kx, ph)| (ky * y + kx * x + ph).sin())
                .sum::<f32>()
    })
}

#[test]
fn patch_alignment_finds_integer_subpixel_and_large_shifts() {
    let (h, w) = (96, 160);
    let reference = texture(h, w, 0.0, 0.0);
    let aligner = ReferenceAligner::new(&reference, &PatchConfig::default()).unwrap();
    let grid = aligner.grid().clone();
    assert_eq!((grid.tiles_y, grid.tiles_x), (11, 19));
    for (dy, dx, tol) in [
        (0.0f32, 0.0f32, 1e-4f32),
        (2.0, -3.0, 0.02),
        (0.37, -0.62, 0.02),
        (-17.4, 23.7, 0.05),
    ] {
        let flow = aligner.align(&texture(h, w, dy, dx)).unwrap();
        let mut errs: Vec<f32> = Vec::new();
        for (i, &cy) in grid.tile_centers_y.iter().enumerate() {
            for (j, &cx) in grid.tile_centers_x.iter().enumerate() {
                // Tiles whose content stays inside the image.
                let inside = |c: f32, d: f32, n: usize| {
                    c - 8.0 + d.min(0.0) >= 0.0 && c + 8.0 + d.max(0.0) <= n as f32
                };
                if inside(cy, dy, h) && inside(cx, dx, w) {
                    errs.push((flow[[i, j, 0]] - dy).hypot(flow[[i, j, 1]] - dx));
                }
            }
        }
        errs.sort_by(f32::total_cmp);
        assert!(errs.len() > 20);
        let med = errs[errs.len() / 2];
        assert!(med <= tol, "shift ({dy},{dx}): median error {med}");
    }
    assert!(aligner.align(&Array2::zeros((10, 10))).is_err());
    let bad = PatchConfig {
        tile_sizes: vec![16],
        ..Default::default()
    };
    assert!(ReferenceAligner::new(&reference, &bad).is_err());
}

#[test]
fn box_pyramid_and_tile_grid_geometry() {
    let img = Array2::from_shape_fn((5, 6), |(y, x)| (y * 6 + x) as f32);
    let d = box_downsample(&img, 2);
    assert_eq!(d.dim(), (3, 3));
    assert_eq!(d[[0, 0]], (0.0 + 1.0 + 6.0 + 7.0) / 4.0);
    assert_eq!(d[[2, 2]], (28.0 + 29.0) / 2.0);
    let g = TileGrid::new(254, 496, 16, 8);
    assert_eq!((g.tiles_y, g.tiles_x), (31, 61));
    assert_eq!(g.tile_centers_y[0], 7.5);
    assert_eq!(g.tile_centers_x[60], 487.5);
}

#[test]
fn frame_flow_interpolates_between_block_centres_and_extrapolates() {
    let plan = BlockPlan::new(400, 100, 200).unwrap();
    let centres = plan.center_frames();
    // Linear motion in time (0.01 px/frame in y, −0.02 in x), varying over tiles by + i + j.
    let v = |t: f64, i: usize, j: usize| {
        [
            (0.01 * (t - 199.5)) as f32 + i as f32,
            (-0.02 * (t - 199.5)) as f32 + j as f32,
        ]
    };
    let flow = Array4::from_shape_fn((plan.len(), 2, 3, 2), |(b, i, j, c)| v(centres[b], i, j)[c]);
    for t in [0.0, 37.0, 120.0, 199.5, 250.0, 399.0] {
        let f = frame_flow(&flow, &plan, t);
        for i in 0..2 {
            for j in 0..3 {
                for c in 0..2 {
                    assert!((f[[i, j, c]] - v(t, i, j)[c]).abs() < 1e-4, "t = {t}");
                }
            }
        }
    }
    let single = BlockPlan::new(50, 100, 10).unwrap();
    let one = Array4::from_elem((1, 2, 3, 2), 0.7f32);
    assert_eq!(
        frame_flow(&one, &single, 40.0),
        Array3::from_elem((2, 3, 2), 0.7f32)
    );
}

#[test]
fn flow_at_is_bilinear_between_tile_centres() {
    let grid = TileGrid::new(64, 80, 16, 8);
    let field = |y: f32, x: f32| [0.1 * y - 2.0, 0.05 * x + 0.02 * y];
    let tiles = Array3::from_shape_fn((grid.tiles_y, grid.tiles_x, 2), |(i, j, c)| {
        field(grid.tile_centers_y[i], grid.tile_centers_x[j])[c]
    });
    for (y, x) in [(7.5, 7.5), (20.3, 33.9), (50.0, 64.2)] {
        let f = flow_at(&tiles, &grid, y, x);
        let t = field(y, x);
        assert!((f[0] - t[0]).abs() < 1e-4 && (f[1] - t[1]).abs() < 1e-4);
    }
    // Beyond the outer centres the edge value is held.
    assert_eq!(
        flow_at(&tiles, &grid, 0.0, 0.0),
        flow_at(&tiles, &grid, 7.5, 7.5)
    );
}

#[test]
fn write_alignment_round_trips() {
    let (t, h, w) = (300, 32, 40);
    let cfa = generate(&Pattern::Bayer, h, w, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let bits = Array3::from_shape_fn((t, h, w), |_| rng.gen_bool(0.4) as u8);
    let frames = frames_from(&bits);
    let cfg = AlignConfig {
        blocks: BlockConfig {
            block_size: Some(100),
            ..Default::default()
        },
        ..Default::default()
    };
    let al = align(&frames, &cfa, None, 150, &cfg, &Silent).unwrap();
    assert_eq!(al.grey.len(), al.plan.len());
    assert!(al.grey.iter().all(|g| g.dim() == (h, w)));
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    write_alignment(&out, &al).unwrap();
    let flow = Array4::<f32>::read_npy(std::fs::File::open(out.join("flow.npy")).unwrap()).unwrap();
    assert_eq!(flow, al.flow);
    let meta: toml::Value =
        toml::from_str(&std::fs::read_to_string(out.join("flow.toml")).unwrap()).unwrap();
    assert_eq!(meta["block_size"].as_integer(), Some(100));
    assert_eq!(
        meta["block_start_frames"].as_array().unwrap().len(),
        al.plan.len()
    );
    assert_eq!(meta["tile_size"].as_integer(), Some(16));
    assert_eq!(meta["tile_stride"].as_integer(), Some(8));
    assert_eq!(
        meta["tile_centers_y"].as_array().unwrap().len(),
        al.grid.tiles_y
    );
    assert_eq!(meta["block_center_frames"][1].as_float(), Some(149.5));
    assert!(std::fs::read_dir(&out).unwrap().all(|e| !e
        .unwrap()
        .file_name()
        .to_string_lossy()
        .ends_with(".tmp")));
    // Mismatched CFA is an error.
    let small = generate(&Pattern::Bayer, 8, 8, 0).unwrap();
    assert!(align(&frames, &small, None, 150, &cfg, &Silent).is_err());
}

#[test]
fn affine_snap_recovers_camera_motion_and_keeps_a_moving_object() {
    use quantacolor::align::{snap_to_affine_fit, TileGrid};
    let (ty, tx) = (12usize, 16usize);
    let grid = TileGrid {
        tile_size: 16,
        tile_stride: 8,
        tiles_y: ty,
        tiles_x: tx,
        tile_centers_y: (0..ty).map(|i| 8.0 + 8.0 * i as f32).collect(),
        tile_centers_x: (0..tx).map(|j| 8.0 + 8.0 * j as f32).collect(),
    };
    // Camera: translation (1.5, -2.0) plus a 0.01 rad rotation about (50, 70).
    let camera = |y: f32, x: f32| {
        let (a, c) = (0.01f32, (50.0f32, 70.0f32));
        (1.5 - a * (x - c.1), -2.0 + a * (y - c.0))
    };
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut flow = ndarray::Array3::<f32>::zeros((ty, tx, 2));
    for i in 0..ty {
        for j in 0..tx {
            let (y, x) = (grid.tile_centers_y[i], grid.tile_centers_x[j]);
            let object = (3..6).contains(&i) && (3..7).contains(&j);
            let (dy, dx) = if object { (6.0, 6.0) } else { camera(y, x) };
            flow[[i, j, 0]] = dy + rng.gen_range(-0.4..0.4);
            flow[[i, j, 1]] = dx + rng.gen_range(-0.4..0.4);
        }
    }
    let snapped = snap_to_affine_fit(&flow, &grid, 2.0);
    let (mut noisy, mut fitted) = (0.0f32, 0.0f32);
    for i in 0..ty {
        for j in 0..tx {
            let object = (3..6).contains(&i) && (3..7).contains(&j);
            if object {
                assert_eq!(snapped[[i, j, 0]], flow[[i, j, 0]], "object tile replaced");
                continue;
            }
            let (dy, dx) = camera(grid.tile_centers_y[i], grid.tile_centers_x[j]);
            noisy = noisy.max(
                (flow[[i, j, 0]] - dy)
                    .abs()
                    .max((flow[[i, j, 1]] - dx).abs()),
            );
            fitted = fitted.max(
                (snapped[[i, j, 0]] - dy)
                    .abs()
                    .max((snapped[[i, j, 1]] - dx).abs()),
            );
        }
    }
    assert!(
        fitted < 0.1 && noisy > 0.3,
        "fit error {fitted}, noise {noisy}"
    );
    // Tolerance 0 disables the fit.
    assert_eq!(snap_to_affine_fit(&flow, &grid, 0.0), flow);
}

#[test]
fn block_centre_flow_turns_block_means_into_centre_frame_flows() {
    // Quadratic trajectory d(t) = 0.001 (t − 256)² + 0.01 (t − 256): block means differ from
    // the value at the centre frame by 0.001 (B² − 1) / 12 and the reference block's mean from
    // d(256) = 0; both are removed exactly for a quadratic.
    let plan = BlockPlan::new(512, 64, 256).unwrap();
    let d = |t: f64| 0.001 * (t - 256.0).powi(2) + 0.01 * (t - 256.0);
    let n = plan.len();
    let reference_mean: f64 = plan.blocks[plan.reference_block]
        .clone()
        .map(|t| d(t as f64))
        .sum::<f64>()
        / plan.blocks[plan.reference_block].len() as f64;
    let mut measured = Array4::<f32>::zeros((n, 2, 3, 2));
    for (k, range) in plan.blocks.iter().enumerate() {
        let mean = range.clone().map(|t| d(t as f64)).sum::<f64>() / range.len() as f64;
        measured
            .slice_mut(ndarray::s![k, .., .., 0])
            .fill((mean - reference_mean) as f32);
        measured.slice_mut(ndarray::s![k, .., .., 1]).fill(1.5);
    }
    let centre = block_centre_flow(&measured, &plan);
    for (k, &c) in plan.center_frames().iter().enumerate() {
        assert!(
            (centre[[k, 1, 2, 0]] as f64 - d(c)).abs() < 1e-3,
            "block {k}: {} vs {}",
            centre[[k, 1, 2, 0]],
            d(c)
        );
        // A constant offset of every block from the reference frame is not motion.
        assert!(centre[[k, 0, 0, 1]].abs() < 1e-4);
    }
    // Without it the 32-frame end blocks are off by 0.001 (64² − 32²) / 12 = 0.26 px.
    let worst = (0..n)
        .map(|k| (measured[[k, 0, 0, 0]] as f64 - d(plan.center_frames()[k])).abs())
        .fold(0.0, f64::max);
    assert!(worst > 0.2, "{worst}");
}

#[test]
fn median_filter_skips_unrefined_tiles() {
    let mut flow = Array3::<f32>::from_elem((3, 3, 2), 0.4);
    let mut valid = Array2::from_elem((3, 3), true);
    for (i, j) in [(0, 0), (0, 1), (1, 0), (1, 1), (2, 2)] {
        flow[[i, j, 0]] = 0.0; // integer result where Lucas–Kanade failed
        valid[[i, j]] = false;
    }
    // Unmasked, the five integer tiles win the median; masked, the refined ones decide.
    assert_eq!(median_filter_flow(&flow, 1)[[1, 1, 0]], 0.0);
    assert_eq!(median_filter_valid_flow(&flow, &valid, 1)[[1, 1, 0]], 0.4);
    // A window with no refined tile falls back to all of them.
    let none = Array2::from_elem((3, 3), false);
    assert_eq!(
        median_filter_valid_flow(&flow, &none, 1),
        median_filter_flow(&flow, 1)
    );
}

#[test]
fn second_motion_leaves_a_still_grating_matched_periods_off_with_the_camera() {
    // A still scene seen 0.5 px to the right: a vertical grating of period 16.25 px in a
    // textured frame. The camera fit is exact, but its integer flow is 0.5 px off the match,
    // while a period on (16.75 px) the integer offset 17 px is 0.25 px off it. The grating's
    // tiles, matched two periods on by the tile search, score better a period away (without
    // the check of the reference's own period they were sent 16.25 px off).
    let (h, w) = (128, 192);
    let (period, motion) = (16.25f32, 0.5f32);
    let on_grating = |y: usize, x: usize| (40..96).contains(&y) && (48..152).contains(&x);
    let scene = |dx: f32| {
        let background = texture(h, w, 0.0, dx);
        Array2::from_shape_fn((h, w), |(y, x)| {
            if on_grating(y, x) {
                1.0 + 0.4 * (std::f32::consts::TAU * (x as f32 - dx) / period).sin()
            } else {
                background[[y, x]]
            }
        })
    };
    let (reference, block) = (scene(0.0), scene(motion));
    let aligner = ReferenceAligner::new(&reference, &PatchConfig::default()).unwrap();
    let grid = aligner.grid().clone();
    let camera = Array3::from_shape_fn((grid.tiles_y, grid.tiles_x, 2), |(_, _, c)| {
        [0.0, motion][c]
    });
    let inside = |i: usize, j: usize| {
        let (y, x) = (i * grid.tile_stride, j * grid.tile_stride);
        on_grating(y, x) && on_grating(y + grid.tile_size - 1, x + grid.tile_size - 1)
    };
    let mut flow = camera.clone();
    let mut grating_tiles = 0;
    for i in 0..grid.tiles_y {
        for j in 0..grid.tiles_x {
            if inside(i, j) {
                flow[[i, j, 1]] = motion + 2.0 * period;
                grating_tiles += 1;
            }
        }
    }
    assert!(grating_tiles >= 40, "{grating_tiles} grating tiles");
    let out = aligner.follow_second_motion(&block, &flow, &camera, 2.0, 16, 4);
    // Every tile ends on the true motion: none a period away.
    let worst = out
        .lanes(Axis(2))
        .into_iter()
        .map(|v| v[0].hypot(v[1] - motion))
        .fold(0.0f32, f32::max);
    assert!(worst < 0.1, "a tile left the true motion by {worst} px");
}

#[test]
fn second_motion_follows_a_moving_square_over_a_still_background() {
    let (h, w) = (128, 192);
    let reference = texture(h, w, 0.0, 0.0);
    // The block: the same still background, a 48 px square moved by (3, -7) px.
    let moved = texture(h, w, 3.0, -7.0);
    let on_square = |y: usize, x: usize| (40..88).contains(&y) && (72..120).contains(&x);
    let block = Array2::from_shape_fn((h, w), |(y, x)| {
        let (sy, sx) = (y as isize - 3, x as isize + 7);
        if sy >= 0 && on_square(sy as usize, sx as usize) {
            moved[[y, x]]
        } else {
            reference[[y, x]]
        }
    });
    let aligner = ReferenceAligner::new(&reference, &PatchConfig::default()).unwrap();
    let grid = aligner.grid().clone();
    let camera = Array3::<f32>::zeros((grid.tiles_y, grid.tiles_x, 2));
    // Tile flows as a mismatch-prone search might leave them: the square's tiles scattered
    // around its motion, a few of them wrongly on the camera's.
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut flow = camera.clone();
    let inside = |i: usize, j: usize| {
        let (y, x) = (i * 8, j * 8);
        on_square(y, x) && on_square(y + 15, x + 15)
    };
    for i in 0..grid.tiles_y {
        for j in 0..grid.tiles_x {
            if inside(i, j) && rng.gen_bool(0.8) {
                flow[[i, j, 0]] = 3.0 + rng.gen_range(-4.0..4.0);
                flow[[i, j, 1]] = -7.0 + rng.gen_range(-4.0..4.0);
            }
        }
    }
    let out = aligner.follow_second_motion(&block, &flow, &camera, 2.0, 16, 4);
    let (mut on, mut off) = (Vec::new(), Vec::new());
    for i in 0..grid.tiles_y {
        for j in 0..grid.tiles_x {
            if inside(i, j) {
                on.push((out[[i, j, 0]] - 3.0).hypot(out[[i, j, 1]] + 7.0));
            } else if !(4..12).contains(&i) || !(8..16).contains(&j) {
                off.push(out[[i, j, 0]].hypot(out[[i, j, 1]]));
            }
        }
    }
    on.sort_by(f32::total_cmp);
    assert!(on.len() >= 9);
    assert!(on[on.len() * 3 / 4] < 0.1, "square tiles: {on:?}");
    assert!(off.iter().all(|&e| e == 0.0), "background moved");
    // Disabled below the component size.
    assert_eq!(
        aligner.follow_second_motion(&block, &flow, &camera, 2.0, 16, 1000),
        flow
    );
    // With the block's pyramid from the tile search (its levels 0 and 1 reused): the same
    // numbers bit for bit, for the default pyramid, one without pre-smoothing and one whose
    // level 1 is not downsampled.
    for config in [
        PatchConfig::default(),
        PatchConfig {
            presmooth_sigma: 0.0,
            ..PatchConfig::default()
        },
        PatchConfig {
            downsample_factors: vec![1, 1, 4, 4],
            ..PatchConfig::default()
        },
    ] {
        let aligner = ReferenceAligner::new(&reference, &config).unwrap();
        let grid = aligner.grid().clone();
        let (ty, tx) = (grid.tiles_y, grid.tiles_x);
        let camera = Array3::<f32>::zeros((ty, tx, 2));
        let flow = Array3::from_shape_fn((ty, tx, 2), |(i, j, c)| {
            let on = on_square(
                grid.tile_centers_y[i] as usize,
                grid.tile_centers_x[j] as usize,
            );
            if on {
                [3.0, -7.0][c] + rng.gen_range(-2.0..2.0)
            } else {
                0.0
            }
        });
        let (_, _, pyramid) = aligner.align_with_pyramid(&block).unwrap();
        let plain = aligner.follow_second_motion(&block, &flow, &camera, 2.0, 16, 4);
        let search = SecondMotionSearch {
            tolerance_px: 2.0,
            radius_px: 16,
            min_tiles: 4,
        };
        let reused = aligner.follow_second_motion_in(&block, &pyramid, &flow, &camera, search);
        assert_ne!(plain, flow, "{config:?}: no second motion to compare");
        assert!(
            plain
                .iter()
                .zip(&reused)
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "{config:?}"
        );
    }
}
