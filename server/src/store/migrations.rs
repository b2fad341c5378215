//! The schema migrations of both backends, embedded in the binary (`migrations/sqlite`,
//! `migrations/postgres`). Listed here rather than by `sqlx::migrate!`, whose macro build
//! compiles SQLite and the PostgreSQL driver a second time for the compiler (about 200 s of a
//! 2-core machine's test build); a test checks the lists against the directories. What sqlx
//! records per migration (version, description from the file name, checksum of the SQL) is the
//! macro's, so databases migrated by earlier builds carry on.

use std::borrow::Cow;

use sqlx::SqlStr;
use sqlx::migrate::{Migration, MigrationType, Migrator};

/// (version, description, SQL): file `{version:04}_{description with _ for spaces}.sql`.
type Entry = (i64, &'static str, &'static str);

const SQLITE: &[Entry] = &[
    (
        1,
        "sessions jobs",
        include_str!("../../../migrations/sqlite/0001_sessions_jobs.sql"),
    ),
    (
        2,
        "labs tokens",
        include_str!("../../../migrations/sqlite/0002_labs_tokens.sql"),
    ),
    (
        3,
        "cameras transport",
        include_str!("../../../migrations/sqlite/0003_cameras_transport.sql"),
    ),
    (
        4,
        "leases and job memory",
        include_str!("../../../migrations/sqlite/0004_leases_and_job_memory.sql"),
    ),
    (
        5,
        "transport shards",
        include_str!("../../../migrations/sqlite/0005_transport_shards.sql"),
    ),
    (
        6,
        "adaptive batches",
        include_str!("../../../migrations/sqlite/0006_adaptive_batches.sql"),
    ),
];

const POSTGRES: &[Entry] = &[
    (
        1,
        "schema",
        include_str!("../../../migrations/postgres/0001_schema.sql"),
    ),
    (
        2,
        "transport shards",
        include_str!("../../../migrations/postgres/0002_transport_shards.sql"),
    ),
    (
        3,
        "adaptive batches",
        include_str!("../../../migrations/postgres/0003_adaptive_batches.sql"),
    ),
];

/// The SQLite store's migrator.
pub(super) fn sqlite() -> Migrator {
    migrator(SQLITE)
}

/// The PostgreSQL store's migrator.
pub(super) fn postgres() -> Migrator {
    migrator(POSTGRES)
}

fn migrator(entries: &[Entry]) -> Migrator {
    Migrator::with_migrations(
        entries
            .iter()
            .map(|&(version, description, sql)| {
                Migration::new(
                    version,
                    Cow::Borrowed(description),
                    MigrationType::Simple,
                    SqlStr::from_static(sql),
                    // As sqlx reads a migration file.
                    sql.starts_with("-- no-transaction"),
                )
            })
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lists are the directories, as sqlx's own reader resolves them (what `migrate!`
    /// embedded): the same versions, descriptions, checksums and transaction flags.
    #[tokio::test]
    async fn the_embedded_migrations_are_the_migration_directories() {
        for (dir, embedded) in [("sqlite", sqlite()), ("postgres", postgres())] {
            let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../migrations")
                .join(dir);
            let read = Migrator::new(path.as_path()).await.unwrap();
            let key = |m: &Migration| {
                (
                    m.version,
                    m.description.to_string(),
                    m.migration_type,
                    m.checksum.to_vec(),
                    m.no_tx,
                )
            };
            let (a, b): (Vec<_>, Vec<_>) = (
                read.iter().map(key).collect(),
                embedded.iter().map(key).collect(),
            );
            assert_eq!(
                a, b,
                "{dir}: a migration file is not listed in store/migrations.rs"
            );
        }
    }
}
