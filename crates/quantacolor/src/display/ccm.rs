//! Colour correction (paper §7, Fig. 14): a 3x3 (or 3x4 affine) colour matrix fitted by least
//! squares from the measured linear means of the 24 ColorChecker patches to their known linear
//! sRGB values, so that the filter spectra of the colour SPAD map to sRGB primaries.
//!
//! Exposure normalisation: before the fit, a global gain `g` is fitted on the six neutral patches
//! (19–24) by least squares (`g = Σ t·m / Σ m·m` over their channels). The matrix `M` is then
//! fitted on the gain-normalised means (`M · g·m ≈ t`) and stored *without* the gain, with the
//! affine offset divided by `g`: [`ColorMatrix::apply`] therefore keeps an image in the
//! reconstruction's own units (mean detections per frame), which the later noise-aware
//! visualisation (supplement Eq. 9, thresholds in those units) and exposure steps rely on. The
//! gain is kept in the TOML for information only.
#![forbid(unsafe_code)]

use crate::color::colorchecker::{colorchecker_patch_rects, srgb8_to_linear, COLORCHECKER_SRGB};
use crate::error::{Error, Result};
use ndarray::{Array3, ArrayView3, Axis, Zip};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Indices of the six neutral patches (white 9.5 ... black 2) in reading order.
pub const NEUTRAL_PATCHES: std::ops::Range<usize> = 18..24;

/// Fraction of each patch's coloured area (centred) that is averaged: the border is left out so
/// that blur and demosaicking at the patch edges do not bias the means.
pub const PATCH_INNER_FRACTION: f64 = 0.6;

/// A linear colour-correction matrix: `out = A · rgb (+ b)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ColorMatrix {
    /// Three rows of 3 (linear) or 4 (affine: the 4th entry is the offset) coefficients.
    pub rows: Vec<Vec<f64>>,
    /// Whether the rows carry an offset column.
    #[serde(default)]
    pub affine: bool,
    /// Exposure gain fitted on the neutral patches (informational; not applied).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gain: Option<f64>,
}

/// The TOML file layout: a `[color_matrix]` table.
#[derive(Debug, Serialize, Deserialize)]
struct CcmFile {
    color_matrix: ColorMatrix,
}

/// Quality of a colour-matrix fit on the 24 patches, in the chart's units after the exposure
/// gain (white patch ≈ 0.9).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitResidual {
    /// Mean CIE76 ΔE (CIELAB, D65, white Y = 1) of the gain-normalised means, uncorrected.
    pub delta_e_before: f64,
    /// Mean CIE76 ΔE after the matrix.
    pub delta_e_after: f64,
    /// RMS linear error before the matrix.
    pub rms_before: f64,
    /// RMS linear error after the matrix.
    pub rms_after: f64,
}

/// A fitted matrix and its residuals.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorFit {
    pub matrix: ColorMatrix,
    pub residual: FitResidual,
}

impl ColorMatrix {
    /// The identity (no colour change).
    pub fn identity() -> Self {
        ColorMatrix {
            rows: vec![
                vec![1.0, 0.0, 0.0],
                vec![0.0, 1.0, 0.0],
                vec![0.0, 0.0, 1.0],
            ],
            affine: false,
            gain: None,
        }
    }

    /// Checks the row shape (3 rows of 3, or of 4 when affine) and finiteness.
    pub fn validate(&self) -> Result<()> {
        let n = if self.affine { 4 } else { 3 };
        if self.rows.len() != 3 || self.rows.iter().any(|r| r.len() != n) {
            return Err(Error::invalid(format!(
                "a colour matrix needs 3 rows of {n} numbers{}, got {:?}",
                if self.affine { " (affine)" } else { "" },
                self.rows.iter().map(|r| r.len()).collect::<Vec<_>>()
            )));
        }
        if self.rows.iter().flatten().any(|v| !v.is_finite()) {
            return Err(Error::invalid("a colour matrix must be finite"));
        }
        Ok(())
    }

