//! A real rig's measurements from disk: CSV or NumPy `.npy`, to `rows x channels` f64.
//!
//! - CSV: one row per pattern, one column per channel. Separator `,` (or `;`, tab, or blanks,
//!   detected from the first line). An optional first line of channel names (any field that is
//!   not a number makes it a header). `#` starts a comment to the end of the line; blank lines are
//!   skipped. Every value must be a finite number.
//! - NPY (format 1.0, 2.0, 3.0; read by [`helmholtz_proto::npy`]): dtypes float64, float32,
//!   int8/16/32/64, uint8/16/32/64 of either byte order, shape `(n,)` (one channel) or
//!   `(n, channels)`, C or Fortran order. A 3-D array `(n, height, width)` is a camera rig's
//!   frames ([`npy_frames`]), streamed a batch of rows at a time.
//!
//! Errors name the file and, for CSV, the line and column.

use std::path::Path;

use helmholtz_proto::npy;
use thiserror::Error;

/// Bucket values read from a file.
#[derive(Clone, Debug, PartialEq)]
pub struct Measurements {
    pub rows: usize,
    pub channels: usize,
    /// Channel names from a CSV header line, if there was one.
    pub names: Option<Vec<String>>,
    /// Row-major: `values[row * channels + channel]`.
    pub values: Vec<f64>,
}

/// Why a measurements file was refused.
#[derive(Debug, Error)]
pub enum MeasurementsError {
    #[error("{file}: {source}")]
    Io {
        file: String,
        source: std::io::Error,
    },
    #[error("{file}: line {line}: {message}")]
    Csv {
        file: String,
        line: usize,
        message: String,
    },
    #[error("{file}: not a usable .npy file: {message}")]
    Npy { file: String, message: String },
    #[error("{file}: {message}")]
    Empty { file: String, message: String },
}

/// Reads `path` as NPY (by the `.npy` extension or the NPY magic bytes) or else as CSV.
pub fn read_measurements(path: &Path) -> Result<Measurements, MeasurementsError> {
    let file = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| MeasurementsError::Io {
        file: file.clone(),
        source,
    })?;
    let is_npy = bytes.starts_with(NPY_MAGIC)
        || path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    if is_npy {
        parse_npy(&bytes, &file)
    } else {
        let text = std::str::from_utf8(&bytes).map_err(|e| MeasurementsError::Csv {
            file: file.clone(),
            line: 1 + bytes[..e.valid_up_to()]
                .iter()
                .filter(|&&b| b == b'\n')
                .count(),
            message: "not UTF-8 text (a binary file? .npy files need the .npy extension)".into(),
        })?;
        parse_csv(text, &file)
    }
}

#[derive(Clone, Copy)]
enum Separator {
    Char(char),
    Blanks,
}

fn split_fields(line: &str, sep: Separator) -> Vec<&str> {
    match sep {
        Separator::Char(c) => line.split(c).map(str::trim).collect(),
        Separator::Blanks => line.split_whitespace().collect(),
    }
}

fn parse_number(field: &str) -> Option<f64> {
    field.parse::<f64>().ok()
}

