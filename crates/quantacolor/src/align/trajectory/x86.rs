//! The AVX2 kernels of the trajectory fit, eight sites at a time: the template's splats (the
//! portable reference is [`Splats::add_row`]) and the score's row sums (reference
//! [`super::likelihood::row_sums_scalar`]). Their safe entry points take an [`Isa`].

use super::likelihood::{
    row_sums_avx2_fits, InformativeBlocks, RowSampling, RowSums, TemplatePlanes, BLOCK, P_MIN,
};
use super::sites::{chunk_bits, RowMap};
use super::template::{splat_at, Splats};
use crate::align::refine::{inside_avx2, TemplateLevel};
use crate::cpu::Isa;
use std::arch::x86_64::*;

/// [`Splats::add_row`] eight columns at a time ([`splat_row_avx2`]; `masks`: the row's
/// [`super::sites::Sites::masks`]).
///
/// # Panics
/// If `isa` lacks AVX2 or FMA, or the images' flat indices do not fit an i32.
pub(super) fn splat_row(
    isa: Isa,
    splats: &mut Splats,
    row: &[u8],
    y: usize,
    masks: &[u8],
    map: &RowMap,
) {
    let (h, w) = splats.sum.dim();
    assert!(
        isa.avx2_fma() && h * w < i32::MAX as usize,
        "the AVX2 splats need AVX2, FMA and i32 indices"
    );
    let sum = splats.sum.as_slice_mut().expect("standard layout");
    let exposure = splats.exposure.as_slice_mut().expect("standard layout");
    // SAFETY: an `Isa` never holds a feature the CPU lacks, so the CPU has AVX2 and FMA; the
    // flat indices fit an i32 (both asserted above).
    unsafe { splat_row_avx2(exposure, sum, (h, w), row, y, masks, map) };
}

/// One row's [`RowSums`] eight columns at a time ([`row_sums_avx2`]); `sampling.planes`, when
/// given, must be `level`'s ([`TemplatePlanes::new`]); with `sampling.blocks`, only the groups
/// they keep are summed.
///
/// # Panics
/// If `isa` lacks AVX2 or FMA, the template's float indices do not fit an i32, or `planes`
/// are not of `level`'s size.
pub(super) fn row_sums(
    isa: Isa,
    level: &TemplateLevel,
    sampling: &RowSampling<'_>,
    row: &[u8],
    y: usize,
    masks: &[u8],
    map: &RowMap,
) -> RowSums {
    let (h, w) = level.dims();
    let planes = sampling.planes;
    let planes_fit =
        planes.is_none_or(|p| p.width == w && p.planes.iter().all(|q| q.len() == h * w));
    assert!(
        isa.avx2_fma() && row_sums_avx2_fits(level) && planes_fit,
        "the AVX2 row sums need AVX2, FMA, i32 indices and the level's planes"
    );
    // SAFETY: an `Isa` never holds a feature the CPU lacks, so the CPU has AVX2 and FMA; the
    // float indices fit an i32 and the planes are the level's size (asserted above).
    unsafe { row_sums_avx2(level, sampling, row, y, masks, map) }
}

/// The pending ninth pixels of [`splat_row_avx2`]'s last row run: (index of the top one,
/// exposure top/bottom, sum top/bottom).
type Carry = Option<(usize, [f32; 4])>;

/// The two images [`splat_row_avx2`] adds to, `w` pixels wide.
struct SplatImages<'a> {
    exposure: &'a mut [f32],
    sum: &'a mut [f32],
    w: usize,
}

