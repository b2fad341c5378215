//! Files derived from a finished bucket reconstruction's dual images: photometric stereo
//! (normals, albedo, residual, report) and the colour composite.

use std::collections::HashMap;
use std::time::Instant;

use axum::body::Bytes;
use axum::http::HeaderMap;
use axum::response::Response;
use serde_json::{Map, Value};

use super::super::images::{self, Scale};
use super::super::{ApiError, AppState};
use super::cache::CachedResponse;
use super::finished;
use super::response::{not_modified, respond, strong_etag};
use crate::auth::Principal;
use crate::store::StoredImage;

/// Files derived from a finished bucket reconstruction's dual images:
/// `normals.png|normals.npy|albedo.png|albedo.npy|residual.npy|photometric.json` (photometric stereo from three or
/// more channels at the session's declared detector directions; query `gains`,
/// `shadow_threshold`, `dark_threshold`) and `composite.png` (channels named r, g, b).
pub const DERIVED_FILES: [&str; 7] = [
    "normals.png",
    "normals.npy",
    "albedo.png",
    "albedo.npy",
    "residual.npy",
    "photometric.json",
    "composite.png",
];

pub async fn derived(
    state: &AppState,
    caller: &Principal,
    id: i64,
    file: &str,
    query: &HashMap<String, String>,
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    let (_, session) = finished(state, caller, id).await?;
    if session.camera.is_some() {
        return Err(ApiError::FailedPrecondition(format!(
            "{file} is made from a bucket session's per-detector dual images; session {:?} is a camera session (relight it instead)",
            session.id
        )));
    }
    let allowed: &[&str] = if file == "composite.png" {
        &[]
    } else {
        &["gains", "shadow_threshold", "dark_threshold"]
    };
    if let Some(key) = query.keys().find(|k| !allowed.contains(&k.as_str())) {
        return Err(ApiError::invalid(
            key.clone(),
            if allowed.is_empty() {
                "unknown query parameter; this file takes none".to_string()
            } else {
                format!("unknown query parameter; expected {}", allowed.join(", "))
            },
        ));
    }
    let mut keyed: Vec<(&String, &String)> = query.iter().collect();
    keyed.sort();
    let key_text = format!("{file}?{keyed:?}");
    let etag = strong_etag(&[b"derived-v1", &id.to_le_bytes(), key_text.as_bytes()]);
    if let Some(r) = not_modified(headers, &etag) {
        return Ok(r);
    }
    if let Some(hit) = state.responses.get(&etag) {
        return Ok(respond(&etag, hit, None));
    }
    let images = state.store.dual_images(id).await?;
    let started = Instant::now();
    let (bytes, mime, extra) = if file == "composite.png" {
        let Some([r, g, b]) = crate::recon::colour::colour_channels(&session.channels) else {
            return Err(ApiError::FailedPrecondition(format!(
                "a colour composite needs channels named r, g, b (or red, green, blue); session {:?} has {}",
                session.id,
                session.channels.join(", ")
            )));
        };
        let pick = |c: usize| {
            images
                .iter()
                .find(|i| i.channel_index as usize == c)
                .map(|i| &i.data[..])
        };
        let (Some(r), Some(g), Some(b)) = (pick(r), pick(g), pick(b)) else {
            return Err(ApiError::Internal(
                "a colour channel's dual image is missing".into(),
            ));
        };
        let first = &images[0];
        let rgb = crate::recon::colour::composite(r, g, b);
        (
            images::rgb_png(first.width, first.height, &rgb),
            "image/png",
            Vec::new(),
        )
    } else {
        if session.directions.is_empty() {
            return Err(ApiError::FailedPrecondition(format!(
                "session {:?} declares no detector directions (DetectorLayout.directions): photometric stereo needs them",
                session.id
            )));
        }
        let mut params = Map::new();
        for (k, v) in query {
            let value = match v.parse::<f64>() {
                Ok(x) if k != "gains" => Value::from(x),
                _ => Value::String(v.clone()),
            };
            params.insert(k.clone(), value);
        }
        let options =
            crate::recon::photometric::PhotometricOptions::from_params(&Value::Object(params))
                .map_err(|e| ApiError::invalid(e.field(), e.to_string()))?;
        let mut ordered: Vec<&StoredImage> = images.iter().collect();
        ordered.sort_by_key(|i| i.channel_index);
        let (w, h) = (ordered[0].width, ordered[0].height);
        let directions = session.directions.clone();
        let data: Vec<Vec<f32>> = ordered.iter().map(|i| i.data.clone()).collect();
        let (map, report) = tokio::task::spawn_blocking(move || {
            let views: Vec<&[f32]> = data.iter().map(|d| &d[..]).collect();
            crate::recon::photometric::photometric_stereo(&views, &directions, w, h, &options)
        })
        .await
        .map_err(|e| ApiError::Internal(e.to_string()))?
        .map_err(|e| {
            // Query options are the request's fault; images and directions are the session's.
            let field = e.field();
            if field.starts_with("directions")
                || field.starts_with("images")
                || field == "width"
                || field == "height"
            {
                ApiError::FailedPrecondition(format!("session {:?}: {field}: {e}", session.id))
            } else {
                ApiError::invalid(field, e.to_string())
            }
        })?;
        let extra = Vec::new();
        let finite = |v: &[f32]| {
            v.iter()
                .map(|x| if x.is_finite() { *x } else { 0.0 })
                .collect::<Vec<f32>>()
        };
        match file {
            "normals.png" => (images::normal_map_png(&map), "image/png", extra),
            "normals.npy" => (
                images::npy_f32_hwc(w, h, 3, &map.normals_interleaved()),
                "application/octet-stream",
                extra,
            ),
            "albedo.png" => (
                images::png_8bit(w, h, &finite(&map.albedo), Scale::Percentile),
                "image/png",
                extra,
            ),
            "albedo.npy" => (
                images::npy_f32(w, h, &map.albedo),
                "application/octet-stream",
                extra,
            ),
            "photometric.json" => (
                serde_json::to_vec_pretty(&report).unwrap_or_default(),
                "application/json",
                extra,
            ),
            _ => (
                images::npy_f32(w, h, &map.residual),
                "application/octet-stream",
                extra,
            ),
        }
    };
    let ms = started.elapsed().as_secs_f64() * 1e3;
    let cached = CachedResponse {
        bytes: Bytes::from(bytes),
        mime,
        headers: extra,
    };
    state.responses.put(etag.clone(), cached.clone());
    Ok(respond(&etag, cached, Some(ms)))
}
