//! Synthetic reconstruction output folders for the report tests.

use ndarray::Array3;
use quantacolor::capture::io::write_npy;
use std::path::{Path, PathBuf};

/// A synthetic linear image: a horizontal ramp over four decades, hue varying down the rows,
/// `noise` of a fixed pattern added.
pub fn scene(h: usize, w: usize, noise: f32) -> Array3<f32> {
    Array3::from_shape_fn((h, w, 3), |(y, x, c)| {
        let level = 10f32.powf(-4.0 + 4.0 * x as f32 / (w - 1) as f32) * 0.3;
        let hue = [
            0.5 + 0.5 * (y as f32 * 0.2).sin(),
            0.6,
            0.5 + 0.5 * (y as f32 * 0.13).cos(),
        ][c];
        let pattern = (((x * 7 + y * 13 + c * 5) % 11) as f32 - 5.0) / 5.0;
        (level * hue * (1.0 + noise * pattern)).max(0.0)
    })
}

/// A reconstruction output folder `dir/name` holding `linear` and a report.toml.
pub fn result_dir(dir: &Path, name: &str, capture: &str, linear: &Array3<f32>) -> PathBuf {
    let out = dir.join(name);
    std::fs::create_dir_all(&out).unwrap();
    write_npy(out.join("linear.npy"), linear).unwrap();
    let (h, w, _) = linear.dim();
    std::fs::write(
        out.join("report.toml"),
        format!(
            "capture = \"{capture}\"\nmethod = \"{name}\"\nframes_used = 1000\nheight = {h}\nwidth = {w}\nw_weights = [1.0, 1.0, 1.0]\n\n[denoise]\nmethod = \"none\"\n\n[[timings]]\nstage = \"merge\"\nseconds = 0.25\n"
        ),
    )
    .unwrap();
    out
}
