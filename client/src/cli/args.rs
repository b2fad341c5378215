//! Argument groups and value enums shared by several commands, and parsing of free-form flag
//! values (`--metadata`, `--params`).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use helmholtz_proto::patterns::{Family, HadamardOrdering};
use helmholtz_proto::{PatternSpec, SpecError};
use serde_json::{Value, json};

use crate::rest::ImageFormat;
use crate::upload::{SampleFormat, UploadOptions};

/// Pattern families.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum FamilyArg {
    /// Each pixel on with probability --fill (random binary; GI/DGI/NGI).
    Bernoulli,
    /// 2D Walsh-Hadamard rows as P+/P- split pairs (--count frames, even, up to 2 x pixels).
    Hadamard,
    /// One pixel (or --block x --block block) on at a time.
    Raster,
    /// Random grey levels on --grain x --grain cells (SLM / rotating diffuser).
    Speckle,
}

/// Hadamard row orderings.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum OrderingArg {
    /// Sylvester (Kronecker) order.
    Natural,
    /// Walsh order: by number of sign changes along the flattened pattern.
    Sequency,
    /// 2D sequency diagonals (low spatial frequencies first).
    Zigzag,
    /// Nested dyadic levels: after 4^j rows the whole 2^j x 2^j basis is measured.
    #[value(name = "russian-doll", alias = "russian_doll")]
    RussianDoll,
    /// By number of constant pieces (Yu et al. 2019).
    #[value(name = "cake-cutting", alias = "cake_cutting")]
    CakeCutting,
}

impl From<OrderingArg> for HadamardOrdering {
    fn from(o: OrderingArg) -> Self {
        match o {
            OrderingArg::Natural => HadamardOrdering::Natural,
            OrderingArg::Sequency => HadamardOrdering::Sequency,
            OrderingArg::Zigzag => HadamardOrdering::Zigzag,
            OrderingArg::RussianDoll => HadamardOrdering::RussianDoll,
            OrderingArg::CakeCutting => HadamardOrdering::CakeCutting,
        }
    }
}

/// The pattern declaration as flags.
#[derive(Debug, Clone, Args)]
pub struct PatternArgs {
    /// Pattern family.
    #[arg(long, value_enum, default_value = "bernoulli")]
    pub family: FamilyArg,
    /// Pattern width in pixels (a power of two for hadamard).
    #[arg(long, default_value_t = 64)]
    pub width: u32,
    /// Pattern height in pixels (a power of two for hadamard).
    #[arg(long, default_value_t = 64)]
    pub height: u32,
    /// Number of patterns (frames) shown. Default: the full basis for hadamard (2 x width x
    /// height frames) and raster (--scans x one per block); required for bernoulli and speckle.
    #[arg(long)]
    pub count: Option<u64>,
    /// Bernoulli: probability that a pixel is on, in (0, 1).
    #[arg(long, default_value_t = 0.5)]
    pub fill: f64,
    /// Hadamard: row ordering (matters when --count is below the full basis).
    #[arg(long, value_enum, default_value = "natural")]
    pub ordering: OrderingArg,
    /// Raster: block side in pixels.
    #[arg(long, default_value_t = 1)]
    pub block: u32,
    /// Raster: how many times the block scan repeats (e.g. to average noise); --count may be
    /// at most scans x blocks, and defaults to exactly that.
    #[arg(long, default_value_t = 1)]
    pub scans: u32,
    /// Speckle: cell side in pixels.
    #[arg(long, default_value_t = 1)]
    pub grain: u32,
    /// Pattern seed: the server regenerates the same patterns from it.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl PatternArgs {
    /// The validated spec; errors name the flag.
    pub fn to_spec(&self) -> anyhow::Result<PatternSpec> {
        let family = match self.family {
            FamilyArg::Bernoulli => Family::Bernoulli { fill: self.fill },
            FamilyArg::Hadamard => Family::Hadamard {
                ordering: self.ordering.into(),
            },
            FamilyArg::Raster => Family::Raster {
                block: self.block,
                scans: self.scans,
            },
            FamilyArg::Speckle => Family::Speckle { grain: self.grain },
        };
        let pixels = self.width as u64 * self.height as u64;
        let count = match (self.count, self.family) {
            (Some(c), _) => c,
            (None, FamilyArg::Hadamard) => 2 * pixels,
            (None, FamilyArg::Raster) => {
                let b = self.block.max(1);
                let blocks = self.width.div_ceil(b) as u64 * self.height.div_ceil(b) as u64;
                blocks * self.scans.max(1) as u64
            }
            (None, f) => bail!(
                "--count is required for {} patterns (correlation imaging needs many: e.g. {} = 8 x width x height)",
                format!("{f:?}").to_lowercase(),
                8 * pixels
            ),
        };
        PatternSpec::new(family, self.width, self.height, count, self.seed).map_err(spec_flag_error)
    }
}

fn spec_flag_error(e: SpecError) -> anyhow::Error {
    anyhow::anyhow!("--{}: {}", e.field, e.message)
}

/// A spec from `--spec FILE` or `--spec-json TEXT`.
#[derive(Debug, Clone, Args)]
#[group(required = true, multiple = false)]
pub struct SpecSource {
    /// Pattern spec JSON file, e.g. {"family":"bernoulli","width":64,"height":64,"count":4096,"seed":7,"fill":0.5}.
    #[arg(long, value_name = "FILE")]
    pub spec: Option<PathBuf>,
    /// Pattern spec as inline JSON (same form as --spec).
    #[arg(long, value_name = "JSON")]
    pub spec_json: Option<String>,
}