/// [`Splats::add_row`] eight columns at a time (`masks`: the row's
/// [`super::sites::Sites::masks`]).
///
/// Under small rotation and zoom, eight neighbouring columns land in one pair of template rows
/// at eight consecutive columns. Their bilinear splats then cover nine consecutive pixels of
/// each row: pixel l takes the left weight of site l and the right weight of site l − 1, so
/// each row is one vector addition; the ninth pixel's weight is carried into the next group
/// when that starts there (as it does along a row), else added alone. Other groups are
/// splatted site by site.
///
/// # Safety
/// The CPU must support AVX2 and FMA, and `h · w` must fit an i32.
#[target_feature(enable = "avx2,fma")]
unsafe fn splat_row_avx2(
    exposure: &mut [f32],
    sum: &mut [f32],
    (h, w): (usize, usize),
    row: &[u8],
    y: usize,
    masks: &[u8],
    map: &RowMap,
) {
    assert!(exposure.len() >= h * w && sum.len() >= h * w);
    let mut images = SplatImages { exposure, sum, w };
    let mut carry: Carry = None;
    for (k, &mask) in masks.iter().enumerate() {
        if mask == 0 {
            continue;
        }
        let detected = u32::from(mask) & chunk_bits(row, k, map.packed);
        let group = group_splat(y, k, map, (h, w));
        if group.inside_bits == 0xFF && group.consecutive {
            splat_run(&mut images, &group, mask, detected, &mut carry);
            continue;
        }
        splat_sites(&mut images, &group, mask, detected);
    }
    flush(&mut carry, &mut images);
}

/// Where the eight sites of one group of [`splat_row_avx2`] land, and their bilinear weights.
struct GroupSplat {
    /// Bit l set where lane l lies inside the images' interior.
    inside_bits: u32,
    /// Each lane's top-left pixel (0 for lanes outside).
    y0: __m256i,
    x0: __m256i,
    /// Lane 0's top-left pixel in every lane.
    first_y: __m256i,
    first_x: __m256i,
    /// Whether the top-left pixels are eight consecutive pixels of one row.
    consecutive: bool,
    /// The weights of the top-left, top-right, bottom-left and bottom-right pixels.
    weights: [__m256; 4],
}

/// The [`GroupSplat`] of columns 8k..8k + 8 of row `y` under `map`, in images of `h` × `w`.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn group_splat(y: usize, k: usize, map: &RowMap, (h, w): (usize, usize)) -> GroupSplat {
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let one = _mm256_set1_ps(1.0);
    let (y_end, x_end) = (
        _mm256_set1_ps((h - 1) as f32),
        _mm256_set1_ps((w - 1) as f32),
    );
    let x = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(8 * k as i32), lane));
    let (_, py, px) = positions_avx2(y, x, map);
    let inside = inside_avx2::<_CMP_LT_OQ>(py, px, y_end, x_end);
    let inside_bits = _mm256_movemask_ps(inside) as u32;
    // Lanes outside take position 0 (in bounds); their weights are not used.
    let (py, px) = (_mm256_and_ps(py, inside), _mm256_and_ps(px, inside));
    let (y0, x0) = (_mm256_cvttps_epi32(py), _mm256_cvttps_epi32(px));
    let fy = _mm256_sub_ps(py, _mm256_cvtepi32_ps(y0));
    let fx = _mm256_sub_ps(px, _mm256_cvtepi32_ps(x0));
    let (gy, gx) = (_mm256_sub_ps(one, fy), _mm256_sub_ps(one, fx));
    let weights = [
        _mm256_mul_ps(gy, gx),
        _mm256_mul_ps(gy, fx),
        _mm256_mul_ps(fy, gx),
        _mm256_mul_ps(fy, fx),
    ];
    let first_y = _mm256_permutevar8x32_epi32(y0, _mm256_setzero_si256());
    let first_x = _mm256_permutevar8x32_epi32(x0, _mm256_setzero_si256());
    let consecutive = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_and_si256(
        _mm256_cmpeq_epi32(y0, first_y),
        _mm256_cmpeq_epi32(x0, _mm256_add_epi32(first_x, lane)),
    ))) == 0xFF;
    GroupSplat {
        inside_bits,
        y0,
        x0,
        first_y,
        first_x,
        consecutive,
        weights,
    }
}

