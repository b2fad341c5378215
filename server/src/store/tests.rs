use std::collections::BTreeMap;

use helmholtz_proto::{ErrorEstimate, Family, PatternSpec};

use super::*;
use sqlx::Row;

/// Each test below runs on both backends: SQLite in a fresh data directory, PostgreSQL in a
/// fresh database that the test creates and drops ([`TestPostgres`]).
macro_rules! on_both_backends {
    ($($name:ident),* $(,)?) => {
        mod on_sqlite {
            $(
                #[tokio::test]
                async fn $name() {
                    let dir = tempfile::tempdir().unwrap();
                    super::$name(super::Store::open(dir.path()).await.unwrap()).await;
                }
            )*
        }
        mod on_postgres {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $name() {
                    let db = crate::store::postgres::testing::TestPostgres::create().await;
                    super::$name(db.store()).await;
                }
            )*
        }
    };
}

on_both_backends!(
    create_is_idempotent_and_conflicts_name_the_field,
    appends_compare_overlap_reject_gaps_and_read_back_exactly,
    leases_expire_and_fencing_stops_stale_workers,
    failures_retry_then_give_up,
    claims_alternate_between_labs_and_respect_the_per_lab_cap,
    sessions_belong_to_labs_and_ids_are_not_shared,
    an_overlap_that_differs_is_refused_and_stores_nothing,
    a_finished_session_refuses_new_rows_but_confirms_equal_ones,
    one_writer_lease_per_session_with_fencing,
    lab_caps_hold_under_concurrent_callers,
    claims_skip_jobs_that_do_not_fit_the_memory_left,
    transport_shards_are_leased_fenced_and_listed_in_order,
    a_shard_out_of_attempts_fails_and_a_cancelled_job_s_shards_stop,
    adaptive_batches_bound_the_rows_and_resolve_the_spec,
);

/// A request whose client cuts the connection drops the store call at any await. On PostgreSQL
/// that must never leave a pooled connection inside a transaction (the next borrower's
/// statements would run in it, hold their locks, and vanish if the connection closes): after
/// every cancelled append, no connection of the database stays `idle in transaction`, and the
/// appends that complete store every row once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn on_postgres_appends_cancelled_at_any_await_leave_no_transaction_open() {
    use sqlx::Connection;
    use std::task::Poll;
    use std::time::{Duration, Instant};
    let db = crate::store::postgres::testing::TestPostgres::create().await;
    let s = db.store();
    let mut admin = sqlx::PgConnection::connect(&crate::store::postgres::testing::admin_url())
        .await
        .unwrap();
    let total = 400;
    s.create_session(&new_session("s", total)).await.unwrap();
    let mut committed = 0;
    let mut cancelled = 0;
    for i in 0..600usize {
        if committed == total {
            break;
        }
        let n = 1 + (i as u64 % 3).min(total - committed - 1);
        let values = rows(committed, n);
        // Poll the append until a deadline between 0 and 1.5 ms (round trips on loopback are
        // ~0.1 ms: the deadlines fall before, inside and after each await), then drop it.
        let deadline = Instant::now() + Duration::from_micros((i as u64 * 37) % 1500);
        let done = {
            let append = s.append_rows("s", committed, 2, &values);
            tokio::pin!(append);
            std::future::poll_fn(|cx| match append.as_mut().poll(cx) {
                Poll::Ready(r) => Poll::Ready(Some(r)),
                Poll::Pending if Instant::now() >= deadline => Poll::Ready(None),
                Poll::Pending => {
                    cx.waker().wake_by_ref();
                    Poll::Pending
                }
            })
            .await
            // The append is dropped here, wherever it stood.
        };
        match done {
            Some(out) => assert!(out.unwrap().committed_rows > committed),
            None => cancelled += 1,
        }
        // The dropped request's connection goes back to the pool (its rollback flushed there);
        // a connection left inside a transaction would stay so.
        let waited = Instant::now();
        loop {
            let open: i64 = sqlx::query_scalar(
                "SELECT count(*) FROM pg_stat_activity \
                 WHERE datname = $1 AND state LIKE 'idle in transaction%'",
            )
            .bind(db.name())
            .fetch_one(&mut admin)
            .await
            .unwrap();
            if open == 0 {
                break;
            }
            if waited.elapsed() >= Duration::from_secs(5) {
                let last: Vec<String> = sqlx::query_scalar(
                    "SELECT query FROM pg_stat_activity \
                     WHERE datname = $1 AND state LIKE 'idle in transaction%'",
                )
                .bind(db.name())
                .fetch_all(&mut admin)
                .await
                .unwrap();
                panic!(
                    "after cancelled append {i}, {open} pooled connection(s) stay idle in a \
                     transaction (last statements: {last:?})"
                );
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        // Whatever the cancelled append did is either all stored or not at all.
        committed = s.session("s").await.unwrap().committed_rows;
    }
    // The rest, uncancelled: it must not stall on a lock a leaked transaction holds.
    if committed < total {
        s.append_rows("s", committed, 2, &rows(committed, total - committed))
            .await
            .unwrap();
    }
    assert!(cancelled > 50, "only {cancelled} appends were cancelled");
    let stored: Vec<f64> = s
        .read_chunks("s", 0, u32::MAX)
        .await
        .unwrap()
        .into_iter()
        .flat_map(|(_, v)| v)
        .collect();
    assert_eq!(stored, rows(0, total), "every row once, as sent");
    admin.close().await.ok();
}

fn new_session(id: &str, count: u64) -> NewSession {
    NewSession {
        id: id.into(),
        lab: "default".into(),
        rig: "bench".into(),
        spec: PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 4, 4, count, 1).unwrap(),
        channels: vec!["a".into(), "b".into()],
        directions: Vec::new(),
        camera: None,
        metadata: BTreeMap::from([("lab".into(), "optics".into())]),
        ground_truth: None,
    }
}

