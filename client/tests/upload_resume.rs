//! The upload's resume and retry logic against an in-process Acquisition service that follows the
//! contract (authoritative committed count, OUT_OF_RANGE on gaps, DATA_LOSS on bad CRCs) and
//! injects faults: transient errors, damaged chunks, and a kill and restart on the same port.
//!
//! This is not the real server (the end-to-end tests in tests/ use that); it exists to drive the
//! client through failure paths the real server only shows under duress.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use helmholtz_client::upload::{RpcError, UploadOptions};
use helmholtz_client::{Backoff, NewSession, PatternSpec};
use helmholtz_proto::v1::{
    self,
    acquisition_server::{Acquisition, AcquisitionServer},
};
use helmholtz_proto::wire;
use tokio_stream::StreamExt;
use tonic::{Code, Request, Response, Status, Streaming};

#[derive(Default)]
struct Store {
    sessions: HashMap<String, Stored>,
}

struct Stored {
    declaration: v1::CreateSessionRequest,
    expected: u64,
    channels: u32,
    values: Vec<f64>,
    finished: bool,
}

impl Stored {
    fn committed(&self) -> u64 {
        (self.values.len() / self.channels as usize) as u64
    }
}

/// Faults to inject, shared across server restarts like the store (the "database").
#[derive(Default)]
struct Faults {
    /// Fail a stream with UNAVAILABLE after this many chunks in it (0 = never).
    unavailable_every: AtomicUsize,
    /// Report DATA_LOSS for the next N chunks.
    data_loss: AtomicUsize,
    /// Sleep per chunk (ms), to make uploads slow enough to interrupt.
    chunk_delay_ms: AtomicUsize,
    chunks_seen: AtomicUsize,
    streams: AtomicUsize,
}

#[derive(Clone)]
struct Fake {
    store: Arc<Mutex<Store>>,
    faults: Arc<Faults>,
}

fn session_view(id: &str, s: &Stored) -> v1::Session {
    v1::Session {
        session_id: id.to_string(),
        rig: s.declaration.rig.clone(),
        patterns: s.declaration.patterns,
        detector: s.declaration.detector.clone(),
        metadata: s.declaration.metadata.clone(),
        committed_rows: s.committed(),
        expected_rows: s.expected,
        state: if s.finished {
            v1::SessionState::Finished
        } else {
            v1::SessionState::Open
        } as i32,
        created_unix_ms: 0,
        has_ground_truth: s.declaration.ground_truth.is_some(),
    }
}

#[tonic::async_trait]
impl Acquisition for Fake {
    async fn create_session(
        &self,
        request: Request<v1::CreateSessionRequest>,
    ) -> Result<Response<v1::CreateSessionResponse>, Status> {
        let req = request.into_inner();
        let spec = PatternSpec::try_from(
            req.patterns
                .as_ref()
                .ok_or_else(|| Status::invalid_argument("no spec"))?,
        )
        .map_err(|e| Status::invalid_argument(e.to_string()))?;
        let channels = req.detector.as_ref().map(|d| d.channels.len()).unwrap_or(0) as u32;
        let mut store = self.store.lock().unwrap();
        if let Some(existing) = store.sessions.get(&req.session_id) {
            if existing.declaration != req {
                return Err(Status::already_exists("different declaration"));
            }
            let session = session_view(&req.session_id, existing);
            return Ok(Response::new(v1::CreateSessionResponse {
                session: Some(session),
                created: false,
            }));
        }
        let stored = Stored {
            declaration: req.clone(),
            expected: spec.count(),
            channels,
            values: vec![],
            finished: false,
        };
        let session = session_view(&req.session_id, &stored);
        store.sessions.insert(req.session_id.clone(), stored);
        Ok(Response::new(v1::CreateSessionResponse {
            session: Some(session),
            created: true,
        }))
    }

