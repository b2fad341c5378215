//! Faults: the server is killed (SIGKILL) mid-upload and mid-reconstruction and restarted; no
//! acknowledged row is lost, none is stored twice, and every job finishes exactly once.

use std::time::{Duration, Instant};

use helmholtz_client::scene::Scene;
use helmholtz_client::simulate::{self, NoiseModel};
use helmholtz_client::{NewSession, PatternSpec, UploadOptions};
use helmholtz_tests::{ServerProcess, parse_npy};

async fn committed(server: &str, id: &str) -> Option<u64> {
    helmholtz_client::upload_status(server, id).await.ok().map(|s| s.committed_rows)
}

#[tokio::test]
async fn server_killed_mid_upload_then_restarted_loses_and_duplicates_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let base = server.base_url.clone();
    let port = server.port;
    let spec: PatternSpec =
        serde_json::from_str(r#"{"family":"bernoulli","width":16,"height":16,"count":60000,"seed":5}"#).unwrap();
    let transport = Scene::builtin("usaf", 16, 16).unwrap().transport(1.0);
    let noise = NoiseModel { snr_db: Some(30.0), ..NoiseModel::default() };
    let sim = simulate::simulate(&spec, &[&transport, &transport], &noise, None);
    let session = NewSession::new("kill-upload", spec.clone(), vec!["a".into(), "b".into()]);
    helmholtz_client::create_session(&base, &session).await.unwrap();

    // Small chunks so that the upload spans many commits; the uploader resumes for up to 60 s.
    let options = UploadOptions { chunk_rows: Some(200), retry_for: Duration::from_secs(60), ..UploadOptions::default() };
    let values = sim.values.clone();
    let uploader = {
        let base = base.clone();
        tokio::spawn(async move { helmholtz_client::upload(&base, "kill-upload", 2, &values, &options).await })
    };
    // Kill the server twice while rows are flowing, restarting it on the same port and data.
    for threshold in [5_000u64, 25_000] {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            if committed(&base, "kill-upload").await.unwrap_or(0) >= threshold {
                break;
            }
            assert!(Instant::now() < deadline, "upload never reached {threshold} rows");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        server.kill();
        tokio::time::sleep(Duration::from_millis(300)).await;
        server = ServerProcess::start(dir.path(), port, &[]).unwrap();
    }
    let report = uploader.await.unwrap().unwrap();
    assert!(report.resumes >= 1, "the uploader must have resumed: {report:?}");
    assert_eq!(report.committed_rows, 60_000);
    helmholtz_client::finish_session(&base, "kill-upload").await.unwrap();
    let bytes = reqwest::get(server.url("/v1/sessions/kill-upload/measurements.npy")).await.unwrap().bytes().await.unwrap();
    let (shape, stored) = parse_npy(&bytes).unwrap();
    assert_eq!(shape, vec![60_000, 2]);
    assert!(stored == sim.values, "stored rows differ from the sent rows");
}

#[tokio::test]
async fn a_job_whose_server_died_is_taken_up_again_and_finishes_once() {
    let dir = tempfile::tempdir().unwrap();
    let lease = ["--lease-seconds", "2", "--workers", "1"];
    let mut server = ServerProcess::start(dir.path(), 0, &lease).unwrap();
    let base = server.base_url.clone();
    let port = server.port;
    // Grey-level speckle patterns: the correlator cannot take the packed-bits path, so the job
    // runs long enough (seconds) to be killed while running.
    let spec: PatternSpec =
        serde_json::from_str(r#"{"family":"speckle","width":64,"height":64,"count":120000,"seed":9}"#).unwrap();
    let transport = Scene::builtin("double-slit", 64, 64).unwrap().transport(1.0);
    let sim = simulate::simulate(&spec, &[&transport], &NoiseModel::default(), None);
    helmholtz_client::create_session(&base, &NewSession::new("kill-job", spec.clone(), vec!["bucket".into()])).await.unwrap();
    helmholtz_client::upload(&base, "kill-job", 1, &sim.values, &UploadOptions::default()).await.unwrap();
    helmholtz_client::finish_session(&base, "kill-job").await.unwrap();
    let rec = helmholtz_client::request_reconstruction(&base, "kill-job", "gi", &serde_json::json!({})).await.unwrap();

    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let r = helmholtz_client::get_reconstruction(&base, rec.id).await.unwrap();
        if r.state == "running" {
            break;
        }
        assert_ne!(r.state, "done", "the job finished before it could be killed; make it longer");
        assert!(Instant::now() < deadline, "job never started");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    server.kill();
    server = ServerProcess::start(dir.path(), port, &lease).unwrap();
    let done = helmholtz_client::wait_reconstruction(&base, rec.id, Duration::from_secs(180)).await.unwrap();
    assert!(done.is_done(), "{done:?}");
    let json: serde_json::Value =
        reqwest::get(server.url(&format!("/v1/reconstructions/{}", rec.id))).await.unwrap().json().await.unwrap();
    assert_eq!(json["attempt"], 2, "taken up again after the lease expired: {json}");
    let listed: serde_json::Value =
        reqwest::get(server.url("/v1/sessions/kill-job/reconstructions")).await.unwrap().json().await.unwrap();
    assert_eq!(listed["reconstructions"].as_array().unwrap().len(), 1);
    let npy = reqwest::get(server.url(&format!("/v1/reconstructions/{}/dual.npy", rec.id))).await.unwrap();
    let (shape, _) = parse_npy(&npy.bytes().await.unwrap()).unwrap();
    assert_eq!(shape, vec![64, 64]);
}
