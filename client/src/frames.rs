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

/// Frames `first..first + count` of `spec`, checked against the spec's count.
fn frame_range(spec: &PatternSpec, first: u64, count: u64) -> anyhow::Result<std::ops::Range<u64>> {
    let end = first.checked_add(count).context("frame range overflows")?;
    anyhow::ensure!(
        end <= spec.count(),
        "frames {first}..{end} run past the spec's {} patterns (--first + --count <= count)",
        spec.count()
    );
    Ok(first..end)
}

/// Writes frames `first..first + count` of `spec` into `dir` (created if missing) and returns
/// their paths. Errors if the range runs past the spec's count. `progress` is told of each
/// frame written.
pub fn write_frames(
    spec: &PatternSpec,
    first: u64,
    count: u64,
    dir: &Path,
    progress: &dyn Fn(u64),
) -> anyhow::Result<Vec<PathBuf>> {
    let range = frame_range(spec, first, count)?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let generator = PatternGenerator::new(spec);
    range
        .map(|i| {
            let png = png::encode_grey8(spec.width(), spec.height(), &frame_pixels(&generator, i))?;
            let path = dir.join(frame_name(i));
            std::fs::write(&path, png).with_context(|| format!("writing {}", path.display()))?;
            progress(1);
            Ok(path)
        })
        .collect()
}

/// Writes frames `first..first + count` of `spec` as one NPY stack, float32 `(count, height,
/// width)` of the generator's exact values (0/1, or speckle levels in [0, 1]), streamed frame by
/// frame. `progress` is told of each frame written.
pub fn write_npy_stack(
    spec: &PatternSpec,
    first: u64,
    count: u64,
    path: &Path,
    progress: &dyn Fn(u64),
) -> anyhow::Result<()> {
    use std::io::Write;
    let range = frame_range(spec, first, count)?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut out = std::io::BufWriter::new(file);
    let shape = [count, spec.height() as u64, spec.width() as u64];
    let write = |out: &mut std::io::BufWriter<std::fs::File>, bytes: &[u8]| {
        out.write_all(bytes)
            .with_context(|| format!("writing {}", path.display()))
    };
    write(
        &mut out,
        &helmholtz_proto::npy::header(helmholtz_proto::npy::Dtype::F32, &shape, false),
    )?;
    let generator = PatternGenerator::new(spec);
    let mut values = vec![0.0f32; spec.pixels()];
    let mut bytes = Vec::with_capacity(values.len() * 4);
    for i in range {
        generator.fill_values(i, &mut values);
        bytes.clear();
        bytes.extend(values.iter().flat_map(|v| v.to_le_bytes()));
        write(&mut out, &bytes)?;
        progress(1);
    }
    out.into_inner()
        .map_err(|e| e.into_error())
        .and_then(|f| f.sync_all())
        .with_context(|| format!("writing {}", path.display()))
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
            let paths = write_frames(&spec, 2, 3, dir.path(), &|_| {}).unwrap();
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
        let e = write_frames(&spec, 10, 10, dir.path(), &|_| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("run past"), "{e}");
    }
}
