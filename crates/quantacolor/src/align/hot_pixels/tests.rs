//! Tests of hot-pixel correction: the ChaCha8 blocks against rand_chacha, the grouped draws
//! (AVX2 and portable) against a per-pixel loop.

#![forbid(unsafe_code)]

use super::chacha::{chacha8_block, chacha8_blocks};
use super::*;
use crate::capture::frames::pack_bits;
use crate::cfa::colorspad_cfa;
use ndarray::Array3;
use rand::Rng;

/// The ChaCha8 blocks of `chacha8_blocks` (eight-lane and scalar paths) are the words of
/// rand_chacha's `ChaCha8Rng` for the same seed, stream and position, for streams and block
/// counters that use their high words too.
#[test]
fn chacha8_blocks_equal_the_generator_words() {
    let cfa = colorspad_cfa();
    let mask = Array2::from_elem((cfa.height(), cfa.width()), false);
    let corrector = HotPixelCorrector::new(&cfa, &mask, 8, 77).unwrap();
    let jobs: Vec<(u64, u64)> = (0..21u64)
        .map(|i| {
            let stream = i.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> ((i % 3) * 20);
            (stream, i * 7 + ((i % 4) << 33))
        })
        .collect();
    for isa in [Isa::generic(), Isa::current()] {
        let mut got = vec![[0u32; BLOCK_WORDS]; jobs.len()];
        chacha8_blocks(&corrector.key, &jobs, &mut got, isa);
        for (&(stream, block), got) in jobs.iter().zip(&got) {
            let mut rng = ChaCha8Rng::seed_from_u64(77);
            rng.set_stream(stream);
            rng.set_word_pos(block as u128 * BLOCK_WORDS as u128);
            let expected: [u32; BLOCK_WORDS] = std::array::from_fn(|_| rng.next_u32());
            assert_eq!(*got, expected, "{isa:?}: stream {stream} block {block}");
            assert_eq!(chacha8_block(&corrector.key, stream, block), expected);
        }
    }
}

/// The grouped, frame-by-frame draws of `corrected_block_sum` are the per-pixel draws of
/// supplement §1.4 as a plain loop makes them (more hot pixels than one group holds, a
/// last group of fewer than eight times a whole number, chunks of frames not multiples of
/// eight): eight candidates and five (the AVX2 paths of `HotSites`, five not a power of
/// two) and twelve (the scalar path).
#[test]
fn grouped_correction_matches_per_pixel_draws() {
    for k in [8, 5, 12] {
        grouped_correction_matches_per_pixel_draws_with(k);
    }
}

fn grouped_correction_matches_per_pixel_draws_with(k: usize) {
    let cfa = colorspad_cfa();
    let (h, w) = (cfa.height(), cfa.width());
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut mask = Array2::from_shape_fn((h, w), |_| rng.gen_bool(0.02));
    if mask.iter().filter(|&&m| m).count() % 8 == 0 {
        mask[[h / 2, w / 2]] ^= true;
    }
    let t = 157;
    let bits = Array3::from_shape_fn((t, h, w), |_| rng.gen_bool(0.3) as u8);
    let frames = BinaryFrames::from_packed(pack_bits(&bits), w).unwrap();
    let corrector = HotPixelCorrector::new(&cfa, &mask, k, 9).unwrap();
    assert!(corrector.hot_count() > 3 * HOT_GROUP);
    assert_ne!(corrector.hot_count() % 8, 0, "a padded last group");
    #[cfg(target_arch = "x86_64")]
    if Isa::current().avx2() {
        // The vector path takes groups of up to eight candidates a pixel, not more.
        let spans = [(0, k.min(corrector.candidates[0].len()) as u64)];
        let sites: Vec<u32> = (0..k as u32).collect();
        assert_eq!(
            super::x86::HotSites::new(&sites, &spans, &[0], 64, &(0..8), Isa::current()).is_some(),
            k <= 8
        );
    }
    let range = 5..t - 3;
    let got = corrector.corrected_block_sum(&frames, range.clone());
    // The AVX2 paths (where the CPU has them) and the portable ones give the same sums.
    assert_eq!(
        corrector.corrected_block_sum_on(&frames, range.clone(), Isa::current()),
        got
    );
    assert_eq!(
        corrector.corrected_block_sum_on(&frames, range.clone(), Isa::generic()),
        got
    );
    let mut expected = frames.sum_range(range.clone());
    for (&idx, cands) in corrector.hot.iter().zip(&corrector.candidates) {
        let mut stream = corrector.stream(idx, range.start);
        let mut count = 0;
        for f in range.clone() {
            let pick = ((stream.next_u32() as u64 * cands.len() as u64) >> 32) as usize;
            let (y, x) = cands[pick];
            count += bits[[f, y as usize, x as usize]] as u32;
        }
        expected[[idx / w, idx % w]] = count;
    }
    assert_eq!(got, expected);
}
