//! The REST contract: the JSON bodies of `/v1/...`, as the server writes them and the client
//! reads them (one set of types on both sides, so the two cannot drift apart).
//!
//! - Responses: [`SessionView`] (`GET /v1/sessions/{id}`, and in [`SessionList`]),
//!   [`ReconstructionView`] (`GET /v1/reconstructions/{id}`, `POST .../reconstructions`, cancel;
//!   in [`ReconstructionList`]), [`TokenView`] (in [`TokenList`]), [`Health`], [`ServiceIndex`],
//!   and every error as [`Problem`] (`application/problem+json`, RFC 9457).
//! - Request bodies: [`ReconstructionRequest`], [`RelightRequest`] (a [`LightRequest`]),
//!   [`PrimalRequest`], [`TokenRequest`]. The server decodes bodies into these types (and the
//!   client sends them), so a valid body is what these types say; a bad body is a problem
//!   naming the field serde stopped at (`light.radius`, `roles[1]`).
//! - The reconstruction report ([`Report`]): what the numerics found ([`ReconReport`]: method,
//!   iterations, method-specific details, the held-out error estimate) and what the service adds
//!   (quality against a simulated ground truth, compute seconds, memory). It is stored as JSON
//!   with the reconstruction and served as it was stored.
//!
//! Open parts stay JSON: a method's `params`, a report's method-specific `details`. Every view
//! keeps fields it does not know in `extra` (a newer server's additions survive a round trip
//! through an older client).

use std::collections::BTreeMap;

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use serde_json::{Map, Value};

use crate::PatternSpec;
use crate::v1;
use crate::wire::SampleFormat;

/// The media type of a [`Problem`] body.
pub const PROBLEM_JSON: &str = "application/problem+json";

// ---------------------------------------------------------------------------------------------
// Errors

/// An error as `application/problem+json` (RFC 9457). The server always sends `type`, `title`,
/// `status` and `detail`; `field` names the offending input of a 400, `limit` the limit a 413
/// or 429 ran into (with `estimate_bytes` and `limit_bytes` for the memory budget).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Problem {
    /// `/problems/{slug}`.
    #[serde(rename = "type", skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(required = true, nullable = false))]
    pub problem_type: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(required = true, nullable = false))]
    pub title: Option<String>,
    /// The HTTP status code.
    #[cfg_attr(feature = "openapi", schema(required = true))]
    pub status: u16,
    #[serde(skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(required = true, nullable = false))]
    pub detail: Option<String>,
    /// A 400's offending input as the request spells it (`limit`, `light.radius`, `roles[1]`,
    /// `content-type`, `body`, ...).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    /// The limit a 413 or 429 ran into (`max_body_bytes`, `rate_per_second`, `memory_budget`,
    /// a cap's name).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub limit: Option<String>,
    /// The memory budget's 413: the reconstruction's estimated working set.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub estimate_bytes: Option<u64>,
    /// The memory budget's 413: the budget.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub limit_bytes: Option<u64>,
}

impl Problem {
    /// A problem of type `/problems/{slug}`.
    pub fn new(slug: &str, title: &str, status: u16, detail: impl Into<String>) -> Problem {
        Problem {
            problem_type: Some(format!("/problems/{slug}")),
            title: Some(title.to_string()),
            status,
            detail: Some(detail.into()),
            ..Problem::default()
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Live preview

/// One event of `GET /v1/sessions/{id}/preview` (`event: preview`): a progressive dual image of
/// the rows committed so far, the same frame as gRPC `WatchPreview`'s `PreviewFrame`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PreviewEvent {
    pub session_id: String,
    /// The channel's name (`camera` for a camera session's pixel sum).
    pub channel: String,
    /// Rows (pattern frames) the image uses: a prefix of the session's rows.
    pub rows: u64,
    pub expected_rows: u64,
    pub width: u32,
    pub height: u32,
    /// The method the image equals on those rows: `dgi` (bernoulli, speckle), `zero_filled`
    /// (hadamard) or `direct` (raster; unmeasured blocks are 0).
    pub method: String,
    /// The image, row-major `height x width` little-endian IEEE-754 float32, base64 (RFC 4648,
    /// with padding).
    pub values_f32le: String,
    /// The session is finished and the image holds every row: the stream's last event.
    #[serde(rename = "final")]
    pub last: bool,
}

// ---------------------------------------------------------------------------------------------
// Service

/// `GET /healthz`: `{"status": "serving"}` (200) or `{"status": "not serving"}` (503).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Health {
    pub status: String,
}

impl Health {
    pub const SERVING: &'static str = "serving";
    pub const NOT_SERVING: &'static str = "not serving";
}

/// `GET /`: what the service is and the routes it serves.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ServiceIndex {
    pub service: String,
    pub version: String,
    pub grpc: String,
    pub routes: Vec<String>,
    pub auth: String,
}

