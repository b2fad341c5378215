//! Pure numerics: from a pattern spec and bucket rows to dual images and a report.
//!
//! Nothing here knows about async, SQL or HTTP. The job layer hands in a [`BucketSource`] (rows in
//! order, in blocks) and a [`Control`] (progress out, cancellation in) and stores what comes back.
//!
//! Methods (see [`MethodConfig`]): `gi`, `dgi`, `ngi` are one-pass streaming correlators with O(k)
//! state per channel; `direct` is the exact inverse of a complete raster or Hadamard set.
//!
//! On finished dual images: [`photometric`] recovers normals and albedo from several detectors at
//! known directions (photometric stereo), [`colour`] composites channels behind r, g, b filters.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use helmholtz_proto::PatternSpec;

pub mod adaptive;
pub mod auto;
pub mod colour;
pub mod compressive;
pub mod correlate;
pub mod direct;
mod fit;
pub mod fwht;
#[cfg(test)]
mod hard_cases;
pub mod holdout;
pub mod linop;
pub mod method;
pub mod metrics;
pub mod noise;
pub mod ops;
pub mod photometric;
pub mod preview;
pub mod request;
pub(crate) mod simd;
pub mod solve;
mod stream;
#[cfg(test)]
mod testutil;
pub mod transforms;
pub mod transport;

pub use method::{MethodConfig, ParamError};
pub use request::Request;

/// Consecutive bucket rows: `values` is row-major, `rows x channels`.
#[derive(Clone, Debug)]
pub struct BucketBlock {
    pub first_row: u64,
    pub values: Vec<f64>,
}

/// Why the source of rows failed (storage error); carried through as text.
#[derive(Debug, Clone, thiserror::Error)]
#[error("reading bucket rows: {0}")]
pub struct SourceError(pub String);

/// Rows 0..problem.rows in order, in blocks of any size. Must not yield rows past `problem.rows`.
pub trait BucketSource {
    fn next_block(&mut self) -> Result<Option<BucketBlock>, SourceError>;
}

/// A source over rows already in memory (tests, benchmarks, the client's simulator).
pub struct SliceSource<'a> {
    values: &'a [f64],
    channels: usize,
    block_rows: usize,
    next_row: usize,
}

impl<'a> SliceSource<'a> {
    pub fn new(values: &'a [f64], channels: usize, block_rows: usize) -> Self {
        assert!(channels > 0 && block_rows > 0 && values.len().is_multiple_of(channels));
        SliceSource {
            values,
            channels,
            block_rows,
            next_row: 0,
        }
    }
}

impl BucketSource for SliceSource<'_> {
    fn next_block(&mut self) -> Result<Option<BucketBlock>, SourceError> {
        let rows = self.values.len() / self.channels;
        if self.next_row >= rows {
            return Ok(None);
        }
        let end = (self.next_row + self.block_rows).min(rows);
        let block = BucketBlock {
            first_row: self.next_row as u64,
            values: self.values[self.next_row * self.channels..end * self.channels].to_vec(),
        };
        self.next_row = end;
        Ok(Some(block))
    }
}

/// Shared between a running reconstruction and whoever watches it.
#[derive(Debug, Default)]
pub struct Control {
    progress_bits: AtomicU64,
    cancelled: AtomicBool,
}

impl Control {
    pub fn new() -> Self {
        Self::default()
    }
    /// Fraction done in [0, 1]. Progress never goes back: the largest fraction reported so far
    /// is kept. Smaller ones do come, and are not news to a watcher: a solve's polish restarts
    /// its iteration count, and `auto`'s candidates run at the same time, each reporting its own
    /// place in the round. (For non-negative floats the bit patterns order as the values, so the
    /// maximum is one atomic `fetch_max`.) NaN is ignored.
    pub fn set_progress(&self, fraction: f64) {
        if fraction.is_nan() {
            return;
        }
        self.progress_bits
            .fetch_max(fraction.clamp(0.0, 1.0).to_bits(), Ordering::Relaxed);
    }
    pub fn progress(&self) -> f64 {
        f64::from_bits(self.progress_bits.load(Ordering::Relaxed))
    }
    pub fn cancel(&self) {
        self.cancelled.store(true, Ordering::Relaxed);
    }
    pub fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::Relaxed)
    }
}

/// What is being reconstructed: the session's spec, its channel count, and how many of its rows
/// (a prefix; at most `spec.count()`) to use.
#[derive(Clone, Debug)]
pub struct Problem<'a> {
    pub spec: &'a PatternSpec,
    pub channels: usize,
    pub rows: u64,
}

/// One dual image: the transport estimate on the pattern grid, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct DualImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

/// The result: one dual image per channel and a JSON-ready report.
#[derive(Clone, Debug)]
pub struct Reconstruction {
    pub images: Vec<DualImage>,
    pub report: Report,
}

