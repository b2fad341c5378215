//! The iterative methods as service methods: `cs` (l1 in an orthonormal transform, t >= 0, by
//! FISTA), `tv` (isotropic total variation, t >= 0), `lsq` (least squares / Tikhonov by CGLS) and
//! `auto` (the data choose the model, [`super::auto`]).
//!
//! All rows are loaded (n x channels values), the pattern family's matrix-free operator is planned
//! once, and each channel is solved on it. Hadamard sessions are solved on the split-pair
//! differences `(y+ - y-) / sqrt(k)` against the orthonormal `H / sqrt(k)` (a dark level cancels);
//! 0/1 families rely on the solvers' automatic mean deflation (the common mode of 0/1 patterns).
//!
//! Error estimate: every channel is first fitted without the held-out rows ([`holdout`]) and
//! scored on them; the served image is then refitted on all rows, warm-started from that fit
//! (the refit costs a fraction of a cold solve). With too few rows to hold any out, the image is
//! fitted once and the report says why there is no estimate.
//!
//! `noise: "poisson"`: the penalised Poisson likelihood by IRLS ([`solve::poisson_irls`]), for
//! photon-counting buckets (never negative, weights from the model).

use serde_json::{Value, json};

use super::auto;
use super::fit::{Offset, Scorer, fit_model, fitting};
use super::holdout::{self, Score};
use super::linop::LinearOperator;
use super::method::{Fit, MethodConfig, Model};
use super::noise::{self, NoiseEstimate};
use super::ops::{self, BernoulliOperator, HaarSubsetOperator, HadamardOperator, RowSubset};
use super::solve::{self, Lambda, Solution, SolveOptions};
use super::stream::RowStream;
use super::{BucketSource, Control, DualImage, Problem, ReconError, Reconstruction, Report};
use helmholtz_proto::{Family, PatternSpec};

/// The session's measurement operator, planned once, and the data each channel is solved on.
pub(crate) struct Planned<'a> {
    spec: &'a PatternSpec,
    op: PlannedOp,
    /// Per channel: the buckets (Hadamard: split-pair differences / sqrt(k)).
    pub data: Vec<Vec<f64>>,
    /// Per channel: the noise of `data` as the session shows it ([`noise`]), where the design
    /// allows an estimate (Hadamard split pairs, Bernoulli rows).
    pub noise: Vec<Option<NoiseEstimate>>,
    /// `adaptive_haar` sessions, per channel: every row's noise from the pair sums of equal
    /// supports ([`noise::from_support_groups`]). (Measured on `adaptive_hadamard` too, where
    /// every pair has one support and one noise level: under read noise it lost 0.4-2.1 dB on
    /// the photo and the shapes against the held-out choice alone, noise-free it gained at most
    /// 0.4 dB: not used there.)
    pub row_noise: Vec<Option<auto::RowNoise>>,
    pub details: serde_json::Map<String, Value>,
}

enum PlannedOp {
    Bernoulli(BernoulliOperator),
    Hadamard(HadamardOperator),
    Haar(HaarSubsetOperator),
    Other(Box<dyn LinearOperator>),
}

