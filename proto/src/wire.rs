//! Encoding of rows inside a `MeasurementChunk`: the sample formats (f64 buckets, f32 or u16
//! camera frames), little-endian, with a CRC-32C.

/// How one measured value is stored and sent: f64 for bucket sessions, f32 or u16 (counts) for
/// camera frames.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum SampleFormat {
    #[default]
    F64,
    F32,
    U16,
}

impl SampleFormat {
    /// Bytes of one value.
    pub fn bytes(self) -> usize {
        match self {
            SampleFormat::F64 => 8,
            SampleFormat::F32 => 4,
            SampleFormat::U16 => 2,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            SampleFormat::F64 => "f64",
            SampleFormat::F32 => "f32",
            SampleFormat::U16 => "u16",
        }
    }

    pub fn to_proto(self) -> crate::v1::SampleFormat {
        match self {
            SampleFormat::F64 => crate::v1::SampleFormat::F64,
            SampleFormat::F32 => crate::v1::SampleFormat::F32,
            SampleFormat::U16 => crate::v1::SampleFormat::U16,
        }
    }

    /// The format named `f64`, `f32` or `u16`.
    pub fn parse(name: &str) -> Option<Self> {
        match name {
            "f64" => Some(SampleFormat::F64),
            "f32" => Some(SampleFormat::F32),
            "u16" => Some(SampleFormat::U16),
            _ => None,
        }
    }

    /// From the protobuf enum; `UNSPECIFIED` is `None`.
    pub fn from_proto(value: crate::v1::SampleFormat) -> Option<Self> {
        match value {
            crate::v1::SampleFormat::F64 => Some(SampleFormat::F64),
            crate::v1::SampleFormat::F32 => Some(SampleFormat::F32),
            crate::v1::SampleFormat::U16 => Some(SampleFormat::U16),
            crate::v1::SampleFormat::Unspecified => None,
        }
    }

    /// Decodes little-endian values of this format (a whole number of them), appending to `out`
    /// as f32 (f64 values are rounded).
    pub fn decode_f32(self, bytes: &[u8], out: &mut Vec<f32>) {
        match self {
            SampleFormat::F64 => out.extend(
                bytes
                    .chunks_exact(8)
                    .map(|b| f64::from_le_bytes(b.try_into().expect("8")) as f32),
            ),
            SampleFormat::F32 => out.extend(
                bytes
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes(b.try_into().expect("4"))),
            ),
            SampleFormat::U16 => out.extend(
                bytes
                    .chunks_exact(2)
                    .map(|b| u16::from_le_bytes(b.try_into().expect("2")) as f32),
            ),
        }
    }

    /// Decodes little-endian values of this format into f64 (exact for every format).
    pub fn decode_f64(self, bytes: &[u8]) -> Vec<f64> {
        match self {
            SampleFormat::F64 => bytes
                .chunks_exact(8)
                .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
                .collect(),
            SampleFormat::F32 => bytes
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes(b.try_into().unwrap()) as f64)
                .collect(),
            SampleFormat::U16 => bytes
                .chunks_exact(2)
                .map(|b| u16::from_le_bytes(b.try_into().unwrap()) as f64)
                .collect(),
        }
    }
}

