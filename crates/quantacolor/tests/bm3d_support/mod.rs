//! Test images shared by the BM3D tests.

use ndarray::Array2;
use std::path::{Path, PathBuf};

/// Piecewise-smooth + texture test image on 0..255: a gradient background with a smooth wave,
/// a disc, a dark rectangle, and two oscillating texture patches.
pub fn synthetic(h: usize, w: usize) -> Array2<f32> {
    Array2::from_shape_fn((h, w), |(y, x)| {
        let (fy, fx) = (y as f32 / h as f32, x as f32 / w as f32);
        let mut v = 60.0 + 80.0 * fx + 30.0 * (3.0 * fy).sin();
        let (dy, dx) = (fy - 0.35, fx - 0.3);
        if dy * dy + dx * dx < 0.04 {
            v = 200.0 - 40.0 * fy;
        }
        if (0.6..0.9).contains(&fy) && (0.1..0.45).contains(&fx) {
            v = 30.0 + 20.0 * fx;
        }
        if (0.55..0.95).contains(&fy) && (0.55..0.95).contains(&fx) {
            v = 128.0 + 60.0 * (x as f32 * 0.9).sin() * (y as f32 * 0.35).cos();
        }
        if (0.1..0.4).contains(&fy) && (0.6..0.9).contains(&fx) {
            v = 110.0 + 70.0 * ((x + y) as f32 * 0.5).sin();
        }
        v
    })
}

/// The project's shared/data/scenes folder, when present.
#[allow(dead_code)] // not every test binary that includes this module uses it
pub fn scenes_dir() -> Option<PathBuf> {
    let rel = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/scenes");
    [rel, PathBuf::from("/work/shared/data/scenes")]
        .into_iter()
        .find(|p| p.is_dir())
}