// ---------------------------------------------------------------------------------------------
// Sessions

/// Whether a session still takes rows.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SessionState {
    #[default]
    Open,
    Finished,
}

impl SessionState {
    pub fn as_str(self) -> &'static str {
        match self {
            SessionState::Open => "open",
            SessionState::Finished => "finished",
        }
    }
}

impl std::fmt::Display for SessionState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.pad(self.as_str())
    }
}

/// A camera session's frame layout: `width x height` samples of `format` per pattern.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CameraView {
    pub width: u32,
    pub height: u32,
    pub format: SampleFormat,
}

/// Where a session's resources are.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SessionLinks {
    #[serde(rename = "self")]
    pub this: String,
    pub reconstructions: String,
    pub dual_png: String,
}

impl SessionLinks {
    /// The links of session `id` (a validated id: URL-safe as it is).
    pub fn of(id: &str) -> SessionLinks {
        SessionLinks {
            this: format!("/v1/sessions/{id}"),
            reconstructions: format!("/v1/sessions/{id}/reconstructions"),
            dual_png: format!("/v1/sessions/{id}/dual.png"),
        }
    }
}

/// A session as `GET /v1/sessions/{id}` returns it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SessionView {
    pub id: String,
    pub rig: String,
    /// The pattern spec (`PATTERNS.md`).
    pub patterns: PatternSpec,
    /// Bucket channel names (empty for a camera session).
    pub channels: Vec<String>,
    /// Declared detector directions (unit vectors), one per channel, or none.
    #[serde(default)]
    pub directions: Vec<[f64; 3]>,
    /// A camera session's frame layout (null for a bucket session).
    #[serde(default)]
    pub camera: Option<CameraView>,
    #[serde(default)]
    pub metadata: BTreeMap<String, String>,
    pub committed_rows: u64,
    pub expected_rows: u64,
    pub state: SessionState,
    pub created_unix_ms: i64,
    #[serde(default)]
    pub finished_unix_ms: Option<i64>,
    #[serde(default)]
    pub has_ground_truth: bool,
    /// The latest finished reconstruction, if any.
    #[serde(default)]
    pub latest_reconstruction: Option<i64>,
    #[serde(default)]
    pub links: SessionLinks,
    /// Fields this version does not know.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// `GET /v1/sessions`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SessionList {
    pub sessions: Vec<SessionView>,
}

// ---------------------------------------------------------------------------------------------
// Reconstructions

/// `POST /v1/sessions/{id}/reconstructions`: a method and its parameters (method-specific, see
/// the method's documentation; `{}` or absent for the defaults).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReconstructionRequest {
    pub method: String,
    #[serde(default)]
    pub params: Value,
}

/// Where a reconstruction's resources are.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ReconstructionLinks {
    #[serde(rename = "self")]
    pub this: String,
    pub dual_png: String,
    pub dual_tiff: String,
    pub dual_npy: String,
}

impl ReconstructionLinks {
    pub fn of(id: i64) -> ReconstructionLinks {
        ReconstructionLinks {
            this: format!("/v1/reconstructions/{id}"),
            dual_png: format!("/v1/reconstructions/{id}/dual.png"),
            dual_tiff: format!("/v1/reconstructions/{id}/dual.tiff"),
            dual_npy: format!("/v1/reconstructions/{id}/dual.npy"),
        }
    }
}

/// A reconstruction job as `GET /v1/reconstructions/{id}` returns it. `R` is its report: the
/// client reads a [`Report`]; the server passes the stored report text through unchanged.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ReconstructionView<R = Report> {
    pub id: i64,
    pub session_id: String,
    pub method: String,
    /// The method's parameters as requested (JSON; method-specific).
    pub params: Value,
    /// "queued", "running", "done", "failed" or "cancelled".
    pub state: String,
    /// In [0, 1].
    pub progress: f64,
    /// Rows of the session it uses.
    pub rows: u64,
    /// Runs started (a run whose worker died is retried).
    #[serde(default)]
    pub attempt: i64,
    /// Compute time; null until the reconstruction is done.
    pub seconds: Option<f64>,
    pub error: Option<String>,
    /// Null until the reconstruction is done.
    pub report: Option<R>,
    /// What the user should know about the result, from its report: the data cannot support
    /// the resolution asked for, too few rows, ... (`Report::warnings`). Empty until done.
    #[serde(default)]
    pub warnings: Vec<String>,
    #[serde(default)]
    pub created_unix_ms: i64,
    #[serde(default)]
    pub started_unix_ms: Option<i64>,
    #[serde(default)]
    pub finished_unix_ms: Option<i64>,
    #[serde(default)]
    pub links: ReconstructionLinks,
    /// Fields this version does not know.
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

