//! The compressive methods as service methods: `cs` (l1 in an orthonormal transform, t >= 0, by
//! FISTA), `tv` (isotropic total variation, t >= 0) and `lsq` (least squares / Tikhonov by CGLS).
//!
//! All rows are loaded (n x channels values), the pattern family's matrix-free operator is planned
//! once, and each channel is solved on it. Hadamard sessions are solved on the split-pair
//! differences `(y+ - y-) / sqrt(k)` against the orthonormal `H / sqrt(k)` (a dark level cancels);
//! 0/1 families rely on the solvers' automatic mean deflation (the common mode of 0/1 patterns).

use serde_json::{Value, json};

use super::method::MethodConfig;
use super::ops::{self, HadamardOperator};
use super::solve::{self, Grid, Lambda, SolveOptions};
use super::stream::RowStream;
use super::linop::LinearOperator;
use super::transforms::sparsifying_transform;
use super::{BucketSource, Control, DualImage, Problem, ReconError, Reconstruction, Report};
use helmholtz_proto::Family;

pub fn run(
    problem: &Problem,
    config: &MethodConfig,
    source: &mut dyn BucketSource,
    control: &Control,
) -> Result<Reconstruction, ReconError> {
    let spec = problem.spec;
    let channels = problem.channels;
    let (w, h) = (spec.width() as usize, spec.height() as usize);
    let mut buckets = Vec::with_capacity(problem.rows as usize * channels);
    let mut rows = RowStream::new(source, control, channels, problem.rows)?;
    while let Some(block) = rows.next_block()? {
        buckets.extend_from_slice(&block.values);
    }
    let hadamard = matches!(spec.family(), Family::Hadamard { .. });
    let unsolvable = |e: ops::OpError| ReconError::Unsolvable(e.to_string());
    let (boxed, hadamard_op): (Option<Box<dyn LinearOperator>>, Option<HadamardOperator>) = if hadamard {
        // Only whole P+/P- pairs are used.
        let frames = problem.rows - problem.rows % 2;
        (None, Some(HadamardOperator::from_spec(spec, frames).map_err(unsolvable)?))
    } else {
        (Some(ops::try_measurement_operator(spec, problem.rows).map_err(unsolvable)?), None)
    };
    let operator: &dyn LinearOperator = match (&boxed, &hadamard_op) {
        (Some(op), _) => op.as_ref(),
        (None, Some(op)) => op,
        (None, None) => unreachable!("one operator is built"),
    };
    let psi = match config {
        MethodConfig::Cs { transform, .. } => Some(sparsifying_transform(*transform, w, h)),
        _ => None,
    };
    let mut images = Vec::with_capacity(channels);
    let mut solver_reports = Vec::with_capacity(channels);
    let mut iterations = 0u64;
    for ch in 0..channels {
        let data: Vec<f64> = match &hadamard_op {
            Some(op) => op.split_pairs_channel(&buckets[..operator.rows() * 2 * channels], channels, ch).data,
            None => buckets.iter().skip(ch).step_by(channels).copied().collect(),
        };
        let span = (ch as f64 / channels as f64, (ch + 1) as f64 / channels as f64);
        let solution = match config {
            MethodConfig::Cs { lambda, max_iter, .. } => {
                let opts = SolveOptions { lambda: Lambda::Relative(*lambda), max_iter: *max_iter, progress: span, ..SolveOptions::default() };
                solve::fista(operator, psi.as_deref(), &data, &opts, control)?
            }
            MethodConfig::Tv { lambda, max_iter } => {
                let opts = SolveOptions { lambda: Lambda::Relative(*lambda), max_iter: *max_iter, progress: span, ..SolveOptions::default() };
                solve::tv_fista(operator, Grid::new(w, h), &data, &opts, control)?
            }
            MethodConfig::Lsq { mu, max_iter } => {
                let opts = SolveOptions { max_iter: *max_iter, progress: span, nonnegative: false, ..SolveOptions::default() };
                solve::cgls(operator, &data, *mu, &opts, control)?
            }
            other => unreachable!("compressive::run called for {}", other.name()),
        };
        if let Some(i) = solution.t.iter().position(|v| !v.is_finite()) {
            return Err(ReconError::Unsolvable(format!("the solver produced a non-finite value at pixel {i}")));
        }
        iterations += solution.report.iterations as u64;
        images.push(DualImage {
            width: spec.width(),
            height: spec.height(),
            data: solution.t.iter().map(|&v| v as f32).collect(),
        });
        solver_reports.push(serde_json::to_value(&solution.report).unwrap_or(Value::Null));
    }
    control.set_progress(1.0);
    let mut details = serde_json::Map::new();
    details.insert("solver".into(), Value::Array(solver_reports));
    details.insert("operator_rows".into(), json!(operator.rows()));
    if hadamard {
        details.insert("data".into(), json!("split-pair differences (y+ - y-)/sqrt(k)"));
    }
    Ok(Reconstruction {
        images,
        report: Report {
            method: config.name().into(),
            params: config.params_json(),
            rows_used: problem.rows,
            iterations,
            details,
            ..Report::default()
        },
    })
}

