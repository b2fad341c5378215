//! The durable edge spool: every measured row is written here, fsync'ed, before it is uploaded,
//! so a crash of the client, the network or the server loses nothing that was measured.
//!
//! # Layout
//!
//! One directory per session under the spool root (`--spool DIR`, env `HELMHOLTZ_SPOOL`, default
//! [`default_root`]):
//!
//! ```text
//! <root>/<session_id>/
//!   session.pb      the CreateSessionRequest (protobuf), written before the manifest
//!   manifest.json   session id, channels (values a row: a camera frame's pixels), sample format
//!                   (f64, f32 or u16; absent in spools of older clients: f64), expected rows,
//!                   whether to finish, crc32c of session.pb; written atomically (temp file, fsync, rename, fsync of the directory): a
//!                   directory without it is an unfinished creation and is ignored
//!   seg-<first row, 20 digits>.rows
//!                   append-only segments of frames (below)
//!   sealed          present once the producer has written every row it will write
//!   state.json      the uploader's last view: committed count, last error (informative only;
//!                   the server's committed count is authoritative)
//!   lock            flock'ed by the one process that writes or drains the session
//! ```
//!
//! A frame is `len: u32 LE` (payload bytes), `crc32c: u32 LE` (of the 8 start-row bytes and the
//! payload), `start_row: u64 LE`, then `len` bytes of row-major little-endian values in the
//! session's sample format (f64 for bucket sessions; a camera session's f32 or u16 frames are
//! stored as they are, never widened): one or more whole rows. [`Spool::append`] writes its frames and fsyncs the segment before it returns: a row is
//! *spooled* only then. On open, frames are checked in order (length, checksum, the start row
//! following on); the first bad frame of the last segment is a torn tail from a crash and is
//! truncated away; a bad frame anywhere else is damage, reported and never silently dropped.
//!
//! Files, not SQLite: the spool is an append-only log read sequentially, which plain segments
//! with per-frame checksums do with one `write` + one `fsync` per batch, no second SQLite
//! library beside the server's (sqlx links its own `libsqlite3-sys`; rusqlite would have to
//! match its version), and files a person can inspect and delete.
//!
//! [`drain`] uploads a spool in the background: it creates the session (idempotent on its id),
//! streams the rows not yet confirmed and repeats as rows arrive, with jittered exponential
//! backoff after failures. The server's count is never taken as proof that it holds *our* rows:
//! rows count as confirmed only when a stream that carried them ends OK (the server stored them
//! or compared them byte for byte equal to what it holds). Segments wholly below the confirmed
//! count are deleted; once every row is confirmed (and the session is finished, if asked), the
//! session's directory is removed. Rows the server refuses (another writer's data under the same
//! id, a finished session) stay in the spool, and the drain says so.

use std::borrow::Cow;
use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{Context, bail};
use helmholtz_proto::v1;
use prost::Message;
use serde::{Deserialize, Serialize};
use tokio::sync::watch;

use crate::upload::{
    self, Disposition, NewSession, RetryPolicy, RowSource, RpcError, SampleFormat, Samples,
    UploadOptions, UploadReport,
};

const MANIFEST: &str = "manifest.json";
const SESSION_PB: &str = "session.pb";
const SEALED: &str = "sealed";
const STATE: &str = "state.json";
const LOCK: &str = "lock";
const SEGMENT_PREFIX: &str = "seg-";
const SEGMENT_SUFFIX: &str = ".rows";
const FRAME_HEADER: usize = 16;
/// Payload of one frame at most (an append of more rows writes several frames).
const FRAME_PAYLOAD_MAX: usize = 1 << 20;
/// A new segment is started once the current one reaches this size.
pub const DEFAULT_SEGMENT_BYTES: u64 = 8 << 20;
/// How long [`SpoolDir::open`] waits for another process's lock before calling the session busy.
const LOCK_WAIT: Duration = Duration::from_secs(2);

/// The spool root used when neither `--spool` nor `HELMHOLTZ_SPOOL` is given:
/// `$XDG_STATE_HOME/helmholtz/spool`, else `$HOME/.local/state/helmholtz/spool`, else
/// `./helmholtz-spool`.
pub fn default_root() -> PathBuf {
    let nonempty = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty());
    if let Some(state) = nonempty("XDG_STATE_HOME") {
        PathBuf::from(state).join("helmholtz").join("spool")
    } else if let Some(home) = nonempty("HOME") {
        PathBuf::from(home).join(".local/state/helmholtz/spool")
    } else {
        PathBuf::from("helmholtz-spool")
    }
}

/// What a session's spool declares (`manifest.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Layout version: 1 (f64 rows, as every older client wrote), 2 (f32 or u16 frames).
    pub format: u32,
    pub session_id: String,
    /// Values a row (a camera session: pixels a frame).
    pub channels: u32,
    /// How the values are stored (absent in older spools: f64).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sample_format: Option<SampleFormat>,
    /// Rows the session's spec declares.
    pub expected_rows: u64,
    /// Finish the session (FinishSession) once every row of the spec is committed.
    pub finish: bool,
    pub created_unix_ms: u64,
    /// CRC-32C of `session.pb`.
    pub request_crc32c: u32,
}

impl Manifest {
    /// The format the rows are stored in (f64 when the manifest names none).
    pub fn sample(&self) -> SampleFormat {
        self.sample_format.unwrap_or(SampleFormat::F64)
    }

    /// Bytes of one row.
    pub fn row_bytes(&self) -> usize {
        self.sample().bytes() * self.channels as usize
    }
}

/// The uploader's last view of a session (`state.json`): informative, never authoritative.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct UploadState {
    /// The server's committed count when last asked.
    pub committed_rows: Option<u64>,
    /// Rows below this were confirmed stored on the server with this spool's bytes (a stream
    /// that carried them ended OK). Written only after the confirmation, so a stale or lost
    /// file only makes the next upload re-send (and the server re-compare) more.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confirmed_rows: Option<u64>,
    pub last_error: Option<String>,
    pub last_attempt_unix_ms: Option<u64>,
    pub finished: bool,
}

fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

fn segment_name(first_row: u64) -> String {
    format!("{SEGMENT_PREFIX}{first_row:020}{SEGMENT_SUFFIX}")
}

fn parse_segment_name(name: &str) -> Option<u64> {
    name.strip_prefix(SEGMENT_PREFIX)?
        .strip_suffix(SEGMENT_SUFFIX)?
        .parse()
        .ok()
}

fn fsync_dir(dir: &Path) -> anyhow::Result<()> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .with_context(|| format!("fsync of directory {}", dir.display()))
}

/// Opens `path` for writing, created readable and writable by its owner only (0600): the spool
/// holds a lab's measurements.
fn private_file(path: &Path, truncate: bool) -> std::io::Result<File> {
    let mut options = OpenOptions::new();
    options.write(true).create(true).truncate(truncate);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    options.open(path)
}

/// Creates `dir` (and its parents) if missing and makes it its owner's only (0700), whatever it
/// was before.
fn private_dir(dir: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o700))
            .with_context(|| format!("making {} private (0700)", dir.display()))?;
    }
    Ok(())
}

/// Writes `bytes` to `dir/name` atomically and durably: temp file, fsync, rename, fsync of `dir`.
fn write_durably(dir: &Path, name: &str, bytes: &[u8]) -> anyhow::Result<()> {
    let tmp = dir.join(format!(".{name}.tmp"));
    let path = dir.join(name);
    let mut f = private_file(&tmp, true).with_context(|| format!("creating {}", tmp.display()))?;
    f.write_all(bytes)
        .and_then(|_| f.sync_all())
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, &path).with_context(|| format!("renaming to {}", path.display()))?;
    fsync_dir(dir)
}

/// Rejects ids that cannot name a directory safely (the server's rule plus: not only dots).
fn check_session_id(id: &str) -> anyhow::Result<()> {
    anyhow::ensure!(
        upload::valid_session_id(id),
        "session id {id:?} must be 1-128 characters of A-Z a-z 0-9 . _ -"
    );
    anyhow::ensure!(
        !id.bytes().all(|b| b == b'.'),
        "session id {id:?} cannot name a spool directory"
    );
    Ok(())
}

/// One frame found by a scan.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Frame {
    /// The segment's first row (its key).
    segment: u64,
    /// Byte offset of the frame header in the segment.
    offset: u64,
    start_row: u64,
    rows: u64,
}

/// One segment found by a scan.
#[derive(Clone, Debug)]
struct Segment {
    first_row: u64,
    path: PathBuf,
    /// Bytes of whole, valid frames.
    valid_len: u64,
    /// Rows `first_row..end_row` are in it.
    end_row: u64,
}

/// The result of checking a session directory's segments.
#[derive(Debug)]
struct Scan {
    segments: Vec<Segment>,
    frames: Vec<Frame>,
    /// First row held (rows below were committed and compacted away).
    base_row: u64,
    /// Rows `0..rows` are spooled (those below `base_row` are on the server).
    rows: u64,
    /// Bytes after the last valid frame of the last segment (a torn tail).
    torn_bytes: u64,
}

/// Parses one segment's bytes: the valid frames, and where they stop.
fn parse_frames(
    bytes: &[u8],
    segment: u64,
    row_bytes: usize,
    mut next_row: u64,
) -> (Vec<Frame>, u64, u64, Option<String>) {
    let payload_max = frame_payload_max(row_bytes);
    let mut frames = Vec::new();
    let mut pos = 0usize;
    let problem = loop {
        if pos == bytes.len() {
            break None;
        }
        let rest = &bytes[pos..];
        if rest.len() < FRAME_HEADER {
            break Some(format!("{} stray bytes at offset {pos}", rest.len()));
        }
        let len = u32::from_le_bytes(rest[0..4].try_into().unwrap()) as usize;
        let crc = u32::from_le_bytes(rest[4..8].try_into().unwrap());
        let start = u64::from_le_bytes(rest[8..16].try_into().unwrap());
        if len == 0 || len > payload_max || !len.is_multiple_of(row_bytes) {
            break Some(format!("bad frame length {len} at offset {pos}"));
        }
        if rest.len() < FRAME_HEADER + len {
            break Some(format!("frame at offset {pos} cut short"));
        }
        let payload = &rest[FRAME_HEADER..FRAME_HEADER + len];
        if crc32c::crc32c_append(crc32c::crc32c(&rest[8..16]), payload) != crc {
            break Some(format!("checksum mismatch in the frame at offset {pos}"));
        }
        if start != next_row {
            break Some(format!(
                "frame at offset {pos} starts at row {start}, expected {next_row}"
            ));
        }
        let rows = (len / row_bytes) as u64;
        frames.push(Frame {
            segment,
            offset: pos as u64,
            start_row: start,
            rows,
        });
        next_row += rows;
        pos += FRAME_HEADER + len;
    };
    (frames, pos as u64, next_row, problem)
}

/// The largest frame payload: [`FRAME_PAYLOAD_MAX`], or one row if a row is larger.
fn frame_payload_max(row_bytes: usize) -> usize {
    FRAME_PAYLOAD_MAX.max(row_bytes)
}

/// Checks every segment of `dir` (rows of `row_bytes` bytes). A bad frame in the last segment is
/// a torn tail (`torn_bytes`); anywhere else it is an error.
fn scan(dir: &Path, row_bytes: usize) -> anyhow::Result<Scan> {
    let mut firsts: Vec<u64> = Vec::new();
    for entry in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let entry = entry?;
        if let Some(first) = entry.file_name().to_str().and_then(parse_segment_name) {
            firsts.push(first);
        }
    }
    firsts.sort_unstable();
    let base_row = firsts.first().copied().unwrap_or(0);
    let mut out = Scan {
        segments: Vec::new(),
        frames: Vec::new(),
        base_row,
        rows: base_row,
        torn_bytes: 0,
    };
    for (i, &first) in firsts.iter().enumerate() {
        let path = dir.join(segment_name(first));
        if first != out.rows {
            bail!(
                "spool {}: segment {} starts at row {first} but the rows before end at {}; the spool is damaged",
                dir.display(),
                path.display(),
                out.rows
            );
        }
        let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
        let (frames, valid_len, end_row, problem) = parse_frames(&bytes, first, row_bytes, first);
        if let Some(problem) = problem {
            if i + 1 < firsts.len() {
                bail!(
                    "spool segment {} is damaged ({problem}) and is not the last one: not a torn write; \
                     rows from {end_row} cannot be recovered from the spool",
                    path.display()
                );
            }
            out.torn_bytes = bytes.len() as u64 - valid_len;
        }
        out.frames.extend(frames);
        out.segments.push(Segment {
            first_row: first,
            path,
            valid_len,
            end_row,
        });
        out.rows = end_row;
    }
    Ok(out)
}

