//! The REST API (axum): sessions, reconstructions and dual images. Errors are problem+json.

use std::collections::HashMap;

use axum::Router;
use axum::body::{Body, Bytes};
use axum::extract::rejection::{PathRejection, QueryRejection};
use axum::extract::{FromRequestParts, State};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use helmholtz_proto::rest::{
    CameraView, Health, PrimalRequest, Problem, ReconstructionLinks, ReconstructionList,
    ReconstructionRequest, ReconstructionView, RelightRequest, ServiceIndex, SessionLinks,
    SessionList, SessionState, SessionView, TokenList, TokenRequest, TokenView,
};
use serde_json::Value;
use serde_json::value::RawValue;

use super::images::{self, Scale};
use super::{ApiError, AppState, validate};
use crate::auth::{Principal, Role, Roles};
use crate::store::{self, ReconstructionRow, SampleFormat, SessionRow, StoredImage, TokenInfo};
use futures::StreamExt;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::openapi::{self, ReconstructionFile, SessionFile};

/// Every REST route, each with its OpenAPI operation (the `#[utoipa::path]` on its handler):
/// what is routed and what `/openapi.json` documents come from this one list. A new route is
/// one `.routes(routes!(handler))` line here and an annotated handler; a plain `.route(...)`
/// would be served but not documented (the openapi tests catch it).
pub fn api() -> OpenApiRouter<AppState> {
    OpenApiRouter::with_openapi(<openapi::Base as utoipa::OpenApi>::openapi())
        .routes(routes!(index))
        .routes(routes!(healthz))
        .routes(routes!(openapi::openapi_json))
        .routes(routes!(openapi::docs))
        .routes(routes!(list_sessions, super::upload::create_session))
        .routes(routes!(
            super::upload::upload_status,
            super::upload::put_rows
        ))
        .routes(routes!(super::upload::finish_session))
        .routes(routes!(crate::telemetry::metrics))
        .routes(routes!(get_session))
        .routes(routes!(list_reconstructions, post_reconstruction))
        .routes(routes!(session_file))
        .routes(routes!(get_reconstruction, delete_reconstruction))
        .routes(routes!(cancel_reconstruction))
        .routes(routes!(relight))
        .routes(routes!(primal))
        .routes(routes!(reconstruction_file))
        .routes(routes!(list_tokens, create_token))
        .routes(routes!(revoke_token))
        .routes(routes!(super::web::asset))
        .routes(routes!(super::web::reconstruction_events))
        .routes(routes!(super::preview::session_preview))
}

/// The REST router: [`routes`] with the state.
pub fn router(state: AppState) -> Router {
    routes().with_state(state)
}

/// [`api`]'s routes, problem+json for unknown paths (404) and methods (405).
pub fn routes() -> Router<AppState> {
    let (router, _) = api().split_for_parts();
    router
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
}

/// `GET /v1/{sessions,reconstructions}/{id}/{file}`: the dual image files.
pub const DUAL_FILES: [&str; 3] = ["dual.png", "dual.tiff", "dual.npy"];

// Parameters as the document describes them (the handlers read them as strings and refuse bad
// ones with a 400 naming the parameter).

/// `{id}` of a session.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
pub(super) struct SessionId {
    /// The session id: 1-128 characters of A-Z a-z 0-9 . _ -
    #[param(pattern = r"^[A-Za-z0-9._-]{1,128}$")]
    id: String,
}

/// `{id}` of a reconstruction.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
pub(super) struct ReconstructionId {
    /// The reconstruction id (an integer)
    id: i64,
}

/// `{id}` and `{file}` of a session's file.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
struct SessionFilePath {
    /// The session id: 1-128 characters of A-Z a-z 0-9 . _ -
    #[param(pattern = r"^[A-Za-z0-9._-]{1,128}$")]
    id: String,
    /// The file
    #[param(inline, value_type = SessionFile)]
    file: String,
}

/// `{id}` and `{file}` of a reconstruction's file.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
struct ReconstructionFilePath {
    /// The reconstruction id (an integer)
    id: i64,
    /// The file
    #[param(inline, value_type = ReconstructionFile)]
    file: String,
}

/// How a PNG maps float values to 8 bits.
#[derive(utoipa::ToSchema)]
#[schema(rename_all = "lowercase")]
#[allow(dead_code)]
enum ScaleName {
    /// Black at the 0.5th percentile, white at the 99.5th (the default)
    Percentile,
    /// Black at the minimum, white at the maximum
    MinMax,
}

/// The encoding of a computed image.
#[derive(utoipa::ToSchema)]
#[schema(rename_all = "lowercase")]
#[allow(dead_code)]
enum FormatName {
    /// 8-bit grey PNG scaled for viewing (`scale`), image/png (the default)
    Png,
    /// 32-bit float TIFF, image/tiff
    Tiff,
    /// float32 NPY of shape (height, width), sent as application/octet-stream
    Npy,
}

/// Photometric stereo's detector gains.
#[derive(utoipa::ToSchema)]
#[schema(rename_all = "lowercase")]
#[allow(dead_code)]
enum GainsName {
    /// Estimated when the data fix them, else equal (the default; photometric.json says which)
    Auto,
    /// All detectors equally sensitive
    Equal,
    /// Estimated from the images (four or more channels)
    Estimate,
}

