//! CFA patterns of the paper's comparison (§5, Fig. 8).

use super::{Cfa, Channel};
use crate::error::{Error, Result};
use ndarray::Array2;

/// A named CFA pattern. `FromStr` accepts the command-line names (`bayer`, `rgbw-75-regular`, ...).
#[derive(Debug, Clone, PartialEq)]
pub enum Pattern {
    /// RGGB Bayer (Bayer 1976).
    Bayer,
    /// 75 % W: one colour site per 2x2 block at (odd row, odd column), colours in Bayer order on
    /// the colour-site lattice (Kwan et al. 2020).
    Rgbw75Regular,
}

impl std::str::FromStr for Pattern {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "bayer" => Ok(Pattern::Bayer),
            "rgbw-75-regular" => Ok(Pattern::Rgbw75Regular),
            other => Err(Error::invalid(format!("unknown CFA pattern '{other}'"))),
        }
    }
}

/// Generates `pattern` at `height` x `width`; `seed` drives the pseudorandom patterns.
pub fn generate(pattern: &Pattern, height: usize, width: usize, seed: u64) -> Result<Cfa> {
    let _ = seed;
    let codes = match pattern {
        Pattern::Bayer => Array2::from_shape_fn((height, width), |(y, x)| match (y % 2, x % 2) {
            (0, 0) => Channel::R.code(),
            (1, 1) => Channel::B.code(),
            _ => Channel::G.code(),
        }),
        Pattern::Rgbw75Regular => Array2::from_shape_fn((height, width), |(y, x)| {
            if y % 2 == 1 && x % 2 == 1 {
                match ((y / 2) % 2, (x / 2) % 2) {
                    (0, 0) => Channel::R.code(),
                    (1, 1) => Channel::B.code(),
                    _ => Channel::G.code(),
                }
            } else {
                Channel::W.code()
            }
        }),
    };
    Cfa::new(codes)
}
