//! The simulated rigs of the demo and what they do against the running service: create a
//! session, upload with the real edge client library (gRPC over loopback), reconstruct over
//! REST, print the URLs.

use std::time::Duration;

use anyhow::Context;
use helmholtz_client::{NewSession, PatternSpec, UploadOptions};
use helmholtz_proto::rest::{Figure, TransportQuality};
use helmholtz_sim::Target;
use helmholtz_sim::simulate::{self, NoiseModel};
use tokio::sync::oneshot;

use helmholtz_server::app::{Application, Config};
use helmholtz_server::auth::{Role, Roles};
use helmholtz_server::cli::{announce, shutdown_signal};

struct DemoRig {
    session_id: &'static str,
    scene: &'static str,
    spec: &'static str,
    noise: NoiseModel,
    method: &'static str,
    what: &'static str,
}

fn rigs() -> Vec<DemoRig> {
    vec![
        DemoRig {
            session_id: "demo-usaf-hadamard",
            scene: "usaf",
            spec: r#"{"family":"hadamard","width":64,"height":64,"count":8192,"seed":0,"ordering":"sequency"}"#,
            noise: NoiseModel {
                snr_db: Some(50.0),
                dark: 0.05,
                seed: 1,
                ..NoiseModel::default()
            },
            method: "direct",
            what: "USAF-1951 target, complete Hadamard split set (8,192 DMD frames), 50 dB read noise and a dark offset, exact inverse by fast Walsh-Hadamard transform",
        },
        DemoRig {
            session_id: "demo-double-slit-dgi",
            scene: "double-slit",
            spec: r#"{"family":"bernoulli","width":64,"height":64,"count":20000,"seed":42,"fill":0.5}"#,
            noise: NoiseModel {
                photons: Some(1e5),
                drift: 0.05,
                seed: 2,
                ..NoiseModel::default()
            },
            method: "dgi",
            what: "double slit, 20,000 random binary patterns, shot noise (1e5 photons per pattern) and 5 % source drift, differential ghost imaging",
        },
    ]
}

/// The demo's lab: its sessions and tokens belong to it.
pub const DEMO_LAB: &str = "demo";

pub async fn run(config: Config, exit_after_demo: bool) -> anyhow::Result<()> {
    // With --tls-cert the simulated rig connects over https: it trusts the system's roots and
    // the CA in HELMHOLTZ_CA_FILE, like the `helmholtz` client.
    if config.edge.tls.is_some()
        && let Some(ca) = std::env::var_os("HELMHOLTZ_CA_FILE")
    {
        helmholtz_client::tls::trust_ca_file(std::path::Path::new(&ca))?;
    }
    let app = Application::build(config.clone()).await?;
    announce(&app, &config);
    let base = app.base_url();
    // Fresh tokens each run (the secrets are not stored, so earlier ones cannot be shown again).
    let (_, rig_token) = app
        .store()
        .create_token(DEMO_LAB, Roles::of(&[Role::Rig]), "demo rig")
        .await?;
    let (_, reader_token) = app
        .store()
        .create_token(DEMO_LAB, Roles::of(&[Role::Reader]), "demo reader")
        .await?;
    println!(
        "\nTokens for lab {DEMO_LAB:?} (shown once; `helmholtz-server token list` lists them, `token revoke ID` revokes):"
    );
    println!("   rig    (create sessions, upload):           {rig_token}");
    println!("   reader (sessions, reconstructions, images): {reader_token}");
    println!("   e.g.  curl -fsS -H 'Authorization: Bearer {reader_token}' {base}/v1/sessions");
    println!("         helmholtz --server {base} --token {reader_token} status");
    // A URL fragment never reaches the server (browsers do not send it), so the token is in no
    // request line and no log; the viewer moves it to the tab's session storage at once.
    println!("   viewer (open in a browser, ready to use):  {base}/#token={reader_token}");
    let rig = helmholtz_client::auth::with_token(&base, &rig_token);
    let reader = helmholtz_client::auth::with_token(&base, &reader_token);
    let (demo_done_tx, demo_done_rx) = oneshot::channel::<()>();
    let server = tokio::spawn(app.run_until(async move {
        if exit_after_demo {
            tokio::select! { _ = demo_done_rx => {}, _ = shutdown_signal() => {} }
        } else {
            shutdown_signal().await;
        }
    }));
    let outcome = run_rigs(&base, &rig, &reader).await;
    let _ = demo_done_tx.send(());
    if let Err(e) = &outcome {
        eprintln!("demo rig failed: {e:#}");
    } else if !exit_after_demo {
        println!("\nServing on {base} until Ctrl-C.");
    }
    server.await.context("server task")??;
    outcome
}

