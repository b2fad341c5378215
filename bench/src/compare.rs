//! Side by side: the service's solvers against the tools users would otherwise use (pylops /
//! pyproximal FISTA and TV, spyrit's Hadamard inverses), on the same problems, timed and scored
//! the same way.
//!
//! `cargo run --release -p helmholtz-bench -- --preset compare --out docs`
//!
//! 1. Every problem is simulated once (noise-free, as in `--preset targets`) and **exported** as
//!    NPY files plus a `problem.json` manifest ([`export`]): the ground truth, the measurement
//!    operator exactly as our solvers apply it and the data vector `b` with `A t = b`.
//!    - Bernoulli: `A.npy`, the dense 0/1 matrix (float32, `rows x k`, row-major pixels
//!      `p = y W + x`), and `b.npy` = the buckets.
//!    - Hadamard split pairs: `natural.npy`, the natural (Sylvester) index of every measured row
//!      in acquisition order, defining `A[r, p] = (-1)^popcount(natural[r] & p) / sqrt(k)` (the
//!      orthonormal `S H / sqrt(k)` of `recon::ops::HadamardOperator`, applied by a fast
//!      Walsh-Hadamard transform of the row-major image followed by picking `natural`), `b.npy`
//!      = `(y+ - y-) / sqrt(k)` (what our solvers fit), and `frames.npy`, the raw frames
//!      (`P+` of row 0, `P-` of row 0, `P+` of row 1, ...).
//! 2. Our methods run on the same acquisitions (median time of `--repeat` runs).
//! 3. `bench/compare/run.py` (in its own venv under `target/compare-venv`) runs the other tools
//!    on the exported problems and writes every reconstruction as NPY with its solve time.
//! 4. Every image, ours and theirs, is scored here by `recon::metrics` (the same PSNR and SSIM);
//!    for the competitors' weight sweeps the best point by ground truth is reported.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, bail, ensure};
use helmholtz_proto::{Family, PatternSpec};
use helmholtz_sim::Target;
use helmholtz_sim::simulate;
use ndarray::{Array1, Array2};
use ndarray_npy::{read_npy, write_npy};
use serde::Serialize;
use serde_json::{Value, json};

use super::{Case, Noise, measure_with_image};
use helmholtz_recon::metrics;
use helmholtz_recon::ops::{BernoulliOperator, HadamardOperator};

/// One problem of the comparison.
#[derive(Clone, Debug)]
pub struct CompareProblem {
    /// Directory name of the export.
    pub name: String,
    pub title: String,
    /// The acquisition (its `method` is unused).
    pub case: Case,
    /// Our methods run on it.
    pub ours: &'static [&'static str],
    /// The figures the issue quotes for the other tools on this problem.
    pub reference: String,
}

fn case(scene: &str, size: u32, family: &str, ratio: f64) -> Case {
    Case {
        scene: scene.into(),
        size: (size, size),
        ratio,
        family: family.into(),
        noise: Noise::None,
        method: String::new(),
    }
}

/// The target problems (noise-free; Hadamard ratios count split pairs, Russian-doll order).
pub fn problems() -> Vec<CompareProblem> {
    vec![
        CompareProblem {
            name: "camera128-bernoulli10".into(),
            title: "128x128 photo, Bernoulli 0/1 patterns, 10 % (1,638 patterns)".into(),
            case: case("camera", 128, "bernoulli", 0.1),
            ours: &["auto", "tv"],
            reference:
                "pyproximal primal-dual TV 24.4 dB in 22 s; pylops FISTA on wavelets 19 dB in 17 s"
                    .into(),
        },
        CompareProblem {
            name: "camera128-hadamard10".into(),
            title: "128x128 photo, Hadamard split pairs, 10 % (1,638 pairs, Russian-doll order)"
                .into(),
            case: case("camera", 128, "hadamard", 0.1),
            ours: &["tv", "auto", "zero_filled"],
            reference: "pyproximal TV 24.8 dB in 0.57 s; spyrit's inverse 20.7 dB in 0.7 ms".into(),
        },
        CompareProblem {
            name: "camera256-hadamard10".into(),
            title: "256x256 photo, Hadamard split pairs, 10 % (6,554 pairs, Russian-doll order)"
                .into(),
            case: case("camera", 256, "hadamard", 0.1),
            ours: &["tv", "auto", "zero_filled"],
            reference: "spyrit's inverse 23.0 dB".into(),
        },
        CompareProblem {
            name: "shapes256-bernoulli1.5".into(),
            title: "256x256 sparse scene, Bernoulli 0/1 patterns, 1.5 % (1,000 patterns)".into(),
            case: case("shapes", 256, "bernoulli", 1000.0 / 65536.0),
            ours: &["auto", "tv"],
            reference: "none quoted".into(),
        },
    ]
}

fn noisy(scene: &str, family: &str, noise: Noise) -> Case {
    Case {
        noise,
        ..case(scene, 128, family, 0.1)
    }
}

/// Issue 20's noisy problems (`--problems noisy`): 128x128 at 10 %, Gaussian read noise at
/// 30 dB SNR of the total bucket power and Poisson shot noise at 1e4 photons per pattern.
pub fn noisy_problems() -> Vec<CompareProblem> {
    vec![
        CompareProblem {
            name: "camera128-bernoulli10-snr30".into(),
            title: "128x128 photo, Bernoulli 0/1 patterns, 10 %, Gaussian noise at 30 dB SNR of the total bucket power".into(),
            case: noisy("camera", "bernoulli", Noise::Snr30),
            ours: &["auto", "tv", "dgi"],
            reference: "issue 20: auto lost 13 of 20 noisy problems to the tuned peers by 0.1-5.0 dB".into(),
        },
        CompareProblem {
            name: "camera128-bernoulli10-poisson".into(),
            title: "128x128 photo, Bernoulli 0/1 patterns, 10 %, Poisson noise at 1e4 photons per pattern".into(),
            case: noisy("camera", "bernoulli", Noise::Poisson),
            ours: &["auto", "tv", "dgi"],
            reference: "issue 20: auto lost 13 of 20 noisy problems to the tuned peers by 0.1-5.0 dB".into(),
        },
        CompareProblem {
            name: "camera128-hadamard10-snr30".into(),
            title: "128x128 photo, Hadamard split pairs, 10 % (Russian-doll order), Gaussian noise at 30 dB SNR of the total bucket power".into(),
            case: noisy("camera", "hadamard", Noise::Snr30),
            ours: &["auto", "tv", "dgi"],
            reference: "issue 20: auto lost 13 of 20 noisy problems to the tuned peers by 0.1-5.0 dB".into(),
        },
        CompareProblem {
            name: "camera128-hadamard10-poisson".into(),
            title: "128x128 photo, Hadamard split pairs, 10 % (Russian-doll order), Poisson noise at 1e4 photons per pattern".into(),
            case: noisy("camera", "hadamard", Noise::Poisson),
            ours: &["auto", "tv", "dgi"],
            reference: "issue 20: auto lost 13 of 20 noisy problems to the tuned peers by 0.1-5.0 dB".into(),
        },
        CompareProblem {
            name: "shapes128-bernoulli10-snr30".into(),
            title: "128x128 sparse scene, Bernoulli 0/1 patterns, 10 %, Gaussian noise at 30 dB SNR of the total bucket power".into(),
            case: noisy("shapes", "bernoulli", Noise::Snr30),
            ours: &["auto", "tv", "dgi"],
            reference: "issue 20: auto lost 13 of 20 noisy problems to the tuned peers by 0.1-5.0 dB".into(),
        },
        CompareProblem {
            name: "shapes128-hadamard10-poisson".into(),
            title: "128x128 sparse scene, Hadamard split pairs, 10 % (Russian-doll order), Poisson noise at 1e4 photons per pattern".into(),
            case: noisy("shapes", "hadamard", Noise::Poisson),
            ours: &["auto", "tv", "dgi"],
            reference: "issue 20: auto lost 13 of 20 noisy problems to the tuned peers by 0.1-5.0 dB".into(),
        },
    ]
}