/// Whether a predicted camera image includes the measured ambient (dark) image.
#[derive(utoipa::ToSchema)]
#[schema(rename_all = "lowercase")]
#[allow(dead_code)]
enum AmbientName {
    /// Add the reconstruction's ambient image (the default)
    Include,
    /// T p alone
    Exclude,
}

#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)]
struct ListQuery {
    /// At most this many sessions (1-1000, default 100)
    #[param(minimum = 1, maximum = 1000)]
    limit: Option<u32>,
}

#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)]
struct DualQuery {
    /// The channel by name or index (default: the first)
    channel: Option<String>,
    /// dual.png only: how values map to 8 bits
    #[param(inline)]
    scale: Option<ScaleName>,
}

#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)]
struct FileQuery {
    /// dual.*: the channel by name or index (default: the first)
    channel: Option<String>,
    /// dual.png: how values map to 8 bits
    #[param(inline)]
    scale: Option<ScaleName>,
    /// normals.*, albedo.*, residual.npy, photometric.json: the detector gains
    #[param(inline)]
    gains: Option<GainsName>,
    /// normals.*, albedo.*, residual.npy, photometric.json: a channel at most this fraction of a pixel's brightest is shadowed there (in [0, 1), default 0.05)
    #[param(minimum = 0, exclusive_maximum = 1)]
    shadow_threshold: Option<f64>,
    /// normals.*, albedo.*, residual.npy, photometric.json: a pixel whose brightest channel is at most this fraction of the image's 99th percentile is too dark to fit (in [0, 1), default 0.05)
    #[param(minimum = 0, exclusive_maximum = 1)]
    dark_threshold: Option<f64>,
}

#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)]
struct RelightQuery {
    /// The image's encoding
    #[param(inline)]
    format: Option<FormatName>,
    /// format=png: how values map to 8 bits
    #[param(inline)]
    scale: Option<ScaleName>,
}

#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)]
struct PrimalQuery {
    /// The image's encoding
    #[param(inline)]
    format: Option<FormatName>,
    /// format=png: how values map to 8 bits
    #[param(inline)]
    scale: Option<ScaleName>,
    /// Whether the camera image includes the ambient image
    #[param(inline)]
    ambient: Option<AmbientName>,
}

#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Header)]
#[allow(dead_code)]
struct Conditional {
    /// An ETag of an earlier answer: 304 without a body when it names this one
    #[param(rename = "If-None-Match")]
    if_none_match: Option<String>,
}

async fn not_found() -> ApiError {
    ApiError::NotFound("no such route; see GET / for the API's routes".into())
}

async fn method_not_allowed() -> Response {
    let body = Problem::new(
        "method-not-allowed",
        "Method not allowed",
        405,
        "this route does not take that HTTP method",
    );
    let body = serde_json::to_string(&body).expect("a problem serializes");
    let mut r = (StatusCode::METHOD_NOT_ALLOWED, body).into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(helmholtz_proto::rest::PROBLEM_JSON),
    );
    r
}

/// The authenticated caller of a REST request (401 problem+json without a valid token, 429
/// over its rate). Handlers then check the role with [`Principal::require`].
pub struct Caller(pub Principal);

impl FromRequestParts<AppState> for Caller {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Self, ApiError> {
        let authorization = parts
            .headers
            .get(header::AUTHORIZATION)
            .map(|v| v.as_bytes());
        state.authenticate(authorization).await.map(Caller)
    }
}

/// Path parameters; a bad one (e.g. invalid percent-encoding) is a 400 problem naming the path.
#[derive(FromRequestParts)]
#[from_request(via(axum::extract::Path), rejection(ApiError))]
pub(super) struct Path<T>(pub T);

/// Query parameters; undecodable ones are a 400 problem naming the query.
#[derive(FromRequestParts)]
#[from_request(via(axum::extract::Query), rejection(ApiError))]
pub(super) struct Query<T>(pub T);

impl From<PathRejection> for ApiError {
    fn from(e: PathRejection) -> Self {
        ApiError::invalid("path", e.body_text())
    }
}

impl From<QueryRejection> for ApiError {
    fn from(e: QueryRejection) -> Self {
        ApiError::invalid("query", e.body_text())
    }
}

/// A request body of at most `max_body_bytes` (413 problem+json naming the limit; 408 when it
/// stops arriving for the body timeout, see `edge::body_timeout`).
async fn read_body(state: &AppState, body: Body) -> Result<Bytes, ApiError> {
    read_body_up_to(body, state.limits.max_body_bytes, "max_body_bytes").await
}

