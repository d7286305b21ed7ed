//! `bench quality`'s second upper bound, independent of the merge it judges: every binary
//! sample splatted bilinearly to its true reference-frame position (the simulator's motion,
//! camera and object), per channel Gaussian-smoothed (σ 1 px for R, G, B, 0.5 px for W), the
//! paper's per-pixel MLE (Eq. 6) and RGBW combination (Eq. 8). It shares no kernel, weight or
//! alignment code with the burst merge, so a blur of the merge's own kernels shows as a gap to
//! it (the "burst (true motion)" column runs the merge itself at the true motion and cannot).
//! And the sharpness figure: the σ of the Gaussian blur of the truth an image matches best.

#![forbid(unsafe_code)]

use anyhow::{bail, Result};
use ndarray::{Array2, Array3, ArrayView3, Axis};
use quantacolor::capture::Capture;
use quantacolor::cfa::Channel;
use quantacolor::filters::gaussian_blur;
use quantacolor::metrics::{evaluate, EvalOptions};
use quantacolor::model::mle_flux;
use quantacolor::rgbw::combine_rgbw;
use quantacolor::simulate::Motion;
use rayon::prelude::*;

/// Smoothing σ of the R, G, B planes and of the W plane, px.
const SIGMA_RGB: f32 = 1.0;
const SIGMA_W: f32 = 0.5;
/// Frames per independently accumulated chunk (summed in chunk order: deterministic).
const CHUNK_FRAMES: usize = 64;

/// Detections and sample weights per channel on the reference grid.
struct Splats {
    ones: [Array2<f64>; 4],
    weight: [Array2<f64>; 4],
}

impl Splats {
    fn zeros(h: usize, w: usize) -> Splats {
        Splats {
            ones: std::array::from_fn(|_| Array2::zeros((h, w))),
            weight: std::array::from_fn(|_| Array2::zeros((h, w))),
        }
    }

    fn add(mut self, other: Splats) -> Splats {
        for c in 0..4 {
            self.ones[c] += &other.ones[c];
            self.weight[c] += &other.weight[c];
        }
        self
    }
}

/// The reference-frame position seen by sensor position `q` in frame `t`: the camera's inverse
/// map, then the moving object's own motion where the object is seen.
fn reference_position(
    motion: &Motion,
    inverse: &([[f64; 2]; 2], [f64; 2]),
    t: usize,
    q: [f64; 2],
) -> [f64; 2] {
    let (a, b) = inverse;
    let m = [
        a[0][0] * q[0] + a[0][1] * q[1] + b[0],
        a[1][0] * q[0] + a[1][1] * q[1] + b[1],
    ];
    match &motion.object {
        Some(o) => {
            let p = [m[0] - o.dy[t], m[1] - o.dx[t]];
            if motion.on_object(p) {
                p
            } else {
                m
            }
        }
        None => m,
    }
}

