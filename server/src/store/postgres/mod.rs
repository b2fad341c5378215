//! The shared backend: PostgreSQL, for API nodes and workers on many machines.
//!
//! Every read-check-write that SQLite serialises with its single write lock is serialised here
//! by a row lock (a session's appends: `SELECT .. FOR UPDATE` on the session) or by a
//! transaction-scoped advisory lock (a lab's session and job caps, the fair claim), so the rules
//! hold across every node that shares the database. Times come from the database's clock
//! (`helmholtz_now_ms()`, migrations/postgres), never a node's.

use std::str::FromStr;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use sqlx::postgres::{PgConnectOptions, PgListener, PgPoolOptions};
use sqlx::{Connection, PgPool, Postgres as Pg, Row, Transaction};

use super::{Database, StoreError};

mod batches;
mod jobs;
mod rows;
mod sessions;
mod shards;
#[cfg(test)]
pub(crate) mod testing;
mod tokens;

/// Connections of the pool for bulk reads ([`Postgres::bulk`]), besides `--database-connections`.
pub const BULK_CONNECTIONS: u32 = 2;

/// A PostgreSQL database; cheap to clone.
#[derive(Clone, Debug)]
pub struct Postgres {
    pub(crate) pool: PgPool,
    /// Reads of bulk data (rows, frames, images, T and its parts) go through a pool of
    /// [`BULK_CONNECTIONS`] of their own, which bounds how many such reads (each up to a part
    /// of T in the driver's receive buffer, then copied out) one process runs at once. Like
    /// the main pool's, its connections shrink their buffers when released: the driver would
    /// otherwise keep each as large as the largest message it carried (16 x an 8 MiB part of
    /// T, say), memory no budget accounts for.
    pub(crate) bulk: PgPool,
    /// host:port/database, for logs (never the password).
    name: String,
}

impl Postgres {
    /// Connects to `url` (`postgres://user@host:port/database`), with at most `max_connections`
    /// pooled connections, and applies pending migrations.
    pub async fn connect(url: &str, max_connections: u32) -> Result<Postgres, StoreError> {
        Postgres::connect_with(PgConnectOptions::from_str(url)?, max_connections).await
    }

    pub async fn connect_with(
        options: PgConnectOptions,
        max_connections: u32,
    ) -> Result<Postgres, StoreError> {
        let name = format!(
            "postgres://{}@{}:{}/{}",
            options.get_username(),
            options.get_host(),
            options.get_port(),
            options.get_database().unwrap_or("")
        );
        // Every connection gives back the memory of a large message (a chunk written, a part of
        // T read) when it returns to its pool, so what a process holds between queries does not
        // grow with the data.
        let pool = PgPoolOptions::new()
            .max_connections(max_connections.max(2))
            .acquire_timeout(Duration::from_secs(30))
            .after_release(shrink_buffers)
            .connect_with(options.clone())
            .await?;
        super::migrations::postgres().run(&pool).await?;
        let bulk = PgPoolOptions::new()
            .max_connections(BULK_CONNECTIONS)
            .acquire_timeout(Duration::from_secs(30))
            .after_release(shrink_buffers)
            .connect_lazy_with(options);
        Ok(Postgres { pool, bulk, name })
    }
}

#[async_trait]
impl Database for Postgres {
    async fn ping(&self) -> bool {
        sqlx::query("SELECT 1::BIGINT")
            .fetch_one(&self.pool)
            .await
            .map(|r| r.get::<i64, _>(0) == 1)
            .unwrap_or(false)
    }

    async fn close(&self) {
        self.bulk.close().await;
        self.pool.close().await;
    }

    fn describe(&self) -> String {
        self.name.clone()
    }

    async fn schema_version(&self) -> Result<i64, StoreError> {
        Ok(sqlx::query(
            "SELECT CAST(COALESCE(MAX(version), 0) AS BIGINT) FROM _sqlx_migrations WHERE success",
        )
        .fetch_one(&self.pool)
        .await?
        .get::<i64, _>(0))
    }