/// A request body of at most `max` bytes (413 problem+json naming `limit`; 408 when it stops
/// arriving for the body timeout).
pub(super) async fn read_body_up_to(
    body: Body,
    max: usize,
    limit: &'static str,
) -> Result<Bytes, ApiError> {
    axum::body::to_bytes(body, max).await.map_err(|e| {
        let timed_out =
            std::iter::successors(Some(&e as &(dyn std::error::Error + 'static)), |e| {
                e.source()
            })
            .any(|e| e.is::<tower_http::timeout::TimeoutError>());
        if timed_out {
            ApiError::Timeout("the request body stopped arriving (body timeout)".into())
        } else {
            ApiError::TooLarge {
                limit,
                message: format!("request bodies may hold at most {max} bytes"),
            }
        }
    })
}

/// The service index
///
/// What the service is, its gRPC services, how to authenticate and every REST route (one line
/// per operation of this document). A browser's request (`Accept: text/html`) gets the web
/// viewer's page instead, without a token (the page holds no data; it asks for a token).
#[utoipa::path(
    get,
    path = "/",
    tag = "service",
    responses((status = 200, description = "The service index (application/json), or the web viewer's page (text/html) when the request accepts text/html",
        content((ServiceIndex = "application/json"), ("text/html"))))
)]
async fn index(State(state): State<AppState>, headers: HeaderMap) -> Result<Response, ApiError> {
    if super::web::wants_html(&headers) {
        return Ok(super::web::index_html());
    }
    let authorization = headers.get(header::AUTHORIZATION).map(|v| v.as_bytes());
    state.authenticate(authorization).await?;
    Ok(axum::Json(ServiceIndex {
        service: "helmholtz".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        grpc: "helmholtz.v1.Acquisition on this same address (HTTP/2); grpc.health.v1.Health and server reflection (grpc.reflection.v1, v1alpha) need no token".into(),
        routes: openapi::document().routes.clone(),
        auth: "every route but /healthz, /openapi.json, /docs and the web viewer (/ in a browser, /assets/*) needs \"Authorization: Bearer <token>\"; tokens belong to one lab and carry roles rig, reader, admin, metrics (GET /metrics)".into(),
    })
    .into_response())
}

/// Health
///
/// Open (no token): load balancers and probes call it. Serving when the database answers
/// within 2 s.
#[utoipa::path(
    get,
    path = "/healthz",
    tag = "service",
    security(()),
    responses(
        (status = 200, description = "The database answers: {\"status\": \"serving\"}", body = Health),
        (status = 503, description = "The database does not answer within 2 s: {\"status\": \"not serving\"}", body = Health),
    )
)]
async fn healthz(State(state): State<AppState>) -> Response {
    let health = |status: &str| {
        axum::Json(Health {
            status: status.into(),
        })
    };
    // A probe wants an answer within its own timeout: a database that does not answer within
    // 2 s (a pool waiting to reconnect) is as good as none.
    let answers = tokio::time::timeout(std::time::Duration::from_secs(2), state.store.ping())
        .await
        .unwrap_or(false);
    if answers {
        health(Health::SERVING).into_response()
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, health(Health::NOT_SERVING)).into_response()
    }
}

pub fn session_view(s: &SessionRow, latest: Option<i64>) -> SessionView {
    SessionView {
        id: s.id.clone(),
        rig: s.rig.clone(),
        patterns: s.spec.clone(),
        channels: s.channels.clone(),
        directions: s.directions.clone(),
        camera: s.camera.map(|c| CameraView {
            width: c.width,
            height: c.height,
            format: c.format,
        }),
        metadata: s.metadata.clone(),
        committed_rows: s.committed_rows,
        expected_rows: s.expected_rows,
        state: match s.state {
            store::SessionState::Open => SessionState::Open,
            store::SessionState::Finished => SessionState::Finished,
        },
        created_unix_ms: s.created_ms,
        finished_unix_ms: s.finished_ms,
        has_ground_truth: s.has_ground_truth,
        latest_reconstruction: latest,
        links: SessionLinks::of(&s.id),
        extra: Default::default(),
    }
}

/// A reconstruction as served. Its report goes out as it was stored (a `rest::Report` the job
/// wrote, or a report of an earlier version), not parsed and written again; stored text that
/// is not JSON is served as null.
pub fn reconstruction_view(r: &ReconstructionRow) -> ReconstructionView<Box<RawValue>> {
    ReconstructionView {
        id: r.id,
        session_id: r.session_id.clone(),
        method: r.method.clone(),
        params: serde_json::from_str(&r.params_json).unwrap_or(Value::Null),
        state: r.state.clone(),
        progress: r.progress,
        rows: r.rows_used,
        attempt: r.attempt,
        seconds: r.seconds,
        error: r.last_error.clone(),
        report: r
            .report_json
            .as_deref()
            .and_then(|s| RawValue::from_string(s.to_string()).ok()),
        warnings: report_warnings(r),
        created_unix_ms: r.created_ms,
        started_unix_ms: r.started_ms,
        finished_unix_ms: r.finished_ms,
        links: ReconstructionLinks::of(r.id),
        extra: Default::default(),
    }
}

/// The stored report's warnings ([`helmholtz_proto::rest::Report::warnings`]); none when there
/// is no report yet or it is not one this version reads.
pub(super) fn report_warnings(r: &ReconstructionRow) -> Vec<String> {
    r.report_json
        .as_deref()
        .and_then(|s| serde_json::from_str::<helmholtz_proto::rest::Report>(s).ok())
        .map(|report| report.warnings())
        .unwrap_or_default()
}

pub(super) fn session_path(id: &str) -> Result<(), ApiError> {
    validate::session_id(id, "id")
}

pub(super) fn recon_path(id: &str) -> Result<i64, ApiError> {
    id.parse::<i64>().map_err(|_| {
        ApiError::invalid(
            "id",
            format!("a reconstruction id is an integer, got {id:?}"),
        )
    })
}

