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
            let sampling = RowSampling {
                planes: Some(&template.planes),
                blocks: template.blocks.as_ref(),
            };
            super::x86::row_sums(isa, level, &sampling, row, y, &sites.masks[y], d)
        });
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = isa;
    frame_score_by_rows(frames, sites, t, camera, margin, |row, y, columns, d| {
        row_sums_scalar(level, template.blocks.as_ref(), row, y, columns, d)
    })
}

/// The template that [`frame_score`] samples: its level, and the level's value and gradients
/// as three planes of their own ([`TemplatePlanes`]) for [`super::x86::row_sums`]'s row runs;
/// the instruction set the row sums run on; and the template's informative blocks, when only
/// the sites that land in them are scored ([`InformativeBlocks`]).
pub(super) struct ScoreTemplate<'a> {
    pub(super) level: &'a TemplateLevel,
    pub(super) planes: TemplatePlanes,
    pub(super) isa: Isa,
    pub(super) blocks: Option<InformativeBlocks>,
}

impl<'a> ScoreTemplate<'a> {
    /// Every site scored.
    #[cfg(test)]
    pub(super) fn new(level: &'a TemplateLevel, isa: Isa) -> ScoreTemplate<'a> {
        ScoreTemplate::informative(level, isa, 1.0)
    }

    /// Only the sites in the blocks that hold `fraction` of the template's information scored
    /// ([`InformativeBlocks::new`]; every site at a fraction of 1 or more).
    pub(super) fn informative(
        level: &'a TemplateLevel,
        isa: Isa,
        fraction: f64,
    ) -> ScoreTemplate<'a> {
        ScoreTemplate {
            level,
            planes: TemplatePlanes::new(level),
            isa,
            blocks: InformativeBlocks::new(level, fraction),
        }
    }
}

/// What [`super::x86::row_sums`] samples besides the level: its planes (for row runs), and the
/// informative blocks that select the groups of sites scored.
#[derive(Clone, Copy, Default)]
pub(super) struct RowSampling<'a> {
    pub(super) planes: Option<&'a TemplatePlanes>,
    pub(super) blocks: Option<&'a InformativeBlocks>,
}

/// The template's blocks of `BLOCK` × `BLOCK` pixels that hold most of its Fisher information
/// about position, Σ (g_y² + g_x²) / (p (1 − p)): the scoring reads only the groups of eight
/// sites that land in one (this project's own saving, not the paper's). Flat regions add
/// almost nothing to a frame's score or information, and on natural scenes they are most of
/// the image; which sites are read depends on the template only, never on the photons, so the
/// score stays unbiased.
pub(super) struct InformativeBlocks {
    /// Blocks per row of the template.
    pub(super) width: usize,
    pub(super) height: usize,
    /// −1 (all bits) for a kept block, 0 for another, row-major: one gather in the AVX2
    /// kernel.
    pub(super) kept: Vec<i32>,
}

/// The side of an [`InformativeBlocks`] block (px): eight columns of sites span at most two.
pub(super) const BLOCK: usize = 8;

impl InformativeBlocks {
    /// The fewest blocks, most informative first, that hold at least `fraction` of the
    /// template's information (ties kept alike); `None` (every block) at a fraction of 1 or
    /// more.
    pub(super) fn new(level: &TemplateLevel, fraction: f64) -> Option<InformativeBlocks> {
        if fraction >= 1.0 {
            return None;
        }
        let (h, w) = level.dims();
        let (height, width) = (h.div_ceil(BLOCK), w.div_ceil(BLOCK));
        let mut information = vec![0.0f64; height * width];
        for (i, pixel) in level.floats().chunks_exact(4).enumerate() {
            let (v, gy, gx) = (pixel[0], pixel[1], pixel[2]);
            let p = f64::from(v).clamp(P_MIN, 1.0 - P_MIN);
            let (gy, gx) = (f64::from(gy), f64::from(gx));
            information[(i / w) / BLOCK * width + (i % w) / BLOCK] +=
                (gy * gy + gx * gx) / (p * (1.0 - p));
        }
        let mut sorted = information.clone();
        sorted.sort_by(|a, b| b.total_cmp(a));
        let total: f64 = sorted.iter().sum();
        let mut held = 0.0;
        let mut threshold = 0.0;
        for &b in &sorted {
            if held >= fraction * total {
                break;
            }
            held += b;
            threshold = b;
        }
        Some(InformativeBlocks {
            width,
            height,
            kept: information
                .iter()
                .map(|&b| -i32::from(b >= threshold))
                .collect(),
        })
    }

