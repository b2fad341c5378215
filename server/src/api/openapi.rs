//! The OpenAPI 3.1 document of the REST API, generated from the handlers: every route of
//! [`rest::api`](super::rest::api) carries its operation (`#[utoipa::path]`), so what is routed
//! and what is documented come from one list. Served open (no token, like `/healthz`) at
//! `GET /openapi.json`, with a self-contained docs page at `GET /docs` (no script, style or font
//! from another host: it works offline).
//!
//! What the handlers' annotations do not say themselves is added here once ([`finish`]): the
//! problem+json answers every authenticated call may get (401, 429, 500, 503), the reconstruction
//! methods the parser accepts, and the service's version.

use std::borrow::Cow;
use std::sync::LazyLock;

use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use helmholtz_proto::rest::{PROBLEM_JSON, Problem, Report};
use utoipa::openapi::schema::{ObjectBuilder, Schema, Type};
use utoipa::openapi::security::{Http, HttpAuthScheme, SecurityRequirement, SecurityScheme};
use utoipa::openapi::{
    self, Content, HeaderBuilder, OpenApi as Document, Ref, RefOr, ResponseBuilder,
};
use utoipa::{Modify, OpenApi, PartialSchema, ToResponse, ToSchema};

/// The served document: built once from the router's own operations.
pub struct ApiDocument {
    pub document: Document,
    /// `document` as JSON, as `GET /openapi.json` serves it.
    pub json: String,
    /// One line per operation, `METHOD /path: summary`, for `GET /`.
    pub routes: Vec<String>,
}

/// The document of [`rest::api`](super::rest::api), finished ([`finish`]).
pub fn document() -> &'static ApiDocument {
    static DOCUMENT: LazyLock<ApiDocument> = LazyLock::new(|| {
        let (_, document) = super::rest::api().split_for_parts();
        let document = finish(document);
        let json = document.to_pretty_json().expect("the document serializes");
        let routes = route_lines(&document);
        ApiDocument {
            document,
            json,
            routes,
        }
    });
    &DOCUMENT
}

/// What the document starts from before the routes add their operations.
#[derive(OpenApi)]
#[openapi(
    info(
        title = "Helmholtz REST API",
        description = "Dual photography and computational ghost imaging: sessions, reconstructions, dual images, relighting and tokens. Measurements are uploaded over gRPC (helmholtz.v1.Acquisition on this same address). Every error is application/problem+json (RFC 9457) with the schema Problem; a 400 names the offending input in `field`. A path no route serves is a 404 problem, an HTTP method a route does not take a 405 problem (with an Allow header).",
        license(name = "MIT", identifier = "MIT"),
    ),
    security(("bearer" = []), ("basic" = [])),
    modifiers(&SecuritySchemes),
    components(
        // Report: a reconstruction's `report` (ReconstructionView is generic over it).
        schemas(Problem, Report),
        responses(
            BadRequest,
            Unauthorized,
            Forbidden,
            NotFound,
            RequestTimeout,
            Conflict,
            TooLarge,
            RangeNotSatisfiable,
            ChecksumMismatch,
            TooManyRequests,
            Internal,
            Unavailable,
            NotModified
        )
    ),
    tags(
        (name = "service", description = "The service index, health, metrics and this document"),
        (name = "sessions", description = "Acquisition sessions (created and uploaded over gRPC, or over REST for tools without gRPC) and their files"),
        (name = "reconstructions", description = "Reconstruction jobs and their files"),
        (name = "relighting", description = "Camera sessions' transport matrices: relit dual images and predicted camera images"),
        (name = "tokens", description = "A lab's access tokens (admin)"),
        (name = "viewer", description = "The web viewer's files (the viewer itself is GET / in a browser)"),
    )
)]
pub struct Base;

struct SecuritySchemes;

