//! The data the fit reads: the grey sites of the sensor (W, not hot) row by row, their
//! detections in a frame's raw row, and where one row's sites land in the template.

#![forbid(unsafe_code)]

use crate::align::refine::AffineMotion;

/// The grey sites of a capture, row by row, relative to the image centre.
pub(super) struct Sites {
    pub(super) width: usize,
    /// For every row, the columns of its grey sites.
    pub(super) columns: Vec<Vec<u16>>,
    /// For every row, one mask per eight columns 8k..8k + 8: bit l set where column 8k + l is
    /// a grey site.
    pub(super) masks: Vec<Vec<u8>>,
    /// The image centre (y, x) that positions are taken about.
    pub(super) centre: [f64; 2],
}

impl Sites {
    /// The sites in `columns` (row by row, increasing) of an image `width` wide.
    pub(super) fn new(width: usize, columns: Vec<Vec<u16>>, centre: [f64; 2]) -> Sites {
        let masks = columns
            .iter()
            .map(|row| {
                let mut masks = vec![0u8; width.div_ceil(8)];
                for &x in row {
                    masks[x as usize / 8] |= 1 << (x % 8);
                }
                masks
            })
            .collect();
        Sites {
            width,
            columns,
            masks,
            centre,
        }
    }

    /// The number of sites.
    pub(super) fn count(&self) -> usize {
        self.columns.iter().map(Vec::len).sum()
    }

    /// The sites of every `step`-th row (0, step, 2·step, …); the other rows keep none.
    pub(super) fn every_nth_row(&self, step: usize) -> Sites {
        let step = step.max(1);
        Sites::new(
            self.width,
            self.columns
                .iter()
                .enumerate()
                .map(|(y, row)| {
                    if y % step == 0 {
                        row.clone()
                    } else {
                        Vec::new()
                    }
                })
                .collect(),
            self.centre,
        )
    }
}

/// Whether the site in column `x` of a frame's raw row detected a photon.
#[inline(always)]
pub(super) fn site_bit(row: &[u8], x: usize, packed: bool) -> bool {
    if packed {
        (row[x / 8] >> (7 - x % 8)) & 1 == 1
    } else {
        row[x] != 0
    }
}

/// The detections of columns 8k..8k + 8 of a frame's raw row: bit l for column 8k + l.
#[inline(always)]
pub(super) fn chunk_bits(row: &[u8], k: usize, packed: bool) -> u32 {
    if packed {
        // Packed rows hold column 8k + l in bit 7 − l of byte k.
        u32::from(row[k].reverse_bits())
    } else {
        row[8 * k..(8 * k + 8).min(row.len())]
            .iter()
            .enumerate()
            .fold(0, |bits, (l, &v)| bits | (u32::from(v != 0) << l))
    }
}

/// How one row's sites map into the template: a site in column x (r_x = x − centre) sits at
/// (y + base_y + m_yx·r_x + margin, x + base_x + m_xx·r_x + margin).
#[derive(Clone, Copy)]
pub(super) struct RowMap {
    /// Whether the frames' rows are bit-packed ([`site_bit`]).
    pub(super) packed: bool,
    pub(super) centre_x: f64,
    /// The displacement (y, x) at r_x = 0.
    pub(super) base: [f64; 2],
    pub(super) m_yx: f64,
    pub(super) m_xx: f64,
    /// The template's margin (px).
    pub(super) margin: f64,
}

impl RowMap {
    /// The map of row `y` under the inverse camera `camera`.
    pub(super) fn new(
        sites: &Sites,
        camera: &AffineMotion,
        y: usize,
        packed: bool,
        margin: f64,
    ) -> RowMap {
        let ry = y as f64 - sites.centre[0];
        RowMap {
            packed,
            centre_x: sites.centre[1],
            // The displacement at r_x = 0 of this row; d = base + m[.][1]·r_x.
            base: camera.at([ry, 0.0]),
            m_yx: camera.m[0][1],
            m_xx: camera.m[1][1],
            margin,
        }
    }

    /// The template position (y, x) of the site in column `x` of row `y`, in f64.
    #[inline(always)]
    pub(super) fn position(&self, y: usize, x: usize) -> (f64, f64) {
        let rx = x as f64 - self.centre_x;
        (
            y as f64 + self.base[0] + self.m_yx * rx + self.margin,
            x as f64 + self.base[1] + self.m_xx * rx + self.margin,
        )
    }
}
