//! The network edge of the real server binary: slow or stalled clients are cut after the header
//! and body timeouts, the connection cap makes extra connections wait, SIGTERM ends within the
//! shutdown deadline even with an idle upload stream open, every response says nosniff, images
//! are privately cacheable, CORS is off unless configured, and the data directory is private.

use std::time::{Duration, Instant};

use helmholtz_proto::v1;
use helmholtz_tests::{OpenUpload, ServerProcess};
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tonic::Code;

fn create(id: &str, count: u64) -> v1::CreateSessionRequest {
    helmholtz_tests::bucket_session(id, v1::PatternFamily::Bernoulli, 8, 8, count, &["a"])
}

fn chunk(id: &str, start: u64, values: &[f64]) -> v1::MeasurementChunk {
    helmholtz_tests::f64_chunk(id, start, 1, values)
}

/// Reads until the server closes the socket (EOF or reset); returns what it sent and when.
async fn until_closed(mut s: TcpStream, limit: Duration) -> Result<(Vec<u8>, Instant), String> {
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        match tokio::time::timeout_at(deadline, s.read(&mut buf)).await {
            Err(_) => {
                return Err(format!(
                    "still open after {limit:?} (got {:?})",
                    String::from_utf8_lossy(&got)
                ));
            }
            Ok(Ok(0)) | Ok(Err(_)) => return Ok((got, Instant::now())),
            Ok(Ok(n)) => got.extend_from_slice(&buf[..n]),
        }
    }
}

async fn healthz(address: &str) -> reqwest::Response {
    helmholtz_tests::http_client()
        .get(format!("{address}/healthz"))
        .timeout(Duration::from_secs(10))
        .send()
        .await
        .expect("a normal request is served")
}

#[tokio::test]
async fn slow_and_silent_connections_are_closed_after_the_header_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &["--header-timeout-secs", "2"]).unwrap();
    let addr = format!("127.0.0.1:{}", server.port);
    // 200 connections with half a request line, 20 with half an HTTP/2 preface, 20 silent.
    let mut sockets = Vec::new();
    let opened = Instant::now();
    for i in 0..240 {
        let mut s = TcpStream::connect(&addr).await.unwrap();
        match i {
            0..200 => s.write_all(b"GET /v1/sessions HT").await.unwrap(),
            200..220 => s.write_all(b"PRI * HTTP/2.0\r\n").await.unwrap(),
            _ => {}
        }
        sockets.push(s);
    }
    // While they are open, a normal request is served at once.
    let r = healthz(&server.address).await;
    assert_eq!(r.status(), 200);
    let readers: Vec<_> = sockets
        .into_iter()
        .map(|s| tokio::spawn(until_closed(s, Duration::from_secs(20))))
        .collect();
    let mut latest = Duration::ZERO;
    for (i, r) in readers.into_iter().enumerate() {
        let (got, closed_at) = r
            .await
            .unwrap()
            .unwrap_or_else(|e| panic!("connection {i}: {e}"));
        assert!(
            got.is_empty() || got.starts_with(b"HTTP/1.1 408") || got.starts_with(b"HTTP/1.1 400"),
            "connection {i} got {:?}",
            String::from_utf8_lossy(&got)
        );
        let after = closed_at - opened;
        // Not before the timeout (with slack for the clocks), and not long after it.
        assert!(
            after >= Duration::from_millis(1500),
            "connection {i} closed after {after:?}, before the 2 s header timeout"
        );
        latest = latest.max(after);
    }
    assert!(
        latest < Duration::from_secs(15),
        "the last slow connection closed after {latest:?}"
    );
    eprintln!("240 slow connections closed; the last {latest:?} after opening");
    // And the server still serves.
    assert_eq!(healthz(&server.address).await.status(), 200);
}

