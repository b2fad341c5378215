//! The speed-against-error report: a grid of scenes x sizes x sampling ratios x pattern families x
//! noise x methods, each reconstructed by the same numerics the service runs, timed, scored
//! against the ground truth, and written as JSON, Markdown tables and SVG plots.
//!
//! `cargo run --release -p helmholtz-bench -- --preset full`
//!
//! `--preset compare` runs the side-by-side comparison with other tools instead ([`compare`]);
//! `--preset transport` the camera-session (transport matrix) benchmark ([`transport`]);
//! `--preset adaptive` adaptive acquisition against the non-adaptive families ([`adaptive`]).

pub mod adaptive;
pub mod compare;
mod grid;
pub mod machine;
pub mod noisy;
mod plot;
mod report;
mod transport;

use std::path::PathBuf;
use std::time::Instant;

use clap::Parser;
use helmholtz_proto::{Family, PatternSpec};
use helmholtz_sim::Target;
use helmholtz_sim::simulate;
use serde::Serialize;

use helmholtz_recon::{self as recon, Control, MethodConfig, Problem, SliceSource, metrics};

pub use grid::{Case, Noise, Preset};

#[derive(Parser, Debug)]
#[command(
    name = "helmholtz-bench",
    about = "Speed against error of every reconstruction method on a grid of simulated acquisitions.\n\nWrites DIR/benchmarks.md (tables and plots) and DIR/benchmarks.json (raw figures); the smaller presets write DIR/benchmarks-PRESET.{md,json}.\n\n--preset compare runs the target problems side by side with other tools (pylops, pyproximal, spyrit; bench/compare/run.py in a venv under target/compare-venv, created on first use) and writes DIR/comparison.md and DIR/comparison.json.\n\n--preset transport benchmarks camera sessions (transport matrix reconstruction, relight/primal latency) and writes DIR/benchmarks-transport.{md,json}."
)]
struct Args {
    /// smoke: a few small cases (CI); targets: the target problems; full: the whole grid;
    /// compare: the target problems against other tools; transport: camera sessions (transport
    /// matrix time, size and error, relight/primal latency); noisy: `auto` on noisy buckets
    /// against the solvers at their ground-truth-best weight, with its error estimates' calibration.
    #[arg(long, default_value = "targets", value_parser = ["smoke", "targets", "full", "compare", "transport", "noisy", "adaptive"])]
    preset: String,
    /// Output directory.
    #[arg(long, default_value = "docs")]
    out: PathBuf,
    /// Only methods in this comma-separated list.
    #[arg(long, value_delimiter = ',')]
    methods: Option<Vec<String>>,
    /// Run every case this many times and report the median time (the figures of the last
    /// run; the numerics are deterministic). Shared 2-core VMs vary by tens of percent run to run.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=20))]
    repeat: u32,
    /// compare: where the exported problems and every tool's images go.
    #[arg(long, default_value_os_t = compare::repo_root().join("target/compare"))]
    work_dir: PathBuf,
    /// compare: the Python interpreter that starts bench/compare/run.py (which then re-runs itself
    /// in its venv).
    #[arg(long, default_value = "python3")]
    python: String,
    /// compare: export the problems and run only our methods (no Python).
    #[arg(long)]
    only_ours: bool,
    /// compare: only these problems (comma-separated names, e.g. camera128-hadamard10).
    #[arg(long, value_delimiter = ',')]
    problems: Option<Vec<String>>,
    /// transport: timed relight and primal calls per transform (median and p99 reported).
    #[arg(long, default_value_t = 300, value_parser = clap::value_parser!(u32).range(10..=100_000))]
    calls: u32,
    /// transport: only the relight/primal latency, no reconstructions.
    #[arg(long)]
    latency_only: bool,
    /// transport: only the reconstruction cases whose name contains one of these
    /// (comma-separated, e.g. "hadamard 50,bernoulli 10").
    #[arg(long, value_delimiter = ',')]
    cases: Option<Vec<String>>,
    /// adaptive: image sides (powers of two).
    #[arg(long, value_delimiter = ',', default_value = "128,256")]
    sizes: Vec<u32>,
    /// adaptive: the planners' `persistence` (PATTERNS.md) for both families; default: each
    /// family's own (adaptive_haar 0.5, adaptive_hadamard 0).
    #[arg(long)]
    persistence: Option<f64>,
    /// noisy, adaptive, compare: scenes (comma-separated; built-in names or PNG paths; adaptive
    /// also takes "relief"). compare: issue 20's noisy problems on these scenes (with
    /// --families, --noises, --size, --ratio) instead of the built-in problems.
    #[arg(long, value_delimiter = ',')]
    scenes: Option<Vec<String>>,
    /// noisy, compare with --scenes: pattern families (bernoulli, hadamard).
    #[arg(long, value_delimiter = ',', default_value = "bernoulli,hadamard", value_parser = ["bernoulli", "hadamard"])]
    families: Vec<String>,
    /// noisy, compare with --scenes: noise conventions (snr30: Gaussian at 30 dB of the total
    /// bucket power; poisson: 1e4 photons per pattern; none).
    #[arg(long, value_delimiter = ',', default_value = "snr30,poisson", value_parser = ["none", "snr30", "poisson"])]
    noises: Vec<String>,
    /// noisy, compare with --scenes: image side (Hadamard needs a power of two).
    #[arg(long, default_value_t = 128)]
    size: u32,
    /// noisy, compare with --scenes: measurements / pixels (Hadamard: split pairs / pixels).
    #[arg(long, default_value_t = 0.1)]
    ratio: f64,
    /// noisy: skip the oracle's weight sweeps.
    #[arg(long)]
    no_oracle: bool,
}