impl<R> ReconstructionView<R> {
    pub fn is_done(&self) -> bool {
        self.state == "done"
    }

    /// Done, failed or cancelled: it will not change any more.
    pub fn is_terminal(&self) -> bool {
        matches!(self.state.as_str(), "done" | "failed" | "cancelled")
    }
}

impl From<v1::Reconstruction> for ReconstructionView {
    /// The gRPC message in the REST shape: JSON fields parsed (text that is no JSON kept as a
    /// string in `params`; a report that does not read as one is left out), seconds only once
    /// done.
    fn from(r: v1::Reconstruction) -> Self {
        let params = if r.params_json.trim().is_empty() {
            Value::Object(Map::new())
        } else {
            serde_json::from_str(&r.params_json).unwrap_or(Value::String(r.params_json.clone()))
        };
        let report = (!r.report_json.trim().is_empty())
            .then(|| serde_json::from_str(&r.report_json).ok())
            .flatten();
        let done = r.state == "done";
        ReconstructionView {
            id: r.reconstruction_id,
            session_id: r.session_id,
            method: r.method,
            params,
            seconds: done.then_some(r.seconds),
            error: (!r.error.is_empty()).then_some(r.error),
            report,
            state: r.state,
            progress: r.progress,
            rows: r.rows,
            links: ReconstructionLinks::of(r.reconstruction_id),
            ..ReconstructionView::default()
        }
    }
}

/// `GET /v1/sessions/{id}/reconstructions`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReconstructionList<R = Report> {
    // The document describes the views as the server sends them (with a `Report`).
    #[cfg_attr(feature = "openapi", schema(value_type = Vec<ReconstructionView>))]
    pub reconstructions: Vec<ReconstructionView<R>>,
}

// ---------------------------------------------------------------------------------------------
// Relighting

/// `POST /v1/reconstructions/{id}/relight` with a JSON body: `{"light": ...}`. (The light may
/// also be sent as a camera-sized PNG or NPY body.)
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RelightRequest {
    pub light: LightRequest,
}

/// A virtual light at the detector side: `{"preset": ...}` or `{"weights": {...}}` (decoded by
/// the key present, so an error names the field, not "no variant matched").
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(untagged)]
pub enum LightRequest {
    /// A camera session's preset (a bucket session takes only `full`).
    Preset(LightPreset),
    /// A bucket session: a weight per channel name (channels not named weigh 0).
    Weights { weights: BTreeMap<String, f64> },
}

