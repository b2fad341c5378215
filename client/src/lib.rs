//! The Helmholtz edge client: what runs next to a rig.
//!
//! A rig shows known patterns `p_i` (declared by a [`PatternSpec`], regenerated on both sides from
//! the seed) and records one bucket value per pattern and detector channel, `c_i = t · p_i + noise`
//! (or, in a camera session, a whole frame `T p_i + noise` per pattern). This crate
//!
//! - simulates a rig measuring a known scene (with [`helmholtz_sim`], the `simulate` command),
//! - reads a real rig's measurements from CSV or NPY ([`measurements`]),
//! - spools every measured row durably on local disk before upload ([`spool`]),
//! - creates a session and streams the rows to the server over gRPC with resume after any
//!   failure ([`upload`]),
//! - requests reconstructions and downloads dual images over REST ([`rest`]),
//! - watches a session's live preview while it uploads ([`preview`]),
//! - runs an adaptive session, measuring the batches of patterns the server chooses as it goes
//!   ([`adaptive`]),
//! - writes pattern frames as PNGs for a projector or DMD ([`frames`]),
//! - and is the `helmholtz` command line ([`cli`]).
//!
//! One address serves both gRPC and REST (`http://127.0.0.1:8080` by default; `https://` is
//! verified against the system roots and a CA trusted with [`tls::trust_ca_file`]). Every network
//! function takes it as `server: &str`; none keeps state between calls, so they can be called
//! from tests against a server started on port 0. The lab's access token rides in it as the
//! URL's user part (`http://hz_...@127.0.0.1:8080`, see [`auth::with_token`]) and is sent as a
//! bearer token, never shown in messages.
//!
//! ```no_run
//! # async fn demo() -> anyhow::Result<()> {
//! use helmholtz_client::{NewSession, UploadOptions};
//! use helmholtz_sim::{Target, simulate};
//! use helmholtz_proto::PatternSpec;
//! let spec: PatternSpec = serde_json::from_str(
//!     r#"{"family":"bernoulli","width":32,"height":32,"count":8192,"seed":7}"#)?;
//! let transport = Target::builtin("double-slit", 32, 32)?.transport(1.0);
//! let sim = simulate::simulate(&spec, &[&transport], &simulate::NoiseModel::default(), None);
//! let server = helmholtz_client::auth::with_token("http://127.0.0.1:8080", "hz_...");
//! let server = server.as_str();
//! let session = NewSession::new("demo-1", spec.clone(), vec!["bucket".into()])
//!     .with_ground_truth(32, 32, transport.clone());
//! helmholtz_client::create_session(server, &session).await?;
//! helmholtz_client::upload(server, "demo-1", 1, &sim.values, &UploadOptions::default()).await?;
//! helmholtz_client::finish_session(server, "demo-1").await?;
//! let rec = helmholtz_client::request_reconstruction(server, "demo-1", "dgi", &serde_json::json!({})).await?;
//! let rec = helmholtz_client::wait_reconstruction(server, rec.id, std::time::Duration::from_secs(60)).await?;
//! assert!(rec.is_done());
//! # Ok(()) }
//! ```

pub mod adaptive;
pub mod auth;
pub mod cli;
pub mod frames;
pub mod measurements;
pub mod preview;
pub mod rest;
pub mod spool;
pub mod tls;
pub mod upload;

pub use helmholtz_proto::PatternSpec;
pub use rest::{
    ApiError, FetchReport, FetchTarget, ImageFormat, ImageReport, Light, PatternInput,
    Reconstruction, SessionView, cancel_reconstruction, fetch, get_reconstruction, get_session,
    list_sessions, normals, primal, relight, request_reconstruction_rest, wait_reconstruction,
    wait_reconstruction_with,
};
pub use upload::{
    Backoff, CameraLayout, CreatedSession, NewSession, RetryPolicy, SampleFormat, Samples,
    UploadOptions, UploadReport, create_session, finish_session, request_reconstruction, upload,
    upload_samples, upload_status,
};
