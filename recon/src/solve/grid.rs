//! The pixel grid of the TV models and what the solvers need on it: `lambda_max` for TV and the
//! grid check. The grid itself, `D` ([`gradient`]), `D^T = -div` ([`gradient_adjoint`]) and the
//! isotropic TV live in [`crate::transforms::tv`], shared with the operator form
//! [`Gradient`](crate::transforms::Gradient); they are re-exported here.
//!
//! Shared by both TV solvers: the primal-dual [`super::tv`] and TV-FISTA in [`super::fista`]. The
//! dependencies go one way: `tv` -> `fista` (its result is polished by FISTA iterations) and both
//! -> `grid`; nothing here imports a solver.

use crate::ReconError;
use crate::linop::{LinearOperator, norm};

pub use crate::transforms::tv::{Grid, gradient_magnitudes, tv_value};
pub(crate) use crate::transforms::tv::{gradient, gradient_adjoint, pair_norm};

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