/// Splats a group whose eight lanes lie inside at consecutive pixels of one row as two
/// nine-pixel runs per image, taking up `carry` where it lies at the runs' start (else adding
/// it alone) and leaving the runs' ninth pixels in it.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn splat_run(
    images: &mut SplatImages<'_>,
    group: &GroupSplat,
    mask: u8,
    detected: u32,
    carry: &mut Carry,
) {
    let w = images.w;
    // All eight lanes inside: the last one's top-left pixel is at most (h − 2, w − 2),
    // so both nine-pixel runs lie inside the images.
    let i = (_mm256_cvtsi256_si32(group.first_y) as usize) * w
        + _mm256_cvtsi256_si32(group.first_x) as usize;
    let mut pending = [0.0f32; 4];
    match *carry {
        // Taken up here; `carry` is replaced below.
        Some((at, values)) if at == i => pending = values,
        _ => flush(carry, images),
    }
    let sites = lane_mask_avx2(u32::from(mask));
    let [a, b, c, d] = group.weights.map(|v| _mm256_and_ps(v, sites));
    let mut next = [
        add_run(images.exposure, i, a, b, pending[0]),
        add_run(images.exposure, i + w, c, d, pending[1]),
        0.0,
        0.0,
    ];
    if detected != 0 {
        let photons = lane_mask_avx2(detected);
        let [a, b, c, d] = group.weights.map(|v| _mm256_and_ps(v, photons));
        next[2] = add_run(images.sum, i, a, b, pending[2]);
        next[3] = add_run(images.sum, i + w, c, d, pending[3]);
    } else {
        images.sum[i] += pending[2];
        images.sum[i + w] += pending[3];
    }
    *carry = Some((i + 8, next));
}

/// Adds the nine-pixel splat (left weights `a`, right weights `b`) of one row at `i`, with
/// `carry` (the previous group's ninth pixel) added to the first; returns the ninth.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn add_run(image: &mut [f32], i: usize, a: __m256, b: __m256, carry: f32) -> f32 {
    let previous = _mm256_setr_epi32(7, 0, 1, 2, 3, 4, 5, 6);
    let rotated = _mm256_permutevar8x32_ps(b, previous);
    let shifted = _mm256_blend_ps::<1>(rotated, _mm256_set1_ps(carry));
    let at = image[i..i + 8].as_mut_ptr();
    _mm256_storeu_ps(
        at,
        _mm256_add_ps(_mm256_loadu_ps(at), _mm256_add_ps(a, shifted)),
    );
    _mm256_cvtss_f32(rotated)
}

/// Adds the pending ninth pixels of `carry`, if any, to the images, and empties it.
#[inline]
fn flush(carry: &mut Carry, images: &mut SplatImages<'_>) {
    if let Some((i, [e_top, e_bottom, s_top, s_bottom])) = carry.take() {
        images.exposure[i] += e_top;
        images.exposure[i + images.w] += e_bottom;
        images.sum[i] += s_top;
        images.sum[i + images.w] += s_bottom;
    }
}

/// Splats the sites of a group (those of `mask` that lie inside) one by one.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn splat_sites(images: &mut SplatImages<'_>, group: &GroupSplat, mask: u8, detected: u32) {
    let w = images.w;
    let mut index = [0i32; 8];
    _mm256_storeu_si256(
        index.as_mut_ptr().cast(),
        _mm256_add_epi32(
            _mm256_mullo_epi32(group.y0, _mm256_set1_epi32(w as i32)),
            group.x0,
        ),
    );
    let mut lanes = [[0.0f32; 8]; 4];
    for (out, v) in lanes.iter_mut().zip(group.weights) {
        _mm256_storeu_ps(out.as_mut_ptr(), v);
    }
    let mut todo = group.inside_bits & u32::from(mask);
    while todo != 0 {
        let l = todo.trailing_zeros() as usize;
        todo &= todo - 1;
        let site_weights = lanes.map(|v| v[l]);
        let photon = detected >> l & 1 == 1;
        splat_at(
            images.exposure,
            images.sum,
            w,
            index[l] as usize,
            site_weights,
            photon,
        );
    }
}

/// All ones in lane l where bit l of `bits` is set, zeros elsewhere.
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn lane_mask_avx2(bits: u32) -> __m256 {
    let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
    _mm256_castsi256_ps(_mm256_cmpeq_epi32(
        _mm256_and_si256(_mm256_set1_epi32(bits as i32), lane_bits),
        lane_bits,
    ))
}

