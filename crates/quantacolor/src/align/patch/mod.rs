//! Hierarchical tile alignment of grey block images (paper §4.1; Ma et al. 2020 §4; the HDR+
//! coarse-to-fine scheme of Hasinoff et al. 2016 §4).
//!
//! Each block image is aligned to the reference block image tile by tile: an image pyramid by
//! box aggregation, an exhaustive L1/L2 search in a small window on every level seeded by three
//! candidates from the coarser level, and Lucas–Kanade iterations on the finest level for
//! sub-pixel accuracy. The result for a tile is the displacement `(dy, dx)` such that the
//! scene point at `p` in the reference image is at `p + (dy, dx)` in the block image.
//!
//! The steps, one file each: `config` (levels, tile sizes, radii, norms), `pyramid` (box
//! aggregates and tile grids), `cost` (L1/L2 patch costs of a tile), `search` (the integer
//! search of one level seeded from the coarser level, Hasinoff et al. 2016 §4.1),
//! `lucas_kanade` (sub-pixel refinement on level 0, this project's choice over HDR+'s
//! quadratic fit), `second_motion` (this project's second translation for tiles the camera fit
//! rejects) and `x86` (the AVX2 kernels of the costs and of Lucas–Kanade, each bit-identical
//! to its portable reference). The instruction set is taken once, in [`ReferenceAligner::new`].
// `deny`, not `forbid`: `x86` (and it alone) allows the unsafe of its AVX2 kernels.
#![deny(unsafe_code)]

mod config;
mod cost;
mod lucas_kanade;
mod pyramid;
mod search;
mod second_motion;
#[cfg(target_arch = "x86_64")]
mod x86;

pub use config::{Norm, PatchConfig};
pub use pyramid::{Pyramid, TileGrid};
pub use second_motion::SecondMotionSearch;

use crate::cpu::Isa;
use crate::error::{Error, Result};
use lucas_kanade::{lk_tile, LkScratch, LkTile};
use ndarray::{Array2, Array3};
use rayon::prelude::*;
use search::ParentLevel;

/// The reference block's pyramid, tile grids and Lucas–Kanade data, shared by all blocks.
#[derive(Debug, Clone)]
pub struct ReferenceAligner {
    config: PatchConfig,
    pyramid: Pyramid,
    grids: Vec<TileGrid>,
    lk: Vec<LkTile>,
    /// The instruction set every cost and Lucas–Kanade kernel of this aligner runs on.
    isa: Isa,
}

impl ReferenceAligner {
    /// Prepares alignment against the reference grey image `reference` (`(H, W)`), on the
    /// process's instruction set ([`Isa::current`], taken here once for every block).
    pub fn new(reference: &Array2<f32>, config: &PatchConfig) -> Result<Self> {
        Self::with_isa(reference, config, Isa::current())
    }

    /// [`ReferenceAligner::new`] on the instruction set `isa` (every choice gives the same
    /// numbers bit for bit; tests compare them).
    pub fn with_isa(reference: &Array2<f32>, config: &PatchConfig, isa: Isa) -> Result<Self> {
        config.validate()?;
        if reference.is_empty() {
            return Err(Error::invalid("reference image is empty"));
        }
        let reference = reference.as_standard_layout().to_owned();
        let mut pyramid = Pyramid::new(&reference, config);
        // Levels smaller than their tile carry no usable patch: coarse-to-fine starts below them.
        let usable = (1..pyramid.levels.len())
            .find(|&l| {
                let (h, w) = pyramid.levels[l].dim();
                h < config.tile_sizes[l] || w < config.tile_sizes[l]
            })
            .unwrap_or(pyramid.levels.len());
        pyramid.levels.truncate(usable);
        let grids: Vec<TileGrid> = pyramid
            .levels
            .iter()
            .zip(&config.tile_sizes)
            .map(|(img, &ts)| TileGrid::new(img.nrows(), img.ncols(), ts, (ts / 2).max(1)))
            .collect();
        let fine = &pyramid.levels[0];
        let g0 = &grids[0];
        let lk = (0..g0.tiles_y * g0.tiles_x)
            .into_par_iter()
            .map(|k| {
                let (oy, ox) = (
                    (k / g0.tiles_x) * g0.tile_stride,
                    (k % g0.tiles_x) * g0.tile_stride,
                );
                lk_tile(fine, oy, ox, g0.tile_size)
            })
            .collect();
        Ok(ReferenceAligner {
            config: config.clone(),
            pyramid,
            grids,
            lk,
            isa,
        })
    }

