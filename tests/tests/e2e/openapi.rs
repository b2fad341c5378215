//! The OpenAPI document against the real server: `/openapi.json` (no token) is a valid OpenAPI
//! 3.1 document whose references all resolve; every operation it lists is served by the router
//! and every method the router serves on a path is in it (the router's own 405 `Allow` header
//! says which); every answer the server gives is one the document lists, with its media type;
//! every error is problem+json; and `/docs` is a page that needs nothing from another host.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use helmholtz_proto::v1;
use helmholtz_tests::{ServerProcess, bucket_session, f64_chunk};
use serde_json::{Value, json};

const PROBLEM_JSON: &str = "application/problem+json";
const METHODS: [&str; 8] = [
    "get", "put", "post", "delete", "options", "head", "patch", "trace",
];

async fn document(server: &ServerProcess) -> (String, Value) {
    // No token: tools fetch the document as they find it.
    let r = helmholtz_tests::http_get(format!("{}/openapi.json", server.address))
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(
        r.headers()["content-type"].to_str().unwrap(),
        "application/json"
    );
    let text = r.text().await.unwrap();
    let value: Value = serde_json::from_str(&text).unwrap();
    (text, value)
}

/// Every `$ref` in `node` (recursively), as JSON pointers.
fn refs<'a>(node: &'a Value, out: &mut Vec<&'a str>) {
    match node {
        Value::Object(map) => {
            for (k, v) in map {
                match (k.as_str(), v) {
                    ("$ref", Value::String(r)) => out.push(r),
                    _ => refs(v, out),
                }
            }
        }
        Value::Array(items) => items.iter().for_each(|v| refs(v, out)),
        _ => {}
    }
}

/// Follows local references (`#/components/...`) to the object they name.
fn resolve<'a>(doc: &'a Value, mut node: &'a Value) -> &'a Value {
    while let Some(r) = node.get("$ref").and_then(Value::as_str) {
        let pointer = r.strip_prefix('#').expect("a local reference");
        node = doc
            .pointer(pointer)
            .unwrap_or_else(|| panic!("{r} resolves to nothing"));
    }
    node
}

/// (method, path, operation) of every operation in the document.
fn operations(doc: &Value) -> Vec<(String, String, &Value)> {
    let mut out = Vec::new();
    for (path, item) in doc["paths"].as_object().expect("paths") {
        for m in METHODS {
            if let Some(op) = item.get(m) {
                out.push((m.to_uppercase(), path.clone(), op));
            }
        }
    }
    out
}

fn is_open(op: &Value) -> bool {
    op["security"].as_array().is_some_and(|s| {
        s.iter()
            .any(|r| r.as_object().is_some_and(|o| o.is_empty()))
    })
}

fn parameters<'a>(doc: &'a Value, op: &'a Value) -> Vec<&'a Value> {
    op["parameters"]
        .as_array()
        .map(|ps| ps.iter().map(|p| resolve(doc, p)).collect())
        .unwrap_or_default()
}

/// The response the document gives for `status` (or its range, or `default`).
fn documented_response<'a>(doc: &'a Value, op: &'a Value, status: u16) -> Option<&'a Value> {
    let responses = &op["responses"];
    let range = format!("{}XX", status / 100);
    [status.to_string(), range, "default".into()]
        .iter()
        .find_map(|k| responses.get(k))
        .map(|r| resolve(doc, r))
}