impl<'de> Deserialize<'de> for LightRequest {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        use serde::de::{Error, MapAccess, Visitor};
        const FIELDS: &[&str] = &["preset", "x", "y", "radius", "x0", "x1", "weights"];
        struct Light;
        impl<'de> Visitor<'de> for Light {
            type Value = LightRequest;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str(r#"an object such as {"preset": "full"} or {"weights": {"r": 1.0}}"#)
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<LightRequest, A::Error> {
                /// A preset's name, read as a string (a derived enum would call any other
                /// JSON type a syntax error).
                enum Preset {
                    Full,
                    Disc,
                    Stripe,
                }
                impl<'de> Deserialize<'de> for Preset {
                    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                        const NAMES: &[&str] = &["full", "disc", "stripe"];
                        match String::deserialize(d)?.as_str() {
                            "full" => Ok(Preset::Full),
                            "disc" => Ok(Preset::Disc),
                            "stripe" => Ok(Preset::Stripe),
                            other => Err(D::Error::unknown_variant(other, NAMES)),
                        }
                    }
                }
                let mut preset: Option<Preset> = None;
                let mut weights: Option<BTreeMap<String, f64>> = None;
                let mut numbers: BTreeMap<&'static str, f64> = BTreeMap::new();
                while let Some(key) = map.next_key::<String>()? {
                    let Some(&name) = FIELDS.iter().find(|f| **f == key) else {
                        return Err(A::Error::unknown_field(&key, FIELDS));
                    };
                    if preset.is_some() && name == "preset"
                        || weights.is_some() && name == "weights"
                        || numbers.contains_key(name)
                    {
                        return Err(A::Error::duplicate_field(name));
                    }
                    match name {
                        "preset" => preset = Some(map.next_value()?),
                        "weights" => weights = Some(map.next_value()?),
                        _ => {
                            numbers.insert(name, map.next_value()?);
                        }
                    }
                }
                fn take<E: Error>(
                    numbers: &BTreeMap<&'static str, f64>,
                    allowed: &'static [&'static str],
                ) -> Result<(), E> {
                    match numbers.keys().find(|k| !allowed.contains(k)) {
                        Some(extra) => Err(E::unknown_field(extra, allowed)),
                        None => Ok(()),
                    }
                }
                let need = |name: &'static str| {
                    numbers
                        .get(name)
                        .copied()
                        .ok_or_else(|| A::Error::missing_field(name))
                };
                match (preset, weights) {
                    (Some(_), Some(_)) => {
                        Err(A::Error::custom("give either preset or weights, not both"))
                    }
                    (None, Some(weights)) => {
                        take::<A::Error>(&numbers, &["weights"])?;
                        Ok(LightRequest::Weights { weights })
                    }
                    (Some(preset), None) => {
                        let light = match preset {
                            Preset::Full => {
                                take::<A::Error>(&numbers, &["preset"])?;
                                LightPreset::Full
                            }
                            Preset::Disc => {
                                take::<A::Error>(&numbers, &["preset", "x", "y", "radius"])?;
                                LightPreset::Disc {
                                    x: need("x")?,
                                    y: need("y")?,
                                    radius: need("radius")?,
                                }
                            }
                            Preset::Stripe => {
                                take::<A::Error>(&numbers, &["preset", "x0", "x1"])?;
                                LightPreset::Stripe {
                                    x0: need("x0")?,
                                    x1: need("x1")?,
                                }
                            }
                        };
                        Ok(LightRequest::Preset(light))
                    }
                    (None, None) => Err(A::Error::custom(
                        r#"give a preset or weights: {"preset": "full"} or {"weights": {"r": 1.0}}"#,
                    )),
                }
            }
        }
        deserializer.deserialize_map(Light)
    }
}

/// `{"preset": "full" | "disc" | "stripe", ...}`, in camera pixel units.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "preset", rename_all = "lowercase", deny_unknown_fields)]
pub enum LightPreset {
    /// Every camera pixel (every channel) at 1.
    Full,
    /// Camera pixels whose centres lie within `radius` of `(x, y)`.
    Disc { x: f64, y: f64, radius: f64 },
    /// Camera columns `x0 <= x < x1`.
    Stripe { x0: f64, x1: f64 },
}

/// `POST /v1/reconstructions/{id}/primal` with a JSON body: one of the session's own patterns.
/// (Any pattern may also be sent as a projector-sized PNG or NPY body.)
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrimalRequest {
    pub pattern_index: u64,
}

// ---------------------------------------------------------------------------------------------
// Tokens

/// `POST /v1/tokens`: roles (`rig`, `reader`, `admin`; at least one) and a note (at most 256
/// characters, no control characters).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenRequest {
    pub roles: Vec<String>,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
}

/// A token of a lab, never with its secret, except in the answer to its creation (`token`,
/// shown that once).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TokenView {
    pub id: i64,
    pub lab: String,
    /// Comma-separated role names.
    pub roles: String,
    pub note: String,
    pub created_unix_ms: i64,
    pub revoked_unix_ms: Option<i64>,
    /// The secret: only when the token was just created.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub token: Option<String>,
}

/// `GET /v1/tokens`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TokenList {
    pub tokens: Vec<TokenView>,
}

// ---------------------------------------------------------------------------------------------
// Reports

/// A reconstruction's report as stored and served (`ReconstructionView::report`): what the
/// numerics report ([`ReconReport`], flattened) and what the service adds. Fields of other
/// versions are kept in `extra`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Report {
    #[serde(flatten)]
    pub recon: ReconReport,
    /// Against the ground truth of a simulated session: per channel for bucket sessions, of T
    /// for camera sessions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quality: Option<Quality>,
    /// The heap the reconstruction took at its peak (when the server counts allocations).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub peak_memory_bytes: Option<u64>,
    /// Compute time.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f64>,
    /// What the request estimated (and the workers reserved) against the memory budget.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_estimate_bytes: Option<u64>,
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

impl Report {
    /// The held-out relative residual (the error estimate without ground truth), if any.
    pub fn held_out_error(&self) -> Option<f64> {
        self.recon.held_out.as_ref()?.relative_residual
    }

