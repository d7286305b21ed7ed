//! Patch alignment gives the same numbers bit for bit on every instruction set: an aligner on
//! `Isa::generic()` (the portable paths) against one on `Isa::current()` (the AVX2 kernels where
//! the CPU has them), over the whole coarse-to-fine search, Lucas–Kanade and the second motion.

use ndarray::{Array2, Array3};
use quantacolor::align::{PatchConfig, ReferenceAligner, SecondMotionSearch};
use quantacolor::cpu::Isa;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A smooth random texture (a sum of plane waves) shifted by `(dy, dx)` px, with uniform noise
/// of amplitude `noise` drawn from `seed`.
fn scene(h: usize, w: usize, (dy, dx): (f32, f32), noise: f32, seed: u64) -> Array2<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    let waves: Vec<(f32, f32, f32)> = (0..40)
        .map(|_| {
            let k = std::f32::consts::TAU / rng.gen_range(6.0..40.0f32);
            let th = rng.gen_range(0.0..std::f32::consts::TAU);
            let phase = rng.gen_range(0.0..std::f32::consts::TAU);
            (k * th.sin(), k * th.cos(), phase)
        })
        .collect();
    let mut noise_rng = ChaCha8Rng::seed_from_u64(seed);
    Array2::from_shape_fn((h, w), |(y, x)| {
        let (y, x) = (y as f32 - dy, x as f32 - dx);
        let wave: f32 = waves
            .iter()
            .map(|&(ky, kx, ph)| (ky * y + kx * x + ph).sin())
            .sum();
        1.0 + 0.1 * wave + noise * noise_rng.gen_range(-1.0..1.0f32)
    })
}

fn bits(a: &Array3<f32>) -> Vec<u32> {
    a.iter().map(|v| v.to_bits()).collect()
}

#[test]
fn patch_alignment_is_bit_identical_on_generic_and_current_isa() {
    let (h, w) = (120, 200);
    let reference = scene(h, w, (0.0, 0.0), 0.05, 1);
    let configs = [
        PatchConfig::default(),
        PatchConfig {
            presmooth_sigma: 0.0,
            ..PatchConfig::default()
        },
    ];
    for config in configs {
        let generic = ReferenceAligner::with_isa(&reference, &config, Isa::generic()).unwrap();
        let current = ReferenceAligner::with_isa(&reference, &config, Isa::current()).unwrap();
        assert_eq!(current.isa(), Isa::current());
        for (k, shift) in [(2.3f32, -5.6f32), (-11.4, 17.2), (0.4, 0.7)]
            .into_iter()
            .enumerate()
        {
            let block = scene(h, w, shift, 0.05, 10 + k as u64);
            let (flow_g, valid_g, pyramid_g) = generic.align_with_pyramid(&block).unwrap();
            let (flow_c, valid_c, pyramid_c) = current.align_with_pyramid(&block).unwrap();
            assert_eq!(bits(&flow_g), bits(&flow_c), "{shift:?}");
            assert_eq!(valid_g, valid_c, "{shift:?}");
            assert!(valid_c.iter().any(|&v| v), "no tile refined to sub-pixel");
            // The flow found the shift on most tiles (so the kernels were exercised on a real
            // search, not on a degenerate one).
            let (ty, tx, _) = flow_c.dim();
            let near = (0..ty * tx)
                .filter(|&k| {
                    let (i, j) = (k / tx, k % tx);
                    (flow_c[[i, j, 0]] - shift.0).abs() < 0.5
                        && (flow_c[[i, j, 1]] - shift.1).abs() < 0.5
                })
                .count();
            assert!(2 * near > ty * tx, "{shift:?}: {near} of {} tiles", ty * tx);
            // The second motion: a camera flow off by 6 px on a square of tiles, so that sets
            // are rejected and searched.
            let camera = Array3::from_shape_fn((ty, tx, 2), |(_, _, c)| [shift.0, shift.1][c]);
            let mut flow = camera.clone();
            for i in ty / 4..ty / 2 {
                for j in tx / 4..tx / 2 {
                    flow[[i, j, 1]] += 6.0;
                }
            }
            let search = SecondMotionSearch {
                tolerance_px: 2.0,
                radius_px: 16,
                min_tiles: 4,
            };
            let out_g = generic.follow_second_motion_in(&block, &pyramid_g, &flow, &camera, search);
            let out_c = current.follow_second_motion_in(&block, &pyramid_c, &flow, &camera, search);
            assert_eq!(bits(&out_g), bits(&out_c), "{shift:?}");
            let plain = current.follow_second_motion(&block, &flow, &camera, 2.0, 16, 4);
            assert_eq!(bits(&plain), bits(&out_c), "{shift:?}");
        }
    }
}
