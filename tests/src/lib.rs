//! Harness for end-to-end tests: the real `helmholtz-server` binary on 127.0.0.1 port 0 with a
//! real SQLite file in a temporary directory, or a real PostgreSQL database made for the test
//! ([`backend`]: `HELMHOLTZ_TEST_BACKEND`), talked to by the real client library and binary.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use helmholtz_client::auth::Grpc;

pub mod backend;
pub mod browser;
pub mod pg;

pub use backend::{Backend, backend, server_command, store_args, store_args_on};

/// A plain REST client for the tests (`reqwest::Client::new()`), after installing rustls's ring
/// provider: the workspace builds rustls with ring alone, and reqwest needs a process-wide
/// provider before it builds a client ([`helmholtz_client::tls::install_crypto_provider`]).
pub fn http_client() -> reqwest::Client {
    helmholtz_client::tls::install_crypto_provider();
    reqwest::Client::new()
}

/// `reqwest::get(url)` on [`http_client`].
pub async fn http_get(url: impl reqwest::IntoUrl) -> reqwest::Result<reqwest::Response> {
    http_client().get(url).send().await
}

/// Path of a workspace binary built beside this test executable (`cargo test --workspace`
/// builds them: the server and client packages each have an integration test). Note that
/// `cargo test -p helmholtz-tests` alone does not rebuild them: it runs whatever binaries the
/// last workspace build left.
pub fn binary(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    let file = format!("{name}{}", std::env::consts::EXE_SUFFIX);
    // A test runs from target/<profile>/deps, a benchmark binary from target/<profile>.
    let beside = exe.parent().map(|d| d.join(&file));
    let path = match beside {
        Some(p) if p.exists() => p,
        _ => exe
            .parent()
            .and_then(Path::parent)
            .expect("target/<profile>/deps/..")
            .join(&file),
    };
    assert!(
        path.exists(),
        "{} is missing: run the tests with `cargo test --workspace`, which builds the binaries",
        path.display()
    );
    path
}

/// The `helmholtz-server` binary for an on-demand benchmark: `explicit` (its `--server-bin`) or
/// the one beside the running benchmark binary (same profile), with a clear error when missing.
pub fn server_binary_beside(explicit: Option<&Path>) -> anyhow::Result<PathBuf> {
    if let Some(p) = explicit {
        return Ok(p.to_path_buf());
    }
    let exe = std::env::current_exe()?;
    let dir = exe.parent().context("binary directory")?;
    let path = dir.join(format!("helmholtz-server{}", std::env::consts::EXE_SUFFIX));
    if !path.exists() {
        bail!(
            "{} is missing: build it with the same profile first (`cargo build -p helmholtz-server --bins`, \
             with --release for a release run) or pass --server-bin",
            path.display()
        );
    }
    Ok(path)
}

/// The lab of the harness's default token.
pub const E2E_LAB: &str = "e2e";

/// Creates a token with the real `helmholtz-server token create` against `data_dir` (the
/// server may be running) and returns its secret.
pub fn create_token(data_dir: &Path, lab: &str, roles: &str) -> anyhow::Result<String> {
    create_token_with(&binary("helmholtz-server"), data_dir, lab, roles)
}

/// [`create_token`] by the server binary at `server_bin`.
pub fn create_token_with(
    server_bin: &Path,
    data_dir: &Path,
    lab: &str,
    roles: &str,
) -> anyhow::Result<String> {
    create_token_on(backend(), server_bin, data_dir, lab, roles)
}

