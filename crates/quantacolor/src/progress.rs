//! Progress reporting without terminal code: long stages call a [`Progress`] sink, which the CLI
//! implements with a progress bar and tests leave silent.
#![forbid(unsafe_code)]

/// Receives progress updates from long-running stages. Implementations must be thread-safe
/// because stages report from rayon workers.
pub trait Progress: Sync {
    /// A new phase named `label` with `total` units of work begins.
    fn start(&self, label: &str, total: u64);
    /// `n` more units of the current phase are done.
    fn advance(&self, n: u64);
    /// The current phase is finished.
    fn finish(&self);
}

/// A progress sink that ignores everything.
#[derive(Debug, Default, Clone, Copy)]
pub struct Silent;

impl Progress for Silent {
    fn start(&self, _label: &str, _total: u64) {}
    fn advance(&self, _n: u64) {}
    fn finish(&self) {}
}
