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

mod grpc;
mod retry;
mod session;

pub use grpc::{
    chunk_payload_len, chunk_ranges, connect, encode_chunk, make_chunk, new_writer_id, read_chunk,
};
pub use retry::{Backoff, Disposition, RetryPolicy, RpcError, code_name, disposition};
pub use session::{
    CameraLayout, CreatedSession, NewSession, create_session, create_session_request,
    finish_session, request_reconstruction, upload_status, upload_status_with, valid_session_id,
};

use std::borrow::Cow;
use std::io::IsTerminal;
use std::time::{Duration, Instant};

use helmholtz_proto::v1::{self};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde::Serialize;
use tonic::Code;

use grpc::{StreamFailure, stream_rows};
use session::status_with;

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
/// ([`UploadReport::confirmed_rows`]); after a failed stream the next carries half as many rows
/// (down to one chunk), so a connection cut again and again still confirms rows between cuts
/// instead of re-sending one long stream. The source's values must be finite.
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
    // The most rows the server has reported committed: when it grows, failures so far were not
    // in vain (rows were stored between cuts), so the retry clock starts again.
    let mut best_committed = 0u64;
    // Rows the next stream carries: a cut stream confirms nothing, so after a failure streams
    // are halved (down to one chunk) to confirm rows between cuts instead of re-sending the same
    // long stream again and again; after a success they grow back.
    let mut stream_length = rows_a_stream;
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
        if committed > best_committed {
            if asked {
                failing_since = None;
                attempt = 0;
            }
            best_committed = committed;
        }
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
        let to = (from + stream_length).min(total);
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
                stream_length = (stream_length * 2).min(rows_a_stream);
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
                stream_length = (stream_length / 2 / chunk_rows as u64 * chunk_rows as u64)
                    .max(chunk_rows as u64);
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