/// Issue 20's noisy problems on any scenes (`--scenes`, built-in names or PNG paths): every
/// scene x family (`bernoulli`: Bernoulli(1/2) rows; `hadamard`: Russian-doll split pairs) x
/// noise, at `size` x `size` and `ratio` of k. Named `LABEL{size}-{family}{percent}-{noise}`,
/// LABEL the built-in name or the PNG's file stem.
pub fn scene_problems(
    scenes: &[String],
    families: &[String],
    noises: &[Noise],
    size: u32,
    ratio: f64,
) -> Vec<CompareProblem> {
    let mut out = Vec::new();
    for scene in scenes {
        let label = Path::new(scene)
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or(scene)
            .to_string();
        let source = if scene.ends_with(".png") {
            format!("{label} ({scene})")
        } else {
            label.clone()
        };
        for family in families {
            for &noise in noises {
                let (family_title, noise_tag, noise_title) = (
                    match family.as_str() {
                        "hadamard" => "Hadamard split pairs (Russian-doll order)",
                        _ => "Bernoulli 0/1 patterns",
                    },
                    match noise {
                        Noise::Snr30 => "-snr30",
                        Noise::Poisson => "-poisson",
                        Noise::None => "",
                    },
                    match noise {
                        Noise::Snr30 => ", Gaussian noise at 30 dB SNR of the total bucket power",
                        Noise::Poisson => ", Poisson noise at 1e4 photons per pattern",
                        Noise::None => ", noise-free",
                    },
                );
                let percent = format!("{}", (ratio * 1000.0).round() / 10.0);
                out.push(CompareProblem {
                    name: format!("{label}{size}-{family}{percent}{noise_tag}"),
                    title: format!(
                        "{size}x{size} {source}, {family_title}, {percent} %{noise_title}"
                    ),
                    case: Case {
                        noise,
                        ..case(scene, size, family, ratio)
                    },
                    ours: &["auto", "tv", "dgi"],
                    reference: "issue 20: auto within 0.5 dB of the best peer at its ground-truth-best weight".into(),
                });
            }
        }
    }
    out
}

/// A simulated acquisition: the spec, the scene's transport (row-major) and the bucket rows.
pub struct Acquisition {
    pub spec: PatternSpec,
    pub truth: Vec<f32>,
    pub values: Vec<f64>,
    /// The buckets before noise (equal to `values` for noise-free problems).
    pub clean: Vec<f64>,
}

pub fn acquire(case: &Case) -> anyhow::Result<Acquisition> {
    let spec = case.spec();
    let truth = Target::load(&case.scene, case.size.0, case.size.1)?.transport(1.0);
    let sim = simulate::simulate(&spec, &[&truth], &case.noise.model(), None);
    Ok(Acquisition {
        spec,
        truth,
        values: sim.values,
        clean: sim.clean,
    })
}

/// The convention of the exported Hadamard operator (also written into the manifest).
pub const HADAMARD_CONVENTION: &str = "A[r, p] = (-1)^popcount(natural[r] & p) / sqrt(k), p = y * W + x (row-major pixels); \
     i.e. A = S H / sqrt(k) with H the k x k Sylvester (natural-order) Hadamard matrix and S picking the rows natural[0..m]; \
     A x = fwht(x.ravel())[natural] / sqrt(k) with an unnormalised natural-order fast Walsh-Hadamard transform; A A^T = I. \
     b[r] = (frames[2r] - frames[2r+1]) / sqrt(k) (P+ minus P- of row r; a dark level cancels).";

/// Writes the problem our solvers see to `dir` (created): `truth.npy` (float32, `H x W`),
/// `b.npy` (float64), `A.npy` (Bernoulli, float32 `rows x k`) or `natural.npy` (int64) and
/// `frames.npy` (Hadamard), and `problem.json`. Returns the manifest.
pub fn export(problem: &CompareProblem, acq: &Acquisition, dir: &Path) -> anyhow::Result<Value> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let spec = &acq.spec;
    let (w, h) = (spec.width() as usize, spec.height() as usize);
    let k = w * h;
    ensure!(
        acq.truth.len() == k,
        "truth has {} pixels, the spec {k}",
        acq.truth.len()
    );
    let npy = |name: &str| dir.join(name);
    write_npy(
        npy("truth.npy"),
        &Array2::from_shape_vec((h, w), acq.truth.clone())?,
    )?;
    let operator = match spec.family() {
        Family::Hadamard { .. } => {
            let frames = spec.count() - spec.count() % 2;
            let op = HadamardOperator::from_spec(spec, frames)?;
            let pairs = op.split_pairs(&acq.values[..frames as usize]);
            let natural: Vec<i64> = op.natural_indices().iter().map(|&n| n as i64).collect();
            write_npy(npy("natural.npy"), &Array1::from(natural))?;
            write_npy(npy("b.npy"), &Array1::from(pairs.data))?;
            let clean = op.split_pairs(&acq.clean[..frames as usize]);
            write_npy(npy("b_clean.npy"), &Array1::from(clean.data))?;
            write_npy(
                npy("frames.npy"),
                &Array1::from(acq.values[..frames as usize].to_vec()),
            )?;
            json!({
                "kind": "hadamard_subset",
                "natural": "natural.npy",
                "frames": "frames.npy",
                "rows": frames / 2,
                "convention": HADAMARD_CONVENTION,
            })
        }
        Family::Bernoulli { .. } => {
            let rows = spec.count() as usize;
            let op = BernoulliOperator::from_spec(spec, rows as u64)?;
            let bits = op.patterns();
            let mut a = vec![0f32; rows * k];
            for (r, row) in a.chunks_mut(k).enumerate() {
                for (c, v) in row.iter_mut().enumerate() {
                    *v = if bits.get(r, c) { 1.0 } else { 0.0 };
                }
            }
            write_npy(npy("A.npy"), &Array2::from_shape_vec((rows, k), a)?)?;
            write_npy(npy("b.npy"), &Array1::from(acq.values.clone()))?;
            write_npy(npy("b_clean.npy"), &Array1::from(acq.clean.clone()))?;
            json!({
                "kind": "dense",
                "matrix": "A.npy",
                "rows": rows,
                "convention": "A[i, p] = pattern i at pixel p = y * W + x (0 or 1, float32); b = A t (the buckets, float64)",
            })
        }
        other => bail!(
            "the comparison exports Bernoulli and Hadamard problems, not {}",
            other.name()
        ),
    };
    let manifest = json!({
        "name": problem.name,
        "title": problem.title,
        "scene": problem.case.scene,
        "width": w,
        "height": h,
        "spec": serde_json::from_str::<Value>(&spec.to_json())?,
        "family": spec.family().name(),
        "noise": problem.case.noise.name(),
        "truth": "truth.npy",
        "b": "b.npy",
        "b_clean": "b_clean.npy",
        "operator": operator,
        "ours": problem.ours,
        "reference": problem.reference,
    });
    std::fs::write(
        dir.join("problem.json"),
        serde_json::to_string_pretty(&manifest)?,
    )?;
    Ok(manifest)
}

/// One reconstruction in the comparison table.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    pub tool: String,
    pub method: String,
    pub params: Value,
    pub iterations: Option<u64>,
    pub convergence: String,
    /// Competitors: the best weight re-solved with 2x the iterations (PSNR, iterations,
    /// objective).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub convergence_check: Option<Value>,
    /// Competitors: the objective `1/2 ||A x - b||^2 + weight R(x)` of the original problem at
    /// this image, its parts, `||A x - b|| / ||b||` and the truth's objective (computed by run.py).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub objective: Option<Value>,
    pub psnr_db: f64,
    pub ssim: f64,
    /// Median solve time over the repeats.
    pub seconds: f64,
    pub all_seconds: Vec<f64>,
    /// Competitors: points of the weight sweep, and the time of the whole sweep.
    pub sweep_points: Option<usize>,
    pub sweep_seconds: Option<f64>,
    /// Every sweep point: its parameters and PSNR (competitors).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub sweep: Vec<Value>,
    pub image: String,
    pub note: String,
}

