//! The README's typical session, run as written: every command of its `sh` block, in order, in
//! a fresh directory, with this build's `quantacolor` first on the PATH. The README cannot
//! drift from the program (a renamed option or a missing step fails here).

use std::path::Path;
use std::process::Command;

/// The first ```sh block after the line that starts with `marker`.
fn sh_block_after(readme: &str, marker: &str) -> String {
    let start = readme
        .find(marker)
        .unwrap_or_else(|| panic!("README has no {marker:?}"));
    let rest = &readme[start..];
    let open = rest.find("```sh\n").expect("a ```sh block") + "```sh\n".len();
    let close = rest[open..].find("```").expect("the block's end");
    rest[open..open + close].to_string()
}

#[test]
fn the_readme_typical_session_runs() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let session = sh_block_after(&readme, "A typical session");
    assert!(session.contains("quantacolor reconstruct"), "{session}");
    let exe = Path::new(env!("CARGO_BIN_EXE_quantacolor"));
    let path = format!(
        "{}:{}",
        exe.parent().unwrap().display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new("bash")
        .args(["-e", "-u", "-o", "pipefail", "-c", &session])
        .current_dir(dir.path())
        .env("PATH", path)
        .output()
        .expect("bash runs");
    assert!(
        out.status.success(),
        "the README's session failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    // What the session says it makes.
    for made in [
        "rec/linear.npy",
        "naive/linear.npy",
        "page/index.html",
        "rec.tif",
        "dark.png",
        "video/linear.npy",
        "clip_00000.png",
        "cfa-sheet/compare.png",
    ] {
        assert!(dir.path().join(made).is_file(), "{made} missing");
    }
}
