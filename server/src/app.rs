//! Start-up: bind first (so the port is known, even for port 0), open the store, start the
//! workers, then serve gRPC and REST on the same address.

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use axum::Router;
use helmholtz_proto::v1::acquisition_server::AcquisitionServer;
use tonic::server::NamedService;
use tower::ServiceExt;
use tower_http::request_id::{
    MakeRequestUuid, PropagateRequestIdLayer, RequestId, SetRequestIdLayer,
};
use tower_http::trace::TraceLayer;

use crate::api::grpc::AcquisitionService;
use crate::api::{AppState, rest};
use crate::edge::EdgeConfig;
use crate::jobs::{PoolConfig, WorkerPool};
use crate::limits::Limits;
use crate::store::Store;

/// Everything the service needs to start.
#[derive(Clone, Debug)]
pub struct Config {
    /// Address for gRPC and REST together; port 0 picks a free port.
    pub listen: SocketAddr,
    /// Holds `helmholtz.sqlite` (and its WAL) when no `database_url` is given.
    pub data_dir: PathBuf,
    /// A PostgreSQL database shared with other processes (`postgres://...`), instead of the
    /// embedded SQLite.
    pub database_url: Option<String>,
    /// Most pooled connections to PostgreSQL.
    pub database_connections: u32,
    /// Reconstruction worker threads.
    pub workers: usize,
    /// Job lease length.
    pub lease: Duration,
    /// Caps on requests, sessions, labs and tokens.
    pub limits: Limits,
    /// Where to serve Prometheus metrics (`GET /metrics`); None: not served.
    pub metrics_listen: Option<SocketAddr>,
    /// Working-set budget of one camera-session reconstruction, bytes.
    pub worker_memory: usize,
    /// Decoded transport matrices kept in memory for relighting, bytes.
    pub transport_cache: usize,
    /// Camera pixels per shard of a transport job (any worker sharing the database takes one).
    pub transport_shard_pixels: usize,
    /// Timeouts, the connection cap, the shutdown deadline, TLS and CORS.
    pub edge: EdgeConfig,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            listen: "127.0.0.1:8080".parse().expect("address"),
            data_dir: PathBuf::from("helmholtz-data"),
            database_url: None,
            database_connections: 16,
            workers: std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(2),
            lease: Duration::from_secs(30),
            limits: Limits::default(),
            worker_memory: crate::recon::transport::DEFAULT_MEMORY_BUDGET,
            transport_cache: 2 << 30,
            transport_shard_pixels: crate::jobs::DEFAULT_TRANSPORT_SHARD_PIXELS,
            metrics_listen: None,
            edge: EdgeConfig::default(),
        }
    }
}

/// A bound, ready-to-run service.
pub struct Application {
    listener: tokio::net::TcpListener,
    addr: SocketAddr,
    router: Router,
    workers: WorkerPool,
    store: Store,
    edge: EdgeConfig,
    tls: Option<tokio_rustls::TlsAcceptor>,
    metrics: Option<(
        tokio::net::TcpListener,
        SocketAddr,
        metrics_exporter_prometheus::PrometheusHandle,
    )>,
}

