//! `--preset transport`: camera sessions of a `helmholtz_sim` Lambertian scene (ground plane,
//! hemisphere, raised box; occlusion and one diffuse bounce), reconstructed into `T` by
//! [`helmholtz_recon::transport`]: time, stored size, relative error of `T`, PSNR of relit dual
//! images, held-out error, iterations, with and without coarse-to-fine; then the rendered scenes
//! of [`RenderedTransport`] (a Cornell-like box with radiosity interreflection, glossy spheres
//! with a caustic, a sparse slide at a grazing angle) at 32x32 projector x 48x48 camera, each
//! reconstructed and solved by plain least squares, scored on the errors a user sees (relit
//! images, total light, frames); then the interactive latency of `relight` / `primal` at
//! 256x256 projector x 64x64 camera.
//!
//! Writes `DIR/benchmarks-transport.md` and `DIR/benchmarks-transport.json`.

use std::path::Path;
use std::time::Instant;

use helmholtz_proto::{Family, HadamardOrdering, PatternGenerator, PatternSpec};
use helmholtz_sim::simulate::random::SplitMix64;
use helmholtz_sim::{Camera, CameraView, Relief, RenderedTransport};
use serde::Serialize;
use serde_json::json;

use helmholtz_recon::metrics::{psnr, relative_error};
use helmholtz_recon::transforms::TransformKind;
use helmholtz_recon::transport::{
    CameraGrid, SliceFrames, TransportConfig, TransportMatrix, reconstruct_transport,
};
use helmholtz_recon::{Control, Report, linop::test_vector};

#[derive(Clone, Debug, Serialize)]
struct Row {
    case: String,
    projector: [u32; 2],
    camera: [u32; 2],
    frames: u64,
    coarse_to_fine: bool,
    /// The model choice may compact the rows (`TransportConfig::compact`).
    compact: bool,
    seconds: f64,
    peak_heap_bytes: Option<usize>,
    transform: String,
    lambda: Option<f64>,
    /// The lasso's coefficients refitted by least squares on their support.
    refit: bool,
    stored_bytes: usize,
    dense_bytes: usize,
    nonzeros_per_row: f64,
    relative_error: f64,
    relit_psnr_db: f64,
    held_out: Option<f64>,
    iterations_per_row: f64,
    error: Option<String>,
}

#[derive(Clone, Debug, Serialize)]
struct Latency {
    transform: String,
    nonzeros: usize,
    stored_bytes: usize,
    relative_error: f64,
    relight_median_ms: f64,
    relight_p99_ms: f64,
    primal_median_ms: f64,
    primal_p99_ms: f64,
    calls: usize,
}

fn frames_of(view: &CameraView, spec: &PatternSpec) -> Vec<f32> {
    let g = PatternGenerator::new(spec);
    let mut p = vec![0f32; spec.pixels()];
    let mut out = Vec::with_capacity(spec.count() as usize * view.pixels());
    for i in 0..spec.count() {
        g.fill_values(i, &mut p);
        let p64: Vec<f64> = p.iter().map(|&v| v as f64).collect();
        out.extend(view.render(&p64).into_iter().map(|v| v as f32));
    }
    out
}

/// Relit dual images under three camera-side lights (uniform, a checkerboard, a random one),
/// PSNR of the concatenation against the scene's own relight.
fn relit_psnr(t: &TransportMatrix, view: &CameraView) -> f64 {
    let m = view.pixels();
    let w = view.width();
    let lights: Vec<Vec<f64>> = vec![
        vec![1.0; m],
        (0..m)
            .map(|j| (((j % w) / 4 + (j / w) / 4) % 2) as f64)
            .collect(),
        test_vector(m, 11).iter().map(|v| 0.5 + 0.5 * v).collect(),
    ];
    let (mut est, mut truth) = (Vec::new(), Vec::new());
    for l in &lights {
        let l32: Vec<f32> = l.iter().map(|&v| v as f32).collect();
        est.extend(t.relight(&l32));
        truth.extend(view.relight(l).into_iter().map(|v| v as f32));
    }
    psnr(&est, &truth)
}

