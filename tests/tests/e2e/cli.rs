//! The `helmholtz` command line against the real server: simulate -> upload -> reconstruct ->
//! fetch, status, and pattern frames, each with `--json` output for scripts.

use std::process::Command;

use helmholtz_sim::Target;
use helmholtz_tests::{ServerProcess, binary, correlation, parse_npy};

/// `helmholtz --server <server> --json <args>`: its JSON output (the command must succeed).
pub(crate) fn helmholtz(server: &ServerProcess, args: &[&str]) -> serde_json::Value {
    let out = Command::new(binary("helmholtz"))
        .arg("--server")
        .arg(&server.base_url)
        .arg("--json")
        .env("HELMHOLTZ_SPOOL", server.data_dir.join("client-spool"))
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "helmholtz {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "{args:?}: not JSON ({e}): {}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

#[test]
fn simulate_reconstruct_fetch_and_status_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let png = dir.path().join("dual.png");
    let sim = helmholtz(
        &server,
        &[
            "simulate",
            "--scene",
            "double-slit",
            "--family",
            "bernoulli",
            "--width",
            "32",
            "--height",
            "32",
            "--count",
            "20000",
            "--seed",
            "3",
            "--snr-db",
            "30",
            "--session-id",
            "cli-slit",
            "--reconstruct",
            "dgi",
            "--wait",
            "--out",
            png.to_str().unwrap(),
        ],
    );
    assert!(png.exists(), "simulate --out wrote no file: {sim}");
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&png).unwrap()));
    let info = decoder.read_info().unwrap();
    assert_eq!((info.info().width, info.info().height), (32, 32));

    let npy = dir.path().join("dual.npy");
    helmholtz(
        &server,
        &[
            "fetch",
            "--session-id",
            "cli-slit",
            "--format",
            "npy",
            "--out",
            npy.to_str().unwrap(),
        ],
    );
    let (shape, image) = parse_npy(&std::fs::read(&npy).unwrap()).unwrap();
    assert_eq!(shape, vec![32, 32]);
    let truth: Vec<f64> = Target::builtin("double-slit", 32, 32)
        .unwrap()
        .transport(1.0)
        .iter()
        .map(|&v| v as f64)
        .collect();
    let r = correlation(&image, &truth);
    assert!(
        r > 0.9,
        "DGI from the CLI correlates {r:.3} with the double slit"
    );

    let status = helmholtz(&server, &["status", "--session-id", "cli-slit"]);
    // The older bare form still works and says the same.
    assert_eq!(helmholtz(&server, &["status", "cli-slit"]), status);
    let text = status.to_string();
    assert!(
        text.contains("20000") && text.contains("finished"),
        "status lacks rows or state: {status}"
    );

    let frames = dir.path().join("frames");
    let spec = r#"{"family":"hadamard","width":8,"height":8,"count":128,"ordering":"sequency"}"#;
    helmholtz(
        &server,
        &[
            "patterns",
            "--spec-json",
            spec,
            "--first",
            "0",
            "--count",
            "4",
            "--out",
            frames.to_str().unwrap(),
        ],
    );
    let mut written: Vec<_> = std::fs::read_dir(&frames)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    written.sort();
    assert_eq!(written.len(), 4, "{written:?}");
    // Frame 0 is P+ of the all-ones row: all white. Frame 1 is its P-: all black (a dark frame).
    let read = |i: usize| {
        let mut r = png::Decoder::new(std::io::BufReader::new(
            std::fs::File::open(frames.join(&written[i])).unwrap(),
        ))
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
    assert!(
        stderr.contains("no-such-session") && stderr.contains("not found"),
        "{stderr}"
    );
}