/// The true-motion splat of `capture` (binary frames) under `motion`: linear RGB (H, W, 3) in
/// the units of a reconstruction (see the module documentation).
pub(super) fn true_motion_splat(capture: &Capture, motion: &Motion) -> Result<Array3<f32>> {
    let frames = &capture.frames;
    if frames.is_multibit() {
        bail!("the true-motion splat needs binary frames");
    }
    let (h, w) = (frames.height(), frames.width());
    let t = frames.frame_count();
    let channel = Array2::from_shape_fn((h, w), |(y, x)| capture.cfa.channel(y, x) as usize);
    let hot = capture.hot_pixels.as_ref();
    let chunks: Vec<std::ops::Range<usize>> = (0..t)
        .step_by(CHUNK_FRAMES)
        .map(|s| s..(s + CHUNK_FRAMES).min(t))
        .collect();
    let partial: Vec<Splats> = chunks
        .par_iter()
        .map(|range| {
            let mut acc = Splats::zeros(h, w);
            for f in range.clone() {
                let inverse = motion.inverse_affine(f);
                for y in 0..h {
                    for x in 0..w {
                        if hot.is_some_and(|m| m[[y, x]]) {
                            continue;
                        }
                        let c = channel[[y, x]];
                        let bit = frames.sample(f, y, x) as f64;
                        let p = reference_position(motion, &inverse, f, [y as f64, x as f64]);
                        let (y0, x0) = (p[0].floor(), p[1].floor());
                        let (fy, fx) = (p[0] - y0, p[1] - x0);
                        for (dy, wy) in [(0, 1.0 - fy), (1, fy)] {
                            for (dx, wx) in [(0, 1.0 - fx), (1, fx)] {
                                let (yy, xx) = (y0 as i64 + dy, x0 as i64 + dx);
                                if yy < 0 || xx < 0 || yy >= h as i64 || xx >= w as i64 {
                                    continue;
                                }
                                let (yy, xx) = (yy as usize, xx as usize);
                                let wt = wy * wx;
                                acc.ones[c][[yy, xx]] += wt * bit;
                                acc.weight[c][[yy, xx]] += wt;
                            }
                        }
                    }
                }
            }
            acc
        })
        .collect();
    let total = partial
        .into_iter()
        .reduce(Splats::add)
        .unwrap_or_else(|| Splats::zeros(h, w));
    let dark = capture.meta.dark_counts_per_frame();
    let mut planes = Array3::<f32>::from_elem((4, h, w), f32::NAN);
    for c in 0..4 {
        if total.weight[c].iter().all(|&v| v == 0.0) {
            continue; // no sites of this channel (W on a Bayer sensor)
        }
        let sigma = if c == Channel::W as usize {
            SIGMA_W
        } else {
            SIGMA_RGB
        };
        let flux = smoothed_flux(&total.ones[c], &total.weight[c], sigma, dark);
        planes.index_axis_mut(Axis(0), c).assign(&flux);
    }
    Ok(combine_rgbw(&planes, capture.meta.w_weights))
}

/// The MLE flux of Gaussian-smoothed detections and weights; where a channel's sites are too
/// sparse for σ (no weight), σ is doubled until there is.
fn smoothed_flux(ones: &Array2<f64>, weight: &Array2<f64>, sigma: f32, dark: f64) -> Array2<f32> {
    let to32 = |a: &Array2<f64>| a.mapv(|v| v as f32);
    let (ones, weight) = (to32(ones), to32(weight));
    let mut flux = Array2::<f32>::from_elem(ones.dim(), f32::NAN);
    let mut sigma = sigma;
    for _ in 0..4 {
        let (s, n) = (gaussian_blur(&ones, sigma), gaussian_blur(&weight, sigma));
        ndarray::Zip::from(&mut flux)
            .and(&s)
            .and(&n)
            .for_each(|f, &s, &n| {
                if f.is_nan() && n > 1e-3 {
                    *f = mle_flux(s as f64, n as f64, dark) as f32;
                }
            });
        if flux.iter().all(|v| !v.is_nan()) {
            break;
        }
        sigma *= 2.0;
    }
    flux.mapv_inplace(|v| if v.is_nan() { 0.0 } else { v });
    flux
}

