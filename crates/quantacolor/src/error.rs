//! Error type shared by every stage: each error names the file (where there is one) and the
//! problem, so the CLI can print it and exit with code 2.
#![forbid(unsafe_code)]

use std::path::{Path, PathBuf};

/// Errors raised by the library.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be opened, read or written.
    #[error("{path}: {cause}")]
    Io {
        path: PathBuf,
        cause: std::io::Error,
    },
    /// A file exists but its content is not what was expected.
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    /// A parameter or argument is out of range or inconsistent.
    #[error("invalid parameter: {0}")]
    Invalid(String),
}

/// Result alias used across the crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// An I/O error on `path`.
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            cause: source,
        }
    }

    /// A content error on `path`.
    pub fn format(path: impl AsRef<Path>, message: impl Into<String>) -> Self {
        Error::Format {
            path: path.as_ref().to_path_buf(),
            message: message.into(),
        }
    }

    /// An invalid-parameter error.
    pub fn invalid(message: impl Into<String>) -> Self {
        Error::Invalid(message.into())
    }
}