    /// Per-channel quality of a bucket session's dual images (empty without ground truth).
    pub fn channel_quality(&self) -> &[ChannelQuality] {
        match &self.quality {
            Some(Quality::Channels(c)) => c,
            _ => &[],
        }
    }

    /// The quality of a camera session's T, when scored.
    pub fn transport_quality(&self) -> Option<&TransportQuality> {
        match &self.quality {
            Some(Quality::Transport(t)) => Some(t),
            _ => None,
        }
    }

    /// `auto`'s choice for the first channel (`details.auto[0]`).
    pub fn auto_choice(&self) -> Option<AutoChoice> {
        let first = self.recon.details.get("auto")?.get(0)?;
        AutoChoice::deserialize(first).ok()
    }

    /// Everything the user should know about the result: `details.warnings` (a transport
    /// matrix the pairs cannot support, ...) and every `auto` choice's warnings (prefixed with
    /// its channel when there are several), in that order.
    pub fn warnings(&self) -> Vec<String> {
        let mut out: Vec<String> = self
            .recon
            .details
            .get("warnings")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
            .filter_map(Value::as_str)
            .map(str::to_string)
            .collect();
        if let Some(choices) = self.recon.details.get("auto").and_then(Value::as_array) {
            for (i, c) in choices.iter().enumerate() {
                let Ok(choice) = AutoChoice::deserialize(c) else {
                    continue;
                };
                let channel = c.get("channel").and_then(Value::as_str).map_or_else(
                    || (choices.len() > 1).then(|| format!("channel {i}")),
                    |s| (choices.len() > 1).then(|| s.to_string()),
                );
                out.extend(choice.warnings.into_iter().map(|w| match &channel {
                    Some(ch) => format!("{ch}: {w}"),
                    None => w,
                }));
            }
        }
        out
    }

    /// A method-specific figure of `details` as a number.
    pub fn detail_f64(&self, key: &str) -> Option<f64> {
        self.recon.details.get(key)?.as_f64()
    }
}

/// What every reconstruction method reports (the numerics' part of a [`Report`]).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ReconReport {
    pub method: String,
    pub params: Value,
    pub rows_used: u64,
    pub iterations: u64,
    /// Method-specific figures (e.g. Hadamard split-pair sums: dark level, drift; `auto`'s
    /// choice; a transport matrix's size).
    pub details: Map<String, Value>,
    /// The error estimate: how well the method, fitted without a fixed subset of the rows,
    /// predicts those rows. `None` (null) when it cannot be had, with the reason in
    /// `held_out_unavailable`.
    pub held_out: Option<HeldOut>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub held_out_unavailable: Option<String>,
}

/// The held-out error estimate as reported (`ReconReport::held_out`).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HeldOut {
    /// Held-out rows scored: patterns; for the iterative methods on Hadamard, split pairs; for
    /// the correlators on Hadamard, frames (both frames of a held-out pair).
    pub rows: usize,
    /// Fraction of rows held out.
    #[serde(deserialize_with = "null_as_nan")]
    #[cfg_attr(feature = "openapi", schema(value_type = Option<f64>, required = true))]
    pub fraction: f64,
    /// `||c_H - c_hat_H|| / ||c_H - mean(c_H)||`, channels pooled; `None` (JSON null) when the
    /// held-out buckets are all equal but not predicted exactly (no scale to compare with).
    pub relative_residual: Option<f64>,
    pub per_channel: Vec<Option<f64>>,
    /// Root-mean-square residual in bucket units.
    #[serde(deserialize_with = "null_as_nan")]
    #[cfg_attr(feature = "openapi", schema(value_type = Option<f64>, required = true))]
    pub rms_residual: f64,
}

/// `auto`'s choice for one channel, as far as clients read it (the rest of `details.auto[i]`
/// stays in `extra`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AutoChoice {
    /// The model chosen (`tv`, `db4`, `dct`, ...; `direct` for a complete set).
    pub model: String,
    /// Why, when the choice was not a race (the exact inverse).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// The regularisation weight chosen, and as a fraction of the largest useful one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lambda: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lambda_fraction: Option<f64>,
    /// The winner's held-out error.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub held_out: Option<f64>,
    /// Coefficients kept by the model.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kept: Option<u64>,
    /// What the user should know about the choice (too few rows, a resolution cut, ...).
    pub warnings: Vec<String>,
    #[serde(flatten)]
    pub extra: Map<String, Value>,
}

