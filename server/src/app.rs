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
use tower_http::trace::TraceLayer;

use crate::api::grpc::AcquisitionService;
use crate::api::{AppState, rest};
use crate::jobs::{PoolConfig, WorkerPool};
use crate::store::Store;

/// Everything the service needs to start.
#[derive(Clone, Debug)]
pub struct Config {
    /// Address for gRPC and REST together; port 0 picks a free port.
    pub listen: SocketAddr,
    /// Holds `helmholtz.sqlite` (and its WAL).
    pub data_dir: PathBuf,
    /// Reconstruction worker threads.
    pub workers: usize,
    /// Job lease length.
    pub lease: Duration,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            listen: "127.0.0.1:8080".parse().expect("address"),
            data_dir: PathBuf::from("helmholtz-data"),
            workers: std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2),
            lease: Duration::from_secs(30),
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
}

impl Application {
    pub async fn build(config: Config) -> anyhow::Result<Application> {
        let listener = tokio::net::TcpListener::bind(config.listen)
            .await
            .with_context(|| format!("cannot listen on {} (try --listen 127.0.0.1:0 for any free port)", config.listen))?;
        let addr = listener.local_addr()?;
        let store = Store::open(&config.data_dir)
            .await
            .with_context(|| format!("opening the database in {}", config.data_dir.display()))?;
        let workers = WorkerPool::start(
            store.clone(),
            tokio::runtime::Handle::current(),
            PoolConfig { workers: config.workers, lease: config.lease, ..PoolConfig::default() },
        );
        let state = AppState::new(store.clone(), workers.notifier());
        let (health_reporter, health_service) = tonic_health::server::health_reporter();
        health_reporter.set_serving::<AcquisitionServer<AcquisitionService>>().await;
        let acquisition = AcquisitionService::new(state.clone()).into_server();
        let router = rest::router(state)
            .route_service(&format!("/{}/{{*rpc}}", <AcquisitionServer<AcquisitionService> as NamedService>::NAME), grpc_route(acquisition))
            .route_service(&format!("/{}/{{*rpc}}", health_name(&health_service)), grpc_route(health_service))
            .layer(TraceLayer::new_for_http());
        Ok(Application { listener, addr, router, workers, store })
    }

    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// `http://host:port`: the address for the client's `--server`.
    pub fn base_url(&self) -> String {
        format!("http://{}", self.addr)
    }

    pub fn store(&self) -> &Store {
        &self.store
    }

    /// Serves until `shutdown` resolves, then stops the workers (running jobs give their lease
    /// back) and closes the database.
    pub async fn run_until(self, shutdown: impl Future<Output = ()> + Send + 'static) -> anyhow::Result<()> {
        let Application { listener, router, workers, store, .. } = self;
        axum::serve(listener, router).with_graceful_shutdown(shutdown).await?;
        tokio::task::spawn_blocking(move || workers.shutdown()).await?;
        store.close().await;
        Ok(())
    }
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
    S: tower::Service<http::Request<tonic::body::Body>, Error = std::convert::Infallible> + Clone + Send + Sync + 'static,
    S::Future: Send + 'static,
{
    svc.map_request(|req: axum::extract::Request| req.map(tonic::body::Body::new))
}
