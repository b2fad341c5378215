//! Minimal PNG reading (any colour type, 8 or 16 bit, to luminance) and grey PNG writing.

use std::io::Cursor;

use anyhow::{Context, bail};

/// A decoded image as luminance in [0, 1], row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct GreyImage {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<f32>,
}

/// Decodes a PNG (grey, grey+alpha, RGB, RGBA or palette; 1 to 16 bit) to luminance in [0, 1].
///
/// Colour is reduced with the Rec. 709 luma weights `0.2126 R + 0.7152 G + 0.0722 B` on the stored
/// values (no gamma linearisation: the stored values are taken as the transport); alpha is ignored.
pub fn decode_luminance(bytes: &[u8]) -> anyhow::Result<GreyImage> {
    let mut decoder = png::Decoder::new(Cursor::new(bytes));
    // EXPAND: palette -> RGB, 1/2/4-bit grey -> 8-bit, tRNS -> alpha. 16-bit stays 16-bit.
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().context("not a readable PNG")?;
    let size = reader
        .output_buffer_size()
        .context("PNG too large for memory")?;
    let mut buf = vec![0u8; size];
    let info = reader
        .next_frame(&mut buf)
        .context("PNG image data is corrupt")?;
    let (w, h) = (info.width, info.height);
    let samples_per_px = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => bail!("palette PNG was not expanded"),
    };
    let (scale, wide) = match info.bit_depth {
        png::BitDepth::Eight => (1.0 / 255.0, false),
        png::BitDepth::Sixteen => (1.0 / 65535.0, true),
        other => bail!("unexpected PNG bit depth {other:?} after expansion"),
    };
    let sample = |row: &[u8], idx: usize| -> f32 {
        if wide {
            u16::from_be_bytes([row[2 * idx], row[2 * idx + 1]]) as f32 * scale
        } else {
            row[idx] as f32 * scale
        }
    };
    let mut pixels = Vec::with_capacity(w as usize * h as usize);
    for y in 0..h as usize {
        let row = &buf[y * info.line_size..(y + 1) * info.line_size];
        for x in 0..w as usize {
            let base = x * samples_per_px;
            let v = if samples_per_px >= 3 {
                0.2126 * sample(row, base)
                    + 0.7152 * sample(row, base + 1)
                    + 0.0722 * sample(row, base + 2)
            } else {
                sample(row, base)
            };
            pixels.push(v.clamp(0.0, 1.0));
        }
    }
    Ok(GreyImage {
        width: w,
        height: h,
        pixels,
    })
}

/// Encodes 8-bit grey pixels (row-major, `width * height` bytes) as a PNG.
pub fn encode_grey8(width: u32, height: u32, pixels: &[u8]) -> anyhow::Result<Vec<u8>> {
    anyhow::ensure!(
        pixels.len() == width as usize * height as usize,
        "pixel count mismatch"
    );
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header()?;
        writer.write_image_data(pixels)?;
        writer.finish()?;
    }
    Ok(out)
}

/// Maps values in [0, 1] to 8-bit grey (rounded, clamped).
pub fn to_grey8(values: &[f32]) -> Vec<u8> {
    values
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grey8_round_trip() {
        let px: Vec<u8> = (0..12).map(|i| (i * 20) as u8).collect();
        let bytes = encode_grey8(4, 3, &px).unwrap();
        let img = decode_luminance(&bytes).unwrap();
        assert_eq!((img.width, img.height), (4, 3));
        for (a, b) in img.pixels.iter().zip(&px) {
            assert!((a * 255.0 - *b as f32).abs() < 1e-3);
        }
    }

    #[test]
    fn rgb16_becomes_luminance() {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, 2, 1);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Sixteen);
            let mut w = enc.write_header().unwrap();
            // pixel 0: pure green at full scale; pixel 1: white at half scale.
            let data: Vec<u8> = [0u16, 65535, 0, 32768, 32768, 32768]
                .iter()
                .flat_map(|v| v.to_be_bytes())
                .collect();
            w.write_image_data(&data).unwrap();
        }
        let img = decode_luminance(&out).unwrap();
        assert!((img.pixels[0] - 0.7152).abs() < 1e-4);
        assert!((img.pixels[1] - 0.5).abs() < 1e-4);
    }

    #[test]
    fn garbage_is_an_error() {
        assert!(decode_luminance(b"not a png at all").is_err());
    }
}
