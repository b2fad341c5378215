//! The gRPC side: create a session, stream its bucket rows with resume, finish it, and request a
//! reconstruction.
//!
//! Resumable upload: a row's identity is (session, index), and a row counts as stored only once
//! the server has confirmed it with our bytes. [`upload`] streams rows from the first one not yet
//! confirmed (streams of at most [`STREAM_BYTES`]); the server compares any rows it already holds
//! byte for byte and refuses the chunk (ALREADY_EXISTS, naming the row) when they differ, so
//! another writer's rows are never taken for ours. After a retryable failure (the server
//! restarting, a dropped connection, UNAVAILABLE, another writer holding the session (ABORTED),
//! ...) it asks the server's count again and resumes from the last confirmed row, with jittered
//! exponential backoff, for as long as [`UploadOptions::retry_for`] allows without progress.
//! Every call opens its own lazily connected channel, so a server killed and restarted on the
//! same port is simply reconnected.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::future::Future;
use std::io::IsTerminal;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use helmholtz_proto::v1::{self, acquisition_client::AcquisitionClient};
use helmholtz_proto::{PatternSpec, wire};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde::Serialize;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Endpoint;
use tonic::{Code, Status};

use crate::auth::Grpc;
use crate::rest::Reconstruction;

/// Default payload per chunk: 256 KiB of values (tonic's default message limit is 4 MiB).
pub const DEFAULT_CHUNK_BYTES: usize = 256 * 1024;

/// The most payload bytes one chunk may carry (the server's default `max_chunk_bytes`): chunk
/// sizes are capped here whatever `--chunk-rows` says (at least one row a chunk).
pub const MAX_CHUNK_BYTES: usize = 8 << 20;

/// The most pixels one camera frame may have (the server's cap: 256 x 256).
pub const MAX_FRAME_PIXELS: u64 = 65_536;

/// The most values a camera session's ground truth (`m * k`, one row of T per camera pixel) may
/// hold; larger sessions send none.
pub const MAX_CAMERA_GROUND_TRUTH: usize = 4_194_304;

pub use helmholtz_proto::wire::{SampleBuf, SampleFormat, Samples};

/// Jittered exponential backoff: attempt `n` waits `min(max, initial · multiplier^n)` scaled by a
/// uniform factor in `[1 - jitter, 1]` (so concurrent clients do not retry in lock step).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Backoff {
    pub initial: Duration,
    pub max: Duration,
    pub multiplier: f64,
    /// In [0, 1]: 0 = no jitter, 1 = "full jitter".
    pub jitter: f64,
}

impl Default for Backoff {
    fn default() -> Self {
        Backoff {
            initial: Duration::from_millis(100),
            max: Duration::from_secs(5),
            multiplier: 2.0,
            jitter: 0.5,
        }
    }
}

impl Backoff {
    /// The un-jittered ceiling of attempt `attempt` (0-based).
    pub fn ceiling(&self, attempt: u32) -> Duration {
        let secs = self.initial.as_secs_f64() * self.multiplier.powi(attempt.min(64) as i32);
        Duration::from_secs_f64(secs.min(self.max.as_secs_f64()))
    }

    /// The delay before retry `attempt`, given `unit` uniform in [0, 1).
    pub fn delay(&self, attempt: u32, unit: f64) -> Duration {
        let jitter = self.jitter.clamp(0.0, 1.0);
        self.ceiling(attempt)
            .mul_f64(1.0 - jitter * unit.clamp(0.0, 1.0))
    }

    /// [`Backoff::delay`] with a fresh uniform draw.
    pub fn random_delay(&self, attempt: u32) -> Duration {
        self.delay(attempt, rand::random::<f64>())
    }
}

/// How long idempotent calls keep retrying retryable failures.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RetryPolicy {
    /// Give up once failures have gone on this long without progress.
    pub retry_for: Duration,
    pub backoff: Backoff,
    /// Deadline of one unary call.
    pub rpc_timeout: Duration,
    /// Deadline of establishing a connection.
    pub connect_timeout: Duration,
}

impl Default for RetryPolicy {
    fn default() -> Self {
        RetryPolicy {
            retry_for: Duration::from_secs(60),
            backoff: Backoff::default(),
            rpc_timeout: Duration::from_secs(30),
            connect_timeout: Duration::from_secs(5),
        }
    }
}

/// Options of [`upload`].
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct UploadOptions {
    /// Rows per chunk; `None` = about [`DEFAULT_CHUNK_BYTES`] of values per chunk.
    pub chunk_rows: Option<usize>,
    /// Keep resuming for this long without progress (default 60 s). The clock restarts whenever
    /// the server's committed count advances.
    pub retry_for: Duration,
    pub backoff: Backoff,
    /// Deadline of each GetUploadStatus call.
    pub rpc_timeout: Duration,
    pub connect_timeout: Duration,
    /// Draw a progress bar on stderr (only if stderr is a terminal).
    pub progress: bool,
}

impl Default for UploadOptions {
    fn default() -> Self {
        let retry = RetryPolicy::default();
        UploadOptions {
            chunk_rows: None,
            retry_for: retry.retry_for,
            backoff: retry.backoff,
            rpc_timeout: retry.rpc_timeout,
            connect_timeout: retry.connect_timeout,
            progress: false,
        }
    }
}

impl UploadOptions {
    /// The retry policy of the unary calls an upload makes.
    pub fn policy(&self) -> RetryPolicy {
        RetryPolicy {
            retry_for: self.retry_for,
            backoff: self.backoff.clone(),
            rpc_timeout: self.rpc_timeout,
            connect_timeout: self.connect_timeout,
        }
    }

    /// Rows per chunk for `channels` channels of f64 values.
    pub fn rows_per_chunk(&self, channels: usize) -> usize {
        self.rows_per_chunk_of(channels, SampleFormat::F64)
    }

    /// Rows (whole frames, for a camera) per chunk for `channels` values a row in `format`:
    /// `chunk_rows`, else about [`DEFAULT_CHUNK_BYTES`]; never more than [`MAX_CHUNK_BYTES`] of
    /// payload (unless a single row is larger), never less than one row.
    pub fn rows_per_chunk_of(&self, channels: usize, format: SampleFormat) -> usize {
        let row_bytes = format.bytes() * channels.max(1);
        self.chunk_rows
            .unwrap_or(DEFAULT_CHUNK_BYTES / row_bytes)
            .min(MAX_CHUNK_BYTES / row_bytes)
            .max(1)
    }
}