fn read_manifest(dir: &Path) -> anyhow::Result<(Manifest, v1::CreateSessionRequest)> {
    let path = dir.join(MANIFEST);
    let text = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    let manifest: Manifest = serde_json::from_slice(&text)
        .with_context(|| format!("{}: not a spool manifest", path.display()))?;
    anyhow::ensure!(
        manifest.format == 1 || manifest.format == 2,
        "{}: spool format {} is not supported (this client reads 1 and 2)",
        path.display(),
        manifest.format
    );
    anyhow::ensure!(
        (manifest.format == 1) == (manifest.sample() == SampleFormat::F64),
        "{}: spool format {} does not go with {} values",
        path.display(),
        manifest.format,
        manifest.sample().name()
    );
    anyhow::ensure!(
        manifest.channels > 0,
        "{}: a spool needs at least one value a row",
        path.display()
    );
    let pb_path = dir.join(SESSION_PB);
    let pb = std::fs::read(&pb_path).with_context(|| format!("reading {}", pb_path.display()))?;
    anyhow::ensure!(
        crc32c::crc32c(&pb) == manifest.request_crc32c,
        "{}: checksum does not match the manifest; the spool is damaged",
        pb_path.display()
    );
    let request = v1::CreateSessionRequest::decode(pb.as_slice())
        .with_context(|| format!("{}: not a CreateSessionRequest", pb_path.display()))?;
    anyhow::ensure!(
        request.session_id == manifest.session_id,
        "{}: holds session {:?}, the manifest says {:?}",
        dir.display(),
        request.session_id,
        manifest.session_id
    );
    Ok((manifest, request))
}

fn read_state(dir: &Path) -> UploadState {
    std::fs::read(dir.join(STATE))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_default()
}

/// A spool root directory holding one directory per session.
#[derive(Clone, Debug)]
pub struct SpoolDir {
    root: PathBuf,
    segment_bytes: u64,
}

impl SpoolDir {
    pub fn new(root: impl Into<PathBuf>) -> Self {
        SpoolDir {
            root: root.into(),
            segment_bytes: DEFAULT_SEGMENT_BYTES,
        }
    }

    /// Starts a new segment once the current one reaches `bytes` (default 8 MiB).
    pub fn with_segment_bytes(mut self, bytes: u64) -> Self {
        self.segment_bytes = bytes.max(1);
        self
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn session_dir(&self, session_id: &str) -> PathBuf {
        self.root.join(session_id)
    }

    /// Session ids with a spool (a manifest), sorted.
    pub fn sessions(&self) -> anyhow::Result<Vec<String>> {
        let entries = match std::fs::read_dir(&self.root) {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => {
                return Err(e).with_context(|| format!("reading spool {}", self.root.display()));
            }
        };
        let mut ids = Vec::new();
        for entry in entries {
            let entry = entry?;
            if let Some(name) = entry.file_name().to_str()
                && entry.path().join(MANIFEST).is_file()
            {
                ids.push(name.to_string());
            }
        }
        ids.sort();
        Ok(ids)
    }

    /// Opens the spool of `session`, creating it if new. An existing spool must hold the same
    /// declaration (else an error says so and nothing changes). `finish`: finish the session
    /// once every row is committed (an existing spool's flag is only ever turned on).
    pub fn create_or_open(&self, session: &NewSession, finish: bool) -> anyhow::Result<Spool> {
        check_session_id(&session.session_id)?;
        session.validate()?;
        let request = session.to_request();
        let dir = self.session_dir(&session.session_id);
        private_dir(&self.root)?;
        match std::fs::create_dir(&dir) {
            Ok(()) => fsync_dir(&self.root)?,
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => return Err(e).with_context(|| format!("creating {}", dir.display())),
        }
        private_dir(&dir)?;
        let lock = lock_exclusive(&dir)?;
        if !dir.join(MANIFEST).is_file() {
            let pb = request.encode_to_vec();
            write_durably(&dir, SESSION_PB, &pb)?;
            let sample = session.sample_format();
            let manifest = Manifest {
                // Format 1 stays readable by older clients; frames need format 2.
                format: if sample == SampleFormat::F64 { 1 } else { 2 },
                session_id: session.session_id.clone(),
                channels: session.channel_count(),
                sample_format: Some(sample),
                expected_rows: session.spec.count(),
                finish,
                created_unix_ms: now_ms(),
                request_crc32c: crc32c::crc32c(&pb),
            };
            write_durably(&dir, MANIFEST, &serde_json::to_vec_pretty(&manifest)?)?;
        }
        let spool = Spool::open_locked(dir, lock, self.segment_bytes)?;
        if spool.request != request {
            bail!(
                "the spool {} already holds session {} with a different declaration (spec, channels, rig, \
                 metadata or ground truth); upload it first (`helmholtz spool upload {}`) or pick another session id",
                spool.dir.display(),
                session.session_id,
                session.session_id
            );
        }
        if finish && !spool.manifest.finish {
            let mut spool = spool;
            spool.manifest.finish = true;
            write_durably(
                &spool.dir,
                MANIFEST,
                &serde_json::to_vec_pretty(&spool.manifest)?,
            )?;
            return Ok(spool);
        }
        Ok(spool)
    }

    /// Opens an existing session's spool for writing or draining (exclusive: fails if another
    /// process holds it). Truncates a torn tail.
    pub fn open(&self, session_id: &str) -> anyhow::Result<Spool> {
        check_session_id(session_id)?;
        let dir = self.session_dir(session_id);
        anyhow::ensure!(
            dir.join(MANIFEST).is_file(),
            "no spool for session {session_id} in {}",
            self.root.display()
        );
        let lock = lock_exclusive(&dir)?;
        Spool::open_locked(dir, lock, self.segment_bytes)
    }

    /// Reads a session's spool without changing it (no lock taken, no tail truncated).
    pub fn inspect(&self, session_id: &str) -> anyhow::Result<SpoolInfo> {
        check_session_id(session_id)?;
        let dir = self.session_dir(session_id);
        let (manifest, _) = read_manifest(&dir)?;
        let scan = scan(&dir, manifest.row_bytes())?;
        Ok(SpoolInfo {
            session_id: session_id.to_string(),
            dir: dir.clone(),
            spooled_rows: scan.rows,
            base_row: scan.base_row,
            expected_rows: manifest.expected_rows,
            channels: manifest.channels,
            sample_format: manifest.sample(),
            sealed: dir.join(SEALED).exists(),
            finish: manifest.finish,
            busy: is_locked(&dir),
            torn_bytes: scan.torn_bytes,
            segments: scan.segments.len(),
            state: read_state(&dir),
        })
    }
}

/// What [`SpoolDir::inspect`] found.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SpoolInfo {
    pub session_id: String,
    pub dir: PathBuf,
    /// Rows `0..spooled_rows` were spooled (durably written).
    pub spooled_rows: u64,
    /// Rows below this were committed on the server and deleted from the spool.
    pub base_row: u64,
    pub expected_rows: u64,
    pub channels: u32,
    pub sample_format: SampleFormat,
    /// The producer wrote every row it will write.
    pub sealed: bool,
    /// The session is to be finished once complete.
    pub finish: bool,
    /// Another process is writing or draining it now.
    pub busy: bool,
    /// Bytes of a torn tail (a write cut by a crash), truncated at the next open.
    pub torn_bytes: u64,
    pub segments: usize,
    pub state: UploadState,
}

