//! The phase bins: every site's robustness-weighted sample splatted into the bin nearest its
//! reference position ([`MergeAccumulator::add`]; this project's implementation of the sum of
//! supplement Eq. 1–3), and the coarser bins of the sparse channels.
#![forbid(unsafe_code)]

use super::*;

/// Sub-blocks whose site targets are made before their samples are splatted together
/// ([`MergeAccumulator::add`]): 8 MB of targets for 496x254 sites.
const SPLAT_GROUP: usize = 8;
/// Bin rows per band of the splat: 16 rows of 12 planes of 1016 bins (496 px wide at 2 bins per
/// px) are 0.8 MB, within a core's L2 cache.
const SPLAT_BAND_ROWS: usize = 16;

/// Kernel scale (covariance factor), relative to the densest channel's, from which a channel
/// counts as sparse and takes the coarser phase bins of
/// `AccumulateConfig::sparse_bins_per_output_px` (its kernel std is then at least 1.5 times the
/// densest channel's). On the colour-SPAD CFA at spacing exponent 0.5 (the default pipeline with
/// denoising) G, B and R have 2.4, 3.5 and 3.5 times W's scale; Bayer's R and B have at most
/// twice G's, and stay on the phase bins (measured: docs/tuning.md).
const SPARSE_SCALE_RATIO: f32 = 2.25;