/// Checks a real answer of `method path` against the document's operation: its status is
/// listed, its content type is one the listed response carries (a response without content
/// has an empty body), and an error is problem+json.
async fn check_answer(
    doc: &Value,
    op: &Value,
    what: &str,
    response: reqwest::Response,
) -> (u16, Vec<u8>) {
    let status = response.status().as_u16();
    let content_type = response.headers().get("content-type").map(|v| {
        v.to_str()
            .unwrap()
            .split(';')
            .next()
            .unwrap()
            .trim()
            .to_string()
    });
    let body = response.bytes().await.unwrap().to_vec();
    let text = String::from_utf8_lossy(&body[..body.len().min(300)]).to_string();
    let documented = documented_response(doc, op, status)
        .unwrap_or_else(|| panic!("{what}: status {status} is not documented ({text})"));
    match (documented.get("content"), content_type) {
        (Some(Value::Object(content)), Some(ct)) => assert!(
            content.contains_key(&ct),
            "{what}: {status} sent {ct}, the document lists {:?} ({text})",
            content.keys().collect::<Vec<_>>()
        ),
        (Some(_), None) => panic!("{what}: {status} sent no content type"),
        (Some(other), _) => panic!("{what}: {status}: content {other}"),
        (None, _) => assert!(
            body.is_empty(),
            "{what}: {status} has a body the document does not list: {text}"
        ),
    }
    if status >= 400 && op["operationId"] != "healthz" {
        assert!(
            documented["content"].get(PROBLEM_JSON).is_some(),
            "{what}: {status} is documented without problem+json"
        );
        let problem: Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(problem["status"], status, "{what}: {problem}");
        assert!(
            problem["type"].as_str().unwrap().starts_with("/problems/"),
            "{what}: {problem}"
        );
        if status == 400 {
            assert!(problem["field"].is_string(), "{what}: {problem}");
        }
    }
    (status, body)
}

/// `path` with its path parameters filled: `{file}` by `file`, ids by ones that exist nowhere.
fn fill(path: &str, session: &str, number: &str, file: &str) -> String {
    let id = if path.starts_with("/v1/sessions/") {
        session
    } else {
        number
    };
    path.replace("{id}", id).replace("{file}", file)
}

/// The values of the enum of parameter `name` of `op` (empty if none).
fn enum_values(doc: &Value, op: &Value, name: &str) -> Vec<String> {
    parameters(doc, op)
        .into_iter()
        .find(|p| p["name"] == name)
        .and_then(|p| p["schema"]["enum"].as_array())
        .map(|v| v.iter().map(|s| s.as_str().unwrap().to_string()).collect())
        .unwrap_or_default()
}

#[tokio::test]
async fn the_document_is_openapi_3_1_and_every_reference_resolves() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let (text, doc) = document(&server).await;

    // A parser for OpenAPI 3.1 reads it, and it says 3.1.
    let spec = oas3::from_json(&text).expect("an OpenAPI 3.1 document");
    let version = spec
        .validate_version()
        .expect("a supported OpenAPI version");
    assert_eq!((version.major, version.minor), (3, 1), "{version}");
    assert!(doc["openapi"].as_str().unwrap().starts_with("3.1"));
    assert!(!doc["info"]["title"].as_str().unwrap().is_empty());

    // Every reference resolves, and the typed view resolves every parameter, body, response
    // and header of every operation.
    let mut all = Vec::new();
    refs(&doc, &mut all);
    assert!(all.len() > 20, "{} references", all.len());
    for r in &all {
        resolve(&doc, &json!({ "$ref": r }));
    }
    let mut ids = BTreeSet::new();
    for (path, method, op) in spec.operations() {
        let what = format!("{method} {path}");
        let id = op.operation_id.clone().unwrap_or_default();
        assert!(ids.insert(id.clone()), "{what}: operationId {id:?} twice");
        assert!(
            op.summary.as_deref().is_some_and(|s| !s.is_empty()),
            "{what}: no summary"
        );
        for p in &op.parameters {
            p.resolve(&spec).unwrap_or_else(|e| panic!("{what}: {e}"));
        }
        if let Some(body) = &op.request_body {
            body.resolve(&spec)
                .unwrap_or_else(|e| panic!("{what}: {e}"));
        }
        let responses = op.responses.as_ref().expect("responses");
        assert!(!responses.is_empty(), "{what}");
        for (status, r) in responses {
            let r = r
                .resolve(&spec)
                .unwrap_or_else(|e| panic!("{what} {status}: {e}"));
            for (name, h) in &r.headers {
                h.resolve(&spec)
                    .unwrap_or_else(|e| panic!("{what} {status} {name}: {e}"));
            }
            for (ct, media) in &r.content {
                media
                    .schema(&spec)
                    .unwrap_or_else(|e| panic!("{what} {status} {ct}: {e}"));
            }
        }
        // Path parameters are exactly the template's.
        let template: BTreeSet<String> = path
            .split('/')
            .filter_map(|s| s.strip_prefix('{')?.strip_suffix('}'))
            .map(String::from)
            .collect();
        let declared: BTreeSet<String> = op
            .parameters(&spec)
            .unwrap()
            .into_iter()
            .filter(|p| p.location == oas3::spec::ParameterIn::Path)
            .map(|p| p.name)
            .collect();
        assert_eq!(template, declared, "{what}");
    }

    // The token: bearer, or the same token as HTTP Basic; required by default.
    let schemes = &doc["components"]["securitySchemes"];
    assert_eq!(schemes["bearer"]["type"], "http");
    assert_eq!(schemes["bearer"]["scheme"], "bearer");
    assert_eq!(schemes["basic"]["scheme"], "basic");
    assert!(
        doc["security"]
            .as_array()
            .unwrap()
            .iter()
            .any(|r| r.get("bearer").is_some())
    );
    // The Problem schema has the fields every error carries.
    let problem = &doc["components"]["schemas"]["Problem"];
    for field in ["type", "title", "status", "detail", "field", "limit"] {
        assert!(problem["properties"].get(field).is_some(), "{problem}");
    }
}

