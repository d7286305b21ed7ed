//! Synthetic scenes and sub-blocks with known truth for the merge tests.
#![allow(dead_code)]

use ndarray::{Array2, Array3};
use quantacolor::align::{grey_image, GreyMethod};
use quantacolor::cfa::{Cfa, Channel};
use quantacolor::merge::SubBlockRobustness;
use quantacolor::merge::{SubBlock, SubBlockMotion};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Binomial, Distribution};
use std::f64::consts::PI;

pub const W_WEIGHTS: [f64; 3] = [1.0, 1.0, 1.0];

/// A colour scene: λ (detections per frame) of R, G, B at a real reference position.
pub type Scene = dyn Fn(f64, f64) -> [f64; 3] + Sync;

/// Textured colour scene: oriented gratings of 6–10 px period over a smooth colour ramp.
pub fn textured(y: f64, x: f64) -> [f64; 3] {
    let t1 = (2.0 * PI * (0.9 * x + 0.4 * y) / 7.0).sin();
    let t2 = (2.0 * PI * (y - 0.3 * x) / 9.0).cos();
    let t3 = (2.0 * PI * (x + y) / 10.0).sin();
    [
        0.12 * (1.0 + 0.6 * t1) * (1.0 + 0.004 * x),
        0.20 * (1.0 + 0.5 * t2),
        0.15 * (1.0 + 0.5 * t3) * (1.0 + 0.004 * y),
    ]
}

/// Mean bit rate of a pixel of `channel` seeing `rgb` (plus dark counts).
pub fn bit_rate(rgb: [f64; 3], channel: Channel, dark: f64) -> f64 {
    let lambda = match channel {
        Channel::W => rgb.iter().zip(W_WEIGHTS).map(|(v, w)| v * w).sum::<f64>(),
        c => rgb[c.index()],
    };
    1.0 - (-(lambda + dark)).exp()
}

/// Counts of a sub-block of `frames` binary frames: pixel q sees the scene at `to_ref(q)`.
pub fn simulate_counts(
    scene: &Scene,
    cfa: &Cfa,
    frames: u32,
    dark: f64,
    to_ref: impl Fn(f64, f64) -> (f64, f64),
    rng: &mut ChaCha8Rng,
) -> Array2<u32> {
    let (h, w) = (cfa.height(), cfa.width());
    Array2::from_shape_fn((h, w), |(y, x)| {
        let (ry, rx) = to_ref(y as f64, x as f64);
        let p = bit_rate(scene(ry, rx), cfa.channel(y, x), dark);
        Binomial::new(frames as u64, p).unwrap().sample(rng) as u32
    })
}

/// Motion of one sub-block: rotation by `theta` about the image centre, then translation.
#[derive(Clone, Copy, Debug)]
pub struct Motion {
    pub dy: f64,
    pub dx: f64,
    pub theta: f64,
}

