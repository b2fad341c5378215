//! Load benchmark (on demand, not a test): the real server binary, N simulated rigs spooling and
//! uploading sessions at once through the real client library, and a steady open-loop stream of
//! dual-image queries, for a fixed time. Reports throughput, latency percentiles per kind, errors
//! and the server's peak memory (VmHWM), as Markdown on stdout and optionally into a file.
//!
//!     cargo build -p helmholtz-server --bins
//!     cargo run -p helmholtz-tests --bin helmholtz-load -- --rigs 50 --seconds 60 --out docs/load.md
//!
//! (Add `--release` to both for a release build; the server binary is looked up beside this one.)

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Parser;
use helmholtz_client::spool::{self, SpoolDir};
use helmholtz_client::{NewSession, PatternSpec, UploadOptions};
use helmholtz_sim::Target;
use helmholtz_sim::simulate::{self, NoiseModel};
use helmholtz_tests::{Backend, ServerProcess};

#[derive(Parser, Debug, Clone)]
#[command(
    name = "helmholtz-load",
    about = "Load benchmark: the real server, simulated rigs uploading at once through the spool, and a steady stream of dual-image queries."
)]
struct Args {
    /// Simulated rigs uploading at once.
    #[arg(long, default_value_t = 50)]
    rigs: usize,
    /// Duration of the measured phase.
    #[arg(long, default_value_t = 60.0)]
    seconds: f64,
    /// Rows (patterns) per uploaded session; each rig uploads session after session.
    #[arg(long, default_value_t = 4096)]
    rows: u64,
    /// Pattern side (bernoulli, side x side pixels).
    #[arg(long, default_value_t = 32)]
    side: u32,
    /// Dual-image queries per second (open loop: sent on schedule whatever the latency).
    #[arg(long, default_value_t = 20.0)]
    query_rate: f64,
    /// Rows per spool write (fsync'ed) of each rig.
    #[arg(long, default_value_t = 1024)]
    batch_rows: usize,
    /// Rows per upload chunk [default: the client's, about 256 KiB].
    #[arg(long)]
    chunk_rows: Option<usize>,
    /// Server reconstruction workers [default: the server's, one per core].
    #[arg(long)]
    workers: Option<usize>,
    /// The helmholtz-server binary [default: beside this binary].
    #[arg(long)]
    server_bin: Option<PathBuf>,
    /// Bearer token for a server with access control: sent on REST queries, and exported as
    /// HELMHOLTZ_TOKEN for the client library's gRPC calls.
    #[arg(long, env = "HELMHOLTZ_TOKEN")]
    token: Option<String>,
    /// Databases to run on, one after the other, comma-separated (sqlite, postgres) [default:
    /// HELMHOLTZ_TEST_BACKEND's, else sqlite]. With several, the report starts with their
    /// figures side by side. PostgreSQL: a database created for the run on
    /// HELMHOLTZ_TEST_POSTGRES (default the local server) and dropped at the end.
    #[arg(long, value_delimiter = ',')]
    backends: Vec<String>,
    /// Also write the Markdown report to this file.
    #[arg(long)]
    out: Option<PathBuf>,
}

/// Latencies of one kind of operation, and its errors.
#[derive(Default)]
struct Samples {
    ok: Vec<f64>,
    errors: u64,
    first_error: Option<String>,
}

impl Samples {
    fn record(&mut self, result: Result<Duration, String>) {
        match result {
            Ok(d) => self.ok.push(d.as_secs_f64()),
            Err(e) => {
                self.errors += 1;
                self.first_error.get_or_insert(e);
            }
        }
    }

    fn percentile(&self, p: f64) -> f64 {
        if self.ok.is_empty() {
            return f64::NAN;
        }
        let mut v = self.ok.clone();
        v.sort_by(f64::total_cmp);
        // Nearest rank.
        let rank = ((p / 100.0) * v.len() as f64).ceil().max(1.0) as usize;
        v[rank.min(v.len()) - 1]
    }
}

