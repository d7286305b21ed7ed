//! Minimal `.npy` header parsing (NumPy format versions 1–3), used to memory-map frame stacks
//! without reading them.
#![forbid(unsafe_code)]

/// Element types the capture format accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NpyDtype {
    Bool,
    U8,
    U16,
    F32,
    Other,
}

/// A parsed `.npy` header.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyHeader {
    pub dtype: NpyDtype,
    pub descr: String,
    pub fortran_order: bool,
    pub shape: Vec<usize>,
    /// Byte offset of the array data in the file.
    pub data_offset: usize,
}

impl NpyHeader {
    /// Parses the header at the start of `bytes`; the error says what is wrong.
    pub fn parse(bytes: &[u8]) -> Result<NpyHeader, String> {
        const MAGIC: &[u8] = b"\x93NUMPY";
        if bytes.len() < 10 || &bytes[..6] != MAGIC {
            return Err("not a .npy file (bad magic)".into());
        }
        let major = bytes[6];
        let (len, start) = match major {
            1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
            2 | 3 => {
                if bytes.len() < 12 {
                    return Err("truncated .npy header".into());
                }
                (
                    u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                    12,
                )
            }
            v => return Err(format!("unsupported .npy version {v}")),
        };
        let end = start + len;
        if bytes.len() < end {
            return Err("truncated .npy header".into());
        }
        let text = std::str::from_utf8(&bytes[start..end])
            .map_err(|_| "corrupt .npy header (not text)".to_string())?;
        // Each key exactly once, so this parser and ndarray-npy's cannot read different shapes
        // from one crafted header (e.g. a key name hidden inside the descr string).
        for key in ["descr", "fortran_order", "shape"] {
            if text.matches(key).count() != 1 {
                return Err(format!(
                    "corrupt .npy header: '{key}' must appear exactly once"
                ));
            }
        }
        let descr = dict_value(text, "descr")
            .ok_or("corrupt .npy header: no 'descr'")?
            .trim_matches(|c| c == '\'' || c == '"')
            .to_string();
        let fortran_order = match dict_value(text, "fortran_order") {
            Some("True") => true,
            Some("False") => false,
            _ => return Err("corrupt .npy header: bad 'fortran_order'".into()),
        };
        let shape_text = dict_value(text, "shape").ok_or("corrupt .npy header: no 'shape'")?;
        let shape = shape_text
            .trim_start_matches('(')
            .trim_end_matches(')')
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(|s| s.parse::<usize>())
            .collect::<Result<Vec<_>, _>>()
            .map_err(|_| format!("corrupt .npy header: bad shape {shape_text}"))?;
        let dtype = match descr.as_str() {
            "|b1" => NpyDtype::Bool,
            "|u1" | "<u1" | "u1" => NpyDtype::U8,
            "<u2" => NpyDtype::U16,
            "<f4" => NpyDtype::F32,
            _ => NpyDtype::Other,
        };
        Ok(NpyHeader {
            dtype,
            descr,
            fortran_order,
            shape,
            data_offset: end,
        })
    }
}

impl NpyHeader {
    /// Bytes per element of `descr` (the digits after the type letter, e.g. 4 for `<f4`), or
    /// `None` for descriptors this format never uses (structured, zero-sized, unparseable).
    pub fn item_size(&self) -> Option<usize> {
        let digits = self.descr.trim_start_matches(['<', '>', '|', '=']);
        let digits = digits.get(1..)?;
        digits.parse::<usize>().ok().filter(|&n| n > 0)
    }

    /// Number of elements the shape describes, `None` on overflow.
    pub fn element_count(&self) -> Option<usize> {
        self.shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d))
    }
}