#[tokio::test]
async fn every_operation_lists_its_parameters_media_types_and_problem_answers() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let (_, doc) = document(&server).await;
    let ops = operations(&doc);
    let problem_ref = |doc: &Value, op: &Value, status: &str| -> bool {
        op["responses"].get(status).is_some_and(|r| {
            let r = resolve(doc, r);
            r["content"][PROBLEM_JSON]["schema"]["$ref"] == "#/components/schemas/Problem"
        })
    };
    let mut open = Vec::new();
    for (method, path, op) in &ops {
        let what = format!("{method} {path}");
        if is_open(op) {
            open.push(path.as_str());
            continue;
        }
        // Authentication, the rate limit and the store can refuse any call with a token.
        for status in ["401", "429", "500", "503"] {
            assert!(problem_ref(&doc, op, status), "{what}: no {status} problem");
        }
        let unauthorized = resolve(&doc, &op["responses"]["401"]);
        assert!(unauthorized["headers"].get("WWW-Authenticate").is_some());
        let limited = resolve(&doc, &op["responses"]["429"]);
        assert!(limited["headers"].get("Retry-After").is_some());
        let params = parameters(&doc, op);
        if params
            .iter()
            .any(|p| p["in"] == "path" || p["in"] == "query")
        {
            assert!(problem_ref(&doc, op, "400"), "{what}: no 400 problem");
        }
        if params.iter().any(|p| p["in"] == "path") {
            assert!(problem_ref(&doc, op, "404"), "{what}: no 404 problem");
        }
        if path != "/" {
            assert!(problem_ref(&doc, op, "403"), "{what}: no 403 problem");
        }
        if op.get("requestBody").is_some() {
            for status in ["400", "408", "413"] {
                assert!(problem_ref(&doc, op, status), "{what}: no {status} problem");
            }
        }
    }
    assert_eq!(
        open,
        ["/assets/{file}", "/docs", "/healthz", "/openapi.json"]
    );

    let op = |method: &str, path: &str| -> &Value { &doc["paths"][path][method.to_lowercase()] };
    let query = |method: &str, path: &str| -> BTreeSet<String> {
        parameters(&doc, op(method, path))
            .iter()
            .filter(|p| p["in"] == "query")
            .map(|p| p["name"].as_str().unwrap().to_string())
            .collect()
    };
    let set = |names: &[&str]| names.iter().map(|s| s.to_string()).collect::<BTreeSet<_>>();
    assert_eq!(query("GET", "/v1/sessions"), set(&["limit"]));
    assert_eq!(
        query("GET", "/v1/sessions/{id}/{file}"),
        set(&["channel", "scale"])
    );
    assert_eq!(
        query("GET", "/v1/reconstructions/{id}/{file}"),
        set(&[
            "channel",
            "scale",
            "gains",
            "shadow_threshold",
            "dark_threshold"
        ])
    );
    assert_eq!(
        query("POST", "/v1/reconstructions/{id}/relight"),
        set(&["format", "scale"])
    );
    // The live preview: its parameters, and the event's data as a schema.
    assert_eq!(
        query("GET", "/v1/sessions/{id}/preview"),
        set(&["channel", "every_rows", "every_ms"])
    );
    let preview = &op("GET", "/v1/sessions/{id}/preview")["responses"]["200"]["content"];
    assert!(preview.get("text/event-stream").is_some(), "{preview}");
    let event = &doc["components"]["schemas"]["PreviewEvent"]["properties"];
    for field in ["rows", "method", "values_f32le", "final"] {
        assert!(event.get(field).is_some(), "PreviewEvent.{field}: {event}");
    }
    assert_eq!(
        query("POST", "/v1/reconstructions/{id}/primal"),
        set(&["format", "scale", "ambient"])
    );
    let relight = op("POST", "/v1/reconstructions/{id}/relight");
    assert_eq!(enum_values(&doc, relight, "format"), ["png", "tiff", "npy"]);
    assert_eq!(
        enum_values(&doc, relight, "scale"),
        ["percentile", "minmax"]
    );
    // Image bodies in, images out.
    for path in [
        "/v1/reconstructions/{id}/relight",
        "/v1/reconstructions/{id}/primal",
    ] {
        let o = op("POST", path);
        let body = resolve(&doc, &o["requestBody"]);
        for ct in [
            "application/json",
            "image/png",
            "application/x-npy",
            "application/octet-stream",
        ] {
            assert!(body["content"].get(ct).is_some(), "{path} takes {ct}");
        }
        let ok = &o["responses"]["200"];
        for ct in ["image/png", "image/tiff", "application/octet-stream"] {
            assert!(ok["content"].get(ct).is_some(), "{path} answers {ct}");
        }
        assert!(ok["headers"].get("ETag").is_some());
        assert!(o["responses"].get("304").is_some());
    }
    let primal = &op("POST", "/v1/reconstructions/{id}/primal")["responses"]["200"]["headers"];
    assert!(primal.get("x-helmholtz-relative-error").is_some());
    let posted = &op("POST", "/v1/sessions/{id}/reconstructions")["responses"]["202"];
    assert!(posted["headers"].get("Location").is_some());
    // The methods the parser accepts, named where the body is described.
    let request = &doc["components"]["schemas"]["ReconstructionRequest"];
    let methods: Vec<&str> = request["properties"]["method"]["enum"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    for m in ["gi", "dgi", "tv", "auto", "transport"] {
        assert!(methods.contains(&m), "{methods:?}");
    }
}