/// For eight sites in columns `x` of row `y` under `map`: r_x (the column about the centre)
/// and the template positions y and x.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn positions_avx2(y: usize, x: __m256, map: &RowMap) -> (__m256, __m256, __m256) {
    let splat = |v: f64| _mm256_set1_ps(v as f32);
    let rx = _mm256_sub_ps(x, splat(map.centre_x));
    let py = _mm256_fmadd_ps(
        splat(map.m_yx),
        rx,
        splat(y as f64 + map.base[0] + map.margin),
    );
    let px = _mm256_add_ps(
        _mm256_fmadd_ps(splat(map.m_xx), rx, splat(map.base[1] + map.margin)),
        x,
    );
    (rx, py, px)
}

/// One row's [`RowSums`], eight columns at a time (`masks`: the row's
/// [`super::sites::Sites::masks`]) in f32 (the template is f32 already; positions in f32 are
/// within 4e-5 px below 1000 px), summed per row in f64.
///
/// `planes`, when given, must be `level`'s ([`TemplatePlanes::new`]): groups of sites that
/// form a row run then sample them instead of `level` (the same floats, so the same sums).
///
/// # Safety
/// The CPU must support AVX2 and FMA, and the template's float indices must fit an i32
/// ([`row_sums_avx2_fits`]).
#[target_feature(enable = "avx2,fma")]
unsafe fn row_sums_avx2(
    level: &TemplateLevel,
    sampling: &RowSampling<'_>,
    row: &[u8],
    y: usize,
    masks: &[u8],
    map: &RowMap,
) -> RowSums {
    let (planes, blocks) = (sampling.planes, sampling.blocks);
    // Bit l: whether group 8·⌊k/8⌋ + l is scored (all without blocks).
    let mut kept = 0xFFu32;
    let mut summed = false;
    let w = level.dims().1;
    let one = _mm256_set1_ps(1.0);
    // Accumulators: score (y, 1), (y, r_x), (x, 1), (x, r_x); weight (yy, yx, xx) × (1, r_x, r_x²).
    let mut acc = [_mm256_setzero_ps(); 13];
    for (k, &mask) in masks.iter().enumerate() {
        if let Some(blocks) = blocks {
            if k % 8 == 0 {
                kept = kept_groups8(blocks, y, k, map);
            }
        }
        if mask == 0 || kept >> (k % 8) & 1 == 0 {
            continue;
        }
        let bit = _mm256_and_ps(lane_mask_avx2(chunk_bits(row, k, map.packed)), one);
        let points = sample_points(level, y, k, mask, map);
        let run_start = if points.all_in_template && planes.is_some() {
            row_run_start(points.y0, points.x0, w)
        } else {
            None
        };
        let samples = if let (Some(planes), Some(start)) = (planes, run_start) {
            sample_row_run(planes, start, &points)
        } else {
            sample_transposed(level, &points)
        };
        accumulate(&mut acc, samples, bit, &points);
        summed = true;
    }
    // A row whose groups were all skipped sums to zero, as `row_sums_of` would make it.
    if summed {
        row_sums_of(&acc)
    } else {
        RowSums::default()
    }
}

/// Which of the groups k..k + 8 of row `y` [`InformativeBlocks::keeps_group`] keeps, bit l
/// for group k + l, eight groups at a time: the positions of each group's columns 8(k + l) and
/// 8(k + l) + 7 are [`positions_avx2`]'s lanes, the same bits as
/// [`super::likelihood::group_end_positions`].
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
pub(super) unsafe fn kept_groups8(
    blocks: &InformativeBlocks,
    y: usize,
    k: usize,
    map: &RowMap,
) -> u32 {
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let groups = _mm256_add_epi32(_mm256_set1_epi32(k as i32), lane);
    let first = _mm256_cvtepi32_ps(_mm256_slli_epi32::<3>(groups));
    let last = _mm256_add_ps(first, _mm256_set1_ps(7.0));
    let (_, py0, px0) = positions_avx2(y, first, map);
    let (_, py7, px7) = positions_avx2(y, last, map);
    kept_lanes(blocks, py0, px0) | kept_lanes(blocks, py7, px7)
}

