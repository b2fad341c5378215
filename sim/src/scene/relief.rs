//! Reliefs: analytic Lambertian height fields with a known light transport, for simulated rigs,
//! tests and benchmarks (the [`Relief`](super::Scene::Relief) kind of [`Scene`](super::Scene)).
//!
//! A relief is a height field over the projector's pixel grid (`W x H`, `k = W H`): projector pixel
//! `x = (col, row)` lights the surface point `P(x) = (col + 1/2, row + 1/2, z(x))` (an orthographic
//! projector looking down `-z`). Coordinates: x along the projector image's rows (right), y
//! down its columns, z from the scene toward the projector; lengths in projector pixels. Every
//! surface is Lambertian with a known unit normal `n(x)` and albedo `rho(x)` (grey, or per colour).
//!
//! **Light transport.** All of a projector pixel's beam lands on its surface patch, whatever the
//! tilt, so the power a distant detector (or camera) in direction `d` collects from it is
//! `rho(x) max(0, n(x).d) vis(x, d)`, `vis` the cast-shadow test (a ray march over the height
//! field). One diffuse bounce adds indirect light: light reflected at `x` reaches `y` with a smooth
//! kernel `G` (three box blurs, about a Gaussian of width `blur_radius`) and is reflected there
//! again, scaled by `indirect`. In matrix form, with `R = diag(rho)`, `W_d = diag(max(0, n.d) vis)`:
//!
//! - bucket detector toward `d`: `t_d = (R + g R G R) W_d 1`, a `k`-vector (its dual image);
//! - camera toward `v` (orthographic, `m = W_c H_c` pixels framing the whole scene): `T = S W_v (R + g R G R)`
//!   with `S` the bilinear splat of each lit surface point into the camera pixels (`S^T 1 = 1`).
//!
//! Hence reciprocity: `T^T 1` (the camera summed over its pixels) equals the dual image `t_v` of
//! one bucket detector where the camera is ([`tests`](self) check it). `G` is symmetric, so both
//! `T p` ([`CameraView::render`]) and `T^T c` ([`CameraView::relight`]) cost O(k), and a row of T
//! ([`CameraView::row`]) is a relight by one camera pixel: dense `T` is never needed (but
//! [`CameraView::dense`] builds it for small sizes).

use std::borrow::Cow;
use std::f64::consts::PI;

/// A height field with normals and albedo on the projector grid.
#[derive(Clone, Debug)]
pub struct Relief {
    width: usize,
    height: usize,
    depth: Vec<f64>,
    normal: Vec<[f64; 3]>,
    albedo_rgb: Vec<[f64; 3]>,
    /// Strength `g` of the one-bounce indirect light.
    pub indirect: f64,
    /// Radius (pixels) of each of the three box blurs forming the indirect kernel.
    pub blur_radius: usize,
}

/// Rec. 709 luma weights: the grey albedo of a colour albedo.
const LUMA: [f64; 3] = [0.2126, 0.7152, 0.0722];