/// The σ (px) of the Gaussian blur of `truth` that `image` matches best (highest sRGB PSNR
/// under `opts`): 0 to 2.5 px in steps of 0.1, then 0.02 around the best. A sharpness figure:
/// 0 is as sharp as the truth.
pub(super) fn blur_sigma(
    image: ArrayView3<f32>,
    truth: ArrayView3<f32>,
    opts: &EvalOptions,
) -> Result<f64> {
    let planes: Vec<Array2<f32>> = (0..3)
        .map(|c| truth.index_axis(Axis(2), c).to_owned())
        .collect();
    let score = |sigma: f64| -> Result<f64> {
        let blurred = if sigma <= 0.0 {
            truth.to_owned()
        } else {
            let mut out = Array3::<f32>::zeros(truth.dim());
            for (c, plane) in planes.iter().enumerate() {
                out.index_axis_mut(Axis(2), c)
                    .assign(&gaussian_blur(plane, sigma as f32));
            }
            out
        };
        Ok(evaluate(image, blurred.view(), opts)?.psnr_srgb)
    };
    let best_of = |candidates: Vec<f64>| -> Result<f64> {
        let mut best = (f64::NEG_INFINITY, 0.0);
        for s in candidates {
            let p = score(s)?;
            if p > best.0 {
                best = (p, s);
            }
        }
        Ok(best.1)
    };
    let coarse = best_of((0..=25).map(|k| k as f64 * 0.1).collect())?;
    best_of(
        (-4..=4)
            .map(|k| coarse + k as f64 * 0.02)
            .filter(|&s| s >= 0.0)
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Against the simulator's truth: the splat at the true motion is close to it, and far
    /// closer than the same splat assuming no motion (a wrong direction of the map, or a
    /// moving object splatted with the camera, would not be).
    #[test]
    fn the_true_motion_splat_recovers_the_scene() {
        use quantacolor::progress::Silent;
        use quantacolor::simulate::{simulate, FluxSpec, Scene, SimulationConfig};
        let opts = EvalOptions {
            border: 8,
            normalize_percentile: Some(99.5),
        };
        for motion in ["handheld", "object"] {
            let config = SimulationConfig {
                height: 64,
                width: 96,
                frames: 800,
                flux: FluxSpec::Mean { flux: 0.3 },
                motion: motion.parse().unwrap(),
                hot_fraction: 0.02,
                seed: 5,
                ..SimulationConfig::default()
            };
            let scene = Scene::from_spec("builtin:chart").unwrap();
            let sim = simulate(&config, &scene, &Silent).unwrap();
            let capture = sim.to_capture().unwrap();
            let gt = sim.ground_truth.view();
            let splat = true_motion_splat(&capture, &sim.motion).unwrap();
            let mut still = sim.motion.clone();
            still.dy.fill(0.0);
            still.dx.fill(0.0);
            still.theta_rad.fill(0.0);
            still.object = None;
            let unaligned = true_motion_splat(&capture, &still).unwrap();
            let good = evaluate(splat.view(), gt, &opts).unwrap().psnr_srgb;
            let bad = evaluate(unaligned.view(), gt, &opts).unwrap().psnr_srgb;
            let sigma = blur_sigma(splat.view(), gt, &opts).unwrap();
            println!(
                "{motion}: true motion {good:.2} dB (blur σ {sigma:.2} px), no motion {bad:.2} dB"
            );
            match &sim.motion.object {
                None => assert!(good > 20.0 && good > bad + 3.0, "{motion}: {good} vs {bad}"),
                Some(o) => {
                    // On the moving object itself (its disk at the reference frame).
                    let error_on_object = |image: &Array3<f32>| {
                        let mut sum = 0.0;
                        for ((y, x, c), &v) in image.indexed_iter() {
                            let (dy, dx) = (y as f64 - o.center[0], x as f64 - o.center[1]);
                            if dy.hypot(dx) < o.radius - 2.0 {
                                sum += ((v - gt[[y, x, c]]) as f64).powi(2);
                            }
                        }
                        sum
                    };
                    let (good, bad) = (error_on_object(&splat), error_on_object(&unaligned));
                    assert!(good < 0.75 * bad, "{motion}: {good} vs {bad}");
                }
            }
        }
    }

    /// The sharpness figure finds the blur put into an image.
    #[test]
    fn blur_sigma_finds_a_known_blur() {
        let truth = Array3::from_shape_fn((64, 64, 3), |(y, x, c)| {
            let v = ((y / 4 + x / 5) % 2) as f32;
            0.2 + 0.6 * v + 0.05 * c as f32
        });
        let opts = EvalOptions {
            border: 8,
            normalize_percentile: Some(99.5),
        };
        for sigma in [0.0f32, 0.7, 1.3] {
            let mut image = truth.clone();
            if sigma > 0.0 {
                for c in 0..3 {
                    let plane = truth.index_axis(Axis(2), c).to_owned();
                    image
                        .index_axis_mut(Axis(2), c)
                        .assign(&gaussian_blur(&plane, sigma));
                }
            }
            let found = blur_sigma(image.view(), truth.view(), &opts).unwrap();
            assert!((found - sigma as f64).abs() <= 0.021, "{sigma}: {found}");
        }
    }
}