fn rows(start: u64, n: u64) -> Vec<f64> {
    (start..start + n)
        .flat_map(|r| [r as f64, -(r as f64)])
        .collect()
}

async fn create_is_idempotent_and_conflicts_name_the_field(s: Store) {
    let (a, created) = s.create_session(&new_session("s1", 10)).await.unwrap();
    assert!(created);
    let (b, created) = s.create_session(&new_session("s1", 10)).await.unwrap();
    assert!(!created);
    assert_eq!(a, b);
    let err = s.create_session(&new_session("s1", 11)).await.unwrap_err();
    assert!(
        matches!(err, StoreError::SessionConflict(_, "patterns")),
        "{err}"
    );
    let mut other_rig = new_session("s1", 10);
    other_rig.rig = "other".into();
    assert!(matches!(
        s.create_session(&other_rig).await,
        Err(StoreError::SessionConflict(_, "rig"))
    ));
}

async fn appends_compare_overlap_reject_gaps_and_read_back_exactly(s: Store) {
    s.create_session(&new_session("s", 10)).await.unwrap();
    let out = s.append_rows("s", 0, 2, &rows(0, 4)).await.unwrap();
    assert_eq!(
        out,
        AppendOutcome {
            committed_rows: 4,
            written: 4,
            matched: 0
        }
    );
    // Overlap: rows 2..6, of which 2 and 3 are already there.
    let out = s.append_rows("s", 2, 2, &rows(2, 4)).await.unwrap();
    assert_eq!(
        out,
        AppendOutcome {
            committed_rows: 6,
            written: 2,
            matched: 2
        }
    );
    // Entirely old.
    let out = s.append_rows("s", 0, 2, &rows(0, 3)).await.unwrap();
    assert_eq!(
        out,
        AppendOutcome {
            committed_rows: 6,
            written: 0,
            matched: 3
        }
    );
    // Gap.
    assert!(matches!(
        s.append_rows("s", 7, 2, &rows(7, 1)).await,
        Err(StoreError::Gap {
            committed: 6,
            start: 7
        })
    ));
    // Past the spec's count.
    assert!(matches!(
        s.append_rows("s", 6, 2, &rows(6, 5)).await,
        Err(StoreError::PastEnd {
            end: 11,
            expected: 10
        })
    ));
    assert!(matches!(
        s.finish_session("s").await,
        Err(StoreError::Incomplete { committed: 6, .. })
    ));
    s.append_rows("s", 6, 2, &rows(6, 4)).await.unwrap();
    let chunks = s.read_chunks("s", 0, 100).await.unwrap();
    let all: Vec<f64> = chunks.iter().flat_map(|(_, v)| v.clone()).collect();
    assert_eq!(all, rows(0, 10));
    assert_eq!(
        chunks.iter().map(|c| c.0).collect::<Vec<_>>(),
        vec![0, 4, 6]
    );
    // Paged reads continue at chunk boundaries.
    let page = s.read_chunks("s", 4, 1).await.unwrap();
    assert_eq!(page.len(), 1);
    assert_eq!(page[0].0, 4);
    let finished = s.finish_session("s").await.unwrap();
    assert_eq!(finished.state, SessionState::Finished);
    assert_eq!(s.finish_session("s").await.unwrap(), finished);
    assert!(matches!(
        s.append_rows("nope", 0, 2, &rows(0, 1)).await,
        Err(StoreError::SessionNotFound(_))
    ));
}

async fn leases_expire_and_fencing_stops_stale_workers(s: Store) {
    s.create_session(&new_session("s", 10)).await.unwrap();
    let r = s
        .enqueue_reconstruction("default", "s", "gi", "{}", 10, 3)
        .await
        .unwrap();
    assert_eq!(r.state, "queued");
    let first = s.claim_job("w1", 200, 0).await.unwrap().unwrap();
    assert_eq!((first.id, first.attempt), (r.id, 1));
    // While the lease holds, nobody else gets the job.
    assert!(s.claim_job("w2", 60_000, 0).await.unwrap().is_none());
    tokio::time::sleep(std::time::Duration::from_millis(250)).await;
    // The lease has expired (the worker died or stalled): another worker takes the job over.
    let second = s.claim_job("w2", 60_000, 0).await.unwrap().unwrap();
    assert_eq!((second.id, second.attempt), (r.id, 2));
    // The stale worker can neither heartbeat nor complete.
    assert!(!s.heartbeat(r.id, 1, 60_000, 0.5).await.unwrap());
    let image = StoredImage {
        channel_index: 0,
        channel_name: "a".into(),
        width: 1,
        height: 1,
        data: vec![1.0],
    };
    assert!(
        !s.complete_reconstruction(r.id, 1, std::slice::from_ref(&image), None, "{}", 0.1)
            .await
            .unwrap()
    );
    assert!(s.heartbeat(r.id, 2, 60_000, 0.5).await.unwrap());
    assert!(
        s.complete_reconstruction(
            r.id,
            2,
            std::slice::from_ref(&image),
            None,
            "{\"ok\":1}",
            0.1
        )
        .await
        .unwrap()
    );
    let done = s.reconstruction(r.id).await.unwrap();
    assert_eq!((done.state.as_str(), done.attempt), ("done", 2));
    assert_eq!(s.dual_images(r.id).await.unwrap(), vec![image]);
    assert_eq!(s.latest_done("s").await.unwrap(), Some(r.id));
    assert!(s.claim_job("w3", 60_000, 0).await.unwrap().is_none());
}