fn dense(t: &TransportMatrix) -> Vec<f32> {
    let (cw, ch) = t.camera();
    (0..(cw * ch) as usize).flat_map(|j| t.row(j)).collect()
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

pub fn run(
    out: &Path,
    calls: usize,
    latency_only: bool,
    only: Option<&[String]>,
) -> anyhow::Result<()> {
    let contention = super::machine::Contention::start();
    let (pw, ph, cw, chh) = (64u32, 64u32, 32u32, 32u32);
    let scene = Relief::demo(pw, ph, 7);
    let view = scene.view(&Camera::tilted(cw, chh, 25.0));
    let truth = view.dense();
    let camera = CameraGrid {
        width: cw,
        height: chh,
    };
    let k = (pw * ph) as u64;
    let rd = HadamardOrdering::RussianDoll;
    // (case, family, frames, coarse-to-fine, compact): the compressive sessions also without
    // compaction (`compact: false`), side by side.
    let mut cases: Vec<(String, Family, u64, bool, bool)> = Vec::new();
    for (name, family, count, variants) in [
        (
            "hadamard complete",
            Family::Hadamard { ordering: rd },
            2 * k,
            &[(false, true)][..],
        ),
        (
            "hadamard 50 %",
            Family::Hadamard { ordering: rd },
            k,
            &[(false, true), (false, false), (true, true)][..],
        ),
        (
            "hadamard 25 %",
            Family::Hadamard { ordering: rd },
            k / 2,
            &[(false, true), (true, true)][..],
        ),
        (
            "bernoulli 25 %",
            Family::Bernoulli { fill: 0.5 },
            k / 4,
            &[(false, true), (false, false), (true, true)][..],
        ),
        (
            "bernoulli 10 %",
            Family::Bernoulli { fill: 0.5 },
            k / 10,
            &[(false, true), (false, false)][..],
        ),
    ] {
        for &(c2f, compact) in variants {
            cases.push((name.into(), family.clone(), count, c2f, compact));
        }
    }
    if latency_only {
        cases.clear();
    }
    if let Some(only) = only {
        cases.retain(|c| only.iter().any(|o| c.0.contains(o.as_str())));
    }
    let mut rows = Vec::new();
    let mut cache: Option<(String, Vec<f32>)> = None;
    for (name, family, count, c2f, compact) in cases {
        let spec = PatternSpec::new(family, pw, ph, count, 3)?;
        let key = format!("{name}/{count}");
        if cache.as_ref().map(|c| &c.0) != Some(&key) {
            cache = Some((key.clone(), frames_of(&view, &spec)));
        }
        let f = &cache.as_ref().expect("cached").1;
        let config = TransportConfig {
            coarse_to_fine: c2f,
            compact,
            ..TransportConfig::default()
        };
        let mut source = SliceFrames::new(f, camera.pixels());
        helmholtz_alloc::reset_peak();
        let base = helmholtz_alloc::live_bytes();
        let started = Instant::now();
        let result =
            reconstruct_transport(&spec, camera, count, &config, &mut source, &Control::new());
        let seconds = started.elapsed().as_secs_f64();
        let peak = helmholtz_alloc::installed()
            .then(|| helmholtz_alloc::peak_bytes().saturating_sub(base));
        let row = match result {
            Ok((t, report)) => {
                let d = &report.details;
                Row {
                    case: name.clone(),
                    projector: [pw, ph],
                    camera: [cw, chh],
                    frames: count,
                    coarse_to_fine: c2f,
                    compact,
                    seconds,
                    peak_heap_bytes: peak,
                    transform: chosen_transform(d),
                    lambda: d["lambda"].as_f64(),
                    refit: d["refit"].as_bool().unwrap_or(false),
                    stored_bytes: t.stored_bytes(),
                    dense_bytes: truth.len() * 4,
                    nonzeros_per_row: t.nonzeros() as f64 / camera.pixels() as f64,
                    relative_error: relative_error(&dense(&t), &truth),
                    relit_psnr_db: relit_psnr(&t, &view),
                    held_out: report.held_out.as_ref().and_then(|h| h.relative_residual),
                    iterations_per_row: report.iterations as f64 / camera.pixels() as f64,
                    error: None,
                }
            }
            Err(e) => Row {
                case: name.clone(),
                projector: [pw, ph],
                camera: [cw, chh],
                frames: count,
                coarse_to_fine: c2f,
                compact,
                seconds,
                peak_heap_bytes: peak,
                transform: String::new(),
                lambda: None,
                refit: false,
                stored_bytes: 0,
                dense_bytes: truth.len() * 4,
                nonzeros_per_row: 0.0,
                relative_error: f64::NAN,
                relit_psnr_db: f64::NAN,
                held_out: None,
                iterations_per_row: 0.0,
                error: Some(e.to_string()),
            },
        };
        eprintln!(
            "{:<18} c2f {:<5} compact {:<5} {:>8.2} s  {:>9} B  err {:.4}  relit {:.2} dB  held-out {:?}  it/row {:.0}  {}{}",
            row.case,
            row.coarse_to_fine,
            row.compact,
            row.seconds,
            row.stored_bytes,
            row.relative_error,
            row.relit_psnr_db,
            row.held_out,
            row.iterations_per_row,
            row.transform,
            row.error
                .as_deref()
                .map(|e| format!("  ({e})"))
                .unwrap_or_default()
        );
        rows.push(row);
    }

    let (stats, scene_rows) = if latency_only {
        (Vec::new(), Vec::new())
    } else {
        rendered_scenes(only)?
    };

    // Interactive latency: the scene's exact rows at 256x256 x 64x64, stored sparse.
    let big = Relief::demo(256, 256, 7);
    let big_view = big.view(&Camera::tilted(64, 64, 25.0));
    let m = big_view.pixels();
    let mut latencies = Vec::new();
    for kind in [
        TransformKind::Haar,
        TransformKind::Identity,
        TransformKind::Dct,
    ] {
        let t = TransportMatrix::from_rows(
            (256, 256),
            (64, 64),
            kind,
            (0..m).map(|j| big_view.row(j)),
            1e-3,
        );
        // Error of the stored rows on a sample of them (the dense T is 1 GiB).
        let (mut est, mut exact) = (Vec::new(), Vec::new());
        for j in (0..m).step_by(37) {
            est.extend(t.row(j));
            exact.extend(big_view.row(j).into_iter().map(|v| v as f32));
        }
        let light: Vec<f32> = test_vector(m, 5)
            .iter()
            .map(|v| (0.5 + 0.5 * v) as f32)
            .collect();
        let pattern: Vec<f32> = test_vector(256 * 256, 6)
            .iter()
            .map(|v| (0.5 + 0.5 * v) as f32)
            .collect();
        let time = |f: &mut dyn FnMut()| {
            let mut v: Vec<f64> = (0..calls)
                .map(|_| {
                    let s = Instant::now();
                    f();
                    s.elapsed().as_secs_f64() * 1e3
                })
                .collect();
            v.sort_by(|a, b| a.total_cmp(b));
            (percentile(&v, 0.5), percentile(&v, 0.99))
        };
        let mut sink = 0f32;
        let (rm, rp) = time(&mut || sink += t.relight(&light)[0]);
        let (pm, pp) = time(&mut || sink += t.primal(&pattern)[0]);
        std::hint::black_box(sink);
        let l = Latency {
            transform: kind.name().into(),
            nonzeros: t.nonzeros(),
            stored_bytes: t.stored_bytes(),
            relative_error: relative_error(&est, &exact),
            relight_median_ms: rm,
            relight_p99_ms: rp,
            primal_median_ms: pm,
            primal_p99_ms: pp,
            calls,
        };
        eprintln!(
            "latency {:<8} nnz {:>9}  {:>10} B  err {:.2e}  relight {:.2} / {:.2} ms  primal {:.2} / {:.2} ms (median / p99)",
            l.transform, l.nonzeros, l.stored_bytes, l.relative_error, rm, rp, pm, pp
        );
        latencies.push(l);
    }
    write(
        out,
        &rows,
        &stats,
        &scene_rows,
        &latencies,
        &contention.finish(),
    )
}

fn write(
    out: &Path,
    rows: &[Row],
    stats: &[SceneStats],
    scene_rows: &[SceneRow],
    latencies: &[Latency],
    machine: &serde_json::Value,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(out)?;
    let json = json!({"reconstructions": rows, "rendered_scenes": stats, "rendered_reconstructions": scene_rows, "latency": latencies, "threads": rayon::current_num_threads(), "machine": machine});
    std::fs::write(
        out.join("benchmarks-transport.json"),
        serde_json::to_string_pretty(&json)?,
    )?;
    let mut md = String::new();
    md.push_str("# Transport matrix benchmarks\n\n");
    md.push_str("`cargo run -p helmholtz-bench -- --preset transport --out docs` ");
    md.push_str(&format!("({} threads; {}). Scene: `helmholtz_sim::Relief::demo(64, 64, 7)`, camera `Camera::tilted(32, 32, 25)`; noise-free frames `c_i = T p_i`. ", rayon::current_num_threads(), super::machine::sentence(machine)));
    md.push_str("Error: relative Frobenius error of T; relit PSNR over three camera-side lights (uniform, checkerboard, random) against the scene's own relight.\n\n");
    md.push_str("| case | frames | coarse-to-fine | compact | seconds | peak heap MiB | transform | lambda | stored KiB (dense KiB) | nnz/row | rel. error T | relit PSNR dB | held-out | iterations/row |\n");
    md.push_str("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for r in rows {
        md.push_str(&format!(
            "| {} | {} | {} | {} | {:.2} | {} | {} | {} | {:.0} ({:.0}) | {:.1} | {:.4} | {:.2} | {} | {:.0} |{}\n",
            r.case,
            r.frames,
            if r.coarse_to_fine { "yes" } else { "no" },
            if r.compact { "yes" } else { "no" },
            r.seconds,
            r.peak_heap_bytes.map_or("-".into(), |b| format!("{:.1}", b as f64 / 1048576.0)),
            r.transform,
            r.lambda.map_or("-".into(), |l| format!("{l:e}{}", if r.refit { " + refit" } else { "" })),
            r.stored_bytes as f64 / 1024.0,
            r.dense_bytes as f64 / 1024.0,
            r.nonzeros_per_row,
            r.relative_error,
            r.relit_psnr_db,
            r.held_out.map_or("-".into(), |h| format!("{h:.4}")),
            r.iterations_per_row,
            r.error.as_deref().map(|e| format!(" error: {e}")).unwrap_or_default()
        ));
    }
    write_scenes(&mut md, stats, scene_rows);
    md.push_str("\n## relight / primal latency, 256x256 projector x 64x64 camera\n\n");
    md.push_str("The scene's exact rows (`Relief::demo(256, 256, 7)`, `Camera::tilted(64, 64, 25)`), each stored with the coefficients above 1e-3 of its largest; error on every 37th row.\n\n");
    md.push_str("| transform | nonzeros | stored MiB | rel. error | relight median ms | relight p99 ms | primal median ms | primal p99 ms | calls |\n|---|---|---|---|---|---|---|---|---|\n");
    for l in latencies {
        md.push_str(&format!(
            "| {} | {} | {:.1} | {:.2e} | {:.2} | {:.2} | {:.2} | {:.2} | {} |\n",
            l.transform,
            l.nonzeros,
            l.stored_bytes as f64 / 1048576.0,
            l.relative_error,
            l.relight_median_ms,
            l.relight_p99_ms,
            l.primal_median_ms,
            l.primal_p99_ms,
            l.calls
        ));
    }
    std::fs::write(out.join("benchmarks-transport.md"), md)?;
    Ok(())
}

/// Projector and camera of the rendered scenes.
const SCENE_PROJECTOR: (u32, u32) = (32, 32);
const SCENE_CAMERA: (u32, u32) = (48, 48);
/// Frame noise of the noisy cases: sigma as a fraction of each frame's RMS.
const FRAME_NOISE: f64 = 0.01;

/// A rendered scene's make-up.
#[derive(Clone, Debug, Serialize)]
struct SceneStats {
    scene: String,
    projector: [u32; 2],
    camera: [u32; 2],
    render_seconds: f64,
    /// `(sum T - sum T_direct) / sum T`.
    indirect_share: f64,
    /// Fraction of camera pixels whose row of T is not all zero.
    lit_rows: f64,
    nonzeros_per_lit_row: f64,
    /// Nonzero entries of T over `m k`.
    fill: f64,
}

/// One estimate of a rendered scene's T, scored against the truth.
#[derive(Clone, Debug, Serialize)]
struct SceneRow {
    scene: String,
    case: String,
    frames: u64,
    /// Frame noise sigma over the frame's RMS.
    noise: f64,
    /// `reconstruct_transport` (default config) or the plain least-squares baseline.
    method: String,
    seconds: f64,
    transform: String,
    lambda: Option<f64>,
    refit: bool,
    nonzeros_per_row: f64,
    /// `||T_hat - T||_F / ||T||_F`.
    relative_error: f64,
    /// `||T_hat^T c - T^T c|| / ||T^T c||` for the full, half and checkerboard camera lights.
    relit_full: f64,
    relit_half: f64,
    relit_checker: f64,
    /// `sum T_hat / sum T`.
    total_light: f64,
    /// `||T_hat p - T p|| / ||T p||`, `p` a random 0/1 projector pattern.
    primal_error: f64,
    held_out: Option<f64>,
    /// An error estimate the reconstruction reports in `details`, as `key = value`.
    error_estimate: Option<String>,
    /// The reported full-light relight error (`details.relight_error_estimate.relative`).
    relight_estimate: Option<f64>,
    /// Its bound (`details.relight_error_estimate.upper`).
    relight_upper: Option<f64>,
    error: Option<String>,
}

/// The session's frames `T p_i` (f32, `n x m`), with Gaussian noise of `noise` times each
/// frame's RMS (seeded per frame).
fn rendered_frames(scene: &RenderedTransport, spec: &PatternSpec, noise: f64) -> Vec<f32> {
    let g = PatternGenerator::new(spec);
    let mut p = vec![0f32; spec.pixels()];
    let mut out = Vec::with_capacity(spec.count() as usize * scene.pixels());
    for i in 0..spec.count() {
        g.fill_values(i, &mut p);
        let p64: Vec<f64> = p.iter().map(|&v| v as f64).collect();
        let mut frame = scene.render(&p64);
        if noise > 0.0 {
            let rms = (frame.iter().map(|v| v * v).sum::<f64>() / frame.len() as f64).sqrt();
            let mut rng = SplitMix64::stream(21, 0, i);
            for v in &mut frame {
                *v += noise * rms * rng.normal();
            }
        }
        out.extend(frame.into_iter().map(|v| v as f32));
    }
    out
}

/// Plain least squares from the frames, no prior, `m x k` row-major: for Hadamard split pairs
/// `T = (1/k) sum_i d_i h_i^T` over the measured pairs (`d_i` the frame difference, `h_i` the
/// +-1 pattern; the exact inverse of a complete set, the minimum-norm solution of a subset, whose
/// rows are orthogonal); otherwise the minimum-norm solution `T^T = A^T (A A^T)^-1 Y`.
fn least_squares(spec: &PatternSpec, frames: &[f32], m: usize) -> anyhow::Result<Vec<f64>> {
    let (k, n) = (spec.pixels(), spec.count() as usize);
    let g = PatternGenerator::new(spec);
    let pattern = |i: usize| -> Vec<f64> {
        let mut p = vec![0f32; k];
        g.fill_values(i as u64, &mut p);
        p.into_iter().map(|v| v as f64).collect()
    };
    let frame = |i: usize| &frames[i * m..(i + 1) * m];
    let mut t = vec![0.0; m * k];
    if matches!(spec.family(), Family::Hadamard { .. }) {
        for pair in 0..n / 2 {
            let h: Vec<f64> = pattern(2 * pair)
                .iter()
                .zip(pattern(2 * pair + 1))
                .map(|(a, b)| a - b)
                .collect();
            for (j, (a, b)) in frame(2 * pair).iter().zip(frame(2 * pair + 1)).enumerate() {
                let d = (*a as f64 - *b as f64) / k as f64;
                for (tv, hv) in t[j * k..(j + 1) * k].iter_mut().zip(&h) {
                    *tv += d * hv;
                }
            }
        }
        return Ok(t);
    }
    let a: Vec<Vec<f64>> = (0..n).map(pattern).collect();
    // Cholesky of the Gram matrix A A^T (n x n).
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let mut v: f64 = a[i].iter().zip(&a[j]).map(|(x, y)| x * y).sum();
            for q in 0..j {
                v -= l[i * n + q] * l[j * n + q];
            }
            if i == j {
                anyhow::ensure!(v > 0.0, "the patterns' Gram matrix is singular");
                l[i * n + i] = v.sqrt();
            } else {
                l[i * n + j] = v / l[j * n + j];
            }
        }
    }
    // Per camera pixel: z = (A A^T)^-1 y, row j of T = A^T z.
    let mut z = vec![0.0; n];
    for j in 0..m {
        for i in 0..n {
            let mut v = frames[i * m + j] as f64;
            for q in 0..i {
                v -= l[i * n + q] * z[q];
            }
            z[i] = v / l[i * n + i];
        }
        for i in (0..n).rev() {
            let mut v = z[i];
            for q in i + 1..n {
                v -= l[q * n + i] * z[q];
            }
            z[i] = v / l[i * n + i];
        }
        let row = &mut t[j * k..(j + 1) * k];
        for (ai, zi) in a.iter().zip(&z) {
            for (tv, av) in row.iter_mut().zip(ai) {
                *tv += zi * av;
            }
        }
    }
    Ok(t)
}

