//! Minimal `.npy` header parsing (NumPy format versions 1–3), used to memory-map frame stacks
//! without reading them.

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
    }
}
