//! quantacolor: colour burst photography for single-photon cameras.
//!
//! Implements "Seeing Photons in Color" (Ma, Sundar, Mos, Bruschini, Charbon, Gupta;
//! ACM TOG 42(4), SIGGRAPH 2023), built on "Quanta Burst Photography" (Ma et al., SIGGRAPH 2020).
//! This crate holds every algorithm as plain functions over `ndarray` arrays plus a config struct
//! per stage; it has no command-line or terminal code (see the `quantacolor-cli` crate).
//!
//! Conventions: arrays are row-major `(y, x)`; pixel centres sit at integer coordinates; flows
//! are `(dy, dx)`; linear images are mean photon detections per binary frame of an R, G or B
//! pixel with dark counts removed (λ of paper Eq. 2–3).

pub mod align;
pub mod atomic;
pub mod burst;
pub mod capture;
pub mod cfa;
pub mod color;
pub mod config_toml;
pub mod convert;
pub mod cpu;
pub mod denoise;
pub mod display;
pub mod error;
pub mod experiments;
pub mod fastmath;
pub mod filters;
pub mod inspect;
pub mod merge;
pub mod metrics;
pub mod model;
pub mod naive;
pub mod output;
pub mod pipeline;
pub mod progress;
pub mod report;
pub mod rgbw;
pub mod simulate;
pub mod stats;
pub mod timing;
pub mod video;

pub use capture::Capture;
pub use cfa::{Cfa, Channel};
pub use error::{Error, Result};
