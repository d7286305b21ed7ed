//! Output directories of a reconstruction, shared by the CLI and the Python package (so that a
//! batch run writes exactly the files `quantacolor reconstruct` writes).
//!
//! [`StagedDir`] never leaves partial results: files are written into a temporary sibling
//! directory, then renamed into place one by one once all of them are complete.
//! [`write_reconstruction`] writes `linear.npy`, `linear.exr`, `preview.png` and `report.toml`.
#![forbid(unsafe_code)]

use crate::atomic::{temp_sibling, TempGuard};
use crate::capture::{io, Capture};
use crate::denoise::chroma::DenoiseReport;
use crate::display::{write_rendered, BitDepth, RenderOptions};
use crate::error::{Error, Result};
use crate::pipeline::{ReconstructConfig, Reconstruction};
use crate::timing::StageTiming;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// The files of a finished reconstruction directory, in the order they are written.
pub const RECONSTRUCTION_FILES: [&str; 4] =
    ["linear.npy", "linear.exr", "preview.png", "report.toml"];

/// Units of `linear.npy`, as `report.toml` states them.
pub const LINEAR_UNITS: &str =
    "mean photon detections per binary frame of an R, G or B pixel, dark counts removed";

/// A staging directory for the files of one output directory: a temporary sibling of the
/// target named and removed by [`crate::atomic`] (gone on drop, after a commit too).
pub struct StagedDir {
    target: PathBuf,
    staging: TempGuard,
}

impl StagedDir {
    /// Creates a staging directory beside `target`.
    pub fn new(target: &Path) -> Result<Self> {
        let name = target
            .file_name()
            .ok_or_else(|| Error::format(target, "not a directory name"))?
            .to_string_lossy()
            .into_owned();
        let parent = match target.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent).map_err(|e| Error::io(&parent, e))?;
        // `.{name}.partial.{pid}-{n}.tmp`: "partial" says what it holds.
        let staging = temp_sibling(&parent.join(format!("{name}.partial")))?;
        if staging.exists() {
            std::fs::remove_dir_all(&staging).ok();
        }
        std::fs::create_dir(&staging).map_err(|e| Error::io(&staging, e))?;
        Ok(StagedDir {
            target: target.to_path_buf(),
            staging: TempGuard::dir(staging),
        })
    }

    /// The staging directory itself.
    pub fn dir(&self) -> &Path {
        self.staging.path()
    }

    /// Path of `file` inside the staging directory.
    pub fn path(&self, file: &str) -> PathBuf {
        self.dir().join(file)
    }

    /// Moves every staged file into the target directory (created if needed); the emptied
    /// staging directory is removed when `self` drops.
    pub fn commit(self) -> Result<PathBuf> {
        if self.target.exists() && !self.target.is_dir() {
            return Err(Error::format(&self.target, "exists and is not a directory"));
        }
        std::fs::create_dir_all(&self.target).map_err(|e| Error::io(&self.target, e))?;
        let staging = self.dir();
        let entries = std::fs::read_dir(staging).map_err(|e| Error::io(staging, e))?;
        let mut names = Vec::new();
        for entry in entries {
            names.push(entry.map_err(|e| Error::io(staging, e))?.file_name());
        }
        // `report.toml` last: its presence marks a complete reconstruction directory.
        names.sort_by_key(|n| n == "report.toml");
        for name in names {
            let dest = self.target.join(&name);
            std::fs::rename(staging.join(&name), &dest).map_err(|e| Error::io(&dest, e))?;
        }
        Ok(self.target.clone())
    }
}

