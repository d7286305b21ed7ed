//! Headless Chromium driven over the DevTools protocol for the page tests.
//!
//! Why this and not chromedriver or a crate: `--remote-debugging-pipe` talks the DevTools
//! protocol over two inherited file descriptors (3: commands in, 4: replies out, NUL-separated
//! JSON), so there is no port to allocate, no second process and no websocket; the protocol
//! gives real input events (`Input.dispatchMouseEvent` wheel/drag/click,
//! `Input.dispatchKeyEvent`), screenshots and downloads. `fantoccini`/`headless_chrome` would
//! add an async runtime or a websocket stack to do the same.
//!
//! [`Browser::launch`] returns `None` (the test then skips with a message) when no Chromium is
//! installed; `QC_CHROMIUM` names a binary explicitly.

#[path = "../../../quantacolor/tests/common/skip.rs"]
mod skip;

use serde_json::{json, Value};
use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::os::fd::FromRawFd;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The Chromium binary: `QC_CHROMIUM`, else the first of the usual names on PATH.
pub fn chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("QC_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let path = std::env::var_os("PATH")?;
    for name in ["chromium", "chromium-browser", "google-chrome", "chrome"] {
        for dir in std::env::split_paths(&path) {
            let p = dir.join(name);
            if p.is_file() {
                return Some(p);
            }
        }
    }
    None
}

/// A headless Chromium with one page attached.
pub struct Browser {
    child: Child,
    to_browser: File,
    from_browser: BufReader<File>,
    next_id: u64,
    session: String,
    /// Events received while waiting for replies.
    pub events: Vec<Value>,
    _profile: tempfile::TempDir,
}

/// A pipe whose ends are closed on exec (the child gets only what `pre_exec` moves to 3 and 4,
/// also when several tests start browsers at once).
fn pipe() -> (i32, i32) {
    let mut fds = [0i32; 2];
    // SAFETY: `fds` is a valid array of two ints for pipe(2) to fill; fcntl on the new fds.
    unsafe {
        assert_eq!(libc::pipe(fds.as_mut_ptr()), 0, "pipe(2) failed");
        for fd in fds {
            libc::fcntl(fd, libc::F_SETFD, libc::FD_CLOEXEC);
        }
    }
    (fds[0], fds[1])
}