impl<'a> Planned<'a> {
    /// `declared`: a read noise per frame the request declares (`auto`'s `read_noise`, bucket
    /// units); it replaces the session's own estimate in `noise` and `row_noise`, which
    /// `details.noise_declared` keeps beside it.
    pub fn load(
        problem: &Problem<'a>,
        source: &mut dyn BucketSource,
        control: &Control,
        declared: Option<crate::method::ReadNoise>,
    ) -> Result<Self, ReconError> {
        let spec = problem.spec;
        let channels = problem.channels;
        let mut buckets = Vec::with_capacity(problem.rows as usize * channels);
        let mut rows = RowStream::new(source, control, channels, problem.rows)?;
        while let Some(block) = rows.next_block()? {
            buckets.extend_from_slice(&block.values);
        }
        let unsolvable = |e: ops::OpError| ReconError::Unsolvable(e.to_string());
        let mut details = serde_json::Map::new();
        let mut row_noise = vec![None; channels];
        let (op, data, noise) = match spec.family() {
            Family::AdaptiveHaar { .. } => {
                let frames = problem.rows - problem.rows % 2;
                if frames == 0 {
                    return Err(ReconError::Unsolvable(
                        "adaptive_haar needs at least one P+/P- pair of frames; the session has 1 frame"
                            .into(),
                    ));
                }
                let op = HaarSubsetOperator::from_spec(spec, frames).map_err(unsolvable)?;
                let used = &buckets[..frames as usize * channels];
                let indices: Vec<u32> = op.indices().iter().map(|&n| n as u32).collect();
                let all = crate::adaptive::pair_coefficients(spec, &indices, channels, used);
                let data: Vec<Vec<f64>> = (0..channels)
                    .map(|ch| all.iter().skip(ch).step_by(channels).copied().collect())
                    .collect();
                details.insert(
                    "data".into(),
                    json!("split-pair differences (y+ - y-)/2^s, s the Haar function's scale"),
                );
                // The pair sums light supports of every size: no one noise level for the held-out
                // comparisons; per support, they give every row's ([`auto::RowNoise`]).
                let w = spec.width();
                let (support, mut gains): (Vec<u64>, Vec<f64>) =
                    indices.iter().map(|&n| noise::haar_support(w, n)).unzip();
                // Pairs decoded from single frames: row r's y+ - y- has the variance f_r sigma^2,
                // not 2 sigma^2; its datum's noise is that of a pair of gain g_r sqrt(2 / f_r).
                let single = declared.is_some_and(|d| d.single_frames);
                if single {
                    let f = crate::adaptive::single_frame_pair_variances(w, &indices);
                    for (g, f) in gains.iter_mut().zip(f) {
                        *g *= (2.0 / f).sqrt();
                    }
                }
                let declared = declared.map(|d| d.sigma);
                let basis = crate::adaptive::Basis::Haar;
                let levels: Vec<u32> = indices.iter().map(|&n| basis.level(w, n)).collect();
                let mut own = Vec::with_capacity(channels);
                for (ch, slot) in row_noise.iter_mut().enumerate() {
                    let sums: Vec<f64> = (0..indices.len())
                        .map(|j| used[2 * j * channels + ch] + used[(2 * j + 1) * channels + ch])
                        .collect();
                    let estimate = noise::from_support_groups(&sums, &support);
                    own.push(json!(estimate));
                    *slot = declared
                        .map(noise::SupportNoise::declared)
                        .or(estimate)
                        .map(|noise| auto::RowNoise {
                            gains: gains.clone(),
                            levels: levels.clone(),
                            noise,
                            measured: None,
                            min_factor: auto::MIN_GROUP_FACTOR,
                        });
                }
                if let Some(sigma) = declared {
                    details.insert(
                        "noise_declared".into(),
                        json!({
                            "read_noise": sigma,
                            "pair_variance": if single {
                                json!("per pair, from the single frames it was decoded from")
                            } else {
                                json!(2.0 * sigma * sigma)
                            },
                            "session_estimate": own,
                        }),
                    );
                }
                (PlannedOp::Haar(op), data, vec![None; channels])
            }
            Family::Hadamard { .. } | Family::AdaptiveHadamard { .. } => {
                // Only whole P+/P- pairs are used.
                let frames = problem.rows - problem.rows % 2;
                if frames == 0 {
                    return Err(ReconError::Unsolvable(
                        "Hadamard needs at least one P+/P- pair of frames; the session has 1 frame"
                            .into(),
                    ));
                }
                let op = HadamardOperator::from_spec(spec, frames).map_err(unsolvable)?;
                let used = &buckets[..frames as usize * channels];
                let pairs: Vec<_> = (0..channels)
                    .map(|ch| op.split_pairs_channel(used, channels, ch))
                    .collect();
                let scale = 1.0 / (spec.pixels() as f64).sqrt();
                let mut noise: Vec<Option<noise::NoiseEstimate>> = pairs
                    .iter()
                    .map(|p| noise::from_pair_sums(&p.sums, scale, &p.data))
                    .collect();
                if let Some(sigma) = declared.map(|d| d.sigma) {
                    // A pair difference has the variance of two frames; the datum is it / sqrt(k).
                    let datum = std::f64::consts::SQRT_2 * sigma * scale;
                    details.insert(
                        "noise_declared".into(),
                        json!({"read_noise": sigma, "datum_sigma": datum, "session_estimate": noise}),
                    );
                    noise = pairs
                        .iter()
                        .map(|p| Some(noise::NoiseEstimate::declared(datum, &p.data)))
                        .collect();
                }
                // Every pair lights half the grid, so the pair sums' noise estimate
                // (drift-free) is every row's, for the consistency step
                // ([`auto::Consistency`]). The data are fitted as measured: denoising them
                // ([`auto::RowNoise::denoised`]) lost up to 9 dB under noise on
                // `adaptive_hadamard`.
                let size = (spec.width() as usize, spec.height() as usize);
                for (slot, e) in row_noise.iter_mut().zip(&noise) {
                    *slot = e
                        .as_ref()
                        .map(|e| auto::RowNoise::walsh(e, scale, op.natural_indices(), size));
                }
                let data = pairs.into_iter().map(|p| p.data).collect();
                details.insert(
                    "data".into(),
                    json!("split-pair differences (y+ - y-)/sqrt(k)"),
                );
                (PlannedOp::Hadamard(op), data, noise)
            }
            family => {
                let data: Vec<Vec<f64>> = (0..channels)
                    .map(|ch| buckets.iter().skip(ch).step_by(channels).copied().collect())
                    .collect();
                let op = if family.is_binary() {
                    PlannedOp::Bernoulli(
                        BernoulliOperator::from_spec(spec, problem.rows).map_err(unsolvable)?,
                    )
                } else {
                    PlannedOp::Other(
                        ops::try_measurement_operator(spec, problem.rows).map_err(unsolvable)?,
                    )
                };
                let mut noise: Vec<Option<NoiseEstimate>> = match (family, &op) {
                    (Family::Bernoulli { .. }, PlannedOp::Bernoulli(a)) => {
                        data.iter().map(|b| noise::from_random_rows(a, b)).collect()
                    }
                    _ => vec![None; channels],
                };
                if let Some(sigma) = declared.map(|d| d.sigma) {
                    details.insert(
                        "noise_declared".into(),
                        json!({"read_noise": sigma, "datum_sigma": sigma, "session_estimate": noise}),
                    );
                    noise = data
                        .iter()
                        .map(|b| Some(NoiseEstimate::declared(sigma, b)))
                        .collect();
                }
                (op, data, noise)
            }
        };
        Ok(Planned {
            spec,
            op,
            data,
            noise,
            row_noise,
            details,
        })
    }

