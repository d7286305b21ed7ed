//! Bilinear warping of block images onto the reference grid (supplement §1.2).

use crate::error::{Error, Result};
use crate::filters::bilinear_taps;
use ndarray::{Array2, Array3};
use rayon::prelude::*;

/// True for a positive number (false for NaN): parameter validation.
pub(crate) fn positive(v: f32) -> bool {
    v > 0.0
}

/// Checks that `flow` is a dense (H, W, 2) field for an (H, W) image; `what` names it.
pub(crate) fn check_flow(flow: &Array3<f32>, h: usize, w: usize, what: &str) -> Result<()> {
    if flow.dim() != (h, w, 2) {
        return Err(Error::invalid(format!(
            "{what}: flow has shape {:?}, expected ({h}, {w}, 2)",
            flow.dim()
        )));
    }
    let non_finite = match flow.as_slice_memory_order() {
        // A plain slice scan vectorises.
        Some(values) => values.iter().any(|v| !v.is_finite()),
        None => flow.iter().any(|v| !v.is_finite()),
    };
    if non_finite {
        return Err(Error::invalid(format!(
            "{what}: flow holds non-finite values"
        )));
    }
    Ok(())
}

/// Warps `block` onto the reference grid: output(p) = block(p + flow(p)) by bilinear sampling
/// (flows are (dy, dx); a scene point at p in the reference is at p + flow(p) in the block).
/// Positions outside the block are clamped to its edge. `flow` must be (H, W, 2).
pub fn warp_to_reference(block: &Array2<f32>, flow: &Array3<f32>) -> Result<Array2<f32>> {
    let (h, w) = block.dim();
    if h == 0 || w == 0 {
        return Err(Error::invalid("cannot warp an empty block image"));
    }
    check_flow(flow, h, w, "warp")?;
    let (block, flow) = (block.as_standard_layout(), flow.as_standard_layout());
    let (pixels, flow) = (
        block.as_slice().expect("standard layout"),
        flow.as_slice().expect("standard layout"),
    );
    let mut out = Array2::<f32>::zeros((h, w));
    out.as_slice_mut()
        .expect("fresh array is contiguous")
        .par_chunks_exact_mut(w)
        .zip(flow.par_chunks_exact(2 * w))
        .enumerate()
        .for_each(|(y, (row, flow))| warp_row(pixels, h, y, flow, row));
    Ok(out)
}

/// Row `y` of [`warp_to_reference`] of the (H, W) image `pixels` (row-major) with that row's
/// flow `flow` ((dy, dx) pairs, finite) into `out`: eight pixels at a time in AVX2 registers
/// where the CPU has them ([`warp_row_avx2`], the same bits), else [`warp_row_scalar`].
#[inline]
fn warp_row(pixels: &[f32], h: usize, y: usize, flow: &[f32], out: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && pixels.len() < i32::MAX as usize {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { warp_row_avx2(pixels, h, y, flow, out) };
            return;
        }
    }
    warp_row_scalar(pixels, h, y, 0, flow, out);
}

/// Pixels `start..` of row `y` of [`warp_row`]. Plain slices: the same taps and arithmetic as
/// [`crate::filters::bilinear`], without the 2-D index checks.
#[inline]
fn warp_row_scalar(
    pixels: &[f32],
    h: usize,
    y: usize,
    start: usize,
    flow: &[f32],
    out: &mut [f32],
) {
    let w = out.len();
    let flow = &flow[2 * start..];
    for (x, (out, d)) in (start..).zip(out[start..].iter_mut().zip(flow.chunks_exact(2))) {
        let (y0, y1, fy) = bilinear_taps(y as f32 + d[0], h);
        let (x0, x1, fx) = bilinear_taps(x as f32 + d[1], w);
        let (top, bottom) = (&pixels[y0 * w..(y0 + 1) * w], &pixels[y1 * w..(y1 + 1) * w]);
        let top = top[x0] * (1.0 - fx) + top[x1] * fx;
        let bottom = bottom[x0] * (1.0 - fx) + bottom[x1] * fx;
        *out = top * (1.0 - fy) + bottom * fy;
    }
}

