//! Live preview of a session while it uploads: a progressive dual image
//! ([`recon::preview::Preview`]) of the rows already committed, sent as frames to one watcher
//! (gRPC `WatchPreview`, REST `GET /v1/sessions/{id}/preview` as server-sent events).
//!
//! One watcher, one preview: [`watch`] starts a thread of its own that reads the session's
//! committed chunks from the store with a cursor (each row is read and accumulated once, never
//! again from row 0), feeds them to the accumulator and sends a frame every `every_rows` rows
//! or `every_ms` milliseconds, and a last (`final`) frame once the session is finished and every
//! row is in. The upload never waits for it: the preview only reads what the upload has already
//! committed (SQLite WAL readers do not block the writer; PostgreSQL reads take no row lock),
//! its CPU work runs on its own thread at a lower scheduling priority (never on the async
//! runtime that serves uploads), and a slow watcher slows only its own preview (the frame
//! channel holds one frame). The thread ends when the watcher goes away (the channel closes).

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use tokio::sync::mpsc;

use crate::api::ApiError;
use crate::recon::preview::Preview;
use crate::store::{SessionRow, SessionState, Store, StoreError};

/// The time trigger when neither is given.
pub const DEFAULT_EVERY_MS: u64 = 500;
/// Bounds of `every_ms` when given.
pub const MIN_EVERY_MS: u64 = 50;
pub const MAX_EVERY_MS: u64 = 600_000;
/// How often a caught-up preview looks for new rows.
const POLL: Duration = Duration::from_millis(100);
/// Stored chunks read per store query.
const READ_CHUNKS: u32 = 4;
/// Previews running at once in this process; more watchers are RESOURCE_EXHAUSTED.
pub const MAX_WATCHERS: usize = 64;

/// What a watcher asked for, validated against its session ([`Watch::parse`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Watch {
    /// The bucket channel's index; `None` for a camera session (the sum over its pixels).
    pub channel: Option<usize>,
    pub channel_name: String,
    /// 0: no row trigger.
    pub every_rows: u64,
    /// `None`: no time trigger.
    pub every: Option<Duration>,
}

impl Watch {
    /// The request's parameters as sent (gRPC: 0 and "" mean unset). Errors name the field.
    pub fn parse(
        session: &SessionRow,
        channel: Option<&str>,
        every_rows: u64,
        every_ms: u64,
    ) -> Result<Watch, ApiError> {
        let channel = channel.filter(|c| !c.is_empty());
        let (channel, channel_name) = match (&session.camera, channel) {
            (Some(_), None) => (None, "camera".to_string()),
            (Some(_), Some(c)) => {
                return Err(ApiError::invalid(
                    "channel",
                    format!(
                        "session {:?} is a camera session: its preview is the sum over the camera pixels; leave channel empty (got {c:?})",
                        session.id
                    ),
                ));
            }
            (None, None) => (Some(0), session.channels[0].clone()),
            (None, Some(c)) => {
                let index = session
                    .channels
                    .iter()
                    .position(|n| n == c)
                    .or_else(|| {
                        c.parse::<usize>()
                            .ok()
                            .filter(|&i| i < session.channels.len())
                    })
                    .ok_or_else(|| {
                        ApiError::invalid(
                            "channel",
                            format!(
                                "no channel {c:?}; session {:?} has {}",
                                session.id,
                                session.channels.join(", ")
                            ),
                        )
                    })?;
                (Some(index), session.channels[index].clone())
            }
        };
        let every = match every_ms {
            0 if every_rows == 0 => Some(Duration::from_millis(DEFAULT_EVERY_MS)),
            0 => None,
            ms if (MIN_EVERY_MS..=MAX_EVERY_MS).contains(&ms) => Some(Duration::from_millis(ms)),
            ms => {
                return Err(ApiError::invalid(
                    "every_ms",
                    format!(
                        "must be {MIN_EVERY_MS}..={MAX_EVERY_MS} milliseconds (or 0 for the default), got {ms}"
                    ),
                ));
            }
        };
        if every_rows > session.expected_rows {
            return Err(ApiError::invalid(
                "every_rows",
                format!(
                    "must be at most the session's {} rows (or 0 for no row trigger), got {every_rows}",
                    session.expected_rows
                ),
            ));
        }
        Ok(Watch {
            channel,
            channel_name,
            every_rows,
            every,
        })
    }
}

