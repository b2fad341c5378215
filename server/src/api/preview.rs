//! `GET /v1/sessions/{id}/preview`: a session's live preview as server-sent events (the REST
//! side of gRPC `WatchPreview`; the preview itself is [`crate::preview`]).

use std::collections::HashMap;
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use base64::Engine;
use helmholtz_proto::rest::PreviewEvent;

use super::rest::{Caller, Path, Query, SessionId, session_path};
use super::{ApiError, AppState, openapi};
use crate::auth::Role;
use crate::preview::{self, Frame, Watch};

/// A comment line this often keeps proxies from closing a quiet stream.
const KEEP_ALIVE: Duration = Duration::from_secs(15);

#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)]
struct PreviewQuery {
    /// Bucket sessions: the channel by name or index (default: the first). Camera sessions: leave it out (their preview is the sum over the camera pixels)
    channel: Option<String>,
    /// A frame once at least this many new rows are committed (0 or absent: no row trigger; at most the session's rows)
    #[param(minimum = 0)]
    every_rows: Option<u64>,
    /// A frame once this many milliseconds passed since the last and new rows are committed (50-600000; absent or 0: 500 when every_rows is absent, else no time trigger)
    #[param(minimum = 0, maximum = 600000)]
    every_ms: Option<u64>,
}

/// The SSE event of one frame.
pub fn event(frame: &Frame) -> String {
    let bytes: Vec<u8> = frame.values.iter().flat_map(|v| v.to_le_bytes()).collect();
    let view = PreviewEvent {
        session_id: frame.session_id.clone(),
        channel: frame.channel.clone(),
        rows: frame.rows,
        expected_rows: frame.expected_rows,
        width: frame.width,
        height: frame.height,
        method: frame.method.into(),
        values_f32le: base64::engine::general_purpose::STANDARD.encode(bytes),
        last: frame.last,
    };
    let json = serde_json::to_string(&view).expect("serializes");
    format!("event: preview\nid: {}\ndata: {json}\n\n", frame.rows)
}

/// A session's live preview
///
/// Server-sent events (`text/event-stream`): while the session uploads, an event `preview`
/// whose data is a `PreviewEvent` (a progressive dual image of the rows committed so far: DGI
/// for bernoulli and speckle patterns, the zero-filled inverse for hadamard, the running scan for
/// raster; a camera session as the sum over its pixels) every `every_rows` rows or `every_ms`
/// milliseconds, and a last event with `final: true` once the session is finished (at once for a
/// finished session); then the stream ends. The preview is computed from the committed rows on a
/// thread of its own and never delays the upload; it stops when the client disconnects. An error
/// after the stream started is an event `error` whose data is `{"detail": ...}`. Browsers read it
/// with `fetch()` (the token in the `Authorization` header), not `EventSource` (role rig or
/// reader).
#[utoipa::path(
    get,
    path = "/v1/sessions/{id}/preview",
    tag = "sessions",
    params(SessionId, PreviewQuery),
    responses(
        (status = 200, description = "Server-sent events: `event: preview`, `id: {rows}`, `data: {PreviewEvent}`; comment lines keep a quiet stream open",
            content((PreviewEvent = "text/event-stream")),
            headers(("Cache-Control" = String, description = "no-cache"))),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
    )
)]
pub(super) async fn session_preview(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
    Query(query): Query<HashMap<String, String>>,
) -> Result<Response, ApiError> {
    caller.require_any(&[Role::Rig, Role::Reader])?;
    session_path(&id)?;
    if let Some(key) = query
        .keys()
        .find(|k| !matches!(k.as_str(), "channel" | "every_rows" | "every_ms"))
    {
        return Err(ApiError::invalid(
            key.clone(),
            "unknown query parameter; expected channel, every_rows or every_ms",
        ));
    }
    let number = |name: &str| -> Result<u64, ApiError> {
        match query.get(name) {
            None => Ok(0),
            Some(v) => v.parse::<u64>().map_err(|_| {
                ApiError::invalid(name, format!("must be a non-negative integer, got {v:?}"))
            }),
        }
    };
    let (every_rows, every_ms) = (number("every_rows")?, number("every_ms")?);
    let session = state.own_session(&caller, &id).await?;
    let watch = Watch::parse(
        &session,
        query.get("channel").map(String::as_str),
        every_rows,
        every_ms,
    )?;
    let frames = preview::watch(state.store.clone(), &state.previews, session, watch)?;
    let events = futures::stream::unfold(Some(frames), |frames| async move {
        let mut frames = frames?;
        match tokio::time::timeout(KEEP_ALIVE, frames.recv()).await {
            Err(_) => Some((Bytes::from_static(b": keep-alive\n\n"), Some(frames))),
            Ok(None) => None,
            Ok(Some(Ok(frame))) => {
                let last = frame.last;
                let text = Bytes::from(event(&frame));
                Some((text, (!last).then_some(frames)))
            }
            Ok(Some(Err(e))) => {
                let msg = serde_json::json!({"detail": e.to_string()});
                Some((Bytes::from(format!("event: error\ndata: {msg}\n\n")), None))
            }
        }
        .map(|(bytes, next)| (Ok::<_, std::io::Error>(bytes), next))
    });
    let mut response = Body::from_stream(events).into_response();
    *response.status_mut() = StatusCode::OK;
    let h = response.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/event-stream"),
    );
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert("x-accel-buffering", HeaderValue::from_static("no"));
    Ok(response)
}