/// Parses CSV text (see the module docs); `file` names it in errors.
pub fn parse_csv(text: &str, file: &str) -> Result<Measurements, MeasurementsError> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let err = |line: usize, message: String| MeasurementsError::Csv {
        file: file.to_string(),
        line,
        message,
    };
    let mut sep = None;
    let mut names: Option<Vec<String>> = None;
    let mut channels = 0usize;
    let mut values = Vec::new();
    let mut rows = 0usize;
    for (idx, raw) in text.lines().enumerate() {
        let lineno = idx + 1;
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let sep = *sep.get_or_insert_with(|| {
            [',', ';', '\t']
                .into_iter()
                .find(|&c| line.contains(c))
                .map(Separator::Char)
                .unwrap_or(Separator::Blanks)
        });
        let fields = split_fields(line, sep);
        if channels == 0 {
            channels = fields.len();
            let numeric = fields.iter().all(|f| parse_number(f).is_some());
            if !numeric {
                let header: Vec<String> = fields
                    .iter()
                    .map(|f| f.trim_matches(['"', '\'']).trim().to_string())
                    .collect();
                if let Some(pos) = header.iter().position(|n| n.is_empty()) {
                    return Err(err(
                        lineno,
                        format!("header column {} has no name", pos + 1),
                    ));
                }
                names = Some(header);
                continue;
            }
        }
        if fields.len() != channels {
            return Err(err(
                lineno,
                format!(
                    "{} columns, but the first {} has {channels}",
                    fields.len(),
                    if names.is_some() {
                        "line (header)"
                    } else {
                        "row"
                    }
                ),
            ));
        }
        for (col, f) in fields.iter().enumerate() {
            match parse_number(f) {
                Some(v) if v.is_finite() => values.push(v),
                Some(_) => {
                    return Err(err(
                        lineno,
                        format!("column {}: {f:?} is not a finite number", col + 1),
                    ));
                }
                None if f.is_empty() => {
                    return Err(err(lineno, format!("column {}: empty value", col + 1)));
                }
                None => {
                    return Err(err(
                        lineno,
                        format!("column {}: {f:?} is not a number", col + 1),
                    ));
                }
            }
        }
        rows += 1;
    }
    if rows == 0 {
        return Err(MeasurementsError::Empty {
            file: file.to_string(),
            message: "no data rows (only blank lines, comments or a header)".into(),
        });
    }
    Ok(Measurements {
        rows,
        channels,
        names,
        values,
    })
}

/// Writes `rows x channels` values as CSV with a header line of channel names.
pub fn to_csv(names: &[String], values: &[f64]) -> String {
    let channels = names.len();
    let mut out = names.join(",");
    out.push('\n');
    for row in values.chunks(channels) {
        let line: Vec<String> = row.iter().map(|v| format!("{v}")).collect();
        out.push_str(&line.join(","));
        out.push('\n');
    }
    out
}

const NPY_MAGIC: &[u8] = b"\x93NUMPY";

/// Parses NPY bytes (see the module docs); `file` names it in errors.
pub fn parse_npy(bytes: &[u8], file: &str) -> Result<Measurements, MeasurementsError> {
    let err = |message: String| MeasurementsError::Npy {
        file: file.to_string(),
        message,
    };
    let header = npy::read_header(&mut &bytes[..]).map_err(|e| err(e.to_string()))?;
    let shape = header.shape_text();
    let (rows, channels) = match header.shape.as_slice() {
        &[n] => (n, 1),
        &[n, c] => (n, c),
        [] => return Err(err("a scalar, not an array of bucket values".into())),
        s => {
            return Err(err(format!(
                "shape {shape} has {} dimensions; expected (rows,) or (rows, channels)",
                s.len()
            )));
        }
    };
    if rows == 0 || channels == 0 {
        return Err(err(format!("shape {shape} holds no values")));
    }
    let (rows, channels) = (
        usize::try_from(rows).map_err(|_| err(format!("shape {shape} overflows")))?,
        usize::try_from(channels).map_err(|_| err(format!("shape {shape} overflows")))?,
    );
    // Values in C order (a Fortran-ordered file is transposed): values[row * channels + col].
    let (_, values) = npy::decode_f64(bytes).map_err(|e| err(e.to_string()))?;
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(err(format!(
            "value at row {}, channel {} is not finite ({})",
            i / channels,
            i % channels,
            values[i]
        )));
    }
    Ok(Measurements {
        rows,
        channels,
        names: None,
        values,
    })
}

/// NPY 1.0 bytes of a little-endian float64 array of shape `(rows,)` (one channel) or
/// `(rows, channels)` ([`helmholtz_proto::npy::write_f64`]).
pub fn to_npy_f64(rows: usize, channels: usize, values: &[f64]) -> Vec<u8> {
    if channels == 1 {
        npy::write_f64(&[rows as u64], values)
    } else {
        npy::write_f64(&[rows as u64, channels as u64], values)
    }
}

/// A camera rig's frames in an NPY file of shape (rows, height, width), uint16 or float32 (either
/// byte order, C order), read a batch of rows at a time ([`helmholtz_proto::npy::NpyReader`]).
#[derive(Debug, Clone)]
pub struct NpyFrames {
    pub path: std::path::PathBuf,
    pub rows: u64,
    pub height: u32,
    pub width: u32,
    pub format: crate::upload::SampleFormat,
}