/// One measured reconstruction.
#[derive(Clone, Debug, Serialize)]
pub struct Measurement {
    pub case: Case,
    pub rows: u64,
    pub seconds: f64,
    pub peak_memory_bytes: Option<usize>,
    /// Raw PSNR against the scene's transport.
    pub psnr_db: f64,
    pub ssim: f64,
    /// After the least-squares scale and offset fit (correlation methods estimate t up to both).
    pub psnr_fitted_db: f64,
    pub ssim_fitted: f64,
    /// For correlation methods: pattern-pixel updates per second (rows * k / seconds).
    pub updates_per_second: Option<f64>,
    pub report: serde_json::Value,
    pub error: Option<String>,
    /// Wall time of every run of the case (`--repeat`); `seconds` is their median.
    pub all_seconds: Vec<f64>,
}

impl Measurement {
    /// The figure plotted: fitted for the scale-free correlation methods, raw for the others.
    pub fn quality_db(&self) -> f64 {
        if grid::scale_free(&self.case.method) {
            self.psnr_fitted_db
        } else {
            self.psnr_db
        }
    }
    pub fn quality_ssim(&self) -> f64 {
        if grid::scale_free(&self.case.method) {
            self.ssim_fitted
        } else {
            self.ssim
        }
    }
}

pub fn main() {
    let args = Args::parse();
    let noises: Vec<Noise> = args
        .noises
        .iter()
        .map(|n| match n.as_str() {
            "snr30" => Noise::Snr30,
            "poisson" => Noise::Poisson,
            _ => Noise::None,
        })
        .collect();
    if args.preset == "compare" {
        let (scene_problems, scene_args) = match &args.scenes {
            Some(scenes) => (
                compare::scene_problems(scenes, &args.families, &noises, args.size, args.ratio),
                format!(
                    " --scenes {} --families {} --noises {} --size {} --ratio {}",
                    scenes.join(","),
                    args.families.join(","),
                    args.noises.join(","),
                    args.size,
                    args.ratio
                ),
            ),
            None => (Vec::new(), String::new()),
        };
        let opts = compare::Options {
            out: args.out.clone(),
            work: args.work_dir.clone(),
            python: args.python.clone(),
            repeat: args.repeat,
            only_ours: args.only_ours,
            problems: args.problems.clone(),
            scene_problems,
            scene_args,
        };
        if let Err(e) = compare::run(&opts) {
            eprintln!("helmholtz-bench: {e:#}");
            std::process::exit(1);
        }
        eprintln!(
            "wrote {}/comparison.md and comparison.json",
            args.out.display()
        );
        return;
    }
    if args.preset == "noisy" {
        let opts = noisy::Options {
            out: args.out.clone(),
            scenes: args
                .scenes
                .clone()
                .unwrap_or_else(noisy::Options::default_scenes),
            families: args.families.clone(),
            noises: noises.clone(),
            size: args.size,
            ratio: args.ratio,
            oracle: !args.no_oracle,
        };
        if let Err(e) = noisy::run(&opts) {
            eprintln!("helmholtz-bench: {e:#}");
            std::process::exit(1);
        }
        eprintln!(
            "wrote {}/benchmarks-noisy.md and benchmarks-noisy.json",
            args.out.display()
        );
        return;
    }
    if args.preset == "adaptive" {
        let opts = adaptive::Options {
            out: args.out.clone(),
            sizes: args.sizes.clone(),
            scenes: args
                .scenes
                .clone()
                .unwrap_or_else(adaptive::Options::default_scenes),
            ratios: adaptive::Options::RATIOS.to_vec(),
            persistence: args.persistence,
        };
        if let Err(e) = adaptive::run(&opts) {
            eprintln!("helmholtz-bench: {e:#}");
            std::process::exit(1);
        }
        eprintln!(
            "wrote {}/benchmarks-adaptive.md and benchmarks-adaptive.json",
            args.out.display()
        );
        return;
    }
    if args.preset == "transport" {
        if let Err(e) = transport::run(
            &args.out,
            args.calls as usize,
            args.latency_only,
            args.cases.as_deref(),
        ) {
            eprintln!("helmholtz-bench: {e:#}");
            std::process::exit(1);
        }
        eprintln!(
            "wrote {}/benchmarks-transport.md and benchmarks-transport.json",
            args.out.display()
        );
        return;
    }
    let preset: Preset = args.preset.parse().expect("clap checked the preset");
    let mut cases = preset.cases();
    if let Some(methods) = &args.methods {
        cases.retain(|c| methods.contains(&c.method));
    }
    eprintln!(
        "helmholtz-bench: {} cases ({}), {} threads",
        cases.len(),
        args.preset,
        rayon::current_num_threads()
    );
    let contention = machine::Contention::start();
    let results = run_cases_repeated(&cases, args.repeat as usize, |i, m| {
        eprintln!(
            "[{}/{}] {:<48} {:>9.4} s  {:>6.2} dB  SSIM {:.3}{}",
            i + 1,
            cases.len(),
            m.case.label(),
            m.seconds,
            m.quality_db(),
            m.quality_ssim(),
            m.error
                .as_deref()
                .map(|e| format!("  ({e})"))
                .unwrap_or_default()
        )
    });
    if let Err(e) = report::write_with(
        &args.out,
        &args.preset,
        args.repeat,
        &contention.finish(),
        &results,
    ) {
        eprintln!("helmholtz-bench: writing the report: {e:#}");
        std::process::exit(1);
    }
    eprintln!("wrote the report to {}", args.out.display());
}

