//! Robustness weights (supplement Eq. 4–6, after Wronski et al. 2019, §5.2): where a block's
//! warped content disagrees with the reference by more than the local variability and the
//! photon noise (binomial, or Gaussian–Poisson for multi-bit frames) explain, its samples are
//! rejected from the merge.
#![forbid(unsafe_code)]

use super::warp::{check_flow, warp_checked};
use super::GreyNoise;
use crate::error::{Error, Result};
use ndarray::{Array2, Array3, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;
use std::sync::OnceLock;

/// Robustness parameters (supplement Eq. 4–6; Wronski et al. 2019, §5.2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RobustnessConfig {
    /// Scale s of R = clamp(s·exp(−d²/σ²) − t, 0, 1) where the local motion is coherent.
    pub s: f32, // 12
    /// Scale s where the local motion spread exceeds `motion_threshold` (stricter).
    pub s_motion: f32, // 1
    /// Offset t (Wronski et al. 2019's value; the supplement leaves it implicit).
    pub t: f32, // 0.12
    /// Motion-spread threshold M_th (px).
    pub motion_threshold: f32, // 10 px
    /// Half-size of the window over which the flow spread (max − min) is measured (px): 8 px is
    /// a 3x3 neighbourhood of 16 px tiles at stride 8.
    pub motion_radius: usize, // 8 px
}

impl Default for RobustnessConfig {
    fn default() -> Self {
        RobustnessConfig {
            s: 12.0,
            s_motion: 1.0,
            t: 0.12,
            motion_threshold: 10.0,
            motion_radius: 8,
        }
    }
}

/// 3x3 local mean and standard deviation (edge-clamped windows).
fn local_stats(image: &Array2<f32>) -> (Array2<f32>, Array2<f32>) {
    let (h, w) = image.dim();
    let image = image.as_standard_layout();
    let pixels = image.as_slice().expect("standard layout");
    let mut mean = Array2::<f32>::zeros((h, w));
    let mut std = Array2::<f32>::zeros((h, w));
    mean.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(std.axis_iter_mut(Axis(0)))
        .enumerate()
        .for_each(|(y, (mut m_row, mut s_row))| {
            let rows: Vec<&[f32]> = (y.saturating_sub(1)..(y + 2).min(h))
                .map(|yy| &pixels[yy * w..(yy + 1) * w])
                .collect();
            for x in 0..w {
                let (mut s1, mut s2, mut n) = (0.0f32, 0.0f32, 0.0f32);
                // Window rows top to bottom, columns left to right (the sums' order).
                for row in &rows {
                    for &v in &row[x.saturating_sub(1)..(x + 2).min(w)] {
                        s1 += v;
                        s2 += v * v;
                        n += 1.0;
                    }
                }
                let m = s1 / n;
                m_row[x] = m;
                s_row[x] = (s2 / n - m * m).max(0.0).sqrt();
            }
        });
    (mean, std)
}

/// The mean of [`local_stats`] alone (the same sums in the same order, so the same bits):
/// each output row adds its window rows top to bottom, each row's left, centre and right
/// neighbours in turn, as plain slice loops over the row.
fn local_mean(image: &Array2<f32>) -> Array2<f32> {
    let (h, w) = image.dim();
    let image = image.as_standard_layout();
    let pixels = image.as_slice().expect("standard layout");
    let mut mean = vec![0.0f32; h * w];
    if w == 0 {
        return Array2::from_shape_vec((h, w), mean).expect("h x w");
    }
    mean.par_chunks_exact_mut(w)
        .enumerate()
        .for_each(|(y, sums)| {
            let window = y.saturating_sub(1)..(y + 2).min(h);
            let rows = window.len() as f32;
            for yy in window {
                let row = &pixels[yy * w..(yy + 1) * w];
                // Columns x − 1, x, x + 1 where they exist, in that order.
                if w == 1 {
                    sums[0] += row[0];
                    continue;
                }
                sums[0] += row[0];
                sums[0] += row[1];
                let inner = &mut sums[1..w - 1];
                inner
                    .iter_mut()
                    .zip(&row[..w - 2])
                    .for_each(|(s, &v)| *s += v);
                inner
                    .iter_mut()
                    .zip(&row[1..w - 1])
                    .for_each(|(s, &v)| *s += v);
                inner.iter_mut().zip(&row[2..]).for_each(|(s, &v)| *s += v);
                sums[w - 1] += row[w - 2];
                sums[w - 1] += row[w - 1];
            }
            // The window's pixel count, as local_stats counts it (exact small integers).
            let count = |x: usize| rows * ((x + 2).min(w) - x.saturating_sub(1)) as f32;
            for (x, s) in sums.iter_mut().enumerate() {
                *s /= count(x);
            }
        });
    Array2::from_shape_vec((h, w), mean).expect("h x w")
}

