//! The REST side: sessions, reconstructions, and dual-image downloads.
//!
//! Errors the server reports as `application/problem+json` (RFC 9457) become an [`ApiError`]
//! carrying its status, title, detail and offending field; downcast an `anyhow::Error` to it.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use helmholtz_proto::rest::{self, LightPreset, LightRequest, Problem, Report};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde::{Deserialize, Serialize};

/// A problem reported by the REST API (or an unexpected HTTP status).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{method} {url}: HTTP {status} {title}{}{}{}", detail_suffix(.detail), field_suffix(.field), request_id_suffix(.request_id))]
pub struct ApiError {
    pub method: String,
    pub url: String,
    pub status: u16,
    pub title: String,
    pub detail: Option<String>,
    pub field: Option<String>,
    /// The problem's `type` URI, if any.
    pub problem_type: Option<String>,
    /// The server's `x-request-id` for this request (to find it in the server's logs).
    pub request_id: Option<String>,
}

fn request_id_suffix(id: &Option<String>) -> String {
    id.as_deref()
        .map(|id| format!(" [request id {id}]"))
        .unwrap_or_default()
}

fn detail_suffix(detail: &Option<String>) -> String {
    detail
        .as_deref()
        .map(|d| format!(": {d}"))
        .unwrap_or_default()
}

fn field_suffix(field: &Option<String>) -> String {
    field
        .as_deref()
        .map(|f| format!(" (field: {f})"))
        .unwrap_or_default()
}

/// A session as `GET /v1/sessions/{id}` returns it (the contract's type). Unknown fields are
/// kept in `extra`.
pub use helmholtz_proto::rest::SessionView;

/// A reconstruction job as `GET /v1/reconstructions/{id}` returns it, its report typed
/// ([`Report`]); gRPC answers convert to it (`Reconstruction::from(v1::Reconstruction)`).
pub type Reconstruction = rest::ReconstructionView<Report>;

fn http() -> anyhow::Result<reqwest::Client> {
    let builder = reqwest::Client::builder()
        .connect_timeout(Duration::from_secs(5))
        .timeout(Duration::from_secs(300));
    crate::tls::http_roots(builder)?
        .build()
        .context("building the HTTP client")
}

/// The URL of `path` on `server`, without any token (that goes in the Authorization header).
fn url(server: &str, path: &str) -> String {
    let (address, _) = crate::auth::split_server(server);
    format!("{}{}", address.trim_end_matches('/'), path)
}

/// Adds the token `server` carries (if any) as `Authorization: Bearer`.
fn auth(request: reqwest::RequestBuilder, server: &str) -> reqwest::RequestBuilder {
    match crate::auth::split_server(server).1 {
        Some(token) => request.bearer_auth(token),
        None => request,
    }
}