/// List the lab's sessions
///
/// The caller's lab's sessions, newest first (role reader).
#[utoipa::path(
    get,
    path = "/v1/sessions",
    tag = "sessions",
    params(ListQuery),
    responses(
        (status = 200, description = "The sessions", body = SessionList),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
    )
)]
async fn list_sessions(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Query(query): Query<HashMap<String, String>>,
) -> Result<axum::Json<SessionList>, ApiError> {
    caller.require(Role::Reader)?;
    let limit = match query.get("limit") {
        None => 100,
        Some(v) => v
            .parse::<u32>()
            .ok()
            .filter(|n| (1..=1000).contains(n))
            .ok_or_else(|| {
                ApiError::invalid(
                    "limit",
                    format!("must be an integer in 1..=1000, got {v:?}"),
                )
            })?,
    };
    let sessions = state.store.list_sessions(&caller.lab, limit).await?;
    let mut out = Vec::with_capacity(sessions.len());
    for s in &sessions {
        out.push(session_view(s, state.store.latest_done(&s.id).await?));
    }
    Ok(axum::Json(SessionList { sessions: out }))
}

/// A session
///
/// Its declaration, upload progress and latest finished reconstruction (role reader).
#[utoipa::path(
    get,
    path = "/v1/sessions/{id}",
    tag = "sessions",
    params(SessionId),
    responses(
        (status = 200, description = "The session", body = SessionView),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
    )
)]
async fn get_session(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::Json<SessionView>, ApiError> {
    caller.require(Role::Reader)?;
    session_path(&id)?;
    let s = state.own_session(&caller, &id).await?;
    let latest = state.store.latest_done(&id).await?;
    Ok(axum::Json(session_view(&s, latest)))
}

/// A session's reconstructions
///
/// Every reconstruction requested on the session, oldest first (role reader).
#[utoipa::path(
    get,
    path = "/v1/sessions/{id}/reconstructions",
    tag = "reconstructions",
    params(SessionId),
    responses(
        (status = 200, description = "The reconstructions", body = ReconstructionList),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
    )
)]
async fn list_reconstructions(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::Json<ReconstructionList<Box<RawValue>>>, ApiError> {
    caller.require(Role::Reader)?;
    session_path(&id)?;
    state.own_session(&caller, &id).await?;
    let rows = state.store.session_reconstructions(&id).await?;
    Ok(axum::Json(ReconstructionList {
        reconstructions: rows.iter().map(reconstruction_view).collect(),
    }))
}

/// Request a reconstruction
///
/// Queues a reconstruction of the session's committed rows by `method` with `params`
/// (method-specific; `{}` or absent for the defaults); `transport` reconstructs a camera
/// session's transport matrix. Poll the answer's `links.self` until `state` is done, failed or
/// cancelled (role reader).
#[utoipa::path(
    post,
    path = "/v1/sessions/{id}/reconstructions",
    tag = "reconstructions",
    params(SessionId),
    request_body(content = ReconstructionRequest, description = "The method and its parameters", content_type = "application/json"),
    responses(
        (status = 202, description = "Queued", body = ReconstructionView,
            headers(("Location" = String, description = "The reconstruction: /v1/reconstructions/{id}"))),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
        (status = 408, response = openapi::RequestTimeout),
        (status = 409, response = openapi::Conflict),
        (status = 413, response = openapi::TooLarge),
    )
)]
async fn post_reconstruction(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
    body: Body,
) -> Result<Response, ApiError> {
    caller.require(Role::Reader)?;
    session_path(&id)?;
    let body = read_body(&state, body).await?;
    let body: ReconstructionRequest =
        super::json::decode(&body, r#"{"method": "dgi", "params": {}}"#)?;
    let request = crate::recon::Request::parse(&body.method, &body.params)
        .map_err(|e| ApiError::invalid(e.field, e.message))?;
    let row = state.request_reconstruction(&caller, &id, &request).await?;
    let location = format!("/v1/reconstructions/{}", row.id);
    let mut response =
        (StatusCode::ACCEPTED, axum::Json(reconstruction_view(&row))).into_response();
    response.headers_mut().insert(
        header::LOCATION,
        HeaderValue::from_str(&location).expect("ascii"),
    );
    Ok(response)
}

/// The committed rows exactly as stored, streamed page by page (a camera session can be
/// gigabytes): bucket sessions float64 of shape (rows, channels); camera sessions their frames,
/// uint16 or float32 of shape (rows, height, width).
/// An adaptive session's issued batches (a session of another family is 409).
async fn adaptive_json(
    state: &AppState,
    caller: &Principal,
    id: &str,
) -> Result<Response, ApiError> {
    let session = state.own_session(caller, id).await?;
    if !session.spec.is_adaptive() {
        return Err(crate::store::StoreError::NotAdaptive(session.id).into());
    }
    let batches = state.store.batches(id).await?;
    let indices: Vec<u32> = batches.iter().flat_map(|b| b.indices.clone()).collect();
    let body = serde_json::json!({
        "session_id": session.id,
        "issued_rows": session.spec.adaptive_rows(indices.len() as u64),
        "indices": indices,
        "batches": batches
            .iter()
            .map(|b| serde_json::json!({
                "number": b.number,
                "first_row": b.first_row,
                "indices": b.indices,
            }))
            .collect::<Vec<_>>(),
    });
    Ok(axum::Json(body).into_response())
}

async fn measurements_npy(
    state: &AppState,
    caller: &Principal,
    id: &str,
) -> Result<Response, ApiError> {
    let session = state.own_session(caller, id).await?;
    let rows = session.committed_rows;
    let format = session.sample_format();
    use helmholtz_proto::npy::{self, Dtype};
    let (dtype, shape) = match (session.camera, format) {
        (Some(c), SampleFormat::U16) => (Dtype::U16, vec![rows, c.height as u64, c.width as u64]),
        (Some(c), _) => (Dtype::F32, vec![rows, c.height as u64, c.width as u64]),
        (None, _) => (Dtype::F64, vec![rows, session.channels.len() as u64]),
    };
    let header = npy::header(dtype, &shape, false);
    let length = header.len() as u64 + rows * session.row_bytes() as u64;
    let store = state.store.clone();
    let (sid, sample_bytes) = (session.id.clone(), format.bytes());
    // Pages of chunks in row order up to the committed count at the time of the request.
    let pages = futures::stream::unfold(Some(0u64), move |next| {
        let (store, sid) = (store.clone(), sid.clone());
        async move {
            let from = next?;
            if from >= rows {
                return None;
            }
            match store.read_raw_chunks(&sid, from, 16, sample_bytes).await {
                Ok(page) if page.is_empty() => None,
                Ok(page) => {
                    let (start, count, _) = page.last().expect("non-empty");
                    let after = start + count;
                    let mut bytes = Vec::new();
                    for (start, count, data) in page {
                        // Never past the count announced in the header.
                        let keep = count.min(rows.saturating_sub(start)) as usize;
                        bytes.extend_from_slice(&data[..keep * (data.len() / count as usize)]);
                    }
                    Some((Ok::<_, std::io::Error>(Bytes::from(bytes)), Some(after)))
                }
                Err(e) => Some((Err(std::io::Error::other(e.to_string())), None)),
            }
        }
    });
    let body = futures::stream::once(async move { Ok::<_, std::io::Error>(Bytes::from(header)) })
        .chain(pages);
    let mut response = Body::from_stream(body).into_response();
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/octet-stream"),
    );
    response
        .headers_mut()
        .insert(header::CONTENT_LENGTH, HeaderValue::from(length));
    Ok(response)
}