/// [`create_token_with`] on `backend` whatever this process's backend is.
pub fn create_token_on(
    backend: Backend,
    server_bin: &Path,
    data_dir: &Path,
    lab: &str,
    roles: &str,
) -> anyhow::Result<String> {
    let out = Command::new(server_bin)
        .args(["token", "create", "--lab", lab, "--role", roles])
        .args(store_args_on(backend, data_dir))
        .env("RUST_LOG", "warn")
        .output()
        .context("running helmholtz-server token create")?;
    if !out.status.success() {
        bail!(
            "token create failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let token = String::from_utf8(out.stdout)?.trim().to_string();
    anyhow::ensure!(
        token.starts_with("hz_"),
        "unexpected token output {token:?}"
    );
    Ok(token)
}

/// A running server process. Killed (SIGKILL) when dropped.
///
/// `base_url` carries the harness's token for lab [`E2E_LAB`] with roles rig and reader as its
/// user part (`http://hz_...@127.0.0.1:PORT`): the client library sends it as a bearer token and
/// reqwest as HTTP Basic, so existing calls through `base_url` / `url()` are authenticated.
/// `address` is the same server without a token.
pub struct ServerProcess {
    child: Child,
    pub base_url: String,
    pub address: String,
    pub token: String,
    pub port: u16,
    pub data_dir: PathBuf,
    /// `http://127.0.0.1:PORT/metrics` when started with `--metrics-listen`.
    pub metrics_url: Option<String>,
    stdout_thread: Option<std::thread::JoinHandle<()>>,
}

impl ServerProcess {
    /// Starts `helmholtz-server serve` on 127.0.0.1 port 0 (or `port`) with `data_dir` (and on
    /// PostgreSQL, `data_dir`'s database: [`backend`]), after
    /// making sure `data_dir` holds the harness's token (kept in `data_dir/.e2e-token` so a
    /// restarted server on the same data accepts the same token).
    pub fn start(data_dir: &Path, port: u16, extra: &[&str]) -> anyhow::Result<ServerProcess> {
        Self::start_binary(&binary("helmholtz-server"), data_dir, port, extra)
    }

    /// [`ServerProcess::start`] with the server binary at `server_bin` (which also creates the
    /// harness's token).
    pub fn start_binary(
        server_bin: &Path,
        data_dir: &Path,
        port: u16,
        extra: &[&str],
    ) -> anyhow::Result<ServerProcess> {
        Self::start_binary_on(backend(), server_bin, data_dir, port, extra)
    }

    /// [`ServerProcess::start`] on SQLite whatever this process's backend is (a test of the
    /// SQLite file itself).
    pub fn start_sqlite(
        data_dir: &Path,
        port: u16,
        extra: &[&str],
    ) -> anyhow::Result<ServerProcess> {
        Self::start_binary_on(
            Backend::Sqlite,
            &binary("helmholtz-server"),
            data_dir,
            port,
            extra,
        )
    }

    /// [`ServerProcess::start_binary`] on `backend` whatever this process's backend is.
    pub fn start_binary_on(
        backend: Backend,
        server_bin: &Path,
        data_dir: &Path,
        port: u16,
        extra: &[&str],
    ) -> anyhow::Result<ServerProcess> {
        std::fs::create_dir_all(data_dir)?;
        let token_file = data_dir.join(".e2e-token");
        let token = match std::fs::read_to_string(&token_file) {
            Ok(t) => t.trim().to_string(),
            Err(_) => {
                let t = create_token_on(backend, server_bin, data_dir, E2E_LAB, "rig,reader")?;
                std::fs::write(&token_file, &t)?;
                t
            }
        };
        let mut args: Vec<std::ffi::OsString> = vec![
            "serve".into(),
            "--listen".into(),
            format!("127.0.0.1:{port}").into(),
        ];
        args.extend(store_args_on(backend, data_dir));
        args.extend(extra.iter().map(Into::into));
        Self::launch(server_bin, &args, token, data_dir)
    }

    /// `helmholtz-server serve` on 127.0.0.1 port 0 against the PostgreSQL database `db`,
    /// accepting `token` (made with [`pg::TestDatabase::create_token`]).
    pub fn start_on_postgres(
        db: &pg::TestDatabase,
        token: &str,
        extra: &[&str],
    ) -> anyhow::Result<ServerProcess> {
        let dir = std::env::temp_dir().join(format!("helmholtz-pg-node-{}", std::process::id()));
        let mut args: Vec<std::ffi::OsString> = vec![
            "serve".into(),
            "--listen".into(),
            "127.0.0.1:0".into(),
            "--database-url".into(),
            db.url().into(),
        ];
        args.extend(extra.iter().map(Into::into));
        Self::launch(&binary("helmholtz-server"), &args, token.to_string(), &dir)
    }

    /// Runs `server_bin` with `args` and waits for the address on its first line.
    fn launch(
        server_bin: &Path,
        args: &[std::ffi::OsString],
        token: String,
        data_dir: &Path,
    ) -> anyhow::Result<ServerProcess> {
        // A test that talks REST to this server with its own reqwest client needs rustls's
        // provider installed first (see [`http_client`]).
        helmholtz_client::tls::install_crypto_provider();
        let mut child = Command::new(server_bin)
            .args(args)
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("spawning helmholtz-server")?;
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        let stdout_thread = std::thread::spawn(move || {
            let mut tx = Some(tx);
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if let Some(tx) = tx.take() {
                    let _ = tx.send(line);
                }
            }
        });
        let line = rx
            .recv_timeout(Duration::from_secs(60))
            .context("server printed no address")?;
        let mut urls = line
            .split_whitespace()
            .filter(|w| w.starts_with("http://") || w.starts_with("https://"));
        let address = urls
            .next()
            .with_context(|| format!("no address in {line:?}"))?
            .to_string();
        let metrics_url = urls.next().map(|u| u.trim_end_matches(',').to_string());
        let port = address
            .rsplit(':')
            .next()
            .and_then(|p| p.parse().ok())
            .context("port")?;
        let base_url = helmholtz_client::auth::with_token(&address, &token);
        Ok(ServerProcess {
            child,
            base_url,
            address,
            token,
            port,
            data_dir: data_dir.to_path_buf(),
            metrics_url,
            stdout_thread: Some(stdout_thread),
        })
    }

    /// A new token of `lab` with `roles` (comma-separated), made by the real CLI.
    pub fn create_token(&self, lab: &str, roles: &str) -> anyhow::Result<String> {
        create_token(&self.data_dir, lab, roles)
    }

    /// This server's address carrying `token`.
    pub fn url_with(&self, token: &str) -> String {
        helmholtz_client::auth::with_token(&self.address, token)
    }

    /// SIGKILL: no graceful shutdown, no chance to flush anything.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if let Some(t) = self.stdout_thread.take() {
            let _ = t.join();
        }
    }

    /// Sends SIGTERM and returns at once (the server shuts down gracefully meanwhile).
    pub fn signal_term(&self) -> anyhow::Result<()> {
        let status = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()?;
        anyhow::ensure!(status.success(), "kill -TERM failed");
        Ok(())
    }

    /// SIGTERM, then wait for a clean exit.
    pub fn terminate(&mut self) -> anyhow::Result<std::process::ExitStatus> {
        let pid = self.child.id().to_string();
        Command::new("kill").args(["-TERM", &pid]).status()?;
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if let Some(status) = self.child.try_wait()? {
                return Ok(status);
            }
            if Instant::now() > deadline {
                bail!("server did not exit within 30 s of SIGTERM");
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// A gRPC client sending the harness's token.
    pub async fn grpc(&self) -> anyhow::Result<Grpc> {
        self.grpc_as(&self.base_url)
    }

    /// A gRPC client for `server` (an address with or without a token).
    pub fn grpc_as(&self, server: &str) -> anyhow::Result<Grpc> {
        helmholtz_client::upload::connect(server, Duration::from_secs(5))
    }

    /// The server's process id (for /proc/PID/status).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.base_url, path)
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A TCP proxy on 127.0.0.1 port 0 in front of a real server that can cut every open connection
/// at once: real network failure (both sockets closed mid-stream), no mock of either end.
pub struct FaultyProxy {
    pub addr: std::net::SocketAddr,
    connections: std::sync::Arc<std::sync::Mutex<Vec<tokio::task::AbortHandle>>>,
    accept: tokio::task::JoinHandle<()>,
}

impl FaultyProxy {
    /// Forwards every connection to `target` (e.g. "127.0.0.1:8080").
    pub async fn start(target: String) -> anyhow::Result<FaultyProxy> {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let connections =
            std::sync::Arc::new(std::sync::Mutex::new(Vec::<tokio::task::AbortHandle>::new()));
        let registry = connections.clone();
        let accept = tokio::spawn(async move {
            while let Ok((mut inbound, _)) = listener.accept().await {
                let target = target.clone();
                let task = tokio::spawn(async move {
                    if let Ok(mut outbound) = tokio::net::TcpStream::connect(&target).await {
                        let _ = tokio::io::copy_bidirectional(&mut inbound, &mut outbound).await;
                    }
                });
                let mut live = registry.lock().unwrap();
                live.retain(|h| !h.is_finished());
                live.push(task.abort_handle());
            }
        });
        Ok(FaultyProxy {
            addr,
            connections,
            accept,
        })
    }

    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// Cuts every open connection (both of its sockets are closed); returns how many.
    pub fn cut_all(&self) -> usize {
        let mut live = self.connections.lock().unwrap();
        let n = live.iter().filter(|h| !h.is_finished()).count();
        for h in live.drain(..) {
            h.abort();
        }
        n
    }
}

impl Drop for FaultyProxy {
    fn drop(&mut self) {
        self.accept.abort();
        self.cut_all();
    }
}

/// A small seeded generator (SplitMix64) for fault schedules: print the seed, replay a failure.
pub struct SplitMix64(pub u64);

impl SplitMix64 {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `lo..hi` (`hi > lo`).
    pub fn range(&mut self, lo: u64, hi: u64) -> u64 {
        lo + self.next_u64() % (hi - lo)
    }
}

/// The seed of a fault test: `HELMHOLTZ_FAULT_SEED` if set (to replay a run), else the clock.
pub fn fault_seed() -> u64 {
    std::env::var("HELMHOLTZ_FAULT_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_nanos() as u64)
                .unwrap_or(1)
        })
}

/// Parses an NPY file ([`helmholtz_proto::npy`], the reader the service and the client use) into
/// (shape, values as f64 in C order); the data must be exactly what the shape needs.
pub fn parse_npy(bytes: &[u8]) -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
    let (header, values) = helmholtz_proto::npy::decode_f64(bytes)?;
    let shape = header.shape.iter().map(|&d| d as usize).collect();
    Ok((shape, values))
}

