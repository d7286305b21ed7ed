//! Display: sRGB transfer function, exposure and tone mapping, colour correction (paper §7).

pub mod srgb;