/// `helmholtz acquire` with rows arriving on stdin: a bad line stops it with the rows before it
/// kept (spooled, then uploaded); a re-run feeds the rest and finishes; the server holds exactly
/// the rows fed, each once.
#[test]
fn acquire_spools_rows_from_stdin_and_a_rerun_continues_after_a_bad_line() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let spool = dir.path().join("spool");
    let spec = r#"{"family":"bernoulli","width":8,"height":8,"count":300,"seed":1}"#;
    let acquire = |input: String| {
        let mut child = Command::new(binary("helmholtz"))
            .args([
                "--server",
                &server.base_url,
                "--spool",
                spool.to_str().unwrap(),
                "--json",
                "acquire",
            ])
            .args([
                "--session-id",
                "rig-stdin",
                "--spec-json",
                spec,
                "--channels",
                "a,b",
                "--finish",
                "--batch-rows",
                "64",
            ])
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        child
            .stdin
            .take()
            .unwrap()
            .write_all(input.as_bytes())
            .unwrap();
        child.wait_with_output().unwrap()
    };
    let line = |i: usize| format!("{i}.5, {}\n", i * 2);
    let mut first: String = (0..200).map(line).collect();
    first.push_str("# a comment\n\n7,x\n");
    let out = acquire(first);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("line 203, column 2") && stderr.contains("200 rows spooled"),
        "{stderr}"
    );

    let out = acquire((200..300).map(line).collect());
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json["spooled_before"], 200);
    assert_eq!(json["finished"], true);
    let url = server.url("/v1/sessions/rig-stdin/measurements.npy");
    let bytes = tokio::runtime::Runtime::new().unwrap().block_on(async {
        helmholtz_tests::http_get(url)
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap()
    });
    let (shape, values) = parse_npy(&bytes).unwrap();
    assert_eq!(shape, vec![300, 2]);
    let expected: Vec<f64> = (0..300)
        .flat_map(|i| [i as f64 + 0.5, (i * 2) as f64])
        .collect();
    assert_eq!(values, expected);
}

/// Logs written to a pipe or a file (journald, `2> log`) carry no terminal colour codes, from
/// the server and from the client.
#[test]
fn logs_off_a_terminal_have_no_colour_codes() {
    let dir = tempfile::tempdir().unwrap();
    let server = Command::new(binary("helmholtz-server"))
        .args(["migrate", "--data-dir"])
        .arg(dir.path().join("data"))
        .env("RUST_LOG", "debug")
        .output()
        .unwrap();
    assert!(server.status.success(), "{server:?}");
    let client = Command::new(binary("helmholtz"))
        .args(["--server", "http://127.0.0.1:9", "status"])
        .env("RUST_LOG", "debug")
        .output()
        .unwrap();
    for (who, stderr) in [("server", &server.stderr), ("client", &client.stderr)] {
        let text = String::from_utf8_lossy(stderr);
        assert!(
            text.contains("DEBUG"),
            "{who} logged nothing at debug: {text}"
        );
        let start: String = text.chars().take(300).collect();
        assert!(
            !text.contains('\u{1b}'),
            "{who} logs carry colour codes: {start:?}"
        );
    }
}