fn lock_exclusive(dir: &Path) -> anyhow::Result<File> {
    let path = dir.join(LOCK);
    let mut options = OpenOptions::new();
    options.create(true).truncate(false).read(true).write(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let file = options
        .open(&path)
        .with_context(|| format!("opening {}", path.display()))?;
    let started = Instant::now();
    loop {
        match file.try_lock() {
            Ok(()) => return Ok(file),
            Err(std::fs::TryLockError::WouldBlock) if started.elapsed() < LOCK_WAIT => {
                std::thread::sleep(Duration::from_millis(50));
            }
            Err(std::fs::TryLockError::WouldBlock) => bail!(
                "the spool {} is busy: another helmholtz process is writing or uploading it",
                dir.display()
            ),
            Err(std::fs::TryLockError::Error(e)) => {
                return Err(e).with_context(|| format!("locking {}", path.display()));
            }
        }
    }
}

/// True if another process holds the session's lock (probed with a shared lock, released at once).
fn is_locked(dir: &Path) -> bool {
    let Ok(file) = File::open(dir.join(LOCK)) else {
        return false;
    };
    matches!(
        file.try_lock_shared(),
        Err(std::fs::TryLockError::WouldBlock)
    )
}

struct Inner {
    segments: Vec<Segment>,
    frames: Vec<Frame>,
    base_row: u64,
    rows: u64,
    sealed: bool,
    /// The last segment, open for appending.
    active: Option<File>,
}

/// One session's spool, held exclusively by this process (see the module docs).
pub struct Spool {
    dir: PathBuf,
    manifest: Manifest,
    request: v1::CreateSessionRequest,
    segment_bytes: u64,
    inner: Mutex<Inner>,
    /// Spooled rows and sealed, for a concurrent [`drain`].
    progress: watch::Sender<(u64, bool)>,
    _lock: File,
}

impl std::fmt::Debug for Spool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Spool")
            .field("dir", &self.dir)
            .field("rows", &self.rows())
            .finish()
    }
}

impl Spool {
    fn open_locked(dir: PathBuf, lock: File, segment_bytes: u64) -> anyhow::Result<Spool> {
        let (manifest, request) = read_manifest(&dir)?;
        let scan = scan(&dir, manifest.row_bytes())?;
        if scan.torn_bytes > 0 {
            let last = scan.segments.last().expect("torn bytes lie in a segment");
            let f = OpenOptions::new()
                .write(true)
                .open(&last.path)
                .with_context(|| format!("opening {}", last.path.display()))?;
            f.set_len(last.valid_len)
                .and_then(|_| f.sync_all())
                .with_context(|| format!("truncating the torn tail of {}", last.path.display()))?;
            tracing::warn!(
                segment = %last.path.display(),
                bytes = scan.torn_bytes,
                "truncated a torn tail left by a crash"
            );
        }
        let sealed = dir.join(SEALED).exists();
        let (progress, _) = watch::channel((scan.rows, sealed));
        Ok(Spool {
            dir,
            manifest,
            request,
            segment_bytes,
            inner: Mutex::new(Inner {
                segments: scan.segments,
                frames: scan.frames,
                base_row: scan.base_row,
                rows: scan.rows,
                sealed,
                active: None,
            }),
            progress,
            _lock: lock,
        })
    }

    fn inner(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().expect("spool lock not poisoned")
    }

