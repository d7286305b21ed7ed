//! Raw recordings split over many files: listing them in natural path order and reading
//! fixed-size frames across file boundaries, one frame in memory at a time.
#![forbid(unsafe_code)]

use crate::error::{Error, Result};
use std::cmp::Ordering;
use std::fs::{self, File};
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Component, Path, PathBuf};

/// Natural order of two strings: runs of ASCII digits compare as numbers (`2` < `10`), other
/// characters compare as bytes; equal numbers with more leading zeros sort after fewer (so the
/// order is total and `a01` and `a1` keep a fixed order).
pub fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        if a[i].is_ascii_digit() && b[j].is_ascii_digit() {
            let (si, sj) = (i, j);
            while i < a.len() && a[i].is_ascii_digit() {
                i += 1;
            }
            while j < b.len() && b[j].is_ascii_digit() {
                j += 1;
            }
            let (na, nb) = (&a[si..i], &b[sj..j]);
            let strip = |n: &[u8]| {
                let k = n.iter().take_while(|&&c| c == b'0').count();
                n[k..].to_vec()
            };
            let (ta, tb) = (strip(na), strip(nb));
            let ord = ta
                .len()
                .cmp(&tb.len())
                .then_with(|| ta.cmp(&tb))
                .then_with(|| na.len().cmp(&nb.len()));
            if ord != Ordering::Equal {
                return ord;
            }
        } else {
            if a[i] != b[j] {
                return a[i].cmp(&b[j]);
            }
            i += 1;
            j += 1;
        }
    }
    (a.len() - i).cmp(&(b.len() - j))
}

/// Natural order of two relative paths, component by component (a directory's files stay
/// together: `2/9.bin` < `10/0.bin`, `0/2.bin` < `0/10.bin`).
pub fn natural_path_cmp(a: &Path, b: &Path) -> Ordering {
    let parts = |p: &Path| -> Vec<String> {
        p.components()
            .filter_map(|c| match c {
                Component::Normal(s) => Some(s.to_string_lossy().into_owned()),
                _ => None,
            })
            .collect()
    };
    let (pa, pb) = (parts(a), parts(b));
    for (x, y) in pa.iter().zip(&pb) {
        let ord = natural_cmp(x, y);
        if ord != Ordering::Equal {
            return ord;
        }
    }
    pa.len().cmp(&pb.len())
}

/// Every file under `input` (itself, if it is a file) whose extension is `ext` (case
/// insensitive), in natural path order. Directories are searched recursively; symbolic links
/// to directories are not followed. No matching file is an error naming `input`.
pub fn list_files(input: &Path, ext: &str) -> Result<Vec<PathBuf>> {
    let info = fs::metadata(input).map_err(|e| Error::io(input, e))?;
    if info.is_file() {
        return Ok(vec![input.to_path_buf()]);
    }
    let mut found = Vec::new();
    let mut stack = vec![input.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in fs::read_dir(&dir).map_err(|e| Error::io(&dir, e))? {
            let entry = entry.map_err(|e| Error::io(&dir, e))?;
            let path = entry.path();
            let kind = entry.file_type().map_err(|e| Error::io(&path, e))?;
            if kind.is_dir() {
                stack.push(path);
            } else if path
                .extension()
                .is_some_and(|e| e.to_string_lossy().eq_ignore_ascii_case(ext))
            {
                found.push(path);
            }
        }
    }
    if found.is_empty() {
        return Err(Error::format(
            input,
            format!("no .{ext} files found (searched every subdirectory)"),
        ));
    }
    found.sort_by(|a, b| {
        natural_path_cmp(
            a.strip_prefix(input).unwrap_or(a),
            b.strip_prefix(input).unwrap_or(b),
        )
    });
    Ok(found)
}

/// How frames sit in each file of a recording.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FileLayout {
    /// Bytes of one raw frame.
    pub frame_bytes: usize,
    /// Frames every file must hold; `None` = any whole number >= 1.
    pub frames_per_file: Option<usize>,
    /// Bytes after the last frame of every file (ignored).
    pub trailer_bytes: usize,
    /// Name of the format, for error messages.
    pub format: &'static str,
}

#[derive(Debug, Clone)]
struct RawFile {
    path: PathBuf,
    first_frame: usize,
}

/// The frames of a list of raw files, read in order, one frame at a time.
#[derive(Debug)]
pub struct RawFileSet {
    layout: FileLayout,
    files: Vec<RawFile>,
    frame_count: usize,
    open: Option<(usize, BufReader<File>, u64)>,
}

impl RawFileSet {
    /// Checks every file's size against `layout` and that it can be opened; the first file
    /// that does not fit is an error naming it and saying what size was expected.
    pub fn new(paths: Vec<PathBuf>, layout: FileLayout) -> Result<RawFileSet> {
        if layout.frame_bytes == 0 {
            return Err(Error::invalid("raw frames cannot be 0 bytes"));
        }
        let mut files = Vec::with_capacity(paths.len());
        let mut next = 0usize;
        for path in paths {
            let size = fs::metadata(&path).map_err(|e| Error::io(&path, e))?.len();
            File::open(&path).map_err(|e| Error::io(&path, e))?;
            let frames = frames_in(size, &layout).map_err(|m| Error::format(&path, m))?;
            files.push(RawFile {
                path,
                first_frame: next,
            });
            next = next
                .checked_add(frames)
                .ok_or_else(|| Error::invalid("too many frames"))?;
        }
        Ok(RawFileSet {
            layout,
            files,
            frame_count: next,
            open: None,
        })
    }