impl Motion {
    pub fn random(rng: &mut ChaCha8Rng, max_shift: f64, max_theta: f64) -> Motion {
        Motion {
            dy: rng.gen_range(-max_shift..max_shift),
            dx: rng.gen_range(-max_shift..max_shift),
            theta: rng.gen_range(-max_theta..=max_theta),
        }
    }
    /// Reference position p -> block position p + flow(p).
    pub fn forward(&self, h: usize, w: usize, y: f64, x: f64) -> (f64, f64) {
        let (cy, cx) = ((h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0);
        let (s, c) = self.theta.sin_cos();
        let (ry, rx) = (y - cy, x - cx);
        (
            cy + c * ry + s * rx + self.dy,
            cx - s * ry + c * rx + self.dx,
        )
    }
    /// Block position q -> reference position.
    pub fn inverse(&self, h: usize, w: usize, y: f64, x: f64) -> (f64, f64) {
        let (cy, cx) = ((h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0);
        let (s, c) = self.theta.sin_cos();
        let (ry, rx) = (y - self.dy - cy, x - self.dx - cx);
        (cy + c * ry - s * rx, cx + s * ry + c * rx)
    }
    /// The same motion as the merge's affine form: reference position = matrix·q + offset.
    pub fn reference_map(&self, h: usize, w: usize) -> SubBlockMotion {
        let (cy, cx) = ((h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0);
        let (s, c) = self.theta.sin_cos();
        SubBlockMotion::Affine {
            matrix: [[c, -s], [s, c]],
            offset: [
                cy - c * (self.dy + cy) + s * (self.dx + cx),
                cx - s * (self.dy + cy) - c * (self.dx + cx),
            ],
        }
    }
    /// Dense (H, W, 2) flow.
    pub fn flow(&self, h: usize, w: usize) -> Array3<f32> {
        Array3::from_shape_fn((h, w, 2), |(y, x, i)| {
            let (fy, fx) = self.forward(h, w, y as f64, x as f64);
            (if i == 0 { fy - y as f64 } else { fx - x as f64 }) as f32
        })
    }
}

/// Sub-blocks with the given motions, each with its own `Block(k)` robustness index.
pub fn sub_blocks(
    scene: &Scene,
    cfa: &Cfa,
    motions: &[Motion],
    frames: u32,
    dark: f64,
    rng: &mut ChaCha8Rng,
) -> Vec<SubBlock> {
    let (h, w) = (cfa.height(), cfa.width());
    motions
        .iter()
        .enumerate()
        .map(|(k, m)| SubBlock {
            counts: simulate_counts(scene, cfa, frames, dark, |y, x| m.inverse(h, w, y, x), rng),
            frames,
            flow: m.flow(h, w).into(),
            robustness: SubBlockRobustness::Block(k),
        })
        .collect()
}

/// Truth (H·s, W·s, 3) on an output grid of `scale`.
pub fn truth(scene: &Scene, h: usize, w: usize, scale: usize) -> Array3<f32> {
    let s = scale as f64;
    Array3::from_shape_fn((h * scale, w * scale, 3), |(y, x, c)| {
        let (ry, rx) = ((y as f64 + 0.5) / s - 0.5, (x as f64 + 0.5) / s - 0.5);
        scene(ry, rx)[c] as f32
    })
}

/// PSNR (dB) of `est` against `truth` (H, W, 3), ignoring `border` pixels at each edge; peak =
/// the truth's maximum.
pub fn psnr(est: &Array3<f32>, truth: &Array3<f32>, border: usize) -> f64 {
    let (h, w, _) = truth.dim();
    let mut se = 0.0;
    let mut n = 0.0;
    let mut peak = 0.0f64;
    for y in border..h - border {
        for x in border..w - border {
            for c in 0..3 {
                let d = est[[y, x, c]] as f64 - truth[[y, x, c]] as f64;
                se += d * d;
                n += 1.0;
                peak = peak.max(truth[[y, x, c]] as f64);
            }
        }
    }
    10.0 * (peak * peak / (se / n)).log10()
}

/// Bilinear upsampling of (H, W, 3) by `scale` (same pixel-centre convention as the merge).
pub fn upsample_bilinear(img: &Array3<f32>, scale: usize) -> Array3<f32> {
    let (h, w, _) = img.dim();
    let s = scale as f32;
    Array3::from_shape_fn((h * scale, w * scale, 3), |(y, x, c)| {
        let plane = img.index_axis(ndarray::Axis(2), c);
        let (ry, rx) = ((y as f32 + 0.5) / s - 0.5, (x as f32 + 0.5) / s - 0.5);
        quantacolor::filters::bilinear(plane, ry, rx)
    })
}

/// The grey image of a sub-block's counts ([`grey_image`] with the method detected for `cfa`),
/// as the burst pipeline builds it for alignment, the reference and robustness.
pub fn grey_block(sub: &SubBlock, cfa: &Cfa) -> Array2<f32> {
    grey_image(
        &sub.counts,
        sub.frames as usize,
        cfa,
        GreyMethod::detect(cfa),
    )
    .unwrap()
}
