//! Frame windows `A:B`: the frames a command reads from a capture or a raw recording
//! (`--frames` of `convert`, `reconstruct` and `align`).
#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::ops::Range;
use std::str::FromStr;

/// A half-open frame range `start:end` as written on the command line; either bound may be
/// omitted (`:B` = from the first frame, `A:` = to the last).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct FrameWindow {
    /// First frame (default 0).
    pub start: Option<usize>,
    /// One past the last frame (default: the number of frames).
    pub end: Option<usize>,
}

impl FrameWindow {
    /// The window as a range inside `0..frame_count`; an empty window or one that ends past
    /// the last frame is an error that says how many frames there are.
    pub fn resolve(&self, frame_count: usize) -> Result<Range<usize>> {
        let start = self.start.unwrap_or(0);
        let end = self.end.unwrap_or(frame_count);
        if end > frame_count {
            return Err(Error::invalid(format!(
                "frame window {self} ends past the last frame: there are {frame_count} frames"
            )));
        }
        if start >= end {
            return Err(Error::invalid(format!(
                "frame window {self} is empty ({frame_count} frames available)"
            )));
        }
        Ok(start..end)
    }
}

impl fmt::Display for FrameWindow {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let show = |v: Option<usize>| v.map(|n| n.to_string()).unwrap_or_default();
        write!(f, "{}:{}", show(self.start), show(self.end))
    }
}

impl FromStr for FrameWindow {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        let bad = || {
            Error::invalid(format!(
                "frame window {s:?} must be A:B, A: or :B with frame numbers A < B"
            ))
        };
        let (a, b) = s.split_once(':').ok_or_else(bad)?;
        let parse = |t: &str| -> Result<Option<usize>> {
            let t = t.trim();
            if t.is_empty() {
                Ok(None)
            } else {
                t.parse::<usize>().map(Some).map_err(|_| bad())
            }
        };
        let window = FrameWindow {
            start: parse(a)?,
            end: parse(b)?,
        };
        if let (Some(a), Some(b)) = (window.start, window.end) {
            if a >= b {
                return Err(bad());
            }
        }
        Ok(window)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_resolves_windows() {
        let w: FrameWindow = "10:20".parse().unwrap();
        assert_eq!(w.resolve(100).unwrap(), 10..20);
        assert_eq!(w.to_string(), "10:20");
        assert_eq!(
            ":5".parse::<FrameWindow>().unwrap().resolve(9).unwrap(),
            0..5
        );
        assert_eq!(
            "7:".parse::<FrameWindow>().unwrap().resolve(9).unwrap(),
            7..9
        );
        assert_eq!(
            ":".parse::<FrameWindow>().unwrap().resolve(9).unwrap(),
            0..9
        );
        for bad in ["", "5", "5:5", "6:2", "a:3", "-1:3", "1:2:3"] {
            assert!(bad.parse::<FrameWindow>().is_err(), "{bad:?}");
        }
        assert!(w.resolve(15).is_err());
        assert!("9:".parse::<FrameWindow>().unwrap().resolve(9).is_err());
    }
}