impl MergeAccumulator<'_> {
    /// Splats `sub_blocks` (whose `SubBlockRobustness::Block(i)` index `block_robustness`)
    /// into the phase bins.
    pub fn add(&mut self, sub_blocks: &[SubBlock], block_robustness: &[Array2<f32>]) -> Result<()> {
        let (h, w) = (self.cfa.height(), self.cfa.width());
        validate(
            sub_blocks,
            block_robustness,
            self.kernels,
            h,
            w,
            &self.config,
            self.model.max_sample(),
        )?;
        let block_maps: Vec<_> = block_robustness
            .iter()
            .map(|m| m.as_standard_layout())
            .collect();
        // The site targets and row spans of a group, kept from one call to the next (the
        // targets are 8 MB: fresh pages and their zeroing cost more than the splat of a small
        // group). Every entry a group uses is written before it is read.
        let group_len = SPLAT_GROUP.min(sub_blocks.len());
        let mut targets = std::mem::take(&mut self.targets);
        let mut row_bins = std::mem::take(&mut self.row_bins);
        if targets.len() < group_len * h * w {
            // Written by all threads: one thread's first touch of 8 MB left the other idle.
            targets = Vec::new();
            cpu::resize_par(&mut targets, group_len * h * w, (u32::MAX, 0.0f32));
            row_bins = vec![(u32::MAX, 0u32); group_len * h];
        }
        // Sub-blocks are splatted a group at a time: the target bins of all sites of the group
        // first, then the samples band of bin rows by band of bin rows ([`Self::splat_group`]).
        for group in sub_blocks.chunks(SPLAT_GROUP) {
            for (k, sub) in group.iter().enumerate() {
                let block_map = |i: usize| block_maps[i].as_slice();
                self.fill_targets(
                    sub,
                    block_map,
                    &mut targets[k * h * w..(k + 1) * h * w],
                    &mut row_bins[k * h..(k + 1) * h],
                );
            }
            self.splat_group(group, &targets, &row_bins);
        }
        self.targets = targets;
        self.row_bins = row_bins;
        Ok(())
    }

    /// The target bin and robustness weight of every site of sub-block `sub` (`block_map(i)`:
    /// block `i`'s robustness map, row-major), and in `spans` the range of target bins of
    /// every row of sites, so that a band skips the rows that cannot reach it.
    fn fill_targets<'m>(
        &self,
        sub: &SubBlock,
        block_map: impl Fn(usize) -> Option<&'m [f32]>,
        targets: &mut [(u32, f32)],
        spans: &mut [(u32, u32)],
    ) {
        let (h, w) = (self.cfa.height(), self.cfa.width());
        let own = match &sub.robustness {
            SubBlockRobustness::Map(m) => Some(m.as_standard_layout()),
            _ => None,
        };
        let robust: Option<&[f32]> = match &sub.robustness {
            SubBlockRobustness::Full => None,
            SubBlockRobustness::Block(i) => block_map(*i),
            SubBlockRobustness::Map(_) => own.as_ref().and_then(|m| m.as_slice()),
        };
        let grid = TargetGrid {
            h,
            w,
            u: self.bins_per_px as f32,
            margin: self.margin as f32,
            bins_h: self.bins_h,
            bins_w: self.bins_w,
            stride: self.stride,
            excluded: self.excluded.as_deref(),
            robust,
        };
        match &sub.flow {
            SubBlockMotion::Affine { matrix, offset } => {
                grid.fill_affine(self.isa, targets, spans, matrix, offset, None)
            }
            SubBlockMotion::CameraAndLocal {
                matrix,
                offset,
                flow,
                local,
            } => {
                let flow = flow.as_standard_layout();
                let flow = flow.as_slice().expect("standard layout");
                let mask = local.as_standard_layout();
                let mask = mask.as_slice().expect("standard layout");
                grid.fill_affine(self.isa, targets, spans, matrix, offset, Some((mask, flow)))
            }
            SubBlockMotion::Dense(flow) => {
                let flow = flow.as_standard_layout();
                let flow = flow.as_slice().expect("standard layout");
                grid.fill(targets, spans, |q: [f32; 2]| {
                    reference_position(flow, h, w, q)
                })
            }
        }
    }

    /// Adds the samples of the sub-blocks of `group` (their sites' `targets` and row spans
    /// `row_bins` from [`Self::fill_targets`], one `h·w` and one `h` slice per sub-block) to the
    /// bins, one band of bin rows per task (a band, ~1 MB, stays in cache while every
    /// sub-block of the group adds to it). Within a band, sub-blocks come in order and each
    /// scans its sites in order, so each bin receives its samples in (sub-block, site) order
    /// whatever the number of threads: the same sums as one serial pass.
    fn splat_group(&mut self, group: &[SubBlock], targets: &[(u32, f32)], row_bins: &[(u32, u32)]) {
        let (h, w) = (self.cfa.height(), self.cfa.width());
        let stride = self.stride;
        let band_floats = SPLAT_BAND_ROWS * SUMS * stride;
        let counts: Vec<_> = group
            .iter()
            .map(|sub| sub.counts.as_standard_layout())
            .collect();
        let codes = &self.codes;
        self.bins
            .par_chunks_mut(band_floats)
            .enumerate()
            .for_each(|(band, cells)| {
                // A local copy: read once, not after every store into the bins (the
                // closure otherwise reads the captured reference).
                #[allow(clippy::redundant_locals)]
                let stride = stride;
                let first = band * band_floats;
                let end = first + cells.len();
                for (k, sub) in group.iter().enumerate() {
                    let frames = sub.frames as f32;
                    let counts = counts[k].as_slice().expect("standard layout");
                    let targets = &targets[k * h * w..(k + 1) * h * w];
                    for (y, &(lo, hi)) in row_bins[k * h..(k + 1) * h].iter().enumerate() {
                        if lo == u32::MAX || (hi as usize) < first || lo as usize >= end {
                            continue;
                        }
                        let sites = y * w..(y + 1) * w;
                        for ((&(bin, r), &count), &code) in targets[sites.clone()]
                            .iter()
                            .zip(&counts[sites.clone()])
                            .zip(&codes[sites])
                        {
                            let bin = bin as usize;
                            if bin < first || bin >= end {
                                continue;
                            }
                            // The three sums of the site's channel in one sub-slice (one
                            // bounds check instead of three): the bins of a band are whole
                            // bin rows of SUMS planes, so the slice is inside the band.
                            let slot = bin - first + (code as usize & 3) * PLANES * stride;
                            let cell = &mut cells[slot..slot + 2 * stride + 1];
                            cell[0] += r * count as f32;
                            cell[stride] += r * frames;
                            cell[2 * stride] += r * r * frames;
                        }
                    }
                }
            });
    }

    /// The channels that gather from the coarser bins of `sparse_bins_per_output_px`: those
    /// present whose kernel scale is at least [`SPARSE_SCALE_RATIO`] times the densest
    /// channel's (none when the sparse bins are the phase bins).
    pub(super) fn sparse_channels(&self) -> [bool; 4] {
        let densest = self
            .channel_scale
            .iter()
            .copied()
            .filter(|&s| s > 0.0)
            .fold(f32::INFINITY, f32::min);
        let coarser = self.config.sparse_bins_per_output_px < self.config.bins_per_output_px;
        self.channel_scale
            .map(|s| coarser && s > 0.0 && s >= SPARSE_SCALE_RATIO * densest)
    }

    /// The phase bins as the regression reads them.
    pub(super) fn fine_grid(&self) -> BinGrid<'_> {
        BinGrid {
            bins: &self.bins,
            stride: self.stride,
            bins_h: self.bins_h,
            bins_w: self.bins_w,
            u: self.bins_per_px as f32,
            margin: self.margin as f32,
        }
    }

    /// The phase bins of the `sparse` channels on a grid f times coarser, f the ratio of
    /// `bins_per_output_px` to `sparse_bins_per_output_px`, in the same plane layout (the other
    /// channels' planes stay 0): coarse bin (k, j) sits on fine bin (f·k, f·j) and takes every
    /// fine bin within f − 1 of it along each axis with the tent weight (1 − |d|/f) per axis
    /// (each channel's first `planes` sums: the fine bin's samples are shared between the
    /// nearest coarse bins, as when splatting with bilinear weights). Unlike rounding to the
    /// coarse grid it moves no sample on average: the positions of a static burst (every site
    /// on a whole reference pixel) stay where they are (rounding pairs of fine bins instead
    /// shifted the sparse channels by a quarter pixel; measured in docs/tuning.md). The splat
    /// itself stays one pass over the fine bins.
    pub(super) fn coarse_bins(&self, sparse: [bool; 4], planes: usize) -> CoarseBins {
        let f = self.config.bins_per_output_px / self.config.sparse_bins_per_output_px;
        // (bins − 1) is a multiple of the bins per reference px, hence of f.
        let (bins_h, bins_w) = ((self.bins_h - 1) / f + 1, (self.bins_w - 1) / f + 1);
        let stride = (bins_w + LANES - 1).next_multiple_of(LANES);
        let mut bins = cpu::zeroed_par::<f32>(bins_h * SUMS * stride);
        let (fine, fine_stride, fine_w) = (&self.bins, self.stride, self.bins_w);
        let fine_rows = self.bins_h as isize;
        let tent = |d: isize| (f as isize - d.abs()) as f32 / f as f32;
        let reach = f as isize - 1;
        bins.par_chunks_mut(SUMS * stride)
            .enumerate()
            .for_each_init(
                || vec![0.0f32; fine_w],
                |rows, (cy, row)| {
                    let centre = (cy * f) as isize;
                    for ch in (0..4).filter(|&ch| sparse[ch]) {
                        for k in 0..planes {
                            let plane = ch * PLANES + k;
                            // The fine rows around the coarse row, tent-weighted...
                            rows.fill(0.0);
                            for by in (centre - reach).max(0)..=(centre + reach).min(fine_rows - 1)
                            {
                                let weight = tent(by - centre);
                                let at = (by as usize * SUMS + plane) * fine_stride;
                                for (r, &v) in rows.iter_mut().zip(&fine[at..at + fine_w]) {
                                    *r += weight * v;
                                }
                            }
                            // ...then the fine columns around each coarse column.
                            let out = &mut row[plane * stride..plane * stride + bins_w];
                            for (cx, o) in out.iter_mut().enumerate() {
                                let centre = (cx * f) as isize;
                                *o = ((centre - reach).max(0)
                                    ..=(centre + reach).min(fine_w as isize - 1))
                                    .map(|bx| tent(bx - centre) * rows[bx as usize])
                                    .sum();
                            }
                        }
                    }
                },
            );
        CoarseBins {
            bins,
            stride,
            bins_h,
            bins_w,
            u: (self.bins_per_px / f) as f32,
            margin: self.margin as f32,
        }
    }
}

/// A grid of phase bins in [`MergeAccumulator`]'s plane layout: bin (by, bx) sits at reference
/// position (by/u − margin, bx/u − margin).
pub(super) struct BinGrid<'b> {
    pub(super) bins: &'b [f32],
    /// Floats per plane row.
    pub(super) stride: usize,
    pub(super) bins_h: usize,
    pub(super) bins_w: usize,
    /// Bins per reference px.
    pub(super) u: f32,
    /// Reference px of margin (not whole for coarse bins).
    pub(super) margin: f32,
}

/// The coarser bins of the sparse channels ([`MergeAccumulator::coarse_bins`]).
pub(super) struct CoarseBins {
    pub(super) bins: Vec<f32>,
    pub(super) stride: usize,
    pub(super) bins_h: usize,
    pub(super) bins_w: usize,
    pub(super) u: f32,
    pub(super) margin: f32,
}

impl CoarseBins {
    pub(super) fn grid(&self) -> BinGrid<'_> {
        BinGrid {
            bins: &self.bins,
            stride: self.stride,
            bins_h: self.bins_h,
            bins_w: self.bins_w,
            u: self.u,
            margin: self.margin,
        }
    }
}