/// Runs every case (sharing the simulation between methods of one acquisition).
pub fn run_cases(cases: &[Case], progress: impl FnMut(usize, &Measurement)) -> Vec<Measurement> {
    run_cases_repeated(cases, 1, progress)
}

/// [`run_cases`], each case `repeat` times: the median wall time is reported (with the figures
/// of the last run) and every run's time is kept in `all_seconds`.
pub fn run_cases_repeated(
    cases: &[Case],
    repeat: usize,
    mut progress: impl FnMut(usize, &Measurement),
) -> Vec<Measurement> {
    let mut out = Vec::with_capacity(cases.len());
    let mut cache: Option<(String, PatternSpec, Vec<f32>, Vec<f64>)> = None;
    for (i, case) in cases.iter().enumerate() {
        let key = case.acquisition_key();
        if cache.as_ref().map(|c| &c.0) != Some(&key) {
            let spec = case.spec();
            let truth = Target::builtin(&case.scene, case.size.0, case.size.1)
                .expect("built-in scene")
                .transport(1.0);
            let sim = simulate::simulate(&spec, &[&truth], &case.noise.model(), None);
            cache = Some((key, spec, truth, sim.values));
        }
        let (_, spec, truth, values) = cache.as_ref().expect("filled above");
        let mut times = Vec::with_capacity(repeat);
        let mut m = measure(case, spec, truth, values);
        times.push(m.seconds);
        for _ in 1..repeat.max(1) {
            m = measure(case, spec, truth, values);
            times.push(m.seconds);
        }
        let mut sorted = times.clone();
        sorted.sort_by(f64::total_cmp);
        m.seconds = sorted[sorted.len() / 2];
        if let Some(u) = m.updates_per_second.as_mut() {
            *u = spec.count() as f64 * spec.pixels() as f64 / m.seconds;
        }
        m.all_seconds = times;
        progress(i, &m);
        out.push(m);
    }
    out
}

