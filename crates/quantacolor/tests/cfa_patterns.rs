//! Defining properties of every CFA pattern (paper §5, Fig. 8; supplement Fig. 3).

use ndarray::{s, Array2};
use quantacolor::cfa::bluenoise::satisfies_neighbour_rule;
use quantacolor::cfa::colorspad::{colorspad_cfa_at_row, colorspad_png_cfa};
use quantacolor::cfa::{
    colorspad_cfa, colorspad_hot_pixel_mask, generate, Cfa, Pattern, SiteLattice, W_FRACTIONS,
};

fn counts(cfa: &Cfa) -> [usize; 4] {
    let mut c = [0; 4];
    for &v in cfa.codes().iter() {
        c[v as usize] += 1;
    }
    c
}

/// Whether `codes` equals itself shifted by `(dy, dx)` on the overlap.
fn has_period(codes: &Array2<u8>, dy: usize, dx: usize) -> bool {
    let (h, w) = codes.dim();
    codes.slice(s![dy.., dx..]) == codes.slice(s![..h - dy, ..w - dx])
}

/// Whether any shift with `0 <= dy, dx <= 16` (not both zero) is a period.
fn any_small_period(codes: &Array2<u8>) -> bool {
    (0..=16).any(|dy| (0..=16).any(|dx| (dy, dx) != (0, 0) && has_period(codes, dy, dx)))
}

#[test]
fn names_round_trip() {
    assert_eq!(Pattern::all().len(), Pattern::NAMES.len());
    for (p, name) in Pattern::all().iter().zip(Pattern::NAMES) {
        assert_eq!(p.to_string(), name);
        assert_eq!(&name.parse::<Pattern>().unwrap(), p);
    }
    assert_eq!(
        "rgbw-75-bluenoise".parse::<Pattern>().unwrap(),
        Pattern::BlueNoise { w_fraction: 0.75 }
    );
    let err = "rgbw-60-bluenoise"
        .parse::<Pattern>()
        .unwrap_err()
        .to_string();
    assert!(err.contains("0.6"), "{err}");
    let err = "quad-bayer".parse::<Pattern>().unwrap_err().to_string();
    assert!(
        err.contains("quad-bayer") && err.contains("rgbw-75-bluenoise"),
        "{err}"
    );
    assert!(Pattern::Bayer.with_w_fraction(0.5).is_err());
    assert_eq!(
        Pattern::BlueNoise { w_fraction: 0.75 }
            .with_w_fraction(0.875)
            .unwrap(),
        Pattern::BlueNoise { w_fraction: 0.875 }
    );
}

#[test]
fn bayer_and_rgbw25_tiles() {
    let b = generate(&Pattern::Bayer, 4, 6, 0).unwrap();
    assert_eq!(
        b.codes().slice(s![..2, ..2]),
        ndarray::arr2(&[[0u8, 1], [1, 2]])
    );
    assert_eq!(b.fractions(), [0.25, 0.5, 0.25, 0.0]);
    let q = generate(&Pattern::Rgbw25, 4, 6, 0).unwrap();
    assert_eq!(q.fractions(), [0.25; 4]);
    // every 2x2 block holds one of each channel
    for y in (0..4).step_by(2) {
        for x in (0..6).step_by(2) {
            let mut seen: Vec<u8> = q
                .codes()
                .slice(s![y..y + 2, x..x + 2])
                .iter()
                .copied()
                .collect();
            seen.sort();
            assert_eq!(seen, vec![0, 1, 2, 3]);
        }
    }
}

#[test]
fn rgbw50_checkerboard_with_double_green() {
    let c = generate(&Pattern::Rgbw50, 64, 64, 0).unwrap();
    for ((y, x), &v) in c.codes().indexed_iter() {
        assert_eq!(
            v == 3,
            (y + x) % 2 == 0,
            "W must sit on the checkerboard (y+x even)"
        );
    }
    let n = counts(&c);
    assert_eq!(n[3], 2048);
    assert_eq!(n[1], 2 * n[0]);
    assert_eq!(n[0], n[2]);
    assert!(
        has_period(c.codes(), 4, 0) && has_period(c.codes(), 0, 4),
        "regular"
    );
}

#[test]
fn rgbw75_regular_and_random_sites() {
    for p in [Pattern::Rgbw75Regular, Pattern::Rgbw75Random] {
        let c = generate(&p, 64, 64, 3).unwrap();
        for ((y, x), &v) in c.codes().indexed_iter() {
            assert_eq!(
                v != 3,
                y % 2 == 1 && x % 2 == 1,
                "{p}: colour only at (odd, odd)"
            );
        }
    }
    let reg = generate(&Pattern::Rgbw75Regular, 8, 8, 0).unwrap();
    // Bayer order on the colour-site lattice.
    assert_eq!(reg.codes()[[1, 1]], 0);
    assert_eq!(reg.codes()[[1, 3]], 1);
    assert_eq!(reg.codes()[[3, 1]], 1);
    assert_eq!(reg.codes()[[3, 3]], 2);
    let a = generate(&Pattern::Rgbw75Random, 128, 128, 1).unwrap();
    let b = generate(&Pattern::Rgbw75Random, 128, 128, 1).unwrap();
    let c = generate(&Pattern::Rgbw75Random, 128, 128, 2).unwrap();
    assert_eq!(a, b);
    assert_ne!(a, c);
    // i.i.d. uniform: each colour near 1/3 of 4096 sites (5 sigma ~ 150).
    let n = counts(&a);
    for k in 0..3 {
        assert!((n[k] as f64 - 4096.0 / 3.0).abs() < 150.0, "{n:?}");
    }
    // i.i.d. colours break the 4-neighbour rule somewhere.
    let lat = SiteLattice::for_w_fraction(0.75).unwrap();
    assert!(!satisfies_neighbour_rule(a.codes(), &lat));
    assert!(!any_small_period(a.codes()));
}

