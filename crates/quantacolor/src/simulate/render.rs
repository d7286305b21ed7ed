//! Frame rendering: the per-pixel photon flux λ of frame `t` (paper Eq. 2–3) through the motion
//! and the scene raster, and the sensor readouts (SPAD Bernoulli, jot threshold, CMOS counts).
//!
//! Frames are rendered in parallel, one frame per rayon task, each with its own random stream
//! seeded from `(seed, t)`, so the output does not depend on the thread count.

use super::motion::Motion;
use super::scene::SceneRaster;
use super::sensor::JotReadout;
use crate::cfa::Cfa;
use crate::progress::Progress;
use ndarray::{Array2, Array3, ArrayViewMut2, ArrayViewMut3, Axis};
use rand::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Poisson, StandardNormal};
use rayon::prelude::*;

/// SplitMix64 finaliser: decorrelates nearby seeds.
pub(crate) fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Random stream of frame `t`.
pub(crate) fn frame_rng(seed: u64, t: usize) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(mix(seed ^ mix(0x6672_616d_6500 ^ t as u64)))
}

/// Flux of every channel of a scene through the motion.
///
/// `background` holds four planes (R, G, B, W) in detections per frame; `object` (present for
/// the object motion) holds R, G, B, W premultiplied by coverage, then the coverage, on a raster
/// centred on the object's centre.
///
/// With `supersampling` s > 1 a pixel's λ is the mean over s x s sample points at offsets
/// ((i + ½)/s − ½, (j + ½)/s − ½) pixel from its centre (the rasters then hold the scene
/// pre-filtered by a 1/s-pixel box, so the mean is the pixel-area integral).
pub(crate) struct FluxField<'a> {
    pub background: &'a SceneRaster,
    pub object: Option<&'a SceneRaster>,
    pub motion: &'a Motion,
    pub supersampling: usize,
}

/// Sub-pixel sample offsets ((i + ½)/s − ½ for i in 0..s), pixels.
pub(crate) fn sub_pixel_offsets(s: usize) -> Vec<f64> {
    let s = s.max(1);
    (0..s).map(|i| (i as f64 + 0.5) / s as f64 - 0.5).collect()
}

