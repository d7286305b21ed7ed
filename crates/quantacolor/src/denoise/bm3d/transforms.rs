//! The transforms of BM3D (Dabov et al., TIP 2007, §III and Table I): the orthonormal 2D DCT-II
//! of N1 × N1 blocks (this project's choice in both steps), the 1D Haar transform along a group,
//! and the Kaiser window of aggregation; and the blocks' stored or computed 2D spectra.

#![forbid(unsafe_code)]

use super::x86::{block_coeffs_row, matmul8};
use super::{recycled, Geometry};
use crate::cpu::Isa;
use rayon::prelude::*;
use std::f32::consts::FRAC_1_SQRT_2;

/// The 2D DCT-II matrix and the Kaiser aggregation window for `N1 × N1` blocks, and the
/// instruction set the run takes.
pub(crate) struct Transforms {
    pub(super) n: usize,
    /// `dct[k·n + i]`: orthonormal DCT-II basis `k` at sample `i`.
    pub(super) dct: Vec<f32>,
    /// Transpose of `dct`.
    pub(super) dct_t: Vec<f32>,
    /// Separable 2D Kaiser window, row-major `n × n`.
    pub(super) kaiser: Vec<f32>,
    /// The instruction set of this run, taken once at the entry: the 8 × 8 products'
    /// kernel ([`matmul8`]) and the AVX2 build of the reference rows (`x86::process_row`).
    pub(super) isa: Isa,
}

impl Transforms {
    pub(crate) fn new(n: usize, beta: f32, isa: Isa) -> Self {
        let mut dct = vec![0.0f32; n * n];
        for k in 0..n {
            let ck = if k == 0 {
                (1.0 / n as f64).sqrt()
            } else {
                (2.0 / n as f64).sqrt()
            };
            for i in 0..n {
                let arg = std::f64::consts::PI * (2 * i + 1) as f64 * k as f64 / (2 * n) as f64;
                dct[k * n + i] = (ck * arg.cos()) as f32;
            }
        }
        let mut dct_t = vec![0.0f32; n * n];
        for k in 0..n {
            for i in 0..n {
                dct_t[i * n + k] = dct[k * n + i];
            }
        }
        let k1 = kaiser_1d(n, beta as f64);
        let kaiser = (0..n * n).map(|i| k1[i / n] * k1[i % n]).collect();
        Transforms {
            n,
            dct,
            dct_t,
            kaiser,
            isa,
        }
    }

    /// `out = D · block · Dᵀ` (row-major `n × n`); `tmp` is scratch of `n²`.
    #[inline(always)]
    pub(crate) fn forward(&self, block: &[f32], tmp: &mut [f32], out: &mut [f32]) {
        self.sandwich(&self.dct, block, &self.dct_t, tmp, out);
    }

    /// `out = Dᵀ · coeffs · D`, the inverse of [`Transforms::forward`].
    #[inline(always)]
    pub(crate) fn inverse(&self, coeffs: &[f32], tmp: &mut [f32], out: &mut [f32]) {
        self.sandwich(&self.dct_t, coeffs, &self.dct, tmp, out);
    }

    /// `out = left · x · right` for row-major `n × n` matrices: `tmp[r][·] = Σ_i left[r][i] ·
    /// x[i][·]`, then `out[r][·] = Σ_j tmp[r][j] · right[j][·]`, each row accumulated from zero
    /// in index order ([`axpy`]); `tmp` is scratch of `n²`.
    #[inline(always)]
    fn sandwich(&self, left: &[f32], x: &[f32], right: &[f32], tmp: &mut [f32], out: &mut [f32]) {
        let n = self.n;
        if n == 8 {
            // The default block size, with sizes known to the compiler (unrolled and
            // vectorised): the same products summed in the same order.
            let left: &[f32; 64] = left[..64].try_into().expect("8 x 8");
            let right: &[f32; 64] = right[..64].try_into().expect("8 x 8");
            let x: &[f32; 64] = x[..64].try_into().expect("8 x 8 block");
            let out: &mut [f32; 64] = (&mut out[..64]).try_into().expect("8 x 8 block");
            let mut t = [0.0f32; 64];
            matmul8(self.isa, left, x, &mut t);
            // The second product reads `t` back from memory (see `x86::matmul8_avx2`).
            std::hint::black_box(&mut t);
            matmul8(self.isa, &t, right, out);
            return;
        }
        tmp[..n * n].fill(0.0);
        for r in 0..n {
            let row = &mut tmp[r * n..(r + 1) * n];
            for i in 0..n {
                axpy(row, left[r * n + i], &x[i * n..(i + 1) * n]);
            }
        }
        out[..n * n].fill(0.0);
        for r in 0..n {
            let dst = &mut out[r * n..(r + 1) * n];
            for j in 0..n {
                axpy(dst, tmp[r * n + j], &right[j * n..(j + 1) * n]);
            }
        }
    }
}