impl Application {
    pub async fn build(config: Config) -> anyhow::Result<Application> {
        // Before binding: a bad certificate or key is refused with nothing listening.
        let tls = config
            .edge
            .tls
            .as_ref()
            .map(crate::edge::tls_acceptor)
            .transpose()?;
        let mut edge = config.edge.clone();
        edge.max_connections = crate::edge::connection_cap(edge.max_connections);
        let listener = tokio::net::TcpListener::bind(config.listen)
            .await
            .with_context(|| {
                format!(
                    "cannot listen on {} (try --listen 127.0.0.1:0 for any free port)",
                    config.listen
                )
            })?;
        let addr = listener.local_addr()?;
        // Metrics are always recorded: served on the main port to `metrics` tokens, and on a
        // listener of their own (no token) when asked.
        let recorder = crate::telemetry::recorder()?;
        let metrics = match config.metrics_listen {
            None => None,
            Some(at) => {
                let l = crate::telemetry::bind(at).await?;
                let a = l.local_addr()?;
                Some((l, a, recorder))
            }
        };
        let store = Store::connect(
            config.database_url.as_deref(),
            &config.data_dir,
            config.database_connections,
        )
        .await
        .with_context(|| match &config.database_url {
            Some(_) => "opening the PostgreSQL database (--database-url)".to_string(),
            None => format!("opening the database in {}", config.data_dir.display()),
        })?;
        let workers = WorkerPool::start(
            store.clone(),
            tokio::runtime::Handle::current(),
            PoolConfig {
                workers: config.workers,
                lease: config.lease,
                max_running_per_lab: config.limits.max_running_jobs_per_lab,
                memory_budget: config.worker_memory,
                process_memory: config.limits.memory_budget,
                transport_shard_pixels: config.transport_shard_pixels,
                ..PoolConfig::default()
            },
        );
        let state = AppState::new(store.clone(), workers.notifier(), config.limits.clone())
            .with_transport_cache(config.transport_cache)
            .with_transport_memory(config.worker_memory as u64);
        let (health_reporter, health_service) = tonic_health::server::health_reporter();
        health_reporter
            .set_serving::<AcquisitionServer<AcquisitionService>>()
            .await;
        let acquisition = AcquisitionService::new(state.clone()).into_server();
        // Server reflection (v1, and v1alpha for clients such as Python's grpcio-reflection
        // that know only it): the contract's schema, open like the health service (the .proto
        // files are public; every call of the service itself still needs a token).
        let reflection = || {
            tonic_reflection::server::Builder::configure()
                .register_encoded_file_descriptor_set(helmholtz_proto::v1::FILE_DESCRIPTOR_SET)
                .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        };
        let reflection_v1 = reflection()
            .build_v1()
            .map_err(|e| anyhow::anyhow!("gRPC reflection: {e}"))?;
        let reflection_v1alpha = reflection()
            .build_v1alpha()
            .map_err(|e| anyhow::anyhow!("gRPC reflection: {e}"))?;
        // REST bodies that stop arriving fail with 408 (gRPC streams are not cut here).
        let rest = rest::router(state).layer(axum::middleware::from_fn_with_state(
            edge.body_timeout,
            crate::edge::body_timeout,
        ));
        let router = rest
            .route_service(&format!("/{}/{{*rpc}}", <AcquisitionServer<AcquisitionService> as NamedService>::NAME), grpc_route(acquisition))
            .route_service(&format!("/{}/{{*rpc}}", health_name(&health_service)), grpc_route(health_service))
            .route_service(&format!("/{}/{{*rpc}}", health_name(&reflection_v1)), grpc_route(reflection_v1))
            .route_service(&format!("/{}/{{*rpc}}", health_name(&reflection_v1alpha)), grpc_route(reflection_v1alpha))
            .layer(axum::middleware::from_fn(crate::telemetry::record_latency))
            // Outermost first: set (or keep the client's) x-request-id, log in a span that
            // carries it, and copy it to the response (HTTP header / gRPC initial metadata).
            .layer(PropagateRequestIdLayer::x_request_id())
            .layer(TraceLayer::new_for_http().make_span_with(|request: &http::Request<_>| {
                let id = request
                    .extensions()
                    .get::<RequestId>()
                    .and_then(|id| id.header_value().to_str().ok())
                    .unwrap_or("-")
                    .to_string();
                tracing::info_span!("request", request_id = %id, method = %request.method(), path = %request.uri().path())
            }))
            .layer(SetRequestIdLayer::x_request_id(MakeRequestUuid))
            .layer(axum::middleware::map_response(nosniff));
        let router = match cors(&edge.cors_origins)? {
            Some(layer) => router.layer(layer),
            None => router,
        };
        Ok(Application {
            listener,
            addr,
            router,
            workers,
            store,
            edge,
            tls,
            metrics,
        })
    }

    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// `http://host:port` (`https://` with TLS): the address for the client's `--server`.
    pub fn base_url(&self) -> String {
        let scheme = if self.tls.is_some() { "https" } else { "http" };
        format!("{scheme}://{}", self.addr)
    }

    /// `http://host:port/metrics` when metrics are served.
    pub fn metrics_url(&self) -> Option<String> {
        self.metrics
            .as_ref()
            .map(|(_, a, _)| format!("http://{a}/metrics"))
    }

