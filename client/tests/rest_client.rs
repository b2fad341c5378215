//! The REST helpers and the CLI's REST commands against a scripted HTTP/1.1 responder: polling,
//! problem+json errors, downloads. (End-to-end tests with the real server live in tests/.)

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use helmholtz_client::{ApiError, FetchTarget, ImageFormat};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

#[derive(Default)]
struct Log {
    hits: HashMap<String, usize>,
    bodies: Vec<String>,
}

fn respond(path: &str, hit: usize) -> (u16, &'static str, Vec<u8>) {
    let json = "application/json";
    let problem = "application/problem+json";
    let rec = |id: i64, state: &str, progress: f64, error: Option<&str>| {
        serde_json::json!({
            "id": id, "session_id": "s1", "method": "dgi", "params": {}, "state": state,
            "progress": progress, "rows": 4096, "seconds": 0.25, "error": error,
            "report": {"psnr_db": 21.5, "ssim": 0.8}
        })
        .to_string()
        .into_bytes()
    };
    match path {
        "/v1/sessions" => (200, json, br#"{"sessions":[{"id":"s1","rig":"bench","patterns":{"family":"bernoulli","width":8,"height":8,"count":64,"seed":1,"fill":0.5},"channels":["bucket"],"metadata":{},"committed_rows":64,"expected_rows":64,"state":"finished","created_unix_ms":5,"has_ground_truth":true,"latest_reconstruction":7}]}"#.to_vec()),
        "/v1/sessions/s1" => (200, json, br#"{"id":"s1","rig":"bench","patterns":{"family":"bernoulli","width":8,"height":8,"count":64,"seed":1,"fill":0.5},"channels":["bucket"],"metadata":{},"committed_rows":64,"expected_rows":64,"state":"finished","created_unix_ms":5,"has_ground_truth":true,"latest_reconstruction":7}"#.to_vec()),
        "/v1/sessions/nope" => (404, problem, br#"{"type":"about:blank","title":"Not Found","status":404,"detail":"no session nope","field":"session_id"}"#.to_vec()),
        "/v1/reconstructions/7" if hit < 3 => (200, json, rec(7, "running", hit as f64 * 0.3, None)),
        "/v1/reconstructions/7" => (200, json, rec(7, "done", 1.0, None)),
        "/v1/reconstructions/8" => (200, json, rec(8, "failed", 0.5, Some("diverged"))),
        "/v1/reconstructions/9" => (503, "text/plain", b"overloaded".to_vec()),
        "/v1/reconstructions/7/dual.png?channel=n%20e" | "/v1/sessions/s1/dual.tiff" => {
            (200, "image/png", b"\x89PNG fake image bytes".to_vec())
        }
        "/v1/sessions/s1/reconstructions" => (202, json, rec(7, "queued", 0.0, None)),
        _ => (404, problem, br#"{"title":"Not Found","status":404,"detail":"no route"}"#.to_vec()),
    }
}

async fn serve(log: Arc<Mutex<Log>>) -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move {
        loop {
            let (mut sock, _) = listener.accept().await.unwrap();
            let log = log.clone();
            tokio::spawn(async move {
                let mut buf = Vec::new();
                let mut tmp = [0u8; 4096];
                let head_end = loop {
                    let n = sock.read(&mut tmp).await.unwrap();
                    if n == 0 {
                        return;
                    }
                    buf.extend_from_slice(&tmp[..n]);
                    if let Some(p) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
                        break p + 4;
                    }
                };
                let head = String::from_utf8_lossy(&buf[..head_end]).to_string();
                let length: usize = head
                    .lines()
                    .find_map(|l| {
                        l.to_ascii_lowercase()
                            .strip_prefix("content-length:")
                            .map(|v| v.trim().parse().unwrap())
                    })
                    .unwrap_or(0);
                while buf.len() < head_end + length {
                    let n = sock.read(&mut tmp).await.unwrap();
                    buf.extend_from_slice(&tmp[..n]);
                }
                let path = head.split_whitespace().nth(1).unwrap().to_string();
                let hit = {
                    let mut log = log.lock().unwrap();
                    log.bodies
                        .push(String::from_utf8_lossy(&buf[head_end..]).to_string());
                    let h = log.hits.entry(path.clone()).or_default();
                    *h += 1;
                    *h
                };
                let (status, ctype, body) = respond(&path, hit);
                let reply = format!(
                    "HTTP/1.1 {status} X\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                    body.len()
                );
                sock.write_all(reply.as_bytes()).await.unwrap();
                sock.write_all(&body).await.unwrap();
                sock.shutdown().await.ok();
            });
        }
    });
    format!("http://{addr}")
}

#[tokio::test]
async fn waits_for_a_reconstruction_and_downloads_its_image() {
    let log = Arc::new(Mutex::new(Log::default()));
    let server = serve(log.clone()).await;
    let rec = helmholtz_client::wait_reconstruction(&server, 7, Duration::from_secs(10))
        .await
        .unwrap();
    assert!(rec.is_done());
    assert_eq!(rec.report["psnr_db"], 21.5);
    assert_eq!(log.lock().unwrap().hits["/v1/reconstructions/7"], 3);

    let failed = helmholtz_client::wait_reconstruction(&server, 8, Duration::from_secs(10))
        .await
        .unwrap();
    assert_eq!(
        (failed.state.as_str(), failed.error.as_deref()),
        ("failed", Some("diverged"))
    );

    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("dual.png");
    let report = helmholtz_client::fetch(
        &server,
        &FetchTarget::Reconstruction(7),
        ImageFormat::Png,
        Some("n e"),
        &out,
    )
    .await
    .unwrap();
    assert_eq!(std::fs::read(&out).unwrap(), b"\x89PNG fake image bytes");
    assert_eq!(report.bytes, 21);
    assert_eq!(report.content_type.as_deref(), Some("image/png"));
}

#[tokio::test]
async fn problems_become_api_errors() {
    let server = serve(Arc::default()).await;
    let err = helmholtz_client::get_session(&server, "nope")
        .await
        .unwrap_err();
    let api = err.downcast_ref::<ApiError>().expect("an ApiError");
    assert_eq!(
        (api.status, api.field.as_deref(), api.detail.as_deref()),
        (404, Some("session_id"), Some("no session nope"))
    );
    assert!(
        err.to_string()
            .contains("HTTP 404 Not Found: no session nope (field: session_id)"),
        "{err}"
    );

    // 4xx while waiting: fail at once. 5xx: keep polling until the timeout.
    let started = Instant::now();
    assert!(
        helmholtz_client::wait_reconstruction(&server, 404, Duration::from_secs(10))
            .await
            .is_err()
    );
    assert!(started.elapsed() < Duration::from_secs(2));
    let started = Instant::now();
    let err = helmholtz_client::wait_reconstruction(&server, 9, Duration::from_millis(600))
        .await
        .unwrap_err();
    assert!(started.elapsed() >= Duration::from_millis(600));
    assert!(err.to_string().contains("HTTP 503"), "{err}");
    assert!(err.to_string().contains("overloaded"), "{err}");

    // A failed download leaves no file behind.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.png");
    assert!(
        helmholtz_client::fetch(
            &server,
            &FetchTarget::Reconstruction(404),
            ImageFormat::Png,
            None,
            &out
        )
        .await
        .is_err()
    );
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[tokio::test]
async fn rest_reconstruction_request_and_listing() {
    let log = Arc::new(Mutex::new(Log::default()));
    let server = serve(log.clone()).await;
    let rec = helmholtz_client::request_reconstruction_rest(
        &server,
        "s1",
        "dgi",
        &serde_json::json!({"k": 2}),
    )
    .await
    .unwrap();
    assert_eq!((rec.id, rec.state.as_str()), (7, "queued"));
    let body: serde_json::Value =
        serde_json::from_str(log.lock().unwrap().bodies.last().unwrap()).unwrap();
    assert_eq!(
        body,
        serde_json::json!({"method": "dgi", "params": {"k": 2}})
    );
    let sessions = helmholtz_client::list_sessions(&server).await.unwrap();
    assert_eq!(sessions.len(), 1);
    assert_eq!(sessions[0].latest_reconstruction, Some(7));
}

/// The binary: JSON output, text output, and a non-zero exit with a clear message.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cli_status_and_fetch() {
    let server = serve(Arc::default()).await;
    let bin = env!("CARGO_BIN_EXE_helmholtz");
    let run = |args: Vec<String>| {
        tokio::task::spawn_blocking(move || {
            std::process::Command::new(bin).args(args).output().unwrap()
        })
    };
    let out = run(vec![
        "--json".into(),
        "--server".into(),
        server.clone(),
        "status".into(),
        "s1".into(),
    ])
    .await
    .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["session"]["committed_rows"], 64);
    assert_eq!(v["latest_reconstruction"]["id"], 7);

    let out = run(vec!["status".into(), "--server".into(), server.clone()])
        .await
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stdout).contains("s1"));

    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("d.tiff");
    let out = run(vec![
        "fetch".into(),
        "--session".into(),
        "s1".into(),
        "--out".into(),
        file.display().to_string(),
        "--server".into(),
        server.clone(),
        "--json".into(),
    ])
    .await
    .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(file.exists());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(
        v["url"]
            .as_str()
            .unwrap()
            .ends_with("/v1/sessions/s1/dual.tiff")
    );

    let out = run(vec![
        "status".into(),
        "nope".into(),
        "--server".into(),
        server.clone(),
        "--json".into(),
    ])
    .await
    .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("error:") && stderr.contains("no session nope"),
        "{stderr}"
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(v["error"].as_str().unwrap().contains("404"));
}
