//! Past one machine: API nodes (`serve --workers 0`) and worker processes (`worker`) share one
//! PostgreSQL database. Any node answers any request, rows uploaded through two nodes are stored
//! exactly, one writer per session holds across nodes, jobs queued on one node run in a worker
//! process, and a killed worker's job is taken up by another; a camera session's transport
//! matrix is solved in shards by several worker processes, a killed worker's shard is taken up
//! again, and the T assembled from the shards is the single-process T bit for bit. Needs
//! PostgreSQL (see
//! `helmholtz_tests::pg`); each test creates and drops its own database.

use std::time::{Duration, Instant};

use helmholtz_client::upload::{SampleRows, Samples, upload_rows_as};
use helmholtz_client::{NewSession, PatternSpec, UploadOptions};
use helmholtz_proto::v1;
use helmholtz_sim::Target;
use helmholtz_sim::simulate::{self, NoiseModel};
use helmholtz_tests::pg::{TestDatabase, WorkerProcess};
use helmholtz_tests::{OpenUpload, ServerProcess, parse_npy, simulate_camera_session};
use serde_json::Value;
use tonic::Code;

async fn simulated(spec: &str) -> (PatternSpec, Vec<f64>) {
    let spec: PatternSpec = serde_json::from_str(spec).unwrap();
    let transport = Target::builtin("double-slit", spec.width(), spec.height())
        .unwrap()
        .transport(1.0);
    let s = spec.clone();
    let values = tokio::task::spawn_blocking(move || {
        simulate::simulate(&s, &[&transport], &NoiseModel::default(), None).values
    })
    .await
    .unwrap();
    (spec, values)
}

async fn get(server: &ServerProcess, path: &str) -> (u16, Value) {
    let r = helmholtz_tests::http_get(server.url(path)).await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

async fn request(server: &ServerProcess, id: &str, body: &str) -> i64 {
    let r = helmholtz_tests::http_client()
        .post(server.url(&format!("/v1/sessions/{id}/reconstructions")))
        .header("content-type", "application/json")
        .body(body.to_string())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 202, "request on {id}");
    r.json::<Value>().await.unwrap()["id"].as_i64().unwrap()
}

