//! The merge's inputs: sub-blocks of summed frames, their robustness weights and their motion
//! relative to the reference (paper §4.2: each sub-block is merged at its own position).
#![forbid(unsafe_code)]

use super::*;

/// Which robustness weights apply to a sub-block's samples.
#[derive(Debug, Clone, PartialEq)]
pub enum SubBlockRobustness {
    /// Weight 1 everywhere (e.g. the reference sub-block).
    Full,
    /// The (H, W) map of block `i` in the `block_robustness` list (sub-blocks share their
    /// block's map).
    Block(usize),
    /// Its own (H, W) map on the reference grid.
    Map(Array2<f32>),
}

/// A group of consecutive frames summed into one multi-bit image whose motion relative
/// to the reference agrees to a fraction of a pixel over its frames (for multi-bit frames of a
/// conventional sensor, one frame: paper §6.1).
#[derive(Debug, Clone)]
pub struct SubBlock {
    /// (H, W) sum of the samples over `frames` frames per pixel: the number of ones of binary
    /// frames, the sum of digital numbers of multi-bit frames.
    pub counts: Array2<u32>,
    /// Frames summed into `counts`.
    pub frames: u32,
    /// Where each site's scene point sits in the reference.
    pub flow: SubBlockMotion,
    pub robustness: SubBlockRobustness,
}

/// The motion of a sub-block, as the merge needs it: the reference position of every site.
#[derive(Debug, Clone)]
pub enum SubBlockMotion {
    /// (H, W, 2) dense flow (dy, dx): the scene point at p in the reference is at p + flow(p);
    /// inverted per site by fixed-point iteration ([`reference_position`]).
    Dense(Array3<f32>),
    /// A global affine map from sensor site q to reference position p = `matrix`·q + `offset`
    /// ((y, x) order): a camera motion with no local motion, inverted once for all sites.
    Affine {
        matrix: [[f64; 2]; 2],
        offset: [f64; 2],
    },
    /// A camera motion (the affine map of [`SubBlockMotion::Affine`]) plus a local residual
    /// (moving objects): `flow` is the dense flow of both, and `local` (H, W) marks the
    /// reference pixels where the residual may be non-zero. A site whose affine reference
    /// position lies inside the image on an unmarked pixel takes that position (there the
    /// dense flow is the camera's, whose inverse the affine map is exactly); the others invert
    /// `flow` as [`SubBlockMotion::Dense`] does.
    CameraAndLocal {
        matrix: [[f64; 2]; 2],
        offset: [f64; 2],
        flow: Array3<f32>,
        local: Array2<bool>,
    },
}

impl From<Array3<f32>> for SubBlockMotion {
    fn from(flow: Array3<f32>) -> Self {
        SubBlockMotion::Dense(flow)
    }
}

impl SubBlockMotion {
    /// The dense flow, if this motion is one.
    pub fn dense(&self) -> Option<&Array3<f32>> {
        match self {
            SubBlockMotion::Dense(flow) => Some(flow),
            SubBlockMotion::CameraAndLocal { flow, .. } => Some(flow),
            SubBlockMotion::Affine { .. } => None,
        }
    }

    /// Checks a dense flow's shape and values, or an affine map's values.
    pub(super) fn check(&self, h: usize, w: usize, what: &str) -> Result<()> {
        match self {
            SubBlockMotion::Dense(flow) => crate::merge::warp::check_flow(flow, h, w, what),
            SubBlockMotion::Affine { matrix, offset } => check_affine(matrix, offset, what),
            SubBlockMotion::CameraAndLocal {
                matrix,
                offset,
                flow,
                local,
            } => {
                check_affine(matrix, offset, what)?;
                crate::merge::warp::check_flow(flow, h, w, what)?;
                if local.dim() != (h, w) {
                    return Err(Error::invalid(format!(
                        "{what}: local-motion mask has shape {:?}, expected ({h}, {w})",
                        local.dim()
                    )));
                }
                Ok(())
            }
        }
    }
}

fn check_affine(matrix: &[[f64; 2]; 2], offset: &[f64; 2], what: &str) -> Result<()> {
    if matrix.iter().flatten().chain(offset).all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(Error::invalid(format!(
            "{what}: affine motion has non-finite values"
        )))
    }
}

/// Reference position p = `matrix`·q + `offset` of site q.
#[inline(always)]
pub(super) fn affine_position(matrix: &[[f64; 2]; 2], offset: &[f64; 2], q: [f32; 2]) -> [f32; 2] {
    let (y, x) = (q[0] as f64, q[1] as f64);
    [
        (matrix[0][0] * y + matrix[0][1] * x + offset[0]) as f32,
        (matrix[1][0] * y + matrix[1][1] * x + offset[1]) as f32,
    ]
}
