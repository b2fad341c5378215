//! Operating the shared service: the job queue is fair across labs, jobs can be cancelled, caps
//! refuse with a clear error and store nothing, metrics describe what happened, and SIGTERM
//! shuts down gracefully (acknowledged rows kept, running jobs give their lease back).

use std::time::{Duration, Instant};

use helmholtz_client::{NewSession, PatternSpec, UploadOptions};
use helmholtz_proto::v1;
use helmholtz_sim::Target;
use helmholtz_sim::simulate::{self, NoiseModel};
use helmholtz_tests::{OpenUpload, ServerProcess};
use serde_json::Value;
use tonic::Code;

/// Creates and fills a simulated session (`spec` JSON, scene "double-slit").
async fn acquire(server: &str, id: &str, spec: &str) {
    let spec: PatternSpec = serde_json::from_str(spec).unwrap();
    let transport = Target::builtin("double-slit", spec.width(), spec.height())
        .unwrap()
        .transport(1.0);
    let sim = {
        let (spec, transport) = (spec.clone(), transport.clone());
        tokio::task::spawn_blocking(move || {
            simulate::simulate(&spec, &[&transport], &NoiseModel::default(), None)
        })
        .await
        .unwrap()
    };
    helmholtz_client::create_session(server, &NewSession::new(id, spec, vec!["bucket".into()]))
        .await
        .unwrap();
    helmholtz_client::upload(server, id, 1, &sim.values, &UploadOptions::default())
        .await
        .unwrap();
    helmholtz_client::finish_session(server, id).await.unwrap();
}

