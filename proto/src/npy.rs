//! NumPy `.npy` files, the one way through them for the service, the edge client and the tests.
//!
//! Reading is built on the `npyz` crate (header parsing, typed element reads of either byte
//! order); this module adds the house's rules and messages on top:
//!
//! - format versions 1.0, 2.0 and 3.0; dtypes float32/64, int8/16/32/64 and uint8/16/32/64 of
//!   either byte order; C or Fortran order; any number of dimensions (callers say which shapes
//!   they take);
//! - clear errors: no magic, an unsupported version, a header that is not a Python dict with
//!   `descr`, `fortran_order` and `shape`, object (pickled) arrays, structured dtypes, other
//!   dtypes, a file shorter than its header, data shorter (or, for whole in-memory arrays, longer)
//!   than the shape says;
//! - [`decode_f64`] / [`decode_f32`]: a whole in-memory array, values in C order (a Fortran-ordered
//!   array is transposed);
//! - [`NpyReader`]: the header, then rows streamed from any reader ([`NpyReader::seek_row`] on a
//!   seekable one), so a multi-gigabyte file is never loaded whole.
//!
//! Writing ([`header`], [`write_f32`], [`write_f64`]) produces format 1.0 (2.0 past a 64 KiB
//! header), little-endian, C order, the header `{'descr': '<f4', 'fortran_order': False, 'shape':
//! (h, w), }` padded with spaces to a multiple of 64 bytes and ended by `\n`, the shape written as
//! Python writes a tuple (`(n,)`, `(h, w)`). The header is written here rather than by `npyz`,
//! whose writer spells shapes `(h, w, )`: NumPy reads both, but these bytes are what the service
//! has always served and what clients may compare.

use std::fmt;
use std::io::{self, Read, Seek, SeekFrom};

use thiserror::Error;

const MAGIC: &[u8] = b"\x93NUMPY";

/// What kind of number an element is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Float,
    Int,
    Uint,
}

/// A plain numeric dtype: kind, size in bytes, byte order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dtype {
    pub kind: Kind,
    /// Bytes per element: 4 or 8 for floats, 1, 2, 4 or 8 for integers.
    pub size: u8,
    pub big_endian: bool,
}

impl Dtype {
    pub const F64: Dtype = Dtype::le(Kind::Float, 8);
    pub const F32: Dtype = Dtype::le(Kind::Float, 4);
    pub const U16: Dtype = Dtype::le(Kind::Uint, 2);
    pub const U8: Dtype = Dtype::le(Kind::Uint, 1);

    const fn le(kind: Kind, size: u8) -> Dtype {
        Dtype {
            kind,
            size,
            big_endian: false,
        }
    }

    /// The NumPy type string: `<f8`, `>i2`, `|u1` (one-byte types have no byte order).
    pub fn descr(&self) -> String {
        let order = if self.size == 1 {
            '|'
        } else if self.big_endian {
            '>'
        } else {
            '<'
        };
        let kind = match self.kind {
            Kind::Float => 'f',
            Kind::Int => 'i',
            Kind::Uint => 'u',
        };
        format!("{order}{kind}{}", self.size)
    }

    /// Parses a NumPy type string (`<f8`, `|u1`, `>i4`, ...) into one of the supported dtypes.
    pub fn parse(descr: &str) -> Result<Dtype, NpyError> {
        let ty: npyz::TypeStr = descr
            .parse()
            .map_err(|e| NpyError::Header(format!("cannot read dtype {descr:?}: {e}")))?;
        Dtype::from_type_str(&ty)
    }

    fn from_type_str(ty: &npyz::TypeStr) -> Result<Dtype, NpyError> {
        if ty.uses_pickled_array() {
            return Err(NpyError::Object);
        }
        let kind = match (ty.type_char(), ty.size_field()) {
            (npyz::TypeChar::Float, 4 | 8) => Kind::Float,
            (npyz::TypeChar::Int, 1 | 2 | 4 | 8) => Kind::Int,
            (npyz::TypeChar::Uint, 1 | 2 | 4 | 8) => Kind::Uint,
            _ => return Err(NpyError::Dtype(ty.to_string())),
        };
        Ok(Dtype {
            kind,
            size: ty.size_field() as u8,
            big_endian: ty.endianness() == npyz::Endianness::Big,
        })
    }
}

