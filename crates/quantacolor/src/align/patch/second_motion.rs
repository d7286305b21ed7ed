//! The second motion model (paper §4.1: patch-wise alignment must follow independently moving
//! objects): one common translation for each large set of tiles the affine camera fit rejects,
//! scored by L1 patch costs on levels 1 and 0 and kept only where it beats the camera flow.
//! This project's own heuristics (margins, the texture-period check), not a paper step.
#![forbid(unsafe_code)]

use super::cost::{offset_cost, window_costs, Tile};
use super::lucas_kanade::LkScratch;
use super::{Norm, Pyramid, ReferenceAligner, TileGrid};
use crate::cpu::Isa;
use crate::filters::gaussian_blur;
use ndarray::{Array2, Array3};
use rayon::prelude::*;
use std::borrow::Cow;

/// Which tiles get a second motion and how far it is searched
/// ([`ReferenceAligner::follow_second_motion_in`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SecondMotionSearch {
    /// A tile is rejected by the camera fit where its flow lies more than this (px) from it.
    pub tolerance_px: f32,
    /// Search radius (px) around a rejected set's median flow.
    pub radius_px: usize,
    /// Fewest tiles of an 8-connected rejected set that gets a translation (0 counts as 1).
    pub min_tiles: usize,
}

impl ReferenceAligner {
    /// Second motion model for tiles the camera model rejects (paper §4.1: patch-wise alignment
    /// must follow independently moving objects; the robust affine camera fit leaves them out).
    ///
    /// `flow` is a block's tile flow after the camera fit, `camera` the fit itself. Tiles whose
    /// flow lies more than `tolerance` px from the fit are rejected; each 8-connected set of at
    /// least `min_tiles` rejected tiles gets one common translation: every integer offset within
    /// ±`radius` px of the set's median flow is scored by the summed L1 patch cost over the set
    /// and its neighbouring tiles (whose edge against the rest of the scene resolves periodic
    /// texture that a single tile cannot), on pyramid level 1 and then within ±f px on level 0,
    /// and refined to sub-pixel as the median of the tiles' Lucas–Kanade results. Every tile
    /// within two tiles of the set then takes that translation where its own patch cost there
    /// is lower than at the camera flow, and the camera flow otherwise; the whole set keeps the
    /// camera flow when the translation's offset from the camera is a period of the reference's
    /// own texture ([`is_texture_period`]): a grating matched a whole number of periods off, which
    /// long blocks (whose camera fit can sit half a pixel off the best integer match) otherwise
    /// sent a period away.
    pub fn follow_second_motion(
        &self,
        block: &Array2<f32>,
        flow: &Array3<f32>,
        camera: &Array3<f32>,
        tolerance: f32,
        radius: usize,
        min_tiles: usize,
    ) -> Array3<f32> {
        let search = SecondMotionSearch {
            tolerance_px: tolerance,
            radius_px: radius,
            min_tiles,
        };
        self.second_motion(block, None, flow, camera, &search)
    }

    /// [`ReferenceAligner::follow_second_motion`] with the block's pyramid `alt` from
    /// [`ReferenceAligner::align_with_pyramid`]: its levels 0 and 1 are the smoothed block and
    /// its level-1 downsampling that the second motion scores, so they are not made again
    /// (where the finest level is not downsampled; otherwise they are made from `block`).
    /// The same numbers as [`ReferenceAligner::follow_second_motion`] with `search`'s
    /// tolerance, radius and least set size.
    pub fn follow_second_motion_in(
        &self,
        block: &Array2<f32>,
        alt: &Pyramid,
        flow: &Array3<f32>,
        camera: &Array3<f32>,
        search: SecondMotionSearch,
    ) -> Array3<f32> {
        self.second_motion(block, Some(alt), flow, camera, &search)
    }

