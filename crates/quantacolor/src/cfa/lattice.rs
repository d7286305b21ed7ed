//! Colour-site lattices of the RGBW patterns (paper §5; supplement §2, Fig. 3).
//!
//! In every sparse RGBW pattern here the colour (R, G, B) sites form a square lattice
//! `origin + i·a + j·b` with `a ⟂ b` and `|a| = |b|`, and all other pixels are W. Because the
//! lattice is square, an isotropic filter in pixel space is isotropic in lattice coordinates
//! `(i, j)`, so the blue-noise design works on the `(i, j)` grid.
#![forbid(unsafe_code)]

use crate::error::{Error, Result};

/// A square lattice of colour sites in pixel coordinates `(y, x)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SiteLattice {
    /// Pixel of the site `(i, j) = (0, 0)`.
    pub origin: (i64, i64),
    /// Pixel step for `i + 1`.
    pub a: (i64, i64),
    /// Pixel step for `j + 1`.
    pub b: (i64, i64),
}

/// The W fractions the blue-noise family supports (supplement Fig. 3).
pub const W_FRACTIONS: [f64; 4] = [0.5, 0.75, 0.875, 0.9375];

impl SiteLattice {
    /// The colour-site lattice giving W fraction `w_fraction`:
    /// - 0.5: checkerboard, colour where `y + x` is odd (basis (1,1), (1,−1));
    /// - 0.75: (odd row, odd column), one colour site per 2x2 (basis (2,0), (0,2));
    /// - 0.875: the (odd, odd) sites with `(y−1)/2 + (x−1)/2` even, one per 8 pixels
    ///   (basis (2,2), (2,−2));
    /// - 0.9375: `y ≡ x ≡ 1 (mod 4)`, one per 4x4 (basis (4,0), (0,4)).
    pub fn for_w_fraction(w_fraction: f64) -> Result<Self> {
        let (origin, a, b) = if w_fraction == 0.5 {
            ((0, 1), (1, 1), (1, -1))
        } else if w_fraction == 0.75 {
            ((1, 1), (2, 0), (0, 2))
        } else if w_fraction == 0.875 {
            ((1, 1), (2, 2), (2, -2))
        } else if w_fraction == 0.9375 {
            ((1, 1), (4, 0), (0, 4))
        } else {
            return Err(Error::invalid(format!(
                "W fraction {w_fraction} is not supported; use one of 0.5, 0.75, 0.875, 0.9375"
            )));
        };
        Ok(SiteLattice { origin, a, b })
    }

    /// The lattice coordinates `(i, j)` of pixel `(y, x)` if it is a colour site.
    pub fn coords(&self, y: usize, x: usize) -> Option<(i64, i64)> {
        let (py, px) = (y as i64 - self.origin.0, x as i64 - self.origin.1);
        let (ay, ax) = self.a;
        let (by, bx) = self.b;
        let det = ay * bx - ax * by;
        let ni = py * bx - px * by;
        let nj = ay * px - ax * py;
        (ni % det == 0 && nj % det == 0).then(|| (ni / det, nj / det))
    }

    /// Whether pixel `(y, x)` is a colour site.
    pub fn is_site(&self, y: usize, x: usize) -> bool {
        self.coords(y, x).is_some()
    }

    /// Pixel of lattice site `(i, j)` (may lie outside any image).
    pub fn pixel(&self, i: i64, j: i64) -> (i64, i64) {
        (
            self.origin.0 + i * self.a.0 + j * self.b.0,
            self.origin.1 + i * self.a.1 + j * self.b.1,
        )
    }

    /// Pixels per colour site (the inverse colour density): 2, 4, 8 or 16.
    pub fn cell_area(&self) -> i64 {
        (self.a.0 * self.b.1 - self.a.1 * self.b.0).abs()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn densities_match_w_fractions() {
        for w in W_FRACTIONS {
            let lat = SiteLattice::for_w_fraction(w).unwrap();
            let n = (0..64)
                .flat_map(|y| (0..64).map(move |x| (y, x)))
                .filter(|&(y, x)| lat.is_site(y, x))
                .count();
            assert_eq!(n as f64 / 4096.0, 1.0 - w, "w = {w}");
            assert_eq!(lat.cell_area() as f64, 1.0 / (1.0 - w));
        }
        assert!(SiteLattice::for_w_fraction(0.6).is_err());
    }

    #[test]
    fn coords_invert_pixel() {
        for w in W_FRACTIONS {
            let lat = SiteLattice::for_w_fraction(w).unwrap();
            for i in -3..4 {
                for j in -3..4 {
                    let (y, x) = lat.pixel(i, j);
                    if y >= 0 && x >= 0 {
                        assert_eq!(lat.coords(y as usize, x as usize), Some((i, j)));
                    }
                }
            }
        }
    }
}