#[cfg(test)]
mod tests {
    use helmholtz_proto::{HadamardOrdering, PatternGenerator, PatternSpec};

    use super::*;
    use crate::recon::{SliceSource, metrics, reconstruct};

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
                p.iter().zip(t).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>() + offset
            })
            .collect()
    }

    fn solve(spec: &PatternSpec, c: &[f64], method: &str, params: Value) -> Vec<f32> {
        let config = MethodConfig::parse(method, &params).unwrap();
        let problem = Problem { spec, channels: 1, rows: spec.count() };
        let r = reconstruct(&problem, &config, &mut SliceSource::new(c, 1, 1000), &Control::new()).unwrap();
        let image = r.images.into_iter().next().unwrap().data;
        assert!(image.iter().all(|v| v.is_finite()), "{method}: non-finite pixel");
        image
    }

    #[test]
    fn compressive_methods_beat_least_squares_on_30_percent_bernoulli() {
        let (w, h) = (32, 32);
        let truth = blocks(w, h);
        let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, w as u32, h as u32, 307, 5).unwrap();
        let c = buckets(&spec, &truth, 0.0);
        let lsq = metrics::psnr(&solve(&spec, &c, "lsq", json!({})), &truth);
        let tv_img = solve(&spec, &c, "tv", json!({}));
        let cs_img = solve(&spec, &c, "cs", json!({"transform": "haar"}));
        assert!(tv_img.iter().chain(&cs_img).all(|&v| v >= 0.0), "transport is never negative");
        let (tv, cs) = (metrics::psnr(&tv_img, &truth), metrics::psnr(&cs_img, &truth));
        // Noise-free, piecewise-constant scene: TV is near exact, Haar-l1 far above the min-norm
        // least-squares image (which spreads the missing 70 % of the information as noise).
        assert!(tv > 30.0, "tv {tv:.1} dB");
        assert!(cs > lsq + 5.0, "cs {cs:.1} dB vs lsq {lsq:.1} dB");
    }

    #[test]
    fn hadamard_split_pairs_cancel_a_dark_level() {
        let (w, h) = (32, 32);
        let truth = blocks(w, h);
        let ordering = HadamardOrdering::RussianDoll;
        let spec = PatternSpec::new(Family::Hadamard { ordering }, w as u32, h as u32, 512, 0).unwrap();
        let clean = solve(&spec, &buckets(&spec, &truth, 0.0), "tv", json!({}));
        let dark = solve(&spec, &buckets(&spec, &truth, 3.0), "tv", json!({}));
        let diff = metrics::relative_error(&dark, &clean);
        assert!(diff < 1e-6, "a constant dark level changed the image by {diff:e}");
        let psnr = metrics::psnr(&clean, &truth);
        assert!(psnr > 25.0, "tv on 25 % Russian-doll Hadamard: {psnr:.1} dB");
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
