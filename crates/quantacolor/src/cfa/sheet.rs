//! The CFA comparison sheet, laid out like paper Fig. 8/9: each pattern as a zoomed tile above
//! its chrominance spectrum, with its aliasing scores ([`super::analysis`]) written underneath
//! in a built-in 3x5 bitmap font (no font files needed).
#![forbid(unsafe_code)]

use super::analysis::{analyze, spectrum_image, AnalysisConfig, SpectralScores};
use super::colorspad::{COLORSPAD_HEIGHT, COLORSPAD_WIDTH};
use super::io::{save_png, save_text, to_rgb_image};
use super::{generate, Cfa, Pattern};
use crate::error::{Error, Result};
use image::{GrayImage, Rgb, RgbImage};
use rayon::prelude::*;
use std::path::Path;

/// Settings of the comparison.
#[derive(Debug, Clone, PartialEq)]
pub struct SheetConfig {
    /// Size `(height, width)` at which generated patterns are analysed. The real `colorspad`
    /// pattern is always analysed on its full 254x496 frame.
    pub size: (usize, usize),
    /// Seed of the pseudorandom patterns.
    pub seed: u64,
    /// Side of the pattern area shown, pixels.
    pub zoom_area: usize,
    /// Magnification of the pattern area.
    pub zoom: usize,
    /// Side of the spectrum picture, pixels.
    pub spectrum_side: usize,
    /// Pattern blocks per sheet row.
    pub columns: usize,
    pub analysis: AnalysisConfig,
}

impl Default for SheetConfig {
    fn default() -> Self {
        SheetConfig {
            size: (256, 256),
            seed: 0,
            zoom_area: 32,
            zoom: 4,
            spectrum_side: 128,
            columns: 5,
            analysis: AnalysisConfig::default(),
        }
    }
}

/// One compared pattern: its CFA, chrominance spectrum picture and scores.
#[derive(Debug, Clone)]
pub struct Entry {
    pub name: String,
    pub cfa: Cfa,
    pub spectrum: GrayImage,
    pub scores: SpectralScores,
}

/// Generates and analyses every pattern of `patterns` (in parallel).
pub fn compare(patterns: &[Pattern], config: &SheetConfig) -> Result<Vec<Entry>> {
    if config.zoom_area == 0 || config.zoom == 0 || config.spectrum_side == 0 {
        return Err(Error::invalid("sheet tile sizes must be positive"));
    }
    patterns
        .par_iter()
        .map(|p| {
            let (h, w) = match p {
                Pattern::Colorspad => (COLORSPAD_HEIGHT, COLORSPAD_WIDTH),
                _ => config.size,
            };
            let cfa = generate(p, h, w, config.seed)?;
            let a = analyze(&cfa, &config.analysis);
            let reference = a.chroma.mean().unwrap_or(0.0);
            Ok(Entry {
                name: p.to_string(),
                spectrum: spectrum_image(&a.chroma, reference),
                scores: a.scores,
                cfa,
            })
        })
        .collect()
}

/// `compare.csv`: one line per entry with its size, channel fractions and scores.
pub fn compare_csv(entries: &[Entry]) -> String {
    let mut csv = String::from(
        "pattern,height,width,r_fraction,g_fraction,b_fraction,w_fraction,chroma_power,\
         baseband_fraction,peak_fraction,peak_to_mean\n",
    );
    for e in entries {
        let f = e.cfa.fractions();
        let s = &e.scores;
        csv.push_str(&format!(
            "{},{},{},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.3}\n",
            e.name,
            e.cfa.height(),
            e.cfa.width(),
            f[0],
            f[1],
            f[2],
            f[3],
            s.chroma_power,
            s.baseband_fraction,
            s.peak_fraction,
            s.peak_to_mean
        ));
    }
    csv
}

/// Pixel layout constants of the sheet.
const MARGIN: u32 = 12; // gap around and between blocks
const TEXT_SCALE: u32 = 2; // font magnification: 3x5 glyphs become 6x10
const LINE: u32 = 6 * TEXT_SCALE; // line height
const BACKGROUND: Rgb<u8> = Rgb([40, 40, 40]);
const INK: Rgb<u8> = Rgb([235, 235, 235]);

