//! `POST /v1/reconstructions/{id}/primal`: the camera image `T p (+ ambient)` a projector
//! pattern would give, with the error against the measured frame for one of the session's own.

use std::collections::HashMap;
use std::time::Instant;

use axum::body::Bytes;
use axum::http::{HeaderMap, header};
use axum::response::Response;
use helmholtz_proto::rest::PrimalRequest;

use super::super::{ApiError, AppState, json};
use super::body::{Input, parse_input};
use super::cache::CachedResponse;
use super::response::{Format, not_modified, respond, strong_etag};
use super::{finished, finite_result};
use crate::auth::Principal;

pub async fn primal(
    state: &AppState,
    caller: &Principal,
    id: i64,
    query: &HashMap<String, String>,
    headers: &HeaderMap,
    body: Bytes,
) -> Result<Response, ApiError> {
    let format = Format::parse(query, &["format", "scale", "ambient"])?;
    let with_ambient = match query.get("ambient").map(String::as_str) {
        None | Some("include") => true,
        Some("exclude") => false,
        Some(other) => {
            return Err(ApiError::invalid(
                "ambient",
                format!("must be include or exclude, got {other:?}"),
            ));
        }
    };
    let (_, session) = finished(state, caller, id).await?;
    let Some(camera) = session.camera else {
        return Err(ApiError::FailedPrecondition(format!(
            "session {:?} has bucket detectors: a primal image needs a camera session's transport matrix",
            session.id
        )));
    };
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .map(|v| v.as_bytes())
        .unwrap_or(b"");
    let etag = strong_etag(&[
        b"primal-v1",
        &id.to_le_bytes(),
        format.tag().as_bytes(),
        &[with_ambient as u8],
        content_type,
        &body,
    ]);
    if let Some(r) = not_modified(headers, &etag) {
        return Ok(r);
    }
    if let Some(hit) = state.responses.get(&etag) {
        return Ok(respond(&etag, hit, None));
    }
    // An adaptive session's patterns are those of its issued index sequence.
    let spec = state.store.resolved_spec(&session).await?;
    let (pw, ph) = (spec.width() as usize, spec.height() as usize);
    let k = pw * ph;
    let t = state.transports.get(state, id).await?;
    // A T on a coarser grid (`projector_binning`) takes patterns at either grid.
    let (tw, th) = (t.projector().0 as usize, t.projector().1 as usize);
    let (pattern, measured_row) = match parse_input(headers, &body, "body")? {
        Input::Image {
            width,
            height,
            values,
        } if (tw, th) != (pw, ph)
            && values.len() == tw * th
            && (height == 1 || (width, height) == (tw, th)) =>
        {
            (values, None)
        }
        Input::Image {
            width,
            height,
            values,
        } => {
            if values.len() != k || (height != 1 && (width, height) != (pw, ph)) {
                return Err(ApiError::invalid(
                    "body",
                    format!(
                        "the pattern is {width}x{height} but the projector is {pw}x{ph} (or send {k} values as a 1-D array)"
                    ),
                ));
            }
            (values, None)
        }
        Input::Json(body) => {
            let body: PrimalRequest = json::decode(&body, r#"{"pattern_index": 0}"#)?;
            let i = body.pattern_index;
            if i >= spec.count() {
                return Err(ApiError::invalid(
                    "pattern_index",
                    format!(
                        "the session declares {} patterns (0..{}), got {i}",
                        spec.count(),
                        spec.count()
                    ),
                ));
            }
            let mut pattern = vec![0f32; k];
            helmholtz_proto::PatternGenerator::new(&spec).fill_values(i, &mut pattern);
            (pattern, Some(i))
        }
    };
    // A session-grid pattern lights a coarse T's blocks with its block means (each column of
    // the coarse T is its block's summed light).
    let pattern = if pattern.len() == k && (tw, th) != (pw, ph) && tw > 0 {
        let b = pw / tw;
        let mut coarse = vec![0f32; tw * th];
        for (i, v) in pattern.iter().enumerate() {
            coarse[(i / pw / b) * tw + (i % pw) / b] += v / (b * b) as f32;
        }
        coarse
    } else {
        pattern
    };
    let started = Instant::now();
    let mut predicted = tokio::task::spawn_blocking(move || t.primal(&pattern))
        .await
        .map_err(|e| ApiError::Internal(e.to_string()))?;
    if with_ambient {
        let images = state.store.dual_images(id).await?;
        if let Some(ambient) = images
            .iter()
            .find(|i| i.channel_name == "ambient" && i.data.len() == predicted.len())
        {
            predicted
                .iter_mut()
                .zip(&ambient.data)
                .for_each(|(p, a)| *p += a);
        }
    }
    finite_result(
        &predicted,
        if measured_row.is_some() {
            "pattern_index"
        } else {
            "body"
        },
    )?;
    let ms = started.elapsed().as_secs_f64() * 1e3;
    metrics::histogram!("helmholtz_relight_seconds", "kind" => "primal").record(ms / 1e3);
    let mut extra = Vec::new();
    if let Some(i) = measured_row {
        // Only rows the reconstruction used are "measured" for it; later rows are still real
        // frames, so compare against them too when they are stored.
        if let Some(bytes) = state
            .store
            .read_row(&session.id, i, session.row_bytes())
            .await?
        {
            let mut measured = Vec::with_capacity(predicted.len());
            session.sample_format().decode_f32(&bytes, &mut measured);
            let (mut e2, mut n2, mut peak) = (0f64, 0f64, 0f64);
            for (p, m) in predicted.iter().zip(&measured) {
                e2 += (*p as f64 - *m as f64).powi(2);
                n2 += (*m as f64).powi(2);
                peak = peak.max(*m as f64);
            }
            let mse = e2 / measured.len().max(1) as f64;
            extra.push((
                "x-helmholtz-relative-error",
                format!("{:.6e}", (e2 / n2).sqrt()),
            ));
            extra.push((
                "x-helmholtz-psnr-db",
                format!("{:.3}", 10.0 * (peak * peak / mse).log10()),
            ));
            extra.push(("x-helmholtz-measured-row", i.to_string()));
        }
    }
    let (bytes, mime) = format.encode(camera.width, camera.height, &predicted);
    let cached = CachedResponse {
        bytes: Bytes::from(bytes),
        mime,
        headers: extra,
    };
    state.responses.put(etag.clone(), cached.clone());
    Ok(respond(&etag, cached, Some(ms)))
}
