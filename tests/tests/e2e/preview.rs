//! Live preview (gRPC `WatchPreview`, REST `GET /v1/sessions/{id}/preview` as server-sent
//! events) against the real server binary: frames arrive while a session uploads in chunks, with
//! increasing row counts and an error against the scene's truth that falls; the final frame is
//! the server's own reconstruction of the finished session (DGI, zero-filled Hadamard); another
//! lab's watcher and bad parameters are refused, naming the field.

use std::time::{Duration, Instant};

use base64::Engine;
use helmholtz_client::preview::{PreviewOptions, watch_preview};
use helmholtz_proto::v1;
use helmholtz_sim::Target;
use helmholtz_sim::simulate::{self, NoiseModel};
use helmholtz_tests::{OpenUpload, ServerProcess, bucket_session, f64_chunk, parse_npy};
use serde_json::{Value, json};

/// A frame as either transport delivers it, and when it arrived.
#[derive(Clone, Debug)]
struct Seen {
    rows: u64,
    method: String,
    values: Vec<f32>,
    last: bool,
    at: Instant,
}

/// Opens the gRPC preview of `id`, then collects its frames until the final one (or the stream
/// ends).
async fn watch_grpc(
    server: &ServerProcess,
    id: &str,
    every_rows: u64,
) -> tokio::task::JoinHandle<Vec<Seen>> {
    let options = PreviewOptions {
        every_rows,
        ..Default::default()
    };
    let mut stream = watch_preview(&server.base_url, id, &options).await.unwrap();
    tokio::spawn(async move {
        let mut seen = Vec::new();
        while let Some(f) = stream.message().await.unwrap() {
            let last = f.r#final;
            seen.push(Seen {
                rows: f.rows,
                method: f.method,
                values: f.values,
                last,
                at: Instant::now(),
            });
            if last {
                break;
            }
        }
        seen
    })
}

/// Collects the SSE frames of `url` until the final one (or the stream ends).
async fn watch_sse(url: String, token: String) -> tokio::task::JoinHandle<Vec<Seen>> {
    let response = helmholtz_tests::http_client()
        .get(url)
        .bearer_auth(token)
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 200);
    assert_eq!(response.headers()["content-type"], "text/event-stream");
    tokio::spawn(async move {
        let mut response = response;
        let (mut buffer, mut seen) = (String::new(), Vec::new());
        while let Some(bytes) = response.chunk().await.unwrap() {
            buffer.push_str(std::str::from_utf8(&bytes).unwrap());
            while let Some(end) = buffer.find("\n\n") {
                let block: String = buffer.drain(..end + 2).collect();
                let mut event = "";
                let mut data = String::new();
                for line in block.lines() {
                    if let Some(v) = line.strip_prefix("event: ") {
                        event = if v == "preview" { "preview" } else { "other" };
                    } else if let Some(v) = line.strip_prefix("data: ") {
                        data.push_str(v);
                    }
                }
                if event.is_empty() {
                    continue; // a keep-alive comment
                }
                assert_eq!(event, "preview", "{block}");
                let v: Value = serde_json::from_str(&data).unwrap();
                let bytes = base64::engine::general_purpose::STANDARD
                    .decode(v["values_f32le"].as_str().unwrap())
                    .unwrap();
                let values: Vec<f32> = bytes
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
                    .collect();
                assert_eq!(
                    values.len() as u64,
                    v["width"].as_u64().unwrap() * v["height"].as_u64().unwrap()
                );
                seen.push(Seen {
                    rows: v["rows"].as_u64().unwrap(),
                    method: v["method"].as_str().unwrap().to_string(),
                    values,
                    last: v["final"].as_bool().unwrap(),
                    at: Instant::now(),
                });
            }
        }
        seen
    })
}

