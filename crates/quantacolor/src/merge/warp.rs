//! Bilinear warping of block images onto the reference grid (supplement §1.2).

use crate::cpu::Isa;
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
        // A plain slice scan without an early exit per value vectorises.
        Some(values) => values
            .chunks(256)
            .any(|chunk| !chunk.iter().fold(true, |ok, v| ok & v.is_finite())),
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
    check_flow(flow, h, w, "warp")?;
    warp_checked(block, flow)
}

/// [`warp_to_reference`] of a `flow` that [`check_flow`] has passed for `block`'s shape.
pub(crate) fn warp_checked(block: &Array2<f32>, flow: &Array3<f32>) -> Result<Array2<f32>> {
    warp_checked_on(Isa::current(), block, flow)
}

/// [`warp_checked`] on the instruction set `isa`.
fn warp_checked_on(isa: Isa, block: &Array2<f32>, flow: &Array3<f32>) -> Result<Array2<f32>> {
    let (h, w) = block.dim();
    if h == 0 || w == 0 {
        return Err(Error::invalid("cannot warp an empty block image"));
    }
    // Plain slices (the same taps and arithmetic as [`crate::filters::bilinear`], without the 2-D index checks).
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
        .for_each(|(y, (row, flow))| warp_row(isa, pixels, h, y, flow, row));
    Ok(out)
}

/// Fixed-point steps of [`relative_flow`]'s inversion: each shrinks the error by the flow's
/// change per pixel (a camera turning by 2° changes it by 0.035), so three leave about 10⁻⁴
/// of the first guess's error.
const INVERSE_STEPS: usize = 3;

/// The flow between two images of one scene on the grid of the first: `from` and `to` are
/// flows from the reference grid (a scene point at p in the reference is at p + flow(p) in
/// each image, as [`warp_to_reference`] takes them); a pixel q of the `from` image shows the
/// scene point that lies at q + out(q) in the `to` image, so `warp_to_reference(to_image,
/// &out)` resamples the `to` image onto the `from` image's grid. The reference position of q
/// is the fixed point of p ← q − from(p) ([`INVERSE_STEPS`] steps, flows sampled bilinearly
/// and clamped at the edges). Both flows must be (H, W, 2) and finite.
pub fn relative_flow(from: &Array3<f32>, to: &Array3<f32>) -> Result<Array3<f32>> {
    let (h, w, _) = from.dim();
    check_flow(from, h, w, "relative flow (from)")?;
    check_flow(to, h, w, "relative flow (to)")?;
    if h == 0 || w == 0 {
        return Err(Error::invalid("relative flow: empty flows"));
    }
    let (from, to) = (from.as_standard_layout(), to.as_standard_layout());
    let (from, to) = (
        from.as_slice().expect("standard layout"),
        to.as_slice().expect("standard layout"),
    );
    let sample = |flow: &[f32], y: f32, x: f32| -> [f32; 2] {
        let (y0, y1, fy) = bilinear_taps(y, h);
        let (x0, x1, fx) = bilinear_taps(x, w);
        std::array::from_fn(|c| {
            let at = |yy: usize, xx: usize| flow[(yy * w + xx) * 2 + c];
            let top = at(y0, x0) * (1.0 - fx) + at(y0, x1) * fx;
            let bottom = at(y1, x0) * (1.0 - fx) + at(y1, x1) * fx;
            top * (1.0 - fy) + bottom * fy
        })
    };
    let mut out = Array3::<f32>::zeros((h, w, 2));
    out.as_slice_mut()
        .expect("fresh array is contiguous")
        .par_chunks_exact_mut(2 * w)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, out) in row.chunks_exact_mut(2).enumerate() {
                let (qy, qx) = (y as f32, x as f32);
                let d = &from[(y * w + x) * 2..][..2];
                let mut p = [qy - d[0], qx - d[1]];
                for _ in 0..INVERSE_STEPS {
                    let d = sample(from, p[0], p[1]);
                    p = [qy - d[0], qx - d[1]];
                }
                let d = sample(to, p[0], p[1]);
                out[0] = p[0] + d[0] - qy;
                out[1] = p[1] + d[1] - qx;
            }
        });
    Ok(out)
}

