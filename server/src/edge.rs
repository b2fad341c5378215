//! The network edge: our own accept loop in front of the router (axum::serve exposes none of
//! this), so that no client can hold the server's sockets or its shutdown forever.
//!
//! - **Connection cap**: a semaphore of `max_connections` permits is taken *before* `accept`;
//!   beyond it new connections wait in the kernel's backlog (logged once per saturation) instead
//!   of failing with EMFILE near the open-file limit.
//! - **Header timeout**: a connection must deliver its first request's headers (after the TLS
//!   handshake and the HTTP/2 preface, all within the same budget) within `header_timeout`, and
//!   every later HTTP/1 request head too (hyper's `header_read_timeout`); else it is closed.
//! - **Body timeout** (REST only, see [`body_timeout`]): a request body that stops arriving for
//!   `body_timeout` fails the request with 408.
//! - **TLS** (rustls, ALPN `h2` and `http/1.1`): REST and gRPC on the same port.
//! - **Shutdown deadline**: on shutdown the loop stops accepting, asks every connection to finish
//!   gracefully (requests in flight complete), and after `shutdown_deadline` cuts every connection
//!   still open, idle upload streams included.

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::Context;
use axum::Router;
use axum::body::Body;
use hyper::body::Incoming;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto::Builder;
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Semaphore, watch};
use tokio::task::JoinSet;
use tower::ServiceExt;

/// Edge settings (the `serve` flags `--header-timeout-secs`, `--body-timeout-secs`,
/// `--max-connections`, `--shutdown-deadline-secs`, `--tls-cert`/`--tls-key`, `--cors-origin`).
#[derive(Clone, Debug)]
pub struct EdgeConfig {
    /// Time a connection has to send a complete request head (first request: from accept,
    /// including the TLS handshake and the HTTP/2 preface).
    pub header_timeout: Duration,
    /// Longest pause between two pieces of a REST request body.
    pub body_timeout: Duration,
    /// Most connections open at once; more wait to be accepted.
    pub max_connections: usize,
    /// After a shutdown signal: how long requests in flight may take before every connection
    /// still open is cut.
    pub shutdown_deadline: Duration,
    /// PEM certificate chain and private key: serve https (REST and gRPC) instead of http.
    pub tls: Option<TlsFiles>,
    /// Origins allowed by CORS (`Access-Control-Allow-Origin`); empty: no CORS headers at all.
    pub cors_origins: Vec<String>,
}

impl Default for EdgeConfig {
    fn default() -> Self {
        EdgeConfig {
            header_timeout: Duration::from_secs(10),
            body_timeout: Duration::from_secs(30),
            max_connections: 1024,
            shutdown_deadline: Duration::from_secs(10),
            tls: None,
            cors_origins: Vec::new(),
        }
    }
}

/// The PEM files of `--tls-cert` and `--tls-key`.
#[derive(Clone, Debug)]
pub struct TlsFiles {
    pub cert: PathBuf,
    pub key: PathBuf,
}

/// Loads the certificate chain and key into a TLS acceptor offering `h2` and `http/1.1`.
pub fn tls_acceptor(files: &TlsFiles) -> anyhow::Result<tokio_rustls::TlsAcceptor> {
    use rustls_pki_types::pem::PemObject;
    use rustls_pki_types::{CertificateDer, PrivateKeyDer};
    let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(&files.cert)
        .with_context(|| format!("--tls-cert {}: cannot read", files.cert.display()))?
        .collect::<Result<_, _>>()
        .with_context(|| {
            format!(
                "--tls-cert {}: not a PEM certificate chain",
                files.cert.display()
            )
        })?;
    anyhow::ensure!(
        !certs.is_empty(),
        "--tls-cert {}: holds no PEM certificate (-----BEGIN CERTIFICATE-----)",
        files.cert.display()
    );
    let key = PrivateKeyDer::from_pem_file(&files.key).with_context(|| {
        format!(
            "--tls-key {}: no PEM private key in it (PKCS#8, PKCS#1 or SEC1)",
            files.key.display()
        )
    })?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .context("TLS protocol versions")?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .with_context(|| {
            format!(
                "--tls-cert {} and --tls-key {} do not make a usable pair",
                files.cert.display(),
                files.key.display()
            )
        })?;
    config.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
    Ok(tokio_rustls::TlsAcceptor::from(Arc::new(config)))
}

