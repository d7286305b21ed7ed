//! Timing of the joint demosaic-merge at the brief's size (10,000 frames as 100 sub-blocks of
//! 100 frames, 496x254). Ignored by default; run in release:
//! `cargo test --release -p quantacolor --test merge_timing -- --ignored --nocapture`.
use ndarray::{Array2, Array3};
use quantacolor::align::{grey_image, GreyMethod};
use quantacolor::cfa::{generate, Pattern};
use quantacolor::merge::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

#[test]
#[ignore]
fn merge_timing_496x254_100_sub_blocks() {
    let (h, w, n, frames) = (254, 496, 100, 100u32);
    let cfa = generate(&Pattern::Rgbw75Regular, h, w, 0).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(41);
    let subs: Vec<SubBlock> = (0..n)
        .map(|k| {
            let (dy, dx) = (rng.gen_range(-4.0..4.0f32), rng.gen_range(-4.0..4.0f32));
            SubBlock {
                counts: Array2::from_shape_fn((h, w), |_| rng.gen_range(0..=frames / 2)),
                frames,
                flow: Array3::from_shape_fn((h, w, 2), |(y, x, i)| {
                    let ripple = 0.3 * ((y + x) as f32 * 0.05).sin();
                    if i == 0 {
                        dy + ripple
                    } else {
                        dx - ripple
                    }
                })
                .into(),
                robustness: SubBlockRobustness::Block(k / 10),
            }
        })
        .collect();
    let grey: Vec<Array2<f32>> = (0..10)
        .map(|k| {
            grey_image(
                &subs[k * 10].counts,
                frames as usize,
                &cfa,
                GreyMethod::InterpolateW,
            )
            .unwrap()
        })
        .collect();
    let flows: Vec<Array3<f32>> = (0..10)
        .map(|k| subs[k * 10].flow.dense().unwrap().clone())
        .collect();
    let config = MergeConfig::default();
    let t0 = Instant::now();
    let reference = reference_image(&grey, &flows, 5, frames as f32, &config.wiener).unwrap();
    let t1 = Instant::now();
    let kernels = kernel_field(&reference, &config.kernels).unwrap();
    let maps: Vec<_> = grey
        .iter()
        .zip(&flows)
        .map(|(g, f)| robustness(&reference, g, f, frames as f32, &config.robustness).unwrap())
        .collect();
    let t2 = Instant::now();
    for scale in [1, 2] {
        let acc = AccumulateConfig {
            scale,
            ..config.accumulate.clone()
        };
        let t = Instant::now();
        let planes = demosaic_merge(&subs, &maps, &cfa, &kernels, 0.001, [1.0; 3], &acc).unwrap();
        println!(
            "demosaic-merge scale {scale}: {:.2} s ({} threads); output {:?}",
            t.elapsed().as_secs_f64(),
            rayon::current_num_threads(),
            planes.flux.dim()
        );
    }
    println!(
        "reference (10 blocks): {:.2} s; kernels + robustness: {:.2} s",
        (t1 - t0).as_secs_f64(),
        (t2 - t1).as_secs_f64()
    );
}