    /// [`ReferenceAligner::follow_second_motion`] on the block's pyramid `alt` where given.
    fn second_motion(
        &self,
        block: &Array2<f32>,
        alt: Option<&Pyramid>,
        flow: &Array3<f32>,
        camera: &Array3<f32>,
        search: &SecondMotionSearch,
    ) -> Array3<f32> {
        let &SecondMotionSearch {
            tolerance_px: tolerance,
            radius_px: radius,
            min_tiles,
        } = search;
        let grid = &self.grids[0];
        if block.dim() != self.dim()
            || flow.dim() != (grid.tiles_y, grid.tiles_x, 2)
            || camera.dim() != flow.dim()
        {
            return flow.clone();
        }
        let components = rejected_components(flow, camera, tolerance, min_tiles);
        if components.is_empty() {
            return flow.clone();
        }
        let levels = self.second_motion_levels(block, alt);
        let scorer = levels.scorer(self, camera);
        let mut out = flow.clone();
        for component in &components {
            let support = scorer.dilate(component, 1).tiles();
            let f = scorer.factor;
            let median = (
                tile_median(flow, component, 0),
                tile_median(flow, component, 1),
            );
            let coarse = scorer.common_offset(
                &support,
                ScoredLevel::Coarse,
                (
                    (median.0 / f as f32).round() as isize,
                    (median.1 / f as f32).round() as isize,
                ),
                (radius / f) as isize,
            );
            let best = scorer.common_offset(
                &support,
                ScoredLevel::Fine,
                (coarse.0 * f as isize, coarse.1 * f as isize),
                f as isize,
            );
            let translation = self.sub_pixel_translation(component, scorer.alt0, best);
            let region = scorer.dilate(component, 2);
            let mut label = scorer.label_tiles(component, &region, best);
            fill_ambiguous_labels(&mut label, &region);
            let followers: Vec<(usize, usize)> = label
                .indexed_iter()
                .filter(|&((i, j), l)| region.0[[i, j]] && *l == Some(true))
                .map(|(p, _)| p)
                .collect();
            let offset_from_camera = |(i, j): (usize, usize)| {
                (
                    (translation.0 - camera[[i, j, 0]]).round() as isize,
                    (translation.1 - camera[[i, j, 1]]).round() as isize,
                )
            };
            if is_texture_period(scorer.ref0, grid, &followers, offset_from_camera, self.isa) {
                label.fill(Some(false));
            }
            for ((i, j), &near) in region.0.indexed_iter() {
                if !near {
                    continue;
                }
                let source = if label[[i, j]] == Some(true) {
                    [translation.0, translation.1]
                } else {
                    [camera[[i, j, 0]], camera[[i, j, 1]]]
                };
                out[[i, j, 0]] = source[0];
                out[[i, j, 1]] = source[1];
            }
        }
        out
    }

