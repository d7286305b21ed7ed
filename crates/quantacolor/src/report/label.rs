//! A comparison strip with a label under each panel (the demo's `comparison.png`), written
//! with the CFA sheet's built-in 3x5 pixel font ([`crate::cfa::sheet::draw_text`]).
#![forbid(unsafe_code)]

use crate::cfa::sheet::draw_text;
use crate::display::hstack;
use image::{Rgb, RgbImage};
use ndarray::{Array3, ArrayView3};

/// Line height of the pixel font at its magnification, px.
const LINE: usize = 12;
/// Band colour under the panels (the font's ink is light grey).
const BAND: u8 = 24;

/// Places `images` side by side (as [`hstack`], `gap` px of `fill`) and writes `labels[i]`
/// (one entry per line; upper case, digits and `.-:/%=()_`) in a dark band under panel `i`.
pub fn labelled_hstack(
    images: &[ArrayView3<u8>],
    labels: &[Vec<String>],
    gap: usize,
    fill: u8,
) -> Array3<u8> {
    let strip = hstack(images, gap, fill);
    let (h, w, _) = strip.dim();
    let lines = labels.iter().map(Vec::len).max().unwrap_or(0);
    let band = if lines == 0 { 0 } else { LINE * lines + 6 };
    let mut img = RgbImage::from_pixel(w as u32, (h + band) as u32, Rgb([BAND; 3]));
    for ((y, x, c), v) in strip.indexed_iter() {
        img.get_pixel_mut(x as u32, y as u32).0[c] = *v;
    }
    let mut x0 = 0;
    for (i, panel) in images.iter().enumerate() {
        for (k, line) in labels.get(i).into_iter().flatten().enumerate() {
            draw_text(&mut img, x0 as u32 + 4, (h + 4 + k * LINE) as u32, line);
        }
        x0 += panel.dim().1 + gap;
    }
    Array3::from_shape_vec((h + band, w, 3), img.into_raw()).expect("(H, W, 3) RGB")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_go_under_their_panel() {
        let a = Array3::<u8>::from_elem((10, 40, 3), 200);
        let b = Array3::<u8>::from_elem((10, 40, 3), 100);
        let out = labelled_hstack(
            &[a.view(), b.view()],
            &[vec!["A".into()], vec![String::new(), "1".into()]],
            2,
            255,
        );
        assert_eq!(out.dim(), (10 + 2 * LINE + 6, 82, 3));
        assert_eq!(out[[0, 0, 0]], 200);
        assert_eq!(out[[0, 40, 0]], 255);
        assert_eq!(out[[0, 42, 0]], 100);
        let ink = |x0: usize, x1: usize, y0: usize, y1: usize| {
            (y0..y1)
                .flat_map(|y| (x0..x1).map(move |x| (y, x)))
                .filter(|&(y, x)| out[[y, x, 0]] > 128)
                .count()
        };
        // Text of line k covers rows 14 + 12k .. 24 + 12k (4 px margin, 10 px glyphs).
        let line = |k: usize| (14 + k * LINE, 24 + k * LINE);
        let ((a0, a1), (b0, b1)) = (line(0), line(1));
        // "A" under the first panel on the first line, nothing under the second there.
        assert!(ink(0, 40, a0, a1) > 10);
        assert_eq!(ink(42, 82, a0, a1), 0);
        // "1" under the second panel on the second line only.
        assert!(ink(42, 82, b0, b1) > 5);
        assert_eq!(ink(0, 40, b0, b1), 0);
    }
}