/// The session ids of a `GET /v1/sessions` body, in its order.
pub fn session_ids(listed: &serde_json::Value) -> Vec<&str> {
    listed["sessions"]
        .as_array()
        .expect("a sessions array")
        .iter()
        .map(|s| s["id"].as_str().expect("a session id"))
        .collect()
}

/// Pearson correlation.
pub fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    sab / (saa * sbb).sqrt()
}

/// ||a - b|| / ||b||.
pub fn relative_error(a: &[f64], b: &[f64]) -> f64 {
    let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
    let den: f64 = b.iter().map(|y| y * y).sum();
    (num / den).sqrt()
}

/// A bucket session's declaration: `count` frames of `family` patterns on a `width` x `height`
/// grid (seed 1), one channel per name in `channels`, no metadata or ground truth.
pub fn bucket_session(
    id: &str,
    family: helmholtz_proto::v1::PatternFamily,
    width: u32,
    height: u32,
    count: u64,
    channels: &[&str],
) -> helmholtz_proto::v1::CreateSessionRequest {
    use helmholtz_proto::v1;
    v1::CreateSessionRequest {
        session_id: id.into(),
        rig: "r".into(),
        patterns: Some(v1::PatternSpec {
            family: family as i32,
            width,
            height,
            count,
            seed: 1,
            params: None,
        }),
        detector: Some(v1::DetectorLayout {
            channels: channels.iter().map(|c| c.to_string()).collect(),
            ..Default::default()
        }),
        metadata: Default::default(),
        ground_truth: None,
    }
}

