//! One sub-block's camera fit: Gauss–Newton on binned photon counts against the template,
//! coarse to fine, weighted by the binomial variance and Huber-robust (this project's stage;
//! the paper aligns whole blocks, §4.1). The portable sums; their AVX2 twins are in x86.rs.
#![forbid(unsafe_code)]

use super::affine::AffineMotion;
use super::bins::{
    bin_observations, most_informative_bins, slot_observations, BinLayout, LaneObservations,
    RunGroups,
};
use super::template::{bilinear4, group_lanes_fit, TemplateLevel};
#[cfg(target_arch = "x86_64")]
use super::x86;
use crate::align::motion::invert;
use crate::cpu::Isa;
use ndarray::Array2;

/// Which gradient component (0 = ∂/∂y, 1 = ∂/∂x) and which basis function (0 = 1, 1 = y,
/// 2 = x, positions relative to the centre) each of the six affine parameters (b_y, b_x, m_yy,
/// m_yx, m_xy, m_xx) multiplies in the Jacobian.
pub(super) const PARAM_GRADIENT: [usize; 6] = [0, 1, 0, 0, 1, 1];
pub(super) const PARAM_BASIS: [usize; 6] = [0, 0, 1, 2, 1, 2];

/// Iterations and bin selection of [`fit_sub_block`].
#[derive(Debug, Clone, Copy)]
pub(in crate::align) struct FitSettings {
    /// Gauss–Newton iterations of every level but the finest, and of the finest.
    pub iterations: usize,
    pub fine_iterations: usize,
    /// Share of its Fisher information the finest level keeps ([`most_informative_bins`]).
    pub fine_information: f64,
    /// Halvings of the run groups the finest level's iterations but the last sum
    /// ([`RefineConfig::fine_thinning`](super::RefineConfig::fine_thinning)).
    pub fine_thinning: usize,
}

/// The factor a Gauss–Newton `step` is scaled by after `previous` (parameters weighted by
/// `scale`): this project's damping. When the step turns back, ρ = ⟨s, s'⟩ / |s'|² < 0, the
/// iterates alternate about the optimum, each step ρ times the one before, and the factor
/// 1 / (1 − ρ) (the sum of that geometric series) steps to where they would converge; ρ is
/// floored at −3. Otherwise 1. Undamped fits alternate (ρ ≈ −0.65 to −1): the template,
/// smoothed and averaged over blocks, is blurrier than the photon counts, so its gradients
/// understate how the counts change.
pub(super) fn alternation_factor(step: &[f64; 6], previous: &[f64; 6], scale: &[f64; 6]) -> f64 {
    let dot: f64 = (0..6)
        .map(|i| step[i] * previous[i] * scale[i] * scale[i])
        .sum();
    let norm: f64 = (0..6).map(|i| (previous[i] * scale[i]).powi(2)).sum();
    let rho = dot / norm.max(1e-30);
    if rho < 0.0 && rho.is_finite() {
        1.0 / (1.0 - rho.max(-3.0))
    } else {
        1.0
    }
}

/// Gauss–Newton fit of the inverse camera map (sub-block → reference) of one sub-block with
/// grey-site counts `counts` over `frames` frames; `None` when it does not converge.
///
/// Every bin contributes w·J·Jᵀ and w·J·r with J = (g_y, g_x, g_y·y, g_y·x, g_x·y, g_x·x) (g the
/// template gradient, (y, x) the bin centroid). The entries are products of a gradient pair, a
/// power of y and a power of x, so along a run of bins on one row (fixed y) only the 9 sums
/// w·g·g'·xᵖ (p ≤ 2) and 4 sums w·g·r·xᵖ (p ≤ 1) are accumulated per bin, and the run's
/// power of y is applied once: 13 products per bin instead of 27 (the same sums up to
/// rounding).
///
/// The last level fits only the bins that hold the share `settings.fine_information` of its
/// Fisher information at the motion the coarser levels reached ([`most_informative_bins`]; 1 =
/// all). A step that turns back on the previous one is shortened ([`alternation_factor`]).
pub(in crate::align) fn fit_sub_block(
    counts: &Array2<u32>,
    frames: usize,
    layouts: &[BinLayout],
    templates: &[&TemplateLevel],
    start: AffineMotion,
    centre: [f64; 2],
    settings: FitSettings,
) -> Option<AffineMotion> {
    // The tracking stage's entry into the fit (track.rs): the instruction set of the process.
    let fit = SubBlockFit {
        counts: counts.as_slice()?,
        frames,
        layouts,
        templates,
        centre,
        settings,
        isa: Isa::current(),
    };
    fit_sub_block_with_information(&fit, start).map(|(fit, _)| fit)
}