async fn failures_retry_then_give_up(s: Store) {
    s.create_session(&new_session("s", 10)).await.unwrap();
    let r = s
        .enqueue_reconstruction("default", "s", "gi", "{}", 10, 2)
        .await
        .unwrap();
    let c = s.claim_job("w", 60_000, 0).await.unwrap().unwrap();
    assert!(
        s.fail_job(r.id, c.attempt, "disk hiccup", true)
            .await
            .unwrap()
    );
    assert_eq!(s.reconstruction(r.id).await.unwrap().state, "queued");
    // Retries wait a little (run_at in the future), so nothing is claimable right now.
    assert!(s.claim_job("w", 60_000, 0).await.unwrap().is_none());
    let r2 = s
        .enqueue_reconstruction("default", "s", "dgi", "{}", 10, 1)
        .await
        .unwrap();
    let c2 = s.claim_job("w", 60_000, 0).await.unwrap().unwrap();
    assert_eq!(c2.id, r2.id);
    assert!(
        s.fail_job(r2.id, c2.attempt, "unsolvable", false)
            .await
            .unwrap()
    );
    let failed = s.reconstruction(r2.id).await.unwrap();
    assert_eq!(
        (failed.state.as_str(), failed.last_error.as_deref()),
        ("failed", Some("unsolvable"))
    );
    assert!(s.cancel_job(r.id).await.unwrap());
    assert_eq!(s.reconstruction(r.id).await.unwrap().state, "cancelled");
}

fn lab_session(lab: &str, id: &str) -> NewSession {
    NewSession {
        lab: lab.into(),
        ..new_session(id, 10)
    }
}

async fn claims_alternate_between_labs_and_respect_the_per_lab_cap(s: Store) {
    s.create_session(&lab_session("a", "sa")).await.unwrap();
    s.create_session(&lab_session("b", "sb")).await.unwrap();
    let mut a_jobs = Vec::new();
    for _ in 0..5 {
        a_jobs.push(
            s.enqueue_reconstruction("a", "sa", "gi", "{}", 10, 3)
                .await
                .unwrap()
                .id,
        );
        tokio::time::sleep(std::time::Duration::from_millis(2)).await;
    }
    let b_job = s
        .enqueue_reconstruction("b", "sb", "gi", "{}", 10, 3)
        .await
        .unwrap()
        .id;
    // One worker, finishing each job before claiming the next: lab b's single job is the second
    // to run, not the sixth.
    let mut order = Vec::new();
    while let Some(job) = s.claim_job("w", 60_000, 0).await.unwrap() {
        order.push(job.id);
        assert!(
            s.complete_reconstruction(job.id, job.attempt, &[], None, "{}", 0.0)
                .await
                .unwrap()
        );
        tokio::time::sleep(std::time::Duration::from_millis(2)).await;
    }
    assert_eq!(order.len(), 6);
    assert_eq!(order[1], b_job, "order {order:?}");
    assert_eq!(
        order
            .iter()
            .filter(|&&id| id != b_job)
            .copied()
            .collect::<Vec<_>>(),
        a_jobs,
        "a's jobs keep their order"
    );

    // Cap 1 per lab: with a's job running, a second of a's is not claimed, b's is.
    let a1 = s
        .enqueue_reconstruction("a", "sa", "gi", "{}", 10, 3)
        .await
        .unwrap()
        .id;
    let a2 = s
        .enqueue_reconstruction("a", "sa", "gi", "{}", 10, 3)
        .await
        .unwrap()
        .id;
    let b1 = s
        .enqueue_reconstruction("b", "sb", "gi", "{}", 10, 3)
        .await
        .unwrap()
        .id;
    let first = s.claim_job("w1", 60_000, 1).await.unwrap().unwrap();
    let second = s.claim_job("w2", 60_000, 1).await.unwrap().unwrap();
    assert_eq!(
        (first.id, second.id),
        (b1, a1),
        "b was served least recently, then a's oldest"
    );
    let _ = a2;
    assert!(
        s.claim_job("w3", 60_000, 1).await.unwrap().is_none(),
        "a is at its cap"
    );
    assert_eq!(s.pending_jobs_for_lab("a").await.unwrap(), 2);
    assert_eq!(s.queue_depth().await.unwrap(), (1, 2));
}

async fn sessions_belong_to_labs_and_ids_are_not_shared(s: Store) {
    s.create_session(&lab_session("a", "x")).await.unwrap();
    let err = s.create_session(&lab_session("b", "x")).await.unwrap_err();
    assert!(matches!(err, StoreError::SessionIdTaken(_)), "{err}");
    assert!(
        !err.to_string().contains("differ"),
        "says nothing about a's session: {err}"
    );
    assert_eq!(s.list_sessions("a", 10).await.unwrap().len(), 1);
    assert!(s.list_sessions("b", 10).await.unwrap().is_empty());
    assert_eq!(s.count_sessions("a").await.unwrap(), 1);
    assert_eq!(s.session("x").await.unwrap().lab, "a");
}

