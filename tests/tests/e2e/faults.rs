//! Faults, all with the real server binary and the real client: the server is killed (SIGKILL)
//! at random moments during 20 spooled uploads (plus one long one that the first kill cuts
//! mid-stream) and restarted; the client process is killed mid-spool and mid-upload and rerun;
//! the server is killed mid-reconstruction. No measured row is lost, none is stored twice, and
//! every job finishes exactly once.

use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use helmholtz_client::spool::{self, SpoolDir};
use helmholtz_client::{Backoff, NewSession, PatternSpec, UploadOptions};
use helmholtz_sim::Target;
use helmholtz_sim::simulate::{self, NoiseModel};
use helmholtz_tests::{FaultyProxy, ServerProcess, SplitMix64, binary, fault_seed, parse_npy};

/// Server flags of the tests that poll the API to time their faults: no per-token rate limit
/// (it is tested on its own), which would refuse the polls and the uploads sharing the token.
const UNLIMITED: &[&str] = &["--rate-per-second", "0"];

/// The rows a session stored, as the server serves them back.
async fn stored(server: &ServerProcess, id: &str) -> (Vec<usize>, Vec<f64>) {
    let response =
        helmholtz_tests::http_get(server.url(&format!("/v1/sessions/{id}/measurements.npy")))
            .await
            .unwrap();
    assert_eq!(response.status(), 200, "measurements of {id}");
    parse_npy(&response.bytes().await.unwrap()).unwrap()
}

/// The committed count of every session the server knows (empty if it does not answer).
async fn all_committed_rows(server: &ServerProcess) -> std::collections::HashMap<String, u64> {
    let Ok(response) = helmholtz_tests::http_get(server.url("/v1/sessions?limit=1000")).await
    else {
        return Default::default();
    };
    let list: serde_json::Value = response.json().await.unwrap_or_default();
    list["sessions"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|s| Some((s["id"].as_str()?.to_string(), s["committed_rows"].as_u64()?)))
        .collect()
}

