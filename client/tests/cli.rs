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

/// `helmholtz patterns` writes every frame of the spec by default (from `--first` on), as PNGs
/// and, with `--npy`, as one float32 stack equal to the generator's values; it needs an output.
#[test]
fn patterns_writes_every_frame_and_an_npy_stack() {
    let dir = tempfile::tempdir().unwrap();
    let spec_json = r#"{"family":"speckle","width":8,"height":4,"count":12,"seed":3,"grain":2}"#;
    let (frames, stack) = (dir.path().join("frames"), dir.path().join("stack.npy"));
    let out = helmholtz()
        .args(["--json", "patterns", "--spec-json", spec_json, "--out"])
        .arg(&frames)
        .arg("--npy")
        .arg(&stack)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(std::fs::read_dir(&frames).unwrap().count(), 12);
    let (header, values) =
        helmholtz_proto::npy::decode_f32(&std::fs::read(&stack).unwrap()).unwrap();
    assert_eq!(header.shape_text(), "(12, 4, 8)");
    let spec: helmholtz_proto::PatternSpec = serde_json::from_str(spec_json).unwrap();
    let generator = helmholtz_proto::PatternGenerator::new(&spec);
    let mut want = vec![0f32; 32];
    for i in 0..12 {
        generator.fill_values(i as u64, &mut want);
        assert_eq!(&values[i * 32..(i + 1) * 32], &want[..], "frame {i}");
    }
    // From --first to the end by default.
    let tail = dir.path().join("tail.npy");
    let out = helmholtz()
        .args([
            "patterns",
            "--spec-json",
            spec_json,
            "--first",
            "9",
            "--npy",
        ])
        .arg(&tail)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (header, rest) = helmholtz_proto::npy::decode_f32(&std::fs::read(&tail).unwrap()).unwrap();
    assert_eq!(header.shape_text(), "(3, 4, 8)");
    assert_eq!(rest, values[9 * 32..]);
    // Without an output it says what to give.
    let out = helmholtz()
        .args(["patterns", "--spec-json", spec_json])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("--out") && stderr.contains("--npy"),
        "{stderr}"
    );
}
