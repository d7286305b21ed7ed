//! Line plots of experiment results as 8-bit RGB images, drawn with `plotters` (bitmap backend,
//! no font backend) and labelled with the built-in 3x5 pixel font of the CFA sheet
//! ([`crate::cfa::sheet::draw_text`]), so that no system font is needed and the bytes are the same
//! on every machine.
#![forbid(unsafe_code)]

use crate::cfa::sheet::draw_text;
use crate::error::{Error, Result};
use image::RgbImage;
use ndarray::Array3;
use plotters::prelude::*;
use std::ops::Range;

/// One curve: a name for the legend and `(x, y)` points (non-finite points are skipped).
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// A line plot.
#[derive(Debug, Clone, PartialEq)]
pub struct LinePlot {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
    /// Names of integer x positions 0, 1, 2, ... instead of numeric ticks (categorical x axis).
    pub x_categories: Option<Vec<String>>,
}

const WIDTH: u32 = 720; // px
const HEIGHT: u32 = 440; // px
const MARGIN: [u32; 4] = [44, 24, 56, 80]; // top, right, bottom, left, px
const BACKGROUND: RGBColor = RGBColor(24, 24, 24);
const GRID: RGBColor = RGBColor(70, 70, 70);
const PALETTE: [RGBColor; 6] = [
    RGBColor(230, 90, 80),
    RGBColor(90, 170, 240),
    RGBColor(120, 210, 110),
    RGBColor(240, 190, 70),
    RGBColor(200, 120, 230),
    RGBColor(220, 220, 220),
];
const TICKS: usize = 5; // numeric ticks per axis
const GLYPH_W: u32 = 8; // advance of one character of draw_text, px
const GLYPH_H: u32 = 10; // height of one character of draw_text, px

fn finite_range(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if lo > hi {
        return None;
    }
    let pad = if hi > lo { 0.05 * (hi - lo) } else { 0.5 };
    Some((lo - pad, hi + pad))
}

/// Tick label: up to 4 significant digits, no exponent for the ranges plotted here.
fn tick_label(v: f64) -> String {
    let a = v.abs();
    if a >= 100.0 || a == 0.0 {
        format!("{v:.0}")
    } else if a >= 10.0 {
        format!("{v:.1}")
    } else if a >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

/// Renders `plot` to an (H, W, 3) sRGB image. Errors if no series has a finite point.
pub fn render(plot: &LinePlot) -> Result<Array3<u8>> {
    let all = || {
        plot.series
            .iter()
            .flat_map(|s| s.points.iter())
            .filter(|p| p.0.is_finite() && p.1.is_finite())
    };
    let (x0, x1) = finite_range(all().map(|p| p.0))
        .ok_or_else(|| Error::invalid(format!("plot '{}' has no finite point", plot.title)))?;
    let (y0, y1) = finite_range(all().map(|p| p.1)).expect("x had finite points");
    let mut buf = vec![0u8; (WIDTH * HEIGHT * 3) as usize];
    let ranges = draw_chart(plot, &mut buf, (x0, x1), (y0, y1))?;
    let mut img = RgbImage::from_raw(WIDTH, HEIGHT, buf).expect("buffer sized WIDTH*HEIGHT*3");
    draw_labels(&mut img, plot, &ranges, (x0, x1), (y0, y1));
    draw_legend(&mut img, plot, &ranges);
    let (w, h) = img.dimensions();
    Ok(
        Array3::from_shape_vec((h as usize, w as usize, 3), img.into_raw())
            .expect("RgbImage layout is (H, W, 3)"),
    )
}

/// The plotting area's pixel ranges along x and y.
type PixelRanges = (Range<i32>, Range<i32>);

/// Draws the background, grid and every series of `plot` into `buf` (`WIDTH` x `HEIGHT` RGB)
/// over the data ranges `(x0, x1)`, `(y0, y1)`; returns the plotting area's pixel ranges.
fn draw_chart(
    plot: &LinePlot,
    buf: &mut [u8],
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
) -> Result<PixelRanges> {
    let draw_err = |e: &dyn std::fmt::Display| Error::invalid(format!("plot drawing: {e}"));
    let root = BitMapBackend::with_buffer(buf, (WIDTH, HEIGHT)).into_drawing_area();
    root.fill(&BACKGROUND).map_err(|e| draw_err(&e))?;
    let mut chart = ChartBuilder::on(&root)
        .margin_top(MARGIN[0])
        .margin_right(MARGIN[1])
        .margin_bottom(MARGIN[2])
        .margin_left(MARGIN[3])
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|e| draw_err(&e))?;
    chart
        .configure_mesh()
        .x_labels(0)
        .y_labels(0)
        .bold_line_style(GRID)
        .light_line_style(BACKGROUND)
        .axis_style(GRID)
        .draw()
        .map_err(|e| draw_err(&e))?;
    for (k, s) in plot.series.iter().enumerate() {
        let colour = PALETTE[k % PALETTE.len()];
        let pts: Vec<(f64, f64)> = s
            .points
            .iter()
            .copied()
            .filter(|p| p.0.is_finite() && p.1.is_finite())
            .collect();
        chart
            .draw_series(LineSeries::new(pts.iter().copied(), colour.stroke_width(2)))
            .map_err(|e| draw_err(&e))?;
        chart
            .draw_series(pts.iter().map(|&p| Circle::new(p, 3, colour.filled())))
            .map_err(|e| draw_err(&e))?;
    }
    root.present().map_err(|e| draw_err(&e))?;
    Ok(chart.plotting_area().get_pixel_range())
}

