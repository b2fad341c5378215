//! The whole path over loopback: simulate -> upload -> reconstruct -> fetch, with the real
//! server binary, the real client library and a real SQLite file.

use std::time::Duration;

use helmholtz_client::{NewSession, PatternSpec, UploadOptions};
use helmholtz_sim::Target;
use helmholtz_sim::simulate::{self, NoiseModel};
use helmholtz_tests::{ServerProcess, correlation, parse_npy, relative_error};

/// Simulates `spec` on a built-in scene (noise-free), uploads it as a finished session and
/// returns the scene's transport.
async fn acquire(
    server: &ServerProcess,
    id: &str,
    scene: &str,
    spec_json: &str,
) -> (PatternSpec, Vec<f32>) {
    let spec: PatternSpec = serde_json::from_str(spec_json).unwrap();
    let transport = Target::builtin(scene, spec.width(), spec.height())
        .unwrap()
        .transport(1.0);
    let sim = simulate::simulate(&spec, &[&transport], &NoiseModel::default(), None);
    let session = NewSession::new(id, spec.clone(), vec!["bucket".into()]).with_ground_truth(
        spec.width(),
        spec.height(),
        transport.clone(),
    );
    helmholtz_client::create_session(&server.base_url, &session)
        .await
        .unwrap();
    let report = helmholtz_client::upload(
        &server.base_url,
        id,
        1,
        &sim.values,
        &UploadOptions::default(),
    )
    .await
    .unwrap();
    assert_eq!(report.committed_rows, spec.count());
    helmholtz_client::finish_session(&server.base_url, id)
        .await
        .unwrap();
    (spec, transport)
}

/// Requests `method`, waits for it, and returns (reconstruction JSON, the dual image as f64).
async fn reconstruct(
    server: &ServerProcess,
    id: &str,
    method: &str,
) -> (serde_json::Value, Vec<f64>) {
    let rec = helmholtz_client::request_reconstruction(
        &server.base_url,
        id,
        method,
        &serde_json::json!({}),
    )
    .await
    .unwrap();
    let done =
        helmholtz_client::wait_reconstruction(&server.base_url, rec.id, Duration::from_secs(120))
            .await
            .unwrap();
    assert!(done.is_done(), "{method} did not finish: {done:?}");
    let json: serde_json::Value =
        helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{}", rec.id)))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
    let npy =
        helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{}/dual.npy", rec.id)))
            .await
            .unwrap();
    assert_eq!(npy.status(), 200);
    let (shape, values) = parse_npy(&npy.bytes().await.unwrap()).unwrap();
    assert_eq!(shape.len(), 2);
    (json, values)
}

fn as_f64(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| x as f64).collect()
}

#[tokio::test]
async fn gi_and_dgi_of_bernoulli_patterns_correlate_with_the_scene() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    // 32x32 USAF target, 30,000 Bernoulli(1/2) patterns. Per pixel, GI's mean is t_j/4 and its
    // noise std is about sqrt(sum t^2 / n)/4 (no detector noise), so SNR_j ~ t_j sqrt(n / sum t^2)
    // ~ 1 * sqrt(30000 / ~400) ~ 9 for bright pixels: the image correlates with the scene far above 0.9.
    let (_, truth) = acquire(
        &server,
        "gi-usaf",
        "usaf",
        r#"{"family":"bernoulli","width":32,"height":32,"count":30000,"seed":11}"#,
    )
    .await;
    let truth = as_f64(&truth);
    for method in ["gi", "dgi", "ngi"] {
        let (json, image) = reconstruct(&server, "gi-usaf", method).await;
        let r = correlation(&image, &truth);
        assert!(r > 0.9, "{method}: correlation {r:.3} with the scene");
        assert_eq!(json["method"], method);
        assert_eq!(json["rows"], 30000);
        assert!(json["seconds"].as_f64().unwrap() >= 0.0);
        let peak = json["report"]["peak_memory_bytes"]
            .as_u64()
            .expect("report carries the peak heap");
        assert!(
            peak > 32 * 32 * 8,
            "a {method} job must at least hold its accumulators: {peak} bytes"
        );
        let quality = &json["report"]["quality"][0];
        assert!(quality["psnr_fitted_db"].as_f64().unwrap() > 15.0, "{json}");
    }
}

