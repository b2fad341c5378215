//! A diffuse floor with a rough metal sphere and a rough glass sphere: a diffuse part plus a
//! sparse, bright specular part.
//!
//! A pinhole projector looks down on a textured Lambertian floor (`y = 0`; albedo a checker with
//! seeded discs, 0.3-0.8) from behind; a metal sphere stands on the floor and a glass ball is held
//! a little above it (its stand is not modelled); a pinhole camera looks on from the front.
//! Projector pixel `i` sends unit power along 2 x 2 sub-rays.
//!
//! - **Diffuse part** (first bounce): a sub-ray landing on the floor (or on a sphere's weak
//!   diffuse layer, albedo 0.04 metal, 0 glass) is a small Lambertian source of radiant intensity
//!   `rho cos(theta_c) / pi` toward the camera, splatted bilinearly into its pixels (divided by
//!   the pixel's solid angle: camera pixels report mean radiance).
//! - **Specular part.** At a sphere the sub-ray is reflected (metal: reflectance 0.85; glass:
//!   Schlick's Fresnel term, index 1.5) into a normalised Phong lobe about the mirror direction
//!   `r`, radiant intensity `power (n + 1) / (2 pi) max(0, r.v)^n` (exponent `n` the roughness:
//!   200 metal, 400 glass). Toward the camera this is a glint, at the camera pixel that sees the
//!   point (first bounce). The rest of the lobe, 16 stratified samples of it, lands on the floor
//!   and is reflected there diffusely toward the camera (second bounce). Glass also transmits
//!   `(1 - F_in)(1 - F_out)` of the power: refracted in, across the ball and out (Snell), then
//!   spread in the same kind of lobe about the exit direction, 16 samples, onto the floor: the
//!   ball lens focuses the light of every projector pixel that hits it into a small bright spot,
//!   the caustic.
//!
//! Approximations: one specular bounce (a lobe sample that hits the other sphere is dropped,
//! as if absorbed); no diffuse interreflection; the camera does not see through the glass (the
//! spheres only occlude for it) nor reflections of the lit floor in the spheres; lobe samples
//! below a sphere's tangent plane are dropped (absorbed).

use std::f64::consts::PI;

use super::RenderedTransport;
use super::geometry::{
    Pinhole, Rect, Sphere, V3, add, basis, dot, norm, reflect, refract, scale, schlick, sub,
    uniform, unit,
};

/// Sub-rays per projector pixel side.
const SUB: usize = 2;
/// Lobe samples per side (per specular event: `LOBE^2`).
const LOBE: usize = 4;
const GLASS_INDEX: f64 = 1.5;
/// The projector, behind and above the spheres (the caustic falls toward the camera).
const PROJECTOR_AT: V3 = [0.5, 2.0, -0.3];
const CAMERA_AT: V3 = [0.5, 1.8, 2.4];
const CAMERA_TARGET: V3 = [0.5, 0.0, 0.55];
const CAMERA_TAN: f64 = 0.45;

#[derive(Clone, Copy, Debug)]
enum Material {
    /// Diffuse albedo, specular reflectance, Phong exponent.
    Metal(f64, f64, f64),
    /// Phong exponent of the reflection and transmission lobes.
    Glass(f64),
}

pub(super) struct Stage {
    floor: Rect,
    spheres: Vec<(Sphere, Material)>,
    seed: u64,
}

/// What a ray meets first.
enum Hit {
    Floor(V3),
    Ball(usize, V3),
}

impl Stage {
    fn new(seed: u64) -> Stage {
        let j = |i: u64| 0.06 * (uniform(seed, 1000 + i) - 0.5);
        Stage {
            floor: Rect::new([-0.4, 0.0, -0.4], [0.0, 0.0, 1.8], [1.8, 0.0, 0.0]),
            spheres: vec![
                (
                    Sphere {
                        centre: [0.3 + j(0), 0.16, 0.42 + j(1)],
                        radius: 0.16,
                    },
                    Material::Metal(0.04, 0.85, 200.0),
                ),
                (
                    Sphere {
                        centre: [0.7 + j(2), 0.22, 0.6 + j(3)],
                        radius: 0.15,
                    },
                    Material::Glass(400.0),
                ),
            ],
            seed,
        }
    }