/// What [`upload`] did.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct UploadReport {
    pub session_id: String,
    /// Rows given to upload.
    pub rows: u64,
    /// Rows put on the wire, re-sends after a resume included.
    pub rows_sent: u64,
    /// Rows the server reported as newly written, over the streams that completed.
    pub rows_written: u64,
    /// Rows the server already held and compared byte for byte equal to ours (a resumed or
    /// repeated upload), over the streams that completed.
    pub rows_matched: u64,
    /// Rows `0..confirmed_rows` of the source are stored on the server with exactly our bytes
    /// (each was written or compared equal by a stream that ended OK). Only these may be
    /// deleted from a spool.
    pub confirmed_rows: u64,
    /// Times the upload re-asked the server's count and resumed after a failure.
    pub resumes: u32,
    /// The server's committed count at the end (authoritative).
    pub committed_rows: u64,
    /// Rows the session's spec declares.
    pub expected_rows: u64,
    pub chunks_sent: u64,
    pub bytes_sent: u64,
    pub seconds: f64,
    /// The last failure that was retried, if any.
    pub last_error: Option<String>,
}

/// A gRPC call refused by the server or failed in transport.
#[derive(Debug, thiserror::Error)]
#[error("{operation}: {} ({}){}", message_or_description(.message, *.code), code_name(*.code), hint(*.code))]
pub struct RpcError {
    pub operation: String,
    pub code: Code,
    pub message: String,
}

impl RpcError {
    pub fn new(operation: impl Into<String>, status: &Status) -> Self {
        let id = crate::auth::request_id(status).map(|id| format!(" [request id {id}]"));
        RpcError {
            operation: operation.into(),
            code: status.code(),
            message: format!("{}{}", status.message(), id.unwrap_or_default()),
        }
    }
}

fn message_or_description(message: &str, code: Code) -> String {
    if message.is_empty() {
        code.description().to_string()
    } else {
        message.to_string()
    }
}

fn hint(code: Code) -> &'static str {
    match code {
        Code::Unavailable => "; is the server running at that address?",
        Code::AlreadyExists => {
            "; the server holds other data under this id: pick another --session-id (or repeat the original declaration)"
        }
        _ => "",
    }
}

/// The canonical gRPC name of a status code, e.g. `INVALID_ARGUMENT`.
pub fn code_name(code: Code) -> &'static str {
    match code {
        Code::Ok => "OK",
        Code::Cancelled => "CANCELLED",
        Code::Unknown => "UNKNOWN",
        Code::InvalidArgument => "INVALID_ARGUMENT",
        Code::DeadlineExceeded => "DEADLINE_EXCEEDED",
        Code::NotFound => "NOT_FOUND",
        Code::AlreadyExists => "ALREADY_EXISTS",
        Code::PermissionDenied => "PERMISSION_DENIED",
        Code::ResourceExhausted => "RESOURCE_EXHAUSTED",
        Code::FailedPrecondition => "FAILED_PRECONDITION",
        Code::Aborted => "ABORTED",
        Code::OutOfRange => "OUT_OF_RANGE",
        Code::Unimplemented => "UNIMPLEMENTED",
        Code::Internal => "INTERNAL",
        Code::Unavailable => "UNAVAILABLE",
        Code::DataLoss => "DATA_LOSS",
        Code::Unauthenticated => "UNAUTHENTICATED",
    }
}

/// What to do after a failed call.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Disposition {
    /// Transient: back off, re-ask the committed count, resume.
    Retry,
    /// The server's count disagrees with ours (a gap, OUT_OF_RANGE) or a chunk was damaged in
    /// transit (DATA_LOSS): re-ask the count once and resume; a second time in a row is fatal.
    ResyncOnce,
    /// The request itself is wrong: retrying cannot help.
    Fatal,
}

/// Classifies a gRPC status code for retrying.
pub fn disposition(code: Code) -> Disposition {
    match code {
        Code::Unavailable
        | Code::DeadlineExceeded
        | Code::Internal
        | Code::Unknown
        | Code::Aborted
        | Code::ResourceExhausted
        | Code::Cancelled => Disposition::Retry,
        Code::OutOfRange | Code::DataLoss => Disposition::ResyncOnce,
        _ => Disposition::Fatal,
    }
}

/// A lazily connecting client: no I/O happens until the first call, and a fresh one is made for
/// each attempt so a restarted server is found again.
pub fn connect(server: &str, connect_timeout: Duration) -> anyhow::Result<Grpc> {
    let (server, token) = crate::auth::split_server(server);
    let endpoint = Endpoint::from_shared(server.clone())
        .with_context(|| {
            format!(
                "invalid server address {server:?} (expected e.g. http://127.0.0.1:8080 or https://host:port)"
            )
        })?
        .connect_timeout(connect_timeout)
        .tcp_nodelay(true)
        .http2_keep_alive_interval(Duration::from_secs(10))
        .keep_alive_timeout(Duration::from_secs(20));
    // https://: verified against the system roots and the lab's CA (--ca-file, see `tls`).
    let endpoint = if crate::tls::is_https(&server) {
        endpoint
            .tls_config(crate::tls::grpc_config())
            .context("TLS settings for the gRPC channel")?
    } else {
        endpoint
    };
    let bearer = crate::auth::Bearer::new(token.as_deref())?;
    Ok(
        AcquisitionClient::with_interceptor(endpoint.connect_lazy(), bearer)
            .max_decoding_message_size(64 << 20)
            .max_encoding_message_size(usize::MAX),
    )
}