async fn get(server: &ServerProcess, token: &str, path: &str) -> (u16, Value) {
    let r = helmholtz_tests::http_client()
        .get(format!("{}{path}", server.address))
        .bearer_auth(token)
        .send()
        .await
        .unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

async fn post(server: &ServerProcess, token: &str, path: &str, body: &str) -> reqwest::Response {
    helmholtz_tests::http_client()
        .post(format!("{}{path}", server.address))
        .bearer_auth(token)
        .header("content-type", "application/json")
        .body(body.to_string())
        .send()
        .await
        .unwrap()
}

async fn wait_state(
    server: &ServerProcess,
    token: &str,
    id: i64,
    states: &[&str],
    within: Duration,
) -> Value {
    let deadline = Instant::now() + within;
    loop {
        let (_, r) = get(server, token, &format!("/v1/reconstructions/{id}")).await;
        if states.contains(&r["state"].as_str().unwrap_or("")) {
            return r;
        }
        assert!(
            Instant::now() < deadline,
            "reconstruction {id} never reached {states:?}: {r}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test]
async fn one_labs_backlog_does_not_starve_another_lab() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &["--workers", "1"]).unwrap();
    let a = server.create_token("lab-a", "rig,reader").unwrap();
    let b = server.create_token("lab-b", "rig,reader").unwrap();
    // Speckle (grey-level) patterns: each gi job takes a noticeable fraction of a second.
    let spec = r#"{"family":"speckle","width":64,"height":64,"count":20000,"seed":3}"#;
    acquire(&server.url_with(&a), "a-big", spec).await;
    acquire(&server.url_with(&b), "b-one", spec).await;
    let mut a_jobs = Vec::new();
    for _ in 0..6 {
        let r = post(
            &server,
            &a,
            "/v1/sessions/a-big/reconstructions",
            r#"{"method": "gi"}"#,
        )
        .await;
        assert_eq!(r.status(), 202);
        a_jobs.push(r.json::<Value>().await.unwrap()["id"].as_i64().unwrap());
    }
    let r = post(
        &server,
        &b,
        "/v1/sessions/b-one/reconstructions",
        r#"{"method": "gi"}"#,
    )
    .await;
    let b_job = r.json::<Value>().await.unwrap()["id"].as_i64().unwrap();
    let (_, listed) = get(&server, &a, "/v1/sessions/a-big/reconstructions").await;
    let queued = listed["reconstructions"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["state"] == "queued")
        .count();
    assert!(
        queued >= 4,
        "lab a's backlog must still be waiting when lab b asks ({queued} queued): the test proves nothing otherwise"
    );
    let b_done = wait_state(&server, &b, b_job, &["done"], Duration::from_secs(120)).await;
    let (b_queued, b_started) = (
        b_done["created_unix_ms"].as_i64().unwrap(),
        b_done["started_unix_ms"].as_i64().unwrap(),
    );
    // Fair: once lab b's job is queued, the one worker takes it next. A job of lab a may already
    // run (or have run) then, on a busy machine more than one; none may start after b's job was
    // queued and before it starts.
    let mut a_started_while_b_waited = 0;
    for id in &a_jobs {
        let r = wait_state(&server, &a, *id, &["done"], Duration::from_secs(120)).await;
        let started = r["started_unix_ms"].as_i64().unwrap();
        if started > b_queued && started < b_started {
            a_started_while_b_waited += 1;
        }
    }
    assert_eq!(
        a_started_while_b_waited, 0,
        "lab b's one job waited while {a_started_while_b_waited} of lab a's 6 started"
    );
}

#[tokio::test]
async fn queued_and_running_jobs_are_cancelled_and_the_worker_is_freed() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(
        dir.path(),
        0,
        &["--workers", "1", "--max-pending-jobs-per-lab", "2"],
    )
    .unwrap();
    let t = server.token.clone();
    // Long: grey-level patterns, many rows (seconds of work).
    acquire(
        &server.base_url,
        "long",
        r#"{"family":"speckle","width":64,"height":64,"count":120000,"seed":9}"#,
    )
    .await;
    let request = |body: &'static str| post(&server, &t, "/v1/sessions/long/reconstructions", body);
    let first = request(r#"{"method": "gi"}"#)
        .await
        .json::<Value>()
        .await
        .unwrap()["id"]
        .as_i64()
        .unwrap();
    let second = request(r#"{"method": "gi"}"#)
        .await
        .json::<Value>()
        .await
        .unwrap()["id"]
        .as_i64()
        .unwrap();
    // The lab's cap on queued + running jobs.
    let third = request(r#"{"method": "gi"}"#).await;
    assert_eq!(third.status(), 429);
    let problem: Value = third.json().await.unwrap();
    assert_eq!(problem["limit"], "max_pending_jobs_per_lab", "{problem}");
    wait_state(&server, &t, first, &["running"], Duration::from_secs(60)).await;

    // The queued one, over gRPC (CancelReconstruction): cancelled, never started.
    let mut grpc = server.grpc().await.unwrap();
    let r = grpc
        .cancel_reconstruction(helmholtz_proto::v1::ReconstructionRef {
            reconstruction_id: second,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.state, "cancelled");
    // The running one (DELETE is the same): the worker stops at its next check.
    let cancelled_at = Instant::now();
    let r = helmholtz_tests::http_client()
        .delete(format!("{}/v1/reconstructions/{first}", server.address))
        .bearer_auth(&t)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    // Cancelling again is harmless (here with `helmholtz cancel`); a finished job cannot be
    // cancelled (409).
    let out = std::process::Command::new(helmholtz_tests::binary("helmholtz"))
        .args([
            "--server",
            &server.address,
            "--token",
            &t,
            "--json",
            "cancel",
            "--reconstruction",
            &first.to_string(),
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("cancelled"),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    // The single worker is free again: a small job runs and finishes.
    acquire(
        &server.base_url,
        "small",
        r#"{"family":"raster","width":8,"height":8,"count":64}"#,
    )
    .await;
    let small = post(
        &server,
        &t,
        "/v1/sessions/small/reconstructions",
        r#"{"method": "direct"}"#,
    )
    .await;
    assert_eq!(
        small.status(),
        202,
        "the cancelled jobs no longer count against the cap"
    );
    let small = small.json::<Value>().await.unwrap()["id"].as_i64().unwrap();
    wait_state(&server, &t, small, &["done"], Duration::from_secs(60)).await;
    let freed_after = cancelled_at.elapsed();
    assert_eq!(
        post(
            &server,
            &t,
            &format!("/v1/reconstructions/{small}/cancel"),
            ""
        )
        .await
        .status(),
        409
    );
    for id in [first, second] {
        let (_, r) = get(&server, &t, &format!("/v1/reconstructions/{id}")).await;
        assert_eq!(r["state"], "cancelled", "{r}");
        let (status, _) = get(&server, &t, &format!("/v1/reconstructions/{id}/dual.png")).await;
        assert_eq!(status, 409, "a cancelled reconstruction has no image");
    }
    let (_, r) = get(&server, &t, &format!("/v1/reconstructions/{second}")).await;
    assert!(
        r["started_unix_ms"].is_null(),
        "the queued job never started: {r}"
    );
    eprintln!("worker freed {freed_after:?} after the cancel");
}

fn create(
    id: &str,
    family: v1::PatternFamily,
    w: u32,
    h: u32,
    count: u64,
) -> v1::CreateSessionRequest {
    helmholtz_tests::bucket_session(id, family, w, h, count, &["a"])
}

fn chunk(id: &str, start: u64, values: &[f64]) -> v1::MeasurementChunk {
    helmholtz_tests::f64_chunk(id, start, 1, values)
}

fn refused<T: std::fmt::Debug>(r: Result<T, tonic::Status>, code: Code, mentions: &[&str]) {
    let status = r.expect_err("must be refused");
    assert_eq!(status.code(), code, "{status:?}");
    for m in mentions {
        assert!(
            status.message().contains(m),
            "{:?} should mention {m:?}",
            status.message()
        );
    }
}

#[tokio::test]
async fn caps_refuse_clearly_and_store_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let flags = [
        "--max-patterns",
        "1000",
        "--max-pixels",
        "256",
        "--max-sessions-per-lab",
        "2",
        "--max-chunk-bytes",
        "800",
        "--max-body-bytes",
        "100",
        "--max-message-bytes",
        "65536",
    ];
    let server = ServerProcess::start(dir.path(), 0, &flags).unwrap();
    let mut c = server.grpc().await.unwrap();
    use v1::PatternFamily::Bernoulli;
    refused(
        c.create_session(create("big", Bernoulli, 8, 8, 1001)).await,
        Code::InvalidArgument,
        &["patterns.count", "max_patterns"],
    );
    refused(
        c.create_session(create("wide", Bernoulli, 32, 32, 10))
            .await,
        Code::InvalidArgument,
        &["patterns.width", "max_pixels"],
    );
    let mut huge = create("huge", Bernoulli, 16, 16, 10);
    huge.metadata.insert("blob".into(), "x".repeat(4000));
    for i in 0..20 {
        huge.metadata.insert(format!("k{i}"), "y".repeat(4000));
    }
    // tonic's own refusal of an oversized message names the limit (--max-message-bytes).
    refused(
        c.create_session(huge).await,
        Code::OutOfRange,
        &["limit is: 65536 bytes"],
    );
    c.create_session(create("s1", Bernoulli, 16, 16, 1000))
        .await
        .unwrap();
    c.create_session(create("s2", Bernoulli, 16, 16, 1000))
        .await
        .unwrap();
    refused(
        c.create_session(create("s3", Bernoulli, 16, 16, 1000))
            .await,
        Code::ResourceExhausted,
        &["max_sessions_per_lab"],
    );
    // Repeating an existing declaration is not a new session; another lab has its own quota.
    c.create_session(create("s1", Bernoulli, 16, 16, 1000))
        .await
        .unwrap();
    let other = server
        .grpc_as(&server.url_with(&server.create_token("lab-2", "rig").unwrap()))
        .unwrap();
    other
        .clone()
        .create_session(create("o1", Bernoulli, 16, 16, 1000))
        .await
        .unwrap();
    // A chunk over max_chunk_bytes (101 rows x 8 bytes) stores nothing; 100 rows are fine.
    let rows: Vec<f64> = (0..101).map(|i| i as f64).collect();
    refused(
        c.upload_measurements(tokio_stream::iter(vec![chunk("s1", 0, &rows)]))
            .await,
        Code::ResourceExhausted,
        &["max_chunk_bytes"],
    );
    let status = c
        .get_upload_status(v1::SessionRef {
            session_id: "s1".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(status.committed_rows, 0);
    let ok = c
        .upload_measurements(tokio_stream::iter(vec![chunk("s1", 0, &rows[..100])]))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(ok.committed_rows, 100);
    // A REST body over max_body_bytes: 413 naming the limit, nothing queued.
    let body = format!(
        r#"{{"method": "gi", "params": {{}}, "pad": "{}"}}"#,
        "z".repeat(200)
    );
    let r = post(
        &server,
        &server.token,
        "/v1/sessions/s1/reconstructions",
        &body,
    )
    .await;
    assert_eq!(r.status(), 413);
    assert_eq!(r.headers()["content-type"], "application/problem+json");
    assert_eq!(r.json::<Value>().await.unwrap()["limit"], "max_body_bytes");
    let (_, listed) = get(&server, &server.token, "/v1/sessions/s1/reconstructions").await;
    assert_eq!(listed["reconstructions"].as_array().unwrap().len(), 0);
    let (_, sessions) = get(&server, &server.token, "/v1/sessions").await;
    let ids: Vec<&str> = sessions["sessions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["id"].as_str().unwrap())
        .collect();
    assert_eq!(ids.len(), 2, "only s1 and s2 were stored: {ids:?}");
}

#[tokio::test]
async fn each_token_has_a_request_rate() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(
        dir.path(),
        0,
        &["--rate-per-second", "1", "--rate-burst", "3"],
    )
    .unwrap();
    let t = &server.token;
    for _ in 0..3 {
        assert_eq!(get(&server, t, "/v1/sessions").await.0, 200);
    }
    let r = helmholtz_tests::http_client()
        .get(format!("{}/v1/sessions", server.address))
        .bearer_auth(t)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 429);
    assert_eq!(r.headers()["retry-after"], "1");
    assert_eq!(r.json::<Value>().await.unwrap()["limit"], "rate_per_second");
    let mut c = server.grpc().await.unwrap();
    refused(
        c.get_upload_status(v1::SessionRef {
            session_id: "x".into(),
        })
        .await,
        Code::ResourceExhausted,
        &["rate_per_second"],
    );
    // Another token has its own budget; health is not limited; the budget refills.
    let other = server.create_token("e2e", "reader").unwrap();
    assert_eq!(get(&server, &other, "/v1/sessions").await.0, 200);
    for _ in 0..5 {
        assert_eq!(
            helmholtz_tests::http_get(format!("{}/healthz", server.address))
                .await
                .unwrap()
                .status(),
            200
        );
    }
    tokio::time::sleep(Duration::from_millis(1100)).await;
    assert_eq!(get(&server, t, "/v1/sessions").await.0, 200);
}

fn sample(metrics: &str, name: &str, labels: &[&str]) -> Option<f64> {
    metrics
        .lines()
        .filter(|l| !l.starts_with('#'))
        .find(|l| {
            let series = l.rsplit_once(' ').map(|(s, _)| s).unwrap_or("");
            (series == name || series.starts_with(&format!("{name}{{")))
                && labels.iter().all(|lab| series.contains(lab))
        })
        .and_then(|l| l.rsplit_once(' ')?.1.parse().ok())
}

#[tokio::test]
async fn metrics_describe_uploads_jobs_and_latencies() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &["--metrics-listen", "127.0.0.1:0"]).unwrap();
    let metrics_url = server
        .metrics_url
        .clone()
        .expect("the first line names the metrics address");
    assert!(
        !metrics_url.contains(&server.address),
        "metrics are on their own listener"
    );
    let mut c = server.grpc().await.unwrap();
    c.create_session(create("m", v1::PatternFamily::Raster, 8, 8, 64))
        .await
        .unwrap();
    let rows: Vec<f64> = (0..64).map(|i| i as f64).collect();
    c.upload_measurements(tokio_stream::iter(vec![chunk("m", 0, &rows[..32])]))
        .await
        .unwrap();
    let mut bad = chunk("m", 32, &rows[32..]);
    bad.values_f64le[0] ^= 1;
    refused(
        c.upload_measurements(tokio_stream::iter(vec![bad])).await,
        Code::DataLoss,
        &[],
    );
    c.upload_measurements(tokio_stream::iter(vec![chunk("m", 32, &rows[32..])]))
        .await
        .unwrap();
    c.finish_session(v1::SessionRef {
        session_id: "m".into(),
    })
    .await
    .unwrap();
    let rec = helmholtz_client::request_reconstruction(
        &server.base_url,
        "m",
        "direct",
        &serde_json::json!({}),
    )
    .await
    .unwrap();
    helmholtz_client::wait_reconstruction(&server.base_url, rec.id, Duration::from_secs(60))
        .await
        .unwrap();
    // The main port serves /metrics only to a token with the metrics role (a lab's rig and
    // reader token is refused, as is no token); the separate listener needs no token.
    let (status, problem) = get(&server, &server.token, "/metrics").await;
    assert_eq!(status, 403, "{problem}");
    assert!(
        problem["detail"].as_str().unwrap().contains("metrics role"),
        "{problem}"
    );
    assert_eq!(get(&server, "", "/metrics").await.0, 401);
    let scraper = server.create_token("ops", "metrics").unwrap();
    let on_main_port = helmholtz_tests::http_client()
        .get(format!("{}/metrics", server.address))
        .bearer_auth(&scraper)
        .send()
        .await
        .unwrap();
    assert_eq!(on_main_port.status().as_u16(), 200);
    let main_text = on_main_port.text().await.unwrap();
    // A metrics token reads nothing of any lab.
    assert_eq!(get(&server, &scraper, "/v1/sessions").await.0, 403);
    let text = helmholtz_tests::http_get(&metrics_url)
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    for t in [&text, &main_text] {
        assert_eq!(
            sample(t, "helmholtz_upload_rows_total", &[]),
            Some(64.0),
            "{t}"
        );
    }
    let expect = |name: &str, labels: &[&str]| {
        sample(&text, name, labels).unwrap_or_else(|| panic!("no {name} {labels:?} in\n{text}"))
    };
    assert_eq!(expect("helmholtz_upload_rows_total", &[]), 64.0);
    assert_eq!(expect("helmholtz_upload_bytes_total", &[]), 512.0);
    assert_eq!(
        expect("helmholtz_upload_resumed_total", &[]),
        2.0,
        "the bad chunk's stream and the resuming one"
    );
    assert_eq!(expect("helmholtz_checksum_failures_total", &[]), 1.0);
    assert_eq!(expect("helmholtz_queue_depth", &["state=\"queued\""]), 0.0);
    assert_eq!(expect("helmholtz_queue_depth", &["state=\"running\""]), 0.0);
    assert_eq!(
        expect(
            "helmholtz_job_duration_seconds_count",
            &["method=\"direct\"", "outcome=\"done\""]
        ),
        1.0
    );
    assert!(
        expect(
            "helmholtz_http_request_duration_seconds_count",
            &["route=\"/v1/reconstructions/{id}\"", "status=\"200\""]
        ) >= 1.0
    );
    assert_eq!(
        expect(
            "helmholtz_grpc_request_duration_seconds_count",
            &[
                "rpc=\"/helmholtz.v1.Acquisition/CreateSession\"",
                "code=\"0\""
            ]
        ),
        1.0
    );
    assert_eq!(
        expect(
            "helmholtz_grpc_request_duration_seconds_count",
            &[
                "rpc=\"/helmholtz.v1.Acquisition/UploadMeasurements\"",
                "code=\"15\""
            ]
        ),
        1.0,
        "the DATA_LOSS upload is counted under its status code"
    );
}

#[tokio::test]
async fn sigterm_finishes_uploads_in_flight_and_gives_running_jobs_back() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = ServerProcess::start(dir.path(), 0, &["--workers", "1"]).unwrap();
    let port = server.port;
    let t = server.token.clone();
    acquire(
        &server.base_url,
        "long",
        r#"{"family":"speckle","width":64,"height":64,"count":120000,"seed":9}"#,
    )
    .await;
    let r = post(
        &server,
        &t,
        "/v1/sessions/long/reconstructions",
        r#"{"method": "gi"}"#,
    )
    .await;
    let job = r.json::<Value>().await.unwrap()["id"].as_i64().unwrap();
    wait_state(&server, &t, job, &["running"], Duration::from_secs(60)).await;

    // An upload stream is open and has one chunk committed when SIGTERM arrives.
    let mut c = server.grpc().await.unwrap();
    c.create_session(create("up", v1::PatternFamily::Bernoulli, 8, 8, 200))
        .await
        .unwrap();
    let rows: Vec<f64> = (0..200).map(|i| i as f64 * 0.5).collect();
    let upload = OpenUpload::start(&c, None, chunk("up", 0, &rows[..100]), 100).await;
    server.signal_term().unwrap();
    tokio::time::sleep(Duration::from_millis(200)).await;
    // The stream in flight is still served to its end: its next chunk is committed too.
    assert!(upload.send(chunk("up", 100, &rows[100..])).await);
    let done = upload
        .finish()
        .await
        .expect("the upload in flight completes");
    assert_eq!(done.committed_rows, 200);
    let status = tokio::task::spawn_blocking(move || {
        let s = server.terminate();
        (server, s)
    })
    .await
    .unwrap();
    let (mut server, exit) = status;
    assert!(exit.unwrap().success(), "clean exit after SIGTERM");
    server.kill();

    // Restarted on the same data: every acknowledged row is there, and the job that was
    // running was given back without spending an attempt, then runs to completion.
    let server = ServerProcess::start(dir.path(), port, &["--workers", "1"]).unwrap();
    let mut c = server.grpc().await.unwrap();
    let status = c
        .get_upload_status(v1::SessionRef {
            session_id: "up".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(status.committed_rows, 200);
    let bytes = helmholtz_tests::http_get(server.url("/v1/sessions/up/measurements.npy"))
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    assert_eq!(helmholtz_tests::parse_npy(&bytes).unwrap().1, rows);
    let r = wait_state(&server, &t, job, &["done"], Duration::from_secs(180)).await;
    assert_eq!(
        r["attempt"], 1,
        "the interrupted run was given back, not counted: {r}"
    );
}

/// `GET /` names every method a reconstruction may request (the list the parser accepts), the
/// open gRPC services, and every REST family of routes.
#[tokio::test]
async fn the_index_names_every_method_and_route() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let index: Value = helmholtz_tests::http_get(server.url("/"))
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let routes = index["routes"].to_string();
    let methods = "gi|dgi|ngi|direct|zero_filled|levels|cs|tv|lsq|auto|transport";
    assert!(routes.contains(methods), "{routes}");
    for route in [
        // The session's files are one route, GET /v1/sessions/{id}/{file}, naming its files.
        "/v1/sessions/{id}/{file}",
        "measurements.npy",
        "/v1/reconstructions/{id}/relight",
        "/v1/reconstructions/{id}/primal",
        "/v1/tokens",
        "/healthz",
    ] {
        assert!(routes.contains(route), "{route} missing: {routes}");
    }
    assert!(
        index["grpc"]
            .as_str()
            .unwrap()
            .contains("grpc.reflection.v1"),
        "{index}"
    );
}