/// Relight: the dual image under a virtual light
///
/// The dual image `T^T c'` of a finished reconstruction under a virtual light `c'` at the
/// detector side (see `api::relight`): a camera session takes a preset
/// (`{"light": {"preset": "full" | "disc" | "stripe", ...}}`) or a camera-sized image (PNG, or
/// NPY of shape (height, width) or (height * width,)); a bucket session takes per-channel weights
/// (`{"light": {"weights": {CHANNEL: W}}}`). Answers are immutable: strong ETag,
/// `If-None-Match` gives 304 (role reader).
#[utoipa::path(
    post,
    path = "/v1/reconstructions/{id}/relight",
    tag = "relighting",
    params(ReconstructionId, RelightQuery, Conditional),
    request_body(description = "The virtual light: JSON, or a camera-sized image",
        content(
            (RelightRequest = "application/json"),
            ("image/png"),
            ("application/x-npy"),
            ("application/octet-stream"),
        )),
    responses(
        (status = 200, description = "The relit dual image (format=npy: float32 NPY sent as application/octet-stream)",
            content(("image/png"), ("image/tiff"), ("application/octet-stream")),
            headers(
                ("ETag" = String, description = "The answer's strong ETag"),
                ("Cache-Control" = String, description = "private, max-age=31536000, immutable"),
                ("Server-Timing" = String, description = "compute;dur=MS, or cache;desc=\"hit\""),
            )),
        (status = 304, response = openapi::NotModified),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
        (status = 408, response = openapi::RequestTimeout),
        (status = 409, response = openapi::Conflict),
        (status = 413, response = openapi::TooLarge),
    )
)]
async fn relight(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
    Query(query): Query<HashMap<String, String>>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    caller.require(Role::Reader)?;
    let id = recon_path(&id)?;
    let body = read_body(&state, body).await?;
    super::relight::relight(&state, &caller, id, &query, &headers, body).await
}

