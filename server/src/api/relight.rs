//! Relighting over HTTP.
//!
//! - `POST /v1/reconstructions/{id}/relight`: the dual image `p' = T^T c'` under a virtual light
//!   `c'` at the detector side: per-channel weights (bucket sessions), a camera-sized image (PNG
//!   or NPY body), or a preset (`full`, a `disc`, a `stripe`; camera sessions).
//! - `POST /v1/reconstructions/{id}/primal`: the camera image `c = T p + ambient` a projector
//!   pattern `p` would give (PNG or NPY body, or `{"pattern_index": i}` for one of the session's
//!   own patterns; then the response also carries the error against the measured frame).
//!
//! Reconstructions never change once done, so a response is a function of (reconstruction,
//! request body, format): its strong ETag is a hash of those, `If-None-Match` answers 304 without
//! computing, and recent responses are kept ([`ResponseCache`]). Decoded transport matrices stay
//! in memory ([`TransportCache`], least recently used dropped first).

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use axum::body::{Body, Bytes};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use helmholtz_proto::npy;
use serde_json::{Map, Value};
use sha2::{Digest, Sha256};

use super::images::{self, Scale};
use super::{ApiError, AppState};
use crate::auth::Principal;
use crate::recon::transport::Light;
use crate::recon::transport::TransportMatrix;
use crate::store::{ReconstructionRow, SessionRow, StoredImage};

/// Decoded transport matrices by reconstruction id, within a byte budget.
#[derive(Debug)]
pub struct TransportCache {
    budget: usize,
    /// Most recently used last.
    entries: Mutex<Vec<(i64, Arc<TransportMatrix>, usize)>>,
}

impl TransportCache {
    pub fn new(budget: usize) -> Self {
        TransportCache {
            budget,
            entries: Mutex::new(Vec::new()),
        }
    }

    /// The decoded T of a finished camera reconstruction (decoded off the async threads).
    pub async fn get(&self, state: &AppState, id: i64) -> Result<Arc<TransportMatrix>, ApiError> {
        {
            let mut entries = self.entries.lock().expect("transport cache");
            if let Some(pos) = entries.iter().position(|(i, _, _)| *i == id) {
                let e = entries.remove(pos);
                let t = e.1.clone();
                entries.push(e);
                return Ok(t);
            }
        }
        let bytes = state.store.transport(id).await?.ok_or_else(|| {
            ApiError::Internal(format!(
                "reconstruction {id} is done but has no stored transport matrix"
            ))
        })?;
        let size = bytes.len();
        let t = tokio::task::spawn_blocking(move || TransportMatrix::decode(&bytes))
            .await
            .map_err(|e| ApiError::Internal(e.to_string()))?
            .map_err(|e| {
                ApiError::Internal(format!(
                    "stored transport matrix of reconstruction {id}: {e}"
                ))
            })?;
        let t = Arc::new(t);
        let mut entries = self.entries.lock().expect("transport cache");
        if !entries.iter().any(|(i, _, _)| *i == id) {
            entries.push((id, t.clone(), size));
            while entries.len() > 1 && entries.iter().map(|e| e.2).sum::<usize>() > self.budget {
                entries.remove(0);
            }
        }
        Ok(t)
    }
}

/// Encoded responses by ETag, within a byte budget (oldest dropped first).
#[derive(Debug)]
pub struct ResponseCache {
    budget: usize,
    inner: Mutex<(HashMap<String, CachedResponse>, VecDeque<String>, usize)>,
}

#[derive(Clone, Debug)]
pub struct CachedResponse {
    bytes: Bytes,
    mime: &'static str,
    headers: Vec<(&'static str, String)>,
}

impl ResponseCache {
    pub fn new(budget: usize) -> Self {
        ResponseCache {
            budget,
            inner: Mutex::new((HashMap::new(), VecDeque::new(), 0)),
        }
    }

    fn get(&self, etag: &str) -> Option<CachedResponse> {
        self.inner
            .lock()
            .expect("response cache")
            .0
            .get(etag)
            .cloned()
    }

    fn put(&self, etag: String, response: CachedResponse) {
        if response.bytes.len() > self.budget {
            return;
        }
        let mut inner = self.inner.lock().expect("response cache");
        let (map, order, used) = &mut *inner;
        if map.contains_key(&etag) {
            return;
        }
        *used += response.bytes.len();
        map.insert(etag.clone(), response);
        order.push_back(etag);
        while *used > self.budget {
            let Some(old) = order.pop_front() else { break };
            if let Some(r) = map.remove(&old) {
                *used -= r.bytes.len();
            }
        }
    }
}

/// Output encodings.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Format {
    Png(Scale),
    Tiff,
    Npy,
}

