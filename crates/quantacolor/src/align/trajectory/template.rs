//! The template the likelihood is evaluated against: the mean bit rate per frame at every
//! scene point, every frame's sites splatted bilinearly to their reference positions along
//! the current trajectory (the Bernoulli probability `p` of the module documentation).

#![forbid(unsafe_code)]

use super::knots::Trajectory;
use super::sites::{site_bit, RowMap, Sites};
use super::SpanFrames;
use crate::capture::frames::FrameLayout;
use crate::cpu::Isa;
use crate::filters::gaussian_blur;
use ndarray::Array2;
use rayon::prelude::*;

/// The mean bit rate per frame at every scene point of the reference frame (with a margin),
/// from the frames of `frames` splatted bilinearly to their reference positions along `trajectory`;
/// normalized convolution at σ 0.7 px, the global mean where nothing landed nearby. `isa`:
/// the splats' instruction set ([`Splats::add_row`]).
pub(super) fn build_template(
    frames: &SpanFrames<'_>,
    sites: &Sites,
    trajectory: &Trajectory,
    height: usize,
    margin: usize,
    isa: Isa,
) -> Array2<f32> {
    let (th, tw) = (height + 2 * margin, sites.width + 2 * margin);
    let span = frames.span.clone();
    let frames = frames.frames;
    let n = span.end;
    let chunk = span
        .len()
        .div_ceil(rayon::current_num_threads().max(1) * 4)
        .max(1);
    let starts: Vec<usize> = span.step_by(chunk).collect();
    let packed = matches!(frames.layout(), FrameLayout::Packed);
    let (sum, exposure) = starts
        .par_iter()
        .map(|&start| {
            let mut splats = Splats::zeros(th, tw, isa);
            for t in start..(start + chunk).min(n) {
                let camera = trajectory.inverse_camera_at(t as f64);
                for (y, columns) in sites.columns.iter().enumerate() {
                    if columns.is_empty() {
                        continue;
                    }
                    let map = RowMap::new(sites, &camera, y, packed, margin as f64);
                    splats.add_row(frames.raw_row(t, y), y, sites, &map);
                }
            }
            (splats.sum, splats.exposure)
        })
        .reduce(
            || (Array2::zeros((th, tw)), Array2::zeros((th, tw))),
            |(a, b), (c, d)| (a + c, b + d),
        );
    let (num, den) = rayon::join(
        || gaussian_blur(&sum, 0.7),
        || gaussian_blur(&exposure, 0.7),
    );
    let mean = sum.sum() / exposure.sum().max(1.0);
    let floor = 1e-3 * den.iter().copied().fold(0.0f32, f32::max);
    ndarray::Zip::from(&num)
        .and(&den)
        .map_collect(|&n, &d| if d > floor { n / d } else { mean })
}

/// The template's two splat images: detections (`sum`) and trials (`exposure`).
pub(super) struct Splats {
    pub(super) sum: Array2<f32>,
    pub(super) exposure: Array2<f32>,
    /// The instruction set [`Self::add_row`] runs on: generic unless the flat indices fit an
    /// i32 ([`super::x86::splat_row`]).
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    isa: Isa,
}

impl Splats {
    /// Empty images of `height` × `width` pixels, to be splatted on `isa`.
    pub(super) fn zeros(height: usize, width: usize, isa: Isa) -> Splats {
        Splats {
            sum: Array2::zeros((height, width)),
            exposure: Array2::zeros((height, width)),
            isa: if height * width < i32::MAX as usize {
                isa
            } else {
                Isa::generic()
            },
        }
    }

    /// Splats every site of one row of a frame: a trial at each, a detection where its bit is
    /// set; bilinearly, sites outside the images' interior dropped.
    pub(super) fn add_row(&mut self, row: &[u8], y: usize, sites: &Sites, map: &RowMap) {
        #[cfg(target_arch = "x86_64")]
        if self.isa.avx2_fma() {
            super::x86::splat_row(self.isa, self, row, y, &sites.masks[y], map);
            return;
        }
        let (h, w) = self.sum.dim();
        let sum = self.sum.as_slice_mut().expect("standard layout");
        let exposure = self.exposure.as_slice_mut().expect("standard layout");
        for &x in &sites.columns[y] {
            let (py, px) = map.position(y, x as usize);
            if !(py >= 0.0 && px >= 0.0 && py < (h - 1) as f64 && px < (w - 1) as f64) {
                continue;
            }
            let (y0, x0) = (py as usize, px as usize);
            let (fy, fx) = ((py - y0 as f64) as f32, (px - x0 as f64) as f32);
            let weights = [
                (1.0 - fy) * (1.0 - fx),
                (1.0 - fy) * fx,
                fy * (1.0 - fx),
                fy * fx,
            ];
            let bit = site_bit(row, x as usize, map.packed);
            splat_at(exposure, sum, w, y0 * w + x0, weights, bit);
        }
    }
}

/// Adds the bilinear `weights` of one site at the pixels (i, i + 1, i + w, i + w + 1) of
/// `exposure`, and of `sum` if it detected a photon.
#[inline(always)]
pub(super) fn splat_at(
    exposure: &mut [f32],
    sum: &mut [f32],
    w: usize,
    i: usize,
    weights: [f32; 4],
    detected: bool,
) {
    let at = [i, i + 1, i + w, i + w + 1];
    for (&j, &v) in at.iter().zip(&weights) {
        exposure[j] += v;
    }
    if detected {
        for (&j, &v) in at.iter().zip(&weights) {
            sum[j] += v;
        }
    }
}