/// The camera-side lights of the relit errors: full, left half, a checkerboard of 4x4 blocks.
fn scene_lights(w: usize, h: usize) -> [Vec<f64>; 3] {
    let m = w * h;
    [
        vec![1.0; m],
        (0..m).map(|j| ((j % w) < w / 2) as u8 as f64).collect(),
        (0..m)
            .map(|j| (((j % w) / 4 + (j / w) / 4) % 2) as f64)
            .collect(),
    ]
}

fn relative(est: &[f64], truth: &[f64]) -> f64 {
    let (mut num, mut den) = (0.0, 0.0);
    for (e, t) in est.iter().zip(truth) {
        num += (e - t) * (e - t);
        den += t * t;
    }
    (num / den).sqrt()
}

/// `T^T c` of a dense `m x k` matrix.
fn dense_relight(t: &[f64], k: usize, c: &[f64]) -> Vec<f64> {
    let mut out = vec![0.0; k];
    for (row, &cv) in t.chunks_exact(k).zip(c) {
        for (o, v) in out.iter_mut().zip(row) {
            *o += cv * v;
        }
    }
    out
}

/// An error estimate the report may carry in `details` (a numeric entry, or an object's numeric
/// field, under a key naming an estimate), as `key = value`.
fn reported_estimate(report: &Report) -> Option<String> {
    // The relight's estimate first (the table's relit columns are its truth), then any other.
    let mut keys: Vec<&String> = report
        .details
        .keys()
        .filter(|key| {
            let name = key.to_lowercase();
            name.contains("estimate") || name.contains("error")
        })
        .collect();
    keys.sort_by_key(|key| *key != "relight_error_estimate");
    let parts: Vec<String> = keys
        .into_iter()
        .filter_map(|key| format_estimate(key, &report.details[key]))
        .collect();
    (!parts.is_empty()).then(|| parts.join("; "))
}