    pub fn op(&self) -> &dyn LinearOperator {
        match &self.op {
            PlannedOp::Bernoulli(op) => op,
            PlannedOp::Hadamard(op) => op,
            PlannedOp::Haar(op) => op,
            PlannedOp::Other(op) => op.as_ref(),
        }
    }

    /// A cold start for the iterative fits: for Hadamard split pairs (orthonormal rows) the
    /// zero-filled inverse `A^T b` clipped at 0, which already satisfies the data on the
    /// measured coefficients (the solvers then only have to shape the unmeasured ones); `None`
    /// (the solvers' own start) for the other families, where `A^T b` is a correlation image,
    /// not an estimate of `t`.
    pub fn cold_start(op: &dyn LinearOperator, b: &[f64], hadamard: bool) -> Option<Vec<f64>> {
        hadamard.then(|| {
            let mut t = vec![0.0; op.cols()];
            op.adjoint(b, &mut t);
            t.iter_mut().for_each(|v| *v = v.max(0.0));
            t
        })
    }

    /// What the error estimate needs to know about the rows ([`auto::Design`]).
    pub fn design(&self) -> auto::Design {
        match (&self.op, self.spec.family()) {
            (PlannedOp::Hadamard(op), _) => auto::Design::Orthonormal {
                measured: op.natural_indices().to_vec(),
            },
            // Orthonormal rows, but not Walsh-Hadamard ones: no extrapolation of the unmeasured
            // energy by Hadamard level.
            (PlannedOp::Haar(_), _) => auto::Design::Orthonormal {
                measured: Vec::new(),
            },
            (PlannedOp::Bernoulli(op), Family::Bernoulli { .. }) => {
                // The rows' actual fill (the operator keeps the pattern sums).
                let sums = op.row_sums();
                let k = self.spec.pixels() as f64;
                let p = sums.iter().sum::<f64>() / (sums.len().max(1) as f64 * k);
                auto::Design::Random {
                    variance: p * (1.0 - p),
                }
            }
            _ => auto::Design::Other,
        }
    }

    /// Split pairs over their gain: orthonormal rows (Hadamard, adaptive Hadamard or Haar).
    pub fn has_orthonormal_rows(&self) -> bool {
        matches!(self.op, PlannedOp::Hadamard(_) | PlannedOp::Haar(_))
    }

    /// Structured designs: the finest grid the rows measure (see [`auto::Channel`]).
    pub fn measured_resolution(&self) -> Option<(usize, usize)> {
        match &self.op {
            PlannedOp::Hadamard(op) => Some(op.finest_resolution()),
            PlannedOp::Haar(op) => Some(op.finest_resolution()),
            _ => None,
        }
    }

    /// Rows the operator has (Hadamard: pairs).
    pub fn rows(&self) -> usize {
        self.op().rows()
    }

    /// The operator of a subset of the rows.
    pub fn subset(&self, rows: &[usize]) -> Result<Box<dyn LinearOperator>, ReconError> {
        Ok(match &self.op {
            PlannedOp::Bernoulli(op) => Box::new(op.select_rows(rows)),
            PlannedOp::Hadamard(op) => Box::new(op.select_rows(rows)),
            PlannedOp::Haar(op) => Box::new(op.select_rows(rows)),
            PlannedOp::Other(op) => {
                let again = ops::try_measurement_operator(self.spec, op.rows() as u64)
                    .map_err(|e| ReconError::Unsolvable(e.to_string()))?;
                Box::new(RowSubset::new(again, rows.to_vec()))
            }
        })
    }
}

/// The share of an adaptive session's rows, the last measured, that judge `auto`'s
/// fill-in of the coefficients no row measured ([`auto::FillIn`]).
const PREQUENTIAL_SHARE: f64 = 0.2;

/// `values[rows]`.
pub(crate) fn gather(values: &[f64], rows: &[usize]) -> Vec<f64> {
    rows.iter().map(|&r| values[r]).collect()
}

