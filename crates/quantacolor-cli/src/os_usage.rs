//! What the benchmarks ask of the operating system beyond the standard library: the peak
//! resident set of one child process (`wait4`'s resource usage, which is that child's own,
//! unlike `getrusage(RUSAGE_CHILDREN)`), and the free space of a folder (`statvfs`). The only
//! unsafe code of the benchmarks: these two libc calls.

use anyhow::{Context, Result};
use std::ffi::CString;
use std::os::unix::ffi::OsStrExt;
use std::os::unix::process::ExitStatusExt;
use std::path::Path;
use std::process::{Child, ExitStatus};

/// How a child process ended and the most memory it held.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ChildUsage {
    pub status: ExitStatus,
    /// Peak resident set size, bytes (`ru_maxrss`).
    pub peak_rss_bytes: u64,
}

/// Waits for `child` to end, reaps it, and returns its exit status and peak resident set.
pub(crate) fn wait_with_usage(child: Child) -> Result<ChildUsage> {
    let pid = libc::pid_t::try_from(child.id()).context("child process id out of range")?;
    let mut status: libc::c_int = 0;
    // SAFETY: `rusage` is plain old data, for which all-zero bytes are a valid value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    loop {
        // SAFETY: `pid` is this process's own child, not yet reaped (`child` is consumed and
        // std never waits on it); `status` and `usage` are valid for writes.
        let reaped = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
        if reaped == pid {
            break;
        }
        let error = std::io::Error::last_os_error();
        if error.kind() != std::io::ErrorKind::Interrupted {
            return Err(error).with_context(|| format!("waiting for child process {pid}"));
        }
    }
    Ok(ChildUsage {
        status: ExitStatus::from_raw(status),
        // Linux reports ru_maxrss in kilobytes.
        peak_rss_bytes: u64::try_from(usage.ru_maxrss).unwrap_or(0) * 1024,
    })
}

/// Bytes available to this (unprivileged) process on the file system holding `dir`.
pub(crate) fn free_bytes(dir: &Path) -> Result<u64> {
    let name = CString::new(dir.as_os_str().as_bytes())
        .with_context(|| format!("{} holds a NUL byte", dir.display()))?;
    // SAFETY: `statvfs` is plain old data, for which all-zero bytes are a valid value.
    let mut stats: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `name` is a NUL-terminated string and `stats` is valid for writes.
    if unsafe { libc::statvfs(name.as_ptr(), &mut stats) } != 0 {
        return Err(std::io::Error::last_os_error())
            .with_context(|| format!("cannot read the free space of {}", dir.display()));
    }
    #[allow(clippy::unnecessary_cast)] // the field types differ between platforms
    Ok(stats.f_bavail as u64 * stats.f_frsize as u64)
}
