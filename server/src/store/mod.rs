//! The only place that speaks SQL: sessions, bucket rows, the job queue and results, in SQLite.
//!
//! SQLite runs in WAL mode with `synchronous = FULL`, so a committed transaction survives a crash
//! of the process or of the machine: rows are acknowledged only after their commit returns.

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use helmholtz_proto::PatternSpec;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{Row, SqlitePool};

mod jobs;
mod rows;
mod sessions;
mod tokens;

pub use jobs::{ClaimedJob, ReconstructionRow, StoredImage};
pub use rows::{AppendOutcome, WriterLease};
pub use sessions::{CameraLayout, NewSession, SampleFormat, SessionRow, SessionState};
pub use tokens::TokenInfo;

/// Storage errors, by what the caller should tell its user.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("session {0:?} not found")]
    SessionNotFound(String),
    #[error("reconstruction {0} not found")]
    ReconstructionNotFound(i64),
    #[error("session id {0:?} is already in use; choose another id")]
    SessionIdTaken(String),
    #[error("session {0:?} exists with a different declaration ({1} differs)")]
    SessionConflict(String, &'static str),
    #[error("rows must continue at row {committed}; this chunk starts at {start} (a gap)")]
    Gap { committed: u64, start: u64 },
    #[error("chunk ends at row {end} but the spec declares only {expected} rows")]
    PastEnd { end: u64, expected: u64 },
    #[error("session {0:?} is finished; it takes no more rows")]
    Finished(String),
    #[error(
        "row {row} of session {session:?} is already stored with different values (first \
         difference at byte {byte} of the row); nothing of this chunk (rows {start}..{end}) was \
         stored. A row's identity is its session and index: this is another measurement than the \
         stored one (another writer's, or another file under the same session id)"
    )]
    RowMismatch {
        session: String,
        row: u64,
        byte: usize,
        start: u64,
        end: u64,
    },
    #[error(
        "this upload no longer holds session {0:?}'s writer lease (another writer took it after \
         this stream fell silent); nothing of this chunk was stored"
    )]
    WriterLost(String),
    /// A per-lab cap (checked and applied in one transaction).
    #[error("{limit}: {message}")]
    Cap {
        limit: &'static str,
        message: String,
    },
    #[error("session {id:?} has {committed} of {expected} rows; upload the rest before finishing")]
    Incomplete {
        id: String,
        committed: u64,
        expected: u64,
    },
    #[error("stored data is corrupt: {0}")]
    Corrupt(String),
    #[error(transparent)]
    Db(#[from] sqlx::Error),
    #[error(transparent)]
    Migrate(#[from] sqlx::migrate::MigrateError),
}

/// Handle to the database; cheap to clone.
#[derive(Clone, Debug)]
pub struct Store {
    pool: SqlitePool,
    path: PathBuf,
}

pub(crate) fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

impl Store {
    /// Opens (creating if needed) `data_dir/helmholtz.sqlite` and applies pending migrations.
    pub async fn open(data_dir: &Path) -> Result<Store, StoreError> {
        let path = data_dir.join("helmholtz.sqlite");
        private_files(data_dir, &path).map_err(|e| {
            StoreError::Corrupt(format!(
                "cannot create data directory {}: {e}",
                data_dir.display()
            ))
        })?;
        let options = SqliteConnectOptions::from_str(&format!("sqlite://{}", path.display()))?
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Full)
            .busy_timeout(Duration::from_secs(10))
            .foreign_keys(true);
        let pool = SqlitePoolOptions::new()
            .max_connections(8)
            .connect_with(options)
            .await?;
        sqlx::migrate!("../migrations").run(&pool).await?;
        Ok(Store { pool, path })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub async fn close(&self) {
        self.pool.close().await;
    }

    /// True when the database answers (health checks).
    pub async fn ping(&self) -> bool {
        sqlx::query("SELECT 1")
            .fetch_one(&self.pool)
            .await
            .map(|r| r.get::<i64, _>(0) == 1)
            .unwrap_or(false)
    }
}

/// The data directory (mode 0700) and the database (0600) are the server's alone: tokens'
/// hashes and every lab's measurements live there. Modes are set explicitly, whatever the umask;
/// an existing directory or database open to others is narrowed, with a warning. SQLite gives its
/// `-wal` and `-shm` files the database's mode.
fn private_files(data_dir: &Path, db: &Path) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::{DirBuilderExt, OpenOptionsExt, PermissionsExt};
        if !data_dir.exists() {
            std::fs::DirBuilder::new()
                .recursive(true)
                .mode(0o700)
                .create(data_dir)?;
            std::fs::set_permissions(data_dir, std::fs::Permissions::from_mode(0o700))?;
        }
        narrow(data_dir, 0o700)?;
        if !db.exists() {
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .mode(0o600)
                .open(db)?;
            std::fs::set_permissions(db, std::fs::Permissions::from_mode(0o600))?;
        }
        for suffix in ["", "-wal", "-shm"] {
            let file = PathBuf::from(format!("{}{suffix}", db.display()));
            if file.exists() {
                narrow(&file, 0o600)?;
            }
        }
        fn narrow(path: &Path, mode: u32) -> std::io::Result<()> {
            let current = std::fs::metadata(path)?.permissions().mode() & 0o777;
            if current & !mode != 0 {
                tracing::warn!(
                    path = %path.display(),
                    from = format!("{current:o}"),
                    to = format!("{mode:o}"),
                    "narrowing permissions: the data directory and database are the server's alone"
                );
                std::fs::set_permissions(path, std::fs::Permissions::from_mode(current & mode))?;
            }
            Ok(())
        }
        Ok(())
    }
    #[cfg(not(unix))]
    {
        let _ = db;
        std::fs::create_dir_all(data_dir)
    }
}

pub(crate) fn parse_spec(json: &str) -> Result<PatternSpec, StoreError> {
    serde_json::from_str(json)
        .or_else(|e| legacy_repeated_raster(json).ok_or(e))
        .map_err(|e| StoreError::Corrupt(format!("stored spec: {e}")))
}

/// A raster stored before `scans` was part of the spec (PATTERNS.md) could run past one scan
/// without declaring it. Such a session was a repeated scan: read it as declaring the scans its
/// count holds, so its rows stay readable and reconstructable.
fn legacy_repeated_raster(json: &str) -> Option<PatternSpec> {
    let mut v: serde_json::Map<String, serde_json::Value> = serde_json::from_str(json).ok()?;
    if v.get("family")?.as_str()? != "raster" || v.contains_key("scans") {
        return None;
    }
    let get = |k: &str| v.get(k).and_then(serde_json::Value::as_u64);
    let (w, h, count) = (get("width")?, get("height")?, get("count")?);
    let block = get("block").unwrap_or(1);
    let helmholtz_proto::Family::Raster { scans, .. } = helmholtz_proto::Family::raster_covering(
        u32::try_from(block).ok()?,
        u32::try_from(w).ok()?,
        u32::try_from(h).ok()?,
        count,
    ) else {
        return None;
    };
    v.insert("scans".into(), scans.into());
    serde_json::from_value(serde_json::Value::Object(v)).ok()
}

pub(crate) fn f32_to_le(data: &[f32]) -> Vec<u8> {
    data.iter().flat_map(|v| v.to_le_bytes()).collect()
}

pub(crate) fn le_to_f32(bytes: &[u8]) -> Result<Vec<f32>, StoreError> {
    if !bytes.len().is_multiple_of(4) {
        return Err(StoreError::Corrupt("f32 blob of ragged length".into()));
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().expect("4")))
        .collect())
}

#[cfg(test)]
mod tests;
