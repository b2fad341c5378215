//! Which database the end-to-end servers use: `HELMHOLTZ_TEST_BACKEND=sqlite` (the default: a
//! SQLite file in the test's data directory) or `postgres` (a fresh PostgreSQL database per data
//! directory, created by the harness and dropped when the test process exits). The README's test
//! command runs the end-to-end suite once with each.
//!
//! A data directory keeps its database for the whole test process (a test that stops a server
//! and starts another on the same directory finds its data again), so the databases are dropped
//! at exit; one left behind by a test process that was killed is dropped by the next one
//! ([`crate::pg::TestDatabase::create`] sweeps databases of processes that are gone).

use std::collections::HashMap;
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use crate::pg::TestDatabase;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    Sqlite,
    Postgres,
}

/// The backend of this test process (`HELMHOLTZ_TEST_BACKEND`).
pub fn backend() -> Backend {
    static BACKEND: OnceLock<Backend> = OnceLock::new();
    *BACKEND.get_or_init(
        || match std::env::var("HELMHOLTZ_TEST_BACKEND").as_deref() {
            Err(_) | Ok("") | Ok("sqlite") => Backend::Sqlite,
            Ok("postgres") => Backend::Postgres,
            Ok(other) => panic!("HELMHOLTZ_TEST_BACKEND={other:?}: use sqlite or postgres"),
        },
    )
}

/// The databases of this process's data directories, dropped at exit.
fn databases() -> &'static Mutex<HashMap<PathBuf, TestDatabase>> {
    static DATABASES: OnceLock<Mutex<HashMap<PathBuf, TestDatabase>>> = OnceLock::new();
    DATABASES.get_or_init(|| {
        extern "C" fn drop_all() {
            if let Some(m) = DATABASES.get() {
                let all: Vec<TestDatabase> = match m.lock() {
                    Ok(mut map) => map.drain().map(|(_, db)| db).collect(),
                    Err(poisoned) => poisoned.into_inner().drain().map(|(_, db)| db).collect(),
                };
                drop(all);
            }
        }
        // SAFETY: registers a plain function without arguments, run once at process exit.
        unsafe {
            libc::atexit(drop_all);
        }
        Mutex::new(HashMap::new())
    })
}

/// The PostgreSQL URL of `data_dir`'s database, created on first use.
pub fn database_url(data_dir: &Path) -> String {
    let key = std::fs::canonicalize(data_dir).unwrap_or_else(|_| data_dir.to_path_buf());
    let mut map = databases().lock().unwrap_or_else(|p| p.into_inner());
    map.entry(key)
        .or_insert_with(TestDatabase::create)
        .url()
        .to_string()
}

/// The arguments that point a `helmholtz-server` command (serve, token, migrate, check) at
/// `data_dir`'s store on this process's backend: `--data-dir DIR` for SQLite; for PostgreSQL
/// also `--database-url URL` (the directory still holds what is not in the database).
pub fn store_args(data_dir: &Path) -> Vec<OsString> {
    store_args_on(backend(), data_dir)
}

/// [`store_args`] on `backend` whatever this process's backend is (for a test of one backend's
/// own behaviour, such as the SQLite file's permissions).
pub fn store_args_on(backend: Backend, data_dir: &Path) -> Vec<OsString> {
    let mut args: Vec<OsString> = vec!["--data-dir".into(), data_dir.into()];
    if backend == Backend::Postgres {
        args.push("--database-url".into());
        args.push(database_url(data_dir).into());
    }
    args
}

/// A `helmholtz-server` command with `args` followed by [`store_args`] of `data_dir`.
pub fn server_command(data_dir: &Path, args: &[&str]) -> std::process::Command {
    let mut c = std::process::Command::new(crate::binary("helmholtz-server"));
    c.args(args)
        .args(store_args(data_dir))
        .env("RUST_LOG", "warn");
    c
}
