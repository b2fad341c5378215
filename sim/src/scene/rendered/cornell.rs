//! A Cornell-like box with multi-bounce diffuse interreflection (radiosity; Goral et al. 1984).
//!
//! The box is the unit cube open at the front (`z = 1`): floor, ceiling, back wall and two side
//! walls, each of one grey albedo (left 0.35, right 0.75), with a short and a tall block on the
//! floor (their places jittered by the seed). All surfaces are Lambertian. A pinhole projector
//! and a pinhole camera look in through the opening from different places.
//!
//! - **Patches.** Each wall is cut into 8 x 8 patches, each block face into 2 x 2 to 2 x 4.
//! - **Form factors** `F_pq` (patch p receives from q) from 2 x 2 sample points on each patch, the
//!   point-to-point kernel `cos cos / (pi r^2)` times the sample areas, with visibility through
//!   the blocks (a segment test). The symmetric `G = diag(A) F` makes reciprocity
//!   `A_p F_pq = A_q F_qp` exact, hence exact energy bookkeeping. The point estimate is rough for
//!   adjacent patches; `sum_q F_pq <= 1` is checked (and `G` scaled down if it were violated).
//! - **Radiosity.** Projector pixel `i` sends unit power along 2 x 2 sub-rays; each lands on a
//!   patch `p`, giving the first-bounce exitance `E_pi = rho_p (power on p) / A_p`. Then
//!   `B = E + diag(rho) F B` is solved by Gauss-Seidel sweeps (each adds about one bounce; the
//!   spectral radius is below `max rho < 1`) until the largest change is below `1e-12` of the
//!   largest `B`.
//! - **Camera.** Direct light is exact per sub-ray: the lit point, if the camera sees it, is a
//!   small Lambertian source of radiant intensity `rho cos(theta_c) / pi` splatted bilinearly
//!   into the camera (divided by the pixel's solid angle: camera pixels report mean radiance).
//!   Indirect light is the radiance `(B - E) / pi` of the surface each of the camera pixel's 2 x 2
//!   sub-rays sees, interpolated bilinearly between patch centres.
//!
//! So `T = T_direct + T_indirect`, `T_indirect` dense and smooth. At 32 x 32 x 48 x 48 about a
//! quarter of the camera's light is indirect (tests check 10-40 %).

use std::f64::consts::PI;

use super::RenderedTransport;
use super::geometry::{
    Pinhole, Rect, V3, bilinear, dot, norm, scale, segment_crosses_box, sub, uniform, unit,
};

/// Patches per wall side.
const WALL_PATCHES: usize = 8;
/// Sub-rays per pixel side (projector and camera).
const SUB: usize = 2;

/// A flat diffuse surface cut into `nu x nv` patches.
#[derive(Clone, Debug)]
pub(super) struct Surface {
    pub rect: Rect,
    pub albedo: f64,
    pub nu: usize,
    pub nv: usize,
    /// Index of its first patch (patches row by row along `ev`, then `eu`).
    pub first: usize,
}

/// The box's geometry, its radiosity system and the rigs.
pub(super) struct Room {
    pub surfaces: Vec<Surface>,
    /// Blocks as axis-aligned boxes `(lo, hi)`: the occluders of the form factors.
    pub blocks: Vec<(V3, V3)>,
    /// Per patch: (surface, area, albedo).
    pub patches: Vec<(usize, f64, f64)>,
    /// `F`, `N x N` row-major.
    pub form: Vec<f64>,
}

