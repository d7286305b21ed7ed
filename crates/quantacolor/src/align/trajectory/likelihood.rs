//! The score (gradient of the Bernoulli log-likelihood, paper Eq. 2–3 for single photons) and
//! Fisher information of one frame's inverse camera parameters against the template, summed
//! row by row; the portable row sums beside the AVX2 ones of `x86.rs`.

#![forbid(unsafe_code)]

use super::sites::{site_bit, RowMap, Sites};
use crate::align::refine::{sample_template, AffineMotion, TemplateLevel};
use crate::capture::frames::FrameLayout;
use crate::capture::BinaryFrames;
use crate::cpu::Isa;

/// Bernoulli probabilities are kept inside [P_MIN, 1 − P_MIN].
pub(super) const P_MIN: f64 = 1e-4;

/// Score (gradient of the log-likelihood) and Fisher information of one frame's inverse camera
/// parameters at `camera`, against the template `level`.
///
/// A site's Jacobian ∂p/∂θ for θ = (b_y, b_x, m_yy, m_yx, m_xy, m_xx) is the template gradient
/// (g_y, g_x) times (1, r_y, r_x), its position about the centre: each entry is g_a·r_y^i·r_x^j.
/// Along a row r_y is fixed, so the row sums Σ s·g_a·r_x^j (score, j ≤ 1) and Σ w·g_a·g_b·r_x^j
/// (information, j ≤ 2) give every entry once multiplied by the row's power of r_y: 13 sums per
/// site instead of the 27 of the 6 + 21 entries (the same terms, grouped by row).
///
/// When the template's `isa` has AVX2 and FMA the row sums are made eight sites at a time in f32
/// ([`super::x86::row_sums`]); otherwise site by site in f64 ([`row_sums_scalar`]). The two
/// agree to f32 rounding.
pub(super) fn frame_score(
    frames: &BinaryFrames,
    sites: &Sites,
    t: usize,
    camera: &AffineMotion,
    template: &ScoreTemplate<'_>,
    margin: f64,
) -> ([f64; 6], [[f64; 6]; 6]) {
    let (level, isa) = (template.level, template.isa);
    #[cfg(target_arch = "x86_64")]
    if isa.avx2_fma() && row_sums_avx2_fits(level) {
        return frame_score_by_rows(frames, sites, t, camera, margin, |row, y, _, d| {
            // The planes are the level's.
            let planes = Some(&template.planes);
            super::x86::row_sums(isa, level, planes, row, y, &sites.masks[y], d)
        });
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = isa;
    frame_score_by_rows(frames, sites, t, camera, margin, |row, y, columns, d| {
        row_sums_scalar(level, row, y, columns, d)
    })
}

/// The template that [`frame_score`] samples: its level, and the level's value and gradients
/// as three planes of their own ([`TemplatePlanes`]) for [`super::x86::row_sums`]'s row runs;
/// and the instruction set the row sums run on.
pub(super) struct ScoreTemplate<'a> {
    pub(super) level: &'a TemplateLevel,
    pub(super) planes: TemplatePlanes,
    pub(super) isa: Isa,
}