impl Format {
    fn parse(query: &HashMap<String, String>, allowed: &[&str]) -> Result<Format, ApiError> {
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

    fn tag(self) -> &'static str {
        match self {
            Format::Png(Scale::Percentile) => "png-p",
            Format::Png(Scale::MinMax) => "png-m",
            Format::Tiff => "tiff",
            Format::Npy => "npy",
        }
    }

    fn encode(self, width: u32, height: u32, data: &[f32]) -> (Vec<u8>, &'static str) {
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

/// A request body: a JSON object or an image (PNG, NPY).
enum Input {
    Json(Map<String, Value>),
    Image {
        width: usize,
        height: usize,
        values: Vec<f32>,
    },
}

fn parse_input(headers: &HeaderMap, body: &[u8], what: &str) -> Result<Input, ApiError> {
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("application/json");
    let mime = content_type
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    match mime.as_str() {
        "application/json" | "" => {
            let value: Value = serde_json::from_slice(body)
                .map_err(|e| ApiError::invalid("body", format!("not JSON: {e}")))?;
            match value {
                Value::Object(map) => Ok(Input::Json(map)),
                _ => Err(ApiError::invalid("body", "must be a JSON object")),
            }
        }
        "image/png" => {
            let (width, height, values) = decode_png(body)
                .map_err(|e| ApiError::invalid(what, format!("not a readable PNG: {e}")))?;
            Ok(Input::Image {
                width,
                height,
                values,
            })
        }
        "application/x-npy" | "application/octet-stream" => {
            let (width, height, values) =
                decode_npy(body).map_err(|e| ApiError::invalid(what, e))?;
            Ok(Input::Image {
                width,
                height,
                values,
            })
        }
        other => Err(ApiError::invalid(
            "content-type",
            format!(
                "{other:?} is not accepted; send application/json, image/png or application/x-npy"
            ),
        )),
    }
}

/// A grey (or colour, reduced to Rec. 709 luma) PNG of 1-16 bits as values in [0, 1].
fn decode_png(bytes: &[u8]) -> Result<(usize, usize, Vec<f32>), String> {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(|e| e.to_string())?;
    let mut buf = vec![0; reader.output_buffer_size().ok_or("image too large")?];
    let info = reader.next_frame(&mut buf).map_err(|e| e.to_string())?;
    let (w, h) = (info.width as usize, info.height as usize);
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err("indexed colour after expansion".into()),
    };
    let sixteen = info.bit_depth == png::BitDepth::Sixteen;
    let max = if sixteen { 65535.0 } else { 255.0 };
    let sample = |i: usize| -> f32 {
        if sixteen {
            u16::from_be_bytes([buf[2 * i], buf[2 * i + 1]]) as f32 / max
        } else {
            buf[i] as f32 / max
        }
    };
    let values = (0..w * h)
        .map(|p| {
            let base = p * channels;
            if channels >= 3 {
                0.2126 * sample(base) + 0.7152 * sample(base + 1) + 0.0722 * sample(base + 2)
            } else {
                sample(base)
            }
        })
        .collect();
    Ok((w, h, values))
}

/// A 1-D or 2-D NPY array ([`helmholtz_proto::npy`]: float32/64 or an integer type, either byte
/// order, C or Fortran order) as f32; 1-D arrays come back as width = len, height = 1.
fn decode_npy(bytes: &[u8]) -> Result<(usize, usize, Vec<f32>), String> {
    let header = npy::read_header(&mut &bytes[..]).map_err(|e| e.to_string())?;
    let (height, width) = match header.shape.as_slice() {
        &[n] => (1, n as usize),
        &[h, w] => (h as usize, w as usize),
        _ => {
            return Err(format!(
                "the array must be 1-D or 2-D, got shape {}",
                header.shape_text()
            ));
        }
    };
    let (_, values) = npy::decode_f32(bytes).map_err(|e| e.to_string())?;
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(format!("value {i} is not finite"));
    }
    Ok((width, height, values))
}

fn strong_etag(parts: &[&[u8]]) -> String {
    let mut h = Sha256::new();
    for p in parts {
        h.update((p.len() as u64).to_le_bytes());
        h.update(p);
    }
    let d = h.finalize();
    let hex: String = d[..16].iter().map(|b| format!("{b:02x}")).collect();
    format!("\"{hex}\"")
}