/// [`matmul8`] without SIMD intrinsics.
#[inline(always)]
pub(super) fn matmul8_portable(a: &[f32; 64], b: &[f32; 64], out: &mut [f32; 64]) {
    for r in 0..8 {
        let mut row = [0.0f32; 8];
        for i in 0..8 {
            let s = a[r * 8 + i];
            for j in 0..8 {
                row[j] += s * b[i * 8 + j];
            }
        }
        out[r * 8..r * 8 + 8].copy_from_slice(&row);
    }
}

#[inline]
pub(super) fn axpy(dst: &mut [f32], a: f32, x: &[f32]) {
    for (d, &v) in dst.iter_mut().zip(x) {
        *d += a * v;
    }
}

/// Symmetric Kaiser window of length `n`: `I0(β·sqrt(1 − (2i/(n−1) − 1)²)) / I0(β)`.
pub(super) fn kaiser_1d(n: usize, beta: f64) -> Vec<f32> {
    if n == 1 {
        return vec![1.0];
    }
    let denom = bessel_i0(beta);
    (0..n)
        .map(|i| {
            let r = 2.0 * i as f64 / (n - 1) as f64 - 1.0;
            (bessel_i0(beta * (1.0 - r * r).max(0.0).sqrt()) / denom) as f32
        })
        .collect()
}

/// Modified Bessel function of the first kind, order 0, by its power series.
pub(super) fn bessel_i0(x: f64) -> f64 {
    let q = x * x / 4.0;
    let (mut term, mut sum) = (1.0f64, 1.0f64);
    for k in 1..200 {
        term *= q / (k * k) as f64;
        sum += term;
        if term < sum * 1e-17 {
            break;
        }
    }
    sum
}

/// 2D DCT coefficients of every `n × n` block position of one plane, row-major over positions.
pub(super) struct BlockCoeffs {
    pub(super) n2: usize,
    pub(super) pw: usize,
    /// Where the coefficients start in `data`: its first 64-byte boundary ([`line_start`]), so
    /// that an 8 × 8 block's 256 bytes are four whole cache lines. From the allocation's own
    /// 16-byte alignment every block spanned five, and matching, which loads a block for every
    /// candidate that passes its first check, waited for a fifth of the lines more (the
    /// prefetch of a block's four lines left its last one out).
    pub(super) start: usize,
    /// `start` + the coefficients + [`LINE_FLOATS`] of room.
    pub(super) data: Vec<f32>,
}

/// f32 values per 64-byte cache line.
const LINE_FLOATS: usize = 16;

/// The index of the first 64-byte boundary in `data` (f32 allocations are 4-byte aligned, so it
/// is below [`LINE_FLOATS`]).
fn line_start(data: &[f32]) -> usize {
    let misalignment = data.as_ptr() as usize % 64;
    (64 - misalignment) % 64 / std::mem::size_of::<f32>()
}

impl BlockCoeffs {
    #[cfg(test)]
    pub(super) fn compute(plane: &[f32], geo: &Geometry, tr: &Transforms) -> Self {
        Self::compute_in(Vec::new(), plane, geo, tr)
    }

    /// [`BlockCoeffs::compute`] in `buffer`'s allocation ([`super::Bm3dBuffers`]; every value is
    /// overwritten).
    pub(super) fn compute_in(
        buffer: Vec<f32>,
        plane: &[f32],
        geo: &Geometry,
        tr: &Transforms,
    ) -> Self {
        let (n, n2, pw, w) = (geo.n, geo.n * geo.n, geo.pw, geo.w);
        let len = geo.ph * pw * n2;
        let mut data = recycled(buffer, len + LINE_FLOATS, false);
        let start = line_start(&data);
        data[start..start + len]
            .par_chunks_mut(pw * n2)
            .enumerate()
            .for_each(|(y, row)| block_coeffs_row(plane, y, n, w, tr, row));
        BlockCoeffs {
            n2,
            pw,
            start,
            data,
        }
    }

