//! What every answer shares: the output encoding, the strong ETag and `If-None-Match`, and the
//! response headers (content type, caching, `server-timing`).

use std::collections::HashMap;

use axum::body::Body;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};

use super::super::ApiError;
use super::super::images::{self, Scale};
use super::cache::CachedResponse;

/// Output encodings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Format {
    Png(Scale),
    Tiff,
    Npy,
}

impl Format {
    pub(super) fn parse(
        query: &HashMap<String, String>,
        allowed: &[&str],
    ) -> Result<Format, ApiError> {
        if let Some(key) = query.keys().find(|k| !allowed.contains(&k.as_str())) {
            return Err(ApiError::invalid(
                key.clone(),
                format!("unknown query parameter; expected {}", allowed.join(", ")),
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
        match query.get("format").map(String::as_str) {
            None | Some("png") => Ok(Format::Png(scale)),
            Some("tiff") => Ok(Format::Tiff),
            Some("npy") => Ok(Format::Npy),
            Some(other) => Err(ApiError::invalid(
                "format",
                format!("must be png, tiff or npy, got {other:?}"),
            )),
        }
    }

    pub(super) fn tag(self) -> &'static str {
        match self {
            Format::Png(Scale::Percentile) => "png-p",
            Format::Png(Scale::MinMax) => "png-m",
            Format::Tiff => "tiff",
            Format::Npy => "npy",
        }
    }

    pub(super) fn encode(self, width: u32, height: u32, data: &[f32]) -> (Vec<u8>, &'static str) {
        match self {
            Format::Png(scale) => (images::png_8bit(width, height, data, scale), "image/png"),
            Format::Tiff => (images::tiff_f32(width, height, data), "image/tiff"),
            Format::Npy => (
                images::npy_f32(width, height, data),
                "application/octet-stream",
            ),
        }
    }
}

/// A strong ETag: a hash of the length-prefixed parts that name an answer.
pub(super) fn strong_etag(parts: &[&[u8]]) -> String {
    let mut h = Sha256::new();
    for p in parts {
        h.update((p.len() as u64).to_le_bytes());
        h.update(p);
    }
    let d = h.finalize();
    let hex: String = d[..16].iter().map(|b| format!("{b:02x}")).collect();
    format!("\"{hex}\"")
}

/// 304 when `If-None-Match` names `etag` (or `*`).
pub(super) fn not_modified(headers: &HeaderMap, etag: &str) -> Option<Response> {
    let hit = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == etag || t.trim() == "*"));
    hit.then(|| {
        let mut r = StatusCode::NOT_MODIFIED.into_response();
        r.headers_mut()
            .insert(header::ETAG, HeaderValue::from_str(etag).expect("ascii"));
        r
    })
}

/// The answer `cached` under `etag`; `computed_ms` None: served from the cache.
pub(super) fn respond(etag: &str, cached: CachedResponse, computed_ms: Option<f64>) -> Response {
    let mut response = Body::from(cached.bytes).into_response();
    let h = response.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(cached.mime));
    h.insert(header::ETAG, HeaderValue::from_str(etag).expect("ascii"));
    h.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static("private, max-age=31536000, immutable"),
    );
    for (name, value) in &cached.headers {
        if let Ok(v) = HeaderValue::from_str(value) {
            h.insert(*name, v);
        }
    }
    let timing = match computed_ms {
        Some(ms) => format!("compute;dur={ms:.3}"),
        None => "cache;desc=\"hit\"".to_string(),
    };
    h.insert(
        "server-timing",
        HeaderValue::from_str(&timing).expect("ascii"),
    );
    response
}
