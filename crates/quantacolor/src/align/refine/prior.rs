//! The similarity prior: a fitted camera moved to its most probable value given that a
//! hand-held camera turns and shifts but hardly shears (this project's heuristic).
#![forbid(unsafe_code)]

use super::affine::AffineMotion;
use super::fit::Information;
use crate::align::motion::invert;

/// The camera `camera` fitted with the photons' [`Information`] `information`, moved to the
/// most probable camera under a Gaussian prior of standard deviation `sigma_px` on its
/// departure from a similarity: the shear R·(m_yx + m_xy) and the anisotropic scale
/// R·(m_yy − m_xx), in px at the distance `radius` from the centre. This project's heuristic,
/// not the paper's (Ma et al. 2023 §4.1 fits no camera model).
///
/// A hand-held camera turns and shifts: its shear and anisotropic scale are near zero, but the
/// affine fit lets the photons decide them, and where the scene constrains one direction only
/// (sky and sea: horizontal structure, so the horizontal motion of the upper half is
/// unobserved) the horizontal shear along y wanders with photon noise.
///
/// The fit's covariance C (the inverse information) is conditioned on the prior as a soft linear
/// constraint A·θ ~ N(0, σ²): θ' = θ − C·Aᵀ·(A·C·Aᵀ + σ²)⁻¹·A·θ. A sub-block whose photons measure
/// its shear (textured scenes: hundredths of a pixel) keeps it; one whose photons don't takes the
/// shear its well-measured rotation implies, and the parameters correlated with that shear (the
/// horizontal translation above) move with it. The prior acts on the camera in reference
/// coordinates ([`refine_camera_motion`](super::refine_camera_motion) applies it after anchoring at
/// the reference frame), not inside the fit: the fit is made against templates registered by the
/// current block motion, whose own unobserved shear it would otherwise fight. The information is
/// about the inverse map the fit solves for; for motions of a few pixels and under a degree its
/// covariance is the forward camera's to first order.
pub(super) fn similarity_posterior(
    camera: &AffineMotion,
    information: &Information,
    sigma_px: f64,
    radius: f64,
) -> AffineMotion {
    let info: Vec<Vec<f64>> = information.iter().map(|r| r.to_vec()).collect();
    let Some(cov) = invert(info) else {
        return *camera;
    };
    let theta = camera.params();
    let mut a = [[0.0f64; 6]; 2];
    a[0][3] = radius;
    a[0][4] = radius;
    a[1][2] = radius;
    a[1][5] = -radius;
    // C·Aᵀ (6 x 2), A·C·Aᵀ + σ² (2 x 2), A·θ.
    let ca: [[f64; 2]; 6] =
        std::array::from_fn(|i| std::array::from_fn(|k| (0..6).map(|j| cov[i][j] * a[k][j]).sum()));
    let s: Vec<Vec<f64>> = (0..2)
        .map(|k| {
            (0..2)
                .map(|l| {
                    (0..6).map(|i| a[k][i] * ca[i][l]).sum::<f64>()
                        + if k == l { sigma_px * sigma_px } else { 0.0 }
                })
                .collect()
        })
        .collect();
    let Some(s_inv) = invert(s) else {
        return *camera;
    };
    let z: [f64; 2] = std::array::from_fn(|k| (0..6).map(|i| a[k][i] * theta[i]).sum());
    let u: [f64; 2] = std::array::from_fn(|k| (0..2).map(|l| s_inv[k][l] * z[l]).sum());
    let moved: [f64; 6] =
        std::array::from_fn(|i| theta[i] - (0..2).map(|k| ca[i][k] * u[k]).sum::<f64>());
    if moved.iter().all(|v| v.is_finite()) {
        AffineMotion::from_params(moved)
    } else {
        *camera
    }
}
