//! The paper's pseudorandom blue-noise RGBW pattern (§5, Fig. 8c; supplement §2).
//!
//! Colour sites lie on a regular sparse lattice ([`SiteLattice`]); their R/G/B labels are
//! pseudorandom with the constraints of Condat 2010 ("A new random color filter array with good
//! spectral properties"):
//!
//! 1. **Neighbour rule**: no two 4-neighbours on the colour-site lattice share a colour. The
//!    8-neighbourhood cannot be used with three colours: any 2x2 block of sites is a complete
//!    graph on four vertices (every pair is a horizontal, vertical or diagonal neighbour), which
//!    needs four colours. The 4-neighbour rule removes all same-colour clusters along the lattice
//!    axes, the largest contributor to low-frequency chrominance.
//! 2. **Equal counts**: R, G and B sites differ in number by at most one (when reachable).
//! 3. **Low chrominance energy near zero frequency** (blue noise), reached by swap optimisation
//!    of a void-and-cluster style energy (Ulichney 1993): `E = Σ_c ‖g ∗ (1_c − p_c)‖²`, the energy
//!    of each colour's indicator (mean removed) blurred by a Gaussian `g`. Swapping two sites'
//!    colours keeps the counts; only swaps that keep the neighbour rule and lower `E` are taken.
//!
//! The labelling starts in raster order like error diffusion (each site takes the allowed colour
//! least present in its causal neighbourhood, plus random jitter) and is then refined by swaps.
//! The jitter is what makes every seed give a different, aperiodic pattern: without it the
//! greedy choice locks into a periodic layout. The defaults (σ_K = 1.5, jitter 1) are this
//! project's, chosen by a scan (`scan_blue_noise_tuning` in `tests/cfa_analysis.rs`) trading
//! baseband chrominance against peakiness (figures: docs/tuning.md). Swaps rarely help because
//! the neighbour rule forbids most of them.
#![forbid(unsafe_code)]

use super::lattice::SiteLattice;
use crate::error::{Error, Result};
use crate::filters::{gaussian_of_squared_distance, gaussian_taps_f64};
use ndarray::Array2;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// No site: a lattice-grid cell outside the image.
const NONE: u8 = u8::MAX;
/// Swap partners are searched within this many lattice steps (a 5x5 window).
const SWAP_RADIUS: i64 = 2;

/// Tuning of the blue-noise optimisation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlueNoiseConfig {
    /// Standard deviation, in lattice units, of the kernel `K = g ⋆ g` whose values the energy
    /// change of a swap needs (`g` has σ/√2).
    pub kernel_sigma: f64,
    /// Upper bound on optimisation sweeps; sweeps stop earlier once no swap is accepted.
    pub max_sweeps: usize,
    /// Amplitude of the uniform random jitter added to the causal colour densities of the
    /// initial labelling (0 = deterministic choice; larger = closer to i.i.d.).
    pub jitter: f64,
}

impl Default for BlueNoiseConfig {
    fn default() -> Self {
        BlueNoiseConfig {
            kernel_sigma: 1.5,
            max_sweeps: 4,
            jitter: 1.0,
        }
    }
}

/// Blue-noise colour labels (0=R 1=G 2=B, 3=W elsewhere) for an `height` x `width` image whose
/// colour sites are `lattice`. Deterministic in `seed`.
pub fn blue_noise_codes(
    lattice: &SiteLattice,
    height: usize,
    width: usize,
    seed: u64,
) -> Result<Array2<u8>> {
    blue_noise_codes_with(lattice, height, width, seed, &BlueNoiseConfig::default())
}

/// [`blue_noise_codes`] with explicit tuning.
pub fn blue_noise_codes_with(
    lattice: &SiteLattice,
    height: usize,
    width: usize,
    seed: u64,
    config: &BlueNoiseConfig,
) -> Result<Array2<u8>> {
    if height == 0 || width == 0 {
        return Err(Error::invalid("CFA size must be at least 1x1"));
    }
    let grid = SiteGrid::new(lattice, height, width);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut labels = initial_labels(&grid.valid, &mut rng, config);
    balance_counts(&grid.valid, &mut labels, &mut rng);
    optimise(&grid.valid, &mut labels, &mut rng, config);
    let mut codes = Array2::from_elem((height, width), 3u8);
    for ((gi, gj), &(y, x)) in grid.pixel.indexed_iter() {
        if grid.valid[[gi, gj]] {
            codes[[y, x]] = labels[[gi, gj]];
        }
    }
    Ok(codes)
}

