//! Streaming correlators: GI, DGI (Ferri 2010), NGI (Sun 2012).
//!
//! One pass over the rows in source order. Patterns are regenerated from the spec (they are never
//! stored); the state is a fixed number of length-k accumulators per channel, whatever n.
//!
//! # Formulas
//!
//! `<.>` is the mean over the n rows used, `R_i` the sum of pattern i's pixel values.
//! - GI: `G(x) = <c p(x)> - <c><p(x)>`. Invariant under `c -> c - c0`; we accumulate the bucket
//!   shifted by the first row's value (per channel), which removes the large common part of
//!   `<c p(x)>` and `<c><p(x)>` before they are subtracted.
//! - DGI: `G_D(x) = <c p(x)> - (<c>/<R>) <R p(x)>`.
//! - NGI: `G_N(x) = <(c_i/R_i - <c>/<R>) p_i(x)> = <(c/R) p(x)> - (<c>/<R>) <p(x)>`.
//!   A row with `R_i = 0` is an all-off pattern (`p_i(x) = 0` for every x, patterns being
//!   non-negative): it has no `c_i/R_i` weight term (its term is 0 rather than 0/0), but it still
//!   counts in n, `<c>` and `<R>`.
//!
//! DGI and NGI are both invariant under `c -> c - a R` (any constant a); we accumulate with
//! `a = c_r / R_r` of the first row r with `R_r > 0`, for the same reason as the GI shift. (Rows
//! before r have `R = 0`, so their shifted value does not depend on a; a can be fixed late.)
//!
//! Expectations for Bernoulli(q) patterns (iid pixels): `E[G] = q(1-q) t`,
//! `E[G_D] = q(1-q) (t - mean(t))`, and to first order in 1/k `E[G_N] ~ (1-q)/k (t - mean(t))`.
//! Speckle levels are uniform on [0, 1), so `E[G] = t / 12`.
//!
//! With the pattern sum `R_i` computed from the known pattern (no reference detector), a
//! multiplicative source drift `g_i` enters GI and DGI identically to first order; DGI's gain over
//! GI is the removal of the `mean(t) * R_i` background term from the noise (Ferri 2010).
//!
//! # Kernel
//!
//! Every accumulator is `acc[x] += sum_i w_i p_i(x)` for some per-row weight `w_i`. Binary
//! families take 64 patterns at a time as packed bits. For each word of 64 pixels, 8 x 8 bit
//! transposes gather, for every pixel and every group g of 8 patterns, the byte of those 8
//! patterns' bits at that pixel; each byte indexes a table of the 256 subset sums of the 8
//! patterns' weights, so a pixel takes eight look-ups per 64 patterns. Table entries hold two
//! columns' sums (16 bytes), so one look-up serves two accumulators. Grey levels (speckle) use
//! plain multiply-adds over tiles of pixels, 8 patterns at a time. Rows are spread over worker
//! threads (rayon), each with its own accumulators, summed at the end.
//!
//! Measured (dev profile, 2-vCPU Xeon VM at 2.1 GHz shared with other builds, so noisy):
//! Bernoulli 128 x 128 and 256 x 256, one channel, GI or DGI, pattern generation included:
//! 5e9-9.5e9 pattern-pixel updates/s on one thread, 0.9e10-1.4e10 on two (`bench_throughput`).
//! About a third of the time is `PatternGenerator::fill_bits`.
//!
//! # Held-out error
//!
//! The served image uses every row. Alongside, the report gives the held-out relative residual
//! ([`holdout`](crate::holdout)) of the same method fitted without the held-out rows H: rows whose
//! `holdout::key` (of the row; Hadamard: of the split pair, `row / 2`) is below
//! `f = min(DEFAULT_FRACTION, MAX_HELD_OUT / n)`, so about `MAX_HELD_OUT` (1024) rows at most
//! whatever n (state stays O(k)). Their indices and buckets are recorded while streaming, as are
//! those of a calibration set C of training rows (`f <= key < f + min(DEFAULT_FRACTION,
//! MAX_CALIBRATION / n)`, about `MAX_CALIBRATION` (256) at most). At the end the held-out rows
//! go through the kernel once more, on their own; subtracting their share from the totals gives
//! the training-only sums, and the training-only image `t_tr` follows by the same formula as the
//! served image (`Worker::image`).
//!
//! The correlators see t only up to a gain and an offset (GI: `q(1-q) t`; DGI, NGI:
//! `~ t - mean(t)`), so a bucket is predicted as `c ~ a (p . t_tr) + b R + c0`, with the three
//! coefficients fitted per channel by least squares on C (never on H); the R term restores the
//! `mean(t) R` part that DGI and NGI drop. The fit is reported as `held_out_calibration`.
//! Extra work: |H| + |C| pattern regenerations and dot products per channel (nibble tables,
//! about two kernel rows' worth each), and |H| more kernel rows and regenerations, with
//! |H| <~ 1024 and |C| <~ 256; relative to the pass it falls as 1/n once n > 10^4. Measured
//! (`bench_throughput`, CPU seconds, busy machine): +0-11 % for one channel at 256 x 256,
//! n = 32768 and 128 x 128, n = 131072; +26-29 % for three channels at 256 x 256, n = 16384;
//! +7-21 % for speckle 128 x 128, n = 4096.
//! Too few rows in H or C (fewer than `holdout::MIN_HELD_OUT`) give no estimate, with the
//! reason in `held_out_unavailable`.
//!
//! # Layout
//!
//! This module runs the pass and reports (`run`, `finish`); [`plan`] fixes the layout and the
//! shift, [`worker`] holds the per-thread accumulators and dispatches rows to them, [`kernel`]
//! has the packed-bit and grey-level kernels, [`held_out`] the error estimate.