#[derive(Clone, Debug, Serialize)]
pub struct ProblemResult {
    pub name: String,
    pub title: String,
    pub reference: String,
    pub rows: Vec<Row>,
    /// 0/1 rows: the naive and the fair set-up of one regulariser at the same weight (each
    /// set-up's best in turn), with their objective values on the original problem.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub same_problem: Vec<Value>,
}

/// Options of a comparison run.
pub struct Options {
    pub out: PathBuf,
    pub work: PathBuf,
    pub python: String,
    pub repeat: u32,
    pub only_ours: bool,
    /// Only these problems (names); all when `None`.
    pub problems: Option<Vec<String>>,
    /// Problems on scenes named by `--scenes` ([`scene_problems`]); when given and `problems`
    /// is `None`, only these run.
    pub scene_problems: Vec<CompareProblem>,
    /// The `--scenes ...` (and family/noise/size/ratio) arguments that built `scene_problems`,
    /// for the command line in the report.
    pub scene_args: String,
}

/// The repository root (bench/compare/run.py lives there).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("server/ has a parent")
        .to_path_buf()
}

pub fn run(opts: &Options) -> anyhow::Result<()> {
    let contention = super::machine::Contention::start();
    let problems_dir = opts.work.join("problems");
    let results_dir = opts.work.join("results");
    std::fs::create_dir_all(&results_dir)?;
    let mut results = Vec::new();
    let mut truths = BTreeMap::new();
    // The noisy problems run when named (or all of them by `noisy`), the noise-free ones by
    // default.
    let selected: Vec<CompareProblem> = match &opts.problems {
        None if !opts.scene_problems.is_empty() => opts.scene_problems.clone(),
        None => problems(),
        Some(names) => problems()
            .into_iter()
            .chain(noisy_problems())
            .chain(opts.scene_problems.iter().cloned())
            .filter(|p| {
                names
                    .iter()
                    .any(|n| *n == p.name || (n == "noisy" && p.case.noise != Noise::None))
            })
            .collect(),
    };
    ensure!(
        !selected.is_empty(),
        "--problems names none of: {}",
        problems()
            .iter()
            .chain(&noisy_problems())
            .chain(&opts.scene_problems)
            .map(|p| p.name.as_str())
            .chain(["noisy"])
            .collect::<Vec<_>>()
            .join(", ")
    );
    for p in selected.iter().cloned() {
        eprintln!("compare: {} (simulating, exporting)", p.name);
        let acq = acquire(&p.case)?;
        export(&p, &acq, &problems_dir.join(&p.name))?;
        let mut rows = Vec::new();
        for &method in p.ours {
            let case = Case {
                method: method.into(),
                ..p.case.clone()
            };
            let mut times = Vec::new();
            let mut last = None;
            for _ in 0..opts.repeat.max(1) {
                let (m, image) = measure_with_image(&case, &acq.spec, &acq.truth, &acq.values);
                times.push(m.seconds);
                last = Some((m, image));
            }
            let (m, image) = last.expect("at least one run");
            if let Some(e) = &m.error {
                bail!("{} {method}: {e}", p.name);
            }
            let image = image.expect("a finished reconstruction has an image");
            let file = format!("{}/helmholtz-{method}.npy", p.name);
            std::fs::create_dir_all(results_dir.join(&p.name))?;
            let (w, h) = (p.case.size.0 as usize, p.case.size.1 as usize);
            write_npy(
                results_dir.join(&file),
                &Array2::from_shape_vec((h, w), image)?,
            )?;
            let row = Row {
                tool: "helmholtz".into(),
                method: method.into(),
                params: m.report["params"].clone(),
                iterations: m.report["iterations"].as_u64(),
                convergence: "the solver's own stopping rule".into(),
                convergence_check: None,
                objective: None,
                // Correlation images have no physical scale: scored after the gain/offset fit.
                psnr_db: m.quality_db(),
                ssim: m.quality_ssim(),
                seconds: median(&times),
                all_seconds: times,
                sweep_points: None,
                sweep_seconds: None,
                sweep: Vec::new(),
                image: file,
                note: if super::grid::scale_free(method) {
                    "PSNR and SSIM after the least-squares gain and offset to the truth".into()
                } else {
                    ours_note(&m.report)
                },
            };
            eprintln!(
                "compare: {} helmholtz {method}: {:.2} dB, SSIM {:.3}, {:.3} s",
                p.name, row.psnr_db, row.ssim, row.seconds
            );
            rows.push(row);
        }
        truths.insert(p.name.clone(), (acq.truth, p.case.size));
        results.push(ProblemResult {
            name: p.name.clone(),
            title: p.title.clone(),
            reference: p.reference.clone(),
            rows,
            same_problem: Vec::new(),
        });
    }
    let mut tools = Value::Null;
    if !opts.only_ours {
        let script = repo_root().join("bench/compare/run.py");
        eprintln!("compare: running {} {}", opts.python, script.display());
        let status = Command::new(&opts.python)
            .arg(&script)
            .arg("--problems")
            .arg(&problems_dir)
            .arg("--out")
            .arg(&results_dir)
            .arg("--repeat")
            .arg(opts.repeat.to_string())
            .arg("--only")
            .arg(
                selected
                    .iter()
                    .map(|p| p.name.as_str())
                    .collect::<Vec<_>>()
                    .join(","),
            )
            .status()
            .with_context(|| format!("starting {}", opts.python))?;
        ensure!(status.success(), "{} failed: {status}", script.display());
        let theirs: Value =
            serde_json::from_str(&std::fs::read_to_string(results_dir.join("results.json"))?)?;
        tools = theirs["environment"].clone();
        score_competitors(&theirs, &results_dir, &truths, &mut results)?;
    }
    write_report(
        &opts.out,
        opts.repeat,
        opts.problems.as_deref(),
        &opts.scene_args,
        &contention,
        &tools,
        &results,
    )
}

fn median(times: &[f64]) -> f64 {
    let mut s = times.to_vec();
    s.sort_by(f64::total_cmp);
    s[s.len() / 2]
}

fn ours_note(report: &Value) -> String {
    let Some(a) = report["details"]["auto"].get(0) else {
        return String::new();
    };
    let res = &a["resolution"]["supported"];
    format!(
        "chose {} (weight {}) at {}x{}, from held-out rows",
        a["model"].as_str().unwrap_or("?"),
        a["lambda_fraction"]
            .as_f64()
            .map(|f| format!("{f:.0e} of lambda_max"))
            .unwrap_or_default(),
        res[0],
        res[1]
    )
}

/// Reads an image the Python side wrote (float32 or float64, `H x W`).
pub fn read_image(path: &Path, w: usize, h: usize) -> anyhow::Result<Vec<f32>> {
    let data: Vec<f32> = match read_npy::<_, Array2<f32>>(path) {
        Ok(a) => {
            ensure!(
                a.dim() == (h, w),
                "{}: shape {:?}, expected ({h}, {w})",
                path.display(),
                a.dim()
            );
            a.iter().copied().collect()
        }
        Err(_) => {
            let a: Array2<f64> =
                read_npy(path).with_context(|| format!("reading {}", path.display()))?;
            ensure!(
                a.dim() == (h, w),
                "{}: shape {:?}, expected ({h}, {w})",
                path.display(),
                a.dim()
            );
            a.iter().map(|&v| v as f32).collect()
        }
    };
    ensure!(
        data.iter().all(|v| v.is_finite()),
        "{}: not finite",
        path.display()
    );
    Ok(data)
}