    /// The coefficients of the blocks of position row `y` into `row` (the portable reference
    /// of `x86::block_coeffs_row`).
    #[inline(always)]
    pub(super) fn row(
        plane: &[f32],
        y: usize,
        n: usize,
        w: usize,
        tr: &Transforms,
        row: &mut [f32],
    ) {
        let n2 = n * n;
        if n == 8 {
            // Separably: the column transform D·(rows y..y+8) once for every column, shared by
            // the eight blocks that contain the column, then each block's ·Dᵀ. Every
            // coefficient is the same products summed in the same order as `forward`'s.
            let d: &[f32; 64] = tr.dct[..64].try_into().expect("8 x 8");
            let dt: &[f32; 64] = tr.dct_t[..64].try_into().expect("8 x 8");
            let mut columns = vec![0.0f32; 8 * w];
            for (k, out) in columns.chunks_exact_mut(w).enumerate() {
                for i in 0..8 {
                    let src = &plane[(y + i) * w..(y + i + 1) * w];
                    axpy(out, d[k * 8 + i], src);
                }
            }
            let mut t = [0.0f32; 64];
            for (x, dst) in row.chunks_exact_mut(n2).enumerate() {
                for k in 0..8 {
                    t[k * 8..k * 8 + 8].copy_from_slice(&columns[k * w + x..k * w + x + 8]);
                }
                let dst: &mut [f32; 64] = dst.try_into().expect("8 x 8 block");
                matmul8(tr.isa, &t, dt, dst);
            }
            return;
        }
        let mut block = vec![0.0f32; n2];
        let mut tmp = vec![0.0f32; n2];
        for (x, dst) in row.chunks_exact_mut(n2).enumerate() {
            for i in 0..n {
                let src = &plane[(y + i) * w + x..(y + i) * w + x + n];
                block[i * n..(i + 1) * n].copy_from_slice(src);
            }
            tr.forward(&block, &mut tmp, dst);
        }
    }

    /// A copy with every coefficient of magnitude ≤ `t` set to zero (Step 1 matching, σ > 40).
    pub(super) fn hard_thresholded(&self, t: f32) -> Self {
        let mut data = vec![0.0f32; self.data.len()];
        let start = line_start(&data);
        let coefficients = self.coefficients();
        data[start..start + coefficients.len()]
            .par_iter_mut()
            .zip(coefficients.par_iter())
            .for_each(|(dst, &v)| *dst = if v.abs() > t { v } else { 0.0 });
        BlockCoeffs {
            n2: self.n2,
            pw: self.pw,
            start,
            data,
        }
    }

    /// Every position's coefficients.
    pub(super) fn coefficients(&self) -> &[f32] {
        &self.data[self.start..self.start + self.data.len() - LINE_FLOATS]
    }

    #[inline]
    pub(super) fn block(&self, pos: usize) -> &[f32] {
        let at = self.start + pos * self.n2;
        &self.data[at..at + self.n2]
    }
}

/// Where a step reads the 2D DCT coefficients of a channel's blocks: stored for every
/// position (the step's matching channel, which is read at every position of every search
/// window), or computed from the plane for each group member (the other channels, and noisy
/// channel 0 in Step 2: with the reference grid's stride of 5 and groups of up to 16 / 32, a
/// position is a group member about once or twice per step on average, so storing every
/// position's coefficients, tens of MB per channel, cost more in page faults and cache misses
/// than transforming the members; measured with perf: keeping Step 1's noisy channel 0 for
/// Step 2 cost 14k page faults per call on a 496 × 254 image). Both give the same bits
/// ([`Transforms::forward`] is [`BlockCoeffs`]' transform, test
/// `block_coefficients_are_each_blocks_own_transform_bit_for_bit`).
pub(super) enum BlockSource<'a> {
    Stored(&'a BlockCoeffs),
    Plane(&'a [f32]),
}

impl BlockSource<'_> {
    /// The coefficients of the block at position `pos` into `out` (`n²`); `pixels` and `tmp`
    /// are scratch of `n²`.
    #[inline(always)]
    pub(super) fn block_into(
        &self,
        pos: usize,
        geo: &Geometry,
        tr: &Transforms,
        (pixels, tmp): (&mut [f32], &mut [f32]),
        out: &mut [f32],
    ) {
        match self {
            BlockSource::Stored(coeffs) => copy_coefficients(out, coeffs.block(pos)),
            BlockSource::Plane(plane) => {
                let (n, w) = (geo.n, geo.w);
                let (y, x) = (pos / geo.pw, pos % geo.pw);
                if n == 8 {
                    let mut block = [0.0f32; 64];
                    for (i, row) in block.chunks_exact_mut(8).enumerate() {
                        let at = (y + i) * w + x;
                        row.copy_from_slice(&plane[at..at + 8]);
                    }
                    tr.forward(&block, tmp, out);
                    return;
                }
                for i in 0..n {
                    let at = (y + i) * w + x;
                    pixels[i * n..(i + 1) * n].copy_from_slice(&plane[at..at + n]);
                }
                tr.forward(pixels, tmp, out);
            }
        }
    }
}

