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
    // Plain slices (the same taps and arithmetic as [`crate::filters::bilinear`], without the 2-D index checks).
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
        .for_each(|(y, (row, flow))| {
            for (x, (out, d)) in row.iter_mut().zip(flow.chunks_exact(2)).enumerate() {
                let (y0, y1, fy) = bilinear_taps(y as f32 + d[0], h);
                let (x0, x1, fx) = bilinear_taps(x as f32 + d[1], w);
                let (top, bottom) = (&pixels[y0 * w..(y0 + 1) * w], &pixels[y1 * w..(y1 + 1) * w]);
                let top = top[x0] * (1.0 - fx) + top[x1] * fx;
                let bottom = bottom[x0] * (1.0 - fx) + bottom[x1] * fx;
                *out = top * (1.0 - fy) + bottom * fy;
            }
        });
    Ok(out)
}
