//! Output directories that never hold partial results: files are written into a temporary
//! sibling directory, then renamed into place one by one once all of them are complete.

use anyhow::{Context, Result};
use std::path::{Path, PathBuf};

/// A staging directory for the files of one output directory.
pub struct StagedDir {
    target: PathBuf,
    staging: PathBuf,
    committed: bool,
}

impl StagedDir {
    /// Creates a staging directory beside `target`.
    pub fn new(target: &Path) -> Result<Self> {
        let name = target
            .file_name()
            .with_context(|| format!("{}: not a directory name", target.display()))?
            .to_string_lossy()
            .into_owned();
        let parent = match target.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent)
            .with_context(|| format!("{}: cannot create directory", parent.display()))?;
        let staging = parent.join(format!(".{name}.partial-{}", std::process::id()));
        if staging.exists() {
            std::fs::remove_dir_all(&staging).ok();
        }
        std::fs::create_dir(&staging)
            .with_context(|| format!("{}: cannot create directory", staging.display()))?;
        Ok(StagedDir {
            target: target.to_path_buf(),
            staging,
            committed: false,
        })
    }

    /// Path of `file` inside the staging directory.
    pub fn path(&self, file: &str) -> PathBuf {
        self.staging.join(file)
    }

    /// Moves every staged file into the target directory (created if needed).
    pub fn commit(mut self) -> Result<PathBuf> {
        if self.target.exists() && !self.target.is_dir() {
            anyhow::bail!("{}: exists and is not a directory", self.target.display());
        }
        std::fs::create_dir_all(&self.target)
            .with_context(|| format!("{}: cannot create directory", self.target.display()))?;
        for entry in std::fs::read_dir(&self.staging)
            .with_context(|| format!("{}: cannot list", self.staging.display()))?
        {
            let entry = entry?;
            let dest = self.target.join(entry.file_name());
            std::fs::rename(entry.path(), &dest)
                .with_context(|| format!("{}: cannot move into place", dest.display()))?;
        }
        std::fs::remove_dir_all(&self.staging).ok();
        self.committed = true;
        Ok(self.target.clone())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.committed {
            std::fs::remove_dir_all(&self.staging).ok();
        }
    }
}