/// Channel 0 from its stored coefficients, the others from their planes.
pub(super) fn block_sources<'a>(
    channel0: &'a BlockCoeffs,
    planes: &'a [Vec<f32>],
) -> Vec<BlockSource<'a>> {
    std::iter::once(BlockSource::Stored(channel0))
        .chain(planes[1..].iter().map(|p| BlockSource::Plane(p)))
        .collect()
}

/// `dst.copy_from_slice(src)`, as a fixed-size copy for 8 × 8 blocks (no call to `memcpy`).
#[inline(always)]
fn copy_coefficients(dst: &mut [f32], src: &[f32]) {
    match (
        <&mut [f32; 64]>::try_from(&mut *dst),
        <&[f32; 64]>::try_from(src),
    ) {
        (Ok(d), Ok(s)) => *d = *s,
        _ => dst.copy_from_slice(src),
    }
}

/// Orthonormal 1D Haar transform along the group (full decomposition) of `m` (a power of two)
/// stacked `n2`-coefficient blocks: `g[b·n2 + k]`. Output order: approximation, then details
/// from coarse to fine.
#[inline(always)]
pub(crate) fn haar_forward(g: &mut [f32], m: usize, n2: usize, tmp: &mut [f32]) {
    let rem = n2 % 8; // not is_multiple_of: rust-version is 1.80
    if rem == 0 && m <= MAX_LANE_GROUP {
        haar_lanes::<true>(g, m, n2);
    } else {
        haar_forward_general(g, m, n2, tmp);
    }
}

/// [`haar_forward`] level by level over whole blocks (any `n2` and `m`).
#[inline(always)]
pub(super) fn haar_forward_general(g: &mut [f32], m: usize, n2: usize, tmp: &mut [f32]) {
    let mut len = m;
    while len > 1 {
        let half = len / 2;
        for i in 0..half {
            for k in 0..n2 {
                let a = g[2 * i * n2 + k];
                let b = g[(2 * i + 1) * n2 + k];
                tmp[i * n2 + k] = (a + b) * FRAC_1_SQRT_2;
                tmp[(half + i) * n2 + k] = (a - b) * FRAC_1_SQRT_2;
            }
        }
        g[..len * n2].copy_from_slice(&tmp[..len * n2]);
        len = half;
    }
}

/// Inverse of [`haar_forward`].
#[inline(always)]
pub(crate) fn haar_inverse(g: &mut [f32], m: usize, n2: usize, tmp: &mut [f32]) {
    let rem = n2 % 8; // not is_multiple_of: rust-version is 1.80
    if rem == 0 && m <= MAX_LANE_GROUP {
        haar_lanes::<false>(g, m, n2);
    } else {
        haar_inverse_general(g, m, n2, tmp);
    }
}

/// [`haar_inverse`] level by level over whole blocks (any `n2` and `m`).
#[inline(always)]
pub(super) fn haar_inverse_general(g: &mut [f32], m: usize, n2: usize, tmp: &mut [f32]) {
    let mut len = 2;
    while len <= m {
        let half = len / 2;
        for i in 0..half {
            for k in 0..n2 {
                let a = g[i * n2 + k];
                let d = g[(half + i) * n2 + k];
                tmp[2 * i * n2 + k] = (a + d) * FRAC_1_SQRT_2;
                tmp[(2 * i + 1) * n2 + k] = (a - d) * FRAC_1_SQRT_2;
            }
        }
        g[..len * n2].copy_from_slice(&tmp[..len * n2]);
        len *= 2;
    }
}

/// Largest group that [`haar_lanes`] transforms on the stack.
pub(super) const MAX_LANE_GROUP: usize = 32;

/// Eight lanes of every group member (`[[f32; 8]; MAX_LANE_GROUP]`, first `m` rows used).
pub(super) type Lanes = [[f32; 8]; MAX_LANE_GROUP];