/// `objective` of a run as a short text: value, the truth's, and the relative data residual.
fn objective_text(obj: &Value) -> Option<String> {
    let o = obj["objective"].as_f64()?;
    let mut text = format!("objective {o:.4e}");
    if let Some(t) = obj["truth_objective"].as_f64() {
        let _ = write!(text, " (the truth's {t:.4e})");
    }
    if let Some(r) = obj["relative_residual"].as_f64() {
        let _ = write!(text, ", ||At-b||/||b|| {r:.1e}");
    }
    Some(text)
}

/// Scores every run of the Python side and keeps, per (problem, tool, method), the best PSNR.
fn score_competitors(
    theirs: &Value,
    results_dir: &Path,
    truths: &BTreeMap<String, (Vec<f32>, (u32, u32))>,
    results: &mut [ProblemResult],
) -> anyhow::Result<()> {
    let runs = theirs["runs"]
        .as_array()
        .context("results.json has no runs")?;
    type Key = (String, String, String);
    // (problem, tool, method) -> scored runs
    let mut groups: BTreeMap<Key, Vec<(f64, f64, &Value)>> = BTreeMap::new();
    // The best weight re-solved with 2x the iterations: how far from convergence the table is.
    let mut checks: BTreeMap<Key, (f64, u64, Value)> = BTreeMap::new();
    // Both set-ups at one weight (0/1 rows): scored below.
    let mut same: Vec<&Value> = Vec::new();
    for r in runs {
        if r["role"] == "same_problem_check" {
            same.push(r);
            continue;
        }
        let problem = r["problem"].as_str().context("run without problem")?;
        let (truth, (w, h)) = truths
            .get(problem)
            .with_context(|| format!("unknown problem {problem}"))?;
        let image = read_image(
            &results_dir.join(r["image"].as_str().context("run without image")?),
            *w as usize,
            *h as usize,
        )?;
        let psnr = metrics::psnr(&image, truth);
        let ssim = metrics::ssim(&image, truth, *w as usize, *h as usize);
        let key = (
            problem.to_string(),
            r["tool"].as_str().unwrap_or("?").to_string(),
            r["method"].as_str().unwrap_or("?").to_string(),
        );
        if r["role"] == "convergence_check" {
            checks.insert(
                key,
                (
                    psnr,
                    r["iterations"].as_u64().unwrap_or(0),
                    r["objective"].clone(),
                ),
            );
        } else {
            groups.entry(key).or_default().push((psnr, ssim, r));
        }
    }
    for (key, mut scored) in groups {
        let check = checks.get(&key).cloned();
        let sweep_seconds: f64 = scored
            .iter()
            .map(|(_, _, r)| r["sweep_seconds"].as_f64().unwrap_or(0.0))
            .sum();
        let sweep: Vec<Value> = scored
            .iter()
            .map(|(p, s, r)| json!({ "params": r["params"], "psnr_db": p, "ssim": s, "seconds": r["seconds"], "iterations": r["iterations"], "objective": r["objective"] }))
            .collect();
        let n = scored.len();
        scored.sort_by(|a, b| b.0.total_cmp(&a.0));
        let (psnr, ssim, best) = scored[0];
        let (problem, tool, method) = key;
        let mut notes: Vec<String> = best["note"]
            .as_str()
            .filter(|s| !s.is_empty())
            .map(str::to_string)
            .into_iter()
            .collect();
        if let Some((p3, it3, obj3)) = &check {
            let mut text = format!(
                "convergence: the same weight with {it3} iterations gives {p3:.2} dB ({:+.2} dB)",
                p3 - psnr
            );
            if let (Some(o3), Some(o)) = (
                obj3["objective"].as_f64(),
                best["objective"]["objective"].as_f64(),
            ) {
                let _ = write!(
                    text,
                    " and objective {o3:.4e} ({:+.2} %)",
                    100.0 * (o3 - o) / o
                );
            }
            notes.push(text);
        }
        if let Some(text) = objective_text(&best["objective"]) {
            notes.push(text);
        }
        if n > 1 && !best["timed_best"].as_bool().unwrap_or(false) {
            notes.push("the Python side re-timed another point: its MSE ranking disagreed".into());
        }
        let note = notes.join("; ");
        let all_seconds: Vec<f64> = best["all_seconds"]
            .as_array()
            .map(|a| a.iter().filter_map(Value::as_f64).collect())
            .unwrap_or_default();
        let row = Row {
            tool,
            method,
            params: best["params"].clone(),
            iterations: best["iterations"].as_u64(),
            convergence: best["convergence"].as_str().unwrap_or_default().into(),
            convergence_check: check.map(
                |(p3, it3, obj3)| json!({ "iterations": it3, "psnr_db": p3, "objective": obj3 }),
            ),
            objective: best.get("objective").cloned(),
            psnr_db: psnr,
            ssim,
            seconds: best["seconds"].as_f64().unwrap_or(f64::NAN),
            all_seconds,
            sweep_points: (n > 1).then_some(n),
            sweep_seconds: (n > 1).then_some(sweep_seconds),
            sweep: if n > 1 { sweep } else { Vec::new() },
            image: best["image"].as_str().unwrap_or_default().into(),
            note,
        };
        let p = results
            .iter_mut()
            .find(|p| p.name == problem)
            .expect("checked above");
        p.rows.push(row);
    }
    for r in same {
        let problem = r["problem"].as_str().context("check without problem")?;
        let (truth, (w, h)) = truths
            .get(problem)
            .with_context(|| format!("unknown problem {problem}"))?;
        let mut sides = serde_json::Map::new();
        for side in ["naive", "fair"] {
            let s = &r[side];
            let image = read_image(
                &results_dir.join(s["image"].as_str().context("check without image")?),
                *w as usize,
                *h as usize,
            )?;
            let key = (
                problem.to_string(),
                s["tool"].as_str().unwrap_or("?").to_string(),
                s["method"].as_str().unwrap_or("?").to_string(),
            );
            // Twice the iterations exist for the best weight only.
            let check = if s["at_its_best"].as_bool().unwrap_or(false) {
                checks.get(&key).cloned()
            } else {
                None
            };
            sides.insert(
                side.into(),
                json!({
                    "tool": s["tool"], "method": s["method"], "iterations": s["iterations"], "objective": s["objective"],
                    "psnr_db": metrics::psnr(&image, truth), "at_its_best": s["at_its_best"],
                    "check": check.map(|(p3, it3, obj3)| json!({ "iterations": it3, "psnr_db": p3, "objective": obj3 })),
                }),
            );
        }
        let entry = json!({
            "regulariser": r["regulariser"], "weight": r["weight"], "fraction": r["fraction"], "at": r["at"],
            "truth_objective": r["truth_objective"], "naive": sides["naive"], "fair": sides["fair"],
        });
        let p = results
            .iter_mut()
            .find(|p| p.name == problem)
            .expect("checked above");
        p.same_problem.push(entry);
    }
    Ok(())
}

fn fmt_params(v: &Value) -> String {
    match v {
        Value::Object(m) if m.is_empty() => "-".into(),
        Value::Object(m) => m
            .iter()
            .map(|(k, v)| match v {
                Value::String(s) => format!("{k}={s}"),
                Value::Number(n) => match n.as_f64() {
                    Some(f) if n.is_f64() => format!("{k}={f:.3e}"),
                    _ => format!("{k}={n}"),
                },
                other => format!("{k}={other}"),
            })
            .collect::<Vec<_>>()
            .join(", "),
        Value::Null => "-".into(),
        other => other.to_string(),
    }
}