/// Bit l set where template position (`py`, `px`) lane l lies in a kept block of `blocks`.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn kept_lanes(blocks: &InformativeBlocks, py: __m256, px: __m256) -> u32 {
    let (height, width) = blocks.limits();
    let zero = _mm256_setzero_ps();
    let inside = _mm256_and_ps(
        _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_GE_OQ>(py, zero),
            _mm256_cmp_ps::<_CMP_GE_OQ>(px, zero),
        ),
        _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_LT_OQ>(py, _mm256_set1_ps(height)),
            _mm256_cmp_ps::<_CMP_LT_OQ>(px, _mm256_set1_ps(width)),
        ),
    );
    // Lanes outside read block 0; truncation is the floor inside (non-negative positions).
    let (py, px) = (_mm256_and_ps(py, inside), _mm256_and_ps(px, inside));
    let shift = BLOCK.trailing_zeros() as i32;
    let by = _mm256_srl_epi32(_mm256_cvttps_epi32(py), _mm_cvtsi32_si128(shift));
    let bx = _mm256_srl_epi32(_mm256_cvttps_epi32(px), _mm_cvtsi32_si128(shift));
    let index = _mm256_add_epi32(
        _mm256_mullo_epi32(by, _mm256_set1_epi32(blocks.width as i32)),
        bx,
    );
    let kept = _mm256_i32gather_epi32::<4>(blocks.kept.as_ptr(), index);
    _mm256_movemask_ps(_mm256_and_ps(_mm256_castsi256_ps(kept), inside)) as u32
}

/// Where the eight sites of one group of [`row_sums_avx2`] sample the template.
#[derive(Clone, Copy)]
struct SamplePoints {
    /// The sites' columns about the centre.
    rx: __m256,
    /// All ones in the lanes that hold a site inside the template.
    inside: __m256,
    /// Whether every lane (site or not) lies inside the template.
    all_in_template: bool,
    /// Each lane's top-left pixel, at most (h − 2, w − 2).
    y0: __m256i,
    x0: __m256i,
    /// The bilinear fractions (f) and their complements (g = 1 − f).
    fy: __m256,
    fx: __m256,
    gy: __m256,
    gx: __m256,
}

/// The [`SamplePoints`] of columns 8k..8k + 8 of row `y` (sites where `mask` is set) under
/// `map`.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn sample_points(
    level: &TemplateLevel,
    y: usize,
    k: usize,
    mask: u8,
    map: &RowMap,
) -> SamplePoints {
    let (h, w) = level.dims();
    let splat = |v: f64| _mm256_set1_ps(v as f32);
    let one = _mm256_set1_ps(1.0);
    let (y_last, x_last) = (splat((h - 1) as f64), splat((w - 1) as f64));
    let (y0_last, x0_last) = (
        _mm256_set1_epi32(h as i32 - 2),
        _mm256_set1_epi32(w as i32 - 2),
    );
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let valid = lane_mask_avx2(u32::from(mask));
    let x = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(8 * k as i32), lane));
    let (rx, py, px) = positions_avx2(y, x, map);
    // Lanes inside the template (and holding a site), as in `sample_template`.
    let in_template = inside_avx2::<_CMP_LE_OQ>(py, px, y_last, x_last);
    let inside = _mm256_and_ps(in_template, valid);
    // Positions of lanes outside are replaced by 0 so that their loads stay in bounds.
    // When every lane is inside, a lane without a site keeps its position (in bounds too):
    // its weight is zero all the same, and a zero weight times a finite sample adds ±0,
    // which leaves every sum as it is.
    let all_in_template = _mm256_movemask_ps(in_template) == 0xFF;
    let (py, px) = if all_in_template {
        (py, px)
    } else {
        (_mm256_and_ps(py, inside), _mm256_and_ps(px, inside))
    };
    let y0 = _mm256_min_epi32(_mm256_cvttps_epi32(py), y0_last);
    let x0 = _mm256_min_epi32(_mm256_cvttps_epi32(px), x0_last);
    let fy = _mm256_sub_ps(py, _mm256_cvtepi32_ps(y0));
    let fx = _mm256_sub_ps(px, _mm256_cvtepi32_ps(x0));
    let (gx, gy) = (_mm256_sub_ps(one, fx), _mm256_sub_ps(one, fy));
    SamplePoints {
        rx,
        inside,
        all_in_template,
        y0,
        x0,
        fy,
        fx,
        gy,
        gx,
    }
}

