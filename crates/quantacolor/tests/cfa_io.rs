//! CFA files: `.npy` codes and colour `.png` pictures, written atomically.

use image::{Rgb, RgbImage};
use quantacolor::cfa::{from_rgb_image, generate, load, load_npy, load_png, save, Pattern};

#[test]
fn npy_and_png_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let cfa = generate(&Pattern::blue_noise(0.75).unwrap(), 33, 47, 5).unwrap();
    for name in ["cfa.npy", "cfa.png"] {
        let path = dir.path().join(name);
        save(&cfa, &path).unwrap();
        assert_eq!(load(&path).unwrap(), cfa, "{name}");
    }
    assert_eq!(load_npy(dir.path().join("cfa.npy")).unwrap(), cfa);
    assert_eq!(load_png(dir.path().join("cfa.png")).unwrap(), cfa);
    // Only the two outputs remain: the temporary files were renamed away.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    // The PNG uses pure colours: (1, 1) of the 75 % pattern is a colour site, (0, 0) is W.
    let img = image::open(dir.path().join("cfa.png")).unwrap().to_rgb8();
    assert_eq!(img.get_pixel(0, 0).0, [255, 255, 255]);
    assert!([[255, 0, 0], [0, 255, 0], [0, 0, 255]].contains(&img.get_pixel(1, 1).0));
}

#[test]
fn bad_inputs_are_errors_naming_the_file() {
    let mut img = RgbImage::from_pixel(4, 3, Rgb([255, 255, 255]));
    img.put_pixel(2, 1, Rgb([255, 128, 0]));
    let err = from_rgb_image(&img, "my_cfa.png").unwrap_err().to_string();
    assert!(
        err.contains("my_cfa.png") && err.contains("(y=1, x=2)"),
        "{err}"
    );

    let dir = tempfile::tempdir().unwrap();
    let cfa = generate(&Pattern::Bayer, 4, 4, 0).unwrap();
    let err = save(&cfa, dir.path().join("cfa.txt"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("cfa.txt"), "{err}");
    let missing = dir.path().join("missing.png");
    assert!(load_png(&missing)
        .unwrap_err()
        .to_string()
        .contains("missing.png"));
    // An .npy holding a code above 3.
    let bad = dir.path().join("bad.npy");
    ndarray_npy::write_npy(&bad, &ndarray::arr2(&[[0u8, 7]])).unwrap();
    let err = load_npy(&bad).unwrap_err().to_string();
    assert!(err.contains("bad.npy") && err.contains("code 7"), "{err}");
    // Unwritable destination.
    let err = save(&cfa, dir.path().join("no/such/dir/cfa.npy"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("cfa.npy"), "{err}");
}