/// One upload chunk of f64 rows (`channels` values each) from row `start`, with its CRC-32C.
pub fn f64_chunk(
    id: &str,
    start: u64,
    channels: u32,
    values: &[f64],
) -> helmholtz_proto::v1::MeasurementChunk {
    let (bytes, crc) = helmholtz_proto::wire::encode_values(values);
    helmholtz_proto::v1::MeasurementChunk {
        session_id: id.into(),
        start_row: start,
        channels,
        values_f64le: bytes,
        crc32c: crc,
        ..Default::default()
    }
}

/// An upload stream kept open: its first chunk sent and committed; send more chunks with
/// [`OpenUpload::send`], end it with [`OpenUpload::finish`] (or drop it).
pub struct OpenUpload {
    tx: tokio::sync::mpsc::Sender<helmholtz_proto::v1::MeasurementChunk>,
    call: tokio::task::JoinHandle<Result<helmholtz_proto::v1::UploadResponse, tonic::Status>>,
}

impl OpenUpload {
    /// Opens a stream on `client` (as writer `writer`, metadata `x-helmholtz-writer`, if given),
    /// sends `first` and waits (up to 20 s) until the session's committed count reaches its end.
    pub async fn start(
        client: &Grpc,
        writer: Option<&str>,
        first: helmholtz_proto::v1::MeasurementChunk,
        rows: u64,
    ) -> OpenUpload {
        let id = first.session_id.clone();
        let end = first.start_row + rows;
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tx.send(first).await.expect("the stream is open");
        let mut request = tonic::Request::new(tokio_stream::wrappers::ReceiverStream::new(rx));
        if let Some(w) = writer {
            request
                .metadata_mut()
                .insert("x-helmholtz-writer", w.parse().expect("ASCII writer id"));
        }
        let mut uploader = client.clone();
        let call = tokio::spawn(async move {
            uploader
                .upload_measurements(request)
                .await
                .map(|r| r.into_inner())
        });
        let mut status = client.clone();
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let committed = status
                .get_upload_status(helmholtz_proto::v1::SessionRef {
                    session_id: id.clone(),
                })
                .await
                .expect("upload status")
                .into_inner()
                .committed_rows;
            if committed >= end {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "the first chunk of {id} was never committed ({committed} of {end} rows)"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        OpenUpload { tx, call }
    }

    /// Sends one more chunk (false when the server already ended the stream).
    pub async fn send(&self, chunk: helmholtz_proto::v1::MeasurementChunk) -> bool {
        self.tx.send(chunk).await.is_ok()
    }

    /// Ends the stream and returns the server's answer.
    pub async fn finish(self) -> Result<helmholtz_proto::v1::UploadResponse, tonic::Status> {
        drop(self.tx);
        self.call.await.expect("the upload task")
    }
}

/// A simulated camera session (Lambertian scene seen by a `camera` ("WxH") camera tilted 20
/// degrees, `count` Bernoulli patterns on a `side` x `side` projector, seed 4), uploaded and
/// finished by the real client binary through `api`.
pub fn simulate_camera_session(api: &ServerProcess, id: &str, camera: &str, side: u32, count: u64) {
    let spool = tempfile::tempdir().expect("spool directory");
    let out = Command::new(binary("helmholtz"))
        .args(["--server", &api.address, "--token", &api.token, "--spool"])
        .arg(spool.path())
        .args([
            "simulate",
            "--scene",
            "lambert",
            "--camera",
            camera,
            "--camera-tilt",
            "20",
            "--family",
            "bernoulli",
            "--width",
            &side.to_string(),
            "--height",
            &side.to_string(),
            "--count",
            &count.to_string(),
            "--seed",
            "4",
            "--session-id",
            id,
        ])
        .output()
        .expect("running helmholtz simulate");
    assert!(
        out.status.success(),
        "helmholtz simulate failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
