//! Scenes: linear RGB radiance to be imaged, from image files or built in, and their rasters.
//!
//! A scene is fitted to the sensor plus a motion margin ("cover" fit, centred) and stored as a
//! [`SceneRaster`]: planes on a regular grid of at most half a footprint spacing (procedural
//! scenes are rasterised at exactly 2 samples per footprint with 3x3 supersampling per raster
//! cell), pre-filtered by the footprint (a box one footprint wide), and then sampled bilinearly
//! at the sub-pixel positions the motion gives. Frames and ground truth use the same sampler.
//!
//! The footprint is one sensor pixel for ordinary captures. With pixel supersampling s (see
//! [`super::SimulationConfig::pixel_supersampling`]) it is 1/s pixel: the raster then keeps the
//! scene's detail finer than a pixel, and the renderer integrates each pixel over its s x s
//! sub-pixel samples instead.
#![deny(unsafe_code)]

use super::chart;
use crate::color::srgb::srgb_to_linear;
use crate::error::{Error, Result};
use ndarray::{s, Array2, Array3, Axis};
use rayon::prelude::*;
use std::path::Path;

/// A scene, in linear RGB (arbitrary scale: the flux setting fixes the light level).
#[derive(Debug, Clone, PartialEq)]
pub enum Scene {
    /// A linear RGB image (H, W, 3), from a file or built in memory.
    Image { image: Array3<f32>, name: String },
    /// The procedural test chart (`builtin:chart`, or `builtin:chart-hdr` with a light source).
    Chart { hdr: bool },
    /// A uniform scene of one linear colour (`builtin:flat`, grey 0.5).
    Constant([f32; 3]),
}

impl Scene {
    /// Parses a scene argument: `builtin:chart`, `builtin:chart-hdr`, `builtin:flat`, or the path
    /// of a PNG/JPEG (sRGB, decoded to linear) or EXR (scene-linear) image.
    pub fn from_spec(spec: &str) -> Result<Scene> {
        match spec {
            "builtin:chart" => Ok(Scene::Chart { hdr: false }),
            "builtin:chart-hdr" => Ok(Scene::Chart { hdr: true }),
            "builtin:flat" => Ok(Scene::Constant([0.5; 3])),
            s if s.starts_with("builtin:") => Err(Error::invalid(format!(
                "unknown built-in scene '{s}' (expected builtin:chart, builtin:chart-hdr or \
                 builtin:flat)"
            ))),
            path => Scene::load(path),
        }
    }

    /// Loads an image file: EXR values are taken as scene-linear; 8/16-bit images are sRGB and
    /// decoded with the sRGB transfer function. Alpha is dropped, grey is replicated.
    pub fn load(path: impl AsRef<Path>) -> Result<Scene> {
        let path = path.as_ref();
        let reader = image::ImageReader::open(path)
            .map_err(|e| Error::io(path, e))?
            .with_guessed_format()
            .map_err(|e| Error::io(path, e))?;
        let linear = matches!(reader.format(), Some(image::ImageFormat::OpenExr));
        let decoded = reader
            .decode()
            .map_err(|e| Error::format(path, format!("cannot decode image: {e}")))?;
        let rgb = decoded.to_rgb32f();
        let (w, h) = (rgb.width() as usize, rgb.height() as usize);
        let raw = rgb.into_raw();
        let image = Array3::from_shape_vec((h, w, 3), raw)
            .map_err(|e| Error::format(path, format!("unexpected image layout: {e}")))?;
        let image = if linear {
            image.mapv(|v| if v.is_finite() { v.max(0.0) } else { 0.0 })
        } else {
            image.mapv(srgb_to_linear)
        };
        Scene::from_linear(image, path.display().to_string())
            .map_err(|e| Error::format(path, e.to_string()))
    }

    /// Wraps a linear RGB image (H, W, 3) with non-negative finite values.
    pub fn from_linear(image: Array3<f32>, name: impl Into<String>) -> Result<Scene> {
        let (h, w, c) = image.dim();
        if c != 3 || h < 2 || w < 2 {
            return Err(Error::invalid(format!(
                "scene image must be (H >= 2, W >= 2, 3), found ({h}, {w}, {c})"
            )));
        }
        if image.iter().any(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(Error::invalid(
                "scene image holds negative or non-finite values",
            ));
        }
        Ok(Scene::Image {
            image,
            name: name.into(),
        })
    }

    /// A short name for metadata and messages.
    pub fn name(&self) -> String {
        match self {
            Scene::Image { name, .. } => name.clone(),
            Scene::Chart { hdr: false } => "builtin:chart".into(),
            Scene::Chart { hdr: true } => "builtin:chart-hdr".into(),
            Scene::Constant(c) => format!("constant {c:?}"),
        }
    }

    /// Rasterises the scene over a `height` x `width` sensor plus `margin` pixels on every side,
    /// pre-filtered by the pixel footprint.
    pub fn rasterise(&self, height: usize, width: usize, margin: f64) -> SceneRaster {
        self.rasterise_with_footprint(height, width, margin, 1.0)
    }