/// The Fisher information of the six inverse-camera parameters (b_y, b_x, m_yy, m_yx, m_xy,
/// m_xx) that a sub-block's photons hold: the Gauss–Newton normal matrix of the finest level's
/// last iteration.
pub(super) type Information = [[f64; 6]; 6];

/// What the fit of one sub-block reads besides its start: the grey-site photon `counts` over
/// `frames` frames, every level's bins and template (coarse to fine), the image centre, the
/// settings and the instruction set its sums run on.
#[derive(Clone, Copy)]
pub(super) struct SubBlockFit<'a> {
    pub(super) counts: &'a [u32],
    pub(super) frames: usize,
    pub(super) layouts: &'a [BinLayout],
    pub(super) templates: &'a [&'a TemplateLevel],
    pub(super) centre: [f64; 2],
    pub(super) settings: FitSettings,
    pub(super) isa: Isa,
}

/// [`fit_sub_block`] from `start` and the [`Information`] of its photons about the fitted
/// parameters; the AVX2 build of the same code where `fit.isa` offers AVX2.
pub(super) fn fit_sub_block_with_information(
    fit: &SubBlockFit,
    start: AffineMotion,
) -> Option<(AffineMotion, Information)> {
    #[cfg(target_arch = "x86_64")]
    if fit.isa.avx2() {
        return x86::fit_sub_block(fit, start);
    }
    fit_sub_block_generic(fit, start)
}

/// The fit of [`fit_sub_block_with_information`], level after level: at the finest, only the
/// bins holding the share `fine_information` of the Fisher information at the motion the
/// coarser levels reached ([`most_informative_bins`]).
#[inline(always)]
pub(super) fn fit_sub_block_generic(
    fit: &SubBlockFit,
    start: AffineMotion,
) -> Option<(AffineMotion, Information)> {
    let mut params = start.params();
    let mut information = [[0.0f64; 6]; 6];
    let last = fit.layouts.len().min(fit.templates.len()).saturating_sub(1);
    for (level, (layout, template)) in fit.layouts.iter().zip(fit.templates).enumerate() {
        let reduced = (level == last && fit.settings.fine_information < 1.0).then(|| {
            let keep = most_informative_bins(
                layout,
                template,
                &AffineMotion::from_params(params),
                fit.centre,
                fit.settings.fine_information,
            );
            layout.subset(&keep)
        });
        let level = Level::new(
            fit,
            reduced.as_ref().unwrap_or(layout),
            template,
            level == last,
        );
        level.iterate(&mut params, &mut information)?;
    }
    Some((AffineMotion::from_params(params), information))
}

/// One coarse-to-fine level of a sub-block's fit: its bins, template and observations.
struct Level<'a> {
    fit: &'a SubBlockFit<'a>,
    layout: &'a BinLayout,
    template: &'a TemplateLevel,
    /// Whether this is the finest level (its own iterations, thinning and information).
    fine: bool,
    observations: Observations,
}

/// The bins' observations as the level's sums read them.
enum Observations {
    /// Bin by bin, for the portable sums ([`run_sums`]): mean bit rate and trials.
    Bins {
        observed: Vec<f32>,
        trials: Vec<f32>,
    },
    /// As the run groups' slots (made straight from the counts), for the AVX2 sums.
    Slots(LaneObservations),
}

impl<'a> Level<'a> {
    /// The level of `layout` and `template`; the AVX2 sums read the observations laid out as
    /// the run groups' slots, the portable ones bin by bin.
    #[inline(always)]
    fn new(
        fit: &'a SubBlockFit<'a>,
        layout: &'a BinLayout,
        template: &'a TemplateLevel,
        fine: bool,
    ) -> Self {
        let by_groups = fit.isa.avx2() && group_lanes_fit(template);
        let observations = if by_groups {
            Observations::Slots(slot_observations(layout, fit.counts, fit.frames))
        } else {
            let (observed, trials) = bin_observations(layout, fit.counts, fit.frames);
            Observations::Bins { observed, trials }
        };
        Level {
            fit,
            layout,
            template,
            fine,
            observations,
        }
    }