/// What every reconstruction reports (served on `GET /v1/reconstructions/{id}`, inside the
/// service's report): the contract's [`helmholtz_proto::rest::ReconReport`].
pub use helmholtz_proto::rest::ReconReport as Report;

#[derive(Debug, Clone, thiserror::Error)]
pub enum ReconError {
    #[error("cancelled")]
    Cancelled,
    #[error(transparent)]
    Source(#[from] SourceError),
    /// The request cannot be solved with these rows (e.g. `direct` on an incomplete set).
    #[error("{0}")]
    Unsolvable(String),
    /// The source yielded rows that do not fit the problem (a bug upstream).
    #[error("bad input rows: {0}")]
    BadRows(String),
}

/// Runs one reconstruction to completion (or cancellation).
pub fn reconstruct(
    problem: &Problem,
    config: &MethodConfig,
    source: &mut dyn BucketSource,
    control: &Control,
) -> Result<Reconstruction, ReconError> {
    if problem.spec.adaptive_single() {
        return reconstruct_single_frames(problem, config, source, control);
    }
    config.check(problem)?;
    match config {
        MethodConfig::Gi | MethodConfig::Dgi | MethodConfig::Ngi => {
            correlate::run(problem, config, source, control)
        }
        MethodConfig::Direct | MethodConfig::ZeroFilled | MethodConfig::Levels { .. } => {
            direct::run(problem, config, source, control)
        }
        MethodConfig::Auto { .. } if auto::exact_inverse_applies(problem) => {
            let mut r = direct::run(problem, &MethodConfig::Direct, source, control)?;
            // For an orthogonal set, min ||A t - c|| s.t. t >= 0 is the exact inverse clipped
            // at 0 (A preserves norms), so auto keeps its promise t >= 0 at no cost.
            for image in &mut r.images {
                image.data.iter_mut().for_each(|v| *v = v.max(0.0));
            }
            r.report.method = config.name().into();
            r.report.params = config.params_json();
            let noise = r.report.details.get("noise_estimate").cloned();
            let declared = match config {
                MethodConfig::Auto {
                    read_noise: Some(d),
                    ..
                } => Some((d.sigma, declared_pixel_sigma(problem.spec, *d))),
                _ => None,
            };
            let choices = r
                .images
                .iter()
                .enumerate()
                .map(|(ch, image)| {
                    let estimate = noise.as_ref().map(|n| n[ch].clone()).unwrap_or_default();
                    let mut choice = serde_json::json!({
                        "model": "direct",
                        "reason": auto::EXACT_REASON,
                        "noise_estimate": estimate,
                    });
                    let sigma = match declared {
                        Some((read_noise, pixel)) => {
                            choice["noise_declared"] =
                                serde_json::json!({"read_noise": read_noise, "pixel_sigma": pixel});
                            Some(pixel)
                        }
                        None => estimate["sigma"].as_f64(),
                    };
                    choice["error_estimate"] =
                        serde_json::json!(auto::exact_error_estimate(&image.data, sigma));
                    choice
                })
                .collect();
            r.report
                .details
                .insert("auto".into(), serde_json::Value::Array(choices));
            Ok(r)
        }
        MethodConfig::Cs { .. }
        | MethodConfig::Tv { .. }
        | MethodConfig::Lsq { .. }
        | MethodConfig::Auto { .. } => compressive::run(problem, config, source, control),
    }
}

/// The RMS noise per pixel of a complete orthonormal set's exact inverse under a declared read
/// noise: the mean noise variance of its data (Hadamard: `2 sigma^2 / k`; `adaptive_haar`:
/// `2 sigma^2 / g_n^2`, or the single frames' [`adaptive::single_frame_pair_variances`] over
/// `g_n^2`; raster: `sigma^2`).
fn declared_pixel_sigma(spec: &helmholtz_proto::PatternSpec, d: method::ReadNoise) -> f64 {
    use helmholtz_proto::Family;
    let k = spec.pixels() as f64;
    let variance = match spec.family() {
        Family::AdaptiveHaar { .. } => {
            let indices = spec.adaptive_indices().unwrap_or(&[]);
            let w = spec.width();
            let factors = match d.single_frames {
                true => adaptive::single_frame_pair_variances(w, indices),
                false => vec![2.0; indices.len()],
            };
            let sum: f64 = indices
                .iter()
                .zip(&factors)
                .map(|(&n, f)| f / noise::haar_support(w, n).1.powi(2))
                .sum();
            sum / (indices.len().max(1) as f64)
        }
        Family::Raster { .. } => 1.0,
        _ => 2.0 / k,
    };
    d.sigma * variance.sqrt()
}

/// The warning a reconstruction of a single-frame session carries unless it declares the read
/// noise (`auto`'s `read_noise`).
pub const SINGLE_FRAMES_WARNING: &str = "single frames carry no noise estimate of their own (each y- is computed from the others, so the pair sums the noise is read from are exact): this image treats the frames as noise-free; on a rig whose fine details do not stand clear of its read noise it can be far off (30 dB read noise on the benchmark: far below the flat image). Declare the detector's read noise (auto's params.read_noise, the spread of dark frames in bucket units), or use split pairs";

/// A single-frame adaptive session (PATTERNS.md, "Single frames") is the split-pair session of
/// the same indices, each `y-` following from its block's light: every method runs on those
/// pairs ([`adaptive::single_frames_as_pairs`], [`adaptive::pair_spec`]). Its rows are few (at
/// most `k + 1` frames of bucket channels), so they are read whole.
fn reconstruct_single_frames(
    problem: &Problem,
    config: &MethodConfig,
    source: &mut dyn BucketSource,
    control: &Control,
) -> Result<Reconstruction, ReconError> {
    let c = problem.channels.max(1);
    let mut frames = Vec::with_capacity(problem.rows as usize * c);
    while let Some(block) = source.next_block()? {
        if block.first_row != (frames.len() / c) as u64 {
            return Err(ReconError::BadRows(format!(
                "a block starts at row {}, after {} rows",
                block.first_row,
                frames.len() / c
            )));
        }
        frames.extend_from_slice(&block.values);
    }
    if frames.len() != problem.rows as usize * c {
        return Err(ReconError::BadRows(format!(
            "{} values for {} rows of {c} channels",
            frames.len(),
            problem.rows
        )));
    }
    let pairs = adaptive::single_frames_as_pairs(problem.spec, c, &frames);
    let spec = adaptive::pair_spec(problem.spec);
    let pair_problem = Problem {
        spec: &spec,
        channels: problem.channels,
        rows: (pairs.len() / c) as u64,
    };
    // A declared read noise is the frames'; the pairs carry it as the decoding combines them.
    let mut config = config.clone();
    let mut declared = false;
    if let MethodConfig::Auto {
        read_noise: Some(d),
        ..
    } = &mut config
    {
        d.single_frames = true;
        declared = true;
    }
    let mut r = reconstruct(
        &pair_problem,
        &config,
        &mut SliceSource::new(&pairs, c, 4096),
        control,
    )?;
    r.report.details.insert(
        "single_frames".into(),
        serde_json::json!({
            "frames": problem.rows,
            "pairs": pair_problem.rows / 2,
            "basis": "one frame an index but index 0's two: each y- is its block's light less y+ (PATTERNS.md, \"Single frames\"), and the method ran on the split pairs that gives",
        }),
    );
    // Pair sums that are exact by construction measure no noise: every estimate of it the
    // method made from them reads 0, and under read noise its image can be far off.
    if declared {
        return Ok(r);
    }
    let warnings = r
        .report
        .details
        .entry("warnings")
        .or_insert_with(|| serde_json::Value::Array(Vec::new()));
    if let Some(list) = warnings.as_array_mut() {
        list.push(SINGLE_FRAMES_WARNING.into());
    }
    Ok(r)
}

#[cfg(test)]
mod control_tests {
    use super::*;

