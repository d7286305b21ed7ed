//! The kernel regression over the phase bins (paper §4.2; supplement Eq. 1–3): for every output
//! pixel, the anisotropic-kernel-weighted sums of every channel's bins.

#![forbid(unsafe_code)]

#[cfg(target_arch = "x86_64")]
use super::x86::gather_row_avx2;
use super::*;
use crate::cpu::Isa;

/// A channel's own ellipse bounds its bins in the regression ([`gather_row_generic`]) when its
/// limit is below this fraction of the widest channel's (this project's heuristic: it changes
/// only the work, not the result).
const OWN_ELLIPSE_RATIO: f64 = 0.8;

impl MergeAccumulator<'_> {
    /// (Σ g·S0, Σ g·S1, Σ g²·S2) per channel (the sums of supplement Eq. 1–3 over the bins, g the
    /// kernel weight) of every output pixel, row-major, in parallel by output rows; `with_flux`:
    /// Σ g·S3 as well (the bins' own fluxes, [`MergeAccumulator::fill_flux_planes`]), else 0.
    /// The sparse channels ([`MergeAccumulator::sparse_channels`]), if any, gather from
    /// coarser bins ([`MergeAccumulator::coarse_bins`]), the others from the phase bins.
    pub(super) fn regression(&self, channels: [bool; 4], with_flux: bool) -> Vec<[f32; SUMS]> {
        let (hs, ws) = (
            self.cfa.height() * self.config.scale,
            self.cfa.width() * self.config.scale,
        );
        let inv_cov = self.kernels.inv_cov.as_standard_layout();
        let inv_cov = inv_cov.as_slice().expect("standard layout");
        let mut sums = cpu::zeroed_par::<[f32; SUMS]>(hs * ws);
        let isa = self.isa;
        let gather_rows = |sums: &mut [[f32; SUMS]], gather: &Gather| {
            sums.par_chunks_mut(ws)
                .enumerate()
                .for_each(|(oy, row)| gather_row(gather, isa, oy, row))
        };
        let all_sparse = self.sparse_channels();
        let sparse: [bool; 4] = std::array::from_fn(|ch| all_sparse[ch] && channels[ch]);
        if !sparse.contains(&true) {
            gather_rows(
                &mut sums,
                &self.gather(self.fine_grid(), channels, inv_cov, with_flux),
            );
            return sums;
        }
        let planes = if with_flux { PLANES } else { RATE_PLANES };
        let coarse = self.coarse_bins(sparse, planes);
        let dense: [bool; 4] = std::array::from_fn(|ch| channels[ch] && !sparse[ch]);
        if !(0..4).any(|ch| dense[ch] && self.channel_scale[ch] > 0.0) {
            gather_rows(
                &mut sums,
                &self.gather(coarse.grid(), sparse, inv_cov, with_flux),
            );
            return sums;
        }
        let fine = self.gather(self.fine_grid(), dense, inv_cov, with_flux);
        let coarse = self.gather(coarse.grid(), sparse, inv_cov, with_flux);
        sums.par_chunks_mut(ws).enumerate().for_each_init(
            || vec![[0.0f32; SUMS]; ws],
            |sparse_row, (oy, row)| {
                gather_row(&fine, isa, oy, row);
                gather_row(&coarse, isa, oy, sparse_row);
                for (out, s) in row.iter_mut().zip(sparse_row.iter()) {
                    for ch in (0..4).filter(|&ch| sparse[ch]) {
                        let sums = ch * PLANES..(ch + 1) * PLANES;
                        out[sums.clone()].copy_from_slice(&s[sums]);
                    }
                }
            },
        );
        sums
    }

    /// What the regression of `channels` over the bins of `grid` reads ([`Gather`]), with the
    /// (H, W, 3) inverse kernel covariances `inv_cov`; `with_flux`: the bins' flux planes too.
    pub(super) fn gather<'g>(
        &self,
        grid: BinGrid<'g>,
        channels: [bool; 4],
        inv_cov: &'g [f32],
        with_flux: bool,
    ) -> Gather<'g> {
        let scale = self.config.scale;
        let (h, w) = (self.cfa.height(), self.cfa.width());
        let inv_scale = self.inv_scale;
        let cutoff = self.config.cutoff;
        let u = grid.u;
        let inv_s = 1.0 / scale as f32;
        // Every channel skips a bin whose quadratic form times the smallest channel factor is
        // at or above the cutoff (rounding is monotone and the form is then positive), so the
        // gather only visits the bins of each row inside that widest ellipse, widened by a bin
        // on each side against rounding ([`ellipse_span`]).
        let present: [bool; 4] =
            std::array::from_fn(|ch| channels[ch] && self.channel_scale[ch] > 0.0);
        let min_inv_scale = (0..4)
            .filter(|&ch| present[ch])
            .map(|ch| inv_scale[ch])
            .fold(f32::INFINITY, f32::min);
        // The sparsest channel makes its weights with exponentials; a channel whose factor is
        // the same reuses them (R, G and B of most CFAs: the same values, computed once), one
        // whose factor is k times it takes their k-th power ([`snap_scales`]). Without the
        // sparsest channel among `channels`, each channel makes its own.
        let min_present = (0..4)
            .filter(|&ch| present[ch])
            .map(|ch| inv_scale[ch])
            .fold(f32::INFINITY, f32::min);
        let base = (0..4)
            .find(|&ch| present[ch] && self.multiples[ch] == 0 && inv_scale[ch] == min_present);
        let source = std::array::from_fn(|ch| match base {
            Some(base) if self.multiples[ch] == 1 => base,
            _ => ch,
        });
        let power = std::array::from_fn(|ch| match self.multiples[ch] {
            k if k >= 2 && base.is_some() => k,
            _ => 0,
        });
        Gather {
            bins: grid.bins,
            stride: grid.stride,
            bins_h: grid.bins_h as isize,
            bins_w: grid.bins_w as isize,
            inv_cov,
            h,
            w,
            u,
            inv_u: 1.0 / u,
            margin: grid.margin,
            radius: self.radius,
            inv_s,
            offset: 0.5 * inv_s - 0.5,
            cutoff,
            inv_scale,
            present,
            with_flux,
            base: base.unwrap_or(0),
            source,
            power,
            ellipse_limit: (min_inv_scale > 0.0).then(|| cutoff as f64 / min_inv_scale as f64),
            // A channel with a larger factor (W of a W-rich CFA) has its own, narrower ellipse.
            channel_limit: std::array::from_fn(|ch| {
                (min_inv_scale > 0.0 && present[ch] && inv_scale[ch] > min_inv_scale)
                    .then(|| cutoff as f64 / inv_scale[ch] as f64)
            }),
        }
    }
}

