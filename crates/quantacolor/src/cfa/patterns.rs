//! CFA patterns of the paper's comparison (§5, Fig. 8; supplement §2, Fig. 3).
#![deny(unsafe_code)]

use super::bluenoise::blue_noise_codes;
use super::lattice::SiteLattice;
use super::{colorspad, Cfa, Channel};
use crate::error::{Error, Result};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A named CFA pattern. `FromStr` accepts the command-line names ([`Pattern::NAMES`]) and
/// `Display` prints them back.
#[derive(Debug, Clone, PartialEq)]
pub enum Pattern {
    /// RGGB Bayer (Bayer 1976).
    Bayer,
    /// 25 % W: Bayer with one G of each 2x2 replaced by W, `R G / W B` (Gindele & Gallagher 2002).
    Rgbw25,
    /// 50 % W on a checkerboard (`y + x` even); the colour sites carry a regular 4x4-periodic
    /// layout with G twice as often as R and B (Tachi 2012 style):
    /// `W G W R / G W R W / W B W G / B W G W`.
    Rgbw50,
    /// 75 % W: one colour site per 2x2 block at (odd row, odd column), colours in Bayer order on
    /// the colour-site lattice (Kwan et al. 2020).
    Rgbw75Regular,
    /// 75 % W, same sites as [`Pattern::Rgbw75Regular`], colours i.i.d. uniform over R, G, B
    /// (Oh et al. 2017).
    Rgbw75Random,
    /// The paper's design (§5, Fig. 8c): colour sites on the regular lattice of W fraction
    /// `w_fraction` (0.5, 0.75, 0.875 or 0.9375, supplement Fig. 3), colours pseudorandom blue
    /// noise with the 4-neighbour rule of Condat 2010 (see [`super::bluenoise`]).
    BlueNoise { w_fraction: f64 },
    /// The fabricated colour SwissSPAD2's CFA (75 % W pseudorandom), 254x496 in the corrected
    /// frame geometry (see [`super::colorspad`]).
    Colorspad,
}

impl Pattern {
    /// Every command-line name, in the order of the paper's comparison.
    pub const NAMES: [&'static str; 10] = [
        "bayer",
        "rgbw-25",
        "rgbw-50",
        "rgbw-75-regular",
        "rgbw-75-random",
        "rgbw-75-bluenoise",
        "rgbw-50-bluenoise",
        "rgbw-87.5-bluenoise",
        "rgbw-93.75-bluenoise",
        "colorspad",
    ];

    /// Every pattern, in the order of [`Pattern::NAMES`].
    pub fn all() -> Vec<Pattern> {
        Self::NAMES
            .iter()
            .map(|n| n.parse().expect("every listed name parses"))
            .collect()
    }

    /// The blue-noise pattern with W fraction `w_fraction` (one of 0.5, 0.75, 0.875, 0.9375).
    pub fn blue_noise(w_fraction: f64) -> Result<Pattern> {
        SiteLattice::for_w_fraction(w_fraction)?;
        Ok(Pattern::BlueNoise { w_fraction })
    }

    /// This pattern with its W fraction replaced (`--w-fraction`); only the blue-noise family
    /// has a W fraction to choose.
    pub fn with_w_fraction(&self, w_fraction: f64) -> Result<Pattern> {
        match self {
            Pattern::BlueNoise { .. } => Pattern::blue_noise(w_fraction),
            other => Err(Error::invalid(format!(
                "--w-fraction applies only to the blue-noise patterns, not '{other}'"
            ))),
        }
    }

    /// Whether [`generate`] ignores its seed for this pattern.
    pub fn is_deterministic(&self) -> bool {
        !matches!(self, Pattern::Rgbw75Random | Pattern::BlueNoise { .. })
    }
}

impl std::fmt::Display for Pattern {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = match self {
            Pattern::Bayer => "bayer",
            Pattern::Rgbw25 => "rgbw-25",
            Pattern::Rgbw50 => "rgbw-50",
            Pattern::Rgbw75Regular => "rgbw-75-regular",
            Pattern::Rgbw75Random => "rgbw-75-random",
            Pattern::BlueNoise { w_fraction } => {
                return write!(f, "rgbw-{}-bluenoise", w_fraction * 100.0)
            }
            Pattern::Colorspad => "colorspad",
        };
        f.write_str(name)
    }
}

