//! The image pyramid of box aggregates and the overlapping tile grid of each level (the
//! coarse-to-fine structure of Hasinoff et al. 2016 §4; Ma et al. 2020 §4).
#![forbid(unsafe_code)]

use super::PatchConfig;
use crate::filters::gaussian_blur;
use ndarray::Array2;
use serde::{Deserialize, Serialize};

/// A regular grid of square tiles overlapping by `tile_size - tile_stride`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileGrid {
    /// Tile side, px.
    pub tile_size: usize,
    /// Distance between tile origins, px.
    pub tile_stride: usize,
    /// Number of tile rows.
    pub tiles_y: usize,
    /// Number of tile columns.
    pub tiles_x: usize,
    /// Centre row of each tile row, px (`i · stride + (size − 1) / 2`).
    pub tile_centers_y: Vec<f32>,
    /// Centre column of each tile column, px.
    pub tile_centers_x: Vec<f32>,
}

impl TileGrid {
    /// Tiles covering an `height` x `width` image: `ceil((H − size) / stride) + 1` rows (at least
    /// one), the last tiles reaching past the image where the size does not divide evenly.
    pub fn new(height: usize, width: usize, tile_size: usize, tile_stride: usize) -> TileGrid {
        let count = |n: usize| {
            if n <= tile_size {
                1
            } else {
                (n - tile_size).div_ceil(tile_stride) + 1
            }
        };
        let (ty, tx) = (count(height), count(width));
        let centre = |i: usize| (i * tile_stride) as f32 + (tile_size as f32 - 1.0) / 2.0;
        TileGrid {
            tile_size,
            tile_stride,
            tiles_y: ty,
            tiles_x: tx,
            tile_centers_y: (0..ty).map(centre).collect(),
            tile_centers_x: (0..tx).map(centre).collect(),
        }
    }
}

/// Image pyramid: level 0 the (smoothed) grey image, each next level a box aggregate (mean).
#[derive(Debug, Clone)]
pub struct Pyramid {
    /// Levels, finest first.
    pub levels: Vec<Array2<f32>>,
}

impl Pyramid {
    /// Builds the pyramid of `grey` per `config` (factors and pre-smoothing).
    pub fn new(grey: &Array2<f32>, config: &PatchConfig) -> Pyramid {
        let base = if config.presmooth_sigma > 0.0 {
            gaussian_blur(grey, config.presmooth_sigma)
        } else {
            grey.clone()
        };
        let mut levels: Vec<Array2<f32>> = Vec::with_capacity(config.downsample_factors.len());
        let mut base = Some(base);
        for &f in &config.downsample_factors {
            // Each level from the one before (the base for the first); a factor of 1 is a copy,
            // so the first level takes the base itself when it is not downsampled.
            let next = match (levels.last(), base.take()) {
                (None, Some(b)) if f == 1 => b,
                (None, Some(b)) => crate::filters::box_downsample(&b, f),
                (Some(prev), _) => crate::filters::box_downsample(prev, f),
                (None, None) => unreachable!("the base is taken by the first level"),
            };
            levels.push(next);
        }
        Pyramid { levels }
    }
}
