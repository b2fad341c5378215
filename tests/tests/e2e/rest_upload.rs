//! Sessions and rows over REST (`POST /v1/sessions`, `PUT /v1/sessions/{id}/rows`,
//! `POST /v1/sessions/{id}/finish`), for tools without gRPC: the same integrity rules as the
//! gRPC upload (checksum, sample format, whole rows, overlap compared, gaps refused, one writer),
//! bad input refused with a problem naming the field and nothing stored, and what is stored is
//! bit for bit what was sent.

use std::process::Command;

use helmholtz_proto::npy::{self, Dtype};
use helmholtz_sim::Target;
use helmholtz_sim::simulate::{self, NoiseModel};
use helmholtz_tests::{OpenUpload, ServerProcess, f64_chunk, parse_npy, relative_error};
use serde_json::{Value, json};

struct Rest<'a> {
    server: &'a ServerProcess,
    token: String,
    http: reqwest::Client,
}

struct Answer {
    status: u16,
    body: Value,
    location: Option<String>,
}

impl Rest<'_> {
    async fn send(&self, request: reqwest::RequestBuilder) -> Answer {
        let r = request.bearer_auth(&self.token).send().await.unwrap();
        let status = r.status().as_u16();
        let location = r
            .headers()
            .get("location")
            .map(|v| v.to_str().unwrap().to_string());
        let content_type = r
            .headers()
            .get("content-type")
            .map(|v| v.to_str().unwrap().to_string())
            .unwrap_or_default();
        let body: Value = r.json().await.unwrap_or(Value::Null);
        if status >= 400 {
            assert_eq!(
                content_type, "application/problem+json",
                "errors are problem+json: {body}"
            );
        }
        Answer {
            status,
            body,
            location,
        }
    }

    async fn create(&self, body: &Value) -> Answer {
        self.send(
            self.http
                .post(format!("{}/v1/sessions", self.server.address))
                .json(body),
        )
        .await
    }

    /// `PUT rows` with `body` of `content_type`, its CRC-32C (or `crc` instead), as `writer`.
    async fn put(
        &self,
        id: &str,
        start: &str,
        content_type: &str,
        body: Vec<u8>,
        crc: Option<&str>,
        writer: Option<&str>,
    ) -> Answer {
        let crc = crc
            .map(str::to_string)
            .unwrap_or_else(|| format!("{:08x}", crc32c::crc32c(&body)));
        let mut request = self
            .http
            .put(format!(
                "{}/v1/sessions/{id}/rows?start_row={start}",
                self.server.address
            ))
            .header("content-type", content_type)
            .header("x-helmholtz-crc32c", crc)
            .body(body);
        if let Some(w) = writer {
            request = request.header("x-helmholtz-writer", w);
        }
        self.send(request).await
    }

    /// `PUT .../rows{query}` with exactly `headers` (no checksum added).
    async fn put_with(
        &self,
        id: &str,
        query: &str,
        headers: &[(&str, &str)],
        body: Vec<u8>,
    ) -> Answer {
        let mut request = self.http.put(format!(
            "{}/v1/sessions/{id}/rows{query}",
            self.server.address
        ));
        for (name, value) in headers {
            request = request.header(*name, *value);
        }
        self.send(request.body(body)).await
    }

    async fn committed(&self, id: &str) -> u64 {
        let a = self
            .send(
                self.http
                    .get(format!("{}/v1/sessions/{id}/rows", self.server.address)),
            )
            .await;
        assert_eq!(a.status, 200, "{}", a.body);
        a.body["committed_rows"].as_u64().unwrap()
    }

    async fn measurements(&self, id: &str) -> Vec<u8> {
        let r = self
            .http
            .get(format!(
                "{}/v1/sessions/{id}/measurements.npy",
                self.server.address
            ))
            .bearer_auth(&self.token)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 200);
        r.bytes().await.unwrap().to_vec()
    }
}