impl fmt::Display for Dtype {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.descr())
    }
}

/// An array's header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Header {
    pub dtype: Dtype,
    pub shape: Vec<u64>,
    pub fortran_order: bool,
    /// Bytes before the data: magic, version, header length and header text.
    pub data_offset: u64,
}

impl Header {
    /// The number of elements (1 for a scalar); `None` if it overflows.
    pub fn len(&self) -> Option<u64> {
        self.shape.iter().try_fold(1u64, |n, &d| n.checked_mul(d))
    }

    /// Whether the array holds no element.
    pub fn is_empty(&self) -> bool {
        self.shape.contains(&0)
    }

    /// Bytes of data the shape needs; `None` if it overflows.
    pub fn data_bytes(&self) -> Option<u64> {
        self.len()?.checked_mul(self.dtype.size as u64)
    }

    /// Elements in one row (one index of the first axis): the product of the other axes.
    pub fn row_len(&self) -> u64 {
        self.shape.iter().skip(1).product()
    }

    /// The shape as Python writes the tuple: `()`, `(n,)`, `(h, w)`.
    pub fn shape_text(&self) -> String {
        shape_text(&self.shape)
    }

    /// Checks that `available` bytes of data are what the shape needs (`exact`) or at least that.
    pub fn check_data_len(&self, available: u64, exact: bool) -> Result<(), NpyError> {
        let needs = self
            .data_bytes()
            .ok_or_else(|| NpyError::Overflow(self.shape_text()))?;
        if available < needs || (exact && available != needs) {
            return Err(NpyError::DataLength {
                shape: self.shape_text(),
                descr: self.dtype.descr(),
                needs,
                has: available,
            });
        }
        Ok(())
    }
}

/// Why an NPY file was refused.
#[derive(Debug, Error)]
pub enum NpyError {
    #[error("not an NPY file (missing the \\x93NUMPY magic bytes)")]
    Magic,
    #[error("truncated: the file is shorter than its header says")]
    TruncatedHeader,
    #[error("bad NPY header: {0}")]
    Header(String),
    #[error("object arrays (pickled Python objects) are not supported")]
    Object,
    #[error("dtype {0} is a structured/record dtype; save a plain numeric array")]
    Structured(String),
    #[error(
        "dtype {0:?} is not supported: use float64, float32 or an integer type (int8..int64, uint8..uint64)"
    )]
    Dtype(String),
    #[error("shape {0} overflows")]
    Overflow(String),
    #[error("shape {shape} of {descr} needs {needs} bytes of data, the file has {has}")]
    DataLength {
        shape: String,
        descr: String,
        needs: u64,
        has: u64,
    },
    #[error("truncated: the data ends before element {0} that the shape promises")]
    TruncatedData(u64),
    #[error("asked for elements past the end of the array ({asked} of {len})")]
    PastEnd { asked: u64, len: u64 },
    #[error("the rows of a Fortran-ordered array are not contiguous; save it in C order")]
    FortranRows,
    #[error("{0}")]
    Io(io::Error),
}

/// Reads `count` elements of whatever numeric dtype the file has, cast to `$t`.
macro_rules! read_as {
    ($self:ident, $count:expr, $t:ty) => {{
        let d = $self.header.dtype;
        Ok(match (d.kind, d.size) {
            (Kind::Float, 8) => cast!($self.pull::<f64>($count)?, $t),
            (Kind::Float, 4) => cast!($self.pull::<f32>($count)?, $t),
            (Kind::Int, 1) => cast!($self.pull::<i8>($count)?, $t),
            (Kind::Int, 2) => cast!($self.pull::<i16>($count)?, $t),
            (Kind::Int, 4) => cast!($self.pull::<i32>($count)?, $t),
            (Kind::Int, 8) => cast!($self.pull::<i64>($count)?, $t),
            (Kind::Uint, 1) => cast!($self.pull::<u8>($count)?, $t),
            (Kind::Uint, 2) => cast!($self.pull::<u16>($count)?, $t),
            (Kind::Uint, 4) => cast!($self.pull::<u32>($count)?, $t),
            (Kind::Uint, 8) => cast!($self.pull::<u64>($count)?, $t),
            _ => return Err(NpyError::Dtype(d.descr())),
        })
    }};
}