impl FluxField<'_> {
    /// λ of channel `k` (0..4 = R, G, B, W) seen at pixel `(y, x)` of frame `t`.
    #[inline]
    fn at(&self, t: usize, k: usize, p: [f64; 2]) -> f32 {
        let bg = self.background.sample(k, p);
        match (self.object, &self.motion.object) {
            (Some(obj), Some(track)) => {
                let o = [
                    p[0] - track.center[0] - track.dy[t],
                    p[1] - track.center[1] - track.dx[t],
                ];
                if obj.contains(o) {
                    let alpha = obj.sample(4, o);
                    obj.sample(k, o) + (1.0 - alpha) * bg
                } else {
                    bg
                }
            }
            _ => bg,
        }
    }

    /// λ of channel `k` at sensor position `(yf, xf)` of frame `t`, integrated over the pixel's
    /// sub-pixel samples when `supersampling` > 1.
    #[inline]
    fn pixel(
        &self,
        t: usize,
        k: usize,
        (a, b): ([[f64; 2]; 2], [f64; 2]),
        yf: f64,
        xf: f64,
        offsets: &[f64],
    ) -> f32 {
        let map = |y: f64, x: f64| {
            [
                a[0][0] * y + a[0][1] * x + b[0],
                a[1][0] * y + a[1][1] * x + b[1],
            ]
        };
        if offsets.len() <= 1 {
            return self.at(t, k, map(yf, xf));
        }
        let mut sum = 0.0f32;
        for &oy in offsets {
            for &ox in offsets {
                sum += self.at(t, k, map(yf + oy, xf + ox));
            }
        }
        sum / (offsets.len() * offsets.len()) as f32
    }

    /// λ of every pixel of row `y` of frame `t`, each through its own CFA channel.
    pub fn row(&self, t: usize, y: usize, cfa_row: &[u8], out: &mut [f32]) {
        let affine = self.motion.inverse_affine(t);
        let offsets = sub_pixel_offsets(self.supersampling);
        let yf = y as f64;
        for (x, (o, &code)) in out.iter_mut().zip(cfa_row).enumerate() {
            *o = self.pixel(t, code as usize, affine, yf, x as f64, &offsets);
        }
    }

    /// Ground truth: λ of R, G, B at every pixel of frame `t` (integrated over the pixel's
    /// sub-pixel samples like the frames), (H, W, 3).
    pub fn rgb(&self, t: usize, height: usize, width: usize) -> Array3<f32> {
        self.rgb_grid(t, height, width, 1, &sub_pixel_offsets(self.supersampling))
    }

    /// High-resolution ground truth at `scale` s: pixel (Y, X) of the (s·H, s·W, 3) result is
    /// λ of R, G, B at sensor position ((Y + ½)/s − ½, (X + ½)/s − ½) of frame `t` (the merge's
    /// scale-s output grid), from the rasters as they are (pre-filtered by the footprint set by
    /// `supersampling`, so with `scale == supersampling` each value is the mean over its own
    /// 1/s-pixel area, and the s x s box mean of the result is [`FluxField::rgb`]).
    pub fn rgb_hr(&self, t: usize, height: usize, width: usize, scale: usize) -> Array3<f32> {
        self.rgb_grid(t, height * scale, width * scale, scale, &[0.0])
    }

    /// λ of R, G, B on an `hs` x `ws` grid whose pixel (Y, X) sits at sensor position
    /// ((Y + ½)/s − ½, (X + ½)/s − ½), averaged over `offsets` x `offsets` around it.
    fn rgb_grid(&self, t: usize, hs: usize, ws: usize, s: usize, offsets: &[f64]) -> Array3<f32> {
        let mut gt = Array3::<f32>::zeros((hs, ws, 3));
        let affine = self.motion.inverse_affine(t);
        let grid = |i: usize| (i as f64 + 0.5) / s as f64 - 0.5;
        gt.axis_iter_mut(Axis(0))
            .into_par_iter()
            .enumerate()
            .for_each(|(y, mut row)| {
                for x in 0..ws {
                    for k in 0..3 {
                        row[[x, k]] = self.pixel(t, k, affine, grid(y), grid(x), offsets);
                    }
                }
            });
        gt
    }
}

/// How a binary sensor turns λ + d into a bit.
#[derive(Debug, Clone, Copy)]
pub(crate) enum BinaryReadout {
    /// P(1) = 1 − exp(−(λ + d)) (paper Eq. 2).
    Spad,
    Jot(JotReadout),
}

const TWO_POW_32: f32 = 4_294_967_296.0;

/// The frames a renderer draws: the flux `field` seen through `cfa`, plus `dark_per_frame`
/// dark detections per frame of every pixel; `frames` of them, frame `t` drawn from the random
/// stream [`frame_rng`]`(seed, t)`.
pub(crate) struct FrameJob<'a> {
    pub field: &'a FluxField<'a>,
    pub cfa: &'a Cfa,
    pub dark_per_frame: &'a Array2<f32>,
    pub frames: usize,
    pub seed: u64,
}

/// Renders the job's frames as binary frames, bit-packed (T, H, ceil(W/8)) MSB first.
pub(crate) fn render_binary(
    job: &FrameJob<'_>,
    readout: BinaryReadout,
    progress: &dyn Progress,
) -> Array3<u8> {
    let (h, w) = (job.cfa.height(), job.cfa.width());
    let mut packed = Array3::<u8>::zeros((job.frames, h, w.div_ceil(8)));
    progress.start(super::PROGRESS_BINARY, job.frames as u64);
    render_binary_into(job, readout, 0, packed.view_mut(), progress);
    progress.finish();
    packed
}

