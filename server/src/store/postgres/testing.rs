//! A fresh PostgreSQL database per test, created at the start and dropped at the end (also when
//! the test fails: the guard drops it while unwinding).

use std::str::FromStr;

use sqlx::postgres::PgConnectOptions;
use sqlx::{Connection, Executor, PgConnection};

use super::Postgres;
use crate::store::Store;

/// Where the tests' PostgreSQL server is: `HELMHOLTZ_TEST_POSTGRES`, or the local server with
/// trust authentication.
pub(crate) fn admin_url() -> String {
    std::env::var("HELMHOLTZ_TEST_POSTGRES")
        .unwrap_or_else(|_| "postgres://postgres@127.0.0.1:5432/postgres".to_string())
}

pub(crate) struct TestPostgres {
    name: String,
    store: Store,
}

impl TestPostgres {
    pub(crate) async fn create() -> TestPostgres {
        let admin = admin_url();
        let mut conn = PgConnection::connect(&admin).await.unwrap_or_else(|e| {
            panic!(
                "this test needs PostgreSQL at {admin} ({e}). Start the local server \
                 (Debian: `pg_ctlcluster $(ls /etc/postgresql) main start`; .ci/run does this) or \
                 set HELMHOLTZ_TEST_POSTGRES to a postgres:// URL of a user who may CREATE DATABASE"
            )
        });
        let name = format!("helmholtz_test_{:016x}", rand::random::<u64>());
        conn.execute(sqlx::AssertSqlSafe(format!("CREATE DATABASE \"{name}\"")))
            .await
            .unwrap_or_else(|e| panic!("creating the test database {name} at {admin}: {e}"));
        conn.close().await.ok();
        let options = PgConnectOptions::from_str(&admin)
            .expect("HELMHOLTZ_TEST_POSTGRES is a postgres:// URL")
            .database(&name);
        let db = Postgres::connect_with(options, 8)
            .await
            .unwrap_or_else(|e| panic!("migrating the test database {name}: {e}"));
        TestPostgres {
            name,
            store: Store::from(db),
        }
    }

    pub(crate) fn store(&self) -> Store {
        self.store.clone()
    }

    /// The database's name (for `pg_stat_activity`).
    pub(crate) fn name(&self) -> &str {
        &self.name
    }
}

impl Drop for TestPostgres {
    fn drop(&mut self) {
        let name = self.name.clone();
        // Drop may run inside the test's runtime: drop the database from a thread of its own.
        std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .expect("runtime");
            rt.block_on(async {
                if let Ok(mut conn) = PgConnection::connect(&admin_url()).await {
                    let _ = conn
                        .execute(sqlx::AssertSqlSafe(format!(
                            "DROP DATABASE IF EXISTS \"{name}\" WITH (FORCE)"
                        )))
                        .await;
                }
            });
        })
        .join()
        .ok();
    }
}