/// One estimate of the report's `details` as the table shows it.
fn format_estimate(key: &str, value: &serde_json::Value) -> Option<String> {
    if let Some(v) = value.as_f64() {
        return Some(format!("{key} = {v:.4}"));
    }
    let relative = value.get("relative").and_then(serde_json::Value::as_f64);
    // An estimate with a bound: its value when resolved, else only the bound.
    if let Some(upper) = value.get("upper").and_then(serde_json::Value::as_f64) {
        return Some(
            match (
                relative,
                value.get("resolved").and_then(serde_json::Value::as_bool),
            ) {
                (Some(v), Some(false)) => {
                    format!("{key}.relative = {v:.4} (noise alone; upper {upper:.4})")
                }
                (Some(v), _) => format!("{key}.relative = {v:.4} (upper {upper:.4})"),
                (None, _) => format!("{key}: unresolved, upper {upper:.4}"),
            },
        );
    }
    if let Some(v) = relative {
        return Some(format!("{key}.relative = {v:.4}"));
    }
    value
        .as_object()?
        .iter()
        .find_map(|(field, v)| v.as_f64().map(|v| format!("{key}.{field} = {v:.4}")))
}

/// Scores an estimate `t_hat` (`m x k`) of `scene`.
fn score(scene: &RenderedTransport, t_hat: &[f64], row: &mut SceneRow) {
    let (k, truth) = (scene.projector_pixels(), scene.matrix());
    row.relative_error = relative(t_hat, truth);
    let [full, half, checker] = scene_lights(scene.width(), scene.height());
    let relit = |c: &[f64]| relative(&dense_relight(t_hat, k, c), &scene.relight(c));
    (row.relit_full, row.relit_half, row.relit_checker) =
        (relit(&full), relit(&half), relit(&checker));
    row.total_light = t_hat.iter().sum::<f64>() / scene.total();
    let p: Vec<f64> = test_vector(k, 17)
        .iter()
        .map(|v| (*v > 0.0) as u8 as f64)
        .collect();
    let est: Vec<f64> = t_hat
        .chunks_exact(k)
        .map(|r| r.iter().zip(&p).map(|(a, b)| a * b).sum())
        .collect();
    row.primal_error = relative(&est, &scene.render(&p));
}