#[derive(Default)]
struct Totals {
    sessions: u64,
    rows: u64,
    bytes: u64,
    resumed_sessions: u64,
}

fn proc_status_kib(pid: u32, key: &str) -> Option<u64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = text.lines().find(|l| l.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

fn machine() -> String {
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(0);
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let load: Vec<&str> = load.split_whitespace().take(3).collect();
    format!(
        "{cores} cores ({model}), load average {} at the start",
        load.join(" ")
    )
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    anyhow::ensure!(args.rigs >= 1, "--rigs must be at least 1");
    anyhow::ensure!(args.seconds > 0.0, "--seconds must be > 0");
    anyhow::ensure!(args.query_rate > 0.0, "--query-rate must be > 0");
    if let Some(token) = &args.token {
        // SAFETY: set before any other thread of ours reads the environment.
        unsafe { std::env::set_var("HELMHOLTZ_TOKEN", token) };
    }
    let backends = if args.backends.is_empty() {
        vec![helmholtz_tests::backend()]
    } else {
        args.backends
            .iter()
            .map(|b| match b.as_str() {
                "sqlite" => Ok(Backend::Sqlite),
                "postgres" => Ok(Backend::Postgres),
                other => Err(anyhow::anyhow!(
                    "--backends: {other:?} is not sqlite or postgres"
                )),
            })
            .collect::<anyhow::Result<Vec<_>>>()?
    };
    let mut reports = Vec::new();
    for &backend in &backends {
        eprintln!("== {} ==", name(backend));
        reports.push((backend, measure(&args, backend).await?));
    }
    let mut md = String::new();
    if reports.len() > 1 {
        md.push_str("| figure |");
        for (b, _) in &reports {
            md.push_str(&format!(" {} |", name(*b)));
        }
        md.push_str("\n|---|");
        for _ in &reports {
            md.push_str("---|");
        }
        md.push('\n');
        for (i, (label, _)) in reports[0].1.summary.iter().enumerate() {
            md.push_str(&format!("| {label} |"));
            for (_, r) in &reports {
                md.push_str(&format!(" {} |", r.summary[i].1));
            }
            md.push('\n');
        }
        md.push('\n');
    }
    for (b, r) in &reports {
        if reports.len() > 1 {
            md.push_str(&format!("### {}\n\n", name(*b)));
        }
        md.push_str(&r.markdown);
        md.push('\n');
    }
    println!("{md}");
    if let Some(out) = &args.out {
        std::fs::write(out, &md).with_context(|| format!("writing {}", out.display()))?;
        eprintln!("wrote {}", out.display());
    }
    let errors: u64 = reports.iter().map(|(_, r)| r.errors).sum();
    if errors > 0 {
        bail!("{errors} errors under load");
    }
    Ok(())
}

fn name(backend: Backend) -> &'static str {
    match backend {
        Backend::Sqlite => "SQLite",
        Backend::Postgres => "PostgreSQL",
    }
}

/// One backend's run: its Markdown report, its headline figures (label, value) in a fixed
/// order, and its error count.
struct Report {
    markdown: String,
    summary: Vec<(String, String)>,
    errors: u64,
}

