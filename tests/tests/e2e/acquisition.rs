//! The gRPC acquisition contract against the real server: idempotent sessions, resumable
//! uploads, and bad input refused with a clear status and nothing stored.

use helmholtz_client::auth::Grpc;
use helmholtz_proto::v1;
use helmholtz_proto::wire::encode_values;
use helmholtz_tests::{ServerProcess, parse_npy};
use tonic::Code;

fn spec(family: v1::PatternFamily, w: u32, h: u32, count: u64) -> v1::PatternSpec {
    v1::PatternSpec {
        family: family as i32,
        width: w,
        height: h,
        count,
        seed: 7,
        params: None,
    }
}

fn create(id: &str, spec: v1::PatternSpec, channels: &[&str]) -> v1::CreateSessionRequest {
    v1::CreateSessionRequest {
        session_id: id.into(),
        rig: "bench-1".into(),
        patterns: Some(spec),
        detector: Some(v1::DetectorLayout {
            channels: channels.iter().map(|c| c.to_string()).collect(),
            ..Default::default()
        }),
        metadata: [("operator".to_string(), "e2e".to_string())].into(),
        ground_truth: None,
    }
}

fn chunk(id: &str, start: u64, channels: u32, values: &[f64]) -> v1::MeasurementChunk {
    let (bytes, crc) = encode_values(values);
    v1::MeasurementChunk {
        session_id: id.into(),
        start_row: start,
        channels,
        values_f64le: bytes,
        crc32c: crc,
        ..Default::default()
    }
}

async fn send(
    client: &mut Grpc,
    chunks: Vec<v1::MeasurementChunk>,
) -> Result<v1::UploadResponse, tonic::Status> {
    client
        .upload_measurements(tokio_stream::iter(chunks))
        .await
        .map(|r| r.into_inner())
}

async fn committed(client: &mut Grpc, id: &str) -> u64 {
    client
        .get_upload_status(v1::SessionRef {
            session_id: id.into(),
        })
        .await
        .unwrap()
        .into_inner()
        .committed_rows
}

fn rows(start: u64, n: u64, channels: usize) -> Vec<f64> {
    (start..start + n)
        .flat_map(|r| (0..channels).map(move |c| r as f64 * 10.0 + c as f64 + 0.25))
        .collect()
}

fn assert_status(result: Result<impl std::fmt::Debug, tonic::Status>, code: Code, mentions: &str) {
    let status = result.expect_err("must be refused");
    assert_eq!(status.code(), code, "{status:?}");
    assert!(
        status.message().contains(mentions),
        "message {:?} should name {mentions:?}",
        status.message()
    );
}

#[tokio::test]
async fn absurd_specs_are_refused_and_create_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    use v1::PatternFamily::*;
    let cases = [
        (
            create("a", spec(Bernoulli, 0, 8, 10), &["b"]),
            "patterns.width",
        ),
        (
            create("a", spec(Bernoulli, 8, 8, 1_000_000_000), &["b"]),
            "patterns.count",
        ),
        (
            create("a", spec(Bernoulli, 8, 8, 0), &["b"]),
            "patterns.count",
        ),
        (
            create("a", spec(Unspecified, 8, 8, 10), &["b"]),
            "patterns.family",
        ),
        (
            create("a", spec(Hadamard, 12, 8, 10), &["b"]),
            "patterns.width",
        ),
        (
            create("a", spec(Raster, 5000, 5000, 10), &["b"]),
            "patterns.width",
        ),
        (
            create("a", spec(Bernoulli, 8, 8, 10), &[]),
            "detector.channels",
        ),
        (
            create("a", spec(Bernoulli, 8, 8, 10), &["x", "x"]),
            "detector.channels[1]",
        ),
        (
            create("bad id!", spec(Bernoulli, 8, 8, 10), &["b"]),
            "session_id",
        ),
        (create("", spec(Bernoulli, 8, 8, 10), &["b"]), "session_id"),
    ];
    for (req, field) in cases {
        assert_status(c.create_session(req).await, Code::InvalidArgument, field);
    }
    let mut no_patterns = create("a", spec(Bernoulli, 8, 8, 10), &["b"]);
    no_patterns.patterns = None;
    assert_status(
        c.create_session(no_patterns).await,
        Code::InvalidArgument,
        "patterns",
    );
    let mut gt = create("a", spec(Bernoulli, 8, 8, 10), &["b"]);
    gt.ground_truth = Some(v1::GroundTruth {
        width: 8,
        height: 8,
        transport: vec![f32::NAN; 64],
    });
    assert_status(
        c.create_session(gt).await,
        Code::InvalidArgument,
        "ground_truth.transport",
    );
    let listed: serde_json::Value = helmholtz_tests::http_get(server.url("/v1/sessions"))
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        listed["sessions"].as_array().unwrap().len(),
        0,
        "nothing may be stored: {listed}"
    );
}

