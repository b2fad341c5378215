//! The Helmholtz contract, compiled by both the edge client and the server.
//!
//! - [`v1`]: the messages of package `helmholtz.v1` (prost), and with feature `grpc` its
//!   service's tonic client and server.
//! - [`patterns`]: the seed -> pattern generator, defined in `PATTERNS.md` beside this crate.
//! - [`wire`]: how rows travel in a `MeasurementChunk`: the sample formats (f64 buckets, f32/u16
//!   camera frames), little-endian, with a CRC-32C.
//! - [`npy`]: NumPy `.npy` files, read (header, then whole arrays or streamed rows) and written.
//! - [`png`]: PNG to luminance and grey PNG out (scene files, pattern frames for a projector).
//! - [`rest`]: the REST API's JSON bodies (sessions, reconstructions and their reports, relight
//!   and token requests, problem+json errors), written by the server and read by the client.

pub mod npy;
pub mod patterns;
pub mod png;
pub mod rest;
pub mod wire;

#[allow(clippy::all, missing_docs)]
pub mod v1 {
    include!(concat!(env!("OUT_DIR"), "/helmholtz.v1.rs"));

    /// The encoded `FileDescriptorSet` of `helmholtz.v1` (what gRPC server reflection serves).
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        include_bytes!(concat!(env!("OUT_DIR"), "/helmholtz_descriptor.bin"));
}

pub use patterns::{
    AdaptiveFrames, ErrorEstimate, Family, HaarFunction, HadamardOrdering, PatternGenerator,
    PatternSpec, SpecError,
};
