//! What a rig would measure, with the truth known: the ground truth of the demo, the tests and
//! the benchmarks.
//!
//! - [`scene`]: what the rig looks at, a [`Scene`] with its exact light transport toward any
//!   bucket detector or camera. Either flat ([`Scene::Flat`]: a [`Target`], a photo, a USAF-1951
//!   chart or a double slit as a grey image on the pattern grid; seen by one bucket detector its
//!   transport `t` is the image itself, the dual image a reconstruction should return) or a
//!   relief ([`Scene::Relief`]: an analytic Lambertian height field with normals, albedo, cast
//!   shadows and one diffuse bounce; the ground truth of photometric stereo and of camera
//!   sessions, a transport matrix `T` and its relighting). Besides, [`RenderedTransport`]: small
//!   scenes given as a dense `T` ([`scene::rendered`]: a Cornell-like box with radiosity
//!   interreflection, glossy spheres with a caustic, a sparse slide at a grazing angle).
//! - [`simulate`]: the rig: bucket values `c_i = t · p_i` (or camera frames `T p_i`) for every
//!   pattern of a spec, then source drift, shot and read noise, a dark offset and the ADC.
//!
//! Pure computation: nothing here does I/O beyond reading a PNG the caller names.

pub mod scene;
pub mod simulate;

pub use scene::{Camera, CameraView, Relief, RenderedTransport, Scene, Target};
