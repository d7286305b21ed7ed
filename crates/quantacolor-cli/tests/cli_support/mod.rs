//! Running the `quantacolor` binary from the CLI tests.

use std::process::{Command, Output};

/// Runs the binary with `args`.
pub fn quantacolor(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_quantacolor"))
        .args(args)
        .output()
        .expect("binary runs")
}

/// Runs the binary and asserts success.
pub fn ok(args: &[&str]) -> Output {
    let out = quantacolor(args);
    assert!(
        out.status.success(),
        "{args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}