/// Percent-encodes one URL path segment or query value (RFC 3986 unreserved kept).
pub fn encode_component(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for b in s.bytes() {
        if b.is_ascii_alphanumeric() || matches!(b, b'-' | b'.' | b'_' | b'~') {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// Turns a non-success response into an [`ApiError`] (reading problem+json when present).
async fn check(
    method: &str,
    url: &str,
    response: reqwest::Response,
) -> anyhow::Result<reqwest::Response> {
    let status = response.status();
    if status.is_success() {
        return Ok(response);
    }
    let request_id = response
        .headers()
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .map(str::to_string);
    let body = response.text().await.unwrap_or_default();
    // A problem+json body, or (from something in between, say a proxy) any other text.
    let (problem, fallback) = match serde_json::from_str::<Problem>(&body) {
        Ok(problem) => (problem, None),
        Err(_) => (
            Problem::default(),
            (!body.trim().is_empty()).then(|| body.chars().take(300).collect::<String>()),
        ),
    };
    Err(ApiError {
        method: method.to_string(),
        url: url.to_string(),
        status: status.as_u16(),
        title: problem
            .title
            .unwrap_or_else(|| status.canonical_reason().unwrap_or("").to_string()),
        detail: problem.detail.or(fallback),
        field: problem.field,
        problem_type: problem.problem_type,
        request_id,
    }
    .into())
}

async fn get_json<T: serde::de::DeserializeOwned>(server: &str, path: &str) -> anyhow::Result<T> {
    let u = url(server, path);
    let response = auth(http()?.get(&u), server)
        .send()
        .await
        .with_context(|| format!("GET {u}: cannot reach the server"))?;
    let response = check("GET", &u, response).await?;
    response
        .json()
        .await
        .with_context(|| format!("GET {u}: unexpected response body"))
}

/// `GET /v1/sessions`.
pub async fn list_sessions(server: &str) -> anyhow::Result<Vec<SessionView>> {
    Ok(get_json::<rest::SessionList>(server, "/v1/sessions")
        .await?
        .sessions)
}

/// `GET /v1/sessions/{id}`.
pub async fn get_session(server: &str, session_id: &str) -> anyhow::Result<SessionView> {
    get_json(
        server,
        &format!("/v1/sessions/{}", encode_component(session_id)),
    )
    .await
}

/// `GET /v1/reconstructions/{id}`.
pub async fn get_reconstruction(server: &str, id: i64) -> anyhow::Result<Reconstruction> {
    get_json(server, &format!("/v1/reconstructions/{id}")).await
}

/// `POST /v1/sessions/{id}/reconstructions` (the REST twin of
/// [`crate::request_reconstruction`]).
pub async fn request_reconstruction_rest(
    server: &str,
    session_id: &str,
    method: &str,
    params: &serde_json::Value,
) -> anyhow::Result<Reconstruction> {
    let u = url(
        server,
        &format!(
            "/v1/sessions/{}/reconstructions",
            encode_component(session_id)
        ),
    );
    let body = rest::ReconstructionRequest {
        method: method.to_string(),
        params: params.clone(),
    };
    let response = auth(http()?.post(&u), server)
        .json(&body)
        .send()
        .await
        .with_context(|| format!("POST {u}: cannot reach the server"))?;
    let response = check("POST", &u, response).await?;
    response
        .json()
        .await
        .with_context(|| format!("POST {u}: unexpected response body"))
}

/// Polls `GET /v1/reconstructions/{id}` until it is done, failed or cancelled, and returns it
/// (a failed one is returned, not an error: look at `state` and `error`). Errors after `timeout`.
pub async fn wait_reconstruction(
    server: &str,
    id: i64,
    timeout: Duration,
) -> anyhow::Result<Reconstruction> {
    wait_reconstruction_with(server, id, timeout, false).await
}

/// [`wait_reconstruction`], with a progress bar on stderr when `progress` and stderr is a terminal.
/// Transient failures to reach the server are retried until the timeout.
pub async fn wait_reconstruction_with(
    server: &str,
    id: i64,
    timeout: Duration,
    progress: bool,
) -> anyhow::Result<Reconstruction> {
    let started = Instant::now();
    let bar = if progress && std::io::stderr().is_terminal() {
        let bar = ProgressBar::with_draw_target(Some(1000), ProgressDrawTarget::stderr());
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix:>10} [{bar:40.green/blue}] {percent}% {elapsed} {msg}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.set_prefix(format!("recon {id}"));
        bar
    } else {
        ProgressBar::hidden()
    };
    let mut poll = Duration::from_millis(50);
    loop {
        match get_reconstruction(server, id).await {
            Ok(rec) => {
                bar.set_position((rec.progress.clamp(0.0, 1.0) * 1000.0) as u64);
                bar.set_message(rec.state.clone());
                if rec.is_terminal() {
                    bar.finish();
                    return Ok(rec);
                }
            }
            // A problem the server states (404, 400, ...) will not go away by waiting.
            Err(e) if e.downcast_ref::<ApiError>().is_some_and(|a| a.status < 500) => {
                bar.abandon();
                return Err(e);
            }
            Err(e) if started.elapsed() >= timeout => {
                bar.abandon();
                return Err(e);
            }
            Err(_) => {}
        }
        if started.elapsed() >= timeout {
            bar.abandon();
            anyhow::bail!("reconstruction {id} did not finish within {timeout:?}");
        }
        tokio::time::sleep(poll.min(timeout.saturating_sub(started.elapsed()))).await;
        poll = (poll * 2).min(Duration::from_secs(1));
    }
}

/// Image formats the server renders a dual image in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ImageFormat {
    /// 8-bit (or 16-bit) grey PNG, for viewing.
    Png,
    /// 32-bit float TIFF, the values themselves.
    Tiff,
    /// NumPy array (float), for analysis.
    Npy,
}

impl ImageFormat {
    pub fn extension(self) -> &'static str {
        match self {
            ImageFormat::Png => "png",
            ImageFormat::Tiff => "tiff",
            ImageFormat::Npy => "npy",
        }
    }

    /// From a file name's extension (`.png`, `.tif`/`.tiff`, `.npy`).
    pub fn from_path(path: &Path) -> Option<ImageFormat> {
        match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
            "png" => Some(ImageFormat::Png),
            "tif" | "tiff" => Some(ImageFormat::Tiff),
            "npy" => Some(ImageFormat::Npy),
            _ => None,
        }
    }
}

