//! Sessions and rows over REST, for tools without gRPC (MATLAB `webwrite`, curl, a browser):
//! `POST /v1/sessions`, `GET` and `PUT /v1/sessions/{id}/rows?start_row=N`,
//! `POST /v1/sessions/{id}/finish`.
//!
//! The same rules as the gRPC upload: a body is one chunk, checked whole (the CRC-32C of the body
//! in `x-helmholtz-crc32c`, or its SHA-256 in an RFC 9530 `Content-Digest`;
//! the session's sample format, whole rows, finite values, the size cap) before anything is
//! stored; rows below the committed count must equal the stored ones byte for byte; a start
//! above it is a gap; one writer per session (the `x-helmholtz-writer` header names a client's
//! upload, as the gRPC metadata does); the new rows and count commit in one transaction.

use std::collections::HashMap;

use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use helmholtz_proto::npy::{self, Dtype};
use helmholtz_proto::rest::{NewSessionRequest, SessionState, UploadResult, UploadStatusView};
use helmholtz_proto::v1;

use super::openapi;
use super::rest::{Caller, Path, Query, SessionId, read_body_up_to, session_path, session_view};
use super::{ApiError, AppState, validate};
use crate::auth::Role;
use crate::store::{self, SampleFormat, SessionRow, StoreError};

/// The header carrying the CRC-32C (Castagnoli) of a rows body: 8 hexadecimal digits
/// (`0x` allowed), as `crc32c` tools print it.
pub const CRC_HEADER: &str = "x-helmholtz-crc32c";

/// The media type of a NumPy `.npy` body.
pub const NPY: &str = "application/x-npy";
/// The media type of a raw body: little-endian samples of the session's format, row-major.
pub const RAW: &str = "application/octet-stream";

/// Room for an NPY header on top of `max_chunk_bytes` of samples.
const NPY_HEADER_ROOM: usize = 64 << 10;

/// Create a session
///
/// The REST twin of gRPC `CreateSession`, for tools without gRPC (role rig): 201 with the
/// session and its `Location`, or 200 with the stored one when the id exists with the same
/// declaration; 409 when it differs or the id is another lab's.
#[utoipa::path(
    post,
    path = "/v1/sessions",
    tag = "sessions",
    request_body(content = NewSessionRequest, content_type = "application/json"),
    responses(
        (status = 201, description = "Created", body = helmholtz_proto::rest::SessionView,
            headers(("Location" = String, description = "/v1/sessions/{id}"))),
        (status = 200, description = "It exists with this declaration", body = helmholtz_proto::rest::SessionView),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 408, response = openapi::RequestTimeout),
        (status = 409, response = openapi::Conflict),
        (status = 413, response = openapi::TooLarge),
        (status = 429, response = openapi::TooManyRequests),
    )
)]
pub(super) async fn create_session(
    Caller(caller): Caller,
    State(state): State<AppState>,
    body: Body,
) -> Result<Response, ApiError> {
    caller.require(Role::Rig)?;
    let body = read_body_up_to(body, state.limits.max_message_bytes, "max_message_bytes").await?;
    let req: NewSessionRequest = super::json::decode(
        &body,
        r#"{"id": "run-1", "rig": "bench", "patterns": {"family": "hadamard", "width": 32, "height": 32, "count": 1024, "seed": 0}, "channels": ["bucket"]}"#,
    )?;
    let message = v1::CreateSessionRequest {
        session_id: req.id,
        rig: req.rig,
        patterns: Some((&req.patterns).into()),
        detector: Some(v1::DetectorLayout {
            channels: req.channels,
            directions: req
                .directions
                .iter()
                .map(|d| v1::Direction {
                    x: d[0],
                    y: d[1],
                    z: d[2],
                })
                .collect(),
            camera: req.camera.map(|c| v1::CameraLayout {
                width: c.width,
                height: c.height,
                format: c.format.to_proto() as i32,
            }),
        }),
        metadata: req.metadata.into_iter().collect(),
        ground_truth: req.ground_truth.map(|g| v1::GroundTruth {
            width: g.width,
            height: g.height,
            transport: g.transport,
        }),
    };
    let new = validate::new_session(&message, &caller.lab, &state.limits)?;
    let (session, created) = state
        .store
        .create_session_capped(&new, state.limits.max_sessions_per_lab)
        .await?;
    if created {
        tracing::info!(session = %session.id, lab = %session.lab, rig = %session.rig, spec = %session.spec.to_json(), "session created over REST");
    }
    let latest = state.store.latest_done(&session.id).await?;
    let view = session_view(&session, latest);
    if !created {
        return Ok(axum::Json(view).into_response());
    }
    let mut response = (StatusCode::CREATED, axum::Json(view)).into_response();
    let location = format!("/v1/sessions/{}", session.id);
    response.headers_mut().insert(
        header::LOCATION,
        HeaderValue::from_str(&location).expect("session ids are ascii"),
    );
    Ok(response)
}