/// Width of `t` in the 3x5 font, px.
fn text_w(t: &str) -> u32 {
    t.chars().count() as u32 * GLYPH_W
}

/// Writes the title, the tick labels of both axes and the axis names onto `img`.
fn draw_labels(
    img: &mut RgbImage,
    plot: &LinePlot,
    (xr, yr): &PixelRanges,
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
) {
    let to_px = |x: f64| xr.start as f64 + (x - x0) / (x1 - x0) * (xr.end - xr.start) as f64;
    let to_py = |y: f64| yr.end as f64 - (y - y0) / (y1 - y0) * (yr.end - yr.start) as f64;
    draw_text(img, 8, 8, &plot.title);
    // x ticks
    let x_ticks: Vec<(f64, String)> = match &plot.x_categories {
        Some(names) => names
            .iter()
            .enumerate()
            .map(|(i, n)| (i as f64, n.clone()))
            .collect(),
        None => (0..TICKS)
            .map(|i| {
                let v = x0 + (x1 - x0) * (i as f64 + 0.5) / TICKS as f64;
                (v, tick_label(v))
            })
            .collect(),
    };
    for (v, t) in &x_ticks {
        let cx = to_px(*v).round() as i64 - i64::from(text_w(t)) / 2;
        draw_text(img, cx.max(0) as u32, yr.end as u32 + 6, t);
    }
    for i in 0..TICKS {
        let v = y0 + (y1 - y0) * (i as f64 + 0.5) / TICKS as f64;
        let t = tick_label(v);
        let cy = to_py(v).round() as i64 - i64::from(GLYPH_H) / 2;
        let x = (xr.start as i64 - 6 - i64::from(text_w(&t))).max(0) as u32;
        draw_text(img, x, cy.max(0) as u32, &t);
    }
    let xl = &plot.x_label;
    let cx = (xr.start + xr.end) / 2 - (text_w(xl) / 2) as i32;
    draw_text(img, cx.max(0) as u32, HEIGHT - 2 * GLYPH_H - 2, xl);
    draw_text(img, 8, 8 + 2 * GLYPH_H, &plot.y_label);
}

/// Draws the legend (a colour swatch and the name of each series), top right inside the
/// plotting area.
fn draw_legend(img: &mut RgbImage, plot: &LinePlot, (xr, yr): &PixelRanges) {
    let longest = plot
        .series
        .iter()
        .map(|s| text_w(&s.name))
        .max()
        .unwrap_or(0);
    let lx = (xr.end as u32).saturating_sub(longest + 30);
    for (k, s) in plot.series.iter().enumerate() {
        let ly = yr.start as u32 + 6 + k as u32 * (GLYPH_H + 6);
        let c = PALETTE[k % PALETTE.len()];
        for dy in 2..8 {
            for dx in 0..16 {
                img.put_pixel(lx + dx, ly + dy, image::Rgb([c.0, c.1, c.2]));
            }
        }
        draw_text(img, lx + 22, ly, &s.name);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_each_series_in_its_colour() {
        let plot = LinePlot {
            title: "T".into(),
            x_label: "X".into(),
            y_label: "Y".into(),
            series: vec![
                Series {
                    name: "a".into(),
                    points: vec![(0.0, 0.0), (1.0, 1.0)],
                },
                Series {
                    name: "b".into(),
                    points: vec![(0.0, 1.0), (1.0, f64::NAN), (2.0, 0.0)],
                },
            ],
            x_categories: None,
        };
        let img = render(&plot).unwrap();
        assert_eq!(img.dim(), (HEIGHT as usize, WIDTH as usize, 3));
        for c in &PALETTE[..2] {
            let n = img
                .outer_iter()
                .flat_map(|row| {
                    row.outer_iter()
                        .filter(|p| p[0] == c.0 && p[1] == c.1 && p[2] == c.2)
                        .map(|_| ())
                        .collect::<Vec<_>>()
                })
                .count();
            assert!(n > 100, "colour {c:?} drawn on only {n} pixels");
        }
        let empty = LinePlot {
            series: vec![],
            ..plot
        };
        assert!(render(&empty).is_err());
    }
}