impl std::str::FromStr for Pattern {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "bayer" => Ok(Pattern::Bayer),
            "rgbw-25" => Ok(Pattern::Rgbw25),
            "rgbw-50" => Ok(Pattern::Rgbw50),
            "rgbw-75-regular" => Ok(Pattern::Rgbw75Regular),
            "rgbw-75-random" => Ok(Pattern::Rgbw75Random),
            "colorspad" => Ok(Pattern::Colorspad),
            other => {
                let percent = other
                    .strip_prefix("rgbw-")
                    .and_then(|r| r.strip_suffix("-bluenoise"))
                    .and_then(|p| p.parse::<f64>().ok());
                match percent {
                    Some(p) => Pattern::blue_noise(p / 100.0),
                    None => Err(Error::invalid(format!(
                        "unknown CFA pattern '{other}'; known patterns: {}",
                        Pattern::NAMES.join(", ")
                    ))),
                }
            }
        }
    }
}

/// Generates `pattern` at `height` x `width`; `seed` drives the pseudorandom patterns
/// (the same seed gives the same pattern). [`Pattern::Colorspad`] is the real sensor's CFA: any
/// size up to its 254x496 frame gives its top-left crop, larger sizes are an error.
pub fn generate(pattern: &Pattern, height: usize, width: usize, seed: u64) -> Result<Cfa> {
    if height == 0 || width == 0 {
        return Err(Error::invalid(format!(
            "CFA size {width}x{height} is empty"
        )));
    }
    let (r, g, b, w) = (
        Channel::R.code(),
        Channel::G.code(),
        Channel::B.code(),
        Channel::W.code(),
    );
    let codes = match pattern {
        Pattern::Bayer => Array2::from_shape_fn((height, width), |(y, x)| match (y % 2, x % 2) {
            (0, 0) => r,
            (1, 1) => b,
            _ => g,
        }),
        Pattern::Rgbw25 => Array2::from_shape_fn((height, width), |(y, x)| match (y % 2, x % 2) {
            (0, 0) => r,
            (0, 1) => g,
            (1, 0) => w,
            _ => b,
        }),
        Pattern::Rgbw50 => {
            const TILE: [[u8; 4]; 4] = [[3, 1, 3, 0], [1, 3, 0, 3], [3, 2, 3, 1], [2, 3, 1, 3]];
            Array2::from_shape_fn((height, width), |(y, x)| TILE[y % 4][x % 4])
        }
        Pattern::Rgbw75Regular => Array2::from_shape_fn((height, width), |(y, x)| {
            if y % 2 == 1 && x % 2 == 1 {
                match ((y / 2) % 2, (x / 2) % 2) {
                    (0, 0) => r,
                    (1, 1) => b,
                    _ => g,
                }
            } else {
                w
            }
        }),
        Pattern::Rgbw75Random => {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let mut codes = Array2::from_elem((height, width), w);
            for y in (1..height).step_by(2) {
                for x in (1..width).step_by(2) {
                    codes[[y, x]] = rng.gen_range(0..3u8);
                }
            }
            codes
        }
        Pattern::BlueNoise { w_fraction } => {
            let lattice = SiteLattice::for_w_fraction(*w_fraction)?;
            blue_noise_codes(&lattice, height, width, seed)?
        }
        Pattern::Colorspad => {
            let full = colorspad::colorspad_cfa();
            let (fh, fw) = (full.height(), full.width());
            if height > fh || width > fw {
                return Err(Error::invalid(format!(
                    "the colorspad CFA is {fw}x{fh} (width x height); {width}x{height} does not \
                     fit (smaller sizes give its top-left crop)"
                )));
            }
            full.codes()
                .slice(ndarray::s![..height, ..width])
                .to_owned()
        }
    };
    Cfa::new(codes)
}