/// Which dual image to download.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum FetchTarget {
    /// `GET /v1/reconstructions/{id}/dual.{ext}`
    Reconstruction(i64),
    /// `GET /v1/sessions/{id}/dual.{ext}`: the session's latest finished reconstruction.
    Session(String),
}

/// What [`fetch`] wrote.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FetchReport {
    pub url: String,
    pub path: PathBuf,
    pub bytes: u64,
    pub content_type: Option<String>,
}

/// The URL path of a dual image.
pub fn dual_path(target: &FetchTarget, format: ImageFormat, channel: Option<&str>) -> String {
    let base = match target {
        FetchTarget::Reconstruction(id) => format!("/v1/reconstructions/{id}"),
        FetchTarget::Session(id) => format!("/v1/sessions/{}", encode_component(id)),
    };
    let mut path = format!("{base}/dual.{}", format.extension());
    if let Some(ch) = channel {
        path.push_str(&format!("?channel={}", encode_component(ch)));
    }
    path
}

/// Downloads a dual image to `out` (written to a temporary file beside it, then renamed, so a
/// failed download never leaves a truncated image). `channel` selects one detector channel.
pub async fn fetch(
    server: &str,
    target: &FetchTarget,
    format: ImageFormat,
    channel: Option<&str>,
    out: &Path,
) -> anyhow::Result<FetchReport> {
    let u = url(server, &dual_path(target, format, channel));
    let response = auth(http()?.get(&u), server)
        .send()
        .await
        .with_context(|| format!("GET {u}: cannot reach the server"))?;
    let response = check("GET", &u, response).await?;
    let content_type = response
        .headers()
        .get(reqwest::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .map(str::to_string);
    let body = response
        .bytes()
        .await
        .with_context(|| format!("GET {u}: download interrupted"))?;
    write_atomically(out, &body)?;
    Ok(FetchReport {
        url: u,
        path: out.to_path_buf(),
        bytes: body.len() as u64,
        content_type,
    })
}

/// A virtual light for [`relight`]: what shines from the camera (or the bucket detectors).
#[derive(Clone, Debug, PartialEq)]
pub enum Light {
    /// Every camera pixel at 1.
    Full,
    /// A disc of camera pixels, centre `(x, y)`, radius `radius` (camera pixel units).
    Disc { x: f64, y: f64, radius: f64 },
    /// Camera columns `x0 <= x < x1`.
    Stripe { x0: f64, x1: f64 },
    /// Bucket sessions: a weight per detector channel.
    Weights(Vec<(String, f64)>),
    /// A camera-sized light image (PNG or NPY file).
    Image(PathBuf),
}

/// A projector pattern for [`primal`]: a measured one by index, or any pattern image.
#[derive(Clone, Debug, PartialEq)]
pub enum PatternInput {
    Index(u64),
    Image(PathBuf),
}

/// A request body and its content type.
#[derive(Clone, Debug, PartialEq)]
pub struct Body {
    pub content_type: String,
    pub bytes: Vec<u8>,
}

impl Body {
    fn json(value: impl Serialize) -> Body {
        Body {
            content_type: "application/json".to_string(),
            bytes: serde_json::to_vec(&value).expect("JSON serialises"),
        }
    }

    /// An image file sent as it is: `image/png` for .png, `application/x-npy` for .npy.
    pub fn image_file(path: &Path, what: &str) -> anyhow::Result<Body> {
        let content_type = match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("png") => "image/png",
            Some("npy") => "application/x-npy",
            _ => anyhow::bail!("{what} {}: use a .png or .npy file", path.display()),
        };
        let bytes =
            std::fs::read(path).with_context(|| format!("{what}: reading {}", path.display()))?;
        Ok(Body {
            content_type: content_type.to_string(),
            bytes,
        })
    }
}

