//! Colour reference data and conversions shared by the simulator and the display stages: the
//! sRGB transfer function ([`srgb`]) and the ColorChecker reference ([`colorchecker`]). Lower
//! than both `simulate` and `display`, and imports neither.
#![forbid(unsafe_code)]

pub mod colorchecker;
pub mod srgb;