/// Row `r`, channel `c` of rig `k`: distinct everywhere, so a row stored twice or out of place
/// cannot match.
fn rig_value(k: u64, r: u64, c: u64) -> f64 {
    k as f64 * 1e6 + r as f64 + c as f64 * 0.25 + 0.125
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn twenty_spooled_uploads_survive_the_server_killed_at_random_moments() {
    let seed = fault_seed();
    println!("fault seed {seed} (rerun with HELMHOLTZ_FAULT_SEED={seed})");
    let mut rng = SplitMix64(seed);
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let mut server = ServerProcess::start(&data, 0, UNLIMITED).unwrap();
    let base = server.base_url.clone();
    let port = server.port;
    let spools = SpoolDir::new(dir.path().join("spool"));
    let options = UploadOptions {
        chunk_rows: Some(100),
        retry_for: Duration::from_secs(60),
        backoff: Backoff {
            initial: Duration::from_millis(20),
            max: Duration::from_millis(500),
            ..Backoff::default()
        },
        ..UploadOptions::default()
    };

    // 20 rigs measuring at once: each spools its rows in batches (a few ms apart) while its
    // uploader drains the spool.
    let mut sent: Vec<(String, u64, Vec<f64>)> = Vec::new();
    let mut rigs = Vec::new();
    let done = Arc::new(AtomicUsize::new(0));
    // Every rig keeps its session open (unsealed) until the server has been killed at least
    // MIN_KILLS times, so the kills land mid-upload however fast the machine is.
    const MIN_KILLS: usize = 3;
    let kills_seen = Arc::new(AtomicUsize::new(0));
    for k in 0..20u64 {
        let rows = rng.range(2_000, 6_000);
        let channels = rng.range(1, 3);
        let id = format!("rig-{k:02}");
        let values: Vec<f64> = (0..rows)
            .flat_map(|r| (0..channels).map(move |c| rig_value(k, r, c)))
            .collect();
        let spec: PatternSpec = serde_json::from_str(&format!(
            r#"{{"family":"bernoulli","width":16,"height":16,"count":{rows},"seed":{k}}}"#
        ))
        .unwrap();
        let names = (0..channels).map(|c| format!("ch{c}")).collect();
        let session = NewSession::new(id.clone(), spec, names);
        let spool = Arc::new(spools.create_or_open(&session, true).unwrap());
        let batch = rng.range(50, 400) as usize;
        let pause = Duration::from_millis(rng.range(1, 15));
        sent.push((id.clone(), channels, values.clone()));
        let (base, options, done, kills_seen) = (
            base.clone(),
            options.clone(),
            done.clone(),
            kills_seen.clone(),
        );
        rigs.push(tokio::spawn(async move {
            let drainer = tokio::spawn({
                let (spool, base, options) = (spool.clone(), base.clone(), options.clone());
                async move { spool::drain(&base, spool, &options, true).await }
            });
            for rows in values.chunks(batch * channels as usize) {
                spool.append(rows).unwrap();
                tokio::time::sleep(pause).await;
            }
            while kills_seen.load(Ordering::SeqCst) < MIN_KILLS {
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
            spool.seal().unwrap();
            let report = drainer.await.unwrap();
            done.fetch_add(1, Ordering::SeqCst);
            report
        }));
    }

    // One more rig spools a long run of rows in one go and uploads it in small chunks: its first
    // pass is a single stream, so while the server's committed count for it lies strictly
    // between 0 and its total, that stream is open. The first kill lands at a random point of
    // it, so at least one kill cuts a stream mid-flight however fast or slow the machine is
    // (the other rigs' streams are short bursts that random kills may all miss).
    const BIG_ROWS: u64 = 40_000;
    let big_id = "rig-big".to_string();
    {
        let values: Vec<f64> = (0..BIG_ROWS).map(|r| rig_value(99, r, 0)).collect();
        let spec: PatternSpec = serde_json::from_str(&format!(
            r#"{{"family":"bernoulli","width":16,"height":16,"count":{BIG_ROWS},"seed":99}}"#
        ))
        .unwrap();
        let session = NewSession::new(big_id.clone(), spec, vec!["ch0".to_string()]);
        let spool = Arc::new(spools.create_or_open(&session, true).unwrap());
        spool.append(&values).unwrap();
        spool.seal().unwrap();
        sent.push((big_id.clone(), 1, values));
        let options = UploadOptions {
            chunk_rows: Some(10),
            ..options.clone()
        };
        let (base, done) = (base.clone(), done.clone());
        rigs.push(tokio::spawn(async move {
            let report = spool::drain(&base, spool, &options, true).await;
            done.fetch_add(1, Ordering::SeqCst);
            report
        }));
    }
    let uploads = rigs.len();
    let first_kill_at = rng.range(BIG_ROWS / 10, BIG_ROWS * 6 / 10);
    let wait_until = Instant::now() + Duration::from_secs(60);
    let committed_at_first_kill = loop {
        match committed(&base, &big_id).await {
            Some(c) if c >= first_kill_at => break c,
            _ => {}
        }
        assert!(
            Instant::now() < wait_until,
            "{big_id} did not reach {first_kill_at} committed rows within 60 s; seed {seed}"
        );
        tokio::time::sleep(Duration::from_millis(2)).await;
    };

    // SIGKILL the server at random moments while rigs are uploading (the first one mid-stream,
    // above); restart it on the same port with the same data directory.
    let mut kills = 0;
    let deadline = Instant::now() + Duration::from_secs(120);
    while done.load(Ordering::SeqCst) < uploads && kills < 10 {
        if kills > 0 {
            tokio::time::sleep(Duration::from_millis(rng.range(100, 600))).await;
            if done.load(Ordering::SeqCst) == uploads {
                break;
            }
        }
        server.kill();
        kills += 1;
        kills_seen.store(kills, Ordering::SeqCst);
        tokio::time::sleep(Duration::from_millis(rng.range(0, 300))).await;
        server = ServerProcess::start(&data, port, UNLIMITED).unwrap();
        assert!(
            Instant::now() < deadline,
            "the uploads did not finish within 120 s"
        );
    }
    println!(
        "killed the server {kills} times, the first with {committed_at_first_kill} of {BIG_ROWS} rows of {big_id} committed"
    );
    assert!(
        committed_at_first_kill < BIG_ROWS,
        "{big_id} finished before the first kill, which was to land mid-stream; seed {seed}"
    );
    assert!(
        kills >= MIN_KILLS,
        "the server must die several times mid-upload (only {kills}); seed {seed}"
    );

    let mut interrupted = 0;
    for rig in rigs {
        let report = rig
            .await
            .unwrap()
            .unwrap_or_else(|e| panic!("seed {seed}: {e:#}"));
        assert!(report.finished && report.removed, "seed {seed}: {report:?}");
        assert_eq!(report.committed_rows, report.expected_rows);
        if report.session_id == big_id {
            assert!(
                report.resumes > 0,
                "the kill mid-stream of {big_id} went unnoticed: {report:?}; seed {seed}"
            );
        }
        interrupted += (report.resumes > 0) as usize;
    }
    println!("{interrupted} of {uploads} uploads were interrupted and resumed");
    let mut resumed = 0;
    for (id, channels, values) in &sent {
        let (shape, rows) = stored(&server, id).await;
        assert_eq!(
            shape,
            vec![values.len() / *channels as usize, *channels as usize],
            "{id}, seed {seed}"
        );
        assert!(
            rows == *values,
            "{id}: the stored rows differ from the sent rows (seed {seed})"
        );
        let session: serde_json::Value =
            helmholtz_tests::http_get(server.url(&format!("/v1/sessions/{id}")))
                .await
                .unwrap()
                .json()
                .await
                .unwrap();
        assert_eq!(session["state"], "finished", "{id}: {session}");
        resumed += 1;
    }
    assert_eq!(resumed, uploads);
    assert!(
        spools.sessions().unwrap().is_empty(),
        "every spool is cleared once its rows are committed"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_through_a_proxy_that_cuts_connections_store_every_row_once() {
    let seed = fault_seed();
    println!("fault seed {seed} (rerun with HELMHOLTZ_FAULT_SEED={seed})");
    let mut rng = SplitMix64(seed);
    let dir = tempfile::tempdir().unwrap();
    // On PostgreSQL this test found a cancelled request returning a pooled connection inside a
    // transaction (seed 1795673659740224053); store::postgres::begin is the fix.
    let server = ServerProcess::start(&dir.path().join("data"), 0, UNLIMITED).unwrap();
    let proxy = FaultyProxy::start(format!("127.0.0.1:{}", server.port))
        .await
        .unwrap();
    let spools = SpoolDir::new(dir.path().join("spool"));
    let options = UploadOptions {
        chunk_rows: Some(10),
        backoff: Backoff {
            initial: Duration::from_millis(10),
            max: Duration::from_millis(200),
            ..Backoff::default()
        },
        ..UploadOptions::default()
    };
    let mut sent = Vec::new();
    let mut rigs = Vec::new();
    for k in 0..5u64 {
        let rows = rng.range(3_000, 6_000);
        let id = format!("cut-{k}");
        let values: Vec<f64> = (0..rows).map(|r| rig_value(k, r, 0)).collect();
        let spec: PatternSpec = serde_json::from_str(&format!(
            r#"{{"family":"bernoulli","width":8,"height":8,"count":{rows},"seed":{k}}}"#
        ))
        .unwrap();
        let spool = Arc::new(
            spools
                .create_or_open(
                    &NewSession::new(id.clone(), spec, vec!["bucket".into()]),
                    true,
                )
                .unwrap(),
        );
        spool.append(&values).unwrap();
        spool.seal().unwrap();
        sent.push((id, values));
        // The proxy's address with the harness's token (the server checks it).
        let url = helmholtz_client::auth::with_token(&proxy.url(), &server.token);
        let options = options.clone();
        rigs.push(tokio::spawn(async move {
            spool::drain(&url, spool, &options, false).await
        }));
    }
    // Each rig's rows are spooled before its drain starts, so a pass is one stream to the end:
    // a committed count that grew since the last look and is still 10 chunks short of the total
    // means that rig's stream is open now. Cut every connection at such moments (found by
    // polling the server directly at random intervals), so the cuts land mid-stream however
    // fast the machine is; a rig is only cut again after it made progress.
    let mut seen = vec![0u64; sent.len()];
    let (mut cuts, mut mid_stream_cuts) = (0, 0);
    while !rigs.iter().all(|r| r.is_finished()) {
        tokio::time::sleep(Duration::from_millis(rng.range(5, 40))).await;
        let committed = all_committed_rows(&server).await;
        let mut streaming = false;
        for (i, (id, values)) in sent.iter().enumerate() {
            let Some(&c) = committed.get(id) else {
                continue;
            };
            streaming |= c > seen[i] && c + 500 <= values.len() as u64;
            seen[i] = seen[i].max(c);
        }
        if streaming {
            let n = proxy.cut_all();
            cuts += n;
            mid_stream_cuts += (n > 0) as usize;
        }
    }
    println!("cut {cuts} connections at {mid_stream_cuts} moments mid-stream");
    assert!(
        mid_stream_cuts >= 3,
        "the proxy must have cut connections mid-upload (only {mid_stream_cuts} times); seed {seed}"
    );
    let mut resumed = 0;
    for rig in rigs {
        let report = rig
            .await
            .unwrap()
            .unwrap_or_else(|e| panic!("seed {seed}: {e:#}"));
        assert!(report.finished && report.removed, "{report:?}");
        resumed += (report.resumes > 0) as usize;
    }
    assert!(resumed >= 1, "no upload was cut and resumed; seed {seed}");
    for (id, values) in &sent {
        let (shape, rows) = stored(&server, id).await;
        assert_eq!(shape, vec![values.len(), 1], "{id}");
        assert!(
            rows == *values,
            "{id}: the stored rows differ from the sent rows (seed {seed})"
        );
    }
}

fn helmholtz(server: &str, spool: &std::path::Path, args: &[&str]) -> Command {
    let mut c = Command::new(binary("helmholtz"));
    c.arg("--server")
        .arg(server)
        .arg("--spool")
        .arg(spool)
        .arg("--json")
        .args(args);
    c.stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    c
}

fn run_json(mut command: Command) -> serde_json::Value {
    let out = command.output().unwrap();
    assert!(
        out.status.success(),
        "{command:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// Waits until `ready()` or panics after `secs`.
async fn wait_for(what: &str, secs: u64, mut ready: impl AsyncFnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    while !ready().await {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// The server's committed count once it stops moving: chunks a killed client had already put on
/// the wire may still be committed for a moment after it died (they were sent; that is fine).
async fn settled_committed(server: &str, id: &str) -> u64 {
    let mut last = spool::probe_committed(server, id).await.unwrap();
    loop {
        tokio::time::sleep(Duration::from_millis(300)).await;
        let now = spool::probe_committed(server, id).await.unwrap();
        if now == last {
            return now;
        }
        last = now;
    }
}

fn sigkill(child: &mut Child) {
    child.kill().unwrap(); // SIGKILL on Unix
    child.wait().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_client_killed_mid_spool_and_mid_upload_loses_and_duplicates_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let spool_dir = dir.path().join("spool");
    let spools = SpoolDir::new(&spool_dir);
    let mut server = ServerProcess::start(&data, 0, &[]).unwrap();
    let base = server.base_url.clone();
    let port = server.port;
    let values_file = dir.path().join("values.npy");
    let total = 40_000u64;
    let count = total.to_string();
    // A rig showing 20,000 patterns a second, spooling every 250 rows, uploading 50-row chunks.
    let simulate: Vec<&str> = vec![
        "simulate",
        "--scene",
        "usaf",
        "--width",
        "16",
        "--height",
        "16",
        "--count",
        &count,
        "--seed",
        "9",
        "--snr-db",
        "30",
        "--channels",
        "a,b",
        "--session-id",
        "killed",
        "--frame-rate",
        "20000",
        "--batch-rows",
        "250",
        "--chunk-rows",
        "50",
        "--retry-for",
        "60",
    ];

    // 1. SIGKILL the client while it is measuring (spooling) and uploading.
    let mut child = helmholtz(&base, &spool_dir, &simulate).spawn().unwrap();
    wait_for("rows in the spool", 60, async || {
        spools
            .inspect("killed")
            .is_ok_and(|i| i.spooled_rows >= 8_000)
    })
    .await;
    sigkill(&mut child);
    let info = spools.inspect("killed").unwrap();
    println!(
        "client killed with {} of {total} rows spooled",
        info.spooled_rows
    );
    assert!(
        info.spooled_rows < total && !info.sealed,
        "killed mid-spool: {info:?}"
    );
    assert!(!info.busy, "a dead process holds no lock");
    let committed = settled_committed(&base, "killed").await;
    assert!(
        committed <= info.spooled_rows,
        "the server cannot have rows that were never spooled"
    );
    let status = run_json(helmholtz(&base, &spool_dir, &["spool", "status"]));
    let entry = &status["sessions"][0];
    assert_eq!(entry["session_id"], "killed");
    // Pending: the spooled rows the server has not confirmed with the spool's bytes (the
    // killed client's last stream never ended, so its rows count as pending even where the
    // server committed them; the next upload re-sends them and the server compares).
    let confirmed = entry["state"]["confirmed_rows"]
        .as_u64()
        .unwrap_or(0)
        .max(info.base_row);
    assert!(
        confirmed <= committed,
        "the client never counts rows the server does not hold: {status}"
    );
    let pending = info.spooled_rows - confirmed;
    assert_eq!(
        entry["status"],
        if pending > 0 { "pending" } else { "incomplete" },
        "{status}"
    );
    assert_eq!(entry["committed_rows"], committed);
    assert_eq!(entry["pending_rows"], pending);

    // 2. Rerun with the server down: the rig spools every row (the upload keeps failing), then
    //    the server comes back and the client is SIGKILLed again halfway through the upload.
    server.kill();
    let mut rerun = simulate.clone();
    rerun.extend(["--values-out", values_file.to_str().unwrap()]);
    let mut child = helmholtz(&base, &spool_dir, &rerun).spawn().unwrap();
    wait_for("the whole session spooled", 60, async || {
        spools.inspect("killed").is_ok_and(|i| i.sealed)
    })
    .await;
    assert_eq!(spools.inspect("killed").unwrap().spooled_rows, total);
    server = ServerProcess::start(&data, port, &[]).unwrap();
    let before = helmholtz_client::upload_status(&base, "killed")
        .await
        .unwrap()
        .committed_rows;
    wait_for("the upload to resume", 60, async || {
        helmholtz_client::upload_status(&base, "killed")
            .await
            .is_ok_and(|s| s.committed_rows >= before + 2_000)
    })
    .await;
    sigkill(&mut child);
    let mid = settled_committed(&base, "killed").await;
    println!("client killed again with {mid} of {total} rows committed");
    assert!(
        mid < total,
        "killed mid-upload ({mid} of {total} rows committed)"
    );
    let status = run_json(helmholtz(&base, &spool_dir, &["spool", "status", "killed"]));
    let entry = &status["sessions"][0];
    assert_eq!(entry["status"], "pending", "{status}");
    let confirmed = entry["state"]["confirmed_rows"]
        .as_u64()
        .unwrap_or(0)
        .max(entry["base_row"].as_u64().unwrap());
    assert!(confirmed <= mid, "{status}");
    assert_eq!(entry["pending_rows"], total - confirmed, "{status}");
    assert!(entry["sealed"].as_bool().unwrap(), "{status}");

    // 3. `spool upload` drains what is pending, finishes the session and clears the spool.
    let uploaded = run_json(helmholtz(&base, &spool_dir, &["spool", "upload"]));
    let report = &uploaded["uploaded"][0];
    assert_eq!(report["committed_rows"], total, "{uploaded}");
    assert!(
        report["rows_sent"].as_u64().unwrap() >= total - mid,
        "{uploaded}"
    );
    assert_eq!(report["finished"], true);
    assert_eq!(report["removed"], true);
    assert!(spools.sessions().unwrap().is_empty());
    let status = run_json(helmholtz(&base, &spool_dir, &["spool", "status"]));
    assert_eq!(status["sessions"].as_array().unwrap().len(), 0, "{status}");

    // Exactly the simulated rows, each once, in order.
    let (shape, rows) = stored(&server, "killed").await;
    assert_eq!(shape, vec![total as usize, 2]);
    let m = helmholtz_client::measurements::read_measurements(&values_file).unwrap();
    assert!(
        rows == m.values,
        "the stored rows differ from the simulated rows"
    );
    let session: serde_json::Value = helmholtz_tests::http_get(server.url("/v1/sessions/killed"))
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(session["state"], "finished");
}

async fn committed(server: &str, id: &str) -> Option<u64> {
    helmholtz_client::upload_status(server, id)
        .await
        .ok()
        .map(|s| s.committed_rows)
}

#[tokio::test]
async fn server_killed_mid_upload_then_restarted_loses_and_duplicates_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let base = server.base_url.clone();
    let port = server.port;
    let spec: PatternSpec = serde_json::from_str(
        r#"{"family":"bernoulli","width":16,"height":16,"count":60000,"seed":5}"#,
    )
    .unwrap();
    let transport = Target::builtin("usaf", 16, 16).unwrap().transport(1.0);
    let noise = NoiseModel {
        snr_db: Some(30.0),
        ..NoiseModel::default()
    };
    let sim = simulate::simulate(&spec, &[&transport, &transport], &noise, None);
    let session = NewSession::new("kill-upload", spec.clone(), vec!["a".into(), "b".into()]);
    helmholtz_client::create_session(&base, &session)
        .await
        .unwrap();

    // Small chunks so that the upload spans many commits; the uploader resumes for up to 60 s.
    let options = UploadOptions {
        chunk_rows: Some(200),
        retry_for: Duration::from_secs(60),
        ..UploadOptions::default()
    };
    let values = sim.values.clone();
    let uploader = {
        let base = base.clone();
        tokio::spawn(async move {
            helmholtz_client::upload(&base, "kill-upload", 2, &values, &options).await
        })
    };
    // Kill the server twice while rows are flowing, restarting it on the same port and data.
    for threshold in [5_000u64, 25_000] {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if committed(&base, "kill-upload").await.unwrap_or(0) >= threshold {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "upload never reached {threshold} rows"
            );
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        server.kill();
        tokio::time::sleep(Duration::from_millis(300)).await;
        server = ServerProcess::start(dir.path(), port, &[]).unwrap();
    }
    let report = uploader.await.unwrap().unwrap();
    assert!(
        report.resumes >= 1,
        "the uploader must have resumed: {report:?}"
    );
    assert_eq!(report.committed_rows, 60_000);
    helmholtz_client::finish_session(&base, "kill-upload")
        .await
        .unwrap();
    let bytes = helmholtz_tests::http_get(server.url("/v1/sessions/kill-upload/measurements.npy"))
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let (shape, stored) = parse_npy(&bytes).unwrap();
    assert_eq!(shape, vec![60_000, 2]);
    assert!(
        stored == sim.values,
        "stored rows differ from the sent rows"
    );
}

#[tokio::test]
async fn a_job_whose_server_died_is_taken_up_again_and_finishes_once() {
    let dir = tempfile::tempdir().unwrap();
    let lease = ["--lease-seconds", "2", "--workers", "1"];
    let mut server = ServerProcess::start(dir.path(), 0, &lease).unwrap();
    let base = server.base_url.clone();
    let port = server.port;
    // Grey-level speckle patterns: the correlator cannot take the packed-bits path, so the job
    // runs long enough (seconds) to be killed while running.
    let spec: PatternSpec = serde_json::from_str(
        r#"{"family":"speckle","width":64,"height":64,"count":120000,"seed":9}"#,
    )
    .unwrap();
    let transport = Target::builtin("double-slit", 64, 64)
        .unwrap()
        .transport(1.0);
    let sim = simulate::simulate(&spec, &[&transport], &NoiseModel::default(), None);
    helmholtz_client::create_session(
        &base,
        &NewSession::new("kill-job", spec.clone(), vec!["bucket".into()]),
    )
    .await
    .unwrap();
    helmholtz_client::upload(&base, "kill-job", 1, &sim.values, &UploadOptions::default())
        .await
        .unwrap();
    helmholtz_client::finish_session(&base, "kill-job")
        .await
        .unwrap();
    let rec =
        helmholtz_client::request_reconstruction(&base, "kill-job", "gi", &serde_json::json!({}))
            .await
            .unwrap();

    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let r = helmholtz_client::get_reconstruction(&base, rec.id)
            .await
            .unwrap();
        if r.state == "running" {
            break;
        }
        assert_ne!(
            r.state, "done",
            "the job finished before it could be killed; make it longer"
        );
        assert!(Instant::now() < deadline, "job never started");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    server.kill();
    server = ServerProcess::start(dir.path(), port, &lease).unwrap();
    let done = helmholtz_client::wait_reconstruction(&base, rec.id, Duration::from_secs(180))
        .await
        .unwrap();
    assert!(done.is_done(), "{done:?}");
    let json: serde_json::Value =
        helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{}", rec.id)))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
    assert_eq!(
        json["attempt"], 2,
        "taken up again after the lease expired: {json}"
    );
    let listed: serde_json::Value =
        helmholtz_tests::http_get(server.url("/v1/sessions/kill-job/reconstructions"))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
    assert_eq!(listed["reconstructions"].as_array().unwrap().len(), 1);
    let npy =
        helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{}/dual.npy", rec.id)))
            .await
            .unwrap();
    let (shape, _) = parse_npy(&npy.bytes().await.unwrap()).unwrap();
    assert_eq!(shape, vec![64, 64]);
}
