//! A fresh PostgreSQL database per test (created at the start, dropped when the guard drops, also
//! when the test fails), and the server's processes on it: API nodes and workers.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::{Context, bail};
use sqlx::{Connection, Executor, PgConnection};

use crate::binary;

/// Where the tests' PostgreSQL server is: `HELMHOLTZ_TEST_POSTGRES` (a URL of a user who may
/// CREATE DATABASE), or the local server with trust authentication.
pub fn admin_url() -> String {
    std::env::var("HELMHOLTZ_TEST_POSTGRES")
        .unwrap_or_else(|_| "postgres://postgres@127.0.0.1:5432/postgres".to_string())
}

/// A database of its own for one test.
pub struct TestDatabase {
    name: String,
    url: String,
}

/// Runs `f` to completion on a runtime of its own in a thread of its own, so the harness can be
/// called from sync and async tests alike.
fn on_own_runtime<T: Send + 'static>(
    f: impl std::future::Future<Output = T> + Send + 'static,
) -> T {
    std::thread::spawn(move || {
        tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .expect("runtime")
            .block_on(f)
    })
    .join()
    .unwrap_or_else(|e| std::panic::resume_unwind(e))
}

impl TestDatabase {
    /// Creates the database. Panics, saying how to provide PostgreSQL, when there is none.
    pub fn create() -> TestDatabase {
        let admin = admin_url();
        sweep_orphans(&admin);
        let name = format!("helmholtz_e2e_{}_{:016x}", std::process::id(), rand_u64());
        let (admin_, name_) = (admin.clone(), name.clone());
        on_own_runtime(async move {
            let (admin, name) = (admin_, name_);
            let mut conn = PgConnection::connect(&admin).await.unwrap_or_else(|e| {
                panic!(
                    "this test needs PostgreSQL at {admin} ({e}). Start the local server \
                     (Debian: `pg_ctlcluster $(ls /etc/postgresql) main start`; .ci/run does \
                     this) or set HELMHOLTZ_TEST_POSTGRES to a postgres:// URL of a user who \
                     may CREATE DATABASE"
                )
            });
            conn.execute(sqlx::AssertSqlSafe(format!("CREATE DATABASE \"{name}\"")))
                .await
                .unwrap_or_else(|e| panic!("creating the test database {name}: {e}"));
            conn.close().await.ok();
        });
        let base = admin.rsplit_once('/').map_or(admin.as_str(), |(b, _)| b);
        let url = format!("{base}/{name}");
        TestDatabase { name, url }
    }

    pub fn url(&self) -> &str {
        &self.url
    }