/// Uploads `values` (one channel) in chunks of `chunk_rows`, pausing between chunks like a rig,
/// then finishes the session; returns when the last chunk was committed.
async fn upload_slowly(
    server: &ServerProcess,
    id: &str,
    values: &[f64],
    chunk_rows: usize,
    pause: Duration,
) -> Instant {
    let grpc = server.grpc().await.unwrap();
    let mut chunks = values
        .chunks(chunk_rows)
        .enumerate()
        .map(|(i, c)| f64_chunk(id, (i * chunk_rows) as u64, 1, c));
    let upload = OpenUpload::start(&grpc, None, chunks.next().unwrap(), chunk_rows as u64).await;
    for chunk in chunks {
        tokio::time::sleep(pause).await;
        assert!(upload.send(chunk).await);
    }
    let answer = upload.finish().await.unwrap();
    let done = Instant::now();
    assert_eq!(answer.committed_rows, values.len() as u64);
    grpc.clone()
        .finish_session(v1::SessionRef {
            session_id: id.into(),
        })
        .await
        .unwrap();
    done
}

/// The server's own reconstruction of `id` by `method`, as f32 values.
async fn server_image(server: &ServerProcess, id: &str, method: &str) -> Vec<f32> {
    let r = helmholtz_client::request_reconstruction(&server.base_url, id, method, &json!({}))
        .await
        .unwrap();
    let r = helmholtz_client::wait_reconstruction(&server.base_url, r.id, Duration::from_secs(60))
        .await
        .unwrap();
    assert!(r.is_done(), "{r:?}");
    let bytes =
        helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{}/dual.npy", r.id)))
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap();
    parse_npy(&bytes)
        .unwrap()
        .1
        .iter()
        .map(|&v| v as f32)
        .collect()
}

/// Max |a - b| over max |b|.
fn max_rel_diff(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0f64, |m, &v| m.max(v.abs() as f64));
    let worst = a
        .iter()
        .zip(b)
        .fold(0f64, |m, (&x, &y)| m.max((x as f64 - y as f64).abs()));
    worst / scale
}

/// Relative error of `image` against `truth` after the best gain and offset (DGI sees t only up
/// to both): `|| a image + b - truth || / || truth - mean(truth) ||`.
fn fitted_error(image: &[f32], truth: &[f32]) -> f64 {
    let n = image.len() as f64;
    let (x, y): (Vec<f64>, Vec<f64>) = image
        .iter()
        .zip(truth)
        .map(|(&a, &b)| (a as f64, b as f64))
        .unzip();
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let sxy: f64 = x.iter().zip(&y).map(|(a, b)| (a - mx) * (b - my)).sum();
    let sxx: f64 = x.iter().map(|a| (a - mx) * (a - mx)).sum();
    let syy: f64 = y.iter().map(|b| (b - my) * (b - my)).sum();
    let gain = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    let residual: f64 = x
        .iter()
        .zip(&y)
        .map(|(a, b)| (gain * (a - mx) - (b - my)).powi(2))
        .sum();
    (residual / syy).sqrt()
}