/// Primal: the camera image a pattern would give
///
/// The camera image `T p` (+ the ambient image) a projector pattern `p` would give, from a
/// finished camera session's transport matrix (see `api::relight`): one of the
/// session's own patterns (`{"pattern_index": I}`; the answer then carries the error against
/// the measured frame) or any projector-sized image (PNG, or NPY of shape (height, width) or
/// (height * width,)). Answers are immutable: strong ETag, `If-None-Match` gives 304 (role reader).
#[utoipa::path(
    post,
    path = "/v1/reconstructions/{id}/primal",
    tag = "relighting",
    params(ReconstructionId, PrimalQuery, Conditional),
    request_body(description = "The pattern: one of the session's (JSON), or a projector-sized image",
        content(
            (PrimalRequest = "application/json"),
            ("image/png"),
            ("application/x-npy"),
            ("application/octet-stream"),
        )),
    responses(
        (status = 200, description = "The predicted camera image (format=npy: float32 NPY sent as application/octet-stream)",
            content(("image/png"), ("image/tiff"), ("application/octet-stream")),
            headers(
                ("ETag" = String, description = "The answer's strong ETag"),
                ("Cache-Control" = String, description = "private, max-age=31536000, immutable"),
                ("Server-Timing" = String, description = "compute;dur=MS, or cache;desc=\"hit\""),
                ("x-helmholtz-relative-error" = String, description = "pattern_index with a stored frame: ||c - measured|| / ||measured||"),
                ("x-helmholtz-psnr-db" = String, description = "pattern_index with a stored frame: PSNR against the measured frame, dB"),
                ("x-helmholtz-measured-row" = String, description = "pattern_index with a stored frame: the row compared"),
            )),
        (status = 304, response = openapi::NotModified),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
        (status = 408, response = openapi::RequestTimeout),
        (status = 409, response = openapi::Conflict),
        (status = 413, response = openapi::TooLarge),
    )
)]
async fn primal(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
    Query(query): Query<HashMap<String, String>>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    caller.require(Role::Reader)?;
    let id = recon_path(&id)?;
    let body = read_body(&state, body).await?;
    super::relight::primal(&state, &caller, id, &query, &headers, body).await
}

/// A reconstruction
///
/// Its state, progress and, once done, its report (role reader).
#[utoipa::path(
    get,
    path = "/v1/reconstructions/{id}",
    tag = "reconstructions",
    params(ReconstructionId),
    responses(
        (status = 200, description = "The reconstruction", body = ReconstructionView),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
    )
)]
async fn get_reconstruction(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::Json<ReconstructionView<Box<RawValue>>>, ApiError> {
    caller.require(Role::Reader)?;
    let id = recon_path(&id)?;
    Ok(axum::Json(reconstruction_view(
        &state.own_reconstruction(&caller, id).await?,
    )))
}

/// Cancel a reconstruction
///
/// The cancelled reconstruction; 409 if it already ended (role reader). Also
/// `DELETE /v1/reconstructions/{id}`.
#[utoipa::path(
    post,
    path = "/v1/reconstructions/{id}/cancel",
    tag = "reconstructions",
    params(ReconstructionId),
    responses(
        (status = 200, description = "Cancelled", body = ReconstructionView),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
        (status = 409, response = openapi::Conflict),
    )
)]
async fn cancel_reconstruction(
    caller: Caller,
    state: State<AppState>,
    id: Path<String>,
) -> Result<axum::Json<ReconstructionView<Box<RawValue>>>, ApiError> {
    cancel(caller, state, id).await
}

/// Cancel a reconstruction
///
/// As `POST /v1/reconstructions/{id}/cancel`: the cancelled reconstruction; 409 if it already
/// ended (role reader).
#[utoipa::path(
    delete,
    path = "/v1/reconstructions/{id}",
    tag = "reconstructions",
    params(ReconstructionId),
    responses(
        (status = 200, description = "Cancelled", body = ReconstructionView),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
        (status = 409, response = openapi::Conflict),
    )
)]
async fn delete_reconstruction(
    caller: Caller,
    state: State<AppState>,
    id: Path<String>,
) -> Result<axum::Json<ReconstructionView<Box<RawValue>>>, ApiError> {
    cancel(caller, state, id).await
}

async fn cancel(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::Json<ReconstructionView<Box<RawValue>>>, ApiError> {
    caller.require(Role::Reader)?;
    let id = recon_path(&id)?;
    Ok(axum::Json(reconstruction_view(
        &state.cancel_reconstruction(&caller, id).await?,
    )))
}

/// A token as served; `secret` only in the answer to its creation.
pub fn token_view(t: &TokenInfo, secret: Option<String>) -> TokenView {
    TokenView {
        id: t.id,
        lab: t.lab.clone(),
        roles: t.roles.clone(),
        note: t.note.clone(),
        created_unix_ms: t.created_unix_ms,
        revoked_unix_ms: t.revoked_unix_ms,
        token: secret,
    }
}

/// List the lab's tokens
///
/// The admin's lab's tokens, never their secrets (role admin).
#[utoipa::path(
    get,
    path = "/v1/tokens",
    tag = "tokens",
    responses(
        (status = 200, description = "The tokens", body = TokenList),
        (status = 403, response = openapi::Forbidden),
    )
)]
async fn list_tokens(
    Caller(caller): Caller,
    State(state): State<AppState>,
) -> Result<axum::Json<TokenList>, ApiError> {
    caller.require(Role::Admin)?;
    let tokens = state.store.list_tokens(Some(&caller.lab)).await?;
    Ok(axum::Json(TokenList {
        tokens: tokens.iter().map(|t| token_view(t, None)).collect(),
    }))
}