    /// Total number of frames.
    pub fn frame_count(&self) -> usize {
        self.frame_count
    }

    /// Number of files.
    pub fn file_count(&self) -> usize {
        self.files.len()
    }

    /// The files in reading order.
    pub fn paths(&self) -> impl Iterator<Item = &Path> {
        self.files.iter().map(|f| f.path.as_path())
    }

    /// Reads raw frame `t` into `buf` (`frame_bytes` long). Sequential reads stream through
    /// each file without seeking.
    pub fn read_raw(&mut self, t: usize, buf: &mut [u8]) -> Result<()> {
        if t >= self.frame_count || buf.len() != self.layout.frame_bytes {
            return Err(Error::invalid(format!(
                "raw frame {t} of {} requested into a {}-byte buffer",
                self.frame_count,
                buf.len()
            )));
        }
        let idx = self.files.partition_point(|f| f.first_frame <= t) - 1;
        let file = &self.files[idx];
        let offset = ((t - file.first_frame) * self.layout.frame_bytes) as u64;
        let reopen = !matches!(&self.open, Some((i, _, _)) if *i == idx);
        if reopen {
            let f = File::open(&file.path).map_err(|e| Error::io(&file.path, e))?;
            self.open = Some((idx, BufReader::with_capacity(1 << 22, f), 0));
        }
        let (_, reader, pos) = self.open.as_mut().expect("opened above");
        if *pos != offset {
            reader
                .seek(SeekFrom::Start(offset))
                .map_err(|e| Error::io(&file.path, e))?;
        }
        reader.read_exact(buf).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                Error::format(
                    &file.path,
                    "file ended early (did it change while reading?)",
                )
            } else {
                Error::io(&file.path, e)
            }
        })?;
        *pos = offset + buf.len() as u64;
        Ok(())
    }
}

/// Frames in a file of `size` bytes, or why the size does not fit `layout`.
fn frames_in(size: u64, layout: &FileLayout) -> std::result::Result<usize, String> {
    let fb = layout.frame_bytes as u64;
    let trailer = layout.trailer_bytes as u64;
    let describe = || match layout.frames_per_file {
        Some(n) => format!(
            "{} frames x {} bytes{} = {} bytes",
            n,
            fb,
            trailer_note(trailer),
            n as u64 * fb + trailer
        ),
        None => format!(
            "a whole number of {fb}-byte frames{}",
            trailer_note(trailer)
        ),
    };
    if size == 0 {
        return Err(format!(
            "file is empty; a {} file holds {}",
            layout.format,
            describe()
        ));
    }
    let ok = size >= trailer + fb && {
        let rem = (size - trailer) % fb; // not is_multiple_of: rust-version is 1.80
        rem == 0
    };
    let frames = if ok {
        ((size - trailer) / fb) as usize
    } else {
        0
    };
    match layout.frames_per_file {
        Some(n) if ok && frames == n => Ok(n),
        None if ok => Ok(frames),
        _ => Err(format!(
            "{size} bytes does not fit a {} file ({}): truncated, padded or another format",
            layout.format,
            describe()
        )),
    }
}

fn trailer_note(trailer: u64) -> String {
    if trailer == 0 {
        String::new()
    } else {
        format!(" + a {trailer}-byte trailer")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_order_compares_numbers_by_value() {
        let mut v = vec![
            "10.bin", "2.bin", "1.bin", "a10", "a9", "a09", "b", "01.bin",
        ];
        v.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(
            v,
            ["1.bin", "01.bin", "2.bin", "10.bin", "a9", "a09", "a10", "b"]
        );
        assert_eq!(
            natural_path_cmp(Path::new("2/9.bin"), Path::new("10/0.bin")),
            Ordering::Less
        );
        assert_eq!(
            natural_path_cmp(Path::new("0/10.bin"), Path::new("0/2.bin")),
            Ordering::Greater
        );
    }

    #[test]
    fn file_sizes_are_checked() {
        let layout = FileLayout {
            frame_bytes: 10,
            frames_per_file: Some(3),
            trailer_bytes: 0,
            format: "test",
        };
        assert_eq!(frames_in(30, &layout), Ok(3));
        assert!(frames_in(29, &layout).unwrap_err().contains("29 bytes"));
        assert!(frames_in(20, &layout).is_err());
        assert!(frames_in(0, &layout).unwrap_err().contains("empty"));
        let free = FileLayout {
            frames_per_file: None,
            trailer_bytes: 4,
            ..layout
        };
        assert_eq!(frames_in(24, &free), Ok(2));
        assert!(frames_in(20, &free).is_err());
        assert!(frames_in(4, &free).is_err());
    }
}