    /// The level's Gauss–Newton iterations from `params` (updated in place); `information`
    /// takes every iteration's normal matrix. A step that turns back on the previous one is
    /// shortened ([`alternation_factor`]); `None` when a step cannot be solved for.
    #[inline(always)]
    fn iterate(&self, params: &mut [f64; 6], information: &mut Information) -> Option<()> {
        let (settings, centre) = (&self.fit.settings, self.fit.centre);
        let mut group_sums = vec![[0.0f64; 13]; self.layout.runs.len()];
        let mut previous: Option<[f64; 6]> = None;
        let iterations = if self.fine {
            settings.fine_iterations
        } else {
            settings.iterations
        };
        // Parameters in px at the image's far edges, for the alternation test.
        let scale = [1.0, 1.0, centre[0], centre[1], centre[0], centre[1]];
        let mut converging = false;
        for iteration in 0..iterations {
            // Every `group_step`-th run group: thinned iterations of the finest level.
            let group_step = if self.fine && !converging {
                settings.thinned_group_step(iteration, iterations)
            } else {
                1
            };
            let motion = AffineMotion::from_params(*params);
            let (normal, rhs) = self.normal_equations(&motion, group_step, &mut group_sums);
            let step = gauss_newton_step(&normal, &rhs, previous.as_ref(), &scale, information)?;
            previous = Some(step);
            params.iter_mut().zip(&step).for_each(|(p, s)| *p += s);
            if step_size_px(&step, centre) < 0.002 && iteration > 0 {
                if group_step == 1 {
                    break;
                }
                converging = true;
            }
        }
        Some(())
    }

    /// The upper triangle of the normal equations and their right-hand side at `motion`, over
    /// the runs of every `group_step`-th run group (`group_sums`: the AVX2 sums' scratch).
    #[inline(always)]
    fn normal_equations(
        &self,
        motion: &AffineMotion,
        group_step: usize,
        group_sums: &mut [[f64; 13]],
    ) -> ([[f64; 6]; 6], [f64; 6]) {
        let (layout, template, centre) = (self.layout, self.template, self.fit.centre);
        let mut normal = [[0.0f64; 6]; 6];
        let mut rhs = [0.0f64; 6];
        #[cfg(target_arch = "x86_64")]
        if let Observations::Slots(slots) = &self.observations {
            let runs = GroupedRuns {
                template,
                groups: &layout.groups,
                slots,
            };
            x86::run_sums_groups(self.fit.isa, &runs, motion, centre, group_step, group_sums);
        }
        for (r, run) in layout.runs.iter().enumerate() {
            if !layout.groups.group_of_run[r].is_multiple_of(group_step) {
                continue;
            }
            // Per gradient pair (yy, yx, xx) and power of x (0, 1, 2): Σ w·g·g'·xᵖ at
            // [pair + 3·p]; per gradient (y, x) and power of x (0, 1): Σ w·g·r·xᵖ at
            // [9 + g + 2·p].
            let sums = match &self.observations {
                Observations::Slots(_) => group_sums[r],
                Observations::Bins { observed, trials } => {
                    let bins = RunBins {
                        row: layout.centroid[run.start][0] as f32,
                        x: &layout.x[run.clone()],
                        x2: &layout.x2[run.clone()],
                        observed: &observed[run.clone()],
                        trials: &trials[run.clone()],
                    };
                    run_sums(template, motion, centre, &bins)
                }
            };
            add_run(&mut normal, &mut rhs, layout.centroid[run.start][0], &sums);
        }
        (normal, rhs)
    }
}

/// The runs of a level grouped for the AVX2 sums: the template they sample, the run groups
/// and their observations laid out as the groups' slots.
pub(super) struct GroupedRuns<'a> {
    pub(super) template: &'a TemplateLevel,
    pub(super) groups: &'a RunGroups,
    pub(super) slots: &'a LaneObservations,
}