#[tokio::test]
async fn sessions_are_idempotent_on_their_id() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    let req = create(
        "s1",
        spec(v1::PatternFamily::Bernoulli, 8, 8, 100),
        &["bucket"],
    );
    let first = c.create_session(req.clone()).await.unwrap().into_inner();
    assert!(first.created);
    let again = c.create_session(req.clone()).await.unwrap().into_inner();
    assert!(!again.created);
    assert_eq!(first.session, again.session);
    let mut different = req.clone();
    different.patterns.as_mut().unwrap().seed = 8;
    assert_status(
        c.create_session(different).await,
        Code::AlreadyExists,
        "patterns",
    );
    let session: serde_json::Value = helmholtz_tests::http_get(server.url("/v1/sessions/s1"))
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(session["patterns"]["seed"], 7);
    assert_eq!(session["patterns"]["fill"], 0.5);
    assert_eq!(session["expected_rows"], 100);
}

#[tokio::test]
async fn bad_chunks_are_refused_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    c.create_session(create(
        "s",
        spec(v1::PatternFamily::Bernoulli, 8, 8, 100),
        &["a", "b"],
    ))
    .await
    .unwrap();
    let ok = send(
        &mut c,
        vec![
            chunk("s", 0, 2, &rows(0, 6, 2)),
            chunk("s", 6, 2, &rows(6, 4, 2)),
        ],
    )
    .await
    .unwrap();
    assert_eq!(
        (ok.committed_rows, ok.rows_written, ok.rows_skipped),
        (10, 10, 0)
    );

    let mut nan = rows(10, 5, 2);
    nan[3] = f64::NAN;
    assert_status(
        send(&mut c, vec![chunk("s", 10, 2, &nan)]).await,
        Code::InvalidArgument,
        "values_f64le",
    );
    let mut inf = rows(10, 5, 2);
    inf[9] = f64::NEG_INFINITY;
    assert_status(
        send(&mut c, vec![chunk("s", 10, 2, &inf)]).await,
        Code::InvalidArgument,
        "not finite",
    );
    assert_status(
        send(&mut c, vec![chunk("s", 10, 1, &rows(10, 5, 1))]).await,
        Code::InvalidArgument,
        "channels",
    );
    assert_status(
        send(&mut c, vec![chunk("nope", 0, 2, &rows(0, 5, 2))]).await,
        Code::NotFound,
        "nope",
    );
    assert_status(
        send(&mut c, vec![chunk("s", 11, 2, &rows(11, 5, 2))]).await,
        Code::OutOfRange,
        "gap",
    );
    let mut corrupt = chunk("s", 10, 2, &rows(10, 5, 2));
    corrupt.values_f64le[3] ^= 0x40;
    assert_status(send(&mut c, vec![corrupt]).await, Code::DataLoss, "crc32c");
    assert_status(
        send(&mut c, vec![chunk("s", 10, 2, &rows(10, 91, 2))]).await,
        Code::OutOfRange,
        "100",
    );
    let mut ragged = chunk("s", 10, 2, &rows(10, 5, 2));
    ragged.values_f64le.truncate(72);
    ragged.crc32c = crc32c::crc32c(&ragged.values_f64le);
    assert_status(
        send(&mut c, vec![ragged]).await,
        Code::InvalidArgument,
        "values_f64le",
    );
    assert_status(
        send(&mut c, vec![chunk("s", 10, 2, &[])]).await,
        Code::InvalidArgument,
        "no rows",
    );
    // A bad chunk after a good one: the good one is durable, the bad one stores nothing.
    let mut bad_second = rows(13, 2, 2);
    bad_second[0] = f64::NAN;
    assert_status(
        send(
            &mut c,
            vec![
                chunk("s", 10, 2, &rows(10, 3, 2)),
                chunk("s", 13, 2, &bad_second),
            ],
        )
        .await,
        Code::InvalidArgument,
        "values_f64le",
    );
    assert_eq!(committed(&mut c, "s").await, 13);

    assert_status(
        c.finish_session(v1::SessionRef {
            session_id: "s".into(),
        })
        .await,
        Code::FailedPrecondition,
        "13 of 100",
    );
    let bytes = helmholtz_tests::http_get(server.url("/v1/sessions/s/measurements.npy"))
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let (shape, stored) = parse_npy(&bytes).unwrap();
    assert_eq!(shape, vec![13, 2]);
    assert_eq!(
        stored,
        rows(0, 13, 2),
        "stored rows must equal the accepted rows exactly"
    );

    // Overlap is skipped, then the rest completes and the session finishes (twice, harmlessly).
    let resumed = send(&mut c, vec![chunk("s", 5, 2, &rows(5, 95, 2))])
        .await
        .unwrap();
    assert_eq!(
        (
            resumed.committed_rows,
            resumed.rows_written,
            resumed.rows_skipped
        ),
        (100, 87, 8)
    );
    let done = c
        .finish_session(v1::SessionRef {
            session_id: "s".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(done.state, v1::SessionState::Finished as i32);
    let again = c
        .finish_session(v1::SessionRef {
            session_id: "s".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(done, again);
    let bytes = helmholtz_tests::http_get(server.url("/v1/sessions/s/measurements.npy"))
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    assert_eq!(parse_npy(&bytes).unwrap().1, rows(0, 100, 2));
}

#[tokio::test]
async fn a_second_concurrent_writer_is_aborted() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    c.create_session(create(
        "w",
        spec(v1::PatternFamily::Bernoulli, 8, 8, 100),
        &["a"],
    ))
    .await
    .unwrap();
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let mut first_client = c.clone();
    let first = tokio::spawn(async move {
        first_client
            .upload_measurements(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
    });
    tx.send(chunk("w", 0, 1, &rows(0, 10, 1))).await.unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
    while committed(&mut c, "w").await < 10 {
        assert!(
            std::time::Instant::now() < deadline,
            "first writer's chunk never committed"
        );
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert_status(
        send(&mut c, vec![chunk("w", 10, 1, &rows(10, 5, 1))]).await,
        Code::Aborted,
        "another upload",
    );
    tx.send(chunk("w", 10, 1, &rows(10, 5, 1))).await.unwrap();
    drop(tx);
    let first = first.await.unwrap().unwrap().into_inner();
    assert_eq!(first.committed_rows, 15);
}

#[tokio::test]
async fn reconstruction_requests_are_validated() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    c.create_session(create(
        "r",
        spec(v1::PatternFamily::Bernoulli, 8, 8, 100),
        &["a"],
    ))
    .await
    .unwrap();
    let req = |method: &str, params: &str| v1::ReconstructionRequest {
        session_id: "r".into(),
        method: method.into(),
        params_json: params.into(),
    };
    assert_status(
        c.request_reconstruction(req("gi", "")).await,
        Code::FailedPrecondition,
        "no committed rows",
    );
    send(&mut c, vec![chunk("r", 0, 1, &rows(0, 50, 1))])
        .await
        .unwrap();
    assert_status(
        c.request_reconstruction(req("magic", "")).await,
        Code::InvalidArgument,
        "method",
    );
    assert_status(
        c.request_reconstruction(req("gi", "{not json")).await,
        Code::InvalidArgument,
        "params_json",
    );
    assert_status(
        c.request_reconstruction(req("gi", r#"{"lambda": 2}"#))
            .await,
        Code::InvalidArgument,
        "params.lambda",
    );
    assert_status(
        c.request_reconstruction(req("direct", "")).await,
        Code::FailedPrecondition,
        "bernoulli",
    );
    let http = helmholtz_tests::http_client();
    let bad = http
        .post(server.url("/v1/sessions/r/reconstructions"))
        .body("{\"method\": 3}")
        .send()
        .await
        .unwrap();
    assert_eq!(bad.status(), 400);
    assert_eq!(bad.headers()["content-type"], "application/problem+json");
    let problem: serde_json::Value = bad.json().await.unwrap();
    assert_eq!(problem["field"], "method");
    let missing = http
        .post(server.url("/v1/sessions/zz/reconstructions"))
        .body(r#"{"method":"gi"}"#)
        .send()
        .await
        .unwrap();
    assert_eq!(missing.status(), 404);
    let listed: serde_json::Value = http
        .get(server.url("/v1/sessions/r/reconstructions"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        listed["reconstructions"].as_array().unwrap().len(),
        0,
        "refused requests queue nothing"
    );
    // A good request on a partial session uses the rows committed so far.
    let queued = c
        .request_reconstruction(req("gi", "{}"))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(queued.rows, 50);
}

#[tokio::test]
async fn health_is_served_on_grpc_and_http() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let channel = tonic::transport::Channel::from_shared(server.address.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    let reply = health
        .check(tonic_health::pb::HealthCheckRequest {
            service: "helmholtz.v1.Acquisition".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        reply.status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
    let http: serde_json::Value = helmholtz_tests::http_get(format!("{}/healthz", server.address))
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(http["status"], "serving");
}
