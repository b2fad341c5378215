//! Rendered scenes: small light transports given exactly as a dense matrix `T` (`m` camera
//! pixels x `k` projector pixels), for the transport benchmarks and tests that need what the
//! [`Relief`](super::Relief) does not have: dense low-amplitude multi-bounce light, sparse bright
//! specular paths, and very sparse rows.
//!
//! - [`RenderedTransport::cornell`] ([`cornell`]): a box with diffuse walls and two blocks, lit by
//!   a pinhole projector and seen by a pinhole camera; the indirect light solves the radiosity
//!   equation, so every entry of `T` is direct plus a dense floor of indirect light.
//! - [`RenderedTransport::glossy`] ([`glossy`]): a diffuse floor with a rough metal and a rough
//!   glass sphere: a diffuse part plus a sparse, bright specular part (glints, and a caustic the
//!   glass ball focuses on the floor).
//! - [`RenderedTransport::slide`] ([`slide`]): a printed slide seen at a grazing angle: about a
//!   third of the camera pixels see lit print, each through 2-6 projector pixels; the other rows
//!   are exactly zero.
//!
//! Each keeps its first-bounce part ([`RenderedTransport::direct_only`]; light that reached the
//! camera after one reflection), so tests can measure the indirect share. Every constructor is
//! deterministic in its arguments. Units: a projector pixel emits unit power; a camera pixel
//! reports the mean radiance over its solid angle.

pub mod cornell;
mod geometry;
pub mod glossy;
pub mod slide;
#[cfg(test)]
mod tests;

/// A light transport given as a dense matrix, with its first-bounce part (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct RenderedTransport {
    projector: (usize, usize),
    camera: (usize, usize),
    /// `m x k`, row-major: row `j` is the dual image seen by camera pixel `j`.
    t: Vec<f64>,
    /// The first-bounce part of `t`, same layout.
    direct: Vec<f64>,
}

impl RenderedTransport {
    /// A transport from its dense matrix `t` (`m x k` row-major, `m = camera.0 * camera.1`,
    /// `k = projector.0 * projector.1`) and its first-bounce part `direct` (same layout).
    pub fn new(
        projector: (usize, usize),
        camera: (usize, usize),
        t: Vec<f64>,
        direct: Vec<f64>,
    ) -> RenderedTransport {
        let (m, k) = (camera.0 * camera.1, projector.0 * projector.1);
        assert!(m > 0 && k > 0, "a transport needs pixels on both sides");
        assert_eq!(t.len(), m * k, "t is m x k");
        assert_eq!(direct.len(), m * k, "direct is m x k");
        RenderedTransport {
            projector,
            camera,
            t,
            direct,
        }
    }

    /// The Cornell-like box with radiosity interreflection ([`cornell`]) at `projector` and
    /// `camera` `(width, height)`; `seed` jitters the blocks' places.
    pub fn cornell(
        projector: (usize, usize),
        camera: (usize, usize),
        seed: u64,
    ) -> RenderedTransport {
        cornell::render(projector, camera, seed).transport
    }

    /// The diffuse floor with a rough metal and a rough glass sphere ([`glossy`]); `seed`
    /// varies the floor's texture and the spheres' places.
    pub fn glossy(
        projector: (usize, usize),
        camera: (usize, usize),
        seed: u64,
    ) -> RenderedTransport {
        glossy::render(projector, camera, seed).transport
    }

    /// The printed slide at a grazing angle ([`slide`]); `seed` varies the print.
    pub fn slide(
        projector: (usize, usize),
        camera: (usize, usize),
        seed: u64,
    ) -> RenderedTransport {
        slide::render(projector, camera, seed)
    }

    /// The transport with its first bounce only (itself its own direct part).
    pub fn direct_only(&self) -> RenderedTransport {
        RenderedTransport {
            projector: self.projector,
            camera: self.camera,
            t: self.direct.clone(),
            direct: self.direct.clone(),
        }
    }

    /// `(width, height)` of the projector.
    pub fn projector(&self) -> (usize, usize) {
        self.projector
    }
    /// `(width, height)` of the camera.
    pub fn camera(&self) -> (usize, usize) {
        self.camera
    }
    /// Camera width.
    pub fn width(&self) -> usize {
        self.camera.0
    }
    /// Camera height.
    pub fn height(&self) -> usize {
        self.camera.1
    }
    /// `m`, camera pixels (rows of `T`).
    pub fn pixels(&self) -> usize {
        self.camera.0 * self.camera.1
    }
    /// `k`, projector pixels (columns of `T`).
    pub fn projector_pixels(&self) -> usize {
        self.projector.0 * self.projector.1
    }
    /// `T`, `m x k` row-major.
    pub fn matrix(&self) -> &[f64] {
        &self.t
    }

    /// The frame `T p` for a projector pattern `p` (`k` values).
    pub fn render(&self, pattern: &[f64]) -> Vec<f64> {
        let k = self.projector_pixels();
        assert_eq!(pattern.len(), k, "pattern has the projector's pixel count");
        self.t
            .chunks_exact(k)
            .map(|row| row.iter().zip(pattern).map(|(a, b)| a * b).sum())
            .collect()
    }

    /// The relit dual image `T^T c` for a virtual light `c` at the camera (`m` values).
    pub fn relight(&self, light: &[f64]) -> Vec<f64> {
        let k = self.projector_pixels();
        assert_eq!(
            light.len(),
            self.pixels(),
            "light has the camera's pixel count"
        );
        let mut out = vec![0.0; k];
        for (row, &c) in self.t.chunks_exact(k).zip(light) {
            if c != 0.0 {
                for (o, v) in out.iter_mut().zip(row) {
                    *o += c * v;
                }
            }
        }
        out
    }

    /// Row `j` of `T`: the dual image seen by camera pixel `j`.
    pub fn row(&self, j: usize) -> &[f64] {
        let k = self.projector_pixels();
        &self.t[j * k..(j + 1) * k]
    }

    /// Dense `T`, `m x k` row-major f32.
    pub fn dense(&self) -> Vec<f32> {
        self.t.iter().map(|&v| v as f32).collect()
    }

    /// `sum T`: the camera's total under a full-white pattern.
    pub fn total(&self) -> f64 {
        self.t.iter().sum()
    }

    /// `(sum T - sum T_direct) / sum T`: the share of the light that reached the camera after
    /// more than one bounce.
    pub fn indirect_share(&self) -> f64 {
        let total = self.total();
        (total - self.direct.iter().sum::<f64>()) / total
    }

    /// Rows of `T` with a nonzero entry (camera pixels that see projector light).
    pub fn lit_rows(&self) -> usize {
        self.t
            .chunks_exact(self.projector_pixels())
            .filter(|r| r.iter().any(|&v| v != 0.0))
            .count()
    }

    /// Nonzero entries of `T`.
    pub fn nonzeros(&self) -> usize {
        self.t.iter().filter(|&&v| v != 0.0).count()
    }
}
