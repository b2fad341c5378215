//! TLS end to end: the real server with `--tls-cert/--tls-key` (a CA and server certificate made
//! here with rcgen) serves gRPC and REST on one https port; the real `helmholtz` binary uploads,
//! reads status and fetches over it when told the lab's CA (`--ca-file`), and refuses with a
//! certificate error when not.

use std::path::Path;
use std::process::{Command, Output};

use helmholtz_tests::{ServerProcess, binary};
use rcgen::{
    BasicConstraints, CertificateParams, CertifiedIssuer, DnType, IsCa, KeyPair, KeyUsagePurpose,
};

/// Writes ca.pem, server.pem (for 127.0.0.1 and localhost, signed by the CA) and server.key.
fn make_pki(dir: &Path) {
    let mut ca = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca.distinguished_name
        .push(DnType::CommonName, "Helmholtz test lab CA");
    ca.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    let ca = CertifiedIssuer::self_signed(ca, KeyPair::generate().unwrap()).unwrap();
    let mut leaf =
        CertificateParams::new(vec!["127.0.0.1".to_string(), "localhost".to_string()]).unwrap();
    leaf.distinguished_name
        .push(DnType::CommonName, "helmholtz test server");
    let key = KeyPair::generate().unwrap();
    let cert = leaf.signed_by(&key, &ca).unwrap();
    std::fs::write(dir.join("ca.pem"), ca.pem()).unwrap();
    std::fs::write(dir.join("server.pem"), cert.pem()).unwrap();
    std::fs::write(dir.join("server.key"), key.serialize_pem()).unwrap();
}

fn helmholtz(server: &ServerProcess, ca: Option<&Path>, args: &[&str]) -> Output {
    let mut c = Command::new(binary("helmholtz"));
    c.arg("--server")
        .arg(&server.address)
        .arg("--token")
        .arg(&server.token)
        .arg("--json")
        .env("HELMHOLTZ_SPOOL", server.data_dir.join("client-spool"))
        .env_remove("HELMHOLTZ_CA_FILE");
    if let Some(ca) = ca {
        c.arg("--ca-file").arg(ca);
    }
    c.args(args).output().unwrap()
}