    /// Whether this is exactly the identity without offset.
    pub fn is_identity(&self) -> bool {
        self.rows.iter().enumerate().all(|(i, r)| {
            r.iter()
                .enumerate()
                .all(|(j, &v)| v == (i == j) as u8 as f64)
        })
    }

    /// The matrix applied to one pixel.
    pub fn apply_pixel(&self, rgb: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|i| {
            let r = &self.rows[i];
            let offset = if self.affine { r[3] } else { 0.0 };
            r[0] * rgb[0] + r[1] * rgb[1] + r[2] * rgb[2] + offset
        })
    }

    /// The matrix applied to every pixel of `image` (H, W, 3). The identity returns an exact
    /// copy. Errors on a malformed matrix or an image without 3 channels.
    pub fn apply(&self, image: ArrayView3<f32>) -> Result<Array3<f32>> {
        self.validate()?;
        check_rgb(image)?;
        if self.is_identity() {
            return Ok(image.to_owned());
        }
        let mut out = Array3::<f32>::zeros(image.dim());
        Zip::from(out.lanes_mut(Axis(2)))
            .and(image.lanes(Axis(2)))
            .par_for_each(|mut o, px| {
                let v = self.apply_pixel([px[0] as f64, px[1] as f64, px[2] as f64]);
                for c in 0..3 {
                    o[c] = v[c] as f32;
                }
            });
        Ok(out)
    }

    /// Fits the matrix to measured linear patch means (24, reading order) against the known
    /// linear sRGB of the ColorChecker (see the module doc for the exposure normalisation).
    pub fn fit(measured: &[[f64; 3]; 24], affine: bool) -> Result<ColorFit> {
        let targets = colorchecker_linear();
        let (num, den) = NEUTRAL_PATCHES.fold((0.0, 0.0), |(n, d), i| {
            (0..3).fold((n, d), |(n, d), c| {
                (
                    n + targets[i][c] * measured[i][c],
                    d + measured[i][c] * measured[i][c],
                )
            })
        });
        if !(den > 0.0 && num > 0.0 && (num / den).is_finite()) {
            return Err(Error::invalid(
                "the neutral patches measure zero or negative: cannot normalise exposure",
            ));
        }
        let gain = num / den;
        let normalised: Vec<[f64; 3]> = measured.iter().map(|m| m.map(|v| v * gain)).collect();
        // Normal equations X^T X a = X^T t, one right-hand side per output channel.
        let n = if affine { 4 } else { 3 };
        let row_of = |m: &[f64; 3]| -> [f64; 4] { [m[0], m[1], m[2], 1.0] };
        let mut xtx = [[0.0f64; 4]; 4];
        let mut xtt = [[0.0f64; 3]; 4];
        for (m, t) in normalised.iter().zip(&targets) {
            let x = row_of(m);
            for a in 0..n {
                for b in 0..n {
                    xtx[a][b] += x[a] * x[b];
                }
                for c in 0..3 {
                    xtt[a][c] += x[a] * t[c];
                }
            }
        }
        let mut rows = vec![vec![0.0; n]; 3];
        for c in 0..3 {
            let rhs: Vec<f64> = (0..n).map(|a| xtt[a][c]).collect();
            let sol = solve(
                &(0..n).map(|a| xtx[a][..n].to_vec()).collect::<Vec<_>>(),
                &rhs,
            )
            .ok_or_else(|| {
                Error::invalid("the patch means are degenerate: the colour fit is singular")
            })?;
            rows[c] = sol;
        }
        let fitted = ColorMatrix {
            rows: rows.clone(),
            affine,
            gain: Some(gain),
        };
        let residual = residuals(&normalised, &targets, &fitted);
        // Store without the gain: the offset acts on un-normalised values.
        if affine {
            for r in &mut rows {
                r[3] /= gain;
            }
        }
        Ok(ColorFit {
            matrix: ColorMatrix {
                rows,
                affine,
                gain: Some(gain),
            },
            residual,
        })
    }

    /// The `[color_matrix]` TOML table.
    pub fn to_toml(&self) -> String {
        toml::to_string(&CcmFile {
            color_matrix: self.clone(),
        })
        .expect("a colour matrix serialises")
    }

    /// Parses a `[color_matrix]` TOML table; `path` names the file in errors.
    pub fn from_toml(text: &str, path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let file: CcmFile = toml::from_str(text).map_err(|e| Error::format(path, e.message()))?;
        file.color_matrix
            .validate()
            .map_err(|e| Error::format(path, e.to_string()))?;
        Ok(file.color_matrix)
    }

    /// Reads a `[color_matrix]` TOML file.
    pub fn read(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::from_toml(&text, path)
    }

    /// Writes the `[color_matrix]` TOML file atomically.
    pub fn write(&self, path: impl AsRef<Path>) -> Result<()> {
        let text = self.to_toml();
        crate::atomic::write_atomic(path, |w| w.write_all(text.as_bytes()))
    }
}

