//! `helmholtz simulate --adaptive haar|hadamard`: a simulated rig on the adaptive acquisition
//! stream. The server chooses each batch of split pairs from the values so far; the simulated rig
//! generates every frame of a batch from the resolved spec (the proto's pattern generator, as a
//! projector would) and measures the scene's bucket transports through it.

use clap::ValueEnum;
use helmholtz_proto::patterns::Family;
use helmholtz_proto::wire::SampleBuf;
use helmholtz_proto::{PatternGenerator, PatternSpec};
use helmholtz_sim::simulate::{self, NoiseModel};
use serde_json::{Value, json};

use crate::adaptive::{BatchToMeasure, acquire_adaptive};
use crate::upload::{self, NewSession, UploadOptions};

use super::Outcome;
use super::args::{ResultArgs, spec_summary};
use super::reconstruct::finish_reconstruction;

/// The adaptive families.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum AdaptiveArg {
    /// 2D orthonormal Haar functions, chosen coarse to fine where the image has detail.
    Haar,
    /// 2D Walsh-Hadamard rows, chosen by the energy of those measured.
    Hadamard,
}

/// How an adaptive session shows its basis functions (`--frames`, the spec's `frames`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum FramesArg {
    /// Every basis function a split pair (two frames).
    Pairs,
    /// adaptive_haar: one frame a basis function but the first.
    Single,
}

/// What an adaptive session's `--target-error` compares with (the spec's `error_estimate`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ErrorEstimateArg {
    /// The predicted energy of what is not measured, each level's measured prediction miss and
    /// the noise the pair sums show.
    Measured,
    /// The predicted energy alone.
    Prediction,
}

/// The adaptive spec of `--adaptive`: `family` (from `Family::adaptive`) on the grid and seed of
/// the pattern flags, `count` the frame budget (default: the whole basis, 2 x width x height
/// frames).
pub fn adaptive_spec(
    family: Family,
    width: u32,
    height: u32,
    count: Option<u64>,
    seed: u64,
) -> anyhow::Result<PatternSpec> {
    // The whole basis: two frames an index, or with single frames one but index 0's two.
    let pixels = width as u64 * height as u64;
    let count = count.unwrap_or(
        if family.adaptive_frames() == Some(helmholtz_proto::AdaptiveFrames::Single) {
            pixels + 1
        } else {
            2 * pixels
        },
    );
    PatternSpec::new(family, width, height, count, seed).map_err(|e| {
        let flag = match e.field {
            "batch" => "adaptive-batch",
            "target_error" => "target-error",
            other => other,
        };
        anyhow::anyhow!("--{flag}: {}", e.message)
    })
}

/// The noise of batch `number`: the model with a seed of the batch's own (the noise of a batch
/// depends only on its number and its clean values, so a resumed run measures the same values).
fn batch_noise(model: &NoiseModel, number: u64) -> NoiseModel {
    let mut m = model.clone();
    m.seed = model
        .seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(number.wrapping_mul(0xD1B5_4A32_D192_ED03) ^ 0xA5A5_A5A5);
    m
}

/// The bucket values of one batch: each frame generated from the resolved spec and measured
/// through every channel's transport, then the noise model applied to the batch.
pub fn measure_batch(
    batch: &BatchToMeasure<'_>,
    transports: &[Vec<f32>],
    model: &NoiseModel,
) -> Vec<f64> {
    let generator = PatternGenerator::new(batch.spec);
    let mut pattern = vec![0f32; batch.spec.pixels()];
    let mut clean =
        Vec::with_capacity((batch.rows.end - batch.rows.start) as usize * transports.len());
    for row in batch.rows.clone() {
        generator.fill_values(row, &mut pattern);
        for t in transports {
            clean.push(
                t.iter()
                    .zip(&pattern)
                    .map(|(&t, &p)| t as f64 * p as f64)
                    .sum::<f64>(),
            );
        }
    }
    simulate::apply_noise(&clean, transports.len(), &batch_noise(model, batch.number)).0
}

/// What `simulate --adaptive` needs beyond the common flags.
pub(super) struct AdaptiveRun<'a> {
    pub session: NewSession,
    pub opts: UploadOptions,
    pub reconstruct: Option<&'a str>,
    pub params: &'a Value,
    pub result: &'a ResultArgs,
    pub progress: bool,
}

/// Creates the session and runs it through the stream, `measure` measuring each batch (bucket
/// values, or camera frames); reconstructs if asked.
pub(super) async fn simulate_adaptive(
    server: &str,
    run: AdaptiveRun<'_>,
    mut measure: impl FnMut(&BatchToMeasure<'_>) -> anyhow::Result<SampleBuf>,
    mut out: serde_json::Map<String, Value>,
    mut text: String,
) -> anyhow::Result<Outcome> {
    let spec = run.session.spec.clone();
    let created = upload::create_session(server, &run.session).await?;
    let bar = super::simulate::sim_progress(spec.count(), run.progress);
    let report = acquire_adaptive(server, &created.session, &run.opts, |batch| {
        let values = measure(batch)?;
        bar.inc(batch.rows.end - batch.rows.start);
        Ok(values)
    })
    .await?;
    bar.finish_and_clear();
    let id = &run.session.session_id;
    text.push_str(&format!(
        "adaptive session {id} ({}): {} of {} frames in {} batches, stopped by {}{}\n",
        spec_summary(&spec),
        report.rows,
        spec.count(),
        report.batches,
        report.reason,
        report
            .estimated_error
            .map(|e| format!(", estimated error {e:.4}"))
            .unwrap_or_default()
    ));
    text.push_str(&format!(
        "  {:.2} s, rig idle {:.3} s waiting for batches, {} reconnect(s)\n",
        report.seconds, report.idle_seconds, report.reconnects
    ));
    out.insert("adaptive".into(), serde_json::to_value(&report)?);
    out.insert("created".into(), json!(created.created));
    if let Some(method) = run.reconstruct {
        let rec = upload::request_reconstruction(server, id, method, run.params).await?;
        finish_reconstruction(server, rec, run.result, run.progress, &mut out, &mut text).await?;
    }
    Ok(Outcome {
        json: Value::Object(out),
        text,
    })
}
