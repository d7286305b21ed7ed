//! Criterion benchmarks of the burst pipeline's hot kernels on a simulated capture of the
//! built-in chart (496x254, colour-SPAD CFA, hand-held motion, 0.1 photons/pixel/frame): block
//! alignment, the sub-block motion refinement, the merge guide (reference, kernels, robustness),
//! the phase-bin accumulator of the joint demosaic-merge, BM3D, the branch-free exponential
//! of the merge's kernel weights against libm, and the photon trajectory of a fast-shake
//! capture.
//!
//! `cargo bench -p quantacolor --bench kernels` (CI only builds them, with clippy). The whole
//! pipeline against the naive sum: `quantacolor bench speed`.

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};
use ndarray::{Array2, Array3};
use quantacolor::align::{
    align, fit_photon_trajectory, plan_sub_blocks, refine_camera_motion, Alignment, FrameMotion,
};
use quantacolor::burst::BurstConfig;
use quantacolor::capture::Capture;
use quantacolor::cfa::colorspad_cfa;
use quantacolor::denoise::bm3d::{bm3d_grey, Bm3dConfig};
use quantacolor::fastmath;
use quantacolor::merge::{
    merge_guide, robustness, GreyNoise, MergeAccumulator, MergeGuide, SubBlock, SubBlockRobustness,
};
use quantacolor::progress::Silent;
use quantacolor::simulate::{simulate_with_cfa, FluxSpec, MotionConfig, Scene, SimulationConfig};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hint::black_box;

/// A 1024-frame capture: long enough for several blocks and sub-blocks, short to simulate.
fn capture() -> Capture {
    capture_with(1024, "handheld")
}

/// A capture of the chart of `frames` frames under `motion`.
fn capture_with(frames: usize, motion: &str) -> Capture {
    let config = SimulationConfig {
        frames,
        flux: FluxSpec::Mean { flux: 0.1 },
        motion: motion.parse::<MotionConfig>().expect("motion"),
        ..SimulationConfig::default()
    };
    let scene = Scene::from_spec("builtin:chart").expect("chart");
    simulate_with_cfa(&config, &scene, &colorspad_cfa(), &Silent)
        .expect("simulation")
        .to_capture()
        .expect("capture")
}

/// The block alignment of `capture` with `config`'s settings.
fn block_alignment(capture: &Capture, config: &BurstConfig) -> Alignment {
    align(
        &capture.frames,
        &capture.cfa,
        capture.hot_pixels.as_ref(),
        capture.reference_frame(),
        &config.align,
        &Silent,
    )
    .expect("alignment")
}

/// The frame motion that `alignment` gives, with `config`'s settings.
fn block_motion(alignment: &Alignment, config: &BurstConfig) -> FrameMotion {
    FrameMotion::from_alignment(
        alignment,
        config.align.affine_tolerance_px,
        config.refine.min_local_tiles,
        config.refine.local_consistency,
    )
}

fn pipeline_kernels(c: &mut Criterion) {
    let capture = capture();
    let config = BurstConfig::default();
    let alignment = block_alignment(&capture, &config);
    c.bench_function("align (1024 frames)", |b| {
        b.iter(|| block_alignment(&capture, &config))
    });
    let mut motion = block_motion(&alignment, &config);

    let grey_blocks: &[Array2<f32>] = &alignment.grey;
    let reference_block = alignment.plan.reference_block;
    let detections = alignment.grey[reference_block].mean().unwrap_or(0.0) as f64;
    plan_sub_blocks(&mut motion, detections, &config.refine);
    c.bench_function("motion refinement (sub-block fits)", |b| {
        b.iter_batched(
            || motion.clone(),
            |mut m| {
                refine_camera_motion(
                    &capture,
                    alignment.grey_method,
                    grey_blocks,
                    &mut m,
                    &config.refine,
                    &Silent,
                )
                .expect("refinement");
                m
            },
            BatchSize::LargeInput,
        )
    });

    let flows: Vec<Array3<f32>> = (0..alignment.plan.len())
        .map(|b| motion.block_flow(b))
        .collect();
    let noise = GreyNoise {
        trials: alignment.plan.block_size as f32,
        model: capture.meta.pixel_model(),
    };
    c.bench_function("merge guide (reference, kernels, robustness)", |b| {
        b.iter(|| {
            merge_guide(grey_blocks, &flows, reference_block, noise, &config.merge).expect("guide")
        })
    });
    let guide =
        merge_guide(grey_blocks, &flows, reference_block, noise, &config.merge).expect("guide");
    let other = (reference_block + 1) % grey_blocks.len();
    c.bench_function("robustness (one block)", |b| {
        b.iter(|| {
            robustness(
                &guide.reference,
                &grey_blocks[other],
                &flows[other],
                noise,
                &config.merge.robustness,
            )
            .expect("robustness")
        })
    });

    merge_accumulate(c, &capture, &motion, &guide, &config);
}