#[tokio::test]
async fn tokens_are_stored_hashed_and_revocable() {
    use crate::auth::{Role, Roles};
    let d = tempfile::tempdir().unwrap();
    // The SQLite backend itself: the test reads its token table.
    let s = Sqlite::open(d.path()).await.unwrap();
    let (info, secret) = s
        .create_token("optics", Roles::of(&[Role::Rig, Role::Reader]), "bench")
        .await
        .unwrap();
    assert_eq!(info.roles, "rig,reader");
    let p = s.authenticate(&secret).await.unwrap().unwrap();
    assert_eq!((p.lab.as_str(), p.token_id), ("optics", info.id));
    assert!(p.roles.contains(Role::Rig) && !p.roles.contains(Role::Admin));
    assert!(
        s.authenticate(&crate::auth::generate_token())
            .await
            .unwrap()
            .is_none()
    );
    // The secret itself is nowhere in the database file's token table.
    let stored: Vec<u8> = sqlx::query("SELECT sha256 FROM tokens")
        .fetch_one(&s.pool)
        .await
        .unwrap()
        .get(0);
    assert_eq!(stored, crate::auth::token_hash(&secret).to_vec());
    assert!(
        s.revoke_token(info.id, Some("other"))
            .await
            .unwrap()
            .is_none(),
        "another lab cannot revoke it"
    );
    assert!(s.authenticate(&secret).await.unwrap().is_some());
    let revoked = s
        .revoke_token(info.id, Some("optics"))
        .await
        .unwrap()
        .unwrap();
    assert!(revoked.revoked_unix_ms.is_some());
    assert!(s.authenticate(&secret).await.unwrap().is_none());
    assert_eq!(s.list_tokens(Some("optics")).await.unwrap().len(), 1);
    assert!(s.list_tokens(Some("other")).await.unwrap().is_empty());
}