    async fn upload_measurements(
        &self,
        request: Request<Streaming<v1::MeasurementChunk>>,
    ) -> Result<Response<v1::UploadResponse>, Status> {
        self.faults.streams.fetch_add(1, Ordering::SeqCst);
        let mut stream = request.into_inner();
        let (mut written, mut skipped, mut in_stream) = (0u64, 0u64, 0usize);
        let mut last_session = String::new();
        while let Some(chunk) = stream.next().await {
            let chunk = chunk?;
            in_stream += 1;
            self.faults.chunks_seen.fetch_add(1, Ordering::SeqCst);
            let delay = self.faults.chunk_delay_ms.load(Ordering::SeqCst);
            if delay > 0 {
                tokio::time::sleep(Duration::from_millis(delay as u64)).await;
            }
            let every = self.faults.unavailable_every.load(Ordering::SeqCst);
            if every > 0 && in_stream > every {
                return Err(Status::unavailable("injected: server busy"));
            }
            if self
                .faults
                .data_loss
                .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1))
                .is_ok()
            {
                return Err(Status::data_loss("injected: crc32c mismatch"));
            }
            let mut store = self.store.lock().unwrap();
            let s = store
                .sessions
                .get_mut(&chunk.session_id)
                .ok_or_else(|| Status::not_found("no such session"))?;
            if chunk.channels != s.channels {
                return Err(Status::invalid_argument(format!(
                    "session has {} channels",
                    s.channels
                )));
            }
            let values =
                wire::decode_values(&chunk.values_f64le, chunk.channels as usize, chunk.crc32c)
                    .map_err(|e| Status::data_loss(e.to_string()))?;
            let rows = (values.len() / s.channels as usize) as u64;
            let committed = s.committed();
            if chunk.start_row > committed {
                return Err(Status::out_of_range(format!(
                    "gap: chunk starts at {}, committed {committed}",
                    chunk.start_row
                )));
            }
            if chunk.start_row + rows > s.expected {
                return Err(Status::out_of_range("past the spec's count"));
            }
            let overlap = (committed - chunk.start_row).min(rows);
            s.values
                .extend_from_slice(&values[overlap as usize * s.channels as usize..]);
            written += rows - overlap;
            skipped += overlap;
            last_session = chunk.session_id.clone();
        }
        let store = self.store.lock().unwrap();
        let committed = store
            .sessions
            .get(&last_session)
            .map(Stored::committed)
            .unwrap_or(0);
        Ok(Response::new(v1::UploadResponse {
            committed_rows: committed,
            rows_written: written,
            rows_skipped: skipped,
        }))
    }

    async fn get_upload_status(
        &self,
        request: Request<v1::SessionRef>,
    ) -> Result<Response<v1::UploadStatus>, Status> {
        let id = request.into_inner().session_id;
        let store = self.store.lock().unwrap();
        let s = store
            .sessions
            .get(&id)
            .ok_or_else(|| Status::not_found(format!("no session {id}")))?;
        Ok(Response::new(v1::UploadStatus {
            session_id: id,
            committed_rows: s.committed(),
            expected_rows: s.expected,
            state: if s.finished {
                v1::SessionState::Finished
            } else {
                v1::SessionState::Open
            } as i32,
        }))
    }

    async fn finish_session(
        &self,
        request: Request<v1::SessionRef>,
    ) -> Result<Response<v1::Session>, Status> {
        let id = request.into_inner().session_id;
        let mut store = self.store.lock().unwrap();
        let s = store
            .sessions
            .get_mut(&id)
            .ok_or_else(|| Status::not_found("no session"))?;
        if s.committed() < s.expected {
            return Err(Status::failed_precondition(format!(
                "{} of {} rows committed",
                s.committed(),
                s.expected
            )));
        }
        s.finished = true;
        Ok(Response::new(session_view(&id, s)))
    }

    async fn request_reconstruction(
        &self,
        request: Request<v1::ReconstructionRequest>,
    ) -> Result<Response<v1::Reconstruction>, Status> {
        let r = request.into_inner();
        Ok(Response::new(v1::Reconstruction {
            reconstruction_id: 1,
            session_id: r.session_id,
            method: r.method,
            params_json: r.params_json,
            state: "queued".into(),
            ..Default::default()
        }))
    }

    async fn get_reconstruction(
        &self,
        _request: Request<v1::ReconstructionRef>,
    ) -> Result<Response<v1::Reconstruction>, Status> {
        Err(Status::unimplemented("not in the fake"))
    }
}

