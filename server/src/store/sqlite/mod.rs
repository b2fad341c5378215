//! The embedded backend: one SQLite file in the data directory.
//!
//! SQLite runs in WAL mode with `synchronous = FULL`, so a committed transaction survives a crash
//! of the process or of the machine. Writers take the database's write lock first
//! (`BEGIN IMMEDIATE`), so every read-check-write transaction is serialised.

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

use async_trait::async_trait;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{Row, SqlitePool};

use super::{Database, StoreError};

mod batches;
mod jobs;
mod rows;
mod sessions;
mod shards;
mod tokens;

/// The SQLite database `helmholtz.sqlite` of a data directory; cheap to clone.
#[derive(Clone, Debug)]
pub struct Sqlite {
    pub(crate) pool: SqlitePool,
    path: PathBuf,
}

impl Sqlite {
    /// Opens (creating if needed) `data_dir/helmholtz.sqlite` and applies pending migrations.
    pub async fn open(data_dir: &Path) -> Result<Sqlite, StoreError> {
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
        super::migrations::sqlite().run(&pool).await?;
        Ok(Sqlite { pool, path })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[async_trait]
impl Database for Sqlite {
    async fn ping(&self) -> bool {
        sqlx::query("SELECT 1")
            .fetch_one(&self.pool)
            .await
            .map(|r| r.get::<i64, _>(0) == 1)
            .unwrap_or(false)
    }

    async fn close(&self) {
        self.pool.close().await;
    }

    fn describe(&self) -> String {
        format!("sqlite:{}", self.path.display())
    }

    async fn schema_version(&self) -> Result<i64, StoreError> {
        Ok(sqlx::query(
            "SELECT CAST(COALESCE(MAX(version), 0) AS BIGINT) FROM _sqlx_migrations WHERE success",
        )
        .fetch_one(&self.pool)
        .await?
        .get::<i64, _>(0))
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