/// Output row `y` of [`warp_to_reference`]: `row[x]` = the bilinear sample of the (H, W)
/// image `pixels` at (y, x) + `flow[x]` (`h` = H, W = `row.len()`), eight pixels at a time
/// where `isa` has AVX2 (the same bits).
fn warp_row(isa: Isa, pixels: &[f32], h: usize, y: usize, flow: &[f32], row: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if isa.avx2() {
            // SAFETY: an `Isa` with AVX2 exists only on a CPU that supports it.
            let done = unsafe { warp_row_avx2(pixels, h, y, flow, row) };
            return warp_row_from(pixels, h, y, flow, row, done);
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = isa;
    warp_row_from(pixels, h, y, flow, row, 0)
}

/// [`warp_row`] from column `x0` on, one pixel at a time.
fn warp_row_from(pixels: &[f32], h: usize, y: usize, flow: &[f32], row: &mut [f32], x0: usize) {
    let w = row.len();
    for (x, (out, d)) in row
        .iter_mut()
        .zip(flow.chunks_exact(2))
        .enumerate()
        .skip(x0)
    {
        let (y0, y1, fy) = bilinear_taps(y as f32 + d[0], h);
        let (x0, x1, fx) = bilinear_taps(x as f32 + d[1], w);
        let (top, bottom) = (&pixels[y0 * w..(y0 + 1) * w], &pixels[y1 * w..(y1 + 1) * w]);
        let top = top[x0] * (1.0 - fx) + top[x1] * fx;
        let bottom = bottom[x0] * (1.0 - fx) + bottom[x1] * fx;
        *out = top * (1.0 - fy) + bottom * fy;
    }
}

/// [`warp_row_from`] eight pixels at a time with AVX2 gathers, over the leading multiple of
/// eight columns; returns how many columns it made. The same operations per pixel (the clamp
/// of [`bilinear_taps`] as min then max, truncation, no fused multiply-add), so the same bits.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn warp_row_avx2(
    pixels: &[f32],
    h: usize,
    y: usize,
    flow: &[f32],
    row: &mut [f32],
) -> usize {
    use std::arch::x86_64::*;
    let w = row.len();
    // Gather offsets are i32: larger images take the scalar path.
    if pixels.len() != h * w || pixels.len() > i32::MAX as usize || flow.len() < 2 * w {
        return 0;
    }
    let lanes = w / 8 * 8;
    let zero = _mm256_setzero_ps();
    let one = _mm256_set1_ps(1.0);
    let y_max = _mm256_set1_ps((h - 1) as f32);
    let x_max = _mm256_set1_ps((w - 1) as f32);
    let y_last = _mm256_set1_epi32((h - 1) as i32);
    let x_last = _mm256_set1_epi32((w - 1) as i32);
    let ones_i = _mm256_set1_epi32(1);
    let width = _mm256_set1_epi32(w as i32);
    let yf = _mm256_set1_ps(y as f32);
    let steps = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    // (value clamped to [0, max], its truncation, the truncation + 1 clamped to `last`, the
    // fraction): `bilinear_taps` lane-wise. `f32::clamp` keeps −0.0 and takes max − min in
    // this order: min(max, v) then max(0, ·) with 0 second keep v where they compare equal.
    let taps = |v: __m256, max: __m256, last: __m256i| {
        let v = _mm256_max_ps(zero, _mm256_min_ps(max, v));
        let v0 = _mm256_cvttps_epi32(v);
        let v1 = _mm256_min_epi32(_mm256_add_epi32(v0, ones_i), last);
        (v0, v1, _mm256_sub_ps(v, _mm256_cvtepi32_ps(v0)))
    };
    let base = pixels.as_ptr();
    for x in (0..lanes).step_by(8) {
        // 16 interleaved (dy, dx) values: deinterleave into eight dy and eight dx in x order.
        let a = _mm256_loadu_ps(flow.as_ptr().add(2 * x));
        let b = _mm256_loadu_ps(flow.as_ptr().add(2 * x + 8));
        let order = |v: __m256| {
            _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(v)))
        };
        let dy = order(_mm256_shuffle_ps::<0b10_00_10_00>(a, b));
        let dx = order(_mm256_shuffle_ps::<0b11_01_11_01>(a, b));
        let xs = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(x as i32), steps));
        let (y0, y1, fy) = taps(_mm256_add_ps(yf, dy), y_max, y_last);
        let (x0, x1, fx) = taps(_mm256_add_ps(xs, dx), x_max, x_last);
        let (r0, r1) = (_mm256_mullo_epi32(y0, width), _mm256_mullo_epi32(y1, width));
        let at = |i: __m256i| _mm256_i32gather_ps::<4>(base, i);
        let (p00, p01) = (at(_mm256_add_epi32(r0, x0)), at(_mm256_add_epi32(r0, x1)));
        let (p10, p11) = (at(_mm256_add_epi32(r1, x0)), at(_mm256_add_epi32(r1, x1)));
        let gx = _mm256_sub_ps(one, fx);
        let top = _mm256_add_ps(_mm256_mul_ps(p00, gx), _mm256_mul_ps(p01, fx));
        let bottom = _mm256_add_ps(_mm256_mul_ps(p10, gx), _mm256_mul_ps(p11, fx));
        let gy = _mm256_sub_ps(one, fy);
        let out = _mm256_add_ps(_mm256_mul_ps(top, gy), _mm256_mul_ps(bottom, fy));
        _mm256_storeu_ps(row.as_mut_ptr().add(x), out);
    }
    lanes
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
    let isa = Isa::current();
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
                warp_row(isa, pixels, h, y, flow, row);
                Ok(())
            },
        )?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filters::bilinear;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Every row (eight-lane and one-pixel paths together) equals [`bilinear`] at p + flow(p)
    /// bit for bit, with flows that reach past every edge and land on whole pixels, −0.0
    /// included; widths with and without a one-pixel tail.
    #[test]
    fn warp_equals_bilinear_sampling_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        for (h, w) in [(11, 37), (5, 8), (1, 17), (9, 1), (3, 3)] {
            let block = Array2::from_shape_fn((h, w), |_| rng.gen_range(0.0f32..1.0));
            let flow = Array3::from_shape_fn((h, w, 2), |(y, x, c)| match (y + 2 * x + c) % 4 {
                0 => rng.gen_range(-30.0f32..30.0),
                1 => rng.gen_range(-2i32..3) as f32,
                2 => -((if c == 0 { y } else { x }) as f32),
                _ => -0.0,
            });
            // The portable rows and, where the CPU has them, the AVX2 ones.
            for isa in [Isa::generic(), Isa::current()] {
                let warped = warp_checked_on(isa, &block, &flow).unwrap();
                for ((y, x), &v) in warped.indexed_iter() {
                    let expected = bilinear(
                        block.view(),
                        y as f32 + flow[[y, x, 0]],
                        x as f32 + flow[[y, x, 1]],
                    );
                    let at = format!("{h}x{w} at ({y}, {x}), {}", isa.name());
                    assert_eq!(v.to_bits(), expected.to_bits(), "{at}");
                }
            }
        }
    }

    /// The relative flow of two affine flows is their composition K ∘ B⁻¹ (computed in f64)
    /// wherever B⁻¹ stays inside the image; a flow relative to itself is zero; mismatched
    /// shapes are an error.
    #[test]
    fn relative_flow_composes_one_flow_with_the_other_inverted() {
        let (h, w) = (40usize, 64usize);
        // Reference → image: p ↦ A·(p − c) + c + t.
        let c = [(h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0];
        let maps = [
            ([[1.02, 0.03], [-0.03, 1.02]], [1.5, -2.25]),
            ([[0.99, -0.02], [0.02, 0.99]], [-0.75, 3.1]),
        ];
        let apply = |(a, t): ([[f64; 2]; 2], [f64; 2]), p: [f64; 2]| {
            let r = [p[0] - c[0], p[1] - c[1]];
            [
                a[0][0] * r[0] + a[0][1] * r[1] + c[0] + t[0],
                a[1][0] * r[0] + a[1][1] * r[1] + c[1] + t[1],
            ]
        };
        let invert = |(a, t): ([[f64; 2]; 2], [f64; 2]), q: [f64; 2]| {
            let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
            let r = [q[0] - c[0] - t[0], q[1] - c[1] - t[1]];
            [
                (a[1][1] * r[0] - a[0][1] * r[1]) / det + c[0],
                (-a[1][0] * r[0] + a[0][0] * r[1]) / det + c[1],
            ]
        };
        let flow = |m| {
            Array3::from_shape_fn((h, w, 2), |(y, x, k)| {
                let p = apply(m, [y as f64, x as f64]);
                (p[k] - if k == 0 { y as f64 } else { x as f64 }) as f32
            })
        };
        let (from, to) = (flow(maps[0]), flow(maps[1]));
        let relative = relative_flow(&from, &to).unwrap();
        let mut checked = 0;
        for y in 0..h {
            for x in 0..w {
                let p = invert(maps[0], [y as f64, x as f64]);
                if !(p[0] >= 0.0 && p[1] >= 0.0 && p[0] <= (h - 1) as f64 && p[1] <= (w - 1) as f64)
                {
                    continue;
                }
                let expected = apply(maps[1], p);
                for k in 0..2 {
                    let q = if k == 0 { y } else { x } as f64;
                    let got = q + f64::from(relative[[y, x, k]]);
                    assert!(
                        (got - expected[k]).abs() < 1e-3,
                        "({y}, {x}) axis {k}: {got} against {}",
                        expected[k]
                    );
                }
                checked += 1;
            }
        }
        assert!(checked > h * w / 2, "{checked} pixels checked");
        let itself = relative_flow(&from, &from).unwrap();
        assert!(itself.iter().all(|v| v.abs() < 1e-3));
        assert!(relative_flow(&from, &Array3::zeros((h, w + 1, 2))).is_err());
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