/// Running extremum along each row over x−r..=x+r, clipped to the row (`take_max` picks max or
/// min), by the van Herk–Gil-Werman algorithm: three comparisons per pixel whatever `r`.
/// The extremum of a set does not depend on the order it is taken in, so this equals the direct
/// scan of every window.
fn row_extreme(img: &Array2<f32>, r: usize, take_max: bool) -> Array2<f32> {
    let (h, w) = img.dim();
    let img = img.as_standard_layout();
    let src = img.as_slice().expect("standard layout");
    let mut out = vec![0.0f32; h * w];
    if w == 0 {
        return Array2::from_shape_vec((h, w), out).expect("h x w");
    }
    let pick = |a: f32, b: f32| if take_max { a.max(b) } else { a.min(b) };
    let fill = if take_max {
        f32::NEG_INFINITY
    } else {
        f32::INFINITY
    };
    let k = 2 * r + 1;
    out.par_chunks_mut(w).zip(src.par_chunks(w)).for_each_init(
        || (Vec::new(), Vec::new(), Vec::new()),
        |(padded, prefix, suffix), (lane, row)| {
            // The row padded with r neutral values each side: window x is padded[x..x + k].
            padded.clear();
            padded.resize(r, fill);
            padded.extend_from_slice(row);
            padded.resize(w + 2 * r, fill);
            let n = padded.len();
            prefix.resize(n, fill);
            suffix.resize(n, fill);
            // `phase` = i mod k, stepped instead of divided.
            let mut phase = 0;
            for (i, &v) in padded.iter().enumerate() {
                prefix[i] = if phase == 0 {
                    v
                } else {
                    pick(prefix[i - 1], v)
                };
                phase = if phase == k - 1 { 0 } else { phase + 1 };
            }
            let mut phase = (n - 1) % k;
            for i in (0..n).rev() {
                suffix[i] = if phase == k - 1 || i == n - 1 {
                    padded[i]
                } else {
                    pick(suffix[i + 1], padded[i])
                };
                phase = if phase == 0 { k - 1 } else { phase - 1 };
            }
            for (x, o) in lane.iter_mut().enumerate() {
                *o = pick(suffix[x], prefix[x + k - 1]);
            }
        },
    );
    Array2::from_shape_vec((h, w), out).expect("h x w")
}

/// Running extremum along each column over y−r..=y+r, clipped to the image: whole rows at a
/// time (the same set of values per pixel as a column scan).
fn column_extreme(img: &Array2<f32>, r: usize, take_max: bool) -> Array2<f32> {
    let (h, w) = img.dim();
    let img = img.as_standard_layout();
    let src = img.as_slice().expect("standard layout");
    let mut out = vec![0.0f32; h * w];
    out.par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(y, lane)| {
            lane.copy_from_slice(&src[y * w..(y + 1) * w]);
            for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                let row = &src[yy * w..(yy + 1) * w];
                if take_max {
                    lane.iter_mut().zip(row).for_each(|(o, &v)| *o = o.max(v));
                } else {
                    lane.iter_mut().zip(row).for_each(|(o, &v)| *o = o.min(v));
                }
            }
        });
    Array2::from_shape_vec((h, w), out).expect("h x w")
}

/// Max − min of `values` over a (2r+1)² window (clipped at the borders), by separable running
/// extrema.
fn local_spread(values: &Array2<f32>, r: usize) -> Array2<f32> {
    let extreme = |take_max: bool| column_extreme(&row_extreme(values, r, take_max), r, take_max);
    extreme(true) - extreme(false)
}

/// Robustness weights R ∈ [0, 1] of one block on the reference grid (supplement Eq. 4–6).
///
/// The block's grey image is warped by `flow` (H, W, 2); its 3x3 local mean μ_k is compared
/// with the reference's 3x3 mean μ and std σ_ref: d = |μ_k − μ|, σ² = σ_ref² + v(μ) with v the
/// noise of a grey value ([`GreyNoise`]: binomial μ(1−μ)/trials for binary frames, the
/// Gaussian–Poisson variance for multi-bit ones), R = clamp(s·exp(−d²/σ²) − t, 0, 1), with s = `s` where
/// the flow's local spread (Euclidean norm of the max − min of dy and dx over a
/// (2·motion_radius+1)² window) is at most `motion_threshold`, and `s_motion` elsewhere.
pub fn robustness(
    reference: &Array2<f32>,
    grey_block: &Array2<f32>,
    flow: &Array3<f32>,
    noise: impl Into<GreyNoise>,
    config: &RobustnessConfig,
) -> Result<Array2<f32>> {
    robustness_against(
        &ReferenceStats::new(reference),
        grey_block,
        flow,
        noise,
        config,
    )
}