#[derive(Serialize)]
struct Report<'a> {
    capture: String,
    method: String,
    reference_frame: usize,
    frames_used: usize,
    height: usize,
    width: usize,
    units: &'static str,
    /// W = wR·R + wG·G + wB·B of the capture (read back by `quantacolor display`).
    w_weights: [f64; 3],
    #[serde(skip_serializing_if = "Option::is_none")]
    sub_blocks: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    alignment_blocks: Option<usize>,
    /// Grey block images remade sharp for the merge guide (`[burst.merge] sharpen_blocks_px`).
    #[serde(skip_serializing_if = "Option::is_none")]
    sharpened_blocks: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    denoise: Option<&'a DenoiseReport>,
    config: &'a ReconstructConfig,
    /// How preview.png was rendered.
    preview: &'a RenderOptions,
    timings: &'a [StageTiming],
}

/// Refuses the output directory `out` when it already holds files, unless `overwrite`: an
/// earlier result is never replaced by accident. Checked before any work, so a refused run
/// costs nothing; the replacement itself stays atomic ([`StagedDir`]). `name` is how the
/// caller spells the directory's argument (`--out`, `out_dir`) and `allow` how to permit the
/// replacement (`give --overwrite`, `pass overwrite=True`); both go into the message.
pub fn check_out_dir(out: &Path, name: &str, allow: &str, overwrite: bool) -> Result<()> {
    if !out.exists() {
        return Ok(());
    }
    if !out.is_dir() {
        return Err(Error::format(out, "exists and is not a directory"));
    }
    let mut entries = std::fs::read_dir(out).map_err(|e| Error::io(out, e))?;
    if entries.next().is_some() && !overwrite {
        return Err(Error::format(
            out,
            format!(
                "the directory already holds files (an earlier result?); choose another \
                 {name}, or {allow} to replace them"
            ),
        ));
    }
    Ok(())
}

/// True when `out` holds every file [`write_reconstruction`] writes (`report.toml` is moved
/// into place last, so an interrupted commit is not mistaken for a finished one).
pub fn reconstruction_complete(out: &Path) -> bool {
    RECONSTRUCTION_FILES.iter().all(|f| out.join(f).is_file())
}

/// Writes the reconstruction files into `out` (staged, then moved into place): `linear.npy`
/// (float32 (H, W, 3)), `linear.exr`, `preview.png` rendered with `preview`, and `report.toml`
/// (the capture as `capture_label`, the config, the denoiser's report and the stage timings).
pub fn write_reconstruction(
    out: &Path,
    capture_label: &str,
    capture: &Capture,
    config: &ReconstructConfig,
    rec: &Reconstruction,
    preview: &RenderOptions,
) -> Result<()> {
    let staged = StagedDir::new(out)?;
    io::write_npy(staged.path("linear.npy"), &rec.linear)?;
    io::write_exr_rgb(staged.path("linear.exr"), &rec.linear)?;
    write_rendered(
        staged.path("preview.png"),
        rec.linear.view(),
        preview,
        BitDepth::Eight,
    )?;
    let (height, width, _) = rec.linear.dim();
    let report = Report {
        capture: capture_label.to_string(),
        method: config.method.to_string(),
        reference_frame: rec.reference_frame,
        frames_used: rec.frames_used,
        height,
        width,
        units: LINEAR_UNITS,
        w_weights: capture.meta.w_weights,
        sub_blocks: rec.burst.as_ref().map(|b| b.sub_blocks.len()),
        alignment_blocks: rec.burst.as_ref().map(|b| b.alignment.plan.len()),
        sharpened_blocks: rec.burst.as_ref().map(|b| b.sharpened_blocks),
        denoise: rec.denoise.as_ref(),
        config,
        preview,
        timings: &rec.timings,
    };
    let report_path = staged.path("report.toml");
    let text = toml::to_string_pretty(&report)
        .map_err(|e| Error::format(&report_path, format!("cannot serialise: {e}")))?;
    std::fs::write(&report_path, text).map_err(|e| Error::io(out.join("report.toml"), e))?;
    staged.commit()?;
    Ok(())
}

