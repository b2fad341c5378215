//! A simulated rig: bucket values `c_i = t · p_i` for every pattern of a spec, then the noise a
//! real rig adds, in the order it happens (imaging.md §4):
//!
//! 1. source drift: every channel's signal times a slow multiplicative factor `1 + x_i`, where
//!    `x` is a stationary AR(1) (Ornstein-Uhlenbeck) walk with standard deviation `drift` and
//!    correlation length `drift_correlation` patterns;
//! 2. shot noise: `c -> Poisson(alpha c) / alpha`, `alpha = photons / mean(c)` (so a pattern
//!    collects `photons` photo-electrons on average);
//! 3. Gaussian read noise with `sigma = rms(c) / 10^(snr_db / 20)`;
//! 4. the dark offset `dark` is added;
//! 5. the ADC: clip to `[0, full_scale]` with `full_scale = 1.1 max(c) + dark` (saturation), then
//!    round to `2^bits` levels. Values stay in signal units (level × full_scale / (2^bits - 1)).
//!
//! `c` above is the noiseless signal of that channel. Everything is deterministic from
//! `NoiseModel::seed` and independent of the number of threads: each row draws from its own
//! counter-based stream.

pub mod lambert;
pub mod random;

use std::sync::atomic::{AtomicUsize, Ordering};

use helmholtz_proto::{PatternGenerator, PatternSpec};
use indicatif::ProgressBar;
use serde::Serialize;

use random::SplitMix64;

/// Noise stages' stream identifiers (see [`SplitMix64::stream`]).
const STAGE_DRIFT: u64 = 1;
const STAGE_ROW: u64 = 2;

/// What a simulated detector adds to the noiseless bucket signal. `Default` is noiseless.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct NoiseModel {
    /// Relative standard deviation of the multiplicative source drift (0 = a stable source).
    pub drift: f64,
    /// Correlation length of the drift in patterns; `None` = `max(count / 20, 16)`.
    pub drift_correlation: Option<f64>,
    /// Mean photo-electrons per pattern (shot noise); `None` = no shot noise.
    pub photons: Option<f64>,
    /// Signal-to-read-noise ratio in dB, `20 log10(rms(c) / sigma)`; `None` = no read noise.
    pub snr_db: Option<f64>,
    /// Dark offset added to every value, in signal units.
    pub dark: f64,
    /// ADC resolution in bits (1..=32); `None` = no quantisation and no saturation.
    pub adc_bits: Option<u32>,
    /// Seed of every random draw of the noise.
    pub seed: u64,
}

impl Default for NoiseModel {
    fn default() -> Self {
        NoiseModel {
            drift: 0.0,
            drift_correlation: None,
            photons: None,
            snr_db: None,
            dark: 0.0,
            adc_bits: None,
            seed: 0,
        }
    }
}

impl NoiseModel {
    /// Checks the parameters; the messages name the CLI flags.
    pub fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            self.drift >= 0.0 && self.drift.is_finite(),
            "--drift must be >= 0"
        );
        if let Some(l) = self.drift_correlation {
            anyhow::ensure!(l > 0.0 && l.is_finite(), "--drift-correlation must be > 0");
        }
        if let Some(n) = self.photons {
            anyhow::ensure!(n > 0.0 && n.is_finite(), "--photons must be > 0, got {n}");
        }
        if let Some(s) = self.snr_db {
            anyhow::ensure!(s.is_finite(), "--snr-db must be finite");
        }
        anyhow::ensure!(self.dark.is_finite(), "--dark must be finite");
        if let Some(b) = self.adc_bits {
            anyhow::ensure!((1..=32).contains(&b), "--adc-bits must be 1..=32, got {b}");
        }
        Ok(())
    }
}

/// Per-channel figures of the applied noise.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ChannelNoise {
    /// Mean of the noiseless signal.
    pub mean_signal: f64,
    /// Photo-electrons per signal unit (shot noise), if any.
    pub photons_per_unit: Option<f64>,
    /// Read-noise standard deviation in signal units, if any.
    pub read_sigma: Option<f64>,
    /// ADC full scale in signal units, if quantised.
    pub full_scale: Option<f64>,
    /// Values clipped at full scale (saturated).
    pub saturated: usize,
    /// `10 log10(mean(c²) / mean((v - dark - c)²))`: all noise sources together vs the clean
    /// signal `c` (infinite when noiseless).
    pub effective_snr_db: f64,
}

/// What [`apply_noise`] did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct NoiseReport {
    pub channels: Vec<ChannelNoise>,
    /// Range of the drift factor over the run (1, 1 without drift).
    pub drift_min: f64,
    pub drift_max: f64,
}

