//! The `helmholtz` binary without a server: help, offline simulation, and giving up cleanly when
//! nothing listens. (Everything that talks to a server is tested against the real server in the
//! workspace's tests/; this integration test also makes `cargo test --workspace` build the binary.)

use std::process::Command;
use std::time::{Duration, Instant};

use helmholtz_client::UploadOptions;
use helmholtz_client::measurements::read_measurements;

fn helmholtz() -> Command {
    Command::new(env!("CARGO_BIN_EXE_helmholtz"))
}

#[test]
fn help_names_every_command() {
    let out = helmholtz().arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    for command in [
        "simulate",
        "upload",
        "acquire",
        "status",
        "fetch",
        "reconstruct",
        "relight",
        "primal",
        "normals",
        "cancel",
        "patterns",
        "spool",
    ] {
        assert!(text.contains(command), "--help lacks {command}: {text}");
    }
}

#[test]
fn offline_simulation_writes_the_bucket_values() {
    let dir = tempfile::tempdir().unwrap();
    let values = dir.path().join("buckets.npy");
    let out = helmholtz()
        .args([
            "--json",
            "simulate",
            "--offline",
            "--scene",
            "usaf",
            "--family",
            "bernoulli",
        ])
        .args([
            "--width",
            "16",
            "--height",
            "16",
            "--count",
            "300",
            "--seed",
            "4",
            "--channels",
            "a,b",
        ])
        .arg("--values-out")
        .arg(&values)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let m = read_measurements(&values).unwrap();
    assert_eq!((m.rows, m.channels), (300, 2));
    assert!(m.values.iter().all(|v| v.is_finite() && *v > 0.0));
}

#[test]
fn a_bad_spec_is_a_clear_error() {
    let out = helmholtz()
        .args([
            "simulate",
            "--offline",
            "--scene",
            "usaf",
            "--family",
            "hadamard",
        ])
        .args(["--width", "12", "--height", "8", "--seed", "1"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("width") && stderr.contains("power of two"),
        "{stderr}"
    );
}

#[tokio::test]
async fn upload_gives_up_after_retry_for_when_nobody_listens() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let server = format!("http://127.0.0.1:{port}");
    let opts = UploadOptions {
        retry_for: Duration::from_millis(800),
        ..UploadOptions::default()
    };
    let started = Instant::now();
    let err = helmholtz_client::upload(&server, "x", 1, &[1.0; 10], &opts)
        .await
        .unwrap_err();
    let took = started.elapsed();
    assert!(
        took >= Duration::from_millis(800) && took < Duration::from_secs(10),
        "{took:?}"
    );
    let text = format!("{err:#}");
    assert!(
        text.contains("gave up") && text.contains("UNAVAILABLE"),
        "{text}"
    );
}