    pub fn session_id(&self) -> &str {
        &self.manifest.session_id
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// The CreateSessionRequest the session is declared with.
    pub fn request(&self) -> &v1::CreateSessionRequest {
        &self.request
    }

    /// Rows `0..rows()` are spooled (durable).
    pub fn rows(&self) -> u64 {
        self.inner().rows
    }

    /// Rows below this were committed on the server and deleted from the spool.
    pub fn base_row(&self) -> u64 {
        self.inner().base_row
    }

    pub fn is_sealed(&self) -> bool {
        self.inner().sealed
    }

    /// Segment files on disk.
    pub fn segment_count(&self) -> usize {
        self.inner().segments.len()
    }

    /// Spooled rows and the sealed flag, updated on every append and seal.
    pub fn watch(&self) -> watch::Receiver<(u64, bool)> {
        self.progress.subscribe()
    }

    /// Appends whole rows of f64 values (a bucket session's spool); see [`Spool::append_samples`].
    pub fn append(&self, values: &[f64]) -> anyhow::Result<u64> {
        self.append_samples(Samples::F64(values))
    }

    /// Appends whole rows (`channels` values each, row-major, all finite, in the spool's sample
    /// format) after the spooled ones and fsyncs them: when this returns `Ok`, they are spooled.
    /// Bad input (another sample format, a non-finite value, more rows than the spec declares)
    /// is refused and spools nothing. On an I/O error a partly written frame is cut off again;
    /// rows an earlier segment already made durable (appends spanning a segment change) stay
    /// spooled, as [`Spool::rows`] says. Returns the spooled row count.
    pub fn append_samples(&self, values: Samples<'_>) -> anyhow::Result<u64> {
        let ch = self.manifest.channels as usize;
        let format = self.manifest.sample();
        anyhow::ensure!(
            values.format() == format,
            "session {} stores {} values, not {}; nothing was spooled",
            self.session_id(),
            format.name(),
            values.format().name()
        );
        anyhow::ensure!(
            !values.is_empty() && values.len().is_multiple_of(ch),
            "{} values are not a whole, non-zero number of rows of {ch} channel(s)",
            values.len()
        );
        let mut inner = self.inner();
        anyhow::ensure!(
            !inner.sealed,
            "the spool of session {} is sealed: no more rows",
            self.session_id()
        );
        if let Some(pos) = values.first_non_finite() {
            bail!(
                "row {}, channel {}: value {} is not finite; nothing was spooled",
                inner.rows + (pos / ch) as u64,
                pos % ch,
                values.get_f64(pos)
            );
        }
        let new_rows = (values.len() / ch) as u64;
        let expected = self.manifest.expected_rows;
        anyhow::ensure!(
            inner.rows + new_rows <= expected,
            "{new_rows} more rows would make {} but session {} declares {expected}; nothing was spooled",
            inner.rows + new_rows,
            self.session_id()
        );
        let row_bytes = self.manifest.row_bytes();
        let rows_per_frame = (frame_payload_max(row_bytes) / row_bytes).max(1);
        let mut start = inner.rows;
        let mut pending: Vec<Frame> = Vec::new();
        let mut buf: Vec<u8> = Vec::new();
        let mut from = 0usize;
        while from < values.len() {
            let to = (from + rows_per_frame * ch).min(values.len());
            // A new segment once the last one (with what is buffered for it) is full.
            let full = inner
                .segments
                .last()
                .is_none_or(|seg| seg.valid_len + buf.len() as u64 >= self.segment_bytes);
            if full {
                if !buf.is_empty() {
                    self.flush(&mut inner, &mut buf, &mut pending)?;
                }
                self.start_segment(&mut inner, start)?;
            }
            let seg = inner.segments.last().expect("a segment");
            let offset = seg.valid_len + buf.len() as u64;
            let payload = values.encode_range(from, to);
            let start_bytes = start.to_le_bytes();
            let crc = crc32c::crc32c_append(crc32c::crc32c(&start_bytes), &payload);
            buf.extend_from_slice(&(payload.len() as u32).to_le_bytes());
            buf.extend_from_slice(&crc.to_le_bytes());
            buf.extend_from_slice(&start_bytes);
            buf.extend_from_slice(&payload);
            let n = ((to - from) / ch) as u64;
            pending.push(Frame {
                segment: seg.first_row,
                offset,
                start_row: start,
                rows: n,
            });
            start += n;
            from = to;
        }
        if !buf.is_empty() {
            self.flush(&mut inner, &mut buf, &mut pending)?;
        }
        let rows = inner.rows;
        drop(inner);
        self.progress.send_replace((rows, false));
        Ok(rows)
    }

    /// Writes `buf` (whole frames) to the active segment and fsyncs it; then the frames count.
    fn flush(
        &self,
        inner: &mut Inner,
        buf: &mut Vec<u8>,
        pending: &mut Vec<Frame>,
    ) -> anyhow::Result<()> {
        let seg_len = inner.segments.last().expect("a segment").valid_len;
        let path = inner.segments.last().expect("a segment").path.clone();
        if inner.active.is_none() {
            let f = OpenOptions::new()
                .write(true)
                .open(&path)
                .with_context(|| format!("opening {}", path.display()))?;
            inner.active = Some(f);
        }
        let file = inner.active.as_mut().expect("opened");
        let written = file
            .seek(SeekFrom::Start(seg_len))
            .and_then(|_| file.write_all(buf))
            .and_then(|_| file.sync_data());
        if let Err(e) = written {
            // Cut off whatever part reached the file: the spool stays as it was.
            let _ = file.set_len(seg_len).and_then(|_| file.sync_data());
            inner.active = None;
            return Err(e).with_context(|| format!("writing rows to {}", path.display()));
        }
        let seg = inner.segments.last_mut().expect("a segment");
        seg.valid_len += buf.len() as u64;
        for f in pending.drain(..) {
            seg.end_row = f.start_row + f.rows;
            inner.rows = seg.end_row;
            inner.frames.push(f);
        }
        buf.clear();
        Ok(())
    }

    fn start_segment(&self, inner: &mut Inner, first_row: u64) -> anyhow::Result<()> {
        let path = self.dir.join(segment_name(first_row));
        let file =
            private_file(&path, true).with_context(|| format!("creating {}", path.display()))?;
        file.sync_all()
            .with_context(|| format!("fsync of {}", path.display()))?;
        fsync_dir(&self.dir)?;
        if let Some(old) = inner.active.take() {
            drop(old);
        }
        inner.active = Some(file);
        inner.segments.push(Segment {
            first_row,
            path,
            valid_len: 0,
            end_row: first_row,
        });
        Ok(())
    }

    /// Makes an empty spool continue at row `row`: its next appended row is row `row` of the
    /// session (the server holds the rows before it, e.g. from an earlier `acquire` whose spool
    /// was uploaded and cleared). Refused when the spool holds rows (they fix where it
    /// continues) or `row` is past the spec's count. Durable (an empty segment named for `row`).
    pub fn start_at(&self, row: u64) -> anyhow::Result<()> {
        let mut inner = self.inner();
        if inner.rows == row {
            return Ok(());
        }
        anyhow::ensure!(
            inner.frames.is_empty(),
            "the spool {} holds rows {}..{} of session {}, so its next row is {}, not {row}",
            self.dir.display(),
            inner.base_row,
            inner.rows,
            self.session_id(),
            inner.rows
        );
        anyhow::ensure!(
            row <= self.manifest.expected_rows,
            "row {row} is past the {} rows session {} declares",
            self.manifest.expected_rows,
            self.session_id()
        );
        inner.active = None;
        for seg in std::mem::take(&mut inner.segments) {
            std::fs::remove_file(&seg.path)
                .with_context(|| format!("deleting {}", seg.path.display()))?;
        }
        self.start_segment(&mut inner, row)?;
        inner.base_row = row;
        inner.rows = row;
        let sealed = inner.sealed;
        drop(inner);
        self.progress.send_replace((row, sealed));
        Ok(())
    }

    /// True when the spool holds no rows (any rows before [`Spool::rows`] are on the server).
    pub fn is_empty(&self) -> bool {
        self.inner().frames.is_empty()
    }

    /// Marks the producer done: no more rows will be appended. Durable.
    pub fn seal(&self) -> anyhow::Result<()> {
        let mut inner = self.inner();
        if !inner.sealed {
            write_durably(&self.dir, SEALED, b"")?;
            inner.sealed = true;
        }
        let rows = inner.rows;
        drop(inner);
        self.progress.send_replace((rows, true));
        Ok(())
    }

    /// Lets a new producer append more rows after an earlier one sealed the spool (e.g. a
    /// second partial upload of a growing file).
    pub fn unseal(&self) -> anyhow::Result<()> {
        let mut inner = self.inner();
        if inner.sealed {
            std::fs::remove_file(self.dir.join(SEALED)).context("removing the sealed marker")?;
            fsync_dir(&self.dir)?;
            inner.sealed = false;
        }
        let rows = inner.rows;
        drop(inner);
        self.progress.send_replace((rows, false));
        Ok(())
    }

    /// The values of rows `start..end` (row-major) widened to f64, checked against their frame
    /// checksums.
    pub fn read(&self, start: u64, end: u64) -> anyhow::Result<Vec<f64>> {
        Ok(self
            .manifest
            .sample()
            .decode_f64(&self.read_bytes(start, end)?))
    }

    /// Rows `start..end` as stored: little-endian values of the spool's sample format
    /// (row-major), checked against their frame checksums.
    pub fn read_bytes(&self, start: u64, end: u64) -> anyhow::Result<Vec<u8>> {
        let row_bytes = self.manifest.row_bytes();
        let (frames, paths) = {
            let inner = self.inner();
            anyhow::ensure!(
                end <= inner.rows && start <= end,
                "rows {start}..{end} are not in the spool (it holds rows up to {})",
                inner.rows
            );
            anyhow::ensure!(
                start >= inner.base_row || start == end,
                "rows {start}..{} of session {} were deleted from the spool after the server had \
                 committed them, yet the server now asks for them again; the server lost rows it \
                 acknowledged",
                inner.base_row,
                self.session_id()
            );
            let first = inner
                .frames
                .partition_point(|f| f.start_row + f.rows <= start);
            let frames: Vec<Frame> = inner.frames[first..]
                .iter()
                .take_while(|f| f.start_row < end)
                .copied()
                .collect();
            let paths: Vec<(u64, PathBuf)> = inner
                .segments
                .iter()
                .map(|s| (s.first_row, s.path.clone()))
                .collect();
            (frames, paths)
        };
        let mut out: Vec<u8> = Vec::with_capacity((end - start) as usize * row_bytes);
        let mut open: Option<(u64, File)> = None;
        for f in frames {
            if open.as_ref().is_none_or(|(k, _)| *k != f.segment) {
                let path = &paths
                    .iter()
                    .find(|(k, _)| *k == f.segment)
                    .context("segment vanished")?
                    .1;
                open = Some((
                    f.segment,
                    File::open(path).with_context(|| format!("opening {}", path.display()))?,
                ));
            }
            let file = &mut open.as_mut().expect("opened").1;
            let len = f.rows as usize * row_bytes;
            let mut frame = vec![0u8; FRAME_HEADER + len];
            file.seek(SeekFrom::Start(f.offset))
                .and_then(|_| file.read_exact(&mut frame))
                .with_context(|| format!("reading rows {}.. from the spool", f.start_row))?;
            let crc = u32::from_le_bytes(frame[4..8].try_into().unwrap());
            anyhow::ensure!(
                crc32c::crc32c_append(crc32c::crc32c(&frame[8..16]), &frame[FRAME_HEADER..]) == crc,
                "spool frame of rows {}..{} of session {} fails its checksum: the spool is damaged",
                f.start_row,
                f.start_row + f.rows,
                self.session_id()
            );
            let lo = start.max(f.start_row) - f.start_row;
            let hi = end.min(f.start_row + f.rows) - f.start_row;
            out.extend_from_slice(
                &frame[FRAME_HEADER + lo as usize * row_bytes
                    ..FRAME_HEADER + hi as usize * row_bytes],
            );
        }
        anyhow::ensure!(
            out.len() == (end - start) as usize * row_bytes,
            "the spool index of session {} is inconsistent",
            self.session_id()
        );
        Ok(out)
    }

    /// Rows below this are confirmed stored on the server with this spool's bytes: the rows
    /// deleted from the spool, and those the last upload's streams confirmed (`state.json`).
    pub fn confirmed_rows(&self) -> u64 {
        let (base, rows) = {
            let inner = self.inner();
            (inner.base_row, inner.rows)
        };
        base.max(self.state().confirmed_rows.unwrap_or(0).min(rows))
    }

    /// Deletes the segments whose rows all lie below `confirmed` (the server confirmed it
    /// stores them with these bytes), except the last one (still appended to). Returns how
    /// many were deleted.
    pub fn compact(&self, confirmed: u64) -> anyhow::Result<usize> {
        let mut inner = self.inner();
        let mut deleted = 0;
        while inner.segments.len() > 1 && inner.segments[0].end_row <= confirmed {
            let seg = inner.segments.remove(0);
            std::fs::remove_file(&seg.path)
                .with_context(|| format!("deleting {}", seg.path.display()))?;
            let keep = inner.frames.partition_point(|f| f.segment == seg.first_row);
            inner.frames.drain(..keep);
            inner.base_row = inner.segments[0].first_row;
            deleted += 1;
        }
        if deleted > 0 {
            fsync_dir(&self.dir)?;
        }
        Ok(deleted)
    }

    pub fn state(&self) -> UploadState {
        read_state(&self.dir)
    }

    /// Records the uploader's view (best effort: it is informative only).
    pub fn save_state(&self, state: &UploadState) {
        let path = self.dir.join(STATE);
        let tmp = self.dir.join(format!(".{STATE}.tmp"));
        let ok = serde_json::to_vec_pretty(state)
            .ok()
            .and_then(|b| {
                private_file(&tmp, true)
                    .and_then(|mut f| f.write_all(&b))
                    .ok()
            })
            .and_then(|_| std::fs::rename(&tmp, &path).ok());
        if ok.is_none() {
            tracing::warn!(path = %path.display(), "could not record the upload state");
        }
    }

    /// Deletes the session's spool directory (every row is on the server). Only for a sealed
    /// spool: nothing may be appended any more.
    pub fn remove(&self) -> anyhow::Result<()> {
        let mut inner = self.inner();
        anyhow::ensure!(inner.sealed, "only a sealed spool can be removed");
        inner.active = None;
        std::fs::remove_dir_all(&self.dir)
            .with_context(|| format!("removing {}", self.dir.display()))?;
        if let Some(parent) = self.dir.parent() {
            let _ = fsync_dir(parent);
        }
        Ok(())
    }
}

/// The rows `0..upto` of a spool as an upload source.
struct SpoolRows<'a> {
    spool: &'a Spool,
    upto: u64,
}