/// Probes every path the document lists: each documented method is served (not the router's
/// 404 or 405 fallback) and answers as documented; every other method gets the router's 405,
/// whose `Allow` header lists what the router serves there, which must be what is documented.
#[tokio::test]
async fn the_router_serves_exactly_the_documented_paths_and_methods() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let (_, doc) = document(&server).await;
    let client = helmholtz_tests::http_client();
    let paths = doc["paths"].as_object().unwrap();
    assert!(paths.len() >= 15, "{} paths", paths.len());
    let mut probes = 0;
    for (path, item) in paths {
        let documented: BTreeSet<String> = METHODS
            .iter()
            .filter(|m| item.get(**m).is_some())
            .map(|m| m.to_uppercase())
            .collect();
        let files = item
            .as_object()
            .unwrap()
            .values()
            .map(|op| enum_values(&doc, op, "file"))
            .find(|v| !v.is_empty())
            .unwrap_or_else(|| vec![String::new()]);
        for file in &files {
            let url = server.url(&fill(path, "no-such-session", "987654", file));
            // Methods the router does not serve here: 405 problem naming those it does.
            for method in ["GET", "POST", "PUT", "PATCH", "DELETE"] {
                if documented.contains(method) {
                    continue;
                }
                let r = client
                    .request(method.parse().unwrap(), &url)
                    .send()
                    .await
                    .unwrap();
                assert_eq!(r.status(), 405, "{method} {url}");
                let mut allowed: BTreeSet<String> = r.headers()["allow"]
                    .to_str()
                    .unwrap()
                    .split(',')
                    .map(|m| m.trim().to_string())
                    .collect();
                if documented.contains("GET") {
                    assert!(allowed.remove("HEAD"), "{url}: GET implies HEAD");
                }
                assert_eq!(allowed, documented, "{path}: routed vs documented");
                assert_eq!(r.headers()["content-type"], PROBLEM_JSON);
                probes += 1;
            }
            // Methods it documents: served by their handler, answering as documented.
            for method in &documented {
                let op = &item[method.to_lowercase()];
                let mut request = client.request(method.parse().unwrap(), &url);
                if op.get("requestBody").is_some() {
                    request = request
                        .header("content-type", "application/json")
                        .body("{}");
                }
                let r = request.send().await.unwrap();
                let (status, body) = check_answer(&doc, op, &format!("{method} {url}"), r).await;
                assert_ne!(status, 405, "{method} {url}");
                if status == 404 {
                    let detail = String::from_utf8_lossy(&body).to_string();
                    assert!(
                        !detail.contains("no such route"),
                        "{method} {url}: {detail}"
                    );
                }
                probes += 1;
            }
        }
    }
    assert!(probes > 40, "{probes} probes");

    // A path the document does not list is the router's 404 problem.
    let r = client
        .get(server.url("/v1/nothing-here"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404);
    assert!(r.text().await.unwrap().contains("no such route"));
}