/// The colour sites of an image arranged on their lattice grid `(i − i0, j − j0)`.
struct SiteGrid {
    /// Whether each grid cell is a site inside the image.
    valid: Array2<bool>,
    /// Pixel `(y, x)` of each valid cell.
    pixel: Array2<(usize, usize)>,
}

impl SiteGrid {
    fn new(lattice: &SiteLattice, height: usize, width: usize) -> Self {
        let sites: Vec<((i64, i64), (usize, usize))> = (0..height)
            .flat_map(|y| (0..width).map(move |x| (y, x)))
            .filter_map(|(y, x)| lattice.coords(y, x).map(|c| (c, (y, x))))
            .collect();
        let (i0, i1) = min_max(sites.iter().map(|s| s.0 .0));
        let (j0, j1) = min_max(sites.iter().map(|s| s.0 .1));
        let shape = if sites.is_empty() {
            (0, 0)
        } else {
            ((i1 - i0 + 1) as usize, (j1 - j0 + 1) as usize)
        };
        let mut valid = Array2::from_elem(shape, false);
        let mut pixel = Array2::from_elem(shape, (0, 0));
        for ((i, j), p) in sites {
            let g = [(i - i0) as usize, (j - j0) as usize];
            valid[g] = true;
            pixel[g] = p;
        }
        SiteGrid { valid, pixel }
    }
}

fn min_max(it: impl Iterator<Item = i64>) -> (i64, i64) {
    it.fold((i64::MAX, i64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)))
}

/// The valid 4-neighbours of grid cell `(i, j)`.
fn neighbours4(valid: &Array2<bool>, i: usize, j: usize) -> impl Iterator<Item = [usize; 2]> + '_ {
    let (n, m) = valid.dim();
    [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)]
        .into_iter()
        .filter_map(move |(di, dj)| {
            let (a, b) = (i as i64 + di, j as i64 + dj);
            (a >= 0
                && b >= 0
                && (a as usize) < n
                && (b as usize) < m
                && valid[[a as usize, b as usize]])
            .then_some([a as usize, b as usize])
        })
}

/// Constrained random initialisation, in raster order like error diffusion: each site takes,
/// among the colours its labelled upper and left neighbours do not use (at least one of three
/// remains, so no backtracking is needed), the one least present in its already labelled
/// neighbourhood (Gaussian-weighted density minus the colour's expected share, the "largest
/// void"), after adding uniform random jitter that makes the result aperiodic and seed-dependent.
fn initial_labels(
    valid: &Array2<bool>,
    rng: &mut ChaCha8Rng,
    config: &BlueNoiseConfig,
) -> Array2<u8> {
    let sigma = config.kernel_sigma;
    let r = (2.0 * sigma).ceil() as i64;
    let weight = |di: i64, dj: i64| gaussian_of_squared_distance(di * di + dj * dj, sigma);
    let mut labels = Array2::from_elem(valid.dim(), NONE);
    let (n, m) = valid.dim();
    for i in 0..n {
        for j in 0..m {
            if !valid[[i, j]] {
                continue;
            }
            let mut allowed = [true; 3];
            if i > 0 && labels[[i - 1, j]] != NONE {
                allowed[labels[[i - 1, j]] as usize] = false;
            }
            if j > 0 && labels[[i, j - 1]] != NONE {
                allowed[labels[[i, j - 1]] as usize] = false;
            }
            // Causal neighbourhood: rows above within r, and the current row to the left.
            let mut density = [0.0f64; 3];
            let mut total = 0.0;
            for di in -r..=0 {
                for dj in -r..=r {
                    if di == 0 && dj >= 0 {
                        break;
                    }
                    let (a, b) = (i as i64 + di, j as i64 + dj);
                    if a < 0 || b < 0 || b as usize >= m {
                        continue;
                    }
                    let l = labels[[a as usize, b as usize]];
                    if l != NONE {
                        let wgt = weight(di, dj);
                        density[l as usize] += wgt;
                        total += wgt;
                    }
                }
            }
            let c = (0..3)
                .filter(|&c| allowed[c])
                .map(|c| {
                    (
                        c,
                        density[c] - total / 3.0 + config.jitter * rng.gen::<f64>(),
                    )
                })
                .min_by(|x, y| x.1.total_cmp(&y.1))
                .map(|(c, _)| c)
                .expect("at most two of three colours are excluded");
            labels[[i, j]] = c as u8;
        }
    }
    labels
}