impl Modify for SecuritySchemes {
    fn modify(&self, openapi: &mut Document) {
        let components = openapi.components.get_or_insert_with(Default::default);
        let mut bearer = Http::new(HttpAuthScheme::Bearer);
        bearer.bearer_format = Some("hz_...".into());
        bearer.description = Some(
            "A token of a lab (helmholtz-server token create, or POST /v1/tokens): `Authorization: Bearer <token>`. Roles: rig, reader, admin."
                .into(),
        );
        components.add_security_scheme("bearer", SecurityScheme::Http(bearer));
        let mut basic = Http::new(HttpAuthScheme::Basic);
        basic.description = Some(
            "The same token as the password (or the user name) of HTTP Basic, for tools that only speak Basic (e.g. a URL `http://TOKEN@host`)."
                .into(),
        );
        components.add_security_scheme("basic", SecurityScheme::Http(basic));
    }
}

/// A problem+json response (schema [`Problem`]) with `headers` (name, description).
fn problem(description: &str, headers: &[(&str, &str)]) -> openapi::Response {
    let mut response = ResponseBuilder::new().description(description).content(
        PROBLEM_JSON,
        Content::new(Some(Ref::from_schema_name("Problem"))),
    );
    for (name, about) in headers {
        let schema = ObjectBuilder::new().schema_type(Type::String);
        response = response.header(
            *name,
            HeaderBuilder::new()
                .schema(Some(schema))
                .description(Some(*about))
                .build(),
        );
    }
    response.build()
}