/// Eight coefficients of every group member at a time, held in stack arrays while the
/// transform ([`haar_forward_lanes`] when `FORWARD`, else [`haar_inverse_lanes`]) runs all
/// levels on them: the same operations on the same values as the general path of
/// [`haar_forward`] / [`haar_inverse`] (so the same bits), without copying the whole group back
/// after every level.
///
/// The transforms are called directly, not passed as functions: passed as a value, the
/// transform was compiled on its own (through `Fn::call`, without AVX2 and out of line) and
/// took 8 % of the denoiser's time (perf); called directly it is inlined into the AVX2 build.
/// The work arrays are made once per call, not once per eight coefficients (every row a
/// transform reads was written by it first, so their contents never matter).
///
/// For 8 × 8 blocks (`n2` = 64) and every group size up to [`MAX_LANE_GROUP`], the sizes are
/// passed as constants to [`haar_lanes_sized`] (inlined), so that the compiler unrolls the
/// levels and drops the bounds checks of the copies in and out (they took about half of the
/// transform's time, perf); the same operations, so the same bits.
#[inline(always)]
fn haar_lanes<const FORWARD: bool>(g: &mut [f32], m: usize, n2: usize) {
    if n2 == 64 {
        match m {
            1 => return haar_lanes_sized::<FORWARD>(&mut g[..64], 1, 64),
            2 => return haar_lanes_sized::<FORWARD>(&mut g[..2 * 64], 2, 64),
            4 => return haar_lanes_sized::<FORWARD>(&mut g[..4 * 64], 4, 64),
            8 => return haar_lanes_sized::<FORWARD>(&mut g[..8 * 64], 8, 64),
            16 => return haar_lanes_sized::<FORWARD>(&mut g[..16 * 64], 16, 64),
            32 => return haar_lanes_sized::<FORWARD>(&mut g[..32 * 64], 32, 64),
            _ => {}
        }
    }
    haar_lanes_sized::<FORWARD>(g, m, n2);
}

/// The body of [`haar_lanes`], for `m` blocks of `n2` coefficients.
#[inline(always)]
fn haar_lanes_sized<const FORWARD: bool>(g: &mut [f32], m: usize, n2: usize) {
    let (mut x, mut y) = ([[0.0f32; 8]; MAX_LANE_GROUP], [[0.0f32; 8]; MAX_LANE_GROUP]);
    let mut work = [[[0.0f32; 8]; MAX_LANE_GROUP]; 2];
    for chunk in 0..n2 / 8 {
        let lanes = chunk * 8..chunk * 8 + 8;
        for (x, row) in x[..m].iter_mut().zip(g.chunks_exact(n2)) {
            *x = row[lanes.clone()].try_into().expect("eight lanes");
        }
        if FORWARD {
            haar_forward_lanes(&mut x, &mut y, &mut work[0], m);
        } else {
            haar_inverse_lanes(&mut x, &mut y, &mut work, m);
        }
        for (y, row) in y[..m].iter().zip(g.chunks_exact_mut(n2)) {
            row[lanes.clone()].copy_from_slice(y);
        }
    }
}

/// [`haar_forward`] of the lanes `x` into `y` (`x` is overwritten): each level's details go
/// straight to their place in `y`, its approximation to the other of `x` and `work`.
#[inline(always)]
pub(super) fn haar_forward_lanes(x: &mut Lanes, y: &mut Lanes, work: &mut Lanes, m: usize) {
    let (mut src, mut dst) = (x, work);
    let mut len = m;
    while len > 1 {
        let half = len / 2;
        for i in 0..half {
            // Whole rows into locals first: no store can alias a load, so it vectorises.
            let (a, b) = (src[2 * i], src[2 * i + 1]);
            dst[i] = std::array::from_fn(|k| (a[k] + b[k]) * FRAC_1_SQRT_2);
            y[half + i] = std::array::from_fn(|k| (a[k] - b[k]) * FRAC_1_SQRT_2);
        }
        std::mem::swap(&mut src, &mut dst);
        len = half;
    }
    y[0] = src[0];
}

/// [`haar_inverse`] of the lanes `x` into `y`: each level reads the approximation of the
/// level before (at first `x[0]`) and its details in `x`, and writes to the other of the two
/// `work` arrays; the last level writes `y`.
#[inline(always)]
pub(super) fn haar_inverse_lanes(x: &mut Lanes, y: &mut Lanes, work: &mut [Lanes; 2], m: usize) {
    if m == 1 {
        y[0] = x[0];
        return;
    }
    let [p, q] = work;
    p[0] = x[0];
    let (mut approx, mut next) = (p, q);
    let mut len = 2;
    while len <= m {
        let half = len / 2;
        let out: &mut Lanes = if len == m { &mut *y } else { &mut *next };
        for i in 0..half {
            // As in `haar_forward_lanes` (here `out` is one of two arrays chosen at run time,
            // and the compiler left the element-wise loop scalar).
            let (a, d) = (approx[i], x[half + i]);
            out[2 * i] = std::array::from_fn(|k| (a[k] + d[k]) * FRAC_1_SQRT_2);
            out[2 * i + 1] = std::array::from_fn(|k| (a[k] - d[k]) * FRAC_1_SQRT_2);
        }
        std::mem::swap(&mut approx, &mut next);
        len *= 2;
    }
}