/// The image's total light, where one row of `op` measures it and every other row is
/// orthogonal to it: `op 1` is `sqrt(k)` on that row (the constant `1 / sqrt(k)`, which is
/// the all-on Hadamard or coarsest Haar pair over `sqrt(k)`) and 0 elsewhere. Then `sum t`
/// is `sqrt(k)` times that datum, and only that datum; `cs` and `tv` hold it
/// ([`SolveOptions::total`]). `None` for any other design (random rows, a centred operator
/// with a fitted offset, a subset without that pair).
fn measured_total(op: &dyn LinearOperator, b: &[f64]) -> Option<f64> {
    let k = op.cols();
    let mut ones = vec![0.0; op.rows()];
    op.apply(&vec![1.0; k], &mut ones);
    let root = (k as f64).sqrt();
    let close = |v: f64, to: f64| (v - to).abs() <= 1e-9 * root;
    let dc = ones.iter().position(|&v| close(v, root))?;
    let others_zero = ones
        .iter()
        .enumerate()
        .all(|(i, &v)| i == dc || close(v, 0.0));
    others_zero.then(|| root * b[dc])
}

/// Noise above rounding: the estimate's lower bound above `1e-6` of the data's spread
/// (noise-free simulated pairs read ~1e-16).
fn is_noisy(noise: Option<&NoiseEstimate>) -> bool {
    noise.is_some_and(|e| e.relative() > 1e-6)
}

/// How far (relative) a fit's light may stray from the total a pair measures before the fit
/// is solved again holding it ([`holding_total`]).
const TOTAL_TOLERANCE: f64 = 1e-3;

/// Where one pair measures the total ([`measured_total`]), `solve` holding it
/// ([`SolveOptions::total`]). Holding it costs every TV prox iteration a threshold (about
/// twice the time of `tv` on 128x128 pairs), which a fit that keeps its light by itself does
/// not need: noise-free and bright, the fits' light was the datum's to 1e-4. So on data the
/// session finds noise-free (`noisy` false) the fit is solved as asked, and solved again
/// holding the total (from its image and dual, the iterations of both reported) only where
/// its light strays from it by more than [`TOTAL_TOLERANCE`]; under noise, where the light
/// strays always (by 3 to 28 % for `cs` and `tv` from 10 % of the pairs of 15 scenes at 30 dB),
/// the total is held from the start.
fn holding_total(
    op: &dyn LinearOperator,
    b: &[f64],
    opts: &SolveOptions,
    noisy: bool,
    solve: impl Fn(&SolveOptions) -> Result<Solution, ReconError>,
) -> Result<Solution, ReconError> {
    let Some(total) = measured_total(op, b).filter(|_| opts.nonnegative) else {
        return solve(opts);
    };
    if noisy {
        return solve(&SolveOptions {
            total: Some(total),
            ..opts.clone()
        });
    }
    let first = solve(opts)?;
    let light: f64 = first.t.iter().sum();
    if (light - total).abs() <= TOTAL_TOLERANCE * total.abs() {
        return Ok(first);
    }
    let held = SolveOptions {
        total: Some(total),
        warm_start: Some(first.t.clone()),
        warm_dual: first.dual.clone(),
        progress: (opts.progress.1, opts.progress.1),
        ..opts.clone()
    };
    let mut second = solve(&held)?;
    let r = &mut second.report;
    r.iterations += first.report.iterations;
    r.inner_iterations += first.report.inner_iterations;
    r.restarts += first.report.restarts;
    r.seconds += first.report.seconds;
    Ok(second)
}

/// `noisy`: the session's noise estimate is above rounding ([`holding_total`]).
fn fit_fixed(
    config: &MethodConfig,
    size: (usize, usize),
    (op, b, noisy): (&dyn LinearOperator, &[f64], bool),
    opts: SolveOptions,
    control: &Control,
) -> Result<Solution, ReconError> {
    match config {
        MethodConfig::Cs {
            transform,
            lambda,
            max_iter,
            fit,
        } => {
            let o = SolveOptions {
                lambda: Lambda::Relative(*lambda),
                max_iter: *max_iter,
                ..opts
            };
            holding_total(op, b, &o, noisy, |o| {
                fit_model(Model::L1(*transform), size, op, b, fit.noise, o, control)
            })
        }
        MethodConfig::Tv {
            lambda,
            max_iter,
            fit,
        } => {
            let o = SolveOptions {
                lambda: Lambda::Relative(*lambda),
                max_iter: *max_iter,
                accelerated_prox: true,
                ..opts
            };
            holding_total(op, b, &o, noisy, |o| {
                fit_model(Model::Tv, size, op, b, fit.noise, o, control)
            })
        }
        MethodConfig::Lsq { mu, max_iter, .. } => {
            let o = SolveOptions {
                max_iter: *max_iter,
                nonnegative: false,
                ..opts
            };
            solve::cgls(op, b, *mu, &o, control)
        }
        other => unreachable!("fit_fixed called for {}", other.name()),
    }
}