/// Mean CIE76 ΔE and RMS linear error of `measured` (after `matrix`) against `targets`.
fn residuals(measured: &[[f64; 3]], targets: &[[f64; 3]], matrix: &ColorMatrix) -> FitResidual {
    let score = |f: &dyn Fn(&[f64; 3]) -> [f64; 3]| {
        let (mut de, mut se) = (0.0, 0.0);
        for (m, t) in measured.iter().zip(targets) {
            let v = f(m);
            de += delta_e76(v, *t);
            se += (0..3).map(|c| (v[c] - t[c]).powi(2)).sum::<f64>();
        }
        let n = measured.len() as f64;
        (de / n, (se / (3.0 * n)).sqrt())
    };
    let (delta_e_before, rms_before) = score(&|m| *m);
    let (delta_e_after, rms_after) = score(&|m| matrix.apply_pixel(*m));
    FitResidual {
        delta_e_before,
        delta_e_after,
        rms_before,
        rms_after,
    }
}

/// Linear sRGB of the 24 ColorChecker patches (reading order).
pub fn colorchecker_linear() -> [[f64; 3]; 24] {
    COLORCHECKER_SRGB.map(|c| srgb8_to_linear(c).map(|v| v as f64))
}

/// Mean of the central [`PATCH_INNER_FRACTION`] of each ColorChecker patch of an (H, W, 3)
/// reconstruction of the built-in chart (`builtin:chart`), located from the chart's layout for
/// that (H, W). Errors if a patch covers no pixel (image too small) or a mean is not finite.
pub fn chart_patch_means(linear: ArrayView3<f32>) -> Result<[[f64; 3]; 24]> {
    check_rgb(linear)?;
    let (h, w, _) = linear.dim();
    let rects = colorchecker_patch_rects(h, w);
    let mut means = [[0.0; 3]; 24];
    for (i, r) in rects.iter().enumerate() {
        let shrink = |a: f64, b: f64| {
            let m = 0.5 * (b - a) * (1.0 - PATCH_INNER_FRACTION);
            // Integer pixel centres inside [a + m, b - m).
            (
                (a + m).ceil().max(0.0) as usize,
                (b - m).ceil().max(0.0) as usize,
            )
        };
        let (y0, y1) = shrink(r[0], r[1]);
        let (x0, x1) = shrink(r[2], r[3]);
        let (y1, x1) = (y1.min(h), x1.min(w));
        if y1 <= y0 || x1 <= x0 {
            return Err(Error::invalid(format!(
                "a {h}x{w} image is too small to measure ColorChecker patch {}",
                i + 1
            )));
        }
        let mut sum = [0.0f64; 3];
        for y in y0..y1 {
            for x in x0..x1 {
                for (c, s) in sum.iter_mut().enumerate() {
                    *s += linear[[y, x, c]] as f64;
                }
            }
        }
        let n = ((y1 - y0) * (x1 - x0)) as f64;
        means[i] = sum.map(|s| s / n);
        if means[i].iter().any(|v| !v.is_finite()) {
            return Err(Error::invalid(format!(
                "ColorChecker patch {} has a non-finite mean",
                i + 1
            )));
        }
    }
    Ok(means)
}

