//! Denoising of the merged image (paper §4.3, Fig. 6; supplement §1.5): variance stabilisation
//! ([`anscombe`]), BM3D ([`bm3d`]) and the chrominance-focused colour BM3D ([`chroma`]).

pub mod anscombe;
pub mod bm3d;
pub mod chroma;

pub use chroma::{denoise_linear, DenoiseConfig, DenoiseMethod};