/// Runs an idempotent unary call, retrying retryable failures per `policy`.
async fn unary<T, F, Fut>(
    server: &str,
    policy: &RetryPolicy,
    operation: &str,
    mut call: F,
) -> anyhow::Result<T>
where
    F: FnMut(Grpc) -> Fut,
    Fut: Future<Output = Result<tonic::Response<T>, Status>>,
{
    let started = Instant::now();
    let mut attempt = 0u32;
    loop {
        let client = connect(server, policy.connect_timeout)?;
        let status = match tokio::time::timeout(policy.rpc_timeout, call(client)).await {
            Ok(Ok(response)) => return Ok(response.into_inner()),
            Ok(Err(status)) => status,
            Err(_) => {
                Status::deadline_exceeded(format!("no answer within {:?}", policy.rpc_timeout))
            }
        };
        if disposition(status.code()) != Disposition::Retry
            || started.elapsed() >= policy.retry_for
            || crate::tls::is_certificate_error(&status)
        {
            return Err(RpcError::new(operation, &status).into());
        }
        let remaining = policy.retry_for.saturating_sub(started.elapsed());
        tokio::time::sleep(policy.backoff.random_delay(attempt).min(remaining)).await;
        attempt += 1;
    }
}

/// A session to create: the declaration the server checks idempotently.
#[derive(Clone, Debug, PartialEq)]
pub struct NewSession {
    /// 1-128 characters of `[A-Za-z0-9._-]`, generated by the client.
    pub session_id: String,
    /// The rig's name (1-128 printable characters); [`NewSession::new`] starts with "rig".
    pub rig: String,
    pub spec: PatternSpec,
    /// One name per bucket channel (empty for a camera session).
    pub channels: Vec<String>,
    /// Optional: per bucket channel, the unit direction from the scene toward its detector
    /// (empty: unknown).
    pub directions: Vec<[f64; 3]>,
    /// A camera in place of bucket detectors: each row is a `width x height` frame.
    pub camera: Option<CameraLayout>,
    pub metadata: BTreeMap<String, String>,
    /// The noiseless scene of a simulated rig, so the server can score reconstructions.
    pub ground_truth: Option<v1::GroundTruth>,
}

/// A camera session's frames: `width x height` pixels (row-major) in `format` (F32 or U16).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct CameraLayout {
    pub width: u32,
    pub height: u32,
    pub format: SampleFormat,
}

impl CameraLayout {
    /// Pixels of one frame: the session's channel count.
    pub fn pixels(&self) -> u64 {
        self.width as u64 * self.height as u64
    }

    /// Checks the layout the server will accept: 1..=65,536 pixels, F32 or U16.
    pub fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            self.width > 0 && self.height > 0,
            "camera frames must be at least 1x1, got {}x{}",
            self.width,
            self.height
        );
        anyhow::ensure!(
            self.pixels() <= MAX_FRAME_PIXELS,
            "a {}x{} camera frame has {} pixels; the most is {MAX_FRAME_PIXELS} (256x256)",
            self.width,
            self.height,
            self.pixels()
        );
        anyhow::ensure!(
            self.format != SampleFormat::F64,
            "camera frames are f32 or u16, not f64"
        );
        Ok(())
    }
}

impl NewSession {
    pub fn new(session_id: impl Into<String>, spec: PatternSpec, channels: Vec<String>) -> Self {
        NewSession {
            session_id: session_id.into(),
            rig: "rig".to_string(),
            spec,
            channels,
            directions: Vec::new(),
            camera: None,
            metadata: BTreeMap::new(),
            ground_truth: None,
        }
    }

    /// A camera session: every pattern's row is a `width x height` frame in `format`.
    pub fn camera(
        session_id: impl Into<String>,
        spec: PatternSpec,
        width: u32,
        height: u32,
        format: SampleFormat,
    ) -> Self {
        NewSession {
            camera: Some(CameraLayout {
                width,
                height,
                format,
            }),
            ..NewSession::new(session_id, spec, Vec::new())
        }
    }

    /// Declares the direction toward each bucket channel's detector (one per channel).
    pub fn with_directions(mut self, directions: Vec<[f64; 3]>) -> Self {
        self.directions = directions;
        self
    }

    /// Values per row: the bucket channels, or a camera frame's pixels.
    pub fn channel_count(&self) -> u32 {
        match &self.camera {
            Some(c) => c.pixels() as u32,
            None => self.channels.len() as u32,
        }
    }

    /// The format rows are stored and sent in.
    pub fn sample_format(&self) -> SampleFormat {
        self.camera.map(|c| c.format).unwrap_or(SampleFormat::F64)
    }

    /// Checks the detector declaration: bucket channels (with one unit direction each, if
    /// any), or a valid camera and no channels.
    pub fn validate(&self) -> anyhow::Result<()> {
        match &self.camera {
            Some(camera) => {
                camera.validate()?;
                anyhow::ensure!(
                    self.channels.is_empty() && self.directions.is_empty(),
                    "a camera session has no bucket channels or detector directions"
                );
            }
            None => {
                anyhow::ensure!(
                    !self.channels.is_empty(),
                    "a session needs at least one channel"
                );
                anyhow::ensure!(
                    self.directions.is_empty() || self.directions.len() == self.channels.len(),
                    "{} detector directions given for {} channels (one per channel, or none)",
                    self.directions.len(),
                    self.channels.len()
                );
                for (d, name) in self.directions.iter().zip(&self.channels) {
                    let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    anyhow::ensure!(
                        d.iter().all(|v| v.is_finite()) && (norm - 1.0).abs() < 1e-9,
                        "the direction of channel {name} must be a unit vector, got {d:?}"
                    );
                }
            }
        }
        Ok(())
    }

    pub fn with_rig(mut self, rig: impl Into<String>) -> Self {
        self.rig = rig.into();
        self
    }

    pub fn with_metadata(mut self, key: impl Into<String>, value: impl Into<String>) -> Self {
        self.metadata.insert(key.into(), value.into());
        self
    }

    /// `width x height`: the pattern grid. `transport`: the noiseless transport, row-major:
    /// `width * height` values (every channel's), or one such image per channel, channel after
    /// channel; for a camera session `m * k` values (one row of T per camera pixel).
    pub fn with_ground_truth(mut self, width: u32, height: u32, transport: Vec<f32>) -> Self {
        self.ground_truth = Some(v1::GroundTruth {
            width,
            height,
            transport,
        });
        self
    }