/// The rendered scenes' sessions: complete Hadamard sets (noise-free and with 1 % frame
/// noise), 50 % Hadamard (Russian-doll order), 25 % Bernoulli; each reconstructed with the
/// default [`TransportConfig`] and by plain least squares.
fn rendered_scenes(only: Option<&[String]>) -> anyhow::Result<(Vec<SceneStats>, Vec<SceneRow>)> {
    let (pw, ph) = SCENE_PROJECTOR;
    let (cw, chh) = SCENE_CAMERA;
    let (proj, cam) = ((pw as usize, ph as usize), (cw as usize, chh as usize));
    let camera = CameraGrid {
        width: cw,
        height: chh,
    };
    let k = (pw * ph) as u64;
    let rd = HadamardOrdering::RussianDoll;
    let cases: [(&str, Family, u64, f64); 6] = [
        (
            "hadamard complete",
            Family::Hadamard { ordering: rd },
            2 * k,
            0.0,
        ),
        (
            "hadamard complete",
            Family::Hadamard { ordering: rd },
            2 * k,
            FRAME_NOISE,
        ),
        ("hadamard 50 %", Family::Hadamard { ordering: rd }, k, 0.0),
        (
            "hadamard 50 %",
            Family::Hadamard { ordering: rd },
            k,
            FRAME_NOISE,
        ),
        (
            "bernoulli 25 %",
            Family::Bernoulli { fill: 0.5 },
            k / 4,
            0.0,
        ),
        (
            "bernoulli 25 %",
            Family::Bernoulli { fill: 0.5 },
            k / 4,
            FRAME_NOISE,
        ),
    ];
    type Build = fn((usize, usize), (usize, usize), u64) -> RenderedTransport;
    let builds: [(&str, Build); 3] = [
        ("cornell", RenderedTransport::cornell),
        ("glossy", RenderedTransport::glossy),
        ("slide", RenderedTransport::slide),
    ];
    let wanted = |label: &str| only.is_none_or(|o| o.iter().any(|w| label.contains(w.as_str())));
    let (mut stats, mut rows) = (Vec::new(), Vec::new());
    for (scene_name, build) in builds {
        if !cases
            .iter()
            .any(|c| wanted(&format!("{scene_name} {}", c.0)))
        {
            continue;
        }
        let started = Instant::now();
        let scene = build(proj, cam, 1);
        let render_seconds = started.elapsed().as_secs_f64();
        let lit = scene.lit_rows();
        let s = SceneStats {
            scene: scene_name.into(),
            projector: [pw, ph],
            camera: [cw, chh],
            render_seconds,
            indirect_share: scene.indirect_share(),
            lit_rows: lit as f64 / scene.pixels() as f64,
            nonzeros_per_lit_row: scene.nonzeros() as f64 / lit.max(1) as f64,
            fill: scene.nonzeros() as f64 / (scene.pixels() * scene.projector_pixels()) as f64,
        };
        eprintln!(
            "scene {:<8} rendered in {:.1} s: indirect {:.3}, lit rows {:.3}, nnz/lit row {:.1}, fill {:.4}",
            s.scene, s.render_seconds, s.indirect_share, s.lit_rows, s.nonzeros_per_lit_row, s.fill
        );
        stats.push(s);
        for (case, family, count, noise) in cases.iter().cloned() {
            if !wanted(&format!("{scene_name} {case}")) {
                continue;
            }
            let spec = PatternSpec::new(family, pw, ph, count, 3)?;
            let frames = rendered_frames(&scene, &spec, noise);
            let blank = |method: &str| SceneRow {
                scene: scene_name.into(),
                case: case.into(),
                frames: count,
                noise,
                method: method.into(),
                seconds: 0.0,
                transform: String::new(),
                lambda: None,
                refit: false,
                nonzeros_per_row: 0.0,
                relative_error: f64::NAN,
                relit_full: f64::NAN,
                relit_half: f64::NAN,
                relit_checker: f64::NAN,
                total_light: f64::NAN,
                primal_error: f64::NAN,
                held_out: None,
                error_estimate: None,
                relight_estimate: None,
                relight_upper: None,
                error: None,
            };
            // The reconstruction, default configuration; a compressive session also without
            // compaction (`compact: false`), side by side.
            let complete = case.contains("complete");
            let configs = [
                ("reconstruct_transport", TransportConfig::default()),
                (
                    "compact: false",
                    TransportConfig {
                        compact: false,
                        ..TransportConfig::default()
                    },
                ),
            ];
            for (method, config) in configs.iter().take(if complete { 1 } else { 2 }) {
                let mut row = blank(method);
                let mut source = SliceFrames::new(&frames, camera.pixels());
                let started = Instant::now();
                let result = reconstruct_transport(
                    &spec,
                    camera,
                    count,
                    config,
                    &mut source,
                    &Control::new(),
                );
                row.seconds = started.elapsed().as_secs_f64();
                match result {
                    Ok((t, report)) => {
                        let d = &report.details;
                        row.transform = chosen_transform(d);
                        row.lambda = d["lambda"].as_f64();
                        row.refit = d["refit"].as_bool().unwrap_or(false);
                        row.nonzeros_per_row = t.nonzeros() as f64 / camera.pixels() as f64;
                        row.held_out = report.held_out.as_ref().and_then(|h| h.relative_residual);
                        row.error_estimate = reported_estimate(&report);
                        let relight = d.get("relight_error_estimate");
                        row.relight_estimate = relight.and_then(|e| e["relative"].as_f64());
                        row.relight_upper = relight.and_then(|e| e["upper"].as_f64());
                        let t_hat: Vec<f64> = dense(&t).into_iter().map(|v| v as f64).collect();
                        score(&scene, &t_hat, &mut row);
                    }
                    Err(e) => row.error = Some(e.to_string()),
                }
                log_scene_row(&row);
                rows.push(row);
            }
            // The oracle-free baseline: plain least squares.
            let mut row = blank("least squares");
            let started = Instant::now();
            match least_squares(&spec, &frames, camera.pixels()) {
                Ok(t_hat) => {
                    row.seconds = started.elapsed().as_secs_f64();
                    row.nonzeros_per_row =
                        t_hat.iter().filter(|&&v| v != 0.0).count() as f64 / camera.pixels() as f64;
                    score(&scene, &t_hat, &mut row);
                }
                Err(e) => row.error = Some(e.to_string()),
            }
            log_scene_row(&row);
            rows.push(row);
        }
    }
    Ok((stats, rows))
}