/// A report's `quality`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Quality {
    /// A bucket session: one entry per channel whose image has the truth's size.
    Channels(Vec<ChannelQuality>),
    /// A camera session: T against the simulator's.
    Transport(TransportQuality),
    /// A shape this version does not know (kept as it is).
    Other(Value),
}

/// A figure in a report: finite values as numbers, `+inf` (a perfect PSNR) as `"inf"`, anything
/// else as `null`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Figure(pub f64);

impl Serialize for Figure {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        if self.0.is_finite() {
            s.serialize_f64(self.0)
        } else if self.0 == f64::INFINITY {
            s.serialize_str("inf")
        } else {
            s.serialize_none()
        }
    }
}

impl<'de> Deserialize<'de> for Figure {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Number(f64),
            Text(String),
            Null(()),
        }
        Ok(Figure(match Option::<Raw>::deserialize(d)? {
            Some(Raw::Number(x)) => x,
            Some(Raw::Text(t)) if t == "inf" => f64::INFINITY,
            Some(Raw::Text(t)) => {
                return Err(serde::de::Error::custom(format!(
                    "a figure is a number, \"inf\" or null, got {t:?}"
                )));
            }
            Some(Raw::Null(())) | None => f64::NAN,
        }))
    }
}

/// One channel's dual image against its truth, raw and after the least-squares affine fit
/// (correlation methods estimate t only up to scale and offset).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChannelQuality {
    pub channel: String,
    pub psnr_db: Figure,
    pub ssim: Figure,
    pub relative_error: Figure,
    pub psnr_fitted_db: Figure,
    pub ssim_fitted: Figure,
    pub fit: AffineFit,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AffineFit {
    #[serde(deserialize_with = "null_as_nan")]
    #[cfg_attr(feature = "openapi", schema(value_type = Option<f64>, required = true))]
    pub scale: f64,
    #[serde(deserialize_with = "null_as_nan")]
    #[cfg_attr(feature = "openapi", schema(value_type = Option<f64>, required = true))]
    pub offset: f64,
}

/// A transport matrix against the simulator's (`m x k`, row-major).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum TransportQuality {
    Scored {
        /// Relative Frobenius error of T.
        transport_relative_error: Figure,
        /// The worst camera pixel's (row's) relative error.
        worst_row_relative_error: Figure,
        /// The dual image under the whole camera (`T^T 1`) against the truth's column sums.
        camera_dual_psnr_db: Figure,
        camera_dual_ssim: Figure,
    },
    Unavailable {
        unavailable: String,
    },
}

/// An f64 that JSON may carry as null (how serde_json writes NaN and the infinities).
fn null_as_nan<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

// ---------------------------------------------------------------------------------------------
// Sessions and rows over REST (for tools without gRPC: MATLAB, curl)

/// `POST /v1/sessions`: the same declaration as gRPC `CreateSession`, in the shape
/// `GET /v1/sessions/{id}` returns.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewSessionRequest {
    /// Client-generated: 1-128 characters of `A-Z a-z 0-9 . _ -`. Creating again with the same
    /// declaration returns the stored session (200); a different one is 409.
    pub id: String,
    pub rig: String,
    /// The pattern spec (`PATTERNS.md`).
    pub patterns: PatternSpec,
    /// Bucket channel names, e.g. `["bucket"]` (empty for a camera session).
    #[serde(default)]
    pub channels: Vec<String>,
    /// Optional: the direction from the scene toward each bucket detector, one per channel.
    #[serde(default)]
    pub directions: Vec<[f64; 3]>,
    /// Set for a camera session (then `channels` is empty).
    #[serde(default)]
    pub camera: Option<CameraView>,
    #[serde(default)]
    pub metadata: BTreeMap<String, String>,
    /// The imaged scene, when known (simulations): the server then reports PSNR and SSIM.
    #[serde(default)]
    pub ground_truth: Option<GroundTruthView>,
}

/// A session's known transport (`width x height` per channel, channels one after another; a
/// camera session: one row of T per camera pixel).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GroundTruthView {
    pub width: u32,
    pub height: u32,
    pub transport: Vec<f32>,
}

/// `GET /v1/sessions/{id}/rows` (rig or reader): where an upload stands; resume from
/// `committed_rows`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct UploadStatusView {
    pub session_id: String,
    pub committed_rows: u64,
    pub expected_rows: u64,
    pub state: SessionState,
}

/// `PUT /v1/sessions/{id}/rows`: what one upload request did.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct UploadResult {
    pub session_id: String,
    /// Rows stored for the session now (resume from here).
    pub committed_rows: u64,
    /// Rows this request added.
    pub rows_written: u64,
    /// Rows of this request that were already stored with exactly these bytes.
    pub rows_skipped: u64,
    pub expected_rows: u64,
    pub state: SessionState,
}

