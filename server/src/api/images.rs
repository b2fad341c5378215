//! Dual images as files: 8-bit PNG scaled for viewing, 32-bit float TIFF, float32 NPY; RGB
//! composites and normal maps as 8-bit RGB PNG, multi-channel float32 NPY `(h, w, c)`.

use std::io::Cursor;

use helmholtz_proto::npy;

use crate::recon::photometric::NormalMap;

/// How a float image maps to 8 bits for viewing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Scale {
    /// Black at the 0.5th percentile, white at the 99.5th (robust to a few hot pixels).
    Percentile,
    /// Black at the minimum, white at the maximum.
    MinMax,
}

/// The (black, white) levels of `data` under `scale`.
pub fn levels(data: &[f32], scale: Scale) -> (f32, f32) {
    let mut finite: Vec<f32> = data.iter().copied().filter(|v| v.is_finite()).collect();
    if finite.is_empty() {
        return (0.0, 1.0);
    }
    finite.sort_by(|a, b| a.total_cmp(b));
    let at = |q: f64| finite[((finite.len() - 1) as f64 * q).round() as usize];
    match scale {
        Scale::MinMax => (at(0.0), at(1.0)),
        Scale::Percentile => (at(0.005), at(0.995)),
    }
}

pub fn png_8bit(width: u32, height: u32, data: &[f32], scale: Scale) -> Vec<u8> {
    let (lo, hi) = levels(data, scale);
    let span = if hi > lo { hi - lo } else { 1.0 };
    let pixels: Vec<u8> = data
        .iter()
        .map(|&v| {
            if v.is_finite() {
                (((v - lo) / span).clamp(0.0, 1.0) * 255.0).round() as u8
            } else {
                0
            }
        })
        .collect();
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().expect("png header to memory");
        writer
            .write_image_data(&pixels)
            .expect("png data to memory");
    }
    out
}

pub fn tiff_f32(width: u32, height: u32, data: &[f32]) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    {
        let mut encoder = tiff::encoder::TiffEncoder::new(&mut out).expect("tiff to memory");
        encoder
            .write_image::<tiff::encoder::colortype::Gray32Float>(width, height, data)
            .expect("tiff image to memory");
    }
    out.into_inner()
}

/// NPY: little-endian float32, C order, shape (height, width) ([`helmholtz_proto::npy`]).
pub fn npy_f32(width: u32, height: u32, data: &[f32]) -> Vec<u8> {
    npy::write_f32(&[height as u64, width as u64], data)
}

/// NPY: little-endian float64, C order, shape (rows, channels) ([`helmholtz_proto::npy`]).
pub fn npy_f64(rows: u64, channels: usize, data: &[f64]) -> Vec<u8> {
    npy::write_f64(&[rows, channels as u64], data)
}

/// 8-bit RGB PNG of an interleaved RGB image with values in [0, 1] (clamped; non-finite -> 0).
/// Panics if `rgb` does not hold `3 * width * height` values.
pub fn rgb_png(width: u32, height: u32, rgb: &[f32]) -> Vec<u8> {
    assert_eq!(
        rgb.len(),
        3 * width as usize * height as usize,
        "rgb holds 3 values per pixel"
    );
    let bytes: Vec<u8> = rgb
        .iter()
        .map(|&v| {
            if v.is_finite() {
                (v.clamp(0.0, 1.0) * 255.0).round() as u8
            } else {
                0
            }
        })
        .collect();
    png_rgb8(width, height, &bytes)
}

/// A normal map as 8-bit RGB PNG: RGB = (n + 1) / 2 with n in scene coordinates (x right, y down
/// the image, z toward the viewer: the "DirectX" convention, green grows downward), so a normal
/// facing the viewer is (128, 128, 255). Undetermined pixels (n = [0, 0, 0]) are black, which no
/// unit normal with z >= 0 produces.
pub fn normal_map_png(map: &NormalMap) -> Vec<u8> {
    let bytes: Vec<u8> = map
        .normals
        .iter()
        .flat_map(|n| {
            if *n == [0.0; 3] || n.iter().any(|v| !v.is_finite()) {
                [0u8; 3]
            } else {
                n.map(|v| ((v.clamp(-1.0, 1.0) + 1.0) * 0.5 * 255.0).round() as u8)
            }
        })
        .collect();
    png_rgb8(map.width, map.height, &bytes)
}

fn png_rgb8(width: u32, height: u32, bytes: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().expect("png header to memory");
        writer.write_image_data(bytes).expect("png data to memory");
    }
    out
}

