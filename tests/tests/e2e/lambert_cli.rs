//! The edge client's analytic Lambertian rigs against the real server, command line to image:
//! four photodiodes -> photometric stereo normals, colour filters -> an RGB composite, and a
//! camera -> T -> relit and predicted images through `helmholtz relight` / `helmholtz primal`.

use std::path::Path;
use std::process::Command;

use helmholtz_sim::Relief;
use helmholtz_tests::{ServerProcess, binary, parse_npy};

fn helmholtz(server: &ServerProcess, spool: &Path, args: &[&str]) -> String {
    let out = Command::new(binary("helmholtz"))
        .args([
            "--server",
            &server.address,
            "--token",
            &server.token,
            "--spool",
            spool.to_str().unwrap(),
        ])
        .args(args)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "helmholtz {args:?} failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

async fn latest(server: &ServerProcess, session: &str) -> i64 {
    let doc: serde_json::Value =
        helmholtz_tests::http_get(server.url(&format!("/v1/sessions/{session}")))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
    doc["latest_reconstruction"]
        .as_i64()
        .unwrap_or_else(|| panic!("no reconstruction: {doc}"))
}

#[tokio::test]
async fn four_photodiodes_give_normals_and_colour_filters_a_composite() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let spool = dir.path().join("spool");
    helmholtz(
        &server,
        &spool,
        &[
            "simulate",
            "--scene",
            "lambert",
            "--scene-seed",
            "3",
            "--detectors",
            "n,e,s,w",
            "--detector-elevation",
            "50",
            "--family",
            "hadamard",
            "--width",
            "32",
            "--height",
            "32",
            "--session-id",
            "ps",
            "--reconstruct",
            "direct",
            "--wait",
        ],
    );
    let id = latest(&server, "ps").await;
    let out = dir.path().join("normals.npy");
    helmholtz(
        &server,
        &spool,
        &[
            "normals",
            "--reconstruction",
            &id.to_string(),
            "--format",
            "npy",
            "--out",
            out.to_str().unwrap(),
        ],
    );
    let (shape, normals) = parse_npy(&std::fs::read(&out).unwrap()).unwrap();
    assert_eq!(shape, vec![32, 32, 3]);
    // Against the scene's true normals, over the pixels photometric stereo determined.
    let scene = Relief::demo(32, 32, 3);
    let mut angles: Vec<f64> = scene
        .normals()
        .iter()
        .enumerate()
        .filter_map(|(i, n)| {
            let got = &normals[3 * i..3 * i + 3];
            let len = got.iter().map(|v| v * v).sum::<f64>().sqrt();
            (len > 0.5).then(|| {
                (got.iter().zip(n).map(|(a, b)| a * b).sum::<f64>() / len)
                    .clamp(-1.0, 1.0)
                    .acos()
                    .to_degrees()
            })
        })
        .collect();
    angles.sort_by(f64::total_cmp);
    let determined = angles.len() as f64 / 1024.0;
    let median = angles[angles.len() / 2];
    // The scene has one diffuse bounce (interreflection), which the Lambertian model does not
    // know: where surfaces face each other (hemisphere and box on the ground) the normals tilt.
    // Most of the scene is open ground and sphere, so the median stays small (measured 0.25
    // degrees, 99 % of pixels determined, 90th percentile 4 degrees).
    eprintln!(
        "photometric stereo: {:.1} % of pixels determined, median angular error {median:.2} degrees, 90th percentile {:.2}",
        100.0 * determined,
        angles[angles.len() * 9 / 10]
    );
    assert!(
        determined > 0.8,
        "only {determined:.2} of the pixels got a normal"
    );
    assert!(median < 1.0, "median angular error {median:.2} degrees");
    let report: serde_json::Value = helmholtz_tests::http_get(
        server.url(&format!("/v1/reconstructions/{id}/photometric.json")),
    )
    .await
    .unwrap()
    .json()
    .await
    .unwrap();
    assert!(report.to_string().contains("interreflection"), "{report}");
    let png =
        helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{id}/normals.png")))
            .await
            .unwrap();
    assert_eq!(png.status(), 200);
    assert!(png.headers()["etag"].to_str().unwrap().starts_with('"'));
    // Composite needs colour channels: refused for n,e,s,w.
    let r =
        helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{id}/composite.png")))
            .await
            .unwrap();
    assert_eq!(r.status(), 409);

    helmholtz(
        &server,
        &spool,
        &[
            "simulate",
            "--scene",
            "lambert",
            "--scene-seed",
            "3",
            "--colour",
            "--family",
            "hadamard",
            "--width",
            "32",
            "--height",
            "32",
            "--session-id",
            "rgb",
            "--reconstruct",
            "direct",
            "--wait",
        ],
    );
    let id = latest(&server, "rgb").await;
    let bytes =
        helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{id}/composite.png")))
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap();
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes.to_vec()))
        .read_info()
        .unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(
        (info.width, info.height, info.color_type),
        (32, 32, png::ColorType::Rgb)
    );
    // The hemisphere's albedo is (0.85, 0.55, 0.45): red over green over blue at its top.
    let top = (0.42 * 32.0) as usize * 32 + (0.33 * 32.0) as usize;
    let (r, g, b) = (buf[3 * top], buf[3 * top + 1], buf[3 * top + 2]);
    assert!(r > g && g > b, "hemisphere top is ({r}, {g}, {b})");
    // Photometric stereo needs three directions that are not coplanar: three colour filters on
    // one detector are one direction.
    let r = helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{id}/normals.png")))
        .await
        .unwrap();
    assert_eq!(r.status(), 409);
    assert!(r.text().await.unwrap().contains("direction"));
}

