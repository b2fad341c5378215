//! `POST /v1/reconstructions/{id}/relight`: the virtual light from the body, and the dual image
//! under it (camera sessions: `T^T c'`; bucket sessions: the channels' images weighted).

use std::collections::HashMap;
use std::time::Instant;

use axum::body::Bytes;
use axum::http::{HeaderMap, header};
use axum::response::Response;
use helmholtz_proto::rest::{LightPreset, LightRequest, RelightRequest};

use super::super::{ApiError, AppState, json};
use super::body::{Input, parse_input};
use super::cache::CachedResponse;
use super::response::{Format, not_modified, respond, strong_etag};
use super::{finished, finite_result};
use crate::auth::Principal;
use crate::recon::transport::Light;
use crate::store::StoredImage;

/// The virtual light of a camera session: `m` weights on the camera pixels.
fn camera_light(input: Input, cw: usize, ch: usize) -> Result<Vec<f32>, ApiError> {
    let m = cw * ch;
    let light = match input {
        Input::Image {
            width,
            height,
            values,
        } => {
            if values.len() != m || (height != 1 && (width, height) != (cw, ch)) {
                return Err(ApiError::invalid(
                    "body",
                    format!(
                        "the light image is {width}x{height} but the camera is {cw}x{ch} (or send {m} values as a 1-D array)"
                    ),
                ));
            }
            values
        }
        Input::Json(body) => {
            let body: RelightRequest = json::decode(&body, r#"{"light": {"preset": "full"}}"#)?;
            let light = match body.light {
                LightRequest::Weights { .. } => {
                    return Err(ApiError::invalid(
                        "light.weights",
                        "per-channel weights relight bucket sessions; this is a camera session: use a preset or a camera-sized image",
                    ));
                }
                LightRequest::Preset(LightPreset::Full) => Light::Full,
                LightRequest::Preset(LightPreset::Disc { x, y, radius }) => {
                    Light::Disc { x, y, radius }
                }
                LightRequest::Preset(LightPreset::Stripe { x0, x1 }) => Light::Stripe { x0, x1 },
            };
            light
                .weights(cw, ch)
                .map_err(|e| ApiError::invalid(e.field, e.message))?
        }
    };
    Ok(light)
}

/// The relit dual image of a bucket session: the channels' dual images weighted.
fn bucket_relight(
    input: Input,
    images: &[StoredImage],
    channels: &[String],
) -> Result<StoredImage, ApiError> {
    let Input::Json(body) = input else {
        return Err(ApiError::invalid(
            "body",
            format!(
                "a bucket session is relit by per-channel weights, e.g. {{\"light\": {{\"weights\": {{\"{}\": 1.0}}}}}}",
                channels[0]
            ),
        ));
    };
    let body: RelightRequest = json::decode(&body, r#"{"light": {"weights": {"r": 1.0}}}"#)?;
    let weights: Vec<f64> = match body.light {
        LightRequest::Weights { weights } => {
            let mut out = vec![0.0; channels.len()];
            for (name, v) in weights {
                let i = channels.iter().position(|c| *c == name).ok_or_else(|| {
                    ApiError::invalid(
                        format!("light.weights.{name}"),
                        format!("no such channel; this session has {}", channels.join(", ")),
                    )
                })?;
                if v.abs() > f32::MAX as f64 {
                    return Err(ApiError::invalid(
                        format!("light.weights.{name}"),
                        format!(
                            "{v} is outside the 32-bit float range of the images (|w| <= {:e})",
                            f32::MAX
                        ),
                    ));
                }
                out[i] = v;
            }
            out
        }
        LightRequest::Preset(LightPreset::Full) => vec![1.0; channels.len()],
        LightRequest::Preset(p) => {
            let name = match p {
                LightPreset::Disc { .. } => "disc",
                _ => "stripe",
            };
            return Err(ApiError::invalid(
                "light.preset",
                format!(
                    "a bucket session has no camera: the only preset is \"full\" (all channels), got {name:?}"
                ),
            ));
        }
    };
    let first = images
        .first()
        .ok_or_else(|| ApiError::Internal("finished reconstruction without images".into()))?;
    // Summed in f64, then checked: weights that make any pixel overflow f32 are refused (an
    // image of inf/NaN is no answer).
    let mut sum = vec![0f64; first.data.len()];
    for image in images {
        let w = weights
            .get(image.channel_index as usize)
            .copied()
            .unwrap_or(0.0);
        if w != 0.0 {
            sum.iter_mut()
                .zip(&image.data)
                .for_each(|(d, v)| *d += w * *v as f64);
        }
    }
    let data: Vec<f32> = sum.iter().map(|v| *v as f32).collect();
    if let Some(i) = data.iter().position(|v| !v.is_finite()) {
        return Err(ApiError::invalid(
            "light.weights",
            format!(
                "the weighted sum overflows 32-bit floats (pixel {i} would be {:e}); use smaller weights",
                sum[i]
            ),
        ));
    }
    Ok(StoredImage {
        channel_index: 0,
        channel_name: "relit".into(),
        width: first.width,
        height: first.height,
        data,
    })
}

pub async fn relight(
    state: &AppState,
    caller: &Principal,
    id: i64,
    query: &HashMap<String, String>,
    headers: &HeaderMap,
    body: Bytes,
) -> Result<Response, ApiError> {
    let format = Format::parse(query, &["format", "scale"])?;
    let (_, session) = finished(state, caller, id).await?;
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .map(|v| v.as_bytes())
        .unwrap_or(b"");
    let etag = strong_etag(&[
        b"relight-v1",
        &id.to_le_bytes(),
        format.tag().as_bytes(),
        content_type,
        &body,
    ]);
    if let Some(r) = not_modified(headers, &etag) {
        return Ok(r);
    }
    if let Some(hit) = state.responses.get(&etag) {
        return Ok(respond(&etag, hit, None));
    }
    let input = parse_input(headers, &body, "body")?;
    let started = Instant::now();
    let (width, height, data) = match session.camera {
        Some(camera) => {
            let field = match input {
                Input::Json(_) => "light",
                Input::Image { .. } => "body",
            };
            let light = camera_light(input, camera.width as usize, camera.height as usize)?;
            let t = state.transports.get(state, id).await?;
            let (pw, ph) = t.projector();
            let data = tokio::task::spawn_blocking(move || t.relight(&light))
                .await
                .map_err(|e| ApiError::Internal(e.to_string()))?;
            finite_result(&data, field)?;
            (pw, ph, data)
        }
        None => {
            let images = state.store.dual_images(id).await?;
            let image = bucket_relight(input, &images, &session.channels)?;
            (image.width, image.height, image.data)
        }
    };
    let ms = started.elapsed().as_secs_f64() * 1e3;
    metrics::histogram!("helmholtz_relight_seconds", "kind" => "relight").record(ms / 1e3);
    let (bytes, mime) = format.encode(width, height, &data);
    let cached = CachedResponse {
        bytes: Bytes::from(bytes),
        mime,
        headers: Vec::new(),
    };
    state.responses.put(etag.clone(), cached.clone());
    Ok(respond(&etag, cached, Some(ms)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_light_the_pixels_they_name() {
        let disc = camera_light(
            Input::Json(Bytes::from_static(
                br#"{"light": {"preset": "disc", "x": 2, "y": 2, "radius": 1}}"#,
            )),
            4,
            4,
        )
        .unwrap();
        // Pixel centres within 1 of (2, 2): (1.5,1.5), (2.5,1.5), (1.5,2.5), (2.5,2.5).
        assert_eq!(disc.iter().sum::<f32>(), 4.0);
        assert_eq!(disc[5] + disc[6] + disc[9] + disc[10], 4.0);
        let stripe = camera_light(
            Input::Json(Bytes::from_static(
                br#"{"light": {"preset": "stripe", "x0": 1, "x1": 3}}"#,
            )),
            4,
            2,
        )
        .unwrap();
        assert_eq!(stripe, vec![0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0]);
        let err = camera_light(
            Input::Json(Bytes::from_static(
                br#"{"light": {"preset": "disc", "x": 2, "y": 2}}"#,
            )),
            4,
            4,
        );
        assert!(
            matches!(err, Err(ApiError::InvalidArgument { ref field, .. }) if field == "light.radius"),
            "{err:?}"
        );
    }
}