fn f64_le(values: &[f64]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// An NPY file of `dtype` and `shape` holding `data` (already little-endian bytes).
fn npy_file(dtype: Dtype, shape: &[u64], data: &[u8]) -> Vec<u8> {
    let mut out = npy::header(dtype, shape, false);
    out.extend_from_slice(data);
    out
}

fn problem_field(a: &Answer) -> &str {
    a.body["field"].as_str().unwrap_or("")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bucket_session_made_and_filled_over_rest_keeps_every_row_and_refuses_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let rest = Rest {
        server: &server,
        token: server.token.clone(),
        http: helmholtz_tests::http_client(),
    };
    let (id, rows, channels) = ("rest-buckets", 256u64, 2usize);
    let declaration = json!({
        "id": id, "rig": "matlab-bench",
        "patterns": {"family": "hadamard", "width": 16, "height": 16, "count": rows, "seed": 0},
        "channels": ["r", "g"],
        "metadata": {"operator": "octave"}
    });
    let created = rest.create(&declaration).await;
    assert_eq!(created.status, 201, "{}", created.body);
    assert_eq!(
        created.location.as_deref(),
        Some("/v1/sessions/rest-buckets")
    );
    assert_eq!(created.body["expected_rows"], rows);
    assert_eq!(created.body["channels"], json!(["r", "g"]));
    // The same declaration again answers the stored session; a different one is a conflict.
    assert_eq!(rest.create(&declaration).await.status, 200);
    let mut other = declaration.clone();
    other["channels"] = json!(["r"]);
    let conflict = rest.create(&other).await;
    assert_eq!(conflict.status, 409, "{}", conflict.body);
    // Bad declarations name their field.
    let mut bad = declaration.clone();
    bad["id"] = json!("no spaces allowed");
    let refused = rest.create(&bad).await;
    assert_eq!(
        (refused.status, problem_field(&refused)),
        (400, "session_id")
    );
    let mut bad = declaration.clone();
    bad["patterns"]["width"] = json!(0);
    let refused = rest.create(&bad).await;
    assert_eq!(refused.status, 400, "{}", refused.body);
    assert!(
        problem_field(&refused).starts_with("patterns"),
        "{}",
        refused.body
    );
    let mut bad = declaration.clone();
    bad["colour"] = json!("blue");
    assert_eq!(rest.create(&bad).await.status, 400);

    // Distinct values, so that any row stored at the wrong index shows.
    let values: Vec<f64> = (0..rows as usize * channels)
        .map(|i| (i as f64 * 0.731).sin() * 1e3 + i as f64)
        .collect();
    let rows_bytes = |from: usize, to: usize| f64_le(&values[from * channels..to * channels]);
    let npy_rows = |from: usize, to: usize| {
        npy_file(
            Dtype::F64,
            &[(to - from) as u64, channels as u64],
            &rows_bytes(from, to),
        )
    };

    // Rows 0..100 as NPY, 100..150 as raw samples.
    let a = rest
        .put(id, "0", "application/x-npy", npy_rows(0, 100), None, None)
        .await;
    assert_eq!(a.status, 200, "{}", a.body);
    assert_eq!(
        (
            a.body["committed_rows"].as_u64(),
            a.body["rows_written"].as_u64()
        ),
        (Some(100), Some(100))
    );
    let a = rest
        .put(
            id,
            "100",
            "application/octet-stream",
            rows_bytes(100, 150),
            None,
            Some("lab-pc"),
        )
        .await;
    assert_eq!(a.status, 200, "{}", a.body);
    assert_eq!(a.body["committed_rows"], 150);

    // Every refusal below names its field (or limit) and stores nothing.
    let refusals: Vec<(Answer, u16, &str)> = vec![
        // A checksum that does not match the body.
        (
            rest.put(
                id,
                "150",
                "application/x-npy",
                npy_rows(150, 160),
                Some("deadbeef"),
                None,
            )
            .await,
            422,
            "",
        ),
        // No checksum.
        (
            rest.put_with(
                id,
                "?start_row=150",
                &[("content-type", "application/octet-stream")],
                rows_bytes(150, 160),
            )
            .await,
            400,
            "x-helmholtz-crc32c",
        ),
        (
            rest.put(
                id,
                "150",
                "application/octet-stream",
                rows_bytes(150, 160),
                Some("xyz"),
                None,
            )
            .await,
            400,
            "x-helmholtz-crc32c",
        ),
        // No start row, or not a number.
        (
            {
                let body = rows_bytes(150, 160);
                let crc = format!("{:08x}", crc32c::crc32c(&body));
                let headers = [
                    ("content-type", "application/octet-stream"),
                    ("x-helmholtz-crc32c", crc.as_str()),
                ];
                rest.put_with(id, "", &headers, body).await
            },
            400,
            "start_row",
        ),
        (
            rest.put(
                id,
                "-1",
                "application/octet-stream",
                rows_bytes(150, 160),
                None,
                None,
            )
            .await,
            400,
            "start_row",
        ),
        // An unknown media type.
        (
            rest.put(id, "150", "text/csv", b"1,2\n".to_vec(), None, None)
                .await,
            400,
            "content-type",
        ),
        // A gap above the committed count.
        (
            rest.put(
                id,
                "151",
                "application/octet-stream",
                rows_bytes(151, 160),
                None,
                None,
            )
            .await,
            416,
            "",
        ),
        // Half a row.
        (
            rest.put(
                id,
                "150",
                "application/octet-stream",
                rows_bytes(150, 160)[..24].to_vec(),
                None,
                None,
            )
            .await,
            400,
            "body",
        ),
        // The wrong dtype (f32 for an f64 session), the wrong shape, Fortran order.
        (
            {
                let data: Vec<u8> = values[300..320]
                    .iter()
                    .flat_map(|v| (*v as f32).to_le_bytes())
                    .collect();
                rest.put(
                    id,
                    "150",
                    "application/x-npy",
                    npy_file(Dtype::F32, &[10, 2], &data),
                    None,
                    None,
                )
                .await
            },
            400,
            "body",
        ),
        (
            rest.put(
                id,
                "150",
                "application/x-npy",
                npy_file(Dtype::F64, &[5, 4], &rows_bytes(150, 160)),
                None,
                None,
            )
            .await,
            400,
            "body",
        ),
        (
            rest.put(
                id,
                "150",
                "application/x-npy",
                {
                    let mut f = npy::header(Dtype::F64, &[10, 2], true);
                    f.extend(rows_bytes(150, 160));
                    f
                },
                None,
                None,
            )
            .await,
            400,
            "body",
        ),
        // An NPY whose header promises more rows than it holds.
        (
            rest.put(
                id,
                "150",
                "application/x-npy",
                npy_file(Dtype::F64, &[11, 2], &rows_bytes(150, 160)),
                None,
                None,
            )
            .await,
            400,
            "body",
        ),
        // A non-finite value.
        (
            {
                let mut v = values[300..320].to_vec();
                v[7] = f64::NAN;
                rest.put(
                    id,
                    "150",
                    "application/octet-stream",
                    f64_le(&v),
                    None,
                    None,
                )
                .await
            },
            400,
            "body",
        ),
        // A Content-Digest that does not match, one of another algorithm, a malformed one.
        (
            {
                let digest = format!("sha-256=:{}=:", "A".repeat(43));
                let headers = [
                    ("content-type", "application/octet-stream"),
                    ("content-digest", digest.as_str()),
                ];
                rest.put_with(id, "?start_row=150", &headers, rows_bytes(150, 160))
                    .await
            },
            422,
            "",
        ),
        (
            rest.put_with(
                id,
                "?start_row=150",
                &[
                    ("content-type", "application/octet-stream"),
                    ("content-digest", "md5=:AAAAAAAAAAAAAAAAAAAAAA==:"),
                ],
                rows_bytes(150, 160),
            )
            .await,
            400,
            "content-digest",
        ),
        (
            rest.put_with(
                id,
                "?start_row=150",
                &[
                    ("content-type", "application/octet-stream"),
                    ("content-digest", "sha-256=:not base64:"),
                ],
                rows_bytes(150, 160),
            )
            .await,
            400,
            "content-digest",
        ),
        // A bad writer id.
        (
            rest.put(
                id,
                "150",
                "application/octet-stream",
                rows_bytes(150, 160),
                None,
                Some("no spaces"),
            )
            .await,
            400,
            "x-helmholtz-writer",
        ),
        // Overlapping rows that differ from the stored ones (row 120's second channel).
        (
            {
                let mut v = values[110 * channels..130 * channels].to_vec();
                v[10 * channels + 1] += 1e-9;
                rest.put(
                    id,
                    "110",
                    "application/octet-stream",
                    f64_le(&v),
                    None,
                    None,
                )
                .await
            },
            409,
            "",
        ),
    ];
    for (i, (answer, status, field)) in refusals.iter().enumerate() {
        assert_eq!(answer.status, *status, "refusal {i}: {}", answer.body);
        if !field.is_empty() {
            assert_eq!(
                problem_field(answer),
                *field,
                "refusal {i}: {}",
                answer.body
            );
        }
        assert!(
            answer.body["detail"]
                .as_str()
                .is_some_and(|d| !d.is_empty()),
            "refusal {i} explains itself: {}",
            answer.body
        );
    }
    assert_eq!(rest.committed(id).await, 150, "no refusal stored anything");

    // Another writer's open gRPC stream holds the session: a REST request is refused whole.
    let grpc = server.grpc().await.unwrap();
    let first = f64_chunk(
        id,
        150,
        channels as u32,
        &values[150 * channels..160 * channels],
    );
    let stream = OpenUpload::start(&grpc, Some("grpc-rig"), first, 10).await;
    let busy = rest
        .put(
            id,
            "160",
            "application/octet-stream",
            rows_bytes(160, 170),
            None,
            Some("lab-pc"),
        )
        .await;
    assert_eq!(busy.status, 409, "{}", busy.body);
    assert!(
        busy.body["detail"]
            .as_str()
            .unwrap()
            .contains("another writer"),
        "{}",
        busy.body
    );
    assert_eq!(rest.committed(id).await, 160);
    stream.finish().await.unwrap();

    // Resuming with overlap: rows 140..256 in one NPY; the 20 stored ones are compared.
    let a = rest
        .put(
            id,
            "140",
            "application/x-npy",
            npy_rows(140, rows as usize),
            None,
            Some("lab-pc"),
        )
        .await;
    assert_eq!(a.status, 200, "{}", a.body);
    assert_eq!(
        (
            a.body["committed_rows"].as_u64(),
            a.body["rows_written"].as_u64(),
            a.body["rows_skipped"].as_u64()
        ),
        (Some(rows), Some(rows - 160), Some(20))
    );

    let finished = rest
        .send(
            rest.http
                .post(format!("{}/v1/sessions/{id}/finish", server.address)),
        )
        .await;
    assert_eq!(
        (finished.status, finished.body["state"].as_str()),
        (200, Some("finished"))
    );

    // What is stored is bit for bit what was sent, in order.
    let stored = rest.measurements(id).await;
    let (shape, stored_values) = helmholtz_tests::parse_npy(&stored).unwrap();
    assert_eq!(shape, vec![rows as usize, channels]);
    assert_eq!(f64_le(&stored_values), f64_le(&values));

    // A reader-only token may not create or upload.
    let reader = server.create_token("e2e", "reader").unwrap();
    let as_reader = Rest {
        server: &server,
        token: reader,
        http: helmholtz_tests::http_client(),
    };
    let mut another = declaration.clone();
    another["id"] = json!("rest-by-reader");
    assert_eq!(as_reader.create(&another).await.status, 403);
    assert_eq!(
        as_reader
            .put(id, "0", "application/x-npy", npy_rows(0, 1), None, None)
            .await
            .status,
        403
    );
    // Another lab sees no such session.
    let stranger = server.create_token("other-lab", "rig,reader").unwrap();
    let as_stranger = Rest {
        server: &server,
        token: stranger,
        http: helmholtz_tests::http_client(),
    };
    assert_eq!(
        as_stranger
            .put(id, "0", "application/x-npy", npy_rows(0, 1), None, None)
            .await
            .status,
        404
    );

    // The session reconstructs like any other.
    let job = rest
        .send(
            rest.http
                .post(format!(
                    "{}/v1/sessions/{id}/reconstructions",
                    server.address
                ))
                .json(&json!({"method": "dgi"})),
        )
        .await;
    assert_eq!(job.status, 202, "{}", job.body);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn camera_frames_over_rest_are_stored_as_sent_and_bodies_over_the_chunk_cap_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    // 4 frames of 16 x 12 f32 pixels are 3,072 bytes: the cap lets 4 frames through, not 5.
    let server = ServerProcess::start(dir.path(), 0, &["--max-chunk-bytes", "3072"]).unwrap();
    let rest = Rest {
        server: &server,
        token: server.token.clone(),
        http: helmholtz_tests::http_client(),
    };
    let (w, h, rows) = (16u64, 12u64, 16u64);
    for (id, format) in [("rest-cam-f32", "f32"), ("rest-cam-u16", "u16")] {
        let created = rest
            .create(&json!({
                "id": id, "rig": "cam",
                "patterns": {"family": "hadamard", "width": 4, "height": 4, "count": rows, "seed": 0},
                "camera": {"width": w, "height": h, "format": format}
            }))
            .await;
        assert_eq!(created.status, 201, "{}", created.body);
        assert_eq!(created.body["camera"]["format"], format);
    }
    let pixels = (w * h) as usize;
    let f32_frames: Vec<f32> = (0..rows as usize * pixels)
        .map(|i| (i as f32 * 0.37).cos() * 100.0)
        .collect();
    let u16_frames: Vec<u16> = (0..rows as usize * pixels)
        .map(|i| (i * 7919 % 65_536) as u16)
        .collect();
    let f32_bytes = |from: usize, to: usize| -> Vec<u8> {
        f32_frames[from * pixels..to * pixels]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect()
    };
    let u16_bytes = |from: usize, to: usize| -> Vec<u8> {
        u16_frames[from * pixels..to * pixels]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect()
    };
    // f32 frames as (rows, h, w) and (rows, h*w) arrays; u16 frames raw.
    for start in (0..rows as usize).step_by(4) {
        let shape: Vec<u64> = if start % 8 == 0 {
            vec![4, h, w]
        } else {
            vec![4, h * w]
        };
        let a = rest
            .put(
                "rest-cam-f32",
                &start.to_string(),
                "application/x-npy",
                npy_file(Dtype::F32, &shape, &f32_bytes(start, start + 4)),
                None,
                None,
            )
            .await;
        assert_eq!(a.status, 200, "{}", a.body);
        let a = rest
            .put(
                "rest-cam-u16",
                &start.to_string(),
                "application/octet-stream",
                u16_bytes(start, start + 4),
                None,
                None,
            )
            .await;
        assert_eq!(a.status, 200, "{}", a.body);
    }
    // Five frames exceed the chunk cap: 413 naming the limit, nothing stored.
    let big = rest
        .put(
            "rest-cam-u16",
            "0",
            "application/octet-stream",
            u16_bytes(0, 5).repeat(2),
            None,
            None,
        )
        .await;
    assert_eq!(big.status, 413, "{}", big.body);
    assert_eq!(big.body["limit"], "max_chunk_bytes", "{}", big.body);
    // A frame of the wrong size.
    let a = rest
        .put(
            "rest-cam-f32",
            "0",
            "application/x-npy",
            npy_file(Dtype::F32, &[1, w, h], &f32_bytes(0, 1)),
            None,
            None,
        )
        .await;
    assert_eq!((a.status, problem_field(&a)), (400, "body"), "{}", a.body);

    for (id, sent) in [
        ("rest-cam-f32", f32_bytes(0, rows as usize)),
        ("rest-cam-u16", u16_bytes(0, rows as usize)),
    ] {
        assert_eq!(rest.committed(id).await, rows);
        let stored = rest.measurements(id).await;
        let header = npy::read_header(&mut &stored[..]).unwrap();
        assert_eq!(header.shape, vec![rows, h, w]);
        assert_eq!(
            &stored[header.data_offset as usize..],
            &sent[..],
            "{id} stored as sent"
        );
    }
}

/// docs/examples/rest-upload.sh, run as it is with sh, curl and openssl: the session it makes
/// and fills reconstructs exactly (a complete 8 x 8 Hadamard set, noise-free), and running it
/// again stores nothing twice.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_curl_example_uploads_a_session_that_reconstructs_exactly() {
    for tool in ["sh", "curl", "openssl", "base64"] {
        let found = Command::new("sh")
            .args(["-c", &format!("command -v {tool}")])
            .output()
            .unwrap();
        assert!(
            found.status.success(),
            "this test runs docs/examples/rest-upload.sh, which needs {tool}: install it (Debian: apt-get install curl openssl coreutils)"
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let spec: helmholtz_client::PatternSpec = serde_json::from_str(
        r#"{"family": "hadamard", "width": 8, "height": 8, "count": 128, "seed": 0}"#,
    )
    .unwrap();
    let truth = Target::builtin("shapes", 8, 8).unwrap().transport(1.0);
    let sim = simulate::simulate(&spec, &[&truth], &NoiseModel::default(), None);
    let rows = dir.path().join("rows.f64");
    std::fs::write(&rows, f64_le(&sim.values)).unwrap();
    let script =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/examples/rest-upload.sh");
    let run = || {
        let out = Command::new("sh")
            .arg(&script)
            .arg(&rows)
            .arg("curl-run")
            .env("HELMHOLTZ_SERVER", &server.address)
            .env("HELMHOLTZ_TOKEN", &server.token)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{} failed:\n{}\n{}",
            script.display(),
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_str::<Value>(String::from_utf8_lossy(&out.stdout).trim()).unwrap()
    };
    let first = run();
    assert_eq!(
        (
            first["rows_written"].as_u64(),
            first["committed_rows"].as_u64()
        ),
        (Some(128), Some(128)),
        "{first}"
    );
    let again = run();
    assert_eq!(
        (
            again["rows_written"].as_u64(),
            again["rows_skipped"].as_u64()
        ),
        (Some(0), Some(128)),
        "{again}"
    );
    let rest = Rest {
        server: &server,
        token: server.token.clone(),
        http: helmholtz_tests::http_client(),
    };
    let job = rest
        .send(
            rest.http
                .post(format!(
                    "{}/v1/sessions/curl-run/reconstructions",
                    server.address
                ))
                .json(&json!({"method": "direct"})),
        )
        .await;
    assert_eq!(job.status, 202, "{}", job.body);
    let rec = helmholtz_client::wait_reconstruction(
        &server.base_url,
        job.body["id"].as_i64().unwrap(),
        std::time::Duration::from_secs(60),
    )
    .await
    .unwrap();
    assert!(rec.is_done(), "{rec:?}");
    let npy = rest
        .http
        .get(format!(
            "{}/v1/reconstructions/{}/dual.npy",
            server.address, rec.id
        ))
        .bearer_auth(&server.token)
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let (shape, image) = parse_npy(&npy).unwrap();
    assert_eq!(shape, vec![8, 8]);
    let truth: Vec<f64> = truth.iter().map(|&v| v as f64).collect();
    let err = relative_error(&image, &truth);
    assert!(
        err < 1e-5,
        "the exact inverse of the uploaded rows is {err:.2e} off the scene"
    );
}
