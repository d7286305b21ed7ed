//! The fit's template: the other blocks' grey images warped to the reference, smoothed, with
//! their gradients interleaved per pixel; its bilinear samples.
#![forbid(unsafe_code)]

use super::frame_motion::FrameMotion;
use crate::cpu;
use crate::error::Result;
use crate::filters::gaussian_blur;
use ndarray::Array2;
use rayon::prelude::*;

/// Whether a template's pixels can be indexed in the i32 lanes of `run_sums_group_avx2` (x86.rs).
pub(super) fn group_lanes_fit(template: &TemplateLevel) -> bool {
    let (h, w) = (template.height, template.width);
    h >= 2 && w >= 2 && h.saturating_mul(w) < (1 << 28)
}

/// A smoothed reference and its gradients, interleaved per pixel for the fit's inner loop.
pub(in crate::align) struct TemplateLevel {
    pub(super) height: usize,
    pub(super) width: usize,
    /// (value, ∂/∂y, ∂/∂x, 0) of every pixel, row-major (padded to four lanes so that one
    /// pixel is one vector in the fit's bilinear interpolation).
    pub(super) samples: Vec<[f32; 4]>,
}

impl TemplateLevel {
    /// (height, width) in pixels.
    pub(in crate::align) fn dims(&self) -> (usize, usize) {
        (self.height, self.width)
    }

    /// The samples as one float slice: pixel i's (value, ∂/∂y, ∂/∂x, 0) at 4i..4i + 4.
    pub(in crate::align) fn floats(&self) -> &[f32] {
        self.samples.as_flattened()
    }

    /// The number of floats in [`Self::floats`].
    pub(in crate::align) fn float_len(&self) -> usize {
        4 * self.samples.len()
    }
}

/// Bilinear value and gradient of `level` at (y, x); `None` outside the interior.
#[inline(always)]
pub(in crate::align) fn sample_template(level: &TemplateLevel, y: f64, x: f64) -> Option<[f64; 3]> {
    let (h, w) = (level.height, level.width);
    if !(y >= 0.0 && x >= 0.0 && y <= (h - 1) as f64 && x <= (w - 1) as f64) {
        return None;
    }
    let (y0, x0) = ((y as usize).min(h - 2), (x as usize).min(w - 2));
    let (fy, fx) = ((y - y0 as f64) as f32, (x - x0 as f64) as f32);
    let i = y0 * w + x0;
    let (top, bottom) = (&level.samples[i..i + 2], &level.samples[i + w..i + w + 2]);
    let (a, b, c, d) = (top[0], top[1], bottom[0], bottom[1]);
    let v = bilinear4(a, b, c, d, fx, fy);
    Some([v[0] as f64, v[1] as f64, v[2] as f64])
}

/// Bilinear interpolation of the four lanes of the pixels `a` (top left), `b` (top right), `c`
/// (bottom left) and `d` (bottom right) at fractions `fx`, `fy`.
#[inline(always)]
pub(super) fn bilinear4(
    a: [f32; 4],
    b: [f32; 4],
    c: [f32; 4],
    d: [f32; 4],
    fx: f32,
    fy: f32,
) -> [f32; 4] {
    let (gx, gy) = (1.0 - fx, 1.0 - fy);
    std::array::from_fn(|k| {
        let top = a[k] * gx + b[k] * fx;
        let bottom = c[k] * gx + d[k] * fx;
        top * gy + bottom * fy
    })
}

/// The template of `reference` at one level: smoothed with σ = `sigma` px, with its gradients.
pub(in crate::align) fn template_level(reference: &Array2<f32>, sigma: f32) -> TemplateLevel {
    let value = gaussian_blur(reference, sigma);
    let (h, w) = value.dim();
    let value = value.as_standard_layout();
    let value = value.as_slice().expect("standard layout");
    // Central differences over 2 px inside, one-sided over 1 px at the edges: the difference
    // divided by the span, made as a product with 1 / span (1 or 1/2, so the same bits as the
    // division, without one per value).
    let inverse_span = |a: usize, b: usize| if b - a == 2 { 0.5f32 } else { 1.0 };
    // Written once, row by row (not zeroed first: a finest-level template is 2 MB, and every
    // block of every pass makes one).
    let mut samples = Vec::with_capacity(h * w);
    for y in 0..h {
        let (ya, yb) = (y.saturating_sub(1), (y + 1).min(h - 1));
        let scale_y = inverse_span(ya, yb);
        let row = &value[y * w..(y + 1) * w];
        let (above, below) = (&value[ya * w..(ya + 1) * w], &value[yb * w..(yb + 1) * w]);
        samples.extend((0..w).map(|x| {
            let (xa, xb) = (x.saturating_sub(1), (x + 1).min(w - 1));
            [
                row[x],
                (below[x] - above[x]) * scale_y,
                (row[xb] - row[xa]) * inverse_span(xa, xb),
                0.0,
            ]
        }));
    }
    TemplateLevel {
        height: h,
        width: w,
        samples,
    }
}