/// Schemas written by hand where serde's shape is custom ([`Figure`], [`PatternSpec`]) and the
/// parameter schemas of the OpenAPI document (feature `openapi`).
#[cfg(feature = "openapi")]
mod openapi {
    use utoipa::openapi::schema::{ObjectBuilder, OneOfBuilder, Schema, Type};
    use utoipa::openapi::{RefOr, schema};
    use utoipa::{PartialSchema, ToSchema};

    use super::{Figure, PatternSpec};
    use crate::patterns::{Family, MAX_COUNT, MAX_SIDE};

    impl PartialSchema for Figure {
        /// A number, `"inf"` or null.
        fn schema() -> RefOr<Schema> {
            OneOfBuilder::new()
                .item(ObjectBuilder::new().schema_type(Type::Number))
                .item(
                    ObjectBuilder::new()
                        .schema_type(Type::String)
                        .enum_values(Some(["inf"])),
                )
                .item(ObjectBuilder::new().schema_type(Type::Null))
                .description(Some(
                    "A figure: a finite number, \"inf\" (+infinity, e.g. a perfect PSNR) or null (undefined)",
                ))
                .into()
        }
    }

    impl ToSchema for Figure {}

    /// One object per family, as `PatternSpec` writes and reads it: the family's own fields
    /// (from [`Family`]'s schema) beside `width`, `height`, `count` and `seed`.
    impl PartialSchema for PatternSpec {
        fn schema() -> RefOr<Schema> {
            let common = |object: schema::Object| {
                let mut object = schema::ObjectBuilder::from(object)
                    .property(
                        "width",
                        ObjectBuilder::new()
                            .schema_type(Type::Integer)
                            .minimum(Some(1))
                            .maximum(Some(MAX_SIDE)),
                    )
                    .required("width")
                    .property(
                        "height",
                        ObjectBuilder::new()
                            .schema_type(Type::Integer)
                            .minimum(Some(1))
                            .maximum(Some(MAX_SIDE)),
                    )
                    .required("height")
                    .property(
                        "count",
                        ObjectBuilder::new()
                            .schema_type(Type::Integer)
                            .minimum(Some(1))
                            .maximum(Some(MAX_COUNT))
                            .description(Some("Patterns in the session")),
                    )
                    .required("count")
                    .property(
                        "seed",
                        ObjectBuilder::new()
                            .schema_type(Type::Integer)
                            .minimum(Some(0))
                            .description(Some("The generator's seed (0 if absent)")),
                    );
                // Family denies unknown fields on its own; here the common fields belong too.
                object = object
                    .additional_properties(Some(schema::AdditionalProperties::FreeForm(false)));
                object.build()
            };
            let variants = match Family::schema() {
                RefOr::T(Schema::OneOf(one_of)) => one_of.items,
                other => panic!(
                    "Family's schema is a oneOf of its families, got {}",
                    serde_json::to_string(&other).unwrap_or_default()
                ),
            };
            let mut spec = OneOfBuilder::new().description(Some(
                "A pattern spec (PATTERNS.md): the family and its parameters beside the common fields, e.g. {\"family\": \"bernoulli\", \"width\": 64, \"height\": 64, \"count\": 4096, \"seed\": 7, \"fill\": 0.5}",
            ));
            for variant in variants {
                match variant {
                    RefOr::T(Schema::Object(object)) => spec = spec.item(common(object)),
                    other => panic!(
                        "a family's schema is an object, got {}",
                        serde_json::to_string(&other).unwrap_or_default()
                    ),
                }
            }
            spec.into()
        }
    }