impl Room {
    pub fn new(seed: u64) -> Room {
        let j = |i: u64| 0.08 * (uniform(seed, i) - 0.5);
        let mut surfaces = Vec::new();
        let mut add = |rect: Rect, albedo: f64, nu: usize, nv: usize| {
            let first = surfaces.iter().map(|s: &Surface| s.nu * s.nv).sum();
            surfaces.push(Surface {
                rect,
                albedo,
                nu,
                nv,
                first,
            });
        };
        let n = WALL_PATCHES;
        // Walls, normals pointing into the box.
        add(
            Rect::new([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]),
            0.6,
            n,
            n,
        ); // floor, +y
        add(
            Rect::new([0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
            0.55,
            n,
            n,
        ); // ceiling, -y
        add(
            Rect::new([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
            0.65,
            n,
            n,
        ); // back, +z
        add(
            Rect::new([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]),
            0.35,
            n,
            n,
        ); // left, +x
        add(
            Rect::new([1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]),
            0.75,
            n,
            n,
        ); // right, -x
        // Blocks: (centre x, centre z, side, height, albedo).
        let blocks_spec = [
            (0.67 + j(0), 0.62 + j(1), 0.28, 0.28, 0.7),
            (0.32 + j(2), 0.36 + j(3), 0.28, 0.58, 0.7),
        ];
        let mut blocks = Vec::new();
        for &(cx, cz, side, h, albedo) in &blocks_spec {
            let (x0, x1, z0, z1) = (
                cx - side / 2.0,
                cx + side / 2.0,
                cz - side / 2.0,
                cz + side / 2.0,
            );
            let up = if h > 0.4 { 4 } else { 2 };
            add(
                Rect::new([x0, h, z0], [0.0, 0.0, side], [side, 0.0, 0.0]),
                albedo,
                2,
                2,
            ); // top, +y
            add(
                Rect::new([x0, 0.0, z1], [side, 0.0, 0.0], [0.0, h, 0.0]),
                albedo,
                2,
                up,
            ); // front, +z
            add(
                Rect::new([x0, 0.0, z0], [0.0, h, 0.0], [side, 0.0, 0.0]),
                albedo,
                up,
                2,
            ); // back, -z
            add(
                Rect::new([x0, 0.0, z0], [0.0, 0.0, side], [0.0, h, 0.0]),
                albedo,
                2,
                up,
            ); // left, -x
            add(
                Rect::new([x1, 0.0, z0], [0.0, h, 0.0], [0.0, 0.0, side]),
                albedo,
                up,
                2,
            ); // right, +x
            blocks.push(([x0, 0.0, z0], [x1, h, z1]));
        }
        let mut patches = Vec::new();
        for (s, surf) in surfaces.iter().enumerate() {
            let area = surf.rect.area() / (surf.nu * surf.nv) as f64;
            patches.extend(std::iter::repeat_n(
                (s, area, surf.albedo),
                surf.nu * surf.nv,
            ));
        }
        let mut room = Room {
            surfaces,
            blocks,
            patches,
            form: Vec::new(),
        };
        room.form = room.form_factors();
        room
    }

    pub fn len(&self) -> usize {
        self.patches.len()
    }

    /// Centre of sample `s` (of `SUB x SUB`) of patch `p`.
    fn sample(&self, p: usize, s: usize) -> V3 {
        let surf = &self.surfaces[self.patches[p].0];
        let local = p - surf.first;
        let (iu, iv) = (local / surf.nv, local % surf.nv);
        let (su, sv) = (s / SUB, s % SUB);
        surf.rect.point(
            (iu as f64 + (su as f64 + 0.5) / SUB as f64) / surf.nu as f64,
            (iv as f64 + (sv as f64 + 0.5) / SUB as f64) / surf.nv as f64,
        )
    }

    /// The patch of surface `s` at local coordinates `(a, b)`.
    fn patch_at(&self, s: usize, a: f64, b: f64) -> usize {
        let surf = &self.surfaces[s];
        let iu = ((a * surf.nu as f64) as usize).min(surf.nu - 1);
        let iv = ((b * surf.nv as f64) as usize).min(surf.nv - 1);
        surf.first + iu * surf.nv + iv
    }

    /// `F` from the symmetric point-to-point estimate of `G = diag(A) F` (module docs).
    fn form_factors(&self) -> Vec<f64> {
        let n = self.len();
        let ss = SUB * SUB;
        let samples: Vec<V3> = (0..n)
            .flat_map(|p| (0..ss).map(move |s| (p, s)))
            .map(|(p, s)| self.sample(p, s))
            .collect();
        let mut g = vec![0.0; n * n];
        for p in 0..n {
            let (sp, ap, _) = self.patches[p];
            let np = self.surfaces[sp].rect.normal;
            for q in p + 1..n {
                let (sq, aq, _) = self.patches[q];
                if sq == sp {
                    continue;
                }
                let nq = self.surfaces[sq].rect.normal;
                let mut sum = 0.0;
                for x in &samples[p * ss..(p + 1) * ss] {
                    for y in &samples[q * ss..(q + 1) * ss] {
                        let d = sub(*y, *x);
                        let r2 = dot(d, d);
                        let (ci, cj) = (dot(np, d), -dot(nq, d));
                        if ci <= 0.0 || cj <= 0.0 {
                            continue;
                        }
                        if self
                            .blocks
                            .iter()
                            .any(|&(lo, hi)| segment_crosses_box(*x, *y, lo, hi))
                        {
                            continue;
                        }
                        sum += ci * cj / (PI * r2 * r2);
                    }
                }
                let v = sum * (ap / ss as f64) * (aq / ss as f64);
                g[p * n + q] = v;
                g[q * n + p] = v;
            }
        }
        // Row sums of F must stay below 1 (a closed surface's are 1); the point estimate could
        // overshoot for adjacent patches.
        let worst = (0..n)
            .map(|p| g[p * n..(p + 1) * n].iter().sum::<f64>() / self.patches[p].1)
            .fold(0.0, f64::max);
        let fix = if worst >= 0.999 { 0.999 / worst } else { 1.0 };
        for p in 0..n {
            let a = self.patches[p].1;
            for v in &mut g[p * n..(p + 1) * n] {
                *v *= fix / a;
            }
        }
        g
    }

    /// The nearest surface along `o + t d`: `(surface, t, a, b)`.
    pub fn trace(&self, o: V3, d: V3) -> Option<(usize, f64, f64, f64)> {
        self.surfaces
            .iter()
            .enumerate()
            .filter_map(|(s, surf)| surf.rect.hit(o, d).map(|(t, a, b)| (s, t, a, b)))
            .min_by(|x, y| x.1.total_cmp(&y.1))
    }

    /// Solves `B = E + diag(rho) F B` (`E`, `B`: `N x k` row-major) by Gauss-Seidel from
    /// `B = E`; returns `B` and the number of sweeps.
    pub fn solve(&self, e: &[f64], k: usize) -> (Vec<f64>, usize) {
        let n = self.len();
        let mut b = e.to_vec();
        let scale_of = |b: &[f64]| b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let mut row = vec![0.0; k];
        for sweep in 1..=10_000 {
            let mut change = 0.0f64;
            for p in 0..n {
                row.copy_from_slice(&e[p * k..(p + 1) * k]);
                let rho = self.patches[p].2;
                for q in 0..n {
                    let f = rho * self.form[p * n + q];
                    if f != 0.0 {
                        for (r, v) in row.iter_mut().zip(&b[q * k..(q + 1) * k]) {
                            *r += f * v;
                        }
                    }
                }
                for (old, new) in b[p * k..(p + 1) * k].iter_mut().zip(&row) {
                    change = change.max((*old - new).abs());
                    *old = *new;
                }
            }
            if change <= 1e-12 * scale_of(&b) {
                return (b, sweep);
            }
        }
        panic!("radiosity did not converge (albedo must stay below 1)");
    }
}

/// The rigs of the box: projector and camera.
fn rigs(projector: (usize, usize), camera: (usize, usize)) -> (Pinhole, Pinhole) {
    let up = [0.0, 1.0, 0.0];
    (
        Pinhole::looking_at(
            [0.5, 0.72, 2.2],
            [0.5, 0.42, 0.0],
            up,
            0.33,
            projector.0,
            projector.1,
        ),
        Pinhole::looking_at(
            [0.36, 0.55, 2.6],
            [0.5, 0.45, 0.3],
            up,
            0.34,
            camera.0,
            camera.1,
        ),
    )
}

/// The pieces of a render, for the tests: the room, `E` and `B` (`N x k`), and `T`.
#[cfg_attr(not(test), allow(dead_code))]
pub(super) struct Render {
    pub room: Room,
    pub e: Vec<f64>,
    pub b: Vec<f64>,
    pub sweeps: usize,
    /// Power each projector pixel puts on the room (1 where all its sub-rays land).
    pub power: Vec<f64>,
    pub transport: RenderedTransport,
}

pub(super) fn render(projector: (usize, usize), camera: (usize, usize), seed: u64) -> Render {
    assert!(
        projector.0 > 0 && projector.1 > 0 && camera.0 > 0 && camera.1 > 0,
        "a rig needs pixels"
    );
    let room = Room::new(seed);
    let (proj, cam) = rigs(projector, camera);
    let (n, k, m) = (room.len(), projector.0 * projector.1, camera.0 * camera.1);
    let sub_power = 1.0 / (SUB * SUB) as f64;
    let mut e = vec![0.0; n * k];
    let mut direct = vec![0.0; m * k];
    let mut power = vec![0.0; k];
    for i in 0..k {
        let (col, row) = ((i % projector.0) as f64, (i / projector.0) as f64);
        for s in 0..SUB * SUB {
            let (du, dv) = (
                ((s % SUB) as f64 + 0.5) / SUB as f64,
                ((s / SUB) as f64 + 0.5) / SUB as f64,
            );
            let d = proj.ray(col + du - 0.5, row + dv - 0.5);
            let Some((surf, t, a, b)) = room.trace(proj.position, d) else {
                continue;
            };
            let p = room.patch_at(surf, a, b);
            let (_, area, rho) = room.patches[p];
            e[p * k + i] += rho * sub_power / area;
            power[i] += sub_power;
            // Direct: the lit point as a small Lambertian source seen by the camera.
            let x = super::geometry::add(proj.position, scale(d, t));
            let to_cam = sub(cam.position, x);
            let dist = norm(to_cam);
            let cos_c = dot(room.surfaces[surf].rect.normal, to_cam) / dist;
            if cos_c <= 0.0 {
                continue;
            }
            let seen = room.trace(cam.position, unit(scale(to_cam, -1.0)));
            if !seen.is_some_and(|h| (h.1 - dist).abs() < 1e-7 * dist) {
                continue;
            }
            let Some((cu, cv)) = cam.project(x) else {
                continue;
            };
            let intensity = sub_power * rho * cos_c / (PI * dist * dist);
            for (j, w) in cam.splat(cu, cv) {
                let omega = cam.pixel_solid_angle((j % camera.0) as f64, (j / camera.0) as f64);
                direct[j * k + i] += w * intensity / omega;
            }
        }
    }
    let (b, sweeps) = room.solve(&e, k);
    // Indirect: (B - E) / pi where the camera looks, bilinear between patch centres.
    let mut t = direct.clone();
    let cam_sub = 1.0 / (SUB * SUB) as f64;
    for j in 0..m {
        let (col, row) = ((j % camera.0) as f64, (j / camera.0) as f64);
        let mut weights: Vec<(usize, f64)> = Vec::new();
        for s in 0..SUB * SUB {
            let (du, dv) = (
                ((s % SUB) as f64 + 0.5) / SUB as f64,
                ((s / SUB) as f64 + 0.5) / SUB as f64,
            );
            let d = cam.ray(col + du - 0.5, row + dv - 0.5);
            if let Some((surf, _, a, bb)) = room.trace(cam.position, d) {
                let sf = &room.surfaces[surf];
                // Patches run along `ev` fastest: a grid `nv` wide, `nu` high.
                for (local, w) in bilinear(
                    bb * sf.nv as f64 - 0.5,
                    a * sf.nu as f64 - 0.5,
                    sf.nv,
                    sf.nu,
                ) {
                    weights.push((sf.first + local, w * cam_sub / PI));
                }
            }
        }
        let out = &mut t[j * k..(j + 1) * k];
        for (p, w) in weights {
            for ((o, bv), ev) in out
                .iter_mut()
                .zip(&b[p * k..(p + 1) * k])
                .zip(&e[p * k..(p + 1) * k])
            {
                *o += w * (bv - ev);
            }
        }
    }
    Render {
        room,
        e,
        b,
        sweeps,
        power,
        transport: RenderedTransport::new(projector, camera, t, direct),
    }
}