impl Relief {
    /// The demo scene: a textured ground plane, a hemisphere and a raised box (which casts
    /// shadows for oblique detectors and hides ground from an oblique camera). `seed` varies the
    /// albedo texture (coloured discs on the ground).
    pub fn demo(width: u32, height: u32, seed: u64) -> Relief {
        let (w, h) = (width.max(4) as usize, height.max(4) as usize);
        let s = w.min(h) as f64;
        let mut depth = vec![0.0; w * h];
        let mut normal = vec![[0.0, 0.0, 1.0]; w * h];
        let mut albedo_rgb = vec![[0.0; 3]; w * h];
        // Ground: soft checker plus seeded discs of colour.
        let cell = (s / 8.0).max(2.0);
        let discs: Vec<(f64, f64, f64, [f64; 3])> = (0..6)
            .map(|i| {
                let r = |j: u64| unit(seed, i * 8 + j);
                (
                    r(0) * w as f64,
                    r(1) * h as f64,
                    (0.04 + 0.06 * r(2)) * s,
                    [0.2 + 0.7 * r(3), 0.2 + 0.7 * r(4), 0.2 + 0.7 * r(5)],
                )
            })
            .collect();
        for row in 0..h {
            for col in 0..w {
                let (x, y) = (col as f64 + 0.5, row as f64 + 0.5);
                let checker =
                    ((x / cell).floor() as i64 + (y / cell).floor() as i64).rem_euclid(2) as f64;
                let mut a = [0.35 + 0.25 * checker; 3];
                for &(cx, cy, r, c) in &discs {
                    if (x - cx).powi(2) + (y - cy).powi(2) < r * r {
                        a = c;
                    }
                }
                albedo_rgb[row * w + col] = a;
            }
        }
        // Hemisphere.
        let (cx, cy, radius) = (0.33 * w as f64, 0.42 * h as f64, 0.22 * s);
        // Box: flat top at box_h.
        let (bx0, bx1, by0, by1, box_h) = (
            0.62 * w as f64,
            0.86 * w as f64,
            0.58 * h as f64,
            0.84 * h as f64,
            0.18 * s,
        );
        for row in 0..h {
            for col in 0..w {
                let (x, y) = (col as f64 + 0.5, row as f64 + 0.5);
                let i = row * w + col;
                let r2 = (x - cx).powi(2) + (y - cy).powi(2);
                if r2 < radius * radius {
                    let z = (radius * radius - r2).sqrt();
                    depth[i] = z;
                    normal[i] = [(x - cx) / radius, (y - cy) / radius, z / radius];
                    albedo_rgb[i] = [0.85, 0.55, 0.45];
                } else if (bx0..bx1).contains(&x) && (by0..by1).contains(&y) {
                    depth[i] = box_h;
                    albedo_rgb[i] = [0.45, 0.6, 0.9];
                }
            }
        }
        Relief {
            width: w,
            height: h,
            depth,
            normal,
            albedo_rgb,
            indirect: 0.3,
            blur_radius: (w.min(h) / 24).max(1),
        }
    }

    /// A level plane at height 0 facing the projector (normals +z), unit albedo, no indirect
    /// light: the geometry of a flat scene, whose albedo (its image) is passed to
    /// [`Relief::detector_transport_with`] and [`CameraView::new`] as is (the grey albedo of
    /// [`Relief::albedo`] is a luma sum, which would round it).
    pub(super) fn level(width: usize, height: usize) -> Relief {
        assert!(width > 0 && height > 0, "a scene needs at least one pixel");
        let k = width * height;
        Relief {
            width,
            height,
            depth: vec![0.0; k],
            normal: vec![[0.0, 0.0, 1.0]; k],
            albedo_rgb: vec![[1.0; 3]; k],
            indirect: 0.0,
            blur_radius: 1,
        }
    }

    pub fn width(&self) -> usize {
        self.width
    }
    pub fn height(&self) -> usize {
        self.height
    }
    /// `k = W H`, the length of a dual image.
    pub fn pixels(&self) -> usize {
        self.width * self.height
    }
    /// Surface height `z(x)` per projector pixel.
    pub fn depth(&self) -> &[f64] {
        &self.depth
    }
    /// Unit normals per projector pixel (z >= 0).
    pub fn normals(&self) -> &[[f64; 3]] {
        &self.normal
    }
    /// Grey albedo (Rec. 709 luma of the colour albedo).
    pub fn albedo(&self) -> Vec<f64> {
        self.albedo_rgb
            .iter()
            .map(|a| a.iter().zip(LUMA).map(|(c, l)| c * l).sum())
            .collect()
    }
    /// Albedo of colour `channel` (0 red, 1 green, 2 blue).
    pub fn albedo_channel(&self, channel: usize) -> Vec<f64> {
        self.albedo_rgb.iter().map(|a| a[channel]).collect()
    }