/// NPY: little-endian float32, C order, shape (height, width, channels), from pixel-interleaved
/// `data` (e.g. [`NormalMap::normals_interleaved`] or an RGB composite).
/// Panics if `data` does not hold `width * height * channels` values.
pub fn npy_f32_hwc(width: u32, height: u32, channels: usize, data: &[f32]) -> Vec<u8> {
    npy::write_f32(&[height as u64, width as u64, channels as u64], data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_round_trips_with_scaling() {
        let data = [0.0, 0.5, 1.0, 2.0];
        let bytes = png_8bit(2, 2, &data, Scale::MinMax);
        let decoder = png::Decoder::new(Cursor::new(bytes));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (2, 2));
        assert_eq!(&buf[..4], &[0, 64, 128, 255]);
    }

    #[test]
    fn tiff_round_trips_exact_floats() {
        let data = [0.1f32, -2.5, 3.0e-7, 42.0, 1.0, 0.0];
        let bytes = tiff_f32(3, 2, &data);
        let mut decoder = tiff::decoder::Decoder::new(Cursor::new(bytes)).unwrap();
        assert_eq!(decoder.dimensions().unwrap(), (3, 2));
        match decoder.read_image().unwrap() {
            tiff::decoder::DecodingResult::F32(v) => assert_eq!(v, data),
            other => panic!("unexpected {other:?}"),
        }
    }

    #[test]
    fn npy_header_is_aligned_and_data_exact() {
        let data = [1.5f32, -2.0, 3.25];
        let bytes = npy_f32(3, 1, &data);
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        let header = std::str::from_utf8(&bytes[10..10 + hlen]).unwrap();
        assert!(
            header.contains("'shape': (1, 3)") && header.ends_with('\n'),
            "{header}"
        );
        let values: Vec<f32> = bytes[10 + hlen..]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        assert_eq!(values, data);
    }

    #[test]
    fn percentile_levels_ignore_hot_pixels() {
        let mut data = vec![0.0f32; 1000];
        for (i, v) in data.iter_mut().enumerate() {
            *v = i as f32 / 999.0;
        }
        data[10] = 1e6;
        let (lo, hi) = levels(&data, Scale::Percentile);
        assert!(lo < 0.01 && hi < 1.0, "{lo} {hi}");
        assert_eq!(levels(&data, Scale::MinMax).1, 1e6);
    }

    fn decode_rgb(bytes: Vec<u8>) -> (u32, u32, Vec<u8>) {
        let decoder = png::Decoder::new(Cursor::new(bytes));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!(
            (info.color_type, info.bit_depth),
            (png::ColorType::Rgb, png::BitDepth::Eight)
        );
        buf.truncate(info.buffer_size());
        (info.width, info.height, buf)
    }

    #[test]
    fn rgb_png_round_trips() {
        let rgb = [
            0.0,
            0.5,
            1.0,
            2.0,
            -1.0,
            f32::NAN,
            0.25,
            0.75,
            1.0 / 255.0,
            1.0,
            1.0,
            1.0,
            0.0,
            0.0,
            0.0,
            0.1,
            0.2,
            0.3,
        ];
        let (w, h, buf) = decode_rgb(rgb_png(3, 2, &rgb));
        assert_eq!((w, h), (3, 2));
        assert_eq!(
            buf,
            vec![
                0, 128, 255, 255, 0, 0, 64, 191, 1, 255, 255, 255, 0, 0, 0, 26, 51, 77
            ]
        );
    }

    #[test]
    fn normal_map_png_uses_normal_map_colours() {
        let s = 0.5f32.sqrt();
        let map = NormalMap {
            width: 2,
            height: 2,
            normals: vec![[0.0, 0.0, 1.0], [s, 0.0, s], [0.0, -s, s], [0.0; 3]],
            albedo: vec![1.0, 1.0, 1.0, f32::NAN],
            residual: vec![0.0, 0.0, 0.0, f32::NAN],
            lit: vec![4, 4, 4, 2],
        };
        let (w, h, buf) = decode_rgb(normal_map_png(&map));
        assert_eq!((w, h), (2, 2));
        assert_eq!(
            buf,
            vec![128, 128, 255, 218, 128, 218, 128, 37, 218, 0, 0, 0]
        );
    }

    #[test]
    fn measurement_headers_are_the_ones_served_before() {
        // measurements.npy headers (rest.rs) as the hand-written writer produced them.
        let header = npy::header(npy::Dtype::U16, &[16, 5, 6], false);
        let text = "{'descr': '<u2', 'fortran_order': False, 'shape': (16, 5, 6), }";
        assert_eq!(header.len(), 128);
        assert_eq!(&header[..10], b"\x93NUMPY\x01\x00\x76\x00");
        assert_eq!(&header[10..10 + text.len()], text.as_bytes());
        assert!(header[10 + text.len()..127].iter().all(|&b| b == b' '));
        assert_eq!(header[127], b'\n');
    }

    #[test]
    fn npy_hwc_header_has_three_axes() {
        let data: Vec<f32> = (0..2 * 3 * 4).map(|i| i as f32 * 0.5).collect();
        let bytes = npy_f32_hwc(3, 2, 4, &data);
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        let header = std::str::from_utf8(&bytes[10..10 + hlen]).unwrap();
        assert!(
            header.starts_with("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3, 4), }"),
            "{header}"
        );
        assert!(header.ends_with('\n'));
        let values: Vec<f32> = bytes[10 + hlen..]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        assert_eq!(values, data);
    }
}