pub fn run(
    problem: &Problem,
    config: &MethodConfig,
    source: &mut dyn BucketSource,
    control: &Control,
) -> Result<Reconstruction, ReconError> {
    let spec = problem.spec;
    let channels = problem.channels;
    let size = (spec.width() as usize, spec.height() as usize);
    let fit: Fit = config.fit().expect("an iterative method");
    let declared = match config {
        MethodConfig::Auto { read_noise, .. } => *read_noise,
        _ => None,
    };
    let planned = Planned::load(problem, source, control, declared)?;
    let offset = fit.fits_offset(spec.family());
    // `auto` judges its choices on the held-out rows: where the session's own noise estimate
    // says the noise is most of what the buckets vary by, a tenth of the rows cannot tell
    // fits apart ([`holdout::noisy_fraction`]), so more are held out.
    let relative_noise = planned
        .noise
        .iter()
        .flatten()
        .map(|e| e.relative())
        .fold(0.0, f64::max);
    let fraction = fit.holdout.unwrap_or_else(|| {
        let base = holdout::default_fraction(planned.rows());
        match config {
            MethodConfig::Auto { .. } => base.max(holdout::noisy_fraction(relative_noise)),
            _ => base,
        }
    });
    // (Held out at random, also for adaptive sessions. Holding out an adaptive_haar session's
    // last pairs instead, which resemble the unmeasured ones more, measured: +2.9 dB on the
    // relief at 25 % but -22 dB on a piecewise-smooth 64x64 scene (the flat image won where TV
    // fills in to 62.6 dB), and on adaptive_hadamard -3.6 to -6.9 dB under read noise.)
    let split = holdout::split(planned.rows(), fraction);
    if let (MethodConfig::Auto { .. }, Err(why)) = (config, &split) {
        return Err(ReconError::Unsolvable(format!(
            "auto chooses its model by held-out error and cannot here: {why}. Use tv or cs with a fixed lambda, or a larger holdout"
        )));
    }
    let parts = match &split {
        Ok(s) => Some((planned.subset(&s.train)?, planned.subset(&s.test)?)),
        Err(_) => None,
    };
    // `auto` on random-pattern rows under noise checks its weight on folds of all the rows
    // ([`auto::Fold`]; the same rows for every channel). The folds are views of the session's
    // operator: no copy of its patterns (five copies at 256x256 from 10 % rows would be
    // 540 MB), for a product that costs the whole operator's (the fold stage 1.72 -> 1.94 s on
    // the coffee, 128x128 from 10 % Bernoulli rows at 30 dB).
    let folds = match (config, planned.design(), &split) {
        (MethodConfig::Auto { folds, .. }, auto::Design::Random { .. }, Ok(_))
            if *folds > 0 && planned.noise.iter().any(|e| auto::folds_apply(e.as_ref())) =>
        {
            (0..*folds)
                .map(|j| {
                    let (train, test) = auto::fold_rows(planned.rows(), j, *folds);
                    let view = |rows: &[usize]| -> Box<dyn LinearOperator + '_> {
                        Box::new(RowSubset::new(Box::new(planned.op()), rows.to_vec()))
                    };
                    Ok::<_, ReconError>((view(&train), view(&test), train, test))
                })
                .collect::<Result<Vec<_>, ReconError>>()?
        }
        _ => Vec::new(),
    };
    // Too few rows for every fold to score some: the race's held-out set alone chooses.
    let folds = match folds.iter().all(|f| f.3.len() >= holdout::MIN_HELD_OUT) {
        true => folds,
        false => Vec::new(),
    };
    let mut score = Score::new(channels);
    let mut images = Vec::with_capacity(channels);
    let mut channel_reports = Vec::with_capacity(channels);
    let mut iterations = 0u64;
    for ch in 0..channels {
        let b = &planned.data[ch];
        let span = (
            ch as f64 / channels as f64,
            (ch + 1) as f64 / channels as f64,
        );
        let mid = span.0 + 0.6 * (span.1 - span.0);
        // A fixed-weight method's fit ([`fit_fixed`]), with this channel's noise.
        let noisy = is_noisy(planned.noise[ch].as_ref());
        let fixed = |op: &dyn LinearOperator, b: &[f64], opts: SolveOptions| {
            fit_fixed(config, size, (op, b, noisy), opts, control)
        };
        let (t, report) = match (config, &split, &parts) {
            (
                MethodConfig::Auto {
                    models,
                    max_iter,
                    fit,
                    ..
                },
                Ok(split),
                Some((train, test)),
            ) => {
                // adaptive_haar: the model is fitted to the data shrunk by their noise
                // ([`auto::RowNoise::denoised`]); the measured values go back in at the end.
                let mut row_noise = planned.row_noise[ch].clone();
                let denoise = matches!(planned.spec.family(), Family::AdaptiveHaar { .. });
                let denoised = row_noise.as_mut().filter(|_| denoise).map(|rows| {
                    rows.measured = Some(b.clone());
                    rows.denoised(b)
                });
                let b = denoised.as_ref().unwrap_or(b);
                // Adaptive sessions: their rows in the order measured, split where they were.
                let n = planned.rows();
                let cut = n - ((n as f64 * PREQUENTIAL_SHARE).round() as usize).min(n);
                let adaptive = matches!(
                    planned.spec.family(),
                    Family::AdaptiveHaar { .. } | Family::AdaptiveHadamard { .. }
                );
                let ordered = match adaptive {
                    true if cut >= holdout::MIN_HELD_OUT && n - cut >= holdout::MIN_HELD_OUT => {
                        let first: Vec<usize> = (0..cut).collect();
                        let last: Vec<usize> = (cut..n).collect();
                        Some((planned.subset(&first)?, planned.subset(&last)?, first, last))
                    }
                    _ => None,
                };
                let job = auto::Channel {
                    size,
                    full: planned.op(),
                    train: train.as_ref(),
                    test: test.as_ref(),
                    b,
                    b_train: gather(b, &split.train),
                    b_test: gather(b, &split.test),
                    measured_resolution: planned.measured_resolution(),
                    offset,
                    noise: planned.noise[ch],
                    design: planned.design(),
                    row_noise,
                    prequential: ordered.as_ref().map(|(prefix, suffix, first, last)| {
                        auto::Prequential {
                            prefix: prefix.as_ref(),
                            suffix: suffix.as_ref(),
                            b_prefix: gather(b, first),
                            d_suffix: gather(&planned.data[ch], last),
                        }
                    }),
                    folds: match auto::folds_apply(planned.noise[ch].as_ref()) {
                        true => folds
                            .iter()
                            .map(|(train, test, rows_train, rows_test)| auto::Fold {
                                train: train.as_ref(),
                                test: test.as_ref(),
                                b_train: gather(b, rows_train),
                                b_test: gather(b, rows_test),
                            })
                            .collect(),
                        false => Vec::new(),
                    },
                    sure: !adaptive
                        && matches!(config, MethodConfig::Auto { folds, .. } if *folds > 0),
                };
                let out = auto::run(&job, models, *max_iter, *fit, span, control)?;
                score.add_channel(ch, &job.b_test, &out.held_out_prediction);
                iterations += out.iterations as u64;
                (out.t, out.report)
            }
            (MethodConfig::Auto { .. }, _, _) => unreachable!("refused above"),
            (_, Ok(split), Some((train, test))) => {
                let b_train = gather(b, &split.train);
                let (op_fit, b_fit) = fitting(train.as_ref(), &b_train, offset);
                let warm_start =
                    Planned::cold_start(op_fit.as_ref(), &b_fit, planned.has_orthonormal_rows());
                let opts = SolveOptions {
                    progress: (span.0, mid),
                    warm_start,
                    ..SolveOptions::default()
                };
                let first = fixed(op_fit.as_ref(), &b_fit, opts)?;
                let scorer = Scorer {
                    test: test.as_ref(),
                    offset: offset.then(|| Offset::new(train.as_ref(), &b_train)),
                };
                score.add_channel(ch, &gather(b, &split.test), &scorer.predict(&first.t));
                let (op_fit, b_fit) = fitting(planned.op(), b, offset);
                let opts = SolveOptions {
                    progress: (mid, span.1),
                    warm_start: Some(first.t),
                    warm_dual: first.dual,
                    ..SolveOptions::default()
                };
                let sol = fixed(op_fit.as_ref(), &b_fit, opts)?;
                iterations += (first.report.iterations + sol.report.iterations) as u64;
                let mut report = json!({"held_out_fit": first.report, "fit": sol.report});
                if offset {
                    report["offset"] = json!(Offset::new(planned.op(), b).at(&sol.t));
                }
                (sol.t, report)
            }
            _ => {
                let (op_fit, b_fit) = fitting(planned.op(), b, offset);
                let warm_start =
                    Planned::cold_start(op_fit.as_ref(), &b_fit, planned.has_orthonormal_rows());
                let opts = SolveOptions {
                    progress: span,
                    warm_start,
                    ..SolveOptions::default()
                };
                let sol = fixed(op_fit.as_ref(), &b_fit, opts)?;
                iterations += sol.report.iterations as u64;
                let mut report = json!({"fit": sol.report});
                if offset {
                    report["offset"] = json!(Offset::new(planned.op(), b).at(&sol.t));
                }
                (sol.t, report)
            }
        };
        if let Some(i) = t.iter().position(|v| !v.is_finite()) {
            return Err(ReconError::Unsolvable(format!(
                "the solver produced a non-finite value at pixel {i}"
            )));
        }
        images.push(DualImage {
            width: spec.width(),
            height: spec.height(),
            data: t.iter().map(|&v| v as f32).collect(),
        });
        channel_reports.push(report);
    }
    control.set_progress(1.0);
    let mut details = planned.details.clone();
    let key = if matches!(config, MethodConfig::Auto { .. }) {
        "auto"
    } else {
        "solver"
    };
    details.insert(key.into(), Value::Array(channel_reports));
    details.insert("operator_rows".into(), json!(planned.rows()));
    // Per channel (null where the design allows no estimate): see [`noise`].
    details.insert("noise_estimate".into(), json!(planned.noise));
    details.insert(
        "offset".into(),
        json!(if offset {
            "fitted: buckets = A t + d, d unknown (reported per channel)"
        } else {
            "none: buckets = A t"
        }),
    );
    let (held_out, held_out_unavailable) = match &split {
        Ok(s) => (Some(score.finish(s.fraction)), None),
        Err(why) => (None, Some(why.clone())),
    };
    Ok(Reconstruction {
        images,
        report: Report {
            method: config.name().into(),
            params: config.params_json(),
            rows_used: problem.rows,
            iterations,
            details,
            held_out,
            held_out_unavailable,
        },
    })
}