/// Most blocks whose templates [`refine_pass`](super::pass::refine_pass) makes at a time (their
/// sub-blocks' fits then run in one parallel loop: the fewer groups, the less time a thread waits
/// for the group's last fit). The groups are of equal size ([`cpu::balanced_chunk_len`]): 25 blocks
/// in groups of 7, 7, 7 and 4 rather than 8, 8, 8 and 1, whose one template and few fits left a
/// core idle.
pub(super) const TEMPLATE_GROUP: usize = 8;

/// Most bytes of warped block images [`refine_pass`](super::pass::refine_pass) keeps from the mean
/// template for the blocks' own templates (32 MB: 66 blocks at 496x254); beyond, it warps them
/// again.
const WARP_CACHE_BYTES: usize = 32 << 20;

/// The sum of every grey block warped to the reference grid by `motion`, and the warped
/// images themselves when they fit in [`WARP_CACHE_BYTES`] (`None` each otherwise: they are
/// warped again when needed, the same numbers).
pub(super) struct WarpedBlocks {
    pub(super) total: Array2<f32>,
    pub(super) kept: Vec<Option<Array2<f32>>>,
}

/// [`WarpedBlocks`] of `grey_blocks`: each block's grey image on the reference grid is made
/// when needed rather than kept (the blocks' dense flows would grow with the number of frames);
/// warped in parallel a group at a time, summed in block order (the same sum as one at a time).
pub(super) fn warp_blocks_to_reference(
    grey_blocks: &[Array2<f32>],
    motion: &FrameMotion,
) -> Result<WarpedBlocks> {
    let n_blocks = grey_blocks.len();
    let mut total = Array2::<f32>::zeros(grey_blocks[0].dim());
    let keep = n_blocks * total.len() * std::mem::size_of::<f32>() <= WARP_CACHE_BYTES;
    let mut kept: Vec<Option<Array2<f32>>> = vec![None; n_blocks];
    let block_ids: Vec<usize> = (0..n_blocks).collect();
    for group in block_ids.chunks(cpu::balanced_chunk_len(n_blocks, TEMPLATE_GROUP)) {
        let images: Vec<Array2<f32>> = group
            .par_iter()
            .map(|&b| motion.warp_block(b, &grey_blocks[b]))
            .collect::<Result<_>>()?;
        for (&b, image) in group.iter().zip(images) {
            total += &image;
            if keep {
                kept[b] = Some(image);
            }
        }
    }
    Ok(WarpedBlocks { total, kept })
}

/// The finest template level of each block of `group`: the mean of the other blocks' warped
/// images, `(total − own) / (n − 1)` (the block's own warped image from `own_images` or warped
/// again), smoothed with `sigma_px`; `None` each when there is one block only.
pub(super) fn leave_one_out_templates(
    group: &[usize],
    own_images: Vec<Option<Array2<f32>>>,
    total: &Array2<f32>,
    grey_blocks: &[Array2<f32>],
    motion: &FrameMotion,
    sigma_px: f32,
) -> Result<Vec<Option<TemplateLevel>>> {
    let n_blocks = grey_blocks.len();
    group
        .par_iter()
        .zip(own_images)
        .map(|(&b, own)| -> Result<Option<TemplateLevel>> {
            if n_blocks == 1 {
                return Ok(None);
            }
            let own = match own {
                Some(image) => image,
                None => motion.warp_block(b, &grey_blocks[b])?,
            };
            // (total − own) / (n − 1) in one pass, element by element.
            let others = ndarray::Zip::from(total)
                .and(&own)
                .map_collect(|&t, &o| (t - o) / (n_blocks - 1) as f32);
            Ok(Some(template_level(&others, sigma_px)))
        })
        .collect()
}