#[tokio::test]
async fn a_rest_body_that_stops_arriving_fails_with_408_after_the_body_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &["--body-timeout-secs", "2"]).unwrap();
    let mut s = TcpStream::connect(format!("127.0.0.1:{}", server.port))
        .await
        .unwrap();
    let admin = server.create_token("e2e", "admin").unwrap();
    let head = format!(
        "POST /v1/tokens HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {admin}\r\n\
         Content-Type: application/json\r\nContent-Length: 1000000000\r\n\r\n{{\"lab\""
    );
    let sent = Instant::now();
    s.write_all(head.as_bytes()).await.unwrap();
    let (got, closed_at) = until_closed(s, Duration::from_secs(20)).await.unwrap();
    let text = String::from_utf8_lossy(&got);
    assert!(text.starts_with("HTTP/1.1 408"), "{text}");
    assert!(text.contains("application/problem+json"), "{text}");
    assert!(text.contains("body timeout"), "{text}");
    let after = closed_at - sent;
    assert!(
        after >= Duration::from_millis(1500) && after < Duration::from_secs(15),
        "cut after {after:?} (body timeout 2 s)"
    );
}

#[tokio::test]
async fn connections_beyond_the_cap_wait_until_one_closes() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(
        dir.path(),
        0,
        &["--max-connections", "3", "--header-timeout-secs", "60"],
    )
    .unwrap();
    let addr = format!("127.0.0.1:{}", server.port);
    let mut held = Vec::new();
    for _ in 0..3 {
        held.push(TcpStream::connect(&addr).await.unwrap());
    }
    // Let the server accept all three (each takes a permit).
    tokio::time::sleep(Duration::from_millis(300)).await;
    let address = server.address.clone();
    let waiting = tokio::spawn(async move { healthz(&address).await.status() });
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!(
        !waiting.is_finished(),
        "a fourth connection was served while 3 of --max-connections 3 were open"
    );
    drop(held.pop());
    let status = tokio::time::timeout(Duration::from_secs(10), waiting)
        .await
        .expect("served once a connection closed")
        .unwrap();
    assert_eq!(status, 200);
}