    /// Floor albedo at `(x, z)`: a soft checker with seeded discs.
    fn albedo(&self, p: V3) -> f64 {
        let checker = ((p[0] / 0.125).floor() as i64 + (p[2] / 0.125).floor() as i64).rem_euclid(2);
        let mut a = 0.45 + 0.2 * checker as f64;
        for i in 0..6u64 {
            let u = |k: u64| uniform(self.seed, 8 * i + k);
            let (cx, cz, r) = (u(0), u(1), 0.04 + 0.06 * u(2));
            if (p[0] - cx).powi(2) + (p[2] - cz).powi(2) < r * r {
                a = 0.3 + 0.5 * u(3);
            }
        }
        a
    }

    fn trace(&self, o: V3, d: V3) -> Option<(f64, Hit)> {
        let mut best: Option<(f64, Hit)> = self
            .floor
            .hit(o, d)
            .map(|(t, _, _)| (t, Hit::Floor(add(o, scale(d, t)))));
        for (s, (sphere, _)) in self.spheres.iter().enumerate() {
            if let Some(t) = sphere.hit(o, d)
                && best.as_ref().is_none_or(|b| t < b.0)
            {
                best = Some((t, Hit::Ball(s, add(o, scale(d, t)))));
            }
        }
        best
    }

    /// Does the camera at `c` see the point `x` (nothing in between)?
    fn visible(&self, c: V3, x: V3) -> bool {
        let d = sub(x, c);
        let dist = norm(d);
        self.trace(c, scale(d, 1.0 / dist))
            .is_some_and(|(t, _)| (t - dist).abs() < 1e-7 * dist)
    }

    /// `LOBE^2` stratified directions of a Phong lobe of exponent `n` about unit `axis`.
    fn lobe(&self, axis: V3, n: f64, key: u64) -> Vec<V3> {
        let (e1, e2) = basis(axis);
        let mut out = Vec::with_capacity(LOBE * LOBE);
        for a in 0..LOBE {
            for b in 0..LOBE {
                let s = key * 64 + (a * LOBE + b) as u64;
                let u = (a as f64 + uniform(self.seed ^ 0x5EED, 2 * s)) / LOBE as f64;
                let v = (b as f64 + uniform(self.seed ^ 0x5EED, 2 * s + 1)) / LOBE as f64;
                let cos = u.powf(1.0 / (n + 1.0));
                let sin = (1.0 - cos * cos).max(0.0).sqrt();
                let phi = 2.0 * PI * v;
                out.push(add(
                    scale(axis, cos),
                    add(scale(e1, sin * phi.cos()), scale(e2, sin * phi.sin())),
                ));
            }
        }
        out
    }
}

/// The camera side of a render: splats point sources into `m x k` matrices.
struct Film<'a> {
    cam: &'a Pinhole,
    k: usize,
}

impl Film<'_> {
    /// Adds a point source at `x` of radiant intensity `intensity` toward the camera (already
    /// known visible) to column `i` of `out`.
    fn splat(&self, out: &mut [f64], i: usize, x: V3, intensity: f64) {
        let Some((cu, cv)) = self.cam.project(x) else {
            return;
        };
        let d2 = dot(sub(self.cam.position, x), sub(self.cam.position, x));
        for (j, w) in self.cam.splat(cu, cv) {
            let omega = self
                .cam
                .pixel_solid_angle((j % self.cam.width) as f64, (j / self.cam.width) as f64);
            out[j * self.k + i] += w * intensity / (d2 * omega);
        }
    }
}

/// The parts of a render, for the tests.
#[cfg_attr(not(test), allow(dead_code))]
pub(super) struct Render {
    /// Diffuse first bounce.
    pub diffuse: Vec<f64>,
    /// Glints (first bounce, specular).
    pub glint: Vec<f64>,
    /// Specular then diffuse on the floor (second bounce; the caustic).
    pub caustic: Vec<f64>,
    /// Projector pixels with a sub-ray on each sphere.
    pub on_sphere: Vec<Vec<usize>>,
    pub transport: RenderedTransport,
}