/// The Gauss–Newton step of the normal equations (upper triangle `normal`, right-hand side
/// `rhs`), shortened after the `previous` step by [`alternation_factor`] (parameters weighted
/// by `scale`); `information` takes the full normal matrix. `None` when the matrix cannot be
/// inverted or the step is not finite.
#[inline(always)]
fn gauss_newton_step(
    normal: &[[f64; 6]; 6],
    rhs: &[f64; 6],
    previous: Option<&[f64; 6]>,
    scale: &[f64; 6],
    information: &mut Information,
) -> Option<[f64; 6]> {
    let normal = symmetric_from_upper(normal);
    for (row, values) in information.iter_mut().zip(&normal) {
        row.copy_from_slice(values);
    }
    let inv = invert(normal)?;
    let mut step: [f64; 6] = std::array::from_fn(|r| (0..6).map(|c| inv[r][c] * rhs[c]).sum());
    if step.iter().any(|v| !v.is_finite()) {
        return None;
    }
    if let Some(previous) = previous {
        let factor = alternation_factor(&step, previous, scale);
        step.iter_mut().for_each(|v| *v *= factor);
    }
    Some(step)
}

impl FitSettings {
    /// The run-group step of iteration `iteration` of `iterations` at the finest level before
    /// it converges: every 2^k-th group, k = min(`fine_thinning`, iterations left after this
    /// one, 8), so the last iteration sums every group.
    pub(super) fn thinned_group_step(&self, iteration: usize, iterations: usize) -> usize {
        if iteration + 1 < iterations {
            1 << self.fine_thinning.min(iterations - 1 - iteration).min(8)
        } else {
            1
        }
    }
}

/// Adds a run's sums to the Gauss–Newton normal equations' upper triangle `normal` and
/// right-hand side `rhs`: the run at bin row `y` with, per gradient pair (yy, yx, xx) and power
/// of x (0, 1, 2), Σ w·g·g'·xᵖ at `sums[pair + 3·p]` and, per gradient (y, x) and power of x
/// (0, 1), Σ w·g·r·xᵖ at `sums[9 + g + 2·p]`; each parameter's basis function brings its
/// power of y ([`PARAM_GRADIENT`], [`PARAM_BASIS`]).
#[inline(always)]
pub(super) fn add_run(normal: &mut [[f64; 6]; 6], rhs: &mut [f64; 6], y: f64, sums: &[f64; 13]) {
    let y_power = [1.0, y, y * y];
    for p in 0..6 {
        let (gp, bp) = (PARAM_GRADIENT[p], PARAM_BASIS[p]);
        for q in p..6 {
            let (gq, bq) = (PARAM_GRADIENT[q], PARAM_BASIS[q]);
            let pair = gp + gq;
            let py = (bp == 1) as usize + (bq == 1) as usize;
            let px = (bp == 2) as usize + (bq == 2) as usize;
            normal[p][q] += y_power[py] * sums[pair + 3 * px];
        }
        let py = (bp == 1) as usize;
        let px = (bp == 2) as usize;
        rhs[p] += y_power[py] * sums[9 + gp + 2 * px];
    }
}

/// The symmetric matrix from its upper triangle `upper`, the diagonal raised by 1e-6.
pub(super) fn symmetric_from_upper(upper: &[[f64; 6]; 6]) -> Vec<Vec<f64>> {
    (0..6)
        .map(|r| {
            (0..6)
                .map(|c| match r.cmp(&c) {
                    std::cmp::Ordering::Less => upper[r][c],
                    std::cmp::Ordering::Equal => upper[r][r] * (1.0 + 1e-6),
                    std::cmp::Ordering::Greater => upper[c][r],
                })
                .collect()
        })
        .collect()
}

/// How far a parameter `step` moves the image, px: the translation's length plus the linear
/// part's entries at the distance of the farther image edge from the `centre`.
pub(super) fn step_size_px(step: &[f64; 6], centre: [f64; 2]) -> f64 {
    (step[0].powi(2) + step[1].powi(2)).sqrt()
        + centre[0].max(centre[1]) * step[2..].iter().map(|v| v.abs()).sum::<f64>()
}

/// The bins of one run of a [`BinLayout`] (one centroid row), as [`fit_sub_block`] reads them.
pub(super) struct RunBins<'a> {
    /// Centroid row (relative to the image centre), shared by the run.
    pub(super) row: f32,
    /// Centroid column of every bin, and its square.
    pub(super) x: &'a [f32],
    pub(super) x2: &'a [f32],
    /// Mean bit rate and number of trials of every bin.
    pub(super) observed: &'a [f32],
    pub(super) trials: &'a [f32],
}