impl RowSource for SpoolRows<'_> {
    fn rows(&self) -> u64 {
        self.upto
    }

    fn read(&self, start: u64, end: u64) -> anyhow::Result<Cow<'_, [f64]>> {
        Ok(Cow::Owned(self.spool.read(start, end)?))
    }

    fn format(&self) -> SampleFormat {
        self.spool.manifest.sample()
    }

    /// The stored bytes as they are: frames are sent in their own format, never widened.
    fn read_payload(&self, start: u64, end: u64) -> anyhow::Result<Vec<u8>> {
        self.spool.read_bytes(start, end)
    }
}

/// What [`drain`] did.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct DrainReport {
    pub session_id: String,
    /// Rows spooled when the drain ended.
    pub spooled_rows: u64,
    /// The server's committed count at the end.
    pub committed_rows: u64,
    /// Rows confirmed stored on the server with the spool's bytes.
    pub confirmed_rows: u64,
    pub expected_rows: u64,
    /// Rows put on the wire (re-sends after a resume included).
    pub rows_sent: u64,
    pub bytes_sent: u64,
    /// Upload passes (one per batch of newly spooled rows, plus retries).
    pub passes: u32,
    /// Resumes inside passes plus passes retried after a failure.
    pub resumes: u32,
    /// Segments deleted because the server had committed their rows.
    pub segments_deleted: usize,
    /// The session was finished on the server.
    pub finished: bool,
    /// Every row was committed and the spool directory was removed.
    pub removed: bool,
    pub seconds: f64,
    pub last_error: Option<String>,
}

