//! Output directories that never hold partial results (the library's [`StagedDir`]).

#![forbid(unsafe_code)]

pub use quantacolor::output::StagedDir;