#[tokio::test]
async fn upgrading_a_database_keeps_its_sessions_and_jobs_in_the_default_lab() {
    use sqlx::sqlite::SqliteConnectOptions;
    use std::str::FromStr;
    let dir = tempfile::tempdir().unwrap();
    // A database as the first schema left it.
    let first = dir.path().join("first-migration");
    std::fs::create_dir_all(&first).unwrap();
    std::fs::write(
        first.join("0001_sessions_jobs.sql"),
        include_str!("../../../migrations/sqlite/0001_sessions_jobs.sql"),
    )
    .unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).unwrap();
    let options = SqliteConnectOptions::from_str(&format!(
        "sqlite://{}",
        data.join("helmholtz.sqlite").display()
    ))
    .unwrap()
    .create_if_missing(true);
    let pool = sqlx::SqlitePool::connect_with(options).await.unwrap();
    sqlx::migrate::Migrator::new(first.as_path())
        .await
        .unwrap()
        .run(&pool)
        .await
        .unwrap();
    for id in ["old-run", "demo-usaf-hadamard"] {
        sqlx::query(
            "INSERT INTO sessions (id, rig, spec_json, channels_json, metadata_json, expected_rows, committed_rows, created_ms) \
             VALUES ($1, 'r', $2, '[\"a\"]', '{}', 16, 0, 1)",
        )
        .bind(id)
        .bind(r#"{"family":"raster","width":4,"height":4,"count":16,"seed":0}"#)
        .execute(&pool)
        .await
        .unwrap();
    }
    // A repeated raster stored before `scans` existed (two scans of 16 blocks, no declaration).
    sqlx::query(
        "INSERT INTO sessions (id, rig, spec_json, channels_json, metadata_json, expected_rows, committed_rows, created_ms) \
         VALUES ('old-repeat', 'r', $1, '[\"a\"]', '{}', 32, 0, 1)",
    )
    .bind(r#"{"family":"raster","block":1,"width":4,"height":4,"count":32,"seed":0}"#)
    .execute(&pool)
    .await
    .unwrap();
    // An adaptive session stored before `persistence` and `error_estimate` existed, and one
    // stored after `persistence` but before `error_estimate`.
    sqlx::query(
        "INSERT INTO sessions (id, rig, spec_json, channels_json, metadata_json, expected_rows, committed_rows, created_ms) \
         VALUES ('old-estimate', 'r', $1, '[\"a\"]', '{}', 32, 0, 1)",
    )
    .bind(r#"{"family":"adaptive_hadamard","batch":0,"target_error":0.1,"persistence":0.25,"width":4,"height":4,"count":32,"seed":0}"#)
    .execute(&pool)
    .await
    .unwrap();
    sqlx::query(
        "INSERT INTO sessions (id, rig, spec_json, channels_json, metadata_json, expected_rows, committed_rows, created_ms) \
         VALUES ('old-adaptive', 'r', $1, '[\"a\"]', '{}', 32, 0, 1)",
    )
    .bind(r#"{"family":"adaptive_haar","batch":0,"target_error":0.0,"width":4,"height":4,"count":32,"seed":0}"#)
    .execute(&pool)
    .await
    .unwrap();
    sqlx::query("INSERT INTO jobs (id, kind, state, run_at_ms, created_ms) VALUES (1, 'reconstruction', 'queued', 1, 1)")
        .execute(&pool)
        .await
        .unwrap();
    sqlx::query("INSERT INTO reconstructions (id, session_id, method, params_json, rows_used) VALUES (1, 'old-run', 'gi', '{}', 0)")
        .execute(&pool)
        .await
        .unwrap();
    pool.close().await;
    // Opening it applies 0002: nothing is lost, everything has a lab.
    let s = Store::open(&data).await.unwrap();
    assert_eq!(s.session("old-run").await.unwrap().lab, "default");
    assert_eq!(s.session("demo-usaf-hadamard").await.unwrap().lab, "demo");
    let r = s.reconstruction(1).await.unwrap();
    assert_eq!((r.lab.as_str(), r.state.as_str()), ("default", "queued"));
    assert_eq!(s.list_sessions("default", 10).await.unwrap().len(), 4);
    // The old repeated raster still opens, now declaring the two scans its count holds.
    let old = s.session("old-repeat").await.unwrap();
    assert_eq!(old.spec.family(), &Family::Raster { block: 1, scans: 2 });
    assert_eq!(old.spec.count(), 32);
    // The old adaptive session keeps the planner rule it was run with (no persistence), while
    // a new declaration without the field gets the family's default.
    let old = s.session("old-adaptive").await.unwrap();
    assert_eq!(old.spec.family().adaptive_persistence(), Some(0.0));
    assert_eq!(
        old.spec.family().adaptive_error_estimate(),
        Some(ErrorEstimate::Prediction)
    );
    let old = s.session("old-estimate").await.unwrap();
    assert_eq!(old.spec.family().adaptive_persistence(), Some(0.25));
    assert_eq!(
        old.spec.family().adaptive_error_estimate(),
        Some(ErrorEstimate::Prediction)
    );
    let new: PatternSpec = serde_json::from_str(
        r#"{"family":"adaptive_haar","batch":0,"target_error":0.0,"width":4,"height":4,"count":32,"seed":0}"#,
    )
    .unwrap();
    assert_eq!(
        new.family().adaptive_persistence(),
        Some(helmholtz_proto::patterns::HAAR_PERSISTENCE)
    );
    assert_eq!(
        new.family().adaptive_error_estimate(),
        Some(ErrorEstimate::Measured)
    );
    assert!(
        s.claim_job("w", 60_000, 0).await.unwrap().is_some(),
        "the queued job still runs"
    );
}

async fn an_overlap_that_differs_is_refused_and_stores_nothing(s: Store) {
    s.create_session(&new_session("s", 10)).await.unwrap();
    s.append_rows("s", 0, 2, &rows(0, 6)).await.unwrap();
    // Rows 4..8: row 5 differs in its second value; rows 6 and 7 would be new.
    let mut sent = rows(4, 4);
    sent[3] = 99.0;
    let err = s.append_rows("s", 4, 2, &sent).await.unwrap_err();
    match &err {
        StoreError::RowMismatch {
            row,
            byte,
            start,
            end,
            ..
        } => assert_eq!((*row, *byte / 8, *start, *end), (5, 1, 4, 8), "{err}"),
        other => panic!("expected a mismatch, got {other}"),
    }
    assert!(err.to_string().contains("row 5 of session"), "{err}");
    // Nothing of the chunk was stored: the count and the bytes are the earlier ones.
    assert_eq!(s.session("s").await.unwrap().committed_rows, 6);
    let all: Vec<f64> = s
        .read_chunks("s", 0, 100)
        .await
        .unwrap()
        .into_iter()
        .flat_map(|(_, v)| v)
        .collect();
    assert_eq!(all, rows(0, 6));
    // The same rows, equal, spanning two stored chunks and past the end: matched, then written.
    s.append_rows("s", 6, 2, &rows(6, 1)).await.unwrap();
    let out = s.append_rows("s", 3, 2, &rows(3, 6)).await.unwrap();
    assert_eq!(
        out,
        AppendOutcome {
            committed_rows: 9,
            written: 2,
            matched: 4
        }
    );
    // -0.0 and 0.0 compare equal as numbers but not as bytes: a row is its bytes.
    let mut signed = rows(0, 1);
    signed[0] = -0.0;
    assert!(matches!(
        s.append_rows("s", 0, 2, &signed).await,
        Err(StoreError::RowMismatch { row: 0, .. })
    ));
}

async fn a_finished_session_refuses_new_rows_but_confirms_equal_ones(s: Store) {
    s.create_session(&new_session("s", 4)).await.unwrap();
    s.append_rows("s", 0, 2, &rows(0, 4)).await.unwrap();
    s.finish_session("s").await.unwrap();
    let out = s.append_rows("s", 1, 2, &rows(1, 3)).await.unwrap();
    assert_eq!((out.written, out.matched), (0, 3));
    let mut other = rows(1, 3);
    other[0] = 7.0;
    assert!(matches!(
        s.append_rows("s", 1, 2, &other).await,
        Err(StoreError::RowMismatch { row: 1, .. })
    ));
    // One row past the spec's end (the spec is complete).
    assert!(matches!(
        s.append_rows("s", 4, 2, &rows(4, 1)).await,
        Err(StoreError::PastEnd { .. })
    ));
    let mut longer = new_session("t", 10);
    longer.id = "t".into();
    s.create_session(&longer).await.unwrap();
    s.append_rows("t", 0, 2, &rows(0, 10)).await.unwrap();
    s.finish_session("t").await.unwrap();
    assert_eq!(s.session("t").await.unwrap().committed_rows, 10);
}

async fn one_writer_lease_per_session_with_fencing(s: Store) {
    use std::time::Duration;
    s.create_session(&new_session("s", 10)).await.unwrap();
    let ttl = Duration::from_millis(300);
    let lease = |holder: &str| WriterLease {
        session_id: "s".into(),
        holder: holder.into(),
        writer: String::new(),
        ttl,
    };
    let (a, b, c) = (lease("a"), lease("b"), lease("c"));
    assert!(s.acquire_writer(&a).await.unwrap());
    assert!(!s.acquire_writer(&b).await.unwrap(), "held by a");
    assert!(s.acquire_writer(&a).await.unwrap(), "a renews its own");
    let blob =
        |r: u64, n: u64| -> Vec<u8> { rows(r, n).iter().flat_map(|v| v.to_le_bytes()).collect() };
    s.append_raw("s", Some(&a), 0, 16, &blob(0, 2))
        .await
        .unwrap();
    // b holds no lease: fenced off.
    assert!(matches!(
        s.append_raw("s", Some(&b), 2, 16, &blob(2, 2)).await,
        Err(StoreError::WriterLost(_))
    ));
    // a falls silent past its ttl; b takes the session; a's next append is refused.
    tokio::time::sleep(ttl + Duration::from_millis(100)).await;
    assert!(s.acquire_writer(&b).await.unwrap(), "a's lease expired");
    assert!(!s.renew_writer(&a).await.unwrap());
    assert!(matches!(
        s.append_raw("s", Some(&a), 2, 16, &blob(2, 2)).await,
        Err(StoreError::WriterLost(_))
    ));
    s.append_raw("s", Some(&b), 2, 16, &blob(2, 2))
        .await
        .unwrap();
    // Releasing is the holder's only: a's release leaves b's lease.
    s.release_writer(&a).await.unwrap();
    assert!(!s.acquire_writer(&c).await.unwrap());
    s.release_writer(&b).await.unwrap();
    assert!(s.acquire_writer(&c).await.unwrap());
    assert_eq!(s.session("s").await.unwrap().committed_rows, 4);

    // A writer's new stream takes over from its own earlier one (a connection cut without the
    // server noticing), which is fenced off; another writer still cannot.
    let stream = |holder: &str, writer: &str| WriterLease {
        session_id: "s".into(),
        holder: holder.into(),
        writer: writer.into(),
        ttl: Duration::from_secs(60),
    };
    s.release_writer(&c).await.unwrap();
    let (w1, w2, v) = (
        stream("w1", "rig-7"),
        stream("w2", "rig-7"),
        stream("v", "rig-8"),
    );
    assert!(s.acquire_writer(&w1).await.unwrap());
    assert!(!s.acquire_writer(&v).await.unwrap(), "another writer");
    assert!(
        s.acquire_writer(&w2).await.unwrap(),
        "the same writer's new stream"
    );
    assert!(matches!(
        s.append_raw("s", Some(&w1), 4, 16, &blob(4, 1)).await,
        Err(StoreError::WriterLost(_))
    ));
    s.append_raw("s", Some(&w2), 4, 16, &blob(4, 1))
        .await
        .unwrap();
    s.release_writer(&w1).await.unwrap();
    assert!(
        !s.acquire_writer(&v).await.unwrap(),
        "w1's release leaves w2's lease"
    );
}

async fn lab_caps_hold_under_concurrent_callers(s: Store) {
    let creates: Vec<_> = (0..30)
        .map(|i| {
            let s = s.clone();
            tokio::spawn(async move {
                s.create_session_capped(&lab_session("a", &format!("s{i}")), 3)
                    .await
            })
        })
        .collect();
    let mut created = 0;
    for t in creates {
        match t.await.unwrap() {
            Ok((_, true)) => created += 1,
            Ok((_, false)) => panic!("every id is new"),
            Err(StoreError::Cap { limit, message }) => {
                assert_eq!(limit, "max_sessions_per_lab");
                assert!(message.contains("limit 3"), "{message}");
            }
            Err(e) => panic!("{e}"),
        }
    }
    assert_eq!(created, 3);
    assert_eq!(s.count_sessions("a").await.unwrap(), 3);
    // An existing id is still returned at the cap (creation is idempotent).
    let first = s.list_sessions("a", 10).await.unwrap()[0].id.clone();
    let (_, created_again) = s
        .create_session_capped(&lab_session("a", &first), 3)
        .await
        .unwrap();
    assert!(!created_again);

    let requests: Vec<_> = (0..50)
        .map(|_| {
            let (s, id) = (s.clone(), first.clone());
            tokio::spawn(async move {
                s.enqueue_reconstruction_capped("a", &id, "gi", "{}", 0, 3, 5, 0)
                    .await
            })
        })
        .collect();
    let mut accepted = 0;
    for t in requests {
        match t.await.unwrap() {
            Ok(_) => accepted += 1,
            Err(StoreError::Cap { limit, .. }) => assert_eq!(limit, "max_pending_jobs_per_lab"),
            Err(e) => panic!("{e}"),
        }
    }
    assert_eq!(accepted, 5);
    assert_eq!(s.pending_jobs_for_lab("a").await.unwrap(), 5);
}

async fn claims_skip_jobs_that_do_not_fit_the_memory_left(s: Store) {
    s.create_session(&new_session("m", 10)).await.unwrap();
    let big = s
        .enqueue_reconstruction_capped("default", "m", "gi", "{}", 10, 3, u64::MAX, 900)
        .await
        .unwrap();
    let small = s
        .enqueue_reconstruction_capped("default", "m", "gi", "{}", 10, 3, u64::MAX, 100)
        .await
        .unwrap();
    // 500 bytes left: the older, larger job waits; the smaller one is taken.
    let job = s
        .claim_job_within("w", 10_000, 0, 500)
        .await
        .unwrap()
        .unwrap();
    assert_eq!((job.id, job.memory_bytes), (small.id, 100));
    assert!(
        s.claim_job_within("w", 10_000, 0, 500)
            .await
            .unwrap()
            .is_none()
    );
    let job = s
        .claim_job_within("w", 10_000, 0, 900)
        .await
        .unwrap()
        .unwrap();
    assert_eq!((job.id, job.memory_bytes), (big.id, 900));
}

/// A running transport job with its shards started: (reconstruction id, job attempt).
async fn running_transport(s: &Store, session: &str, max_attempts: u32, memory: u64) -> (i64, i64) {
    s.create_session(&new_session(session, 10)).await.unwrap();
    let r = s
        .enqueue_reconstruction_capped(
            "default",
            session,
            "transport",
            "{}",
            10,
            max_attempts,
            u64::MAX,
            memory,
        )
        .await
        .unwrap();
    let job = s.claim_job("holder", 60_000, 0).await.unwrap().unwrap();
    assert_eq!(job.id, r.id);
    (r.id, job.attempt)
}

async fn transport_shards_are_leased_fenced_and_listed_in_order(s: Store) {
    let (id, attempt) = running_transport(&s, "cam", 3, 1000).await;
    // Nothing to claim before the holder stores the model and its shards.
    assert!(
        s.claim_shard("w1", 60_000, u64::MAX, None)
            .await
            .unwrap()
            .is_none()
    );
    assert_eq!(s.transport_model(id).await.unwrap(), None);
    // Only the run that holds the job stores the model.
    assert_eq!(
        s.start_shards(id, attempt + 1, r#"{"m":0}"#, &[(0, 5)])
            .await
            .unwrap(),
        None
    );
    let first = s
        .start_shards(id, attempt, r#"{"m":1}"#, &[(0, 2), (2, 3), (3, 5)])
        .await
        .unwrap();
    assert_eq!(first.as_deref(), Some(r#"{"m":1}"#));
    // The model is chosen once: a second start (a later holder) gets the stored one back and
    // the shards stay as they were.
    let again = s
        .start_shards(id, attempt, r#"{"m":2}"#, &[(0, 5)])
        .await
        .unwrap();
    assert_eq!(again.as_deref(), Some(r#"{"m":1}"#));
    assert_eq!(
        s.transport_model(id).await.unwrap().as_deref(),
        Some(r#"{"m":1}"#)
    );
    let listed = s.shards(id).await.unwrap();
    assert_eq!(
        listed
            .iter()
            .map(|r| (
                r.shard,
                r.first_block,
                r.end_block,
                r.state.as_str(),
                r.attempt
            ))
            .collect::<Vec<_>>(),
        vec![
            (0, 0, 2, "queued", 0),
            (1, 2, 3, "queued", 0),
            (2, 3, 5, "queued", 0)
        ]
    );
    // The job's memory estimate must fit; shards of another reconstruction only when asked.
    assert!(s.claim_shard("w1", 200, 999, None).await.unwrap().is_none());
    assert!(
        s.claim_shard("w1", 200, u64::MAX, Some(id + 1))
            .await
            .unwrap()
            .is_none()
    );
    let a = s
        .claim_shard("w1", 200, 1000, Some(id))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(
        (
            a.reconstruction_id,
            a.shard,
            a.attempt,
            a.first_block,
            a.end_block
        ),
        (id, 0, 1, 0, 2)
    );
    assert_eq!(
        (
            a.session_id.as_str(),
            a.rows_used,
            a.model_json.as_str(),
            a.memory_bytes
        ),
        ("cam", 10, r#"{"m":1}"#, 1000)
    );
    let b = s
        .claim_shard("w2", 60_000, u64::MAX, None)
        .await
        .unwrap()
        .unwrap();
    assert_eq!((b.shard, b.attempt), (1, 1));
    // w1 stops heart-beating (killed): once its lease has run out, its shard is claimed again.
    tokio::time::sleep(std::time::Duration::from_millis(250)).await;
    let c = s
        .claim_shard("w3", 60_000, u64::MAX, None)
        .await
        .unwrap()
        .unwrap();
    assert_eq!((c.shard, c.attempt), (0, 2));
    // The stale run is fenced out: no heartbeat, no result.
    assert!(!s.heartbeat_shard(id, 0, 1, 60_000).await.unwrap());
    assert!(!s.complete_shard(id, 0, 1, b"stale").await.unwrap());
    assert!(s.heartbeat_shard(id, 0, 2, 60_000).await.unwrap());
    assert!(s.complete_shard(id, 0, 2, b"part 0").await.unwrap());
    assert!(!s.complete_shard(id, 0, 2, b"again").await.unwrap());
    // Not all done: no parts yet.
    assert!(s.shard_parts(id).await.is_err());
    // A transient failure queues the shard again; the next claim takes it (attempt 2).
    assert!(s.fail_shard(id, 1, 1, "disk hiccup", true).await.unwrap());
    assert!(!s.complete_shard(id, 1, 1, b"late").await.unwrap());
    let d = s
        .claim_shard("w2", 60_000, u64::MAX, None)
        .await
        .unwrap()
        .unwrap();
    assert_eq!((d.shard, d.attempt), (1, 2));
    assert!(s.complete_shard(id, 1, 2, b"part 1").await.unwrap());
    // A graceful shutdown gives the shard back without spending an attempt.
    let e = s
        .claim_shard("w4", 60_000, u64::MAX, None)
        .await
        .unwrap()
        .unwrap();
    assert_eq!((e.shard, e.attempt), (2, 1));
    assert!(s.release_shard(id, 2, 1).await.unwrap());
    let f = s
        .claim_shard("w5", 60_000, u64::MAX, None)
        .await
        .unwrap()
        .unwrap();
    assert_eq!((f.shard, f.attempt), (2, 1));
    assert!(s.complete_shard(id, 2, 1, b"part 2").await.unwrap());
    assert!(
        s.claim_shard("w6", 60_000, u64::MAX, None)
            .await
            .unwrap()
            .is_none()
    );
    let listed = s.shards(id).await.unwrap();
    assert_eq!(
        listed
            .iter()
            .map(|r| (
                r.state.as_str(),
                r.attempt,
                r.worker_id.as_deref(),
                r.part_bytes
            ))
            .collect::<Vec<_>>(),
        vec![
            ("done", 2, Some("w3"), Some(6)),
            ("done", 2, Some("w2"), Some(6)),
            ("done", 1, Some("w5"), Some(6))
        ]
    );
    assert_eq!(
        s.shard_parts(id).await.unwrap(),
        vec![b"part 0".to_vec(), b"part 1".to_vec(), b"part 2".to_vec()]
    );
    // The job completes with T whole; the parts are dropped, the shards' rows kept.
    assert!(
        s.complete_reconstruction(id, attempt, &[], Some(b"T"), "{}", 1.0)
            .await
            .unwrap()
    );
    assert_eq!(s.transport(id).await.unwrap().as_deref(), Some(&b"T"[..]));
    let listed = s.shards(id).await.unwrap();
    assert_eq!(listed.len(), 3);
    assert!(
        listed
            .iter()
            .all(|r| r.state == "done" && r.part_bytes.is_none())
    );
}

async fn a_shard_out_of_attempts_fails_and_a_cancelled_job_s_shards_stop(s: Store) {
    let (id, attempt) = running_transport(&s, "one", 1, 0).await;
    s.start_shards(id, attempt, "{}", &[(0, 1), (1, 2)])
        .await
        .unwrap()
        .unwrap();
    let a = s
        .claim_shard("w1", 60_000, u64::MAX, None)
        .await
        .unwrap()
        .unwrap();
    // Retry asked, but the job allows one attempt: the shard fails for good.
    assert!(
        s.fail_shard(id, a.shard, a.attempt, "bad frames", true)
            .await
            .unwrap()
    );
    // A shard whose worker died with no attempts left is marked failed at the next claim.
    let b = s
        .claim_shard("w2", 100, u64::MAX, None)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(b.shard, 1);
    tokio::time::sleep(std::time::Duration::from_millis(150)).await;
    assert!(
        s.claim_shard("w3", 60_000, u64::MAX, None)
            .await
            .unwrap()
            .is_none()
    );
    let listed = s.shards(id).await.unwrap();
    assert_eq!(
        listed
            .iter()
            .map(|r| (r.state.as_str(), r.last_error.as_deref()))
            .collect::<Vec<_>>(),
        vec![
            ("failed", Some("bad frames")),
            ("failed", Some("worker lost its lease (no attempts left)"))
        ]
    );
    // A cancelled job's shards are neither claimed, heart-beaten nor completed.
    let (id2, attempt2) = running_transport(&s, "two", 3, 0).await;
    s.start_shards(id2, attempt2, "{}", &[(0, 1), (1, 2)])
        .await
        .unwrap()
        .unwrap();
    let c = s
        .claim_shard("w1", 60_000, u64::MAX, None)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(c.reconstruction_id, id2);
    assert!(s.cancel_job(id2).await.unwrap());
    assert!(
        !s.heartbeat_shard(id2, c.shard, c.attempt, 60_000)
            .await
            .unwrap()
    );
    assert!(
        !s.complete_shard(id2, c.shard, c.attempt, b"late")
            .await
            .unwrap()
    );
    assert!(
        s.claim_shard("w2", 60_000, u64::MAX, None)
            .await
            .unwrap()
            .is_none()
    );
}

/// An adaptive session takes rows of its issued batches only; batches are stored in order,
/// idempotently, and resolve the spec; it may finish early.
async fn adaptive_batches_bound_the_rows_and_resolve_the_spec(s: Store) {
    let mut new = new_session("ad", 32);
    new.spec = PatternSpec::new(
        Family::AdaptiveHaar {
            batch: 2,
            target_error: 0.0,
            persistence: 0.5,
            error_estimate: ErrorEstimate::Measured,
            frames: helmholtz_proto::AdaptiveFrames::Pairs,
        },
        4,
        4,
        32,
        0,
    )
    .unwrap();
    let (session, _) = s.create_session(&new).await.unwrap();
    assert_eq!(s.resolved_spec_and_rows(&session).await.unwrap().1, 0);
    // Nothing issued: no row is taken.
    let e = s.append_rows("ad", 0, 2, &rows(0, 2)).await.unwrap_err();
    assert!(
        matches!(
            e,
            StoreError::NotIssued {
                end: 2,
                issued: 0,
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().starts_with("start_row"), "{e}");
    let b0 = IssuedBatch {
        number: 0,
        first_row: 0,
        indices: vec![0, 5],
    };
    assert_eq!(s.issue_batch("ad", None, &b0, 4).await.unwrap(), 4);
    // Issuing the same batch again changes nothing; another one at its number is refused.
    assert_eq!(s.issue_batch("ad", None, &b0, 4).await.unwrap(), 4);
    let other = IssuedBatch {
        indices: vec![0, 6],
        ..b0.clone()
    };
    assert!(matches!(
        s.issue_batch("ad", None, &other, 4).await,
        Err(StoreError::Corrupt(_))
    ));
    // A batch must continue the stored ones.
    let skipping = IssuedBatch {
        number: 2,
        first_row: 4,
        indices: vec![1],
    };
    assert!(s.issue_batch("ad", None, &skipping, 6).await.is_err());
    let b1 = IssuedBatch {
        number: 1,
        first_row: 4,
        indices: vec![3],
    };
    assert_eq!(s.issue_batch("ad", None, &b1, 6).await.unwrap(), 6);
    assert_eq!(s.batches("ad").await.unwrap(), vec![b0, b1]);
    let e = s.append_rows("ad", 0, 2, &rows(0, 7)).await.unwrap_err();
    assert!(
        matches!(
            e,
            StoreError::NotIssued {
                end: 7,
                issued: 6,
                ..
            }
        ),
        "{e}"
    );
    assert_eq!(
        s.session("ad").await.unwrap().committed_rows,
        0,
        "nothing stored"
    );
    s.append_rows("ad", 0, 2, &rows(0, 6)).await.unwrap();
    let (spec, issued) = s.resolved_spec_and_rows(&session).await.unwrap();
    assert_eq!(issued, 6);
    assert_eq!(spec.adaptive_indices(), Some(&[0u32, 5, 3][..]));
    // A non-adaptive session has no batches to issue.
    s.create_session(&new_session("plain", 8)).await.unwrap();
    assert!(matches!(
        s.issue_batch(
            "plain",
            None,
            &IssuedBatch {
                number: 0,
                first_row: 0,
                indices: vec![1]
            },
            2
        )
        .await,
        Err(StoreError::NotAdaptive(_))
    ));
    // An adaptive session finishes with the rows measured so far.
    let finished = s.finish_session("ad").await.unwrap();
    assert_eq!(finished.state, SessionState::Finished);
    assert_eq!(finished.committed_rows, 6);
}