/// A server on its own runtime thread: dropping it kills every connection at once, like a crash.
struct Running {
    shutdown: Option<std::sync::mpsc::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Running {
    fn start(fake: Fake, addr: SocketAddr) -> (Running, SocketAddr) {
        let (addr_tx, addr_rx) = std::sync::mpsc::channel();
        let (stop_tx, stop_rx) = std::sync::mpsc::channel::<()>();
        let thread = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
                .unwrap();
            rt.block_on(async move {
                let socket = tokio::net::TcpSocket::new_v4().unwrap();
                socket.set_reuseaddr(true).unwrap();
                // The old port may linger briefly after a kill: retry the bind.
                let mut tries = 0;
                while let Err(e) = socket.bind(addr) {
                    tries += 1;
                    assert!(tries < 100, "cannot rebind {addr}: {e}");
                    std::thread::sleep(Duration::from_millis(20));
                }
                let listener = socket.listen(128).unwrap();
                addr_tx.send(listener.local_addr().unwrap()).unwrap();
                let incoming = tokio_stream::wrappers::TcpListenerStream::new(listener);
                tokio::spawn(async move {
                    tonic::transport::Server::builder()
                        .add_service(AcquisitionServer::new(fake))
                        .serve_with_incoming(incoming)
                        .await
                        .unwrap();
                });
                // Park until told to die; then the runtime is dropped with all its tasks.
                tokio::task::spawn_blocking(move || stop_rx.recv())
                    .await
                    .ok();
            });
            rt.shutdown_background();
        });
        let bound = addr_rx.recv().unwrap();
        (
            Running {
                shutdown: Some(stop_tx),
                thread: Some(thread),
            },
            bound,
        )
    }

    fn kill(mut self) {
        drop(self.shutdown.take());
        self.thread.take().unwrap().join().unwrap();
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        drop(self.shutdown.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn fake() -> Fake {
    Fake {
        store: Arc::default(),
        faults: Arc::default(),
    }
}

fn spec(count: u64) -> PatternSpec {
    serde_json::from_str(&format!(
        r#"{{"family":"bernoulli","width":8,"height":8,"count":{count},"seed":3}}"#
    ))
    .unwrap()
}

fn values(rows: usize, channels: usize) -> Vec<f64> {
    (0..rows * channels)
        .map(|i| (i as f64) * 0.5 + 0.25)
        .collect()
}

fn quick_opts() -> UploadOptions {
    UploadOptions {
        chunk_rows: Some(500),
        retry_for: Duration::from_secs(20),
        backoff: Backoff {
            initial: Duration::from_millis(20),
            max: Duration::from_millis(200),
            ..Backoff::default()
        },
        ..UploadOptions::default()
    }
}

async fn create(server: &str, id: &str, count: u64, channels: usize) {
    let names = (0..channels).map(|c| format!("c{c}")).collect();
    let created =
        helmholtz_client::create_session(server, &NewSession::new(id, spec(count), names))
            .await
            .unwrap();
    assert!(created.created);
}

fn stored_values(f: &Fake, id: &str) -> Vec<f64> {
    f.store.lock().unwrap().sessions[id].values.clone()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clean_upload_then_idempotent_rerun() {
    let f = fake();
    let (_srv, addr) = Running::start(f.clone(), "127.0.0.1:0".parse().unwrap());
    let server = format!("http://{addr}");
    create(&server, "clean", 3000, 2).await;
    let v = values(3000, 2);
    let report = helmholtz_client::upload(&server, "clean", 2, &v, &quick_opts())
        .await
        .unwrap();
    assert_eq!(
        (
            report.rows,
            report.rows_sent,
            report.rows_skipped,
            report.resumes
        ),
        (3000, 3000, 0, 0)
    );
    assert_eq!(
        (
            report.committed_rows,
            report.expected_rows,
            report.rows_written
        ),
        (3000, 3000, 3000)
    );
    assert_eq!(report.chunks_sent, 6);
    assert_eq!(report.bytes_sent, 3000 * 2 * 8);
    assert_eq!(stored_values(&f, "clean"), v);

    // Again: nothing to send.
    let again = helmholtz_client::upload(&server, "clean", 2, &v, &quick_opts())
        .await
        .unwrap();
    assert_eq!((again.rows_sent, again.rows_skipped), (0, 3000));
    let session = helmholtz_client::finish_session(&server, "clean")
        .await
        .unwrap();
    assert_eq!(session.state, v1::SessionState::Finished as i32);
    // Creating again with the same declaration is idempotent; a different one is refused.
    let same = helmholtz_client::create_session(
        &server,
        &NewSession::new("clean", spec(3000), vec!["c0".into(), "c1".into()]),
    )
    .await
    .unwrap();
    assert!(!same.created);
    assert_eq!(same.session.committed_rows, 3000);
    let err = helmholtz_client::create_session(
        &server,
        &NewSession::new("clean", spec(3001), vec!["c0".into(), "c1".into()]),
    )
    .await
    .unwrap_err();
    assert_eq!(
        err.downcast_ref::<RpcError>().unwrap().code,
        Code::AlreadyExists
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn resumes_a_partial_upload_from_the_servers_count() {
    let f = fake();
    let (_srv, addr) = Running::start(f.clone(), "127.0.0.1:0".parse().unwrap());
    let server = format!("http://{addr}");
    create(&server, "partial", 2000, 1).await;
    let v = values(2000, 1);
    // A rig that stopped after 700 rows.
    helmholtz_client::upload(&server, "partial", 1, &v[..700], &quick_opts())
        .await
        .unwrap();
    let err = helmholtz_client::finish_session(&server, "partial")
        .await
        .unwrap_err();
    assert_eq!(
        err.downcast_ref::<RpcError>().unwrap().code,
        Code::FailedPrecondition
    );
    let report = helmholtz_client::upload(&server, "partial", 1, &v, &quick_opts())
        .await
        .unwrap();
    assert_eq!(
        (report.rows_skipped, report.rows_sent, report.committed_rows),
        (700, 1300, 2000)
    );
    assert_eq!(stored_values(&f, "partial"), v);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn transient_failures_are_retried_and_resumed() {
    let f = fake();
    f.faults.unavailable_every.store(3, Ordering::SeqCst);
    let (_srv, addr) = Running::start(f.clone(), "127.0.0.1:0".parse().unwrap());
    let server = format!("http://{addr}");
    create(&server, "flaky", 5000, 1).await;
    let v = values(5000, 1);
    let report = helmholtz_client::upload(&server, "flaky", 1, &v, &quick_opts())
        .await
        .unwrap();
    assert_eq!(stored_values(&f, "flaky"), v);
    // 3 chunks of 500 per stream: 4 failures, each followed by a resume.
    assert!(report.resumes >= 3, "{report:?}");
    assert!(
        report
            .last_error
            .as_deref()
            .unwrap()
            .contains("UNAVAILABLE")
    );
    assert_eq!(report.committed_rows, 5000);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn data_loss_resyncs_once_but_not_forever() {
    let f = fake();
    f.faults.data_loss.store(1, Ordering::SeqCst);
    let (_srv, addr) = Running::start(f.clone(), "127.0.0.1:0".parse().unwrap());
    let server = format!("http://{addr}");
    create(&server, "dl", 2000, 1).await;
    let v = values(2000, 1);
    let report = helmholtz_client::upload(&server, "dl", 1, &v, &quick_opts())
        .await
        .unwrap();
    assert_eq!(report.resumes, 1);
    assert_eq!(stored_values(&f, "dl"), v);

    create(&server, "dl2", 2000, 1).await;
    f.faults.data_loss.store(1000, Ordering::SeqCst);
    let started = Instant::now();
    let err = helmholtz_client::upload(&server, "dl2", 1, &v, &quick_opts())
        .await
        .unwrap_err();
    assert_eq!(
        err.downcast_ref::<RpcError>().unwrap().code,
        Code::DataLoss,
        "{err:#}"
    );
    assert!(started.elapsed() < Duration::from_secs(5));
    assert!(
        format!("{err:#}").contains("0 of 2000 rows committed"),
        "{err:#}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fatal_errors_fail_fast() {
    let f = fake();
    let (_srv, addr) = Running::start(f.clone(), "127.0.0.1:0".parse().unwrap());
    let server = format!("http://{addr}");
    let v = values(100, 1);
    let started = Instant::now();
    let err = helmholtz_client::upload(&server, "missing", 1, &v, &quick_opts())
        .await
        .unwrap_err();
    assert_eq!(err.downcast_ref::<RpcError>().unwrap().code, Code::NotFound);
    // Wrong channel count: INVALID_ARGUMENT, not retried.
    create(&server, "two", 100, 2).await;
    let err = helmholtz_client::upload(&server, "two", 1, &v, &quick_opts())
        .await
        .unwrap_err();
    assert_eq!(
        err.downcast_ref::<RpcError>().unwrap().code,
        Code::InvalidArgument
    );
    assert!(started.elapsed() < Duration::from_secs(3));
    assert_eq!(f.faults.streams.load(Ordering::SeqCst), 1);
    // More rows than the spec: refused before sending.
    create(&server, "small", 10, 1).await;
    let err = helmholtz_client::upload(&server, "small", 1, &v, &quick_opts())
        .await
        .unwrap_err();
    assert!(
        err.to_string()
            .contains("100 rows given but session small expects 10"),
        "{err}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gives_up_after_retry_for_when_nobody_listens() {
    // A port with nothing behind it.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let server = format!("http://127.0.0.1:{port}");
    let opts = UploadOptions {
        retry_for: Duration::from_millis(800),
        ..quick_opts()
    };
    let started = Instant::now();
    let err = helmholtz_client::upload(&server, "x", 1, &values(10, 1), &opts)
        .await
        .unwrap_err();
    let took = started.elapsed();
    assert!(
        took >= Duration::from_millis(800) && took < Duration::from_secs(5),
        "{took:?}"
    );
    let text = format!("{err:#}");
    assert!(
        text.contains("gave up") && text.contains("UNAVAILABLE"),
        "{text}"
    );
}

/// The server dies mid-upload (every connection cut) and comes back on the same port a little
/// later with its durable rows: the upload resumes from the server's count and completes exactly.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn survives_a_server_kill_and_restart_on_the_same_port() {
    let f = fake();
    f.faults.chunk_delay_ms.store(2, Ordering::SeqCst);
    let (srv, addr) = Running::start(f.clone(), "127.0.0.1:0".parse().unwrap());
    let server = format!("http://{addr}");
    create(&server, "crash", 100_000, 1).await;
    let v = values(100_000, 1);
    let opts = UploadOptions {
        chunk_rows: Some(250),
        ..quick_opts()
    };
    let upload = {
        let (server, v, opts) = (server.clone(), v.clone(), opts.clone());
        tokio::spawn(async move { helmholtz_client::upload(&server, "crash", 1, &v, &opts).await })
    };
    // Let it get going, then kill the server.
    let committed = || f.store.lock().unwrap().sessions["crash"].committed();
    while committed() < 20_000 {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    tokio::task::spawn_blocking(move || srv.kill())
        .await
        .unwrap();
    let at_kill = committed();
    assert!(
        at_kill < 100_000,
        "the upload finished before the kill; slow the fake down"
    );
    tokio::time::sleep(Duration::from_millis(700)).await;
    let (_srv2, addr2) = Running::start(f.clone(), addr);
    assert_eq!(addr2, addr);
    let report = upload.await.unwrap().unwrap();
    assert_eq!(stored_values(&f, "crash"), v);
    assert!(report.resumes >= 1, "{report:?}");
    assert_eq!(report.committed_rows, 100_000);
    // Rows in flight when the server died (HTTP/2 windows hold a lot) are sent again.
    assert!(
        report.rows_sent >= 100_000 && report.rows_sent <= 200_000,
        "{report:?}"
    );
    assert!(report.last_error.is_some());
}

/// The binary's `simulate` and `upload` commands against the fake (gRPC only: no --reconstruct).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cli_simulate_and_upload() {
    let f = fake();
    let (_srv, addr) = Running::start(f.clone(), "127.0.0.1:0".parse().unwrap());
    let server = format!("http://{addr}");
    let dir = tempfile::tempdir().unwrap();
    let bin = env!("CARGO_BIN_EXE_helmholtz");
    let run = |args: Vec<String>| {
        let server = server.clone();
        tokio::task::spawn_blocking(move || {
            std::process::Command::new(bin)
                .args(args)
                .args(["--server", &server])
                .output()
                .unwrap()
        })
    };
    let npy = dir.path().join("v.npy");
    let out = run([
        "simulate",
        "--scene",
        "double-slit",
        "--family",
        "hadamard",
        "--width",
        "16",
        "--height",
        "16",
        "--ordering",
        "sequency",
        "--photons",
        "1e6",
        "--adc-bits",
        "16",
        "--channels",
        "a,b",
        "--channel-gains",
        "1,0.5",
        "--session-id",
        "cli-sim",
        "--json",
        "--values-out",
        npy.to_str().unwrap(),
    ]
    .map(String::from)
    .to_vec())
    .await
    .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["upload"]["committed_rows"], 512);
    assert_eq!(v["spec"]["ordering"], "sequency");
    let written = helmholtz_client::measurements::read_measurements(&npy).unwrap();
    assert_eq!((written.rows, written.channels), (512, 2));
    {
        let store = f.store.lock().unwrap();
        let s = &store.sessions["cli-sim"];
        assert_eq!(s.values, written.values);
        assert!(s.finished);
        let gt = s.declaration.ground_truth.as_ref().unwrap();
        assert_eq!(gt.transport.len(), 256);
        assert_eq!(
            s.declaration.detector.as_ref().unwrap().channels,
            ["a", "b"]
        );
    }

    // A rig's CSV: header names the channels; the row count must match the spec.
    let csv = dir.path().join("rig.csv");
    let rows: String = (0..64).map(|i| format!("{}\n", i as f64 * 0.5)).collect();
    std::fs::write(&csv, format!("# bench run\npd0\n{rows}")).unwrap();
    let spec = r#"{"family":"raster","width":8,"height":8,"count":64}"#;
    let out = run([
        "upload",
        "--session-id",
        "rig-1",
        "--spec-json",
        spec,
        "--values",
        csv.to_str().unwrap(),
        "--finish",
    ]
    .map(String::from)
    .to_vec())
    .await
    .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("uploaded 64 rows"));
    assert_eq!(
        f.store.lock().unwrap().sessions["rig-1"]
            .declaration
            .detector
            .as_ref()
            .unwrap()
            .channels,
        ["pd0"]
    );

    let short = dir.path().join("short.csv");
    std::fs::write(&short, "1\n2\n3\n").unwrap();
    let out = run([
        "upload",
        "--session-id",
        "rig-2",
        "--spec-json",
        spec,
        "--values",
        short.to_str().unwrap(),
    ]
    .map(String::from)
    .to_vec())
    .await
    .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("short.csv: 3 rows, but the spec declares 64 patterns"),
        "{stderr}"
    );
    assert!(
        !f.store.lock().unwrap().sessions.contains_key("rig-2"),
        "validated before creating"
    );
}
