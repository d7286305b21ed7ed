//! The one way a test skips for want of an optional tool or data file (node, Chromium, pfstools,
//! the shared data folder): a message on stderr — or, where `QUANTACOLOR_REQUIRE_ALL_TESTS` is
//! set, as `.ci/run` sets it, a failure, so that CI never counts a skipped test as passed.
//! Included by path (`#[path = ".../common/skip.rs"] mod skip;`) from the test crates.

/// The variable that turns skips into failures.
pub const REQUIRE_ALL: &str = "QUANTACOLOR_REQUIRE_ALL_TESTS";

/// Skips `test` with `why` (the caller returns), or panics when skips are not allowed.
pub fn skip(test: &str, why: &str) {
    if std::env::var_os(REQUIRE_ALL).is_some_and(|v| !v.is_empty() && v != "0") {
        panic!("{test} cannot run: {why} ({REQUIRE_ALL} is set, so it may not skip)");
    }
    eprintln!("skipping {test}: {why}");
}