/// Finish a session
///
/// No more rows (role rig): the session as stored. Refused (409) while rows of the spec are
/// missing.
#[utoipa::path(
    post,
    path = "/v1/sessions/{id}/finish",
    tag = "sessions",
    params(SessionId),
    responses(
        (status = 200, description = "Finished", body = helmholtz_proto::rest::SessionView),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
        (status = 409, response = openapi::Conflict),
    )
)]
pub(super) async fn finish_session(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::Json<helmholtz_proto::rest::SessionView>, ApiError> {
    caller.require(Role::Rig)?;
    session_path(&id)?;
    state.own_session(&caller, &id).await?;
    let session = state.store.finish_session(&id).await?;
    let latest = state.store.latest_done(&id).await?;
    Ok(axum::Json(session_view(&session, latest)))
}

/// Upload status
///
/// The committed count to resume an upload from (role rig or reader; the REST twin of gRPC
/// `GetUploadStatus`).
#[utoipa::path(
    get,
    path = "/v1/sessions/{id}/rows",
    tag = "sessions",
    params(SessionId),
    responses(
        (status = 200, description = "Where the upload stands", body = UploadStatusView),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
    )
)]
pub(super) async fn upload_status(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::Json<UploadStatusView>, ApiError> {
    caller.require_any(&[Role::Rig, Role::Reader])?;
    session_path(&id)?;
    let session = state.own_session(&caller, &id).await?;
    Ok(axum::Json(UploadStatusView {
        session_id: session.id,
        committed_rows: session.committed_rows,
        expected_rows: session.expected_rows,
        state: session_state(session.state),
    }))
}

fn session_state(state: store::SessionState) -> SessionState {
    match state {
        store::SessionState::Open => SessionState::Open,
        store::SessionState::Finished => SessionState::Finished,
    }
}

/// The query of `PUT /v1/sessions/{id}/rows`.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[allow(dead_code)]
struct RowsQuery {
    /// The pattern index of the body's first row (`GET .../rows` gives `committed_rows`, where
    /// to resume; rows below it are compared with the stored ones)
    start_row: u64,
}

/// The headers of `PUT /v1/sessions/{id}/rows`.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Header)]
#[allow(dead_code)]
struct RowsHeaders {
    /// The CRC-32C (Castagnoli) of the body, 8 hexadecimal digits; required unless
    /// Content-Digest is sent
    #[param(rename = "x-helmholtz-crc32c", pattern = "^(0[xX])?[0-9A-Fa-f]{1,8}$")]
    crc32c: Option<String>,
    /// RFC 9530: `sha-256=:BASE64:`, the body's SHA-256; required unless x-helmholtz-crc32c is
    /// sent
    #[param(rename = "content-digest")]
    content_digest: Option<String>,
    /// One id for every request of one client upload (1-64 of A-Z a-z 0-9 _ -): one writer
    /// per session at a time
    #[param(rename = "x-helmholtz-writer", pattern = "^[A-Za-z0-9_-]{1,64}$")]
    writer: Option<String>,
}

/// Upload rows
///
/// Rows `start_row..` of a session without gRPC (role rig), under the gRPC upload's rules: the
/// body (at most `max_chunk_bytes` of samples) is checked whole (checksum, dtype, shape, whole
/// rows, finite values) before anything is stored; rows below the committed count must equal
/// the stored ones byte for byte (409 naming the first that differs); a start above it is a gap
/// (416); another writer's upload in progress is 409. New rows and the new count commit in one
/// transaction.
#[utoipa::path(
    put,
    path = "/v1/sessions/{id}/rows",
    tag = "sessions",
    params(SessionId, RowsQuery, RowsHeaders),
    request_body(description = "The rows: an NPY array of the session's sample type in C order \
        (float64 (rows, channels); a camera's float32/uint16 (rows, height, width) or (rows, \
        height*width)), or the same samples raw and little-endian",
        content(("application/x-npy"), ("application/octet-stream"))),
    responses(
        (status = 200, description = "Stored (or already stored with these bytes)", body = UploadResult),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
        (status = 408, response = openapi::RequestTimeout),
        (status = 409, response = openapi::Conflict),
        (status = 413, response = openapi::TooLarge),
        (status = 416, response = openapi::RangeNotSatisfiable),
        (status = 422, response = openapi::ChecksumMismatch),
    )
)]
pub(super) async fn put_rows(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
    Query(query): Query<HashMap<String, String>>,
    headers: HeaderMap,
    body: Body,
) -> Result<axum::Json<UploadResult>, ApiError> {
    caller.require(Role::Rig)?;
    session_path(&id)?;
    let start_row = start_row(&query)?;
    let writer = validate::writer_id(
        headers
            .get(super::grpc::WRITER_HEADER)
            .map(|v| v.as_bytes()),
    )?;
    let checks = body_checks(&headers)?;
    let npy_body = body_kind(&headers)?;
    let session = state.own_session(&caller, &id).await?;
    let max_chunk = state.limits.max_chunk_bytes;
    let limit = if npy_body {
        max_chunk + NPY_HEADER_ROOM
    } else {
        max_chunk
    };
    let body = read_body_up_to(body, limit, "max_chunk_bytes").await?;
    checks.verify(&body)?;
    let rows = if npy_body {
        npy_rows(&body, &session)?
    } else {
        &body[..]
    };
    if rows.is_empty() {
        return Err(ApiError::invalid("body", "holds no rows"));
    }
    if rows.len() > max_chunk {
        return Err(ApiError::TooLarge {
            limit: "max_chunk_bytes",
            message: format!(
                "the body holds {} bytes of samples; one request may hold at most {max_chunk} (send fewer rows per request)",
                rows.len()
            ),
        });
    }
    validate::stored_rows("body", rows, &session)?;
    let guard = state.lock_writer(&session.id, &writer).await?;
    let outcome = state
        .store
        .append_raw(
            &session.id,
            Some(&guard.lease),
            start_row,
            session.row_bytes(),
            rows,
        )
        .await;
    guard.release().await;
    let outcome = outcome.map_err(|e| {
        if matches!(e, StoreError::RowMismatch { .. }) {
            metrics::counter!("helmholtz_upload_row_mismatches_total").increment(1);
        }
        ApiError::from(e)
    })?;
    metrics::counter!("helmholtz_upload_rows_total").increment(outcome.written);
    metrics::counter!("helmholtz_upload_bytes_total")
        .increment(outcome.written * session.row_bytes() as u64);
    Ok(axum::Json(UploadResult {
        session_id: session.id.clone(),
        committed_rows: outcome.committed_rows,
        rows_written: outcome.written,
        rows_skipped: outcome.matched,
        expected_rows: session.expected_rows,
        // Rows that equal stored ones may be sent again to a finished session; new ones not.
        state: session_state(session.state),
    }))
}