/// The simulated rig uploads with the rig token; reconstructions are requested and awaited with
/// the reader token. `base` (without a token) is only printed.
async fn run_rigs(base: &str, rig: &str, reader: &str) -> anyhow::Result<()> {
    let rig_url = rig;
    for rig in rigs() {
        let spec: PatternSpec = serde_json::from_str(rig.spec).expect("demo spec is valid");
        println!("\n== {}: {}", rig.session_id, rig.what);
        let transport = Target::builtin(rig.scene, spec.width(), spec.height())?.transport(1.0);
        let sim = tokio::task::spawn_blocking({
            let (spec, transport, noise) = (spec.clone(), transport.clone(), rig.noise.clone());
            move || simulate::simulate(&spec, &[&transport], &noise, None)
        })
        .await?;
        let session = NewSession::new(rig.session_id, spec.clone(), vec!["bucket".into()])
            .with_rig("demo-rig")
            .with_metadata("scene", rig.scene)
            .with_ground_truth(spec.width(), spec.height(), transport);
        helmholtz_client::create_session(rig_url, &session).await?;
        let upload = helmholtz_client::upload(
            rig_url,
            rig.session_id,
            1,
            &sim.values,
            &UploadOptions::default(),
        )
        .await?;
        helmholtz_client::finish_session(rig_url, rig.session_id).await?;
        println!(
            "   uploaded {} rows ({} already stored) in {:.2} s",
            upload.rows, upload.rows_matched, upload.seconds
        );
        let rec = helmholtz_client::request_reconstruction(
            reader,
            rig.session_id,
            rig.method,
            &serde_json::json!({}),
        )
        .await?;
        let rec =
            helmholtz_client::wait_reconstruction(reader, rec.id, Duration::from_secs(600)).await?;
        anyhow::ensure!(
            rec.is_done(),
            "reconstruction {} ended {}: {:?}",
            rec.id,
            rec.state,
            rec.error
        );
        let q = rec
            .report
            .as_ref()
            .and_then(|r| r.channel_quality().first());
        println!(
            "   {} reconstruction {} in {:.3} s: PSNR {} dB, SSIM {} (after scale/offset fit: {} dB)",
            rec.method,
            rec.id,
            rec.seconds.unwrap_or(0.0),
            figure(q.map(|q| q.psnr_db)),
            figure(q.map(|q| q.ssim)),
            figure(q.map(|q| q.psnr_fitted_db))
        );
        println!("   session:    {base}/v1/sessions/{}", rig.session_id);
        println!("   report:     {base}/v1/reconstructions/{}", rec.id);
        println!(
            "   dual image: {base}/v1/reconstructions/{}/dual.png  (also .tiff, .npy)",
            rec.id
        );
    }
    camera_rig(base, rig_url, reader).await
}

