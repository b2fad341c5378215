//! The little ray geometry the rendered scenes need: vectors, pinhole cameras and projectors,
//! rectangles and spheres, and the bilinear splat of a point into a pixel grid.

pub type V3 = [f64; 3];

pub fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
pub fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub fn scale(a: V3, s: f64) -> V3 {
    [a[0] * s, a[1] * s, a[2] * s]
}
pub fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub fn norm(a: V3) -> f64 {
    dot(a, a).sqrt()
}
pub fn unit(a: V3) -> V3 {
    scale(a, 1.0 / norm(a))
}
/// `d` mirrored about the unit normal `n`.
pub fn reflect(d: V3, n: V3) -> V3 {
    sub(d, scale(n, 2.0 * dot(d, n)))
}
/// Snell refraction of the unit direction `d` at the unit normal `n` (facing against `d`) with
/// `eta = n_from / n_to`; `None` on total internal reflection.
pub fn refract(d: V3, n: V3, eta: f64) -> Option<V3> {
    let cos_i = -dot(d, n);
    let k = 1.0 - eta * eta * (1.0 - cos_i * cos_i);
    (k >= 0.0).then(|| add(scale(d, eta), scale(n, eta * cos_i - k.sqrt())))
}
/// Schlick's approximation of the Fresnel reflectance for refractive indices `n1`, `n2`.
pub fn schlick(cos_i: f64, n1: f64, n2: f64) -> f64 {
    let r0 = ((n1 - n2) / (n1 + n2)).powi(2);
    r0 + (1.0 - r0) * (1.0 - cos_i.clamp(0.0, 1.0)).powi(5)
}

