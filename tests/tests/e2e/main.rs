//! The end-to-end tests: the real `helmholtz-server` (and `helmholtz-demo`) binaries on
//! 127.0.0.1 port 0 with a real SQLite file, or a real PostgreSQL database with
//! `HELMHOLTZ_TEST_BACKEND=postgres`, talked to by the real client library and binary.
//!
//! One test binary, one module per area (run one with `cargo test -p helmholtz-tests --test e2e
//! -- browser::`). As 23 binaries of their own, every file compiled and linked the client stack
//! again: 606 s of the test build's 4,120 s of compile time on a 2-core machine (`cargo test
//! --workspace --no-run --timings`), against 206 s for this one binary.

mod acquisition;
mod adaptive;
mod auth;
mod browser;
mod camera;
mod cli;
mod edge;
mod faults;
mod fuzz;
mod integrity;
mod lambert_cli;
mod layout;
mod memory;
mod openapi;
mod pipeline;
mod postgres;
mod preview;
mod python;
mod reflection;
mod rest_upload;
mod service;
mod tls;
mod transport;
