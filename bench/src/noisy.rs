//! `--preset noisy`: `auto` on noisy acquisitions, against the same solvers at the weight the
//! ground truth says is best (an oracle no user has), the default `tv`, and DGI; with the
//! calibration of every reported error estimate against the true error.
//!
//! Problems: scenes x families (Bernoulli 1/2, Russian-doll Hadamard split pairs) x noise
//! conventions (Gaussian read noise at 30 dB SNR of the *total* bucket power, Poisson shot noise
//! at 1e4 photons per pattern), one size and ratio (128x128, 10 % by default). Each problem is
//! simulated once; every method runs on the same buckets.
//!
//! Per problem it reports:
//! - `auto`: raw PSNR (the image as served), PSNR after the least-squares gain/offset fit to the
//!   truth, the gain (the slope of the image on the truth: 1 = the right physical units, < 1 the
//!   image is shrunk towards its mean; noise in the image does not bias it), the model and weight it chose, its noise
//!   estimate and its error estimate against the true relative error, and its time;
//! - the oracle: `tv` and `cs` (Daubechies-4) solved at every weight of a grid reaching
//!   `lambda_max` (fractions 1 ... 1e-4), the best raw PSNR of each and its weight;
//! - the default `tv` (raw PSNR, time) and DGI (PSNR after the fit: correlation images have no
//!   physical scale).
//!
//! `cargo run --release -p helmholtz-bench -- --preset noisy` writes docs/benchmarks-noisy.md and
//! .json; `--scenes`, `--families`, `--noises`, `--size`, `--ratio` narrow or change the grid,
//! `--no-oracle` skips the weight sweeps (most of the time).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context as _;
use helmholtz_proto::PatternSpec;
use helmholtz_recon::{self as recon, Control, MethodConfig, Problem, SliceSource, metrics};
use helmholtz_sim::{Target, simulate};
use serde::Serialize;
use serde_json::{Value, json};

use super::{Case, Noise, machine};

/// The weight grid of the oracle sweeps (fractions of `lambda_max`), reaching `lambda_max`.
pub const ORACLE_FRACTIONS: [f64; 14] = [
    1.0, 0.7, 0.5, 0.35, 0.25, 0.18, 0.12, 0.08, 0.05, 0.03, 0.01, 3e-3, 1e-3, 1e-4,
];

pub struct Options {
    pub out: PathBuf,
    pub scenes: Vec<String>,
    pub families: Vec<String>,
    pub noises: Vec<Noise>,
    pub size: u32,
    pub ratio: f64,
    pub oracle: bool,
}

impl Options {
    pub fn default_scenes() -> Vec<String> {
        ["camera", "shapes", "usaf", "smooth", "text"]
            .map(String::from)
            .to_vec()
    }
}

/// One method's result on one problem.
#[derive(Clone, Debug, Serialize)]
pub struct Run {
    pub method: String,
    pub params: Value,
    pub seconds: f64,
    pub psnr_db: f64,
    pub psnr_fitted_db: f64,
    /// Least-squares slope of the image on the truth (`image ~ gain * truth + offset`): 1 in
    /// the right physical units, < 1 shrunk towards the mean (noise in the image does not
    /// bias it, unlike the slope of the truth on the image).
    pub gain: f64,
    /// Least-squares slope of the truth on the image (`truth ~ slope * image + offset`, the
    /// fitted PSNR's gain): 1 when no rescaling of the image predicts the truth better (an
    /// image shrunk the way the noise asks, as a Wiener filter is, has 1 here and a `gain` below
    /// 1; one carrying amplified noise has a slope below 1).
    pub calibration_slope: f64,
    /// `||image - truth|| / ||truth||`.
    pub relative_error: f64,
    pub error: Option<String>,
    #[serde(skip)]
    pub report: Value,
}