/// Two unit vectors completing `n` to an orthonormal basis.
pub fn basis(n: V3) -> (V3, V3) {
    let a = if n[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let u = unit(cross(n, a));
    (u, cross(n, u))
}

/// A pinhole camera (or projector) at `position` looking along `forward`, `width x height`
/// square pixels, row 0 at the top, `tan_half_width` the tangent of half the horizontal field.
#[derive(Clone, Copy, Debug)]
pub struct Pinhole {
    pub position: V3,
    forward: V3,
    right: V3,
    up: V3,
    tan_w: f64,
    tan_h: f64,
    pub width: usize,
    pub height: usize,
}

impl Pinhole {
    pub fn looking_at(
        position: V3,
        target: V3,
        up_hint: V3,
        tan_half_width: f64,
        width: usize,
        height: usize,
    ) -> Pinhole {
        let forward = unit(sub(target, position));
        let right = unit(cross(forward, up_hint));
        let up = cross(right, forward);
        Pinhole {
            position,
            forward,
            right,
            up,
            tan_w: tan_half_width,
            tan_h: tan_half_width * height as f64 / width as f64,
            width,
            height,
        }
    }

    /// Image-plane coordinates (at unit distance) of continuous pixel position `(col, row)`,
    /// pixel centres at `c + 1/2`.
    fn plane(&self, col: f64, row: f64) -> (f64, f64) {
        (
            (2.0 * col / self.width as f64 - 1.0) * self.tan_w,
            (1.0 - 2.0 * row / self.height as f64) * self.tan_h,
        )
    }

    /// The unit direction through continuous pixel position `(col, row)`.
    pub fn ray(&self, col: f64, row: f64) -> V3 {
        let (x, y) = self.plane(col, row);
        unit(add(
            self.forward,
            add(scale(self.right, x), scale(self.up, y)),
        ))
    }

    /// Where `p` lands on the image: continuous pixel-centre coordinates (`(0, 0)` the centre of
    /// the top-left pixel), or `None` behind the pinhole.
    pub fn project(&self, p: V3) -> Option<(f64, f64)> {
        let d = sub(p, self.position);
        let f = dot(d, self.forward);
        if f <= 1e-12 {
            return None;
        }
        let (x, y) = (dot(d, self.right) / f, dot(d, self.up) / f);
        Some((
            (x / self.tan_w + 1.0) * 0.5 * self.width as f64 - 0.5,
            (1.0 - y / self.tan_h) * 0.5 * self.height as f64 - 0.5,
        ))
    }

    /// Solid angle of the pixel whose centre is at continuous position `(col, row)`.
    pub fn pixel_solid_angle(&self, col: f64, row: f64) -> f64 {
        let (x, y) = self.plane(col + 0.5, row + 0.5);
        let cell = 4.0 * self.tan_w * self.tan_h / (self.width * self.height) as f64;
        cell / (1.0 + x * x + y * y).powf(1.5)
    }

    /// Up to four `(pixel, weight)` of the bilinear splat of continuous position `(col, row)`,
    /// weights summing to 1; empty outside the frame (beyond the outer pixels' edges).
    pub fn splat(&self, col: f64, row: f64) -> Vec<(usize, f64)> {
        bilinear(col, row, self.width, self.height)
    }
}

/// Bilinear weights of continuous pixel-centre position `(x, y)` on a `w x h` grid: up to four
/// `(index, weight)` (zero weights dropped), summing to 1; empty outside `[-1/2, w - 1/2] x
/// [-1/2, h - 1/2]` (positions within half a pixel of the border are clamped onto it).
pub fn bilinear(x: f64, y: f64, w: usize, h: usize) -> Vec<(usize, f64)> {
    if !(x >= -0.5 && y >= -0.5 && x <= w as f64 - 0.5 && y <= h as f64 - 0.5) {
        return Vec::new();
    }
    let (x, y) = (x.clamp(0.0, (w - 1) as f64), y.clamp(0.0, (h - 1) as f64));
    let (c0, r0) = (x.floor() as usize, y.floor() as usize);
    let (c1, r1) = ((c0 + 1).min(w - 1), (r0 + 1).min(h - 1));
    let (fx, fy) = (x - c0 as f64, y - r0 as f64);
    let mut out: Vec<(usize, f64)> = Vec::with_capacity(4);
    for (r, c, wgt) in [
        (r0, c0, (1.0 - fx) * (1.0 - fy)),
        (r0, c1, fx * (1.0 - fy)),
        (r1, c0, (1.0 - fx) * fy),
        (r1, c1, fx * fy),
    ] {
        if wgt > 0.0 {
            let i = r * w + c;
            match out.iter_mut().find(|(j, _)| *j == i) {
                Some(e) => e.1 += wgt,
                None => out.push((i, wgt)),
            }
        }
    }
    out
}

/// A rectangle `origin + a eu + b ev`, `a, b` in [0, 1], lit and seen on the side of `normal`
/// (`eu x ev` normalised).
#[derive(Clone, Copy, Debug)]
pub struct Rect {
    pub origin: V3,
    pub eu: V3,
    pub ev: V3,
    pub normal: V3,
}

impl Rect {
    pub fn new(origin: V3, eu: V3, ev: V3) -> Rect {
        Rect {
            origin,
            eu,
            ev,
            normal: unit(cross(eu, ev)),
        }
    }
    pub fn area(&self) -> f64 {
        norm(cross(self.eu, self.ev))
    }
    pub fn point(&self, a: f64, b: f64) -> V3 {
        add(self.origin, add(scale(self.eu, a), scale(self.ev, b)))
    }
    /// Distance along the ray `o + t d` (`t > 1e-9`) to the rectangle (either side), with its
    /// local coordinates `(a, b)`.
    pub fn hit(&self, o: V3, d: V3) -> Option<(f64, f64, f64)> {
        let den = dot(self.normal, d);
        if den.abs() < 1e-14 {
            return None;
        }
        let t = dot(self.normal, sub(self.origin, o)) / den;
        if t <= 1e-9 {
            return None;
        }
        let q = sub(add(o, scale(d, t)), self.origin);
        let (a, b) = (
            dot(q, self.eu) / dot(self.eu, self.eu),
            dot(q, self.ev) / dot(self.ev, self.ev),
        );
        ((0.0..=1.0).contains(&a) && (0.0..=1.0).contains(&b)).then_some((t, a, b))
    }
}

/// A sphere.
#[derive(Clone, Copy, Debug)]
pub struct Sphere {
    pub centre: V3,
    pub radius: f64,
}

impl Sphere {
    /// Nearest `t > 1e-7` where the ray `o + t d` (`d` unit) meets the sphere (the margin keeps
    /// a ray leaving the surface from meeting it again by rounding).
    pub fn hit(&self, o: V3, d: V3) -> Option<f64> {
        let oc = sub(o, self.centre);
        let b = dot(oc, d);
        let c = dot(oc, oc) - self.radius * self.radius;
        let disc = b * b - c;
        if disc < 0.0 {
            return None;
        }
        let s = disc.sqrt();
        [-b - s, -b + s].into_iter().find(|&t| t > 1e-7)
    }
    pub fn normal(&self, p: V3) -> V3 {
        unit(sub(p, self.centre))
    }
}

/// An axis-aligned box `[lo, hi]`: does the open segment `p -> q` pass through its interior
/// shrunk by `1e-7` (so points on its faces do not occlude themselves)?
pub fn segment_crosses_box(p: V3, q: V3, lo: V3, hi: V3) -> bool {
    let (mut t0, mut t1): (f64, f64) = (1e-9, 1.0 - 1e-9);
    for k in 0..3 {
        let (a, b) = (lo[k] + 1e-7, hi[k] - 1e-7);
        let d = q[k] - p[k];
        if d.abs() < 1e-15 {
            if p[k] <= a || p[k] >= b {
                return false;
            }
        } else {
            let (mut ta, mut tb) = ((a - p[k]) / d, (b - p[k]) / d);
            if ta > tb {
                std::mem::swap(&mut ta, &mut tb);
            }
            t0 = t0.max(ta);
            t1 = t1.min(tb);
            if t0 >= t1 {
                return false;
            }
        }
    }
    true
}

/// Deterministic uniform in [0, 1) (SplitMix64 of `seed`, `i`).
pub fn uniform(seed: u64, i: u64) -> f64 {
    let mut z = seed.wrapping_add(0x9E37_79B9_7F4A_7C15u64.wrapping_mul(i + 1));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}
