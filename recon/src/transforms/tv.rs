//! Isotropic total variation pieces on a pixel grid: the forward-difference gradient `D` and its
//! adjoint `-div`, the one implementation used by the TV solvers ([`crate::solve`]) and by the
//! operator form [`Gradient`].
//!
//! `D` maps a row-major `W x H` image `u` to `2k` values: first the horizontal differences
//! `gx[y W + x] = u[y][x + 1] - u[y][x]` (0 in the last column), then the vertical ones
//! `gy[y W + x] = u[y + 1][x] - u[y][x]` (0 in the last row): Neumann boundary (no flux out of
//! the image). `D^T = -div` with the matching boundary. `||D||^2 <= 8` (each difference operator
//! has norm <= 2; the bound is approached for large images), [`Gradient::NORM_SQ_BOUND`].
//!
//! Isotropic TV: `TV(u) = sum_p sqrt(gx_p^2 + gy_p^2)` ([`isotropic_tv`], [`tv_value`],
//! [`Gradient::tv`]); anisotropic: `sum |gx| + |gy|`.

use serde::Serialize;

use super::Transform;
use crate::linop::LinearOperator;

/// A `width x height` pixel grid; images are row-major (`index = y * width + x`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct Grid {
    pub width: usize,
    pub height: usize,
}

impl Grid {
    pub fn new(width: usize, height: usize) -> Self {
        Grid { width, height }
    }
    pub fn pixels(&self) -> usize {
        self.width * self.height
    }
}

/// `sqrt(x^2 + y^2)` (not `hypot`: 5x faster; intensities never reach 1e154).
#[inline]
pub(crate) fn pair_norm(x: f64, y: f64) -> f64 {
    (x * x + y * y).sqrt()
}

/// Forward differences, Neumann boundary: `g[..k] = D_x t`, `g[k..] = D_y t`.
pub(crate) fn gradient(t: &[f64], grid: Grid, g: &mut [f64]) {
    let (w, h) = (grid.width, grid.height);
    let k = w * h;
    let (gx, gy) = g.split_at_mut(k);
    for y in 0..h {
        let row = &t[y * w..(y + 1) * w];
        let gxr = &mut gx[y * w..(y + 1) * w];
        for x in 0..w - 1 {
            gxr[x] = row[x + 1] - row[x];
        }
        gxr[w - 1] = 0.0;
        let gyr = &mut gy[y * w..(y + 1) * w];
        if y + 1 < h {
            let next = &t[(y + 1) * w..(y + 2) * w];
            for x in 0..w {
                gyr[x] = next[x] - row[x];
            }
        } else {
            gyr.fill(0.0);
        }
    }
}

/// `D^T g = -div g` (adjoint of [`gradient`]); entries of `g` on the far boundary are ignored.
pub(crate) fn gradient_adjoint(g: &[f64], grid: Grid, out: &mut [f64]) {
    let (w, h) = (grid.width, grid.height);
    let k = w * h;
    let (gx, gy) = g.split_at(k);
    for y in 0..h {
        let o = &mut out[y * w..(y + 1) * w];
        let gxr = &gx[y * w..(y + 1) * w];
        o.fill(0.0);
        for x in 0..w - 1 {
            o[x] -= gxr[x];
            o[x + 1] += gxr[x];
        }
        if y + 1 < h {
            let gyr = &gy[y * w..(y + 1) * w];
            for x in 0..w {
                o[x] -= gyr[x];
            }
        }
        if y > 0 {
            let gyp = &gy[(y - 1) * w..y * w];
            for x in 0..w {
                o[x] += gyp[x];
            }
        }
    }
}

/// `|grad t|_i` per pixel (forward differences, Neumann): the terms of the isotropic TV.
pub fn gradient_magnitudes(t: &[f64], grid: Grid) -> Vec<f64> {
    let k = grid.pixels();
    let mut g = vec![0.0; 2 * k];
    gradient(t, grid, &mut g);
    (0..k).map(|i| pair_norm(g[i], g[k + i])).collect()
}