macro_rules! cast {
    ($values:expr, $t:ty) => {
        $values.into_iter().map(|v| v as $t).collect()
    };
}

/// The longest header read (NumPy itself refuses more than 10,000 bytes by default): a larger
/// length field is a damaged or hostile file, not something to allocate for.
pub const MAX_HEADER_LEN: usize = 1 << 20;

fn header_error(e: io::Error) -> NpyError {
    match e.kind() {
        io::ErrorKind::UnexpectedEof => NpyError::TruncatedHeader,
        io::ErrorKind::InvalidData if e.to_string().contains("magic") => NpyError::Magic,
        io::ErrorKind::InvalidData => NpyError::Header(e.to_string()),
        _ => NpyError::Io(e),
    }
}

/// Reads the header from `reader`, leaving it at the first byte of data.
pub fn read_header<R: Read>(reader: &mut R) -> Result<Header, NpyError> {
    read_raw_header(reader).map(|(h, _)| h)
}

fn read_raw_header<R: Read>(reader: &mut R) -> Result<(Header, npyz::NpyHeader), NpyError> {
    // The fixed prefix is read here, so that the length field is bounded before anything is
    // allocated for it and the data offset is known; npyz then parses the whole header.
    let mut bytes = vec![0u8; 10];
    reader.read_exact(&mut bytes).map_err(|e| match e.kind() {
        io::ErrorKind::UnexpectedEof => NpyError::Magic,
        _ => NpyError::Io(e),
    })?;
    if &bytes[..6] != MAGIC {
        return Err(NpyError::Magic);
    }
    let len = match bytes[6] {
        1 => u16::from_le_bytes([bytes[8], bytes[9]]) as usize,
        2 | 3 => {
            let mut rest = [0u8; 2];
            reader.read_exact(&mut rest).map_err(header_error)?;
            bytes.extend_from_slice(&rest);
            u32::from_le_bytes([bytes[8], bytes[9], rest[0], rest[1]]) as usize
        }
        major => {
            return Err(NpyError::Header(format!(
                "format version {major}.{} is not supported (1.0, 2.0 and 3.0 are)",
                bytes[7]
            )));
        }
    };
    if len > MAX_HEADER_LEN {
        return Err(NpyError::Header(format!(
            "a header of {len} bytes is too long (at most {MAX_HEADER_LEN})"
        )));
    }
    let prefix = bytes.len();
    bytes.resize(prefix + len, 0);
    reader
        .read_exact(&mut bytes[prefix..])
        .map_err(header_error)?;
    guard_shape(&bytes[prefix..])?;
    let raw = npyz::NpyHeader::from_reader(&bytes[..]).map_err(header_error)?;
    let dtype = match raw.dtype() {
        npyz::DType::Plain(ty) => Dtype::from_type_str(&ty)?,
        other => return Err(NpyError::Structured(other.descr())),
    };
    let header = Header {
        dtype,
        shape: raw.shape().to_vec(),
        fortran_order: raw.order() == npyz::Order::Fortran,
        data_offset: bytes.len() as u64,
    };
    Ok((header, raw))
}

/// Refuses a shape whose element count overflows u64 before npyz multiplies it out (it does so
/// unchecked). Only a guard: the header's syntax is npyz's to judge.
fn guard_shape(text: &[u8]) -> Result<(), NpyError> {
    let text = String::from_utf8_lossy(text);
    let Some(at) = text.find("'shape'").or_else(|| text.find("\"shape\"")) else {
        return Ok(());
    };
    let rest = &text[at..];
    let (Some(open), Some(close)) = (rest.find(['(', '[']), rest.find([')', ']'])) else {
        return Ok(());
    };
    if close < open {
        return Ok(());
    }
    let tuple = &rest[open + 1..close];
    let mut product = 1u64;
    for dim in tuple.split(',').map(str::trim).filter(|d| !d.is_empty()) {
        let Ok(dim) = dim.trim_end_matches(['L', 'l']).parse::<u64>() else {
            return Ok(());
        };
        product = product
            .checked_mul(dim)
            .ok_or_else(|| NpyError::Overflow(format!("({tuple})")))?;
    }
    Ok(())
}

