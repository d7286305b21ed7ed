//! Robustness weights (supplement Eq. 4–6) on blocks with known agreement or disagreement.
mod merge_support;

use merge_support::textured;
use ndarray::{Array2, Array3};
use quantacolor::merge::{robustness, RobustnessConfig};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Binomial, Distribution};

const H: usize = 40;
const W: usize = 48;
const TRIALS: u32 = 100;

fn noisy(truth: &Array2<f32>, rng: &mut ChaCha8Rng) -> Array2<f32> {
    truth.mapv(|p| {
        Binomial::new(TRIALS as u64, p as f64).unwrap().sample(rng) as f32 / TRIALS as f32
    })
}

fn grey_truth() -> Array2<f32> {
    Array2::from_shape_fn((H, W), |(y, x)| {
        let l: f64 = textured(y as f64, x as f64).iter().sum();
        (1.0 - (-l).exp()) as f32
    })
}

#[test]
fn agreeing_block_is_kept_and_a_moving_object_is_rejected() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let truth = grey_truth();
    let reference = truth.clone(); // a clean reference (the Wiener merge's role)
    let flow = Array3::<f32>::zeros((H, W, 2));
    let config = RobustnessConfig::default();
    let agree = robustness(
        &reference,
        &noisy(&truth, &mut rng),
        &flow,
        TRIALS as f32,
        &config,
    )
    .unwrap();
    let mean_agree = agree.mean().unwrap();
    // Same block with a bright object (bit rate 0.95) over a 12x12 square.
    let mut moved = truth.clone();
    moved.slice_mut(ndarray::s![10..22, 20..32]).fill(0.95);
    let r = robustness(
        &reference,
        &noisy(&moved, &mut rng),
        &flow,
        TRIALS as f32,
        &config,
    )
    .unwrap();
    let inside = r.slice(ndarray::s![12..20, 22..30]).mean().unwrap();
    let outside = r.slice(ndarray::s![26..38, 2..46]).mean().unwrap();
    println!("robustness: agreeing {mean_agree:.3}, object {inside:.3}, rest {outside:.3}");
    assert!(mean_agree > 0.9, "{mean_agree}");
    assert!(inside < 0.05, "{inside}");
    assert!(outside > 0.9, "{outside}");
}

#[test]
fn a_wrong_flow_is_rejected_where_it_misplaces_content() {
    // Checkerboard of 8 px squares (bit rates 0.2 / 0.7); a flow off by 4 px in x puts the
    // wrong square under half of the pixels.
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    let board = |y: usize, x: usize| {
        if (y / 8 + x / 8) & 1 == 0 {
            0.2f32
        } else {
            0.7
        }
    };
    let truth = Array2::from_shape_fn((H, W), |(y, x)| board(y, x));
    let block = noisy(&truth, &mut rng);
    let wrong = Array3::from_shape_fn((H, W, 2), |(_, _, i)| if i == 0 { 0.0 } else { 4.0 });
    let r = robustness(
        &truth,
        &block,
        &wrong,
        TRIALS as f32,
        &RobustnessConfig::default(),
    )
    .unwrap();
    let (mut bad, mut n_bad, mut good, mut n_good) = (0.0, 0.0, 0.0, 0.0);
    for y in 0..H {
        for x in 2..W - 6 {
            // Away from square edges (±2 px), is the content under p + flow right or wrong?
            let inside = |v: usize| (1..=6).contains(&(v % 8));
            if !(inside(y) && inside(x) && inside(x + 4)) {
                continue;
            }
            if board(y, x) != board(y, x + 4) {
                bad += r[[y, x]];
                n_bad += 1.0;
            } else {
                good += r[[y, x]];
                n_good += 1.0;
            }
        }
    }
    let (bad, good) = (bad / n_bad, good / n_good);
    println!("wrong flow: R where misplaced {bad:.3}, where consistent {good:.3}");
    assert!(bad < 0.05, "{bad}");
    assert!(good > 0.9, "{good}");
}

#[test]
fn incoherent_local_motion_makes_the_test_stricter() {
    // Flat scene: any flow matches in content, but a 12 px jump in the flow (spread above
    // M_th = 10 px) switches s from 12 to 1, so R drops to at most 1 − t near the jump.
    let mut rng = ChaCha8Rng::seed_from_u64(23);
    let truth = Array2::from_elem((H, W), 0.4f32);
    let block = noisy(&truth, &mut rng);
    let flow = Array3::from_shape_fn(
        (H, W, 2),
        |(_, x, i)| if i == 1 && x >= 24 { 12.0 } else { 0.0 },
    );
    let config = RobustnessConfig::default();
    let r = robustness(&truth, &block, &flow, TRIALS as f32, &config).unwrap();
    let near = r.slice(ndarray::s![.., 18..30]);
    let far = r.slice(ndarray::s![.., 0..10]);
    assert!(near.iter().all(|&v| v <= 1.0 - config.t + 1e-6));
    assert!(far.mean().unwrap() > 0.95);
    assert!(near.mean().unwrap() < far.mean().unwrap() - 0.1);
}

#[test]
fn shape_mismatch_is_an_error() {
    let a = Array2::<f32>::zeros((8, 8));
    let b = Array2::<f32>::zeros((8, 9));
    let f = Array3::<f32>::zeros((8, 8, 2));
    assert!(robustness(&a, &b, &f, 10.0, &RobustnessConfig::default()).is_err());
    assert!(robustness(
        &a,
        &a,
        &Array3::zeros((8, 8, 1)),
        10.0,
        &RobustnessConfig::default()
    )
    .is_err());
    assert!(robustness(&a, &a, &f, 0.0, &RobustnessConfig::default()).is_err());
}