    /// Tile grid of the finest level (the grid of the output flow).
    pub fn grid(&self) -> &TileGrid {
        &self.grids[0]
    }

    /// The instruction set this aligner's kernels run on.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// Image size `(H, W)` of the finest level.
    pub fn dim(&self) -> (usize, usize) {
        self.pyramid.levels[0].dim()
    }

    /// Flow `(tiles_y, tiles_x, 2)` of `(dy, dx)` from the reference to the grey image `block`.
    pub fn align(&self, block: &Array2<f32>) -> Result<Array3<f32>> {
        Ok(self.align_with_validity(block)?.0)
    }

    /// [`ReferenceAligner::align`] and, per tile, whether Lucas–Kanade refined it to sub-pixel
    /// precision (`false`: flat or one-directional tile, or the iterations left the ±1 px
    /// window, and the flow is the integer search result).
    pub fn align_with_validity(&self, block: &Array2<f32>) -> Result<(Array3<f32>, Array2<bool>)> {
        let (flow, valid, _) = self.align_with_pyramid(block)?;
        Ok((flow, valid))
    }

    /// [`ReferenceAligner::align_with_validity`] and the block's pyramid it searched (for
    /// [`ReferenceAligner::follow_second_motion_in`], which then need not build it again).
    pub fn align_with_pyramid(
        &self,
        block: &Array2<f32>,
    ) -> Result<(Array3<f32>, Array2<bool>, Pyramid)> {
        if block.dim() != self.dim() {
            return Err(Error::invalid(format!(
                "block image is {:?}, the reference is {:?}",
                block.dim(),
                self.dim()
            )));
        }
        // A copy only where the block is not already row-major (the pyramid's filters read
        // rows as slices); grey block images always are.
        let owned;
        let block = if block.is_standard_layout() {
            block
        } else {
            owned = block.as_standard_layout().to_owned();
            &owned
        };
        let mut alt = Pyramid::new(block, &self.config);
        let n_levels = self.grids.len();
        alt.levels.truncate(n_levels);
        // Offsets of the coarser level, in that level's pixels.
        let mut coarse: Option<Array3<f32>> = None;
        let g0 = &self.grids[0];
        let mut valid = Array2::from_elem((g0.tiles_y, g0.tiles_x), false);
        for level in (0..n_levels).rev() {
            let grid = &self.grids[level];
            let parent = coarse.as_ref().map(|c| ParentLevel {
                offsets: c,
                grid: &self.grids[level + 1],
                factor: self.config.downsample_factors[level + 1] as f32,
            });
            let offsets: Vec<(f32, f32, bool)> = (0..grid.tiles_y * grid.tiles_x)
                .into_par_iter()
                .map_init(LkScratch::default, |scratch, k| {
                    self.align_tile(level, k, &alt.levels[level], parent.as_ref(), scratch)
                })
                .collect();
            let mut arr = Array3::<f32>::zeros((grid.tiles_y, grid.tiles_x, 2));
            for (k, (dy, dx, ok)) in offsets.into_iter().enumerate() {
                arr[[k / grid.tiles_x, k % grid.tiles_x, 0]] = dy;
                arr[[k / grid.tiles_x, k % grid.tiles_x, 1]] = dx;
                if level == 0 {
                    valid[[k / grid.tiles_x, k % grid.tiles_x]] = ok;
                }
            }
            coarse = Some(arr);
        }
        Ok((coarse.expect("at least one level"), valid, alt))
    }
}

#[cfg(test)]
mod tests;
