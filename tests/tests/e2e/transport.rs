//! Camera sessions end to end: an analytic Lambertian scene (known T, cast shadows, one diffuse
//! bounce) imaged by a camera under Hadamard patterns, uploaded over gRPC to the real server,
//! T reconstructed by a worker, then relit and predicted over HTTP and checked against the truth.

use std::time::Duration;

use helmholtz_proto::{PatternGenerator, PatternSpec, v1};
use helmholtz_sim::{Camera, Relief};
use helmholtz_tests::{ServerProcess, parse_npy, relative_error};

/// An f32 camera session of `scene` under the first `count` frames of a Hadamard spec; every
/// frame gets `ambient` added to each pixel (a dark level the split pairs cancel). Returns the
/// dense truth T (m x k).
async fn camera_session(
    server: &ServerProcess,
    id: &str,
    scene: &Relief,
    camera: Camera,
    count: u64,
    ambient: f32,
    ground_truth: bool,
) -> Vec<f32> {
    let (w, h) = (scene.width() as u32, scene.height() as u32);
    let spec = PatternSpec::new(
        helmholtz_proto::Family::Hadamard {
            ordering: helmholtz_proto::HadamardOrdering::Sequency,
        },
        w,
        h,
        count,
        5,
    )
    .unwrap();
    let view = scene.view(&camera);
    let truth = view.dense();
    let mut c = server.grpc().await.unwrap();
    let req = v1::CreateSessionRequest {
        session_id: id.into(),
        rig: "camera-rig".into(),
        patterns: Some((&spec).into()),
        detector: Some(v1::DetectorLayout {
            camera: Some(v1::CameraLayout {
                width: camera.width,
                height: camera.height,
                format: v1::SampleFormat::F32 as i32,
            }),
            ..Default::default()
        }),
        metadata: Default::default(),
        ground_truth: ground_truth.then(|| v1::GroundTruth {
            width: w,
            height: h,
            transport: truth.clone(),
        }),
    };
    c.create_session(req).await.unwrap();
    let generator = PatternGenerator::new(&spec);
    let mut pattern = vec![0f32; spec.pixels()];
    let m = view.pixels();
    let mut chunks = Vec::new();
    let rows_per_chunk = 32u64;
    for start in (0..count).step_by(rows_per_chunk as usize) {
        let mut bytes = Vec::new();
        for i in start..(start + rows_per_chunk).min(count) {
            generator.fill_values(i, &mut pattern);
            let p: Vec<f64> = pattern.iter().map(|&v| v as f64).collect();
            for v in view.render(&p) {
                bytes.extend_from_slice(&(v as f32 + ambient).to_le_bytes());
            }
        }
        let crc = crc32c::crc32c(&bytes);
        chunks.push(v1::MeasurementChunk {
            session_id: id.into(),
            start_row: start,
            channels: m as u32,
            values_f32le: bytes,
            crc32c: crc,
            ..Default::default()
        });
    }
    let r = c
        .upload_measurements(tokio_stream::iter(chunks))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.committed_rows, count);
    truth
}

async fn reconstruct(
    server: &ServerProcess,
    id: &str,
    method: &str,
    params: serde_json::Value,
) -> serde_json::Value {
    let rec = helmholtz_client::request_reconstruction(&server.base_url, id, method, &params)
        .await
        .unwrap();
    let done =
        helmholtz_client::wait_reconstruction(&server.base_url, rec.id, Duration::from_secs(300))
            .await
            .unwrap();
    assert!(done.is_done(), "{method} did not finish: {done:?}");
    helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{}", rec.id)))
        .await
        .unwrap()
        .json()
        .await
        .unwrap()
}

async fn post(server: &ServerProcess, path: &str, body: &str) -> reqwest::Response {
    helmholtz_tests::http_client()
        .post(server.url(path))
        .header("content-type", "application/json")
        .body(body.to_string())
        .send()
        .await
        .unwrap()
}

async fn post_npy(
    server: &ServerProcess,
    path: &str,
    body: &str,
) -> (Vec<usize>, Vec<f64>, reqwest::header::HeaderMap) {
    let r = post(server, path, body).await;
    assert_eq!(
        r.status(),
        200,
        "{path} {body}: {}",
        r.text().await.unwrap()
    );
    let headers = r.headers().clone();
    let (shape, values) = parse_npy(&r.bytes().await.unwrap()).unwrap();
    (shape, values, headers)
}