/// The reference's 3x3 local mean μ and std σ_ref that [`robustness`] compares every block
/// with: made once per reference, whatever the number of blocks.
#[derive(Debug, Clone)]
pub struct ReferenceStats {
    mean: Array2<f32>,
    std: Array2<f32>,
    /// σ² = max(σ_ref² + v(μ), 1e−12) of every pixel for the grey noise it was made for: it
    /// depends on the reference alone, so the first block's map makes it for every block.
    sigma2: OnceLock<(GreyNoise, Array2<f32>)>,
}

impl ReferenceStats {
    pub fn new(reference: &Array2<f32>) -> Self {
        let (mean, std) = local_stats(reference);
        ReferenceStats {
            mean,
            std,
            sigma2: OnceLock::new(),
        }
    }

    /// The σ² of [`weights`] per pixel for `noise`: kept from the first call, made afresh for
    /// another noise.
    fn sigma2(&self, noise: GreyNoise) -> Cow<'_, Array2<f32>> {
        let make = || {
            let mut sigma2 = Array2::<f32>::zeros(self.mean.dim());
            ndarray::Zip::from(&mut sigma2)
                .and(&self.mean)
                .and(&self.std)
                .par_for_each(|v, &mu, &sd| *v = (sd * sd + noise.variance(mu)).max(1e-12));
            sigma2
        };
        let (kept_noise, sigma2) = self.sigma2.get_or_init(|| (noise, make()));
        if *kept_noise == noise {
            Cow::Borrowed(sigma2)
        } else {
            Cow::Owned(make())
        }
    }

    /// (H, W) of the reference.
    pub fn dim(&self) -> (usize, usize) {
        self.mean.dim()
    }
}

/// [`robustness`] against a reference's [`ReferenceStats`] (the same map).
pub fn robustness_against(
    reference: &ReferenceStats,
    grey_block: &Array2<f32>,
    flow: &Array3<f32>,
    noise: impl Into<GreyNoise>,
    config: &RobustnessConfig,
) -> Result<Array2<f32>> {
    let noise: GreyNoise = noise.into();
    let (h, w) = reference.dim();
    if grey_block.dim() != (h, w) {
        return Err(Error::invalid(format!(
            "robustness: grey block has shape {:?}, the reference has ({h}, {w})",
            grey_block.dim()
        )));
    }
    check_flow(flow, h, w, "robustness")?;
    if !super::warp::positive(noise.trials) {
        return Err(Error::invalid("robustness: trials must be positive"));
    }
    let mean_k = local_mean(&warp_checked(grey_block, flow)?);
    let flow_range = flow_ranges(flow);
    // Every window's spread is at most the whole flow's (max − min over a subset): when that
    // is under the threshold, no pixel takes `s_motion` and the running extrema are skipped.
    let spread = if spread_exceeds(flow_range[0], flow_range[1], config) {
        Some([0, 1].map(|c| {
            local_spread(
                &flow.index_axis(Axis(2), c).to_owned(),
                config.motion_radius,
            )
        }))
    } else {
        None
    };
    Ok(weights(&mean_k, reference, spread.as_ref(), noise, config))
}

/// Whether a flow spread (max − min of dy and dx) is above `config.motion_threshold`.
fn spread_exceeds(dy: f32, dx: f32, config: &RobustnessConfig) -> bool {
    (dy * dy + dx * dx).sqrt() > config.motion_threshold
}

/// R of every pixel (supplement Eq. 4–6) from the warped block's local means `mean_k`, the
/// reference's statistics and the flow's local `spread` (dy, dx); `None`: no spread above the
/// threshold anywhere.
fn weights(
    mean_k: &Array2<f32>,
    reference: &ReferenceStats,
    spread: Option<&[Array2<f32>; 2]>,
    noise: GreyNoise,
    config: &RobustnessConfig,
) -> Array2<f32> {
    let sigma2 = reference.sigma2(noise);
    let weight = [config.s, config.s_motion].map(|s| Weight::new(s, config.t));
    let mut out = Array2::<f32>::zeros(mean_k.dim());
    let pixels = ndarray::Zip::from(&mut out)
        .and(mean_k)
        .and(&reference.mean)
        .and(&*sigma2);
    match spread {
        None => pixels.par_for_each(|r, &mk, &mu, &sigma2| *r = weight[0].at(mk - mu, sigma2)),
        Some([spread_y, spread_x]) => {
            pixels
                .and(spread_y)
                .and(spread_x)
                .par_for_each(|r, &mk, &mu, &sigma2, &sy, &sx| {
                    let motion = spread_exceeds(sy, sx, config);
                    *r = weight[motion as usize].at(mk - mu, sigma2);
                })
        }
    }
    out
}

