//! `capture::io`: atomic writes, typed `.npy` readers and image files.

use ndarray::{Array2, Array3};
use quantacolor::capture::io::{self, PixelEncoding};
use std::fs;

fn no_temporaries(dir: &std::path::Path) {
    let left: Vec<_> = fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".tmp"))
        .collect();
    assert!(left.is_empty(), "temporary files left: {left:?}");
}

#[test]
fn write_atomic_replaces_on_success_and_keeps_the_old_file_on_error() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("out.txt");
    quantacolor::atomic::write_atomic(&path, |w| w.write_all(b"first")).unwrap();
    assert_eq!(fs::read(&path).unwrap(), b"first");
    quantacolor::atomic::write_atomic_synced(&path, |w| w.write_all(b"second")).unwrap();
    assert_eq!(fs::read(&path).unwrap(), b"second");

    let err = quantacolor::atomic::write_atomic(&path, |w| {
        w.write_all(&[7u8; 3 << 20])?; // more than the buffer: bytes reach the temporary file
        Err(std::io::Error::other("disk on fire"))
    })
    .unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("out.txt") && msg.contains("disk on fire"),
        "{msg}"
    );
    assert_eq!(fs::read(&path).unwrap(), b"second");
    no_temporaries(tmp.path());

    let missing_dir = tmp.path().join("no/such/dir/x.bin");
    let err = quantacolor::atomic::write_atomic(&missing_dir, |w| w.write_all(b"x")).unwrap_err();
    assert!(err.to_string().contains("x.bin"));
}

#[test]
fn npy_round_trip_and_typed_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let a = Array2::from_shape_fn((3, 4), |(y, x)| y as f32 * 0.5 - x as f32);
    let p = tmp.path().join("a.npy");
    io::write_npy(&p, &a).unwrap();
    assert_eq!(io::read_npy_2d::<f32>(&p).unwrap(), a);
    // A transposed (non-standard layout) view is written in logical order.
    io::write_npy(&p, &a.t()).unwrap();
    assert_eq!(io::read_npy_2d::<f32>(&p).unwrap(), a.t());

    let b = Array3::from_shape_fn((2, 3, 2), |(i, j, k)| (i + j + k) % 2 == 0);
    let q = tmp.path().join("b.npy");
    io::write_npy(&q, &b).unwrap();
    assert_eq!(io::read_npy_3d::<bool>(&q).unwrap(), b);

    let msg = io::read_npy_2d::<bool>(&q).unwrap_err().to_string();
    assert!(msg.contains("b.npy") && msg.contains("2-D"), "{msg}");
    let msg = io::read_npy_3d::<u8>(&q).unwrap_err().to_string();
    assert!(
        msg.contains("b.npy") && msg.contains("dtype") && msg.contains("uint8"),
        "{msg}"
    );
    let msg = io::read_npy_2d::<f32>(tmp.path().join("none.npy"))
        .unwrap_err()
        .to_string();
    assert!(msg.contains("none.npy"), "{msg}");

    // Extra bytes after the data and bytes that are no bool are corrupt files.
    let mut bytes = fs::read(&p).unwrap();
    bytes.push(0);
    fs::write(&p, &bytes).unwrap();
    let msg = io::read_npy_2d::<f32>(&p).unwrap_err().to_string();
    assert!(msg.contains("unexpected bytes"), "{msg}");
    let mut bytes = fs::read(&q).unwrap();
    *bytes.last_mut().unwrap() = 9;
    fs::write(&q, &bytes).unwrap();
    let msg = io::read_npy_3d::<bool>(&q).unwrap_err().to_string();
    assert!(msg.contains("corrupt array data"), "{msg}");
    no_temporaries(tmp.path());
}

#[test]
fn huge_shape_in_a_small_file_is_truncation_not_an_allocation() {
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("bomb.npy");
    let mut bytes = quantacolor::capture::npy::encode_header("<f4", &[1 << 40, 1 << 20]);
    bytes.extend_from_slice(&[0; 16]);
    fs::write(&p, &bytes).unwrap();
    let msg = io::read_npy_2d::<f32>(&p).unwrap_err().to_string();
    assert!(
        msg.contains("bomb.npy") && msg.contains("truncated"),
        "{msg}"
    );
}

fn gradient_u16() -> Array3<u16> {
    Array3::from_shape_fn((4, 5, 3), |(y, x, c)| {
        (y * 9000 + x * 3000 + c * 777) as u16
    })
}