/// One preview image.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub session_id: String,
    pub channel: String,
    pub rows: u64,
    pub expected_rows: u64,
    pub width: u32,
    pub height: u32,
    pub method: &'static str,
    pub values: Vec<f32>,
    /// The session is finished and the image holds every row: the last frame.
    pub last: bool,
}

/// Counts the previews running in this process.
#[derive(Debug, Default)]
pub struct Watchers(AtomicUsize);

/// A running preview's place among [`MAX_WATCHERS`]; given back when dropped.
struct Slot(Arc<Watchers>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.0.fetch_sub(1, Ordering::Relaxed);
    }
}

impl Watchers {
    pub fn running(&self) -> usize {
        self.0.load(Ordering::Relaxed)
    }

    fn take(self: &Arc<Self>) -> Result<Slot, ApiError> {
        let before = self.0.fetch_add(1, Ordering::Relaxed);
        let slot = Slot(self.clone());
        if before >= MAX_WATCHERS {
            return Err(ApiError::ResourceExhausted {
                limit: "max_preview_watchers",
                message: format!(
                    "{MAX_WATCHERS} previews are being watched on this server; retry later"
                ),
                retry_after: Some(5),
            });
        }
        Ok(slot)
    }
}

/// Starts the preview of `session` for one watcher: frames (or the error that ended it) arrive
/// on the returned channel; dropping the receiver stops the preview. Call from within the
/// async runtime (the preview's thread reads the store through it).
pub fn watch(
    store: Store,
    watchers: &Arc<Watchers>,
    session: SessionRow,
    watch: Watch,
) -> Result<mpsc::Receiver<Result<Frame, ApiError>>, ApiError> {
    let slot = watchers.take()?;
    let runtime = tokio::runtime::Handle::current();
    let (tx, rx) = mpsc::channel(1);
    std::thread::Builder::new()
        .name("preview".into())
        .spawn(move || {
            let _slot = slot;
            lower_priority();
            let id = session.id.clone();
            let mut run = Run::new(store, session, watch, tx.clone());
            if let Err(e) = run.until_final(&runtime) {
                tracing::debug!(session = %id, error = %e, "preview ended");
                let _ = tx.blocking_send(Err(e.into()));
            }
        })
        .map_err(|e| ApiError::Internal(format!("starting a preview thread: {e}")))?;
    Ok(rx)
}

/// Linux schedules threads one by one: a niceness of 10 lets the runtime's threads (uploads,
/// every other request) and the reconstruction workers take the CPU first on a busy machine.
fn lower_priority() {
    #[cfg(target_os = "linux")]
    // SAFETY: setpriority on the calling thread (who = 0) only changes its niceness.
    unsafe {
        libc::setpriority(libc::PRIO_PROCESS, 0, 10);
    }
}

/// Why a preview stopped early.
#[derive(Debug)]
enum Stop {
    /// The watcher went away.
    Gone,
    Store(StoreError),
    Corrupt(String),
}

impl std::fmt::Display for Stop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Stop::Gone => write!(f, "the watcher went away"),
            Stop::Store(e) => write!(f, "{e}"),
            Stop::Corrupt(m) => write!(f, "{m}"),
        }
    }
}

impl From<Stop> for ApiError {
    fn from(s: Stop) -> ApiError {
        match s {
            Stop::Store(e) => e.into(),
            other => ApiError::Internal(other.to_string()),
        }
    }
}

impl From<StoreError> for Stop {
    fn from(e: StoreError) -> Stop {
        Stop::Store(e)
    }
}

struct Run {
    store: Store,
    session: SessionRow,
    watch: Watch,
    tx: mpsc::Sender<Result<Frame, ApiError>>,
    preview: Preview,
    /// Rows the preview's spec generates: an adaptive session's grow with each issued batch.
    spec_rows: u64,
    /// The next row to read (a stored chunk boundary).
    cursor: u64,
    last_rows: u64,
    last_sent: Instant,
    /// Scratch: the selected channel (or pixel sum) of each row of a chunk.
    buckets: Vec<f64>,
}

impl Run {
    fn new(
        store: Store,
        session: SessionRow,
        watch: Watch,
        tx: mpsc::Sender<Result<Frame, ApiError>>,
    ) -> Run {
        let preview = Preview::new(&session.spec, 1);
        Run {
            store,
            // An adaptive session's spec is resolved at its first row.
            spec_rows: if session.spec.is_adaptive() {
                0
            } else {
                session.spec.count()
            },
            session,
            watch,
            tx,
            preview,
            cursor: 0,
            last_rows: 0,
            last_sent: Instant::now(),
            buckets: Vec::new(),
        }
    }