    /// As [`Scene::rasterise`], pre-filtered by a box `footprint` sensor pixels wide (1 = the
    /// pixel; 1/s for a sensor that integrates s x s sub-pixel samples), on a grid of at most
    /// half a footprint spacing where the scene has that much detail.
    pub fn rasterise_with_footprint(
        &self,
        height: usize,
        width: usize,
        margin: f64,
        footprint: f64,
    ) -> SceneRaster {
        let footprint = if footprint > 0.0 && footprint <= 1.0 {
            footprint
        } else {
            1.0
        };
        let centre = [(height as f64 - 1.0) / 2.0, (width as f64 - 1.0) / 2.0];
        match self {
            Scene::Constant(c) => SceneRaster {
                planes: Array3::from_shape_fn((3, 2, 2), |(k, _, _)| c[k]),
                origin: [0.0, 0.0],
                step: 1.0,
            },
            Scene::Chart { hdr } => {
                let hdr = *hdr;
                let step = 0.5 * footprint;
                let origin = [-margin - 1.0, -margin - 1.0];
                let hr = ((height as f64 + 2.0 * margin + 2.0) / step).ceil() as usize + 1;
                let wr = ((width as f64 + 2.0 * margin + 2.0) / step).ceil() as usize + 1;
                let planes = supersample(hr, wr, origin, step, |y, x| {
                    chart::chart_value(y, x, height, width, hdr)
                });
                SceneRaster::new_filtered_footprint(planes, origin, step, footprint)
            }
            Scene::Image { image, .. } => {
                let (hi, wi, _) = image.dim();
                let (hs, ws) = (height as f64 + 2.0 * margin, width as f64 + 2.0 * margin);
                let scale = (hi as f64 / hs).min(wi as f64 / ws); // image px per sensor px
                                                                  // Box-downsample while keeping at least 2 image samples per footprint.
                let factor = ((scale * footprint / 2.0).floor() as usize).max(1);
                let planes = box_downsample(image, factor);
                let scale = scale / factor as f64;
                let (hp, wp) = (planes.dim().1, planes.dim().2);
                let step = 1.0 / scale;
                let origin = [
                    centre[0] - (hp as f64 - 1.0) / 2.0 * step,
                    centre[1] - (wp as f64 - 1.0) / 2.0 * step,
                ];
                SceneRaster::new_filtered_footprint(planes, origin, step, footprint)
            }
        }
    }
}

/// Rasterises `f(y, x) -> [channels]` on an `hr` x `wr` grid, averaging 3x3 samples per cell.
pub(crate) fn supersample<const C: usize>(
    hr: usize,
    wr: usize,
    origin: [f64; 2],
    step: f64,
    f: impl Fn(f64, f64) -> [f32; C] + Sync,
) -> Array3<f32> {
    let mut planes = Array3::<f32>::zeros((C, hr, wr));
    let rows: Vec<Vec<[f32; C]>> = (0..hr)
        .into_par_iter()
        .map(|i| {
            (0..wr)
                .map(|j| {
                    let mut acc = [0.0f32; C];
                    for a in 0..3 {
                        for b in 0..3 {
                            let y = origin[0] + (i as f64 + (a as f64 - 1.0) / 3.0) * step;
                            let x = origin[1] + (j as f64 + (b as f64 - 1.0) / 3.0) * step;
                            let v = f(y, x);
                            for k in 0..C {
                                acc[k] += v[k] / 9.0;
                            }
                        }
                    }
                    acc
                })
                .collect()
        })
        .collect();
    for (i, row) in rows.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            for k in 0..C {
                planes[[k, i, j]] = v[k];
            }
        }
    }
    planes
}

/// (H, W, 3) image to (3, H/f, W/f) planes averaged over f x f blocks.
fn box_downsample(image: &Array3<f32>, f: usize) -> Array3<f32> {
    let (h, w, _) = image.dim();
    let (ho, wo) = ((h / f).max(1), (w / f).max(1));
    let norm = 1.0 / (f * f) as f32;
    Array3::from_shape_fn((3, ho, wo), |(k, i, j)| {
        image
            .slice(s![
                i * f..((i + 1) * f).min(h),
                j * f..((j + 1) * f).min(w),
                k
            ])
            .sum()
            * norm
    })
}

/// Weights of a box of `width` samples centred on a sample, with partial end taps.
fn box_taps(width: f64) -> Vec<f32> {
    let half = width / 2.0;
    let reach = (half - 0.5).ceil().max(0.0) as i64;
    let taps: Vec<f64> = (-reach..=reach)
        .map(|k| {
            let (lo, hi) = ((k as f64 - 0.5).max(-half), (k as f64 + 0.5).min(half));
            (hi - lo).max(0.0)
        })
        .collect();
    let sum: f64 = taps.iter().sum();
    taps.iter().map(|t| (t / sum) as f32).collect()
}