/// The text a person reads after `simulate --reconstruct auto --wait`: the model auto chose and
/// its weight, the held-out error, the report's warnings (here: too few rows for 64x64) and the
/// PSNR against the simulated scene; `status` shows the same report, not stale figures.
#[test]
fn text_output_says_what_the_report_knows() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(&dir.path().join("data"), 0, &[]).unwrap();
    let run = |args: &[&str]| {
        let out = Command::new(binary("helmholtz"))
            .arg("--server")
            .arg(&server.base_url)
            .env("HELMHOLTZ_SPOOL", server.data_dir.join("client-spool"))
            .args(args)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "helmholtz {args:?} failed:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8(out.stdout).unwrap()
    };
    // 64 x 64 from 120 Bernoulli rows (3 %): auto says the rows cannot support 64x64.
    let text = run(&[
        "simulate",
        "--scene",
        "camera",
        "--family",
        "bernoulli",
        "--width",
        "64",
        "--height",
        "64",
        "--count",
        "120",
        "--seed",
        "5",
        "--session-id",
        "cli-report",
        "--reconstruct",
        "auto",
        "--wait",
    ]);
    for want in [
        "auto: model ",
        " of lambda_max)",
        "held-out error ",
        "warning: too few rows for 64x64",
        "vs ground truth [bucket]: PSNR ",
        "after a gain/offset fit",
        " iterations, ",
    ] {
        assert!(text.contains(want), "{want:?} missing from:\n{text}");
    }
    let status = run(&["status", "--session-id", "cli-report"]);
    for want in ["auto: model ", "warning: too few rows for 64x64", "PSNR "] {
        assert!(status.contains(want), "{want:?} missing from:\n{status}");
    }
    // The job state carries the same warnings (REST and gRPC), for clients that never read
    // the report.
    let rt = tokio::runtime::Runtime::new().unwrap();
    let (rest, grpc) = rt.block_on(async {
        let list: serde_json::Value =
            helmholtz_tests::http_get(server.url("/v1/sessions/cli-report/reconstructions"))
                .await
                .unwrap()
                .json()
                .await
                .unwrap();
        let job = list["reconstructions"][0].clone();
        let id = job["id"].as_i64().unwrap();
        let mut c = server.grpc().await.unwrap();
        let grpc = c
            .get_reconstruction(helmholtz_proto::v1::ReconstructionRef {
                reconstruction_id: id,
            })
            .await
            .unwrap()
            .into_inner();
        (job, grpc)
    });
    let warnings: Vec<&str> = rest["warnings"]
        .as_array()
        .unwrap_or_else(|| panic!("no warnings in the job state: {rest}"))
        .iter()
        .filter_map(serde_json::Value::as_str)
        .collect();
    assert!(
        warnings
            .iter()
            .any(|w| w.starts_with("too few rows for 64x64")),
        "REST job state warnings: {warnings:?}"
    );
    assert_eq!(grpc.warnings, warnings, "gRPC and REST job states differ");

    // A linear inverse of noisy split pairs says how much of its image is noise: 10 % of the
    // Russian-doll pairs at 20 dB read noise, reconstructed zero-filled.
    let text = run(&[
        "simulate",
        "--scene",
        "camera",
        "--family",
        "hadamard",
        "--ordering",
        "russian-doll",
        "--width",
        "64",
        "--height",
        "64",
        "--count",
        "820",
        "--snr-db",
        "20",
        "--session-id",
        "cli-noisy",
        "--reconstruct",
        "zero_filled",
        "--wait",
    ]);
    assert!(
        text.contains("warning: the detector noise the pair sums show is "),
        "no noise warning in:\n{text}"
    );
}

/// `completions SHELL` prints a script that names the subcommands, for both binaries; bash
/// accepts it.
#[test]
fn both_binaries_print_shell_completions() {
    for (bin, subcommand) in [("helmholtz", "relight"), ("helmholtz-server", "worker")] {
        for shell in ["bash", "zsh", "fish", "powershell", "elvish"] {
            let out = Command::new(binary(bin))
                .args(["completions", shell])
                .output()
                .unwrap();
            assert!(out.status.success(), "{bin} completions {shell}: {out:?}");
            let script = String::from_utf8(out.stdout).unwrap();
            assert!(
                script.contains(subcommand) && script.contains(bin),
                "{bin}'s {shell} script names neither {subcommand} nor itself:\n{script}"
            );
        }
        let out = Command::new(binary(bin))
            .args(["completions", "bash"])
            .output()
            .unwrap();
        let path = std::env::temp_dir().join(format!("{bin}-{}.bash", std::process::id()));
        std::fs::write(&path, &out.stdout).unwrap();
        let checked = Command::new("bash").arg("-n").arg(&path).output().unwrap();
        let _ = std::fs::remove_file(&path);
        assert!(
            checked.status.success(),
            "bash -n refuses {bin}'s script: {}",
            String::from_utf8_lossy(&checked.stderr)
        );
        let bad = Command::new(binary(bin))
            .args(["completions", "tcsh"])
            .output()
            .unwrap();
        assert!(!bad.status.success(), "{bin} accepted an unknown shell");
    }
}