/// Raises the soft open-file limit to the hard one (each connection holds a descriptor) and
/// returns the limit now in force (None where it cannot be read).
pub fn raise_open_file_limit() -> Option<u64> {
    #[cfg(unix)]
    unsafe {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) != 0 {
            return None;
        }
        if limit.rlim_cur < limit.rlim_max {
            let raised = libc::rlimit {
                rlim_cur: limit.rlim_max,
                rlim_max: limit.rlim_max,
            };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &raised) == 0 {
                limit.rlim_cur = limit.rlim_max;
            }
        }
        #[allow(clippy::unnecessary_cast)] // rlim_t is not u64 everywhere
        Some(limit.rlim_cur as u64)
    }
    #[cfg(not(unix))]
    None
}

/// Descriptors kept free of connections: the SQLite pool, its WAL, the metrics listener, logs.
const RESERVED_FDS: u64 = 64;

/// `requested` connections, lowered (with a warning) so they fit under the open-file limit.
pub fn connection_cap(requested: usize) -> usize {
    match raise_open_file_limit() {
        Some(limit) if (requested as u64).saturating_add(RESERVED_FDS) > limit => {
            let cap = limit.saturating_sub(RESERVED_FDS).max(1) as usize;
            tracing::warn!(
                requested,
                open_file_limit = limit,
                cap,
                "--max-connections lowered to fit under the open-file limit"
            );
            cap
        }
        _ => requested.max(1),
    }
}

/// Wraps every request body in an idle timeout: a body that sends nothing for `timeout` fails
/// with [`tower_http::timeout::TimeoutError`] (the REST handlers answer 408).
pub async fn body_timeout(
    axum::extract::State(timeout): axum::extract::State<Duration>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> axum::response::Response {
    let request =
        request.map(|body| Body::new(tower_http::timeout::TimeoutBody::new(timeout, body)));
    next.run(request).await
}

/// Serves `router` on `listener` until `shutdown` resolves, then drains (see the module doc).
pub async fn serve(
    listener: TcpListener,
    router: Router,
    config: &EdgeConfig,
    tls: Option<tokio_rustls::TlsAcceptor>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) {
    let cap = config.max_connections.max(1);
    let permits = Arc::new(Semaphore::new(cap));
    let (graceful_tx, graceful_rx) = watch::channel(false);
    let (cut_tx, cut_rx) = watch::channel(false);
    let mut builder = Builder::new(TokioExecutor::new());
    builder
        .http1()
        .timer(TokioTimer::new())
        .header_read_timeout(config.header_timeout);
    builder
        .http2()
        .timer(TokioTimer::new())
        .enable_connect_protocol()
        // A peer that stops answering pings (gone without a FIN) is dropped.
        .keep_alive_interval(Some(Duration::from_secs(20)))
        .keep_alive_timeout(Duration::from_secs(20));
    let shared = Arc::new(Shared {
        builder,
        router,
        tls,
        header_timeout: config.header_timeout,
    });
    let mut connections = JoinSet::new();
    // Logged when the cap is reached, and again only once 10% of it is free (no flapping at the
    // boundary) or a minute has passed.
    let mut saturated = false;
    let mut last_warning: Option<tokio::time::Instant> = None;
    let relief = (cap / 10).max(1);
    tokio::pin!(shutdown);
    loop {
        while connections.try_join_next().is_some() {}
        if permits.available_permits() == 0
            && (!saturated || last_warning.is_none_or(|t| t.elapsed() >= Duration::from_secs(60)))
        {
            saturated = true;
            last_warning = Some(tokio::time::Instant::now());
            tracing::warn!(
                max_connections = cap,
                "connection cap reached: new connections wait to be accepted"
            );
        }
        let permit = tokio::select! {
            _ = &mut shutdown => break,
            p = permits.clone().acquire_owned() => p.expect("semaphore never closed"),
        };
        if saturated && permits.available_permits() >= relief {
            saturated = false;
            tracing::info!(max_connections = cap, "below the connection cap again");
        }
        let (stream, peer) = tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                Err(e) => {
                    // EMFILE/ENFILE and friends: back off instead of spinning; never give up.
                    if !is_connection_error(&e) {
                        tracing::error!(error = %e, "accept failed; retrying in 100 ms");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                    continue;
                }
            },
        };
        connections.spawn(connection(
            stream,
            peer,
            shared.clone(),
            graceful_rx.clone(),
            cut_rx.clone(),
            permit,
        ));
    }
    drop(listener);
    let _ = graceful_tx.send(true);
    while connections.try_join_next().is_some() {}
    if connections.is_empty() {
        return;
    }
    tracing::info!(
        open = connections.len(),
        deadline_secs = config.shutdown_deadline.as_secs_f64(),
        "stopped accepting; letting requests in flight finish"
    );
    let drained = tokio::time::timeout(config.shutdown_deadline, async {
        while connections.join_next().await.is_some() {}
    })
    .await;
    if drained.is_err() {
        tracing::warn!(
            open = connections.len(),
            "shutdown deadline passed: cutting the connections still open"
        );
        let _ = cut_tx.send(true);
        if tokio::time::timeout(Duration::from_secs(1), async {
            while connections.join_next().await.is_some() {}
        })
        .await
        .is_err()
        {
            connections.abort_all();
            while connections.join_next().await.is_some() {}
        }
    }
}