#[test]
fn blue_noise_family_properties() {
    for w in W_FRACTIONS {
        let p = Pattern::blue_noise(w).unwrap();
        let lat = SiteLattice::for_w_fraction(w).unwrap();
        let (h, wd) = (96, 128);
        let c = generate(&p, h, wd, 11).unwrap();
        // lattice and W fraction
        for ((y, x), &v) in c.codes().indexed_iter() {
            assert_eq!(v != 3, lat.is_site(y, x), "{p} at ({y},{x})");
        }
        assert!(
            (c.fractions()[3] - w).abs() < 1e-9,
            "{p}: {:?}",
            c.fractions()
        );
        // neighbour rule on the colour-site lattice
        assert!(satisfies_neighbour_rule(c.codes(), &lat), "{p}");
        // equal counts within 1 % (or one site)
        let n = counts(&c);
        let third = (n[0] + n[1] + n[2]) as f64 / 3.0;
        let spread = *n[..3].iter().max().unwrap() - *n[..3].iter().min().unwrap();
        assert!(spread as f64 <= (0.01 * third).max(1.0), "{p}: {n:?}");
        // determinism, seeds differ, no period up to 16
        assert_eq!(c, generate(&p, h, wd, 11).unwrap(), "{p}");
        assert_ne!(c, generate(&p, h, wd, 12).unwrap(), "{p}");
        assert!(!any_small_period(c.codes()), "{p}");
    }
}

#[test]
fn neighbour_rule_checker_detects_violations() {
    let lat = SiteLattice::for_w_fraction(0.75).unwrap();
    let reg = generate(&Pattern::Rgbw75Regular, 16, 16, 0).unwrap();
    // Bayer order on the sites: G sites are diagonal, never 4-adjacent.
    assert!(satisfies_neighbour_rule(reg.codes(), &lat));
    let mut bad = reg.codes().clone();
    bad[[1, 1]] = 1; // R -> G next to the G at (1, 3)
    assert!(!satisfies_neighbour_rule(&bad, &lat));
}

#[test]
fn blue_noise_odd_sizes_and_tiny() {
    for (h, w) in [(1, 1), (2, 2), (3, 7), (17, 5)] {
        let c = generate(&Pattern::blue_noise(0.75).unwrap(), h, w, 0).unwrap();
        assert_eq!((c.height(), c.width()), (h, w));
    }
    assert!(generate(&Pattern::Bayer, 0, 4, 0).is_err());
}

#[test]
fn colorspad_geometry_and_alignment() {
    let png = colorspad_png_cfa();
    assert_eq!((png.height(), png.width()), (256, 512));
    // Colour only at (odd row, odd column) and the last 16 columns all W.
    for ((y, x), &v) in png.codes().indexed_iter() {
        if v != 3 {
            assert!(y % 2 == 1 && x % 2 == 1 && x < 496, "colour at ({y},{x})");
        }
    }
    let c = colorspad_cfa();
    assert_eq!((c.height(), c.width()), (254, 496));
    assert_eq!(c.codes(), &png.codes().slice(s![2..256, ..496]).to_owned());
    let row0 = colorspad_cfa_at_row(0);
    for cfa in [&c, &row0] {
        for ((y, x), &v) in cfa.codes().indexed_iter() {
            assert_eq!(
                v != 3,
                y % 2 == 1 && x % 2 == 1,
                "frame colour site ({y},{x})"
            );
        }
    }
    // Same W mask, different colour labels.
    assert_eq!(
        c.mask(quantacolor::Channel::W),
        row0.mask(quantacolor::Channel::W)
    );
    assert_ne!(c, row0);
    // README: R/G/B 8.07 % each of the 256x512 picture.
    let n = counts(&png);
    for k in 0..3 {
        assert!(
            (n[k] as f64 / (256.0 * 512.0) - 0.0807).abs() < 5e-4,
            "{n:?}"
        );
    }
    // Crops and the size limit.
    let crop = generate(&Pattern::Colorspad, 64, 100, 0).unwrap();
    assert_eq!(crop.codes(), &c.codes().slice(s![..64, ..100]).to_owned());
    let err = generate(&Pattern::Colorspad, 256, 512, 0)
        .unwrap_err()
        .to_string();
    assert!(err.contains("496x254"), "{err}");
    assert!(!any_small_period(c.codes()));
}

#[test]
fn colorspad_hot_pixel_mask_shape() {
    let m = colorspad_hot_pixel_mask();
    assert_eq!(m.dim(), (254, 496));
    let hot = m.iter().filter(|&&v| v).count();
    assert!(hot > 0 && hot < m.len() / 10, "{hot} hot pixels");
}