fn write_report(
    dir: &Path,
    repeat: u32,
    problems: Option<&[String]>,
    scene_args: &str,
    contention: &super::machine::Contention,
    environment: &Value,
    results: &[ProblemResult],
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    let repeat_arg = if repeat > 1 {
        format!(" --repeat {repeat}")
    } else {
        String::new()
    };
    let problems_arg = problems
        .map(|p| format!(" --problems {}", p.join(",")))
        .unwrap_or_default();
    let command = format!(
        "cargo run{} -p helmholtz-bench -- --preset compare{repeat_arg}{problems_arg}{scene_args} --out {}",
        if cfg!(debug_assertions) {
            ""
        } else {
            " --release"
        },
        dir.display()
    );
    let mut machine = json!({
        "cores": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
        "rayon_threads": rayon::current_num_threads(),
        "profile": if cfg!(debug_assertions) { "debug" } else { "release" },
    });
    super::machine::merge(&mut machine, &contention.finish());
    let raw = json!({ "command": command, "machine": machine, "python": environment, "problems": results });
    std::fs::write(
        dir.join("comparison.json"),
        serde_json::to_string_pretty(&raw)?,
    )?;

    let mut md = String::new();
    let _ = writeln!(
        md,
        "# Side by side: Helmholtz against the tools users would otherwise use\n"
    );
    let _ = writeln!(
        md,
        "Produced by `{command}` ({} cores, {} build; {}; the Python side: {}). Raw figures, every sweep point included: [`comparison.json`](comparison.json).\n",
        machine["cores"],
        machine["profile"].as_str().unwrap_or("?"),
        super::machine::sentence(&machine),
        env_line(environment)
    );
    let _ = write!(md, "{}", auto_summary(results));
    let _ = write!(md, "{}", METHOD_TEXT);
    let _ = writeln!(md, "{}", bernoulli_summary(results));
    for p in results {
        let _ = writeln!(md, "## {}\n", p.title);
        let _ = writeln!(
            md,
            "Issue's reference figures for the other tools: {}.\n",
            p.reference
        );
        let _ = writeln!(
            md,
            "| tool | method | parameters | iterations | PSNR dB | SSIM | seconds | notes |"
        );
        let _ = writeln!(md, "|---|---|---|---|---|---|---|---|");
        let mut rows: Vec<&Row> = p.rows.iter().filter(|r| r.tool == "helmholtz").collect();
        let mut others: Vec<&Row> = p.rows.iter().filter(|r| r.tool != "helmholtz").collect();
        others.sort_by(|a, b| b.psnr_db.total_cmp(&a.psnr_db));
        rows.extend(others);
        for r in &rows {
            let mut notes = Vec::new();
            if !r.note.is_empty() {
                notes.push(r.note.clone());
            }
            if let (Some(n), Some(s)) = (r.sweep_points, r.sweep_seconds) {
                notes.push(format!(
                    "best of {n} weights by ground truth (whole sweep {s:.2} s)"
                ));
            }
            if !r.convergence.is_empty() && r.tool != "helmholtz" {
                notes.push(r.convergence.clone());
            }
            let _ = writeln!(
                md,
                "| {} | {} | {} | {} | {:.2} | {:.3} | {} | {} |",
                r.tool,
                r.method,
                fmt_params(&r.params),
                r.iterations
                    .map(|i| i.to_string())
                    .unwrap_or_else(|| "-".into()),
                r.psnr_db,
                r.ssim,
                fmt_seconds(r.seconds),
                notes.join("; ")
            );
        }
        md.push('\n');
        if let Some(line) = verdict(&p.rows) {
            let _ = writeln!(md, "{line}\n");
        }
        same_problem_table(&mut md, &p.same_problem);
    }
    std::fs::write(dir.join("comparison.md"), md)?;
    Ok(())
}

/// The cheapest single solve of another tool (any weight of any sweep) whose PSNR reaches
/// `psnr`: (seconds, tool and method, its PSNR); `None` when no point reaches it.
fn cheapest_match(rows: &[Row], psnr: f64) -> Option<(f64, String, f64)> {
    let mut best: Option<(f64, String, f64)> = None;
    for r in rows.iter().filter(|r| r.tool != "helmholtz") {
        let points: Vec<(f64, f64)> = if r.sweep.is_empty() {
            vec![(r.psnr_db, r.seconds)]
        } else {
            r.sweep
                .iter()
                .filter_map(|v| Some((v["psnr_db"].as_f64()?, v["seconds"].as_f64()?)))
                .collect()
        };
        for (p, sec) in points {
            if p >= psnr && best.as_ref().is_none_or(|b| sec < b.0) {
                best = Some((sec, format!("{} {}", r.tool, r.method), p));
            }
        }
    }
    best
}

/// Issue 20's targets per problem where `auto` ran: its PSNR against the best other tool at its
/// ground-truth-best weight, DGI after its oracle gain and offset, and the cheapest single solve
/// of another tool that reaches `auto`'s PSNR against `auto`'s time.
fn auto_summary(results: &[ProblemResult]) -> String {
    let mut md = String::new();
    let mut lines = Vec::new();
    let (mut within, mut ahead, mut above_dgi, mut dgi_n) = (0, 0, 0, 0);
    let (mut fast, mut unreached, mut n) = (0, 0, 0);
    for p in results {
        let Some(auto) = p
            .rows
            .iter()
            .find(|r| r.tool == "helmholtz" && r.method == "auto")
        else {
            continue;
        };
        let Some(best) = p
            .rows
            .iter()
            .filter(|r| r.tool != "helmholtz")
            .max_by(|a, b| a.psnr_db.total_cmp(&b.psnr_db))
        else {
            continue;
        };
        n += 1;
        let diff = auto.psnr_db - best.psnr_db;
        within += usize::from(diff >= -0.5);
        ahead += usize::from(diff >= 0.0);
        let dgi = p
            .rows
            .iter()
            .find(|r| r.tool == "helmholtz" && r.method == "dgi");
        if let Some(d) = dgi {
            dgi_n += 1;
            above_dgi += usize::from(auto.psnr_db >= d.psnr_db);
        }
        let matched = match cheapest_match(&p.rows, auto.psnr_db) {
            Some((sec, who, psnr)) => {
                let ratio = sec / auto.seconds;
                fast += usize::from(ratio >= 10.0);
                format!("{who}, {psnr:.2} dB in {} s | {ratio:.2}", fmt_seconds(sec))
            }
            None => {
                unreached += 1;
                "none reaches it | -".into()
            }
        };
        lines.push(format!(
            "| {} | {:.2} | {} | {} {} | {:.2} | {} | {diff:+.2} | {matched} | {} |",
            p.name,
            auto.psnr_db,
            fmt_seconds(auto.seconds),
            best.tool,
            best.method,
            best.psnr_db,
            fmt_seconds(best.seconds),
            dgi.map(|d| format!("{:.2}", d.psnr_db))
                .unwrap_or_else(|| "-".into()),
        ));
    }
    if n == 0 {
        return md;
    }
    let _ = writeln!(
        md,
        "**`auto` against the best other tool** ({n} problems): within 0.5 dB of the best other tool at its ground-truth-best weight on {within}, at or above it on {ahead}; at or above DGI after DGI's oracle gain and offset on {above_dgi} of {dgi_n}. No single solve of another tool (any weight of its sweep) reaches `auto`'s PSNR on {unreached}; on {fast} more the cheapest one that does takes at least 10x `auto`'s time.\n"
    );
    let _ = writeln!(
        md,
        "| problem | auto dB | auto s | best other tool | its dB | its s | auto - best dB | cheapest other solve reaching auto's dB | its s / auto s | DGI fitted dB |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|");
    for l in lines {
        let _ = writeln!(md, "{l}");
    }
    md.push('\n');
    md
}

/// The computed bullet after the method text: on every problem with both set-ups, what each
/// reaches, next to the reference figures.
fn bernoulli_summary(results: &[ProblemResult]) -> String {
    let mut parts = Vec::new();
    for p in results
        .iter()
        .filter(|p| p.rows.iter().any(|r| r.method.ends_with("set-up")))
    {
        let mut rows: Vec<&Row> = p
            .rows
            .iter()
            .filter(|r| r.method.ends_with("set-up"))
            .collect();
        rows.sort_by(|a, b| a.method.cmp(&b.method));
        let figures: Vec<String> = rows
            .iter()
            .map(|r| {
                format!(
                    "{} {} {:.2} dB in {} s",
                    r.tool,
                    r.method,
                    r.psnr_db,
                    fmt_seconds(r.seconds)
                )
            })
            .collect();
        parts.push(format!(
            "{}: {} (the issue's reference figures: {})",
            p.name,
            figures.join(", "),
            p.reference
        ));
    }
    if parts.is_empty() {
        return String::new();
    }
    format!(
        "- **What the other tools reach on 0/1 rows in this run** (best weight by ground truth, that solve's time): {}.\n",
        parts.join("; ")
    )
}