    #[test]
    fn progress_never_goes_back() {
        let c = Control::new();
        assert_eq!(c.progress(), 0.0);
        for (report, seen) in [
            (0.5, 0.5),
            (0.3, 0.5),
            (0.7, 0.7),
            (f64::NAN, 0.7),
            (-1.0, 0.7),
            (2.0, 1.0),
            (0.9, 1.0),
        ] {
            c.set_progress(report);
            assert_eq!(c.progress(), seen, "after reporting {report}");
        }
    }

    #[test]
    fn a_watcher_sees_auto_progress_only_grow() {
        // auto's candidates report from three threads at once, and every solve's polish starts
        // its iteration count again: a watcher polling the job must still see progress grow.
        let spec = PatternSpec::new(
            helmholtz_proto::Family::Bernoulli { fill: 0.5 },
            32,
            32,
            300,
            7,
        )
        .unwrap();
        let op = ops::measurement_operator(&spec, 300);
        let t: Vec<f64> = (0..1024)
            .map(|i| ((i % 32) as f64 / 31.0).powi(2))
            .collect();
        let mut c = vec![0.0; 300];
        op.apply(&t, &mut c);
        let control = Control::new();
        let config = MethodConfig::parse("auto", &serde_json::json!({})).unwrap();
        let problem = Problem {
            spec: &spec,
            channels: 1,
            rows: 300,
        };
        let done = AtomicBool::new(false);
        let seen = std::thread::scope(|s| {
            let watcher = s.spawn(|| {
                let mut seen = Vec::new();
                while !done.load(Ordering::Relaxed) {
                    seen.push(control.progress());
                    std::thread::yield_now();
                }
                seen
            });
            reconstruct(
                &problem,
                &config,
                &mut SliceSource::new(&c, 1, 100),
                &control,
            )
            .unwrap();
            done.store(true, Ordering::Relaxed);
            watcher.join().unwrap()
        });
        assert!(seen.windows(2).all(|w| w[0] <= w[1]), "progress went back");
        assert_eq!(control.progress(), 1.0);
    }
}
