//! What the rig looks at: a [`Scene`] on the projector's pixel grid (`W x H`, `k = W H`), with
//! its light transport known exactly.
//!
//! Two kinds:
//!
//! - [`Scene::Flat`], a flat test [`Target`] ([`target`]: a photo, a USAF-1951 chart, a double
//!   slit): a grey image in [0, 1]. It is a level Lambertian plane facing the projector whose
//!   albedo is the image, without shadows or indirect light, so one bucket detector at the
//!   projector sees the image itself as its transport: the dual image a reconstruction should
//!   return. ([`Target::transport`] scales it to a peak for a simulated rig.)
//! - [`Scene::Relief`], an analytic Lambertian height field ([`relief`]: normals, albedo, cast
//!   shadows, one diffuse bounce): the ground truth of photometric stereo (detectors in several
//!   directions) and of camera sessions (a transport matrix `T` and its relighting).
//!
//! What both answer: their size ([`Scene::width`], [`Scene::height`], [`Scene::pixels`]), the
//! transport toward a distant bucket detector in any direction ([`Scene::detector_transport`])
//! and what an orthographic camera sees ([`Scene::view`], a [`CameraView`]: frames `T p` and
//! relighting `T^T c`). Reciprocity holds for both: a camera summed over its pixels is the bucket
//! detector where it stands.
//!
//! Besides these, [`rendered`]: small camera scenes given as an exact dense `T`
//! ([`RenderedTransport`]: a Cornell-like box with radiosity interreflection, glossy spheres with
//! a caustic, a sparse slide at a grazing angle), with their first-bounce part.

pub mod relief;
pub mod rendered;
pub mod target;

use std::borrow::Cow;

pub use relief::{Camera, CameraView, Relief, direction, unit_vector};
pub use rendered::RenderedTransport;
pub use target::Target;

/// The name of the demo relief ([`Relief::demo`]) where a scene is named (`--scene lambert`).
pub const LAMBERT: &str = "lambert";

/// What the rig looks at (module docs).
#[derive(Clone, Debug)]
pub enum Scene {
    /// A flat test target: a level plane whose albedo is the image.
    Flat(Target),
    /// A Lambertian height field.
    Relief(Relief),
}

impl From<Target> for Scene {
    fn from(target: Target) -> Self {
        Scene::Flat(target)
    }
}

impl From<Relief> for Scene {
    fn from(relief: Relief) -> Self {
        Scene::Relief(relief)
    }
}

impl Scene {
    /// A scene by name at `width x height`: [`LAMBERT`] is the demo relief ([`Relief::demo`],
    /// albedo texture from `seed`); anything else a flat target ([`Target::load`]: a built-in
    /// name or a PNG file).
    pub fn load(name_or_path: &str, width: u32, height: u32, seed: u64) -> anyhow::Result<Scene> {
        if name_or_path == LAMBERT {
            anyhow::ensure!(
                width >= 4 && height >= 4,
                "the {LAMBERT} scene needs at least 4x4 pixels"
            );
            return Ok(Scene::Relief(Relief::demo(width, height, seed)));
        }
        Ok(Scene::Flat(Target::load(name_or_path, width, height)?))
    }

    pub fn width(&self) -> usize {
        match self {
            Scene::Flat(t) => t.width as usize,
            Scene::Relief(r) => r.width(),
        }
    }

    pub fn height(&self) -> usize {
        match self {
            Scene::Flat(t) => t.height as usize,
            Scene::Relief(r) => r.height(),
        }
    }

    /// `k = W H`, the length of a dual image.
    pub fn pixels(&self) -> usize {
        self.width() * self.height()
    }

    /// The dual image of a distant bucket detector toward `d` (grey): for a relief
    /// [`Relief::detector_transport`]; for a flat target its image times `max(0, d_z / |d|)`
    /// (the image itself for a detector at the projector, `d = (0, 0, 1)`).
    pub fn detector_transport(&self, d: [f64; 3]) -> Vec<f64> {
        match self {
            Scene::Flat(t) => self.level().detector_transport_with(d, &flat_albedo(t)),
            Scene::Relief(r) => r.detector_transport(d),
        }
    }

