//! Robustness weights (supplement Eq. 4–6, after Wronski et al. 2019, §5.2): where a block's
//! warped content disagrees with the reference by more than the local variability and the
//! photon noise (binomial, or Gaussian–Poisson for multi-bit frames) explain, its samples are
//! rejected from the merge.

use super::warp::{check_flow, warp_to_reference};
use super::GreyNoise;
use crate::error::{Error, Result};
use ndarray::{Array2, Array3, Axis};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

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
    let mut mean = Array2::<f32>::zeros((h, w));
    let mut std = Array2::<f32>::zeros((h, w));
    mean.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(std.axis_iter_mut(Axis(0)))
        .enumerate()
        .for_each(|(y, (mut m_row, mut s_row))| {
            for x in 0..w {
                let (mut s1, mut s2, mut n) = (0.0f32, 0.0f32, 0.0f32);
                for yy in y.saturating_sub(1)..(y + 2).min(h) {
                    for xx in x.saturating_sub(1)..(x + 2).min(w) {
                        let v = image[[yy, xx]];
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

/// Running extremum along each row over x−r..=x+r (`take_max` picks max or min).
fn row_extreme(img: &Array2<f32>, r: usize, take_max: bool) -> Array2<f32> {
    let (h, w) = img.dim();
    let mut out = Array2::<f32>::zeros((h, w));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(img.axis_iter(Axis(0)))
        .for_each(|(mut lane, src)| {
            for x in 0..w {
                let window = src.slice(ndarray::s![x.saturating_sub(r)..(x + r + 1).min(w)]);
                lane[x] =
                    window.iter().copied().fold(
                        src[x],
                        |e, v| {
                            if take_max {
                                e.max(v)
                            } else {
                                e.min(v)
                            }
                        },
                    );
            }
        });
    out
}

/// Max − min of `values` over a (2r+1)² window, by separable running extrema.
fn local_spread(values: &Array2<f32>, r: usize) -> Array2<f32> {
    let extreme = |take_max: bool| {
        let rows = row_extreme(values, r, take_max);
        row_extreme(&rows.t().to_owned(), r, take_max)
            .t()
            .to_owned()
    };
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
    let warped = warp_to_reference(grey_block, flow)?;
    let (mean_k, _) = local_stats(&warped);
    let (mean_ref, std_ref) = local_stats(reference);
    let spread_y = local_spread(
        &flow.index_axis(Axis(2), 0).to_owned(),
        config.motion_radius,
    );
    let spread_x = local_spread(
        &flow.index_axis(Axis(2), 1).to_owned(),
        config.motion_radius,
    );
    let mut out = Array2::<f32>::zeros((h, w));
    ndarray::Zip::from(&mut out)
        .and(&mean_k)
        .and(&mean_ref)
        .and(&std_ref)
        .and(&spread_y)
        .and(&spread_x)
        .par_for_each(|r, &mk, &mu, &sd, &sy, &sx| {
            let sigma2 = (sd * sd + noise.variance(mu)).max(1e-12);
            let d = mk - mu;
            let s = if (sy * sy + sx * sx).sqrt() > config.motion_threshold {
                config.s_motion
            } else {
                config.s
            };
            *r = (s * (-d * d / sigma2).exp() - config.t).clamp(0.0, 1.0);
        });
    Ok(out)
}