/// A real bucket session, reconstructed: every file and every documented value of every
/// enumerated query parameter answers as the document says (status, media type).
#[tokio::test]
async fn real_answers_have_the_documented_statuses_and_media_types() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let (_, doc) = document(&server).await;
    let client = helmholtz_tests::http_client();

    // Three channels r, g, b with detector directions: dual images, a colour composite and
    // photometric stereo all apply.
    let id = "openapi-rgb";
    let (side, rows, channels) = (8u32, 64u64, 3u32);
    let mut declaration = bucket_session(
        id,
        v1::PatternFamily::Bernoulli,
        side,
        side,
        rows,
        &["r", "g", "b"],
    );
    let s = 0.5f64.sqrt();
    declaration.detector.as_mut().unwrap().directions = vec![
        v1::Direction { x: s, y: 0.0, z: s },
        v1::Direction {
            x: -s,
            y: 0.0,
            z: s,
        },
        v1::Direction { x: 0.0, y: s, z: s },
    ];
    let mut grpc = server.grpc().await.unwrap();
    grpc.create_session(declaration).await.unwrap();
    let values: Vec<f64> = (0..rows * channels as u64)
        .map(|i| 1.0 + ((i * 2654435761) % 1000) as f64 / 1000.0)
        .collect();
    let chunk = f64_chunk(id, 0, channels, &values);
    let answer = grpc
        .upload_measurements(tokio_stream::iter(vec![chunk]))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.committed_rows, rows);

    let post = &doc["paths"]["/v1/sessions/{id}/reconstructions"]["post"];
    let r = client
        .post(server.url(&format!("/v1/sessions/{id}/reconstructions")))
        .header("content-type", "application/json")
        .body(r#"{"method": "dgi"}"#)
        .send()
        .await
        .unwrap();
    let location = r.headers()["location"].to_str().unwrap().to_string();
    let (status, body) = check_answer(&doc, post, "POST reconstructions", r).await;
    assert_eq!(status, 202);
    let rid = serde_json::from_slice::<Value>(&body).unwrap()["id"]
        .as_i64()
        .unwrap();
    assert_eq!(location, format!("/v1/reconstructions/{rid}"));
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let view: Value = client
            .get(server.url(&location))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if view["state"] == "done" {
            break;
        }
        assert!(
            view["state"] == "queued" || view["state"] == "running",
            "{view}"
        );
        assert!(Instant::now() < deadline, "not done: {view}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    // Every GET of the document on this session and reconstruction, with every enumerated
    // query value: the answers it documents. Dual images and the composite are 200s.
    let mut seen: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (method, path, op) in operations(&doc) {
        if method != "GET" || !path.contains("{id}") || path.starts_with("/v1/tokens") {
            continue;
        }
        let files = {
            let f = enum_values(&doc, op, "file");
            if f.is_empty() { vec![String::new()] } else { f }
        };
        for file in files {
            let base = fill(&path, id, &rid.to_string(), &file);
            let mut queries = vec![String::new()];
            for name in ["scale", "gains", "format"] {
                for v in enum_values(&doc, op, name) {
                    queries.push(format!("?{name}={v}"));
                }
            }
            for q in queries {
                let applies = match q.split('=').next().unwrap() {
                    "?scale" => file == "dual.png",
                    "?gains" => {
                        file.starts_with("normals")
                            || file.starts_with("albedo")
                            || file.starts_with("residual")
                            || file.starts_with("photometric")
                    }
                    _ => true,
                };
                if !applies {
                    continue;
                }
                let url = format!("{base}{q}");
                let r = client.get(server.url(&url)).send().await.unwrap();
                let ct = r
                    .headers()
                    .get("content-type")
                    .map(|v| v.to_str().unwrap().to_string())
                    .unwrap_or_default();
                let (status, body) = check_answer(&doc, op, &format!("GET {url}"), r).await;
                if file.starts_with("dual.") || file == "composite.png" || file.is_empty() {
                    assert_eq!(status, 200, "GET {url}: {}", String::from_utf8_lossy(&body));
                }
                if status == 200 {
                    seen.entry(path.clone()).or_default().insert(ct);
                }
            }
        }
    }
    let file_types = &seen["/v1/reconstructions/{id}/{file}"];
    for ct in ["image/png", "image/tiff", "application/octet-stream"] {
        assert!(file_types.contains(ct), "{file_types:?}");
    }
    assert!(seen["/v1/sessions/{id}/{file}"].contains("application/octet-stream"));

    // Relighting a bucket session by channel weights, in every documented format; primal is a
    // camera session's and a documented 409 here.
    let relight = &doc["paths"]["/v1/reconstructions/{id}/relight"]["post"];
    for format in enum_values(&doc, relight, "format") {
        let r = client
            .post(server.url(&format!(
                "/v1/reconstructions/{rid}/relight?format={format}"
            )))
            .header("content-type", "application/json")
            .body(r#"{"light": {"weights": {"r": 1.0, "b": 0.5}}}"#)
            .send()
            .await
            .unwrap();
        let (status, body) = check_answer(&doc, relight, &format!("relight {format}"), r).await;
        assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    }
    let primal = &doc["paths"]["/v1/reconstructions/{id}/primal"]["post"];
    let r = client
        .post(server.url(&format!("/v1/reconstructions/{rid}/primal")))
        .header("content-type", "application/json")
        .body(r#"{"pattern_index": 0}"#)
        .send()
        .await
        .unwrap();
    let (status, _) = check_answer(&doc, primal, "primal", r).await;
    assert_eq!(status, 409);
}

#[tokio::test]
async fn the_index_lists_the_documents_operations() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let (_, doc) = document(&server).await;
    let index: Value = helmholtz_tests::http_get(server.url("/"))
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let routes: Vec<&str> = index["routes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r.as_str().unwrap())
        .collect();
    let ops = operations(&doc);
    assert_eq!(routes.len(), ops.len(), "{routes:#?}");
    for (method, path, _) in &ops {
        let line = format!("{method} {path}");
        assert!(
            routes
                .iter()
                .any(|r| r.starts_with(&line) && r[line.len()..].starts_with([':', '?'])),
            "{line} not in the index: {routes:#?}"
        );
    }
}

#[tokio::test]
async fn the_docs_page_is_served_and_needs_nothing_from_another_host() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    // No token, like the document it reads.
    let r = helmholtz_tests::http_get(format!("{}/docs", server.address))
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(
        r.headers()["content-type"].to_str().unwrap(),
        "text/html; charset=utf-8"
    );
    let page = r.text().await.unwrap();
    assert!(page.contains("<html") && page.contains("/openapi.json"));
    // No absolute URL at all (so none to another host), no protocol-relative one, and no
    // external script, style sheet, font or image.
    for needle in [
        "http://",
        "https://",
        "src=\"//",
        "href=\"//",
        "url(",
        "@import",
    ] {
        assert!(!page.contains(needle), "the page holds {needle:?}");
    }
    for tag in ["<script", "<link", "<img", "<iframe"] {
        for (i, _) in page.match_indices(tag) {
            let end = page[i..].find('>').unwrap();
            let element = &page[i..i + end];
            assert!(
                !element.contains("src=") && !element.contains("href="),
                "external resource: {element}"
            );
        }
    }
}