    /// What an orthographic camera sees ([`Relief::view`]; a flat target is seen as its level
    /// plane).
    pub fn view(&self, camera: &Camera) -> CameraView<'_> {
        match self {
            Scene::Flat(t) => CameraView::new(Cow::Owned(self.level()), camera, flat_albedo(t)),
            Scene::Relief(r) => r.view(camera),
        }
    }

    /// The level plane of a flat scene.
    fn level(&self) -> Relief {
        Relief::level(self.width(), self.height())
    }
}

/// A flat target's image as the albedo of its plane.
fn flat_albedo(target: &Target) -> Vec<f64> {
    target.pixels.iter().map(|&v| v as f64).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn max_diff(a: &[f64], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max)
    }

    #[test]
    fn a_flat_target_is_its_own_transport_at_the_projector() {
        let target = Target::builtin("usaf", 24, 16).unwrap();
        let scene = Scene::from(target.clone());
        assert_eq!(
            (scene.width(), scene.height(), scene.pixels()),
            (24, 16, 384)
        );
        let image: Vec<f64> = target.pixels.iter().map(|&v| v as f64).collect();
        assert_eq!(scene.detector_transport([0.0, 0.0, 1.0]), image);
        // Oblique: the image times the cosine; below the horizon, dark.
        let d = direction(30.0, 40.0);
        let t = scene.detector_transport(d);
        let want: Vec<f64> = image.iter().map(|v| v * d[2]).collect();
        assert!(max_diff(&t, &want) < 1e-12);
        assert!(
            scene
                .detector_transport([1.0, 0.0, -1.0])
                .iter()
                .all(|&v| v == 0.0)
        );
    }

    #[test]
    fn a_flat_target_seen_by_a_camera_keeps_reciprocity() {
        let scene = Scene::Flat(Target::builtin("double-slit", 20, 12).unwrap());
        let camera = Camera::tilted(10, 8, 20.0);
        let view = scene.view(&camera);
        assert_eq!(view.pixels(), 80);
        let summed = view.relight(&vec![1.0; view.pixels()]);
        let bucket = scene.detector_transport(camera.direction);
        assert!(max_diff(&summed, &bucket) < 1e-12);
        // Straight down, all of the light reaches the camera.
        let view = scene.view(&Camera::tilted(10, 8, 0.0));
        let frame = view.render(&vec![1.0; scene.pixels()]);
        let total: f64 = frame.iter().sum();
        let image: f64 = scene.detector_transport([0.0, 0.0, 1.0]).iter().sum();
        assert!((total - image).abs() < 1e-9 * image, "{total} vs {image}");
    }

    #[test]
    fn a_relief_answers_as_itself() {
        let relief = Relief::demo(16, 12, 3);
        let camera = Camera::tilted(8, 6, 25.0);
        let d = direction(90.0, 50.0);
        let want = (relief.detector_transport(d), relief.view(&camera).dense());
        let scene = Scene::from(relief);
        assert_eq!((scene.width(), scene.height()), (16, 12));
        assert_eq!(scene.detector_transport(d), want.0);
        assert_eq!(scene.view(&camera).dense(), want.1);
    }

    #[test]
    fn scenes_load_by_name() {
        assert!(matches!(
            Scene::load(LAMBERT, 8, 8, 1).unwrap(),
            Scene::Relief(_)
        ));
        assert!(matches!(
            Scene::load("usaf", 8, 8, 1).unwrap(),
            Scene::Flat(_)
        ));
        assert!(Scene::load(LAMBERT, 3, 8, 1).is_err());
        assert!(Scene::load("no-such-scene", 8, 8, 1).is_err());
    }
}