/// Recolours sites of the most frequent colour to the least frequent one (where the neighbour
/// rule allows) until the counts differ by at most one or no such move exists.
fn balance_counts(valid: &Array2<bool>, labels: &mut Array2<u8>, rng: &mut ChaCha8Rng) {
    let mut cells: Vec<[usize; 2]> = labels
        .indexed_iter()
        .filter(|(_, &l)| l != NONE)
        .map(|((i, j), _)| [i, j])
        .collect();
    cells.shuffle(rng);
    loop {
        let counts = colour_counts(labels);
        let hi = (0..3).max_by_key(|&c| counts[c]).unwrap();
        let lo = (0..3).min_by_key(|&c| counts[c]).unwrap();
        if counts[hi] - counts[lo] <= 1 {
            return;
        }
        let movable = cells.iter().copied().find(|&[i, j]| {
            labels[[i, j]] as usize == hi
                && neighbours4(valid, i, j).all(|nb| labels[nb] as usize != lo)
        });
        match movable {
            Some(cell) => labels[cell] = lo as u8,
            None => return,
        }
    }
}

fn colour_counts(labels: &Array2<u8>) -> [usize; 3] {
    let mut counts = [0usize; 3];
    for &l in labels.iter().filter(|&&l| l != NONE) {
        counts[l as usize] += 1;
    }
    counts
}

/// Swap optimisation of `E = Σ_c ‖g ∗ x_c‖²`, `x_c = 1_c − p_c` on the valid sites.
///
/// With `K = g ⋆ g` and `H_c = K ∗ x_c`, swapping colour `a` at site `s` with colour `b` at `t`
/// changes the energy by `ΔE = 2[H_a(t) − H_a(s) + H_b(s) − H_b(t)] + 4[K(0) − K(t − s)]`, so
/// each candidate costs O(1) and an accepted swap updates `H_a`, `H_b` in a kernel-sized window.
fn optimise(
    valid: &Array2<bool>,
    labels: &mut Array2<u8>,
    rng: &mut ChaCha8Rng,
    config: &BlueNoiseConfig,
) {
    let (n, m) = valid.dim();
    let radius = (3.0 * config.kernel_sigma).ceil() as i64;
    let kernel = Kernel::gaussian(config.kernel_sigma, radius);
    let n_sites = valid.iter().filter(|&&v| v).count().max(1);
    let counts = colour_counts(labels);
    // H_c = K ∗ x_c for the three colours.
    let mut h: Vec<Array2<f64>> = (0..3)
        .map(|c| {
            let p = counts[c] as f64 / n_sites as f64;
            let x = Array2::from_shape_fn((n, m), |ix| {
                if !valid[ix] {
                    0.0
                } else if labels[ix] as usize == c {
                    1.0 - p
                } else {
                    -p
                }
            });
            kernel.convolve(&x)
        })
        .collect();

    let mut cells: Vec<[usize; 2]> = labels
        .indexed_iter()
        .filter(|(_, &l)| l != NONE)
        .map(|((i, j), _)| [i, j])
        .collect();
    for _ in 0..config.max_sweeps {
        cells.shuffle(rng);
        let mut accepted = 0usize;
        for &s in &cells {
            let a = labels[s] as usize;
            let mut best: Option<(f64, [usize; 2])> = None;
            for di in -SWAP_RADIUS..=SWAP_RADIUS {
                for dj in -SWAP_RADIUS..=SWAP_RADIUS {
                    let (ti, tj) = (s[0] as i64 + di, s[1] as i64 + dj);
                    if ti < 0 || tj < 0 || ti as usize >= n || tj as usize >= m {
                        continue;
                    }
                    let t = [ti as usize, tj as usize];
                    let b = labels[t];
                    if b == NONE || b as usize == a {
                        continue;
                    }
                    let b = b as usize;
                    let delta = 2.0 * (h[a][t] - h[a][s] + h[b][s] - h[b][t])
                        + 4.0 * (kernel.at(0, 0) - kernel.at(di, dj));
                    if delta < -1e-12
                        && best.map(|(d, _)| delta < d).unwrap_or(true)
                        && swap_keeps_rule(valid, labels, s, t)
                    {
                        best = Some((delta, t));
                    }
                }
            }
            if let Some((_, t)) = best {
                let b = labels[t] as usize;
                labels[s] = b as u8;
                labels[t] = a as u8;
                kernel.stamp(&mut h[a], t, 1.0);
                kernel.stamp(&mut h[a], s, -1.0);
                kernel.stamp(&mut h[b], s, 1.0);
                kernel.stamp(&mut h[b], t, -1.0);
                accepted += 1;
            }
        }
        if accepted == 0 {
            break;
        }
    }
}