fn not_modified(headers: &HeaderMap, etag: &str) -> Option<Response> {
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

fn respond(etag: &str, cached: CachedResponse, computed_ms: Option<f64>) -> Response {
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

/// The caller's finished reconstruction and its session.
async fn finished(
    state: &AppState,
    caller: &Principal,
    id: i64,
) -> Result<(ReconstructionRow, SessionRow), ApiError> {
    let r = state.own_reconstruction(caller, id).await?;
    if r.state != "done" {
        return Err(ApiError::FailedPrecondition(format!(
            "reconstruction {id} is {}; relighting needs a finished reconstruction",
            r.state
        )));
    }
    let session = state.store.session(&r.session_id).await?;
    Ok((r, session))
}

fn number(map: &Map<String, Value>, key: &str, field: &str) -> Result<f64, ApiError> {
    match map.get(key) {
        Some(Value::Number(n)) if n.as_f64().is_some_and(f64::is_finite) => {
            Ok(n.as_f64().expect("checked"))
        }
        Some(other) => Err(ApiError::invalid(
            format!("{field}.{key}"),
            format!("must be a finite number, got {other}"),
        )),
        None => Err(ApiError::invalid(format!("{field}.{key}"), "is required")),
    }
}

/// Refuses a computed image holding inf or NaN (the input's values overflow 32-bit floats),
/// naming the input `field`.
fn finite_result(data: &[f32], field: &str) -> Result<(), ApiError> {
    match data.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => Err(ApiError::invalid(
            field,
            format!(
                "the result is not finite at pixel {i} ({}): the values overflow 32-bit floats; scale them down",
                data[i]
            ),
        )),
    }
}

fn only_keys(map: &Map<String, Value>, allowed: &[&str], field: &str) -> Result<(), ApiError> {
    match map.keys().find(|k| !allowed.contains(&k.as_str())) {
        Some(k) => Err(ApiError::invalid(
            if field.is_empty() {
                k.clone()
            } else {
                format!("{field}.{k}")
            },
            format!("unknown field; expected {}", allowed.join(", ")),
        )),
        None => Ok(()),
    }
}

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
            only_keys(&body, &["light"], "")?;
            let Some(Value::Object(light)) = body.get("light") else {
                return Err(ApiError::invalid(
                    "light",
                    "is required: an object such as {\"preset\": \"full\"}",
                ));
            };
            if light.contains_key("weights") {
                return Err(ApiError::invalid(
                    "light.weights",
                    "per-channel weights relight bucket sessions; this is a camera session: use a preset or a camera-sized image",
                ));
            }
            let preset = match light.get("preset") {
                Some(Value::String(p)) => p.as_str(),
                Some(_) => return Err(ApiError::invalid("light.preset", "must be a string")),
                None => {
                    return Err(ApiError::invalid(
                        "light.preset",
                        "is required: full, disc or stripe",
                    ));
                }
            };
            let light = match preset {
                "full" => {
                    only_keys(light, &["preset"], "light")?;
                    Light::Full
                }
                "disc" => {
                    only_keys(light, &["preset", "x", "y", "radius"], "light")?;
                    Light::Disc {
                        x: number(light, "x", "light")?,
                        y: number(light, "y", "light")?,
                        radius: number(light, "radius", "light")?,
                    }
                }
                "stripe" => {
                    only_keys(light, &["preset", "x0", "x1"], "light")?;
                    Light::Stripe {
                        x0: number(light, "x0", "light")?,
                        x1: number(light, "x1", "light")?,
                    }
                }
                other => {
                    return Err(ApiError::invalid(
                        "light.preset",
                        format!("must be full, disc or stripe, got {other:?}"),
                    ));
                }
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
    only_keys(&body, &["light"], "")?;
    let Some(Value::Object(light)) = body.get("light") else {
        return Err(ApiError::invalid(
            "light",
            "is required: {\"weights\": {CHANNEL: WEIGHT, ...}} or {\"preset\": \"full\"}",
        ));
    };
    let weights: Vec<f64> = match (light.get("weights"), light.get("preset")) {
        (Some(Value::Object(w)), None) => {
            only_keys(light, &["weights"], "light")?;
            let mut out = vec![0.0; channels.len()];
            for name in w.keys() {
                let i = channels.iter().position(|c| c == name).ok_or_else(|| {
                    ApiError::invalid(
                        format!("light.weights.{name}"),
                        format!("no such channel; this session has {}", channels.join(", ")),
                    )
                })?;
                let v = number(w, name, "light.weights")?;
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
        (None, Some(Value::String(p))) if p == "full" => {
            only_keys(light, &["preset"], "light")?;
            vec![1.0; channels.len()]
        }
        (None, Some(p)) => {
            return Err(ApiError::invalid(
                "light.preset",
                format!(
                    "a bucket session has no camera: the only preset is \"full\" (all channels), got {p}"
                ),
            ));
        }
        _ => return Err(ApiError::invalid("light", "give either weights or preset")),
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
    let (pw, ph) = (
        session.spec.width() as usize,
        session.spec.height() as usize,
    );
    let k = pw * ph;
    let (pattern, measured_row) = match parse_input(headers, &body, "body")? {
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
        Input::Json(map) => {
            only_keys(&map, &["pattern_index"], "")?;
            let i = match map.get("pattern_index") {
                Some(Value::Number(n)) if n.as_u64().is_some() => n.as_u64().expect("checked"),
                Some(other) => {
                    return Err(ApiError::invalid(
                        "pattern_index",
                        format!("must be a non-negative integer, got {other}"),
                    ));
                }
                None => {
                    return Err(ApiError::invalid(
                        "pattern_index",
                        "is required (or send the pattern as a PNG or NPY body)",
                    ));
                }
            };
            if i >= session.spec.count() {
                return Err(ApiError::invalid(
                    "pattern_index",
                    format!(
                        "the session declares {} patterns (0..{}), got {i}",
                        session.spec.count(),
                        session.spec.count()
                    ),
                ));
            }
            let mut pattern = vec![0f32; k];
            helmholtz_proto::PatternGenerator::new(&session.spec).fill_values(i, &mut pattern);
            (pattern, Some(i))
        }
    };
    let started = Instant::now();
    let t = state.transports.get(state, id).await?;
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_bodies_parse_and_bad_ones_say_why() {
        let values = [0.5f32, 1.0, 2.0, 3.0, 4.0, 5.0];
        let bytes = images::npy_f32(3, 2, &values);
        assert_eq!(decode_npy(&bytes).unwrap(), (3, 2, values.to_vec()));
        let wide = images::npy_f64(1, 4, &[1.0, 2.0, 3.0, 4.0]);
        assert_eq!(decode_npy(&wide).unwrap(), (4, 1, vec![1.0, 2.0, 3.0, 4.0]));
        assert!(decode_npy(b"nope").unwrap_err().contains("magic"));
        let mut short = bytes.clone();
        short.pop();
        assert!(decode_npy(&short).unwrap_err().contains("bytes"));
        let cube = npy::write_f32(&[1, 1, 2], &[1.0, 2.0]);
        assert!(decode_npy(&cube).unwrap_err().contains("1-D or 2-D"));
        let u16_be = npy::Dtype {
            kind: npy::Kind::Uint,
            size: 2,
            big_endian: true,
        };
        let mut be = npy::header(u16_be, &[2], false);
        be.extend_from_slice(&[0, 1, 1, 0]);
        assert_eq!(decode_npy(&be).unwrap(), (2, 1, vec![1.0, 256.0]));
        let nan = npy::write_f64(&[2], &[1.0, f64::NAN]);
        assert!(
            decode_npy(&nan)
                .unwrap_err()
                .contains("value 1 is not finite")
        );
    }

    #[test]
    fn presets_light_the_pixels_they_name() {
        let disc = camera_light(
            Input::Json(
                serde_json::from_str(
                    r#"{"light": {"preset": "disc", "x": 2, "y": 2, "radius": 1}}"#,
                )
                .unwrap(),
            ),
            4,
            4,
        )
        .unwrap();
        // Pixel centres within 1 of (2, 2): (1.5,1.5), (2.5,1.5), (1.5,2.5), (2.5,2.5).
        assert_eq!(disc.iter().sum::<f32>(), 4.0);
        assert_eq!(disc[5] + disc[6] + disc[9] + disc[10], 4.0);
        let stripe = camera_light(
            Input::Json(
                serde_json::from_str(r#"{"light": {"preset": "stripe", "x0": 1, "x1": 3}}"#)
                    .unwrap(),
            ),
            4,
            2,
        )
        .unwrap();
        assert_eq!(stripe, vec![0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0]);
        let err = camera_light(
            Input::Json(
                serde_json::from_str(r#"{"light": {"preset": "disc", "x": 2, "y": 2}}"#).unwrap(),
            ),
            4,
            4,
        );
        assert!(
            matches!(err, Err(ApiError::InvalidArgument { ref field, .. }) if field == "light.radius"),
            "{err:?}"
        );
    }
}
