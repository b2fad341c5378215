//! Request bodies: a JSON object, or an image as PNG or NPY (the light of a relight, the
//! pattern of a primal), chosen by `content-type`.

use axum::body::Bytes;
use axum::http::{HeaderMap, header};
use helmholtz_proto::npy;

use super::super::ApiError;

/// A request body: JSON (decoded by its handler into the contract's request type) or an image
/// (PNG, NPY).
pub(super) enum Input {
    Json(Bytes),
    Image {
        width: usize,
        height: usize,
        values: Vec<f32>,
    },
}

pub(super) fn parse_input(
    headers: &HeaderMap,
    body: &Bytes,
    what: &str,
) -> Result<Input, ApiError> {
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("application/json");
    let mime = content_type
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    match mime.as_str() {
        "application/json" | "" => Ok(Input::Json(body.clone())),
        "image/png" => {
            let (width, height, values) = decode_png(body)
                .map_err(|e| ApiError::invalid(what, format!("not a readable PNG: {e}")))?;
            Ok(Input::Image {
                width,
                height,
                values,
            })
        }
        "application/x-npy" | "application/octet-stream" => {
            let (width, height, values) =
                decode_npy(body).map_err(|e| ApiError::invalid(what, e))?;
            Ok(Input::Image {
                width,
                height,
                values,
            })
        }
        other => Err(ApiError::invalid(
            "content-type",
            format!(
                "{other:?} is not accepted; send application/json, image/png or application/x-npy"
            ),
        )),
    }
}

/// A grey (or colour, reduced to Rec. 709 luma) PNG of 1-16 bits as values in [0, 1].
fn decode_png(bytes: &[u8]) -> Result<(usize, usize, Vec<f32>), String> {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(|e| e.to_string())?;
    let mut buf = vec![0; reader.output_buffer_size().ok_or("image too large")?];
    let info = reader.next_frame(&mut buf).map_err(|e| e.to_string())?;
    let (w, h) = (info.width as usize, info.height as usize);
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err("indexed colour after expansion".into()),
    };
    let sixteen = info.bit_depth == png::BitDepth::Sixteen;
    let max = if sixteen { 65535.0 } else { 255.0 };
    let sample = |i: usize| -> f32 {
        if sixteen {
            u16::from_be_bytes([buf[2 * i], buf[2 * i + 1]]) as f32 / max
        } else {
            buf[i] as f32 / max
        }
    };
    let values = (0..w * h)
        .map(|p| {
            let base = p * channels;
            if channels >= 3 {
                0.2126 * sample(base) + 0.7152 * sample(base + 1) + 0.0722 * sample(base + 2)
            } else {
                sample(base)
            }
        })
        .collect();
    Ok((w, h, values))
}

/// A 1-D or 2-D NPY array ([`helmholtz_proto::npy`]: float32/64 or an integer type, either byte
/// order, C or Fortran order) as f32; 1-D arrays come back as width = len, height = 1.
pub(super) fn decode_npy(bytes: &[u8]) -> Result<(usize, usize, Vec<f32>), String> {
    let header = npy::read_header(&mut &bytes[..]).map_err(|e| e.to_string())?;
    let (height, width) = match header.shape.as_slice() {
        [n] => (1, *n as usize),
        [h, w] => (*h as usize, *w as usize),
        _ => {
            return Err(format!(
                "the array must be 1-D or 2-D, got shape {}",
                header.shape_text()
            ));
        }
    };
    let (_, values) = npy::decode_f32(bytes).map_err(|e| e.to_string())?;
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(format!("value {i} is not finite"));
    }
    Ok((width, height, values))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::api::images;

    #[test]
    fn npy_bodies_parse_and_bad_ones_say_why() {
        let values = [0.5f32, 1.0, 2.0, 3.0, 4.0, 5.0];
        let bytes = images::npy_f32(3, 2, &values);
        assert_eq!(decode_npy(&bytes).unwrap(), (3, 2, values.to_vec()));
        let wide = images::npy_f64(1, 4, &[1.0, 2.0, 3.0, 4.0]);
        assert_eq!(decode_npy(&wide).unwrap(), (4, 1, vec![1.0, 2.0, 3.0, 4.0]));
        assert!(decode_npy(b"nope").unwrap_err().contains("magic"));
        let mut short = bytes.clone();
        short.pop();
        assert!(decode_npy(&short).unwrap_err().contains("bytes"));
        let cube = npy::write_f32(&[1, 1, 2], &[1.0, 2.0]);
        assert!(decode_npy(&cube).unwrap_err().contains("1-D or 2-D"));
        let u16_be = npy::Dtype {
            kind: npy::Kind::Uint,
            size: 2,
            big_endian: true,
        };
        let mut be = npy::header(u16_be, &[2], false);
        be.extend_from_slice(&[0, 1, 1, 0]);
        assert_eq!(decode_npy(&be).unwrap(), (2, 1, vec![1.0, 256.0]));
        let nan = npy::write_f64(&[2], &[1.0, f64::NAN]);
        assert!(
            decode_npy(&nan)
                .unwrap_err()
                .contains("value 1 is not finite")
        );
    }
}
