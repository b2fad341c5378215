//! Observability: Prometheus metrics (on the main port for a token with the `metrics` role, and
//! without a token on their own listener when `--metrics-listen` is set) and per-request latency
//! recording; request ids are set in `app` (tower-http) and carried in every log span.
//!
//! Series:
//! - `helmholtz_upload_rows_total`, `helmholtz_upload_bytes_total`: rows (and their f64 bytes) committed
//! - `helmholtz_upload_resumed_total`: upload streams continuing a session that already had rows
//! - `helmholtz_checksum_failures_total`: chunks refused for a CRC-32C mismatch
//! - `helmholtz_rate_limited_total`: requests refused by the per-token rate limit
//! - `helmholtz_queue_depth{state="queued"|"running"}`: reconstruction jobs
//! - `helmholtz_job_duration_seconds{method, outcome}`: done, failed, cancelled, released
//! - `helmholtz_http_request_duration_seconds{method, route, status}`: REST, by matched route
//! - `helmholtz_grpc_request_duration_seconds{rpc, code}`: gRPC, by method and status code
//! - `helmholtz_adaptive_streams_total`, `helmholtz_adaptive_batches_total`: adaptive acquisition
//!   streams opened and batches issued; `helmholtz_adaptive_decision_seconds`: from a committed
//!   chunk to the batches it lets the planner issue; `helmholtz_adaptive_replay_seconds`: rebuilding
//!   a session's planner from its stored rows when a stream opens

use std::net::SocketAddr;
use std::sync::OnceLock;
use std::time::Instant;

use axum::extract::{MatchedPath, Request, State};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use metrics_exporter_prometheus::{PrometheusBuilder, PrometheusHandle};

use crate::store::Store;

static HANDLE: OnceLock<PrometheusHandle> = OnceLock::new();

const LATENCY_BUCKETS: &[f64] = &[
    0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
];
const JOB_BUCKETS: &[f64] = &[
    0.01, 0.05, 0.1, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0,
];

/// Installs the process-wide Prometheus recorder (once; later calls reuse it).
pub fn recorder() -> anyhow::Result<PrometheusHandle> {
    if let Some(h) = HANDLE.get() {
        return Ok(h.clone());
    }
    let handle = PrometheusBuilder::new()
        .set_buckets_for_metric(
            metrics_exporter_prometheus::Matcher::Suffix("request_duration_seconds".into()),
            LATENCY_BUCKETS,
        )?
        .set_buckets_for_metric(
            metrics_exporter_prometheus::Matcher::Full("helmholtz_job_duration_seconds".into()),
            JOB_BUCKETS,
        )?
        .set_buckets_for_metric(
            metrics_exporter_prometheus::Matcher::Prefix("helmholtz_adaptive_".into()),
            LATENCY_BUCKETS,
        )?
        .install_recorder()?;
    describe();
    Ok(HANDLE.get_or_init(|| handle).clone())
}

fn describe() {
    metrics::describe_counter!(
        "helmholtz_upload_rows_total",
        "Bucket rows committed by uploads"
    );
    metrics::describe_counter!(
        "helmholtz_upload_bytes_total",
        "Bytes of bucket values (f64) committed by uploads"
    );
    metrics::describe_counter!(
        "helmholtz_upload_resumed_total",
        "Upload streams that continued a session already holding rows"
    );
    metrics::describe_counter!(
        "helmholtz_checksum_failures_total",
        "Upload chunks refused for a CRC-32C mismatch"
    );
    metrics::describe_counter!(
        "helmholtz_rate_limited_total",
        "Requests refused by the per-token rate limit"
    );
    metrics::describe_gauge!(
        "helmholtz_queue_depth",
        "Reconstruction jobs queued or running"
    );
    metrics::describe_histogram!(
        "helmholtz_job_duration_seconds",
        "Reconstruction job run time by method and outcome"
    );
    metrics::describe_histogram!(
        "helmholtz_http_request_duration_seconds",
        "REST latency by matched route"
    );
    metrics::describe_histogram!(
        "helmholtz_grpc_request_duration_seconds",
        "gRPC latency (to the response head) by method"
    );
    metrics::describe_counter!(
        "helmholtz_adaptive_streams_total",
        "Adaptive acquisition streams opened"
    );
    metrics::describe_counter!(
        "helmholtz_adaptive_batches_total",
        "Adaptive batches issued (stored before they are sent)"
    );
    metrics::describe_histogram!(
        "helmholtz_adaptive_decision_seconds",
        "Adaptive planner: from a committed chunk to the batches it issues"
    );
    metrics::describe_histogram!(
        "helmholtz_adaptive_replay_seconds",
        "Adaptive planner rebuilt from the stored rows when a stream opens"
    );
}