/// The required `start_row` query parameter: the index of the body's first row.
fn start_row(query: &HashMap<String, String>) -> Result<u64, ApiError> {
    let value = query.get("start_row").ok_or_else(|| {
        ApiError::invalid(
            "start_row",
            "is required: the index of the body's first row (GET the session for committed_rows to resume)",
        )
    })?;
    value.parse::<u64>().map_err(|_| {
        ApiError::invalid(
            "start_row",
            format!("must be a non-negative integer, got {value:?}"),
        )
    })
}

/// What a rows body must hash to: its CRC-32C ([`CRC_HEADER`]) and/or its SHA-256 (RFC 9530
/// `Content-Digest: sha-256=:BASE64:`, which `openssl dgst -sha256 -binary | base64` makes);
/// at least one.
struct BodyChecks {
    crc32c: Option<u32>,
    sha256: Option<[u8; 32]>,
}

impl BodyChecks {
    fn verify(&self, body: &[u8]) -> Result<(), ApiError> {
        if let Some(crc) = self.crc32c {
            let actual = crc32c::crc32c(body);
            if actual != crc {
                metrics::counter!("helmholtz_checksum_failures_total").increment(1);
                return Err(ApiError::DataLoss(format!(
                    "crc32c mismatch: {CRC_HEADER} says {crc:#010x}, the body has {actual:#010x}"
                )));
            }
        }
        if let Some(sha) = self.sha256 {
            use sha2::Digest;
            let actual: [u8; 32] = sha2::Sha256::digest(body).into();
            if actual != sha {
                metrics::counter!("helmholtz_checksum_failures_total").increment(1);
                return Err(ApiError::DataLoss(
                    "content-digest mismatch: the body's sha-256 differs from the one sent".into(),
                ));
            }
        }
        Ok(())
    }
}

fn body_checks(headers: &HeaderMap) -> Result<BodyChecks, ApiError> {
    let crc32c = headers.get(CRC_HEADER).map(crc_value).transpose()?;
    let sha256 = headers
        .get("content-digest")
        .map(sha256_value)
        .transpose()?;
    if crc32c.is_none() && sha256.is_none() {
        return Err(ApiError::invalid(
            CRC_HEADER,
            "is required: the CRC-32C (Castagnoli) of the body as 8 hexadecimal digits (or send \
             Content-Digest: sha-256=:BASE64: instead)",
        ));
    }
    Ok(BodyChecks { crc32c, sha256 })
}