    /// The fraction of blocks kept.
    #[cfg(test)]
    pub(super) fn kept_fraction(&self) -> f64 {
        self.kept.iter().filter(|&&k| k != 0).count() as f64 / self.kept.len().max(1) as f64
    }

    /// The template's extent (y, x) in px that the blocks cover.
    pub(super) fn limits(&self) -> (f32, f32) {
        ((self.height * BLOCK) as f32, (self.width * BLOCK) as f32)
    }

    /// Whether a site at template position (`py`, `px`) lies in a kept block (the AVX2
    /// kernel's `x86::kept_lanes`, lane by lane).
    #[inline(always)]
    fn kept_at(&self, py: f32, px: f32) -> bool {
        let (height, width) = self.limits();
        let inside = (py >= 0.0) & (px >= 0.0) & (py < height) & (px < width);
        // Truncation is the floor where it is used (non-negative positions).
        let index = if inside {
            py as usize / BLOCK * self.width + px as usize / BLOCK
        } else {
            0
        };
        inside & (self.kept[index] != 0)
    }

    /// Whether the group of sites in columns 8k..8k + 8 of a row is scored, from the template
    /// positions (y, x) of its columns 8k and 8k + 7 in f32 ([`group_end_positions`], the
    /// AVX2 kernel's lanes 0 and 7): when either lies in a kept block.
    #[inline(always)]
    pub(super) fn keeps_group(&self, ends: [(f32, f32); 2]) -> bool {
        self.kept_at(ends[0].0, ends[0].1) | self.kept_at(ends[1].0, ends[1].1)
    }
}

/// The template positions (y, x) of columns 8k and 8k + 7 of row `y` under `map`, in f32 with
/// fused multiply-adds: the same operations, so the same bits, as lanes 0 and 7 of the AVX2
/// kernel's positions (`x86::positions_avx2`).
pub(super) fn group_end_positions(map: &RowMap, y: usize, k: usize) -> [(f32, f32); 2] {
    let position = |x: usize| {
        let x = x as f32;
        let rx = x - map.centre_x as f32;
        (
            (map.m_yx as f32).mul_add(rx, (y as f64 + map.base[0] + map.margin) as f32),
            (map.m_xx as f32).mul_add(rx, (map.base[1] + map.margin) as f32) + x,
        )
    };
    [position(8 * k), position(8 * k + 7)]
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
        // A row without a scored site adds nothing (the same bits as adding its zeros).
        if score
            .iter()
            .flatten()
            .chain(weight.iter().flatten())
            .all(|&v| v == 0.0)
        {
            continue;
        }
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

/// One row's [`RowSums`], site by site in f64; with `blocks`, of the groups they keep only.
pub(super) fn row_sums_scalar(
    level: &TemplateLevel,
    blocks: Option<&InformativeBlocks>,
    row: &[u8],
    y: usize,
    columns: &[u16],
    map: &RowMap,
) -> RowSums {
    let mut sums = RowSums::default();
    let (score, weight) = (&mut sums.score, &mut sums.weight);
    let mut group = (usize::MAX, true);
    for &x in columns {
        let x = x as usize;
        if let Some(blocks) = blocks {
            if group.0 != x / 8 {
                let k = x / 8;
                group = (k, blocks.keeps_group(group_end_positions(map, y, k)));
            }
            if !group.1 {
                continue;
            }
        }
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