/// What the kernel regression ([`gather_row`]) reads: the phase bins and the kernels, with the
/// geometry of both grids (see [`MergeAccumulator`]).
pub(super) struct Gather<'g> {
    /// The bins in [`MergeAccumulator`]'s plane layout.
    pub(super) bins: &'g [f32],
    pub(super) stride: usize,
    pub(super) bins_h: isize,
    pub(super) bins_w: isize,
    /// (H, W, 3) inverse kernel covariances (a, b, c), row-major.
    pub(super) inv_cov: &'g [f32],
    pub(super) h: usize,
    pub(super) w: usize,
    /// Bins per reference px and its inverse.
    pub(super) u: f32,
    pub(super) inv_u: f32,
    /// Margin of the bin grid and gather radius (reference px).
    pub(super) margin: f32,
    pub(super) radius: f32,
    /// Reference px per output px, and the reference position of output pixel 0.
    pub(super) inv_s: f32,
    pub(super) offset: f32,
    pub(super) cutoff: f32,
    /// Kernel factor 1/scale_c of every channel (Ω_c⁻¹ = Ω⁻¹/scale_c).
    pub(super) inv_scale: [f32; 4],
    /// Channels with sites in the CFA.
    pub(super) present: [bool; 4],
    /// Whether Σ g·S3 (the bins' own fluxes) is gathered as well.
    pub(super) with_flux: bool,
    /// The sparsest channel (the smallest factor), whose weights are exponentials.
    pub(super) base: usize,
    /// The channel whose weights each channel uses (itself, or `base` for a channel of the
    /// same factor).
    pub(super) source: [usize; 4],
    /// k ≥ 2: the channel's weights are the k-th power of `base`'s ([`lane_power`]); 0: its
    /// own (or its source's).
    pub(super) power: [u32; 4],
    /// Bound of the quadratic form inside which some channel's weight is non-zero.
    pub(super) ellipse_limit: Option<f64>,
    /// Bound of the quadratic form inside which channel c's weight is non-zero, for the
    /// channels whose ellipse is narrower than `ellipse_limit`'s (`None`: that one).
    pub(super) channel_limit: [Option<f64>; 4],
}