fn finite(value: f64, what: &str) -> anyhow::Result<f64> {
    anyhow::ensure!(
        value.is_finite(),
        "{what} must be a finite number, got {value}"
    );
    Ok(value)
}

/// The body of `POST /v1/reconstructions/{id}/relight` for `light`.
pub fn light_body(light: &Light) -> anyhow::Result<Body> {
    let json = |light: LightRequest| Body::json(rest::RelightRequest { light });
    Ok(match light {
        Light::Full => json(LightRequest::Preset(LightPreset::Full)),
        Light::Disc { x, y, radius } => {
            let (x, y) = (finite(*x, "--disc X")?, finite(*y, "--disc Y")?);
            let radius = finite(*radius, "--disc R")?;
            anyhow::ensure!(radius > 0.0, "--disc R must be > 0, got {radius}");
            json(LightRequest::Preset(LightPreset::Disc { x, y, radius }))
        }
        Light::Stripe { x0, x1 } => {
            let (x0, x1) = (finite(*x0, "--stripe X0")?, finite(*x1, "--stripe X1")?);
            anyhow::ensure!(
                x0 < x1,
                "--stripe X0,X1 lights columns X0 <= x < X1: X0 must be below X1, got {x0},{x1}"
            );
            json(LightRequest::Preset(LightPreset::Stripe { x0, x1 }))
        }
        Light::Weights(weights) => {
            anyhow::ensure!(!weights.is_empty(), "--weights: name at least one channel");
            let mut map = std::collections::BTreeMap::new();
            for (name, w) in weights {
                anyhow::ensure!(!name.is_empty(), "--weights: empty channel name");
                let w = finite(*w, &format!("--weights {name}"))?;
                anyhow::ensure!(
                    map.insert(name.clone(), w).is_none(),
                    "--weights: channel {name:?} given twice"
                );
            }
            json(LightRequest::Weights { weights: map })
        }
        Light::Image(path) => Body::image_file(path, "--light")?,
    })
}

/// Parses `--weights NAME=W,...`.
pub fn parse_weights(text: &str) -> anyhow::Result<Vec<(String, f64)>> {
    text.split(',')
        .filter(|item| !item.trim().is_empty())
        .map(|item| {
            let (name, w) = item
                .split_once('=')
                .with_context(|| format!("--weights {item:?}: expected NAME=WEIGHT"))?;
            let w: f64 = w
                .trim()
                .parse()
                .map_err(|_| anyhow::anyhow!("--weights {item:?}: {w:?} is not a number"))?;
            Ok((name.trim().to_string(), w))
        })
        .collect()
}