/// A whole in-memory NPY array as f64, in C order (row-major, whatever the file's order); the
/// data must be exactly what the shape needs.
pub fn decode_f64(bytes: &[u8]) -> Result<(Header, Vec<f64>), NpyError> {
    decode(bytes, |r, n| r.read_f64(n))
}

/// As [`decode_f64`], as f32 (float64 values rounded; out-of-range ones become infinite).
pub fn decode_f32(bytes: &[u8]) -> Result<(Header, Vec<f32>), NpyError> {
    decode(bytes, |r, n| r.read_f32(n))
}

fn decode<T: Copy>(
    bytes: &[u8],
    read: impl FnOnce(&mut NpyReader<&[u8]>, u64) -> Result<Vec<T>, NpyError>,
) -> Result<(Header, Vec<T>), NpyError> {
    let mut reader = NpyReader::new(bytes)?;
    let header = reader.header().clone();
    header.check_data_len(
        (bytes.len() as u64).saturating_sub(header.data_offset),
        true,
    )?;
    let len = header.len().expect("checked with the data length");
    let values = read(&mut reader, len)?;
    let values = if header.fortran_order {
        fortran_to_c(&header.shape, &values)
    } else {
        values
    };
    Ok((header, values))
}

/// Fortran-order values (first axis fastest) reordered to C order (last axis fastest).
fn fortran_to_c<T: Copy>(shape: &[u64], values: &[T]) -> Vec<T> {
    if shape.len() < 2 || values.is_empty() {
        return values.to_vec();
    }
    let dims: Vec<usize> = shape.iter().map(|&d| d as usize).collect();
    let mut strides = vec![1usize; dims.len()];
    for k in (0..dims.len() - 1).rev() {
        strides[k] = strides[k + 1] * dims[k + 1];
    }
    let mut out = values.to_vec();
    let mut index = vec![0usize; dims.len()];
    let mut at = 0usize;
    for &v in values {
        out[at] = v;
        // Next Fortran index: axis 0 first, carrying into later axes.
        for k in 0..dims.len() {
            index[k] += 1;
            at += strides[k];
            if index[k] < dims[k] {
                break;
            }
            at -= dims[k] * strides[k];
            index[k] = 0;
        }
    }
    out
}

/// An NPY array read element by element (or row by row) from any reader after its header: the
/// data is never held whole. Reads convert from the file's dtype with Rust's `as` casts.
/// Wrap a file in a `BufReader`: elements are read a few bytes at a time.
pub struct NpyReader<R> {
    header: Header,
    raw: npyz::NpyHeader,
    reader: R,
    /// Index of the next element to read (in file order).
    next: u64,
}

impl<R: Read> NpyReader<R> {
    /// Reads the header; the reader is left at the data.
    pub fn new(mut reader: R) -> Result<Self, NpyError> {
        let (header, raw) = read_raw_header(&mut reader)?;
        Ok(NpyReader {
            header,
            raw,
            reader,
            next: 0,
        })
    }

    pub fn header(&self) -> &Header {
        &self.header
    }

    pub fn into_inner(self) -> R {
        self.reader
    }

    /// The next `count` elements (file order) as f64.
    pub fn read_f64(&mut self, count: u64) -> Result<Vec<f64>, NpyError> {
        read_as!(self, count, f64)
    }

    /// The next `count` elements (file order) as f32.
    pub fn read_f32(&mut self, count: u64) -> Result<Vec<f32>, NpyError> {
        read_as!(self, count, f32)
    }

    /// The next `count` elements (file order) as u16 (saturating for wider or float dtypes:
    /// callers that want exact values accept only uint8 and uint16).
    pub fn read_u16(&mut self, count: u64) -> Result<Vec<u16>, NpyError> {
        read_as!(self, count, u16)
    }

    /// The next `rows` rows (indices of the first axis) as f64; C order only.
    pub fn read_rows_f64(&mut self, rows: u64) -> Result<Vec<f64>, NpyError> {
        let n = self.row_elements(rows)?;
        self.read_f64(n)
    }

    /// The next `rows` rows as f32; C order only.
    pub fn read_rows_f32(&mut self, rows: u64) -> Result<Vec<f32>, NpyError> {
        let n = self.row_elements(rows)?;
        self.read_f32(n)
    }