/// The naive and the fair set-up on the same objective at the same weight (module docs of run.py).
fn same_problem_table(md: &mut String, entries: &[Value]) {
    if entries.is_empty() {
        return;
    }
    let _ = writeln!(
        md,
        "Same problem, two set-ups: at each set-up's best weight both minimise the same objective `1/2 ||A t - b||^2 + weight R(t)` \
         (R = TV or the l1 norm of the db4 coefficients); the lower value is the better minimiser. Twice the iterations are shown where \
         they were run (each set-up's best weight), and the truth's objective for scale (noise-free data: the minimum lies below it).\n"
    );
    let _ = writeln!(
        md,
        "| R | weight (fraction) | best of | set-up | iterations | objective | \\|At-b\\|/\\|b\\| | PSNR dB |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|");
    let num =
        |v: &Value, f: &dyn Fn(f64) -> String| v.as_f64().map(f).unwrap_or_else(|| "-".into());
    for e in entries {
        let reg = e["regulariser"].as_str().unwrap_or("?");
        let weight = format!(
            "{} ({})",
            num(&e["weight"], &|w| format!("{w:.3e}")),
            num(&e["fraction"], &|f| format!("{f:.1e}"))
        );
        let at = match e["at"].as_str() {
            Some("naive_best") => "naive",
            Some("fair_best") => "fair",
            _ => "?",
        };
        let mut line = |label: String, it: &Value, obj: &Value, psnr: &Value| {
            let _ = writeln!(
                md,
                "| {reg} | {weight} | {at} | {label} | {} | {} | {} | {} |",
                it.as_u64()
                    .map(|i| i.to_string())
                    .unwrap_or_else(|| "-".into()),
                num(&obj["objective"], &|o| format!("{o:.4e}")),
                num(&obj["relative_residual"], &|r| format!("{r:.2e}")),
                num(psnr, &|p| format!("{p:.2}"))
            );
        };
        for side in ["naive", "fair"] {
            let s = &e[side];
            line(
                format!(
                    "{} {}",
                    s["tool"].as_str().unwrap_or("?"),
                    s["method"].as_str().unwrap_or("?")
                ),
                &s["iterations"],
                &s["objective"],
                &s["psnr_db"],
            );
            let c = &s["check"];
            if !c.is_null() {
                line(
                    "the same, twice the iterations".into(),
                    &c["iterations"],
                    &c["objective"],
                    &c["psnr_db"],
                );
            }
        }
        let _ = writeln!(
            md,
            "| {reg} | {weight} | {at} | the truth | - | {} | 0 | - |",
            num(&e["truth_objective"], &|o| format!("{o:.4e}"))
        );
    }
    md.push('\n');
}

fn fmt_seconds(s: f64) -> String {
    if s < 0.01 {
        format!("{s:.5}")
    } else if s < 10.0 {
        format!("{s:.3}")
    } else {
        format!("{s:.1}")
    }
}

fn env_line(env: &Value) -> String {
    match env {
        Value::Object(m) => m
            .iter()
            .filter(|(k, _)| k.as_str() != "notes")
            .map(|(k, v)| {
                format!(
                    "{k} {}",
                    v.as_str()
                        .map(str::to_string)
                        .unwrap_or_else(|| v.to_string())
                )
            })
            .collect::<Vec<_>>()
            .join(", "),
        _ => "not run".into(),
    }
}

/// The best of ours against the best other tool, by PSNR, with their times; computed, not written.
fn verdict(rows: &[Row]) -> Option<String> {
    let best = |ours: bool| {
        rows.iter()
            .filter(|r| (r.tool == "helmholtz") == ours)
            .max_by(|a, b| a.psnr_db.total_cmp(&b.psnr_db))
    };
    let (o, t) = (best(true)?, best(false)?);
    let faster_theirs = rows
        .iter()
        .filter(|r| r.tool != "helmholtz")
        .min_by(|a, b| a.seconds.total_cmp(&b.seconds))?;
    let speed = if o.seconds <= t.seconds {
        format!("{:.1}x faster", t.seconds / o.seconds)
    } else {
        format!("{:.1}x slower", o.seconds / t.seconds)
    };
    Some(format!(
        "Best of ours by PSNR: `{}` {:.2} dB in {} s; best other tool: {} {} {:.2} dB in {} s (its best weight alone; its sweep is not counted): ours {:+.2} dB, {speed}. The fastest other tool: {} {} {:.2} dB in {} s.",
        o.method,
        o.psnr_db,
        fmt_seconds(o.seconds),
        t.tool,
        t.method,
        t.psnr_db,
        fmt_seconds(t.seconds),
        o.psnr_db - t.psnr_db,
        faster_theirs.tool,
        faster_theirs.method,
        faster_theirs.psnr_db,
        fmt_seconds(faster_theirs.seconds)
    ))
}

const METHOD_TEXT: &str = "How it is measured:

- **Same problems.** Each problem is simulated once (noise-free unless its title names the noise: Gaussian read noise at 30 dB SNR of the total bucket power, or Poisson shot noise at 1e4 photons per pattern, the same draw for every tool; the scene's transport scaled to [0, 1]) and exported as NPY: the ground truth, the measurement operator exactly as our solvers apply it (Bernoulli: the dense 0/1 matrix; Hadamard: the measured rows' natural indices, an orthonormal Walsh-Hadamard subset `A = S H / sqrt(k)` with data `b = (y+ - y-) / sqrt(k)`), and the data (see `bench/src/compare.rs`). The other tools read these files; ours run on the same simulated buckets.
- **Same metric.** Every image, ours and theirs, is scored by the service's own `recon::metrics` (PSNR with the truth's range as peak, SSIM with an 11x11 Gaussian window), raw (no gain/offset fit).
- **Times** are wall-clock seconds of the solve alone (not loading, not the operator's set-up from files; for ours the patterns are regenerated from the seed inside the timed call, and every iterative method's time includes its held-out error estimate), the median of the repeats, with default threads (rayon / the BLAS of numpy and torch) on the same 2 cores. The machine is a shared VM: times vary by up to 2x between runs.
- **Weights favour the other tools.** Their regularisation weight is swept over a grid and the best point **by ground truth** is shown (its time is that point's solve alone; the whole sweep's time is in the notes). Ours use no ground truth: `tv` runs at its default weight and `auto` chooses the model and weight from held-out rows.
- **The other tools' set-up** (`bench/compare/run.py`, versions pinned in `bench/compare/requirements*.txt`; on 0/1 rows this is the *naive set-up*, see below): pylops FISTA on orthonormal db4 wavelet coefficients (pylops `DWT2D`, periodised, coarsest scale 8x8; the approximation coefficients are penalised too, as pylops does), step from pylops' own eigenvalue estimate; pyproximal `PrimalDual` (Chambolle-Pock) on `[A / ||A||; grad]` with `L2` data, isotropic `L21` TV and `Box(lower=0)` for t >= 0, `tau = mu = 0.99 / 3`; for Hadamard problems, spyrit's `HadamSplit2d` (its rows ordered to be ours, checked against our frames) with `PinvNet(Unsplit, use_fast_pinv=True)`, i.e. the zero-filled inverse, timed after one untimed warm-up call. pylops has no Walsh-Hadamard operator, so the Hadamard rows are a pylops `LinearOperator` around a numpy fast Walsh-Hadamard transform (a dense matrix would only be slower). The Bernoulli matrix is multiplied in float32 (exact for 0/1).
- **Iterations.** Fixed counts: Hadamard 500 (primal-dual) and 200 (FISTA); Bernoulli 500 at 128x128 and 300 at 256x256, both set-ups (one iteration costs one or two products with the dense matrix, ~50 ms and ~150 ms here). Every best weight is re-solved with twice the iterations (untimed) and the notes give that PSNR and objective: where they move, the solver had not converged.
- **Two set-ups on 0/1 rows, one problem.** Called as above (the *naive set-up* rows), both solvers crawl on Bernoulli rows: their common mode makes `||A||` about 30 times the other singular values, so the steps (`1 / ||A||^2`, or `A / ||A||` in the primal-dual) leave every other direction almost still. The *fair set-up* rows solve the same objective (`1/2 ||A t - b||^2 + weight R(t)`, same data, same unknown, `t >= 0` for TV) written with the exact identity `||A t - b||^2 = ||A_c t - b_c||^2 + n (m . t - mean(b))^2` (`m = A^T 1 / n` the mean row, `A_c = A - 1 m^T` the centred rows, `b_c = b - mean(b)`), as our solvers do, and treat the one stiff *mean equation* apart, with pyproximal's own building blocks: the primal-dual runs on `K = [A_c / ||A_c||; m^T / ||m||; grad]` with one `L2` per block (their weights rescaled so that the objective is unchanged: Pock and Chambolle's 2011 preconditioning with a block-diagonal dual step), `||K||^2 <= 10`, `tau = 10 s`, `mu = s / 10`, `s = 0.99 / sqrt(10)` (the ratio 10 picked once, on the 128x128 problem, by the objective reached in 300 iterations, not by ground truth); FISTA is pyproximal's `ProximalGradient(acceleration=\"fista\")` on the centred data term (step `1 / (1.01 ||A_c||^2)`, ARPACK) with the mean equation inside the proximal map of the l1 term (exact: a one-dimensional monotone root, `L1MeanEquation` in `run.py`). Centring and `||A_c||` are inside the timed solve. Both set-ups sweep weight fractions of the same `lambda_max` (the same fraction is the same weight); the fair grids start lower, where the better-converged solvers find their best, and may be extended by two points instead of one. **Same problem, checked:** every point's objective on the original `A, b` is recorded, and each set-up is also solved (untimed) at the other's best weight: the table under each 0/1 section compares the two objective values at both weights (the lower, the better minimiser), with twice the iterations at each set-up's own best weight and the truth's value for scale.
- **TVAL3** is MATLAB code; no maintained Python port of it is on PyPI (the only names near `tval` there are unrelated validators), so it is not in the table.
";

