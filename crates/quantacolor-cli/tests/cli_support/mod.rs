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

/// The cells of a Markdown table row `| a | b |`, trimmed (for the bench tables).
#[allow(dead_code, reason = "used by the bench tests only")]
pub fn table_cells(row: &str) -> Vec<String> {
    row.trim_matches('|')
        .split('|')
        .map(|c| c.trim().to_string())
        .collect()
}
