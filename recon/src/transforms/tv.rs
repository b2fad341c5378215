//! Isotropic total variation pieces: the forward-difference gradient `D` and its adjoint `-div`.
//!
//! `D` maps a row-major `W x H` image `u` to `2k` values: first the horizontal differences
//! `gx[y W + x] = u[y][x + 1] - u[y][x]` (0 in the last column), then the vertical ones
//! `gy[y W + x] = u[y + 1][x] - u[y][x]` (0 in the last row): Neumann boundary (no flux out of
//! the image). `D^T = -div` with the matching boundary. `||D||^2 <= 8` (each difference operator
//! has norm <= 2; the bound is approached for large images), [`Gradient::NORM_SQ_BOUND`].
//!
//! Isotropic TV: `TV(u) = sum_p sqrt(gx_p^2 + gy_p^2)` ([`isotropic_tv`], [`Gradient::tv`]);
//! anisotropic: `sum |gx| + |gy|`.

use super::Transform;
use crate::linop::LinearOperator;

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Gradient {
    width: usize,
    height: usize,
}

impl Gradient {
    /// Upper bound of `||D||^2`, usable as the step-size constant of primal-dual methods.
    pub const NORM_SQ_BOUND: f64 = 8.0;

    pub fn new(width: usize, height: usize) -> Self {
        assert!(width > 0 && height > 0, "gradient needs a non-empty image");
        Gradient { width, height }
    }

    pub fn width(&self) -> usize {
        self.width
    }
    pub fn height(&self) -> usize {
        self.height
    }

    /// Isotropic TV of an image.
    pub fn tv(&self, u: &[f64]) -> f64 {
        let mut g = vec![0.0; 2 * u.len()];
        self.apply(u, &mut g);
        isotropic_tv(&g)
    }

    /// Anisotropic TV of an image.
    pub fn tv_anisotropic(&self, u: &[f64]) -> f64 {
        let mut g = vec![0.0; 2 * u.len()];
        self.apply(u, &mut g);
        g.iter().map(|v| v.abs()).sum()
    }
}

/// `sum_p sqrt(gx_p^2 + gy_p^2)` of a gradient laid out as [`Gradient`] produces (`gx` then `gy`).
pub fn isotropic_tv(g: &[f64]) -> f64 {
    let k = g.len() / 2;
    g[..k].iter().zip(&g[k..]).map(|(a, b)| a.hypot(*b)).sum()
}

impl LinearOperator for Gradient {
    fn rows(&self) -> usize {
        2 * self.width * self.height
    }
    fn cols(&self) -> usize {
        self.width * self.height
    }
    fn apply(&self, u: &[f64], g: &mut [f64]) {
        let (w, h) = (self.width, self.height);
        let k = w * h;
        assert_eq!(u.len(), k);
        assert_eq!(g.len(), 2 * k);
        let (gx, gy) = g.split_at_mut(k);
        for (row, out) in u.chunks_exact(w).zip(gx.chunks_exact_mut(w)) {
            for (o, pair) in out.iter_mut().zip(row.windows(2)) {
                *o = pair[1] - pair[0];
            }
            out[w - 1] = 0.0;
        }
        for y in 0..h - 1 {
            let (a, b) = (&u[y * w..(y + 1) * w], &u[(y + 1) * w..(y + 2) * w]);
            for ((o, &p), &q) in gy[y * w..(y + 1) * w].iter_mut().zip(a).zip(b) {
                *o = q - p;
            }
        }
        gy[(h - 1) * w..].fill(0.0);
    }
    fn adjoint(&self, g: &[f64], u: &mut [f64]) {
        let (w, h) = (self.width, self.height);
        let k = w * h;
        assert_eq!(g.len(), 2 * k);
        assert_eq!(u.len(), k);
        let (gx, gy) = g.split_at(k);
        // x part: u[x] = gx[x - 1] (x >= 1) - gx[x] (x < w - 1).
        for (row, p) in u.chunks_exact_mut(w).zip(gx.chunks_exact(w)) {
            row[0] = 0.0;
            row[1..].copy_from_slice(&p[..w - 1]);
            for x in 0..w - 1 {
                row[x] -= p[x];
            }
        }
        // y part.
        for y in 0..h {
            let row = &mut u[y * w..(y + 1) * w];
            if y >= 1 {
                for (o, &p) in row.iter_mut().zip(&gy[(y - 1) * w..y * w]) {
                    *o += p;
                }
            }
            if y + 1 < h {
                for (o, &p) in row.iter_mut().zip(&gy[y * w..(y + 1) * w]) {
                    *o -= p;
                }
            }
        }
    }
}

impl Transform for Gradient {
    fn name(&self) -> &'static str {
        "tv"
    }
    fn is_orthonormal(&self) -> bool {
        false
    }
}
