//! The main job: `helmholtz-demo` runs the real service on a fresh SQLite file with the
//! simulated rigs, and re-running it on the same data is idempotent.

use std::process::Command;

fn run(data: &std::path::Path) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_helmholtz-demo"))
        .args(["--listen", "127.0.0.1:0", "--exit-after-demo", "--data-dir"])
        .arg(data)
        .output()
        .expect("running helmholtz-demo");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "helmholtz-demo failed\nstdout:\n{stdout}\nstderr:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// The PSNR (dB) the demo printed for `session`'s reconstruction.
fn psnr(stdout: &str, session: &str) -> f64 {
    let block = stdout
        .split("== ")
        .find(|b| b.starts_with(session))
        .unwrap();
    let at = block.find("PSNR ").expect("a PSNR line") + 5;
    block[at..]
        .split_whitespace()
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

#[test]
fn the_demo_reconstructs_its_sessions_and_reruns_idempotently() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let first = run(&data);
    assert!(
        first.starts_with("helmholtz-server listening on http://127.0.0.1:"),
        "{first}"
    );
    assert!(
        first.contains("uploaded 8192 rows (0 already stored)"),
        "{first}"
    );
    assert!(
        first.contains("uploaded 2048 frames (0 already stored)"),
        "{first}"
    );
    // The exact Hadamard inverse at 50 dB read noise; DGI of a double slit under drift.
    assert!(psnr(&first, "demo-usaf-hadamard") > 30.0, "{first}");
    assert!(psnr(&first, "demo-double-slit-dgi") > 12.0, "{first}");
    assert!(first.contains("/v1/reconstructions/3/relight"), "{first}");
    // Same data again: nothing is uploaded twice, new reconstructions are queued.
    let second = run(&data);
    assert!(
        second.contains("uploaded 8192 rows (8192 already stored)"),
        "{second}"
    );
    assert!(
        second.contains("uploaded 20000 rows (20000 already stored)"),
        "{second}"
    );
    assert!(
        second.contains("/v1/reconstructions/4/dual.png"),
        "{second}"
    );
}