    /// The smoothed block and its downsampling to pyramid level 1 (level 0 alone when the
    /// pyramid has one level) that the second motion scores: the block pyramid's levels 0 and 1
    /// where `alt` is given and level 0 is not downsampled (`box_downsample` by 1 is a copy),
    /// made from `block` otherwise.
    fn second_motion_levels<'a>(
        &self,
        block: &Array2<f32>,
        alt: Option<&'a Pyramid>,
    ) -> SecondMotionLevels<'a> {
        let factor = if self.grids.len() > 1 {
            self.config.downsample_factors[1]
        } else {
            1
        };
        let (alt0, alt1) = match alt {
            Some(p)
                if self.config.downsample_factors[0] == 1
                    && p.levels.len() >= self.grids.len()
                    && p.levels[0].dim() == block.dim() =>
            {
                let alt1 = &p.levels[if factor > 1 { 1 } else { 0 }];
                (Cow::Borrowed(&p.levels[0]), Cow::Borrowed(alt1))
            }
            _ => {
                let alt0 = if self.config.presmooth_sigma > 0.0 {
                    gaussian_blur(
                        &block.as_standard_layout().to_owned(),
                        self.config.presmooth_sigma,
                    )
                } else {
                    block.as_standard_layout().to_owned()
                };
                let alt1 = crate::filters::box_downsample(&alt0, factor);
                (Cow::Owned(alt0), Cow::Owned(alt1))
            }
        };
        SecondMotionLevels { alt0, alt1, factor }
    }

    /// The second motion's translation to sub-pixel precision: the median of the Lucas–Kanade
    /// results of the `component`'s tiles started at the integer offset `start` (`start` when
    /// none converges).
    fn sub_pixel_translation(
        &self,
        component: &[(usize, usize)],
        alt0: &Array2<f32>,
        start: (isize, isize),
    ) -> (f32, f32) {
        let grid = &self.grids[0];
        let start = (start.0 as f32, start.1 as f32);
        let mut scratch = LkScratch::default();
        let refined: Vec<(f32, f32)> = component
            .iter()
            .filter_map(|&(i, j)| {
                let origin = (i * grid.tile_stride, j * grid.tile_stride);
                self.refine(i * grid.tiles_x + j, alt0, origin, start, &mut scratch)
            })
            .collect();
        if refined.is_empty() {
            return start;
        }
        let mut ys: Vec<f32> = refined.iter().map(|r| r.0).collect();
        let mut xs: Vec<f32> = refined.iter().map(|r| r.1).collect();
        ys.sort_by(f32::total_cmp);
        xs.sort_by(f32::total_cmp);
        (ys[ys.len() / 2], xs[xs.len() / 2])
    }
}

/// The 8-connected sets of at least `min_tiles` (at least one) tiles whose `flow` lies more
/// than `tolerance` px from the `camera` fit.
pub(super) fn rejected_components(
    flow: &Array3<f32>,
    camera: &Array3<f32>,
    tolerance: f32,
    min_tiles: usize,
) -> Vec<Vec<(usize, usize)>> {
    let (ty, tx, _) = flow.dim();
    let rejected = Array2::from_shape_fn((ty, tx), |(i, j)| {
        let dy = flow[[i, j, 0]] - camera[[i, j, 0]];
        let dx = flow[[i, j, 1]] - camera[[i, j, 1]];
        (dy * dy + dx * dx).sqrt() > tolerance
    });
    connected_components(&rejected)
        .into_iter()
        .filter(|c| c.len() >= min_tiles.max(1))
        .collect()
}

/// The median (upper, of an even count) of flow component `c` over `tiles`.
fn tile_median(flow: &Array3<f32>, tiles: &[(usize, usize)], c: usize) -> f32 {
    let mut v: Vec<f32> = tiles.iter().map(|&(i, j)| flow[[i, j, c]]).collect();
    v.sort_by(f32::total_cmp);
    v[v.len() / 2]
}

/// The block's two levels that [`ReferenceAligner::second_motion`] scores, and the
/// downsampling `factor` from the first to the second.
struct SecondMotionLevels<'a> {
    alt0: Cow<'a, Array2<f32>>,
    alt1: Cow<'a, Array2<f32>>,
    factor: usize,
}

impl SecondMotionLevels<'_> {
    fn scorer<'s>(&'s self, aligner: &'s ReferenceAligner, camera: &'s Array3<f32>) -> Scorer<'s> {
        let ref0 = &aligner.pyramid.levels[0];
        Scorer {
            grid: &aligner.grids[0],
            ref0,
            ref1: if self.factor > 1 {
                &aligner.pyramid.levels[1]
            } else {
                ref0
            },
            alt0: &self.alt0,
            alt1: &self.alt1,
            factor: self.factor,
            camera,
            isa: aligner.isa,
        }
    }
}

/// Which of the two levels of [`SecondMotionLevels`] a cost is taken on.
#[derive(Clone, Copy)]
enum ScoredLevel {
    /// Level 0 (the block's resolution).
    Fine,
    /// Level 1 (downsampled by the factor).
    Coarse,
}