    pub fn to_request(&self) -> v1::CreateSessionRequest {
        v1::CreateSessionRequest {
            session_id: self.session_id.clone(),
            rig: self.rig.clone(),
            patterns: Some(v1::PatternSpec::from(&self.spec)),
            detector: Some(v1::DetectorLayout {
                channels: self.channels.clone(),
                directions: self
                    .directions
                    .iter()
                    .map(|d| v1::Direction {
                        x: d[0],
                        y: d[1],
                        z: d[2],
                    })
                    .collect(),
                camera: self.camera.map(|c| v1::CameraLayout {
                    width: c.width,
                    height: c.height,
                    format: c.format.to_proto() as i32,
                }),
            }),
            metadata: self.metadata.clone().into_iter().collect(),
            ground_truth: self.ground_truth.clone(),
        }
    }
}

/// Result of [`create_session`].
#[derive(Clone, Debug, PartialEq)]
pub struct CreatedSession {
    /// False when the session already existed with the same declaration.
    pub created: bool,
    pub session: v1::Session,
}

/// True for ids the server accepts: 1-128 characters of `[A-Za-z0-9._-]`, but not `.` or `..`.
pub fn valid_session_id(id: &str) -> bool {
    (1..=128).contains(&id.len())
        && id != "."
        && id != ".."
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

/// Creates the session (idempotent: the same declaration again returns the existing session with
/// `created = false`; a different one fails with ALREADY_EXISTS). Retries transient failures.
pub async fn create_session(server: &str, session: &NewSession) -> anyhow::Result<CreatedSession> {
    anyhow::ensure!(
        valid_session_id(&session.session_id),
        "session id {:?} must be 1-128 characters of A-Z a-z 0-9 . _ - (and not . or ..)",
        session.session_id
    );
    session.validate()?;
    create_session_request(server, &session.to_request(), &RetryPolicy::default()).await
}

/// [`create_session`] from the wire request (as kept in a spool manifest), retrying transient
/// failures per `policy`.
pub async fn create_session_request(
    server: &str,
    request: &v1::CreateSessionRequest,
    policy: &RetryPolicy,
) -> anyhow::Result<CreatedSession> {
    let operation = format!("creating session {}", request.session_id);
    let response = unary(server, policy, &operation, |mut c| {
        let request = request.clone();
        async move { c.create_session(request).await }
    })
    .await?;
    let session = response
        .session
        .context("server answered CreateSession without a session")?;
    Ok(CreatedSession {
        created: response.created,
        session,
    })
}

/// The server's committed and expected row counts of a session. Retries transient failures.
pub async fn upload_status(server: &str, session_id: &str) -> anyhow::Result<v1::UploadStatus> {
    status_with(server, session_id, &RetryPolicy::default()).await
}

/// [`upload_status`] with its own retry policy (`retry_for` zero: a single attempt).
pub async fn upload_status_with(
    server: &str,
    session_id: &str,
    policy: &RetryPolicy,
) -> anyhow::Result<v1::UploadStatus> {
    status_with(server, session_id, policy).await
}

async fn status_with(
    server: &str,
    session_id: &str,
    policy: &RetryPolicy,
) -> anyhow::Result<v1::UploadStatus> {
    let request = v1::SessionRef {
        session_id: session_id.to_string(),
    };
    unary(
        server,
        policy,
        &format!("upload status of session {session_id}"),
        |mut c| {
            let request = request.clone();
            async move { c.get_upload_status(request).await }
        },
    )
    .await
}

/// Marks the session finished (every row of the spec must be committed; finishing twice is
/// harmless). Retries transient failures.
pub async fn finish_session(server: &str, session_id: &str) -> anyhow::Result<v1::Session> {
    let request = v1::SessionRef {
        session_id: session_id.to_string(),
    };
    unary(
        server,
        &RetryPolicy::default(),
        &format!("finishing session {session_id}"),
        |mut c| {
            let request = request.clone();
            async move { c.finish_session(request).await }
        },
    )
    .await
}

/// Requests a reconstruction over gRPC. `method`: "gi", "dgi", "ngi", "direct", "lsq", "cs" or "tv"; `params` a
/// JSON object (`{}` for the defaults). Not retried: each call queues a new job.
pub async fn request_reconstruction(
    server: &str,
    session_id: &str,
    method: &str,
    params: &serde_json::Value,
) -> anyhow::Result<Reconstruction> {
    anyhow::ensure!(
        params.is_object(),
        "reconstruction params must be a JSON object, got {params}"
    );
    let request = v1::ReconstructionRequest {
        session_id: session_id.to_string(),
        method: method.to_string(),
        params_json: params.to_string(),
    };
    let mut client = connect(server, RetryPolicy::default().connect_timeout)?;
    let operation = format!("requesting a {method} reconstruction of session {session_id}");
    let response = client
        .request_reconstruction(request)
        .await
        .map_err(|s| RpcError::new(operation, &s))?;
    Ok(Reconstruction::from(response.into_inner()))
}

/// Streams `values` (`rows x channels`, row-major: every row of the session from row 0) to
/// session `session_id`, starting at the server's committed count and resuming after failures
/// (see the module docs). Rows the server already has are not sent again. `values` may hold
/// fewer rows than the spec (a prefix; finish later), never more.
///
/// Errors: a fatal status (INVALID_ARGUMENT, FAILED_PRECONDITION, NOT_FOUND, ALREADY_EXISTS,
/// PERMISSION_DENIED, ...; or OUT_OF_RANGE / DATA_LOSS twice in a row) ends the upload at once;
/// retryable ones end it after `opts.retry_for` without progress. The error is an [`RpcError`]
/// (downcast it for the code) with the rows committed so far in its context.
pub async fn upload(
    server: &str,
    session_id: &str,
    channels: u32,
    values: &[f64],
    opts: &UploadOptions,
) -> anyhow::Result<UploadReport> {
    let ch = channels as usize;
    anyhow::ensure!(ch > 0, "channels must be at least 1");
    anyhow::ensure!(
        values.len().is_multiple_of(ch),
        "{} values are not a whole number of rows of {ch} channels",
        values.len()
    );
    if let Some(pos) = values.iter().position(|v| !v.is_finite()) {
        anyhow::bail!(
            "value at row {}, channel {} is not finite ({})",
            pos / ch,
            pos % ch,
            values[pos]
        );
    }
    upload_rows(
        server,
        session_id,
        channels,
        &SliceRows {
            values,
            channels: ch,
        },
        opts,
    )
    .await
}

/// The rows an upload reads: rows `0..rows()` of a session (row-major, `channels` values a row),
/// in memory ([`upload`]) or in a durable spool ([`crate::spool`]).
pub trait RowSource: Sync {
    /// Rows that can be read now.
    fn rows(&self) -> u64;
    /// The values of rows `start..end` (`end <= rows()`), row-major, widened to f64.
    fn read(&self, start: u64, end: u64) -> anyhow::Result<Cow<'_, [f64]>>;
    /// The format the rows are sent in (f64 unless a camera session's f32 / u16 frames).
    fn format(&self) -> SampleFormat {
        SampleFormat::F64
    }
    /// Rows `start..end` as the chunk payload: little-endian values of [`RowSource::format`].
    fn read_payload(&self, start: u64, end: u64) -> anyhow::Result<Vec<u8>> {
        let values = self.read(start, end)?;
        Ok(Samples::F64(&values).encode())
    }
}

/// Rows in memory in any sample format (`channels` values a row).
pub struct SampleRows<'a> {
    pub samples: Samples<'a>,
    pub channels: usize,
}