/// Convolves each row (axis 1) of `plane` with `taps`, clamping at the edges.
fn filter_rows(plane: &mut Array2<f32>, taps: &[f32]) {
    let r = (taps.len() / 2) as i64;
    plane
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .for_each(|mut row| {
            let src = row.to_vec();
            let n = src.len() as i64;
            for (j, out) in row.iter_mut().enumerate() {
                *out = taps
                    .iter()
                    .enumerate()
                    .map(|(k, &t)| t * src[(j as i64 + k as i64 - r).clamp(0, n - 1) as usize])
                    .sum();
            }
        });
}

/// Scene planes on a regular grid: plane `k` at raster index `(i, j)` is the scene at
/// reference-frame sensor position `origin + (i, j) · step`.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneRaster {
    /// (channels, Hr, Wr).
    pub planes: Array3<f32>,
    /// Sensor position (y, x) of raster sample (0, 0).
    pub origin: [f64; 2],
    /// Sensor pixels per raster sample.
    pub step: f64,
}

impl SceneRaster {
    /// Wraps `planes` after filtering them by a one-sensor-pixel box (the pixel footprint).
    pub fn new_filtered(planes: Array3<f32>, origin: [f64; 2], step: f64) -> SceneRaster {
        Self::new_filtered_footprint(planes, origin, step, 1.0)
    }

    /// Wraps `planes` after filtering them by a box `footprint` sensor pixels wide.
    pub fn new_filtered_footprint(
        mut planes: Array3<f32>,
        origin: [f64; 2],
        step: f64,
        footprint: f64,
    ) -> SceneRaster {
        let taps = box_taps(footprint / step);
        for mut plane in planes.outer_iter_mut() {
            let mut owned = plane.to_owned();
            filter_rows(&mut owned, &taps);
            let mut t = owned.reversed_axes().as_standard_layout().to_owned();
            filter_rows(&mut t, &taps);
            plane.assign(&t.reversed_axes());
        }
        SceneRaster {
            planes: planes.as_standard_layout().to_owned(),
            origin,
            step,
        }
    }

    /// Number of planes.
    pub fn channels(&self) -> usize {
        self.planes.dim().0
    }

    /// Bilinear sample of plane `k` at sensor position `p`; positions beyond the raster take the
    /// edge value.
    #[inline]
    pub fn sample(&self, k: usize, p: [f64; 2]) -> f32 {
        let (_, hr, wr) = self.planes.dim();
        let ry = ((p[0] - self.origin[0]) / self.step).clamp(0.0, (hr - 1) as f64);
        let rx = ((p[1] - self.origin[1]) / self.step).clamp(0.0, (wr - 1) as f64);
        let (i, j) = ((ry as usize).min(hr - 2), (rx as usize).min(wr - 2));
        let (fy, fx) = ((ry - i as f64) as f32, (rx - j as f64) as f32);
        // Flat indexing into the standard-layout planes: this is the renderer's inner loop.
        let data = self
            .planes
            .as_slice()
            .expect("raster planes are contiguous");
        let at = (k * hr + i) * wr + j;
        let (a, b) = (data[at], data[at + 1]);
        let (c, d) = (data[at + wr], data[at + wr + 1]);
        let top = a + fx * (b - a);
        let bottom = c + fx * (d - c);
        top + fy * (bottom - top)
    }

    /// Whether `p` lies inside the raster's extent.
    #[inline]
    pub fn contains(&self, p: [f64; 2]) -> bool {
        let (_, hr, wr) = self.planes.dim();
        let ry = (p[0] - self.origin[0]) / self.step;
        let rx = (p[1] - self.origin[1]) / self.step;
        ry >= 0.0 && rx >= 0.0 && ry <= (hr - 1) as f64 && rx <= (wr - 1) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_taps_cover_the_width() {
        assert_eq!(box_taps(1.0), vec![1.0]);
        let t = box_taps(2.0);
        assert_eq!(t.len(), 3);
        assert!((t[0] - 0.25).abs() < 1e-6 && (t[1] - 0.5).abs() < 1e-6);
        let t = box_taps(1.5);
        assert!((t.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        assert!((t[0] - 0.25 / 1.5).abs() < 1e-6);
    }

    #[test]
    fn bilinear_sampling_reproduces_a_ramp() {
        // A ramp is invariant under the box filter away from the edges, and bilinear is exact.
        let planes = Array3::from_shape_fn((1, 20, 20), |(_, i, j)| (i + 2 * j) as f32);
        let r = SceneRaster::new_filtered(planes, [-2.0, -3.0], 0.5);
        let p = [1.3, 2.7];
        let expected = (p[0] + 2.0) / 0.5 + 2.0 * (p[1] + 3.0) / 0.5;
        assert!((r.sample(0, p) as f64 - expected).abs() < 1e-4);
    }
}