/// Float k (value, ∂/∂y, ∂/∂x) of the bilinear interpolation at `points`, as `bilinear4`,
/// from each lane's top-left, top-right, bottom-left and bottom-right pixels' float k.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn bilinear(
    points: &SamplePoints,
    tl: __m256,
    tr: __m256,
    bl: __m256,
    br: __m256,
) -> __m256 {
    let SamplePoints { fy, fx, gy, gx, .. } = *points;
    let t = _mm256_fmadd_ps(tl, gx, _mm256_mul_ps(tr, fx));
    let b = _mm256_fmadd_ps(bl, gx, _mm256_mul_ps(br, fx));
    _mm256_fmadd_ps(t, gy, _mm256_mul_ps(b, fy))
}

/// The value, ∂/∂y and ∂/∂x at `points` when they form a row run (the lanes' top-left pixels
/// are eight consecutive pixels of one row from flat index `start`, as under small rotation and
/// zoom): each corner of every lane is one load from each plane, the same floats as the
/// transposed loads of [`sample_transposed`].
///
/// # Safety
/// The CPU must support AVX2 and FMA; lane 7's top-left pixel must be at most (h − 2, w − 2)
/// of `planes`, so that the nine pixels of both rows lie inside.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn sample_row_run(
    planes: &TemplatePlanes,
    start: usize,
    points: &SamplePoints,
) -> [__m256; 3] {
    let sample = |k: usize| {
        let p = planes.planes[k].as_ptr().add(start);
        let below = p.add(planes.width);
        bilinear(
            points,
            _mm256_loadu_ps(p),
            _mm256_loadu_ps(p.add(1)),
            _mm256_loadu_ps(below),
            _mm256_loadu_ps(below.add(1)),
        )
    };
    [sample(0), sample(1), sample(2)]
}

/// The value, ∂/∂y and ∂/∂x at `points` from `level`'s interleaved samples: each lane's two
/// top pixels (8 floats) and two bottom pixels, transposed so that vector k holds float k of
/// every lane: (value, ∂/∂y, ∂/∂x, 0) left, then right (eight loads and a transpose were faster
/// than twelve gathers).
///
/// # Safety
/// The CPU must support AVX2 and FMA; the template's float indices must fit an i32.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn sample_transposed(level: &TemplateLevel, points: &SamplePoints) -> [__m256; 3] {
    let w = level.dims().1;
    let samples = level.floats().as_ptr();
    let row_floats = _mm256_set1_epi32(4 * w as i32);
    // A lane's top-left pixel is at most (h − 2, w − 2), so both pairs lie inside the
    // template.
    let mut top_left = [0i32; 8];
    _mm256_storeu_si256(
        top_left.as_mut_ptr().cast(),
        _mm256_add_epi32(
            _mm256_mullo_epi32(points.y0, row_floats),
            _mm256_slli_epi32::<2>(points.x0),
        ),
    );
    let pairs = |offset: usize| {
        let rows: [__m256i; 8] = std::array::from_fn(|l| {
            _mm256_castps_si256(_mm256_loadu_ps(samples.add(top_left[l] as usize + offset)))
        });
        crate::cpu::transpose8x8(&rows).map(|r| _mm256_castsi256_ps(r))
    };
    let (top, bottom) = (pairs(0), pairs(4 * w));
    let sample = |k: usize| bilinear(points, top[k], top[4 + k], bottom[k], bottom[4 + k]);
    [sample(0), sample(1), sample(2)]
}

