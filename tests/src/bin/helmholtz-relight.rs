//! Relight benchmark (on demand, not a test): interactive relighting through HTTP on a real camera
//! session. Starts the real server, creates a camera session of a `helmholtz_sim` Lambertian
//! scene (default: 256x256 projector, 64x64 camera, the first 8,192 frames of a Russian-doll
//! Hadamard set, i.e. every pattern of the 64x64 level), uploads the frames through the client
//! library, reconstructs `T` (method `transport`), then sends relight and primal queries whose
//! light or pattern changes with every call (so none is served from the response cache) and
//! reports the server's own compute time (`server-timing: compute;dur=...`) and the round trip,
//! median and 99th percentile, as Markdown on stdout and optionally into a file.
//!
//!     cargo build --release -p helmholtz-server --bins
//!     cargo run --release -p helmholtz-tests --bin helmholtz-relight -- --out docs/relight.md

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Parser;
use helmholtz_client::{NewSession, PatternSpec, UploadOptions};
use helmholtz_tests::ServerProcess;

#[derive(Parser, Debug, Clone)]
#[command(
    name = "helmholtz-relight",
    about = "Relight benchmark: a real camera session through the real server; server compute time and round trip of relight and primal queries."
)]
struct Args {
    /// Projector side (square, a power of two for Hadamard).
    #[arg(long, default_value_t = 256)]
    projector: u32,
    /// Camera side (square).
    #[arg(long, default_value_t = 64)]
    camera: u32,
    /// Frames uploaded (the first of a Russian-doll Hadamard set: 2 x 4^j frames measure every
    /// pattern of the 2^j x 2^j level).
    #[arg(long, default_value_t = 8192)]
    frames: u64,
    /// Parameters of the `transport` reconstruction, as JSON.
    #[arg(long, default_value = "{}")]
    params: String,
    /// Queries of each kind.
    #[arg(long, default_value_t = 300)]
    calls: usize,
    /// The helmholtz-server binary [default: beside this binary].
    #[arg(long)]
    server_bin: Option<PathBuf>,
    /// Also write the Markdown report to this file.
    #[arg(long)]
    out: Option<PathBuf>,
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .unwrap_or_default()
        .split_whitespace()
        .take(3)
        .collect::<Vec<_>>()
        .join(" ")
}

/// One kind of query: the server's compute times and the round trips, in milliseconds.
#[derive(Default)]
struct Timings {
    server_ms: Vec<f64>,
    round_trip_ms: Vec<f64>,
    bytes: usize,
    cache_hits: usize,
}

fn percentile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(|a, b| a.total_cmp(b));
    if s.is_empty() {
        return f64::NAN;
    }
    s[((s.len() - 1) as f64 * q).round() as usize]
}