/// Renders the sheet: blocks of `name / pattern tile / spectrum / scores`, `config.columns` per
/// row.
pub fn render_sheet(entries: &[Entry], config: &SheetConfig) -> RgbImage {
    let tile = (config.zoom_area * config.zoom) as u32;
    let spec = config.spectrum_side as u32;
    let block_w = tile.max(spec).max(22 * 4 * TEXT_SCALE);
    let block_h = LINE + 4 + tile + 4 + spec + 4 + 4 * LINE;
    let cols = config.columns.max(1) as u32;
    let rows = (entries.len() as u32).div_ceil(cols).max(1);
    let mut img = RgbImage::from_pixel(
        MARGIN + cols * (block_w + MARGIN),
        MARGIN + rows * (block_h + MARGIN),
        BACKGROUND,
    );
    for (k, e) in entries.iter().enumerate() {
        let bx = MARGIN + (k as u32 % cols) * (block_w + MARGIN);
        let mut y = MARGIN + (k as u32 / cols) * (block_h + MARGIN);
        draw_text(&mut img, bx, y, &e.name.to_ascii_uppercase());
        y += LINE + 4;
        // Zoomed pattern area (top-left corner of the CFA).
        let colours = to_rgb_image(&e.cfa);
        for ty in 0..tile {
            for tx in 0..tile {
                let (sy, sx) = (ty / config.zoom as u32, tx / config.zoom as u32);
                if sy < colours.height() && sx < colours.width() {
                    img.put_pixel(bx + tx, y + ty, *colours.get_pixel(sx, sy));
                }
            }
        }
        y += tile + 4;
        let small = resample_max(&e.spectrum, spec, spec);
        for (sx, sy, p) in small.enumerate_pixels() {
            img.put_pixel(bx + sx, y + sy, Rgb([p.0[0]; 3]));
        }
        y += spec + 4;
        let s = &e.scores;
        for line in [
            format!("BASE {:.4}", s.baseband_fraction),
            format!("PEAK {:.4}", s.peak_fraction),
            format!("MAX/MEAN {:.0}", s.peak_to_mean),
            format!("CHROMA {:.4}", s.chroma_power),
        ] {
            draw_text(&mut img, bx, y, &line);
            y += LINE;
        }
    }
    img
}

/// Generates, analyses and writes `dir/compare.png` and `dir/compare.csv` for every pattern of
/// [`Pattern::all`]; returns the entries.
pub fn write_compare(dir: &Path, config: &SheetConfig) -> Result<Vec<Entry>> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let entries = compare(&Pattern::all(), config)?;
    save_png(&render_sheet(&entries, config), dir.join("compare.png"))?;
    save_text(&compare_csv(&entries), dir.join("compare.csv"))?;
    Ok(entries)
}

/// Resizes `img` to `w` x `h`, each output pixel the maximum of the input pixels it covers (so
/// isolated spectral peaks stay visible when shrinking).
pub fn resample_max(img: &GrayImage, w: u32, h: u32) -> GrayImage {
    let (iw, ih) = img.dimensions();
    let span = |d: u32, n: u32, src: u32| {
        let lo = (d as u64 * src as u64 / n as u64) as u32;
        let hi = (((d as u64 + 1) * src as u64 / n as u64) as u32).max(lo + 1);
        lo..hi.min(src)
    };
    GrayImage::from_fn(w, h, |x, y| {
        let mut m = 0u8;
        for sy in span(y, h, ih) {
            for sx in span(x, w, iw) {
                m = m.max(img.get_pixel(sx, sy).0[0]);
            }
        }
        image::Luma([m])
    })
}

/// Draws `text` with its top-left corner at `(x, y)`; characters without a glyph are blank.
pub fn draw_text(img: &mut RgbImage, x: u32, y: u32, text: &str) {
    for (k, ch) in text.chars().enumerate() {
        let rows = glyph(ch);
        let gx = x + k as u32 * 4 * TEXT_SCALE;
        for (r, bits) in rows.iter().enumerate() {
            for c in 0..3u32 {
                if bits & (0b100 >> c) == 0 {
                    continue;
                }
                for dy in 0..TEXT_SCALE {
                    for dx in 0..TEXT_SCALE {
                        let (px, py) = (gx + c * TEXT_SCALE + dx, y + r as u32 * TEXT_SCALE + dy);
                        if px < img.width() && py < img.height() {
                            img.put_pixel(px, py, INK);
                        }
                    }
                }
            }
        }
    }
}