/// `T^T c` from the dense truth.
fn truth_relight(t: &[f32], m: usize, k: usize, light: &[f64]) -> Vec<f64> {
    let mut out = vec![0.0; k];
    for j in 0..m {
        if light[j] != 0.0 {
            for (o, v) in out.iter_mut().zip(&t[j * k..(j + 1) * k]) {
                *o += light[j] * *v as f64;
            }
        }
    }
    out
}

#[tokio::test]
async fn a_complete_hadamard_camera_session_recovers_t_relights_and_predicts_frames() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let scene = Relief::demo(16, 16, 4);
    let camera = Camera::tilted(12, 10, 25.0);
    let (m, k) = (120usize, 256usize);
    let ambient = 0.02f32;
    let truth = camera_session(&server, "cam", &scene, camera, 2 * k as u64, ambient, true).await;

    // Other methods are refused for a camera session, naming the right one.
    let refused = post(
        &server,
        "/v1/sessions/cam/reconstructions",
        r#"{"method": "tv"}"#,
    )
    .await;
    assert_eq!(refused.status(), 409);
    assert!(refused.text().await.unwrap().contains("transport"));

    let rec = reconstruct(&server, "cam", "transport", serde_json::json!({})).await;
    let id = rec["id"].as_i64().unwrap();
    let q = &rec["report"]["quality"];
    // A complete noise-free set: T to f32 precision up to what the sparse storage drops.
    let err = q["transport_relative_error"].as_f64().unwrap();
    assert!(err < 1e-3, "relative error of T {err}: {q}");
    assert!(q["camera_dual_psnr_db"].as_f64().unwrap() > 50.0, "{q}");

    // Relight: the full camera (T^T 1), a disc and a stripe, against the truth.
    let full = vec![1.0; m];
    let disc: Vec<f64> = (0..m)
        .map(|j| {
            (((j % 12) as f64 + 0.5 - 6.0).powi(2) + ((j / 12) as f64 + 0.5 - 5.0).powi(2) <= 9.0)
                as u8 as f64
        })
        .collect();
    let stripe: Vec<f64> = (0..m)
        .map(|j| ((2..5).contains(&(j % 12))) as u8 as f64)
        .collect();
    for (body, light) in [
        (r#"{"light": {"preset": "full"}}"#, &full),
        (
            r#"{"light": {"preset": "disc", "x": 6, "y": 5, "radius": 3}}"#,
            &disc,
        ),
        (
            r#"{"light": {"preset": "stripe", "x0": 2, "x1": 5}}"#,
            &stripe,
        ),
    ] {
        let (shape, got, _) = post_npy(
            &server,
            &format!("/v1/reconstructions/{id}/relight?format=npy"),
            body,
        )
        .await;
        assert_eq!(shape, vec![16, 16]);
        let want = truth_relight(&truth, m, k, light);
        let e = relative_error(&got, &want);
        assert!(e < 1e-3, "{body}: relative error {e}");
    }

    // A camera-sized NPY light gives the same as the equivalent preset.
    let light_npy = {
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        let mut header =
            "{'descr': '<f4', 'fortran_order': False, 'shape': (10, 12), }".to_string();
        let total = 10 + header.len() + 1;
        header.push_str(&" ".repeat(total.next_multiple_of(64) - total));
        header.push('\n');
        bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
        bytes.extend_from_slice(header.as_bytes());
        for v in &stripe {
            bytes.extend_from_slice(&(*v as f32).to_le_bytes());
        }
        bytes
    };
    let r = helmholtz_tests::http_client()
        .post(server.url(&format!("/v1/reconstructions/{id}/relight?format=npy")))
        .header("content-type", "application/x-npy")
        .body(light_npy)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let (_, from_image) = parse_npy(&r.bytes().await.unwrap()).unwrap();
    let (_, from_preset, headers) = post_npy(
        &server,
        &format!("/v1/reconstructions/{id}/relight?format=npy"),
        r#"{"light": {"preset": "stripe", "x0": 2, "x1": 5}}"#,
    )
    .await;
    assert_eq!(from_image, from_preset);
    // Repeating a request: the same strong ETag, served from the cache; If-None-Match is 304.
    let etag = headers["etag"].to_str().unwrap().to_string();
    assert!(etag.starts_with('"') && !etag.starts_with("W/"));
    assert!(
        headers["server-timing"].to_str().unwrap().contains("cache"),
        "{headers:?}"
    );
    let r = helmholtz_tests::http_client()
        .post(server.url(&format!("/v1/reconstructions/{id}/relight?format=npy")))
        .header("content-type", "application/json")
        .header("if-none-match", &etag)
        .body(r#"{"light": {"preset": "stripe", "x0": 2, "x1": 5}}"#)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 304);
    let png = post(
        &server,
        &format!("/v1/reconstructions/{id}/relight"),
        r#"{"light": {"preset": "full"}}"#,
    )
    .await;
    assert_eq!(png.headers()["content-type"], "image/png");
    assert_ne!(png.headers()["etag"].to_str().unwrap(), etag);

    // Primal: a measured pattern's predicted frame (T p + ambient) against the stored frame.
    let (shape, predicted, headers) = post_npy(
        &server,
        &format!("/v1/reconstructions/{id}/primal?format=npy"),
        r#"{"pattern_index": 37}"#,
    )
    .await;
    assert_eq!(shape, vec![10, 12]);
    let e: f64 = headers["x-helmholtz-relative-error"]
        .to_str()
        .unwrap()
        .parse()
        .unwrap();
    assert!(
        e < 1e-3,
        "primal relative error against the measured frame {e}"
    );
    let spec = PatternSpec::new(
        helmholtz_proto::Family::Hadamard {
            ordering: helmholtz_proto::HadamardOrdering::Sequency,
        },
        16,
        16,
        512,
        5,
    )
    .unwrap();
    let mut p = vec![0f32; k];
    PatternGenerator::new(&spec).fill_values(37, &mut p);
    let p: Vec<f64> = p.iter().map(|&v| v as f64).collect();
    let want: Vec<f64> = scene
        .view(&camera)
        .render(&p)
        .iter()
        .map(|v| v + ambient as f64)
        .collect();
    assert!(relative_error(&predicted, &want) < 1e-3);
    let (_, without, _) = post_npy(
        &server,
        &format!("/v1/reconstructions/{id}/primal?format=npy&ambient=exclude"),
        r#"{"pattern_index": 37}"#,
    )
    .await;
    let mean_gap = predicted
        .iter()
        .zip(&without)
        .map(|(a, b)| a - b)
        .sum::<f64>()
        / m as f64;
    assert!(
        (mean_gap - ambient as f64).abs() < 1e-3,
        "ambient estimate {mean_gap} vs {ambient}"
    );

    // Bad requests: each a 400 problem naming the field, nothing cached or changed.
    for (path, body, field) in [
        (
            "relight",
            r#"{"light": {"weights": {"a": 1}}}"#,
            "light.weights",
        ),
        (
            "relight",
            r#"{"light": {"preset": "disc", "x": 1, "y": 1}}"#,
            "light.radius",
        ),
        (
            "relight",
            r#"{"light": {"preset": "moon"}}"#,
            "light.preset",
        ),
        (
            "relight",
            r#"{"light": {"preset": "stripe", "x0": 40, "x1": 50}}"#,
            "light",
        ),
        ("relight", r#"{"lamp": 1}"#, "lamp"),
        ("primal", r#"{"pattern_index": 512}"#, "pattern_index"),
        ("primal", r#"{"pattern_index": -1}"#, "pattern_index"),
    ] {
        let r = post(&server, &format!("/v1/reconstructions/{id}/{path}"), body).await;
        assert_eq!(r.status(), 400, "{path} {body}");
        assert_eq!(r.headers()["content-type"], "application/problem+json");
        let problem: serde_json::Value = r.json().await.unwrap();
        assert!(
            problem["detail"].as_str().unwrap().contains(field),
            "{body}: {problem}"
        );
    }
}

#[tokio::test]
async fn reciprocity_the_camera_summed_equals_one_bucket_detector_where_it_stands() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let scene = Relief::demo(16, 16, 9);
    let camera = Camera::tilted(8, 8, 30.0);
    let k = 256;
    camera_session(&server, "cam", &scene, camera, 2 * k as u64, 0.0, false).await;
    let rec = reconstruct(&server, "cam", "transport", serde_json::json!({})).await;
    let id = rec["id"].as_i64().unwrap();
    let (_, summed, _) = post_npy(
        &server,
        &format!("/v1/reconstructions/{id}/relight?format=npy"),
        r#"{"light": {"preset": "full"}}"#,
    )
    .await;

    // The same scene with one photodiode where the camera was, with shot-like noise on the buckets.
    let spec = PatternSpec::new(
        helmholtz_proto::Family::Hadamard {
            ordering: helmholtz_proto::HadamardOrdering::Sequency,
        },
        16,
        16,
        2 * k as u64,
        5,
    )
    .unwrap();
    let t = scene.detector_transport(camera.direction);
    let generator = PatternGenerator::new(&spec);
    let mut p = vec![0f32; k];
    let mut rng = helmholtz_tests::SplitMix64(17);
    let noise = 1e-3;
    let values: Vec<f64> = (0..spec.count())
        .map(|i| {
            generator.fill_values(i, &mut p);
            let clean: f64 = p.iter().zip(&t).map(|(a, b)| *a as f64 * b).sum();
            let u = (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
            clean + noise * (u - 0.5) * 12f64.sqrt()
        })
        .collect();
    let session = helmholtz_client::NewSession::new("diode", spec.clone(), vec!["bucket".into()]);
    helmholtz_client::create_session(&server.base_url, &session)
        .await
        .unwrap();
    helmholtz_client::upload(
        &server.base_url,
        "diode",
        1,
        &values,
        &helmholtz_client::UploadOptions::default(),
    )
    .await
    .unwrap();
    let rec = reconstruct(&server, "diode", "direct", serde_json::json!({})).await;
    let npy = helmholtz_tests::http_get(
        server.url(&format!("/v1/reconstructions/{}/dual.npy", rec["id"])),
    )
    .await
    .unwrap();
    let (_, dual) = parse_npy(&npy.bytes().await.unwrap()).unwrap();
    // Equal up to the bucket noise: per pixel the exact inverse spreads noise 1e-3 over 256 pairs,
    // about 1e-3 * sqrt(2/256) ~ 1e-4 against values ~0.1-0.5, so a few 1e-4 relative overall.
    let e = relative_error(&summed, &dual);
    assert!(
        e < 5e-3,
        "camera summed vs photodiode dual image: relative difference {e}"
    );
    // And a bucket session relights by channel weights (here its only channel, doubled).
    let (_, doubled, _) = post_npy(
        &server,
        &format!("/v1/reconstructions/{}/relight?format=npy", rec["id"]),
        r#"{"light": {"weights": {"bucket": 2}}}"#,
    )
    .await;
    assert!(
        doubled
            .iter()
            .zip(&dual)
            .all(|(a, b)| (a - 2.0 * b).abs() <= 1e-6 * b.abs().max(1.0))
    );
    let r = post(
        &server,
        &format!("/v1/reconstructions/{}/primal", rec["id"]),
        r#"{"pattern_index": 1}"#,
    )
    .await;
    assert_eq!(r.status(), 409);
}

#[tokio::test]
async fn a_session_larger_than_the_worker_memory_budget_reconstructs_in_blocks() {
    let dir = tempfile::tempdir().unwrap();
    // 1 MiB working set; the frames are 1024 x 32 x 32 f32 = 4 MiB.
    let server = ServerProcess::start(
        dir.path(),
        0,
        &["--worker-memory-mib", "1", "--workers", "1"],
    )
    .unwrap();
    let scene = Relief::demo(32, 16, 2);
    let camera = Camera::tilted(32, 32, 20.0);
    camera_session(&server, "big", &scene, camera, 1024, 0.0, true).await;
    let frames_bytes = 1024 * 32 * 32 * 4;
    // One upload chunk (32 frames) is read at a time.
    let chunk_bytes = 32 * 32 * 32 * 4;
    let rec = reconstruct(&server, "big", "transport", serde_json::json!({})).await;
    let report = &rec["report"];
    let err = report["quality"]["transport_relative_error"]
        .as_f64()
        .unwrap();
    assert!(err < 1e-3, "relative error of T {err}");
    // The job's peak before it loads the ground truth (m x k, 2 MiB here) to score itself.
    let peak = report["details"]["reconstruction_peak_bytes"]
        .as_u64()
        .expect("the server binary counts its heap") as usize;
    let stored = report["details"]["stored_bytes"]
        .as_u64()
        .expect("stored size reported") as usize;
    // Beyond the budget: the result T (held twice while it is encoded for storage), the stored
    // chunk being read (twice while it is copied out of the database's row), and 256 KiB for the
    // runtime's own buffers. All of it well under the frames' size.
    let allowed = (1 << 20) + 2 * stored + 2 * chunk_bytes + (256 << 10);
    println!("peak {peak} bytes, allowed {allowed} (T {stored} bytes)");
    assert!(
        peak <= allowed,
        "peak {peak} bytes > {allowed} (T {stored} bytes, frames {frames_bytes} bytes)"
    );
    assert!(
        peak < frames_bytes / 2,
        "peak {peak} vs frames {frames_bytes}"
    );
    assert!(
        report["details"]["frame_passes"].as_u64().unwrap() >= 2,
        "{report}"
    );
}

#[tokio::test]
async fn half_a_hadamard_set_gives_t_and_relit_images_within_stated_tolerances() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let scene = Relief::demo(16, 16, 6);
    let camera = Camera::tilted(8, 8, 20.0);
    let (m, k) = (64usize, 256usize);
    // 50 % of the split pairs in Russian-doll order: the complete 8x8 block level and half of
    // the finer coefficients. Noise-free: the error is what the missing coefficients cost.
    let spec_count = k as u64; // frames = half of the 2k of a complete set
    let truth = {
        let (w, h) = (16u32, 16u32);
        let spec = PatternSpec::new(
            helmholtz_proto::Family::Hadamard {
                ordering: helmholtz_proto::HadamardOrdering::RussianDoll,
            },
            w,
            h,
            spec_count,
            5,
        )
        .unwrap();
        let view = scene.view(&camera);
        let truth = view.dense();
        let mut c = server.grpc().await.unwrap();
        let req = v1::CreateSessionRequest {
            session_id: "half".into(),
            rig: "camera-rig".into(),
            patterns: Some((&spec).into()),
            detector: Some(v1::DetectorLayout {
                camera: Some(v1::CameraLayout {
                    width: 8,
                    height: 8,
                    format: v1::SampleFormat::F32 as i32,
                }),
                ..Default::default()
            }),
            metadata: Default::default(),
            ground_truth: Some(v1::GroundTruth {
                width: w,
                height: h,
                transport: truth.clone(),
            }),
        };
        c.create_session(req).await.unwrap();
        let generator = PatternGenerator::new(&spec);
        let mut p = vec![0f32; k];
        let mut bytes = Vec::new();
        for i in 0..spec_count {
            generator.fill_values(i, &mut p);
            let p: Vec<f64> = p.iter().map(|&v| v as f64).collect();
            for v in view.render(&p) {
                bytes.extend_from_slice(&(v as f32).to_le_bytes());
            }
        }
        let crc = crc32c::crc32c(&bytes);
        let chunk = v1::MeasurementChunk {
            session_id: "half".into(),
            start_row: 0,
            channels: m as u32,
            values_f32le: bytes,
            crc32c: crc,
            ..Default::default()
        };
        c.upload_measurements(tokio_stream::iter(vec![chunk]))
            .await
            .unwrap();
        truth
    };
    let rec = reconstruct(&server, "half", "transport", serde_json::json!({})).await;
    let id = rec["id"].as_i64().unwrap();
    let err = rec["report"]["quality"]["transport_relative_error"]
        .as_f64()
        .unwrap();
    eprintln!(
        "half Hadamard: relative error of T {err}, report {}",
        rec["report"]["details"]
    );
    // Measured 0.107 (the data chose l1 in the pixel basis); the numerics' own test of the same
    // sampling on a 32x32 projector gets 0.14 where the zero-filled inverse gets 0.20.
    assert!(err < 0.2, "relative error of T {err}");
    let (_, summed, _) = post_npy(
        &server,
        &format!("/v1/reconstructions/{id}/relight?format=npy"),
        r#"{"light": {"preset": "full"}}"#,
    )
    .await;
    let want = truth_relight(&truth, m, k, &vec![1.0; m]);
    let e = relative_error(&summed, &want);
    eprintln!("half Hadamard: relit full-camera dual image relative error {e}");
    // Measured 0.082: summing rows averages part of their errors out.
    assert!(e < 0.12, "relit dual image relative error {e}");

    // The report offers the grid the pairs measure completely (a quarter of a Russian-doll set
    // on 16x16 is the complete set on 8x8 blocks of 2x2), and params {"projector_binning": 2}
    // reconstructs T there: each column the light of a 2x2 block, exact but for what the
    // inverse drops as noise.
    assert_eq!(
        rec["report"]["details"]["coarser"]["projector_binning"], 2,
        "{}",
        rec["report"]["details"]
    );
    let coarse = reconstruct(
        &server,
        "half",
        "transport",
        serde_json::json!({"projector_binning": 2}),
    )
    .await;
    assert_eq!(
        coarse["report"]["details"]["projector"],
        serde_json::json!([8, 8])
    );
    let err = coarse["report"]["quality"]["transport_relative_error"]
        .as_f64()
        .unwrap();
    eprintln!("half Hadamard, projector_binning 2: relative error of the 8x8 T {err}");
    // Measured 1.6e-3: the exact inverse drops what it takes for noise, and on an 8x8 grid the
    // finest diagonal details its noise estimate reads are part of the scene.
    assert!(err < 5e-3, "relative error of the binned T {err}");
    let (shape, summed, _) = post_npy(
        &server,
        &format!(
            "/v1/reconstructions/{}/relight?format=npy",
            coarse["id"].as_i64().unwrap()
        ),
        r#"{"light": {"preset": "full"}}"#,
    )
    .await;
    assert_eq!(shape, vec![8, 8]);
    let fine = truth_relight(&truth, m, k, &vec![1.0; m]);
    let want: Vec<f64> = (0..64)
        .map(|c| {
            let (y, x) = (c / 8, c % 8);
            [(0, 0), (0, 1), (1, 0), (1, 1)]
                .iter()
                .map(|(dy, dx)| fine[(2 * y + dy) * 16 + 2 * x + dx])
                .sum()
        })
        .collect();
    let e = relative_error(&summed, &want);
    eprintln!("binned relit full-camera image relative error {e}");
    assert!(e < 5e-3, "binned relit dual image relative error {e}");
    // Its primal image of a session pattern (pattern 0, the all-on half of the first pair:
    // constant on the blocks) predicts the measured frame.
    let (shape, predicted, _) = post_npy(
        &server,
        &format!(
            "/v1/reconstructions/{}/primal?format=npy",
            coarse["id"].as_i64().unwrap()
        ),
        r#"{"pattern_index": 0}"#,
    )
    .await;
    assert_eq!(shape, vec![8, 8]);
    let frame0: Vec<f64> = (0..m)
        .map(|j| truth[j * k..(j + 1) * k].iter().map(|v| *v as f64).sum())
        .collect();
    let e = relative_error(&predicted, &frame0);
    eprintln!("binned primal image of pattern 0 relative error {e}");
    assert!(e < 5e-3, "binned primal image relative error {e}");
    // A factor that is no power of two is refused at the edge; one that does not tile the grid,
    // against the session; both name the field, and nothing is queued.
    for (params, status) in [
        (r#"{"projector_binning": 3}"#, 400),
        (r#"{"projector_binning": 32}"#, 409),
    ] {
        let r = post(
            &server,
            "/v1/sessions/half/reconstructions",
            &format!(r#"{{"method": "transport", "params": {params}}}"#),
        )
        .await;
        let code = r.status().as_u16();
        let body = r.text().await.unwrap();
        assert_eq!(code, status, "{params}: {body}");
        assert!(
            body.contains("params.projector_binning"),
            "{params}: {body}"
        );
    }
}