impl RowSource for SampleRows<'_> {
    fn rows(&self) -> u64 {
        (self.samples.len() / self.channels.max(1)) as u64
    }

    fn read(&self, start: u64, end: u64) -> anyhow::Result<Cow<'_, [f64]>> {
        let ch = self.channels;
        Ok(Cow::Owned(
            (start as usize * ch..end as usize * ch)
                .map(|i| self.samples.get_f64(i))
                .collect(),
        ))
    }

    fn format(&self) -> SampleFormat {
        self.samples.format()
    }

    fn read_payload(&self, start: u64, end: u64) -> anyhow::Result<Vec<u8>> {
        let ch = self.channels;
        Ok(self
            .samples
            .encode_range(start as usize * ch, end as usize * ch))
    }
}

/// [`upload`] for rows in any sample format (a camera session's f32 or u16 frames: `channels`
/// = pixels per frame, whole frames only).
pub async fn upload_samples(
    server: &str,
    session_id: &str,
    channels: u32,
    samples: Samples<'_>,
    opts: &UploadOptions,
) -> anyhow::Result<UploadReport> {
    let ch = channels as usize;
    anyhow::ensure!(ch > 0, "channels must be at least 1");
    anyhow::ensure!(
        samples.len().is_multiple_of(ch),
        "{} values are not a whole number of rows of {ch} values",
        samples.len()
    );
    if let Some(pos) = samples.first_non_finite() {
        anyhow::bail!(
            "value at row {}, column {} is not finite ({})",
            pos / ch,
            pos % ch,
            samples.get_f64(pos)
        );
    }
    upload_rows(
        server,
        session_id,
        channels,
        &SampleRows {
            samples,
            channels: ch,
        },
        opts,
    )
    .await
}

struct SliceRows<'a> {
    values: &'a [f64],
    channels: usize,
}

impl RowSource for SliceRows<'_> {
    fn rows(&self) -> u64 {
        (self.values.len() / self.channels) as u64
    }

    fn read(&self, start: u64, end: u64) -> anyhow::Result<Cow<'_, [f64]>> {
        let ch = self.channels;
        Ok(Cow::Borrowed(
            &self.values[start as usize * ch..end as usize * ch],
        ))
    }
}

/// [`upload`] from any [`RowSource`], from row 0; see [`upload_rows_from`].
pub async fn upload_rows(
    server: &str,
    session_id: &str,
    channels: u32,
    source: &dyn RowSource,
    opts: &UploadOptions,
) -> anyhow::Result<UploadReport> {
    upload_rows_from(server, session_id, channels, source, 0, opts).await
}

/// The most payload one upload stream carries before it ends and a new one starts: a stream
/// that ends OK confirms its rows, so a failure re-sends at most this much.
pub const STREAM_BYTES: usize = 64 << 20;

/// Uploads rows `confirmed..source.rows()` of `source`, where rows below `confirmed` are
/// already known to be stored with the same bytes (a spool's confirmed prefix).
///
/// Nothing is skipped on the server's word: every row is sent at least once, and the server
/// compares rows it already holds byte for byte (a resumed upload re-sends the last unconfirmed
/// stream, at most [`STREAM_BYTES`]). So rows of another writer or another file under the same
/// session id are refused (ALREADY_EXISTS naming the first differing row), never taken for
/// ours. Streams of at most [`STREAM_BYTES`] each confirm their rows when they end OK
/// ([`UploadReport::confirmed_rows`]). The source's values must be finite.
pub async fn upload_rows_from(
    server: &str,
    session_id: &str,
    channels: u32,
    source: &dyn RowSource,
    confirmed: u64,
    opts: &UploadOptions,
) -> anyhow::Result<UploadReport> {
    let writer = new_writer_id();
    upload_rows_as(
        server, session_id, channels, source, confirmed, opts, &writer,
    )
    .await
}

/// A fresh writer id for [`upload_rows_as`]: 128 random bits in hex.
pub fn new_writer_id() -> String {
    format!("{:032x}", rand::random::<u128>())
}

