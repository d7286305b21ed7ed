//! The fit's observations: the grey channel's photon counts summed over square bins, bins
//! along a row grouped into runs (and runs into lanes for the AVX2 sums), and the bins that
//! carry the most Fisher information.
#![forbid(unsafe_code)]

use super::affine::AffineMotion;
use super::fit::{PARAM_BASIS, PARAM_GRADIENT};
use super::template::{sample_template, TemplateLevel};
use crate::align::grey::GreyMethod;
use crate::cfa::{Cfa, Channel};
use ndarray::Array2;
use std::ops::Range;

/// Bins of one level: the grey channel's sites summed over `bin` x `bin` squares. Only bins
/// holding at least one site are kept, in row-major order.
pub(in crate::align) struct BinLayout {
    /// Site indices (row-major) of bin b: `site_index[site_start[b]..site_start[b + 1]]`.
    pub(super) site_index: Vec<u32>,
    pub(super) site_start: Vec<u32>,
    /// Mean site position of every bin, relative to the image centre.
    pub(super) centroid: Vec<[f64; 2]>,
    /// Runs of consecutive bins whose centroids share one row coordinate (a row of 1 px bins):
    /// the fit sums the normal equations' x-dependence along a run and multiplies by the row
    /// coordinate once per run.
    pub(super) runs: Vec<Range<usize>>,
    /// The centroids' x coordinate and its square in single precision, one array each (the
    /// fit's inner loop reads them for several bins at a time).
    pub(super) x: Vec<f32>,
    pub(super) x2: Vec<f32>,
    /// The runs [`GROUP_LANES`] at a time, for `run_sums_group_avx2` (x86.rs).
    pub(super) groups: RunGroups,
}

/// Runs summed side by side by `run_sums_group_avx2` (x86.rs): the f32 lanes of an AVX2 register.
pub(super) const GROUP_LANES: usize = 8;

/// The runs of a [`BinLayout`] grouped [`GROUP_LANES`] at a time (runs of similar length
/// together), each group's bins interleaved step by step: slot `s` of a group holds bin `s` of
/// each of its runs in the lanes (a shorter run's lanes past its end are padding). The fit then
/// sums the runs lane-parallel, each lane in its run's own bin order, so that every run's sums
/// are the ones [`run_sums`](super::fit::run_sums) makes, without moving lanes between registers.
#[derive(Default)]
pub(super) struct RunGroups {
    /// Runs of every group (`usize::MAX`: no run in that lane).
    pub(super) runs: Vec<[usize; GROUP_LANES]>,
    /// Slots of group g: `slot_start[g]..slot_start[g + 1]`.
    pub(super) slot_start: Vec<usize>,
    /// Bin of every slot and lane (`u32::MAX`: padding).
    pub(super) bin: Vec<[u32; GROUP_LANES]>,
    /// Centroid column of every slot's bins, and its square (0 for padding).
    pub(super) x: Vec<[f32; GROUP_LANES]>,
    pub(super) x2: Vec<[f32; GROUP_LANES]>,
    /// Centroid row of every group's runs (0 for an empty lane).
    pub(super) row: Vec<[f32; GROUP_LANES]>,
    /// Group of every run.
    pub(super) group_of_run: Vec<usize>,
    /// Site of every slot and lane where every bin holds one site (`u32::MAX`: padding);
    /// empty otherwise.
    pub(super) site: Vec<[u32; GROUP_LANES]>,
}

impl RunGroups {
    /// Groups `runs` (bins with centroid columns `x`, squares `x2`; run r's centroid row
    /// `rows[r]`).
    pub(super) fn new(runs: &[Range<usize>], rows: &[f32], x: &[f32], x2: &[f32]) -> RunGroups {
        // Longest first, so that the runs of one group have similar lengths (little padding).
        let mut order: Vec<usize> = (0..runs.len()).collect();
        order.sort_by_key(|&r| std::cmp::Reverse(runs[r].len()));
        let mut groups = RunGroups {
            slot_start: vec![0],
            group_of_run: vec![0; runs.len()],
            ..RunGroups::default()
        };
        for group in order.chunks(GROUP_LANES) {
            let members: [usize; GROUP_LANES] =
                std::array::from_fn(|l| group.get(l).copied().unwrap_or(usize::MAX));
            let len = group.iter().map(|&r| runs[r].len()).max().unwrap_or(0);
            for s in 0..len {
                let mut bins = [u32::MAX; GROUP_LANES];
                let (mut xs, mut x2s) = ([0.0; GROUP_LANES], [0.0; GROUP_LANES]);
                for (l, &r) in group.iter().enumerate() {
                    if s < runs[r].len() {
                        let b = runs[r].start + s;
                        bins[l] = b as u32;
                        xs[l] = x[b];
                        x2s[l] = x2[b];
                    }
                }
                groups.bin.push(bins);
                groups.x.push(xs);
                groups.x2.push(x2s);
            }
            for &r in group {
                groups.group_of_run[r] = groups.runs.len();
            }
            groups.runs.push(members);
            groups
                .row
                .push(members.map(|r| if r == usize::MAX { 0.0 } else { rows[r] }));
            groups.slot_start.push(groups.bin.len());
        }
        groups
    }

