//! What the benchmarks ask of the operating system beyond the standard library: the peak
//! resident set of one child process (`wait4`'s resource usage, which is that child's own,
//! unlike `getrusage(RUSAGE_CHILDREN)`, checked against its sampled `VmHWM`), and the free
//! space of a folder (`statvfs`). The only unsafe code of the benchmarks: these libc calls.

use anyhow::{Context, Result};
use std::ffi::CString;
use std::os::unix::ffi::OsStrExt;
use std::os::unix::process::ExitStatusExt;
use std::path::Path;
use std::process::{Child, ExitStatus};
use std::time::Duration;

/// How a child process ended and the most memory it held.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ChildUsage {
    pub status: ExitStatus,
    /// Peak resident set size of the child's own program, bytes.
    pub peak_rss_bytes: u64,
}

/// How often [`wait_with_usage`] samples the child's `VmHWM`.
const POLL: Duration = Duration::from_millis(10);

/// A `kB` field of `/proc/<pid>/status`, bytes.
fn status_kb(pid: &str, field: &str) -> Option<u64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = text.lines().find(|l| l.starts_with(field))?;
    let kb = line[field.len()..].trim().trim_end_matches("kB").trim();
    kb.parse::<u64>().ok().map(|v| v * 1024)
}

/// Waits for `child` to end, reaps it, and returns its exit status and peak resident set.
///
/// `wait4`'s `ru_maxrss` is the child's own, but Linux starts it at the high-water mark of the
/// memory the child had before `exec`, which is this (vforked) process's: it is exact when it
/// exceeds this process's own peak, and otherwise the child's `VmHWM` sampled every
/// [`POLL`] while it runs is used (growth in its last moments may then be missed).
pub(crate) fn wait_with_usage(child: Child) -> Result<ChildUsage> {
    let pid = libc::pid_t::try_from(child.id()).context("child process id out of range")?;
    let own_peak = status_kb("self", "VmHWM:").unwrap_or(u64::MAX);
    let pid_text = pid.to_string();
    let mut sampled = 0u64;
    let mut status: libc::c_int = 0;
    // SAFETY: `rusage` is plain old data, for which all-zero bytes are a valid value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    loop {
        if let Some(hwm) = status_kb(&pid_text, "VmHWM:") {
            sampled = sampled.max(hwm);
        }
        // SAFETY: `pid` is this process's own child, not yet reaped (`child` is consumed and
        // std never waits on it); `status` and `usage` are valid for writes.
        let reaped = unsafe { libc::wait4(pid, &mut status, libc::WNOHANG, &mut usage) };
        if reaped == pid {
            break;
        }
        if reaped == 0 {
            std::thread::sleep(POLL);
            continue;
        }
        let error = std::io::Error::last_os_error();
        if error.kind() != std::io::ErrorKind::Interrupted {
            return Err(error).with_context(|| format!("waiting for child process {pid}"));
        }
    }
    // Linux reports ru_maxrss in kilobytes.
    let maxrss = u64::try_from(usage.ru_maxrss).unwrap_or(0) * 1024;
    Ok(ChildUsage {
        status: ExitStatus::from_raw(status),
        peak_rss_bytes: if maxrss > own_peak { maxrss } else { sampled },
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
