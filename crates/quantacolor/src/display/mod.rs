//! Display: exposure, sRGB encoding and side-by-side sheets for linear reconstructions
//! (paper §7; tone mapping and colour correction build on this).

pub mod exposure;
pub mod srgb;

pub use exposure::{auto_exposure_scale, encode_srgb16, encode_srgb8, hstack};
