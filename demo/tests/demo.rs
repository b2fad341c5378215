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

/// The lines the demo prints for a user to paste (the curl and `helmholtz` commands after
/// "e.g.", "relight:" and "or:") work as printed, run by a shell against the demo while it
/// serves: the real tokens, JSON sent as JSON, images written.
#[test]
fn the_demo_s_printed_hints_work_when_pasted() {
    use std::io::{BufRead, BufReader};
    let dir = tempfile::tempdir().unwrap();
    let mut demo = Command::new(env!("CARGO_BIN_EXE_helmholtz-demo"))
        .args(["--listen", "127.0.0.1:0", "--data-dir"])
        .arg(dir.path().join("data"))
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("running helmholtz-demo");
    let mut printed = Vec::new();
    for line in BufReader::new(demo.stdout.take().unwrap()).lines() {
        let line = line.unwrap();
        let serving = line.starts_with("Serving on");
        printed.push(line);
        if serving {
            break;
        }
    }
    let text = printed.join("\n");
    // The client binary sits beside the demo's (`cargo test --workspace` builds both).
    let bin_dir = std::path::Path::new(env!("CARGO_BIN_EXE_helmholtz-demo"))
        .parent()
        .unwrap()
        .to_path_buf();
    assert!(
        bin_dir.join("helmholtz").exists(),
        "the client binary is missing beside helmholtz-demo: run `cargo test --workspace`"
    );
    let path = format!(
        "{}:{}",
        bin_dir.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let commands: Vec<&str> = printed
        .iter()
        .filter_map(|l| {
            let l = l.trim_start();
            ["e.g.", "relight:", "or:"]
                .iter()
                .find_map(|p| l.strip_prefix(p))
                .map(str::trim)
                .or_else(|| l.starts_with("helmholtz --server").then_some(l))
        })
        .collect();
    assert_eq!(commands.len(), 4, "printed hints: {commands:?}\n{text}");
    let work = tempfile::tempdir().unwrap();
    for command in &commands {
        let out = Command::new("sh")
            .args(["-c", command])
            .current_dir(work.path())
            .env("PATH", &path)
            .env_remove("HELMHOLTZ_TOKEN")
            .output()
            .expect("running sh (and curl: Debian's curl package)");
        assert!(
            out.status.success(),
            "the printed line failed when pasted: {command}\nstdout: {}\nstderr: {}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        if command.starts_with("curl") && command.ends_with("/v1/sessions") {
            let body = String::from_utf8_lossy(&out.stdout);
            assert!(body.contains("demo-lambert-camera"), "{body}");
        }
        if command.contains("relit.png") {
            let png = std::fs::read(work.path().join("relit.png")).expect("relit.png written");
            assert!(png.starts_with(b"\x89PNG"), "{command}: not a PNG");
            std::fs::remove_file(work.path().join("relit.png")).unwrap();
        }
    }
    let _ = Command::new("kill")
        .args(["-TERM", &demo.id().to_string()])
        .status();
    let status = demo.wait().unwrap();
    assert!(status.success(), "the demo exited {status:?} after SIGTERM");
}
