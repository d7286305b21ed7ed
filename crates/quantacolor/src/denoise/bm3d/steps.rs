//! The two steps of BM3D (Dabov et al., TIP 2007, §III): Step 1, the basic estimate by hard
//! thresholding, and Step 2, the final estimate by Wiener filtering, each over the grid of
//! reference blocks (grouping, filtering, aggregation), rows in parallel.

#![forbid(unsafe_code)]

use super::aggregation::{aggregate_group, sum_strips, Strip};
use super::config::{Bm3dConfig, NoiseRegime};
use super::filtering::filter_channel;
use super::grouping::{find_group, low_planes_in};
use super::transforms::{block_sources, BlockCoeffs, BlockSource};
use super::x86::process_row;
use super::{recycled, Bm3dBuffers, Geometry, Scratch, SharedParams, StepParams, Transforms};
use crate::cpu;
use rayon::prelude::*;

/// Step 1 (TIP 2007 §III-A): matching on noisy channel 0 (hard-thresholded in 2D when the
/// noise is high), hard thresholding of every group's 3D spectrum; the basic estimate.
pub(super) fn hard_threshold_step(
    shared: &SharedParams,
    regime: &NoiseRegime,
    sigmas: &[f32],
    config: &Bm3dConfig,
    buffers: &mut Bm3dBuffers,
) -> Vec<Vec<f32>> {
    let noisy_coeffs = BlockCoeffs::compute_in(
        std::mem::take(&mut buffers.coeffs),
        &shared.planes[0],
        shared.geo,
        shared.tr,
    );
    let noisy = block_sources(&noisy_coeffs, shared.planes);
    let thresholded;
    let matching = if regime.high_noise && config.lambda_2d > 0.0 {
        thresholded = noisy_coeffs.hard_thresholded(config.lambda_2d * sigmas[0]);
        &thresholded
    } else {
        &noisy_coeffs
    };
    let low = low_planes_in(std::mem::take(&mut buffers.low), matching, shared.geo);
    let step = StepParams {
        matching,
        low: low.as_ref(),
        tau_sum: regime.tau_sum(
            config.tau_match_ht,
            config.tau_match_ht_high_noise,
            config.block_size,
        ),
        max_group: config.max_group_ht,
        noisy: &noisy,
        basic: None,
        sigmas,
        block_variance: shared.block_variance,
        lambda_3d: if regime.high_noise {
            config.lambda_3d_high_noise
        } else {
            config.lambda_3d
        },
        profiles: shared.profiles,
    };
    let out = run_step(&step, shared.geo, shared.tr, shared.planes, buffers);
    if let Some(low) = low {
        buffers.low = low.planes;
    }
    buffers.coeffs = noisy_coeffs.data;
    out
}

/// Step 2 (TIP 2007 §III-B): matching on the basic estimate's channel 0, empirical Wiener
/// shrinkage of the noisy groups with the basic estimate as the oracle; the final estimate.
/// The basic estimate's coefficients take the buffer of Step 1's noisy ones, so the noisy
/// blocks of every channel are transformed from the planes (the same bits).
pub(super) fn wiener_step(
    shared: &SharedParams,
    regime: &NoiseRegime,
    sigmas: &[f32],
    config: &Bm3dConfig,
    basic: &[Vec<f32>],
    buffers: &mut Bm3dBuffers,
) -> Vec<Vec<f32>> {
    let basic_coeffs = BlockCoeffs::compute_in(
        std::mem::take(&mut buffers.coeffs),
        &basic[0],
        shared.geo,
        shared.tr,
    );
    let basic_sources = block_sources(&basic_coeffs, basic);
    let noisy: Vec<BlockSource> = shared
        .planes
        .iter()
        .map(|p| BlockSource::Plane(p))
        .collect();
    let low = low_planes_in(std::mem::take(&mut buffers.low), &basic_coeffs, shared.geo);
    let step = StepParams {
        matching: &basic_coeffs,
        low: low.as_ref(),
        tau_sum: regime.tau_sum(
            config.tau_match_wiener,
            config.tau_match_wiener_high_noise,
            config.block_size,
        ),
        max_group: config.max_group_wiener,
        noisy: &noisy,
        basic: Some(&basic_sources),
        sigmas,
        block_variance: shared.block_variance,
        lambda_3d: config.lambda_3d,
        profiles: shared.profiles,
    };
    let out = run_step(&step, shared.geo, shared.tr, basic, buffers);
    if let Some(low) = low {
        buffers.low = low.planes;
    }
    buffers.coeffs = basic_coeffs.data;
    out
}

