//! Past one machine: API nodes (`serve --workers 0`) and worker processes (`worker`) share one
//! PostgreSQL database. Any node answers any request, rows uploaded through two nodes are stored
//! exactly, one writer per session holds across nodes, jobs queued on one node run in a worker
//! process, and a killed worker's job is taken up by another; a camera session's transport
//! matrix is solved in shards by several worker processes, a killed worker's shard is taken up
//! again, and the T assembled from the shards is the single-process T bit for bit. Needs
//! PostgreSQL (see
//! `helmholtz_tests::pg`); each test creates and drops its own database.

use std::time::{Duration, Instant};

use helmholtz_client::{NewSession, PatternSpec, UploadOptions};
use helmholtz_proto::v1;
use helmholtz_sim::Target;
use helmholtz_sim::simulate::{self, NoiseModel};
use helmholtz_tests::pg::{TestDatabase, WorkerProcess};
use helmholtz_tests::{OpenUpload, ServerProcess, parse_npy};
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
    let r = reqwest::get(server.url(path)).await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

async fn request(server: &ServerProcess, id: &str, body: &str) -> i64 {
    let r = reqwest::Client::new()
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
    let r = reqwest::get(server.url(&format!("/v1/sessions/{id}/measurements.npy")))
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
        text.contains("reachable, schema at migration 2, clock skew"),
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
        async move { reqwest::get(url).await.unwrap().bytes().await.unwrap() }
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

/// A simulated camera session (Lambertian scene, Bernoulli patterns), uploaded and finished by
/// the real client through `api`.
fn simulate_camera_session(api: &ServerProcess, id: &str, camera: &str, side: u32, count: u64) {
    let spool = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(helmholtz_tests::binary("helmholtz"))
        .args(["--server", &api.address, "--token", &api.token, "--spool"])
        .arg(spool.path())
        .args([
            "simulate",
            "--scene",
            "lambert",
            "--camera",
            camera,
            "--camera-tilt",
            "20",
            "--family",
            "bernoulli",
            "--width",
            &side.to_string(),
            "--height",
            &side.to_string(),
            "--count",
            &count.to_string(),
            "--seed",
            "4",
            "--session-id",
            id,
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "helmholtz simulate failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
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
    let done = wait_state(&api, job, &["done", "failed"], Duration::from_secs(300)).await;
    assert_eq!(done["state"], "done", "{done}");
    let (count, workers, _) = shard_figures(&db, job);
    assert_eq!(count, 6, "{done}");
    // Both processes took shards (the worker ids on the shard rows start with the pid).
    assert_eq!(
        workers,
        2,
        "shards by one process only: {:?}",
        db.strings(&format!(
            "SELECT worker_id FROM transport_shards WHERE reconstruction_id = {job}"
        ))
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_worker_s_shard_is_leased_again_and_t_is_unchanged() {
    let db = TestDatabase::create();
    let token = db.create_token("e2e", "rig,reader").unwrap();
    let api = ServerProcess::start_on_postgres(&db, &token, &["--workers", "0"]).unwrap();
    simulate_camera_session(&api, "cam", "16x16", 32, 384);
    // Shards of 16 camera pixels: 16 of the 256; leases of 2 s.
    let args = ["--transport-shard-pixels", "16", "--lease-seconds", "2"];
    let mut workers = vec![
        WorkerProcess::start(&db, 1, &args).unwrap(),
        WorkerProcess::start(&db, 1, &args).unwrap(),
    ];
    let job = request(&api, "cam", TRANSPORT).await;
    // As soon as a worker holds a shard (not the last one), SIGKILL its process.
    let deadline = Instant::now() + Duration::from_secs(120);
    let (victim, shard) = loop {
        let holders = db.strings(&format!(
            "SELECT worker_id || ' ' || shard FROM transport_shards WHERE reconstruction_id = {job} \
             AND state = 'running' AND shard < 15 ORDER BY shard"
        ));
        if let Some(w) = holders.first() {
            let (worker, shard) = w.split_once(' ').unwrap();
            let pid: u32 = worker.split('-').next().unwrap().parse().unwrap();
            let victim = workers
                .iter()
                .position(|p| p.pid() == pid)
                .expect("a worker of ours");
            break (victim, shard.parse::<i64>().unwrap());
        }
        assert!(Instant::now() < deadline, "no shard ever ran");
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    let killed_pid = workers[victim].pid();
    workers[victim].kill();
    // A fresh worker process takes the place of the killed one.
    workers.push(WorkerProcess::start(&db, 1, &args).unwrap());
    let done = wait_state(&api, job, &["done", "failed"], Duration::from_secs(300)).await;
    assert_eq!(done["state"], "done", "{done}");
    let (count, _, _) = shard_figures(&db, job);
    assert_eq!(count, 16);
    // The killed worker's shard was leased again (a second attempt) and solved by another.
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
    let (single, _) = single_process_t(&db, &api, "cam").await;
    assert!(
        sharded == single,
        "the T after a killed shard differs from the single-process T"
    );
}