/// Whether swapping the labels of `s` and `t` keeps the 4-neighbour rule.
fn swap_keeps_rule(
    valid: &Array2<bool>,
    labels: &Array2<u8>,
    s: [usize; 2],
    t: [usize; 2],
) -> bool {
    let (ls, lt) = (labels[s], labels[t]);
    // After the swap s holds lt and t holds ls; the pair itself differs by construction.
    neighbours4(valid, s[0], s[1]).all(|nb| nb == t || labels[nb] != lt)
        && neighbours4(valid, t[0], t[1]).all(|nb| nb == s || labels[nb] != ls)
}

/// A truncated, unnormalised Gaussian `K(d) = exp(−|d|²/2σ²)` on the lattice grid.
struct Kernel {
    radius: i64,
    /// 1-D factor `exp(−d²/2σ²)` for `d = −radius..=radius`.
    taps: Vec<f64>,
}

impl Kernel {
    fn gaussian(sigma: f64, radius: i64) -> Self {
        let taps = gaussian_taps_f64(sigma, radius);
        Kernel { radius, taps }
    }

    /// `K(di, dj)`, zero beyond the truncation radius.
    fn at(&self, di: i64, dj: i64) -> f64 {
        if di.abs() > self.radius || dj.abs() > self.radius {
            return 0.0;
        }
        self.taps[(di + self.radius) as usize] * self.taps[(dj + self.radius) as usize]
    }

    /// Adds `weight · K(· − centre)` to `field`.
    fn stamp(&self, field: &mut Array2<f64>, centre: [usize; 2], weight: f64) {
        let (n, m) = field.dim();
        let r = self.radius;
        let i_lo = (centre[0] as i64 - r).max(0) as usize;
        let i_hi = ((centre[0] as i64 + r) as usize).min(n - 1);
        let j_lo = (centre[1] as i64 - r).max(0) as usize;
        let j_hi = ((centre[1] as i64 + r) as usize).min(m - 1);
        for i in i_lo..=i_hi {
            let wi = weight * self.taps[(i as i64 - centre[0] as i64 + r) as usize];
            for j in j_lo..=j_hi {
                field[[i, j]] += wi * self.taps[(j as i64 - centre[1] as i64 + r) as usize];
            }
        }
    }

    /// `K ∗ x` with zeros outside the grid (separable: rows, then columns).
    fn convolve(&self, x: &Array2<f64>) -> Array2<f64> {
        let (n, m) = x.dim();
        let r = self.radius;
        let pass = |src: &Array2<f64>, along_rows: bool| {
            Array2::from_shape_fn((n, m), |(i, j)| {
                let mut acc = 0.0;
                for d in -r..=r {
                    let (a, b) = if along_rows {
                        (i as i64, j as i64 + d)
                    } else {
                        (i as i64 + d, j as i64)
                    };
                    if a >= 0 && b >= 0 && (a as usize) < n && (b as usize) < m {
                        acc += self.taps[(d + r) as usize] * src[[a as usize, b as usize]];
                    }
                }
                acc
            })
        };
        pass(&pass(x, true), false)
    }
}

/// Whether no two 4-neighbours on `lattice` share a colour in `codes` (W pixels are ignored).
pub fn satisfies_neighbour_rule(codes: &Array2<u8>, lattice: &SiteLattice) -> bool {
    let (h, w) = codes.dim();
    codes.indexed_iter().all(|((y, x), &c)| {
        let Some((i, j)) = lattice.coords(y, x) else {
            return true;
        };
        [(i + 1, j), (i, j + 1)].into_iter().all(|(a, b)| {
            let (py, px) = lattice.pixel(a, b);
            if py < 0 || px < 0 || py as usize >= h || px as usize >= w {
                return true;
            }
            codes[[py as usize, px as usize]] != c
        })
    })
}
