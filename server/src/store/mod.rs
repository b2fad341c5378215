//! What the service keeps: sessions, bucket rows, the job queue and results, tokens. The
//! domain's types and the [`Database`] trait (in parts: [`Sessions`], [`Rows`], [`Batches`], [`Jobs`],
//! [`Shards`], [`Tokens`]) live here with the rules every backend shares; the SQL lives in a backend
//! ([`sqlite`], embedded; [`postgres`], shared by many nodes). Rows are acknowledged only after their commit returns.

use std::path::Path;
use std::sync::Arc;
use std::time::{SystemTime, UNIX_EPOCH};

use async_trait::async_trait;
use helmholtz_proto::PatternSpec;

mod batches;
mod jobs;
mod migrations;
pub mod postgres;
mod record;
mod rows;
mod sessions;
mod shards;
pub mod sqlite;
mod tokens;

pub use batches::{Batches, IssuedBatch};
pub use jobs::{ClaimedJob, Jobs, ReconstructionRow, StoredImage};
pub use postgres::Postgres;
pub(crate) use record::StoreRow;
pub use rows::{AppendOutcome, RawChunk, Rows, WriterLease};
pub use sessions::{CameraLayout, NewSession, SampleFormat, SessionRow, SessionState, Sessions};
pub use shards::{ClaimedShard, ShardRow, Shards};
pub use sqlite::Sqlite;
pub use tokens::{TokenInfo, Tokens};

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
        "start_row: rows up to {end} of adaptive session {session:?} were not issued: the server \
         has issued rows 0..{issued} so far (send rows of the issued batches only; the next \
         batch follows their values)"
    )]
    NotIssued {
        session: String,
        end: u64,
        issued: u64,
    },
    #[error("session {0:?} does not declare an adaptive pattern family")]
    NotAdaptive(String),
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
    #[error(
        "the database URL must start with postgres:// or postgresql:// (leave it out for the \
         embedded SQLite database in the data directory)"
    )]
    UnsupportedUrl,
    #[error("stored data is corrupt: {0}")]
    Corrupt(String),
    #[error(transparent)]
    Db(#[from] sqlx::Error),
    #[error(transparent)]
    Migrate(#[from] sqlx::migrate::MigrateError),
}

impl StoreError {
    /// The database cannot be reached now (connections lost or refused, a pool waiting to
    /// reconnect, the server shutting down or out of connections): the request may succeed if
    /// retried, and nothing of it was stored.
    pub fn is_unavailable(&self) -> bool {
        let StoreError::Db(e) = self else {
            return false;
        };
        match e {
            sqlx::Error::Io(_)
            | sqlx::Error::Tls(_)
            | sqlx::Error::PoolTimedOut
            | sqlx::Error::PoolClosed
            | sqlx::Error::WorkerCrashed => true,
            sqlx::Error::Database(db) => {
                let code = db.code().unwrap_or_default();
                // 08: connection exception; 57P: operator intervention (shutdown, cannot
                // connect now); 53300: too many connections; 55000 as PostgreSQL says it of a
                // database that does not accept connections.
                code.starts_with("08")
                    || code.starts_with("57P")
                    || code == "53300"
                    || (code == "55000" && db.message().contains("accepting connections"))
            }
            _ => false,
        }
    }
}

/// Everything the service keeps, as one backend stores it: sessions and their rows, the job
/// queue and results, tokens. SQLite ([`Sqlite`]) is the embedded implementation; a backend
/// implements the parts and these.
#[async_trait]
pub trait Database:
    Sessions + Rows + Batches + Jobs + Shards + Tokens + std::fmt::Debug + Send + Sync + 'static
{
    /// True when the database answers (health checks).
    async fn ping(&self) -> bool;

    /// Closes the connections (after the last request).
    async fn close(&self);

    /// Where the data lives, for logs and the operator (never a password).
    fn describe(&self) -> String;

    /// The newest migration applied to the database.
    async fn schema_version(&self) -> Result<i64, StoreError>;

    /// The clock leases are measured on, Unix milliseconds: the database's own (PostgreSQL), or
    /// this process's (SQLite, one machine).
    async fn clock_ms(&self) -> Result<i64, StoreError> {
        Ok(now_ms())
    }

    /// Runs until dropped: wakes `wake`'s waiters whenever any process sharing the database
    /// queues a job (a hint: idle workers also look every so often). The default never wakes:
    /// an embedded database has no other process, and this one wakes its workers directly.
    async fn forward_job_wakeups(&self, wake: Arc<tokio::sync::Notify>) {
        let _ = wake;
        std::future::pending::<()>().await
    }
}

/// Handle to the database the process uses; cheap to clone. Dereferences to [`Database`], so
/// every part's methods are called on it directly.
#[derive(Clone, Debug)]
pub struct Store(Arc<dyn Database>);

impl std::ops::Deref for Store {
    type Target = dyn Database;
    fn deref(&self) -> &Self::Target {
        &*self.0
    }
}

impl Store {
    /// Opens (creating if needed) the embedded SQLite database in `data_dir` and applies
    /// pending migrations.
    pub async fn open(data_dir: &Path) -> Result<Store, StoreError> {
        Ok(Store::from(Sqlite::open(data_dir).await?))
    }

    /// The database a process was told to use: PostgreSQL at `database_url`
    /// (`postgres://...`, with at most `max_connections` pooled connections), or without a URL
    /// the embedded SQLite in `data_dir`. Applies pending migrations either way.
    pub async fn connect(
        database_url: Option<&str>,
        data_dir: &Path,
        max_connections: u32,
    ) -> Result<Store, StoreError> {
        match database_url {
            None => Store::open(data_dir).await,
            Some(url) if url.starts_with("postgres://") || url.starts_with("postgresql://") => {
                Ok(Store::from(Postgres::connect(url, max_connections).await?))
            }
            Some(_) => Err(StoreError::UnsupportedUrl),
        }
    }
}

impl<D: Database> From<D> for Store {
    fn from(db: D) -> Store {
        Store(Arc::new(db))
    }
}

pub(crate) fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

pub(crate) fn parse_spec(json: &str) -> Result<PatternSpec, StoreError> {
    let legacy = legacy_adaptive(json);
    serde_json::from_str(legacy.as_deref().unwrap_or(json))
        .or_else(|e| legacy_repeated_raster(json).ok_or(e))
        .map_err(|e| StoreError::Corrupt(format!("stored spec: {e}")))
}

/// An adaptive session stored before `persistence` or `error_estimate` was part of the spec
/// (PATTERNS.md) was planned without it, so it reads as `persistence: 0` and
/// `error_estimate: "prediction"`: a replay of its values must give back the indices it showed.
/// (A new declaration that leaves either out gets the default instead; the canonical form stored
/// since states both.)
fn legacy_adaptive(json: &str) -> Option<String> {
    if !json.contains("\"adaptive_")
        || (json.contains("\"persistence\"") && json.contains("\"error_estimate\""))
    {
        return None;
    }
    let mut v: serde_json::Map<String, serde_json::Value> = serde_json::from_str(json).ok()?;
    if !v.get("family")?.as_str()?.starts_with("adaptive_") {
        return None;
    }
    v.entry("persistence").or_insert(0.0.into());
    v.entry("error_estimate").or_insert("prediction".into());
    Some(serde_json::Value::Object(v).to_string())
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