/// Frames of one watcher: increasing rows, the final one last and complete, some before the
/// upload ended.
fn check_frames(what: &str, frames: &[Seen], expected: u64, method: &str, upload_done: Instant) {
    assert!(frames.len() >= 3, "{what}: {} frames", frames.len());
    assert!(
        frames.windows(2).all(|w| w[0].rows < w[1].rows),
        "{what}: rows not increasing: {:?}",
        frames.iter().map(|f| f.rows).collect::<Vec<_>>()
    );
    let last = frames.last().unwrap();
    assert!(
        last.last && last.rows == expected,
        "{what}: last frame {} rows",
        last.rows
    );
    assert!(frames[..frames.len() - 1].iter().all(|f| !f.last), "{what}");
    assert!(frames.iter().all(|f| f.method == method), "{what}");
    let early = frames
        .iter()
        .filter(|f| f.at < upload_done && f.rows < expected)
        .count();
    assert!(
        early >= 2,
        "{what}: only {early} frames arrived before the upload ended"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dgi_preview_frames_arrive_while_uploading_and_converge_to_the_final_image() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let (id, side, count, chunk) = ("preview-dgi", 24u32, 3072u64, 192usize);
    let mut grpc = server.grpc().await.unwrap();
    grpc.create_session(bucket_session(
        id,
        v1::PatternFamily::Bernoulli,
        side,
        side,
        count,
        &["bucket"],
    ))
    .await
    .unwrap();
    let spec: helmholtz_client::PatternSpec = serde_json::from_value(json!({
        "family": "bernoulli", "width": side, "height": side, "count": count, "seed": 1
    }))
    .unwrap();
    let truth = Target::builtin("shapes", side, side)
        .unwrap()
        .transport(1.0);
    let sim = simulate::simulate(&spec, &[&truth], &NoiseModel::default(), None);

    let by_grpc = watch_grpc(&server, id, chunk as u64).await;
    let by_sse = watch_sse(
        format!("{}/v1/sessions/{id}/preview?every_rows=384", server.address),
        server.token.clone(),
    )
    .await;
    let done = upload_slowly(&server, id, &sim.values, chunk, Duration::from_millis(60)).await;
    let grpc_frames = tokio::time::timeout(Duration::from_secs(60), by_grpc)
        .await
        .expect("the gRPC preview ended")
        .unwrap();
    let sse_frames = tokio::time::timeout(Duration::from_secs(60), by_sse)
        .await
        .expect("the SSE preview ended")
        .unwrap();
    check_frames("grpc", &grpc_frames, count, "dgi", done);
    check_frames("sse", &sse_frames, count, "dgi", done);
    // Row trigger: frames at least every_rows apart (rows arrive in whole chunks).
    assert!(
        grpc_frames
            .windows(2)
            .all(|w| w[1].rows - w[0].rows >= chunk as u64 || w[1].last)
    );
    assert!(
        sse_frames
            .windows(2)
            .all(|w| w[1].rows - w[0].rows >= 384 || w[1].last)
    );

    // The final frame is the server's DGI of the finished session; both transports agree.
    let last = &grpc_frames.last().unwrap().values;
    assert_eq!(last, &sse_frames.last().unwrap().values);
    let dgi = server_image(&server, id, "dgi").await;
    let diff = max_rel_diff(last, &dgi);
    assert!(diff < 1e-4, "final frame vs dgi: {diff}");

    // Converges: the error against the scene falls from early to late frames.
    let errors: Vec<f64> = grpc_frames
        .iter()
        .map(|f| fitted_error(&f.values, &truth))
        .collect();
    let (first, final_) = (errors[0], *errors.last().unwrap());
    assert!(final_ < 0.8 * first, "error against the truth: {errors:?}");
    let mid = errors[errors.len() / 2];
    assert!(mid < first && final_ < mid, "{errors:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hadamard_preview_is_the_zero_filled_inverse_and_ends_exact() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let (id, side, chunk) = ("preview-hadamard", 16u32, 32usize);
    let count = 2 * (side * side) as u64;
    let mut grpc = server.grpc().await.unwrap();
    grpc.create_session(bucket_session(
        id,
        v1::PatternFamily::Hadamard,
        side,
        side,
        count,
        &["bucket"],
    ))
    .await
    .unwrap();
    let spec: helmholtz_client::PatternSpec = serde_json::from_value(json!({
        "family": "hadamard", "width": side, "height": side, "count": count, "seed": 1
    }))
    .unwrap();
    let truth = Target::builtin("shapes", side, side)
        .unwrap()
        .transport(1.0);
    let sim = simulate::simulate(&spec, &[&truth], &NoiseModel::default(), None);

    let by_grpc = watch_grpc(&server, id, 64).await;
    let done = upload_slowly(&server, id, &sim.values, chunk, Duration::from_millis(40)).await;
    let frames = tokio::time::timeout(Duration::from_secs(60), by_grpc)
        .await
        .expect("the preview ended")
        .unwrap();
    check_frames("grpc", &frames, count, "zero_filled", done);
    let last = &frames.last().unwrap().values;
    let zero_filled = server_image(&server, id, "zero_filled").await;
    assert!(max_rel_diff(last, &zero_filled) < 1e-5);
    // A complete set: the exact image.
    assert!(
        max_rel_diff(last, &truth) < 1e-5,
        "{}",
        max_rel_diff(last, &truth)
    );
    let errors: Vec<f64> = frames
        .iter()
        .map(|f| helmholtz_tests::relative_error(&to_f64(&f.values), &to_f64(&truth)))
        .collect();
    assert!(
        errors.windows(2).all(|w| w[1] <= w[0] + 1e-9),
        "the zero-filled error never grows: {errors:?}"
    );
    assert!(
        errors[0] > 0.05 && *errors.last().unwrap() < 1e-5,
        "{errors:?}"
    );

    // Watching a finished session: one final frame at once.
    let again = watch_grpc(&server, id, count).await.await.unwrap();
    assert_eq!(again.len(), 1);
    assert!(again[0].last && again[0].rows == count);
    assert_eq!(&again[0].values, last);

    // The CLI: `helmholtz preview` prints the frames and writes the final image.
    let out = dir.path().join("final.npy");
    let run = std::process::Command::new(helmholtz_tests::binary("helmholtz"))
        .args([
            "--server",
            &server.address,
            "--token",
            &server.token,
            "--json",
        ])
        .args(["preview", "--session-id", id, "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let printed: Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(
        (&printed["frames"], &printed["rows"], &printed["final"]),
        (&json!(1), &json!(count), &json!(true)),
        "{printed}"
    );
    assert_eq!(printed["method"], "zero_filled");
    let written = parse_npy(&std::fs::read(&out).unwrap()).unwrap().1;
    assert_eq!(written, to_f64(last));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_camera_session_is_previewed_as_the_sum_over_its_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let (id, side, count) = ("preview-camera", 16u32, 256u64);
    helmholtz_tests::simulate_camera_session(&server, id, "8x6", side, count);
    let frames = watch_grpc(&server, id, 0).await.await.unwrap();
    let last = frames.last().unwrap();
    assert!(last.last && last.rows == count && last.method == "dgi");
    assert_eq!(last.values.len(), (side * side) as usize);
    assert!(last.values.iter().all(|v| v.is_finite()));
    assert!(last.values.iter().any(|&v| v != 0.0));
    // The camera's frames summed per pattern, correlated by DGI here, give the same image.
    let npy = helmholtz_tests::http_get(server.url(&format!("/v1/sessions/{id}/measurements.npy")))
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let (_, pixels) = helmholtz_proto::npy::decode_f64(&npy).unwrap();
    let per_row = pixels.len() / count as usize;
    let buckets: Vec<f64> = pixels.chunks(per_row).map(|f| f.iter().sum()).collect();
    let spec: helmholtz_client::PatternSpec = serde_json::from_value(json!({
        "family": "bernoulli", "width": side, "height": side, "count": count, "seed": 4
    }))
    .unwrap();
    let generator = helmholtz_proto::PatternGenerator::new(&spec);
    let k = (side * side) as usize;
    let (mut cp, mut rp, mut sum_c, mut sum_r) = (vec![0f64; k], vec![0f64; k], 0f64, 0f64);
    let mut p = vec![0f32; k];
    for (i, &c) in buckets.iter().enumerate() {
        generator.fill_values(i as u64, &mut p);
        let r: f64 = p.iter().map(|&v| v as f64).sum();
        sum_c += c;
        sum_r += r;
        for x in 0..k {
            cp[x] += c * p[x] as f64;
            rp[x] += r * p[x] as f64;
        }
    }
    let n = count as f64;
    let dgi: Vec<f32> = (0..k)
        .map(|x| ((cp[x] - sum_c / sum_r * rp[x]) / n) as f32)
        .collect();
    let diff = max_rel_diff(&last.values, &dgi);
    assert!(
        diff < 1e-3,
        "camera preview vs DGI of the pixel sums: {diff}"
    );
    // A camera session takes no channel.
    let status = server
        .grpc()
        .await
        .unwrap()
        .watch_preview(v1::PreviewRequest {
            session_id: id.into(),
            channel: "camera".into(),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    assert!(status.message().starts_with("channel"), "{status:?}");
}

fn to_f64(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| x as f64).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn other_labs_and_bad_parameters_are_refused_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let id = "preview-refusals";
    let mut grpc = server.grpc().await.unwrap();
    grpc.create_session(bucket_session(
        id,
        v1::PatternFamily::Bernoulli,
        8,
        8,
        64,
        &["a", "b"],
    ))
    .await
    .unwrap();
    let http = helmholtz_tests::http_client();
    let get = |token: String, query: &str| {
        http.get(format!(
            "{}/v1/sessions/{id}/preview{query}",
            server.address
        ))
        .bearer_auth(token)
        .send()
    };

    // Another lab's token: NOT_FOUND / 404, as for a session that does not exist.
    let other = server.create_token("other-lab", "rig,reader").unwrap();
    let status = server
        .grpc_as(&server.url_with(&other))
        .unwrap()
        .watch_preview(v1::PreviewRequest {
            session_id: id.into(),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::NotFound, "{status:?}");
    let r = get(other.clone(), "").await.unwrap();
    assert_eq!(r.status(), 404);
    assert_eq!(r.headers()["content-type"], "application/problem+json");
    // No token: 401; a token without rig or reader: 403.
    let r = http
        .get(format!("{}/v1/sessions/{id}/preview", server.address))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 401);
    let metrics = server.create_token("e2e", "metrics").unwrap();
    assert_eq!(get(metrics, "").await.unwrap().status(), 403);

    // Bad parameters: INVALID_ARGUMENT / 400 naming the field.
    for (options, field) in [
        (
            PreviewOptions {
                every_ms: 1,
                ..Default::default()
            },
            "every_ms",
        ),
        (
            PreviewOptions {
                every_rows: 65,
                ..Default::default()
            },
            "every_rows",
        ),
        (
            PreviewOptions {
                channel: "c".into(),
                ..Default::default()
            },
            "channel",
        ),
    ] {
        let mut client = server.grpc().await.unwrap();
        let status = client
            .watch_preview(v1::PreviewRequest {
                session_id: id.into(),
                channel: options.channel.clone(),
                every_rows: options.every_rows,
                every_ms: options.every_ms,
            })
            .await
            .unwrap_err();
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
        assert!(status.message().starts_with(field), "{status:?}");
    }
    for (query, field) in [
        ("?every_ms=10", "every_ms"),
        ("?every_ms=abc", "every_ms"),
        ("?every_rows=-1", "every_rows"),
        ("?channel=c", "channel"),
        ("?every_second=1", "every_second"),
    ] {
        let r = get(server.token.clone(), query).await.unwrap();
        assert_eq!(r.status(), 400, "{query}");
        let problem: Value = r.json().await.unwrap();
        assert_eq!(problem["field"], field, "{query}: {problem}");
    }
    let mut client = server.grpc().await.unwrap();
    let status = client
        .watch_preview(v1::PreviewRequest {
            session_id: "no such".into(),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);

    // A channel by name or index is accepted; the stream ends once every declared row is in.
    let values: Vec<f64> = (0..128).map(|i| 1.0 + (i % 7) as f64).collect();
    grpc.upload_measurements(tokio_stream::iter(vec![f64_chunk(id, 0, 2, &values)]))
        .await
        .unwrap();
    for channel in ["b", "1"] {
        let mut stream = watch_preview(
            &server.base_url,
            id,
            &PreviewOptions {
                channel: channel.into(),
                ..Default::default()
            },
        )
        .await
        .unwrap();
        let frame = stream.message().await.unwrap().unwrap();
        assert!(
            frame.r#final && frame.rows == 64 && frame.channel == "b",
            "{channel}"
        );
    }
}
