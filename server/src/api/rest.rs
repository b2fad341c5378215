//! The REST API (axum): sessions, reconstructions and dual images. Errors are problem+json.

use std::collections::HashMap;

use axum::Router;
use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde_json::{Value, json};

use super::images::{self, Scale};
use super::{ApiError, AppState, validate};
use crate::store::{ReconstructionRow, SessionRow, StoredImage};

pub fn router(state: AppState) -> Router {
    Router::new()
        .route("/", get(index))
        .route("/healthz", get(healthz))
        .route("/v1/sessions", get(list_sessions))
        .route("/v1/sessions/{id}", get(get_session))
        .route("/v1/sessions/{id}/reconstructions", get(list_reconstructions).post(post_reconstruction))
        // measurements.npy, dual.png, dual.tiff, dual.npy
        .route("/v1/sessions/{id}/{file}", get(session_file))
        .route("/v1/reconstructions/{id}", get(get_reconstruction))
        .route("/v1/reconstructions/{id}/{file}", get(reconstruction_file))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .with_state(state)
}

async fn not_found() -> ApiError {
    ApiError::NotFound("no such route; see GET / for the API's routes".into())
}

async fn method_not_allowed() -> Response {
    let body = json!({"type": "/problems/method-not-allowed", "title": "Method not allowed", "status": 405,
        "detail": "this route does not take that HTTP method"});
    let mut r = (StatusCode::METHOD_NOT_ALLOWED, body.to_string()).into_response();
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("application/problem+json"));
    r
}

async fn index() -> axum::Json<Value> {
    axum::Json(json!({
        "service": "helmholtz",
        "version": env!("CARGO_PKG_VERSION"),
        "grpc": "helmholtz.v1.Acquisition on this same address (HTTP/2)",
        "routes": [
            "GET /v1/sessions", "GET /v1/sessions/{id}", "GET /v1/sessions/{id}/reconstructions",
            "POST /v1/sessions/{id}/reconstructions {\"method\": \"gi|dgi|ngi|direct|lsq|cs|tv\", \"params\": {}}",
            "GET /v1/sessions/{id}/dual.png|dual.tiff|dual.npy (latest finished reconstruction)",
            "GET /v1/sessions/{id}/measurements.npy (the committed bucket rows, float64, shape (rows, channels))",
            "GET /v1/reconstructions/{id}",
            "GET /v1/reconstructions/{id}/dual.png|dual.tiff|dual.npy?channel=NAME&scale=percentile|minmax",
            "GET /healthz"
        ]
    }))
}

async fn healthz(State(state): State<AppState>) -> Response {
    if state.store.ping().await {
        axum::Json(json!({"status": "serving"})).into_response()
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, axum::Json(json!({"status": "not serving"}))).into_response()
    }
}

pub fn session_json(s: &SessionRow, latest: Option<i64>) -> Value {
    json!({
        "id": s.id,
        "rig": s.rig,
        "patterns": serde_json::to_value(&s.spec).expect("spec json"),
        "channels": s.channels,
        "metadata": s.metadata,
        "committed_rows": s.committed_rows,
        "expected_rows": s.expected_rows,
        "state": s.state,
        "created_unix_ms": s.created_ms,
        "finished_unix_ms": s.finished_ms,
        "has_ground_truth": s.has_ground_truth,
        "latest_reconstruction": latest,
        "links": {
            "self": format!("/v1/sessions/{}", s.id),
            "reconstructions": format!("/v1/sessions/{}/reconstructions", s.id),
            "dual_png": format!("/v1/sessions/{}/dual.png", s.id),
        }
    })
}

pub fn reconstruction_json(r: &ReconstructionRow) -> Value {
    let parse = |s: &str| serde_json::from_str::<Value>(s).unwrap_or(Value::Null);
    json!({
        "id": r.id,
        "session_id": r.session_id,
        "method": r.method,
        "params": parse(&r.params_json),
        "state": r.state,
        "progress": r.progress,
        "rows": r.rows_used,
        "attempt": r.attempt,
        "seconds": r.seconds,
        "error": r.last_error,
        "report": r.report_json.as_deref().map(parse),
        "created_unix_ms": r.created_ms,
        "started_unix_ms": r.started_ms,
        "finished_unix_ms": r.finished_ms,
        "links": {
            "self": format!("/v1/reconstructions/{}", r.id),
            "dual_png": format!("/v1/reconstructions/{}/dual.png", r.id),
            "dual_tiff": format!("/v1/reconstructions/{}/dual.tiff", r.id),
            "dual_npy": format!("/v1/reconstructions/{}/dual.npy", r.id),
        }
    })
}