mod held_out;
mod kernel;
mod plan;
mod worker;

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // index loops read best in the reference computations
mod tests;

use helmholtz_proto::Family;
use serde_json::{Map, Value, json};

use self::held_out::{Recorded, held_out_estimate};
use self::plan::{Plan, Shift};
use self::worker::{Worker, dispatch};
use crate::stream::RowStream;
use crate::{
    BucketSource, Control, DualImage, MethodConfig, Problem, ReconError, Reconstruction, Report,
};

/// Patterns per bit batch (one 64 x 64 bit tile per word of pixels).
const BATCH: usize = 64;
/// Patterns per grey-level batch.
const GREY_BATCH: usize = 8;
/// Pixels per tile in the grey-level kernel.
const GREY_TILE: usize = 512;
/// Pattern-pixel products (times columns) one worker handles per dispatch (~5-50 ms): bounds
/// the time to notice cancellation and the rows held in memory.
const DISPATCH_WORK: usize = 1 << 26;
/// Upper bound on the accumulator and scratch memory of all workers together.
const MEMORY_BUDGET: usize = 1 << 30;
/// Expected number of held-out rows above which the held-out fraction shrinks below
/// `holdout::DEFAULT_FRACTION` (see "Held-out error" in the module docs). The estimate of rho
/// then has a relative standard error of about 1 / sqrt(2048) = 2.2 %.
const MAX_HELD_OUT: usize = 1024;
/// The same for the calibration rows. Three coefficients fitted on 256 rows inflate the
/// residual variance by about 3 / 256 (0.6 % on rho); the dot products are the costliest part.
const MAX_CALIBRATION: usize = 256;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Gi,
    Dgi,
    Ngi,
}

/// Overrides for tests (number of workers, rows per dispatch).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Tuning {
    pub workers: Option<usize>,
    pub dispatch_rows: Option<usize>,
}

/// Runs GI, DGI or NGI (see the module docs) over `problem.rows` rows of `source`.
///
/// Errors: [`ReconError::BadRows`] for a block that is not whole rows, out of order or past
/// `problem.rows`; [`ReconError::Unsolvable`] when fewer rows arrive (or `config` is not a
/// correlator); [`ReconError::Cancelled`] soon after `control.cancel()`.
pub fn run(
    problem: &Problem,
    config: &MethodConfig,
    source: &mut dyn BucketSource,
    control: &Control,
) -> Result<Reconstruction, ReconError> {
    run_tuned(problem, config, source, control, Tuning::default())
}

pub(crate) fn run_tuned(
    problem: &Problem,
    config: &MethodConfig,
    source: &mut dyn BucketSource,
    control: &Control,
    tuning: Tuning,
) -> Result<Reconstruction, ReconError> {
    run_inner(problem, config, source, control, tuning, true).map(|run| run.reconstruction)
}

/// A run's result, plus the training-only images when the held-out estimate was made.
struct Run {
    reconstruction: Reconstruction,
    /// Per channel, the image fitted without the held-out rows (f64; tests compare it).
    #[cfg_attr(not(test), allow(dead_code))]
    training: Option<Vec<Vec<f64>>>,
}