/// A simulated acquisition: `rows x channels`, row-major.
#[derive(Clone, Debug)]
pub struct Simulation {
    pub rows: usize,
    pub channels: usize,
    /// Noiseless bucket values `t · p_i`.
    pub clean: Vec<f64>,
    /// What the detector reports.
    pub values: Vec<f64>,
    pub noise: NoiseReport,
}

/// Simulates every pattern of `spec` against one transport per channel (each `width * height`
/// values, row-major), then applies `noise`. `progress`, if given, is advanced by one per pattern.
pub fn simulate(
    spec: &PatternSpec,
    transports: &[&[f32]],
    noise: &NoiseModel,
    progress: Option<&ProgressBar>,
) -> Simulation {
    let clean = bucket_signals(spec, transports, progress);
    let (values, report) = apply_noise(&clean, transports.len(), noise);
    Simulation {
        rows: spec.count() as usize,
        channels: transports.len(),
        clean,
        values,
        noise: report,
    }
}

fn threads_for(rows: usize) -> usize {
    let cpus = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    cpus.min(rows.div_ceil(64)).max(1)
}

/// Splits `out` (rows of `channels` values) over threads; `f(first_row, rows_chunk)`.
fn par_rows<F>(out: &mut [f64], channels: usize, f: F)
where
    F: Fn(usize, &mut [f64]) + Sync,
{
    let rows = out.len() / channels.max(1);
    if rows == 0 {
        return;
    }
    let per = rows.div_ceil(threads_for(rows));
    std::thread::scope(|s| {
        for (t, chunk) in out.chunks_mut(per * channels).enumerate() {
            let f = &f;
            s.spawn(move || f(t * per, chunk));
        }
    });
}

/// Noiseless bucket values `c[i * channels + j] = t_j · p_i` for i in 0..count, in f64.
///
/// Binary families take the packed-bits fast path (sum of `t` over the set bits); speckle uses
/// the grey levels. Parallel over patterns with scoped threads.
pub fn bucket_signals(
    spec: &PatternSpec,
    transports: &[&[f32]],
    progress: Option<&ProgressBar>,
) -> Vec<f64> {
    let k = spec.pixels();
    let channels = transports.len();
    assert!(channels > 0, "at least one channel");
    for t in transports {
        assert_eq!(t.len(), k, "each transport must have width * height values");
    }
    // Pixel-major interleaving: all channels of one pixel are adjacent.
    let interleaved: Vec<f64> = (0..k)
        .flat_map(|p| transports.iter().map(move |t| t[p] as f64))
        .collect();
    let generator = PatternGenerator::new(spec);
    let binary = spec.family().is_binary();
    let rows = spec.count() as usize;
    let mut out = vec![0.0f64; rows * channels];
    const TICK: usize = 1024;
    par_rows(&mut out, channels, |first, chunk| {
        let mut words = vec![0u64; generator.words_per_pattern()];
        let mut grey = if binary { Vec::new() } else { vec![0.0f32; k] };
        let mut pending = 0;
        for (r, row) in chunk.chunks_exact_mut(channels).enumerate() {
            let i = (first + r) as u64;
            if binary {
                generator.fill_bits(i, &mut words).expect("binary family");
                if channels == 1 {
                    // Hot path: one bucket, sum t over the set bits.
                    let mut acc = 0.0f64;
                    for (w, &word) in words.iter().enumerate() {
                        let base = &interleaved[w * 64..(w * 64 + 64).min(k)];
                        let mut bits = word;
                        while bits != 0 {
                            acc += base[bits.trailing_zeros() as usize];
                            bits &= bits - 1;
                        }
                    }
                    row[0] = acc;
                } else {
                    for (w, &word) in words.iter().enumerate() {
                        let mut bits = word;
                        while bits != 0 {
                            let p = w * 64 + bits.trailing_zeros() as usize;
                            bits &= bits - 1;
                            let t = &interleaved[p * channels..(p + 1) * channels];
                            for (acc, v) in row.iter_mut().zip(t) {
                                *acc += v;
                            }
                        }
                    }
                }
            } else {
                generator.fill_values(i, &mut grey);
                for (p, &g) in grey.iter().enumerate() {
                    if g != 0.0 {
                        let t = &interleaved[p * channels..(p + 1) * channels];
                        for (acc, v) in row.iter_mut().zip(t) {
                            *acc += g as f64 * v;
                        }
                    }
                }
            }
            pending += 1;
            if pending == TICK {
                if let Some(pb) = progress {
                    pb.inc(TICK as u64);
                }
                pending = 0;
            }
        }
        if let Some(pb) = progress {
            pb.inc(pending as u64);
        }
    });
    out
}

