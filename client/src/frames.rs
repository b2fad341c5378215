//! Pattern frames as 8-bit grey PNGs, for a projector, DMD or SLM to show.

use std::path::{Path, PathBuf};

use anyhow::Context;
use helmholtz_proto::{PatternGenerator, PatternSpec};

use helmholtz_proto::png;

/// File name of frame `i`: `frame_000000.png`, ... (six digits, more if needed).
pub fn frame_name(i: u64) -> String {
    format!("frame_{i:06}.png")
}

/// Pattern `i` as 8-bit grey: 0/255 for binary families, round(255 v) for speckle levels.
pub fn frame_pixels(generator: &PatternGenerator, i: u64) -> Vec<u8> {
    let mut values = vec![0.0f32; generator.spec().pixels()];
    generator.fill_values(i, &mut values);
    png::to_grey8(&values)
}

/// Writes frames `first..first + count` of `spec` into `dir` (created if missing) and returns
/// their paths. Errors if the range runs past the spec's count.
pub fn write_frames(
    spec: &PatternSpec,
    first: u64,
    count: u64,
    dir: &Path,
) -> anyhow::Result<Vec<PathBuf>> {
    let end = first.checked_add(count).context("frame range overflows")?;
    anyhow::ensure!(
        end <= spec.count(),
        "frames {first}..{end} run past the spec's {} patterns (--first + --count <= count)",
        spec.count()
    );
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let generator = PatternGenerator::new(spec);
    (first..end)
        .map(|i| {
            let png = png::encode_grey8(spec.width(), spec.height(), &frame_pixels(&generator, i))?;
            let path = dir.join(frame_name(i));
            std::fs::write(&path, png).with_context(|| format!("writing {}", path.display()))?;
            Ok(path)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_match_the_generator() {
        let dir = tempfile::tempdir().unwrap();
        for json in [
            r#"{"family":"hadamard","width":8,"height":4,"count":64,"seed":1,"ordering":"sequency"}"#,
            r#"{"family":"speckle","width":6,"height":5,"count":10,"seed":3,"grain":2}"#,
        ] {
            let spec: PatternSpec = serde_json::from_str(json).unwrap();
            let paths = write_frames(&spec, 2, 3, dir.path()).unwrap();
            assert_eq!(paths.len(), 3);
            assert!(paths[0].ends_with("frame_000002.png"));
            let generator = PatternGenerator::new(&spec);
            let mut expect = vec![0.0f32; spec.pixels()];
            for (n, path) in paths.iter().enumerate() {
                generator.fill_values(2 + n as u64, &mut expect);
                let img = png::decode_luminance(&std::fs::read(path).unwrap()).unwrap();
                assert_eq!((img.width, img.height), (spec.width(), spec.height()));
                for (a, b) in img.pixels.iter().zip(&expect) {
                    assert!((a - b).abs() <= 0.5 / 255.0 + 1e-6);
                }
                if spec.family().is_binary() {
                    assert!(img.pixels.iter().all(|&v| v == 0.0 || v == 1.0));
                }
            }
        }
        let spec: PatternSpec =
            serde_json::from_str(r#"{"family":"raster","width":4,"height":4,"count":16}"#).unwrap();
        let e = write_frames(&spec, 10, 10, dir.path())
            .unwrap_err()
            .to_string();
        assert!(e.contains("run past"), "{e}");
    }
}