#[cfg(test)]
mod tests {
    use super::*;

    fn small(family: &str, size: u32, ratio: f64) -> (CompareProblem, Acquisition) {
        let p = CompareProblem {
            name: "small".into(),
            title: "small".into(),
            case: case("camera", size, family, ratio),
            ours: &["tv"],
            reference: "-".into(),
        };
        let acq = acquire(&p.case).unwrap();
        (p, acq)
    }

    #[test]
    fn bernoulli_export_round_trips_and_the_matrix_gives_the_buckets() {
        let (p, acq) = small("bernoulli", 16, 0.2);
        let dir = tempfile::tempdir().unwrap();
        let manifest = export(&p, &acq, dir.path()).unwrap();
        assert_eq!(manifest["operator"]["kind"], "dense");
        assert_eq!(
            (manifest["width"].as_u64(), manifest["height"].as_u64()),
            (Some(16), Some(16))
        );
        let truth: Array2<f32> = read_npy(dir.path().join("truth.npy")).unwrap();
        assert_eq!(truth.dim(), (16, 16));
        assert_eq!(truth.iter().copied().collect::<Vec<_>>(), acq.truth);
        let a: Array2<f32> = read_npy(dir.path().join("A.npy")).unwrap();
        let b: Array1<f64> = read_npy(dir.path().join("b.npy")).unwrap();
        let rows = acq.spec.count() as usize;
        assert_eq!(a.dim(), (rows, 256));
        assert_eq!(b.to_vec(), acq.values);
        assert!(
            a.iter().all(|&v| v == 0.0 || v == 1.0)
                && a.iter().any(|&v| v == 1.0)
                && a.iter().any(|&v| v == 0.0)
        );
        // The exported matrix times the ground truth is the simulator's buckets.
        let t: Vec<f64> = acq.truth.iter().map(|&v| v as f64).collect();
        for r in 0..rows {
            let at: f64 = a.row(r).iter().zip(&t).map(|(&x, &y)| x as f64 * y).sum();
            assert!(
                (at - b[r]).abs() <= 1e-9 * b[r].abs().max(1.0),
                "row {r}: {at} vs {}",
                b[r]
            );
        }
        // And it is the patterns of the contract (pattern 0 from the generator).
        let mut p0 = vec![0f32; 256];
        helmholtz_proto::patterns::PatternGenerator::new(&acq.spec).fill_values(0, &mut p0);
        assert_eq!(a.row(0).to_vec(), p0);
        let again: Value = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join("problem.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(again, manifest);
    }

    #[test]
    fn hadamard_export_is_the_operator_our_solvers_apply() {
        let (p, acq) = small("hadamard", 16, 0.15);
        let dir = tempfile::tempdir().unwrap();
        let manifest = export(&p, &acq, dir.path()).unwrap();
        let natural: Array1<i64> = read_npy(dir.path().join("natural.npy")).unwrap();
        let b: Array1<f64> = read_npy(dir.path().join("b.npy")).unwrap();
        let frames: Array1<f64> = read_npy(dir.path().join("frames.npy")).unwrap();
        let m = acq.spec.count() as usize / 2;
        assert_eq!((natural.len(), b.len(), frames.len()), (m, m, 2 * m));
        assert_eq!(manifest["operator"]["rows"].as_u64(), Some(m as u64));
        assert_eq!(frames.to_vec(), acq.values);
        let k = 256usize;
        let t: Vec<f64> = acq.truth.iter().map(|&v| v as f64).collect();
        // The documented convention, as a dense matrix, times the truth is the exported data ...
        for r in 0..m {
            let n = natural[r] as usize;
            let row_dot: f64 = (0..k)
                .map(|p| {
                    if (n & p).count_ones().is_multiple_of(2) {
                        t[p]
                    } else {
                        -t[p]
                    }
                })
                .sum::<f64>()
                / (k as f64).sqrt();
            assert!(
                (row_dot - b[r]).abs() < 1e-9,
                "row {r}: {row_dot} vs {}",
                b[r]
            );
            assert!(((frames[2 * r] - frames[2 * r + 1]) / (k as f64).sqrt() - b[r]).abs() < 1e-12);
        }
        // ... and the same as our operator's product.
        let op = HadamardOperator::from_spec(&acq.spec, acq.spec.count()).unwrap();
        let mut y = vec![0.0; m];
        helmholtz_recon::linop::LinearOperator::apply(&op, &t, &mut y);
        for r in 0..m {
            assert!((y[r] - b[r]).abs() < 1e-9);
        }
        // Russian-doll order starts with the DC row.
        assert_eq!(natural[0], 0);
    }

    #[test]
    fn the_same_problem_table_and_summary_show_both_set_ups() {
        let row = |method: &str, psnr: f64| Row {
            tool: "pyproximal".into(),
            method: method.into(),
            params: json!({}),
            iterations: Some(500),
            convergence: String::new(),
            convergence_check: None,
            objective: None,
            psnr_db: psnr,
            ssim: 0.5,
            seconds: 12.0,
            all_seconds: vec![12.0],
            sweep_points: None,
            sweep_seconds: None,
            sweep: Vec::new(),
            image: String::new(),
            note: String::new(),
        };
        let entry = json!({
            "regulariser": "tv", "weight": 1.5, "fraction": 1e-3, "at": "naive_best", "truth_objective": 30.0,
            "naive": { "tool": "pyproximal", "method": "primal-dual TV, naive set-up", "iterations": 500,
                       "objective": { "objective": 40.0, "relative_residual": 1e-2 }, "psnr_db": 11.0,
                       "check": { "iterations": 1000, "psnr_db": 11.5, "objective": { "objective": 39.0, "relative_residual": 9e-3 } } },
            "fair": { "tool": "pyproximal", "method": "primal-dual TV, fair set-up", "iterations": 500,
                      "objective": { "objective": 20.0, "relative_residual": 1e-3 }, "psnr_db": 20.0, "check": null },
        });
        let mut md = String::new();
        same_problem_table(&mut md, &[entry]);
        let w = "| tv | 1.500e0 (1.0e-3) | naive |";
        assert!(
            md.contains(&format!(
                "{w} pyproximal primal-dual TV, naive set-up | 500 | 4.0000e1 | 1.00e-2 | 11.00 |"
            )),
            "{md}"
        );
        assert!(
            md.contains(&format!(
                "{w} the same, twice the iterations | 1000 | 3.9000e1 | 9.00e-3 | 11.50 |"
            )),
            "{md}"
        );
        assert!(
            md.contains(&format!(
                "{w} pyproximal primal-dual TV, fair set-up | 500 | 2.0000e1 | 1.00e-3 | 20.00 |"
            )),
            "{md}"
        );
        assert!(
            md.contains(&format!("{w} the truth | - | 3.0000e1 | 0 | - |")),
            "{md}"
        );
        assert_eq!(md.matches("twice the iterations |").count(), 1, "{md}");
        let mut none = String::new();
        same_problem_table(&mut none, &[]);
        assert!(none.is_empty());
        let p = ProblemResult {
            name: "p".into(),
            title: "t".into(),
            reference: "24.4 dB".into(),
            rows: vec![
                row("primal-dual TV, naive set-up", 11.0),
                row("primal-dual TV, fair set-up", 24.0),
                row("primal-dual TV, t >= 0", 30.0),
            ],
            same_problem: Vec::new(),
        };
        let summary = bernoulli_summary(&[p]);
        assert!(summary.contains("p: pyproximal primal-dual TV, fair set-up 24.00 dB in 12.0 s, pyproximal primal-dual TV, naive set-up 11.00 dB in 12.0 s (the issue's reference figures: 24.4 dB)"), "{summary}");
        assert!(!summary.contains("30.00"));
    }

    #[test]
    fn python_images_are_read_in_either_precision_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let f32_path = dir.path().join("a.npy");
        write_npy(
            &f32_path,
            &Array2::from_shape_vec((2, 3), vec![1f32, 2., 3., 4., 5., 6.]).unwrap(),
        )
        .unwrap();
        assert_eq!(
            read_image(&f32_path, 3, 2).unwrap(),
            vec![1., 2., 3., 4., 5., 6.]
        );
        let f64_path = dir.path().join("b.npy");
        write_npy(
            &f64_path,
            &Array2::from_shape_vec((2, 3), vec![1f64, 2., 3., 4., 5., 6.5]).unwrap(),
        )
        .unwrap();
        assert_eq!(
            read_image(&f64_path, 3, 2).unwrap(),
            vec![1., 2., 3., 4., 5., 6.5]
        );
        assert!(
            read_image(&f64_path, 2, 3).is_err(),
            "a transposed shape is refused"
        );
    }