impl<'a> ScoreTemplate<'a> {
    pub(super) fn new(level: &'a TemplateLevel, isa: Isa) -> ScoreTemplate<'a> {
        ScoreTemplate {
            level,
            planes: TemplatePlanes::new(level),
            isa,
        }
    }
}

/// A [`TemplateLevel`]'s value, ∂/∂y and ∂/∂x, each as a row-major plane of its own: eight
/// consecutive pixels of one are one load.
pub(super) struct TemplatePlanes {
    pub(super) width: usize,
    /// Value, ∂/∂y, ∂/∂x.
    pub(super) planes: [Vec<f32>; 3],
}

impl TemplatePlanes {
    pub(super) fn new(level: &TemplateLevel) -> TemplatePlanes {
        let floats = level.floats();
        TemplatePlanes {
            width: level.dims().1,
            planes: std::array::from_fn(|k| floats.iter().skip(k).step_by(4).copied().collect()),
        }
    }
}

/// The 13 row sums of [`frame_score`]: `score[a][j]` = Σ s·g_a·r_x^j; `weight[k][j]` =
/// Σ w·g_a·g_b·r_x^j for (a, b) = (y, y), (y, x), (x, x).
#[derive(Default)]
pub(super) struct RowSums {
    pub(super) score: [[f64; 2]; 2],
    pub(super) weight: [[f64; 3]; 3],
}

/// [`frame_score`] from the row sums that `row_sums(raw row, y, columns, map)` makes.
pub(super) fn frame_score_by_rows(
    frames: &BinaryFrames,
    sites: &Sites,
    t: usize,
    camera: &AffineMotion,
    margin: f64,
    mut row_sums: impl FnMut(&[u8], usize, &[u16], &RowMap) -> RowSums,
) -> ([f64; 6], [[f64; 6]; 6]) {
    let packed = matches!(frames.layout(), FrameLayout::Packed);
    let mut g = [0.0f64; 6];
    let mut info = [[0.0f64; 6]; 6];
    for (y, columns) in sites.columns.iter().enumerate() {
        if columns.is_empty() {
            continue;
        }
        let ry = y as f64 - sites.centre[0];
        let map = RowMap::new(sites, camera, y, packed, margin);
        let RowSums { score, weight } = row_sums(frames.raw_row(t, y), y, columns, &map);
        // Parameter p is g_{GRADIENT[p]}·r_y^{POWER_Y[p]}·r_x^{POWER_X[p]}.
        const GRADIENT: [usize; 6] = [0, 1, 0, 0, 1, 1];
        const POWER_Y: [usize; 6] = [0, 0, 1, 0, 1, 0];
        const POWER_X: [usize; 6] = [0, 0, 0, 1, 0, 1];
        let ry_power = [1.0, ry, ry * ry];
        for a in 0..6 {
            g[a] += ry_power[POWER_Y[a]] * score[GRADIENT[a]][POWER_X[a]];
            for b in a..6 {
                let pair = GRADIENT[a] + GRADIENT[b];
                info[a][b] +=
                    ry_power[POWER_Y[a] + POWER_Y[b]] * weight[pair][POWER_X[a] + POWER_X[b]];
            }
        }
    }
    for a in 0..6 {
        for b in 0..a {
            info[a][b] = info[b][a];
        }
    }
    (g, info)
}

/// One row's [`RowSums`], site by site in f64.
pub(super) fn row_sums_scalar(
    level: &TemplateLevel,
    row: &[u8],
    y: usize,
    columns: &[u16],
    map: &RowMap,
) -> RowSums {
    let mut sums = RowSums::default();
    let (score, weight) = (&mut sums.score, &mut sums.weight);
    for &x in columns {
        let x = x as usize;
        let bit = site_bit(row, x, map.packed);
        let rx = x as f64 - map.centre_x;
        let (py, px) = map.position(y, x);
        let Some([v, gy, gx]) = sample_template(level, py, px) else {
            continue;
        };
        let p = v.clamp(P_MIN, 1.0 - P_MIN);
        let w = 1.0 / (p * (1.0 - p));
        let s = if bit { 1.0 / p } else { -1.0 / (1.0 - p) };
        let (sy, sx) = (s * gy, s * gx);
        score[0][0] += sy;
        score[0][1] += sy * rx;
        score[1][0] += sx;
        score[1][1] += sx * rx;
        let rx2 = rx * rx;
        for (k, wk) in [w * gy * gy, w * gy * gx, w * gx * gx]
            .into_iter()
            .enumerate()
        {
            weight[k][0] += wk;
            weight[k][1] += wk * rx;
            weight[k][2] += wk * rx2;
        }
    }
    sums
}

/// Whether every float index of the template fits an i32, as [`super::x86::row_sums`] needs.
#[cfg(target_arch = "x86_64")]
pub(super) fn row_sums_avx2_fits(level: &TemplateLevel) -> bool {
    level.float_len() < i32::MAX as usize
}