/// A camera in place of the photodiode: the analytic Lambertian scene (hemisphere, box, cast
/// shadows, one diffuse bounce) on a 32x32 projector under the complete Hadamard set, seen by a
/// 32x24 camera tilted 25 degrees; the worker reconstructs T, and T relights the scene.
async fn camera_rig(base: &str, rig: &str, reader: &str) -> anyhow::Result<()> {
    const ID: &str = "demo-lambert-camera";
    println!(
        "\n== {ID}: Lambertian scene, 32x24 camera, complete Hadamard set (2,048 frames), transport matrix T"
    );
    let spec: PatternSpec =
        serde_json::from_str(r#"{"family":"hadamard","width":32,"height":32,"count":2048,"seed":0,"ordering":"sequency"}"#)
            .expect("demo spec is valid");
    let (frames, truth) = tokio::task::spawn_blocking({
        let spec = spec.clone();
        move || {
            let scene = helmholtz_sim::Relief::demo(32, 32, 1);
            let view = scene.view(&helmholtz_sim::Camera::tilted(32, 24, 25.0));
            let generator = helmholtz_proto::PatternGenerator::new(&spec);
            let mut p = vec![0f32; spec.pixels()];
            let mut frames = Vec::with_capacity(spec.count() as usize * view.pixels());
            for i in 0..spec.count() {
                generator.fill_values(i, &mut p);
                let p: Vec<f64> = p.iter().map(|&v| v as f64).collect();
                // A small ambient level on every pixel (the split pairs cancel it; the
                // reconstruction estimates it as the "ambient" image).
                frames.extend(view.render(&p).into_iter().map(|v| v as f32 + 0.01));
            }
            (frames, view.dense())
        }
    })
    .await?;
    let session = NewSession::camera(
        ID,
        spec.clone(),
        32,
        24,
        helmholtz_proto::wire::SampleFormat::F32,
    )
    .with_rig("demo-camera-rig")
    .with_ground_truth(spec.width(), spec.height(), truth);
    helmholtz_client::create_session(rig, &session).await?;
    let upload = helmholtz_client::upload_samples(
        rig,
        ID,
        32 * 24,
        helmholtz_proto::wire::Samples::F32(&frames),
        &UploadOptions::default(),
    )
    .await?;
    helmholtz_client::finish_session(rig, ID).await?;
    println!(
        "   uploaded {} frames ({} already stored) in {:.2} s",
        upload.rows, upload.rows_matched, upload.seconds
    );
    let rec =
        helmholtz_client::request_reconstruction(reader, ID, "transport", &serde_json::json!({}))
            .await?;
    let rec =
        helmholtz_client::wait_reconstruction(reader, rec.id, Duration::from_secs(600)).await?;
    anyhow::ensure!(
        rec.is_done(),
        "reconstruction {} ended {}: {:?}",
        rec.id,
        rec.state,
        rec.error
    );
    println!(
        "   transport reconstruction {} in {:.3} s: relative error of T {}, stored {} bytes",
        rec.id,
        rec.seconds.unwrap_or(0.0),
        figure(
            match rec.report.as_ref().and_then(|r| r.transport_quality()) {
                Some(TransportQuality::Scored {
                    transport_relative_error,
                    ..
                }) => Some(*transport_relative_error),
                _ => None,
            }
        ),
        fmt(rec
            .report
            .as_ref()
            .and_then(|r| r.recon.details.get("stored_bytes"))
            .unwrap_or(&serde_json::Value::Null))
    );
    // Lines a user pastes as they are: the reader's real token, JSON declared as such.
    let token = helmholtz_client::auth::split_server(reader)
        .1
        .unwrap_or_default();
    println!("   report:     {base}/v1/reconstructions/{}", rec.id);
    println!(
        "   relight:    curl -fsS -H 'Authorization: Bearer {token}' -H 'Content-Type: application/json' -d '{{\"light\": {{\"preset\": \"disc\", \"x\": 16, \"y\": 12, \"radius\": 5}}}}' -o relit.png {base}/v1/reconstructions/{}/relight",
        rec.id
    );
    println!(
        "   or:         helmholtz --server {base} --token {token} relight --reconstruction {} --disc 16,12,5 --out relit.png",
        rec.id
    );
    Ok(())
}

/// A report's figure: two decimals, "inf" for a perfect PSNR, "null" when there is none.
fn figure(f: Option<Figure>) -> String {
    match f {
        Some(Figure(x)) if x.is_finite() => format!("{x:.2}"),
        Some(Figure(x)) if x == f64::INFINITY => "\"inf\"".into(),
        _ => "null".into(),
    }
}

fn fmt(v: &serde_json::Value) -> String {
    if let Some(n) = v.as_u64() {
        return n.to_string();
    }
    match v.as_f64() {
        Some(x) => format!("{x:.2}"),
        None => v.to_string(),
    }
}