fn measure(case: &Case, spec: &PatternSpec, truth: &[f32], values: &[f64]) -> Measurement {
    measure_with_image(case, spec, truth, values).0
}

/// [`measure`], also handing back the reconstructed image (channel 0; `None` on error).
pub(crate) fn measure_with_image(
    case: &Case,
    spec: &PatternSpec,
    truth: &[f32],
    values: &[f64],
) -> (Measurement, Option<Vec<f32>>) {
    let problem = Problem {
        spec,
        channels: 1,
        rows: spec.count(),
    };
    let config =
        MethodConfig::parse(&case.method, &serde_json::Value::Null).expect("grid methods exist");
    let control = Control::new();
    let mut source = SliceSource::new(values, 1, 4096);
    let base = helmholtz_alloc::live_bytes();
    helmholtz_alloc::reset_peak();
    let started = Instant::now();
    let result = recon::reconstruct(&problem, &config, &mut source, &control);
    let seconds = started.elapsed().as_secs_f64();
    let peak =
        helmholtz_alloc::installed().then(|| helmholtz_alloc::peak_bytes().saturating_sub(base));
    let k = spec.pixels() as f64;
    match result {
        Ok(mut r) => {
            let data = std::mem::take(&mut r.images[0].data);
            let image = &data;
            let (a, b) = metrics::fit_affine(image, truth);
            let fitted: Vec<f32> = image.iter().map(|&v| (a * v as f64 + b) as f32).collect();
            let (w, h) = (spec.width() as usize, spec.height() as usize);
            let m = Measurement {
                case: case.clone(),
                rows: spec.count(),
                seconds,
                peak_memory_bytes: peak,
                psnr_db: metrics::psnr(image, truth),
                ssim: metrics::ssim(image, truth, w, h),
                psnr_fitted_db: metrics::psnr(&fitted, truth),
                ssim_fitted: metrics::ssim(&fitted, truth, w, h),
                updates_per_second: grid::scale_free(&case.method)
                    .then(|| spec.count() as f64 * k / seconds),
                report: without_histories(serde_json::to_value(&r.report).unwrap_or_default()),
                error: None,
                all_seconds: Vec::new(),
            };
            (m, Some(data))
        }
        Err(e) => (
            Measurement {
                case: case.clone(),
                rows: spec.count(),
                seconds,
                peak_memory_bytes: peak,
                psnr_db: f64::NAN,
                ssim: f64::NAN,
                psnr_fitted_db: f64::NAN,
                ssim_fitted: f64::NAN,
                updates_per_second: None,
                report: serde_json::Value::Null,
                error: Some(e.to_string()),
                all_seconds: Vec::new(),
            },
            None,
        ),
    }
}

/// The report without the solvers' objective histories (hundreds of numbers per solve; the
/// service serves them, the benchmark JSON keeps the figures).
fn without_histories(v: serde_json::Value) -> serde_json::Value {
    use serde_json::Value;
    match v {
        Value::Object(map) => Value::Object(
            map.into_iter()
                .filter(|(k, _)| k != "objective_history")
                .map(|(k, v)| (k, without_histories(v)))
                .collect(),
        ),
        Value::Array(items) => Value::Array(items.into_iter().map(without_histories).collect()),
        other => other,
    }
}

/// Frames for a sampling ratio: Bernoulli/speckle count patterns, Hadamard counts P+/P- pairs.
/// Whether the probes' environment switch `name` (`ONE_REPORT`, `TRANSPORT_REPORT`, ...) is on:
/// set to anything but empty, `0`, `false` or `no`.
pub fn env_flag(name: &str) -> bool {
    flag_is_on(std::env::var(name).ok().as_deref())
}

/// [`env_flag`] on the variable's value (`None`: unset).
fn flag_is_on(value: Option<&str>) -> bool {
    value.is_some_and(|v| !matches!(v.trim(), "" | "0" | "false" | "no"))
}

pub fn frames_for(family: &Family, k: usize, ratio: f64) -> u64 {
    let rows = ((ratio * k as f64).round() as u64).clamp(1, k as u64);
    match family {
        Family::Hadamard { .. } | Family::AdaptiveHaar { .. } | Family::AdaptiveHadamard { .. } => {
            2 * rows
        }
        _ => rows,
    }
}

#[cfg(test)]
mod tests;