/// Reusable responses, `#/components/responses/{name}`: the problem+json answers.
macro_rules! problem_responses {
    ($($(#[$doc:meta])* $name:ident: $description:literal $([$header:literal: $about:literal])*;)*) => {
        $(
            $(#[$doc])*
            pub struct $name;

            impl<'r> ToResponse<'r> for $name {
                fn response() -> (&'r str, RefOr<openapi::Response>) {
                    (stringify!($name), problem($description, &[$(($header, $about)),*]).into())
                }
            }
        )*
    };
}

problem_responses! {
    BadRequest: "Invalid input (invalid-argument): `field` names it as the request spells it (a path or query parameter, a body field such as `light.radius`, `content-type`, `body`)";
    Unauthorized: "No usable token (unauthenticated): missing, malformed, unknown or revoked"
        ["WWW-Authenticate": "Bearer realm=\"helmholtz\""];
    Forbidden: "The token's roles do not allow this call (permission-denied)";
    NotFound: "No such resource in the caller's lab (not-found)";
    RequestTimeout: "The request body stopped arriving for the body timeout (request-timeout)";
    Conflict: "Not possible in the resource's current state (failed-precondition, e.g. a reconstruction that is not done or already ended), or conflicting with an existing resource (already-exists)";
    TooLarge: "The request body is over max_body_bytes (too-large, `limit`), or the reconstruction's estimated memory is over the budget (memory-budget, `estimate_bytes`, `limit_bytes`)";
    TooManyRequests: "Over the token's request rate or a cap (resource-exhausted, `limit` names it)"
        ["Retry-After": "Seconds to wait before retrying (the request rate)"];
    RangeNotSatisfiable: "Rows that do not follow the committed ones (out-of-range): a start above the committed count (a gap), or rows past the spec's count";
    ChecksumMismatch: "The body does not match its checksum (data-loss): nothing was stored; send it again";
    Internal: "Internal error (internal; the cause is logged, not sent)";
    Unavailable: "The database does not answer; retry shortly (unavailable)";
}

/// `304 Not Modified` for an `If-None-Match` naming the current ETag (no body).
pub struct NotModified;

impl<'r> ToResponse<'r> for NotModified {
    fn response() -> (&'r str, RefOr<openapi::Response>) {
        let etag = HeaderBuilder::new()
            .schema(Some(ObjectBuilder::new().schema_type(Type::String)))
            .description(Some("The answer's strong ETag"))
            .build();
        (
            "NotModified",
            ResponseBuilder::new()
                .description("The `If-None-Match` request header names this answer's ETag: nothing changed (no body)")
                .header("ETag", etag)
                .build()
                .into(),
        )
    }
}

/// Adds what the annotations leave to one place: the answers of authentication and the store
/// to every operation that needs a token, the methods of `POST .../reconstructions`.
pub fn finish(mut document: Document) -> Document {
    let methods: Vec<&str> = crate::recon::Request::method_names().collect();
    for item in document.paths.paths.values_mut() {
        for operation in operations_mut(item) {
            if operation.operation_id.as_deref() == Some("post_reconstruction") {
                operation.summary = Some(format!(
                    "Request a reconstruction: {{\"method\": \"{}\", \"params\": {{}}}} (transport: camera sessions)",
                    methods.join("|")
                ));
            }
            if is_open(operation) {
                continue;
            }
            for (status, name) in [
                ("401", "Unauthorized"),
                ("429", "TooManyRequests"),
                ("500", "Internal"),
                ("503", "Unavailable"),
            ] {
                operation
                    .responses
                    .responses
                    .entry(status.to_string())
                    .or_insert_with(|| RefOr::Ref(Ref::from_response_name(name)));
            }
        }
    }
    // The method names the parser accepts, as an enum of ReconstructionRequest.method.
    if let Some(RefOr::T(Schema::Object(request))) = document
        .components
        .as_mut()
        .and_then(|c| c.schemas.get_mut("ReconstructionRequest"))
        && let Some(RefOr::T(Schema::Object(method))) = request.properties.get_mut("method")
    {
        method.enum_values = Some(methods.iter().map(|m| (*m).into()).collect());
    }
    document
}

/// An operation anyone may call: its security is the empty requirement (`security: [{}]`).
pub fn is_open(operation: &openapi::path::Operation) -> bool {
    operation
        .security
        .as_ref()
        .is_some_and(|s| s.iter().any(|r| *r == SecurityRequirement::default()))
}

/// The operations of a path item with their HTTP methods, in a fixed order.
pub fn operations(
    item: &openapi::PathItem,
) -> impl Iterator<Item = (&'static str, &openapi::path::Operation)> {
    [
        ("GET", &item.get),
        ("PUT", &item.put),
        ("POST", &item.post),
        ("DELETE", &item.delete),
        ("OPTIONS", &item.options),
        ("HEAD", &item.head),
        ("PATCH", &item.patch),
        ("TRACE", &item.trace),
    ]
    .into_iter()
    .filter_map(|(method, op)| op.as_ref().map(|op| (method, op)))
}

fn operations_mut(
    item: &mut openapi::PathItem,
) -> impl Iterator<Item = &mut openapi::path::Operation> {
    [
        &mut item.get,
        &mut item.put,
        &mut item.post,
        &mut item.delete,
        &mut item.options,
        &mut item.head,
        &mut item.patch,
        &mut item.trace,
    ]
    .into_iter()
    .filter_map(Option::as_mut)
}

/// `GET /`'s route list: `METHOD /path?query|names: summary (no token)`, from the document.
fn route_lines(document: &Document) -> Vec<String> {
    let mut lines = Vec::new();
    for (path, item) in &document.paths.paths {
        for (method, operation) in operations(item) {
            let query: Vec<&str> = operation
                .parameters
                .iter()
                .flatten()
                .filter_map(|p| match p {
                    RefOr::T(p) if p.parameter_in == openapi::path::ParameterIn::Query => {
                        Some(p.name.as_str())
                    }
                    _ => None,
                })
                .collect();
            let query = if query.is_empty() {
                String::new()
            } else {
                format!("?{}", query.join("&"))
            };
            // Enumerated path parameters name their values: `({file}: a|b|c)`.
            let choices: String = operation
                .parameters
                .iter()
                .flatten()
                .filter_map(|p| match p {
                    RefOr::T(p) if p.parameter_in == openapi::path::ParameterIn::Path => {
                        match &p.schema {
                            Some(RefOr::T(Schema::Object(o))) => o.enum_values.as_ref().map(|v| {
                                let v: Vec<&str> = v.iter().filter_map(|v| v.as_str()).collect();
                                format!(" ({{{}}}: {})", p.name, v.join("|"))
                            }),
                            _ => None,
                        }
                    }
                    _ => None,
                })
                .collect();
            let summary = operation.summary.as_deref().unwrap_or("");
            let open = if is_open(operation) {
                " (no token needed)"
            } else {
                ""
            };
            lines.push(format!("{method} {path}{query}: {summary}{choices}{open}"));
        }
    }
    lines
}

/// The OpenAPI 3.1 document of this API
///
/// Open (no token): the document describes the API, it holds no data.
#[utoipa::path(
    get,
    path = "/openapi.json",
    tag = "service",
    security(()),
    responses((status = 200, description = "The OpenAPI 3.1 document", content_type = "application/json", body = Object))
)]
pub async fn openapi_json() -> Response {
    (
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        )],
        document().json.clone(),
    )
        .into_response()
}