    pub fn store(&self) -> &Store {
        &self.store
    }

    /// Serves until `shutdown` resolves, then: stops accepting connections and lets requests
    /// in flight finish (an upload stream commits every chunk it has received; the client
    /// resumes the rest elsewhere or later) until the shutdown deadline, when every connection
    /// still open is cut (idle upload streams included), stops the workers (running jobs stop at their next
    /// check and give their lease back without spending an attempt), and closes the database.
    pub async fn run_until(
        self,
        shutdown: impl Future<Output = ()> + Send + 'static,
    ) -> anyhow::Result<()> {
        let Application {
            listener,
            router,
            workers,
            store,
            metrics,
            edge,
            tls,
            ..
        } = self;
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        // The metrics listener stops after the API: scrapes are short, so its own deadline is
        // at most a second (the total stays within the API's deadline plus one second).
        let metrics_edge = EdgeConfig {
            shutdown_deadline: edge.shutdown_deadline.min(Duration::from_secs(1)),
            max_connections: edge.max_connections.min(64),
            tls: None,
            ..edge.clone()
        };
        let metrics_task = metrics.map(|(l, _, handle)| {
            let mut rx = stop_rx.clone();
            tokio::spawn(crate::telemetry::serve(
                l,
                handle,
                store.clone(),
                metrics_edge,
                async move {
                    let _ = rx.wait_for(|s| *s).await;
                },
            ))
        });
        crate::edge::serve(listener, router, &edge, tls, shutdown).await;
        tracing::info!("no longer serving; stopping the workers");
        let _ = stop_tx.send(true);
        tokio::task::spawn_blocking(move || workers.shutdown()).await?;
        if let Some(t) = metrics_task {
            let _ = t.await;
        }
        store.close().await;
        tracing::info!("shut down cleanly");
        Ok(())
    }
}

/// Every HTTP response: browsers must not guess a content type other than the one we send.
pub(crate) async fn nosniff(mut response: axum::response::Response) -> axum::response::Response {
    response.headers_mut().insert(
        http::header::X_CONTENT_TYPE_OPTIONS,
        http::HeaderValue::from_static("nosniff"),
    );
    response
}

/// CORS: none unless origins are configured (`--cors-origin`), then exactly those origins.
fn cors(origins: &[String]) -> anyhow::Result<Option<tower_http::cors::CorsLayer>> {
    use http::{HeaderName, HeaderValue, Method, header};
    if origins.is_empty() {
        return Ok(None);
    }
    let allowed = origins
        .iter()
        .map(|o| {
            let o = o.trim_end_matches('/');
            let host = o
                .strip_prefix("https://")
                .or_else(|| o.strip_prefix("http://"));
            anyhow::ensure!(
                host.is_some_and(|h| !h.is_empty() && !h.contains('/')),
                "--cors-origin {o:?}: expected an origin such as https://lab.example.org"
            );
            HeaderValue::from_str(o)
                .map_err(|_| anyhow::anyhow!("--cors-origin {o:?}: not a valid header value"))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok(Some(
        tower_http::cors::CorsLayer::new()
            .allow_origin(allowed)
            .allow_methods([Method::GET, Method::POST, Method::DELETE])
            .allow_headers([
                header::AUTHORIZATION,
                header::CONTENT_TYPE,
                header::IF_NONE_MATCH,
                HeaderName::from_static("x-request-id"),
            ])
            .expose_headers([header::ETAG, HeaderName::from_static("x-request-id")])
            .max_age(Duration::from_secs(600)),
    ))
}

fn health_name<S: NamedService>(_: &S) -> &'static str {
    S::NAME
}

/// Adapts a tonic service to an axum route (tonic's own `Routes` does the same).
fn grpc_route<S>(
    svc: S,
) -> impl tower::Service<
    axum::extract::Request,
    Response = S::Response,
    Error = std::convert::Infallible,
    Future = impl Send + 'static,
> + Clone
+ Send
+ Sync
+ 'static
where
    S: tower::Service<http::Request<tonic::body::Body>, Error = std::convert::Infallible>
        + Clone
        + Send
        + Sync
        + 'static,
    S::Future: Send + 'static,
{
    svc.map_request(|req: axum::extract::Request| req.map(tonic::body::Body::new))
}
