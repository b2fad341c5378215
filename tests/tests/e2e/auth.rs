//! Access control against the real server: every REST route and every RPC, called by each kind
//! of caller (a lab's rig, reader and admin tokens, no token, an unknown token, a revoked token,
//! a malformed header) on its own lab's resources and on another lab's, with the exact status.

use helmholtz_client::{NewSession, PatternSpec, UploadOptions};
use helmholtz_proto::v1;
use helmholtz_proto::wire::encode_values;
use helmholtz_tests::ServerProcess;
use reqwest::StatusCode;
use tonic::Code;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Need {
    Open,
    Any,
    Rig,
    Reader,
    RigOrReader,
    Admin,
}

#[derive(Clone, Debug)]
struct Caller {
    name: &'static str,
    /// The Authorization header sent, if any.
    header: Option<String>,
    /// Roles of a valid token; None: not a valid token.
    roles: Option<&'static [&'static str]>,
}

impl Caller {
    fn may(&self, need: Need) -> Result<(), Denied> {
        let Some(roles) = self.roles else {
            return if need == Need::Open {
                Ok(())
            } else {
                Err(Denied::Unauthenticated)
            };
        };
        let has = |r: &str| roles.contains(&r);
        let ok = match need {
            Need::Open | Need::Any => true,
            Need::Rig => has("rig"),
            Need::Reader => has("reader"),
            Need::RigOrReader => has("rig") || has("reader"),
            Need::Admin => has("admin"),
        };
        if ok { Ok(()) } else { Err(Denied::Forbidden) }
    }
}

enum Denied {
    Unauthenticated,
    Forbidden,
}

/// Lab A and lab B, each with a finished 4x4 raster session reconstructed once, and an open
/// session to upload to.
struct World {
    server: ServerProcess,
    a_recon: i64,
    b_recon: i64,
    a_victim_token: i64,
    b_victim_token: i64,
}

