//! The real colour SwissSPAD2 sensor's CFA and hot-pixel mask (paper §6 "colour SPAD";
//! calibration files of the MIT-licensed WISION-Lab `photoncube` project, notice in
//! `data/colorspad/LICENSE-photoncube.txt`).
//!
//! Geometry. The sensor is read as a 256x512 half-array frame. The *corrected* frame used by
//! the capture format is rows 2..256 and columns 0..496 of it (254x496), after the readout's
//! column blocks 252..255 and 260..263 are swapped. The embedded PNG
//! `rgbw_oh_bn_color_ss2_corrected.png` (512 wide, 256 high) is already column-corrected and
//! covers the whole half array; colour pixels sit only at (odd row, odd column) of it and its
//! last 16 columns are all W.
//!
//! Row alignment (an open question in public code, which crops the PNG either at row 0 or at
//! row 2): we crop rows [`PNG_ROW_OFFSET`]`..` = 2..256, the same rows the corrected frame keeps
//! of the raw frame, so PNG pixel `(y + 2, x)` is frame pixel `(y, x)`. Both choices put the
//! colour sites at (odd row, odd column) of the frame (the offset is even) and give the same
//! W/colour mask; only the R/G/B labels differ (tested).
#![deny(unsafe_code)]

use super::io::from_rgb_image;
use super::Cfa;
use ndarray::{s, Array2};
use ndarray_npy::ReadNpyExt;
use std::sync::OnceLock;

/// The CFA picture, 512x256 RGB (pure R/G/B = colour filter, white = W).
pub const COLORSPAD_CFA_PNG: &[u8] =
    include_bytes!("../../data/colorspad/rgbw_oh_bn_color_ss2_corrected.png");
/// The hot/dead pixel mask, bool `(254, 496)` in corrected-frame coordinates.
pub const COLORSPAD_INPAINT_MASK_NPY: &[u8] =
    include_bytes!("../../data/colorspad/colorspad_inpaint_mask.npy");

/// Height of the corrected colour-SPAD frame.
pub const COLORSPAD_HEIGHT: usize = 254;
/// Width of the corrected colour-SPAD frame.
pub const COLORSPAD_WIDTH: usize = 496;
/// First PNG row of the corrected frame (see the module documentation).
pub const PNG_ROW_OFFSET: usize = 2;

/// The full embedded CFA picture as a [`Cfa`] (256x512, the raw half-array geometry).
pub fn colorspad_png_cfa() -> Cfa {
    let img = image::load_from_memory_with_format(COLORSPAD_CFA_PNG, image::ImageFormat::Png)
        .expect("embedded colorspad PNG decodes")
        .to_rgb8();
    from_rgb_image(&img, "rgbw_oh_bn_color_ss2_corrected.png (embedded)")
        .expect("embedded colorspad PNG holds only R, G, B and W")
}

/// The colour SwissSPAD2 CFA in the corrected 254x496 frame: rows
/// `PNG_ROW_OFFSET..PNG_ROW_OFFSET + 254`, columns `0..496` of the embedded PNG.
pub fn colorspad_cfa() -> Cfa {
    static CFA: OnceLock<Cfa> = OnceLock::new();
    CFA.get_or_init(|| colorspad_cfa_at_row(PNG_ROW_OFFSET))
        .clone()
}

/// The corrected-frame crop of the PNG starting at PNG row `row_offset` (0 or 2 are the two
/// alignments seen in public code).
pub fn colorspad_cfa_at_row(row_offset: usize) -> Cfa {
    let png = colorspad_png_cfa();
    let rows = row_offset..row_offset + COLORSPAD_HEIGHT;
    Cfa::new(png.codes().slice(s![rows, ..COLORSPAD_WIDTH]).to_owned())
        .expect("crop of a valid CFA")
}

/// The sensor's hot (and dead) pixels to inpaint, `(254, 496)` in corrected-frame coordinates,
/// `true` = hot.
pub fn colorspad_hot_pixel_mask() -> Array2<bool> {
    let mask = Array2::<bool>::read_npy(COLORSPAD_INPAINT_MASK_NPY)
        .expect("embedded colorspad inpaint mask is a 2-D bool .npy");
    debug_assert_eq!(mask.dim(), (COLORSPAD_HEIGHT, COLORSPAD_WIDTH));
    mask
}
