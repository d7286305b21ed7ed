//! A closed pipe ends the program quietly, as it ends a C tool: `quantacolor eval A B | head -1`
//! would otherwise panic in `println!` ("failed printing to stdout: Broken pipe"), since Rust
//! programs ignore SIGPIPE and their writes fail with EPIPE instead.

/// Restores SIGPIPE's default action (the process ends, status 128 + 13, no message).
pub fn end_quietly_on_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: sets the disposition of one signal, before any thread starts; no handler runs.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}