pub(super) fn render(projector: (usize, usize), camera: (usize, usize), seed: u64) -> Render {
    assert!(
        projector.0 > 0 && projector.1 > 0 && camera.0 > 0 && camera.1 > 0,
        "a rig needs pixels"
    );
    let stage = Stage::new(seed);
    let up = [0.0, 1.0, 0.0];
    let proj = Pinhole::looking_at(
        PROJECTOR_AT,
        [0.5, 0.0, 0.5],
        up,
        0.22,
        projector.0,
        projector.1,
    );
    let cam = Pinhole::looking_at(CAMERA_AT, CAMERA_TARGET, up, CAMERA_TAN, camera.0, camera.1);
    let (k, m) = (projector.0 * projector.1, camera.0 * camera.1);
    let film = Film { cam: &cam, k };
    let (mut diffuse, mut glint, mut caustic) =
        (vec![0.0; m * k], vec![0.0; m * k], vec![0.0; m * k]);
    let mut on_sphere = vec![Vec::new(); stage.spheres.len()];
    let sub_power = 1.0 / (SUB * SUB) as f64;
    // A floor point lit with `power` by light arriving from anywhere: its diffuse reflection.
    let floor_to_camera = |out: &mut [f64], i: usize, y: V3, power: f64| {
        let to_cam = sub(cam.position, y);
        let cos_c = to_cam[1] / norm(to_cam);
        if cos_c > 0.0 && stage.visible(cam.position, y) {
            film.splat(out, i, y, power * stage.albedo(y) * cos_c / PI);
        }
    };
    for i in 0..k {
        let (col, row) = ((i % projector.0) as f64, (i / projector.0) as f64);
        for s in 0..SUB * SUB {
            let (du, dv) = (
                ((s % SUB) as f64 + 0.5) / SUB as f64,
                ((s / SUB) as f64 + 0.5) / SUB as f64,
            );
            let d = proj.ray(col + du - 0.5, row + dv - 0.5);
            let Some((_, hit)) = stage.trace(proj.position, d) else {
                continue;
            };
            match hit {
                Hit::Floor(x) => floor_to_camera(&mut diffuse, i, x, sub_power),
                Hit::Ball(b, x) => {
                    if on_sphere[b].last() != Some(&i) {
                        on_sphere[b].push(i);
                    }
                    let (sphere, material) = stage.spheres[b];
                    let n = sphere.normal(x);
                    let to_cam = sub(cam.position, x);
                    let v = unit(to_cam);
                    let seen = dot(n, v) > 0.0 && stage.visible(cam.position, x);
                    let r = reflect(d, n);
                    let key = (i * SUB * SUB + s) as u64 * 4;
                    // (power reflected, exponent) of the mirror lobe; the glass's transmission.
                    let (reflected, exponent) = match material {
                        Material::Metal(rho_d, k_s, n_exp) => {
                            if seen {
                                film.splat(&mut diffuse, i, x, sub_power * rho_d * dot(n, v) / PI);
                            }
                            (sub_power * k_s, n_exp)
                        }
                        Material::Glass(n_exp) => {
                            (sub_power * schlick(-dot(d, n), 1.0, GLASS_INDEX), n_exp)
                        }
                    };
                    if seen {
                        let lobe =
                            (exponent + 1.0) / (2.0 * PI) * dot(r, v).max(0.0).powf(exponent);
                        film.splat(&mut glint, i, x, reflected * lobe);
                    }
                    let samples = stage.lobe(r, exponent, key);
                    let each = reflected / samples.len() as f64;
                    for w in samples {
                        if dot(w, n) <= 0.0 {
                            continue;
                        }
                        if let Some((_, Hit::Floor(y))) = stage.trace(x, w) {
                            floor_to_camera(&mut caustic, i, y, each);
                        }
                    }
                    if let Material::Glass(n_exp) = material {
                        let f_in = schlick(-dot(d, n), 1.0, GLASS_INDEX);
                        let Some(t1) = refract(d, n, 1.0 / GLASS_INDEX) else {
                            continue;
                        };
                        let Some(t) = sphere.hit(add(x, scale(t1, 1e-9)), t1) else {
                            continue;
                        };
                        let x2 = add(x, scale(t1, t));
                        let n2 = sphere.normal(x2);
                        let Some(t2) = refract(t1, scale(n2, -1.0), GLASS_INDEX) else {
                            continue;
                        };
                        let f_out = schlick(dot(t2, n2), 1.0, GLASS_INDEX);
                        let through = sub_power * (1.0 - f_in) * (1.0 - f_out);
                        let samples = stage.lobe(t2, n_exp, key + 1);
                        let each = through / samples.len() as f64;
                        for w in samples {
                            if dot(w, n2) <= 0.0 {
                                continue;
                            }
                            if let Some((_, Hit::Floor(y))) = stage.trace(x2, w) {
                                floor_to_camera(&mut caustic, i, y, each);
                            }
                        }
                    }
                }
            }
        }
    }
    let t: Vec<f64> = diffuse
        .iter()
        .zip(&glint)
        .zip(&caustic)
        .map(|((a, b), c)| a + b + c)
        .collect();
    let direct: Vec<f64> = diffuse.iter().zip(&glint).map(|(a, b)| a + b).collect();
    Render {
        diffuse,
        glint,
        caustic,
        on_sphere,
        transport: RenderedTransport::new(projector, camera, t, direct),
    }
}
