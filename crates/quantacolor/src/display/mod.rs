//! Display of linear reconstructions (paper §7, Fig. 14 and Fig. 20; supplement §4):
//! colour correction ([`ccm`]), noise-aware low-light visualisation ([`mesopic`]), exposure and
//! tone mapping ([`tonemap`], [`mantiuk`]), sRGB encoding ([`crate::color::srgb`], [`exposure`]), all chained by
//! [`render`].
#![deny(unsafe_code)]

pub mod ccm;
pub mod exposure;
pub mod mantiuk;
pub mod mesopic;
pub mod render;
pub mod tonemap;

pub use ccm::{chart_patch_means, ColorFit, ColorMatrix, FitResidual};
pub use exposure::{auto_exposure_scale, encode_srgb16, encode_srgb8, hstack, vstack};
pub use mantiuk::Mantiuk06Config;
pub use mesopic::{
    auto_offset, effective_frames, mesopic_blend, mesopic_weight, MesopicConfig, MesopicOffset,
    MesopicParams,
};
pub use render::{
    frame_path, mesopic_params, output_is_tiff, quantise16, quantise8, render, render_srgb16,
    render_srgb8, render_stack, write_display, write_rendered, BitDepth, RenderOptions,
};
pub use tonemap::{
    global_exposure, global_white, tone_map, tone_map_global, GlobalConfig, ToneMap,
};