/// [`warp_row_scalar`] eight pixels at a time: the positions clamped as
/// [`bilinear_taps`] clamps them (`min(hi, max(0, v))`, operands in that order, keeps a −0 as
/// `clamp` does; the flow is finite, so no NaN), the four taps gathered, and the same products and sums in the same order (no
/// fused multiply-add), so the same bits; the row's last `W mod 8` pixels scalar.
///
/// # Safety
/// The CPU must support AVX2; `pixels` (H·W values) must be indexable in i32 and `flow` hold
/// 2·W finite values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn warp_row_avx2(pixels: &[f32], h: usize, y: usize, flow: &[f32], out: &mut [f32]) {
    use std::arch::x86_64::*;
    let w = out.len();
    assert!(pixels.len() == h * w && flow.len() == 2 * w && h * w < i32::MAX as usize);
    let (zero, one) = (_mm256_setzero_ps(), _mm256_set1_ps(1.0));
    let (y_hi, x_hi) = (
        _mm256_set1_ps((h - 1) as f32),
        _mm256_set1_ps((w - 1) as f32),
    );
    let (y_last, x_last) = (
        _mm256_set1_epi32((h - 1) as i32),
        _mm256_set1_epi32((w - 1) as i32),
    );
    let (width, step) = (_mm256_set1_epi32(w as i32), _mm256_set1_epi32(1));
    let row = _mm256_set1_ps(y as f32);
    let lanes = _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0);
    let base = pixels.as_ptr();
    let taps = |v: __m256, hi: __m256, last: __m256i| {
        // `bilinear_taps`: clamp, truncate, the next tap and the fraction.
        let v = _mm256_min_ps(hi, _mm256_max_ps(zero, v));
        let v0 = _mm256_cvttps_epi32(v);
        let v1 = _mm256_min_epi32(_mm256_add_epi32(v0, step), last);
        (v0, v1, _mm256_sub_ps(v, _mm256_cvtepi32_ps(v0)))
    };
    let mut x = 0;
    while x + 8 <= w {
        // (dy, dx) of pixels x..x + 8, split into dy and dx in pixel order.
        let a = _mm256_loadu_ps(flow.as_ptr().add(2 * x));
        let b = _mm256_loadu_ps(flow.as_ptr().add(2 * x + 8));
        let dy = _mm256_castpd_ps(_mm256_permute4x64_pd::<0xD8>(_mm256_castps_pd(
            _mm256_shuffle_ps::<0x88>(a, b),
        )));
        let dx = _mm256_castpd_ps(_mm256_permute4x64_pd::<0xD8>(_mm256_castps_pd(
            _mm256_shuffle_ps::<0xDD>(a, b),
        )));
        let column = _mm256_add_ps(_mm256_set1_ps(x as f32), lanes);
        let (y0, y1, fy) = taps(_mm256_add_ps(row, dy), y_hi, y_last);
        let (x0, x1, fx) = taps(_mm256_add_ps(column, dx), x_hi, x_last);
        let (top, bottom) = (_mm256_mullo_epi32(y0, width), _mm256_mullo_epi32(y1, width));
        let gather = |i: __m256i| _mm256_i32gather_ps::<4>(base, i);
        let (t0, t1) = (
            gather(_mm256_add_epi32(top, x0)),
            gather(_mm256_add_epi32(top, x1)),
        );
        let (b0, b1) = (
            gather(_mm256_add_epi32(bottom, x0)),
            gather(_mm256_add_epi32(bottom, x1)),
        );
        let (gx, gy) = (_mm256_sub_ps(one, fx), _mm256_sub_ps(one, fy));
        let t = _mm256_add_ps(_mm256_mul_ps(t0, gx), _mm256_mul_ps(t1, fx));
        let b = _mm256_add_ps(_mm256_mul_ps(b0, gx), _mm256_mul_ps(b1, fx));
        let v = _mm256_add_ps(_mm256_mul_ps(t, gy), _mm256_mul_ps(b, fy));
        _mm256_storeu_ps(out.as_mut_ptr().add(x), v);
        x += 8;
    }
    warp_row_scalar(pixels, h, y, x, flow, out);
}