/// The regression sums of output row `oy` into `row` (W·scale pixels), compiled for AVX2
/// where `isa` has it (the same bits).
pub(super) fn gather_row(g: &Gather, isa: Isa, oy: usize, row: &mut [[f32; SUMS]]) {
    #[cfg(target_arch = "x86_64")]
    {
        if isa.avx2() {
            return gather_row_avx2(isa, g, oy, row);
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = isa;
    gather_row_generic(g, oy, row)
}

/// Kernel regression of one output row over the phase bins (supplement Eq. 1–3): for every
/// output pixel p and every bin within the gather radius (and inside the widest channel's
/// ellipse), the weight g = exp(−½·dᵀΩ_c⁻¹d) of the bin's offset d for every channel c with
/// dᵀΩ_c⁻¹d below the cutoff, accumulated as Σ g·S0, Σ g·S1, Σ g²·S2 (and Σ g·S3 with
/// `with_flux`) of the bin's sums.
///
/// Eight bins of a row at a time: the quadratic forms, the exponentials ([`fastmath::exp`])
/// and the products are lane-wise, with bins outside the row segment or the cutoff weighted 0
/// (empty bins hold zeros); each lane keeps its own partial sums, added in a fixed tree at
/// the end of the pixel. Deterministic and independent of the thread count; the order of the
/// additions differs from one sum over the bins in row order only by rounding.
///
/// Per bin row, the weights of every group of eight bins are made first (exponentials once per
/// distinct channel factor; a channel whose factor is k times the sparsest channel's takes the
/// k-th power of its weights, [`snap_scales`]), then each channel runs over the groups with its
/// three partial sums held in registers (three channels that share weights and groups in one
/// pass, [`RowPass::run3`]):
/// each partial sum receives the same products in the same order (rows, then groups) as when
/// the channels took turns per group, so the same bits
/// (`gather_row_matches_the_group_by_group_reference`).
#[inline(always)]
pub(super) fn gather_row_generic(g: &Gather, oy: usize, row: &mut [[f32; SUMS]]) {
    let mut scratch = RowScratch::new(g, oy);
    for (ox, out) in row.iter_mut().enumerate() {
        scratch.pixel(g, ox, out);
    }
}

/// What [`gather_row_generic`] makes once per output row and reuses for every pixel of it.
struct RowScratch {
    /// Reference row of the kernels.
    iy: usize,
    /// The bin rows within the gather radius.
    by0: isize,
    by1: isize,
    /// Row offsets of the bin rows from the pixel row.
    dys: Vec<f32>,
    /// A pixel's dx interval of the main ellipse in each bin row ([`ellipse_spans`]).
    main_span: Vec<[f64; 2]>,
    /// The channels' own ellipses ([`own_ellipses`]) and their dx intervals.
    own: [Option<usize>; 4],
    channel_span: [Vec<[f64; 2]>; 4],
    /// Groups of eight bins of a bin row: at most the bins within the radius, plus one.
    max_groups: usize,
    /// The quadratic forms of a bin row's groups ([`fill_quads`]).
    quads: Vec<f32>,
    /// weights[ch][group·8 + lane] of the channels that make their own weights.
    weights: [Vec<f32>; 4],
    plan: ChannelPlan,
    /// 0, 1, 2, … in f32 (exact): the bins' offsets from the first of a row segment.
    lane_index: Vec<f32>,
}

/// An output pixel's kernel and bins, as each bin row of [`RowScratch::pixel`] reads them.
struct PixelKernel {
    /// Reference x of the pixel.
    px: f32,
    /// The bin columns within the gather radius.
    bx0: isize,
    bx1: isize,
    /// The kernel's inverse covariance (a, 2b, c).
    a: f32,
    b2: f32,
    c: f32,
}

impl RowScratch {
    /// The scratch of output row `oy`.
    #[inline(always)]
    fn new(g: &Gather, oy: usize) -> RowScratch {
        let (u, inv_u, margin, radius) = (g.u, g.inv_u, g.margin, g.radius);
        let py = oy as f32 * g.inv_s + g.offset;
        let iy = (py.round().max(0.0) as usize).min(g.h - 1);
        let by0 = (((py - radius + margin) * u).ceil() as isize).max(0);
        let by1 = (((py + radius + margin) * u).floor() as isize).min(g.bins_h - 1);
        // Row offsets of the bin rows from the pixel row, and each pixel's dx interval of every
        // ellipse in each bin row (the main one, then each channel's own), made for all rows at
        // once ([`ellipse_spans`]).
        let dys: Vec<f32> = (by0..=by1)
            .map(|by| by as f32 * inv_u - margin - py)
            .collect();
        let rows = dys.len();
        let main_span = vec![[0.0f64; 2]; rows];
        let own = own_ellipses(g);
        let channel_span: [Vec<[f64; 2]>; 4] = std::array::from_fn(|ch| {
            if own[ch] == Some(ch) {
                vec![[0.0f64; 2]; rows]
            } else {
                Vec::new()
            }
        });
        // Groups of eight bins of a bin row: at most the bins within the radius, plus one.
        let max_groups = ((2.0 * radius * u) as usize + 2).div_ceil(LANES) + 1;
        let quads = vec![0.0f32; max_groups * LANES];
        // weights[ch][group·8 + lane] of the channels that make their own weights.
        let weights: [Vec<f32>; 4] = std::array::from_fn(|ch| {
            vec![
                0.0f32;
                if g.present[ch] && g.source[ch] == ch {
                    max_groups * LANES
                } else {
                    0
                }
            ]
        });
        let plan = ChannelPlan::new(g, &own);
        // 0, 1, 2, … in f32 (exact): the bins' offsets from the first of a row segment.
        let lane_index: Vec<f32> = (0..max_groups * LANES).map(|k| k as f32).collect();
        RowScratch {
            iy,
            by0,
            by1,
            dys,
            main_span,
            own,
            channel_span,
            max_groups,
            quads,
            weights,
            plan,
            lane_index,
        }
    }

    /// The regression sums of output pixel `ox` of the row into `out`.
    #[inline(always)]
    fn pixel(&mut self, g: &Gather, ox: usize, out: &mut [f32; SUMS]) {
        let (u, margin, radius) = (g.u, g.margin, g.radius);
        let px = ox as f32 * g.inv_s + g.offset;
        let ix = (px.round().max(0.0) as usize).min(g.w - 1);
        let k = 3 * (self.iy * g.w + ix);
        let (a, b2, c) = (g.inv_cov[k], 2.0 * g.inv_cov[k + 1], g.inv_cov[k + 2]);
        let bx0 = (((px - radius + margin) * u).ceil() as isize).max(0);
        let bx1 = (((px + radius + margin) * u).floor() as isize).min(g.bins_w - 1);
        if let Some(limit) = g.ellipse_limit {
            ellipse_spans(a, b2, c, &self.dys, limit, &mut self.main_span);
        }
        for (ch, spans) in self.channel_span.iter_mut().enumerate() {
            if let (Some(limit), Some(true)) = (g.channel_limit[ch], self.own[ch].map(|o| o == ch))
            {
                ellipse_spans(a, b2, c, &self.dys, limit, spans);
            }
        }
        let pixel = PixelKernel {
            px,
            bx0,
            bx1,
            a,
            b2,
            c,
        };
        // acc[channel][sum][lane]
        let mut acc = [[[0.0f32; LANES]; PLANES]; 4];
        for (row, by) in (self.by0..=self.by1).enumerate() {
            self.bin_row(g, &pixel, row, by, &mut acc);
        }
        for (ch, acc) in acc.iter().enumerate() {
            for (sum, lanes) in acc.iter().enumerate() {
                out[ch * PLANES + sum] = lane_sum(lanes);
            }
        }
    }

    /// Adds bin row `by` (the `row`-th of the pixel's) to the pixel's partial sums `acc`: each
    /// channel's groups, the kernel's quadratic form of their bins, the channels' weights,
    /// then the sums.
    #[inline(always)]
    fn bin_row(
        &mut self,
        g: &Gather,
        pixel: &PixelKernel,
        row: usize,
        by: isize,
        acc: &mut [[[f32; LANES]; PLANES]; 4],
    ) {
        let (bins, stride) = (g.bins, g.stride);
        let (u, inv_u, margin) = (g.u, g.inv_u, g.margin);
        let PixelKernel {
            px,
            bx0,
            bx1,
            a,
            b2,
            c,
        } = *pixel;
        let dy = self.dys[row];
        let ady2 = a * dy * dy;
        let bdy = b2 * dy;
        // The bins of the row inside an ellipse's dx interval, widened by a bin each side.
        let cols = BinSpan {
            bx0,
            bx1,
            inv_u: inv_u as f64,
            centre: (margin + px) as f64,
            u: u as f64,
        };
        let (lo, hi) = match g.ellipse_limit {
            Some(_) => cols.of(self.main_span[row]),
            None => (bx0, bx1),
        };
        if lo > hi {
            return;
        }
        let groups = ((hi - lo) as usize) / LANES + 1;
        debug_assert!(groups <= self.max_groups);
        let ranges = channel_group_ranges(
            &self.plan,
            &self.own,
            &cols,
            &self.channel_span,
            row,
            (lo, hi),
            groups,
        );
        fill_quads(
            &mut self.quads[..groups * LANES],
            &self.lane_index[..groups * LANES],
            (lo, hi),
            (inv_u, margin, px),
            (ady2, bdy, c),
        );
        make_weights(g, &self.plan, &ranges, &self.quads, &mut self.weights);
        let row_start = by as usize * SUMS * stride;
        // The channels that share weights and groups (R, G and B of most CFAs) run over
        // the groups together: one pass with all their partial sums in registers (more
        // independent additions in flight), each partial sum receiving the same products
        // in the same order as in a pass of its own, so the same bits.
        for members in self.plan.passes() {
            let pass = RowPass {
                bins,
                weights: &self.weights[g.source[members[0]]],
                start: row_start + lo as usize,
                stride,
                groups: ranges[members[0]],
            };
            match (members, g.with_flux) {
                (&[c0, c1, c2], false) => pass.run3::<false>(acc, [c0, c1, c2]),
                (&[c0, c1, c2], true) => pass.run3::<true>(acc, [c0, c1, c2]),
                (_, false) => members
                    .iter()
                    .for_each(|&ch| pass.run1::<false>(&mut acc[ch], ch)),
                (_, true) => members
                    .iter()
                    .for_each(|&ch| pass.run1::<true>(&mut acc[ch], ch)),
            }
        }
    }
}

/// Which channels of [`gather_row_generic`] take their own, narrower ellipse: only where it is
/// markedly narrower than the main one (a nearly equal one, e.g. R and G against B of a CFA
/// with one site fewer of B, would skip about no group for the cost of its spans), made once
/// per distinct limit: `own[ch]` is the channel whose spans channel `ch` uses. Groups outside
/// a channel's ellipse add exact zeros to its sums, so which ellipses are used changes no bit.
fn own_ellipses(g: &Gather) -> [Option<usize>; 4] {
    let mut own: [Option<usize>; 4] = [None; 4];
    for ch in 0..4 {
        if let (Some(limit), Some(main)) = (g.channel_limit[ch], g.ellipse_limit) {
            if limit < OWN_ELLIPSE_RATIO * main {
                let same =
                    (0..ch).find(|&l| own[l] == Some(l) && g.channel_limit[l] == Some(limit));
                own[ch] = Some(same.unwrap_or(ch));
            }
        }
    }
    own
}

/// The groups of eight bins of a bin row (from bin `lo`, `groups` of them) that each present
/// channel of `plan` runs over: those overlapping its own bins `(lo, hi)` or, for a channel
/// with its own ellipse ([`own_ellipses`]), those of that ellipse's dx interval in `row`
/// (`channel_span`); a group of lanes outside them would add exact zeros to the channel's
/// sums, so it is skipped. Channels that share weights share the factor, hence the span.
/// (Plain functions, not closures, so that they are compiled with the caller's instruction
/// set: no libm calls for `floor` and `ceil`.)
#[inline(always)]
fn channel_group_ranges(
    plan: &ChannelPlan,
    own: &[Option<usize>; 4],
    cols: &BinSpan,
    channel_span: &[Vec<[f64; 2]>; 4],
    row: usize,
    (lo, hi): (isize, isize),
    groups: usize,
) -> [(usize, usize); 4] {
    let mut span = [(lo, hi); 4];
    for ch in 0..4 {
        match own[ch] {
            Some(o) if o == ch => {
                let (l, h) = cols.of(channel_span[ch][row]);
                span[ch] = (l.max(lo), h.min(hi));
            }
            Some(o) => span[ch] = span[o],
            None => {}
        }
    }
    let mut ranges = [(0usize, 0usize); 4];
    for ch in plan.present() {
        let (l, h) = span[ch];
        // First group whose last lane reaches l, last group starting at or before h.
        let first = if l <= lo {
            0
        } else {
            ((l - lo) as usize)
                .saturating_sub(LANES - 1)
                .div_ceil(LANES)
        };
        let end = if h < lo {
            0
        } else {
            (((h - lo) as usize) / LANES + 1).min(groups)
        };
        ranges[ch] = (first, end);
    }
    ranges
}

/// The kernel's quadratic form a·dy² + dx·(2b·dy + c·dx) of every bin of a row segment's
/// groups (`quads`, whole groups of eight): bin lo + k at dx = (lo + k)/u − margin − px, with
/// lo + k made in f32 as the sum of two exact integers (below 2^24), so the same value as
/// converting the integer bin index; lanes past the segment's last bin `hi` get a form no
/// factor brings below the cutoff (weight 0).
#[inline(always)]
fn fill_quads(
    quads: &mut [f32],
    lane_index: &[f32],
    (lo, hi): (isize, isize),
    (inv_u, margin, px): (f32, f32, f32),
    (ady2, bdy, c): (f32, f32, f32),
) {
    let lo_f = lo as f32;
    for (quad, &k) in quads.iter_mut().zip(lane_index) {
        let dx = (lo_f + k) * inv_u - margin - px;
        *quad = ady2 + dx * (bdy + c * dx);
    }
    quads[(hi - lo) as usize + 1..].fill(f32::INFINITY);
}

/// One bin row's pass of the regression ([`gather_row_generic`]) for channels that share
/// weights: groups `groups` (first, end) of eight bins from bin `start` (the row's first bin in
/// the channel-0 plane of the bins), with `weights` per group.
struct RowPass<'p> {
    bins: &'p [f32],
    weights: &'p [f32],
    start: usize,
    stride: usize,
    groups: (usize, usize),
}

impl RowPass<'_> {
    /// The four planes (S0, S1, S2, S3) of channel `ch` over the pass's groups.
    #[inline(always)]
    fn planes(&self, ch: usize) -> [&[f32]; PLANES] {
        let len = self.groups.1 * LANES;
        let at = self.start + ch * PLANES * self.stride;
        std::array::from_fn(|k| &self.bins[at + k * self.stride..at + k * self.stride + len])
    }

    /// Adds the pass's products to channel `ch`'s partial sums acc[sum][lane]: Σ g·S0, Σ g·S1
    /// and Σ g²·S2 (and Σ g·S3 with `FLUX`), group by group.
    #[inline(always)]
    fn run1<const FLUX: bool>(&self, acc: &mut [[f32; LANES]; PLANES], ch: usize) {
        let [p0, p1, p2, p3] = self.planes(ch);
        let [mut s0acc, mut s1acc, mut s2acc, mut s3acc] = *acc;
        for group in self.groups.0..self.groups.1 {
            let r = group * LANES..(group + 1) * LANES;
            let weight: &[f32; LANES] = self.weights[r.clone()].try_into().expect("lanes");
            let s0: &[f32; LANES] = p0[r.clone()].try_into().expect("lanes");
            let s1: &[f32; LANES] = p1[r.clone()].try_into().expect("lanes");
            let s2: &[f32; LANES] = p2[r.clone()].try_into().expect("lanes");
            for i in 0..LANES {
                s0acc[i] += weight[i] * s0[i];
                s1acc[i] += weight[i] * s1[i];
                s2acc[i] += weight[i] * weight[i] * s2[i];
            }
            if FLUX {
                let s3: &[f32; LANES] = p3[r].try_into().expect("lanes");
                for i in 0..LANES {
                    s3acc[i] += weight[i] * s3[i];
                }
            }
        }
        *acc = [s0acc, s1acc, s2acc, s3acc];
    }

    /// [`RowPass::run1`] of three channels in one pass over the groups (nine or twelve
    /// independent partial sums in flight instead of three or four): the same products in the
    /// same order per partial sum.
    #[inline(always)]
    fn run3<const FLUX: bool>(
        &self,
        acc: &mut [[[f32; LANES]; PLANES]; 4],
        [c0, c1, c2]: [usize; 3],
    ) {
        let [p00, p01, p02, p03] = self.planes(c0);
        let [p10, p11, p12, p13] = self.planes(c1);
        let [p20, p21, p22, p23] = self.planes(c2);
        let [mut a0, mut a1, mut a2, mut a3] = acc[c0];
        let [mut b0, mut b1, mut b2, mut b3] = acc[c1];
        let [mut d0, mut d1, mut d2, mut d3] = acc[c2];
        for group in self.groups.0..self.groups.1 {
            let r = group * LANES..(group + 1) * LANES;
            let w: &[f32; LANES] = self.weights[r.clone()].try_into().expect("lanes");
            let lanes = |p: &[f32]| -> [f32; LANES] { p[r.clone()].try_into().expect("lanes") };
            let (x00, x01, x02) = (lanes(p00), lanes(p01), lanes(p02));
            let (x10, x11, x12) = (lanes(p10), lanes(p11), lanes(p12));
            let (x20, x21, x22) = (lanes(p20), lanes(p21), lanes(p22));
            for i in 0..LANES {
                let sq = w[i] * w[i];
                a0[i] += w[i] * x00[i];
                a1[i] += w[i] * x01[i];
                a2[i] += sq * x02[i];
                b0[i] += w[i] * x10[i];
                b1[i] += w[i] * x11[i];
                b2[i] += sq * x12[i];
                d0[i] += w[i] * x20[i];
                d1[i] += w[i] * x21[i];
                d2[i] += sq * x22[i];
            }
            if FLUX {
                let (x03, x13, x23) = (lanes(p03), lanes(p13), lanes(p23));
                for i in 0..LANES {
                    a3[i] += w[i] * x03[i];
                    b3[i] += w[i] * x13[i];
                    d3[i] += w[i] * x23[i];
                }
            }
        }
        acc[c0] = [a0, a1, a2, a3];
        acc[c1] = [b0, b1, b2, b3];
        acc[c2] = [d0, d1, d2, d3];
    }
}