#[tokio::test]
async fn a_simulated_camera_rig_is_relit_and_predicted_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let spool = dir.path().join("spool");
    helmholtz(
        &server,
        &spool,
        &[
            "simulate",
            "--scene",
            "lambert",
            "--camera",
            "12x10",
            "--camera-tilt",
            "25",
            "--frame-format",
            "u16",
            "--family",
            "hadamard",
            "--width",
            "16",
            "--height",
            "16",
            "--session-id",
            "cam",
            "--reconstruct",
            "transport",
            "--wait",
        ],
    );
    let id = latest(&server, "cam").await.to_string();
    let rec: serde_json::Value =
        helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{id}")))
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
    let err = rec["report"]["quality"]["transport_relative_error"]
        .as_f64()
        .unwrap();
    // u16 frames quantise each pixel to 1 count in ~60000 at the brightest; T from a complete set
    // inherits that, well under 1 %.
    assert!(err < 1e-2, "relative error of T {err}: {rec}");

    let relit = dir.path().join("relit.npy");
    helmholtz(
        &server,
        &spool,
        &[
            "relight",
            "--reconstruction",
            &id,
            "--disc",
            "6,5,3",
            "--format",
            "npy",
            "--out",
            relit.to_str().unwrap(),
        ],
    );
    let (shape, values) = parse_npy(&std::fs::read(&relit).unwrap()).unwrap();
    assert_eq!(shape, vec![16, 16]);
    assert!(values.iter().any(|&v| v > 0.0));
    let predicted = dir.path().join("frame.npy");
    let stdout = helmholtz(
        &server,
        &spool,
        &[
            "--json",
            "primal",
            "--reconstruction",
            &id,
            "--pattern-index",
            "7",
            "--format",
            "npy",
            "--out",
            predicted.to_str().unwrap(),
        ],
    );
    let (shape, _) = parse_npy(&std::fs::read(&predicted).unwrap()).unwrap();
    assert_eq!(shape, vec![10, 12]);
    assert!(
        stdout.contains("relative_error") || stdout.contains("relative error"),
        "{stdout}"
    );
}

#[tokio::test]
async fn a_camera_rigs_frames_upload_from_an_npy_file() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let spool = dir.path().join("spool");
    // 512 u16 frames of a 10x8 camera (Hadamard 16x16, complete), written as a real rig's
    // driver would: an NPY of shape (frames, height, width).
    let spec_json = r#"{"family":"hadamard","width":16,"height":16,"count":512,"seed":0,"ordering":"sequency"}"#;
    let spec: helmholtz_proto::PatternSpec = serde_json::from_str(spec_json).unwrap();
    let scene = Relief::demo(16, 16, 8);
    let view = scene.view(&helmholtz_sim::Camera::tilted(10, 8, 15.0));
    let generator = helmholtz_proto::PatternGenerator::new(&spec);
    let mut p = vec![0f32; 256];
    let counts_per_unit = 20000.0;
    let mut data = Vec::new();
    for i in 0..512 {
        generator.fill_values(i, &mut p);
        let p: Vec<f64> = p.iter().map(|&v| v as f64).collect();
        for v in view.render(&p) {
            data.extend_from_slice(
                &((v * counts_per_unit).round().clamp(0.0, 65535.0) as u16).to_le_bytes(),
            );
        }
    }
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    let mut header =
        "{'descr': '<u2', 'fortran_order': False, 'shape': (512, 8, 10), }".to_string();
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat(total.next_multiple_of(64) - total));
    header.push('\n');
    npy.extend_from_slice(&(header.len() as u16).to_le_bytes());
    npy.extend_from_slice(header.as_bytes());
    npy.extend_from_slice(&data);
    let (frames, spec_file) = (dir.path().join("frames.npy"), dir.path().join("spec.json"));
    std::fs::write(&frames, &npy).unwrap();
    std::fs::write(&spec_file, spec_json).unwrap();
    helmholtz(
        &server,
        &spool,
        &[
            "upload",
            "--session-id",
            "camfile",
            "--spec",
            spec_file.to_str().unwrap(),
            "--values",
            frames.to_str().unwrap(),
            "--finish",
        ],
    );
    // Stored exactly as in the file.
    let stored = helmholtz_tests::http_get(server.url("/v1/sessions/camfile/measurements.npy"))
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    assert_eq!(&stored[stored.len() - data.len()..], &data[..]);
    let doc: serde_json::Value = helmholtz_tests::http_get(server.url("/v1/sessions/camfile"))
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        doc["camera"],
        serde_json::json!({"width": 10, "height": 8, "format": "u16"})
    );
    // And T reconstructs from it: the full-camera dual image against the truth, in counts.
    let rec = helmholtz_client::request_reconstruction(
        &server.base_url,
        "camfile",
        "transport",
        &serde_json::json!({}),
    )
    .await
    .unwrap();
    let rec = helmholtz_client::wait_reconstruction(
        &server.base_url,
        rec.id,
        std::time::Duration::from_secs(120),
    )
    .await
    .unwrap();
    assert!(rec.is_done(), "{rec:?}");
    let npy =
        helmholtz_tests::http_get(server.url(&format!("/v1/reconstructions/{}/dual.npy", rec.id)))
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap();
    let (_, summed) = parse_npy(&npy).unwrap();
    let want: Vec<f64> = view
        .relight(&vec![1.0; 80])
        .iter()
        .map(|v| v * counts_per_unit)
        .collect();
    let e = helmholtz_tests::relative_error(&summed, &want);
    // Rounding to whole counts (about 0.3 count rms per pixel against ~10^3-10^4 counts).
    assert!(e < 1e-3, "relative error {e}");
}