fn log_scene_row(r: &SceneRow) {
    eprintln!(
        "{:<8} {:<18} noise {:<4} {:<22} {:>7.2} s  err {:.4}  relit {:.4}/{:.4}/{:.4}  total {:.4}  primal {:.4}  held-out {:?}  {}{}",
        r.scene,
        r.case,
        r.noise,
        r.method,
        r.seconds,
        r.relative_error,
        r.relit_full,
        r.relit_half,
        r.relit_checker,
        r.total_light,
        r.primal_error,
        r.held_out,
        r.transform,
        r.error
            .as_deref()
            .map(|e| format!("  ({e})"))
            .unwrap_or_default()
    );
}

fn write_scenes(md: &mut String, stats: &[SceneStats], rows: &[SceneRow]) {
    if stats.is_empty() {
        return;
    }
    let (pw, ph) = SCENE_PROJECTOR;
    let (cw, chh) = SCENE_CAMERA;
    md.push_str(&format!(
        "\n## Rendered scenes, {pw}x{ph} projector x {cw}x{chh} camera\n\n"
    ));
    md.push_str("Scenes given as an exact dense `T` (`helmholtz_sim::RenderedTransport`, seed 1): `cornell`, a Cornell-like box whose indirect light solves the radiosity equation (dense low-amplitude transport); `glossy`, a diffuse floor with a rough metal and a rough glass sphere (a sparse bright specular part: glints and a caustic); `slide`, a printed slide at a grazing angle (very sparse rows, most exactly zero). Indirect share: `(sum T - sum T_direct) / sum T`, the light that reached the camera after more than one bounce.\n\n");
    md.push_str("| scene | indirect share | lit camera pixels | nonzeros per lit row | fill of T | render s |\n|---|---|---|---|---|---|\n");
    for s in stats {
        md.push_str(&format!(
            "| {} | {:.3} | {:.1} % | {:.1} | {:.4} | {:.1} |\n",
            s.scene,
            s.indirect_share,
            100.0 * s.lit_rows,
            s.nonzeros_per_lit_row,
            s.fill,
            s.render_seconds
        ));
    }
    md.push_str(&format!("\nSessions, each noise-free and with Gaussian frame noise of sigma = {:.0} % of each frame's RMS: a complete Hadamard set (split pairs); the first 50 % of the Hadamard pairs in Russian-doll order; 25 % Bernoulli (fill 0.5) frames. Each is reconstructed by `reconstruct_transport` with the default `TransportConfig` (method `reconstruct_transport`; the compressive sessions also with params `compact: false`, which keeps every coefficient the fit kept: method `compact: false`), and solved by plain least squares for comparison: for Hadamard `T = (1/k) sum d_i h_i^T` over the measured pairs (the exact inverse of a complete set, the minimum-norm zero-filled solution of a subset), for Bernoulli the minimum-norm solution `A^T (A A^T)^-1 Y`.\n\n", 100.0 * FRAME_NOISE));
    md.push_str("Columns, all against the true T: **rel. error T**, `||T_hat - T||_F / ||T||_F`; **relit** errors `||T_hat^T c - T^T c|| / ||T^T c||` for a full camera-side light (all ones), the left half of the camera, and a checkerboard of 4x4 camera blocks; **total light**, `sum T_hat / sum T` (1 when no light is lost); **primal**, `||T_hat p - T p|| / ||T p||` for a random 0/1 projector pattern; **held-out**, the report's held-out relative residual (its own error estimate; none for complete sets); **estimate**, the error estimates the report's `details` carry: `relight_error_estimate` first (a full-light relight's: its truth is **relit full**), then any other (`error_estimate`, of T).\n\n");
    md.push_str("| scene | case | frames | noise | method | seconds | transform | lambda | nnz/row | rel. error T | relit full | relit half | relit checker | total light | primal | held-out | estimate |\n");
    md.push_str("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for r in rows {
        md.push_str(&format!(
            "| {} | {} | {} | {} | {} | {:.2} | {} | {} | {:.1} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {} | {} |{}\n",
            r.scene,
            r.case,
            r.frames,
            if r.noise > 0.0 { format!("{:.0} %", 100.0 * r.noise) } else { "none".into() },
            r.method,
            r.seconds,
            if r.transform.is_empty() { "-" } else { &r.transform },
            r.lambda.map_or("-".into(), |l| format!("{l:e}{}", if r.refit { " + refit" } else { "" })),
            r.nonzeros_per_row,
            r.relative_error,
            r.relit_full,
            r.relit_half,
            r.relit_checker,
            r.total_light,
            r.primal_error,
            r.held_out.map_or("-".into(), |h| if h < 1e-3 { format!("{h:.1e}") } else { format!("{h:.4}") }),
            r.error_estimate.as_deref().unwrap_or("-"),
            r.error.as_deref().map(|e| format!(" error: {e}")).unwrap_or_default()
        ));
    }
    calibration(md, rows);
}

