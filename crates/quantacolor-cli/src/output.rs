//! Output directories that never hold partial results (the library's [`StagedDir`]).

pub use quantacolor::output::StagedDir;