    /// `vis(x, d)`: 1 where the surface point of projector pixel `x` sees direction `d` (unit,
    /// `d.z > 0`) over the height field, else 0.
    pub fn visibility(&self, d: [f64; 3]) -> Vec<f64> {
        let d = unit_vector(d);
        let top = self.depth.iter().cloned().fold(0.0, f64::max);
        let horizontal = (d[0] * d[0] + d[1] * d[1]).sqrt();
        (0..self.pixels())
            .map(|i| {
                if horizontal < 1e-12 {
                    return 1.0;
                }
                let (x0, y0, z0) = (
                    (i % self.width) as f64 + 0.5,
                    (i / self.width) as f64 + 0.5,
                    self.depth[i],
                );
                // March in half-pixel steps across the grid until above every surface.
                let step = 0.5 / horizontal;
                let mut s = step;
                loop {
                    let (x, y, z) = (x0 + s * d[0], y0 + s * d[1], z0 + s * d[2]);
                    if z > top
                        || x < 0.0
                        || y < 0.0
                        || x >= self.width as f64
                        || y >= self.height as f64
                    {
                        return 1.0;
                    }
                    if self.depth_at(x, y) > z + 0.75 {
                        return 0.0;
                    }
                    s += step;
                }
            })
            .collect()
    }

    fn depth_at(&self, x: f64, y: f64) -> f64 {
        let (c, r) = (
            (x.floor() as usize).min(self.width - 1),
            (y.floor() as usize).min(self.height - 1),
        );
        self.depth[r * self.width + c]
    }

    /// `max(0, n.d) vis(x, d)` per projector pixel: how much of a patch's reflected light leaves
    /// toward `d`.
    pub fn exitance(&self, d: [f64; 3]) -> Vec<f64> {
        let d = unit_vector(d);
        let vis = self.visibility(d);
        self.normal
            .iter()
            .zip(vis)
            .map(|(n, v)| v * (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]).max(0.0))
            .collect()
    }

    /// The dual image of a distant bucket detector toward `d` (grey albedo): `t_d` above.
    pub fn detector_transport(&self, d: [f64; 3]) -> Vec<f64> {
        self.detector_transport_with(d, &self.albedo())
    }

    /// [`Relief::detector_transport`] for a colour filter (`channel` 0 red, 1 green, 2 blue).
    pub fn detector_transport_colour(&self, d: [f64; 3], channel: usize) -> Vec<f64> {
        self.detector_transport_with(d, &self.albedo_channel(channel))
    }

    pub(super) fn detector_transport_with(&self, d: [f64; 3], albedo: &[f64]) -> Vec<f64> {
        let e = self.exitance(d);
        self.reflect_adjoint(albedo, &e)
    }

    /// `(R + g R G R) u`: the light leaving each patch when `u` falls on the scene (direct plus
    /// one bounce). Symmetric in the sense `(R + gRGR)^T = R + gRGR`.
    fn reflect_adjoint(&self, albedo: &[f64], u: &[f64]) -> Vec<f64> {
        let ru: Vec<f64> = u.iter().zip(albedo).map(|(a, b)| a * b).collect();
        let mut out = ru.clone();
        if self.indirect > 0.0 {
            let blurred = self.blur(&ru);
            for ((o, b), a) in out.iter_mut().zip(blurred).zip(albedo) {
                *o += self.indirect * a * b;
            }
        }
        out
    }

    /// `G u`: three separable box blurs of radius `blur_radius`, zero outside the grid (so `G`
    /// is symmetric), each normalised by the full box size.
    pub fn blur(&self, u: &[f64]) -> Vec<f64> {
        let mut a = u.to_vec();
        for _ in 0..3 {
            a = box_pass(&a, self.width, self.height, self.blur_radius, true);
            a = box_pass(&a, self.width, self.height, self.blur_radius, false);
        }
        a
    }

    /// An orthographic camera's view of the scene.
    pub fn view(&self, camera: &Camera) -> CameraView<'_> {
        CameraView::new(Cow::Borrowed(self), camera, self.albedo())
    }

    /// [`Relief::view`] through a colour filter.
    pub fn view_colour(&self, camera: &Camera, channel: usize) -> CameraView<'_> {
        CameraView::new(Cow::Borrowed(self), camera, self.albedo_channel(channel))
    }
}