/// The reported full-light relight error against the true one, per compressive session.
fn calibration(md: &mut String, rows: &[SceneRow]) {
    md.push_str("\n### Calibration: the reported relight error against the truth\n\nEvery `reconstruct_transport` and `compact: false` row of a compressive session (complete sets are left out: their T is exact up to its noise): `details.relight_error_estimate.relative` against the true **relit full** error.\n\n| scene | case | noise | method | estimate | true relit full | estimate / truth |\n|---|---|---|---|---|---|---|\n");
    let (mut within, mut low, mut high, mut missing) = (0, 0, 0, 0);
    for r in rows
        .iter()
        .filter(|r| r.method != "least squares" && !r.case.contains("complete"))
    {
        let ratio = r.relight_estimate.map(|e| e / r.relit_full);
        match ratio {
            Some(q) if (0.5..=2.0).contains(&q) => within += 1,
            Some(q) if q < 0.5 => low += 1,
            Some(_) => high += 1,
            None => missing += 1,
        }
        let estimate = match (r.relight_estimate, r.relight_upper) {
            (Some(e), _) => format!("{e:.4}"),
            (None, Some(u)) => format!("unresolved, at most {u:.4}"),
            (None, None) => "-".into(),
        };
        md.push_str(&format!(
            "| {} | {} | {} | {} | {} | {:.4} | {} |\n",
            r.scene,
            r.case,
            if r.noise > 0.0 {
                format!("{:.0} %", 100.0 * r.noise)
            } else {
                "none".into()
            },
            r.method,
            estimate,
            r.relit_full,
            ratio.map_or("-".into(), |q| format!("{q:.2}")),
        ));
    }
    md.push_str(&format!(
        "\nWithin 2x of the truth: {within}; below half: {low}; above twice: {high}; no estimate or only a bound: {missing}.\n"
    ));
}

/// The fitted transform as reported, with " (coarse as measured)" where the model took the
/// coarse Haar coefficients of a Hadamard subset from the pairs (`details.coarse_exact`).
fn chosen_transform(d: &serde_json::Map<String, serde_json::Value>) -> String {
    let name = d["transform"].as_str().unwrap_or("");
    if d.get("coarse_exact").and_then(|v| v.as_bool()) == Some(true) {
        format!("{name} (coarse as measured)")
    } else {
        name.to_string()
    }
}