#[cfg(test)]
mod tests {
    use helmholtz_proto::{HadamardOrdering, PatternGenerator, PatternSpec};

    use super::*;
    use crate::{SliceSource, metrics, reconstruct};

    /// Two flat rectangles on a dim background: piecewise constant, sparse in Haar and in TV.
    fn blocks(w: usize, h: usize) -> Vec<f32> {
        let mut t = vec![0.05f32; w * h];
        for y in 0..h {
            for x in 0..w {
                if (4..14).contains(&x) && (6..20).contains(&y) {
                    t[y * w + x] = 1.0;
                }
                if (18..28).contains(&x) && (10..26).contains(&y) {
                    t[y * w + x] = 0.6;
                }
            }
        }
        t
    }

    fn buckets(spec: &PatternSpec, t: &[f32], offset: f64) -> Vec<f64> {
        let g = PatternGenerator::new(spec);
        let mut p = vec![0f32; spec.pixels()];
        (0..spec.count())
            .map(|i| {
                g.fill_values(i, &mut p);
                p.iter()
                    .zip(t)
                    .map(|(a, b)| *a as f64 * *b as f64)
                    .sum::<f64>()
                    + offset
            })
            .collect()
    }

    fn solve(spec: &PatternSpec, c: &[f64], method: &str, params: Value) -> Vec<f32> {
        let config = MethodConfig::parse(method, &params).unwrap();
        let problem = Problem {
            spec,
            channels: 1,
            rows: spec.count(),
        };
        let r = reconstruct(
            &problem,
            &config,
            &mut SliceSource::new(c, 1, 1000),
            &Control::new(),
        )
        .unwrap();
        let image = r.images.into_iter().next().unwrap().data;
        assert!(
            image.iter().all(|v| v.is_finite()),
            "{method}: non-finite pixel"
        );
        image
    }