/// The oracle sweep of one model.
#[derive(Clone, Debug, Serialize)]
pub struct Sweep {
    pub model: String,
    /// `(fraction, raw PSNR, seconds)` per weight.
    pub points: Vec<(f64, f64, f64)>,
    pub best_fraction: f64,
    pub best_psnr_db: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct ProblemResult {
    pub scene: String,
    pub family: String,
    pub noise: String,
    pub size: u32,
    pub ratio: f64,
    pub rows: u64,
    /// The noise put in, in the units `auto` estimates it (Bernoulli: buckets; Hadamard:
    /// `(y+ - y-) / sqrt(k)`): the root-mean-square of what the simulation added.
    pub true_sigma: f64,
    pub auto: Run,
    /// What `auto` reported (details.auto[0]): model, weight, noise and error estimates.
    pub auto_choice: Value,
    pub tv: Run,
    pub dgi: Run,
    pub oracle: Vec<Sweep>,
}

fn solve(
    spec: &PatternSpec,
    values: &[f64],
    truth: &[f32],
    method: &str,
    params: Value,
) -> (Run, Option<Vec<f32>>) {
    let problem = Problem {
        spec,
        channels: 1,
        rows: spec.count(),
    };
    let config = MethodConfig::parse(method, &params).expect("bench parameters are valid");
    let mut source = SliceSource::new(values, 1, 4096);
    let started = Instant::now();
    let result = recon::reconstruct(&problem, &config, &mut source, &Control::new());
    let seconds = started.elapsed().as_secs_f64();
    match result {
        Ok(mut r) => {
            let image = std::mem::take(&mut r.images[0].data);
            let (a, b) = metrics::fit_affine(&image, truth);
            let fitted: Vec<f32> = image.iter().map(|&v| (a * v as f64 + b) as f32).collect();
            let run = Run {
                method: method.into(),
                params,
                seconds,
                psnr_db: metrics::psnr(&image, truth),
                psnr_fitted_db: metrics::psnr(&fitted, truth),
                gain: metrics::fit_affine(truth, &image).0,
                calibration_slope: a,
                relative_error: metrics::relative_error(&image, truth),
                error: None,
                report: serde_json::to_value(&r.report).unwrap_or_default(),
            };
            (run, Some(image))
        }
        Err(e) => (
            Run {
                method: method.into(),
                params,
                seconds,
                psnr_db: f64::NAN,
                psnr_fitted_db: f64::NAN,
                gain: f64::NAN,
                calibration_slope: f64::NAN,
                relative_error: f64::NAN,
                error: Some(e.to_string()),
                report: Value::Null,
            },
            None,
        ),
    }
}

pub fn run(opts: &Options) -> anyhow::Result<Vec<ProblemResult>> {
    let contention = machine::Contention::start();
    let mut results = Vec::new();
    for scene in &opts.scenes {
        let truth = Target::load(scene, opts.size, opts.size)
            .with_context(|| format!("scene {scene}"))?
            .transport(1.0);
        for family in &opts.families {
            for &noise in &opts.noises {
                let case = Case {
                    scene: scene.clone(),
                    size: (opts.size, opts.size),
                    ratio: opts.ratio,
                    family: family.clone(),
                    noise,
                    method: "auto".into(),
                };
                let spec = case.spec();
                let sim = simulate::simulate(&spec, &[&truth], &noise.model(), None);
                let added: Vec<f64> = sim
                    .values
                    .iter()
                    .zip(&sim.clean)
                    .map(|(v, c)| v - c)
                    .collect();
                let true_sigma = if family == "hadamard" {
                    let root = (spec.pixels() as f64).sqrt();
                    let d: Vec<f64> = added
                        .chunks_exact(2)
                        .map(|p| (p[0] - p[1]) / root)
                        .collect();
                    (d.iter().map(|v| v * v).sum::<f64>() / d.len().max(1) as f64).sqrt()
                } else {
                    (added.iter().map(|v| v * v).sum::<f64>() / added.len().max(1) as f64).sqrt()
                };
                let values = sim.values;
                let (auto, _) = solve(&spec, &values, &truth, "auto", Value::Null);
                let auto_choice = auto.report["details"]["auto"][0].clone();
                let (tv, _) = solve(&spec, &values, &truth, "tv", Value::Null);
                let (dgi, _) = solve(&spec, &values, &truth, "dgi", Value::Null);
                let mut oracle = Vec::new();
                if opts.oracle {
                    for (method, extra) in [("tv", json!({})), ("cs", json!({"transform": "db4"}))]
                    {
                        let mut points = Vec::new();
                        for &f in &ORACLE_FRACTIONS {
                            let mut params = extra.clone();
                            params["lambda"] = json!(f);
                            params["max_iter"] = json!(500);
                            let (r, _) = solve(&spec, &values, &truth, method, params);
                            points.push((f, r.psnr_db, r.seconds));
                        }
                        let best = points
                            .iter()
                            .copied()
                            .filter(|p| p.1.is_finite())
                            .max_by(|a, b| a.1.total_cmp(&b.1))
                            .unwrap_or((f64::NAN, f64::NAN, 0.0));
                        oracle.push(Sweep {
                            model: if method == "tv" {
                                "tv".into()
                            } else {
                                "db4".into()
                            },
                            points,
                            best_fraction: best.0,
                            best_psnr_db: best.1,
                        });
                    }
                }
                let r = ProblemResult {
                    scene: scene.clone(),
                    family: family.clone(),
                    noise: noise.name().into(),
                    size: opts.size,
                    ratio: opts.ratio,
                    rows: spec.count(),
                    true_sigma,
                    auto,
                    auto_choice,
                    tv,
                    dgi,
                    oracle,
                };
                eprintln!("{}", line(&r));
                results.push(r);
            }
        }
    }
    let machine = contention.finish();
    write(&opts.out, opts, &machine, &results)?;
    Ok(results)
}

fn best_oracle(r: &ProblemResult) -> Option<&Sweep> {
    r.oracle
        .iter()
        .filter(|s| s.best_psnr_db.is_finite())
        .max_by(|a, b| a.best_psnr_db.total_cmp(&b.best_psnr_db))
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

/// `auto`'s error estimate: the estimated relative error of its image (`error_estimate`), or
/// NaN when it reports none.
fn estimate(r: &ProblemResult) -> f64 {
    num(&r.auto_choice["error_estimate"]["relative_error"])
}

/// Counts against the targets, per noise convention.
fn summary(md: &mut String, results: &[ProblemResult]) -> anyhow::Result<()> {
    md.push_str("\n## Summary against the targets\n\n| noise | problems | auto within 0.5 dB of the oracle | median auto - oracle dB (worst) | auto >= DGI after its fit | gain within 5 % of 1 | truth-on-image slope within 5 % of 1 | median auto / default tv time |\n|---|---|---|---|---|---|---|---|\n");
    let mut noises: Vec<&str> = Vec::new();
    for r in results {
        if !noises.contains(&r.noise.as_str()) {
            noises.push(&r.noise);
        }
    }
    for noise in noises {
        let rs: Vec<&ProblemResult> = results.iter().filter(|r| r.noise == noise).collect();
        let gaps: Vec<f64> = rs
            .iter()
            .filter_map(|r| best_oracle(r).map(|s| r.auto.psnr_db - s.best_psnr_db))
            .collect();
        let mut sorted = gaps.clone();
        sorted.sort_by(f64::total_cmp);
        let mut ratios: Vec<f64> = rs.iter().map(|r| r.auto.seconds / r.tv.seconds).collect();
        ratios.sort_by(f64::total_cmp);
        writeln!(
            md,
            "| {noise} | {} | {} of {} | {} | {} of {} | {} of {} | {} of {} | {:.1} |",
            rs.len(),
            gaps.iter().filter(|g| **g >= -0.5).count(),
            gaps.len(),
            if sorted.is_empty() {
                "-".into()
            } else {
                format!("{:+.2} ({:+.2})", sorted[sorted.len() / 2], sorted[0])
            },
            rs.iter()
                .filter(|r| r.auto.psnr_db >= r.dgi.psnr_fitted_db)
                .count(),
            rs.len(),
            rs.iter()
                .filter(|r| (r.auto.gain - 1.0).abs() <= 0.05)
                .count(),
            rs.len(),
            rs.iter()
                .filter(|r| (r.auto.calibration_slope - 1.0).abs() <= 0.05)
                .count(),
            rs.len(),
            ratios.get(ratios.len() / 2).copied().unwrap_or(f64::NAN),
        )?;
    }
    Ok(())
}

/// The range of `auto`'s error estimate, if reported.
fn range(r: &ProblemResult) -> Option<(f64, f64)> {
    let v = &r.auto_choice["error_estimate"]["relative_error_range"];
    Some((v[0].as_f64()?, v[1].as_f64()?))
}

fn line(r: &ProblemResult) -> String {
    let oracle = best_oracle(r)
        .map(|s| {
            format!(
                "oracle {} {:.2} dB @ {}",
                s.model, s.best_psnr_db, s.best_fraction
            )
        })
        .unwrap_or_default();
    format!(
        "{:<7} {:<9} {:<11} auto {:.2} dB (fitted {:.2}, gain {:.3}) {} f {:.3} err {:.3} est {:.3} sigma {:.3e}/{:.3e} {:.2} s | tv {:.2} dB {:.2} s | dgi fitted {:.2} | {oracle}",
        r.scene,
        r.family,
        r.noise,
        r.auto.psnr_db,
        r.auto.psnr_fitted_db,
        r.auto.gain,
        r.auto_choice["model"].as_str().unwrap_or("?"),
        num(&r.auto_choice["lambda_fraction"]),
        r.auto.relative_error,
        estimate(r),
        num(&r.auto_choice["noise_estimate"]["sigma"]),
        r.true_sigma,
        r.auto.seconds,
        r.tv.psnr_db,
        r.tv.seconds,
        r.dgi.psnr_fitted_db,
    )
}

fn write(
    out: &Path,
    opts: &Options,
    machine: &Value,
    results: &[ProblemResult],
) -> anyhow::Result<()> {
    std::fs::create_dir_all(out)?;
    let json = json!({
        "machine": machine,
        "size": opts.size,
        "ratio": opts.ratio,
        "oracle_fractions": ORACLE_FRACTIONS,
        "problems": results,
    });
    std::fs::write(
        out.join("benchmarks-noisy.json"),
        serde_json::to_string_pretty(&json)?,
    )?;
    let mut md = String::new();
    let command = format!(
        "cargo run{} -p helmholtz-bench -- --preset noisy --out {}",
        if cfg!(debug_assertions) {
            ""
        } else {
            " --release"
        },
        out.display()
    );
    writeln!(
        md,
        "# `auto` on noisy buckets\n\nGenerated by `{command}` ({} build, our crates at opt-level 3; {} threads; {}). {}x{}, {:.0} % of k (Hadamard: split pairs), Bernoulli(1/2) and Russian-doll Hadamard; noise: Gaussian at 30 dB SNR of the total bucket power (`30 dB`), Poisson at 1e4 photons per pattern (`Poisson 1e4`). Each problem is simulated once and every method runs on the same buckets. Raw PSNR is the image as served; *fitted* after the least-squares gain and offset to the truth; *gain* is the slope of the image regressed on the truth (1: the right physical units; < 1: contrast shrunk). The oracle solves `tv` and `cs` (db4) at every weight in {:?} x `lambda_max` (500 iterations each) and keeps the one the ground truth likes best: no user can do that.\n",
        if cfg!(debug_assertions) {
            "dev"
        } else {
            "release"
        },
        rayon::current_num_threads(),
        machine::sentence(machine),
        opts.size,
        opts.size,
        opts.ratio * 100.0,
        ORACLE_FRACTIONS
    )?;
    md.push_str("| scene | family | noise | auto raw dB | fitted dB | gain | truth-on-image slope | model @ f | s | oracle best dB (model @ f) | auto - oracle dB | default tv dB | tv s | DGI fitted dB | auto/tv time |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for r in results {
        let (oracle, gap) = match best_oracle(r) {
            Some(s) => (
                format!("{:.2} ({} @ {})", s.best_psnr_db, s.model, s.best_fraction),
                format!("{:+.2}", r.auto.psnr_db - s.best_psnr_db),
            ),
            None => ("-".into(), "-".into()),
        };
        writeln!(
            md,
            "| {} | {} | {} | {:.2} | {:.2} | {:.3} | {:.3} | {} @ {:.3} | {:.2} | {} | {} | {:.2} | {:.2} | {:.2} | {:.2} |",
            r.scene,
            r.family,
            r.noise,
            r.auto.psnr_db,
            r.auto.psnr_fitted_db,
            r.auto.gain,
            r.auto.calibration_slope,
            r.auto_choice["model"].as_str().unwrap_or("?"),
            num(&r.auto_choice["lambda_fraction"]),
            r.auto.seconds,
            oracle,
            gap,
            r.tv.psnr_db,
            r.tv.seconds,
            r.dgi.psnr_fitted_db,
            r.auto.seconds / r.tv.seconds,
        )?;
    }
    summary(&mut md, results)?;
    md.push_str("\n## Calibration: the error `auto` reports against the true error\n\n`error_estimate.relative_error` in `auto`'s report is its estimate of `||t_hat - t|| / ||t||` from the held-out rows and the noise it estimated (docs/usage.md, `recon/src/auto.rs`), with a range; for Hadamard subsets it is the residual on the measured coefficients less the noise plus twice the noise the image absorbed (its divergence), and the coefficients no row measured, from the scene's energy there extrapolated across the measured scales (`orthonormal_error` in `recon/src/auto.rs`). The truth is measured here against the scene.\n\n| scene | family | noise | noise put in (sigma) | estimated noise (sigma +- se, source) | estimated relative error (range) | true relative error | estimate / truth | truth in range |\n|---|---|---|---|---|---|---|---|---|\n");
    for r in results {
        let est = estimate(r);
        let noise = &r.auto_choice["noise_estimate"];
        writeln!(
            md,
            "| {} | {} | {} | {:.4e} | {} ({}) | {:.4} ({}) | {:.4} | {:.2} | {} |",
            r.scene,
            r.family,
            r.noise,
            r.true_sigma,
            noise["sigma"].as_f64().map_or("-".into(), |s| format!(
                "{s:.4e} +- {:.1e}",
                noise["standard_error"].as_f64().unwrap_or(f64::NAN)
            )),
            noise["source"]
                .as_str()
                .map_or("-", |s| s.split(" (").next().unwrap_or(s)),
            est,
            range(r).map_or("-".into(), |(lo, hi)| format!("{lo:.3} to {hi:.3}")),
            r.auto.relative_error,
            est / r.auto.relative_error,
            range(r).map_or("-", |(lo, hi)| {
                if (lo..=hi).contains(&r.auto.relative_error) {
                    "yes"
                } else {
                    "no"
                }
            }),
        )?;
    }
    std::fs::write(out.join("benchmarks-noisy.md"), md)?;
    Ok(())
}