/// Serves `GET /metrics` on `listener` until `shutdown`.
/// Serves `GET /metrics` (plain HTTP) through the same edge as the API: header timeout,
/// connection cap and shutdown deadline, so a stalled scraper cannot hold the shutdown.
pub async fn serve(
    listener: tokio::net::TcpListener,
    handle: PrometheusHandle,
    store: Store,
    edge: crate::edge::EdgeConfig,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) {
    let app = axum::Router::new()
        .route("/metrics", axum::routing::get(render))
        .with_state((handle, store))
        .layer(axum::middleware::map_response(crate::app::nosniff));
    crate::edge::serve(listener, app, &edge, None, shutdown).await
}

/// Metrics
///
/// The server's Prometheus metrics in the text exposition format, for a token with the
/// `metrics` role (server-wide counts, nothing of any lab's sessions). `--metrics-listen`
/// serves the same without a token on a separate address.
#[utoipa::path(
    get,
    path = "/metrics",
    tag = "service",
    responses(
        (status = 200, description = "Prometheus text format 0.0.4",
            content_type = "text/plain; version=0.0.4", body = String),
        (status = 403, response = crate::api::openapi::Forbidden),
    )
)]
pub(crate) async fn metrics(
    State(state): State<crate::api::AppState>,
    headers: http::HeaderMap,
) -> Result<Response, crate::api::ApiError> {
    let authorization = headers
        .get(http::header::AUTHORIZATION)
        .map(|v| v.as_bytes());
    let caller = state.authenticate(authorization).await?;
    caller.require(crate::auth::Role::Metrics)?;
    let handle = recorder().map_err(|e| crate::api::ApiError::Internal(e.to_string()))?;
    Ok(render(State((handle, state.store.clone()))).await)
}

async fn render(State((handle, store)): State<(PrometheusHandle, Store)>) -> Response {
    if let Ok((queued, running)) = store.queue_depth().await {
        metrics::gauge!("helmholtz_queue_depth", "state" => "queued").set(queued as f64);
        metrics::gauge!("helmholtz_queue_depth", "state" => "running").set(running as f64);
    }
    handle.run_upkeep();
    (
        [(http::header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        handle.render(),
    )
        .into_response()
}

/// The gRPC methods this server knows (labels stay bounded whatever paths clients send).
const RPCS: &[&str] = &[
    "/helmholtz.v1.Acquisition/CreateSession",
    "/helmholtz.v1.Acquisition/UploadMeasurements",
    "/helmholtz.v1.Acquisition/GetUploadStatus",
    "/helmholtz.v1.Acquisition/FinishSession",
    "/helmholtz.v1.Acquisition/RequestReconstruction",
    "/helmholtz.v1.Acquisition/GetReconstruction",
    "/grpc.health.v1.Health/Check",
    "/grpc.health.v1.Health/Watch",
];

/// Records each request's latency: gRPC by method and status code, REST by matched route.
pub async fn record_latency(request: Request, next: Next) -> Response {
    let started = Instant::now();
    let path = request.uri().path().to_string();
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map(|m| m.as_str().to_string());
    let method = request.method().clone();
    let is_grpc = request
        .headers()
        .get(http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/grpc"));
    let response = next.run(request).await;
    let seconds = started.elapsed().as_secs_f64();
    if is_grpc {
        let rpc = RPCS
            .iter()
            .find(|r| **r == path)
            .copied()
            .unwrap_or("unknown");
        // Errors come as trailers-only responses (grpc-status in the head); a head without it
        // is a call that succeeded (or failed later in its stream, which these RPCs do not).
        let code = response
            .headers()
            .get("grpc-status")
            .and_then(|v| v.to_str().ok())
            .map(str::to_string)
            .unwrap_or_else(|| "0".into());
        metrics::histogram!("helmholtz_grpc_request_duration_seconds", "rpc" => rpc, "code" => code).record(seconds);
    } else {
        let route = route.unwrap_or_else(|| "unmatched".into());
        metrics::histogram!(
            "helmholtz_http_request_duration_seconds",
            "method" => method.to_string(),
            "route" => route,
            "status" => response.status().as_u16().to_string()
        )
        .record(seconds);
    }
    response
}

/// Binds the metrics listener (before anything else starts, so a bad address fails early).
pub async fn bind(addr: SocketAddr) -> anyhow::Result<tokio::net::TcpListener> {
    use anyhow::Context;
    tokio::net::TcpListener::bind(addr)
        .await
        .with_context(|| format!("cannot listen for metrics on {addr} (--metrics-listen)"))
}