/// [`upload_rows_from`] as writer `writer`: every stream carries it (metadata
/// `x-helmholtz-writer`), so when a connection is cut without the server noticing, the next
/// stream of the same upload takes the session over from the stale one at once instead of
/// being refused as a second writer until the stale stream times out. Another writer's streams
/// are still refused (ABORTED).
pub async fn upload_rows_as(
    server: &str,
    session_id: &str,
    channels: u32,
    source: &dyn RowSource,
    confirmed: u64,
    opts: &UploadOptions,
    writer: &str,
) -> anyhow::Result<UploadReport> {
    anyhow::ensure!(channels > 0, "channels must be at least 1");
    let total = source.rows();
    let chunk_rows = opts.rows_per_chunk_of(channels as usize, source.format());
    let row_bytes = channels as usize * source.format().bytes();
    let rows_a_stream = ((STREAM_BYTES / row_bytes.max(1)).max(chunk_rows) / chunk_rows).max(1)
        as u64
        * chunk_rows as u64;
    let policy = opts.policy();
    let started = Instant::now();
    let bar = progress_bar(total, opts.progress);
    let mut report = UploadReport {
        session_id: session_id.to_string(),
        rows: total,
        confirmed_rows: confirmed.min(total),
        ..Default::default()
    };
    let mut confirmed = confirmed.min(total);

    let mut asked = false;
    let mut failing_since: Option<Instant> = None;
    let mut attempt = 0u32;
    let mut resync_used = false;

    // Waits before the next attempt, or gives up once failures have lasted `retry_for`.
    macro_rules! back_off_or_fail {
        ($err:expr) => {{
            let err: RpcError = $err;
            let since = *failing_since.get_or_insert_with(Instant::now);
            if since.elapsed() >= policy.retry_for {
                bar.abandon();
                return Err(anyhow::Error::new(err).context(format!(
                    "upload of session {session_id} gave up after {:.0?} without progress; {confirmed} of {total} rows confirmed stored",
                    policy.retry_for,
                )));
            }
            report.last_error = Some(err.to_string());
            bar.set_message(format!("retrying: {}", err));
            let remaining = policy.retry_for.saturating_sub(since.elapsed());
            tokio::time::sleep(policy.backoff.random_delay(attempt).min(remaining)).await;
            attempt += 1;
        }};
    }
    macro_rules! fatal {
        ($err:expr) => {{
            bar.abandon();
            return Err(anyhow::Error::new($err).context(format!(
                "upload of session {session_id} failed; {confirmed} of {total} rows confirmed stored"
            )));
        }};
    }

    while confirmed < total || !asked {
        // 1. Where does the server stand?
        let status_policy = RetryPolicy {
            retry_for: Duration::ZERO,
            ..policy.clone()
        };
        let status = match status_with(server, session_id, &status_policy).await {
            Ok(s) => s,
            Err(e) => {
                let err = e.downcast::<RpcError>()?;
                match disposition(err.code) {
                    Disposition::Fatal => fatal!(err),
                    _ => {
                        back_off_or_fail!(err);
                        continue;
                    }
                }
            }
        };
        let committed = status.committed_rows;
        if !asked {
            asked = true;
            report.expected_rows = status.expected_rows;
            if status.expected_rows > 0 && total > status.expected_rows {
                bar.abandon();
                anyhow::bail!(
                    "{total} rows given but session {session_id} expects {} (its spec's count)",
                    status.expected_rows
                );
            }
        }
        report.committed_rows = committed;
        if confirmed >= total {
            break;
        }
        if status.state == v1::SessionState::Finished as i32 && total > committed {
            fatal!(RpcError {
                operation: format!("uploading to session {session_id}"),
                code: Code::FailedPrecondition,
                message: format!(
                    "the session is finished with {committed} rows; rows {committed}..{total} were never stored and never will be (kept where they are)"
                ),
            });
        }

        // 2. Stream from the first unconfirmed row (the server compares what it already has);
        // below the server's count only if it lost rows we confirmed (the source says so).
        let from = confirmed.min(committed);
        let to = (from + rows_a_stream).min(total);
        let outcome = stream_rows(
            server,
            session_id,
            writer,
            channels,
            source,
            to,
            from,
            chunk_rows,
            opts,
            &bar,
            &mut report,
        )
        .await;
        match outcome {
            Ok(response) => {
                report.rows_written += response.rows_written;
                report.rows_matched += response.rows_skipped;
                report.committed_rows = response.committed_rows;
                if to > confirmed {
                    confirmed = to;
                    report.confirmed_rows = confirmed;
                    failing_since = None;
                    attempt = 0;
                    resync_used = false;
                }
                bar.set_position(confirmed);
            }
            Err(StreamFailure::Local(e)) => {
                bar.abandon();
                return Err(e.context(format!(
                    "upload of session {session_id} stopped: cannot read its rows; {confirmed} of {total} rows confirmed stored"
                )));
            }
            Err(StreamFailure::Rpc(status)) => {
                let err = RpcError::new(format!("uploading to session {session_id}"), &status);
                match disposition(status.code()) {
                    Disposition::Fatal => fatal!(err),
                    Disposition::ResyncOnce if resync_used => fatal!(err),
                    Disposition::ResyncOnce => {
                        resync_used = true;
                        report.last_error = Some(err.to_string());
                    }
                    Disposition::Retry => back_off_or_fail!(err),
                }
                report.resumes += 1;
                bar.set_message(format!("resumed {}x", report.resumes));
            }
        }
    }
    report.seconds = started.elapsed().as_secs_f64();
    bar.finish_with_message(if report.resumes > 0 {
        format!("done, resumed {}x", report.resumes)
    } else {
        "done".to_string()
    });
    Ok(report)
}

/// The chunks of rows `from..total`: (start_row, values slice).
pub fn chunk_ranges(
    total_rows: u64,
    from: u64,
    chunk_rows: usize,
) -> impl Iterator<Item = (u64, u64)> {
    let step = chunk_rows.max(1) as u64;
    (from..total_rows)
        .step_by(step as usize)
        .map(move |s| (s, (s + step).min(total_rows)))
}

/// One chunk message carrying `payload` (rows from `start_row`, little-endian values of
/// `format`) in the field of that format, with its CRC-32C.
pub fn encode_chunk(
    session_id: &str,
    channels: u32,
    format: SampleFormat,
    start_row: u64,
    payload: Vec<u8>,
) -> v1::MeasurementChunk {
    let crc32c = crc32c::crc32c(&payload);
    let mut chunk = v1::MeasurementChunk {
        session_id: session_id.to_string(),
        start_row,
        channels,
        crc32c,
        ..Default::default()
    };
    match format {
        SampleFormat::F64 => chunk.values_f64le = payload,
        SampleFormat::F32 => chunk.values_f32le = payload,
        SampleFormat::U16 => chunk.values_u16le = payload,
    }
    chunk
}