/// Adds one group's terms to the 13 accumulators of [`row_sums_avx2`]: from the template's
/// value and gradients at the sites (`samples`) and their detections (`bit`, 1 or 0 per lane).
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn accumulate(
    acc: &mut [__m256; 13],
    [v, grad_y, grad_x]: [__m256; 3],
    bit: __m256,
    points: &SamplePoints,
) {
    let splat = |v: f64| _mm256_set1_ps(v as f32);
    let one = _mm256_set1_ps(1.0);
    let (p_min, p_max) = (splat(P_MIN), splat(1.0 - P_MIN));
    let (rx, inside) = (points.rx, points.inside);
    let p = _mm256_min_ps(_mm256_max_ps(v, p_min), p_max);
    let q = _mm256_sub_ps(one, p);
    // w = 1 / (p (1 − p)); s = 1/p = q·w for a detection, −1/(1 − p) = −p·w otherwise.
    let weight = _mm256_and_ps(_mm256_div_ps(one, _mm256_mul_ps(p, q)), inside);
    let s = _mm256_mul_ps(
        weight,
        _mm256_sub_ps(
            _mm256_mul_ps(bit, q),
            _mm256_mul_ps(_mm256_sub_ps(one, bit), p),
        ),
    );
    let (sy, sx) = (_mm256_mul_ps(s, grad_y), _mm256_mul_ps(s, grad_x));
    acc[0] = _mm256_add_ps(acc[0], sy);
    acc[1] = _mm256_fmadd_ps(sy, rx, acc[1]);
    acc[2] = _mm256_add_ps(acc[2], sx);
    acc[3] = _mm256_fmadd_ps(sx, rx, acc[3]);
    let rx2 = _mm256_mul_ps(rx, rx);
    let wy = _mm256_mul_ps(weight, grad_y);
    for (k, wk) in [
        _mm256_mul_ps(wy, grad_y),
        _mm256_mul_ps(wy, grad_x),
        _mm256_mul_ps(_mm256_mul_ps(weight, grad_x), grad_x),
    ]
    .into_iter()
    .enumerate()
    {
        acc[4 + 3 * k] = _mm256_add_ps(acc[4 + 3 * k], wk);
        acc[5 + 3 * k] = _mm256_fmadd_ps(wk, rx, acc[5 + 3 * k]);
        acc[6 + 3 * k] = _mm256_fmadd_ps(wk, rx2, acc[6 + 3 * k]);
    }
}

/// The [`RowSums`] of [`row_sums_avx2`]'s accumulators: each one's lanes summed in f64.
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn row_sums_of(acc: &[__m256; 13]) -> RowSums {
    let total = acc.map(|a| {
        let mut lanes = [0.0f32; 8];
        _mm256_storeu_ps(lanes.as_mut_ptr(), a);
        lanes.iter().map(|&l| l as f64).sum::<f64>()
    });
    RowSums {
        score: [[total[0], total[1]], [total[2], total[3]]],
        weight: std::array::from_fn(|k| std::array::from_fn(|j| total[4 + 3 * k + j])),
    }
}

/// The flat index `y0 · width + x0` of lane 0's pixel when the eight lanes' pixels `(y0, x0)`
/// are consecutive pixels of one row (lane l at `(y0[0], x0[0] + l)`), else `None`.
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn row_run_start(y0: __m256i, x0: __m256i, width: usize) -> Option<usize> {
    let first_y = _mm256_broadcastd_epi32(_mm256_castsi256_si128(y0));
    let first_x = _mm256_broadcastd_epi32(_mm256_castsi256_si128(x0));
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let same = _mm256_and_si256(
        _mm256_cmpeq_epi32(y0, first_y),
        _mm256_cmpeq_epi32(x0, _mm256_add_epi32(first_x, lane)),
    );
    if _mm256_movemask_epi8(same) != -1 {
        return None;
    }
    let (y, x) = (_mm256_cvtsi256_si32(first_y), _mm256_cvtsi256_si32(first_x));
    (y >= 0 && x >= 0).then(|| y as usize * width + x as usize)
}
