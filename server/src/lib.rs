//! Helmholtz server: gRPC acquisition, SQLite storage, a CPU worker pool and the REST API.
//!
//! Data flows one way: `api` (gRPC, REST) -> `jobs` -> `recon` (pure numerics), with `store`
//! the only module that speaks SQL.

pub mod alloc;
pub mod api;
pub mod app;
pub mod auth;
pub mod bench;
pub mod cli;
mod demo;
pub mod edge;
pub mod jobs;
pub mod limits;
pub mod recon;
pub mod store;
pub mod telemetry;

pub use app::{Application, Config};