impl NpyFrames {
    /// Frames `start..end`.
    pub fn read(&self, start: u64, end: u64) -> anyhow::Result<crate::upload::SampleBuf> {
        let context = |e: npy::NpyError| {
            anyhow::anyhow!(
                "{}: reading frames {start}..{end}: {e}",
                self.path.display()
            )
        };
        let file = std::fs::File::open(&self.path)
            .map_err(|e| anyhow::anyhow!("{}: {e}", self.path.display()))?;
        let mut reader = npy::NpyReader::new(std::io::BufReader::new(file)).map_err(context)?;
        reader.seek_row(start).map_err(context)?;
        let rows = end.saturating_sub(start);
        Ok(match self.format {
            crate::upload::SampleFormat::U16 => {
                crate::upload::SampleBuf::U16(reader.read_rows_u16(rows).map_err(context)?)
            }
            _ => crate::upload::SampleBuf::F32(reader.read_rows_f32(rows).map_err(context)?),
        })
    }
}

/// `Some` when `path` is an NPY file holding a 3-D array (camera frames); `None` for anything
/// else (CSV, 1-D or 2-D NPY: bucket rows, and NPY files whose header does not read, which
/// [`read_measurements`] then refuses saying why). A 3-D array of another dtype is an error.
pub fn npy_frames(path: &Path) -> anyhow::Result<Option<NpyFrames>> {
    if path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.eq_ignore_ascii_case("npy"))
        != Some(true)
    {
        return Ok(None);
    }
    let file = std::fs::File::open(path).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    let size = file.metadata()?.len();
    let header = match npy::read_header(&mut std::io::BufReader::new(file)) {
        Ok(header) => header,
        Err(_) => return Ok(None),
    };
    let &[rows, height, width] = header.shape.as_slice() else {
        return Ok(None);
    };
    let format = match (header.dtype.kind, header.dtype.size) {
        (npy::Kind::Uint, 2) => crate::upload::SampleFormat::U16,
        (npy::Kind::Float, 4) => crate::upload::SampleFormat::F32,
        _ => anyhow::bail!(
            "{}: camera frames must be uint16 or float32, got dtype {:?}",
            path.display(),
            header.dtype.descr()
        ),
    };
    anyhow::ensure!(
        !header.fortran_order,
        "{}: save the frames in C order",
        path.display()
    );
    anyhow::ensure!(
        height > 0 && width > 0 && height <= u32::MAX as u64 && width <= u32::MAX as u64,
        "{}: frames of shape ({height}, {width})",
        path.display()
    );
    header
        .check_data_len(size.saturating_sub(header.data_offset), false)
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok(Some(NpyFrames {
        path: path.to_path_buf(),
        rows,
        height: height as u32,
        width: width as u32,
        format,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn npy(descr: &str, fortran: bool, shape: &str, data: &[u8]) -> Vec<u8> {
        let header = format!(
            "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}\n",
            if fortran { "True" } else { "False" }
        );
        let mut out = NPY_MAGIC.to_vec();
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(data);
        out
    }

    #[test]
    fn csv_with_header_comments_and_blank_lines() {
        let text = "\u{feff}# rig 3, run 2\nn, e ,\"s\"\n1,2,3\n\n4.5,-5e-1,6 # note\n";
        let m = parse_csv(text, "run.csv").unwrap();
        assert_eq!(m.rows, 2);
        assert_eq!(m.channels, 3);
        assert_eq!(
            m.names.as_deref(),
            Some(&["n".to_string(), "e".into(), "s".into()][..])
        );
        assert_eq!(m.values, vec![1.0, 2.0, 3.0, 4.5, -0.5, 6.0]);
    }

    #[test]
    fn csv_separators() {
        for text in ["1;2\n3;4\n", "1\t2\n3\t4\n", "1 2\n  3   4\n"] {
            let m = parse_csv(text, "x.csv").unwrap();
            assert_eq!(
                (m.rows, m.channels, m.values.clone()),
                (2, 2, vec![1.0, 2.0, 3.0, 4.0])
            );
            assert!(m.names.is_none());
        }
        let m = parse_csv("0.5\n1.5\n2.5", "one.csv").unwrap();
        assert_eq!((m.rows, m.channels), (3, 1));
    }

    #[test]
    fn malformed_csv_says_where() {
        let cases = [
            ("a,b\n1,2\n3\n", "line 3", "1 columns"),
            ("1,2\n3,x\n", "line 2", "column 2: \"x\" is not a number"),
            ("1,2\n3,\n", "line 2", "empty value"),
            ("1,2\n3,inf\n", "line 2", "not a finite number"),
            ("1,2\n3,NaN\n", "line 2", "not a finite number"),
            ("a,,c\n1,2,3\n", "line 1", "no name"),
        ];
        for (text, line, what) in cases {
            let e = parse_csv(text, "bad.csv").unwrap_err().to_string();
            assert!(e.starts_with("bad.csv: "), "{e}");
            assert!(e.contains(line) && e.contains(what), "{text:?}: {e}");
        }
        let e = parse_csv("# nothing\n\nbucket\n", "empty.csv")
            .unwrap_err()
            .to_string();
        assert!(e.contains("empty.csv") && e.contains("no data rows"), "{e}");
    }

    #[test]
    fn npy_round_trip_f64() {
        let values: Vec<f64> = (0..12).map(|v| v as f64 * 0.5 - 2.0).collect();
        let m = parse_npy(&to_npy_f64(6, 2, &values), "a.npy").unwrap();
        assert_eq!((m.rows, m.channels), (6, 2));
        assert_eq!(m.values, values);
        let m = parse_npy(&to_npy_f64(12, 1, &values), "a.npy").unwrap();
        assert_eq!((m.rows, m.channels), (12, 1));
        // Header padded to a multiple of 64 bytes as NumPy does.
        let bytes = to_npy_f64(12, 1, &values);
        assert_eq!((bytes.len() - 12 * 8) % 64, 0);
    }

    #[test]
    fn npy_dtypes_and_orders() {
        let f32s: Vec<u8> = [1.5f32, -2.0, 3.25]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        assert_eq!(
            parse_npy(&npy("<f4", false, "(3,)", &f32s), "x")
                .unwrap()
                .values,
            [1.5, -2.0, 3.25]
        );
        let i16s: Vec<u8> = [-3i16, 7, 30000]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        assert_eq!(
            parse_npy(&npy("<i2", false, "(3,)", &i16s), "x")
                .unwrap()
                .values,
            [-3.0, 7.0, 30000.0]
        );
        let u16s: Vec<u8> = [65535u16, 0, 1]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        assert_eq!(
            parse_npy(&npy("<u2", false, "(3,)", &u16s), "x")
                .unwrap()
                .values,
            [65535.0, 0.0, 1.0]
        );
        let i32s: Vec<u8> = [-70000i32, 5]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        assert_eq!(
            parse_npy(&npy("<i4", false, "(2,)", &i32s), "x")
                .unwrap()
                .values,
            [-70000.0, 5.0]
        );
        let be: Vec<u8> = [1.0f64, 2.0].iter().flat_map(|v| v.to_be_bytes()).collect();
        assert_eq!(
            parse_npy(&npy(">f8", false, "(2,)", &be), "x")
                .unwrap()
                .values,
            [1.0, 2.0]
        );
        // Fortran order (3 rows x 2 channels), column by column.
        let f: Vec<u8> = [1.0f64, 2.0, 3.0, 10.0, 20.0, 30.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let m = parse_npy(&npy("<f8", true, "(3, 2)", &f), "x").unwrap();
        assert_eq!(m.values, [1.0, 10.0, 2.0, 20.0, 3.0, 30.0]);
        // Version 2.0 header.
        let mut v2 = npy("<f8", false, "(2,)", &be);
        v2[6] = 2;
        let len = u16::from_le_bytes([v2[8], v2[9]]) as u32;
        v2.splice(8..10, len.to_le_bytes());
        assert_eq!(
            parse_npy(&v2, "x").unwrap().values,
            [1.0, 2.0].map(|v: f64| f64::from_le_bytes(v.to_be_bytes()))
        );
    }

    #[test]
    fn malformed_npy_says_why() {
        let eight: Vec<u8> = 1.0f64.to_le_bytes().to_vec();
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (b"NUMPY".to_vec(), "magic"),
            (
                npy("<f8", false, "(2,)", &eight),
                "needs 16 bytes of data, the file has 8",
            ),
            (npy("<c16", false, "(1,)", &[0; 16]), "not supported"),
            (npy("|O", false, "(1,)", &eight), "object arrays"),
            (npy("<f8", false, "(1, 1, 1)", &eight), "3 dimensions"),
            (npy("<f8", false, "()", &eight), "scalar"),
            (npy("<f8", false, "(0,)", &[]), "no values"),
            (
                npy("<f8", false, "(1,)", &f64::NAN.to_le_bytes()),
                "row 0, channel 0 is not finite",
            ),
        ];
        for (bytes, what) in cases {
            let e = parse_npy(&bytes, "rig.npy").unwrap_err().to_string();
            assert!(e.starts_with("rig.npy: "), "{e}");
            assert!(e.contains(what), "expected {what:?} in {e}");
        }
        let mut truncated = npy("<f8", false, "(1,)", &eight);
        truncated.truncate(20);
        assert!(
            parse_npy(&truncated, "t.npy")
                .unwrap_err()
                .to_string()
                .contains("shorter")
        );
    }

    #[test]
    fn read_measurements_dispatches_on_content() {
        let dir = tempfile::tempdir().unwrap();
        let csv = dir.path().join("m.csv");
        std::fs::write(&csv, "bucket\n1\n2\n").unwrap();
        assert_eq!(read_measurements(&csv).unwrap().values, [1.0, 2.0]);
        let npy_path = dir.path().join("m.dat");
        std::fs::write(&npy_path, to_npy_f64(2, 1, &[3.0, 4.0])).unwrap();
        assert_eq!(read_measurements(&npy_path).unwrap().values, [3.0, 4.0]);
        let missing = dir.path().join("nope.csv");
        let e = read_measurements(&missing).unwrap_err().to_string();
        assert!(e.contains("nope.csv"), "{e}");
    }

    #[test]
    fn csv_writer_round_trips() {
        let names = vec!["a".to_string(), "b".to_string()];
        let values = [1.0, 2.5, -3.0, 1e-300];
        let m = parse_csv(&to_csv(&names, &values), "w.csv").unwrap();
        assert_eq!(m.values, values);
        assert_eq!(m.names, Some(names));
    }

    fn npy3(descr: &str, shape: &str, payload: &[u8]) -> Vec<u8> {
        let mut header =
            format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
        let total = 10 + header.len() + 1;
        header.push_str(&" ".repeat(total.next_multiple_of(64) - total));
        header.push('\n');
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(payload);
        out
    }

    #[test]
    fn three_d_npy_files_are_camera_frames_read_in_batches() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.npy");
        let values: Vec<u16> = (0..3 * 2 * 4).map(|v| v as u16 * 1000).collect();
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(&path, npy3("<u2", "(3, 2, 4)", &bytes)).unwrap();
        let f = npy_frames(&path).unwrap().expect("3-D is frames");
        assert_eq!(
            (f.rows, f.height, f.width, f.format),
            (3, 2, 4, crate::upload::SampleFormat::U16)
        );
        match f.read(1, 3).unwrap() {
            crate::upload::SampleBuf::U16(v) => assert_eq!(v, values[8..].to_vec()),
            other => panic!("{other:?}"),
        }
        // 2-D arrays are bucket rows; other dtypes and short files are errors.
        std::fs::write(&path, npy3("<f8", "(3, 2)", &[0u8; 48])).unwrap();
        assert!(npy_frames(&path).unwrap().is_none());
        std::fs::write(&path, npy3("<f8", "(3, 2, 4)", &[0u8; 192])).unwrap();
        assert!(
            npy_frames(&path)
                .unwrap_err()
                .to_string()
                .contains("uint16 or float32")
        );
        std::fs::write(&path, npy3("<f4", "(3, 2, 4)", &[0u8; 50])).unwrap();
        assert!(npy_frames(&path).unwrap_err().to_string().contains("needs"));
    }
}
