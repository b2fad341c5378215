//! Acknowledged means kept (issue 17), through the real server binary and the real client:
//! a row's identity is (session, index); an overlapping row must be byte for byte the stored
//! one or the chunk is refused and nothing of it stored; one writer per session, enforced in the
//! database (so across server processes); a finished session takes no new rows; `acquire`
//! resumes where the session continues; the client deletes only rows the server confirmed with
//! the same bytes; per-lab caps hold under concurrent callers. After each case the stored rows
//! are read back and compared bit for bit with what was sent.

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use helmholtz_client::auth::Grpc;
use helmholtz_proto::v1;
use helmholtz_tests::{OpenUpload, ServerProcess, binary, parse_npy};
use tonic::Code;

const SPEC: &str = r#"{"family":"bernoulli","width":8,"height":8,"count":200,"seed":5}"#;

/// Runs the real `helmholtz` with its spool in `spool`, `stdin` fed if given.
fn helmholtz(server: &ServerProcess, spool: &Path, args: &[&str], stdin: Option<&str>) -> Output {
    use std::io::Write;
    let mut child = Command::new(binary("helmholtz"))
        .arg("--server")
        .arg(&server.base_url)
        .arg("--spool")
        .arg(spool)
        .arg("--json")
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut input = child.stdin.take().unwrap();
    if let Some(text) = stdin {
        input.write_all(text.as_bytes()).unwrap();
    }
    drop(input);
    child.wait_with_output().unwrap()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn ok(out: &Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "expected success:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        stderr(out)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// Rows `range` of data set `k` (one channel): distinct across sets and rows.
fn values(k: u32, range: std::ops::Range<u64>) -> Vec<f64> {
    range
        .map(|r| k as f64 * 1000.0 + r as f64 + 0.125)
        .collect()
}

fn csv(values: &[f64]) -> String {
    let mut s = String::from("bucket\n");
    for v in values {
        s.push_str(&format!("{v:?}\n"));
    }
    s
}

fn write_csv(dir: &Path, name: &str, values: &[f64]) -> String {
    let path = dir.join(name);
    std::fs::write(&path, csv(values)).unwrap();
    path.to_str().unwrap().to_string()
}

/// The session's stored rows, as bit patterns (so -0.0 and 0.0, or NaN payloads, differ).
async fn stored_bits(server: &ServerProcess, id: &str) -> Vec<u64> {
    let response =
        helmholtz_tests::http_get(server.url(&format!("/v1/sessions/{id}/measurements.npy")))
            .await
            .unwrap();
    assert_eq!(response.status(), 200, "measurements of {id}");
    let (_, values) = parse_npy(&response.bytes().await.unwrap()).unwrap();
    values.iter().map(|v| v.to_bits()).collect()
}

fn bits(values: &[f64]) -> Vec<u64> {
    values.iter().map(|v| v.to_bits()).collect()
}

/// Rows held in the spool of session `id` (0 if it has none), by the real `spool status`.
fn spooled_rows(server: &ServerProcess, spool: &Path, id: &str) -> Option<u64> {
    if !spool.join(id).join("manifest.json").is_file() {
        return None;
    }
    let out = ok(&helmholtz(server, spool, &["spool", "status", id], None));
    let entry = &out["sessions"][0];
    Some(entry["spooled_rows"].as_u64().unwrap_or(0) - entry["base_row"].as_u64().unwrap_or(0))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_clients_uploading_different_data_to_one_session_never_interleave() {
    let dir = tempfile::tempdir().unwrap();
    let server =
        ServerProcess::start(&dir.path().join("data"), 0, &["--rate-per-second", "0"]).unwrap();
    let (a, b) = (values(1, 0..200), values(2, 0..200));
    let files = [
        write_csv(dir.path(), "a.csv", &a),
        write_csv(dir.path(), "b.csv", &b),
    ];
    let spools = [dir.path().join("spool-a"), dir.path().join("spool-b")];
    // Both at once, small chunks so the streams overlap in time.
    let outs: Vec<Output> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..2)
            .map(|i| {
                let (server, file, spool) = (&server, &files[i], &spools[i]);
                s.spawn(move || {
                    helmholtz(
                        server,
                        spool,
                        &[
                            "upload",
                            "--session-id",
                            "shared",
                            "--spec-json",
                            SPEC,
                            "--values",
                            file,
                            "--finish",
                            "--chunk-rows",
                            "5",
                            "--batch-rows",
                            "10",
                            "--retry-for",
                            "20",
                        ],
                        None,
                    )
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let winners: Vec<usize> = (0..2).filter(|&i| outs[i].status.success()).collect();
    assert_eq!(
        winners.len(),
        1,
        "exactly one upload wins:\nA: {}\nB: {}",
        stderr(&outs[0]),
        stderr(&outs[1])
    );
    let (w, l) = (winners[0], 1 - winners[0]);
    let loser = stderr(&outs[l]);
    assert!(
        loser.contains("already stored with different values")
            && loser.contains("row 0 of session"),
        "the loser is told which row differs: {loser}"
    );
    assert!(loser.contains("safe in the spool"), "{loser}");
    // The loser's rows are all still in its spool; the winner's spool is cleared.
    assert_eq!(spooled_rows(&server, &spools[l], "shared"), Some(200));
    assert_eq!(spooled_rows(&server, &spools[w], "shared"), None);
    let sent = if w == 0 { &a } else { &b };
    assert_eq!(stored_bits(&server, "shared").await, bits(sent));

    // Retrying the loser's spool changes nothing and keeps it.
    let again = helmholtz(&server, &spools[l], &["spool", "upload", "shared"], None);
    assert!(!again.status.success());
    assert!(
        stderr(&again).contains("row 0 of session"),
        "{}",
        stderr(&again)
    );
    assert_eq!(spooled_rows(&server, &spools[l], "shared"), Some(200));
    assert_eq!(stored_bits(&server, "shared").await, bits(sent));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn new_rows_under_an_existing_session_are_refused_and_kept_not_deleted() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let spool = dir.path().join("spool");
    let first = values(1, 0..100);
    let upload = |file: &str, extra: &[&str]| {
        let mut args = vec![
            "upload",
            "--session-id",
            "s",
            "--spec-json",
            SPEC,
            "--values",
            file,
        ];
        args.extend_from_slice(extra);
        helmholtz(&server, &spool, &args, None)
    };
    let f1 = write_csv(dir.path(), "first.csv", &first);
    ok(&upload(&f1, &["--partial"]));
    // Other values for the same rows (the reported bug: "0 rows sent ... spool cleared").
    let other = values(3, 0..100);
    let f2 = write_csv(dir.path(), "other.csv", &other);
    let out = upload(&f2, &["--partial"]);
    assert!(!out.status.success(), "different rows must be refused");
    let text = stderr(&out);
    assert!(text.contains("row 0 of session \"s\""), "{text}");
    assert!(text.contains("100 rows are safe in the spool"), "{text}");
    assert_eq!(spooled_rows(&server, &spool, "s"), Some(100));
    assert_eq!(stored_bits(&server, "s").await, bits(&first));

    // A longer file whose first rows agree but one differs (row 42): refused, nothing added.
    let mut longer = values(1, 0..150);
    longer[42] = -longer[42];
    std::fs::remove_dir_all(spool.join("s")).unwrap();
    let f3 = write_csv(dir.path(), "longer.csv", &longer);
    let out = upload(&f3, &["--partial"]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("row 42 of session"),
        "{}",
        stderr(&out)
    );
    assert_eq!(stored_bits(&server, "s").await, bits(&first));

    // The right rows again (a repeat): confirmed, the spool cleared; then the rest.
    std::fs::remove_dir_all(spool.join("s")).unwrap();
    let report = ok(&upload(&f1, &["--partial"]));
    assert_eq!(
        report["upload"]["rows_sent"], 100,
        "every row is sent and compared"
    );
    assert_eq!(report["upload"]["confirmed_rows"], 100);
    assert_eq!(spooled_rows(&server, &spool, "s"), None);
    let all = values(1, 0..200);
    let f4 = write_csv(dir.path(), "all.csv", &all);
    let report = ok(&upload(&f4, &["--finish"]));
    assert_eq!(report["finished"], true);
    assert_eq!(stored_bits(&server, "s").await, bits(&all));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_finished_session_refuses_new_rows_and_the_client_keeps_them() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let spool = dir.path().join("spool");
    let all = values(1, 0..200);
    let f = write_csv(dir.path(), "all.csv", &all);
    let args = |file: &str| -> Vec<String> {
        [
            "upload",
            "--session-id",
            "done",
            "--spec-json",
            SPEC,
            "--values",
            file,
            "--finish",
        ]
        .map(String::from)
        .to_vec()
    };
    let run = |a: Vec<String>| {
        let a: Vec<&str> = a.iter().map(String::as_str).collect();
        helmholtz(&server, &spool, &a, None)
    };
    ok(&run(args(&f)));
    // acquire into the finished session: refused before reading stdin.
    let out = helmholtz(
        &server,
        &spool,
        &[
            "acquire",
            "--session-id",
            "done",
            "--spec-json",
            SPEC,
            "--channels",
            "bucket",
        ],
        Some("1.0\n2.0\n"),
    );
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("is finished with 200 rows"),
        "{}",
        stderr(&out)
    );
    // Other values for its rows: refused, kept in the spool.
    let other = values(4, 0..200);
    let f2 = write_csv(dir.path(), "other.csv", &other);
    let out = run(args(&f2));
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("row 0 of session"),
        "{}",
        stderr(&out)
    );
    assert_eq!(spooled_rows(&server, &spool, "done"), Some(200));
    assert_eq!(stored_bits(&server, "done").await, bits(&all));
    // The same rows again: confirmed (the finished session compares them) and cleared.
    std::fs::remove_dir_all(spool.join("done")).unwrap();
    let report = ok(&run(args(&f)));
    assert_eq!(report["upload"]["confirmed_rows"], 200);
    assert_eq!(spooled_rows(&server, &spool, "done"), None);
    assert_eq!(stored_bits(&server, "done").await, bits(&all));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn acquire_stopped_and_resumed_continues_where_the_session_continues() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let spool = dir.path().join("spool");
    let lines = |range: std::ops::Range<u64>| -> String {
        values(1, range)
            .iter()
            .map(|v| format!("{v:?}\n"))
            .collect()
    };
    let acquire = |stdin: &str, extra: &[&str], spool: &Path| {
        let mut args = vec![
            "acquire",
            "--session-id",
            "rig",
            "--spec-json",
            SPEC,
            "--channels",
            "bucket",
            "--batch-rows",
            "4",
        ];
        args.extend_from_slice(extra);
        helmholtz(&server, spool, &args, Some(stdin))
    };
    // Rows 0..90, stopped without --finish: uploaded, the spool cleared.
    let first = ok(&acquire(&lines(0..90), &[], &spool));
    assert_eq!(first["first_row"], 0);
    assert_eq!(spooled_rows(&server, &spool, "rig"), None);
    // A gap is refused before stdin is read.
    let gap = acquire(&lines(95..100), &["--start-row", "95"], &spool);
    assert!(!gap.status.success());
    assert!(
        stderr(&gap).contains("would leave a gap"),
        "{}",
        stderr(&gap)
    );
    // Replaying rows 80..90 with other values (another spool): refused at row 80, kept.
    let wrong_spool = dir.path().join("wrong");
    let wrong: String = values(7, 80..90)
        .iter()
        .map(|v| format!("{v:?}\n"))
        .collect();
    let out = acquire(&wrong, &["--start-row", "80"], &wrong_spool);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("row 80 of session"),
        "{}",
        stderr(&out)
    );
    assert_eq!(spooled_rows(&server, &wrong_spool, "rig"), Some(10));
    // The next rows, as its help says: numbered from the server's count (90), not from 0.
    let second = ok(&acquire(&lines(90..200), &["--finish"], &spool));
    assert_eq!(second["first_row"], 90);
    assert_eq!(second["finished"], true);
    assert_eq!(stored_bits(&server, "rig").await, bits(&values(1, 0..200)));
}

fn create(id: &str, count: u64) -> v1::CreateSessionRequest {
    helmholtz_tests::bucket_session(id, v1::PatternFamily::Bernoulli, 8, 8, count, &["a", "b"])
}

fn chunk(id: &str, start: u64, values: &[f64]) -> v1::MeasurementChunk {
    helmholtz_tests::f64_chunk(id, start, 2, values)
}

fn rows2(range: std::ops::Range<u64>) -> Vec<f64> {
    range
        .flat_map(|r| [r as f64 + 0.5, -(r as f64) - 0.25])
        .collect()
}

async fn send(
    c: &mut Grpc,
    chunks: Vec<v1::MeasurementChunk>,
) -> Result<v1::UploadResponse, tonic::Status> {
    c.upload_measurements(tokio_stream::iter(chunks))
        .await
        .map(|r| r.into_inner())
}

async fn committed(c: &mut Grpc, id: &str) -> u64 {
    c.get_upload_status(v1::SessionRef {
        session_id: id.into(),
    })
    .await
    .unwrap()
    .into_inner()
    .committed_rows
}

#[tokio::test]
async fn an_overlap_with_other_bytes_is_refused_naming_the_row_and_stores_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    c.create_session(create("o", 100)).await.unwrap();
    send(&mut c, vec![chunk("o", 0, &rows2(0..10))])
        .await
        .unwrap();
    // Rows 5..15: row 7's second value differs by its sign bit only (-x vs x is one bit).
    let mut sent = rows2(5..15);
    sent[2 * 2 + 1] = -sent[2 * 2 + 1];
    let status = send(&mut c, vec![chunk("o", 5, &sent)]).await.unwrap_err();
    assert_eq!(status.code(), Code::AlreadyExists, "{status:?}");
    assert!(
        status.message().contains("row 7 of session \"o\""),
        "{}",
        status.message()
    );
    assert!(
        status
            .message()
            .contains("nothing of this chunk (rows 5..15)"),
        "{}",
        status.message()
    );
    assert_eq!(committed(&mut c, "o").await, 10);
    assert_eq!(stored_bits(&server, "o").await, bits(&rows2(0..10)));
    // The faithful resume of the same rows: 5 compared equal, 5 written.
    let r = send(&mut c, vec![chunk("o", 5, &rows2(5..15))])
        .await
        .unwrap();
    assert_eq!(
        (r.committed_rows, r.rows_written, r.rows_skipped),
        (15, 5, 5)
    );
    assert_eq!(stored_bits(&server, "o").await, bits(&rows2(0..15)));
}

#[tokio::test]
async fn one_writer_per_session_across_two_server_processes_on_one_database() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let a = ServerProcess::start(&data, 0, &[]).unwrap();
    let b = ServerProcess::start(&data, 0, &[]).unwrap();
    let (mut ca, mut cb) = (a.grpc().await.unwrap(), b.grpc().await.unwrap());
    ca.create_session(create("w", 100)).await.unwrap();
    // A stream through server A that has sent one chunk and stays open.
    let open = OpenUpload::start(&ca, None, chunk("w", 0, &rows2(0..10)), 10).await;
    // Through server B, the same rows and new ones: ABORTED naming the session, nothing stored.
    let status = send(&mut cb, vec![chunk("w", 10, &rows2(10..20))])
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::Aborted, "{status:?}");
    assert!(
        status.message().contains("session \"w\""),
        "{}",
        status.message()
    );
    assert_eq!(committed(&mut cb, "w").await, 10);
    // The first stream goes on and ends; then B's writer gets the session.
    assert!(open.send(chunk("w", 10, &rows2(10..20))).await);
    let done = open.finish().await.unwrap();
    assert_eq!((done.committed_rows, done.rows_written), (20, 20));
    // The lease is given back before the response: the session is free at once.
    let r = send(&mut cb, vec![chunk("w", 15, &rows2(15..30))])
        .await
        .unwrap();
    assert_eq!(
        (r.committed_rows, r.rows_written, r.rows_skipped),
        (30, 10, 5)
    );
    assert_eq!(stored_bits(&a, "w").await, bits(&rows2(0..30)));
    assert_eq!(stored_bits(&b, "w").await, bits(&rows2(0..30)));
}

