//! The `helmholtz` command line against the real server: simulate -> upload -> reconstruct ->
//! fetch, status, and pattern frames, each with `--json` output for scripts.

use std::process::Command;

use helmholtz_client::scene::Scene;
use helmholtz_tests::{ServerProcess, binary, correlation, parse_npy};

fn helmholtz(server: &ServerProcess, args: &[&str]) -> serde_json::Value {
    let out = Command::new(binary("helmholtz"))
        .arg("--server")
        .arg(&server.base_url)
        .arg("--json")
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "helmholtz {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{args:?}: not JSON ({e}): {}", String::from_utf8_lossy(&out.stdout)))
}

#[test]
fn simulate_reconstruct_fetch_and_status_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let png = dir.path().join("dual.png");
    let sim = helmholtz(
        &server,
        &[
            "simulate", "--scene", "double-slit", "--family", "bernoulli", "--width", "32", "--height", "32",
            "--count", "20000", "--seed", "3", "--snr-db", "30", "--session-id", "cli-slit",
            "--reconstruct", "dgi", "--wait", "--out", png.to_str().unwrap(),
        ],
    );
    assert!(png.exists(), "simulate --out wrote no file: {sim}");
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&png).unwrap()));
    let info = decoder.read_info().unwrap();
    assert_eq!((info.info().width, info.info().height), (32, 32));

    let npy = dir.path().join("dual.npy");
    helmholtz(&server, &["fetch", "--session", "cli-slit", "--format", "npy", "--out", npy.to_str().unwrap()]);
    let (shape, image) = parse_npy(&std::fs::read(&npy).unwrap()).unwrap();
    assert_eq!(shape, vec![32, 32]);
    let truth: Vec<f64> = Scene::builtin("double-slit", 32, 32).unwrap().transport(1.0).iter().map(|&v| v as f64).collect();
    let r = correlation(&image, &truth);
    assert!(r > 0.9, "DGI from the CLI correlates {r:.3} with the double slit");

    let status = helmholtz(&server, &["status", "cli-slit"]);
    let text = status.to_string();
    assert!(text.contains("20000") && text.contains("finished"), "status lacks rows or state: {status}");

    let frames = dir.path().join("frames");
    let spec = r#"{"family":"hadamard","width":8,"height":8,"count":128,"ordering":"sequency"}"#;
    helmholtz(&server, &["patterns", "--spec-json", spec, "--first", "0", "--count", "4", "--out", frames.to_str().unwrap()]);
    let mut written: Vec<_> = std::fs::read_dir(&frames).unwrap().map(|e| e.unwrap().file_name()).collect();
    written.sort();
    assert_eq!(written.len(), 4, "{written:?}");
    // Frame 0 is P+ of the all-ones row: all white. Frame 1 is its P-: all black (a dark frame).
    let read = |i: usize| {
        let mut r = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(frames.join(&written[i])).unwrap()))
            .read_info()
            .unwrap();
        let mut buf = vec![0; r.output_buffer_size().unwrap()];
        r.next_frame(&mut buf).unwrap();
        buf
    };
    assert!(read(0).iter().all(|&v| v == 255));
    assert!(read(1).iter().all(|&v| v == 0));
}

#[test]
fn command_line_errors_are_clear_and_exit_non_zero() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let out = Command::new(binary("helmholtz"))
        .args(["--server", &server.base_url, "status", "no-such-session"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("no-such-session") && stderr.contains("not found"), "{stderr}");
}