/// Renders frames `first..first + n` of the job into `out`, zeroed bit-packed
/// (n, H, ceil(W/8)), in parallel (one frame per task), advancing `progress` by one per frame.
pub(crate) fn render_binary_into(
    job: &FrameJob<'_>,
    readout: BinaryReadout,
    first: usize,
    mut out: ArrayViewMut3<'_, u8>,
    progress: &dyn Progress,
) {
    let FrameJob {
        field,
        cfa,
        dark_per_frame,
        seed,
        ..
    } = *job;
    let (h, w) = (cfa.height(), cfa.width());
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(i, mut frame): (usize, ArrayViewMut2<u8>)| {
            let t = first + i;
            let mut rng = frame_rng(seed, t);
            let mut lambda = vec![0.0f32; w];
            for y in 0..h {
                let cfa_row = cfa.codes().row(y);
                let cfa_row = cfa_row.as_slice().expect("CFA rows are contiguous");
                field.row(t, y, cfa_row, &mut lambda);
                let dark = dark_per_frame.row(y);
                let mut out = frame.row_mut(y);
                for (x, (&l, &d)) in lambda.iter().zip(dark.iter()).enumerate() {
                    let mean = l + d;
                    let p = match readout {
                        BinaryReadout::Spad => -(-mean).exp_m1(),
                        BinaryReadout::Jot(j) => j.one_probability(mean as f64) as f32,
                    };
                    if (rng.next_u32() as f32) < p * TWO_POW_32 {
                        out[x / 8] |= 0x80 >> (x % 8);
                    }
                }
            }
            progress.advance(1);
        });
}

/// Renders the job's frames as CMOS frames: Poisson photoelectrons plus Gaussian read noise,
/// divided by the gain, offset by the black level, rounded and clipped to
/// `0..2^bit_depth − 1`, (T, H, W) uint16 (the Gaussian–Poisson model of
/// [`crate::model::GaussianPoisson`]).
pub(crate) fn render_cmos(
    job: &FrameJob<'_>,
    sensor: &super::SensorModel,
    progress: &dyn Progress,
) -> Array3<u16> {
    let (h, w) = (job.cfa.height(), job.cfa.width());
    let mut out = Array3::<u16>::zeros((job.frames, h, w));
    progress.start(super::PROGRESS_CMOS, job.frames as u64);
    render_cmos_into(job, sensor, 0, out.view_mut(), progress);
    progress.finish();
    out
}

/// Renders frames `first..first + n` of the job as CMOS frames (see [`render_cmos`]) into
/// `out`, (n, H, W), in parallel (one frame per task), advancing `progress` by one per frame.
pub(crate) fn render_cmos_into(
    job: &FrameJob<'_>,
    sensor: &super::SensorModel,
    first: usize,
    mut out: ArrayViewMut3<'_, u16>,
    progress: &dyn Progress,
) {
    let FrameJob {
        field,
        cfa,
        dark_per_frame,
        seed,
        ..
    } = *job;
    let (h, w) = (cfa.height(), cfa.width());
    let max = ((1u32 << sensor.bit_depth.min(16)) - 1) as f64;
    let (read_noise_e, gain, black) = (
        sensor.read_noise_e,
        sensor.gain_e_per_dn,
        sensor.black_level_dn,
    );
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(i, mut frame): (usize, ArrayViewMut2<u16>)| {
            let t = first + i;
            let mut rng = frame_rng(seed, t);
            let mut lambda = vec![0.0f32; w];
            for y in 0..h {
                let cfa_row = cfa.codes().row(y);
                let cfa_row = cfa_row.as_slice().expect("CFA rows are contiguous");
                field.row(t, y, cfa_row, &mut lambda);
                for x in 0..w {
                    let mean = (lambda[x] + dark_per_frame[[y, x]]) as f64;
                    let electrons = if mean > 0.0 {
                        Poisson::new(mean)
                            .map(|d| d.sample(&mut rng))
                            .unwrap_or(0.0)
                    } else {
                        0.0
                    };
                    let noise: f64 = StandardNormal.sample(&mut rng);
                    let dn = black + (electrons + read_noise_e * noise) / gain;
                    frame[[y, x]] = dn.round().clamp(0.0, max) as u16;
                }
            }
            progress.advance(1);
        });
}
