//! Bit layouts of raw sensor frames, decoded into the capture format's packing (rows of
//! `ceil(W/8)` bytes, pixel `x` in bit `7 - x % 8` of byte `x / 8`, as `np.packbits`).
//!
//! Facts from public code (none of it is copied here):
//! - SwissSPAD2 (Ulku et al. 2019; the paper's colour prototype, §6): `.bin` files without a
//!   header, bits LSB first (pixel `x` is bit `x % 8` of byte `x / 8`; WISION-Lab
//!   `photoncube2video` reverses every byte). Half array: 512 frames of 256x512 per file, 64
//!   bytes a row. Full array: 256 frames of 512x512 per file; a stored row of 128 bytes holds
//!   eight 16-byte zones `T0 B0 T1 B1 T2 B2 T3 B3`, `Tk` = columns `128k..128k+128` of top row
//!   `r`, `Bk` = the same columns of bottom row `511 - r` (the bottom half is stored upside
//!   down).
//! - Colour SwissSPAD2 (`photoncube2video`'s `process_colorspad`): rows `2..256`, columns
//!   `0..496` of the half-array frame, column blocks `252..256` and `260..264` swapped.
//! - Pi Imaging SPAD512S: 512x512 frames, bits MSB first, frames back to back. The public
//!   readers disagree on two points, so both are options ([`Spad512sOrientation`] and the
//!   trailer length of [`super::Spad512sOptions`]): a MATLAB reader (`read_512Sbin.m`) drops
//!   the last 4 bytes of every file and shows each stored row mirrored left-right (a
//!   column-major reshape followed by a 90° clockwise rotation); a Python port unpacks the
//!   first 256 frames, ignores what follows, and shows the frame rotated 90° counter-clockwise
//!   (`transpose` + `flip`, i.e. `np.rot90`).
#![forbid(unsafe_code)]

/// Orientation of SPAD512S frames in the capture.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Spad512sOrientation {
    /// Stored row `r` is image row `r`, stored bit `x` (MSB first) is column `x` (default: no
    /// transform, so nothing is assumed that the file does not say).
    #[default]
    Stored,
    /// Every row mirrored left-right: the MATLAB `read_512Sbin.m` view.
    FlipLr,
    /// Rotated 90° counter-clockwise (`np.rot90`): the Python reader's view.
    Rot90,
}

/// The raw frame layouts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RawLayout {
    /// SwissSPAD2 half array, 256x512, LSB first.
    SwissSpad2Half,
    /// SwissSPAD2 full array, 512x512, LSB first, zone-interleaved with a flipped bottom half.
    SwissSpad2Full,
    /// SPAD512S, 512x512, MSB first.
    Spad512s(Spad512sOrientation),
}

impl RawLayout {
    /// (H, W) of a decoded frame.
    pub fn dims(&self) -> (usize, usize) {
        match self {
            RawLayout::SwissSpad2Half => (256, 512),
            RawLayout::SwissSpad2Full | RawLayout::Spad512s(_) => (512, 512),
        }
    }

    /// Bytes of one stored frame.
    pub fn frame_bytes(&self) -> usize {
        let (h, w) = self.dims();
        h * w / 8
    }

    /// Decodes one stored frame `raw` (`frame_bytes` long) into packed MSB-first rows `out`
    /// (same length).
    pub fn decode(&self, raw: &[u8], out: &mut [u8]) {
        debug_assert_eq!(raw.len(), self.frame_bytes());
        debug_assert_eq!(out.len(), self.frame_bytes());
        match self {
            RawLayout::SwissSpad2Half => {
                for (o, &r) in out.iter_mut().zip(raw) {
                    *o = r.reverse_bits();
                }
            }
            RawLayout::SwissSpad2Full => {
                const ROW: usize = 64; // output bytes per row
                const ZONE: usize = 16; // bytes per zone (128 columns)
                for (r, stored) in raw.chunks_exact(2 * ROW).enumerate() {
                    for (z, zone) in stored.chunks_exact(ZONE).enumerate() {
                        let k = z / 2;
                        let y = if z & 1 == 0 { r } else { 511 - r };
                        let dst = &mut out[y * ROW + k * ZONE..][..ZONE];
                        for (o, &b) in dst.iter_mut().zip(zone) {
                            *o = b.reverse_bits();
                        }
                    }
                }
            }
            RawLayout::Spad512s(orientation) => {
                const ROW: usize = 64;
                match orientation {
                    Spad512sOrientation::Stored => out.copy_from_slice(raw),
                    Spad512sOrientation::FlipLr => {
                        for (o_row, r_row) in out.chunks_exact_mut(ROW).zip(raw.chunks_exact(ROW)) {
                            for (o, &b) in o_row.iter_mut().zip(r_row.iter().rev()) {
                                *o = b.reverse_bits();
                            }
                        }
                    }
                    Spad512sOrientation::Rot90 => {
                        // out[i][j] = raw[j][511 - i]
                        out.fill(0);
                        for j in 0..512 {
                            let src = &raw[j * ROW..][..ROW];
                            for i in 0..512 {
                                let x = 511 - i;
                                if (src[x / 8] >> (7 - x % 8)) & 1 == 1 {
                                    out[i * ROW + j / 8] |= 0x80 >> (j % 8);
                                }
                            }
                        }
                    }
                }
            }
        }
    }
}

/// Height of the colour SwissSPAD2 frame (rows 2..256 of the half array).
pub const COLORSPAD_ROWS: std::ops::Range<usize> = 2..256;
/// Width of the colour SwissSPAD2 frame (columns 0..496).
pub const COLORSPAD_WIDTH: usize = 496;

/// The colour SwissSPAD2 geometry on a decoded (packed MSB-first) 256x512 half-array frame:
/// rows 2..256, columns 0..496, column blocks 252..256 and 260..264 swapped. Columns
/// 252..256 are the low nibble of byte 31 and 260..264 that of byte 32, so the swap is a
/// nibble exchange. `out` is 254 · 62 bytes.
pub fn colorspad_crop(half: &[u8], out: &mut [u8]) {
    const IN_ROW: usize = 64;
    const OUT_ROW: usize = COLORSPAD_WIDTH / 8;
    debug_assert_eq!(half.len(), 256 * IN_ROW);
    debug_assert_eq!(out.len(), COLORSPAD_ROWS.len() * OUT_ROW);
    for (o_row, y) in out.chunks_exact_mut(OUT_ROW).zip(COLORSPAD_ROWS) {
        o_row.copy_from_slice(&half[y * IN_ROW..][..OUT_ROW]);
        let (a, b) = (o_row[31], o_row[32]);
        o_row[31] = (a & 0xF0) | (b & 0x0F);
        o_row[32] = (b & 0xF0) | (a & 0x0F);
    }
}