fn ok(out: Output, what: &str) -> serde_json::Value {
    assert!(
        out.status.success(),
        "{what} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "{what}: not JSON ({e}): {}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

#[test]
fn the_client_uploads_and_fetches_over_tls_with_the_labs_ca_and_refuses_without_it() {
    let dir = tempfile::tempdir().unwrap();
    make_pki(dir.path());
    let (cert, key, ca) = (
        dir.path().join("server.pem"),
        dir.path().join("server.key"),
        dir.path().join("ca.pem"),
    );
    let server = ServerProcess::start(
        &dir.path().join("data"),
        0,
        &[
            "--tls-cert",
            cert.to_str().unwrap(),
            "--tls-key",
            key.to_str().unwrap(),
        ],
    )
    .unwrap();
    assert!(
        server.address.starts_with("https://127.0.0.1:"),
        "{}",
        server.address
    );

    // Upload (gRPC over TLS, h2 by ALPN), reconstruct and save the image (REST over TLS).
    let png = dir.path().join("dual.png");
    let sim = ok(
        helmholtz(
            &server,
            Some(&ca),
            &[
                "simulate",
                "--scene",
                "double-slit",
                "--family",
                "bernoulli",
                "--width",
                "16",
                "--height",
                "16",
                "--count",
                "4000",
                "--session-id",
                "tls-1",
                "--reconstruct",
                "dgi",
                "--wait",
                "--out",
                png.to_str().unwrap(),
            ],
        ),
        "simulate over TLS",
    );
    assert!(png.exists(), "no image saved: {sim}");
    let status = ok(
        helmholtz(&server, Some(&ca), &["status", "tls-1"]),
        "status over TLS",
    );
    assert_eq!(status["session"]["committed_rows"], 4000, "{status}");
    let npy = dir.path().join("dual.npy");
    ok(
        helmholtz(
            &server,
            Some(&ca),
            &[
                "fetch",
                "--session",
                "tls-1",
                "--format",
                "npy",
                "--out",
                npy.to_str().unwrap(),
            ],
        ),
        "fetch over TLS",
    );
    let (shape, _) = helmholtz_tests::parse_npy(&std::fs::read(&npy).unwrap()).unwrap();
    assert_eq!(shape, vec![16, 16]);

    // The same through HELMHOLTZ_CA_FILE.
    let out = Command::new(binary("helmholtz"))
        .args([
            "--server",
            &server.address,
            "--token",
            &server.token,
            "--json",
        ])
        .args(["status", "tls-1"])
        .env("HELMHOLTZ_CA_FILE", &ca)
        .output()
        .unwrap();
    ok(out, "status with HELMHOLTZ_CA_FILE");

    // Without the lab's CA: a clear certificate error at once (not retried), for gRPC (creating
    // the session) and for REST (status, fetch).
    for args in [
        &[
            "simulate",
            "--scene",
            "double-slit",
            "--width",
            "8",
            "--height",
            "8",
            "--count",
            "100",
            "--session-id",
            "no-ca",
        ][..],
        &["status", "tls-1"][..],
        &[
            "fetch",
            "--session",
            "tls-1",
            "--format",
            "npy",
            "--out",
            "/dev/null",
        ][..],
    ] {
        let started = std::time::Instant::now();
        let out = helmholtz(&server, None, args);
        assert!(!out.status.success(), "{args:?} succeeded without the CA");
        // Transient failures are retried for 60 s; a refused certificate is not one.
        assert!(
            started.elapsed() < std::time::Duration::from_secs(30),
            "{args:?} retried a certificate error for {:?}",
            started.elapsed()
        );
        let err = String::from_utf8_lossy(&out.stderr).to_string()
            + &String::from_utf8_lossy(&out.stdout);
        assert!(
            err.to_ascii_lowercase().contains("certificate"),
            "{args:?} without the CA should say why: {err}"
        );
    }

    // Plain http to the TLS port is no way in either.
    let plain = server.address.replace("https://", "http://");
    let out = Command::new(binary("helmholtz"))
        .args(["--server", &plain, "--token", &server.token, "--json"])
        .args(["status", "tls-1"])
        .output()
        .unwrap();
    assert!(!out.status.success(), "plain http to the TLS port worked");
}

#[tokio::test]
async fn one_tls_port_speaks_http1_and_http2_by_alpn() {
    let dir = tempfile::tempdir().unwrap();
    make_pki(dir.path());
    let server = ServerProcess::start(
        &dir.path().join("data"),
        0,
        &[
            "--tls-cert",
            dir.path().join("server.pem").to_str().unwrap(),
            "--tls-key",
            dir.path().join("server.key").to_str().unwrap(),
        ],
    )
    .unwrap();
    let ca =
        reqwest::Certificate::from_pem(&std::fs::read(dir.path().join("ca.pem")).unwrap()).unwrap();
    let url = format!("{}/v1/sessions", server.address);
    helmholtz_client::tls::install_crypto_provider();
    for (client, version) in [
        (
            reqwest::Client::builder()
                .tls_certs_merge([ca.clone()])
                .http1_only()
                .build()
                .unwrap(),
            reqwest::Version::HTTP_11,
        ),
        (
            reqwest::Client::builder()
                .tls_certs_merge([ca.clone()])
                .build()
                .unwrap(),
            reqwest::Version::HTTP_2,
        ),
    ] {
        let r = client
            .get(&url)
            .bearer_auth(&server.token)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200);
        assert_eq!(r.version(), version);
        assert_eq!(r.headers()["x-content-type-options"], "nosniff");
    }
    // A client that does not trust the lab's CA is refused by its own verifier.
    let e = helmholtz_tests::http_client()
        .get(&url)
        .send()
        .await
        .unwrap_err();
    let chain = format!("{:?}", e).to_ascii_lowercase();
    assert!(chain.contains("certificate"), "{chain}");
}

#[test]
fn bad_tls_files_are_refused_at_start_naming_the_flag() {
    let dir = tempfile::tempdir().unwrap();
    make_pki(dir.path());
    let junk = dir.path().join("junk.pem");
    std::fs::write(&junk, "not a certificate\n").unwrap();
    let server_bin = binary("helmholtz-server");
    let cases: [(&Path, &Path, &str); 3] = [
        (&junk, &dir.path().join("server.key"), "--tls-cert"),
        (&dir.path().join("server.pem"), &junk, "--tls-key"),
        (
            &dir.path().join("server.pem"),
            &dir.path().join("missing.key"),
            "--tls-key",
        ),
    ];
    for (cert, key, flag) in cases {
        let out = Command::new(&server_bin)
            .args(["serve", "--listen", "127.0.0.1:0", "--tls-cert"])
            .arg(cert)
            .arg("--tls-key")
            .arg(key)
            .arg("--data-dir")
            .arg(dir.path().join("data"))
            .output()
            .unwrap();
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(flag), "{flag}: {err}");
        assert!(
            !String::from_utf8_lossy(&out.stdout).contains("listening"),
            "listened with bad TLS files"
        );
    }
    // One without the other is a usage error.
    let out = Command::new(&server_bin)
        .args(["serve", "--listen", "127.0.0.1:0", "--tls-cert"])
        .arg(dir.path().join("server.pem"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--tls-key"));
}