fn crc_value(value: &HeaderValue) -> Result<u32, ApiError> {
    let text = value.to_str().unwrap_or("").trim();
    let digits = text
        .strip_prefix("0x")
        .or_else(|| text.strip_prefix("0X"))
        .unwrap_or(text);
    if digits.is_empty() || digits.len() > 8 || !digits.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(ApiError::invalid(
            CRC_HEADER,
            format!("must be the CRC-32C as 1-8 hexadecimal digits, got {text:?}"),
        ));
    }
    Ok(u32::from_str_radix(digits, 16).expect("checked hex"))
}

/// The `sha-256` member of an RFC 9530 `Content-Digest` dictionary.
fn sha256_value(value: &HeaderValue) -> Result<[u8; 32], ApiError> {
    use base64::Engine;
    let text = value.to_str().unwrap_or("");
    let member = text.split(',').find_map(|m| {
        let (key, value) = m.trim().split_once('=')?;
        key.trim()
            .eq_ignore_ascii_case("sha-256")
            .then_some(value.trim())
    });
    let Some(member) = member else {
        return Err(ApiError::invalid(
            "content-digest",
            format!("only sha-256 is accepted (sha-256=:BASE64:), got {text:?}"),
        ));
    };
    member
        .strip_prefix(':')
        .and_then(|m| m.strip_suffix(':'))
        .and_then(|b| base64::engine::general_purpose::STANDARD.decode(b).ok())
        .and_then(|bytes| <[u8; 32]>::try_from(bytes).ok())
        .ok_or_else(|| {
            ApiError::invalid(
                "content-digest",
                format!(
                    "sha-256 must be the 32-byte digest in base64 between colons, got {member:?}"
                ),
            )
        })
}

/// Whether the body is NPY (`application/x-npy`) rather than raw samples
/// (`application/octet-stream`).
fn body_kind(headers: &HeaderMap) -> Result<bool, ApiError> {
    let value = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let essence = value.split(';').next().unwrap_or("").trim();
    if essence.eq_ignore_ascii_case(NPY) {
        Ok(true)
    } else if essence.eq_ignore_ascii_case(RAW) {
        Ok(false)
    } else {
        Err(ApiError::invalid(
            "content-type",
            format!(
                "rows are sent as {NPY} (a NumPy array) or {RAW} (little-endian samples of the session's format); got {value:?}"
            ),
        ))
    }
}

/// The samples of an NPY body, after checking its dtype and shape against the session.
fn npy_rows<'b>(body: &'b [u8], session: &SessionRow) -> Result<&'b [u8], ApiError> {
    let mut reader = body;
    let header =
        npy::read_header(&mut reader).map_err(|e| ApiError::invalid("body", e.to_string()))?;
    let format = session.sample_format();
    let want = match format {
        SampleFormat::F64 => Dtype::F64,
        SampleFormat::F32 => Dtype::F32,
        SampleFormat::U16 => Dtype::U16,
    };
    if header.dtype != want {
        return Err(ApiError::invalid(
            "body",
            format!(
                "the array's dtype is {}; session {:?} stores {} samples ({}): convert before sending",
                header.dtype.descr(),
                session.id,
                format.name(),
                want.descr()
            ),
        ));
    }
    if header.fortran_order {
        return Err(ApiError::invalid(
            "body",
            "the array is in Fortran (column-major) order: send rows in C order (numpy.ascontiguousarray; MATLAB: transpose first)",
        ));
    }
    let shape = &header.shape;
    let fits = match session.camera {
        Some(c) => {
            let (h, w) = (c.height as u64, c.width as u64);
            matches!(shape.as_slice(), [_, a, b] if (*a, *b) == (h, w))
                || matches!(shape.as_slice(), [_, p] if *p == h * w)
        }
        None => {
            let ch = session.channels.len() as u64;
            matches!(shape.as_slice(), [_, c] if *c == ch) || (ch == 1 && shape.len() == 1)
        }
    };
    if !fits {
        let want = match session.camera {
            Some(c) => format!(
                "(rows, {}, {}) or (rows, {})",
                c.height,
                c.width,
                c.height as u64 * c.width as u64
            ),
            None if session.channels.len() == 1 => "(rows, 1) or (rows,)".into(),
            None => format!("(rows, {})", session.channels.len()),
        };
        return Err(ApiError::invalid(
            "body",
            format!(
                "the array's shape is {}; session {:?} takes {want}",
                header.shape_text(),
                session.id
            ),
        ));
    }
    let data = &body[header.data_offset as usize..];
    header
        .check_data_len(data.len() as u64, true)
        .map_err(|e| ApiError::invalid("body", e.to_string()))?;
    Ok(data)
}