    #[test]
    fn scene_problems_are_named_per_scene_family_and_noise() {
        let ps = scene_problems(
            &["camera".into(), "/data/coins.png".into()],
            &["bernoulli".into(), "hadamard".into()],
            &[Noise::Snr30, Noise::Poisson],
            64,
            0.1,
        );
        let names: Vec<&str> = ps.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names.len(), 8);
        assert!(names.contains(&"camera64-bernoulli10-snr30"), "{names:?}");
        assert!(names.contains(&"coins64-hadamard10-poisson"), "{names:?}");
        let coins = ps
            .iter()
            .find(|p| p.name == "coins64-hadamard10-poisson")
            .unwrap();
        assert_eq!(coins.case.scene, "/data/coins.png");
        assert_eq!(coins.case.noise, Noise::Poisson);
        assert_eq!(coins.case.family, "hadamard");
        assert!(
            coins.title.contains("coins (/data/coins.png)"),
            "{}",
            coins.title
        );
        assert!(coins.ours.contains(&"auto") && coins.ours.contains(&"dgi"));
    }

    #[test]
    fn the_auto_summary_counts_the_targets_and_finds_the_cheapest_matching_solve() {
        let row = |tool: &str, method: &str, psnr: f64, seconds: f64, sweep: Vec<Value>| Row {
            tool: tool.into(),
            method: method.into(),
            params: json!({}),
            iterations: None,
            convergence: String::new(),
            convergence_check: None,
            objective: None,
            psnr_db: psnr,
            ssim: 0.5,
            seconds,
            all_seconds: vec![seconds],
            sweep_points: None,
            sweep_seconds: None,
            sweep,
            image: String::new(),
            note: String::new(),
        };
        let point = |psnr: f64, seconds: f64| json!({ "psnr_db": psnr, "seconds": seconds });
        let problem = |name: &str, rows: Vec<Row>| ProblemResult {
            name: name.into(),
            title: name.into(),
            reference: String::new(),
            rows,
            same_problem: Vec::new(),
        };
        // a: auto 20 dB in 1 s; the best other solve 20.3 dB, but a cheaper point of another
        // sweep reaches 20.1 dB in 2 s. b: auto 3 dB ahead of everything. c: 0.8 dB behind.
        let results = vec![
            problem(
                "a",
                vec![
                    row("helmholtz", "auto", 20.0, 1.0, vec![]),
                    row("helmholtz", "dgi", 19.0, 0.01, vec![]),
                    row(
                        "pyproximal",
                        "tv",
                        20.3,
                        5.0,
                        vec![point(20.3, 5.0), point(18.0, 1.0)],
                    ),
                    row(
                        "pylops",
                        "db4",
                        20.1,
                        2.0,
                        vec![point(20.1, 2.0), point(19.0, 0.5)],
                    ),
                ],
            ),
            problem(
                "b",
                vec![
                    row("helmholtz", "auto", 25.0, 1.0, vec![]),
                    row("helmholtz", "dgi", 26.0, 0.01, vec![]),
                    row(
                        "pyproximal",
                        "tv",
                        22.0,
                        5.0,
                        vec![point(22.0, 5.0), point(21.0, 0.1)],
                    ),
                ],
            ),
            problem(
                "c",
                vec![
                    row("helmholtz", "auto", 10.0, 0.1, vec![]),
                    row("pyproximal", "tv", 10.8, 3.0, vec![]),
                ],
            ),
        ];
        assert_eq!(
            cheapest_match(&results[0].rows, 20.0),
            Some((2.0, "pylops db4".to_string(), 20.1))
        );
        assert_eq!(cheapest_match(&results[1].rows, 25.0), None);
        let md = auto_summary(&results);
        assert!(
            md.contains("(3 problems): within 0.5 dB of the best other tool at its ground-truth-best weight on 2, at or above it on 1; at or above DGI after DGI's oracle gain and offset on 1 of 2. No single solve of another tool (any weight of its sweep) reaches `auto`'s PSNR on 1; on 1 more the cheapest one that does takes at least 10x"),
            "{md}"
        );
        assert!(
            md.contains("| a | 20.00 | 1.000 | pyproximal tv | 20.30 | 5.000 | -0.30 | pylops db4, 20.10 dB in 2.000 s | 2.00 | 19.00 |"),
            "{md}"
        );
        assert!(md.contains("| b | 25.00 | 1.000 | pyproximal tv | 22.00 | 5.000 | +3.00 | none reaches it | - | 26.00 |"), "{md}");
        assert!(md.contains("| c | 10.00 | 0.100 | pyproximal tv | 10.80 | 3.000 | -0.80 | pyproximal tv, 10.80 dB in 3.000 s | 30.00 | - |"), "{md}");
        assert!(auto_summary(&[]).is_empty());
    }
}