/// The drift factor of each of `rows` patterns: `max(0, 1 + x_i)`, `x` an AR(1) walk with
/// stationary standard deviation `model.drift` and correlation length `L` patterns
/// (`x_i = a x_{i-1} + sqrt(1 - a²) drift N(0,1)`, `a = exp(-1/L)`), started in its stationary law.
pub fn drift_factors(rows: usize, model: &NoiseModel) -> Vec<f64> {
    if model.drift == 0.0 {
        return vec![1.0; rows];
    }
    let length = model
        .drift_correlation
        .unwrap_or((rows as f64 / 20.0).max(16.0));
    let a = (-1.0 / length).exp();
    let kick = (1.0 - a * a).sqrt() * model.drift;
    let mut rng = SplitMix64::stream(model.seed, STAGE_DRIFT, 0);
    let mut x = model.drift * rng.normal();
    (0..rows)
        .map(|i| {
            if i > 0 {
                x = a * x + kick * rng.normal();
            }
            (1.0 + x).max(0.0)
        })
        .collect()
}

/// Applies `model` to noiseless values (`rows x channels`, row-major); see the module docs for
/// the order and formulas. Returns the noisy values and per-channel figures.
pub fn apply_noise(clean: &[f64], channels: usize, model: &NoiseModel) -> (Vec<f64>, NoiseReport) {
    assert!(channels > 0 && clean.len().is_multiple_of(channels));
    let rows = clean.len() / channels;
    let drift = drift_factors(rows, model);

    struct Plan {
        alpha: Option<f64>,
        sigma: Option<f64>,
        full_scale: Option<f64>,
        step: f64,
    }
    let mut stats = Vec::with_capacity(channels);
    let plans: Vec<Plan> = (0..channels)
        .map(|j| {
            let column = clean.iter().skip(j).step_by(channels);
            let (mut sum, mut sum_sq, mut max) = (0.0f64, 0.0f64, 0.0f64);
            for &c in column {
                sum += c;
                sum_sq += c * c;
                max = max.max(c);
            }
            let mean = sum / rows.max(1) as f64;
            let rms = (sum_sq / rows.max(1) as f64).sqrt();
            stats.push(mean);
            let alpha = model.photons.filter(|_| mean > 0.0).map(|n| n / mean);
            let sigma = model.snr_db.map(|db| rms / 10f64.powf(db / 20.0));
            let full_scale = model.adc_bits.map(|_| max * 1.1 + model.dark);
            let levels = model
                .adc_bits
                .map(|b| ((1u64 << b) - 1) as f64)
                .unwrap_or(1.0);
            let step = full_scale.map(|fs| fs / levels).unwrap_or(0.0);
            Plan {
                alpha,
                sigma,
                full_scale,
                step,
            }
        })
        .collect();

    let saturated: Vec<AtomicUsize> = (0..channels).map(|_| AtomicUsize::new(0)).collect();
    let mut values = clean.to_vec();
    par_rows(&mut values, channels, |first, chunk| {
        for (r, row) in chunk.chunks_exact_mut(channels).enumerate() {
            let i = first + r;
            let mut rng = SplitMix64::stream(model.seed, STAGE_ROW, i as u64);
            for (j, v) in row.iter_mut().enumerate() {
                let plan = &plans[j];
                let mut x = *v * drift[i];
                if let Some(alpha) = plan.alpha {
                    x = rng.poisson(alpha * x) / alpha;
                }
                if let Some(sigma) = plan.sigma {
                    x += sigma * rng.normal();
                }
                x += model.dark;
                if let Some(fs) = plan.full_scale {
                    if x >= fs {
                        saturated[j].fetch_add(1, Ordering::Relaxed);
                    }
                    x = x.clamp(0.0, fs);
                    if plan.step > 0.0 {
                        x = ((x / plan.step).round() * plan.step).min(fs);
                    }
                }
                *v = x;
            }
        }
    });

    let report_channels = (0..channels)
        .map(|j| {
            let (mut sig, mut err) = (0.0f64, 0.0f64);
            for i in 0..rows {
                let c = clean[i * channels + j];
                sig += c * c;
                err += (values[i * channels + j] - model.dark - c).powi(2);
            }
            let plan = &plans[j];
            ChannelNoise {
                mean_signal: stats[j],
                photons_per_unit: plan.alpha,
                read_sigma: plan.sigma,
                full_scale: plan.full_scale,
                saturated: saturated[j].load(Ordering::Relaxed),
                effective_snr_db: if err > 0.0 {
                    10.0 * (sig / err).log10()
                } else {
                    f64::INFINITY
                },
            }
        })
        .collect();
    let (drift_min, drift_max) = drift
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &f| {
            (lo.min(f), hi.max(f))
        });
    let report = NoiseReport {
        channels: report_channels,
        drift_min: if rows == 0 { 1.0 } else { drift_min },
        drift_max: if rows == 0 { 1.0 } else { drift_max },
    };
    (values, report)
}

#[cfg(test)]
mod tests;
