//! The pixel grid of the TV models and its geometry: forward differences `D` with Neumann
//! boundary ([`gradient`]), `D^T = -div` ([`gradient_adjoint`]), the isotropic TV and
//! `lambda_max` for TV.
//!
//! Shared by both TV solvers: the primal-dual [`super::tv`] and TV-FISTA in [`super::fista`]. The
//! dependencies go one way: `tv` -> `fista` (its result is polished by FISTA iterations) and both
//! -> `grid`; nothing here imports a solver.

use serde::Serialize;

use crate::ReconError;
use crate::linop::{LinearOperator, norm};

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
    let k = grid.pixels();
    (0..k).map(|i| pair_norm(g[i], g[k + i])).sum()
}

/// `lambda_max` for TV: the smallest `lambda` for which a constant image `c 1`
/// (`c = max(0, <A1, W b> / ||W^1/2 A 1||^2)`) solves the problem. Optimality needs
/// `g = A^T W (b - c A 1) = lambda D^T p` (up to a non-positive constant when `c = 0`) with
/// `|p_i| <= 1`; this returns `max_i |p_i|` for the least-squares certificate
/// `p = D (D^T D)^+ g` (a Neumann Poisson solve by conjugate gradients), an upper bound on
/// the exact value that is within a small factor of it.
pub fn lambda_max_tv(
    a: &dyn LinearOperator,
    grid: Grid,
    b: &[f64],
    weights: Option<&[f64]>,
) -> f64 {
    let (n, k) = (a.rows(), a.cols());
    if grid.pixels() != k || b.len() != n || k == 0 {
        return 0.0;
    }
    let ones = vec![1.0; k];
    let mut e = vec![0.0; n];
    a.apply(&ones, &mut e);
    let wt = |i: usize| weights.map_or(1.0, |w| w[i]);
    let (mut eb, mut ee) = (0.0, 0.0);
    for i in 0..n {
        eb += wt(i) * e[i] * b[i];
        ee += wt(i) * e[i] * e[i];
    }
    let c = if ee > 0.0 { (eb / ee).max(0.0) } else { 0.0 };
    let rho: Vec<f64> = (0..n).map(|i| wt(i) * (b[i] - c * e[i])).collect();
    let mut g = vec![0.0; k];
    a.adjoint(&rho, &mut g);
    let mean = g.iter().sum::<f64>() / k as f64;
    g.iter_mut().for_each(|v| *v -= mean);
    let gn = norm(&g);
    if !(gn > 0.0 && gn.is_finite()) {
        return 0.0;
    }
    // D^T D phi = g (consistent: g has zero mean), solved exactly: the Neumann Laplacian
    // D^T D is diagonal in the orthonormal DCT-II basis, eigenvalue
    // 4 sin^2(pi u / 2W) + 4 sin^2(pi v / 2H) at coefficient (v, u) (0 only for the mean).
    let (w, h) = (grid.width, grid.height);
    let dct = crate::transforms::Dct2d::new(w, h);
    let mut coef = vec![0.0; k];
    dct.apply(&g, &mut coef);
    let ex: Vec<f64> = (0..w)
        .map(|u| {
            4.0 * (std::f64::consts::PI * u as f64 / (2 * w) as f64)
                .sin()
                .powi(2)
        })
        .collect();
    for v in 0..h {
        let ey = 4.0
            * (std::f64::consts::PI * v as f64 / (2 * h) as f64)
                .sin()
                .powi(2);
        for u in 0..w {
            let lam = ex[u] + ey;
            let c = &mut coef[v * w + u];
            *c = if lam > 0.0 { *c / lam } else { 0.0 };
        }
    }
    let mut phi = vec![0.0; k];
    dct.adjoint(&coef, &mut phi);
    let mut dd = vec![0.0; 2 * k];
    gradient(&phi, grid, &mut dd);
    let m = (0..k)
        .map(|i| pair_norm(dd[i], dd[k + i]))
        .fold(0.0f64, f64::max);
    if m.is_finite() { m } else { 0.0 }
}

pub(crate) fn check_grid(grid: Grid, k: usize) -> Result<(), ReconError> {
    if grid.width == 0 || grid.height == 0 || grid.pixels() != k {
        return Err(ReconError::Unsolvable(format!(
            "grid {}x{} does not match the operator's {k} pixels",
            grid.width, grid.height
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linop::{dot, test_vector};

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