/// The payload bytes a chunk carries (whichever field is set).
pub fn chunk_payload_len(chunk: &v1::MeasurementChunk) -> usize {
    chunk.values_f64le.len() + chunk.values_f32le.len() + chunk.values_u16le.len()
}

/// The chunk of rows `start..end` read from `source`.
pub fn read_chunk(
    session_id: &str,
    channels: u32,
    source: &dyn RowSource,
    start: u64,
    end: u64,
) -> anyhow::Result<v1::MeasurementChunk> {
    let payload = source.read_payload(start, end)?;
    let format = source.format();
    anyhow::ensure!(
        payload.len() as u64 == (end - start) * channels as u64 * format.bytes() as u64,
        "rows {start}..{end}: {} payload bytes read, not whole rows of {channels} {} values",
        payload.len(),
        format.name()
    );
    Ok(encode_chunk(session_id, channels, format, start, payload))
}

/// One chunk message for rows `start..end` of `values`.
pub fn make_chunk(
    session_id: &str,
    channels: u32,
    values: &[f64],
    start: u64,
    end: u64,
) -> v1::MeasurementChunk {
    let ch = channels as usize;
    let (bytes, crc) = wire::encode_values(&values[start as usize * ch..end as usize * ch]);
    v1::MeasurementChunk {
        session_id: session_id.to_string(),
        start_row: start,
        channels,
        values_f64le: bytes,
        crc32c: crc,
        ..Default::default()
    }
}

/// Why one stream of chunks ended early.
enum StreamFailure {
    /// The server or the transport refused it.
    Rpc(Status),
    /// The rows could not be read locally (a damaged spool): not retried.
    Local(anyhow::Error),
}

/// One client stream of chunks from row `from` to `total`; the chunks are read and encoded as
/// the transport takes them (at most a few in flight), so memory stays bounded whatever the
/// session size.
#[allow(clippy::too_many_arguments)]
async fn stream_rows(
    server: &str,
    session_id: &str,
    writer: &str,
    channels: u32,
    source: &dyn RowSource,
    total: u64,
    from: u64,
    chunk_rows: usize,
    opts: &UploadOptions,
    bar: &ProgressBar,
    report: &mut UploadReport,
) -> Result<v1::UploadResponse, StreamFailure> {
    let mut client = connect(server, opts.connect_timeout)
        .map_err(|e| StreamFailure::Rpc(Status::invalid_argument(e.to_string())))?;
    let (tx, rx) = tokio::sync::mpsc::channel::<v1::MeasurementChunk>(2);
    // Counters shared with the producer (atomics keep the upload future `Send`).
    let rows_sent = AtomicU64::new(0);
    let chunks_sent = AtomicU64::new(0);
    let bytes_sent = AtomicU64::new(0);
    let read_error = std::sync::Mutex::new(None::<anyhow::Error>);
    let producer = async {
        let tx = tx; // dropped when the producer ends: the end of the stream
        for (start, end) in chunk_ranges(total, from, chunk_rows) {
            let chunk = match read_chunk(session_id, channels, source, start, end) {
                Ok(c) => c,
                Err(e) => {
                    *read_error.lock().expect("not poisoned") = Some(e);
                    return;
                }
            };
            let bytes = chunk_payload_len(&chunk) as u64;
            if tx.send(chunk).await.is_err() {
                return; // the call ended; its result says why
            }
            rows_sent.fetch_add(end - start, Ordering::Relaxed);
            chunks_sent.fetch_add(1, Ordering::Relaxed);
            bytes_sent.fetch_add(bytes, Ordering::Relaxed);
            bar.set_position(end);
        }
    };
    let mut request = tonic::Request::new(ReceiverStream::new(rx));
    if let Ok(value) = writer.parse() {
        request.metadata_mut().insert("x-helmholtz-writer", value);
    }
    let call = client.upload_measurements(request);
    tokio::pin!(producer);
    tokio::pin!(call);
    let mut producing = true;
    let result = loop {
        tokio::select! {
            result = &mut call => break result,
            _ = &mut producer, if producing => producing = false,
        }
    };
    report.rows_sent += rows_sent.load(Ordering::Relaxed);
    report.chunks_sent += chunks_sent.load(Ordering::Relaxed);
    report.bytes_sent += bytes_sent.load(Ordering::Relaxed);
    if let Some(e) = read_error.lock().expect("not poisoned").take() {
        return Err(StreamFailure::Local(e));
    }
    result
        .map(tonic::Response::into_inner)
        .map_err(StreamFailure::Rpc)
}