#[tokio::test]
async fn direct_inversion_of_complete_sets_matches_the_scene() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let cases = [
        (
            "raster",
            "camera",
            r#"{"family":"raster","width":32,"height":32,"count":1024,"seed":0}"#,
        ),
        (
            "hadamard-seq",
            "usaf",
            r#"{"family":"hadamard","width":32,"height":32,"count":2048,"ordering":"sequency"}"#,
        ),
        (
            "hadamard-rect",
            "camera",
            r#"{"family":"hadamard","width":64,"height":16,"count":2048,"ordering":"russian_doll"}"#,
        ),
    ];
    for (id, scene, spec) in cases {
        let (_, truth) = acquire(&server, id, scene, spec).await;
        let (json, image) = reconstruct(&server, id, "direct").await;
        let err = relative_error(&image, &as_f64(&truth));
        assert!(err < 1e-4, "{id}: relative error {err:e}");
        assert_eq!(json["report"]["method"], "direct");
    }
}

#[tokio::test]
async fn dual_images_are_served_as_png_tiff_and_npy_with_etags() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    acquire(
        &server,
        "img",
        "shapes",
        r#"{"family":"hadamard","width":32,"height":16,"count":1024}"#,
    )
    .await;
    let (json, npy) = reconstruct(&server, "img", "direct").await;
    let id = json["id"].as_i64().unwrap();
    let http = helmholtz_tests::http_client();

    let png = http
        .get(server.url(&format!("/v1/reconstructions/{id}/dual.png")))
        .send()
        .await
        .unwrap();
    assert_eq!(png.headers()["content-type"], "image/png");
    let etag = png.headers()["etag"].to_str().unwrap().to_string();
    let bytes = png.bytes().await.unwrap();
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes.to_vec()))
        .read_info()
        .unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(
        (info.width, info.height, info.bit_depth),
        (32, 16, png::BitDepth::Eight)
    );
    let not_modified = http
        .get(server.url(&format!("/v1/reconstructions/{id}/dual.png")))
        .header("if-none-match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(not_modified.status(), 304);

    let tiff = http
        .get(server.url(&format!("/v1/reconstructions/{id}/dual.tiff")))
        .send()
        .await
        .unwrap();
    assert_eq!(tiff.headers()["content-type"], "image/tiff");
    let mut decoder =
        tiff::decoder::Decoder::new(std::io::Cursor::new(tiff.bytes().await.unwrap().to_vec()))
            .unwrap();
    assert_eq!(decoder.dimensions().unwrap(), (32, 16));
    let tiff::decoder::DecodingResult::F32(values) = decoder.read_image().unwrap() else {
        panic!("not f32")
    };
    assert_eq!(
        values.iter().map(|&v| v as f64).collect::<Vec<_>>(),
        npy,
        "TIFF and NPY carry the same floats"
    );

    // The session's dual.png is its latest finished reconstruction.
    let latest = http
        .get(server.url("/v1/sessions/img/dual.png"))
        .send()
        .await
        .unwrap();
    assert_eq!(latest.headers()["etag"].to_str().unwrap(), etag);
    let bad = http
        .get(server.url(&format!("/v1/reconstructions/{id}/dual.png?channel=nope")))
        .send()
        .await
        .unwrap();
    assert_eq!(bad.status(), 400);
    let problem: serde_json::Value = bad.json().await.unwrap();
    assert_eq!(problem["field"], "channel");
    let none = http
        .get(server.url("/v1/reconstructions/999/dual.png"))
        .send()
        .await
        .unwrap();
    assert_eq!(none.status(), 404);
    assert_eq!(none.headers()["content-type"], "application/problem+json");
}