    /// A token made by the real `helmholtz-server token create` against this database.
    pub fn create_token(&self, lab: &str, roles: &str) -> anyhow::Result<String> {
        let out = Command::new(binary("helmholtz-server"))
            .args([
                "token",
                "create",
                "--lab",
                lab,
                "--role",
                roles,
                "--database-url",
            ])
            .arg(&self.url)
            .env("RUST_LOG", "warn")
            .output()
            .context("running helmholtz-server token create")?;
        if !out.status.success() {
            bail!(
                "token create failed: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        Ok(String::from_utf8(out.stdout)?.trim().to_string())
    }

    /// The database's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Runs `sql` on the PostgreSQL server as the administrator (connected to its maintenance
    /// database, not to this one), e.g. to refuse this database's connections for a while.
    pub fn admin(&self, sql: &str) {
        let sql = sql.to_string();
        on_own_runtime(async move {
            let mut conn = PgConnection::connect(&admin_url()).await.expect("connect");
            conn.execute(sqlx::AssertSqlSafe(sql.clone()))
                .await
                .unwrap_or_else(|e| panic!("{sql}: {e}"));
            conn.close().await.ok();
        })
    }

    /// Runs one SQL query returning one BIGINT (for checks on what is stored).
    pub fn scalar(&self, sql: &str) -> i64 {
        let (url, sql) = (self.url.clone(), sql.to_string());
        on_own_runtime(async move {
            let sql = sql.as_str();
            let mut conn = PgConnection::connect(&url).await.expect("connect");
            let v: i64 = sqlx::query_scalar(sqlx::AssertSqlSafe(sql.to_string()))
                .fetch_one(&mut conn)
                .await
                .unwrap_or_else(|e| panic!("{sql}: {e}"));
            conn.close().await.ok();
            v
        })
    }
}

/// Drops the test databases (`helmholtz_e2e_PID_...`) of test processes that are gone (killed
/// before their databases were dropped), once per process.
fn sweep_orphans(admin: &str) {
    static SWEPT: std::sync::Once = std::sync::Once::new();
    let admin = admin.to_string();
    // Process ids name processes of this machine only.
    if !(admin.contains("@127.0.0.1") || admin.contains("@localhost") || admin.contains("@[::1]")) {
        return;
    }
    SWEPT.call_once(move || {
        on_own_runtime(async move {
            let Ok(mut conn) = PgConnection::connect(&admin).await else {
                return; // create() says how to provide PostgreSQL
            };
            let names: Vec<String> = sqlx::query_scalar(
                "SELECT datname FROM pg_database WHERE datname LIKE 'helmholtz_e2e_%'",
            )
            .fetch_all(&mut conn)
            .await
            .unwrap_or_default();
            for name in names {
                let pid = name
                    .strip_prefix("helmholtz_e2e_")
                    .and_then(|rest| rest.split('_').next())
                    .and_then(|p| p.parse::<u32>().ok());
                // Only databases named by a process that no longer runs on this machine.
                if pid.is_some_and(|p| !std::path::Path::new(&format!("/proc/{p}")).exists()) {
                    let _ = conn
                        .execute(sqlx::AssertSqlSafe(format!(
                            "DROP DATABASE IF EXISTS \"{name}\" WITH (FORCE)"
                        )))
                        .await;
                }
            }
            conn.close().await.ok();
        });
    });
}

impl TestDatabase {
    /// Runs one SQL query returning rows of one TEXT column (NULLs skipped).
    pub fn strings(&self, sql: &str) -> Vec<String> {
        let (url, sql) = (self.url.clone(), sql.to_string());
        on_own_runtime(async move {
            let mut conn = PgConnection::connect(&url).await.expect("connect");
            let v: Vec<Option<String>> = sqlx::query_scalar(sqlx::AssertSqlSafe(sql.clone()))
                .fetch_all(&mut conn)
                .await
                .unwrap_or_else(|e| panic!("{sql}: {e}"));
            conn.close().await.ok();
            v.into_iter().flatten().collect()
        })
    }

    /// A reconstruction's stored transport matrix (its parts joined), as the server wrote it.
    pub fn transport(&self, reconstruction_id: i64) -> Vec<u8> {
        let url = self.url.clone();
        on_own_runtime(async move {
            let mut conn = PgConnection::connect(&url).await.expect("connect");
            let parts: Vec<Vec<u8>> = sqlx::query_scalar(
                "SELECT data FROM transports WHERE reconstruction_id = $1 ORDER BY part",
            )
            .bind(reconstruction_id)
            .fetch_all(&mut conn)
            .await
            .expect("reading the stored transport matrix");
            conn.close().await.ok();
            parts.concat()
        })
    }
}

impl Drop for TestDatabase {
    fn drop(&mut self) {
        let name = self.name.clone();
        on_own_runtime(async move {
            if let Ok(mut conn) = PgConnection::connect(&admin_url()).await {
                let _ = conn
                    .execute(sqlx::AssertSqlSafe(format!(
                        "DROP DATABASE IF EXISTS \"{name}\" WITH (FORCE)"
                    )))
                    .await;
            }
        });
    }
}

fn rand_u64() -> u64 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos()),
    );
    h.finish()
}

/// A `helmholtz-server worker` process (no listener). Killed (SIGKILL) when dropped.
pub struct WorkerProcess {
    child: Child,
}

impl WorkerProcess {
    /// Starts `workers` worker threads on `db` and waits until they run.
    pub fn start(db: &TestDatabase, workers: u32, extra: &[&str]) -> anyhow::Result<WorkerProcess> {
        Self::start_with_env(db, workers, extra, &[])
    }

    /// [`WorkerProcess::start`] with environment variables `env` set for the process.
    pub fn start_with_env(
        db: &TestDatabase,
        workers: u32,
        extra: &[&str],
        env: &[(&str, &str)],
    ) -> anyhow::Result<WorkerProcess> {
        let mut child = Command::new(binary("helmholtz-server"))
            .args([
                "worker",
                "--workers",
                &workers.to_string(),
                "--database-url",
            ])
            .arg(db.url())
            .args(extra)
            .envs(env.iter().copied())
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("spawning helmholtz-server worker")?;
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut lines = BufReader::new(stdout).lines();
            let _ = tx.send(lines.next());
            for _ in lines {}
        });
        let line = rx
            .recv_timeout(Duration::from_secs(60))
            .context("the worker printed nothing")?;
        anyhow::ensure!(
            matches!(&line, Some(Ok(l)) if l.contains("workers on postgres://")),
            "unexpected first line from the worker: {line:?}"
        );
        Ok(WorkerProcess { child })
    }

    /// The process id (a worker's id in the database starts with it).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// SIGKILL.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for WorkerProcess {
    fn drop(&mut self) {
        self.kill();
    }
}