    /// The next `rows` rows as u16; C order only.
    pub fn read_rows_u16(&mut self, rows: u64) -> Result<Vec<u16>, NpyError> {
        let n = self.row_elements(rows)?;
        self.read_u16(n)
    }

    fn row_elements(&self, rows: u64) -> Result<u64, NpyError> {
        if self.header.fortran_order && self.header.shape.len() > 1 {
            return Err(NpyError::FortranRows);
        }
        rows.checked_mul(self.header.row_len())
            .ok_or_else(|| NpyError::Overflow(self.header.shape_text()))
    }

    /// The next `count` elements in the file's own type.
    fn pull<N: npyz::Deserialize>(&mut self, count: u64) -> Result<Vec<N>, NpyError> {
        let len = self
            .header
            .len()
            .ok_or_else(|| NpyError::Overflow(self.header.shape_text()))?;
        let end = self.next.saturating_add(count);
        if end > len {
            return Err(NpyError::PastEnd { asked: end, len });
        }
        let file = npyz::NpyFile::with_header(self.raw.clone(), &mut self.reader);
        let data = file
            .data::<N>()
            .map_err(|e| NpyError::Dtype(format!("{} ({e})", self.header.dtype)))?;
        // Grown as elements arrive, not sized from the header: a short file with a large shape
        // ends in an error, not in a huge allocation.
        let mut out = Vec::with_capacity(count.min(1 << 20) as usize);
        for (i, v) in data.take(count as usize).enumerate() {
            match v {
                Ok(v) => out.push(v),
                Err(e) if e.kind() == io::ErrorKind::UnexpectedEof => {
                    return Err(NpyError::TruncatedData(self.next + i as u64));
                }
                Err(e) => return Err(NpyError::Io(e)),
            }
        }
        self.next = end;
        Ok(out)
    }
}

impl<R: Read + Seek> NpyReader<R> {
    /// Moves to the start of row `row` (index of the first axis); C order only. The reader must
    /// have been at the file's start when the header was read.
    pub fn seek_row(&mut self, row: u64) -> Result<(), NpyError> {
        let element = self.row_elements(row)?;
        let len = self.header.len().unwrap_or(u64::MAX);
        if element > len {
            return Err(NpyError::PastEnd {
                asked: element,
                len,
            });
        }
        let offset = self.header.data_offset + element * self.header.dtype.size as u64;
        self.reader
            .seek(SeekFrom::Start(offset))
            .map_err(NpyError::Io)?;
        self.next = element;
        Ok(())
    }
}

/// A shape as Python writes the tuple: `()`, `(n,)`, `(h, w)`.
pub fn shape_text(shape: &[u64]) -> String {
    match shape {
        [n] => format!("({n},)"),
        _ => {
            let dims: Vec<String> = shape.iter().map(u64::to_string).collect();
            format!("({})", dims.join(", "))
        }
    }
}

/// The bytes before the data of an array of `dtype` and `shape`: magic, version, header length
/// and the header text padded to a multiple of 64 bytes (see the module docs).
pub fn header(dtype: Dtype, shape: &[u64], fortran_order: bool) -> Vec<u8> {
    let mut text = format!(
        "{{'descr': '{}', 'fortran_order': {}, 'shape': {}, }}",
        dtype.descr(),
        if fortran_order { "True" } else { "False" },
        shape_text(shape)
    );
    // Version 1.0 has a u16 header length; past that, 2.0 and a u32.
    let mut prefix = 10;
    if prefix + text.len() + 1 > u16::MAX as usize {
        prefix = 12;
    }
    let total = prefix + text.len() + 1;
    text.push_str(&" ".repeat(total.next_multiple_of(64) - total));
    text.push('\n');
    let mut out = Vec::with_capacity(prefix + text.len());
    out.extend_from_slice(MAGIC);
    if prefix == 10 {
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(text.len() as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&[2, 0]);
        out.extend_from_slice(&(text.len() as u32).to_le_bytes());
    }
    out.extend_from_slice(text.as_bytes());
    out
}

fn check_len(shape: &[u64], len: usize) {
    let want: u64 = shape.iter().product();
    assert_eq!(
        want,
        len as u64,
        "shape {} holds {want} values, not {len}",
        shape_text(shape)
    );
}