#[test]
fn png_and_tiff_read_back_as_srgb_in_unit_range() {
    let tmp = tempfile::tempdir().unwrap();
    let img8 = Array3::from_shape_fn((4, 5, 3), |(y, x, c)| (y * 50 + x * 10 + c) as u8);
    let p8 = tmp.path().join("a.png");
    io::write_png_rgb8(&p8, &img8).unwrap();
    let (back, enc) = io::read_rgb_image(&p8).unwrap();
    assert_eq!(enc, PixelEncoding::Srgb);
    assert_eq!(back.dim(), (4, 5, 3));
    for (v, &o) in back.iter().zip(img8.iter()) {
        assert!((v - o as f32 / 255.0).abs() < 1e-6);
    }

    let img16 = gradient_u16();
    for name in ["b.png", "c.tiff"] {
        let p = tmp.path().join(name);
        if name.ends_with("png") {
            io::write_png_rgb16(&p, &img16).unwrap();
        } else {
            io::write_tiff_rgb16(&p, &img16).unwrap();
        }
        let (back, enc) = io::read_rgb_image(&p).unwrap();
        assert_eq!(enc, PixelEncoding::Srgb, "{name}");
        for (v, &o) in back.iter().zip(img16.iter()) {
            assert!((v - o as f32 / 65535.0).abs() < 1e-6, "{name}");
        }
    }
    no_temporaries(tmp.path());
}

#[test]
fn jpeg_reads_as_srgb() {
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("flat.jpg");
    let flat = image::RgbImage::from_pixel(16, 8, image::Rgb([200, 100, 50]));
    flat.save(&p).unwrap();
    let (back, enc) = io::read_rgb_image(&p).unwrap();
    assert_eq!((enc, back.dim()), (PixelEncoding::Srgb, (8, 16, 3)));
    for (c, want) in [200.0f32, 100.0, 50.0].into_iter().enumerate() {
        assert!((back[[3, 5, c]] - want / 255.0).abs() < 3.0 / 255.0);
    }
}

#[test]
fn exr_round_trips_linear_floats_exactly() {
    let tmp = tempfile::tempdir().unwrap();
    let img = Array3::from_shape_fn((3, 4, 3), |(y, x, c)| {
        (y as f32 + 1.0) * 10f32.powi(x as i32 - 2) + c as f32 * 0.125
    });
    let p = tmp.path().join("hdr.exr");
    io::write_exr_rgb(&p, &img).unwrap();
    let (back, enc) = io::read_rgb_image(&p).unwrap();
    assert_eq!(enc, PixelEncoding::Linear);
    assert_eq!(back, img);

    let mut bad = img.clone();
    bad[[1, 2, 0]] = f32::NAN;
    io::write_exr_rgb(&p, &bad).unwrap();
    let msg = io::read_rgb_image(&p).unwrap_err().to_string();
    assert!(msg.contains("hdr.exr") && msg.contains("y=1, x=2"), "{msg}");
}

#[test]
fn image_errors_name_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("broken.png");
    fs::write(&p, b"\x89PNG\r\n\x1a\nnot really").unwrap();
    let msg = io::read_rgb_image(&p).unwrap_err().to_string();
    assert!(
        msg.contains("broken.png") && msg.contains("corrupt"),
        "{msg}"
    );
    let msg = io::read_rgb_image(tmp.path().join("gone.png"))
        .unwrap_err()
        .to_string();
    assert!(msg.contains("gone.png"), "{msg}");
    let msg = io::write_png_rgb8(tmp.path().join("x.png"), &Array3::zeros((2, 2, 4)))
        .unwrap_err()
        .to_string();
    assert!(msg.contains("x.png") && msg.contains("(H, W, 3)"), "{msg}");
    assert!(!tmp.path().join("x.png").exists());
}

#[test]
fn cfa_png_maps_pure_colours_to_codes() {
    let tmp = tempfile::tempdir().unwrap();
    let colours = [[255u8, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]];
    let codes = Array2::from_shape_fn((3, 7), |(y, x)| ((x + 2 * y) % 4) as u8);
    let img = Array3::from_shape_fn((3, 7, 3), |(y, x, c)| colours[codes[[y, x]] as usize][c]);
    let p = tmp.path().join("cfa.png");
    io::write_png_rgb8(&p, &img).unwrap();
    assert_eq!(io::read_cfa_png(&p).unwrap(), codes);
    let mut black = img.clone();
    black.slice_mut(ndarray::s![2, 6, ..]).fill(0);
    io::write_png_rgb8(&p, &black).unwrap();
    let msg = io::read_cfa_png(&p).unwrap_err().to_string();
    assert!(
        msg.contains("cfa.png") && msg.contains("(y=2, x=6)") && msg.contains("(0, 0, 0)"),
        "{msg}"
    );
}