/// Rows of values in one sample format (row-major), borrowed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Samples<'a> {
    F64(&'a [f64]),
    F32(&'a [f32]),
    U16(&'a [u16]),
}

impl Samples<'_> {
    pub fn format(&self) -> SampleFormat {
        match self {
            Samples::F64(_) => SampleFormat::F64,
            Samples::F32(_) => SampleFormat::F32,
            Samples::U16(_) => SampleFormat::U16,
        }
    }

    /// Number of values.
    pub fn len(&self) -> usize {
        match self {
            Samples::F64(v) => v.len(),
            Samples::F32(v) => v.len(),
            Samples::U16(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The index of the first non-finite value (never for u16).
    pub fn first_non_finite(&self) -> Option<usize> {
        match self {
            Samples::F64(v) => v.iter().position(|x| !x.is_finite()),
            Samples::F32(v) => v.iter().position(|x| !x.is_finite()),
            Samples::U16(_) => None,
        }
    }

    /// Value `i` widened to f64 (for messages).
    pub fn get_f64(&self, i: usize) -> f64 {
        match self {
            Samples::F64(v) => v[i],
            Samples::F32(v) => v[i] as f64,
            Samples::U16(v) => v[i] as f64,
        }
    }

    /// Values `from..to` as little-endian bytes of their own format.
    pub fn encode_range(&self, from: usize, to: usize) -> Vec<u8> {
        let mut out = Vec::with_capacity((to - from) * self.format().bytes());
        match self {
            Samples::F64(v) => v[from..to]
                .iter()
                .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
            Samples::F32(v) => v[from..to]
                .iter()
                .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
            Samples::U16(v) => v[from..to]
                .iter()
                .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
        }
        out
    }

    /// Every value as little-endian bytes.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_range(0, self.len())
    }
}

/// Owned rows in one sample format.
#[derive(Clone, Debug, PartialEq)]
pub enum SampleBuf {
    F64(Vec<f64>),
    F32(Vec<f32>),
    U16(Vec<u16>),
}

impl SampleBuf {
    pub fn as_samples(&self) -> Samples<'_> {
        match self {
            SampleBuf::F64(v) => Samples::F64(v),
            SampleBuf::F32(v) => Samples::F32(v),
            SampleBuf::U16(v) => Samples::U16(v),
        }
    }
}

/// Row-major f64 values as little-endian bytes, and their CRC-32C.
pub fn encode_values(values: &[f64]) -> (Vec<u8>, u32) {
    let mut bytes = Vec::with_capacity(values.len() * 8);
    for v in values {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    let crc = crc32c::crc32c(&bytes);
    (bytes, crc)
}

/// Why a chunk's payload was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WireError {
    #[error("values_f64le has {len} bytes, not a whole number of rows of {channels} f64 values")]
    Ragged { len: usize, channels: usize },
    #[error("crc32c mismatch: chunk says {expected:#010x}, payload has {actual:#010x}")]
    Checksum { expected: u32, actual: u32 },
    #[error("value at row {row}, channel {channel} is not finite ({value})")]
    NotFinite {
        row: usize,
        channel: usize,
        value: f64,
    },
}

/// Checks the checksum and shape, then decodes. Every value must be finite.
pub fn decode_values(bytes: &[u8], channels: usize, crc: u32) -> Result<Vec<f64>, WireError> {
    let actual = crc32c::crc32c(bytes);
    if actual != crc {
        return Err(WireError::Checksum {
            expected: crc,
            actual,
        });
    }
    if channels == 0 || !bytes.len().is_multiple_of(8 * channels) {
        return Err(WireError::Ragged {
            len: bytes.len(),
            channels,
        });
    }
    let mut out = Vec::with_capacity(bytes.len() / 8);
    for (idx, raw) in bytes.chunks_exact(8).enumerate() {
        let value = f64::from_le_bytes(raw.try_into().expect("8 bytes"));
        if !value.is_finite() {
            return Err(WireError::NotFinite {
                row: idx / channels,
                channel: idx % channels,
                value,
            });
        }
        out.push(value);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_rejections() {
        let values = [1.0, -2.5, 3.25, 1e300];
        let (bytes, crc) = encode_values(&values);
        assert_eq!(decode_values(&bytes, 2, crc).unwrap(), values);
        assert!(matches!(
            decode_values(&bytes, 2, crc ^ 1),
            Err(WireError::Checksum { .. })
        ));
        assert!(matches!(
            decode_values(&bytes, 3, crc),
            Err(WireError::Ragged { .. })
        ));
        let (bytes, crc) = encode_values(&[1.0, f64::NAN]);
        assert!(matches!(
            decode_values(&bytes, 1, crc),
            Err(WireError::NotFinite {
                row: 1,
                channel: 0,
                ..
            })
        ));
        let (bytes, crc) = encode_values(&[f64::INFINITY]);
        assert!(decode_values(&bytes, 1, crc).is_err());
    }

    #[test]
    fn sample_formats_round_trip() {
        for f in [SampleFormat::F64, SampleFormat::F32, SampleFormat::U16] {
            assert_eq!(SampleFormat::parse(f.name()), Some(f));
            assert_eq!(SampleFormat::from_proto(f.to_proto()), Some(f));
        }
        assert_eq!(SampleFormat::parse("f16"), None);
        let buf = SampleBuf::U16(vec![0, 1, 65535]);
        let bytes = buf.as_samples().encode();
        assert_eq!(SampleFormat::U16.decode_f64(&bytes), [0.0, 1.0, 65535.0]);
        let mut out = Vec::new();
        SampleFormat::F32.decode_f32(&Samples::F32(&[1.5, -2.0]).encode(), &mut out);
        assert_eq!(out, [1.5, -2.0]);
        assert_eq!(Samples::F64(&[1.0, f64::NAN]).first_non_finite(), Some(1));
    }

    #[test]
    fn crc32c_is_castagnoli() {
        // RFC 3720 B.4 check value for "123456789".
        assert_eq!(crc32c::crc32c(b"123456789"), 0xE306_9283);
    }
}