/// The body of `POST /v1/reconstructions/{id}/primal` for `pattern`.
pub fn pattern_body(pattern: &PatternInput) -> anyhow::Result<Body> {
    Ok(match pattern {
        PatternInput::Index(i) => Body::json(rest::PrimalRequest { pattern_index: *i }),
        PatternInput::Image(path) => Body::image_file(path, "--pattern")?,
    })
}

/// `/v1/reconstructions/{id}/{action}?format=...` (relight, primal).
pub fn image_action_path(id: i64, action: &str, format: ImageFormat) -> String {
    format!(
        "/v1/reconstructions/{id}/{action}?format={}",
        format.extension()
    )
}

/// `/v1/reconstructions/{id}/normals.{png,npy}`.
pub fn normals_path(id: i64, format: ImageFormat) -> anyhow::Result<String> {
    anyhow::ensure!(
        format != ImageFormat::Tiff,
        "normal maps come as png or npy, not tiff"
    );
    Ok(format!(
        "/v1/reconstructions/{id}/normals.{}",
        format.extension()
    ))
}

/// What [`relight`], [`primal`] and [`normals`] wrote.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ImageReport {
    pub url: String,
    pub path: PathBuf,
    pub bytes: u64,
    pub content_type: Option<String>,
    /// `x-helmholtz-relative-error`: a measured pattern's prediction against its frame.
    pub relative_error: Option<f64>,
    /// `x-helmholtz-psnr-db`: the same comparison as PSNR.
    pub psnr_db: Option<f64>,
}

/// Sends `body` (or nothing: a GET) to `path` and saves the image the server answers.
async fn image_request(
    server: &str,
    path: &str,
    body: Option<Body>,
    out: &Path,
) -> anyhow::Result<ImageReport> {
    let u = url(server, path);
    let (method, request) = match body {
        Some(body) => (
            "POST",
            http()?
                .post(&u)
                .header(reqwest::header::CONTENT_TYPE, body.content_type)
                .body(body.bytes),
        ),
        None => ("GET", http()?.get(&u)),
    };
    let response = auth(request, server)
        .send()
        .await
        .with_context(|| format!("{method} {u}: cannot reach the server"))?;
    let response = check(method, &u, response).await?;
    let header = |name: &str| {
        response
            .headers()
            .get(name)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string)
    };
    let content_type = header(reqwest::header::CONTENT_TYPE.as_str());
    let number = |name: &str| header(name).and_then(|v| v.trim().parse::<f64>().ok());
    let relative_error = number("x-helmholtz-relative-error");
    let psnr_db = number("x-helmholtz-psnr-db");
    let body = response
        .bytes()
        .await
        .with_context(|| format!("{method} {u}: download interrupted"))?;
    write_atomically(out, &body)?;
    Ok(ImageReport {
        url: u,
        path: out.to_path_buf(),
        bytes: body.len() as u64,
        content_type,
        relative_error,
        psnr_db,
    })
}

/// `POST /v1/reconstructions/{id}/relight`: the dual image (projector-sized) under `light`,
/// saved to `out`.
pub async fn relight(
    server: &str,
    id: i64,
    light: &Light,
    format: ImageFormat,
    out: &Path,
) -> anyhow::Result<ImageReport> {
    let body = light_body(light)?;
    image_request(
        server,
        &image_action_path(id, "relight", format),
        Some(body),
        out,
    )
    .await
}

/// `POST /v1/reconstructions/{id}/primal`: the camera image the reconstructed transport
/// predicts for `pattern`, saved to `out` (with the server's error figures for a measured one).
pub async fn primal(
    server: &str,
    id: i64,
    pattern: &PatternInput,
    format: ImageFormat,
    out: &Path,
) -> anyhow::Result<ImageReport> {
    let body = pattern_body(pattern)?;
    image_request(
        server,
        &image_action_path(id, "primal", format),
        Some(body),
        out,
    )
    .await
}