    impl ToSchema for PatternSpec {
        fn schemas(schemas: &mut Vec<(String, RefOr<Schema>)>) {
            // What the families' fields refer to (e.g. HadamardOrdering).
            <Family as ToSchema>::schemas(schemas);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn a_reports_warnings_are_its_details_then_every_auto_choices() {
        let r: Report = serde_json::from_value(json!({
            "method": "auto", "params": {}, "rows_used": 10, "iterations": 1,
            "details": {"warnings": ["pairs cannot support T"],
                "auto": [{"model": "tv", "channel": "r", "warnings": ["few rows"]},
                         {"model": "tv", "warnings": []},
                         {"model": "db4", "warnings": ["a resolution cut"]}]},
            "held_out": null
        }))
        .unwrap();
        assert_eq!(
            r.warnings(),
            [
                "pairs cannot support T",
                "r: few rows",
                "channel 2: a resolution cut"
            ]
        );
        let one: Report = serde_json::from_value(json!({
            "method": "auto", "params": {}, "rows_used": 10, "iterations": 1,
            "details": {"auto": [{"model": "tv", "warnings": ["few rows"]}]}, "held_out": null
        }))
        .unwrap();
        assert_eq!(one.warnings(), ["few rows"]);
        assert!(Report::default().warnings().is_empty());
    }

    #[test]
    fn reports_of_both_kinds_read_and_write_back_the_same_json() {
        let bucket = json!({
            "method": "auto", "params": {"lambda": 0.1}, "rows_used": 307, "iterations": 812,
            "details": {"auto": [{"model": "tv", "lambda": 0.002, "lambda_fraction": 0.05,
                "kept": 140, "held_out": 0.08, "warnings": ["few rows"], "resolution": {"fitted": [32, 32]}}]},
            "held_out": {"rows": 31, "fraction": 0.1, "relative_residual": 0.08,
                "per_channel": [0.08], "rms_residual": 0.5},
            "quality": [{"channel": "bucket", "psnr_db": "inf", "ssim": 1.0, "relative_error": null,
                "psnr_fitted_db": 30.5, "ssim_fitted": 0.9, "fit": {"scale": 1.0, "offset": 0.0}}],
            "peak_memory_bytes": 1234, "seconds": 0.25, "memory_estimate_bytes": 99
        });
        let r: Report = serde_json::from_value(bucket.clone()).unwrap();
        assert_eq!(serde_json::to_value(&r).unwrap(), bucket);
        assert_eq!(r.held_out_error(), Some(0.08));
        assert_eq!(r.channel_quality()[0].psnr_db, Figure(f64::INFINITY));
        assert!(r.channel_quality()[0].relative_error.0.is_nan());
        let choice = r.auto_choice().unwrap();
        assert_eq!(
            (choice.model.as_str(), choice.lambda, choice.warnings.len()),
            ("tv", Some(0.002), 1)
        );
        assert!(r.extra.is_empty(), "{:?}", r.extra);

        let camera = json!({
            "method": "transport", "params": {}, "rows_used": 64, "iterations": 0,
            "details": {"stored_bytes": 4096, "frame_passes": 3, "ambient_mean": 0.01},
            "held_out": null, "held_out_unavailable": "exact",
            "quality": {"transport_relative_error": 0.01, "worst_row_relative_error": 0.02,
                "camera_dual_psnr_db": 40.0, "camera_dual_ssim": 0.99},
            "seconds": 1.5, "memory_estimate_bytes": 7, "written_by": "a later version"
        });
        let r: Report = serde_json::from_value(camera.clone()).unwrap();
        assert_eq!(serde_json::to_value(&r).unwrap(), camera);
        assert!(matches!(
            r.transport_quality(),
            Some(TransportQuality::Scored { .. })
        ));
        assert_eq!(r.detail_f64("stored_bytes"), Some(4096.0));
        assert_eq!(r.extra["written_by"], "a later version");
    }

    #[test]
    fn light_bodies_have_the_documented_shapes() {
        let disc = RelightRequest {
            light: LightRequest::Preset(LightPreset::Disc {
                x: 1.0,
                y: 2.0,
                radius: 3.0,
            }),
        };
        assert_eq!(
            serde_json::to_value(&disc).unwrap(),
            json!({"light": {"preset": "disc", "x": 1.0, "y": 2.0, "radius": 3.0}})
        );
        let weights: RelightRequest =
            serde_json::from_value(json!({"light": {"weights": {"n": 1.0}}})).unwrap();
        assert_eq!(
            weights.light,
            LightRequest::Weights {
                weights: [("n".to_string(), 1.0)].into()
            }
        );
        assert_eq!(
            serde_json::to_value(PrimalRequest { pattern_index: 4 }).unwrap(),
            json!({"pattern_index": 4})
        );
    }

    #[test]
    fn problems_write_only_what_they_carry() {
        let mut p = Problem::new("invalid-argument", "Invalid argument", 400, "x: bad");
        p.field = Some("x".into());
        assert_eq!(
            serde_json::to_value(&p).unwrap(),
            json!({"type": "/problems/invalid-argument", "title": "Invalid argument",
                "status": 400, "detail": "x: bad", "field": "x"})
        );
        let read: Problem = serde_json::from_str(r#"{"title": "t", "other": 1}"#).unwrap();
        assert_eq!((read.title.as_deref(), read.detail), (Some("t"), None));
    }
}