async fn wait_state(server: &ServerProcess, id: i64, states: &[&str], within: Duration) -> Value {
    let deadline = Instant::now() + within;
    loop {
        let (_, r) = get(server, &format!("/v1/reconstructions/{id}")).await;
        if states.contains(&r["state"].as_str().unwrap_or("")) {
            return r;
        }
        assert!(
            Instant::now() < deadline,
            "reconstruction {id} never reached {states:?}: {r}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

async fn stored_bits(server: &ServerProcess, id: &str) -> Vec<u64> {
    let r = helmholtz_tests::http_get(server.url(&format!("/v1/sessions/{id}/measurements.npy")))
        .await
        .unwrap();
    assert_eq!(r.status(), 200, "measurements of {id}");
    let (_, values) = parse_npy(&r.bytes().await.unwrap()).unwrap();
    values.iter().map(|v| v.to_bits()).collect()
}

fn chunk(id: &str, start: u64, values: &[f64]) -> v1::MeasurementChunk {
    helmholtz_tests::f64_chunk(id, start, 1, values)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_nodes_and_worker_processes_share_one_postgres_database() {
    let db = TestDatabase::create();
    // The operator's checks: migrate, then check (reachable, schema, clock).
    let run = |args: &[&str]| {
        std::process::Command::new(helmholtz_tests::binary("helmholtz-server"))
            .args(args)
            .env("RUST_LOG", "warn")
            .output()
            .unwrap()
    };
    let migrated = run(&["migrate", "--database-url", db.url()]);
    assert!(migrated.status.success(), "{migrated:?}");
    let checked = run(&["check", "--database-url", db.url()]);
    let text = String::from_utf8_lossy(&checked.stdout);
    assert!(checked.status.success(), "{checked:?}");
    assert!(
        text.contains("reachable, schema at migration 3, clock skew"),
        "{text}"
    );
    let refused = run(&["check", "--database-url", "mysql://root@127.0.0.1/x"]);
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("must start with postgres://"),
        "{refused:?}"
    );
    let token = db.create_token("e2e", "rig,reader").unwrap();
    let a = ServerProcess::start_on_postgres(&db, &token, &["--workers", "0"]).unwrap();
    let b = ServerProcess::start_on_postgres(&db, &token, &["--workers", "0"]).unwrap();

    // A session created on node A, its first half uploaded through A, all of it again through
    // B (the overlap compared, the rest written), finished on B: stored exactly as sent.
    let (spec, values) =
        simulated(r#"{"family":"hadamard","width":16,"height":16,"count":512,"seed":3}"#).await;
    helmholtz_client::create_session(
        &a.base_url,
        &NewSession::new("shared", spec, vec!["bucket".into()]),
    )
    .await
    .unwrap();
    let half = values.len() / 2;
    helmholtz_client::upload(
        &a.base_url,
        "shared",
        1,
        &values[..half],
        &UploadOptions::default(),
    )
    .await
    .unwrap();
    helmholtz_client::upload(&b.base_url, "shared", 1, &values, &UploadOptions::default())
        .await
        .unwrap();
    helmholtz_client::finish_session(&b.base_url, "shared")
        .await
        .unwrap();
    let sent: Vec<u64> = values.iter().map(|v| v.to_bits()).collect();
    assert_eq!(stored_bits(&a, "shared").await, sent);
    assert_eq!(stored_bits(&b, "shared").await, sent);

    // One writer per session across nodes: a stream open on A holds the session; B's writer is
    // ABORTED naming it, and nothing of B's chunk is stored.
    let (mut ca, mut cb) = (a.grpc().await.unwrap(), b.grpc().await.unwrap());
    ca.create_session(helmholtz_tests::bucket_session(
        "w",
        v1::PatternFamily::Bernoulli,
        8,
        8,
        100,
        &["bucket"],
    ))
    .await
    .unwrap();
    let rows = |r: std::ops::Range<u64>| r.map(|i| i as f64 + 0.25).collect::<Vec<_>>();
    let open = OpenUpload::start(&ca, Some("rig-a"), chunk("w", 0, &rows(0..10)), 10).await;
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    tx.send(chunk("w", 10, &rows(10..20))).await.unwrap();
    drop(tx);
    let mut req = tonic::Request::new(tokio_stream::wrappers::ReceiverStream::new(rx));
    req.metadata_mut()
        .insert("x-helmholtz-writer", "rig-b".parse().unwrap());
    let status = cb.upload_measurements(req).await.unwrap_err();
    assert_eq!(status.code(), Code::Aborted, "{status:?}");
    assert!(
        status.message().contains("session \"w\""),
        "{}",
        status.message()
    );
    assert!(open.send(chunk("w", 10, &rows(10..20))).await);
    let done = open.finish().await.unwrap();
    assert_eq!((done.committed_rows, done.rows_written), (20, 20));
    assert_eq!(
        db.scalar("SELECT committed_rows FROM sessions WHERE id = 'w'"),
        20
    );

    // A reconstruction requested on A waits in the queue: no node of this database has workers.
    let job = request(&a, "shared", r#"{"method": "dgi"}"#).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(
        get(&b, &format!("/v1/reconstructions/{job}")).await.1["state"],
        "queued"
    );
    // A worker process takes it (woken by the notification, or at its next look).
    let _worker = WorkerProcess::start(&db, 1, &[]).unwrap();
    let done = wait_state(&b, job, &["done", "failed"], Duration::from_secs(60)).await;
    assert_eq!(done["state"], "done", "{done}");
    // Either node serves the result, the same bytes.
    let image = |s: &ServerProcess| {
        let url = s.url(&format!("/v1/reconstructions/{job}/dual.npy"));
        async move {
            helmholtz_tests::http_get(url)
                .await
                .unwrap()
                .bytes()
                .await
                .unwrap()
        }
    };
    let (from_a, from_b) = (image(&a).await, image(&b).await);
    let (shape, pixels) = parse_npy(&from_a).unwrap();
    assert_eq!(shape.iter().product::<usize>(), 16 * 16, "{shape:?}");
    assert!(pixels.iter().any(|v| *v != 0.0));
    assert_eq!(from_a, from_b);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_worker_process_s_job_is_taken_up_by_another() {
    let db = TestDatabase::create();
    let token = db.create_token("e2e", "rig,reader").unwrap();
    let api = ServerProcess::start_on_postgres(&db, &token, &["--workers", "0"]).unwrap();
    // Grey-level patterns, many rows: seconds of work.
    let (spec, values) =
        simulated(r#"{"family":"speckle","width":64,"height":64,"count":60000,"seed":9}"#).await;
    helmholtz_client::create_session(
        &api.base_url,
        &NewSession::new("long", spec, vec!["bucket".into()]),
    )
    .await
    .unwrap();
    helmholtz_client::upload(&api.base_url, "long", 1, &values, &UploadOptions::default())
        .await
        .unwrap();
    helmholtz_client::finish_session(&api.base_url, "long")
        .await
        .unwrap();
    let job = request(&api, "long", r#"{"method": "gi"}"#).await;
    let mut first = WorkerProcess::start(&db, 1, &["--lease-seconds", "2"]).unwrap();
    wait_state(&api, job, &["running"], Duration::from_secs(30)).await;
    first.kill();
    // Another worker process takes the job over once the dead one's lease runs out.
    let _second = WorkerProcess::start(&db, 1, &["--lease-seconds", "2"]).unwrap();
    let done = wait_state(&api, job, &["done", "failed"], Duration::from_secs(120)).await;
    assert_eq!(done["state"], "done", "{done}");
    assert_eq!(done["attempt"], 2, "{done}");
    // Exactly one result: one image per channel.
    assert_eq!(
        db.scalar(&format!(
            "SELECT COUNT(*) FROM dual_images WHERE reconstruction_id = {job}"
        )),
        1
    );
}

const TRANSPORT: &str = r#"{"method": "transport", "params": {"sample_pixels": 16}}"#;

/// The shards of a reconstruction: (count, distinct worker processes, most attempts).
fn shard_figures(db: &TestDatabase, id: i64) -> (i64, i64, i64) {
    (
        db.scalar(&format!(
            "SELECT COUNT(*) FROM transport_shards WHERE reconstruction_id = {id} AND state = 'done'"
        )),
        db.scalar(&format!(
            "SELECT COUNT(DISTINCT split_part(worker_id, '-', 1)) FROM transport_shards WHERE reconstruction_id = {id}"
        )),
        db.scalar(&format!(
            "SELECT COALESCE(MAX(attempt), 0) FROM transport_shards WHERE reconstruction_id = {id}"
        )),
    )
}

/// The same session's T from one worker process with sharding effectively off (one shard of
/// all its blocks): the single-process T.
async fn single_process_t(
    db: &TestDatabase,
    api: &ServerProcess,
    session: &str,
) -> (Vec<u8>, Value) {
    let _worker = WorkerProcess::start(db, 1, &[]).unwrap();
    let job = request(api, session, TRANSPORT).await;
    let done = wait_state(api, job, &["done", "failed"], Duration::from_secs(300)).await;
    assert_eq!(done["state"], "done", "{done}");
    assert_eq!(shard_figures(db, job).0, 1, "one shard");
    (db.transport(job), done)
}

/// Sends `signal` (`STOP`, `CONT`) to a process.
fn signal(pid: u32, signal: &str) {
    let status = std::process::Command::new("kill")
        .args([&format!("-{signal}"), &pid.to_string()])
        .status()
        .expect("running kill");
    assert!(status.success(), "kill -{signal} {pid}");
}

/// Polls `sql` (a count) until it is `want`, at most `within`.
async fn wait_count(db: &TestDatabase, sql: &str, want: i64, within: Duration) {
    let deadline = Instant::now() + within;
    loop {
        if db.scalar(sql) == want {
            return;
        }
        assert!(Instant::now() < deadline, "never {want}: {sql}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// Two worker processes solve one transport job's shards, and the T they assemble is the
/// single-process T bit for bit. The turns are made certain: once the job's holder has stored
/// its shards it is paused (SIGSTOP) with at most the shard it is solving, so the other process
/// must take the rest (it is woken by the shards' notification, or by its poll); the holder goes
/// on (SIGCONT) when nothing is left for the other and assembles T. Without the pause the
/// holder can solve all six small shards before the other process is scheduled (seen on a
/// loaded CI machine).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_transport_in_shards_on_two_worker_processes_is_the_single_process_t() {
    let db = TestDatabase::create();
    let token = db.create_token("e2e", "rig,reader").unwrap();
    let api = ServerProcess::start_on_postgres(&db, &token, &["--workers", "0"]).unwrap();
    simulate_camera_session(&api, "cam", "16x12", 32, 384);
    // Shards of 32 camera pixels: 6 of the 192.
    let shards = ["--transport-shard-pixels", "32"];
    let a = WorkerProcess::start(&db, 1, &shards).unwrap();
    let b = WorkerProcess::start(&db, 1, &shards).unwrap();
    let job = request(&api, "cam", TRANSPORT).await;
    wait_count(
        &db,
        &format!("SELECT LEAST(COUNT(*), 1) FROM transport_shards WHERE reconstruction_id = {job}"),
        1,
        Duration::from_secs(120),
    )
    .await;
    let holder = db
        .strings(&format!("SELECT worker_id FROM jobs WHERE id = {job}"))
        .pop()
        .expect("the job's holder");
    let held = match holder.starts_with(&format!("{}-", a.pid())) {
        true => a.pid(),
        false => b.pid(),
    };
    assert!(holder.starts_with(&format!("{held}-")), "{holder}");
    signal(held, "STOP");
    // Nothing queued, and nothing running but the holder's own shard.
    let left = format!(
        "SELECT COUNT(*) FROM transport_shards WHERE reconstruction_id = {job} \
         AND (state = 'queued' OR (state = 'running' AND worker_id NOT LIKE '{held}-%'))"
    );
    wait_count(&db, &left, 0, Duration::from_secs(120)).await;
    signal(held, "CONT");
    let done = wait_state(&api, job, &["done", "failed"], Duration::from_secs(300)).await;
    assert_eq!(done["state"], "done", "{done}");
    let (count, workers, _) = shard_figures(&db, job);
    assert_eq!(count, 6, "{done}");
    // Both processes took shards (the worker ids on the shard rows start with the pid).
    let timeline = db.strings(&format!(
        "SELECT shard || ' ' || worker_id || ' ' || started_ms || ' ' || finished_ms \
         FROM transport_shards WHERE reconstruction_id = {job} ORDER BY shard"
    ));
    assert_eq!(
        workers, 2,
        "shards by one process only (shard, worker, started, finished ms): {timeline:#?}"
    );
    let pids: Vec<String> = [a.pid(), b.pid()].iter().map(|p| p.to_string()).collect();
    for w in db.strings(&format!(
        "SELECT worker_id FROM transport_shards WHERE reconstruction_id = {job}"
    )) {
        assert!(
            pids.iter().any(|p| w.starts_with(&format!("{p}-"))),
            "{w} of {pids:?}"
        );
    }
    // The parts are dropped once T is stored whole.
    assert_eq!(
        db.scalar(&format!(
            "SELECT COUNT(*) FROM transport_shards WHERE reconstruction_id = {job} AND part IS NOT NULL"
        )),
        0
    );
    let report = &done["report"];
    println!(
        "shards: {}, seconds {}",
        report["details"]["shards"], report["seconds"]
    );
    assert_eq!(report["details"]["shards"]["count"], 6, "{report}");
    let sharded = db.transport(job);
    assert!(sharded.len() > 64, "{} bytes of T", sharded.len());
    drop((a, b));

    let (single, single_done) = single_process_t(&db, &api, "cam").await;
    assert!(
        sharded == single,
        "the sharded T differs from the single-process T"
    );
    // The same model, chosen once on the same sample: the same figures.
    for key in [
        "transform",
        "lambda",
        "refit",
        "selection",
        "nonzeros",
        "iterations_max",
    ] {
        assert_eq!(
            report["details"][key], single_done["report"]["details"][key],
            "{key}"
        );
    }
    assert_eq!(report["held_out"], single_done["report"]["held_out"]);
    assert_eq!(report["iterations"], single_done["report"]["iterations"]);
}

/// A node that loses its database says so in its health check (503 "not serving", within the
/// probe's patience), uploads meanwhile wait and retry, and once the database takes connections
/// again the node reconnects by itself, reports SERVING, and the upload completes: every row
/// stored once, as sent.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_node_that_loses_the_database_says_so_and_recovers_without_losing_rows() {
    let db = TestDatabase::create();
    let token = db.create_token("e2e", "rig,reader").unwrap();
    let api = ServerProcess::start_on_postgres(&db, &token, &["--workers", "0"]).unwrap();
    let health = || async {
        let r = helmholtz_tests::http_get(format!("{}/healthz", api.address))
            .await
            .unwrap();
        (
            r.status().as_u16(),
            r.json::<Value>().await.unwrap_or(Value::Null),
        )
    };
    let wait_health = |want: u16, within: Duration| async move {
        let deadline = Instant::now() + within;
        loop {
            let (status, body) = health().await;
            if status == want {
                return body;
            }
            assert!(
                Instant::now() < deadline,
                "health never became {want}: {status} {body}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    };
    assert_eq!(
        wait_health(200, Duration::from_secs(5)).await["status"],
        "serving"
    );
    let (spec, values) = rig_rows(7, 4000).await;
    helmholtz_client::create_session(
        &api.base_url,
        &NewSession::new("outage", spec, vec!["bucket".into()]),
    )
    .await
    .unwrap();
    let writer = helmholtz_client::upload::new_writer_id();
    upload_as(
        &api.base_url,
        "outage",
        &values[..2000],
        &writer,
        Duration::from_secs(5),
    )
    .await
    .unwrap();

    // The database goes away for this node: no new connections, the open ones ended.
    let name = db.name().to_string();
    db.admin(&format!(
        "ALTER DATABASE \"{name}\" ALLOW_CONNECTIONS false"
    ));
    db.admin(&format!(
        "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = '{name}'"
    ));
    let down = wait_health(503, Duration::from_secs(10)).await;
    assert_eq!(down["status"], "not serving", "{down}");
    // Requests meanwhile are refused as unavailable (retry), not as internal errors.
    let (status, problem) = get(&api, "/v1/sessions/outage").await;
    assert_eq!(
        (status, problem["type"].as_str()),
        (503, Some("/problems/unavailable")),
        "{problem}"
    );
    let once = helmholtz_client::upload::RetryPolicy {
        retry_for: Duration::ZERO,
        ..Default::default()
    };
    let refused = helmholtz_client::upload::upload_status_with(&api.base_url, "outage", &once)
        .await
        .unwrap_err()
        .downcast::<helmholtz_client::upload::RpcError>()
        .unwrap();
    assert_eq!(refused.code, Code::Unavailable, "{refused}");
    let upload = tokio::spawn({
        let (base, values, writer) = (api.base_url.clone(), values.clone(), writer.clone());
        async move { upload_as(&base, "outage", &values, &writer, Duration::from_secs(60)).await }
    });
    tokio::time::sleep(Duration::from_secs(2)).await;
    assert!(
        !upload.is_finished(),
        "an upload finished while the database refused every connection"
    );
    assert_eq!(health().await.0, 503);

    // Back: the node reconnects by itself.
    db.admin(&format!("ALTER DATABASE \"{name}\" ALLOW_CONNECTIONS true"));
    assert_eq!(
        wait_health(200, Duration::from_secs(30)).await["status"],
        "serving"
    );
    let report = upload.await.unwrap().unwrap();
    assert_eq!(report.confirmed_rows, 4000, "{report:?}");
    assert!(
        report.resumes > 0 || report.last_error.is_some(),
        "{report:?}"
    );
    let sent: Vec<u64> = values.iter().map(|v| v.to_bits()).collect();
    assert!(
        stored_bits(&api, "outage").await == sent,
        "stored rows differ from sent rows"
    );
}

/// Bucket rows of one rig: `count` Bernoulli patterns on 16x16 (seed `seed`), one detector.
async fn rig_rows(seed: u64, count: u64) -> (PatternSpec, Vec<f64>) {
    simulated(&format!(
        r#"{{"family":"bernoulli","width":16,"height":16,"count":{count},"seed":{seed}}}"#
    ))
    .await
}

/// Uploads `values` (one detector) through `node` as writer `writer`, in chunks of 100 rows,
/// retrying for `retry_for` without progress.
async fn upload_as(
    node: &str,
    id: &str,
    values: &[f64],
    writer: &str,
    retry_for: Duration,
) -> anyhow::Result<helmholtz_client::upload::UploadReport> {
    let rows = SampleRows {
        samples: Samples::F64(values),
        channels: 1,
    };
    let opts = UploadOptions {
        chunk_rows: Some(100),
        retry_for,
        ..UploadOptions::default()
    };
    upload_rows_as(node, id, 1, &rows, 0, &opts, writer).await
}

/// Uploads `values` as writer `writer` through `node`; when that node stops answering, goes on
/// through `fallback` as the same writer (what a rig behind a load balancer sees). Returns the
/// nodes used.
async fn rig_upload(
    node: String,
    fallback: String,
    id: String,
    values: Vec<f64>,
    writer: String,
) -> Vec<String> {
    let mut used = vec![node.clone()];
    if let Err(e) = upload_as(&node, &id, &values, &writer, Duration::from_secs(3)).await {
        assert_ne!(node, fallback, "upload of {id} through {node}: {e:#}");
        used.push(fallback.clone());
        upload_as(&fallback, &id, &values, &writer, Duration::from_secs(60))
            .await
            .unwrap_or_else(|e| panic!("upload of {id} through {fallback}: {e:#}"));
    }
    helmholtz_client::finish_session(&fallback, &id)
        .await
        .unwrap_or_else(|e| panic!("finishing {id}: {e:#}"));
    used
}

/// A reconstruction of a rig's session that takes a while (a fixed number of TV iterations), so
/// that jobs overlap and the running cap has something to hold back.
const SLOW_JOB: &str = r#"{"method": "tv", "params": {"max_iter": 1000}}"#;

/// The issue's cluster: 2 API nodes and 3 worker processes on one PostgreSQL database. 20 rigs
/// upload through both nodes while 4 rogue writers (other writer ids, other values) try the same
/// sessions through the other node; one API node is SIGKILLed mid-upload (its rigs go on
/// through the other, as the same writer) and a third node joins; a camera session's T is solved
/// in shards while one worker is SIGKILLed mid-shard; every session then gets a reconstruction
/// requested on either node. Checked: stored rows equal sent rows byte for byte, the rogues
/// stored nothing, every job finished exactly once, the per-lab caps (sessions on the API nodes,
/// running jobs on the workers) held across processes, and the sharded T is the single-process
/// T bit for bit.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_api_nodes_and_three_workers_lose_nothing_when_nodes_are_killed() {
    const RIGS: usize = 20;
    const ROWS: u64 = 10_000;
    const SESSION_CAP: usize = 24;
    let db = TestDatabase::create();
    let token = db.create_token("e2e", "rig,reader").unwrap();
    let api_args = [
        "--workers",
        "0",
        "--max-sessions-per-lab",
        "24",
        "--rate-per-second",
        "0",
    ];
    let a = ServerProcess::start_on_postgres(&db, &token, &api_args).unwrap();
    let mut b = ServerProcess::start_on_postgres(&db, &token, &api_args).unwrap();
    let worker_args = [
        "--transport-shard-pixels",
        "16",
        "--lease-seconds",
        "2",
        "--max-running-jobs-per-lab",
        "2",
    ];
    let mut workers: Vec<WorkerProcess> = (0..3)
        .map(|_| WorkerProcess::start(&db, 1, &worker_args).unwrap())
        .collect();

    // The per-lab session cap across nodes: 30 creates at once, alternating between the nodes,
    // for a lab of its own: exactly the cap succeed, the rest are refused naming the limit.
    let capped = db.create_token("capped", "rig").unwrap();
    let creates: Vec<_> = (0..30)
        .map(|i| {
            let node = if i % 2 == 0 { &a } else { &b }.url_with(&capped);
            tokio::spawn(async move {
                let spec: PatternSpec = serde_json::from_str(
                    r#"{"family":"bernoulli","width":8,"height":8,"count":10,"seed":1}"#,
                )
                .unwrap();
                helmholtz_client::create_session(
                    &node,
                    &NewSession::new(format!("capped-{i}"), spec, vec!["bucket".into()]),
                )
                .await
            })
        })
        .collect();
    let mut results = Vec::new();
    for create in creates {
        results.push(create.await.unwrap());
    }
    let created = results.iter().filter(|r| r.is_ok()).count();
    assert_eq!(created, SESSION_CAP, "sessions created past the cap");
    for e in results.iter().filter_map(|r| r.as_ref().err()) {
        assert!(format!("{e:#}").contains("sessions"), "{e:#}");
    }

    // The camera session (through the CLI) and the 20 rigs' sessions, half created on each node.
    simulate_camera_session(&a, "cam", "16x16", 32, 384);
    let mut sent = Vec::new();
    for i in 0..RIGS {
        let (spec, values) = rig_rows(100 + i as u64, ROWS).await;
        let node = if i % 2 == 0 { &a } else { &b };
        helmholtz_client::create_session(
            &node.base_url,
            &NewSession::new(format!("rig-{i}"), spec, vec!["bucket".into()]),
        )
        .await
        .unwrap();
        sent.push(values);
    }
    let mut rigs = Vec::new();
    for (i, values) in sent.iter().enumerate() {
        let node = if i % 2 == 0 { &a } else { &b };
        rigs.push(tokio::spawn(rig_upload(
            node.base_url.clone(),
            a.base_url.clone(),
            format!("rig-{i}"),
            values.clone(),
            helmholtz_client::upload::new_writer_id(),
        )));
    }
    // Rogue writers: other values, another writer id, through the other node, once their rig
    // has stored rows. Refused: ABORTED while the rig holds the session, ALREADY_EXISTS on the
    // first differing row otherwise; either way nothing of theirs is stored.
    let mut rogues = Vec::new();
    for (i, sent) in sent.iter().enumerate().take(4) {
        let id = format!("rig-{i}");
        let node = if i % 2 == 0 { &b } else { &a }.base_url.clone();
        let values: Vec<f64> = sent.iter().map(|v| v + 1.0).collect();
        rogues.push(tokio::spawn(async move {
            loop {
                let once = helmholtz_client::upload::RetryPolicy {
                    retry_for: Duration::ZERO,
                    ..Default::default()
                };
                match helmholtz_client::upload::upload_status_with(&node, &id, &once).await {
                    Ok(s) if s.committed_rows == 0 => {}
                    // Rows stored, or the node is gone (killed): try now.
                    _ => break,
                }
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
            let writer = helmholtz_client::upload::new_writer_id();
            upload_as(&node, &id, &values, &writer, Duration::from_secs(2)).await
        }));
    }

    // SIGKILL node B once its rigs are under way (the first of its sessions holds a tenth of
    // its rows), while the rest of its uploads are in flight.
    let deadline = Instant::now() + Duration::from_secs(60);
    let at_kill = loop {
        let committed = db.strings(
            "SELECT id || ' ' || committed_rows FROM sessions WHERE id LIKE 'rig-%' ORDER BY id",
        );
        let odd: Vec<u64> = committed
            .iter()
            .filter_map(|l| l.split_once(' '))
            .filter(|(id, _)| id[4..].parse::<usize>().unwrap() % 2 == 1)
            .map(|(_, c)| c.parse().unwrap())
            .collect();
        if odd.iter().any(|&c| c >= ROWS / 10) {
            break odd;
        }
        assert!(Instant::now() < deadline, "node B's uploads never started");
        tokio::time::sleep(Duration::from_millis(5)).await;
    };
    b.kill();
    let mid_upload = at_kill.iter().filter(|&&c| c < ROWS).count();
    assert!(
        mid_upload > 0,
        "node B was killed after all its uploads: {at_kill:?}"
    );
    println!("node B killed with its sessions at rows {at_kill:?}");
    let c = ServerProcess::start_on_postgres(&db, &token, &api_args).unwrap();

    // T in shards: requested on the new node; as soon as a worker holds a shard (not the last
    // one), SIGKILL its process and start another. A shard takes tens of milliseconds, so the
    // worker may finish it between the look and the kill: then the shard was not lost to the
    // kill, and the next running shard is taken instead (the kill waits for the process to
    // exit, so the shard's state read after it is final for that worker).
    let job = request(&c, "cam", TRANSPORT).await;
    let deadline = Instant::now() + Duration::from_secs(120);
    let (killed_pid, shard) = 'kill: loop {
        let holders = db.strings(&format!(
            "SELECT worker_id || ' ' || shard FROM transport_shards WHERE reconstruction_id = {job} \
             AND state = 'running' AND shard < 15 ORDER BY shard"
        ));
        if let Some(w) = holders.first() {
            let (worker, shard) = w.split_once(' ').unwrap();
            let pid: u32 = worker.split('-').next().unwrap().parse().unwrap();
            let shard = shard.parse::<i64>().unwrap();
            let victim = workers
                .iter()
                .position(|p| p.pid() == pid)
                .expect("a worker of ours");
            workers[victim].kill();
            workers.push(WorkerProcess::start(&db, 1, &worker_args).unwrap());
            let after = db.strings(&format!(
                "SELECT state || ' ' || worker_id FROM transport_shards WHERE reconstruction_id = {job} \
                 AND shard = {shard}"
            ));
            let held = after
                .first()
                .is_some_and(|s| s.starts_with("running ") && s.ends_with(worker));
            if held {
                break 'kill (pid, shard);
            }
            println!(
                "shard {shard} was finished by worker {worker} before its kill landed: {after:?}"
            );
        }
        assert!(
            Instant::now() < deadline,
            "no shard was ever killed mid-solve"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    };

    // Every rig finishes; those of node B went on through node A.
    let mut failed_over = 0;
    for rig in rigs {
        if rig.await.unwrap().len() > 1 {
            failed_over += 1;
        }
    }
    assert!(failed_over > 0, "no rig had to fail over");
    for rogue in rogues {
        let result = rogue.await.unwrap();
        assert!(result.is_err(), "a rogue writer's upload was accepted");
    }
    // Stored rows equal sent rows, byte for byte, read through either live node.
    for (i, values) in sent.iter().enumerate() {
        let node = if i % 2 == 0 { &a } else { &c };
        let bits: Vec<u64> = values.iter().map(|v| v.to_bits()).collect();
        assert!(
            stored_bits(node, &format!("rig-{i}")).await == bits,
            "rig-{i}: stored rows differ from sent rows"
        );
    }

    // A reconstruction of every rig's session, requested on either node.
    let mut jobs = Vec::new();
    for i in 0..RIGS {
        let node = if i % 2 == 0 { &a } else { &c };
        jobs.push(request(node, &format!("rig-{i}"), SLOW_JOB).await);
    }
    for &id in &jobs {
        let done = wait_state(&a, id, &["done", "failed"], Duration::from_secs(300)).await;
        assert_eq!(done["state"], "done", "{done}");
    }
    let done = wait_state(&a, job, &["done", "failed"], Duration::from_secs(300)).await;
    assert_eq!(done["state"], "done", "{done}");
    // Exactly once: one result per job (one detector: one image), no job left over.
    for &id in &jobs {
        assert_eq!(
            db.scalar(&format!(
                "SELECT COUNT(*) FROM dual_images WHERE reconstruction_id = {id}"
            )),
            1,
            "results of job {id}"
        );
    }
    assert_eq!(
        db.scalar("SELECT COUNT(*) FROM jobs WHERE state <> 'done'"),
        0
    );
    assert_eq!(
        db.scalar("SELECT COUNT(*) FROM jobs"),
        RIGS as i64 + 1,
        "one job per request"
    );
    // The running cap (2 a lab) held across the worker processes: at no job's start were more
    // than 2 of the lab's jobs running (start and finish times from the database's clock).
    let most_running = db.scalar(
        "SELECT COALESCE(MAX(n), 0) FROM (SELECT (SELECT COUNT(*) FROM jobs o \
         WHERE o.lab = j.lab AND o.started_ms <= j.started_ms AND o.finished_ms > j.started_ms) AS n \
         FROM jobs j WHERE j.started_ms IS NOT NULL) t",
    );
    let seconds = db.strings(
        "SELECT ((finished_ms - started_ms) / 1000.0)::text FROM jobs WHERE kind = 'reconstruction' ORDER BY id",
    );
    println!("most jobs of the lab running at once: {most_running}; job seconds {seconds:?}");
    assert_eq!(
        most_running, 2,
        "the cap of 2 running jobs a lab, with 3 worker processes free"
    );

    // The killed worker's shard was leased again and solved by another process.
    let (count, _, _) = shard_figures(&db, job);
    assert_eq!(count, 16);
    let again = db.strings(&format!(
        "SELECT attempt || ' ' || worker_id FROM transport_shards WHERE reconstruction_id = {job} AND shard = {shard}"
    ));
    let (attempt, worker) = again[0].split_once(' ').unwrap();
    assert!(
        attempt.parse::<i64>().unwrap() >= 2,
        "shard {shard}: {}",
        again[0]
    );
    assert!(
        !worker.starts_with(&format!("{killed_pid}-")),
        "shard {shard} done by the killed worker: {}",
        again[0]
    );
    let sharded = db.transport(job);
    drop(workers);
    let (single, _) = single_process_t(&db, &a, "cam").await;
    assert!(
        sharded == single,
        "the T after a killed shard differs from the single-process T"
    );
}
