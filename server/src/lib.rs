//! Helmholtz server: gRPC acquisition, SQLite storage, a CPU worker pool and the REST API.
//!
//! Data flows one way: `api` (gRPC, REST) -> `jobs` -> `recon` (pure numerics), with `store`
//! the only module that speaks SQL.

pub use helmholtz_alloc as alloc;
pub mod adaptive;
pub mod api;
pub mod app;
pub mod auth;
pub mod cli;
pub mod edge;
pub mod jobs;
pub mod limits;
pub mod preview;
/// The numerics live in their own crate (no async, SQL or HTTP); the server calls them as `recon`.
pub use helmholtz_recon as recon;
pub mod store;
pub mod telemetry;

pub use app::{Application, Config};