/// The phase-bin accumulator of the joint demosaic-merge: splatting eight sub-blocks of
/// `motion` with `guide`'s kernels and robustness, and the kernel regression that finishes it.
fn merge_accumulate(
    c: &mut Criterion,
    capture: &Capture,
    motion: &FrameMotion,
    guide: &MergeGuide,
    config: &BurstConfig,
) {
    let hot = capture.hot_pixels.as_ref();
    let sub_blocks: Vec<SubBlock> = (0..motion.sub_blocks.len().min(8))
        .map(|k| SubBlock {
            counts: capture.frames.sum_range(motion.sub_blocks[k].clone()),
            frames: motion.sub_blocks[k].len() as u32,
            flow: motion.sub_block_motion(k),
            robustness: SubBlockRobustness::Block(motion.block_of[k]),
        })
        .collect();
    let new_accumulator = || {
        let mut acc = MergeAccumulator::new(
            &capture.cfa,
            &guide.kernels,
            &config.merge.accumulate,
            capture.meta.pixel_model(),
        )
        .expect("accumulator");
        if let Some(hot) = hot {
            acc.exclude_sites(hot).expect("mask");
        }
        acc
    };
    c.bench_function("merge accumulate (splat 8 sub-blocks)", |b| {
        b.iter_batched(
            new_accumulator,
            |mut acc| {
                acc.add(&sub_blocks, &guide.robustness).expect("add");
                acc
            },
            BatchSize::LargeInput,
        )
    });
    c.bench_function("merge finish (kernel regression)", |b| {
        b.iter_batched(
            || {
                let mut acc = new_accumulator();
                acc.add(&sub_blocks, &guide.robustness).expect("add");
                acc
            },
            |acc| acc.finish(capture.meta.w_weights),
            BatchSize::LargeInput,
        )
    });
}

fn bm3d(c: &mut Criterion) {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let noisy = Array2::from_shape_fn((128, 128), |(y, x)| {
        let clean = if (y / 16 + x / 16) % 2 == 0 {
            60.0
        } else {
            190.0
        };
        clean + rng.gen_range(-40.0f32..40.0)
    });
    let config = Bm3dConfig::default();
    c.bench_function("bm3d grey 128x128", |b| {
        b.iter(|| bm3d_grey(black_box(noisy.view()), 23.0, &config).expect("bm3d"))
    });
}

/// The kernel weights' exponential over the range the merge uses (e^(−q/2), q below the
/// cutoff 9), vectorisable, against libm's.
fn exp(c: &mut Criterion) {
    let xs: Vec<f32> = (0..4096).map(|i| -4.5 * i as f32 / 4096.0).collect();
    let mut out = vec![0.0f32; xs.len()];
    c.bench_function("exp 4096 (fastmath)", |b| {
        b.iter(|| {
            for (o, &x) in out.iter_mut().zip(black_box(&xs)) {
                *o = fastmath::exp(x);
            }
            black_box(&out);
        })
    });
    c.bench_function("exp 4096 (libm)", |b| {
        b.iter(|| {
            for (o, &x) in out.iter_mut().zip(black_box(&xs)) {
                *o = x.exp();
            }
            black_box(&out);
        })
    });
}

/// The photon trajectory (per-frame camera fitted to every photon) of a 256-frame fast-shake
/// capture, from the block alignment's motion: the slow stage of fast captures.
fn trajectory(c: &mut Criterion) {
    let capture = capture_with(256, "fast-handheld");
    let config = BurstConfig::default();
    let alignment = block_alignment(&capture, &config);
    let motion = block_motion(&alignment, &config);
    c.bench_function("photon trajectory (256 fast-shake frames)", |b| {
        b.iter_batched(
            || motion.clone(),
            |mut m| {
                fit_photon_trajectory(
                    &capture,
                    alignment.grey_method,
                    &mut m,
                    &config.trajectory,
                    config.refine.max_sub_block_motion_px,
                    &Silent,
                )
                .expect("trajectory");
                m
            },
            BatchSize::LargeInput,
        )
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = pipeline_kernels, bm3d, exp, trajectory
}
criterion_main!(benches);