/// `compute;dur=1.234` -> 1.234; `None` for a cache hit.
fn compute_ms(header: &str) -> Option<f64> {
    header
        .split(';')
        .find_map(|part| part.trim().strip_prefix("dur="))
        .and_then(|v| v.parse().ok())
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    anyhow::ensure!(args.calls >= 1, "--calls must be at least 1");
    let params: serde_json::Value =
        serde_json::from_str(&args.params).context("--params is not JSON")?;
    let (pw, cw) = (args.projector, args.camera);
    let load_start = load_average();
    let bin = helmholtz_tests::server_binary_beside(args.server_bin.as_deref())?;
    let dir = tempfile::tempdir()?;
    let max_frame = (cw * cw).max(65_536).to_string();
    // Queries go one at a time, faster than the per-token rate limit (100/s by default) on a
    // quiet machine: the benchmark measures latency, not the limiter, so it lifts the limit.
    let mut server = ServerProcess::start_binary(
        &bin,
        &dir.path().join("data"),
        0,
        &[
            "--max-frame-pixels",
            &max_frame,
            "--rate-per-second",
            "1000000",
        ],
    )?;
    let base = server.base_url.clone();
    eprintln!("server {} at {}", bin.display(), server.address);

    // The session: frames of the scene's transport under the first `frames` patterns.
    let spec: PatternSpec = serde_json::from_str(&format!(
        r#"{{"family":"hadamard","ordering":"russian_doll","width":{pw},"height":{pw},"count":{},"seed":1}}"#,
        args.frames
    ))?;
    let scene = helmholtz_sim::Relief::demo(pw, pw, 7);
    let view = scene.view(&helmholtz_sim::Camera::tilted(cw, cw, 25.0));
    eprintln!(
        "rendering {} frames of {pw}x{pw} patterns on a {cw}x{cw} camera...",
        args.frames
    );
    let started = Instant::now();
    let generator = helmholtz_proto::PatternGenerator::new(&spec);
    let mut p = vec![0f32; spec.pixels()];
    let mut frames = Vec::with_capacity(args.frames as usize * view.pixels());
    for i in 0..spec.count() {
        generator.fill_values(i, &mut p);
        let p64: Vec<f64> = p.iter().map(|&v| v as f64).collect();
        frames.extend(view.render(&p64).into_iter().map(|v| v as f32));
    }
    let render_seconds = started.elapsed().as_secs_f64();
    let id = "relight-bench";
    helmholtz_client::create_session(
        &base,
        &NewSession::camera(
            id,
            spec.clone(),
            cw,
            cw,
            helmholtz_proto::wire::SampleFormat::F32,
        ),
    )
    .await?;
    let started = Instant::now();
    helmholtz_client::upload_samples(
        &base,
        id,
        cw * cw,
        helmholtz_proto::wire::Samples::F32(&frames),
        &UploadOptions::default(),
    )
    .await?;
    helmholtz_client::finish_session(&base, id).await?;
    let upload_seconds = started.elapsed().as_secs_f64();
    let upload_mib = frames.len() as f64 * 4.0 / (1 << 20) as f64;
    drop(frames);
    eprintln!("uploaded {upload_mib:.0} MiB in {upload_seconds:.1} s; reconstructing T...");
    let rec = helmholtz_client::request_reconstruction(&base, id, "transport", &params).await?;
    let rec =
        helmholtz_client::wait_reconstruction(&base, rec.id, Duration::from_secs(4 * 3600)).await?;
    anyhow::ensure!(
        rec.is_done(),
        "the transport reconstruction failed: {rec:?}"
    );
    let report = rec.report.clone().unwrap_or_default();
    let details = &report.recon.details;
    let seconds = rec.seconds.unwrap_or(0.0);
    let null = serde_json::Value::Null;
    let detail = |key: &str| details.get(key).unwrap_or(&null);
    eprintln!("T in {seconds:.1} s: {}", detail("transform"));

    // Queries: each light / pattern differs from every other (no response-cache hits).
    let http = helmholtz_tests::http_client();
    let mut kinds: Vec<(&str, Timings)> = vec![
        ("relight, disc light, PNG", Timings::default()),
        ("relight, disc light, NPY", Timings::default()),
        ("primal, stored pattern, NPY", Timings::default()),
    ];
    eprintln!("{} queries of each kind...", args.calls);
    for i in 0..args.calls {
        for (kind, timings) in kinds.iter_mut().enumerate() {
            let (path, body) = match kind {
                0 | 1 => {
                    let (x, y) = (i as u32 % cw, (i as u32 / cw + 7 * kind as u32) % cw);
                    let format = if kind == 0 { "png" } else { "npy" };
                    (
                        format!("/v1/reconstructions/{}/relight?format={format}", rec.id),
                        format!(
                            r#"{{"light": {{"preset": "disc", "x": {x}, "y": {y}, "radius": {}}}}}"#,
                            2 + i % 5
                        ),
                    )
                }
                _ => (
                    format!("/v1/reconstructions/{}/primal?format=npy", rec.id),
                    format!(r#"{{"pattern_index": {}}}"#, i as u64 % args.frames),
                ),
            };
            let t0 = Instant::now();
            let response = http
                .post(server.url(&path))
                .header("content-type", "application/json")
                .body(body)
                .send()
                .await
                .with_context(|| format!("POST {path}"))?;
            let status = response.status();
            let timing = response
                .headers()
                .get("server-timing")
                .and_then(|v| v.to_str().ok())
                .unwrap_or("")
                .to_string();
            let bytes = response.bytes().await?;
            let rtt = t0.elapsed().as_secs_f64() * 1e3;
            anyhow::ensure!(
                status.is_success(),
                "POST {path}: HTTP {status}: {}",
                String::from_utf8_lossy(&bytes)
            );
            timings.1.round_trip_ms.push(rtt);
            timings.1.bytes = bytes.len();
            match compute_ms(&timing) {
                Some(ms) => timings.1.server_ms.push(ms),
                None => timings.1.cache_hits += 1,
            }
        }
    }
    let load_end = load_average();
    let _ = server.terminate();

    let mut md = String::new();
    md.push_str("# Relighting through HTTP\n\n");
    md.push_str(&format!(
        "`cargo run{} -p helmholtz-tests --bin helmholtz-relight --{}{}` ({}; load average {load_start} at the start, {load_end} at the end).\n\n",
        if cfg!(debug_assertions) { "" } else { " --release" },
        if args.params == "{}" { String::new() } else { format!(" --params '{}'", args.params) },
        if args.frames == 8192 && pw == 256 && cw == 64 { String::new() } else { format!(" --projector {pw} --camera {cw} --frames {}", args.frames) },
        if cfg!(debug_assertions) { "dev profile: optimised, with debug assertions" } else { "release build" },
    ));
    md.push_str(&format!(
        "Session: `helmholtz_sim::Relief::demo({pw}, {pw}, 7)` seen by `Camera::tilted({cw}, {cw}, 25)`, the first {} frames of a Russian-doll Hadamard set (f32, {upload_mib:.0} MiB, rendered in {render_seconds:.1} s, uploaded through the client library in {upload_seconds:.1} s), reconstructed by the server with `transport` (params `{}`); the server runs with `--rate-per-second 1000000` (queries go one at a time, faster than the default per-token limit).\n\n",
        args.frames, args.params
    ));
    md.push_str("| T: seconds | transform | lambda | stored MiB | dense f32 MiB | nonzeros/row | held-out |\n|---|---|---|---|---|---|---|\n");
    md.push_str(&format!(
        "| {:.1} | {} | {} | {:.1} | {:.0} | {:.1} | {:.4} |\n\n",
        seconds,
        detail("transform").as_str().unwrap_or("-"),
        detail("lambda"),
        report.detail_f64("stored_bytes").unwrap_or(0.0) / (1 << 20) as f64,
        report.detail_f64("dense_f32_bytes").unwrap_or(0.0) / (1 << 20) as f64,
        report.detail_f64("nonzeros_per_row").unwrap_or(0.0),
        report.held_out_error().unwrap_or(f64::NAN),
    ));
    md.push_str(&format!(
        "Queries: {} of each kind, one at a time; every disc light (a moving centre, radius 2-6 camera pixels) and every stored pattern index differs from the previous ones, so no answer comes from the response cache. \"Server\" is the compute time the server reports in `server-timing` (light parsed, `T^T c'` or `T p` on the decoded T, which is in the server's cache after the first query); \"round trip\" adds the database lookup of the reconstruction, the image encoding and HTTP on loopback.\n\n",
        args.calls
    ));
    md.push_str("| query | answer bytes | server median ms | server p99 ms | round trip median ms | round trip p99 ms | cache hits |\n|---|---|---|---|---|---|---|\n");
    for (name, t) in &kinds {
        md.push_str(&format!(
            "| {name} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {} |\n",
            t.bytes,
            percentile(&t.server_ms, 0.5),
            percentile(&t.server_ms, 0.99),
            percentile(&t.round_trip_ms, 0.5),
            percentile(&t.round_trip_ms, 0.99),
            t.cache_hits
        ));
    }
    print!("{md}");
    if let Some(out) = &args.out {
        std::fs::write(out, &md).with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(())
}