/// [`warp_to_reference`] with the flow made row by row: `flow_row(y, row)` fills `row` with
/// the (dy, dx) pairs of image row `y` (2·W values). The same output as the dense flow those
/// rows make up, without holding it: a flow given by a formula (a camera's affine motion)
/// costs neither the (H, W, 2) array nor its memory traffic. A row holding a non-finite value
/// is an error, as [`check_flow`] makes it.
pub(crate) fn warp_rows_to_reference(
    block: &Array2<f32>,
    flow_row: impl Fn(usize, &mut [f32]) + Sync,
) -> Result<Array2<f32>> {
    let (h, w) = block.dim();
    if h == 0 || w == 0 {
        return Err(Error::invalid("cannot warp an empty block image"));
    }
    let block = block.as_standard_layout();
    let pixels = block.as_slice().expect("standard layout");
    let mut out = Array2::<f32>::zeros((h, w));
    out.as_slice_mut()
        .expect("fresh array is contiguous")
        .par_chunks_exact_mut(w)
        .enumerate()
        .try_for_each_init(
            || vec![0.0f32; 2 * w],
            |flow, (y, row)| {
                flow_row(y, flow);
                if flow.iter().any(|v| !v.is_finite()) {
                    return Err(Error::invalid("warp: flow holds non-finite values"));
                }
                warp_row(pixels, h, y, flow, row);
                Ok(())
            },
        )?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The AVX2 row warp equals the scalar one bit for bit: widths with and without a scalar
    /// tail, one-pixel rows and columns, positions past every edge and at −0.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_row_warp_is_bit_identical_to_scalar() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut checked = 0;
        for (h, w) in [
            (1usize, 1usize),
            (1, 17),
            (9, 1),
            (7, 8),
            (11, 13),
            (24, 40),
        ] {
            let pixels: Vec<f32> = (0..h * w).map(|_| rng.gen_range(-1.0..2.0)).collect();
            for y in 0..h {
                let flow: Vec<f32> = (0..2 * w)
                    .map(|i| match rng.gen_range(0..6) {
                        // Onto the first row or column exactly: a −0 position.
                        0 => -((if i % 2 == 0 { y } else { i / 2 }) as f32),
                        1 => rng.gen_range(-60.0..60.0),
                        _ => rng.gen_range(-2.5..2.5),
                    })
                    .collect();
                let (mut simd, mut scalar) = (vec![f32::NAN; w], vec![f32::NAN; w]);
                // SAFETY: AVX2 checked above; the sizes are the function's.
                unsafe { warp_row_avx2(&pixels, h, y, &flow, &mut simd) };
                warp_row_scalar(&pixels, h, y, 0, &flow, &mut scalar);
                for x in 0..w {
                    assert_eq!(
                        simd[x].to_bits(),
                        scalar[x].to_bits(),
                        "{h}x{w} at ({y}, {x}): {} vs {}",
                        simd[x],
                        scalar[x]
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked > 1000);
    }

    /// The row-by-row warp equals the dense one, and a non-finite flow is an error in both.
    #[test]
    fn row_warp_matches_the_dense_warp() {
        let (h, w) = (19usize, 29usize);
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let block = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0));
        let mut flow = Array3::from_shape_fn((h, w, 2), |_| rng.gen_range(-4.0f32..4.0));
        let dense = warp_to_reference(&block, &flow).unwrap();
        let rows = warp_rows_to_reference(&block, |y, row| {
            row.copy_from_slice(flow.slice(ndarray::s![y, .., ..]).as_slice().unwrap())
        })
        .unwrap();
        assert!(dense
            .iter()
            .zip(&rows)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!(dense.iter().zip(&block).any(|(a, b)| a != b));
        flow[[3, 4, 1]] = f32::NAN;
        assert!(warp_to_reference(&block, &flow).is_err());
        assert!(warp_rows_to_reference(&block, |y, row| {
            row.copy_from_slice(flow.slice(ndarray::s![y, .., ..]).as_slice().unwrap())
        })
        .is_err());
    }
}
