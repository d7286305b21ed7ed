//! The X-Rite ColorChecker Classic: reference colours and the patch geometry of the built-in
//! chart scene. Shared by the simulator (`crate::simulate::chart`, which draws the chart) and
//! colour correction (`crate::display::ccm`, paper §7, Fig. 14, which measures it), so that
//! neither imports the other.
#![forbid(unsafe_code)]

use super::srgb::srgb_to_linear;

/// ColorChecker Classic patches in reading order (dark skin ... black), 8-bit sRGB as published
/// by X-Rite for the post-2009 formulation (tabulated in the Wikipedia article "ColorChecker";
/// BabelColor's "ColorChecker RGB coordinates" (Pascale 2006) agree within a few codes).
pub const COLORCHECKER_SRGB: [[u8; 3]; 24] = [
    [115, 82, 68],   // dark skin
    [194, 150, 130], // light skin
    [98, 122, 157],  // blue sky
    [87, 108, 67],   // foliage
    [133, 128, 177], // blue flower
    [103, 189, 170], // bluish green
    [214, 126, 44],  // orange
    [80, 91, 166],   // purplish blue
    [193, 90, 99],   // moderate red
    [94, 60, 108],   // purple
    [157, 188, 64],  // yellow green
    [224, 163, 46],  // orange yellow
    [56, 61, 150],   // blue
    [70, 148, 73],   // green
    [175, 54, 60],   // red
    [231, 199, 31],  // yellow
    [187, 86, 149],  // magenta
    [8, 133, 161],   // cyan
    [243, 243, 242], // white 9.5
    [200, 200, 200], // neutral 8
    [160, 160, 160], // neutral 6.5
    [122, 122, 121], // neutral 5
    [85, 85, 85],    // neutral 3.5
    [52, 52, 52],    // black 2
];

/// Where the 6 x 4 patch grid sits on the built-in chart, as fractions of the sensor
/// `[x0, x1, y0, y1]` (x of width, y of height): left half, top.
pub const COLORCHECKER_AREA: [f64; 4] = [0.02, 0.46, 0.04, 0.56];

/// Linear value of an 8-bit sRGB triple.
pub fn srgb8_to_linear(c: [u8; 3]) -> [f32; 3] {
    c.map(|v| srgb_to_linear(v as f32 / 255.0))
}

/// The coloured area of each of the 24 ColorChecker patches (reading order, as
/// [`COLORCHECKER_SRGB`]) of a `height` x `width` chart, as `[y0, y1, x0, x1]` in sensor pixel
/// coordinates (half-open, pixel centres at integers): the inner 10-90 % of each cell of the
/// 6 x 4 grid laid out by the built-in chart
/// (`crate::simulate::chart::chart_value`); the rest of the cell is the dark frame.
pub fn colorchecker_patch_rects(height: usize, width: usize) -> [[f64; 4]; 24] {
    let (h, w) = (height as f64, width as f64);
    let [cx0, cx1, cy0, cy1] = COLORCHECKER_AREA;
    let (cx0, cx1, cy0, cy1) = (cx0 * w, cx1 * w, cy0 * h, cy1 * h);
    let (cw, ch) = ((cx1 - cx0) / 6.0, (cy1 - cy0) / 4.0);
    std::array::from_fn(|i| {
        let (row, col) = ((i / 6) as f64, (i % 6) as f64);
        [
            cy0 + (row + 0.1) * ch,
            cy0 + (row + 0.9) * ch,
            cx0 + (col + 0.1) * cw,
            cx0 + (col + 0.9) * cw,
        ]
    })
}