struct Shared {
    builder: Builder<TokioExecutor>,
    router: Router,
    tls: Option<tokio_rustls::TlsAcceptor>,
    header_timeout: Duration,
}

fn is_connection_error(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::ConnectionRefused
            | std::io::ErrorKind::ConnectionAborted
            | std::io::ErrorKind::ConnectionReset
    )
}

async fn connection(
    stream: TcpStream,
    peer: SocketAddr,
    shared: Arc<Shared>,
    graceful: watch::Receiver<bool>,
    cut: watch::Receiver<bool>,
    _permit: tokio::sync::OwnedSemaphorePermit,
) {
    let _ = stream.set_nodelay(true);
    let started = tokio::time::Instant::now();
    match &shared.tls {
        None => serve_io(stream, peer, &shared, started, graceful, cut).await,
        Some(acceptor) => {
            match tokio::time::timeout(shared.header_timeout, acceptor.accept(stream)).await {
                Ok(Ok(tls)) => serve_io(tls, peer, &shared, started, graceful, cut).await,
                Ok(Err(e)) => tracing::debug!(%peer, error = %e, "TLS handshake failed"),
                Err(_) => tracing::debug!(%peer, "no TLS handshake within the header timeout"),
            }
        }
    }
}

async fn serve_io<I>(
    io: I,
    peer: SocketAddr,
    shared: &Shared,
    started: tokio::time::Instant,
    mut graceful: watch::Receiver<bool>,
    mut cut: watch::Receiver<bool>,
) where
    I: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    let seen = Arc::new(AtomicBool::new(false));
    let flag = seen.clone();
    let service = shared
        .router
        .clone()
        .map_request(move |request: http::Request<Incoming>| {
            flag.store(true, Ordering::Relaxed);
            request.map(Body::new)
        });
    let conn = shared
        .builder
        .serve_connection_with_upgrades(TokioIo::new(io), TowerToHyperService::new(service));
    tokio::pin!(conn);
    let first_request = tokio::time::sleep_until(started + shared.header_timeout);
    tokio::pin!(first_request);
    let mut waiting_first = true;
    let mut draining = false;
    loop {
        tokio::select! {
            result = conn.as_mut() => {
                if let Err(e) = result {
                    tracing::debug!(%peer, error = %e, "connection ended with an error");
                }
                return;
            }
            _ = &mut first_request, if waiting_first => {
                waiting_first = false;
                if !seen.load(Ordering::Relaxed) {
                    tracing::debug!(%peer, "no complete request head within the header timeout: closing");
                    return;
                }
            }
            _ = graceful.wait_for(|stop| *stop), if !draining => {
                draining = true;
                conn.as_mut().graceful_shutdown();
            }
            _ = cut.wait_for(|cut| *cut) => {
                tracing::debug!(%peer, "cut at the shutdown deadline");
                return;
            }
        }
    }
}