/// `w_weights` of a parsed `report.toml` (W = wR·R + wG·G + wB·B), when it has them.
pub fn report_w_weights(report: &toml::Table) -> Option<[f64; 3]> {
    let v = report.get("w_weights")?.as_array()?;
    let w: Vec<f64> = v
        .iter()
        .filter_map(|x| x.as_float().or(x.as_integer().map(|i| i as f64)))
        .collect();
    (w.len() == 3).then(|| [w[0], w[1], w[2]])
}

/// `frames_used` of a parsed `report.toml`, when it has a positive one.
pub fn report_frames(report: &toml::Table) -> Option<f64> {
    let v = report.get("frames_used")?;
    v.as_integer()
        .map(|i| i as f64)
        .or(v.as_float())
        .filter(|t| *t > 0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entries(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn an_interrupted_staged_dir_leaves_nothing() {
        let tmp = tempfile::tempdir().unwrap();
        let target = tmp.path().join("out");
        {
            let staged = StagedDir::new(&target).unwrap();
            assert!(staged.dir().starts_with(tmp.path()));
            assert!(staged.dir().is_dir());
            std::fs::write(staged.path("linear.npy"), b"half").unwrap();
        }
        assert!(entries(tmp.path()).is_empty(), "{:?}", entries(tmp.path()));
        // A commit that fails (the target is a file) leaves the file alone and no staging.
        std::fs::write(&target, b"a file").unwrap();
        let staged = StagedDir::new(&target).unwrap();
        std::fs::write(staged.path("report.toml"), b"x").unwrap();
        assert!(staged.commit().is_err());
        assert_eq!(entries(tmp.path()), ["out"]);
        assert_eq!(std::fs::read(&target).unwrap(), b"a file");
    }

    #[test]
    fn a_committed_staged_dir_replaces_its_files_and_leaves_no_staging() {
        let tmp = tempfile::tempdir().unwrap();
        let target = tmp.path().join("out");
        std::fs::create_dir(&target).unwrap();
        std::fs::write(target.join("linear.npy"), b"old").unwrap();
        std::fs::write(target.join("notes.txt"), b"kept").unwrap();
        let first = StagedDir::new(&target).unwrap();
        let second = StagedDir::new(&target).unwrap();
        assert_ne!(
            first.dir(),
            second.dir(),
            "each stage gets its own directory"
        );
        assert!(first.dir().to_string_lossy().contains("partial"));
        drop(second);
        std::fs::write(first.path("linear.npy"), b"new").unwrap();
        std::fs::write(first.path("report.toml"), b"done").unwrap();
        assert_eq!(first.commit().unwrap(), target);
        assert_eq!(entries(tmp.path()), ["out"]);
        assert_eq!(entries(&target), ["linear.npy", "notes.txt", "report.toml"]);
        assert_eq!(std::fs::read(target.join("linear.npy")).unwrap(), b"new");
        assert_eq!(std::fs::read(target.join("notes.txt")).unwrap(), b"kept");
    }

    #[test]
    fn a_non_empty_out_dir_is_refused_unless_overwrite() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("out");
        check_out_dir(&out, "--out", "give --overwrite", false).unwrap();
        std::fs::create_dir(&out).unwrap();
        check_out_dir(&out, "--out", "give --overwrite", false).unwrap();
        std::fs::write(out.join("linear.npy"), b"earlier").unwrap();
        let e = check_out_dir(&out, "out_dir", "pass overwrite=True", false)
            .unwrap_err()
            .to_string();
        assert!(e.contains(&out.display().to_string()), "{e}");
        assert!(
            e.contains("choose another out_dir, or pass overwrite=True"),
            "{e}"
        );
        check_out_dir(&out, "out_dir", "pass overwrite=True", true).unwrap();
        let file = tmp.path().join("file");
        std::fs::write(&file, b"x").unwrap();
        let e = check_out_dir(&file, "--out", "give --overwrite", true).unwrap_err();
        assert!(e.to_string().contains("not a directory"), "{e}");
    }
}