/// Isotropic total variation of `t`.
pub fn tv_value(t: &[f64], grid: Grid) -> f64 {
    let mut g = vec![0.0; 2 * grid.pixels()];
    gradient(t, grid, &mut g);
    isotropic_tv(&g)
}

/// `D` as an operator on `width x height` images ([`gradient`], [`gradient_adjoint`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Gradient {
    grid: Grid,
}

impl Gradient {
    /// Upper bound of `||D||^2`, usable as the step-size constant of primal-dual methods.
    pub const NORM_SQ_BOUND: f64 = 8.0;

    pub fn new(width: usize, height: usize) -> Self {
        assert!(width > 0 && height > 0, "gradient needs a non-empty image");
        Gradient {
            grid: Grid::new(width, height),
        }
    }

    pub fn width(&self) -> usize {
        self.grid.width
    }
    pub fn height(&self) -> usize {
        self.grid.height
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

/// `sum_p sqrt(gx_p^2 + gy_p^2)` of a gradient laid out as [`gradient`] produces (`gx` then `gy`).
pub fn isotropic_tv(g: &[f64]) -> f64 {
    let k = g.len() / 2;
    g[..k]
        .iter()
        .zip(&g[k..])
        .map(|(&a, &b)| pair_norm(a, b))
        .sum()
}

impl LinearOperator for Gradient {
    fn rows(&self) -> usize {
        2 * self.grid.pixels()
    }
    fn cols(&self) -> usize {
        self.grid.pixels()
    }
    fn apply(&self, u: &[f64], g: &mut [f64]) {
        let k = self.grid.pixels();
        assert_eq!(u.len(), k);
        assert_eq!(g.len(), 2 * k);
        gradient(u, self.grid, g);
    }
    fn adjoint(&self, g: &[f64], u: &mut [f64]) {
        let k = self.grid.pixels();
        assert_eq!(g.len(), 2 * k);
        assert_eq!(u.len(), k);
        gradient_adjoint(g, self.grid, u);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linop::{dot, norm, test_vector};

    #[test]
    fn gradient_adjoint_matches() {
        for &(w, h) in &[(1, 1), (1, 7), (5, 1), (4, 3), (17, 9)] {
            let grid = Grid::new(w, h);
            let k = w * h;
            let t = test_vector(k, 1);
            let p = test_vector(2 * k, 2);
            let mut g = vec![0.0; 2 * k];
            let mut dtp = vec![0.0; k];
            gradient(&t, grid, &mut g);
            gradient_adjoint(&p, grid, &mut dtp);
            // The far-boundary entries of p are ignored by D^T and D t is 0 there.
            let l = dot(&g, &p);
            let r = dot(&t, &dtp);
            assert!(
                (l - r).abs() <= 1e-12 * (l.abs() + r.abs() + 1.0),
                "{w}x{h}: {l} vs {r}"
            );
            // ||D||^2 <= 8 (power iteration).
            let mut x = test_vector(k, 3);
            let mut est = 0.0;
            for _ in 0..200 {
                let nx = norm(&x);
                x.iter_mut().for_each(|v| *v /= nx);
                gradient(&x, grid, &mut g);
                gradient_adjoint(&g, grid, &mut x);
                est = norm(&x);
            }
            assert!(est <= 8.0 + 1e-9, "{w}x{h}: ||D||^2 ~ {est}");
        }
        // Constant image: zero gradient; a step: TV = its length.
        let grid = Grid::new(6, 4);
        assert_eq!(tv_value(&[3.0; 24], grid), 0.0);
        let step: Vec<f64> = (0..24)
            .map(|i| if i % 6 >= 3 { 1.0 } else { 0.0 })
            .collect();
        assert!((tv_value(&step, grid) - 4.0).abs() < 1e-12);
    }
}
