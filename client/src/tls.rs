//! `https://` servers: certificates are verified against the system's roots, plus a lab's own
//! CA when one is trusted with [`trust_ca_file`] (the command line's `--ca-file`, env
//! `HELMHOLTZ_CA_FILE`). `http://` addresses are unaffected.
//!
//! The trusted CA is process-wide (like the system roots): every gRPC and REST call made after
//! [`trust_ca_file`] trusts it.

use std::path::Path;
use std::sync::{Arc, RwLock};

use anyhow::Context;

static EXTRA_CA: RwLock<Option<Arc<Vec<u8>>>> = RwLock::new(None);

/// Trusts the PEM CA certificate(s) in `path` for `https://` servers, besides the system roots.
/// Fails (and trusts nothing new) when the file holds no PEM certificate.
pub fn trust_ca_file(path: &Path) -> anyhow::Result<()> {
    use rustls_pki_types::CertificateDer;
    use rustls_pki_types::pem::PemObject;
    let pem = std::fs::read(path)
        .with_context(|| format!("--ca-file {}: cannot read", path.display()))?;
    let certs = CertificateDer::pem_slice_iter(&pem)
        .collect::<Result<Vec<_>, _>>()
        .with_context(|| format!("--ca-file {}: not a PEM certificate file", path.display()))?;
    anyhow::ensure!(
        !certs.is_empty(),
        "--ca-file {}: holds no PEM certificate (-----BEGIN CERTIFICATE-----)",
        path.display()
    );
    *EXTRA_CA.write().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(pem));
    Ok(())
}

/// The trusted extra CA certificates (PEM), if any.
pub fn extra_ca() -> Option<Arc<Vec<u8>>> {
    EXTRA_CA.read().unwrap_or_else(|e| e.into_inner()).clone()
}

/// True for an `https://` address.
pub fn is_https(server: &str) -> bool {
    server
        .get(..8)
        .is_some_and(|s| s.eq_ignore_ascii_case("https://"))
}

/// The gRPC client's TLS settings: system roots plus the trusted CA.
pub(crate) fn grpc_config() -> tonic::transport::ClientTlsConfig {
    let config = tonic::transport::ClientTlsConfig::new().with_native_roots();
    match extra_ca() {
        Some(pem) => config.ca_certificate(tonic::transport::Certificate::from_pem(pem.as_slice())),
        None => config,
    }
}

/// Installs ring as rustls's process-wide crypto provider, unless one is installed already. The
/// project builds rustls with ring alone (no aws-lc C build); the REST client (reqwest) then
/// needs a provider installed before any client is built, which this does (idempotent, cheap).
pub fn install_crypto_provider() {
    // Err means a provider is installed already: that one stays.
    let _ = rustls::crypto::ring::default_provider().install_default();
}

/// Adds the trusted CA to a REST client (reqwest verifies with the platform's roots).
pub(crate) fn http_roots(
    builder: reqwest::ClientBuilder,
) -> anyhow::Result<reqwest::ClientBuilder> {
    install_crypto_provider();
    Ok(match extra_ca() {
        Some(pem) => builder.tls_certs_merge(
            reqwest::Certificate::from_pem_bundle(&pem).context("--ca-file: bad PEM")?,
        ),
        None => builder,
    })
}

/// True when `error` (or anything in its source chain) is a refused server certificate: an
/// unknown issuer, a name mismatch, an expired certificate. Waiting does not fix those, so
/// callers give up at once instead of retrying.
pub fn is_certificate_error(error: &(dyn std::error::Error + 'static)) -> bool {
    let mut next = Some(error);
    while let Some(e) = next {
        let inner = e
            .downcast_ref::<std::io::Error>()
            .and_then(|io| io.get_ref())
            .map(|i| i as &(dyn std::error::Error + 'static));
        for candidate in [Some(e), inner].into_iter().flatten() {
            if let Some(r) = candidate.downcast_ref::<rustls::Error>()
                && matches!(
                    r,
                    rustls::Error::InvalidCertificate(_) | rustls::Error::NoCertificatesPresented
                )
            {
                return true;
            }
        }
        next = e.source();
    }
    false
}

/// A readable cause for a failed connection: the innermost error of the chain names what
/// went wrong (e.g. "invalid peer certificate: UnknownIssuer"), the outer ones rarely do.
pub fn root_cause(error: &(dyn std::error::Error + 'static)) -> String {
    let mut cause = error;
    while let Some(next) = cause.source() {
        cause = next;
    }
    cause.to_string()
}