fn spec() -> PatternSpec {
    serde_json::from_str(r#"{"family":"raster","width":4,"height":4,"count":16,"seed":0}"#).unwrap()
}

async fn populate(server: &str, finished: &str, open: &str) -> i64 {
    let values: Vec<f64> = (0..16).map(|i| i as f64 + 1.0).collect();
    helmholtz_client::create_session(
        server,
        &NewSession::new(finished, spec(), vec!["bucket".into()]),
    )
    .await
    .unwrap();
    helmholtz_client::upload(server, finished, 1, &values, &UploadOptions::default())
        .await
        .unwrap();
    helmholtz_client::finish_session(server, finished)
        .await
        .unwrap();
    let open_spec: PatternSpec = serde_json::from_str(
        r#"{"family":"bernoulli","width":4,"height":4,"count":1000,"seed":1}"#,
    )
    .unwrap();
    helmholtz_client::create_session(
        server,
        &NewSession::new(open, open_spec, vec!["bucket".into()]),
    )
    .await
    .unwrap();
    let rec = helmholtz_client::request_reconstruction(
        server,
        finished,
        "direct",
        &serde_json::json!({}),
    )
    .await
    .unwrap();
    let done =
        helmholtz_client::wait_reconstruction(server, rec.id, std::time::Duration::from_secs(60))
            .await
            .unwrap();
    assert!(done.is_done(), "{done:?}");
    rec.id
}

async fn world() -> (tempfile::TempDir, World, Vec<Caller>) {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let setup_a = server.create_token("lab-a", "rig,reader").unwrap();
    let setup_b = server.create_token("lab-b", "rig,reader").unwrap();
    let a_recon = populate(&server.url_with(&setup_a), "sa", "open-a").await;
    let b_recon = populate(&server.url_with(&setup_b), "sb", "open-b").await;
    let bearer = |t: &str| Some(format!("Bearer {t}"));
    let revoked = server.create_token("lab-a", "rig,reader,admin").unwrap();
    let admin = server.create_token("lab-a", "admin").unwrap();
    // Revoke through the REST API (the admin's own lab) so revocation is shown to work there.
    let http = helmholtz_tests::http_client();
    let listed: serde_json::Value = http
        .get(format!("{}/v1/tokens", server.address))
        .bearer_auth(&admin)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let revoked_id = listed["tokens"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["roles"] == "rig,reader,admin")
        .unwrap()["id"]
        .as_i64()
        .unwrap();
    let r = http
        .delete(format!("{}/v1/tokens/{revoked_id}", server.address))
        .bearer_auth(&admin)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    // Tokens the admin matrix revokes (revoking is idempotent, so every admin call sees 200).
    let victim = |lab: &str| {
        let out = helmholtz_tests::server_command(
            &server.data_dir,
            &[
                "token", "create", "--lab", lab, "--role", "reader", "--json",
            ],
        )
        .output()
        .unwrap();
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert!(v["token"].as_str().unwrap().starts_with("hz_"));
        v["id"].as_i64().unwrap()
    };
    let (a_victim_token, b_victim_token) = (victim("lab-a"), victim("lab-b"));
    let callers = vec![
        Caller {
            name: "rig",
            header: bearer(&server.create_token("lab-a", "rig").unwrap()),
            roles: Some(&["rig"]),
        },
        Caller {
            name: "reader",
            header: bearer(&server.create_token("lab-a", "reader").unwrap()),
            roles: Some(&["reader"]),
        },
        Caller {
            name: "admin",
            header: bearer(&admin),
            roles: Some(&["admin"]),
        },
        Caller {
            name: "none",
            header: None,
            roles: None,
        },
        Caller {
            name: "unknown token",
            header: bearer(&format!("hz_{}", "A".repeat(43))),
            roles: None,
        },
        Caller {
            name: "revoked token",
            header: bearer(&revoked),
            roles: None,
        },
        Caller {
            name: "malformed",
            header: Some("Bearer not-a-token".into()),
            roles: None,
        },
        Caller {
            name: "wrong scheme",
            header: Some(format!("Token {setup_a}")),
            roles: None,
        },
    ];
    (
        dir,
        World {
            server,
            a_recon,
            b_recon,
            a_victim_token,
            b_victim_token,
        },
        callers,
    )
}

struct RestCase {
    method: &'static str,
    /// Path for (own lab, other lab).
    paths: (String, String),
    body: Option<&'static str>,
    need: Need,
    /// Status when allowed, for (own, other).
    ok: (u16, u16),
}

#[tokio::test]
async fn every_route_and_rpc_by_role_and_lab() {
    let (_dir, w, callers) = world().await;
    let s = &w.server;
    let both = |p: &str| (p.to_string(), p.to_string());
    let (ra, rb) = (w.a_recon, w.b_recon);
    let rest = vec![
        RestCase {
            method: "GET",
            paths: both("/healthz"),
            body: None,
            need: Need::Open,
            ok: (200, 200),
        },
        RestCase {
            method: "GET",
            paths: both("/"),
            body: None,
            need: Need::Any,
            ok: (200, 200),
        },
        RestCase {
            method: "GET",
            paths: both("/v1/sessions"),
            body: None,
            need: Need::Reader,
            ok: (200, 200),
        },
        RestCase {
            method: "GET",
            paths: ("/v1/sessions/sa".into(), "/v1/sessions/sb".into()),
            body: None,
            need: Need::Reader,
            ok: (200, 404),
        },
        RestCase {
            method: "GET",
            paths: (
                "/v1/sessions/sa/reconstructions".into(),
                "/v1/sessions/sb/reconstructions".into(),
            ),
            body: None,
            need: Need::Reader,
            ok: (200, 404),
        },
        RestCase {
            method: "POST",
            paths: (
                "/v1/sessions/sa/reconstructions".into(),
                "/v1/sessions/sb/reconstructions".into(),
            ),
            body: Some(r#"{"method": "direct"}"#),
            need: Need::Reader,
            ok: (202, 404),
        },
        RestCase {
            method: "GET",
            paths: (
                "/v1/sessions/sa/preview".into(),
                "/v1/sessions/sb/preview".into(),
            ),
            body: None,
            need: Need::RigOrReader,
            ok: (200, 404),
        },
        RestCase {
            method: "GET",
            paths: (
                "/v1/sessions/sa/measurements.npy".into(),
                "/v1/sessions/sb/measurements.npy".into(),
            ),
            body: None,
            need: Need::Reader,
            ok: (200, 404),
        },
        RestCase {
            method: "GET",
            paths: (
                "/v1/sessions/sa/dual.png".into(),
                "/v1/sessions/sb/dual.png".into(),
            ),
            body: None,
            need: Need::Reader,
            ok: (200, 404),
        },
        RestCase {
            method: "GET",
            paths: (
                "/v1/sessions/sa/dual.tiff".into(),
                "/v1/sessions/sb/dual.tiff".into(),
            ),
            body: None,
            need: Need::Reader,
            ok: (200, 404),
        },
        RestCase {
            method: "GET",
            paths: (
                format!("/v1/reconstructions/{ra}"),
                format!("/v1/reconstructions/{rb}"),
            ),
            body: None,
            need: Need::Reader,
            ok: (200, 404),
        },
        RestCase {
            method: "GET",
            paths: (
                format!("/v1/reconstructions/{ra}/dual.png"),
                format!("/v1/reconstructions/{rb}/dual.png"),
            ),
            body: None,
            need: Need::Reader,
            ok: (200, 404),
        },
        RestCase {
            method: "GET",
            paths: (
                format!("/v1/reconstructions/{ra}/dual.npy"),
                format!("/v1/reconstructions/{rb}/dual.npy"),
            ),
            body: None,
            need: Need::Reader,
            ok: (200, 404),
        },
        // Cancelling a finished reconstruction is a conflict (own) or not found (other).
        RestCase {
            method: "POST",
            paths: (
                format!("/v1/reconstructions/{ra}/cancel"),
                format!("/v1/reconstructions/{rb}/cancel"),
            ),
            body: None,
            need: Need::Reader,
            ok: (409, 404),
        },
        RestCase {
            method: "DELETE",
            paths: (
                format!("/v1/reconstructions/{ra}"),
                format!("/v1/reconstructions/{rb}"),
            ),
            body: None,
            need: Need::Reader,
            ok: (409, 404),
        },
        // Relighting a bucket session by its channel's weight; it has no camera (primal) and no
        // detector directions (normals), so those are conflicts for the own lab.
        RestCase {
            method: "POST",
            paths: (
                format!("/v1/reconstructions/{ra}/relight"),
                format!("/v1/reconstructions/{rb}/relight"),
            ),
            body: Some(r#"{"light": {"weights": {"bucket": 2}}}"#),
            need: Need::Reader,
            ok: (200, 404),
        },
        RestCase {
            method: "POST",
            paths: (
                format!("/v1/reconstructions/{ra}/primal"),
                format!("/v1/reconstructions/{rb}/primal"),
            ),
            body: Some(r#"{"pattern_index": 0}"#),
            need: Need::Reader,
            ok: (409, 404),
        },
        RestCase {
            method: "GET",
            paths: (
                format!("/v1/reconstructions/{ra}/normals.png"),
                format!("/v1/reconstructions/{rb}/normals.png"),
            ),
            body: None,
            need: Need::Reader,
            ok: (409, 404),
        },
        RestCase {
            method: "GET",
            paths: both("/v1/tokens"),
            body: None,
            need: Need::Admin,
            ok: (200, 200),
        },
        RestCase {
            method: "POST",
            paths: both("/v1/tokens"),
            body: Some(r#"{"roles": ["reader"], "note": "matrix"}"#),
            need: Need::Admin,
            ok: (201, 201),
        },
        RestCase {
            method: "DELETE",
            paths: (
                format!("/v1/tokens/{}", w.a_victim_token),
                format!("/v1/tokens/{}", w.b_victim_token),
            ),
            body: None,
            need: Need::Admin,
            ok: (200, 404),
        },
    ];
    let http = helmholtz_tests::http_client();
    let mut checked = 0;
    let mut failures = Vec::new();
    for case in &rest {
        for caller in &callers {
            for (lab, path, ok) in [
                ("own", &case.paths.0, case.ok.0),
                ("other", &case.paths.1, case.ok.1),
            ] {
                let expected = match caller.may(case.need) {
                    Ok(()) => ok,
                    Err(Denied::Unauthenticated) => 401,
                    Err(Denied::Forbidden) => 403,
                };
                let method = reqwest::Method::from_bytes(case.method.as_bytes()).unwrap();
                let mut req = http.request(method, format!("{}{path}", s.address));
                if let Some(h) = &caller.header {
                    req = req.header("authorization", h);
                }
                if let Some(b) = case.body {
                    req = req.header("content-type", "application/json").body(b);
                }
                let response = req.send().await.unwrap();
                let status = response.status();
                assert!(
                    response.headers().contains_key("x-request-id"),
                    "{} {path}: no x-request-id",
                    case.method
                );
                if status.as_u16() >= 400 {
                    assert_eq!(
                        response.headers()["content-type"],
                        "application/problem+json",
                        "{} {path}",
                        case.method
                    );
                }
                if status == StatusCode::UNAUTHORIZED {
                    assert!(response.headers().contains_key("www-authenticate"));
                }
                checked += 1;
                if status.as_u16() != expected {
                    let body = response.text().await.unwrap_or_default();
                    failures.push(format!(
                        "{} {path} as {} ({lab}): {status}, expected {expected}: {body}",
                        case.method, caller.name
                    ));
                }
            }
        }
    }

    // gRPC: every RPC of helmholtz.v1.Acquisition, plus the open health check.
    let chunk = |id: &str| {
        let (bytes, crc) = encode_values(&[1.0, 2.0, 3.0]);
        v1::MeasurementChunk {
            session_id: id.into(),
            start_row: 0,
            channels: 1,
            values_f64le: bytes,
            crc32c: crc,
            ..Default::default()
        }
    };
    let create = |id: &str| {
        helmholtz_client::NewSession::new(id, spec(), vec!["bucket".into()]).to_request()
    };
    let recon_req = |id: &str| v1::ReconstructionRequest {
        session_id: id.into(),
        method: "direct".into(),
        params_json: String::new(),
    };
    let channel = tonic::transport::Channel::from_shared(s.address.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let rpcs: [(&str, Need, (Code, Code)); 9] = [
        // Creating a new id succeeds; another lab's existing id is taken (ids are global).
        ("CreateSession", Need::Rig, (Code::Ok, Code::AlreadyExists)),
        ("UploadMeasurements", Need::Rig, (Code::Ok, Code::NotFound)),
        (
            "GetUploadStatus",
            Need::RigOrReader,
            (Code::Ok, Code::NotFound),
        ),
        ("FinishSession", Need::Rig, (Code::Ok, Code::NotFound)),
        (
            "RequestReconstruction",
            Need::Reader,
            (Code::Ok, Code::NotFound),
        ),
        (
            "GetReconstruction",
            Need::Reader,
            (Code::Ok, Code::NotFound),
        ),
        // The lab's own reconstruction has ended: cancelling it is refused, and changes nothing.
        (
            "CancelReconstruction",
            Need::Reader,
            (Code::FailedPrecondition, Code::NotFound),
        ),
        (
            "WatchPreview",
            Need::RigOrReader,
            (Code::Ok, Code::NotFound),
        ),
        (
            "grpc.health.v1.Health/Check",
            Need::Open,
            (Code::Ok, Code::Ok),
        ),
    ];
    for (rpc, need, (own_code, other_code)) in rpcs {
        for caller in &callers {
            for (lab, ok) in [("own", own_code), ("other", other_code)] {
                let own = lab == "own";
                let expected = match caller.may(need) {
                    Ok(()) => ok,
                    Err(Denied::Unauthenticated) => Code::Unauthenticated,
                    Err(Denied::Forbidden) => Code::PermissionDenied,
                };
                let header = caller.header.clone();
                let mut client =
                    helmholtz_proto::v1::acquisition_client::AcquisitionClient::with_interceptor(
                        channel.clone(),
                        move |mut r: tonic::Request<()>| {
                            if let Some(h) = &header {
                                r.metadata_mut().insert("authorization", h.parse().unwrap());
                            }
                            Ok(r)
                        },
                    );
                let (session, recon) = if own { ("sa", ra) } else { ("sb", rb) };
                let result: Result<(), tonic::Status> = match rpc {
                    "CreateSession" => {
                        let id = if own {
                            format!("new-{}", caller.name.replace(' ', "-"))
                        } else {
                            "sb".into()
                        };
                        client.create_session(create(&id)).await.map(|_| ())
                    }
                    "UploadMeasurements" => {
                        let target = if own { "open-a" } else { "open-b" };
                        client
                            .upload_measurements(tokio_stream::iter(vec![chunk(target)]))
                            .await
                            .map(|_| ())
                    }
                    "GetUploadStatus" => client
                        .get_upload_status(v1::SessionRef {
                            session_id: session.into(),
                        })
                        .await
                        .map(|_| ()),
                    "FinishSession" => client
                        .finish_session(v1::SessionRef {
                            session_id: session.into(),
                        })
                        .await
                        .map(|_| ()),
                    "RequestReconstruction" => client
                        .request_reconstruction(recon_req(session))
                        .await
                        .map(|_| ()),
                    "GetReconstruction" => client
                        .get_reconstruction(v1::ReconstructionRef {
                            reconstruction_id: recon,
                        })
                        .await
                        .map(|_| ()),
                    "CancelReconstruction" => client
                        .cancel_reconstruction(v1::ReconstructionRef {
                            reconstruction_id: recon,
                        })
                        .await
                        .map(|_| ()),
                    "WatchPreview" => client
                        .watch_preview(v1::PreviewRequest {
                            session_id: session.into(),
                            ..Default::default()
                        })
                        .await
                        .map(|_| ()),
                    _ => {
                        let mut health =
                            tonic_health::pb::health_client::HealthClient::new(channel.clone());
                        health
                            .check(tonic_health::pb::HealthCheckRequest {
                                service: String::new(),
                            })
                            .await
                            .map(|_| ())
                    }
                };
                let code = match &result {
                    Ok(()) => Code::Ok,
                    Err(status) => status.code(),
                };
                checked += 1;
                if code != expected {
                    failures.push(format!(
                        "{rpc} as {} ({lab}): {result:?}, expected {expected:?}",
                        caller.name
                    ));
                }
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {checked} calls had the wrong status:\n{}",
        failures.len(),
        failures.join("\n")
    );
    assert_eq!(checked, (rest.len() + 9) * callers.len() * 2);

    // Another lab's resources answer exactly as missing ones do (same problem, same words).
    let reader = callers[1].header.clone().unwrap();
    let body = |path: String| {
        let (http, reader) = (http.clone(), reader.clone());
        async move {
            let r = http
                .get(format!("{}{path}", s.address))
                .header("authorization", reader)
                .send()
                .await
                .unwrap();
            let status = r.status();
            let v: serde_json::Value = r.json().await.unwrap();
            (
                status,
                v["type"].clone(),
                v["title"].clone(),
                v["detail"].as_str().unwrap().to_string(),
            )
        }
    };
    let other = body("/v1/sessions/sb".into()).await;
    let missing = body("/v1/sessions/zz".into()).await;
    assert_eq!(
        (other.0, &other.1, &other.2),
        (missing.0, &missing.1, &missing.2)
    );
    assert_eq!(other.3.replace("\"sb\"", "\"zz\""), missing.3);
    let other = body(format!("/v1/reconstructions/{rb}")).await;
    let missing = body("/v1/reconstructions/999999".into()).await;
    assert_eq!(
        (other.0, &other.1, &other.2),
        (missing.0, &missing.1, &missing.2)
    );
    assert_eq!(other.3.replace(&rb.to_string(), "999999"), missing.3);
    // Listing shows only the caller's lab.
    let listed: serde_json::Value = http
        .get(format!("{}/v1/sessions", s.address))
        .header("authorization", &reader)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let ids = helmholtz_tests::session_ids(&listed);
    assert!(
        ids.contains(&"sa") && !ids.contains(&"sb") && !ids.contains(&"open-b"),
        "{ids:?}"
    );
}

#[tokio::test]
async fn the_client_sends_its_token_and_shows_the_request_id() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    // Without a token the client's error says what is missing and carries the request id.
    let err = helmholtz_client::get_session(&server.address, "x")
        .await
        .unwrap_err();
    let api = err
        .downcast_ref::<helmholtz_client::ApiError>()
        .expect("an API error");
    assert_eq!(api.status, 401);
    assert!(
        api.request_id.as_deref().is_some_and(|id| id.len() >= 16),
        "{api:?}"
    );
    assert!(err.to_string().contains("request id"), "{err}");
    let err = helmholtz_client::upload_status(&server.address, "x")
        .await
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("UNAUTHENTICATED") && err.contains("request id"),
        "{err}"
    );
    // The same call with the token works; the token never appears in messages.
    let err = helmholtz_client::get_session(&server.base_url, "x")
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("404") && !err.contains(&server.token), "{err}");
    // `helmholtz --token` (and HELMHOLTZ_TOKEN) reach the server.
    let out = std::process::Command::new(helmholtz_tests::binary("helmholtz"))
        .args([
            "--server",
            &server.address,
            "--token",
            &server.token,
            "--json",
            "status",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = std::process::Command::new(helmholtz_tests::binary("helmholtz"))
        .args(["--server", &server.address, "status"])
        .env("HELMHOLTZ_TOKEN", &server.token)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = std::process::Command::new(helmholtz_tests::binary("helmholtz"))
        .args(["--server", &server.address, "status"])
        .env_remove("HELMHOLTZ_TOKEN")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("401") && stderr.contains("request id"),
        "{stderr}"
    );
}

#[tokio::test]
async fn tokens_are_made_listed_and_revoked_by_the_cli_and_the_admin_api() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(dir.path(), 0, &[]).unwrap();
    let admin = server.create_token("optics", "admin").unwrap();
    let http = helmholtz_tests::http_client();
    let made: serde_json::Value = http
        .post(format!("{}/v1/tokens", server.address))
        .bearer_auth(&admin)
        .json(&serde_json::json!({"roles": ["rig", "reader"], "note": "bench 2"}))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let token = made["token"].as_str().unwrap().to_string();
    assert_eq!(
        (made["lab"].as_str(), made["roles"].as_str()),
        (Some("optics"), Some("rig,reader"))
    );
    // The new token works, lists without its secret, and stops working once revoked.
    let ok = http
        .get(format!("{}/v1/sessions", server.address))
        .bearer_auth(&token)
        .send()
        .await
        .unwrap();
    assert_eq!(ok.status(), 200);
    let listed = http
        .get(format!("{}/v1/tokens", server.address))
        .bearer_auth(&admin)
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(
        !listed.contains(&token) && listed.contains("bench 2"),
        "{listed}"
    );
    let bad = http
        .post(format!("{}/v1/tokens", server.address))
        .bearer_auth(&admin)
        .json(&serde_json::json!({"roles": ["rig", "root"]}))
        .send()
        .await
        .unwrap();
    assert_eq!(bad.status(), 400);
    assert_eq!(
        bad.json::<serde_json::Value>().await.unwrap()["field"],
        "roles[1]"
    );
    let out = helmholtz_tests::server_command(
        &server.data_dir,
        &["token", "revoke", &made["id"].to_string()],
    )
    .output()
    .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let gone = http
        .get(format!("{}/v1/sessions", server.address))
        .bearer_auth(&token)
        .send()
        .await
        .unwrap();
    assert_eq!(gone.status(), 401);
    // Bad CLI input is refused clearly.
    let out = std::process::Command::new(helmholtz_tests::binary("helmholtz-server"))
        .args([
            "token",
            "create",
            "--lab",
            "bad lab!",
            "--role",
            "rig",
            "--data-dir",
        ])
        .arg(&server.data_dir)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--lab"));
    let out = std::process::Command::new(helmholtz_tests::binary("helmholtz-server"))
        .args([
            "token",
            "create",
            "--lab",
            "optics",
            "--role",
            "superuser",
            "--data-dir",
        ])
        .arg(&server.data_dir)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--role"));
}
