//! Encoding of bucket rows inside a `MeasurementChunk`.

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
    fn crc32c_is_castagnoli() {
        // RFC 3720 B.4 check value for "123456789".
        assert_eq!(crc32c::crc32c(b"123456789"), 0xE306_9283);
    }
}
