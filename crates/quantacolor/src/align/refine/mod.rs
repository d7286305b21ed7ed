//! Camera motion at the sensor's time resolution: this project's own stage, not the paper's.
//!
//! The paper (§4.1; Ma et al. 2020 §4.2) measures motion once per temporal block (50–1000
//! frames) and interpolates it linearly in time to every frame. Under hand shake the true
//! trajectory curves inside a block, so samples merged at the interpolated motion smear (the
//! quality suite measured up to 5 dB below a merge driven by the true motion). Here the camera
//! part of the motion is re-measured on short *sub-blocks* (tens of frames, chosen so that the
//! motion inside one stays below a fraction of a pixel) against the high-SNR reference image:
//!
//! 1. [`FrameMotion::from_alignment`] splits every block's tile flow into an affine camera
//!    motion (the robust fit of [`super::affine_fit_field`]) and a local residual (moving
//!    objects, kept at block granularity);
//! 2. [`plan_sub_blocks`] cuts each block into sub-blocks from the camera's speed and the light
//!    level;
//! 3. [`refine_camera_motion`] fits each sub-block's affine camera motion by Gauss–Newton on
//!    binned photon counts against the reference (coarse to fine, weighted by the binomial
//!    variance, Huber-robust), starting from the block motion interpolated in time;
//! 4. the six affine parameters are smoothed along time by a local quadratic fit (hand shake
//!    is smooth; photon noise of one sub-block is not).
//! 5. after every pass, each sub-block's camera is moved to its most probable value under a
//!    prior that a hand-held camera is close to a similarity (rotation, scale, translation),
//!    weighted against what its photons measured ([`prior::similarity_posterior`]): the directions
//!    that the scene leaves unobserved take the well-measured rotation's values.
//!
//! A sub-block's samples are then merged at its own motion ([`FrameMotion::sub_block_flow`]).
//!
//! Files by step: `config.rs` (settings), `affine.rs` (the affine camera map),
//! `frame_motion.rs` (the motion of every frame), `local.rs` (the tile flow the camera does not
//! explain), `plan.rs` (blocks cut into sub-blocks), `template.rs` and `bins.rs` (the fit's two
//! sides: smoothed reference and binned photon counts), `fit.rs` (one sub-block's Gauss–Newton
//! fit; its AVX2 kernels in `x86.rs`), `prior.rs` (the similarity prior) and `pass.rs` (the
//! stage: passes of templates, fits and smoothing).

mod affine;
mod bins;
mod config;
mod fit;
mod frame_motion;
mod local;
mod pass;
mod plan;
mod prior;
mod template;
#[cfg(target_arch = "x86_64")]
mod x86;

pub use affine::AffineMotion;
pub use config::{RefineConfig, RefineLevel};
pub use frame_motion::FrameMotion;
pub use pass::refine_camera_motion;
pub use plan::{plan_sub_blocks, shortest_sub_block};

pub(in crate::align) use bins::{channel_bin_layout, BinLayout};
pub(in crate::align) use config::validate_levels;
pub(in crate::align) use fit::{fit_sub_block, FitSettings};
pub(in crate::align) use template::{sample_template, template_level, TemplateLevel};
#[cfg(target_arch = "x86_64")]
pub(in crate::align) use x86::inside_avx2;

#[cfg(test)]
mod tests;