/// The bins of a row of the regression between `bx0` and `bx1` inside a dx interval of an
/// ellipse, widened by a bin each side ([`gather_row_generic`]).
pub(super) struct BinSpan {
    pub(super) bx0: isize,
    pub(super) bx1: isize,
    pub(super) inv_u: f64,
    /// Margin plus the output pixel's reference x.
    pub(super) centre: f64,
    pub(super) u: f64,
}

impl BinSpan {
    #[inline(always)]
    pub(super) fn of(&self, [dx_lo, dx_hi]: [f64; 2]) -> (isize, isize) {
        (
            self.bx0
                .max(((dx_lo - self.inv_u + self.centre) * self.u).floor() as isize),
            self.bx1
                .min(((dx_hi + self.inv_u + self.centre) * self.u).ceil() as isize),
        )
    }
}

/// The sum of eight lanes in a fixed order (pairs of halves, then of quarters, then the two).
#[inline(always)]
pub(super) fn lane_sum(l: &[f32; LANES]) -> f32 {
    let (a0, a1, a2, a3) = (l[0] + l[4], l[1] + l[5], l[2] + l[6], l[3] + l[7]);
    let (b0, b1) = (a0 + a2, a1 + a3);
    b0 + b1
}

/// [`ellipse_span`] of every row offset of `dys` into `spans`, a row where the whole row is
/// above the limit getting (+∞, −∞) (whose bins, [`BinSpan::of`], are an empty range). The same
/// operations per row in a loop without branches, which the compiler vectorises (four rows
/// per instruction with AVX2: divisions and square roots were most of the regression's
/// per-row cost), so the same values.
#[inline(always)]
pub(super) fn ellipse_spans(
    a: f32,
    b2: f32,
    c: f32,
    dys: &[f32],
    limit: f64,
    spans: &mut [[f64; 2]],
) {
    let (a, b, c) = (a as f64, b2 as f64 / 2.0, c as f64);
    let det = a * c - b * b;
    if !(c > 0.0 && det > 0.0) {
        spans.fill([f64::NEG_INFINITY, f64::INFINITY]);
        return;
    }
    let slack = limit * 1e-3 + 1e-6;
    for (&dy, span) in dys.iter().zip(spans) {
        let dy = dy as f64;
        let min = dy * dy * det / c;
        let half = ((limit + slack - min).max(0.0) / c).sqrt() * 1.001 + 1e-3;
        let centre = -b * dy / c;
        *span = if min > limit + slack {
            [f64::INFINITY, f64::NEG_INFINITY]
        } else {
            [centre - half, centre + half]
        };
    }
}