/// One BM3D step over the whole image; returns one plane per channel. Channels with σ = 0 are
/// copied from `planes`.
fn run_step(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    planes: &[Vec<f32>],
    work: &mut Bm3dBuffers,
) -> Vec<Vec<f32>> {
    let (h, w, n) = (geo.h, geo.w, geo.n);
    let n2 = n * n;
    let channels = planes.len();
    let mut num = recycled(std::mem::take(&mut work.num), channels * h * w, true);
    let mut den = recycled(std::mem::take(&mut work.den), channels * h * w, true);
    // Reference rows in batches of equal size, so that at most `MAX_ROWS_PER_BATCH` strips live
    // at once; their buffers are made once (or kept from the last step, `work`) and cleared for
    // every batch (fresh ones cost page faults). Each batch ends when its slowest row does, so
    // batches are few and alike (one short last batch left a thread idle).
    const MAX_ROWS_PER_BATCH: usize = 32;
    let rows_per_batch = cpu::balanced_chunk_len(geo.ref_ys.len(), MAX_ROWS_PER_BATCH);
    let strip_rows = (2 * geo.half_window + n).min(h);
    let mut buffers = std::mem::take(&mut work.strips);
    buffers.resize_with(rows_per_batch, Default::default);
    for (num, den) in &mut buffers {
        let len = channels * strip_rows * w;
        *num = recycled(std::mem::take(num), len, false);
        *den = recycled(std::mem::take(den), len, false);
    }
    // Group members lie within the search window's rows.
    let strip_of = |yr: usize| {
        let y0 = yr.saturating_sub(geo.half_window);
        (y0, (yr + geo.half_window + n).min(h) - y0)
    };
    for batch in geo.ref_ys.chunks(rows_per_batch) {
        batch.par_iter().zip(buffers.par_iter_mut()).for_each_init(
            || Scratch::new(n2, p.max_group),
            |scratch, (&yr, (num, den))| {
                let (y0, rows) = strip_of(yr);
                let len = channels * rows * w;
                num[..len].fill(0.0);
                den[..len].fill(0.0);
                let mut strip = Strip {
                    y0,
                    rows,
                    num: &mut num[..len],
                    den: &mut den[..len],
                };
                process_row(p, geo, tr, yr, scratch, &mut strip);
            },
        );
        // Sum the strips in reference-row order: the same float additions for any thread count.
        let strips: Vec<(usize, usize)> = batch.iter().map(|&yr| strip_of(yr)).collect();
        sum_strips(&mut num, &mut den, &strips, &buffers, (h, w));
    }
    let out = (0..channels)
        .map(|c| {
            if p.sigmas[c] == 0.0 {
                return planes[c].clone();
            }
            let plane = c * h * w..(c + 1) * h * w;
            num[plane.clone()]
                .iter()
                .zip(&den[plane])
                .map(|(&a, &b)| a / b)
                .collect()
        })
        .collect();
    (work.num, work.den, work.strips) = (num, den, buffers);
    out
}

/// The reference blocks of row `yr`; `AVX2` selects the explicit AVX2 kernels of [`super::x86`]
/// (matching, hard thresholding, Wiener shrinkage), which give the same bits as the portable
/// ones.
#[inline(always)]
pub(super) fn process_row_generic<const AVX2: bool>(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    yr: usize,
    s: &mut Scratch,
    strip: &mut Strip<'_>,
) {
    for &xr in &geo.ref_xs {
        process_reference::<AVX2>(p, geo, tr, yr, xr, s, strip);
    }
}

/// Groups the blocks similar to reference `(yr, xr)`, filters the group in every channel with
/// σ > 0, and aggregates the block estimates into `strip`.
#[inline(always)]
fn process_reference<const AVX2: bool>(
    p: &StepParams,
    geo: &Geometry,
    tr: &Transforms,
    yr: usize,
    xr: usize,
    s: &mut Scratch,
    strip: &mut Strip<'_>,
) {
    find_group::<AVX2>(p, geo, yr, xr, s);
    let m = s.group.len();
    let channels = p.noisy.len();

    for c in 0..channels {
        let mut sigma = p.sigmas[c];
        if sigma == 0.0 {
            continue;
        }
        if let Some(variance) = p.block_variance {
            let mean: f32 = s.group.iter().map(|&pos| variance[c][pos]).sum::<f32>() / m as f32;
            sigma *= mean.sqrt();
        }
        let weight = filter_channel::<AVX2>(p, geo, tr, c, sigma, s);
        // Aggregation with the Kaiser window (§III-A.3 / §III-B.3; Table I, β = 2).
        aggregate_group(geo, tr, c, weight, s, strip);
    }
}