    /// The (mean bit rate, trials) `observation` of every bin laid out as the slots are (0 for
    /// padding: no trials, so weight zero in the fit).
    pub(super) fn observations(
        &self,
        observation: impl Fn(usize) -> (f32, f32),
    ) -> LaneObservations {
        lane_observations(&self.bin, observation)
    }
}

/// Observations laid out as lanes of slots ([`RunGroups::observations`]): every slot's mean
/// bit rates and numbers of trials (0 for padding).
pub(super) struct LaneObservations {
    pub(super) observed: Vec<[f32; GROUP_LANES]>,
    pub(super) trials: Vec<[f32; GROUP_LANES]>,
}

/// `observation(i)` of every lane's index `i` of `slots` (0 for padding, `u32::MAX`: no
/// trials, so weight zero in the fit).
fn lane_observations(
    slots: &[[u32; GROUP_LANES]],
    observation: impl Fn(usize) -> (f32, f32),
) -> LaneObservations {
    let mut observed = Vec::with_capacity(slots.len());
    let mut trials = Vec::with_capacity(slots.len());
    for indices in slots {
        let (mut o, mut t) = ([0.0; GROUP_LANES], [0.0; GROUP_LANES]);
        for (lane, &i) in indices.iter().enumerate() {
            if i != u32::MAX {
                (o[lane], t[lane]) = observation(i as usize);
            }
        }
        observed.push(o);
        trials.push(t);
    }
    LaneObservations { observed, trials }
}

impl BinLayout {
    /// Number of (non-empty) bins.
    pub(in crate::align) fn len(&self) -> usize {
        self.centroid.len()
    }

    /// Site indices of bin `b`.
    pub(in crate::align) fn sites(&self, b: usize) -> &[u32] {
        &self.site_index[self.site_start[b] as usize..self.site_start[b + 1] as usize]
    }
}

/// Bins of `bin` px over the sites of `cfa` that the grey image is made of (W on a W-rich CFA,
/// every site of a periodic CFA), hot pixels left out.
pub(in crate::align) fn bin_layout(
    cfa: &Cfa,
    method: GreyMethod,
    hot: Option<&Array2<bool>>,
    bin: usize,
) -> BinLayout {
    // Tile averages sit half a period from the pixel they are stored at.
    let offset = match method {
        GreyMethod::TileAverage { py, px } => [(py as f64 - 1.0) / 2.0, (px as f64 - 1.0) / 2.0],
        _ => [0.0, 0.0],
    };
    bin_layout_of(cfa, offset, hot, bin, |y, x| match method {
        GreyMethod::InterpolateW => cfa.channel(y, x) == Channel::W,
        _ => true,
    })
}

/// Bins of `bin` px over the sites of one `channel` of `cfa`, hot pixels left out: what a fit to
/// a template of that channel's sites alone observes (the tracking channel, G of a Bayer CFA).
pub(in crate::align) fn channel_bin_layout(
    cfa: &Cfa,
    channel: Channel,
    hot: Option<&Array2<bool>>,
    bin: usize,
) -> BinLayout {
    bin_layout_of(cfa, [0.0, 0.0], hot, bin, |y, x| {
        cfa.channel(y, x) == channel
    })
}

