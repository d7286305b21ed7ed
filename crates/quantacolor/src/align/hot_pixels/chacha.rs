//! The ChaCha8 blocks whose words are the hot pixels' draws (rand_chacha's `ChaCha8Rng`
//! words, made eight blocks at a time where the instruction set allows).

#![forbid(unsafe_code)]

use super::BLOCK_WORDS;
use crate::cpu::Isa;

/// The ChaCha constant words ("expand 32-byte k").
pub(super) const CHACHA_CONSTANTS: [u32; 4] = [0x6170_7865, 0x3320_646e, 0x7962_2d32, 0x6b20_6574];

/// The ChaCha8 blocks `(stream, block)` of `jobs` under `key` into `out` (one per job): the
/// words `ChaCha8Rng` (rand_chacha) gives, word `16·block + j` of stream `stream` being word j
/// of that block. The generator's own refill makes four consecutive blocks of one stream at a
/// time; here any eight blocks go side by side, one per 32-bit lane (AVX2), so that the few
/// blocks each hot pixel needs per chunk of frames are made at full width. Integer arithmetic:
/// every path gives the same words (eight lanes where `isa` has AVX2).
pub(super) fn chacha8_blocks(
    key: &[u32; 8],
    jobs: &[(u64, u64)],
    out: &mut [[u32; BLOCK_WORDS]],
    isa: Isa,
) {
    assert_eq!(jobs.len(), out.len(), "one output block per job");
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        if isa.avx2() {
            for (jobs, out) in jobs.chunks_exact(8).zip(out.chunks_exact_mut(8)) {
                super::x86::chacha8_blocks8(isa, key, jobs, out);
                done += 8;
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = isa;
    for (&(stream, block), out) in jobs[done..].iter().zip(&mut out[done..]) {
        *out = chacha8_block(key, stream, block);
    }
}

/// The initial ChaCha state of block `block` of stream `stream`: constants, key, 64-bit block
/// counter, 64-bit stream number (rand_chacha's layout).
fn chacha_state(key: &[u32; 8], stream: u64, block: u64) -> [u32; 16] {
    let mut state = [0u32; 16];
    state[..4].copy_from_slice(&CHACHA_CONSTANTS);
    state[4..12].copy_from_slice(key);
    state[12..].copy_from_slice(&[
        block as u32,
        (block >> 32) as u32,
        stream as u32,
        (stream >> 32) as u32,
    ]);
    state
}

/// One ChaCha8 block (4 double rounds, then the initial state added), scalar.
pub(super) fn chacha8_block(key: &[u32; 8], stream: u64, block: u64) -> [u32; 16] {
    let init = chacha_state(key, stream, block);
    let mut x = init;
    let quarter = |x: &mut [u32; 16], a: usize, b: usize, c: usize, d: usize| {
        x[a] = x[a].wrapping_add(x[b]);
        x[d] = (x[d] ^ x[a]).rotate_left(16);
        x[c] = x[c].wrapping_add(x[d]);
        x[b] = (x[b] ^ x[c]).rotate_left(12);
        x[a] = x[a].wrapping_add(x[b]);
        x[d] = (x[d] ^ x[a]).rotate_left(8);
        x[c] = x[c].wrapping_add(x[d]);
        x[b] = (x[b] ^ x[c]).rotate_left(7);
    };
    for _ in 0..4 {
        for (a, b, c, d) in CHACHA_COLUMNS.into_iter().chain(CHACHA_DIAGONALS) {
            quarter(&mut x, a, b, c, d);
        }
    }
    for (x, i) in x.iter_mut().zip(init) {
        *x = x.wrapping_add(i);
    }
    x
}

/// The quarter rounds of a ChaCha column round and diagonal round (state word indices).
const CHACHA_COLUMNS: [(usize, usize, usize, usize); 4] =
    [(0, 4, 8, 12), (1, 5, 9, 13), (2, 6, 10, 14), (3, 7, 11, 15)];
const CHACHA_DIAGONALS: [(usize, usize, usize, usize); 4] =
    [(0, 5, 10, 15), (1, 6, 11, 12), (2, 7, 8, 13), (3, 4, 9, 14)];