    #[test]
    fn compressive_methods_beat_least_squares_on_30_percent_bernoulli() {
        let (w, h) = (32, 32);
        let truth = blocks(w, h);
        let spec =
            PatternSpec::new(Family::Bernoulli { fill: 0.5 }, w as u32, h as u32, 307, 5).unwrap();
        let c = buckets(&spec, &truth, 0.0);
        let lsq = metrics::psnr(&solve(&spec, &c, "lsq", json!({})), &truth);
        let tv_img = solve(&spec, &c, "tv", json!({}));
        let cs_img = solve(&spec, &c, "cs", json!({"transform": "haar"}));
        assert!(
            tv_img.iter().chain(&cs_img).all(|&v| v >= 0.0),
            "transport is never negative"
        );
        let (tv, cs) = (
            metrics::psnr(&tv_img, &truth),
            metrics::psnr(&cs_img, &truth),
        );
        // Noise-free, piecewise-constant scene: TV is near exact, Haar-l1 far above the min-norm
        // least-squares image (which spreads the missing 70 % of the information as noise).
        assert!(tv > 30.0, "tv {tv:.1} dB");
        assert!(cs > lsq + 5.0, "cs {cs:.1} dB vs lsq {lsq:.1} dB");
    }

    /// The all-on pair gives the image's total ([`measured_total`]); rows without it, random
    /// rows, and the centred operator of a fitted offset give none.
    #[test]
    fn the_total_is_read_from_the_all_on_pair_and_from_no_other_design() {
        let (w, h) = (32, 32);
        let truth = blocks(w, h);
        let total: f64 = truth.iter().map(|&v| v as f64).sum();
        let ordering = HadamardOrdering::RussianDoll;
        let spec =
            PatternSpec::new(Family::Hadamard { ordering }, w as u32, h as u32, 300, 0).unwrap();
        let planned = plan(&spec, &buckets(&spec, &truth, 2.0));
        let b = &planned.data[0];
        let got = measured_total(planned.op(), b).expect("the all-on pair measures the total");
        assert!((got - total).abs() < 1e-9 * total, "{got} against {total}");
        let rest: Vec<usize> = (1..planned.rows()).collect();
        let without = planned.subset(&rest).unwrap();
        assert_eq!(measured_total(without.as_ref(), &gather(b, &rest)), None);
        let (centred, cb) = fitting(planned.op(), b, true);
        assert_eq!(measured_total(centred.as_ref(), &cb), None);

        let spec =
            PatternSpec::new(Family::Bernoulli { fill: 0.5 }, w as u32, h as u32, 300, 3).unwrap();
        let planned = plan(&spec, &buckets(&spec, &truth, 0.0));
        assert_eq!(measured_total(planned.op(), &planned.data[0]), None);
    }

