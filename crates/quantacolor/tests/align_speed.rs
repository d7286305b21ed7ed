//! Timing of the whole alignment stage at the real sensor's size (496 x 254, 10,000 frames),
//! ignored by default: `cargo test --release -p quantacolor --test align_speed -- --ignored
//! --nocapture`. Prints times; asserts only that the motion is recovered.

use ndarray::{Array2, Array3, Axis};
use quantacolor::align::{align, AlignConfig};
use quantacolor::capture::BinaryFrames;
use quantacolor::cfa::{generate, Channel, Pattern};
use quantacolor::progress::Silent;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use std::time::Instant;

#[test]
#[ignore]
fn ten_thousand_frames_of_496x254() {
    let (t, h, w) = (10_000usize, 254usize, 496usize);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
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
    // Steady motion of (0.3, −0.5) px per 1000 frames; frames rendered in 100-frame chunks.
    let velocity = (0.3e-3f32, -0.5e-3f32);
    let hot = Array2::from_shape_fn((h, w), |_| rng.gen_bool(0.02));
    let rb = w.div_ceil(8);
    let t0 = Instant::now();
    let mut packed = Array3::<u8>::zeros((t, h, rb));
    packed
        .axis_chunks_iter_mut(Axis(0), 100)
        .into_par_iter()
        .enumerate()
        .for_each(|(c, mut chunk)| {
            let tc = (c * 100 + 50) as f32;
            let thresh = Array2::from_shape_fn((h, w), |(y, x)| {
                let (sy, sx) = (y as f32 - velocity.0 * tc, x as f32 - velocity.1 * tc);
                let s: f32 = waves
                    .iter()
                    .map(|&(ky, kx, ph)| (ky * sy + kx * sx + ph).sin())
                    .sum();
                let flux = 0.1 * (1.0 + 0.1 * s).max(0.02);
                let gain = if cfa.channel(y, x) == Channel::W {
                    1.0
                } else {
                    1.0 / 3.0
                };
                let p = if hot[[y, x]] {
                    0.3
                } else {
                    1.0 - (-flux * gain).exp()
                };
                (p as f64 * 4294967296.0) as u64
            });
            let mut state = 0x9E37_79B9_7F4A_7C15u64 ^ (c as u64 + 1);
            for mut frame in chunk.outer_iter_mut() {
                for ((y, xb), byte) in frame.indexed_iter_mut() {
                    let mut v = 0u8;
                    for i in 0..8 {
                        let x = xb * 8 + i;
                        state ^= state << 13;
                        state ^= state >> 7;
                        state ^= state << 17;
                        if x < w && (state >> 32) < thresh[[y, x]] {
                            v |= 0x80 >> i;
                        }
                    }
                    *byte = v;
                }
            }
        });
    let frames = BinaryFrames::from_packed(packed, w).unwrap();
    eprintln!("rendering: {:.2} s", t0.elapsed().as_secs_f64());
    let t1 = Instant::now();
    let sum = frames.sum_range(0..t);
    eprintln!(
        "one full sum_range: {:.3} s (mean count {:.0})",
        t1.elapsed().as_secs_f64(),
        sum.iter().map(|&v| v as f64).sum::<f64>() / sum.len() as f64
    );
    for with_hot in [false, true] {
        let start = Instant::now();
        let al = align(
            &frames,
            &cfa,
            with_hot.then_some(&hot),
            t / 2,
            &AlignConfig::default(),
            &Silent,
        )
        .unwrap();
        let secs = start.elapsed().as_secs_f64();
        // Truth at block b: velocity · (centre_b − centre_ref).
        let centres = al.plan.center_frames();
        let cref = centres[al.plan.reference_block];
        let mut errs = Vec::new();
        for (b, &c) in centres.iter().enumerate() {
            let (ty, tx) = (
                velocity.0 * (c - cref) as f32,
                velocity.1 * (c - cref) as f32,
            );
            for v in al.flow.index_axis(Axis(0), b).rows() {
                errs.push((v[0] - ty).hypot(v[1] - tx));
            }
        }
        errs.sort_by(f32::total_cmp);
        let med = errs[errs.len() / 2];
        eprintln!(
            "align (hot-pixel correction {with_hot}): {secs:.2} s, B = {}, {} blocks, {}x{} tiles, median EPE {med:.3} px",
            al.plan.block_size,
            al.plan.len(),
            al.grid.tiles_y,
            al.grid.tiles_x
        );
        if with_hot {
            assert!(med < 0.2);
        }
    }
}