impl Browser {
    /// Starts Chromium headless with a `width` x `height` viewport, or `None` when there is no
    /// Chromium (the caller skips).
    pub fn launch(width: u32, height: u32) -> Option<Browser> {
        let binary = chromium()?;
        let profile = tempfile::tempdir().unwrap();
        // Commands: we write `cmd_w`, the browser reads `cmd_r` as fd 3; replies: the browser
        // writes `rep_w` as fd 4, we read `rep_r`.
        let (cmd_r, cmd_w) = pipe();
        let (rep_r, rep_w) = pipe();
        let mut command = Command::new(&binary);
        command
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--no-first-run",
                "--no-default-browser-check",
                "--disable-extensions",
                "--hide-scrollbars",
                "--force-color-profile=srgb",
                "--remote-debugging-pipe",
                &format!("--window-size={width},{height}"),
            ])
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .arg("about:blank")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        // SAFETY: between fork and exec only async-signal-safe calls (fcntl, dup2, close) on
        // descriptors this process created.
        unsafe {
            command.pre_exec(move || {
                // Copies above 4 first (so that dup2 onto 3 and 4 cannot clobber a pipe end
                // that happens to be 3 or 4), then onto 3 and 4 (dup2 clears close-on-exec);
                // every other end is closed by exec.
                let r = libc::fcntl(cmd_r, libc::F_DUPFD, 10);
                let w = libc::fcntl(rep_w, libc::F_DUPFD, 10);
                if r < 0 || w < 0 || libc::dup2(r, 3) < 0 || libc::dup2(w, 4) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                libc::close(r);
                libc::close(w);
                Ok(())
            });
        }
        let child = match command.spawn() {
            Ok(c) => c,
            Err(e) => {
                eprintln!("cannot start {}: {e}", binary.display());
                return None;
            }
        };
        // SAFETY: the parent's ends are owned here from now on; the child's ends are closed.
        let (to_browser, from_browser) = unsafe {
            libc::close(cmd_r);
            libc::close(rep_w);
            (File::from_raw_fd(cmd_w), File::from_raw_fd(rep_r))
        };
        let mut b = Browser {
            child,
            to_browser,
            from_browser: BufReader::new(from_browser),
            next_id: 0,
            session: String::new(),
            events: Vec::new(),
            _profile: profile,
        };
        let target = b.call_browser("Target.createTarget", json!({"url": "about:blank"}));
        let target_id = target["targetId"].as_str().expect("targetId").to_string();
        let attached = b.call_browser(
            "Target.attachToTarget",
            json!({"targetId": target_id, "flatten": true}),
        );
        b.session = attached["sessionId"].as_str().expect("sessionId").into();
        b.call("Page.enable", json!({}));
        b.call("Runtime.enable", json!({}));
        b.call(
            "Emulation.setDeviceMetricsOverride",
            json!({"width": width, "height": height, "deviceScaleFactor": 1, "mobile": false}),
        );
        Some(b)
    }

    fn send(&mut self, method: &str, params: Value, session: bool) -> u64 {
        self.next_id += 1;
        let mut msg = json!({"id": self.next_id, "method": method, "params": params});
        if session {
            msg["sessionId"] = json!(self.session);
        }
        let mut bytes = serde_json::to_vec(&msg).unwrap();
        bytes.push(0);
        self.to_browser
            .write_all(&bytes)
            .expect("write to Chromium");
        self.next_id
    }

    fn reply(&mut self, id: u64, method: &str) -> Value {
        loop {
            let mut buf = Vec::new();
            let n = self
                .from_browser
                .read_until(0, &mut buf)
                .expect("read from Chromium");
            assert!(n > 0, "Chromium closed the pipe while waiting for {method}");
            buf.pop();
            let msg: Value = serde_json::from_slice(&buf).expect("JSON from Chromium");
            if msg["id"].as_u64() == Some(id) {
                if let Some(err) = msg.get("error") {
                    panic!("{method}: {err}");
                }
                return msg["result"].clone();
            }
            if msg.get("method").is_some() {
                self.events.push(msg);
            }
        }
    }

    /// A browser-level command.
    pub fn call_browser(&mut self, method: &str, params: Value) -> Value {
        let id = self.send(method, params, false);
        self.reply(id, method)
    }

    /// A command to the page.
    pub fn call(&mut self, method: &str, params: Value) -> Value {
        let id = self.send(method, params, true);
        self.reply(id, method)
    }

    /// Evaluates `expr` in the page (promises awaited) and returns its value.
    pub fn eval(&mut self, expr: &str) -> Value {
        let r = self.call(
            "Runtime.evaluate",
            json!({"expression": expr, "returnByValue": true, "awaitPromise": true}),
        );
        if let Some(e) = r.get("exceptionDetails") {
            panic!("{expr}: {e}");
        }
        r["result"]["value"].clone()
    }

    /// Polls `expr` until it is `true` (panics after `timeout`).
    pub fn wait_for(&mut self, expr: &str, timeout: Duration) {
        let start = Instant::now();
        while self.eval(expr) != json!(true) {
            assert!(start.elapsed() < timeout, "timed out waiting for {expr}");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    pub fn navigate(&mut self, path: &Path) {
        let url = format!("file://{}", path.canonicalize().unwrap().display());
        self.call("Page.navigate", json!({"url": url}));
    }

    /// A PNG screenshot of the viewport, decoded to RGB.
    pub fn screenshot(&mut self) -> image::RgbImage {
        let r = self.call("Page.captureScreenshot", json!({"format": "png"}));
        let bytes = base64_decode(r["data"].as_str().expect("screenshot data"));
        image::load_from_memory(&bytes).unwrap().to_rgb8()
    }

    fn mouse(&mut self, kind: &str, x: f64, y: f64, extra: Value) {
        let mut p = json!({"type": kind, "x": x, "y": y});
        for (k, v) in extra.as_object().unwrap() {
            p[k] = v.clone();
        }
        self.call("Input.dispatchMouseEvent", p);
    }

    /// One notch of the mouse wheel at (x, y) (`delta_y` < 0 zooms in on the page).
    pub fn wheel(&mut self, x: f64, y: f64, delta_y: f64) {
        self.mouse("mouseWheel", x, y, json!({"deltaX": 0, "deltaY": delta_y}));
    }

    /// Left-button drag from `from` to `to` in `steps` moves.
    pub fn drag(&mut self, from: (f64, f64), to: (f64, f64), steps: usize) {
        self.mouse("mouseMoved", from.0, from.1, json!({}));
        self.mouse(
            "mousePressed",
            from.0,
            from.1,
            json!({"button": "left", "buttons": 1, "clickCount": 1}),
        );
        for k in 1..=steps {
            let t = k as f64 / steps as f64;
            let (x, y) = (from.0 + t * (to.0 - from.0), from.1 + t * (to.1 - from.1));
            self.mouse("mouseMoved", x, y, json!({"button": "left", "buttons": 1}));
        }
        self.mouse(
            "mouseReleased",
            to.0,
            to.1,
            json!({"button": "left", "buttons": 0, "clickCount": 1}),
        );
    }

    /// A left click at (x, y).
    pub fn click(&mut self, x: f64, y: f64) {
        self.mouse("mouseMoved", x, y, json!({}));
        self.mouse(
            "mousePressed",
            x,
            y,
            json!({"button": "left", "buttons": 1, "clickCount": 1}),
        );
        self.mouse(
            "mouseReleased",
            x,
            y,
            json!({"button": "left", "buttons": 0, "clickCount": 1}),
        );
    }

    /// The centre of the element `selector`, page coordinates.
    pub fn centre_of(&mut self, selector: &str) -> (f64, f64) {
        let r = self.eval(&format!(
            "(() => {{ const r = document.querySelector({selector:?}).getBoundingClientRect(); return [r.left + r.width / 2, r.top + r.height / 2]; }})()"
        ));
        (r[0].as_f64().unwrap(), r[1].as_f64().unwrap())
    }

    /// Presses and releases a key (`key` as the DOM names it: "ArrowRight", "1", ...).
    pub fn key(&mut self, key: &str, code: &str, key_code: u32) {
        let text = if key.chars().count() == 1 { key } else { "" };
        for kind in ["keyDown", "keyUp"] {
            let mut p = json!({"type": kind, "key": key, "code": code,
                "windowsVirtualKeyCode": key_code, "nativeVirtualKeyCode": key_code});
            if kind == "keyDown" && !text.is_empty() {
                p["text"] = json!(text);
            }
            self.call("Input.dispatchKeyEvent", p);
        }
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Standard base64 (the screenshots).
pub fn base64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| -> u32 {
        match c {
            b'A'..=b'Z' => (c - b'A') as u32,
            b'a'..=b'z' => (c - b'a' + 26) as u32,
            b'0'..=b'9' => (c - b'0' + 52) as u32,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("not base64: {c}"),
        }
    };
    let bytes: Vec<u8> = s
        .bytes()
        .filter(|c| *c != b'=' && !c.is_ascii_whitespace())
        .collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut n = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            n |= val(c) << (18 - 6 * i);
        }
        for i in 0..chunk.len().saturating_sub(1) {
            out.push((n >> (16 - 8 * i)) as u8);
        }
    }
    out
}

/// Whether the browser tests should run; prints why not.
pub fn browser_or_skip(test: &str, width: u32, height: u32) -> Option<Browser> {
    let b = Browser::launch(width, height);
    if b.is_none() {
        skip::skip(
            test,
            "no Chromium found (install the Debian packages chromium and chromium-driver, or set QC_CHROMIUM)",
        );
    }
    b
}