/// [`run_tuned`]; `held_out: false` skips the held-out estimate (tests: the served image must
/// not depend on it).
fn run_inner(
    problem: &Problem,
    config: &MethodConfig,
    source: &mut dyn BucketSource,
    control: &Control,
    tuning: Tuning,
    held_out: bool,
) -> Result<Run, ReconError> {
    let kind = match config {
        MethodConfig::Gi => Kind::Gi,
        MethodConfig::Dgi => Kind::Dgi,
        MethodConfig::Ngi => Kind::Ngi,
        other => {
            return Err(ReconError::Unsolvable(format!(
                "{} is not a correlation method",
                other.name()
            )));
        }
    };
    if problem.rows > problem.spec.count() {
        return Err(ReconError::Unsolvable(format!(
            "{} rows requested but the spec declares {}",
            problem.rows,
            problem.spec.count()
        )));
    }
    let mut stream = RowStream::new(source, control, problem.channels, problem.rows)?;
    let plan = Plan::new(problem, kind, tuning);
    let m = plan.m;
    let mut workers: Vec<Worker> = (0..plan.workers).map(|_| Worker::new(&plan)).collect();
    let mut shift = Shift {
        values: vec![0.0; m],
        fixed: false,
    };
    let mut record = held_out.then(|| Recorded::new(&plan, problem.rows));

    let mut pending: Vec<f64> = Vec::new();
    let mut pending_first = 0u64;
    while let Some(block) = stream.next_block()? {
        pending.extend_from_slice(&block.values);
        let mut start = 0;
        while (pending.len() - start) / m >= plan.dispatch_rows {
            let end = start + plan.dispatch_rows * m;
            dispatch(
                &plan,
                &mut workers,
                &mut shift,
                record.as_mut(),
                &pending[start..end],
                pending_first,
                control,
            )?;
            pending_first += plan.dispatch_rows as u64;
            start = end;
            control.set_progress(pending_first as f64 / stream.total() as f64);
        }
        pending.drain(..start);
    }
    if !pending.is_empty() {
        dispatch(
            &plan,
            &mut workers,
            &mut shift,
            record.as_mut(),
            &pending,
            pending_first,
            control,
        )?;
        pending_first += (pending.len() / m) as u64;
    }
    debug_assert_eq!(pending_first, stream.rows_seen());
    let result = finish(&plan, config, &shift, workers, record.as_ref());
    control.set_progress(1.0);
    Ok(result)
}

/// Sums the workers and turns the sums into images and a report; with `record`, adds the
/// held-out estimate (see the module docs).
fn finish(
    plan: &Plan,
    config: &MethodConfig,
    shift: &Shift,
    mut workers: Vec<Worker>,
    record: Option<&Recorded>,
) -> Run {
    let mut total = workers.swap_remove(0);
    for w in &workers {
        total.merge(w);
    }
    let n = total.rows as f64;
    let (k, m) = (plan.k, plan.m);
    let images = (0..m)
        .map(|ch| DualImage {
            width: plan.width,
            height: plan.height,
            data: total.image(plan, ch).map(|v| v as f32).collect(),
        })
        .collect();

    let mut details = Map::new();
    details.insert("family".into(), json!(plan.family.name()));
    details.insert(
        "mean_bucket".into(),
        Value::Array(total.sum_raw.iter().map(|s| json!(s / n)).collect()),
    );
    details.insert("mean_pattern_sum".into(), json!(total.sum_r / n));
    match plan.family {
        Family::Bernoulli { fill: q } => {
            details.insert("fill".into(), json!(q));
            let gain = match plan.kind {
                Kind::Gi | Kind::Dgi => q * (1.0 - q),
                Kind::Ngi => (1.0 - q) / k as f64,
            };
            details.insert("expected_gain".into(), json!(gain));
            let form = match plan.kind {
                Kind::Gi => "expected_gain * t",
                Kind::Dgi => "expected_gain * (t - mean(t))",
                Kind::Ngi => "expected_gain * (t - mean(t)), to first order in 1/k",
            };
            details.insert("expected_form".into(), json!(form));
        }
        Family::Speckle { .. } if plan.kind == Kind::Gi => {
            details.insert("expected_gain".into(), json!(1.0 / 12.0));
            details.insert("expected_form".into(), json!("expected_gain * t"));
        }
        _ => {}
    }

    let (mut held_out, mut held_out_unavailable, mut training) = (None, None, None);
    if let Some(record) = record {
        match held_out_estimate(plan, shift, &total, workers, record) {
            Ok(estimate) => {
                let calibration = estimate
                    .calibration
                    .iter()
                    .map(|c| {
                        json!({"gain": c.gain, "pattern_sum": c.pattern_sum, "offset": c.offset})
                    })
                    .collect();
                details.insert("held_out_calibration".into(), Value::Array(calibration));
                details.insert(
                    "held_out_calibration_rows".into(),
                    json!(record.calibration.len()),
                );
                held_out = Some(estimate.held_out);
                training = Some(estimate.training);
            }
            Err(reason) => held_out_unavailable = Some(reason),
        }
    }
    Run {
        reconstruction: Reconstruction {
            images,
            report: Report {
                method: config.name().into(),
                params: config.params_json(),
                rows_used: total.rows,
                iterations: 1,
                details,
                held_out,
                held_out_unavailable,
            },
        },
        training,
    }
}