/// An orthographic camera toward `direction` (unit, z > 0), `width x height` pixels framing the
/// whole scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub direction: [f64; 3],
}

impl Camera {
    /// A camera `tilt_degrees` from the projector's axis, leaning toward +x.
    pub fn tilted(width: u32, height: u32, tilt_degrees: f64) -> Camera {
        let t = tilt_degrees * PI / 180.0;
        Camera {
            width,
            height,
            direction: [t.sin(), 0.0, t.cos()],
        }
    }
}

/// The transport `T = S W_v (R + g R G R)` of one camera, applied without forming it.
#[derive(Clone, Debug)]
pub struct CameraView<'a> {
    /// The relief seen: borrowed, or owned for a flat scene's level plane ([`super::Scene::view`]).
    scene: Cow<'a, Relief>,
    albedo: Vec<f64>,
    width: usize,
    height: usize,
    exitance: Vec<f64>,
    /// Per projector pixel: up to four (camera pixel, weight) pairs, weights summing to 1.
    splat: Vec<[(u32, f64); 4]>,
}

impl<'a> CameraView<'a> {
    pub(super) fn new(scene: Cow<'a, Relief>, camera: &Camera, albedo: Vec<f64>) -> Self {
        let relief: &Relief = &scene;
        let v = unit_vector(camera.direction);
        // Image-plane basis: e1 = x projected off v, e2 = v x e1.
        let e1 = unit_vector([1.0 - v[0] * v[0], -v[0] * v[1], -v[0] * v[2]]);
        let e2 = [
            v[1] * e1[2] - v[2] * e1[1],
            v[2] * e1[0] - v[0] * e1[2],
            v[0] * e1[1] - v[1] * e1[0],
        ];
        let (w, h) = (relief.width as f64, relief.height as f64);
        let top = relief.depth.iter().cloned().fold(0.0, f64::max);
        // Frame: the projection of the scene's bounding box, so every point lands inside.
        let (mut u0, mut u1, mut v0, mut v1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &x in &[0.0, w] {
            for &y in &[0.0, h] {
                for &z in &[0.0, top] {
                    let p = [x, y, z];
                    let (a, b) = (dot(p, e1), dot(p, e2));
                    u0 = u0.min(a);
                    u1 = u1.max(a);
                    v0 = v0.min(b);
                    v1 = v1.max(b);
                }
            }
        }
        let (cw, ch) = (camera.width.max(1) as usize, camera.height.max(1) as usize);
        let (su, sv) = ((u1 - u0) / cw as f64, (v1 - v0) / ch as f64);
        let splat = (0..relief.pixels())
            .map(|i| {
                let p = [
                    (i % relief.width) as f64 + 0.5,
                    (i / relief.width) as f64 + 0.5,
                    relief.depth[i],
                ];
                // Camera pixel centres at (c + 1/2); bilinear weights, clamped into the frame.
                let cu = ((dot(p, e1) - u0) / su - 0.5).clamp(0.0, (cw - 1) as f64);
                let cv = ((dot(p, e2) - v0) / sv - 0.5).clamp(0.0, (ch - 1) as f64);
                let (c0, r0) = (cu.floor() as usize, cv.floor() as usize);
                let (c1, r1) = ((c0 + 1).min(cw - 1), (r0 + 1).min(ch - 1));
                let (fu, fv) = (cu - c0 as f64, cv - r0 as f64);
                [
                    ((r0 * cw + c0) as u32, (1.0 - fu) * (1.0 - fv)),
                    ((r0 * cw + c1) as u32, fu * (1.0 - fv)),
                    ((r1 * cw + c0) as u32, (1.0 - fu) * fv),
                    ((r1 * cw + c1) as u32, fu * fv),
                ]
            })
            .collect();
        let exitance = relief.exitance(v);
        CameraView {
            scene,
            albedo,
            width: cw,
            height: ch,
            exitance,
            splat,
        }
    }

    /// `m = W_c H_c`.
    pub fn pixels(&self) -> usize {
        self.width * self.height
    }
    pub fn width(&self) -> usize {
        self.width
    }
    pub fn height(&self) -> usize {
        self.height
    }

    /// The frame `T p` for a projector pattern `p` (k values).
    pub fn render(&self, pattern: &[f64]) -> Vec<f64> {
        assert_eq!(
            pattern.len(),
            self.scene.pixels(),
            "pattern has the projector's pixel count"
        );
        let lit = self.scene.reflect_adjoint(&self.albedo, pattern);
        let mut frame = vec![0.0; self.pixels()];
        for ((s, l), e) in self.splat.iter().zip(lit).zip(&self.exitance) {
            let out = l * e;
            if out != 0.0 {
                for &(j, wgt) in s {
                    frame[j as usize] += wgt * out;
                }
            }
        }
        frame
    }

    /// The relit dual image `T^T c` for a virtual light `c` at the camera (m values).
    pub fn relight(&self, light: &[f64]) -> Vec<f64> {
        assert_eq!(
            light.len(),
            self.pixels(),
            "light has the camera's pixel count"
        );
        let gathered: Vec<f64> = self
            .splat
            .iter()
            .zip(&self.exitance)
            .map(|(s, e)| {
                e * s
                    .iter()
                    .map(|&(j, wgt)| wgt * light[j as usize])
                    .sum::<f64>()
            })
            .collect();
        self.scene.reflect_adjoint(&self.albedo, &gathered)
    }

    /// Row `j` of T: the dual image seen by camera pixel `j`.
    pub fn row(&self, j: usize) -> Vec<f64> {
        let mut e = vec![0.0; self.pixels()];
        e[j] = 1.0;
        self.relight(&e)
    }

    /// Dense `T`, `m x k` row-major f32 (small sizes only: 64x64 x 64x64 is 64 MiB).
    pub fn dense(&self) -> Vec<f32> {
        let mut t = Vec::with_capacity(self.pixels() * self.scene.pixels());
        for j in 0..self.pixels() {
            t.extend(self.row(j).into_iter().map(|v| v as f32));
        }
        t
    }
}

fn box_pass(a: &[f64], w: usize, h: usize, r: usize, along_rows: bool) -> Vec<f64> {
    let mut out = vec![0.0; a.len()];
    let norm = 1.0 / (2 * r + 1) as f64;
    let (lines, len) = if along_rows { (h, w) } else { (w, h) };
    let idx = |line: usize, pos: usize| {
        if along_rows {
            line * w + pos
        } else {
            pos * w + line
        }
    };
    for line in 0..lines {
        // Running sum over [pos - r, pos + r], zero outside.
        let mut sum: f64 = (0..=r.min(len - 1)).map(|p| a[idx(line, p)]).sum();
        for pos in 0..len {
            out[idx(line, pos)] = sum * norm;
            if pos + r + 1 < len {
                sum += a[idx(line, pos + r + 1)];
            }
            if pos >= r {
                sum -= a[idx(line, pos - r)];
            }
        }
    }
    out
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `d / |d|`.
pub fn unit_vector(d: [f64; 3]) -> [f64; 3] {
    let n = dot(d, d).sqrt();
    assert!(
        n > 0.0 && n.is_finite(),
        "direction must be a nonzero finite vector"
    );
    [d[0] / n, d[1] / n, d[2] / n]
}

/// Direction at `elevation_degrees` above the ground plane and `azimuth_degrees` from +x toward +y.
pub fn direction(azimuth_degrees: f64, elevation_degrees: f64) -> [f64; 3] {
    let (az, el) = (azimuth_degrees * PI / 180.0, elevation_degrees * PI / 180.0);
    [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()]
}

/// Deterministic uniform in [0, 1) (SplitMix64 of `seed`, `i`).
fn unit(seed: u64, i: u64) -> f64 {
    let mut z = seed.wrapping_add(0x9E37_79B9_7F4A_7C15u64.wrapping_mul(i + 1));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pseudo(len: usize, seed: u64) -> Vec<f64> {
        (0..len).map(|i| unit(seed, i as u64)).collect()
    }

    #[test]
    fn render_and_relight_are_adjoint() {
        let scene = Relief::demo(24, 20, 3);
        let view = scene.view(&Camera::tilted(12, 10, 30.0));
        let (p, c) = (pseudo(scene.pixels(), 1), pseudo(view.pixels(), 2));
        let lhs: f64 = view.render(&p).iter().zip(&c).map(|(a, b)| a * b).sum();
        let rhs: f64 = p.iter().zip(view.relight(&c)).map(|(a, b)| a * b).sum();
        assert!((lhs - rhs).abs() <= 1e-12 * lhs.abs(), "{lhs} vs {rhs}");
        // And the dense matrix is the same operator.
        let t = view.dense();
        let k = scene.pixels();
        let j = 37;
        let direct: f64 = t[j * k..(j + 1) * k]
            .iter()
            .zip(&p)
            .map(|(a, b)| *a as f64 * b)
            .sum();
        assert!((direct - view.render(&p)[j]).abs() < 1e-5 * direct.abs().max(1e-3));
    }

    #[test]
    fn camera_summed_over_pixels_is_the_bucket_detector_where_it_stands() {
        let scene = Relief::demo(32, 32, 7);
        let camera = Camera::tilted(16, 16, 25.0);
        let view = scene.view(&camera);
        let summed = view.relight(&vec![1.0; view.pixels()]);
        let bucket = scene.detector_transport(camera.direction);
        let err = summed
            .iter()
            .zip(&bucket)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-12, "max difference {err}");
        assert!(bucket.iter().any(|&v| v > 0.1));
    }

    #[test]
    fn the_box_casts_a_shadow_for_a_low_detector_and_normals_are_unit() {
        let scene = Relief::demo(64, 64, 1);
        for n in scene.normals() {
            assert!((dot(*n, *n) - 1.0).abs() < 1e-12 && n[2] >= 0.0);
        }
        // Light from -x at 20 degrees elevation: ground just left of... the box's -x side is in
        // front of it; ground on the +x side (behind the box as seen from -x) is shadowed.
        let vis = scene.visibility(direction(180.0, 20.0));
        let (row, col) = ((0.7 * 64.0) as usize, (0.9 * 64.0) as usize);
        assert_eq!(
            vis[row * 64 + col],
            0.0,
            "ground behind the box is in its shadow"
        );
        assert_eq!(
            scene.visibility([0.0, 0.0, 1.0]).iter().sum::<f64>(),
            64.0 * 64.0
        );
        // Some ground near the hemisphere and box is shadowed, most is lit.
        let lit = vis.iter().sum::<f64>() / vis.len() as f64;
        assert!(lit > 0.6 && lit < 0.98, "lit fraction {lit}");
    }

    #[test]
    fn direct_transport_is_albedo_times_cosine_without_indirect_light() {
        let mut scene = Relief::demo(32, 32, 2);
        scene.indirect = 0.0;
        let d = direction(45.0, 60.0);
        let t = scene.detector_transport(d);
        let albedo = scene.albedo();
        let vis = scene.visibility(d);
        for i in 0..scene.pixels() {
            let n = scene.normals()[i];
            let want = albedo[i] * dot(n, d).max(0.0) * vis[i];
            assert!((t[i] - want).abs() < 1e-12);
        }
    }
}
