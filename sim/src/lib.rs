//! What a rig would measure, with the truth known: the ground truth of the demo, the tests and
//! the benchmarks.
//!
//! - [`target`]: a flat test target (a photo, a USAF-1951 chart, a double slit) as a grey image
//!   on the pattern grid. Seen by one bucket detector its transport `t` is the image itself, so
//!   it is the dual image a reconstruction should return.
//! - [`scene`]: an analytic Lambertian height field (normals, albedo, cast shadows, one diffuse
//!   bounce) with the exact transport toward any bucket detector or camera: the ground truth of
//!   photometric stereo and of camera sessions (a transport matrix `T` and its relighting).
//! - [`simulate`]: the rig: bucket values `c_i = t · p_i` (or camera frames `T p_i`) for every
//!   pattern of a spec, then source drift, shot and read noise, a dark offset and the ADC.
//!
//! Pure computation: nothing here does I/O beyond reading a PNG the caller names.

pub mod scene;
pub mod simulate;
pub mod target;

pub use scene::{Camera, CameraView, Scene};
pub use target::Target;