    async fn clock_ms(&self) -> Result<i64, StoreError> {
        Ok(sqlx::query("SELECT helmholtz_now_ms()")
            .fetch_one(&self.pool)
            .await?
            .get::<i64, _>(0))
    }

    /// LISTEN on the channel every enqueue notifies; after a lost connection, listens again
    /// with a growing pause (notifications sent meanwhile are lost: workers also poll).
    async fn forward_job_wakeups(&self, wake: Arc<tokio::sync::Notify>) {
        let mut pause = Duration::from_millis(100);
        loop {
            let listening = async {
                let mut listener = PgListener::connect_with(&self.pool).await?;
                listener.listen(JOBS_CHANNEL).await?;
                Ok::<_, sqlx::Error>(listener)
            };
            match listening.await {
                Ok(mut listener) => {
                    pause = Duration::from_millis(100);
                    // Whatever was queued while not listening.
                    wake.notify_waiters();
                    loop {
                        match listener.recv().await {
                            Ok(_) => wake.notify_waiters(),
                            Err(e) => {
                                tracing::warn!(error = %e, "lost the job notifications; listening again");
                                break;
                            }
                        }
                    }
                }
                Err(e) => {
                    tracing::warn!(error = %e, retry_in = ?pause, "cannot listen for job notifications");
                }
            }
            tokio::time::sleep(pause).await;
            pause = (pause * 2).min(Duration::from_secs(10));
        }
    }
}

/// A pool's `after_release`: the connection gives back buffers grown past the driver's default
/// by a large message, and stays in the pool.
fn shrink_buffers(
    conn: &mut sqlx::PgConnection,
    _: sqlx::pool::PoolConnectionMetadata,
) -> futures::future::BoxFuture<'_, Result<bool, sqlx::Error>> {
    Box::pin(async move {
        conn.shrink_buffers();
        Ok(true)
    })
}

/// The channel an enqueue notifies (`pg_notify`) and idle workers listen on.
pub(crate) const JOBS_CHANNEL: &str = "helmholtz_jobs";

/// Starts a transaction on a pooled connection, cancellation-safe.
///
/// sqlx 0.9.0's PostgreSQL `begin` counts the transaction only after `BEGIN`'s answer arrives: a
/// future dropped while waiting for it (a request whose client cut the connection) leaves the
/// session inside a transaction that nothing rolls back, and the pool hands that connection on;
/// the next borrower's statements then run inside it, hold their locks (a session's row lock
/// stalls its appends) and are lost if the connection closes (upstream sqlx issues #4385 and
/// #4393, fixed after 0.9.0). Here `BEGIN` runs in a task of its own that no caller can drop
/// midway; a transaction whose caller has gone is dropped afterwards, fully counted, and its
/// rollback is queued and flushed when the connection returns to the pool. Statements inside a
/// counted transaction are safe to drop: sqlx rolls the transaction back.
pub(crate) async fn begin(pool: &PgPool) -> Result<Transaction<'static, Pg>, StoreError> {
    let pool = pool.clone();
    match tokio::spawn(async move { pool.begin().await }).await {
        Ok(tx) => Ok(tx?),
        Err(e) if e.is_panic() => std::panic::resume_unwind(e.into_panic()),
        // Only when the runtime shuts down.
        Err(_) => Err(sqlx::Error::PoolClosed.into()),
    }
}

/// Takes the transaction-scoped advisory lock named `helmholtz.{what}` (released at commit or
/// rollback).
pub(crate) async fn advisory_lock(
    tx: &mut Transaction<'_, Pg>,
    what: &str,
) -> Result<(), StoreError> {
    sqlx::query("SELECT pg_advisory_xact_lock(hashtextextended($1, 0))")
        .bind(format!("helmholtz.{what}"))
        .execute(&mut **tx)
        .await?;
    Ok(())
}

/// [`advisory_lock`] for one lab's `what` (its sessions, its jobs).
pub(crate) async fn lab_lock(
    tx: &mut Transaction<'_, Pg>,
    what: &str,
    lab: &str,
) -> Result<(), StoreError> {
    advisory_lock(tx, &format!("{what}:{lab}")).await
}