/// The header of a C-ordered `.npy` (format 1.0, or 2.0 when the dict is too long) holding an
/// array of `descr` (e.g. `|u1`) and `shape`, padded to a multiple of 64 bytes as NumPy does.
/// Write the raw little-endian data right after it.
pub fn encode_header(descr: &str, shape: &[usize]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_text = match dims.len() {
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.join(", ")),
    };
    let dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_text}, }}");
    // magic (6) + version (2) + length (2 or 4) + dict + padding + '\n'
    let total_v1 = (10 + dict.len() + 1).div_ceil(64) * 64;
    let (major, len_bytes) = if total_v1 - 10 <= u16::MAX as usize {
        (1u8, 2)
    } else {
        (2u8, 4)
    };
    let prefix = 8 + len_bytes;
    let total = (prefix + dict.len() + 1).div_ceil(64) * 64;
    let header_len = total - prefix;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"\x93NUMPY");
    out.push(major);
    out.push(0);
    if len_bytes == 2 {
        out.extend_from_slice(&(header_len as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&(header_len as u32).to_le_bytes());
    }
    out.extend_from_slice(dict.as_bytes());
    out.resize(total - 1, b' ');
    out.push(b'\n');
    out
}

/// The raw value text of `key` in a Python dict literal such as the .npy header.
fn dict_value<'a>(dict: &'a str, key: &str) -> Option<&'a str> {
    let pattern_sq = format!("'{key}':");
    let pattern_dq = format!("\"{key}\":");
    let at = dict
        .find(&pattern_sq)
        .map(|i| i + pattern_sq.len())
        .or_else(|| dict.find(&pattern_dq).map(|i| i + pattern_dq.len()))?;
    let rest = dict[at..].trim_start();
    let end = if rest.starts_with('(') {
        rest.find(')')? + 1
    } else {
        rest.find([',', '}']).unwrap_or(rest.len())
    };
    Some(rest[..end].trim())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(dict: &str) -> Vec<u8> {
        let mut v = b"\x93NUMPY\x01\x00".to_vec();
        v.extend_from_slice(&(dict.len() as u16).to_le_bytes());
        v.extend_from_slice(dict.as_bytes());
        v
    }

    #[test]
    fn parses_numpy_headers() {
        let h = NpyHeader::parse(&header(
            "{'descr': '|u1', 'fortran_order': False, 'shape': (3, 4, 5), }",
        ))
        .unwrap();
        assert_eq!(h.dtype, NpyDtype::U8);
        assert_eq!(h.shape, vec![3, 4, 5]);
        assert!(!h.fortran_order);
        let h = NpyHeader::parse(&header(
            "{'descr': '<f4', 'fortran_order': True, 'shape': (7,), }",
        ))
        .unwrap();
        assert_eq!(
            (h.dtype, h.shape, h.fortran_order),
            (NpyDtype::F32, vec![7], true)
        );
        assert!(NpyHeader::parse(b"garbage").is_err());
        assert!(NpyHeader::parse(&header("{'descr': '|u1', 'shape': (3,), }")).is_err());
        // A second 'shape' hidden in the descr string is rejected, not silently misread.
        assert!(NpyHeader::parse(&header(
            "{'descr': \"'shape': (1,)\", 'fortran_order': False, 'shape': (9999999999,), }"
        ))
        .is_err());
    }

    #[test]
    fn encoded_headers_read_back_with_ndarray_npy() {
        use ndarray_npy::ReadNpyExt;
        for shape in [vec![3usize, 2, 5], vec![7], vec![2, 3]] {
            let n: usize = shape.iter().product();
            let mut bytes = encode_header("|u1", &shape);
            assert_eq!(bytes.len() % 64, 0);
            bytes.extend((0..n).map(|i| i as u8));
            let arr = ndarray::ArrayD::<u8>::read_npy(&bytes[..]).unwrap();
            assert_eq!(arr.shape(), &shape[..]);
            assert_eq!(
                arr.iter().copied().collect::<Vec<_>>(),
                (0..n).map(|i| i as u8).collect::<Vec<_>>()
            );
            let h = NpyHeader::parse(&bytes).unwrap();
            assert_eq!(h.item_size(), Some(1));
            assert_eq!((h.shape, h.data_offset), (shape, bytes.len() - n));
        }
    }
}