/// R = clamp(s·exp(x) − t, 0, 1) with x = −d²/σ², skipping the exponential where the clamp
/// decides the value anyway: below `zero_below` s·eˣ is under 0.91·t (R = 0), above `one_above`
/// s·eˣ − t is over 1.1 (R = 1); margins of 0.1 in x (10 % in eˣ) are far beyond f32 rounding,
/// so R is bit for bit the direct formula's.
#[derive(Debug, Clone, Copy)]
struct Weight {
    s: f32,
    t: f32,
    zero_below: f32,
    one_above: f32,
}

impl Weight {
    fn new(s: f32, t: f32) -> Self {
        // ln(t/s) and ln((1 + t)/s) where they exist; otherwise (NaN, s or t not positive) the
        // exponential is always taken.
        let (s64, t64) = (s as f64, t as f64);
        let zero_below = if s64 > 0.0 && t64 > 0.0 {
            ((t64 / s64).ln() - 0.1) as f32
        } else {
            f32::NEG_INFINITY
        };
        let one_above = if s64 > 0.0 && t64 > -1.0 {
            ((1.0 + t64) / s64).ln() as f32 + 0.1
        } else {
            f32::INFINITY
        };
        Weight {
            s,
            t,
            zero_below: if zero_below.is_nan() {
                f32::NEG_INFINITY
            } else {
                zero_below
            },
            one_above: if one_above.is_nan() {
                f32::INFINITY
            } else {
                one_above
            },
        }
    }

    /// R for the difference `d` = μ_k − μ and the variance `sigma2`.
    #[inline]
    fn at(&self, d: f32, sigma2: f32) -> f32 {
        let x = -d * d / sigma2;
        if x < self.zero_below {
            0.0
        } else if x > self.one_above {
            1.0
        } else {
            (self.s * x.exp() - self.t).clamp(0.0, 1.0)
        }
    }
}

/// Max − min of a (H, W, 2) flow's dy and of its dx ([`value_range`] of each), in one pass:
/// sixteen running extrema (even lanes dy, odd lanes dx) that compile to vector min and max.
/// The extremum of a set does not depend on the order it is taken in (the flow is finite,
/// [`check_flow`]; a zero's sign does not matter to [`spread_exceeds`]).
fn flow_ranges(flow: &Array3<f32>) -> [f32; 2] {
    const LANES: usize = 16;
    let Some(values) = flow.as_slice() else {
        return [0, 1].map(|c| value_range(flow.index_axis(Axis(2), c)));
    };
    let mut lo = [f32::INFINITY; LANES];
    let mut hi = [f32::NEG_INFINITY; LANES];
    let chunks = values.chunks_exact(LANES);
    let tail = chunks.remainder();
    for chunk in chunks {
        for i in 0..LANES {
            let v = chunk[i];
            lo[i] = if v < lo[i] { v } else { lo[i] };
            hi[i] = if v > hi[i] { v } else { hi[i] };
        }
    }
    // LANES is even, so the tail starts on a dy.
    for (i, &v) in tail.iter().enumerate() {
        lo[i] = if v < lo[i] { v } else { lo[i] };
        hi[i] = if v > hi[i] { v } else { hi[i] };
    }
    [0, 1].map(|c| {
        let lo = (c..LANES)
            .step_by(2)
            .map(|i| lo[i])
            .fold(f32::INFINITY, f32::min);
        let hi = (c..LANES)
            .step_by(2)
            .map(|i| hi[i])
            .fold(f32::NEG_INFINITY, f32::max);
        if hi >= lo {
            hi - lo
        } else {
            0.0
        }
    })
}