/// CIE76 colour difference of two linear sRGB colours (CIELAB, D65 white of Y = 1).
pub fn delta_e76(a: [f64; 3], b: [f64; 3]) -> f64 {
    let (la, lb) = (srgb_linear_to_lab(a), srgb_linear_to_lab(b));
    (0..3).map(|c| (la[c] - lb[c]).powi(2)).sum::<f64>().sqrt()
}

/// Linear sRGB (D65) to CIELAB with the white point of linear (1, 1, 1).
pub fn srgb_linear_to_lab(rgb: [f64; 3]) -> [f64; 3] {
    const M: [[f64; 3]; 3] = [
        [0.4124564, 0.3575761, 0.1804375],
        [0.2126729, 0.7151522, 0.0721750],
        [0.0193339, 0.1191920, 0.9503041],
    ];
    let xyz = |v: [f64; 3]| -> [f64; 3] {
        std::array::from_fn(|i| M[i][0] * v[0] + M[i][1] * v[1] + M[i][2] * v[2])
    };
    let white = xyz([1.0, 1.0, 1.0]);
    let v = xyz(rgb);
    let f = |t: f64| {
        const D: f64 = 6.0 / 29.0;
        if t > D * D * D {
            t.cbrt()
        } else {
            t / (3.0 * D * D) + 4.0 / 29.0
        }
    };
    let (fx, fy, fz) = (f(v[0] / white[0]), f(v[1] / white[1]), f(v[2] / white[2]));
    [116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)]
}

/// Solves the small dense system `a x = b` by Gaussian elimination with partial pivoting.
fn solve(a: &[Vec<f64>], b: &[f64]) -> Option<Vec<f64>> {
    let n = b.len();
    let mut m: Vec<Vec<f64>> = a
        .iter()
        .zip(b)
        .map(|(r, &v)| {
            let mut r = r.clone();
            r.push(v);
            r
        })
        .collect();
    let scale = a.iter().flatten().fold(0.0f64, |s, v| s.max(v.abs()));
    for col in 0..n {
        let piv = (col..n).max_by(|&i, &j| m[i][col].abs().total_cmp(&m[j][col].abs()))?;
        if m[piv][col].abs() <= 1e-12 * scale {
            return None;
        }
        m.swap(col, piv);
        for r in 0..n {
            if r != col {
                let f = m[r][col] / m[col][col];
                let pivot_row = m[col].clone();
                for (v, p) in m[r][col..].iter_mut().zip(&pivot_row[col..]) {
                    *v -= f * p;
                }
            }
        }
    }
    Some((0..n).map(|i| m[i][n] / m[i][i]).collect())
}

fn check_rgb(image: ArrayView3<f32>) -> Result<()> {
    if image.dim().2 != 3 {
        return Err(Error::invalid(format!(
            "expected an (H, W, 3) RGB image, got shape {:?}",
            image.dim()
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solve_recovers_a_known_system() {
        let a = vec![
            vec![2.0, 1.0, 0.0],
            vec![1.0, 3.0, 1.0],
            vec![0.0, 1.0, 4.0],
        ];
        let x = solve(&a, &[3.0, 5.0, 5.0]).unwrap();
        for v in x {
            assert!((v - 1.0).abs() < 1e-12);
        }
        assert!(solve(&[vec![1.0, 2.0], vec![2.0, 4.0]], &[1.0, 2.0]).is_none());
    }

    #[test]
    fn lab_of_white_and_black() {
        let w = srgb_linear_to_lab([1.0, 1.0, 1.0]);
        assert!((w[0] - 100.0).abs() < 1e-9 && w[1].abs() < 1e-9 && w[2].abs() < 1e-9);
        assert!(srgb_linear_to_lab([0.0; 3])[0].abs() < 1e-9);
        // 18 % grey has L* ≈ 49.5.
        assert!((srgb_linear_to_lab([0.18; 3])[0] - 49.5).abs() < 0.1);
    }
}
