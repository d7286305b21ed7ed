//! The built-in procedural test scene `builtin:chart` (and `builtin:chart-hdr`): the 24
//! ColorChecker patches, a Siemens star, fine gratings, a fence, small high-contrast glyphs and a
//! smooth gradient, laid out relative to the sensor size. Values are linear RGB reflectances
//! (white patch ≈ 0.9); the HDR variant adds a light source 1000x brighter than the white patch.
#![forbid(unsafe_code)]

use crate::color::colorchecker::{srgb8_to_linear, COLORCHECKER_AREA, COLORCHECKER_SRGB};
use crate::color::srgb::srgb_to_linear;

/// Brightness of the HDR light source relative to the white patch.
pub const LIGHT_TO_WHITE: f32 = 1000.0;

/// 3x5 glyphs ('#' = ink) for the text-like detail.
const GLYPHS: [[&str; 5]; 14] = [
    ["###", "#.#", "#.#", "#.#", "###"],
    [".#.", "##.", ".#.", ".#.", "###"],
    ["###", "..#", "###", "#..", "###"],
    ["###", "..#", "###", "..#", "###"],
    ["#.#", "#.#", "###", "..#", "..#"],
    ["###", "#..", "###", "..#", "###"],
    ["###", "#..", "###", "#.#", "###"],
    ["###", "..#", "..#", "..#", "..#"],
    ["###", "#.#", "###", "#.#", "###"],
    ["###", "#.#", "###", "..#", "###"],
    [".#.", "#.#", "###", "#.#", "#.#"],
    ["###", "#..", "###", "#..", "###"],
    ["#.#", "#.#", "###", "#.#", "#.#"],
    ["#.#", "#.#", ".#.", "#.#", "#.#"],
];

/// Linear value of the white patch (patch 19).
pub fn white_patch() -> f32 {
    srgb8_to_linear(COLORCHECKER_SRGB[18])[1]
}

const BACKGROUND: [f32; 3] = [0.18, 0.18, 0.18];
const BRIGHT: f32 = 0.8;
const DARK: f32 = 0.03;

fn grey(v: f32) -> [f32; 3] {
    [v, v, v]
}

fn inside(v: f64, lo: f64, hi: f64) -> bool {
    v >= lo && v < hi
}

/// The chart at sensor position `(y, x)` (pixels, reference frame) of a `height` x `width`
/// sensor; positions outside the sensor show the plain background.
pub fn chart_value(y: f64, x: f64, height: usize, width: usize, hdr: bool) -> [f32; 3] {
    let (h, w) = (height as f64, width as f64);
    let mut out = BACKGROUND;

    // ColorChecker: 6 x 4 patches on a dark frame, left half, top.
    let [cx0, cx1, cy0, cy1] = COLORCHECKER_AREA;
    let (cx0, cx1, cy0, cy1) = (cx0 * w, cx1 * w, cy0 * h, cy1 * h);
    if inside(x, cx0, cx1) && inside(y, cy0, cy1) {
        let fx = (x - cx0) / (cx1 - cx0) * 6.0;
        let fy = (y - cy0) / (cy1 - cy0) * 4.0;
        let (col, row) = ((fx as usize).min(5), (fy as usize).min(3));
        let (lx, ly) = (fx - col as f64, fy - row as f64);
        out = if inside(lx, 0.1, 0.9) && inside(ly, 0.1, 0.9) {
            srgb8_to_linear(COLORCHECKER_SRGB[row * 6 + col])
        } else {
            grey(DARK)
        };
    }
    // Smooth gradient: perceptually uniform grey ramp below the patches.
    if inside(x, cx0, cx1) && inside(y, 0.60 * h, 0.70 * h) {
        out = grey(srgb_to_linear(((x - cx0) / (cx1 - cx0)) as f32));
    }
    // Text-like detail: three lines of 3x5 glyphs with 1, 1.5 and 2 px strokes, dark on light.
    if inside(x, cx0, cx1) && inside(y, 0.74 * h, 0.97 * h) {
        out = grey(BRIGHT);
        let mut line_top = 0.74 * h + 1.0;
        for module in [1.0, 1.5, 2.0] {
            let (ly, lx) = ((y - line_top) / module, (x - cx0 - 1.0) / module);
            if inside(ly, 0.0, 5.0) && lx >= 0.0 {
                let (cell, gx) = ((lx / 4.0) as usize, (lx % 4.0) as usize);
                let glyph = &GLYPHS[cell % GLYPHS.len()];
                if gx < 3 && glyph[ly as usize].as_bytes()[gx] == b'#' {
                    out = grey(DARK);
                }
            }
            line_top += 7.0 * module;
        }
    }
    // Siemens star: 18 cycles.
    let (sy, sx, sr) = (0.32 * h, 0.62 * w, (0.27 * h).min(0.14 * w));
    let (dy, dx) = (y - sy, x - sx);
    if dy * dy + dx * dx < sr * sr {
        out = grey(if (18.0 * dy.atan2(dx)).sin() >= 0.0 {
            BRIGHT
        } else {
            DARK
        });
    }
    // Gratings: four bands of period 2, 3, 4, 6 px; vertical bars left, horizontal bars right.
    let (gx0, gx1, gy0, gy1) = (0.78 * w, 0.98 * w, 0.04 * h, 0.60 * h);
    if inside(x, gx0, gx1) && inside(y, gy0, gy1) {
        let band_h = (gy1 - gy0) / 4.0;
        let band = (((y - gy0) / band_h) as usize).min(3);
        let in_band = (y - gy0) - band as f64 * band_h;
        if inside(in_band, 0.0, band_h - 2.0) {
            let period = [2.0, 3.0, 4.0, 6.0][band];
            let along = if x < 0.5 * (gx0 + gx1) {
                x - gx0
            } else {
                in_band
            };
            out = grey(if (along / period).fract() < 0.5 {
                BRIGHT
            } else {
                DARK
            });
        }
    }
    // Fence: dark posts every 8 px and two rails in front of a blue sky gradient.
    let (fx0, fx1, fy0, fy1) = (0.50 * w, 0.98 * w, 0.66 * h, 0.97 * h);
    if inside(x, fx0, fx1) && inside(y, fy0, fy1) {
        let fv = (y - fy0) / (fy1 - fy0);
        let post = ((x - fx0) % 8.0) < 2.5;
        let rail = [0.25, 0.7]
            .iter()
            .any(|&r| inside(y - (fy0 + r * (fy1 - fy0)), 0.0, 2.0));
        out = if post || rail {
            [0.10, 0.06, 0.03]
        } else {
            let s = (1.0 - 0.4 * fv) as f32;
            [0.25 * s, 0.45 * s, 0.85 * s]
        };
    }
    // HDR: a neutral light source 1000x the white patch, in front of the fence's right end.
    if hdr {
        let r = (0.035 * h.min(w)).max(2.0);
        let (ly, lx) = (y - 0.75 * h, x - 0.93 * w);
        if ly * ly + lx * lx < r * r {
            out = grey(LIGHT_TO_WHITE * white_patch());
        }
    }
    out
}

