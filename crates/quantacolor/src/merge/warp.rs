//! Bilinear warping of block images onto the reference grid (supplement §1.2).

use crate::error::{Error, Result};
use crate::filters::bilinear_taps;
use ndarray::{Array2, Array3};
use rayon::prelude::*;

/// True for a positive number (false for NaN): parameter validation.
pub(crate) fn positive(v: f32) -> bool {
    v > 0.0
}

/// Checks that `flow` is a dense (H, W, 2) field for an (H, W) image; `what` names it.
pub(crate) fn check_flow(flow: &Array3<f32>, h: usize, w: usize, what: &str) -> Result<()> {
    if flow.dim() != (h, w, 2) {
        return Err(Error::invalid(format!(
            "{what}: flow has shape {:?}, expected ({h}, {w}, 2)",
            flow.dim()
        )));
    }
    let non_finite = match flow.as_slice_memory_order() {
        // A plain slice scan vectorises.
        Some(values) => values.iter().any(|v| !v.is_finite()),
        None => flow.iter().any(|v| !v.is_finite()),
    };
    if non_finite {
        return Err(Error::invalid(format!(
            "{what}: flow holds non-finite values"
        )));
    }
    Ok(())
}

/// Warps `block` onto the reference grid: output(p) = block(p + flow(p)) by bilinear sampling
/// (flows are (dy, dx); a scene point at p in the reference is at p + flow(p) in the block).
/// Positions outside the block are clamped to its edge. `flow` must be (H, W, 2).
pub fn warp_to_reference(block: &Array2<f32>, flow: &Array3<f32>) -> Result<Array2<f32>> {
    let (h, w) = block.dim();
    if h == 0 || w == 0 {
        return Err(Error::invalid("cannot warp an empty block image"));
    }
    check_flow(flow, h, w, "warp")?;
    let (block, flow) = (block.as_standard_layout(), flow.as_standard_layout());
    let (pixels, flow) = (
        block.as_slice().expect("standard layout"),
        flow.as_slice().expect("standard layout"),
    );
    let mut out = Array2::<f32>::zeros((h, w));
    out.as_slice_mut()
        .expect("fresh array is contiguous")
        .par_chunks_exact_mut(w)
        .zip(flow.par_chunks_exact(2 * w))
        .enumerate()
        .for_each(|(y, (row, flow))| warp_row(pixels, h, y, flow, row));
    Ok(out)
}

/// Row `y` of [`warp_to_reference`] of the (H, W) image `pixels` (row-major) with that row's
/// flow `flow` ((dy, dx) pairs) into `out`. Plain slices: the same taps and arithmetic as
/// [`crate::filters::bilinear`], without the 2-D index checks.
#[inline]
fn warp_row(pixels: &[f32], h: usize, y: usize, flow: &[f32], out: &mut [f32]) {
    let w = out.len();
    for (x, (out, d)) in out.iter_mut().zip(flow.chunks_exact(2)).enumerate() {
        let (y0, y1, fy) = bilinear_taps(y as f32 + d[0], h);
        let (x0, x1, fx) = bilinear_taps(x as f32 + d[1], w);
        let (top, bottom) = (&pixels[y0 * w..(y0 + 1) * w], &pixels[y1 * w..(y1 + 1) * w]);
        let top = top[x0] * (1.0 - fx) + top[x1] * fx;
        let bottom = bottom[x0] * (1.0 - fx) + bottom[x1] * fx;
        *out = top * (1.0 - fy) + bottom * fy;
    }
}

/// [`warp_to_reference`] with the flow made row by row: `flow_row(y, row)` fills `row` with
/// the (dy, dx) pairs of image row `y` (2·W values). The same output as the dense flow those
/// rows make up, without holding it: a flow given by a formula (a camera's affine motion)
/// costs neither the (H, W, 2) array nor its memory traffic. A row holding a non-finite value
/// is an error, as [`check_flow`] makes it.
pub(crate) fn warp_rows_to_reference(
    block: &Array2<f32>,
    flow_row: impl Fn(usize, &mut [f32]) + Sync,
) -> Result<Array2<f32>> {
    let (h, w) = block.dim();
    if h == 0 || w == 0 {
        return Err(Error::invalid("cannot warp an empty block image"));
    }
    let block = block.as_standard_layout();
    let pixels = block.as_slice().expect("standard layout");
    let mut out = Array2::<f32>::zeros((h, w));
    out.as_slice_mut()
        .expect("fresh array is contiguous")
        .par_chunks_exact_mut(w)
        .enumerate()
        .try_for_each_init(
            || vec![0.0f32; 2 * w],
            |flow, (y, row)| {
                flow_row(y, flow);
                if flow.iter().any(|v| !v.is_finite()) {
                    return Err(Error::invalid("warp: flow holds non-finite values"));
                }
                warp_row(pixels, h, y, flow, row);
                Ok(())
            },
        )?;
    Ok(out)
}
