//! Reference image by Wiener merge (supplement §1.2) against a known grey scene.
mod merge_support;

use merge_support::{textured, Motion};
use ndarray::{Array2, Array3};
use quantacolor::merge::{reference_image, warp_to_reference, WienerConfig};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Binomial, Distribution};

const H: usize = 48;
const W: usize = 56;
const TRIALS: u32 = 40;

/// Grey bit rate of the scene at a reference position: the textured scene plus a bright disc
/// (radius 5 px at (24, 28)) whose ghost would be easy to see.
fn grey(y: f64, x: f64) -> f64 {
    let disc = if (y - 24.0).powi(2) + (x - 28.0).powi(2) < 25.0 {
        3.0
    } else {
        0.0
    };
    let lambda: f64 = textured(y, x).iter().sum::<f64>() + disc;
    1.0 - (-lambda).exp()
}

fn grey_block(m: &Motion, rng: &mut ChaCha8Rng) -> Array2<f32> {
    Array2::from_shape_fn((H, W), |(y, x)| {
        let (ry, rx) = m.inverse(H, W, y as f64, x as f64);
        Binomial::new(TRIALS as u64, grey(ry, rx))
            .unwrap()
            .sample(rng) as f32
            / TRIALS as f32
    })
}

fn rmse(a: &Array2<f32>, truth: &Array2<f32>) -> f64 {
    rmse_in(a, truth, 4..H - 4, 4..W - 4)
}

fn rmse_in(
    a: &Array2<f32>,
    truth: &Array2<f32>,
    ys: std::ops::Range<usize>,
    xs: std::ops::Range<usize>,
) -> f64 {
    let mut se = 0.0;
    let mut n = 0.0;
    for y in ys {
        for x in xs.clone() {
            se += (a[[y, x]] as f64 - truth[[y, x]] as f64).powi(2);
            n += 1.0;
        }
    }
    (se / n).sqrt()
}

fn setup(seed: u64, k: usize) -> (Vec<Array2<f32>>, Vec<Array3<f32>>, Array2<f32>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut motions = vec![Motion {
        dy: 0.0,
        dx: 0.0,
        theta: 0.0,
    }];
    for _ in 1..k {
        motions.push(Motion::random(&mut rng, 2.5, 0.02));
    }
    let blocks = motions.iter().map(|m| grey_block(m, &mut rng)).collect();
    let flows = motions.iter().map(|m| m.flow(H, W)).collect();
    let truth = Array2::from_shape_fn((H, W), |(y, x)| grey(y as f64, x as f64) as f32);
    (blocks, flows, truth)
}

#[test]
fn wiener_reference_is_closer_to_truth_than_the_reference_block() {
    let (blocks, flows, truth) = setup(11, 8);
    let merged =
        reference_image(&blocks, &flows, 0, TRIALS as f32, &WienerConfig::default()).unwrap();
    let (e_merged, e_single) = (rmse(&merged, &truth), rmse(&blocks[0], &truth));
    println!("reference RMSE: merged {e_merged:.4}, reference block alone {e_single:.4}");
    assert!(
        e_merged < 0.7 * e_single,
        "merged {e_merged} vs single {e_single}"
    );
}

#[test]
fn misaligned_block_does_not_ghost_into_the_reference() {
    let (blocks, mut flows, truth) = setup(12, 8);
    let config = WienerConfig::default();
    let clean = reference_image(&blocks, &flows, 0, TRIALS as f32, &config).unwrap();
    // Block 3's flow is off by (−9, +9) px: its disc lands around (33, 19) instead of (24, 28).
    flows[3].outer_iter_mut().for_each(|mut row| {
        row.outer_iter_mut().for_each(|mut f| {
            f[0] -= 9.0;
            f[1] += 9.0;
        })
    });
    let robust = reference_image(&blocks, &flows, 0, TRIALS as f32, &config).unwrap();
    // A plain average of the warped blocks ghosts the misplaced content.
    let warped: Vec<_> = blocks
        .iter()
        .zip(&flows)
        .map(|(b, f)| warp_to_reference(b, f).unwrap())
        .collect();
    let mean = warped
        .iter()
        .fold(Array2::<f32>::zeros((H, W)), |a, b| a + b)
        / warped.len() as f32;
    // Errors where the misplaced block's disc would ghost.
    let around = |img: &Array2<f32>| rmse_in(img, &truth, 27..40, 12..26);
    let (e_clean, e_robust, e_mean) = (around(&clean), around(&robust), around(&mean));
    println!("RMSE where the ghost would land: all aligned {e_clean:.4}, one misaligned {e_robust:.4}, plain mean {e_mean:.4}");
    assert!(e_robust < 1.25 * e_clean, "{e_robust} vs {e_clean}");
    assert!(rmse(&robust, &truth) < 1.25 * rmse(&clean, &truth));
    assert!(
        e_robust < 0.65 * e_mean,
        "{e_robust} vs plain mean {e_mean}"
    );
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let (blocks, flows, _) = setup(13, 3);
    let c = WienerConfig::default();
    assert!(reference_image(&blocks, &flows[..2], 0, 40.0, &c).is_err());
    assert!(reference_image(&blocks, &flows, 3, 40.0, &c).is_err());
    assert!(reference_image(&blocks, &flows, 0, 0.0, &c).is_err());
    assert!(reference_image(&[], &[], 0, 40.0, &c).is_err());
    let mut bad = flows.clone();
    bad[1] = Array3::zeros((H, W - 1, 2));
    assert!(reference_image(&blocks, &bad, 0, 40.0, &c).is_err());
}
