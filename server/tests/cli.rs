//! The binary's command line (this integration test also makes `cargo test --workspace` build
//! the `helmholtz-server` binary that the end-to-end tests in tests/ start).

use std::process::Command;

#[test]
fn help_names_every_command() {
    let out = Command::new(env!("CARGO_BIN_EXE_helmholtz-server"))
        .arg("--help")
        .output()
        .unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    for command in ["serve", "token"] {
        assert!(text.contains(command), "--help lacks {command}: {text}");
    }
    // The demo is its own binary (helmholtz-demo): the service does not link the client.
    assert!(!text.contains("demo"), "--help still offers a demo: {text}");
}

#[test]
fn unusable_listen_address_is_a_clear_error() {
    let out = Command::new(env!("CARGO_BIN_EXE_helmholtz-server"))
        .args(["serve", "--listen", "not-an-address"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--listen"));
}