fn rpc_code(e: &anyhow::Error) -> Option<tonic::Code> {
    e.chain()
        .find_map(|c| c.downcast_ref::<RpcError>())
        .map(|r| r.code)
}

fn retryable(e: &anyhow::Error) -> bool {
    rpc_code(e).is_some_and(|c| upload::disposition(c) == Disposition::Retry)
}

/// Uploads a spool: creates the session (idempotent), then streams the spooled rows not yet
/// confirmed (the server compares any it already holds, byte for byte) as they are spooled, until
/// the spool is sealed and every spooled row is confirmed. Then finishes the session if the
/// manifest asks and the spec is complete, and removes the spool directory when nothing is left
/// to do. Segments are deleted only for rows the server confirmed with the same bytes.
///
/// `follow`: a producer in this process is still appending; wait for its rows until it seals the
/// spool. Without `follow` (`helmholtz spool upload`), send what is spooled and stop; a spool
/// that holds every row of the spec but was never sealed (its producer died just before) is
/// sealed then.
///
/// While following an unsealed spool, transient failures are retried without limit, with
/// jittered exponential backoff: the rows are safe in the spool. Otherwise a pass gives up after
/// `opts.retry_for` without progress. Fatal refusals (INVALID_ARGUMENT, ALREADY_EXISTS: the
/// server holds other rows under this id, FAILED_PRECONDITION: finished, ...) and another writer
/// holding the session past `retry_for` (ABORTED) end the drain; the rows stay in the spool. The
/// error is recorded in `state.json`.
pub async fn drain(
    server: &str,
    spool: Arc<Spool>,
    opts: &UploadOptions,
    follow: bool,
) -> anyhow::Result<DrainReport> {
    let started = Instant::now();
    let id = spool.session_id().to_string();
    let channels = spool.manifest().channels;
    let mut report = DrainReport {
        session_id: id.clone(),
        expected_rows: spool.manifest().expected_rows,
        ..Default::default()
    };
    let mut state = spool.state();
    let mut watch = spool.watch();
    let mut created = false;
    let mut confirmed = spool.confirmed_rows();
    // One writer for every pass of this drain: a pass after a cut connection takes the session
    // over from its own stale stream.
    let writer = upload::new_writer_id();
    let mut committed: Option<u64> = None;
    let mut failures = 0u32;
    let opts = UploadOptions {
        progress: false,
        ..opts.clone()
    };
    loop {
        let (spooled, sealed) = *watch.borrow_and_update();
        if committed.is_some() && confirmed >= spooled {
            if sealed || !follow {
                break;
            }
            // Caught up: wait for the producer (the sender lives in `spool`, so this cannot end).
            let _ = watch.changed().await;
            continue;
        }
        let pass = async {
            if !created {
                upload::create_session_request(server, spool.request(), &opts.policy()).await?;
            }
            upload::upload_rows_as(
                server,
                &id,
                channels,
                &SpoolRows {
                    spool: &spool,
                    upto: spooled,
                },
                confirmed,
                &opts,
                &writer,
            )
            .await
        };
        report.passes += 1;
        state.last_attempt_unix_ms = Some(now_ms());
        match pass.await {
            Ok(r) => {
                created = true;
                failures = 0;
                absorb(&mut report, &r);
                committed = Some(r.committed_rows);
                confirmed = confirmed.max(r.confirmed_rows);
                state.committed_rows = Some(r.committed_rows);
                state.confirmed_rows = Some(confirmed);
                state.last_error = r.last_error.clone();
                spool.save_state(&state);
                report.segments_deleted += spool.compact(confirmed)?;
            }
            Err(e) => {
                let message = format!("{e:#}");
                state.last_error = Some(message.clone());
                spool.save_state(&state);
                report.last_error = Some(message);
                let sealed_now = spool.is_sealed();
                let code = rpc_code(&e);
                let busy = code == Some(tonic::Code::Aborted);
                if sealed_now || !follow || !retryable(&e) || busy {
                    let next = match code {
                        Some(tonic::Code::Aborted) => format!(
                            "another upload holds the session; `helmholtz spool upload {id}` resumes once it has ended"
                        ),
                        Some(tonic::Code::AlreadyExists) => format!(
                            "the server holds other rows under this session id, so these are not ours to add; \
                             keep the spool and upload it under a new --session-id, or delete it once you know \
                             which data is right (`helmholtz spool status {id}`)"
                        ),
                        Some(tonic::Code::FailedPrecondition) => {
                            "the session takes no more rows; the unsent rows stay in the spool until you delete it \
                             or upload them under a new --session-id"
                                .to_string()
                        }
                        _ if retryable(&e) => format!("`helmholtz spool upload {id}` resumes"),
                        _ => format!(
                            "retrying cannot help until the cause is fixed; then `helmholtz spool upload {id}`"
                        ),
                    };
                    return Err(e.context(format!(
                        "session {id}: {} rows are safe in the spool {} ({} of them confirmed stored on the server); {next}",
                        spool.rows(),
                        spool.dir().display(),
                        confirmed
                    )));
                }
                report.resumes += 1;
                tokio::time::sleep(opts.backoff.random_delay(failures)).await;
                failures = failures.saturating_add(1);
            }
        }
    }
    let committed = committed.unwrap_or(0);
    if !spool.is_sealed() && spool.rows() >= spool.manifest().expected_rows {
        spool.seal()?; // every row of the spec is here: no producer can add any
    }
    report.spooled_rows = spool.rows();
    report.committed_rows = committed;
    report.confirmed_rows = confirmed;
    if spool.manifest().finish && confirmed >= spool.manifest().expected_rows {
        match upload::finish_session(server, &id).await {
            Ok(_) => {
                report.finished = true;
                state.finished = true;
                spool.save_state(&state);
            }
            Err(e) => {
                state.last_error = Some(format!("{e:#}"));
                spool.save_state(&state);
                return Err(e.context(format!(
                    "session {id}: every row is committed but finishing failed; `helmholtz spool upload {id}` retries"
                )));
            }
        }
    }
    // Sealed and every spooled row confirmed; with `finish`, only a finished session is done
    // (a sealed but incomplete one waits for a producer to add the missing rows).
    let done = spool.is_sealed()
        && confirmed >= spool.rows()
        && (!spool.manifest().finish || report.finished);
    if done {
        spool.remove()?;
        report.removed = true;
    }
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}