impl SpecSource {
    pub fn load(&self) -> anyhow::Result<PatternSpec> {
        let (text, origin) = match (&self.spec, &self.spec_json) {
            (Some(path), _) => (
                std::fs::read_to_string(path)
                    .with_context(|| format!("reading {}", path.display()))?,
                path.display().to_string(),
            ),
            (None, Some(text)) => (text.clone(), "--spec-json".to_string()),
            (None, None) => bail!("give --spec FILE or --spec-json JSON"),
        };
        serde_json::from_str(&text).with_context(|| format!("{origin}: not a valid pattern spec"))
    }
}

/// Upload tuning flags.
#[derive(Debug, Clone, Args)]
pub struct TransferArgs {
    /// Rows per upload chunk [default: about 256 KiB of values].
    #[arg(long)]
    pub chunk_rows: Option<usize>,
    /// Keep retrying (re-asking the server's committed count and resuming) for this many seconds
    /// without progress before giving up.
    #[arg(long, default_value_t = 60.0)]
    pub retry_for: f64,
}

impl TransferArgs {
    pub(super) fn options(&self, progress: bool) -> anyhow::Result<UploadOptions> {
        anyhow::ensure!(
            self.retry_for >= 0.0 && self.retry_for.is_finite(),
            "--retry-for must be >= 0"
        );
        anyhow::ensure!(
            self.chunk_rows != Some(0),
            "--chunk-rows must be at least 1"
        );
        Ok(UploadOptions {
            chunk_rows: self.chunk_rows,
            retry_for: Duration::from_secs_f64(self.retry_for),
            progress,
            ..UploadOptions::default()
        })
    }
}

/// Reconstruction flags shared by `simulate` and `reconstruct`.
#[derive(Debug, Clone, Args)]
pub struct ResultArgs {
    /// Method parameters as a JSON object, e.g. '{"lambda": 0.01}'.
    #[arg(long, value_name = "JSON")]
    pub params: Option<String>,
    /// Wait until the reconstruction is done (implied by --out).
    #[arg(long)]
    pub wait: bool,
    /// Give up waiting after this many seconds.
    #[arg(long, default_value_t = 600.0)]
    pub timeout: f64,
    /// Save the dual image here once done (format from the extension: .png, .tiff, .npy).
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// Image format when --out has no telling extension.
    #[arg(long, value_enum)]
    pub format: Option<ImageFormat>,
    /// Detector channel to save [default: the server's default].
    #[arg(long)]
    pub channel: Option<String>,
}

/// How a simulated camera's frames are stored and sent.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum FrameFormatArg {
    /// 32-bit floats in signal units.
    F32,
    /// 16-bit counts: the brightest noiseless pixel reads about 60000.
    U16,
}

impl From<FrameFormatArg> for SampleFormat {
    fn from(f: FrameFormatArg) -> Self {
        match f {
            FrameFormatArg::F32 => SampleFormat::F32,
            FrameFormatArg::U16 => SampleFormat::U16,
        }
    }
}

pub(super) fn parse_metadata(items: &[String]) -> anyhow::Result<BTreeMap<String, String>> {
    items
        .iter()
        .map(|kv| {
            let (k, v) = kv
                .split_once('=')
                .with_context(|| format!("--metadata {kv:?}: expected KEY=VALUE"))?;
            anyhow::ensure!(!k.trim().is_empty(), "--metadata {kv:?}: empty key");
            Ok((k.trim().to_string(), v.to_string()))
        })
        .collect()
}

pub(super) fn parse_params(params: Option<&str>) -> anyhow::Result<Value> {
    match params {
        None => Ok(json!({})),
        Some(text) => {
            let v: Value = serde_json::from_str(text)
                .with_context(|| format!("--params {text:?}: not valid JSON"))?;
            anyhow::ensure!(
                v.is_object(),
                "--params must be a JSON object like '{{\"lambda\": 0.1}}', got {v}"
            );
            Ok(v)
        }
    }
}

pub(super) fn spec_summary(spec: &PatternSpec) -> String {
    format!(
        "{} {}x{}, {} patterns, seed {}",
        spec.family().name(),
        spec.width(),
        spec.height(),
        spec.count(),
        spec.seed()
    )
}

pub(super) fn spec_json(spec: &PatternSpec) -> Value {
    serde_json::to_value(spec).expect("spec serialises")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::simulate::generated_session_id;
    use crate::upload;

    #[test]
    fn params_and_metadata() {
        assert_eq!(parse_params(None).unwrap(), json!({}));
        assert_eq!(parse_params(Some(r#"{"a":1}"#)).unwrap(), json!({"a":1}));
        assert!(
            parse_params(Some("[1]"))
                .unwrap_err()
                .to_string()
                .contains("JSON object")
        );
        assert!(
            parse_params(Some("{"))
                .unwrap_err()
                .to_string()
                .contains("not valid JSON")
        );
        let m = parse_metadata(&["lens=50mm".into(), "note=a=b".into()]).unwrap();
        assert_eq!(m["note"], "a=b");
        assert!(parse_metadata(&["novalue".into()]).is_err());
        assert!(upload::valid_session_id(&generated_session_id()));
    }
}