/// A set of tiles of the finest grid as a mask.
pub(super) struct TileMask(pub(super) Array2<bool>);

impl TileMask {
    fn tiles(&self) -> Vec<(usize, usize)> {
        self.0
            .indexed_iter()
            .filter(|(_, &m)| m)
            .map(|(p, _)| p)
            .collect()
    }
}

/// L1 patch costs of the second motion's tiles between the reference's and the block's levels
/// ([`offset_cost`], [`window_costs`]), and the camera flow they are compared against.
struct Scorer<'a> {
    grid: &'a TileGrid,
    ref0: &'a Array2<f32>,
    ref1: &'a Array2<f32>,
    alt0: &'a Array2<f32>,
    alt1: &'a Array2<f32>,
    factor: usize,
    camera: &'a Array3<f32>,
    isa: Isa,
}

impl Scorer<'_> {
    /// Tile `(i, j)` on the level: its images, origin and size there, scored by L1.
    fn tile_at(&self, level: ScoredLevel, i: usize, j: usize) -> Tile<'_> {
        let (oy, ox) = (i * self.grid.tile_stride, j * self.grid.tile_stride);
        let (ts, f) = (self.grid.tile_size, self.factor);
        let (reference, alternate, origin, ts) = match level {
            ScoredLevel::Fine => (self.ref0, self.alt0, (oy, ox), ts),
            ScoredLevel::Coarse => (self.ref1, self.alt1, (oy / f, ox / f), (ts / f).max(2)),
        };
        Tile {
            reference,
            alternate,
            origin,
            ts,
            norm: Norm::L1,
            isa: self.isa,
        }
    }

    /// The cost of tile `(i, j)` on the level at the offset `d`.
    fn cost(&self, level: ScoredLevel, i: usize, j: usize, d: (isize, isize)) -> f32 {
        offset_cost(&self.tile_at(level, i, j), d)
    }

    /// The costs of the `side × side` offsets from `corner` (row-major) at once.
    fn window(
        &self,
        level: ScoredLevel,
        (i, j): (usize, usize),
        corner: (isize, isize),
        side: usize,
        out: &mut [f32],
    ) {
        window_costs(&self.tile_at(level, i, j), corner, side, out)
    }

    /// The cost at the camera flow (rounded to the level's pixels).
    fn camera_cost(&self, level: ScoredLevel, i: usize, j: usize) -> f32 {
        let scale = match level {
            ScoredLevel::Fine => 1.0,
            ScoredLevel::Coarse => self.factor as f32,
        };
        let d = (
            (self.camera[[i, j, 0]] / scale).round() as isize,
            (self.camera[[i, j, 1]] / scale).round() as isize,
        );
        self.cost(level, i, j, d)
    }

    /// The tiles within `dist` tiles (Chebyshev) of `tiles`.
    fn dilate(&self, tiles: &[(usize, usize)], dist: usize) -> TileMask {
        let (ty, tx) = (self.grid.tiles_y, self.grid.tiles_x);
        let mut mask = Array2::from_elem((ty, tx), false);
        for &(i, j) in tiles {
            for y in i.saturating_sub(dist)..(i + dist + 1).min(ty) {
                for x in j.saturating_sub(dist)..(j + dist + 1).min(tx) {
                    mask[[y, x]] = true;
                }
            }
        }
        TileMask(mask)
    }

    /// The offset within ±`r` of `centre` (px of `level`) that minimises the total cost when
    /// every tile takes the better of the camera flow and the offset: tiles of the camera's
    /// motion score the same for every offset, so the minimum is the motion of the others
    /// (ties: the offset nearest zero, then the first in row-major order).
    fn common_offset(
        &self,
        tiles: &[(usize, usize)],
        level: ScoredLevel,
        centre: (isize, isize),
        r: isize,
    ) -> (isize, isize) {
        let cam: Vec<f32> = tiles
            .iter()
            .map(|&(i, j)| self.camera_cost(level, i, j))
            .collect();
        let side = (2 * r + 1) as usize;
        // Per tile, its cost at every offset, in the order of `offsets`.
        let table: Vec<Vec<f32>> = tiles
            .par_iter()
            .map(|&tile| {
                let mut costs = vec![0.0f32; side * side];
                self.window(level, tile, (centre.0 - r, centre.1 - r), side, &mut costs);
                costs
            })
            .collect();
        let offsets: Vec<(isize, isize)> = (-r..=r)
            .flat_map(|dy| (-r..=r).map(move |dx| (centre.0 + dy, centre.1 + dx)))
            .collect();
        offsets
            .par_iter()
            .enumerate()
            .map(|(o, &d)| {
                let total: f32 = table
                    .iter()
                    .zip(&cam)
                    .map(|(costs, &c)| (costs[o] / SWITCH_MARGIN).min(c))
                    .filter(|c| c.is_finite())
                    .sum();
                (total, d)
            })
            .min_by(|a, b| {
                a.0.total_cmp(&b.0)
                    .then((a.1 .0.abs() + a.1 .1.abs()).cmp(&(b.1 .0.abs() + b.1 .1.abs())))
            })
            .map(|(_, d)| d)
            .expect("at least one offset")
    }

    /// Each tile of `region`: `Some(true)` where its 3x3 window of tiles costs markedly less
    /// at the offset `best` than at the camera flow ([`SWITCH_MARGIN`]), `Some(false)` where
    /// markedly more, `None` where ambiguous (one tile's costs are too noisy at low light; a
    /// periodic texture whose period is the motion between the two is ambiguous too).
    fn label_tiles(
        &self,
        component: &[(usize, usize)],
        region: &TileMask,
        best: (isize, isize),
    ) -> Array2<Option<bool>> {
        let (ty, tx) = (self.grid.tiles_y, self.grid.tiles_x);
        // Per tile: its costs at the offset and at the camera.
        let mut costs = Array2::<(f32, f32)>::from_elem((ty, tx), (0.0, 0.0));
        for ((i, j), &near) in self.dilate(component, 3).0.indexed_iter() {
            if near {
                let (c_obj, c_cam) = (
                    self.cost(ScoredLevel::Fine, i, j, best),
                    self.camera_cost(ScoredLevel::Fine, i, j),
                );
                if c_obj.is_finite() && c_cam.is_finite() {
                    costs[[i, j]] = (c_obj, c_cam);
                }
            }
        }
        let mut label = Array2::<Option<bool>>::from_elem((ty, tx), None);
        for ((i, j), &near) in region.0.indexed_iter() {
            if !near {
                continue;
            }
            let (mut o, mut c) = (0.0, 0.0);
            for y in i.saturating_sub(1)..(i + 2).min(ty) {
                for x in j.saturating_sub(1)..(j + 2).min(tx) {
                    o += costs[[y, x]].0;
                    c += costs[[y, x]].1;
                }
            }
            label[[i, j]] = if o < SWITCH_MARGIN * c {
                Some(true)
            } else if c < SWITCH_MARGIN * o {
                Some(false)
            } else {
                None
            };
        }
        label
    }
}