/// 3x5 glyph of `ch` (upper-case letters, digits and a little punctuation), one row per entry,
/// bit 2 = left column.
pub fn glyph(ch: char) -> [u8; 5] {
    match ch.to_ascii_uppercase() {
        'A' => [0b010, 0b101, 0b111, 0b101, 0b101],
        'B' => [0b110, 0b101, 0b110, 0b101, 0b110],
        'C' => [0b011, 0b100, 0b100, 0b100, 0b011],
        'D' => [0b110, 0b101, 0b101, 0b101, 0b110],
        'E' => [0b111, 0b100, 0b110, 0b100, 0b111],
        'F' => [0b111, 0b100, 0b110, 0b100, 0b100],
        'G' => [0b011, 0b100, 0b101, 0b101, 0b011],
        'H' => [0b101, 0b101, 0b111, 0b101, 0b101],
        'I' => [0b111, 0b010, 0b010, 0b010, 0b111],
        'J' => [0b001, 0b001, 0b001, 0b101, 0b010],
        'K' => [0b101, 0b101, 0b110, 0b101, 0b101],
        'L' => [0b100, 0b100, 0b100, 0b100, 0b111],
        'M' => [0b101, 0b111, 0b111, 0b101, 0b101],
        'N' => [0b110, 0b101, 0b101, 0b101, 0b101],
        'O' => [0b010, 0b101, 0b101, 0b101, 0b010],
        'P' => [0b110, 0b101, 0b110, 0b100, 0b100],
        'Q' => [0b010, 0b101, 0b101, 0b110, 0b011],
        'R' => [0b110, 0b101, 0b110, 0b101, 0b101],
        'S' => [0b011, 0b100, 0b010, 0b001, 0b110],
        'T' => [0b111, 0b010, 0b010, 0b010, 0b010],
        'U' => [0b101, 0b101, 0b101, 0b101, 0b111],
        'V' => [0b101, 0b101, 0b101, 0b101, 0b010],
        'W' => [0b101, 0b101, 0b111, 0b111, 0b101],
        'X' => [0b101, 0b101, 0b010, 0b101, 0b101],
        'Y' => [0b101, 0b101, 0b010, 0b010, 0b010],
        'Z' => [0b111, 0b001, 0b010, 0b100, 0b111],
        '0' => [0b111, 0b101, 0b101, 0b101, 0b111],
        '1' => [0b010, 0b110, 0b010, 0b010, 0b111],
        '2' => [0b110, 0b001, 0b010, 0b100, 0b111],
        '3' => [0b110, 0b001, 0b010, 0b001, 0b110],
        '4' => [0b101, 0b101, 0b111, 0b001, 0b001],
        '5' => [0b111, 0b100, 0b110, 0b001, 0b110],
        '6' => [0b011, 0b100, 0b110, 0b101, 0b010],
        '7' => [0b111, 0b001, 0b010, 0b010, 0b010],
        '8' => [0b010, 0b101, 0b010, 0b101, 0b010],
        '9' => [0b010, 0b101, 0b011, 0b001, 0b110],
        '.' => [0b000, 0b000, 0b000, 0b000, 0b010],
        '-' => [0b000, 0b000, 0b111, 0b000, 0b000],
        ':' => [0b000, 0b010, 0b000, 0b010, 0b000],
        '/' => [0b001, 0b001, 0b010, 0b100, 0b100],
        '%' => [0b101, 0b001, 0b010, 0b100, 0b101],
        '=' => [0b000, 0b111, 0b000, 0b111, 0b000],
        '(' => [0b001, 0b010, 0b010, 0b010, 0b001],
        ')' => [0b100, 0b010, 0b010, 0b010, 0b100],
        '_' => [0b000, 0b000, 0b000, 0b000, 0b111],
        _ => [0; 5],
    }
}