#[tokio::test]
async fn sigterm_cuts_an_idle_upload_stream_at_the_deadline_and_keeps_committed_rows() {
    let dir = tempfile::tempdir().unwrap();
    let mut server =
        ServerProcess::start(dir.path(), 0, &["--shutdown-deadline-secs", "2"]).unwrap();
    let port = server.port;
    let mut c = server.grpc().await.unwrap();
    c.create_session(create("idle", 200)).await.unwrap();
    let rows: Vec<f64> = (0..200).map(|i| i as f64 * 0.25).collect();
    let upload = OpenUpload::start(&c, None, chunk("idle", 0, &rows[..50]), 50).await;
    // A raw connection with half an HTTP/1 request is open too.
    let mut raw = TcpStream::connect(format!("127.0.0.1:{port}"))
        .await
        .unwrap();
    raw.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        .await
        .unwrap();
    // The stream now idles (tx kept open): SIGTERM must still end the server.
    let sent = Instant::now();
    let (server, exit) = tokio::task::spawn_blocking(move || {
        let exit = server.terminate();
        (server, exit)
    })
    .await
    .unwrap();
    let exit = exit.expect("exited after SIGTERM");
    let took = sent.elapsed();
    assert!(exit.success(), "clean exit: {exit:?}");
    assert!(
        took >= Duration::from_millis(1500),
        "exited after {took:?}: before the 2 s deadline, so the idle stream was not waited for"
    );
    assert!(
        took < Duration::from_secs(12),
        "exited {took:?} after SIGTERM with a 2 s shutdown deadline"
    );
    eprintln!("exited {took:?} after SIGTERM (deadline 2 s)");
    let result = tokio::time::timeout(Duration::from_secs(10), upload.finish())
        .await
        .expect("the cut stream ends on the client too");
    assert!(
        result.is_err(),
        "an idle stream cut at the deadline: {result:?}"
    );
    drop(server);

    // Restarted on the same data: the committed rows are there.
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    let status = c
        .get_upload_status(v1::SessionRef {
            session_id: "idle".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(status.committed_rows, 50);
    let r = helmholtz_tests::http_client()
        .get(server.url("/v1/sessions/idle/measurements.npy"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let (shape, values) = helmholtz_tests::parse_npy(&r.bytes().await.unwrap()).unwrap();
    assert_eq!(shape[0], 50, "{shape:?}");
    assert_eq!(values, rows[..50].to_vec());
}

#[tokio::test]
async fn dot_session_ids_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    for id in [".", ".."] {
        let status = c.create_session(create(id, 16)).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
        assert!(status.message().contains("session_id"), "{status:?}");
    }
    // Nothing was stored; a normal id still works.
    let r = helmholtz_tests::http_client()
        .get(server.url("/v1/sessions"))
        .send()
        .await
        .unwrap();
    let listed: Value = r.json().await.unwrap();
    assert_eq!(listed["sessions"].as_array().unwrap().len(), 0, "{listed}");
    c.create_session(create("ok.1", 16)).await.unwrap();
    // The client library refuses them before calling.
    let spec: helmholtz_client::PatternSpec =
        serde_json::from_str(r#"{"family":"bernoulli","width":8,"height":8,"count":16}"#).unwrap();
    let e = helmholtz_client::create_session(
        &server.base_url,
        &helmholtz_client::NewSession::new("..", spec, vec!["a".into()]),
    )
    .await
    .unwrap_err();
    assert!(e.to_string().contains("session id"), "{e:#}");
}

#[tokio::test]
async fn a_raster_past_one_scan_is_refused_unless_it_declares_its_repeats() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    let raster = |id: &str, block: u32, scans: u32, count: u64| {
        let mut req =
            helmholtz_tests::bucket_session(id, v1::PatternFamily::Raster, 8, 8, count, &["a"]);
        req.patterns.as_mut().unwrap().params =
            Some(v1::pattern_spec::Params::Raster(v1::RasterParams {
                block,
                scans,
            }));
        req
    };
    // More patterns than pixels (64 blocks of 1 pixel), and more than the 16 blocks of 2x2.
    for (id, block, count) in [("px", 1, 65), ("px2", 1, 1_000_000), ("blk", 2, 17)] {
        let status = c
            .create_session(raster(id, block, 0, count))
            .await
            .unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
        assert!(
            status.message().contains("count") && status.message().contains("scans"),
            "{status:?}"
        );
    }
    // Declared repeats are accepted up to scans x blocks, and the canonical spec keeps them.
    let status = c
        .create_session(raster("over", 1, 2, 129))
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    let created = c
        .create_session(raster("twice", 1, 2, 128))
        .await
        .unwrap()
        .into_inner();
    let spec = created.session.unwrap().patterns.unwrap();
    assert_eq!(
        spec.params,
        Some(v1::pattern_spec::Params::Raster(v1::RasterParams {
            block: 1,
            scans: 2
        }))
    );
    // Only that one session exists.
    let listed: Value = helmholtz_tests::http_client()
        .get(server.url("/v1/sessions"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let ids = helmholtz_tests::session_ids(&listed);
    assert_eq!(ids, ["twice"], "{listed}");
    // The CLI refuses it before calling, saying what to declare.
    let out = std::process::Command::new(helmholtz_tests::binary("helmholtz"))
        .args(["patterns", "--out"])
        .arg(dir.path().join("frames"))
        .args([
            "--spec-json",
            r#"{"family":"raster","width":8,"height":8,"count":65}"#,
        ])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("count") && stderr.contains(r#""scans": 2"#),
        "{stderr}"
    );
}

#[cfg(unix)]
#[test]
fn the_data_directory_is_0700_and_the_database_0600_whatever_the_umask() {
    use std::os::unix::fs::PermissionsExt;
    let mode = |p: &std::path::Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
    let dir = tempfile::tempdir().unwrap();
    // A fresh directory, created by the real binary under umask 000.
    let fresh = dir.path().join("fresh").join("data");
    let out = std::process::Command::new("sh")
        .arg("-c")
        .arg(r#"umask 000 && exec "$0" token create --lab l --role admin --data-dir "$1""#)
        .arg(helmholtz_tests::binary("helmholtz-server"))
        .arg(&fresh)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(mode(&fresh), 0o700, "fresh data directory");
    let db = fresh.join("helmholtz.sqlite");
    let mut checked = 0;
    for suffix in ["", "-wal", "-shm"] {
        let f = std::path::PathBuf::from(format!("{}{suffix}", db.display()));
        if f.exists() {
            assert_eq!(mode(&f), 0o600, "{}", f.display());
            checked += 1;
        }
    }
    assert!(checked >= 1, "no database file in {}", fresh.display());

    // An existing world-readable directory and database are narrowed when the server opens them.
    let wide = dir.path().join("wide");
    std::fs::create_dir_all(&wide).unwrap();
    std::fs::set_permissions(&wide, std::fs::Permissions::from_mode(0o755)).unwrap();
    let server = ServerProcess::start_sqlite(&wide, 0, &[]).unwrap();
    drop(server);
    std::fs::set_permissions(&wide, std::fs::Permissions::from_mode(0o755)).unwrap();
    std::fs::set_permissions(
        wide.join("helmholtz.sqlite"),
        std::fs::Permissions::from_mode(0o644),
    )
    .unwrap();
    let _server = ServerProcess::start_sqlite(&wide, 0, &[]).unwrap();
    assert_eq!(mode(&wide), 0o700);
    for suffix in ["", "-wal", "-shm"] {
        let f = std::path::PathBuf::from(format!("{}/helmholtz.sqlite{suffix}", wide.display()));
        if f.exists() {
            assert_eq!(mode(&f), 0o600, "{}", f.display());
        }
    }
}

/// A finished `dgi` reconstruction of a simulated 8x8 session; returns its id.
async fn reconstructed(server: &ServerProcess, id: &str) -> i64 {
    use helmholtz_sim::Target;
    use helmholtz_sim::simulate::{self, NoiseModel};
    let spec: helmholtz_client::PatternSpec = serde_json::from_str(
        r#"{"family":"bernoulli","width":8,"height":8,"count":2000,"seed":3}"#,
    )
    .unwrap();
    let transport = Target::builtin("double-slit", 8, 8).unwrap().transport(1.0);
    let sim = simulate::simulate(&spec, &[&transport], &NoiseModel::default(), None);
    let s = server.base_url.as_str();
    helmholtz_client::create_session(
        s,
        &helmholtz_client::NewSession::new(id, spec, vec!["bucket".into()]),
    )
    .await
    .unwrap();
    helmholtz_client::upload(s, id, 1, &sim.values, &Default::default())
        .await
        .unwrap();
    helmholtz_client::finish_session(s, id).await.unwrap();
    let rec = helmholtz_client::request_reconstruction(s, id, "dgi", &serde_json::json!({}))
        .await
        .unwrap();
    let rec = helmholtz_client::wait_reconstruction(s, rec.id, Duration::from_secs(60))
        .await
        .unwrap();
    assert!(rec.is_done(), "{rec:?}");
    rec.id
}

#[tokio::test]
async fn images_are_private_every_response_is_nosniff_and_cors_is_off_by_default() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let id = reconstructed(&server, "hdr").await;
    let http = helmholtz_tests::http_client();
    let image = http
        .get(server.url(&format!("/v1/reconstructions/{id}/dual.png")))
        .header("origin", "https://viewer.example")
        .send()
        .await
        .unwrap();
    assert_eq!(image.status(), 200);
    let h = image.headers().clone();
    let cache = h["cache-control"].to_str().unwrap();
    assert!(cache.starts_with("private"), "{cache}");
    assert!(!cache.contains("public"), "{cache}");
    assert_eq!(h["x-content-type-options"], "nosniff");
    assert!(
        h.get("access-control-allow-origin").is_none(),
        "CORS headers without --cors-origin: {h:?}"
    );
    // Strong ETag and 304 kept.
    let etag = h["etag"].to_str().unwrap().to_string();
    assert!(etag.starts_with('"'), "strong ETag {etag}");
    let again = http
        .get(server.url(&format!("/v1/reconstructions/{id}/dual.png")))
        .header("if-none-match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(again.status(), 304);
    assert_eq!(again.headers()["x-content-type-options"], "nosniff");
    // Relit images too.
    let relit = http
        .post(server.url(&format!("/v1/reconstructions/{id}/relight")))
        .json(&serde_json::json!({"light": {"weights": {"bucket": 2.0}}}))
        .send()
        .await
        .unwrap();
    assert_eq!(relit.status(), 200);
    let cache = relit.headers()["cache-control"].to_str().unwrap();
    assert!(cache.starts_with("private"), "{cache}");
    assert_eq!(relit.headers()["x-content-type-options"], "nosniff");
    // Errors, health checks and unauthenticated answers say nosniff too.
    for (path, token) in [
        ("/healthz", false),
        ("/v1/sessions", false),
        ("/v1/nowhere", true),
    ] {
        let mut r = http.get(format!("{}{path}", server.address));
        if token {
            r = r.bearer_auth(&server.token);
        }
        let r = r.send().await.unwrap();
        assert_eq!(r.headers()["x-content-type-options"], "nosniff", "{path}");
    }
    // A preflight gets no CORS answer either.
    let pre = http
        .request(
            reqwest::Method::OPTIONS,
            format!("{}/v1/sessions", server.address),
        )
        .header("origin", "https://viewer.example")
        .header("access-control-request-method", "GET")
        .send()
        .await
        .unwrap();
    assert!(pre.headers().get("access-control-allow-origin").is_none());
}

#[tokio::test]
async fn cors_allows_exactly_the_configured_origins() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(
        dir.path(),
        0,
        &[
            "--cors-origin",
            "https://viewer.example",
            "--cors-origin",
            "http://localhost:5173",
        ],
    )
    .unwrap();
    let http = helmholtz_tests::http_client();
    for origin in ["https://viewer.example", "http://localhost:5173"] {
        let r = http
            .get(format!("{}/v1/sessions", server.address))
            .bearer_auth(&server.token)
            .header("origin", origin)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        assert_eq!(r.headers()["access-control-allow-origin"], origin);
        let pre = http
            .request(
                reqwest::Method::OPTIONS,
                format!("{}/v1/sessions", server.address),
            )
            .header("origin", origin)
            .header("access-control-request-method", "GET")
            .header("access-control-request-headers", "authorization")
            .send()
            .await
            .unwrap();
        assert!(pre.status().is_success(), "{}", pre.status());
        assert_eq!(pre.headers()["access-control-allow-origin"], origin);
        let allowed = pre.headers()["access-control-allow-headers"]
            .to_str()
            .unwrap()
            .to_ascii_lowercase();
        assert!(allowed.contains("authorization"), "{allowed}");
    }
    let other = http
        .get(format!("{}/v1/sessions", server.address))
        .bearer_auth(&server.token)
        .header("origin", "https://evil.example")
        .send()
        .await
        .unwrap();
    assert!(
        other.headers().get("access-control-allow-origin").is_none(),
        "{:?}",
        other.headers()
    );
    // A malformed origin is refused at start-up, naming the flag.
    let out = std::process::Command::new(helmholtz_tests::binary("helmholtz-server"))
        .args([
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--cors-origin",
            "viewer.example/x",
        ])
        .arg("--data-dir")
        .arg(dir.path().join("other"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--cors-origin"), "{err}");
}

#[tokio::test]
async fn relight_weights_whose_result_overflows_f32_are_refused_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let id = reconstructed(&server, "big").await;
    let http = helmholtz_tests::http_client();
    let relight = |w: f64| {
        http.post(server.url(&format!("/v1/reconstructions/{id}/relight?format=npy")))
            .json(&serde_json::json!({"light": {"weights": {"bucket": w}}}))
            .send()
    };
    for w in [1e300, -1e300, 1e39] {
        let r = relight(w).await.unwrap();
        assert_eq!(r.status(), 400, "weight {w}");
        assert_eq!(
            r.headers()["content-type"],
            "application/problem+json",
            "weight {w}"
        );
        let p: Value = r.json().await.unwrap();
        assert_eq!(p["field"], "light.weights.bucket", "{p}");
    }
    // A weight within f32 whose products overflow: refused on light.weights, never inf.
    let dual = http
        .get(server.url(&format!("/v1/reconstructions/{id}/dual.npy")))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let (_, values) = helmholtz_tests::parse_npy(&dual).unwrap();
    let peak = values.iter().fold(0f64, |m, v| m.max(v.abs()));
    assert!(peak > 0.0);
    let w = (f32::MAX as f64 / peak * 4.0).min(f32::MAX as f64);
    let r = relight(w).await.unwrap();
    if peak * w > f32::MAX as f64 {
        assert_eq!(r.status(), 400, "weight {w} x peak {peak}");
        let p: Value = r.json().await.unwrap();
        assert_eq!(p["field"], "light.weights", "{p}");
        assert!(p["detail"].as_str().unwrap().contains("overflow"), "{p}");
    } else {
        // peak < 0.25: the largest weight f32 holds cannot overflow; the answer is finite.
        assert_eq!(r.status(), 200);
        let (_, v) = helmholtz_tests::parse_npy(&r.bytes().await.unwrap()).unwrap();
        assert!(v.iter().all(|x| x.is_finite()));
    }
    // A sane weight still works.
    assert_eq!(relight(0.5).await.unwrap().status(), 200);
}

/// A little-endian f32 NPY of shape (h, w) holding `value` everywhere.
fn npy_f32(h: usize, w: usize, value: f32) -> Vec<u8> {
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({h}, {w}), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for _ in 0..h * w {
        out.extend_from_slice(&value.to_le_bytes());
    }
    out
}

#[tokio::test]
async fn camera_relight_and_primal_inputs_whose_result_overflows_f32_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let out = std::process::Command::new(helmholtz_tests::binary("helmholtz"))
        .args(["--server", &server.address, "--token", &server.token])
        .arg("--spool")
        .arg(dir.path().join("spool"))
        .args([
            "simulate",
            "--scene",
            "lambert",
            "--camera",
            "12x10",
            "--frame-format",
            "f32",
            "--family",
            "hadamard",
            "--width",
            "16",
            "--height",
            "16",
            "--session-id",
            "cam",
            "--reconstruct",
            "transport",
            "--wait",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let doc: Value = helmholtz_tests::http_get(server.url("/v1/sessions/cam"))
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let id = doc["latest_reconstruction"].as_i64().unwrap();
    let http = helmholtz_tests::http_client();
    let post = |what: &str, body: Vec<u8>| {
        http.post(server.url(&format!("/v1/reconstructions/{id}/{what}?format=npy")))
            .header("content-type", "application/x-npy")
            .body(body)
            .send()
    };
    // The result is linear in the input: a unit input's peak tells whether f32::MAX overflows.
    for (what, h, w) in [("relight", 10, 12), ("primal", 16, 16)] {
        let unit = post(what, npy_f32(h, w, 1.0)).await.unwrap();
        assert_eq!(unit.status(), 200, "{what} of ones");
        let (_, v) = helmholtz_tests::parse_npy(&unit.bytes().await.unwrap()).unwrap();
        let peak = v.iter().fold(0f64, |m, x| m.max(x.abs()));
        let r = post(what, npy_f32(h, w, f32::MAX)).await.unwrap();
        if peak > 1.01 {
            assert_eq!(r.status(), 400, "{what}: unit peak {peak}");
            let p: Value = r.json().await.unwrap();
            assert_eq!(p["field"], "body", "{p}");
            assert!(p["detail"].as_str().unwrap().contains("not finite"), "{p}");
        } else {
            assert_eq!(r.status(), 200, "{what}: unit peak {peak}");
            let (_, v) = helmholtz_tests::parse_npy(&r.bytes().await.unwrap()).unwrap();
            assert!(v.iter().all(|x| x.is_finite()), "{what}");
        }
        eprintln!("{what}: unit input peak {peak}");
    }
}