fn session_path(id: &str) -> Result<(), ApiError> {
    validate::session_id(id, "id")
}

fn recon_path(id: &str) -> Result<i64, ApiError> {
    id.parse::<i64>().map_err(|_| ApiError::invalid("id", format!("a reconstruction id is an integer, got {id:?}")))
}

async fn list_sessions(
    State(state): State<AppState>,
    Query(query): Query<HashMap<String, String>>,
) -> Result<axum::Json<Value>, ApiError> {
    let limit = match query.get("limit") {
        None => 100,
        Some(v) => v
            .parse::<u32>()
            .ok()
            .filter(|n| (1..=1000).contains(n))
            .ok_or_else(|| ApiError::invalid("limit", format!("must be an integer in 1..=1000, got {v:?}")))?,
    };
    let sessions = state.store.list_sessions(limit).await?;
    let mut out = Vec::with_capacity(sessions.len());
    for s in &sessions {
        out.push(session_json(s, state.store.latest_done(&s.id).await?));
    }
    Ok(axum::Json(json!({ "sessions": out })))
}

async fn get_session(State(state): State<AppState>, Path(id): Path<String>) -> Result<axum::Json<Value>, ApiError> {
    session_path(&id)?;
    let s = state.store.session(&id).await?;
    let latest = state.store.latest_done(&id).await?;
    Ok(axum::Json(session_json(&s, latest)))
}

async fn list_reconstructions(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::Json<Value>, ApiError> {
    session_path(&id)?;
    state.store.session(&id).await?;
    let rows = state.store.session_reconstructions(&id).await?;
    Ok(axum::Json(json!({ "reconstructions": rows.iter().map(reconstruction_json).collect::<Vec<_>>() })))
}

async fn post_reconstruction(
    State(state): State<AppState>,
    Path(id): Path<String>,
    body: Bytes,
) -> Result<Response, ApiError> {
    session_path(&id)?;
    let body: Value = serde_json::from_slice(&body)
        .map_err(|e| ApiError::invalid("body", format!("must be a JSON object like {{\"method\": \"dgi\", \"params\": {{}}}}: {e}")))?;
    let Value::Object(body) = body else {
        return Err(ApiError::invalid("body", "must be a JSON object"));
    };
    if let Some(key) = body.keys().find(|k| !matches!(k.as_str(), "method" | "params")) {
        return Err(ApiError::invalid(key.clone(), "unknown field; expected \"method\" and \"params\""));
    }
    let method = match body.get("method") {
        Some(Value::String(m)) => m.clone(),
        Some(_) => return Err(ApiError::invalid("method", "must be a string")),
        None => return Err(ApiError::invalid("method", "is required")),
    };
    let params = body.get("params").cloned().unwrap_or(Value::Null);
    let row = state.request_reconstruction(&id, &method, &params).await?;
    let location = format!("/v1/reconstructions/{}", row.id);
    let mut response = (StatusCode::ACCEPTED, axum::Json(reconstruction_json(&row))).into_response();
    response.headers_mut().insert(header::LOCATION, HeaderValue::from_str(&location).expect("ascii"));
    Ok(response)
}

/// The committed bucket rows exactly as stored: float64, shape (rows, channels).
async fn measurements_npy(state: &AppState, id: &str) -> Result<Response, ApiError> {
    let session = state.store.session(id).await?;
    let mut values = Vec::with_capacity(session.committed_rows as usize * session.channels.len());
    let mut next = 0u64;
    loop {
        let page = state.store.read_chunks(id, next, 256).await?;
        let Some((start, last)) = page.last() else { break };
        next = start + (last.len() / session.channels.len()) as u64;
        values.extend(page.into_iter().flat_map(|(_, v)| v));
    }
    let rows = (values.len() / session.channels.len()) as u64;
    let mut response = images::npy_f64(rows, session.channels.len(), &values).into_response();
    response.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("application/octet-stream"));
    Ok(response)
}