/// Create a token
///
/// A new token of the admin's lab with roles (rig, reader, admin) and a note; the answer holds
/// the secret, shown this once (role admin).
#[utoipa::path(
    post,
    path = "/v1/tokens",
    tag = "tokens",
    request_body(content = TokenRequest, content_type = "application/json"),
    responses(
        (status = 201, description = "Created; `token` is the secret", body = TokenView),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 408, response = openapi::RequestTimeout),
        (status = 413, response = openapi::TooLarge),
    )
)]
async fn create_token(
    Caller(caller): Caller,
    State(state): State<AppState>,
    body: Body,
) -> Result<Response, ApiError> {
    caller.require(Role::Admin)?;
    let body = read_body(&state, body).await?;
    let body: TokenRequest = super::json::decode(&body, r#"{"roles": ["rig"], "note": "..."}"#)?;
    let mut roles = Vec::new();
    for (i, name) in body.roles.iter().enumerate() {
        roles.push(Role::parse(name).map_err(|e| ApiError::invalid(format!("roles[{i}]"), e))?);
    }
    if roles.is_empty() {
        return Err(ApiError::invalid(
            "roles",
            "name at least one of rig, reader, admin, metrics",
        ));
    }
    let roles = Roles::of(&roles);
    let note = body.note.as_str();
    if note.len() > 256 || note.chars().any(char::is_control) {
        return Err(ApiError::invalid(
            "note",
            "must be a string of at most 256 characters without control characters",
        ));
    }
    let (info, secret) = state.store.create_token(&caller.lab, roles, note).await?;
    tracing::info!(token = info.id, lab = %info.lab, roles = %info.roles, by = caller.token_id, "token created");
    Ok((
        StatusCode::CREATED,
        axum::Json(token_view(&info, Some(secret))),
    )
        .into_response())
}

/// Revoke a token
///
/// Revokes a token of the admin's lab; another lab's is 404 (role admin).
#[utoipa::path(
    delete,
    path = "/v1/tokens/{id}",
    tag = "tokens",
    params(("id" = i64, Path, description = "The token id")),
    responses(
        (status = 200, description = "Revoked", body = TokenView),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
    )
)]
async fn revoke_token(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::Json<TokenView>, ApiError> {
    caller.require(Role::Admin)?;
    let id = id
        .parse::<i64>()
        .map_err(|_| ApiError::invalid("id", format!("a token id is an integer, got {id:?}")))?;
    let info = state
        .store
        .revoke_token(id, Some(&caller.lab))
        .await?
        .ok_or_else(|| ApiError::NotFound(format!("token {id} not found")))?;
    tracing::info!(token = id, lab = %info.lab, by = caller.token_id, "token revoked");
    Ok(axum::Json(token_view(&info, None)))
}

#[derive(Clone, Copy)]
enum Format {
    Png,
    Tiff,
    Npy,
}

fn dual_format(file: &str) -> Result<Format, ApiError> {
    match file {
        "dual.png" => Ok(Format::Png),
        "dual.tiff" => Ok(Format::Tiff),
        "dual.npy" => Ok(Format::Npy),
        _ => Err(ApiError::NotFound(format!(
            "no file {file:?}; try dual.png, dual.tiff or dual.npy (reconstructions also serve {})",
            super::relight::DERIVED_FILES.join(", ")
        ))),
    }
}

/// A reconstruction's file
///
/// `dual.png|dual.tiff|dual.npy`: a dual image (8-bit PNG scaled for viewing, 32-bit float
/// TIFF, float32 NPY of shape (height, width)); bucket sessions also serve
/// `normals.png|normals.npy|albedo.png|albedo.npy|residual.npy|photometric.json` (photometric
/// stereo from 3+ detectors with declared directions) and `composite.png` (channels r, g, b).
/// NPY files are sent as application/octet-stream. Answers are immutable: ETag, `If-None-Match`
/// gives 304 (role reader).
#[utoipa::path(
    get,
    path = "/v1/reconstructions/{id}/{file}",
    tag = "reconstructions",
    params(ReconstructionFilePath, FileQuery, Conditional),
    responses(
        (status = 200, description = "The file: image/png (.png), image/tiff (.tiff), application/octet-stream (.npy, NumPy format), application/json (photometric.json)",
            content(("image/png"), ("image/tiff"), ("application/octet-stream"), ("application/json")),
            headers(
                ("ETag" = String, description = "The answer's ETag"),
                ("Cache-Control" = String, description = "private, max-age=31536000, immutable"),
                ("Content-Disposition" = String, description = "dual.*: inline; filename=\"dual-ID-CHANNEL.EXT\""),
                ("Server-Timing" = String, description = "derived files: compute;dur=MS, or cache;desc=\"hit\""),
            )),
        (status = 304, response = openapi::NotModified),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
        (status = 409, response = openapi::Conflict),
    )
)]
async fn reconstruction_file(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path((id, file)): Path<(String, String)>,
    Query(query): Query<HashMap<String, String>>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    caller.require(Role::Reader)?;
    let id = recon_path(&id)?;
    if super::relight::DERIVED_FILES.contains(&file.as_str()) {
        return super::relight::derived(&state, &caller, id, &file, &query, &headers).await;
    }
    let format = dual_format(&file)?;
    let r = state.own_reconstruction(&caller, id).await?;
    serve_dual(&state, r, &query, &headers, format).await
}