fn absorb(report: &mut DrainReport, r: &UploadReport) {
    report.rows_sent += r.rows_sent;
    report.bytes_sent += r.bytes_sent;
    report.resumes += r.resumes;
    if r.last_error.is_some() {
        report.last_error = r.last_error.clone();
    }
}

/// A quick, single look at a session's upload status (no retries; a short deadline): `None`
/// when the server does not know the session yet.
pub async fn probe_status(
    server: &str,
    session_id: &str,
) -> Result<Option<v1::UploadStatus>, String> {
    let policy = RetryPolicy {
        retry_for: Duration::ZERO,
        rpc_timeout: Duration::from_secs(3),
        connect_timeout: Duration::from_secs(2),
        ..RetryPolicy::default()
    };
    match upload::upload_status_with(server, session_id, &policy).await {
        Ok(s) => Ok(Some(s)),
        Err(e) => match e.downcast_ref::<RpcError>() {
            Some(r) if r.code == tonic::Code::NotFound => Ok(None),
            _ => Err(format!("{e:#}")),
        },
    }
}

/// A quick, single look at the server's committed count (no retries; a short deadline), for
/// status displays. A session the server does not know yet has committed nothing: `Ok(0)`.
pub async fn probe_committed(server: &str, session_id: &str) -> Result<u64, String> {
    let policy = RetryPolicy {
        retry_for: Duration::ZERO,
        rpc_timeout: Duration::from_secs(3),
        connect_timeout: Duration::from_secs(2),
        ..RetryPolicy::default()
    };
    match upload::upload_status_with(server, session_id, &policy).await {
        Ok(s) => Ok(s.committed_rows),
        Err(e) => match e.downcast_ref::<RpcError>() {
            Some(r) if r.code == tonic::Code::NotFound => Ok(0),
            _ => Err(format!("{e:#}")),
        },
    }
}

#[cfg(test)]
mod tests;