/// The parts of a run's sample positions that do not change along it, in single precision:
/// (row + c_y, b_y + m_yy·row, b_x + m_xy·row) (the last two made in double precision), and
/// m_yx, m_xx and c_x. A bin at column x then samples the template at y = (row + c_y) + ((b_y +
/// m_yy·row) + m_yx·x), x' = (x + c_x) + ((b_x + m_xy·row) + m_xx·x), `AffineMotion::at` added
/// as `sample_template` adds it.
#[inline(always)]
pub(super) fn run_frame(motion: &AffineMotion, centre: [f64; 2], row: f32) -> ([f32; 3], [f32; 3]) {
    let r = row as f64;
    (
        [
            row + centre[0] as f32,
            (motion.b[0] + motion.m[0][0] * r) as f32,
            (motion.b[1] + motion.m[1][0] * r) as f32,
        ],
        [
            motion.m[0][1] as f32,
            motion.m[1][1] as f32,
            centre[1] as f32,
        ],
    )
}

/// The 13 sums of one run of [`fit_sub_block`]: per gradient pair (yy, yx, xx) and power of x
/// (0, 1, 2) Σ w·g·g'·xᵖ at [pair + 3·p]; per gradient (y, x) and power of x (0, 1) Σ w·g·r·xᵖ
/// at [9 + g + 2·p]; bins in order, those whose position leaves the template skipped.
///
/// In single precision (positions as [`run_frame`], the template's bilinear value and gradient,
/// the weights and the sums along the run), returned in double: a run is one row of bins (at
/// most a few hundred), so the sums keep about six digits, far below the photon noise they are
/// fitted to, and `run_sums_group_avx2` (x86.rs) sums eight runs per register instead of four
/// (this project's choice; a test bounds the error against double precision).
#[inline(always)]
pub(super) fn run_sums(
    template: &TemplateLevel,
    motion: &AffineMotion,
    centre: [f64; 2],
    bins: &RunBins,
) -> [f64; 13] {
    let ([row_y, base_y, base_x], [m_yx, m_xx, centre_x]) = run_frame(motion, centre, bins.row);
    let (h, w) = (template.height, template.width);
    let (y_max, x_max) = ((h - 1) as f32, (w - 1) as f32);
    let mut sums = [0.0f32; 13];
    for b in 0..bins.x.len() {
        let (x, x2) = (bins.x[b], bins.x2[b]);
        let (observed, trials) = (bins.observed[b], bins.trials[b]);
        let py = row_y + (base_y + m_yx * x);
        let px = (x + centre_x) + (base_x + m_xx * x);
        if !(py >= 0.0 && px >= 0.0 && py <= y_max && px <= x_max) {
            continue;
        }
        let (y0, x0) = ((py as i32).min(h as i32 - 2), (px as i32).min(w as i32 - 2));
        let (fy, fx) = (py - y0 as f32, px - x0 as f32);
        let i = y0 as usize * w + x0 as usize;
        let (top, bottom) = (
            &template.samples[i..i + 2],
            &template.samples[i + w..i + w + 2],
        );
        let [t, gy, gx, _] = bilinear4(top[0], top[1], bottom[0], bottom[1], fx, fy);
        let residual = observed - t;
        // Inverse binomial variance of the bin mean, and a Huber weight at 3 std (moving
        // objects, occlusions): z = |r|·√(1/var), weight (1 or 3/z)/var, with the square root
        // and a second division only past 3 std.
        let inv_variance = trials / (t * (1.0 - t)).max(0.01);
        let z2 = residual * residual * inv_variance;
        let weight = if z2 > 9.0 {
            3.0 * inv_variance.sqrt() / residual.abs()
        } else {
            inv_variance
        };
        let (wgy, wgx) = (weight * gy, weight * gx);
        let pairs = [wgy * gy, wgy * gx, wgx * gx];
        for (i, &v) in pairs.iter().enumerate() {
            sums[i] += v;
            sums[3 + i] += v * x;
            sums[6 + i] += v * x2;
        }
        let (ry, rx) = (wgy * residual, wgx * residual);
        sums[9] += ry;
        sums[10] += rx;
        sums[11] += ry * x;
        sums[12] += rx * x;
    }
    sums.map(f64::from)
}
