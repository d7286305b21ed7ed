//! Colour filter arrays (paper §5, Fig. 7–9; supplement §2).
//!
//! A [`Cfa`] maps every pixel `(y, x)` to the colour filter in front of it, coded
//! 0 = R, 1 = G, 2 = B, 3 = W (clear) as in the capture format's `cfa.npy`.
//!
//! - [`patterns`]: the compared patterns ([`Pattern`], [`generate`]);
//! - [`lattice`], [`bluenoise`]: colour-site lattices and the paper's blue-noise design;
//! - [`colorspad`]: the fabricated colour SwissSPAD2's CFA and hot-pixel mask (embedded);
//! - [`io`]: `.npy` / colour `.png` reading and atomic writing;
//! - [`analysis`]: luminance/chrominance spectra and aliasing scores (Fig. 9);
//! - [`sheet`]: the side-by-side comparison picture (Fig. 8/9).
#![deny(unsafe_code)]

pub mod analysis;
pub mod bluenoise;
pub mod colorspad;
pub mod io;
pub mod lattice;
pub mod patterns;
pub mod sheet;

use crate::error::{Error, Result};
pub use colorspad::{colorspad_cfa, colorspad_hot_pixel_mask};
pub use io::{from_rgb_image, load, load_npy, load_png, save, to_rgb_image};
pub use lattice::{SiteLattice, W_FRACTIONS};
use ndarray::Array2;
pub use patterns::{generate, Pattern};

/// The colour filter of one pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Channel {
    R = 0,
    G = 1,
    B = 2,
    W = 3,
}

impl Channel {
    /// All four channels in code order.
    pub const ALL: [Channel; 4] = [Channel::R, Channel::G, Channel::B, Channel::W];

    /// The channel with code `code` (0..=3), if any.
    pub fn from_code(code: u8) -> Option<Channel> {
        match code {
            0 => Some(Channel::R),
            1 => Some(Channel::G),
            2 => Some(Channel::B),
            3 => Some(Channel::W),
            _ => None,
        }
    }

    /// The code of this channel in `cfa.npy`.
    pub fn code(self) -> u8 {
        self as u8
    }

    /// Index 0..4, for per-channel arrays.
    pub fn index(self) -> usize {
        self as usize
    }
}

/// A colour filter array: an `(H, W)` array of channel codes, validated to hold only 0..=3.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Cfa {
    codes: Array2<u8>,
}

impl Cfa {
    /// Wraps `codes`, rejecting any code above 3 or an empty array.
    pub fn new(codes: Array2<u8>) -> Result<Self> {
        if codes.is_empty() {
            return Err(Error::invalid("CFA is empty"));
        }
        if let Some(((y, x), &c)) = codes.indexed_iter().find(|(_, &c)| c > 3) {
            return Err(Error::invalid(format!(
                "CFA code {c} at (y={y}, x={x}) is not one of 0=R 1=G 2=B 3=W"
            )));
        }
        Ok(Cfa { codes })
    }

    /// A CFA of one channel everywhere (e.g. a monochrome sensor is all W).
    pub fn uniform(height: usize, width: usize, channel: Channel) -> Self {
        Cfa {
            codes: Array2::from_elem((height, width), channel.code()),
        }
    }

    /// The channel codes, `(H, W)`.
    pub fn codes(&self) -> &Array2<u8> {
        &self.codes
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.codes.nrows()
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.codes.ncols()
    }

    /// The channel at `(y, x)`.
    pub fn channel(&self, y: usize, x: usize) -> Channel {
        Channel::from_code(self.codes[[y, x]]).expect("validated on construction")
    }

    /// Boolean mask of the pixels behind `channel`.
    pub fn mask(&self, channel: Channel) -> Array2<bool> {
        self.codes.mapv(|c| c == channel.code())
    }

    /// Fraction of pixels behind each channel, indexed by [`Channel::index`].
    pub fn fractions(&self) -> [f64; 4] {
        let mut counts = [0usize; 4];
        for &c in self.codes.iter() {
            counts[c as usize] += 1;
        }
        let n = self.codes.len() as f64;
        counts.map(|k| k as f64 / n)
    }
}