/// Ambiguous tiles of `region` take the majority label of their decided 8-neighbours in it
/// (ties: the camera), repeatedly (at most 16 rounds), so that labels grow inward from the
/// decided tiles.
pub(super) fn fill_ambiguous_labels(label: &mut Array2<Option<bool>>, region: &TileMask) {
    let (ty, tx) = label.dim();
    let region = &region.0;
    for _ in 0..16 {
        let mut changed = false;
        let snapshot = label.clone();
        for ((i, j), &near) in region.indexed_iter() {
            if !near || snapshot[[i, j]].is_some() {
                continue;
            }
            let (mut yes, mut no) = (0, 0);
            for y in i.saturating_sub(1)..(i + 2).min(ty) {
                for x in j.saturating_sub(1)..(j + 2).min(tx) {
                    match snapshot[[y, x]] {
                        Some(true) if region[[y, x]] => yes += 1,
                        Some(false) if region[[y, x]] => no += 1,
                        _ => {}
                    }
                }
            }
            if yes + no > 0 {
                label[[i, j]] = Some(yes > no);
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }
}

/// A tile leaves the camera's motion for a second one only where its patch cost there is below
/// this fraction of its cost at the camera flow: periodic static texture, equally good at a
/// period's offset, then stays with the camera instead of following the photon noise.
const SWITCH_MARGIN: f32 = 0.9;

/// A second motion is taken for a texture period ([`is_texture_period`]) when the reference
/// matches itself at the motion's offset from the camera with a summed L1 cost below this
/// fraction of the mean cost at the four offsets [`PERIOD_PROBE_PX`] away. This project's
/// heuristic (its measurements: docs/tuning.md).
const PERIOD_RATIO: f32 = 0.75;

/// Distance (px) of the four offsets that [`is_texture_period`] compares the reference's
/// self-match against: a quarter of the chart's 8 px grating period, so the probes fall
/// between the grating's repeats.
const PERIOD_PROBE_PX: isize = 2;

/// Whether the reference shifted onto itself by each tile's `offset` (px, integer) matches
/// itself markedly better there than at the offsets [`PERIOD_PROBE_PX`] away in y and in x,
/// summed over `tiles` of `grid` (L1 patch costs; [`PERIOD_RATIO`]). A block that matches the
/// reference at the camera's motion plus such an offset matches it equally well at the camera's
/// motion: a static periodic texture (a grating matched a whole number of periods off), not a
/// second motion. A natural texture moved by an object matches itself no better at the object's
/// offset than beside it.
fn is_texture_period(
    reference: &Array2<f32>,
    grid: &TileGrid,
    tiles: &[(usize, usize)],
    offset: impl Fn((usize, usize)) -> (isize, isize),
    isa: Isa,
) -> bool {
    let ts = grid.tile_size;
    let (mut at_offset, mut beside) = (0.0f32, 0.0f32);
    for &(i, j) in tiles {
        let origin = (i * grid.tile_stride, j * grid.tile_stride);
        let d = offset((i, j));
        let tile = Tile {
            reference,
            alternate: reference,
            origin,
            ts,
            norm: Norm::L1,
            isa,
        };
        let cost = |d: (isize, isize)| offset_cost(&tile, d);
        let here = cost(d);
        let p = PERIOD_PROBE_PX;
        let around = [(p, 0), (-p, 0), (0, p), (0, -p)].map(|(a, b)| cost((d.0 + a, d.1 + b)));
        if here.is_finite() && around.iter().all(|c| c.is_finite()) {
            at_offset += here;
            beside += around.iter().sum::<f32>() / 4.0;
        }
    }
    beside > 0.0 && at_offset < PERIOD_RATIO * beside
}

/// 8-connected sets of `true` cells, each as its (row, column) list.
fn connected_components(mask: &Array2<bool>) -> Vec<Vec<(usize, usize)>> {
    let (h, w) = mask.dim();
    let mut seen = Array2::from_elem((h, w), false);
    let mut out = Vec::new();
    for start in mask.indexed_iter().filter(|(_, &m)| m).map(|(p, _)| p) {
        if seen[start] {
            continue;
        }
        seen[start] = true;
        let mut stack = vec![start];
        let mut component = Vec::new();
        while let Some((i, j)) = stack.pop() {
            component.push((i, j));
            for y in i.saturating_sub(1)..(i + 2).min(h) {
                for x in j.saturating_sub(1)..(j + 2).min(w) {
                    if mask[[y, x]] && !seen[[y, x]] {
                        seen[[y, x]] = true;
                        stack.push((y, x));
                    }
                }
            }
        }
        out.push(component);
    }
    out
}