/// Bins of `bin` px over the sites `use_site` takes, hot pixels left out, each bin's centroid
/// less `offset` (where its values are stored off the sites).
fn bin_layout_of(
    cfa: &Cfa,
    offset: [f64; 2],
    hot: Option<&Array2<bool>>,
    bin: usize,
    use_site: impl Fn(usize, usize) -> bool,
) -> BinLayout {
    let (h, w) = (cfa.height(), cfa.width());
    let centre = [(h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0];
    let (by, bx) = (h.div_ceil(bin), w.div_ceil(bin));
    let bin_of_site = |y: usize, x: usize| {
        (use_site(y, x) && !hot.is_some_and(|m| m[[y, x]])).then(|| (y / bin) * bx + x / bin)
    };
    // A counting sort: sites per bin and their coordinate sums in one pass, then each site at
    // its bin's next slot in a second (row-major order within a bin, as a scan visits them).
    let mut count = vec![0u32; by * bx];
    let mut sums = vec![[0.0f64; 2]; by * bx];
    for y in 0..h {
        for x in 0..w {
            if let Some(k) = bin_of_site(y, x) {
                count[k] += 1;
                sums[k][0] += y as f64;
                sums[k][1] += x as f64;
            }
        }
    }
    let mut next_slot = vec![0u32; by * bx];
    let mut site_start = vec![0u32];
    let mut centroid = Vec::new();
    for (k, (&n, m)) in count.iter().zip(&sums).enumerate() {
        if n == 0 {
            continue;
        }
        next_slot[k] = *site_start.last().expect("starts at 0");
        site_start.push(next_slot[k] + n);
        let n = n as f64;
        centroid.push([
            m[0] / n - offset[0] - centre[0],
            m[1] / n - offset[1] - centre[1],
        ]);
    }
    let mut site_index = vec![0u32; *site_start.last().expect("starts at 0") as usize];
    for y in 0..h {
        for x in 0..w {
            if let Some(k) = bin_of_site(y, x) {
                site_index[next_slot[k] as usize] = (y * w + x) as u32;
                next_slot[k] += 1;
            }
        }
    }
    BinLayout::from_bins(site_index, site_start, centroid)
}

impl BinLayout {
    /// The layout of bins with sites `site_index[site_start[b]..site_start[b + 1]]` and
    /// centroids `centroid[b]` (row-major order): its runs, columns and run groups.
    fn from_bins(site_index: Vec<u32>, site_start: Vec<u32>, centroid: Vec<[f64; 2]>) -> Self {
        let mut runs: Vec<Range<usize>> = Vec::new();
        for (b, c) in centroid.iter().enumerate() {
            match runs.last_mut() {
                Some(run) if centroid[run.start][0] == c[0] => run.end = b + 1,
                _ => runs.push(b..b + 1),
            }
        }
        let x: Vec<f32> = centroid.iter().map(|c| c[1] as f32).collect();
        let x2: Vec<f32> = centroid.iter().map(|c| (c[1] * c[1]) as f32).collect();
        let rows: Vec<f32> = runs.iter().map(|r| centroid[r.start][0] as f32).collect();
        let mut groups = RunGroups::new(&runs, &rows, &x, &x2);
        if site_index.len() == centroid.len() {
            groups.site = (groups.bin.iter())
                .map(|bins| bins.map(|b| site_index.get(b as usize).copied().unwrap_or(u32::MAX)))
                .collect();
        }
        BinLayout {
            site_index,
            site_start,
            centroid,
            runs,
            x,
            x2,
            groups,
        }
    }

    /// The bins `b` with `keep[b]`, in their order.
    pub(super) fn subset(&self, keep: &[bool]) -> BinLayout {
        let kept = keep.iter().filter(|&&k| k).count();
        let mut site_index = Vec::with_capacity(kept * self.site_index.len() / self.len().max(1));
        let mut site_start = Vec::with_capacity(kept + 1);
        site_start.push(0u32);
        let mut centroid = Vec::with_capacity(kept);
        for b in (0..self.len()).filter(|&b| keep[b]) {
            site_index.extend_from_slice(self.sites(b));
            site_start.push(site_index.len() as u32);
            centroid.push(self.centroid[b]);
        }
        BinLayout::from_bins(site_index, site_start, centroid)
    }
}

/// Which bins of `layout` to keep so that they hold at least the share `keep` of the layout's
/// Fisher information about each of the six affine parameters: this project's heuristic (see
/// [`RefineConfig::fine_information`](super::RefineConfig::fine_information)). Bin b's information
/// about parameter p is its Jacobian entry squared times its weight, g_p²·u_p²·n_b / max(T·(1 − T),
/// 0.01) (g_p the template gradient along y or x, u_p the basis 1, y or x of [`PARAM_GRADIENT`] and
/// [`PARAM_BASIS`], the inverse binomial variance of the fit's weights), with T and ∇T the
/// `template` at the bin's centroid moved by `motion`; a bin outside the template holds none and is
/// dropped. Each parameter is ranked on its own and a bin is kept when any ranking keeps it: a
/// scene whose texture constrains one direction weakly (horizontal structures, a sea under a sky)
/// keeps the many weak bins that carry that direction, and the far bins that carry rotation and
/// scale stay. The bins are ranked by the exponent and top three mantissa bits of their information
/// (eighths of an octave: a histogram in one pass, no sort), and the classes are kept from the most
/// informative down until their sum reaches the share, so slightly more than `keep` is kept; `keep
/// >= 1` keeps every bin.
pub(super) fn most_informative_bins(
    layout: &BinLayout,
    template: &TemplateLevel,
    motion: &AffineMotion,
    centre: [f64; 2],
    keep: f64,
) -> Vec<bool> {
    if keep >= 1.0 {
        return vec![true; layout.len()];
    }
    let information: Vec<[f32; 6]> = (0..layout.len())
        .map(|b| {
            let c = layout.centroid[b];
            let d = motion.at(c);
            match sample_template(template, c[0] + centre[0] + d[0], c[1] + centre[1] + d[1]) {
                Some([t, gy, gx]) => {
                    let n = layout.sites(b).len() as f64 / (t * (1.0 - t)).max(0.01);
                    let (g, u) = ([gy, gx], [1.0, c[0], c[1]]);
                    std::array::from_fn(|p| {
                        let j = g[PARAM_GRADIENT[p]] * u[PARAM_BASIS[p]];
                        (j * j * n) as f32
                    })
                }
                None => [0.0; 6],
            }
        })
        .collect();
    // Positive finite f32 order as their bits do; class = bits >> 20 (< 2048).
    let class = |v: f32| (v.to_bits() >> 20) as usize;
    let counted = |v: f32| v > 0.0 && v.is_finite();
    let lowest: [usize; 6] = std::array::from_fn(|p| {
        let mut histogram = vec![0.0f64; 2048];
        let mut total = 0.0f64;
        for v in information.iter().map(|i| i[p]).filter(|&v| counted(v)) {
            histogram[class(v)] += v as f64;
            total += v as f64;
        }
        let target = keep.max(0.0) * total;
        let mut lowest = histogram.len();
        let mut sum = 0.0f64;
        while lowest > 0 && (sum < target || sum == 0.0) {
            lowest -= 1;
            sum += histogram[lowest];
        }
        lowest
    });
    information
        .iter()
        .map(|i| (0..6).any(|p| counted(i[p]) && class(i[p]) >= lowest[p]))
        .collect()
}

/// Mean bit rate and number of trials (sites x frames) of every bin of `layout` over `frames`
/// frames with per-site `counts`: the photon counts summed bin by bin, each mean divided in
/// double precision and rounded once to single precision for the fit. With one site per bin
/// (1 px bins) a count is at most `frames`, so the means are looked up in a table of the
/// `frames + 1` possible quotients (the same numbers, without a division per bin).
pub(super) fn bin_observations(
    layout: &BinLayout,
    counts: &[u32],
    frames: usize,
) -> (Vec<f32>, Vec<f32>) {
    if layout.site_index.len() == layout.len() {
        // One site per bin (1 px bins): the bins' sites in order.
        let table = mean_table(frames);
        let observed = (layout.site_index.iter())
            .map(|&i| single_site_mean(&table, counts[i as usize], frames))
            .collect();
        (observed, vec![frames as f32; layout.len()])
    } else {
        (0..layout.len())
            .map(|b| {
                let sites = layout.sites(b);
                let sum: u64 = sites.iter().map(|&i| counts[i as usize] as u64).sum();
                let trials = sites.len() as f64 * frames as f64;
                (bin_mean(sum as f64, trials), trials as f32)
            })
            .unzip()
    }
}

/// The observations of [`bin_observations`] laid out as the run groups' slots
/// ([`RunGroups::observations`]); a layout of one site per bin is read straight from the
/// counts through [`RunGroups::site`] (the same numbers without the bin-ordered vectors in
/// between).
pub(super) fn slot_observations(
    layout: &BinLayout,
    counts: &[u32],
    frames: usize,
) -> LaneObservations {
    let groups = &layout.groups;
    if groups.site.len() != groups.bin.len() {
        let (observed, trials) = bin_observations(layout, counts, frames);
        return groups.observations(|b| (observed[b], trials[b]));
    }
    let table = mean_table(frames);
    lane_observations(&groups.site, |i| {
        (single_site_mean(&table, counts[i], frames), frames as f32)
    })
}

/// A bin's mean bit rate: its photon count `sum` over `trials` (sites x frames) divided in
/// double precision and rounded once to single precision.
#[inline(always)]
fn bin_mean(sum: f64, trials: f64) -> f32 {
    (sum / trials.max(1.0)) as f32
}

/// The `frames + 1` possible means of a single site over `frames` frames ([`bin_mean`]).
fn mean_table(frames: usize) -> Vec<f32> {
    (0..=frames)
        .map(|c| bin_mean(c as f64, frames as f64))
        .collect()
}

/// [`bin_mean`] of a single site's `count` over `frames` frames, looked up in `table`
/// ([`mean_table`]) where it holds it.
#[inline(always)]
fn single_site_mean(table: &[f32], count: u32, frames: usize) -> f32 {
    match table.get(count as usize) {
        Some(&m) => m,
        None => bin_mean(count as f64, frames as f64),
    }
}