/// A little-endian float32 array of `shape` (C order). Panics if `data` does not fill the shape.
pub fn write_f32(shape: &[u64], data: &[f32]) -> Vec<u8> {
    check_len(shape, data.len());
    let mut out = header(Dtype::F32, shape, false);
    out.reserve(data.len() * 4);
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// A little-endian float64 array of `shape` (C order). Panics if `data` does not fill the shape.
pub fn write_f64(shape: &[u64], data: &[f64]) -> Vec<u8> {
    check_len(shape, data.len());
    let mut out = header(Dtype::F64, shape, false);
    out.reserve(data.len() * 8);
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An NPY file with a hand-written header, as another writer might produce.
    fn npy(descr: &str, fortran: bool, shape: &str, data: &[u8]) -> Vec<u8> {
        let dict = format!(
            "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}",
            if fortran { "True" } else { "False" }
        );
        raw(&dict, data)
    }

    /// An NPY file with the header dict `dict`.
    fn raw(dict: &str, data: &[u8]) -> Vec<u8> {
        let header = format!("{dict}\n");
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(data);
        out
    }

    fn err(bytes: &[u8]) -> String {
        decode_f64(bytes).unwrap_err().to_string()
    }

    #[test]
    fn round_trips_f32_and_f64_with_numpys_header() {
        let values: Vec<f32> = (0..24).map(|i| i as f32 * 0.25 - 3.0).collect();
        let bytes = write_f32(&[2, 3, 4], &values);
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        let text = std::str::from_utf8(&bytes[10..10 + hlen]).unwrap();
        assert!(
            text.starts_with("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3, 4), }")
                && text.ends_with(" \n"),
            "{text:?}"
        );
        let (h, back) = decode_f32(&bytes).unwrap();
        assert_eq!(
            h,
            Header {
                dtype: Dtype::F32,
                shape: vec![2, 3, 4],
                fortran_order: false,
                data_offset: 10 + hlen as u64,
            }
        );
        assert_eq!(back, values);

        let wide: Vec<f64> = vec![1e-300, -2.5, f64::MAX];
        let bytes = write_f64(&[3], &wide);
        assert!(
            std::str::from_utf8(&bytes[10..74])
                .unwrap()
                .contains("'shape': (3,), }")
        );
        let (h, back) = decode_f64(&bytes).unwrap();
        assert_eq!((h.shape, back), (vec![3], wide));
        assert_eq!(header(Dtype::F64, &[], false).len(), 128);
        assert_eq!(header(Dtype::F64, &[7], false).len(), 128);
        assert!(String::from_utf8_lossy(&header(Dtype::U8, &[], false)).contains("'|u1'"));
    }

    #[test]
    fn the_header_is_byte_for_byte_what_the_service_served() {
        // What server/src/api/images.rs wrote for a 3 x 1 float32 image before this module.
        let mut want = b"\x93NUMPY\x01\x00\x76\x00".to_vec();
        let text = "{'descr': '<f4', 'fortran_order': False, 'shape': (1, 3), }";
        want.extend_from_slice(text.as_bytes());
        want.extend_from_slice(&[b' '; 128 - 10 - 1 - 59]);
        want.push(b'\n');
        assert_eq!(text.len(), 59);
        assert_eq!(header(Dtype::F32, &[1, 3], false)[..], want[..]);
    }

    #[test]
    fn reads_each_dtype_of_either_byte_order() {
        fn le<const N: usize>(v: &[[u8; N]]) -> Vec<u8> {
            v.iter().flatten().copied().collect()
        }
        let cases: Vec<(&str, Vec<u8>, Vec<f64>)> = vec![
            (
                "<f8",
                le(&[1.5f64.to_le_bytes(), (-2.0f64).to_le_bytes()]),
                vec![1.5, -2.0],
            ),
            (
                ">f8",
                le(&[1.5f64.to_be_bytes(), (-2.0f64).to_be_bytes()]),
                vec![1.5, -2.0],
            ),
            (
                "<f4",
                le(&[1.5f32.to_le_bytes(), 3.25f32.to_le_bytes()]),
                vec![1.5, 3.25],
            ),
            (
                ">f4",
                le(&[1.5f32.to_be_bytes(), 3.25f32.to_be_bytes()]),
                vec![1.5, 3.25],
            ),
            ("|i1", vec![0xff, 7], vec![-1.0, 7.0]),
            ("|u1", vec![0xff, 7], vec![255.0, 7.0]),
            (
                "<i2",
                le(&[(-3i16).to_le_bytes(), 30000i16.to_le_bytes()]),
                vec![-3.0, 30000.0],
            ),
            (
                ">i2",
                le(&[(-3i16).to_be_bytes(), 30000i16.to_be_bytes()]),
                vec![-3.0, 30000.0],
            ),
            (
                "<u2",
                le(&[65535u16.to_le_bytes(), 1u16.to_le_bytes()]),
                vec![65535.0, 1.0],
            ),
            (
                ">u2",
                le(&[65535u16.to_be_bytes(), 1u16.to_be_bytes()]),
                vec![65535.0, 1.0],
            ),
            (
                "<i4",
                le(&[(-70000i32).to_le_bytes(), 5i32.to_le_bytes()]),
                vec![-70000.0, 5.0],
            ),
            (
                "<u4",
                le(&[(4e9 as u32).to_le_bytes(), 5u32.to_le_bytes()]),
                vec![4e9, 5.0],
            ),
            (
                "<i8",
                le(&[(-1i64 << 40).to_le_bytes(), 5i64.to_le_bytes()]),
                vec![-(2f64.powi(40)), 5.0],
            ),
            (
                ">u8",
                le(&[(1u64 << 50).to_be_bytes(), 5u64.to_be_bytes()]),
                vec![2f64.powi(50), 5.0],
            ),
        ];
        for (descr, data, want) in cases {
            let (h, got) = decode_f64(&npy(descr, false, "(2,)", &data))
                .unwrap_or_else(|e| panic!("{descr}: {e}"));
            assert_eq!(got, want, "{descr}");
            assert_eq!(Dtype::parse(descr).unwrap(), h.dtype, "{descr}");
            assert_eq!(h.dtype.descr(), descr, "{descr}");
        }
        let u16s = le(&[65535u16.to_be_bytes(), 1u16.to_be_bytes()]);
        let be = npy(">u2", false, "(2,)", &u16s);
        let mut r = NpyReader::new(&be[..]).unwrap();
        assert_eq!(r.read_u16(2).unwrap(), [65535, 1]);
    }

    #[test]
    fn fortran_order_comes_back_in_c_order_and_versions_2_and_3_read() {
        // 3 rows x 2 columns stored column by column.
        let f: Vec<u8> = [1.0f64, 2.0, 3.0, 10.0, 20.0, 30.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let (h, v) = decode_f64(&npy("<f8", true, "(3, 2)", &f)).unwrap();
        assert!(h.fortran_order);
        assert_eq!(v, [1.0, 10.0, 2.0, 20.0, 3.0, 30.0]);
        // (2, 3, 2) in Fortran order: element (i, j, k) at i + 2 j + 6 k.
        let f: Vec<u8> = (0..12).flat_map(|i| (i as f32).to_le_bytes()).collect();
        let (_, v) = decode_f32(&npy("<f4", true, "(2, 3, 2)", &f)).unwrap();
        let want: Vec<f32> = (0..2)
            .flat_map(|i| (0..3).flat_map(move |j| (0..2).map(move |k| (i + 2 * j + 6 * k) as f32)))
            .collect();
        assert_eq!(v, want);
        for version in [2u8, 3] {
            let mut bytes = npy("<f8", false, "(1,)", &2.5f64.to_le_bytes());
            bytes[6] = version;
            let len = u16::from_le_bytes([bytes[8], bytes[9]]) as u32;
            bytes.splice(8..10, len.to_le_bytes());
            let (h, v) = decode_f64(&bytes).unwrap();
            assert_eq!((h.data_offset, v), (12 + len as u64, vec![2.5]));
        }
    }

    #[test]
    fn bad_files_say_why() {
        let eight = 1.0f64.to_le_bytes();
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (b"NUMPY".to_vec(), "magic"),
            (b"not an npy file at all".to_vec(), "magic"),
            (b"\x93NUMPY\x04\x00\x10\x00".to_vec(), "version"),
            (
                npy("<f8", false, "(2,)", &eight),
                "needs 16 bytes of data, the file has 8",
            ),
            (
                npy("<f8", false, "(1,)", &[0; 9]),
                "needs 8 bytes of data, the file has 9",
            ),
            (
                npy("<c16", false, "(1,)", &[0; 16]),
                "\"<c16\" is not supported",
            ),
            (npy("<f2", false, "(1,)", &[0; 2]), "not supported"),
            (npy("|O", false, "(1,)", &eight), "object arrays"),
            (npy("|b1", false, "(1,)", &[1]), "not supported"),
            (npy("<q8", false, "(1,)", &eight), "invalid type string"),
            (b"\x93NUMPY\x02\x00\xff\xff\xff\xff{".to_vec(), "too long"),
            (
                raw(
                    "{'descr': [('a', '<f8')], 'fortran_order': False, 'shape': (1,), }",
                    &eight,
                ),
                "structured/record",
            ),
            (npy("<f8", false, "(1, x)", &eight), "bad NPY header"),
            (npy("<f8", false, "(-1,)", &eight), "negative"),
            (
                npy("<f8", false, "(4294967296, 4294967296, 4294967296)", &eight),
                "overflows",
            ),
        ];
        for (bytes, what) in cases {
            let e = err(&bytes);
            assert!(e.contains(what), "expected {what:?} in {e:?}");
        }
        // A header with no shape, or not a dict at all.
        let mut no_shape = npy("<f8", false, "(1,)", &eight);
        let text = b"{'descr': '<f8', 'fortran_order': False}";
        no_shape.splice(10..10 + text.len(), text.iter().copied());
        assert!(
            err(&no_shape).contains("bad NPY header"),
            "{}",
            err(&no_shape)
        );
        // Cut inside the header.
        let mut truncated = npy("<f8", false, "(1,)", &eight);
        truncated.truncate(20);
        assert!(err(&truncated).contains("shorter"), "{}", err(&truncated));
        // A stream that ends inside the data.
        let short = npy("<f8", false, "(3,)", &eight);
        let mut r = NpyReader::new(&short[..]).unwrap();
        assert!(matches!(r.read_f64(3), Err(NpyError::TruncatedData(1))));
        // Past the shape.
        let mut r = NpyReader::new(&short[..]).unwrap();
        assert!(matches!(
            r.read_f64(4),
            Err(NpyError::PastEnd { asked: 4, len: 3 })
        ));
    }

    #[test]
    fn rows_stream_from_a_reader_and_seek() {
        let values: Vec<u16> = (0..5 * 2 * 3).map(|v| v as u16 * 100).collect();
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let mut file = header(Dtype::U16, &[5, 2, 3], false);
        file.extend_from_slice(&bytes);
        let dir = std::env::temp_dir().join(format!("helmholtz-npy-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("frames.npy");
        std::fs::write(&path, &file).unwrap();

        let open = || NpyReader::new(io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut r = open().unwrap();
        assert_eq!(r.header().shape, [5, 2, 3]);
        assert_eq!(r.header().row_len(), 6);
        assert_eq!(r.read_rows_u16(2).unwrap(), values[..12]);
        assert_eq!(r.read_rows_u16(1).unwrap(), values[12..18]);
        r.seek_row(4).unwrap();
        assert_eq!(
            r.read_rows_f32(1).unwrap(),
            values[24..].iter().map(|&v| v as f32).collect::<Vec<_>>()
        );
        r.seek_row(1).unwrap();
        assert_eq!(
            r.read_rows_f64(1).unwrap(),
            values[6..12].iter().map(|&v| v as f64).collect::<Vec<_>>()
        );
        assert!(matches!(r.read_rows_u16(4), Err(NpyError::PastEnd { .. })));
        assert!(matches!(r.seek_row(6), Err(NpyError::PastEnd { .. })));
        let header = read_header(&mut std::fs::File::open(&path).unwrap()).unwrap();
        assert_eq!(header.data_offset, 128);
        header
            .check_data_len(std::fs::metadata(&path).unwrap().len() - 128, true)
            .unwrap();
        std::fs::remove_dir_all(&dir).unwrap();

        // Fortran-ordered arrays have no contiguous rows.
        let fortran = npy("<f8", true, "(1, 1)", &[0; 8]);
        let mut r = NpyReader::new(&fortran[..]).unwrap();
        assert!(matches!(r.read_rows_f64(1), Err(NpyError::FortranRows)));
    }
}