#[tokio::test]
async fn a_silent_upload_stream_is_closed_and_its_rows_stay() {
    let dir = tempfile::tempdir().unwrap();
    let server =
        ServerProcess::start(&dir.path().join("data"), 0, &["--upload-idle-secs", "1"]).unwrap();
    let mut c = server.grpc().await.unwrap();
    c.create_session(create("idle", 100)).await.unwrap();
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(chunk("idle", 0, &rows2(0..10))).await.unwrap();
    let started = Instant::now();
    let status = c
        .upload_measurements(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::Aborted, "{status:?}");
    assert!(
        status.message().contains("no chunk for 1 s"),
        "{}",
        status.message()
    );
    assert!(
        started.elapsed() < Duration::from_secs(10),
        "{:?}",
        started.elapsed()
    );
    drop(tx);
    assert_eq!(committed(&mut c, "idle").await, 10);
    // The session is free for the next writer at once (the lease was given back).
    let r = send(&mut c, vec![chunk("idle", 10, &rows2(10..12))])
        .await
        .unwrap();
    assert_eq!(r.committed_rows, 12);
    assert_eq!(stored_bits(&server, "idle").await, bits(&rows2(0..12)));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn lab_caps_hold_under_concurrent_requests() {
    let dir = tempfile::tempdir().unwrap();
    // No workers in this process: queued jobs stay queued, so the pending count only grows.
    let server = ServerProcess::start(
        &dir.path().join("data"),
        0,
        &[
            "--max-sessions-per-lab",
            "3",
            "--max-pending-jobs-per-lab",
            "5",
            "--workers",
            "0",
            "--rate-per-second",
            "0",
        ],
    )
    .unwrap();
    let c = server.grpc().await.unwrap();
    let creates: Vec<_> = (0..30)
        .map(|i| {
            let mut c = c.clone();
            tokio::spawn(async move { c.create_session(create(&format!("cap-{i}"), 10)).await })
        })
        .collect();
    let mut created = Vec::new();
    for (i, t) in creates.into_iter().enumerate() {
        match t.await.unwrap() {
            Ok(_) => created.push(format!("cap-{i}")),
            Err(s) => {
                assert_eq!(s.code(), Code::ResourceExhausted, "{s:?}");
                assert!(
                    s.message().contains("max_sessions_per_lab"),
                    "{}",
                    s.message()
                );
            }
        }
    }
    assert_eq!(created.len(), 3, "30 concurrent creations under a cap of 3");
    let listed: serde_json::Value = helmholtz_tests::http_get(server.url("/v1/sessions?limit=100"))
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(listed["sessions"].as_array().unwrap().len(), 3);

    let id = created[0].clone();
    let mut c0 = c.clone();
    send(&mut c0, vec![chunk(&id, 0, &rows2(0..10))])
        .await
        .unwrap();
    let requests: Vec<_> = (0..50)
        .map(|_| {
            let (mut c, id) = (c.clone(), id.clone());
            tokio::spawn(async move {
                c.request_reconstruction(v1::ReconstructionRequest {
                    session_id: id,
                    method: "gi".into(),
                    params_json: String::new(),
                })
                .await
            })
        })
        .collect();
    let mut accepted = 0;
    for t in requests {
        match t.await.unwrap() {
            Ok(_) => accepted += 1,
            Err(s) => {
                assert_eq!(s.code(), Code::ResourceExhausted, "{s:?}");
                assert!(
                    s.message().contains("max_pending_jobs_per_lab"),
                    "{}",
                    s.message()
                );
            }
        }
    }
    assert_eq!(accepted, 5, "50 concurrent requests under a cap of 5");
    assert_eq!(stored_bits(&server, &id).await, bits(&rows2(0..10)));
}

/// An upload stream of writer `writer` (metadata `x-helmholtz-writer`).
fn as_writer<S>(writer: &str, stream: S) -> tonic::Request<S> {
    let mut request = tonic::Request::new(stream);
    request
        .metadata_mut()
        .insert("x-helmholtz-writer", writer.parse().unwrap());
    request
}

#[tokio::test]
async fn a_writer_whose_connection_was_cut_takes_over_its_own_stale_stream() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let mut c = server.grpc().await.unwrap();
    c.create_session(create("t", 100)).await.unwrap();
    // Writer rig-a's first stream: one chunk, then silence (its connection "cut" without the
    // server noticing).
    let stale = OpenUpload::start(&c, Some("rig-a"), chunk("t", 0, &rows2(0..10)), 10).await;
    // Another writer: refused while rig-a holds the session.
    let other = c
        .upload_measurements(as_writer(
            "rig-b",
            tokio_stream::iter(vec![chunk("t", 10, &rows2(10..12))]),
        ))
        .await
        .unwrap_err();
    assert_eq!(other.code(), Code::Aborted, "{other:?}");
    // rig-a reconnects: its new stream takes over at once.
    let resumed = c
        .upload_measurements(as_writer(
            "rig-a",
            tokio_stream::iter(vec![chunk("t", 5, &rows2(5..15))]),
        ))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        (
            resumed.committed_rows,
            resumed.rows_written,
            resumed.rows_skipped
        ),
        (15, 5, 5)
    );
    // The stale stream wakes up: fenced off, nothing of it stored.
    stale.send(chunk("t", 15, &rows2(15..20))).await;
    let status = stale.finish().await.unwrap_err();
    assert_eq!(status.code(), Code::Aborted, "{status:?}");
    assert!(
        status.message().contains("no longer holds"),
        "{}",
        status.message()
    );
    assert_eq!(stored_bits(&server, "t").await, bits(&rows2(0..15)));
    // A malformed writer id is refused, naming the header.
    let bad = c
        .upload_measurements(as_writer(
            "no spaces",
            tokio_stream::iter(vec![chunk("t", 15, &rows2(15..16))]),
        ))
        .await
        .unwrap_err();
    assert_eq!(bad.code(), Code::InvalidArgument, "{bad:?}");
    assert!(
        bad.message().contains("x-helmholtz-writer"),
        "{}",
        bad.message()
    );
}