/// The page of `GET /docs`: self-contained (inline script and style), it reads `/openapi.json`.
pub const DOCS_HTML: &str = include_str!("docs.html");

/// The API's documentation page
///
/// A self-contained page (no script, style or font from another host) that reads
/// `/openapi.json` and lists every route with its parameters, bodies, responses and schemas.
#[utoipa::path(
    get,
    path = "/docs",
    tag = "service",
    security(()),
    responses((status = 200, description = "An HTML page", content_type = "text/html", body = String))
)]
pub async fn docs() -> Response {
    (
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("text/html; charset=utf-8"),
        )],
        DOCS_HTML,
    )
        .into_response()
}

/// A string parameter's schema: one of `values`.
fn one_of(values: &[&str], description: &str) -> RefOr<Schema> {
    ObjectBuilder::new()
        .schema_type(Type::String)
        .enum_values(Some(values.iter().copied()))
        .description(Some(description))
        .into()
}

/// `{file}` of `GET /v1/sessions/{id}/{file}`.
pub struct SessionFile;

impl PartialSchema for SessionFile {
    fn schema() -> RefOr<Schema> {
        let mut names = vec!["measurements.npy", "adaptive.json"];
        names.extend(super::rest::DUAL_FILES);
        one_of(
            &names,
            "measurements.npy: the committed rows (NPY); adaptive.json: an adaptive session's issued batches of basis indices, in order; dual.png|dual.tiff|dual.npy: the dual image of the latest finished reconstruction",
        )
    }
}

impl ToSchema for SessionFile {
    fn name() -> Cow<'static, str> {
        "SessionFile".into()
    }
}

/// `{file}` of `GET /v1/reconstructions/{id}/{file}`.
pub struct ReconstructionFile;

impl PartialSchema for ReconstructionFile {
    fn schema() -> RefOr<Schema> {
        let mut names: Vec<&str> = super::rest::DUAL_FILES.to_vec();
        names.extend(super::relight::DERIVED_FILES);
        one_of(
            &names,
            "dual.png|dual.tiff|dual.npy: a dual image; normals, albedo, residual, photometric.json: photometric stereo (3+ channels with declared directions); composite.png: channels r, g, b",
        )
    }
}

impl ToSchema for ReconstructionFile {
    fn name() -> Cow<'static, str> {
        "ReconstructionFile".into()
    }
}

#[cfg(test)]
mod tests {
    use std::collections::{BTreeMap, BTreeSet};

    use super::*;

    /// The (METHOD, path) pairs the REST router itself routes, read from its `Debug` output
    /// (axum has no other way to list its routes): `paths: {RouteId(n): "/path"}` and, per
    /// route, `allow_header: Bytes(b"GET,HEAD")`. Panics when the format is not recognised.
    fn routed(router: &axum::Router<crate::api::AppState>) -> BTreeSet<(String, String)> {
        let text = format!("{router:?}");
        let end = text
            .find("fallback_router")
            .expect("axum's Router Debug output has a fallback_router");
        let mut rest = &text[..end];
        let (mut paths, mut allows) = (BTreeMap::new(), BTreeMap::new());
        while let Some(i) = rest.find("RouteId(") {
            rest = &rest[i + "RouteId(".len()..];
            let close = rest.find(')').expect("RouteId(n)");
            let id: u32 = rest[..close].parse().expect("a route id");
            let after = &rest[close + 1..];
            if let Some(path) = after.strip_prefix(": \"") {
                paths.insert(
                    id,
                    path[..path.find('"').expect("a quoted path")].to_string(),
                );
            } else if after.starts_with(": MethodRouter(") {
                let at = after.find("allow_header: ").expect("allow_header");
                let allow = &after[at + "allow_header: ".len()..];
                let allow = allow
                    .strip_prefix("Bytes(b\"")
                    .map(|a| &a[..a.find('"').expect("closing quote")])
                    .unwrap_or_else(|| panic!("a route without methods: {}", &allow[..20]));
                allows.insert(id, allow.to_string());
            }
        }
        assert!(!paths.is_empty(), "no routes read from {text}");
        assert_eq!(
            paths.keys().collect::<Vec<_>>(),
            allows.keys().collect::<Vec<_>>(),
            "{text}"
        );
        let mut out = BTreeSet::new();
        for (id, path) in paths {
            let methods: Vec<&str> = allows[&id].split(',').collect();
            for m in &methods {
                // axum answers HEAD wherever it serves GET.
                if *m == "HEAD" && methods.contains(&"GET") {
                    continue;
                }
                out.insert((m.to_string(), path.clone()));
            }
        }
        out
    }

