//! Denoising of the merged image (paper §4.3, Fig. 6; supplement §1.5).

pub mod bm3d;