async fn get_reconstruction(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::Json<Value>, ApiError> {
    let id = recon_path(&id)?;
    Ok(axum::Json(reconstruction_json(&state.store.reconstruction(id).await?)))
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
        _ => Err(ApiError::NotFound(format!("no file {file:?}; try dual.png, dual.tiff or dual.npy"))),
    }
}

async fn reconstruction_file(
    State(state): State<AppState>,
    Path((id, file)): Path<(String, String)>,
    Query(query): Query<HashMap<String, String>>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let id = recon_path(&id)?;
    let format = dual_format(&file)?;
    serve_dual(&state, id, &query, &headers, format).await
}

async fn session_file(
    State(state): State<AppState>,
    Path((id, file)): Path<(String, String)>,
    Query(query): Query<HashMap<String, String>>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    session_path(&id)?;
    if file == "measurements.npy" {
        return measurements_npy(&state, &id).await;
    }
    let format = dual_format(&file)?;
    state.store.session(&id).await?;
    let Some(latest) = state.store.latest_done(&id).await? else {
        return Err(ApiError::NotFound(format!("session {id:?} has no finished reconstruction yet")));
    };
    serve_dual(&state, latest, &query, &headers, format).await
}

async fn serve_dual(
    state: &AppState,
    id: i64,
    query: &HashMap<String, String>,
    headers: &HeaderMap,
    format: Format,
) -> Result<Response, ApiError> {
    if let Some(key) = query.keys().find(|k| !matches!(k.as_str(), "channel" | "scale")) {
        return Err(ApiError::invalid(key.clone(), "unknown query parameter; expected channel or scale"));
    }
    let scale = match query.get("scale").map(String::as_str) {
        None | Some("percentile") => Scale::Percentile,
        Some("minmax") => Scale::MinMax,
        Some(other) => return Err(ApiError::invalid("scale", format!("must be percentile or minmax, got {other:?}"))),
    };
    let r = state.store.reconstruction(id).await?;
    if r.state != "done" {
        return Err(ApiError::FailedPrecondition(format!(
            "reconstruction {id} is {}{}; its dual image exists once it is done",
            r.state,
            r.last_error.as_deref().map(|e| format!(" ({e})")).unwrap_or_default()
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
    // Results are immutable: the id, channel and encoding name the bytes.
    let etag = format!("\"r{id}-c{}-{ext}{scale_tag}\"", image.channel_index);
    if headers.get(header::IF_NONE_MATCH).and_then(|v| v.to_str().ok()).is_some_and(|v| {
        v.split(',').any(|t| t.trim() == etag || t.trim() == "*")
    }) {
        let mut r = StatusCode::NOT_MODIFIED.into_response();
        r.headers_mut().insert(header::ETAG, HeaderValue::from_str(&etag).expect("ascii"));
        return Ok(r);
    }
    let bytes = match format {
        Format::Png => images::png_8bit(image.width, image.height, &image.data, scale),
        Format::Tiff => images::tiff_f32(image.width, image.height, &image.data),
        Format::Npy => images::npy_f32(image.width, image.height, &image.data),
    };
    let disposition = format!("inline; filename=\"dual-{id}-{}.{ext}\"", image.channel_name);
    let mut response = bytes.into_response();
    let h = response.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(mime));
    h.insert(header::ETAG, HeaderValue::from_str(&etag).expect("ascii"));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("public, max-age=31536000, immutable"));
    h.insert(header::CONTENT_DISPOSITION, HeaderValue::from_str(&disposition).expect("validated names"));
    Ok(response)
}

fn pick_channel<'a>(images: &'a [StoredImage], channel: Option<&String>) -> Result<&'a StoredImage, ApiError> {
    match channel {
        None => images.first().ok_or_else(|| ApiError::Internal("finished reconstruction without images".into())),
        Some(name) => images
            .iter()
            .find(|i| &i.channel_name == name || i.channel_index.to_string() == *name)
            .ok_or_else(|| {
                let names: Vec<&str> = images.iter().map(|i| i.channel_name.as_str()).collect();
                ApiError::invalid("channel", format!("no channel {name:?}; this session has {}", names.join(", ")))
            }),
    }
}