async fn measure(args: &Args, backend: Backend) -> anyhow::Result<Report> {
    let machine = machine();
    let bin = helmholtz_tests::server_binary_beside(args.server_bin.as_deref())?;
    let dir = tempfile::tempdir()?;
    // The benchmark measures throughput, not the per-lab session cap (10,000 by default, which
    // 50 rigs pass within a minute here): lift it.
    let mut extra: Vec<String> = vec!["--max-sessions-per-lab".into(), "100000000".into()];
    if let Some(w) = args.workers {
        extra.extend(["--workers".into(), w.to_string()]);
    }
    let extra: Vec<&str> = extra.iter().map(String::as_str).collect();
    let mut server =
        ServerProcess::start_binary_on(backend, &bin, &dir.path().join("data"), 0, &extra)?;
    // The harness's token rides in `base_url`; `--token` replaces it.
    let base = match &args.token {
        Some(token) => helmholtz_client::auth::with_token(&server.address, token),
        None => server.base_url.clone(),
    };
    let pid = server.pid();
    eprintln!("server {} (pid {pid}) at {base}", bin.display());

    let http = {
        let mut headers = reqwest::header::HeaderMap::new();
        if let Some(token) = &args.token {
            headers.insert(
                reqwest::header::AUTHORIZATION,
                format!("Bearer {token}")
                    .parse()
                    .context("--token is not a valid header value")?,
            );
        }
        helmholtz_client::tls::install_crypto_provider();
        reqwest::Client::builder()
            .default_headers(headers)
            .build()?
    };

    // Reference sessions with a finished reconstruction: what the queries read.
    let side = args.side;
    let spec = |rows: u64, seed: u64| -> PatternSpec {
        serde_json::from_str(&format!(
            r#"{{"family":"bernoulli","width":{side},"height":{side},"count":{rows},"seed":{seed}}}"#
        ))
        .expect("valid spec")
    };
    let transport = Target::builtin("usaf", side, side)?.transport(1.0);
    let noise = NoiseModel {
        snr_db: Some(30.0),
        ..NoiseModel::default()
    };
    let mut reference = Vec::new();
    for r in 0..4u64 {
        let id = format!("ref-{r}");
        let s = spec(8192, 1000 + r);
        let sim = simulate::simulate(&s, &[&transport], &noise, None);
        helmholtz_client::create_session(&base, &NewSession::new(&id, s, vec!["bucket".into()]))
            .await?;
        helmholtz_client::upload(&base, &id, 1, &sim.values, &UploadOptions::default()).await?;
        helmholtz_client::finish_session(&base, &id).await?;
        let rec =
            helmholtz_client::request_reconstruction(&base, &id, "dgi", &serde_json::json!({}))
                .await?;
        let rec =
            helmholtz_client::wait_reconstruction(&base, rec.id, Duration::from_secs(120)).await?;
        anyhow::ensure!(rec.is_done(), "reference reconstruction failed: {rec:?}");
        reference.push((id, rec.id));
    }
    let reference = Arc::new(reference);

    // A camera session with its transport matrix, for relight queries: the Lambertian scene on
    // a 64x64 projector (complete Hadamard set, 8192 frames) seen by a 32x32 camera.
    eprintln!("reconstructing the camera reference session...");
    let camera_rec = {
        let scene = helmholtz_sim::Relief::demo(64, 64, 1);
        let view = scene.view(&helmholtz_sim::Camera::tilted(32, 32, 25.0));
        let s: PatternSpec = serde_json::from_str(
            r#"{"family":"hadamard","width":64,"height":64,"count":8192,"seed":1}"#,
        )?;
        let generator = helmholtz_proto::PatternGenerator::new(&s);
        let mut p = vec![0f32; s.pixels()];
        let mut frames = Vec::with_capacity(8192 * view.pixels());
        for i in 0..s.count() {
            generator.fill_values(i, &mut p);
            let p64: Vec<f64> = p.iter().map(|&v| v as f64).collect();
            frames.extend(view.render(&p64).into_iter().map(|v| v as f32));
        }
        let id = "ref-camera";
        let session = NewSession::camera(id, s, 32, 32, helmholtz_proto::wire::SampleFormat::F32);
        helmholtz_client::create_session(&base, &session).await?;
        helmholtz_client::upload_samples(
            &base,
            id,
            (32 * 32) as u32,
            helmholtz_proto::wire::Samples::F32(&frames),
            &UploadOptions::default(),
        )
        .await?;
        helmholtz_client::finish_session(&base, id).await?;
        let rec = helmholtz_client::request_reconstruction(
            &base,
            id,
            "transport",
            &serde_json::json!({}),
        )
        .await?;
        let rec =
            helmholtz_client::wait_reconstruction(&base, rec.id, Duration::from_secs(300)).await?;
        anyhow::ensure!(
            rec.is_done(),
            "camera reference reconstruction failed: {rec:?}"
        );
        rec.id
    };

    // One simulation per rig, reused for each of its sessions (new session ids).
    eprintln!("simulating {} rigs ({} rows each)...", args.rigs, args.rows);
    let rig_values: Vec<Arc<Vec<f64>>> = (0..args.rigs)
        .map(|k| {
            Arc::new(
                simulate::simulate(&spec(args.rows, k as u64), &[&transport], &noise, None).values,
            )
        })
        .collect();

    let uploads = Arc::new(Mutex::new(Samples::default()));
    let totals = Arc::new(Mutex::new(Totals::default()));
    let spools = SpoolDir::new(dir.path().join("spool"));
    let options = UploadOptions {
        chunk_rows: args.chunk_rows,
        ..UploadOptions::default()
    };
    // As in a lab, every rig has its own rig token and the queries a reader token (the server
    // limits requests per token); `--token` makes everyone share that one token instead.
    use helmholtz_tests::create_token_on;
    let (rig_bases, query_base) = match &args.token {
        Some(_) => (vec![base.clone(); args.rigs], base.clone()),
        None => {
            let mut bases = Vec::with_capacity(args.rigs);
            for _ in 0..args.rigs {
                bases.push(server.url_with(&create_token_on(
                    backend,
                    &bin,
                    &server.data_dir,
                    helmholtz_tests::E2E_LAB,
                    "rig",
                )?));
            }
            (
                bases,
                server.url_with(&create_token_on(
                    backend,
                    &bin,
                    &server.data_dir,
                    helmholtz_tests::E2E_LAB,
                    "reader",
                )?),
            )
        }
    };
    let started = Instant::now();
    let deadline = started + Duration::from_secs_f64(args.seconds);
    eprintln!(
        "running {} rigs and {} queries/s for {} s...",
        args.rigs, args.query_rate, args.seconds
    );

    let mut rigs = Vec::new();
    for (k, values) in rig_values.into_iter().enumerate() {
        let (base, spools, options) = (rig_bases[k].clone(), spools.clone(), options.clone());
        let (uploads, totals) = (uploads.clone(), totals.clone());
        let s = spec(args.rows, k as u64);
        let batch = args.batch_rows.max(1);
        rigs.push(tokio::spawn(async move {
            let mut n = 0u64;
            while Instant::now() < deadline {
                let id = format!("load-{k:03}-{n:05}");
                n += 1;
                let t0 = Instant::now();
                let session = NewSession::new(&id, s.clone(), vec!["bucket".into()])
                    .with_rig(format!("load-rig-{k}"));
                let result = async {
                    let spool = Arc::new(spools.create_or_open(&session, true)?);
                    let drainer = tokio::spawn({
                        let (spool, base, options) = (spool.clone(), base.clone(), options.clone());
                        async move { spool::drain(&base, spool, &options, true).await }
                    });
                    for rows in values.chunks(batch) {
                        let (spool, rows) = (spool.clone(), rows.to_vec());
                        tokio::task::spawn_blocking(move || spool.append(&rows)).await??;
                    }
                    spool.seal()?;
                    let report = drainer.await??;
                    anyhow::ensure!(report.finished, "session {id} not finished: {report:?}");
                    Ok(report)
                }
                .await;
                match result {
                    Ok(report) => {
                        uploads.lock().unwrap().record(Ok(t0.elapsed()));
                        let mut t = totals.lock().unwrap();
                        t.sessions += 1;
                        t.rows += report.committed_rows;
                        t.bytes += report.committed_rows * 8;
                        t.resumed_sessions += (report.resumes > 0) as u64;
                    }
                    Err(e) => uploads.lock().unwrap().record(Err(format!("{id}: {e:#}"))),
                }
            }
        }));
    }

    // The query stream: open loop at a fixed rate, cycling through the kinds.
    let kinds = [
        "dual.png",
        "dual.npy",
        "reconstruction json",
        "session dual.tiff",
        "relight camera disc (npy)",
        "relight bucket weights (png)",
    ];
    let queries: Arc<Vec<Mutex<Samples>>> = Arc::new(
        kinds
            .iter()
            .map(|_| Mutex::new(Samples::default()))
            .collect(),
    );
    let mut ticker = tokio::time::interval(Duration::from_secs_f64(1.0 / args.query_rate));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
    let mut in_flight = Vec::new();
    let mut i = 0usize;
    while Instant::now() < deadline {
        ticker.tick().await;
        let kind = i % kinds.len();
        let (session, rec) = reference[(i / kinds.len()) % reference.len()].clone();
        i += 1;
        // Relight lights change with every query (a disc wandering over the camera, weights
        // growing), so each is computed, not served from the response cache.
        let (url, body) = match kind {
            0 => (
                format!("{query_base}/v1/reconstructions/{rec}/dual.png"),
                None,
            ),
            1 => (
                format!("{query_base}/v1/reconstructions/{rec}/dual.npy"),
                None,
            ),
            2 => (format!("{query_base}/v1/reconstructions/{rec}"), None),
            3 => (
                format!("{query_base}/v1/sessions/{session}/dual.tiff"),
                None,
            ),
            4 => (
                format!("{query_base}/v1/reconstructions/{camera_rec}/relight?format=npy"),
                Some(format!(
                    r#"{{"light": {{"preset": "disc", "x": {}, "y": {}, "radius": 4}}}}"#,
                    i % 32,
                    (i / 32) % 32
                )),
            ),
            _ => (
                format!("{query_base}/v1/reconstructions/{rec}/relight"),
                Some(format!(
                    r#"{{"light": {{"weights": {{"bucket": {}}}}}}}"#,
                    1 + i
                )),
            ),
        };
        let (http, queries) = (http.clone(), queries.clone());
        in_flight.push(tokio::spawn(async move {
            let t0 = Instant::now();
            let result = async {
                let request = match body {
                    None => http.get(&url),
                    Some(body) => http
                        .post(&url)
                        .header("content-type", "application/json")
                        .body(body),
                };
                let response = request.send().await.map_err(|e| format!("{url}: {e}"))?;
                let status = response.status();
                let body = response.bytes().await.map_err(|e| format!("{url}: {e}"))?;
                if !status.is_success() || body.is_empty() {
                    return Err(format!("{url}: HTTP {status}, {} bytes", body.len()));
                }
                Ok(t0.elapsed())
            }
            .await;
            queries[kind].lock().unwrap().record(result);
        }));
    }
    for q in in_flight {
        q.await?;
    }
    let query_seconds = started.elapsed().as_secs_f64();
    for r in rigs {
        r.await?;
    }
    let elapsed = started.elapsed().as_secs_f64();
    let vm_hwm = proc_status_kib(pid, "VmHWM:");
    let vm_rss = proc_status_kib(pid, "VmRSS:");
    let _ = server.terminate();

    // The report.
    let uploads = uploads.lock().unwrap();
    let totals = totals.lock().unwrap();
    let query_count: usize = queries.iter().map(|q| q.lock().unwrap().ok.len()).sum();
    let query_errors: u64 = queries.iter().map(|q| q.lock().unwrap().errors).sum();
    let errors = uploads.errors + query_errors;
    let mut md = String::new();
    md.push_str(&format!(
        "- command: `helmholtz-load --rigs {} --seconds {} --rows {} --side {} --query-rate {} --batch-rows {}{}`\n",
        args.rigs,
        args.seconds,
        args.rows,
        args.side,
        args.query_rate,
        args.batch_rows,
        args.chunk_rows.map(|c| format!(" --chunk-rows {c}")).unwrap_or_default()
    ));
    md.push_str(&format!("- machine: {machine}\n"));
    md.push_str(&format!(
        "- database: {}\n",
        match backend {
            Backend::Sqlite => "SQLite (the embedded default, a file in the data directory)",
            Backend::Postgres => "PostgreSQL (a database of its own on HELMHOLTZ_TEST_POSTGRES, default the local server)",
        }
    ));
    md.push_str(&format!(
        "- build: {} profile\n",
        if cfg!(debug_assertions) {
            "dev (optimised, debug assertions on)"
        } else {
            "release"
        }
    ));
    md.push_str(&format!(
        "- wall time: {elapsed:.1} s (the last sessions started before the deadline finish after it)\n\n"
    ));
    md.push_str("| figure | value |\n|---|---|\n");
    md.push_str(&format!(
        "| sessions uploaded and finished | {} ({} resumed after a retry) |\n",
        totals.sessions, totals.resumed_sessions
    ));
    md.push_str(&format!(
        "| rows committed | {} ({:.0} rows/s) |\n",
        totals.rows,
        totals.rows as f64 / elapsed
    ));
    md.push_str(&format!(
        "| bucket values committed | {:.1} MB ({:.2} MB/s) |\n",
        totals.bytes as f64 / 1e6,
        totals.bytes as f64 / 1e6 / elapsed
    ));
    md.push_str(&format!(
        "| queries answered | {query_count} ({:.1} queries/s) |\n",
        query_count as f64 / query_seconds
    ));
    md.push_str(&format!(
        "| errors | {errors} (uploads {}, queries {query_errors}) |\n",
        uploads.errors
    ));
    md.push_str(&format!(
        "| server peak RSS (VmHWM) | {} |\n",
        vm_hwm
            .map(|k| format!(
                "{:.1} MiB (VmRSS at the end {:.1} MiB)",
                k as f64 / 1024.0,
                vm_rss.unwrap_or(0) as f64 / 1024.0
            ))
            .unwrap_or_else(|| "unavailable (no /proc)".into())
    ));
    md.push_str(
        "\n| kind | count | p50 ms | p99 ms | max ms | errors |\n|---|---|---|---|---|---|\n",
    );
    let row = |name: &str, s: &Samples| {
        format!(
            "| {name} | {} | {:.1} | {:.1} | {:.1} | {} |\n",
            s.ok.len(),
            s.percentile(50.0) * 1e3,
            s.percentile(99.0) * 1e3,
            s.percentile(100.0) * 1e3,
            s.errors
        )
    };
    md.push_str(&row(
        &format!(
            "upload session ({} rows: spool + upload + finish)",
            args.rows
        ),
        &uploads,
    ));
    for (k, name) in kinds.iter().enumerate() {
        let verb = if name.starts_with("relight") {
            "POST"
        } else {
            "GET"
        };
        md.push_str(&row(&format!("{verb} {name}"), &queries[k].lock().unwrap()));
    }
    let mut first_errors: Vec<String> = Vec::new();
    first_errors.extend(uploads.first_error.clone());
    for q in queries.iter() {
        first_errors.extend(q.lock().unwrap().first_error.clone());
    }
    if !first_errors.is_empty() {
        md.push_str("\nFirst errors:\n\n");
        for e in &first_errors {
            md.push_str(&format!("- {e}\n"));
        }
    }
    let mut summary = vec![
        (
            "rows committed per second".to_string(),
            format!("{:.0}", totals.rows as f64 / elapsed),
        ),
        (
            "sessions uploaded and finished".into(),
            totals.sessions.to_string(),
        ),
        (
            "queries answered per second".into(),
            format!("{:.1}", query_count as f64 / query_seconds),
        ),
        ("errors".into(), errors.to_string()),
        (
            "server peak RSS (VmHWM)".into(),
            vm_hwm.map_or("unavailable".into(), |k| {
                format!("{:.1} MiB", k as f64 / 1024.0)
            }),
        ),
        (
            "upload session p50 / p99 ms".into(),
            format!(
                "{:.1} / {:.1}",
                uploads.percentile(50.0) * 1e3,
                uploads.percentile(99.0) * 1e3
            ),
        ),
    ];
    for (k, name) in kinds.iter().enumerate() {
        let q = queries[k].lock().unwrap();
        summary.push((
            format!("{name} p50 / p99 ms"),
            format!(
                "{:.1} / {:.1}",
                q.percentile(50.0) * 1e3,
                q.percentile(99.0) * 1e3
            ),
        ));
    }
    Ok(Report {
        markdown: md,
        summary,
        errors,
    })
}
