//! `quantacolor bench long` end to end at tiny sizes (`--frames-base 100`, 96x64): every case is
//! a row of the table with sane numbers, the Markdown holds the same table, a second run reuses
//! the cached captures, and bad input exits with status 2 naming the option.

mod cli_support;
use cli_support::{ok, quantacolor, table_cells};
use std::path::Path;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The cells of the table's data rows (not the header or the separator).
fn table_rows(stdout: &str) -> Vec<Vec<String>> {
    stdout
        .lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| case"))
        .map(table_cells)
        .collect()
}

fn number(cell: &str) -> f64 {
    cell.trim_end_matches('x')
        .parse()
        .unwrap_or_else(|_| panic!("{cell:?} is not a number"))
}

#[test]
fn bench_long_reports_every_case_and_reuses_its_captures() {
    let tmp = tempfile::tempdir().unwrap();
    let work = tmp.path().join("work");
    let md = tmp.path().join("long.md");
    let base = [
        "bench",
        "long",
        "--frames-base",
        "100",
        "--size",
        "96x64",
        "--work",
        s(&work),
    ];
    let mut args = base.to_vec();
    args.extend(["--markdown", s(&md)]);
    let out = ok(&args);
    let stdout = String::from_utf8(out.stdout).unwrap();
    let rows = table_rows(&stdout);
    let labels: Vec<&str> = rows.iter().map(|r| r[0].as_str()).collect();
    assert_eq!(
        labels,
        [
            "100 frames, natural",
            "100 frames, the jumps' first part",
            "1,000 frames, natural",
            "1,000 frames, 10 parts (9 jumps)",
            "10,000 frames, the 1,000 repeated 10 times"
        ],
        "{stdout}"
    );
    for (row, frames) in rows.iter().zip([100.0, 100.0, 1000.0, 1000.0, 10_000.0]) {
        assert_eq!(row.len(), 6, "{row:?}");
        let seconds = number(&row[1]);
        let us_per_frame = number(&row[2]);
        let rss_mb = number(&row[3]);
        let psnr = number(&row[5]);
        assert!(seconds > 0.0, "{row:?}");
        // Both rounded in the table: the time to 0.01 s, µs per frame to 0.1 µs.
        let implied = us_per_frame * frames / 1e6;
        assert!((implied - seconds).abs() <= 0.0051, "{row:?}");
        assert!(rss_mb > 1.0 && rss_mb < 4000.0, "{row:?}");
        assert!(number(&row[4]) > 0.0, "{row:?}");
        assert!(psnr > 5.0 && psnr < 60.0, "{row:?}");
    }
    assert_eq!(rows[0][4], "1.00x", "the first case is the ratios' base");
    let markdown = std::fs::read_to_string(&md).unwrap();
    assert!(markdown.contains("bench long"), "{markdown}");
    for row in stdout.lines().filter(|l| l.starts_with('|')) {
        assert!(markdown.contains(row), "{row} missing from {markdown}");
    }

    // The captures are cached: a second run simulates nothing.
    let mut again = base.to_vec();
    again.extend(["--cases", "100k-jumps"]);
    let out = ok(&again);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("reusing"), "{stderr}");
    assert!(!stderr.contains("simulating"), "{stderr}");
    assert_eq!(table_rows(&String::from_utf8(out.stdout).unwrap()).len(), 1);
}

#[test]
fn bench_long_bad_input_exits_2_naming_the_option() {
    let tmp = tempfile::tempdir().unwrap();
    let work = tmp.path().join("work");
    for (args, needle) in [
        (vec!["--frames-base", "1"], "--frames-base"),
        (vec!["--scene", "/no/such/scene.png"], "/no/such/scene.png"),
        (vec!["--size", "96by64"], "--size"),
        (vec!["--cases", "1m", "--skip-million"], "no case"),
    ] {
        let mut all = vec!["bench", "long", "--work", s(&work)];
        all.extend(&args);
        let out = quantacolor(&all);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains(needle), "{args:?}: {stderr}");
        assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
    }
}