#[tokio::test]
async fn compressive_methods_run_through_the_service() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    // 25 % of a Russian-doll Hadamard set on a sparse scene: TV recovers it well; the report
    // carries the solver's iterations and the PSNR against the simulator's ground truth.
    acquire(
        &server,
        "cs-shapes",
        "shapes",
        r#"{"family":"hadamard","width":32,"height":32,"count":512,"ordering":"russian_doll"}"#,
    )
    .await;
    for (method, floor_db) in [("tv", 22.0), ("cs", 18.0)] {
        let (json, image) = reconstruct(&server, "cs-shapes", method).await;
        assert!(
            image.iter().all(|v| v.is_finite() && *v >= 0.0),
            "{method}: negative or non-finite pixels"
        );
        let psnr = json["report"]["quality"][0]["psnr_db"].as_f64().unwrap();
        assert!(psnr > floor_db, "{method}: {psnr:.1} dB: {json}");
        assert!(json["report"]["iterations"].as_u64().unwrap() > 0);
        assert!(
            !json["params"]["lambda"].is_null(),
            "canonical params are stored: {json}"
        );
    }
}

#[tokio::test]
async fn auto_chooses_its_model_and_every_report_carries_its_error_estimate() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    // 30 % Bernoulli on the sparse scene: auto must report the model it chose, its weight, the
    // coefficients kept and the resolution, and its served image must be good.
    acquire(
        &server,
        "auto-shapes",
        "shapes",
        r#"{"family":"bernoulli","width":32,"height":32,"count":307,"fill":0.5,"seed":3}"#,
    )
    .await;
    let (json, image) = reconstruct(&server, "auto-shapes", "auto").await;
    assert!(image.iter().all(|v| v.is_finite() && *v >= 0.0));
    let report = &json["report"];
    let choice = &report["details"]["auto"][0];
    assert!(
        ["tv", "db4", "dct"].contains(&choice["model"].as_str().unwrap()),
        "{choice}"
    );
    assert!(choice["lambda_fraction"].as_f64().unwrap() > 0.0);
    assert!(choice["kept"].as_u64().unwrap() > 0);
    assert_eq!(
        choice["resolution"]["requested"],
        serde_json::json!([32, 32])
    );
    let psnr = report["quality"][0]["psnr_db"].as_f64().unwrap();
    assert!(psnr > 25.0, "auto: {psnr:.1} dB: {choice}");
    // The error estimate without ground truth, on every method that can have one; the exact
    // inverse says why it has none.
    let held = report["held_out"]["relative_residual"].as_f64().unwrap();
    assert!(held > 0.0 && held < 0.3, "held-out {held}");
    for method in ["tv", "dgi"] {
        let (json, _) = reconstruct(&server, "auto-shapes", method).await;
        let held = &json["report"]["held_out"];
        assert!(
            held["relative_residual"].as_f64().is_some() && held["rows"].as_u64().unwrap() >= 8,
            "{method}: {held}"
        );
    }
    acquire(
        &server,
        "direct-shapes",
        "shapes",
        r#"{"family":"raster","width":8,"height":8,"count":64}"#,
    )
    .await;
    let (json, _) = reconstruct(&server, "direct-shapes", "direct").await;
    assert!(json["report"]["held_out"].is_null());
    assert!(
        json["report"]["held_out_unavailable"]
            .as_str()
            .unwrap()
            .contains("exact inverse")
    );
    // A bad parameter is refused naming the field (gRPC and REST), and nothing is queued.
    let count = || async {
        let v: serde_json::Value =
            helmholtz_tests::http_get(server.url("/v1/sessions/auto-shapes/reconstructions"))
                .await
                .unwrap()
                .json()
                .await
                .unwrap();
        v["reconstructions"].as_array().unwrap().len()
    };
    let before = count().await;
    let response = helmholtz_tests::http_client()
        .post(server.url("/v1/sessions/auto-shapes/reconstructions"))
        .json(&serde_json::json!({"method": "auto", "params": {"holdout": 0.9}}))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 400);
    let problem: serde_json::Value = response.json().await.unwrap();
    assert!(problem.to_string().contains("params.holdout"), "{problem}");
    let err = helmholtz_client::request_reconstruction(
        &server.base_url,
        "auto-shapes",
        "auto",
        &serde_json::json!({"models": ["tv", "fourier"]}),
    )
    .await
    .unwrap_err()
    .to_string();
    assert!(err.contains("params.models[1]"), "{err}");
    assert_eq!(count().await, before);
}