/// A rows progress bar on stderr, hidden unless wanted and stderr is a terminal.
pub(crate) fn progress_bar(len: u64, wanted: bool) -> ProgressBar {
    if !wanted || !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
    bar.set_style(
        ProgressStyle::with_template(
            "{prefix:>10} [{bar:40.cyan/blue}] {human_pos}/{human_len} rows {per_sec} eta {eta} {msg}",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    bar.set_prefix("uploading");
    bar
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_grows_caps_and_jitters_within_bounds() {
        let b = Backoff::default();
        let ceilings: Vec<Duration> = (0..10).map(|n| b.ceiling(n)).collect();
        assert_eq!(ceilings[0], Duration::from_millis(100));
        assert_eq!(ceilings[1], Duration::from_millis(200));
        assert_eq!(ceilings[5], Duration::from_millis(3200));
        assert_eq!(ceilings[6], Duration::from_secs(5));
        assert!(ceilings.windows(2).all(|w| w[0] <= w[1]));
        for n in 0..10 {
            assert_eq!(b.delay(n, 0.0), b.ceiling(n));
            assert_eq!(
                b.delay(n, 0.999_999_999).as_millis(),
                b.ceiling(n).as_millis() / 2
            );
            for _ in 0..100 {
                let d = b.random_delay(n);
                assert!(d <= b.ceiling(n) && d >= b.ceiling(n) / 2);
            }
        }
        assert_eq!(b.ceiling(1000), Duration::from_secs(5));
        let none = Backoff { jitter: 0.0, ..b };
        assert_eq!(none.delay(3, 0.7), none.ceiling(3));
    }

    #[test]
    fn status_codes_are_classified() {
        for c in [
            Code::Unavailable,
            Code::DeadlineExceeded,
            Code::Internal,
            Code::Unknown,
            Code::Aborted,
        ] {
            assert_eq!(disposition(c), Disposition::Retry, "{c:?}");
        }
        for c in [Code::OutOfRange, Code::DataLoss] {
            assert_eq!(disposition(c), Disposition::ResyncOnce, "{c:?}");
        }
        for c in [
            Code::InvalidArgument,
            Code::FailedPrecondition,
            Code::NotFound,
            Code::AlreadyExists,
        ] {
            assert_eq!(disposition(c), Disposition::Fatal, "{c:?}");
        }
    }

    #[test]
    fn chunks_cover_rows_exactly_once_with_correct_crcs() {
        let channels = 3u32;
        let rows = 1000u64;
        let values: Vec<f64> = (0..rows * 3).map(|v| v as f64 * 0.25).collect();
        for (from, per) in [(0, 64), (7, 64), (999, 10), (0, 1000), (0, 5000), (1000, 3)] {
            let mut next = from;
            for (s, e) in chunk_ranges(rows, from, per) {
                assert_eq!(s, next);
                assert!(e > s && e - s <= per as u64);
                let chunk = make_chunk("sess", channels, &values, s, e);
                assert_eq!(chunk.start_row, s);
                assert_eq!(chunk.values_f64le.len() as u64, (e - s) * 3 * 8);
                assert_eq!(chunk.crc32c, crc32c::crc32c(&chunk.values_f64le));
                let back = wire::decode_values(&chunk.values_f64le, 3, chunk.crc32c).unwrap();
                assert_eq!(back, values[s as usize * 3..e as usize * 3]);
                next = e;
            }
            assert_eq!(next, rows.max(from));
        }
        // Default chunk size: 256 KiB of values.
        let opts = UploadOptions::default();
        assert_eq!(opts.rows_per_chunk(1), 32768);
        assert_eq!(opts.rows_per_chunk(4), 8192);
        assert_eq!(
            UploadOptions {
                chunk_rows: Some(0),
                ..opts
            }
            .rows_per_chunk(1),
            1
        );
    }

    #[test]
    fn session_ids_and_requests() {
        assert!(valid_session_id("run-2026.11_a"));
        assert!(!valid_session_id(""));
        assert!(!valid_session_id("has space"));
        assert!(!valid_session_id(&"x".repeat(129)));
        let spec: PatternSpec = serde_json::from_str(
            r#"{"family":"hadamard","width":8,"height":8,"count":128,"seed":1}"#,
        )
        .unwrap();
        let req = NewSession::new("s1", spec.clone(), vec!["bucket".into()])
            .with_rig("bench")
            .with_metadata("lens", "50mm")
            .with_ground_truth(8, 8, vec![0.5; 64])
            .to_request();
        assert_eq!(req.patterns, Some(v1::PatternSpec::from(&spec)));
        assert_eq!(req.detector.unwrap().channels, ["bucket"]);
        assert_eq!(req.metadata["lens"], "50mm");
        assert_eq!(req.ground_truth.unwrap().transport.len(), 64);
    }

    #[test]
    fn camera_and_direction_declarations() {
        let spec: PatternSpec = serde_json::from_str(
            r#"{"family":"hadamard","width":8,"height":8,"count":128,"seed":1}"#,
        )
        .unwrap();
        let cam = NewSession::camera("c1", spec.clone(), 32, 16, SampleFormat::U16);
        assert_eq!(
            (cam.channel_count(), cam.sample_format()),
            (512, SampleFormat::U16)
        );
        cam.validate().unwrap();
        let det = cam.to_request().detector.unwrap();
        assert!(det.channels.is_empty() && det.directions.is_empty());
        assert_eq!(
            det.camera,
            Some(v1::CameraLayout {
                width: 32,
                height: 16,
                format: v1::SampleFormat::U16 as i32
            })
        );
        assert!(
            NewSession::camera("c", spec.clone(), 256, 257, SampleFormat::F32)
                .validate()
                .is_err()
        );
        assert!(
            NewSession::camera("c", spec.clone(), 4, 4, SampleFormat::F64)
                .validate()
                .is_err()
        );
        let s = 0.5f64.sqrt();
        let buckets = NewSession::new("b", spec.clone(), vec!["n".into(), "e".into()])
            .with_directions(vec![[0.0, -s, s], [s, 0.0, s]]);
        buckets.validate().unwrap();
        let det = buckets.to_request().detector.unwrap();
        assert_eq!(
            det.directions[0],
            v1::Direction {
                x: 0.0,
                y: -s,
                z: s
            }
        );
        assert_eq!(det.camera, None);
        assert_eq!(buckets.sample_format(), SampleFormat::F64);
        let e = buckets
            .clone()
            .with_directions(vec![[0.0, 0.0, 1.0]])
            .validate()
            .unwrap_err();
        assert!(
            e.to_string()
                .contains("1 detector directions given for 2 channels"),
            "{e}"
        );
        assert!(
            buckets
                .with_directions(vec![[0.0, 0.0, 1.0], [1.0, 1.0, 0.0]])
                .validate()
                .is_err()
        );
        // Chunks of f64 rows keep their field; the byte cap holds for explicit chunk sizes.
        let c = encode_chunk("b", 2, SampleFormat::F64, 3, vec![0; 16]);
        assert_eq!(
            (
                c.values_f64le.len(),
                c.values_f32le.len(),
                c.values_u16le.len()
            ),
            (16, 0, 0)
        );
        let opts = UploadOptions {
            chunk_rows: Some(10_000_000),
            ..UploadOptions::default()
        };
        assert_eq!(opts.rows_per_chunk(4), MAX_CHUNK_BYTES / 32);
    }

    #[test]
    fn rpc_errors_read_well() {
        let e = RpcError::new(
            "finishing session s",
            &Status::failed_precondition("12 of 64 rows committed"),
        );
        assert_eq!(
            e.to_string(),
            "finishing session s: 12 of 64 rows committed (FAILED_PRECONDITION)"
        );
        let e = RpcError::new("x", &Status::unavailable(""));
        assert!(e.to_string().contains("UNAVAILABLE") && e.to_string().contains("server running"));
    }
}
