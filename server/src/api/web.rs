//! The web viewer: a static application (plain HTML, ES modules and CSS, no build step) compiled
//! into the binary and served on the main port (`GET /` to a browser, `GET /assets/{file}`),
//! and the live progress of a reconstruction as server-sent events
//! (`GET /v1/reconstructions/{id}/events`), which the viewer reads with `fetch()` so the token
//! travels in the `Authorization` header, never in a URL.
//!
//! The application holds no data: it calls the REST API with the token the user pasted (kept in
//! the tab's session storage). Its pages are served without a token; its Content-Security-Policy
//! allows nothing but this origin, so the browser makes no request to any other host.

use std::time::{Duration, Instant};

use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use super::rest::{Caller, Path, ReconstructionId, recon_path, reconstruction_view};
use super::{ApiError, AppState, openapi};
use crate::auth::Role;

/// The application's files: name, media type, contents.
pub const ASSETS: [(&str, &str, &str); 10] = [
    ("dom.js", "text/javascript", include_str!("../web/dom.js")),
    ("app.js", "text/javascript", include_str!("../web/app.js")),
    ("api.js", "text/javascript", include_str!("../web/api.js")),
    (
        "image.js",
        "text/javascript",
        include_str!("../web/image.js"),
    ),
    (
        "session.js",
        "text/javascript",
        include_str!("../web/session.js"),
    ),
    (
        "relight.js",
        "text/javascript",
        include_str!("../web/relight.js"),
    ),
    ("jobs.js", "text/javascript", include_str!("../web/jobs.js")),
    ("style.css", "text/css", include_str!("../web/style.css")),
    ("icon.svg", "image/svg+xml", include_str!("../web/icon.svg")),
    ("npy.js", "text/javascript", include_str!("../web/npy.js")),
];

/// The application's page.
pub const INDEX_HTML: &str = include_str!("../web/index.html");

/// Only this origin: scripts, styles, images (and the blob: and data: URLs the viewer makes of
/// fetched images), fetches. No frame may embed it.
const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; connect-src 'self'; form-action 'none'; base-uri 'none'; frame-ancestors 'none'";

fn secured(mut response: Response) -> Response {
    let h = response.headers_mut();
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    response
}

/// Whether a `GET /` comes from a browser's navigation (it asks for HTML).
pub fn wants_html(headers: &HeaderMap) -> bool {
    headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim().starts_with("text/html")))
}

/// The application's page (`GET /` with `Accept: text/html`).
pub fn index_html() -> Response {
    secured(
        (
            [(
                header::CONTENT_TYPE,
                HeaderValue::from_static("text/html; charset=utf-8"),
            )],
            INDEX_HTML,
        )
            .into_response(),
    )
}

/// `{file}` of `GET /assets/{file}`: exactly the names of [`ASSETS`].
pub struct AssetName;

impl utoipa::PartialSchema for AssetName {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        let names: Vec<&str> = ASSETS.iter().map(|(name, _, _)| *name).collect();
        utoipa::openapi::schema::ObjectBuilder::new()
            .schema_type(utoipa::openapi::schema::Type::String)
            .enum_values(Some(names))
            .description(Some(
                "a script (ES module), the style sheet or the icon of the viewer",
            ))
            .into()
    }
}

impl utoipa::ToSchema for AssetName {
    fn name() -> std::borrow::Cow<'static, str> {
        "AssetName".into()
    }
}

/// `{file}` of an asset.
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
struct AssetPath {
    /// The file
    #[param(inline, value_type = AssetName)]
    file: String,
}

/// A file of the web viewer
///
/// The viewer's scripts (ES modules), style sheet and icon, compiled into the server. Open (no
/// token): they hold no data; the viewer itself is `GET /` in a browser.
#[utoipa::path(
    get,
    path = "/assets/{file}",
    tag = "viewer",
    security(()),
    params(AssetPath),
    responses(
        (status = 200, description = "The file",
            content(("text/javascript"), ("text/css"), ("image/svg+xml"))),
        (status = 404, response = openapi::NotFound),
    )
)]
pub(super) async fn asset(Path(file): Path<String>) -> Result<Response, ApiError> {
    let Some((_, mime, text)) = ASSETS.iter().find(|(name, _, _)| *name == file) else {
        return Err(ApiError::NotFound(format!(
            "no asset {file:?}; the viewer is GET / in a browser"
        )));
    };
    Ok(secured(
        (
            [(
                header::CONTENT_TYPE,
                HeaderValue::from_str(&format!("{mime}; charset=utf-8")).expect("ascii"),
            )],
            *text,
        )
            .into_response(),
    ))
}

