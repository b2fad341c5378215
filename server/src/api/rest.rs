//! The REST API (axum): sessions, reconstructions and dual images. Errors are problem+json.

use std::collections::HashMap;

use axum::Router;
use axum::body::{Body, Bytes};
use axum::extract::rejection::{PathRejection, QueryRejection};
use axum::extract::{FromRequestParts, State};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use helmholtz_proto::rest::{
    CameraView, Health, Problem, ReconstructionLinks, ReconstructionList, ReconstructionRequest,
    ReconstructionView, ServiceIndex, SessionLinks, SessionList, SessionState, SessionView,
    TokenList, TokenRequest, TokenView,
};
use serde_json::Value;
use serde_json::value::RawValue;

use super::images::{self, Scale};
use super::{ApiError, AppState, validate};
use crate::auth::{Principal, Role, Roles};
use crate::store::{self, ReconstructionRow, SampleFormat, SessionRow, StoredImage, TokenInfo};
use futures::StreamExt;

pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/", get(index))
        .route("/healthz", get(healthz))
        .route(
            "/v1/sessions",
            get(list_sessions).post(super::upload::create_session),
        )
        .route(
            "/v1/sessions/{id}/rows",
            get(super::upload::upload_status).put(super::upload::put_rows),
        )
        .route(
            "/v1/sessions/{id}/finish",
            post(super::upload::finish_session),
        )
        .route("/v1/sessions/{id}", get(get_session))
        .route(
            "/v1/sessions/{id}/reconstructions",
            get(list_reconstructions).post(post_reconstruction),
        )
        // measurements.npy, dual.png, dual.tiff, dual.npy
        .route("/v1/sessions/{id}/{file}", get(session_file))
        .route(
            "/v1/reconstructions/{id}",
            get(get_reconstruction).delete(cancel_reconstruction),
        )
        .route(
            "/v1/reconstructions/{id}/cancel",
            post(cancel_reconstruction),
        )
        .route("/v1/reconstructions/{id}/relight", post(relight))
        .route("/v1/reconstructions/{id}/primal", post(primal))
        .route("/v1/reconstructions/{id}/{file}", get(reconstruction_file))
        .route("/v1/tokens", get(list_tokens).post(create_token))
        .route("/v1/tokens/{id}", axum::routing::delete(revoke_token))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .with_state(state)
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

async fn index(Caller(_caller): Caller) -> axum::Json<ServiceIndex> {
    axum::Json(ServiceIndex {
        service: "helmholtz".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        grpc: "helmholtz.v1.Acquisition on this same address (HTTP/2); grpc.health.v1.Health and server reflection (grpc.reflection.v1, v1alpha) need no token".into(),
        routes: vec![
            "GET /v1/sessions".to_string(),
            "POST /v1/sessions {\"id\", \"rig\", \"patterns\": {spec}, \"channels\": [..] | \"camera\": {\"width\", \"height\", \"format\"}} (rig; the REST twin of gRPC CreateSession)".into(),
            "PUT /v1/sessions/{id}/rows?start_row=N with an application/x-npy or application/octet-stream body and x-helmholtz-crc32c: <hex> (rig; resumable, one writer, overlap compared)".into(),
            "GET /v1/sessions/{id}/rows (rig or reader: committed_rows, where to resume)".into(),
            "POST /v1/sessions/{id}/finish (rig)".into(),
            "GET /v1/sessions/{id}".into(), "GET /v1/sessions/{id}/reconstructions".into(),
            format!(
                "POST /v1/sessions/{{id}}/reconstructions {{\"method\": \"{}\", \"params\": {{}}}} (transport: camera sessions)",
                crate::recon::Request::method_names().collect::<Vec<_>>().join("|")
            ),
            "GET /v1/sessions/{id}/dual.png|dual.tiff|dual.npy (latest finished reconstruction)".into(),
            "GET /v1/sessions/{id}/measurements.npy (the committed rows: float64 (rows, channels), or a camera session's frames, (rows, height, width))".into(),
            "GET /v1/reconstructions/{id}".into(),
            "GET /v1/reconstructions/{id}/dual.png|dual.tiff|dual.npy?channel=NAME&scale=percentile|minmax".into(),
            "GET /v1/reconstructions/{id}/normals.png|normals.npy|albedo.png|albedo.npy|residual.npy|photometric.json?gains=auto|equal|estimate (photometric stereo from 3+ detectors with declared directions)".into(),
            "GET /v1/reconstructions/{id}/composite.png (channels r, g, b)".into(),
            "POST /v1/reconstructions/{id}/cancel (or DELETE /v1/reconstructions/{id})".into(),
            "POST /v1/reconstructions/{id}/relight?format=png|tiff|npy {\"light\": {\"preset\": \"full\"|\"disc\"|\"stripe\", ...} | {\"weights\": {CHANNEL: W}}} or a camera-sized PNG/NPY body: the dual image T^T c'".into(),
            "POST /v1/reconstructions/{id}/primal?format=png|tiff|npy&ambient=include|exclude {\"pattern_index\": I} or a projector-sized PNG/NPY body: the camera image T p (+ ambient), with x-helmholtz-relative-error for a measured pattern".into(),
            "GET /v1/tokens, POST /v1/tokens {\"roles\": [\"rig\"], \"note\": \"...\"}, DELETE /v1/tokens/{id} (admin)".into(),
            "GET /healthz (no token needed)".into(),
        ],
        auth: "every route but /healthz needs \"Authorization: Bearer <token>\"; tokens belong to one lab and carry roles rig, reader, admin, metrics (GET /metrics)".into(),
    })
}

/// Open (no token): load balancers and probes call it.
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
        created_unix_ms: r.created_ms,
        started_unix_ms: r.started_ms,
        finished_unix_ms: r.finished_ms,
        links: ReconstructionLinks::of(r.id),
        extra: Default::default(),
    }
}

pub(super) fn session_path(id: &str) -> Result<(), ApiError> {
    validate::session_id(id, "id")
}

fn recon_path(id: &str) -> Result<i64, ApiError> {
    id.parse::<i64>().map_err(|_| {
        ApiError::invalid(
            "id",
            format!("a reconstruction id is an integer, got {id:?}"),
        )
    })
}

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

/// `POST /v1/reconstructions/{id}/relight` ([`relight`](super::relight)).
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

/// `POST /v1/reconstructions/{id}/primal` ([`relight`](super::relight)).
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

/// `POST /v1/reconstructions/{id}/cancel` or `DELETE /v1/reconstructions/{id}`: 200 with the
/// cancelled reconstruction; 409 if it already ended.
async fn cancel_reconstruction(
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

/// `GET /v1/tokens`: the admin's lab's tokens (never their secrets).
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

/// `POST /v1/tokens {"roles": ["rig"], "note": "..."}`: a new token of the admin's lab; 201 with
/// the secret, shown this once.
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

/// `DELETE /v1/tokens/{id}`: revokes a token of the admin's lab (another lab's is 404).
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
