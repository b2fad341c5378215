//! Bad input at scale: property-based tests over the request validation and decoding paths of
//! the real server (session declarations, upload chunks, reconstruction request bodies, REST
//! paths and query parameters, raw protobuf bytes). Every case must get a clear answer (a gRPC
//! status with a message, or problem+json naming what is wrong), never a crash or a 5xx, and a
//! refused request must store nothing.
//!
//! `HELMHOLTZ_PROPTEST_CASES` sets the number of cases per property (default 256, for CI); the
//! on-demand run is `HELMHOLTZ_PROPTEST_CASES=25000 cargo test -p helmholtz-tests --test e2e -- fuzz::`
//! (4 properties x 25,000 = 100,000 cases).

use std::collections::HashSet;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU32, Ordering};

use helmholtz_client::auth::Grpc;
use helmholtz_proto::v1;
use helmholtz_tests::ServerProcess;
use proptest::prelude::*;
use proptest::test_runner::{Config, TestRunner};
use prost::Message;
use tonic::Code;

fn cases() -> u32 {
    std::env::var("HELMHOLTZ_PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(256)
}

fn runner() -> TestRunner {
    TestRunner::new(Config {
        cases: cases(),
        failure_persistence: None,
        ..Config::default()
    })
}

/// Counts the cases a property ran (and how many the server accepted), and checks the count.
#[derive(Default)]
struct Tally {
    ran: AtomicU32,
    accepted: AtomicU32,
}

impl Tally {
    fn case(&self) {
        self.ran.fetch_add(1, Ordering::Relaxed);
    }
    fn accepted(&self) {
        self.accepted.fetch_add(1, Ordering::Relaxed);
    }
    fn report(&self, what: &str) {
        let ran = self.ran.load(Ordering::Relaxed);
        eprintln!(
            "{what}: {ran} cases, {} accepted",
            self.accepted.load(Ordering::Relaxed)
        );
        assert!(ran >= cases(), "{what}: ran {ran} of {} cases", cases());
    }
}

struct Harness {
    _dir: tempfile::TempDir,
    server: ServerProcess,
    rt: tokio::runtime::Runtime,
    grpc: Grpc,
    http: reqwest::Client,
}

fn harness() -> Harness {
    let dir = tempfile::tempdir().unwrap();
    // No rate limit: the point is volume.
    let server = ServerProcess::start(
        dir.path(),
        0,
        &[
            "--rate-per-second",
            "0",
            "--workers",
            "1",
            "--max-sessions-per-lab",
            "1000000",
        ],
    )
    .unwrap();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let grpc = rt.block_on(server.grpc()).unwrap();
    Harness {
        _dir: dir,
        server,
        rt,
        grpc,
        http: helmholtz_tests::http_client(),
    }
}

/// Strings that exercise id validation: mostly short, some valid, some hostile.
fn id_strategy() -> impl Strategy<Value = String> {
    prop_oneof![
        "[a-z0-9._-]{1,12}",
        ".{0,20}",
        "[A-Za-z0-9]{120,140}",
        Just(String::new()),
        Just("../etc/passwd".to_string()),
        Just("a\u{0}b".to_string()),
    ]
}

fn u32_edge() -> impl Strategy<Value = u32> {
    prop_oneof![
        0u32..70,
        Just(4096),
        Just(4097),
        Just(2048),
        Just(u32::MAX),
        any::<u32>()
    ]
}

fn u64_edge() -> impl Strategy<Value = u64> {
    prop_oneof![
        0u64..5000,
        Just(10_000_000),
        Just(10_000_001),
        Just(u64::MAX),
        any::<u64>()
    ]
}

fn f64_edge() -> impl Strategy<Value = f64> {
    prop_oneof![
        -1.0f64..2.0,
        Just(0.0),
        Just(1.0),
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(1e-300),
        any::<f64>()
    ]
}

fn params_strategy() -> impl Strategy<Value = Option<v1::pattern_spec::Params>> {
    use v1::pattern_spec::Params;
    prop_oneof![
        Just(None),
        (u32_edge(), u32_edge())
            .prop_map(|(block, scans)| Some(Params::Raster(v1::RasterParams { block, scans }))),
        proptest::option::of(f64_edge())
            .prop_map(|fill| Some(Params::Bernoulli(v1::BernoulliParams { fill }))),
        (-2i32..8).prop_map(|ordering| Some(Params::Hadamard(v1::HadamardParams { ordering }))),
        u32_edge().prop_map(|grain| Some(Params::Speckle(v1::SpeckleParams { grain }))),
    ]
}

/// Mostly well-formed declarations (so the accepting, idempotent and conflicting paths run too),
/// with small ids that collide, optional ground truth of the right or a wrong size.
fn plausible_create_strategy() -> impl Strategy<Value = v1::CreateSessionRequest> {
    (
        "[a-z0-9]{1,2}",
        1i32..5,
        prop_oneof![Just(4u32), Just(8), Just(16), 1u32..20],
        prop_oneof![Just(4u32), Just(8), Just(16), 1u32..20],
        prop_oneof![1u64..600, Just(512)],
        0u64..3,
        proptest::collection::vec("[a-c]", 1..3),
        proptest::option::of(prop_oneof![Just(f32::NAN), -1f32..1.0]),
    )
        .prop_map(
            |(session_id, family, width, height, count, seed, channels, gt)| {
                v1::CreateSessionRequest {
                    session_id,
                    rig: "rig".into(),
                    patterns: Some(v1::PatternSpec {
                        family,
                        width,
                        height,
                        count,
                        seed,
                        params: None,
                    }),
                    detector: Some(v1::DetectorLayout {
                        channels,
                        ..Default::default()
                    }),
                    metadata: Default::default(),
                    ground_truth: gt.map(|v| v1::GroundTruth {
                        width,
                        height,
                        transport: vec![v; (width * height) as usize],
                    }),
                }
            },
        )
}

fn create_strategy() -> impl Strategy<Value = v1::CreateSessionRequest> {
    prop_oneof![arbitrary_create_strategy(), plausible_create_strategy()]
}

fn arbitrary_create_strategy() -> impl Strategy<Value = v1::CreateSessionRequest> {
    let spec = (
        -1i32..7,
        u32_edge(),
        u32_edge(),
        u64_edge(),
        any::<u64>(),
        params_strategy(),
    )
        .prop_map(
            |(family, width, height, count, seed, params)| v1::PatternSpec {
                family,
                width,
                height,
                count,
                seed,
                params,
            },
        );
    let gt = proptest::option::of((
        0u32..20,
        0u32..20,
        proptest::collection::vec(any::<f32>(), 0..50),
    ))
    .prop_map(|g| {
        g.map(|(width, height, transport)| v1::GroundTruth {
            width,
            height,
            transport,
        })
    });
    (
        id_strategy(),
        ".{0,10}",
        proptest::option::of(spec),
        proptest::option::of(proptest::collection::vec(id_strategy(), 0..5)),
        proptest::collection::btree_map(".{0,8}", ".{0,16}", 0..4),
        gt,
    )
        .prop_map(
            |(session_id, rig, patterns, channels, metadata, ground_truth)| {
                v1::CreateSessionRequest {
                    session_id,
                    rig,
                    patterns,
                    detector: channels.map(|channels| v1::DetectorLayout {
                        channels,
                        ..Default::default()
                    }),
                    metadata: metadata.into_iter().collect(),
                    ground_truth,
                }
            },
        )
}

/// A refusal must be one of the statuses that describe bad input, with a message.
fn assert_clear(status: &tonic::Status, allowed: &[Code]) -> Result<(), TestCaseError> {
    prop_assert!(
        allowed.contains(&status.code()),
        "unexpected status {status:?}"
    );
    prop_assert!(
        !status.message().trim().is_empty(),
        "status without a message: {status:?}"
    );
    Ok(())
}

#[test]
fn session_declarations() {
    let mut h = harness();
    let created: Mutex<HashSet<String>> = Mutex::default();
    let tally = Tally::default();
    runner()
        .run(&create_strategy(), |req| {
            tally.case();
            let mut c = h.grpc.clone();
            let id = req.session_id.clone();
            let existed = created.lock().unwrap().contains(&id);
            match h.rt.block_on(c.create_session(req)) {
                Ok(r) => {
                    let r = r.into_inner();
                    prop_assert_eq!(r.created, !existed);
                    created.lock().unwrap().insert(id);
                    tally.accepted();
                }
                Err(status) => {
                    assert_clear(
                        &status,
                        &[
                            Code::InvalidArgument,
                            Code::AlreadyExists,
                            Code::OutOfRange,
                            Code::FailedPrecondition,
                        ],
                    )?;
                    let valid_id = !id.is_empty()
                        && id.len() <= 128
                        && id
                            .chars()
                            .all(|c| c.is_ascii_alphanumeric() || "._-".contains(c))
                        && id != "."
                        && id != "..";
                    if !existed && valid_id {
                        // Nothing was stored under that id.
                        let s = h.rt.block_on(c.get_upload_status(v1::SessionRef {
                            session_id: id.clone(),
                        }));
                        prop_assert_eq!(
                            s.map(|_| ()).unwrap_err().code(),
                            Code::NotFound,
                            "refused {} was stored",
                            id
                        );
                    }
                }
            }
            Ok(())
        })
        .unwrap();
    tally.report("session declarations");
    // The server still serves.
    let listed = h.rt.block_on(async {
        h.http
            .get(h.server.url("/v1/sessions?limit=1000"))
            .send()
            .await
            .unwrap()
            .json::<serde_json::Value>()
            .await
            .unwrap()
    });
    assert_eq!(
        listed["sessions"].as_array().unwrap().len(),
        created.lock().unwrap().len().min(1000)
    );
    h.server.kill();
}

#[test]
fn upload_chunks() {
    let mut h = harness();
    let mut c = h.grpc.clone();
    let spec = v1::PatternSpec {
        family: v1::PatternFamily::Bernoulli as i32,
        width: 4,
        height: 4,
        count: 10_000_000,
        seed: 1,
        params: None,
    };
    let create = v1::CreateSessionRequest {
        session_id: "target".into(),
        rig: "r".into(),
        patterns: Some(spec),
        detector: Some(v1::DetectorLayout {
            channels: vec!["a".into(), "b".into()],
            ..Default::default()
        }),
        metadata: Default::default(),
        ground_truth: None,
    };
    h.rt.block_on(c.create_session(create)).unwrap();
    let committed = Mutex::new(0u64);
    // Every acknowledged row's bytes, in order: the model the server must agree with.
    let stored: Mutex<Vec<u8>> = Mutex::new(Vec::new());
    let tally = Tally::default();
    let strategy = (
        prop_oneof![3 => Just("target".to_string()), 1 => id_strategy()],
        prop_oneof![2 => Just(0i64), 2 => -3i64..4, 1 => Just(1_000_000i64)],
        prop_oneof![3 => Just(2u32), 1 => 0u32..5, 1 => Just(u32::MAX)],
        prop_oneof![
            3 => proptest::collection::vec(-1e6f64..1e6, 1..40).prop_map(|v| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>()),
            1 => proptest::collection::vec(any::<u8>(), 0..100),
            1 => proptest::collection::vec(any::<f64>(), 0..20).prop_map(|v| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>()),
        ],
        prop_oneof![3 => Just(true), 1 => Just(false)],
        any::<u32>(),
        // Overlapping rows: 0 = as drawn (they differ from the stored ones), 1 = the stored
        // bytes (a faithful resume), 2 = the stored bytes with one byte flipped at `flip`.
        0u8..3,
        any::<usize>(),
    );
    runner()
        .run(
            &strategy,
            |(session_id, start_offset, channels, mut bytes, good_crc, crc, overlap, flip)| {
                tally.case();
                let mut c = h.grpc.clone();
                let before = *committed.lock().unwrap();
                let start = (before as i64 + start_offset).max(0) as u64;
                // The overlap with the stored rows, in bytes of this chunk.
                let overlap_bytes = ((before.saturating_sub(start)) as usize * 16).min(bytes.len());
                if overlap > 0 && overlap_bytes > 0 {
                    let model = stored.lock().unwrap();
                    let at = start as usize * 16;
                    bytes[..overlap_bytes].copy_from_slice(&model[at..at + overlap_bytes]);
                    if overlap == 2 {
                        bytes[flip % overlap_bytes] ^= 0x01;
                    }
                }
                // The first overlapping row whose bytes differ from the stored ones, if any.
                let differs = {
                    let model = stored.lock().unwrap();
                    let at = start as usize * 16;
                    (0..overlap_bytes)
                        .find(|&i| model.get(at + i) != bytes.get(i))
                        .map(|i| start + (i / 16) as u64)
                };
                let crc32c = if good_crc {
                    crc32c::crc32c(&bytes)
                } else {
                    crc
                };
                let chunk = v1::MeasurementChunk {
                    session_id: session_id.clone(),
                    start_row: start,
                    channels,
                    values_f64le: bytes.clone(),
                    crc32c,
                    ..Default::default()
                };
                let result =
                    h.rt.block_on(c.upload_measurements(tokio_stream::iter(vec![chunk])));
                let now =
                    h.rt.block_on(c.get_upload_status(v1::SessionRef {
                        session_id: "target".into(),
                    }))
                    .unwrap()
                    .into_inner()
                    .committed_rows;
                match result {
                    Ok(r) => {
                        let r = r.into_inner();
                        // Only well-formed chunks for the target are accepted, and exactly their new rows count.
                        prop_assert_eq!(session_id.as_str(), "target");
                        prop_assert!(
                            channels == 2
                                && bytes.len() % 16 == 0
                                && !bytes.is_empty()
                                && crc32c == crc32c::crc32c(&bytes)
                        );
                        let rows = bytes.len() as u64 / 16;
                        prop_assert!(start <= before);
                        prop_assert_eq!(differs, None, "an overlap that differs was accepted");
                        prop_assert_eq!(now, before.max(start + rows));
                        prop_assert_eq!(r.committed_rows, now);
                        prop_assert_eq!(r.rows_skipped, (overlap_bytes / 16) as u64);
                        stored
                            .lock()
                            .unwrap()
                            .extend_from_slice(&bytes[overlap_bytes..]);
                        *committed.lock().unwrap() = now;
                        tally.accepted();
                    }
                    Err(status) => {
                        assert_clear(
                            &status,
                            &[
                                Code::InvalidArgument,
                                Code::NotFound,
                                Code::OutOfRange,
                                Code::DataLoss,
                                Code::ResourceExhausted,
                                Code::AlreadyExists,
                            ],
                        )?;
                        if status.code() == Code::AlreadyExists {
                            // Only a differing overlap, and the message names its first row.
                            let row = differs.expect("refused as different, yet equal");
                            prop_assert!(
                                status.message().contains(&format!("row {row} of session")),
                                "{}",
                                status.message()
                            );
                        }
                        prop_assert_eq!(now, before, "a refused chunk changed the committed count");
                    }
                }
                Ok(())
            },
        )
        .unwrap();
    tally.report("upload chunks");
    // What is stored is exactly what was acknowledged.
    let bytes = h.rt.block_on(async {
        h.http
            .get(h.server.url("/v1/sessions/target/measurements.npy"))
            .send()
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap()
    });
    let (shape, values) = helmholtz_tests::parse_npy(&bytes).unwrap();
    assert_eq!(shape, vec![*committed.lock().unwrap() as usize, 2]);
    let model: Vec<f64> = stored
        .lock()
        .unwrap()
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
        .collect();
    assert_eq!(
        values.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
        model.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
        "stored rows are byte for byte the acknowledged ones"
    );
    h.server.kill();
}

fn json_strategy() -> impl Strategy<Value = serde_json::Value> {
    use serde_json::{Value, json};
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        any::<i64>().prop_map(|n| json!(n)),
        (-1e3f64..1e3).prop_map(|f| json!(f)),
        prop_oneof![
            Just("gi"),
            Just("dgi"),
            Just("ngi"),
            Just("direct"),
            Just("lsq"),
            Just("cs"),
            Just("tv"),
            Just("auto"),
            Just("levels"),
            Just("zero_filled"),
            Just("haar"),
            Just("db4"),
            Just("poisson"),
            Just("fit"),
        ]
        .prop_map(|s| json!(s)),
        ".{0,8}".prop_map(Value::String),
    ];
    leaf.prop_recursive(3, 24, 6, |inner| {
        prop_oneof![
            proptest::collection::vec(inner.clone(), 0..4).prop_map(Value::Array),
            proptest::collection::btree_map(
                prop_oneof![
                    Just("method".to_string()),
                    Just("params".to_string()),
                    Just("lambda".to_string()),
                    Just("max_iter".to_string()),
                    Just("models".to_string()),
                    Just("holdout".to_string()),
                    Just("noise".to_string()),
                    Just("photon".to_string()),
                    Just("offset".to_string()),
                    Just("transform".to_string()),
                    Just("mu".to_string()),
                    Just("level".to_string()),
                    ".{0,6}",
                ],
                inner,
                0..4
            )
            .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
}

#[test]
fn reconstruction_request_bodies() {
    let mut h = harness();
    let mut c = h.grpc.clone();
    // A session with no rows: every request that passes validation is refused for that (409),
    // so nothing can ever be queued; validation itself runs in full.
    let spec = v1::PatternSpec {
        family: v1::PatternFamily::Hadamard as i32,
        width: 8,
        height: 8,
        count: 128,
        seed: 0,
        params: None,
    };
    let create = v1::CreateSessionRequest {
        session_id: "empty".into(),
        rig: "r".into(),
        patterns: Some(spec),
        detector: Some(v1::DetectorLayout {
            channels: vec!["a".into()],
            ..Default::default()
        }),
        metadata: Default::default(),
        ground_truth: None,
    };
    h.rt.block_on(c.create_session(create)).unwrap();
    let body = prop_oneof![
        json_strategy().prop_map(|v| v.to_string().into_bytes()),
        (json_strategy(), json_strategy()).prop_map(|(m, p)| {
            serde_json::json!({"method": m, "params": p})
                .to_string()
                .into_bytes()
        }),
        proptest::collection::vec(any::<u8>(), 0..64),
    ];
    let tally = Tally::default();
    runner()
        .run(&(body, any::<bool>()), |(body, via_grpc)| {
            tally.case();
            if via_grpc {
                let (method, params) = match serde_json::from_slice::<serde_json::Value>(&body) {
                    Ok(v) => (
                        v["method"].as_str().unwrap_or("").to_string(),
                        v["params"].to_string(),
                    ),
                    Err(_) => (String::new(), String::from_utf8_lossy(&body).into_owned()),
                };
                let mut c = h.grpc.clone();
                let req = v1::ReconstructionRequest {
                    session_id: "empty".into(),
                    method,
                    params_json: params,
                };
                let status =
                    h.rt.block_on(c.request_reconstruction(req))
                        .map(|_| ())
                        .expect_err("nothing can be queued");
                assert_clear(&status, &[Code::InvalidArgument, Code::FailedPrecondition])?;
            } else {
                let r = h.rt.block_on(
                    h.http
                        .post(h.server.url("/v1/sessions/empty/reconstructions"))
                        .header("content-type", "application/json")
                        .body(body)
                        .send(),
                );
                let r = r.unwrap();
                let status = r.status().as_u16();
                prop_assert!(status == 400 || status == 409, "status {}", status);
                prop_assert_eq!(
                    r.headers()["content-type"].to_str().unwrap(),
                    "application/problem+json"
                );
                let problem: serde_json::Value = h.rt.block_on(r.json()).unwrap();
                prop_assert!(!problem["detail"].as_str().unwrap_or("").is_empty());
                if status == 400 {
                    prop_assert!(
                        problem["field"].is_string(),
                        "a 400 names the field: {}",
                        problem
                    );
                }
            }
            Ok(())
        })
        .unwrap();
    tally.report("reconstruction request bodies");
    let listed: serde_json::Value = h.rt.block_on(async {
        h.http
            .get(h.server.url("/v1/sessions/empty/reconstructions"))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap()
    });
    assert_eq!(
        listed["reconstructions"].as_array().unwrap().len(),
        0,
        "nothing was queued"
    );
    h.server.kill();
}

#[test]
fn rest_paths_queries_and_raw_protobuf() {
    let mut h = harness();
    let segment = prop_oneof![
        "[a-z0-9._-]{0,10}",
        "[0-9]{1,20}",
        "-?[0-9]{1,5}",
        "%[0-9A-F]{2}",
        ".{0,6}"
    ];
    let file = prop_oneof![
        Just("dual.png"),
        Just("dual.tiff"),
        Just("dual.npy"),
        Just("measurements.npy"),
        Just("x"),
        Just("cancel")
    ];
    let query = proptest::collection::vec(
        (
            prop_oneof![
                Just("scale".to_string()),
                Just("channel".to_string()),
                Just("limit".to_string()),
                "[a-z]{1,5}"
            ],
            prop_oneof!["[a-z0-9]{0,8}", "-?[0-9]{1,12}", ".{0,5}"],
        ),
        0..3,
    );
    let raw = proptest::collection::vec(any::<u8>(), 0..200);
    let tally = Tally::default();
    runner()
        .run(
            &(0u8..6, segment, file, query, raw),
            |(kind, seg, file, query, raw)| {
                tally.case();
                let q: Vec<String> = query
                    .iter()
                    .map(|(k, v)| format!("{}={}", k, helmholtz_client::rest::encode_component(v)))
                    .collect();
                let q = if q.is_empty() {
                    String::new()
                } else {
                    format!("?{}", q.join("&"))
                };
                let seg = seg.replace(['/', '?', '#', ' '], "_");
                let path = match kind {
                    0 => format!("/v1/sessions{q}"),
                    1 => format!("/v1/sessions/{seg}{q}"),
                    2 => format!("/v1/sessions/{seg}/{file}{q}"),
                    3 => format!("/v1/reconstructions/{seg}{q}"),
                    4 => format!("/v1/reconstructions/{seg}/{file}{q}"),
                    _ => {
                        // Raw bytes as a CreateSession message: a decode error or a validation error.
                        let decoded = v1::CreateSessionRequest::decode(raw.as_slice());
                        if let Ok(req) = decoded {
                            let mut c = h.grpc.clone();
                            if let Err(status) = h.rt.block_on(c.create_session(req)) {
                                assert_clear(
                                    &status,
                                    &[Code::InvalidArgument, Code::AlreadyExists],
                                )?;
                            }
                        }
                        return Ok(());
                    }
                };
                let Ok(url) = reqwest::Url::parse(&h.server.url(&path)) else {
                    return Ok(());
                };
                let r = h.rt.block_on(h.http.get(url).send()).unwrap();
                let status = r.status().as_u16();
                prop_assert!(status < 500, "{} -> {}", path, status);
                if status < 400 {
                    tally.accepted();
                }
                if status >= 400 {
                    prop_assert_eq!(
                        r.headers()["content-type"].to_str().unwrap(),
                        "application/problem+json",
                        "{}",
                        path
                    );
                }
                Ok(())
            },
        )
        .unwrap();
    tally.report("REST paths, queries and raw protobuf");
    h.server.kill();
}