/// `GET /v1/reconstructions/{id}/normals.{png,npy}`, saved to `out`.
pub async fn normals(
    server: &str,
    id: i64,
    format: ImageFormat,
    out: &Path,
) -> anyhow::Result<ImageReport> {
    image_request(server, &normals_path(id, format)?, None, out).await
}

/// `POST /v1/reconstructions/{id}/cancel`: the cancelled reconstruction (409 once it ended).
pub async fn cancel_reconstruction(server: &str, id: i64) -> anyhow::Result<Reconstruction> {
    let u = url(server, &format!("/v1/reconstructions/{id}/cancel"));
    let response = auth(http()?.post(&u), server)
        .send()
        .await
        .with_context(|| format!("POST {u}: cannot reach the server"))?;
    let response = check("POST", &u, response).await?;
    response
        .json()
        .await
        .with_context(|| format!("POST {u}: unexpected response body"))
}

/// Writes `bytes` to `path` via a temporary sibling and a rename.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let name = path
        .file_name()
        .context("output path has no file name")?
        .to_string_lossy();
    let tmp = path.with_file_name(format!(".{name}.part-{}", std::process::id()));
    std::fs::write(&tmp, bytes).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("renaming to {}", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use helmholtz_proto::v1;

    #[test]
    fn session_and_reconstruction_json() {
        let s: SessionView = serde_json::from_str(
            r#"{"id":"s1","rig":"bench","patterns":{"family":"bernoulli","width":8,"height":8,"count":64,"seed":1,"fill":0.5},
                "channels":["bucket"],"metadata":{"lens":"50mm"},"committed_rows":10,"expected_rows":64,
                "state":"open","created_unix_ms":1,"has_ground_truth":true,"latest_reconstruction":null,"new_field":3}"#,
        )
        .unwrap();
        assert_eq!(s.committed_rows, 10);
        assert_eq!(s.latest_reconstruction, None);
        assert_eq!(s.extra["new_field"], 3);
        let r: Reconstruction = serde_json::from_str(
            r#"{"id":4,"session_id":"s1","method":"dgi","params":{},"state":"done","progress":1.0,
                "rows":64,"seconds":0.5,"error":null,"report":{"psnr_db":20.1}}"#,
        )
        .unwrap();
        assert!(r.is_done() && r.is_terminal());
        assert_eq!(r.error, None);
        let p = v1::Reconstruction {
            reconstruction_id: 9,
            state: "running".into(),
            params_json: r#"{"lambda":0.1}"#.into(),
            ..Default::default()
        };
        let r = Reconstruction::from(p);
        assert_eq!(
            (r.id, r.is_terminal(), r.params["lambda"].as_f64()),
            (9, false, Some(0.1))
        );
        assert_eq!(r.report, None);
        assert_eq!(r.error, None);
    }

    #[test]
    fn dual_paths_and_formats() {
        assert_eq!(
            dual_path(
                &FetchTarget::Reconstruction(3),
                ImageFormat::Npy,
                Some("n e")
            ),
            "/v1/reconstructions/3/dual.npy?channel=n%20e"
        );
        assert_eq!(
            dual_path(
                &FetchTarget::Session("a.b-c".into()),
                ImageFormat::Png,
                None
            ),
            "/v1/sessions/a.b-c/dual.png"
        );
        assert_eq!(
            ImageFormat::from_path(Path::new("x/dual.TIF")),
            Some(ImageFormat::Tiff)
        );
        assert_eq!(ImageFormat::from_path(Path::new("dual")), None);
    }

    #[test]
    fn relight_and_primal_requests_are_built_as_specified() {
        let json = |b: Body| {
            assert_eq!(b.content_type, "application/json");
            serde_json::from_slice::<serde_json::Value>(&b.bytes).unwrap()
        };
        assert_eq!(
            json(light_body(&Light::Full).unwrap()),
            serde_json::json!({"light": {"preset": "full"}})
        );
        assert_eq!(
            json(
                light_body(&Light::Disc {
                    x: 12.0,
                    y: 7.5,
                    radius: 4.0
                })
                .unwrap()
            ),
            serde_json::json!({"light": {"preset": "disc", "x": 12.0, "y": 7.5, "radius": 4.0}})
        );
        assert_eq!(
            json(light_body(&Light::Stripe { x0: 3.0, x1: 9.0 }).unwrap()),
            serde_json::json!({"light": {"preset": "stripe", "x0": 3.0, "x1": 9.0}})
        );
        let w = parse_weights("n=1, e=0.5").unwrap();
        assert_eq!(w, [("n".to_string(), 1.0), ("e".to_string(), 0.5)]);
        assert_eq!(
            json(light_body(&Light::Weights(w)).unwrap()),
            serde_json::json!({"light": {"weights": {"n": 1.0, "e": 0.5}}})
        );
        assert_eq!(
            json(pattern_body(&PatternInput::Index(17)).unwrap()),
            serde_json::json!({"pattern_index": 17})
        );
        // Bad lights are refused before anything is sent.
        for bad in [
            Light::Disc {
                x: 1.0,
                y: 1.0,
                radius: 0.0,
            },
            Light::Disc {
                x: f64::NAN,
                y: 1.0,
                radius: 2.0,
            },
            Light::Stripe { x0: 5.0, x1: 5.0 },
            Light::Weights(vec![]),
            Light::Weights(vec![("n".into(), 1.0), ("n".into(), 2.0)]),
            Light::Image(PathBuf::from("light.jpg")),
        ] {
            assert!(light_body(&bad).is_err(), "{bad:?}");
        }
        assert!(parse_weights("n:1").is_err() && parse_weights("n=x").is_err());
        // Images go as they are, typed by extension.
        let dir = tempfile::tempdir().unwrap();
        let png = dir.path().join("light.PNG");
        std::fs::write(&png, b"\x89PNG fake").unwrap();
        let b = light_body(&Light::Image(png)).unwrap();
        assert_eq!(
            (b.content_type.as_str(), b.bytes.as_slice()),
            ("image/png", &b"\x89PNG fake"[..])
        );
        let npy = dir.path().join("p.npy");
        std::fs::write(&npy, b"\x93NUMPY").unwrap();
        let b = pattern_body(&PatternInput::Image(npy)).unwrap();
        assert_eq!(b.content_type, "application/x-npy");
        assert!(pattern_body(&PatternInput::Image(dir.path().join("missing.png"))).is_err());
        // Paths.
        assert_eq!(
            image_action_path(5, "relight", ImageFormat::Tiff),
            "/v1/reconstructions/5/relight?format=tiff"
        );
        assert_eq!(
            image_action_path(5, "primal", ImageFormat::Png),
            "/v1/reconstructions/5/primal?format=png"
        );
        assert_eq!(
            normals_path(8, ImageFormat::Npy).unwrap(),
            "/v1/reconstructions/8/normals.npy"
        );
        assert!(normals_path(8, ImageFormat::Tiff).is_err());
    }

    #[test]
    fn api_errors_read_well() {
        let e = ApiError {
            method: "GET".into(),
            url: "http://h/v1/sessions/x".into(),
            status: 404,
            title: "Not Found".into(),
            detail: Some("no session x".into()),
            field: Some("session_id".into()),
            problem_type: None,
            request_id: Some("7f3a".into()),
        };
        assert_eq!(
            e.to_string(),
            "GET http://h/v1/sessions/x: HTTP 404 Not Found: no session x (field: session_id) [request id 7f3a]"
        );
    }

    #[test]
    fn atomic_write_replaces_whole_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/dual.png");
        write_atomically(&path, b"one").unwrap();
        write_atomically(&path, b"two!").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"two!");
        assert_eq!(
            std::fs::read_dir(path.parent().unwrap()).unwrap().count(),
            1
        );
    }
}