/// Texture of the moving object: a chequerboard of saturated colours with 3 px squares, at
/// offset `(y, x)` from the object's centre.
pub fn object_texture(y: f64, x: f64) -> [f32; 3] {
    const COLOURS: [[f32; 3]; 4] = [
        [0.7, 0.1, 0.05],
        [0.1, 0.6, 0.1],
        [0.05, 0.1, 0.7],
        [0.8, 0.75, 0.1],
    ];
    let (i, j) = ((y / 3.0).floor() as i64, (x / 3.0).floor() as i64);
    COLOURS[((i + 2 * j).rem_euclid(4)) as usize]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::color::colorchecker::colorchecker_patch_rects;

    #[test]
    fn patches_sit_where_the_layout_puts_them() {
        let (h, w) = (254, 496);
        // Centre of patch 1 (dark skin) and patch 19 (white).
        let cell = |row: f64, col: f64| {
            let x = 0.02 * w as f64 + (col + 0.5) * 0.44 * w as f64 / 6.0;
            let y = 0.04 * h as f64 + (row + 0.5) * 0.52 * h as f64 / 4.0;
            chart_value(y, x, h, w, false)
        };
        assert_eq!(cell(0.0, 0.0), srgb8_to_linear([115, 82, 68]));
        assert_eq!(cell(3.0, 0.0), srgb8_to_linear([243, 243, 242]));
        assert_eq!(cell(3.0, 5.0), srgb8_to_linear([52, 52, 52]));
        // The light exists only in the HDR chart and is 1000x the white patch.
        let (ly, lx) = (0.75 * h as f64, 0.93 * w as f64);
        assert!((chart_value(ly, lx, h, w, true)[0] / white_patch() - 1000.0).abs() < 1e-3);
        assert!(chart_value(ly, lx, h, w, false)[0] < 1.0);
    }

    #[test]
    fn patch_rects_cover_exactly_their_patch_colour() {
        let (h, w) = (254, 496);
        for (i, r) in colorchecker_patch_rects(h, w).iter().enumerate() {
            let want = srgb8_to_linear(COLORCHECKER_SRGB[i]);
            // Just inside every corner: the patch colour; just outside the left edge: the frame.
            for (y, x) in [
                (r[0] + 1e-6, r[2] + 1e-6),
                (r[1] - 1e-6, r[3] - 1e-6),
                (r[0] + 1e-6, r[3] - 1e-6),
            ] {
                assert_eq!(chart_value(y, x, h, w, false), want, "patch {i}");
            }
            assert_eq!(
                chart_value(r[0] + 1e-6, r[2] - 1e-6, h, w, false),
                grey(DARK)
            );
        }
    }
}