/// Max − min of all of `values` (0 for none).
fn value_range(values: ndarray::ArrayView2<f32>) -> f32 {
    let (lo, hi) = values
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    if hi >= lo {
        hi - lo
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Max − min over the clipped (2r+1)² window, scanned directly.
    fn brute_spread(values: &Array2<f32>, r: usize) -> Array2<f32> {
        let (h, w) = values.dim();
        Array2::from_shape_fn((h, w), |(y, x)| {
            let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
            for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                    lo = lo.min(values[[yy, xx]]);
                    hi = hi.max(values[[yy, xx]]);
                }
            }
            hi - lo
        })
    }

    /// Under the threshold everywhere, the weights without the running extrema are the
    /// weights with them, bit for bit (a smooth flow whose whole range is 9 px).
    #[test]
    fn a_flow_spread_under_the_threshold_skips_the_local_spread() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (h, w) = (40, 60);
        let reference = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.1f32..0.6));
        let block = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.1f32..0.6));
        let config = RobustnessConfig::default();
        let flow = Array3::from_shape_fn((h, w, 2), |(y, x, c)| {
            if c == 0 {
                0.05 * y as f32
            } else {
                9.0 * x as f32 / (w - 1) as f32 - 0.5
            }
        });
        let range = [0, 1].map(|c| value_range(flow.index_axis(Axis(2), c)));
        assert!(!spread_exceeds(range[0], range[1], &config));
        let stats = ReferenceStats::new(&reference);
        let mean_k = local_mean(&super::super::warp::warp_to_reference(&block, &flow).unwrap());
        let spread = [0, 1].map(|c| {
            local_spread(
                &flow.index_axis(Axis(2), c).to_owned(),
                config.motion_radius,
            )
        });
        let noise = GreyNoise::from(64.0f32);
        let with = weights(&mean_k, &stats, Some(&spread), noise, &config);
        let without = weights(&mean_k, &stats, None, noise, &config);
        assert_eq!(with, without);
        assert_eq!(
            robustness_against(&stats, &block, &flow, 64.0f32, &config).unwrap(),
            without
        );
    }

    /// The mean alone equals [`local_stats`]' mean bit for bit, and the one-pass flow ranges
    /// equal each component's [`value_range`], on shapes down to one row or column.
    #[test]
    fn local_mean_and_flow_ranges_match_their_reference_forms() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for (h, w) in [(13, 29), (1, 7), (6, 1), (2, 2), (1, 1), (9, 40)] {
            let image = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0).powi(3));
            let (mean, _) = local_stats(&image);
            let fast = local_mean(&image);
            assert!(
                fast.iter()
                    .zip(&mean)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "{h}x{w}"
            );
            let flow = Array3::from_shape_fn((h, w, 2), |_| rng.gen_range(-20.0f32..20.0));
            let expected = [0, 1].map(|c| value_range(flow.index_axis(Axis(2), c)));
            assert_eq!(flow_ranges(&flow), expected, "{h}x{w}");
        }
    }

    /// The weight with its skipped exponentials equals the direct formula bit for bit over
    /// differences from 0 to 20σ, for the default scales, the motion scale and others.
    #[test]
    fn skipping_the_exponential_where_the_clamp_decides_keeps_every_weight() {
        for (s, t) in [
            (12.0f32, 0.12f32),
            (1.0, 0.12),
            (3.0, 0.0),
            (0.5, -0.3),
            (2.0, 1.5),
        ] {
            let weight = Weight::new(s, t);
            for i in 0..200_000 {
                let d = i as f32 * 1e-4;
                for sigma2 in [1.0f32, 0.37, 1e-12] {
                    let direct = (s * (-d * d / sigma2).exp() - t).clamp(0.0, 1.0);
                    assert_eq!(
                        weight.at(d, sigma2).to_bits(),
                        direct.to_bits(),
                        "s {s} t {t} d {d} sigma2 {sigma2}"
                    );
                }
            }
        }
    }

    #[test]
    fn running_extrema_match_a_direct_window_scan() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        for (h, w, r) in [(13, 29, 3), (7, 5, 8), (1, 40, 2), (20, 1, 1), (9, 17, 0)] {
            // Coarse values: many ties.
            let values = Array2::from_shape_fn((h, w), |_| rng.gen_range(-4..5) as f32 * 0.5);
            assert_eq!(
                local_spread(&values, r),
                brute_spread(&values, r),
                "{h}x{w} r {r}"
            );
        }
    }

    #[test]
    fn spread_of_a_ramp_is_its_slope_times_the_window() {
        let values = Array2::from_shape_fn((30, 40), |(y, x)| x as f32 + 0.0 * y as f32);
        let spread = local_spread(&values, 4);
        assert_eq!(spread[[10, 20]], 8.0);
        assert_eq!(spread[[10, 0]], 4.0);
        assert_eq!(spread[[0, 39]], 4.0);
    }
}