    /// One channel's buckets, planned as a reconstruction plans them.
    fn plan<'a>(spec: &'a PatternSpec, c: &[f64]) -> Planned<'a> {
        let problem = Problem {
            spec,
            channels: 1,
            rows: spec.count(),
        };
        let mut source = SliceSource::new(c, 1, 1000);
        Planned::load(&problem, &mut source, &Control::new(), None).unwrap()
    }

    #[test]
    fn hadamard_split_pairs_cancel_a_dark_level() {
        let (w, h) = (32, 32);
        let truth = blocks(w, h);
        let ordering = HadamardOrdering::RussianDoll;
        let spec =
            PatternSpec::new(Family::Hadamard { ordering }, w as u32, h as u32, 512, 0).unwrap();
        let clean = solve(&spec, &buckets(&spec, &truth, 0.0), "tv", json!({}));
        let dark = solve(&spec, &buckets(&spec, &truth, 3.0), "tv", json!({}));
        let diff = metrics::relative_error(&dark, &clean);
        assert!(
            diff < 1e-6,
            "a constant dark level changed the image by {diff:e}"
        );
        let psnr = metrics::psnr(&clean, &truth);
        assert!(
            psnr > 25.0,
            "tv on 25 % Russian-doll Hadamard: {psnr:.1} dB"
        );
    }

    #[test]
    fn a_dark_level_on_bernoulli_is_fitted_on_request() {
        // A dark level twice the mean bucket: absorbed into the image without the offset term,
        // cancelled with it (and reported).
        let (w, h) = (32, 32);
        let truth = blocks(w, h);
        let spec =
            PatternSpec::new(Family::Bernoulli { fill: 0.5 }, w as u32, h as u32, 400, 9).unwrap();
        let clean = buckets(&spec, &truth, 0.0);
        let dark = 2.0 * clean.iter().sum::<f64>() / clean.len() as f64;
        let dim = buckets(&spec, &truth, dark);
        for method in ["tv", "auto"] {
            let reference = metrics::psnr(&solve(&spec, &clean, method, json!({})), &truth);
            let ignored = metrics::psnr(&solve(&spec, &dim, method, json!({})), &truth);
            let config = MethodConfig::parse(method, &json!({"offset": "fit"})).unwrap();
            let problem = Problem {
                spec: &spec,
                channels: 1,
                rows: 400,
            };
            let r = reconstruct(
                &problem,
                &config,
                &mut SliceSource::new(&dim, 1, 1000),
                &Control::new(),
            )
            .unwrap();
            let fitted = metrics::psnr(&r.images[0].data, &truth);
            let key = if method == "auto" { "auto" } else { "solver" };
            let d = r.report.details[key][0]["offset"].as_f64().unwrap();
            println!(
                "{method}: no offset {reference:.1} dB; dark {dark:.1} ignored {ignored:.1} dB, fitted {fitted:.1} dB (d = {d:.2})"
            );
            // Measured: tv 59.5 dB clean, 2.3 dB with the dark level ignored, 59.9 dB with it
            // fitted; auto 81.3 / 4.2 / 75.6 dB; the fitted d within 0.03 % of the true one.
            assert!(
                ignored < reference - 15.0,
                "{method}: ignoring the dark level should hurt"
            );
            assert!(
                fitted > reference - 6.0,
                "{method}: {fitted:.1} dB vs {reference:.1} dB"
            );
            assert!(
                (d - dark).abs() < 0.01 * dark,
                "{method}: offset {d} vs {dark}"
            );
        }
        // Where the offset cannot be fitted, the request says why.
        let raster = PatternSpec::new(Family::Raster { block: 1, scans: 1 }, 4, 4, 16, 0).unwrap();
        let e = reconstruct(
            &Problem {
                spec: &raster,
                channels: 1,
                rows: 16,
            },
            &MethodConfig::parse("tv", &json!({"offset": "fit"})).unwrap(),
            &mut SliceSource::new(&[1.0; 16], 1, 16),
            &Control::new(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("same number of pixels"), "{e}");
    }

    #[test]
    fn an_all_dark_scene_gives_zero_not_nan() {
        let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 16, 16, 40, 1).unwrap();
        let zeros = vec![0.0; 40];
        for method in ["cs", "tv", "lsq"] {
            let image = solve(&spec, &zeros, method, json!({}));
            assert!(image.iter().all(|&v| v == 0.0), "{method}: {image:?}");
        }
    }
}