/// How often the events stream looks at the reconstruction.
const POLL: Duration = Duration::from_millis(200);
/// A comment line this often keeps proxies from closing a quiet stream.
const KEEP_ALIVE: Duration = Duration::from_secs(15);

fn terminal(state: &str) -> bool {
    matches!(state, "done" | "failed" | "cancelled")
}

/// A reconstruction's progress, live
///
/// Server-sent events (`text/event-stream`): an event `reconstruction` whose data is the
/// reconstruction (as `GET /v1/reconstructions/{id}`) at once and again whenever its state or
/// progress changes; the stream ends after the event of a final state (done, failed,
/// cancelled). Browsers read it with `fetch()` (the token in the `Authorization` header), not
/// `EventSource` (role reader).
#[utoipa::path(
    get,
    path = "/v1/reconstructions/{id}/events",
    tag = "reconstructions",
    params(ReconstructionId),
    responses(
        (status = 200, description = "Server-sent events: `event: reconstruction`, `data: {ReconstructionView}`; comment lines keep a quiet stream open",
            content(("text/event-stream")),
            headers(("Cache-Control" = String, description = "no-cache"))),
        (status = 400, response = openapi::BadRequest),
        (status = 403, response = openapi::Forbidden),
        (status = 404, response = openapi::NotFound),
    )
)]
pub(super) async fn reconstruction_events(
    Caller(caller): Caller,
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    caller.require(Role::Reader)?;
    let id = recon_path(&id)?;
    let first = state.own_reconstruction(&caller, id).await?;
    struct Cursor {
        state: AppState,
        id: i64,
        last: String,
        last_sent: Instant,
        ended: bool,
        first: Option<crate::store::ReconstructionRow>,
    }
    let cursor = Cursor {
        state,
        id,
        last: String::new(),
        last_sent: Instant::now(),
        ended: false,
        first: Some(first),
    };
    let events = futures::stream::unfold(cursor, |mut c| async move {
        if c.ended {
            return None;
        }
        loop {
            let row = match c.first.take() {
                Some(row) => row,
                None => {
                    tokio::time::sleep(POLL).await;
                    match c.state.store.reconstruction(c.id).await {
                        Ok(row) => row,
                        Err(e) => {
                            c.ended = true;
                            let msg = serde_json::json!({"detail": e.to_string()});
                            return Some((
                                Ok::<_, std::io::Error>(Bytes::from(format!(
                                    "event: error\ndata: {msg}\n\n"
                                ))),
                                c,
                            ));
                        }
                    }
                }
            };
            let json = serde_json::to_string(&reconstruction_view(&row)).expect("serializes");
            if json != c.last {
                c.ended = terminal(&row.state);
                c.last_sent = Instant::now();
                let event = format!("event: reconstruction\ndata: {json}\n\n");
                c.last = json;
                return Some((Ok(Bytes::from(event)), c));
            }
            if c.last_sent.elapsed() >= KEEP_ALIVE {
                c.last_sent = Instant::now();
                return Some((Ok(Bytes::from_static(b": keep-alive\n\n")), c));
            }
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn browsers_get_the_page_and_tools_the_index() {
        let mut h = HeaderMap::new();
        assert!(!wants_html(&h));
        h.insert(header::ACCEPT, HeaderValue::from_static("*/*"));
        assert!(!wants_html(&h));
        h.insert(
            header::ACCEPT,
            HeaderValue::from_static("text/html,application/xhtml+xml,*/*;q=0.8"),
        );
        assert!(wants_html(&h));
    }

    #[test]
    fn the_viewer_loads_nothing_from_another_host() {
        let mut all = vec![INDEX_HTML];
        all.extend(ASSETS.iter().map(|(_, _, text)| *text));
        for text in all {
            // The SVG namespace is a name, not a request.
            let text = text.replace("http://www.w3.org/2000/svg", "");
            for needle in ["http://", "https://", "//cdn", "@import"] {
                assert!(!text.contains(needle), "{needle}");
            }
        }
        // Every module the page or a module imports is served.
        for (name, _, text) in ASSETS.iter() {
            for line in text.lines().filter(|l| l.starts_with("import ")) {
                let from = line.rsplit("from").next().unwrap();
                let file = from
                    .trim()
                    .trim_matches(|c| c == '"' || c == '\'' || c == ';');
                let file = file.trim_start_matches("./");
                assert!(
                    ASSETS.iter().any(|(n, _, _)| *n == file),
                    "{name} imports {file}, which is not served"
                );
            }
        }
        assert!(INDEX_HTML.contains("/assets/app.js"));
    }
}
