//! `--preset transport`: camera sessions of a `helmholtz_sim` Lambertian scene (ground plane,
//! hemisphere, raised box; occlusion and one diffuse bounce), reconstructed into `T` by
//! [`helmholtz_recon::transport`]: time, stored size, relative error of `T`, PSNR of relit dual
//! images, held-out error, iterations, with and without coarse-to-fine; then the interactive
//! latency of `relight` / `primal` at 256x256 projector x 64x64 camera.
//!
//! Writes `DIR/benchmarks-transport.md` and `DIR/benchmarks-transport.json`.

use std::path::Path;
use std::time::Instant;

use helmholtz_proto::{Family, HadamardOrdering, PatternGenerator, PatternSpec};
use helmholtz_sim::{Camera, CameraView, Relief};
use serde::Serialize;
use serde_json::json;

use helmholtz_recon::metrics::{psnr, relative_error};
use helmholtz_recon::transforms::TransformKind;
use helmholtz_recon::transport::{
    CameraGrid, SliceFrames, TransportConfig, TransportMatrix, reconstruct_transport,
};
use helmholtz_recon::{Control, linop::test_vector};

#[derive(Clone, Debug, Serialize)]
struct Row {
    case: String,
    projector: [u32; 2],
    camera: [u32; 2],
    frames: u64,
    coarse_to_fine: bool,
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
    let mut cases: Vec<(String, Family, u64, bool)> = vec![
        (
            "hadamard complete".into(),
            Family::Hadamard { ordering: rd },
            2 * k,
            false,
        ),
        (
            "hadamard 50 %".into(),
            Family::Hadamard { ordering: rd },
            k,
            false,
        ),
        (
            "hadamard 50 %".into(),
            Family::Hadamard { ordering: rd },
            k,
            true,
        ),
        (
            "hadamard 25 %".into(),
            Family::Hadamard { ordering: rd },
            k / 2,
            false,
        ),
        (
            "hadamard 25 %".into(),
            Family::Hadamard { ordering: rd },
            k / 2,
            true,
        ),
        (
            "bernoulli 25 %".into(),
            Family::Bernoulli { fill: 0.5 },
            k / 4,
            false,
        ),
        (
            "bernoulli 25 %".into(),
            Family::Bernoulli { fill: 0.5 },
            k / 4,
            true,
        ),
        (
            "bernoulli 10 %".into(),
            Family::Bernoulli { fill: 0.5 },
            k / 10,
            false,
        ),
    ];
    if latency_only {
        cases.clear();
    }
    if let Some(only) = only {
        cases.retain(|c| only.iter().any(|o| c.0.contains(o.as_str())));
    }
    let mut rows = Vec::new();
    let mut cache: Option<(String, Vec<f32>)> = None;
    for (name, family, count, c2f) in cases {
        let spec = PatternSpec::new(family, pw, ph, count, 3)?;
        let key = format!("{name}/{count}");
        if cache.as_ref().map(|c| &c.0) != Some(&key) {
            cache = Some((key.clone(), frames_of(&view, &spec)));
        }
        let f = &cache.as_ref().expect("cached").1;
        let config = TransportConfig {
            coarse_to_fine: c2f,
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
                    seconds,
                    peak_heap_bytes: peak,
                    transform: d["transform"].as_str().unwrap_or("").to_string(),
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
            "{:<18} c2f {:<5} {:>8.2} s  {:>9} B  err {:.4}  relit {:.2} dB  held-out {:?}  it/row {:.0}  {}{}",
            row.case,
            row.coarse_to_fine,
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
    write(out, &rows, &latencies, &contention.finish())
}

fn write(
    out: &Path,
    rows: &[Row],
    latencies: &[Latency],
    machine: &serde_json::Value,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(out)?;
    let json = json!({"reconstructions": rows, "latency": latencies, "threads": rayon::current_num_threads(), "machine": machine});
    std::fs::write(
        out.join("benchmarks-transport.json"),
        serde_json::to_string_pretty(&json)?,
    )?;
    let mut md = String::new();
    md.push_str("# Transport matrix benchmarks\n\n");
    md.push_str("`cargo run -p helmholtz-bench -- --preset transport --out docs` ");
    md.push_str(&format!("({} threads; {}). Scene: `helmholtz_sim::Relief::demo(64, 64, 7)`, camera `Camera::tilted(32, 32, 25)`; noise-free frames `c_i = T p_i`. ", rayon::current_num_threads(), super::machine::sentence(machine)));
    md.push_str("Error: relative Frobenius error of T; relit PSNR over three camera-side lights (uniform, checkerboard, random) against the scene's own relight.\n\n");
    md.push_str("| case | frames | coarse-to-fine | seconds | peak heap MiB | transform | lambda | stored KiB (dense KiB) | nnz/row | rel. error T | relit PSNR dB | held-out | iterations/row |\n");
    md.push_str("|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for r in rows {
        md.push_str(&format!(
            "| {} | {} | {} | {:.2} | {} | {} | {} | {:.0} ({:.0}) | {:.1} | {:.4} | {:.2} | {} | {:.0} |{}\n",
            r.case,
            r.frames,
            if r.coarse_to_fine { "yes" } else { "no" },
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
