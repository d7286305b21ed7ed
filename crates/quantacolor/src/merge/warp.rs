//! Bilinear warping of block images onto the reference grid (supplement §1.2).

use crate::error::{Error, Result};
use crate::filters::bilinear;
use ndarray::{Array2, Array3, Axis};
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
    let mut out = Array2::<f32>::zeros((h, w));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut row)| {
            for x in 0..w {
                let (dy, dx) = (flow[[y, x, 0]], flow[[y, x, 1]]);
                row[x] = bilinear(block.view(), y as f32 + dy, x as f32 + dx);
            }
        });
    Ok(out)
}