    /// Reads and accumulates every committed row, sending frames as due, until the session is
    /// finished and every row is in (then sends the final frame) or the watcher goes away.
    fn until_final(&mut self, runtime: &tokio::runtime::Handle) -> Result<(), Stop> {
        let id = self.session.id.clone();
        let sample_bytes = self.session.sample_format().bytes();
        loop {
            if self.tx.is_closed() {
                return Err(Stop::Gone);
            }
            if self.cursor >= self.session.expected_rows {
                // Every declared row is in: the image cannot change any more.
                return self.send(true);
            }
            let chunks = runtime.block_on(self.store.read_raw_chunks(
                &id,
                self.cursor,
                READ_CHUNKS,
                sample_bytes,
            ))?;
            if chunks.is_empty() {
                // Caught up: finished (every row in), or wait for more.
                let now = runtime
                    .block_on(self.store.get_session(&id))?
                    .ok_or_else(|| StoreError::SessionNotFound(id.clone()))?;
                if now.state == SessionState::Finished && now.committed_rows <= self.cursor {
                    return self.send(true);
                }
                if self.due() {
                    self.send(false)?;
                }
                std::thread::sleep(POLL);
                continue;
            }
            for (start, count, data) in chunks {
                if start + count > self.spec_rows {
                    // An adaptive session's rows of batches issued after the preview's spec was
                    // resolved: resolve it again (the index sequence only grows).
                    self.resolve(runtime)?;
                }
                if start != self.cursor {
                    return Err(Stop::Corrupt(format!(
                        "session {id}: stored chunk at row {start} does not continue row {}",
                        self.cursor
                    )));
                }
                self.accumulate(count, &data)?;
                self.cursor = start + count;
                // With every row in, the final frame comes next instead.
                if self.cursor < self.session.expected_rows && self.due() {
                    self.send(false)?;
                }
            }
        }
    }

    /// The preview's spec resolved with every index issued so far (an adaptive session).
    fn resolve(&mut self, runtime: &tokio::runtime::Handle) -> Result<(), Stop> {
        let (spec, rows) = runtime.block_on(self.store.resolved_spec_and_rows(&self.session))?;
        if rows <= self.spec_rows {
            return Err(Stop::Corrupt(format!(
                "session {}: stored rows past the {rows} rows its spec generates",
                self.session.id
            )));
        }
        self.preview.resolve(&spec);
        self.spec_rows = rows;
        Ok(())
    }

    /// One stored chunk of `count` rows into the preview.
    fn accumulate(&mut self, count: u64, data: &[u8]) -> Result<(), Stop> {
        let format = self.session.sample_format();
        let row_bytes = self.session.row_bytes();
        if data.len() as u64 != count * row_bytes as u64 {
            return Err(Stop::Corrupt(format!(
                "session {}: a stored chunk of {count} rows holds {} bytes",
                self.session.id,
                data.len()
            )));
        }
        self.buckets.clear();
        let sample = format.bytes();
        match self.watch.channel {
            Some(ch) => self.buckets.extend(
                data.chunks_exact(row_bytes)
                    .map(|row| format.decode_f64(&row[ch * sample..(ch + 1) * sample])[0]),
            ),
            // A camera frame as one bucket: the sum over its pixels.
            None => self.buckets.extend(
                data.chunks_exact(row_bytes)
                    .map(|row| format.decode_f64(row).iter().sum::<f64>()),
            ),
        }
        self.preview.push_rows(&self.buckets);
        Ok(())
    }

    /// Whether a (non-final) frame is due: new rows and a trigger.
    fn due(&self) -> bool {
        let new = self.preview.rows() - self.last_rows;
        new > 0
            && ((self.watch.every_rows > 0 && new >= self.watch.every_rows)
                || self
                    .watch
                    .every
                    .is_some_and(|t| self.last_sent.elapsed() >= t))
    }

    fn send(&mut self, last: bool) -> Result<(), Stop> {
        let image = self.preview.image(0);
        let frame = Frame {
            session_id: self.session.id.clone(),
            channel: self.watch.channel_name.clone(),
            rows: self.preview.rows(),
            expected_rows: self.session.expected_rows,
            width: image.width,
            height: image.height,
            method: self.preview.method(),
            values: image.data,
            last,
        };
        self.tx.blocking_send(Ok(frame)).map_err(|_| Stop::Gone)?;
        self.last_rows = self.preview.rows();
        self.last_sent = Instant::now();
        Ok(())
    }
}