/// A session's file
///
/// `measurements.npy`: the committed rows as stored, streamed (bucket sessions float64 of shape
/// (rows, channels); camera sessions their frames, uint16 or float32 of shape (rows, height,
/// width)). `adaptive.json`: an adaptive session's issued batches in order, `{"session_id",
/// "issued_rows", "indices": [..], "batches": [{"number", "first_row", "indices"}]}` (with the
/// rows, what replays the session: PATTERNS.md). `dual.png|dual.tiff|dual.npy`: the dual image of
/// the latest finished reconstruction. NPY files are sent as application/octet-stream (role
/// reader).
#[utoipa::path(
    get,
    path = "/v1/sessions/{id}/{file}",
    tag = "sessions",
    params(SessionFilePath, DualQuery, Conditional),
    responses(
        (status = 200, description = "The file: image/png (.png), image/tiff (.tiff), application/octet-stream (.npy, NumPy format), application/json (adaptive.json)",
            content(("image/png"), ("image/tiff"), ("application/octet-stream"), ("application/json")),
            headers(
                ("ETag" = String, description = "dual.*: the answer's ETag"),
                ("Cache-Control" = String, description = "dual.*: private, max-age=31536000, immutable"),
                ("Content-Disposition" = String, description = "dual.*: inline; filename=\"dual-ID-CHANNEL.EXT\""),
            )),
        (status = 304, response = openapi::NotModified),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
        (status = 409, response = openapi::Conflict),
    )
)]
async fn session_file(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path((id, file)): Path<(String, String)>,
    Query(query): Query<HashMap<String, String>>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    caller.require(Role::Reader)?;
    session_path(&id)?;
    if file == "measurements.npy" {
        return measurements_npy(&state, &caller, &id).await;
    }
    if file == "adaptive.json" {
        return adaptive_json(&state, &caller, &id).await;
    }
    let format = dual_format(&file)?;
    state.own_session(&caller, &id).await?;
    let Some(latest) = state.store.latest_done(&id).await? else {
        return Err(ApiError::NotFound(format!(
            "session {id:?} has no finished reconstruction yet"
        )));
    };
    let r = state.store.reconstruction(latest).await?;
    serve_dual(&state, r, &query, &headers, format).await
}

async fn serve_dual(
    state: &AppState,
    r: ReconstructionRow,
    query: &HashMap<String, String>,
    headers: &HeaderMap,
    format: Format,
) -> Result<Response, ApiError> {
    let id = r.id;
    if let Some(key) = query
        .keys()
        .find(|k| !matches!(k.as_str(), "channel" | "scale"))
    {
        return Err(ApiError::invalid(
            key.clone(),
            "unknown query parameter; expected channel or scale",
        ));
    }
    let scale = match query.get("scale").map(String::as_str) {
        None | Some("percentile") => Scale::Percentile,
        Some("minmax") => Scale::MinMax,
        Some(other) => {
            return Err(ApiError::invalid(
                "scale",
                format!("must be percentile or minmax, got {other:?}"),
            ));
        }
    };
    if r.state != "done" {
        return Err(ApiError::FailedPrecondition(format!(
            "reconstruction {id} is {}{}; its dual image exists once it is done",
            r.state,
            r.last_error
                .as_deref()
                .map(|e| format!(" ({e})"))
                .unwrap_or_default()
        )));
    }
    let images = state.store.dual_images(id).await?;
    let image = pick_channel(&images, query.get("channel"))?;
    let scale_tag = match (format, scale) {
        (Format::Png, Scale::Percentile) => "p",
        (Format::Png, Scale::MinMax) => "m",
        _ => "",
    };
    let (ext, mime) = match format {
        Format::Png => ("png", "image/png"),
        Format::Tiff => ("tiff", "image/tiff"),
        Format::Npy => ("npy", "application/octet-stream"),
    };
    // Results are immutable: the id, channel and encoding name the bytes. They are a lab's
    // data behind its token: cacheable by the caller's own client only (private), never by a
    // shared cache.
    let etag = format!("\"r{id}-c{}-{ext}{scale_tag}\"", image.channel_index);
    if headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == etag || t.trim() == "*"))
    {
        let mut r = StatusCode::NOT_MODIFIED.into_response();
        r.headers_mut()
            .insert(header::ETAG, HeaderValue::from_str(&etag).expect("ascii"));
        return Ok(r);
    }
    let bytes = match format {
        Format::Png => images::png_8bit(image.width, image.height, &image.data, scale),
        Format::Tiff => images::tiff_f32(image.width, image.height, &image.data),
        Format::Npy => images::npy_f32(image.width, image.height, &image.data),
    };
    let disposition = format!(
        "inline; filename=\"dual-{id}-{}.{ext}\"",
        image.channel_name
    );
    let mut response = bytes.into_response();
    let h = response.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(mime));
    h.insert(header::ETAG, HeaderValue::from_str(&etag).expect("ascii"));
    h.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static("private, max-age=31536000, immutable"),
    );
    h.insert(
        header::CONTENT_DISPOSITION,
        HeaderValue::from_str(&disposition).expect("validated names"),
    );
    Ok(response)
}

fn pick_channel<'a>(
    images: &'a [StoredImage],
    channel: Option<&String>,
) -> Result<&'a StoredImage, ApiError> {
    match channel {
        None => images
            .first()
            .ok_or_else(|| ApiError::Internal("finished reconstruction without images".into())),
        Some(name) => images
            .iter()
            .find(|i| &i.channel_name == name || i.channel_index.to_string() == *name)
            .ok_or_else(|| {
                let names: Vec<&str> = images.iter().map(|i| i.channel_name.as_str()).collect();
                ApiError::invalid(
                    "channel",
                    format!("no channel {name:?}; this session has {}", names.join(", ")),
                )
            }),
    }
}