    fn documented(document: &Document) -> BTreeSet<(String, String)> {
        document
            .paths
            .paths
            .iter()
            .flat_map(|(path, item)| {
                operations(item).map(move |(method, _)| (method.to_string(), path.clone()))
            })
            .collect()
    }

    #[test]
    fn the_router_routes_exactly_the_documented_operations() {
        let routed = routed(&crate::api::rest::routes());
        let documented = documented(&document().document);
        assert_eq!(
            routed.difference(&documented).collect::<Vec<_>>(),
            Vec::<&(String, String)>::new(),
            "routed but not documented: annotate the handler with #[utoipa::path] and route it with .routes(routes!(handler)) in rest::api"
        );
        assert_eq!(
            documented.difference(&routed).collect::<Vec<_>>(),
            Vec::<&(String, String)>::new(),
            "documented but not routed"
        );
        assert!(routed.len() >= 18, "{routed:?}");
    }

    #[test]
    fn the_route_reader_sees_a_route_added_outside_the_document() {
        // The check above would notice a plain .route(): the reader sees it.
        let extra = crate::api::rest::routes()
            .route("/v1/undocumented", axum::routing::put(|| async { "" }));
        let routed = routed(&extra);
        assert!(routed.contains(&("PUT".to_string(), "/v1/undocumented".to_string())));
        assert!(
            !documented(&document().document)
                .contains(&("PUT".to_string(), "/v1/undocumented".to_string()))
        );
    }

    #[test]
    fn every_authenticated_operation_lists_the_problems_of_authentication() {
        let document = &document().document;
        let mut open = Vec::new();
        for (path, item) in &document.paths.paths {
            for (method, operation) in operations(item) {
                if is_open(operation) {
                    open.push(format!("{method} {path}"));
                    continue;
                }
                for status in ["401", "429", "500", "503"] {
                    assert!(
                        operation.responses.responses.contains_key(status),
                        "{method} {path}: no {status}"
                    );
                }
            }
        }
        assert_eq!(
            open,
            [
                "GET /assets/{file}",
                "GET /docs",
                "GET /healthz",
                "GET /openapi.json"
            ]
        );
    }

    #[test]
    fn the_file_parameters_name_every_file_the_handlers_serve() {
        let names = |schema: RefOr<Schema>| -> Vec<String> {
            match schema {
                RefOr::T(Schema::Object(o)) => o
                    .enum_values
                    .unwrap()
                    .iter()
                    .map(|v| v.as_str().unwrap().to_string())
                    .collect(),
                other => panic!("{}", serde_json::to_string(&other).unwrap()),
            }
        };
        let reconstruction = names(ReconstructionFile::schema());
        for f in super::super::relight::DERIVED_FILES
            .iter()
            .chain(&super::super::rest::DUAL_FILES)
        {
            assert!(reconstruction.contains(&f.to_string()), "{f}");
        }
        assert_eq!(reconstruction.len(), 10);
        assert_eq!(
            names(SessionFile::schema()),
            [
                "measurements.npy",
                "adaptive.json",
                "dual.png",
                "dual.tiff",
                "dual.npy"
            ]
        );
    }

    #[test]
    fn the_page_is_self_contained() {
        for needle in ["http://", "https://", "//cdn", "url(", "@import"] {
            assert!(!DOCS_HTML.contains(needle), "{needle}");
        }
        assert!(DOCS_HTML.contains("fetch(\"/openapi.json\")"));
    }
}
