//! FISTA for `min_t 1/2 ||W^1/2 (A t - b)||^2 + lambda R(t)  s.t.  t >= 0`, with
//! `R(t) = ||Psi t||_1` ([`fista`]; `Psi` orthonormal, checked, or absent = pixel basis) or
//! `R(t) = TV(t)` ([`tv_fista`]; isotropic, the `D` of [`super::tv`]).
//!
//! * Non-negativity is handled EXACTLY inside the proximal step. The prox of
//!   `g(t) = gamma R(t) + i_{t >= 0}(t)` has no closed form for `Psi != I` (clipping
//!   `Psi^T soft(Psi v)` is not it: the test `nonnegative_prox_is_exact` shows its objective is
//!   4 % worse and the point 16 % away) nor for TV, so it is computed from its dual. Writing
//!   `R(t) = ||G t||` (`G = Psi`, or `G = D` with the `l_{2,1}` norm):
//!   `max_{u in gamma B} min_{t >= 0} 1/2 ||t - v||^2 + <G^T u, t>` (`B` = the unit box, or
//!   unit discs per pixel), whose inner minimiser is `t(u) = max(v - G^T u, 0)` and whose
//!   gradient is `G t(u)` (Lipschitz `||G||^2`: 1 for `Psi`, 8 for `D`). Projected gradient
//!   ascent `u <- proj(u + G t(u) / ||G||^2)`, warm-started from the previous outer iteration's
//!   `u`. Every primal candidate `t(u)` is feasible (`>= 0` by construction) and the duality gap
//!   `gamma ||G t(u)|| - <u, G t(u)>` bounds its distance to the exact prox:
//!   `||t(u) - prox(v)||^2 <= 2 gap`. The inner loop stops once the gap is below
//!   `min(1e-6 ||v||^2 / 2, 1e-2 ||t_k - t_{k-1}||^2)` (the prox error shrinks with the outer
//!   steps: inexact accelerated proximal gradient, Schmidt-Le Roux-Bach 2011) or after
//!   `MAX_INNER` iterations for TV, `MAX_INNER_ORTHO` in a transform (4x more after each
//!   step the inexact prox failed, see [`Prox::tighten`]). With `Psi = I` the prox is exact
//!   and closed-form: `max(v - gamma, 0)`.
//! * Step size: `L` starts at the power-iteration estimate of `||W^1/2 A||^2` (or the given
//!   one) and backtracks (Beck-Teboulle, `L <- 1.2 max(L, Rayleigh quotient)`) whenever the
//!   quadratic upper bound fails. For a quadratic data term the test is exact and needs no extra
//!   operator product: `||W^1/2 A (z - y)||^2 <= L ||z - y||^2`. Two operator products per
//!   iteration (`A z` and `A^T r`); `A y` follows from `A y = A z + beta (A z - A x)`.
//! * Restarts (O'Donoghue-Candes): gradient scheme (`<y - z, z - x> > 0`) and a function scheme
//!   that also rejects the step, which makes the accepted objective sequence non-increasing.
//! * 0/1 patterns: the iterations run on the mean-deflated problem ([`super::condition`]), then
//!   [`polish_exact`] finishes on the caller's exact objective.
//! * Stops when `||t_k - t_{k-1}|| <= tol ||t_k||` on 3 consecutive iterations, when a plain
//!   (momentum-free) step can no longer decrease the objective at working precision (stalled),
//!   or at `max_iter`. Cold start: 0 (l1), or the best constant image (TV): the `lambda_max`
//!   solutions.

use std::time::Instant;

use rayon::prelude::*;

use super::condition::Prepared;
use super::grid::{Grid, check_grid, gradient, lambda_max_tv, pair_norm};
use super::{
    History, Lambda, Solution, SolveOptions, SolveReport, StopReason, Ticker, check_orthonormal,
    check_problem, count_nonzeros, half_wsq, is_zero_data, lambda_without_solve, lipschitz_of,
    non_finite, relative_residual, zero_solution,
};
use crate::linop::{LinearOperator, dot, norm};
use crate::simd::avx2_dispatch;
use crate::{Control, ReconError};

/// `||A z - (A y)_recurrence||^2` below this fraction of `||A z||^2 + ||A y||^2` is rounding
/// (a relative difference of 1e-10, far above f64 rounding and far below any real step), not
/// evidence that the step-size constant `L` is too small.
const ROUNDING_SLACK: f64 = 1e-20;

/// Upper bound on the inner (dual) iterations of one TV prox. The dual state is kept between
/// outer iterations, so capped inner work still accumulates; measured (128x128 photo, TV): 1-3
/// inner iterations per outer one while the outer iterate moves, the cap binds near
/// convergence; 5 halves the time of 10 at the same PSNR (25.2 dB).
const MAX_INNER: usize = 5;

/// The same bound for the non-negative l1 prox in an orthonormal transform, whose inner
/// iteration costs two transforms (a Daubechies-4 pair on 128x128 takes ~0.24 ms, a DCT pair
/// ~0.35 ms, against ~1 ms for the two operator products of an outer iteration). Measured with
/// `examples/one` against a cap of 5, same code otherwise: `auto` on 128x128 Bernoulli rows at
/// 5 % (Poisson noise, where db4 wins) race 2.14 -> 1.27 s at 9.61 -> 9.63 dB; on the sparse
/// 256x256 target 8.3 -> 5.3 s at the same 30.34 dB; `cs` with the DCT on 128x128 Hadamard
/// rows 1.63 -> 0.49 s at the same 22.34 dB; the l1 candidates in the 128x128 Bernoulli photo's
/// race (which TV wins) 0.84 -> 0.65 s. A cap of 3 sat in between; 1 needed twice the outer
/// iterations. A step that fails still raises the cap ([`Prox::tighten`]).
const MAX_INNER_ORTHO: usize = 2;

/// `lambda_max` for the l1 problem: `|| Psi A^T W b ||_inf` — the smallest `lambda` for which
/// `t = 0` solves the problem without the non-negativity constraint. With `t >= 0` and
/// `Psi = I` the exact value `max(max_j (A^T W b)_j, 0)` is returned; with `t >= 0` and a
/// general `Psi` the value is an upper bound (any `lambda` at or above it gives `t = 0`).
pub fn lambda_max_l1(
    a: &dyn LinearOperator,
    psi: Option<&dyn LinearOperator>,
    b: &[f64],
    weights: Option<&[f64]>,
    nonnegative: bool,
) -> f64 {
    lambda_max_l1_free(a, psi, b, weights, nonnegative, 0)
}

/// [`lambda_max_l1`] when the first `free` coefficients of `Psi t` are not penalised
/// ([`SolveOptions::free_coefficients`]): the largest of the others.
pub fn lambda_max_l1_free(
    a: &dyn LinearOperator,
    psi: Option<&dyn LinearOperator>,
    b: &[f64],
    weights: Option<&[f64]>,
    nonnegative: bool,
    free: usize,
) -> f64 {
    let wb: Vec<f64> = match weights {
        None => b.to_vec(),
        Some(w) => b.iter().zip(w).map(|(b, w)| b * w).collect(),
    };
    let mut g = vec![0.0; a.cols()];
    a.adjoint(&wb, &mut g);
    match psi {
        None if nonnegative => g.iter().fold(0.0f64, |m, &v| m.max(v)),
        None => g.iter().fold(0.0f64, |m, &v| m.max(v.abs())),
        Some(psi) => {
            let mut s = vec![0.0; a.cols()];
            psi.apply(&g, &mut s);
            s.iter().skip(free).fold(0.0f64, |m, &v| m.max(v.abs()))
        }
    }
}

/// The regulariser `R(t) = ||G t||` of a proximal step: `G = I` (l1 of pixels), `G = Psi`
/// orthonormal (l1 of coefficients), or `G = D` (isotropic TV, `||.||_{2,1}`).
#[derive(Clone, Copy)]
pub(crate) enum Reg<'a> {
    /// `||t||_1`.
    Pixel,
    /// `sum_{j >= free} |(Psi t)_j|`: the first `free` coefficients (the DC term of a full
    /// wavelet or DCT decomposition) are not penalised.
    Ortho(&'a dyn LinearOperator, usize),
    Tv(Grid),
}

impl Reg<'_> {
    /// Length of `G t`.
    fn coeffs(&self, k: usize) -> usize {
        match self {
            Reg::Pixel => 0,
            Reg::Ortho(..) => k,
            Reg::Tv(_) => 2 * k,
        }
    }
    /// `R(t)`, leaving `G t` in `s` (resized as needed).
    pub(crate) fn value(&self, t: &[f64], s: &mut Vec<f64>) -> f64 {
        let k = t.len();
        match *self {
            Reg::Pixel => t.iter().map(|v| v.abs()).sum(),
            Reg::Ortho(psi, free) => {
                s.resize(k, 0.0);
                psi.apply(t, s);
                s.iter().skip(free).map(|v| v.abs()).sum()
            }
            Reg::Tv(grid) => {
                s.resize(2 * k, 0.0);
                gradient(t, grid, s);
                (0..k).map(|i| pair_norm(s[i], s[k + i])).sum()
            }
        }
    }
}

/// Proximal operator of `gamma R(t) (+ i_{t >= 0})`, with its dual state kept between calls
/// (warm start). Closed-form for `Pixel` and for `Ortho` without the constraint; otherwise the
/// dual projected-gradient iteration of the module docs (step `1 / ||G||^2`: 1 for `Psi`,
/// 1/8 for `D`; dual set: the box `|u_j| <= gamma`, or the pointwise discs `|p_i| <= gamma`).
pub(crate) struct Prox<'a> {
    reg: Reg<'a>,
    nonneg: bool,
    u: Vec<f64>,
    pub(crate) s: Vec<f64>,
    tmp: Vec<f64>,
    pub(crate) inner: usize,
    pub(crate) last_gap: f64,
    /// Inner-iteration cap per call: [`MAX_INNER`] (TV) or [`MAX_INNER_ORTHO`], raised by
    /// [`Prox::tighten`].
    cap: usize,
}

impl<'a> Prox<'a> {
    pub(crate) fn new(reg: Reg<'a>, nonneg: bool, k: usize) -> Self {
        let m = reg.coeffs(k);
        Prox {
            reg,
            nonneg,
            u: vec![0.0; m],
            s: vec![0.0; m],
            tmp: vec![0.0; k],
            inner: 0,
            last_gap: 0.0,
            cap: Self::base_cap(reg),
        }
    }

    /// The inner-iteration cap outside a retried step.
    fn base_cap(reg: Reg) -> usize {
        match reg {
            Reg::Tv(_) => MAX_INNER,
            _ => MAX_INNER_ORTHO,
        }
    }

    /// Lets the calls run 4x as many inner iterations until the next accepted step
    /// ([`Prox::relax`]). A tighter gap alone is not enough when the cap binds: the retried
    /// call would stop at the same cap, the step would fail again, and the solve would stop
    /// where it started (measured: a 256x256 Hadamard TV path point at f = 0.03 ended
    /// unchanged after four capped calls).
    pub(crate) fn tighten(&mut self) {
        self.cap *= 4;
    }

    /// Back to the base cap ([`MAX_INNER`], [`MAX_INNER_ORTHO`]) once a step is accepted: a
    /// raised cap kept for the whole solve made the path's first points ~30x slower (the cap
    /// binds on almost every call there).
    pub(crate) fn relax(&mut self) {
        self.cap = Self::base_cap(self.reg);
    }

    /// Whether the prox is computed iteratively (inexactly).
    pub(crate) fn inexact(&self) -> bool {
        match self.reg {
            Reg::Pixel => false,
            Reg::Ortho(..) => self.nonneg,
            Reg::Tv(_) => true,
        }
    }

    /// `out = argmin_t 1/2 ||t - v||^2 + gamma R(t) (+ t >= 0)`, to duality gap `eps` when
    /// iterative. Returns `R(out)` as computed (for the objective).
    pub(crate) fn apply(&mut self, v: &[f64], gamma: f64, eps: f64, out: &mut [f64]) -> f64 {
        match self.reg {
            Reg::Pixel => {
                if self.nonneg {
                    out.iter_mut()
                        .zip(v)
                        .for_each(|(o, &v)| *o = (v - gamma).max(0.0));
                } else {
                    out.iter_mut()
                        .zip(v)
                        .for_each(|(o, &v)| *o = soft(v, gamma));
                }
                out.iter().map(|v| v.abs()).sum()
            }
            Reg::Ortho(psi, free) if !self.nonneg => {
                psi.apply(v, &mut self.s);
                self.s
                    .iter_mut()
                    .skip(free)
                    .for_each(|c| *c = soft(*c, gamma));
                psi.adjoint(&self.s, out);
                self.s.iter().skip(free).map(|v| v.abs()).sum()
            }
            Reg::Ortho(psi, free) => {
                // Free coefficients have the dual box [0, 0].
                let free = free.min(self.u.len());
                self.u[..free].fill(0.0);
                self.u[free..]
                    .iter_mut()
                    .for_each(|u| *u = u.clamp(-gamma, gamma));
                let mut j = 0;
                loop {
                    psi.adjoint(&self.u, &mut self.tmp);
                    out.iter_mut()
                        .zip(v.iter().zip(&self.tmp))
                        .for_each(|(o, (&v, &pu))| *o = (v - pu).max(0.0));
                    psi.apply(out, &mut self.s);
                    let (mut l1, mut us, mut mag) = (0.0, 0.0, 0.0);
                    for (&s, &u) in self.s.iter().zip(&self.u).skip(free) {
                        l1 += s.abs();
                        us += u * s;
                        mag += (u * s).abs();
                    }
                    let gap = gamma * l1 - us;
                    j += 1;
                    self.inner += 1;
                    self.last_gap = gap;
                    // Stop at the requested gap, at rounding level, or at the cap.
                    if gap <= eps || gap <= 1e-13 * (gamma * l1 + mag) || j >= self.cap {
                        return l1;
                    }
                    self.u
                        .iter_mut()
                        .zip(&self.s)
                        .skip(free)
                        .for_each(|(u, &s)| *u = (*u + s).clamp(-gamma, gamma));
                }
            }
            Reg::Tv(grid) => {
                project_discs(&mut self.u, gamma);
                let mut j = 0;
                loop {
                    // out = clip(v - D^T u); then s = D out, the gap at u, and the ascent step
                    // u <- proj(u + s / 8) (the step is kept even when we stop: it only
                    // improves the next warm start), all in one pass ([`tv_prox_pass`]).
                    let (l1, us, mag) = tv_prox_pass(&mut self.u, v, grid, self.nonneg, gamma, out);
                    let gap = gamma * l1 - us;
                    j += 1;
                    self.inner += 1;
                    self.last_gap = gap;
                    if gap <= eps || gap <= 1e-13 * (gamma * l1 + mag) || j >= self.cap {
                        return l1;
                    }
                }
            }
        }
    }
}

/// Rows per band of the banded TV passes: about 4,096 pixels, so a band is worth a rayon task.
/// The split depends on the grid only, so the sums (taken band by band, in order) and hence
/// the results are the same whatever the number of threads.
fn band_rows(grid: Grid) -> usize {
    (4096 / grid.width.max(1)).clamp(1, grid.height.max(1))
}

/// One iteration of the TV prox in one pass over the rows: `out = clip(v - D^T u)`, then the
/// dual ascent step on `out` with the gap sums, computed row by row with a lag of one row
/// (row `y`'s ascent needs `out` rows `y` and `y + 1`, and `out` row `y + 1` needs the old `u`
/// of rows `y` and `y + 1`).
/// Bands of rows run in parallel; the dual rows a band reads across its edges are copied
/// before the pass, so every band sees the old `u` there. Same operations in the same order as
/// two separate passes (`primal_from_dual`, then `tv_dual_ascent`, kept as the tests'
/// reference): the same bits (tested), one parallel section and one sweep instead of two.
fn tv_prox_pass(
    u: &mut [f64],
    v: &[f64],
    grid: Grid,
    nonneg: bool,
    gamma: f64,
    out: &mut [f64],
) -> (f64, f64, f64) {
    let (w, h) = (grid.width, grid.height);
    let k = grid.pixels();
    let rows = band_rows(grid);
    let band = rows * w;
    let (ux, uy) = u.split_at_mut(k);
    // Per band: the old uy row above it, and the old ux, uy rows below it.
    let edges: Vec<(Vec<f64>, Vec<f64>)> = (0..h.div_ceil(rows))
        .map(|i| {
            let (y0, y1) = (i * rows, ((i + 1) * rows).min(h));
            let above = if y0 > 0 {
                uy[(y0 - 1) * w..y0 * w].to_vec()
            } else {
                Vec::new()
            };
            let below = if y1 < h {
                [&ux[y1 * w..(y1 + 1) * w], &uy[y1 * w..(y1 + 1) * w]].concat()
            } else {
                Vec::new()
            };
            (above, below)
        })
        .collect();
    let sums: Vec<[f64; 3]> = ux
        .par_chunks_mut(band)
        .zip(uy.par_chunks_mut(band))
        .zip(out.par_chunks_mut(band))
        .enumerate()
        .map(|(i, ((ux, uy), out))| {
            let (above, below) = &edges[i];
            tv_prox_band(ux, uy, v, grid, i * rows, nonneg, gamma, above, below, out)
        })
        .collect();
    sums.iter().fold((0.0, 0.0, 0.0), |acc, s| {
        (acc.0 + s[0], acc.1 + s[1], acc.2 + s[2])
    })
}

/// `o = v_row - (D^T u)_row` (clipped at 0 if `nonneg`) for one row: `uxr` its ux row,
/// `uy_this` its uy row (`None` on the last grid row), `uy_prev` the uy row above (`None` on the
/// first grid row).
#[inline(always)]
fn primal_row(
    vr: &[f64],
    uxr: &[f64],
    uy_this: Option<&[f64]>,
    uy_prev: Option<&[f64]>,
    nonneg: bool,
    o: &mut [f64],
) {
    let w = vr.len();
    o[..w - 1]
        .iter_mut()
        .zip(&vr[..w - 1])
        .zip(&uxr[..w - 1])
        .for_each(|((o, &v), &u)| *o = v + u);
    o[w - 1] = vr[w - 1];
    o[1..]
        .iter_mut()
        .zip(&uxr[..w - 1])
        .for_each(|(o, &u)| *o -= u);
    if let Some(uy) = uy_this {
        o.iter_mut().zip(uy).for_each(|(o, &u)| *o += u);
    }
    if let Some(uy) = uy_prev {
        o.iter_mut().zip(uy).for_each(|(o, &u)| *o -= u);
    }
    if nonneg {
        o.iter_mut().for_each(|o| *o = o.max(0.0));
    }
}

/// The dual ascent step and gap terms of one row (`row` = `t` on it, `next` = `t` on the row
/// below, or `row` itself on the last grid row), accumulated into `lanes` as in
/// [`tv_dual_ascent_band`].
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn ascent_row(
    uxr: &mut [f64],
    uyr: &mut [f64],
    row: &[f64],
    next: &[f64],
    gamma: f64,
    mags: &mut [f64],
    dots: &mut [f64],
    lanes: &mut [[f64; 4]; 3],
) {
    #[inline(always)]
    fn step(a: f64, b: f64, ux: &mut f64, uy: &mut f64, gamma: f64, mag: &mut f64, dot: &mut f64) {
        *dot = *ux * a + *uy * b;
        *mag = (a * a + b * b).sqrt();
        let (nx, ny) = (*ux + 0.125 * a, *uy + 0.125 * b);
        let f = (gamma / (nx * nx + ny * ny).sqrt()).min(1.0);
        *ux = nx * f;
        *uy = ny * f;
    }
    let w = row.len();
    let n = w - 1;
    let (right, left) = (&row[1..], &row[..n]);
    for x in 0..n {
        step(
            right[x] - left[x],
            next[x] - left[x],
            &mut uxr[x],
            &mut uyr[x],
            gamma,
            &mut mags[x],
            &mut dots[x],
        );
    }
    step(
        0.0,
        next[n] - row[n],
        &mut uxr[n],
        &mut uyr[n],
        gamma,
        &mut mags[n],
        &mut dots[n],
    );
    for (m, d) in mags.chunks_exact(4).zip(dots.chunks_exact(4)) {
        for l in 0..4 {
            lanes[0][l] += m[l];
            lanes[1][l] += d[l];
            lanes[2][l] += d[l].abs();
        }
    }
    for x in 4 * (w / 4)..w {
        lanes[0][x & 3] += mags[x];
        lanes[1][x & 3] += dots[x];
        lanes[2][x & 3] += dots[x].abs();
    }
}

avx2_dispatch! {
/// [`tv_prox_pass`] on the rows `y0..` of one band (`ux`, `uy`, `out`: the band's rows; `above`:
/// the old uy row above the band, `below`: the old ux and uy rows below it, empty at the grid's
/// edges).
#[allow(clippy::too_many_arguments)]
fn tv_prox_band(ux: &mut [f64], uy: &mut [f64], v: &[f64], grid: Grid, y0: usize, nonneg: bool, gamma: f64, above: &[f64], below: &[f64], out: &mut [f64]) -> [f64; 3] {
    let (w, h) = (grid.width, grid.height);
    let rows = ux.len() / w;
    let y1 = y0 + rows;
    let mut mags = vec![0.0; w];
    let mut dots = vec![0.0; w];
    let mut lanes = [[0.0f64; 4]; 3];
    for j in 0..rows {
        let y = y0 + j;
        {
            let uy_prev = if y == 0 { None } else if j == 0 { Some(above) } else { Some(&uy[(j - 1) * w..j * w]) };
            let uy_this = (y + 1 < h).then(|| &uy[j * w..(j + 1) * w]);
            primal_row(&v[y * w..(y + 1) * w], &ux[j * w..(j + 1) * w], uy_this, uy_prev, nonneg, &mut out[j * w..(j + 1) * w]);
        }
        if j > 0 {
            let (done, this) = out.split_at(j * w);
            ascent_row(&mut ux[(j - 1) * w..j * w], &mut uy[(j - 1) * w..j * w], &done[(j - 1) * w..], &this[..w], gamma, &mut mags, &mut dots, &mut lanes);
        }
    }
    let j = rows - 1;
    let row = &out[j * w..(j + 1) * w];
    if y1 < h {
        // The first row of the next band, from the old dual rows there.
        let (bx, by) = below.split_at(w);
        let mut halo = vec![0.0; w];
        primal_row(&v[y1 * w..(y1 + 1) * w], bx, (y1 + 1 < h).then_some(by), Some(&uy[j * w..(j + 1) * w]), nonneg, &mut halo);
        ascent_row(&mut ux[j * w..(j + 1) * w], &mut uy[j * w..(j + 1) * w], row, &halo, gamma, &mut mags, &mut dots, &mut lanes);
    } else {
        ascent_row(&mut ux[j * w..(j + 1) * w], &mut uy[j * w..(j + 1) * w], row, row, gamma, &mut mags, &mut dots, &mut lanes);
    }
    let sum = |l: &[f64; 4]| (l[0] + l[1]) + (l[2] + l[3]);
    [sum(&lanes[0]), sum(&lanes[1]), sum(&lanes[2])]
}
}

/// One dual ascent step of the TV prox, fused with the gradient of the primal point `t` and
/// the duality-gap sums: with `s = D t` (forward differences, Neumann), returns
/// `(sum_i |s_i|, <u, s>, sum_i |u_i . s_i|)` at the current `u`, then sets
/// `u <- proj_{|u_i| <= gamma}(u + s / 8)`. Bands of rows run in parallel.
#[cfg(test)]
fn tv_dual_ascent(u: &mut [f64], t: &[f64], grid: Grid, gamma: f64) -> (f64, f64, f64) {
    let w = grid.width;
    let band = band_rows(grid) * w;
    let (ux, uy) = u.split_at_mut(grid.pixels());
    let sums: Vec<[f64; 3]> = ux
        .par_chunks_mut(band)
        .zip(uy.par_chunks_mut(band))
        .enumerate()
        .map(|(i, (ux, uy))| tv_dual_ascent_band(ux, uy, t, grid, i * band / w, gamma))
        .collect();
    sums.iter().fold((0.0, 0.0, 0.0), |acc, s| {
        (acc.0 + s[0], acc.1 + s[1], acc.2 + s[2])
    })
}

avx2_dispatch! {
#[cfg(test)]
/// [`tv_dual_ascent`] on the rows `y0..` of one band (`ux`, `uy`: the band's dual values).
fn tv_dual_ascent_band(ux: &mut [f64], uy: &mut [f64], t: &[f64], grid: Grid, y0: usize, gamma: f64) -> [f64; 3] {
    let (w, h) = (grid.width, grid.height);
    // Per row, one pass without reductions (so LLVM vectorises the square roots and the
    // division) writes |s_i| and u_i . s_i; a second pass sums them on four partial sums
    // (pixel x on sum x & 3), which also breaks the floating-point dependency chains.
    let mut mags = vec![0.0; w];
    let mut dots = vec![0.0; w];
    let mut lanes = [[0.0f64; 4]; 3];
    #[inline(always)]
    fn step(a: f64, b: f64, ux: &mut f64, uy: &mut f64, gamma: f64, mag: &mut f64, dot: &mut f64) {
        *dot = *ux * a + *uy * b;
        *mag = (a * a + b * b).sqrt();
        let (nx, ny) = (*ux + 0.125 * a, *uy + 0.125 * b);
        // Branch-free (the disc test is data-dependent and mispredicts): gamma / 0 = inf -> 1.
        let f = (gamma / (nx * nx + ny * ny).sqrt()).min(1.0);
        *ux = nx * f;
        *uy = ny * f;
    }
    for (j, (uxr, uyr)) in ux.chunks_exact_mut(w).zip(uy.chunks_exact_mut(w)).enumerate() {
        let y = y0 + j;
        let r = y * w;
        let row = &t[r..r + w];
        let last = y + 1 == h;
        let next = if last { row } else { &t[r + w..r + 2 * w] };
        // b = next - row is 0 on the last row (next = row there); a = 0 on the last column.
        let n = w - 1;
        let (right, left) = (&row[1..], &row[..n]);
        for x in 0..n {
            step(right[x] - left[x], next[x] - left[x], &mut uxr[x], &mut uyr[x], gamma, &mut mags[x], &mut dots[x]);
        }
        step(0.0, next[n] - row[n], &mut uxr[n], &mut uyr[n], gamma, &mut mags[n], &mut dots[n]);
        for (m, d) in mags.chunks_exact(4).zip(dots.chunks_exact(4)) {
            for l in 0..4 {
                lanes[0][l] += m[l];
                lanes[1][l] += d[l];
                lanes[2][l] += d[l].abs();
            }
        }
        for x in 4 * (w / 4)..w {
            lanes[0][x & 3] += mags[x];
            lanes[1][x & 3] += dots[x];
            lanes[2][x & 3] += dots[x].abs();
        }
    }
    let sum = |l: &[f64; 4]| (l[0] + l[1]) + (l[2] + l[3]);
    [sum(&lanes[0]), sum(&lanes[1]), sum(&lanes[2])]
}
}

/// `out = v - D^T u`, clipped at 0 if `nonneg` (`D^T` as in `gradient_adjoint`); bands of rows
/// run in parallel.
#[cfg(test)]
fn primal_from_dual(u: &[f64], v: &[f64], grid: Grid, nonneg: bool, out: &mut [f64]) {
    let w = grid.width;
    let band = band_rows(grid) * w;
    out.par_chunks_mut(band)
        .enumerate()
        .for_each(|(i, o)| primal_from_dual_band(u, v, grid, nonneg, i * band / w, o));
}

avx2_dispatch! {
#[cfg(test)]
/// [`primal_from_dual`] on the rows `y0..` of one band (`out`: the band's pixels), in
/// branch-free passes.
fn primal_from_dual_band(u: &[f64], v: &[f64], grid: Grid, nonneg: bool, y0: usize, out: &mut [f64]) {
    let (w, h) = (grid.width, grid.height);
    let k = w * h;
    let (ux, uy) = u.split_at(k);
    for (j, o) in out.chunks_exact_mut(w).enumerate() {
        let y = y0 + j;
        let r = y * w;
        let vr = &v[r..r + w];
        let uxr = &ux[r..r + w];
        // D^T u = -div u, so v - D^T u = v + div u; div: +ux[x] (x < w-1), -ux[x-1] (x > 0),
        // +uy[y] (y < h-1), -uy[y-1] (y > 0).
        o[..w - 1].iter_mut().zip(&vr[..w - 1]).zip(&uxr[..w - 1]).for_each(|((o, &v), &u)| *o = v + u);
        o[w - 1] = vr[w - 1];
        o[1..].iter_mut().zip(&uxr[..w - 1]).for_each(|(o, &u)| *o -= u);
        if y + 1 < h {
            o.iter_mut().zip(&uy[r..r + w]).for_each(|(o, &u)| *o += u);
        }
        if y > 0 {
            o.iter_mut().zip(&uy[r - w..r]).for_each(|(o, &u)| *o -= u);
        }
        if nonneg {
            o.iter_mut().for_each(|o| *o = o.max(0.0));
        }
    }
}
}

avx2_dispatch! {
/// Projects each pixel's `(p_x, p_y)` (stored as `[p_x..., p_y...]`) onto the disc of radius `r`.
/// Branch-free, so it vectorises: the factor `min(1, r / |p|)` is 1 inside the disc (also at
/// `p = 0`, where `r / 0 = inf` or, for `r = 0`, NaN, which `min` ignores).
pub(crate) fn project_discs(p: &mut [f64], r: f64) {
    let k = p.len() / 2;
    let (px, py) = p.split_at_mut(k);
    for (x, y) in px.iter_mut().zip(py.iter_mut()) {
        let f = (r / pair_norm(*x, *y)).min(1.0);
        *x *= f;
        *y *= f;
    }
}
}

fn soft(v: f64, g: f64) -> f64 {
    if v > g {
        v - g
    } else if v < -g {
        v + g
    } else {
        0.0
    }
}

/// FISTA with exact non-negativity, backtracking and adaptive restart (see the module docs).
///
/// `psi`: orthonormal sparsifying transform (`k x k`; `apply` = analysis `Psi t`, `adjoint` =
/// synthesis), or `None` for sparsity in the pixel basis.
pub fn fista(
    a: &dyn LinearOperator,
    psi: Option<&dyn LinearOperator>,
    b: &[f64],
    opts: &SolveOptions,
    control: &Control,
) -> Result<Solution, ReconError> {
    let start = Instant::now();
    let (_, k) = check_problem(a, b, opts)?;
    if let Some(p) = psi {
        check_orthonormal(p, k)?;
    }
    let reg = match psi {
        None => Reg::Pixel,
        Some(p) => Reg::Ortho(p, opts.free_coefficients),
    };
    if is_zero_data(b, opts.weights.as_deref()) {
        return Ok(zero_solution(
            "fista",
            k,
            lambda_without_solve(opts.lambda),
            None,
            0.0,
            start,
        ));
    }
    let prep = Prepared::with_decision(
        a,
        b,
        opts.weights.as_deref(),
        opts.deflate_mean,
        opts.deflation,
    );
    let lambda_max = match opts.lambda {
        Lambda::Absolute(_) => None,
        Lambda::Relative(_) => Some(lambda_max_l1_free(
            prep.op(),
            psi,
            prep.b(),
            prep.weights(),
            opts.nonnegative,
            if psi.is_some() {
                opts.free_coefficients
            } else {
                0
            },
        )),
    };
    with_polish(&prep, a, b, reg, opts, control, lambda_max, "fista", start)
}

/// The TV problem of [`super::tv`] (`1/2 ||W^1/2 (A t - b)||^2 + lambda TV(t)`, `t >= 0`)
/// solved by FISTA with the exact non-negative TV prox (the dual iteration of the module docs on
/// `G = D`, warm-started): fewer iterations than the primal-dual method on our test problems.
pub fn tv_fista(
    a: &dyn LinearOperator,
    grid: Grid,
    b: &[f64],
    opts: &SolveOptions,
    control: &Control,
) -> Result<Solution, ReconError> {
    let start = Instant::now();
    let (_, k) = check_problem(a, b, opts)?;
    check_grid(grid, k)?;
    if is_zero_data(b, opts.weights.as_deref()) {
        return Ok(zero_solution(
            "tv-fista",
            k,
            lambda_without_solve(opts.lambda),
            None,
            0.0,
            start,
        ));
    }
    let prep = Prepared::with_decision(
        a,
        b,
        opts.weights.as_deref(),
        opts.deflate_mean,
        opts.deflation,
    );
    let lambda_max = match opts.lambda {
        Lambda::Absolute(_) => None,
        Lambda::Relative(_) => Some(lambda_max_tv(prep.op(), grid, prep.b(), prep.weights())),
    };
    with_polish(
        &prep,
        a,
        b,
        Reg::Tv(grid),
        opts,
        control,
        lambda_max,
        "tv-fista",
        start,
    )
}

/// Solves the prepared (possibly deflated) problem, then [`polish_exact`].
#[allow(clippy::too_many_arguments)]
fn with_polish(
    prep: &Prepared,
    a: &dyn LinearOperator,
    b: &[f64],
    reg: Reg,
    opts: &SolveOptions,
    control: &Control,
    lambda_max: Option<f64>,
    solver: &'static str,
    start: Instant,
) -> Result<Solution, ReconError> {
    let first = fista_core(prep, a, b, reg, opts, control, lambda_max, solver, start)?;
    polish_exact(first, prep, a, b, reg, opts, control, solver, start)
}

/// If the problem was mean-deflated, finishes with FISTA iterations on the caller's exact
/// objective, warm-started, with the same absolute lambda (the centred parts of the two data
/// terms are identical) and at most `max(20, max_iter / 5)` iterations. Deflation under-weights
/// the mean measurement: harmless for clean data (the polish stops after 3 iterations), but
/// with noise it lets the image mean drift (measured: x0.4 at 10 photons per pattern). On the
/// exact objective the mean is the stiffest direction, so it is corrected first.
#[allow(clippy::too_many_arguments)]
pub(crate) fn polish_exact(
    first: Solution,
    prep: &Prepared,
    a: &dyn LinearOperator,
    b: &[f64],
    reg: Reg,
    opts: &SolveOptions,
    control: &Control,
    solver: &'static str,
    start: Instant,
) -> Result<Solution, ReconError> {
    if !prep.is_deflated() {
        return Ok(first);
    }
    let exact = Prepared::new(a, b, opts.weights.as_deref(), false);
    let mut o = opts.clone();
    o.lambda = Lambda::Absolute(first.report.lambda);
    o.warm_start = Some(first.t.clone());
    o.lipschitz = Some(
        prep.decision()
            .undeflated_lipschitz(a.rows(), first.report.lipschitz),
    );
    o.max_iter = (opts.max_iter / 5).max(20).min(opts.max_iter);
    o.progress = (opts.progress.1, opts.progress.1);
    let mut second = fista_core(
        &exact,
        a,
        b,
        reg,
        &o,
        control,
        first.report.lambda_max,
        solver,
        start,
    )?;
    let r = &mut second.report;
    // The history stays that of the main (deflated) iterations: one objective throughout.
    r.objective_history = first.report.objective_history;
    r.history_stride = first.report.history_stride;
    r.polish_iterations = r.iterations;
    r.iterations += first.report.iterations;
    r.inner_iterations += first.report.inner_iterations;
    r.restarts += first.report.restarts;
    r.deflated = true;
    if first.report.stop != StopReason::Converged && r.stop == StopReason::Converged {
        r.stop = first.report.stop;
        r.converged = first.report.converged;
    }
    Ok(second)
}

avx2_dispatch! {
/// The FISTA iterations (compiled twice, see [`crate::simd`]: its vector updates are
/// most of the work besides the operator and the prox).
#[allow(clippy::too_many_arguments)]
fn fista_core(
    prep: &Prepared,
    original: &dyn LinearOperator,
    original_b: &[f64],
    reg: Reg,
    opts: &SolveOptions,
    control: &Control,
    lambda_max: Option<f64>,
    solver: &'static str,
    start: Instant,
) -> Result<Solution, ReconError> {
    let (a, b, w) = (prep.op(), prep.b(), prep.weights());
    let (n, k) = (a.rows(), a.cols());
    let lambda = match (opts.lambda, lambda_max) {
        (Lambda::Absolute(l), _) => l,
        (Lambda::Relative(f), m) => f * m.unwrap_or(0.0),
    };
    if !lambda.is_finite() {
        return Err(ReconError::Unsolvable(format!(
            "lambda is not finite ({lambda}): the operator or data overflow"
        )));
    }
    let mut lip = lipschitz_of(a, w, opts.lipschitz)?;
    if lip == 0.0 {
        return Err(ReconError::Unsolvable(
            "the measurement operator is zero (every pattern dark, or all weights zero): \
             nothing can be recovered"
                .into(),
        ));
    }

    // Work vectors, allocated once.
    let mut x = vec![0.0; k];
    let mut ax = vec![0.0; n];
    match &opts.warm_start {
        Some(t0) => {
            x.copy_from_slice(t0);
            if opts.nonnegative {
                x.iter_mut().for_each(|v| *v = v.max(0.0));
            }
            a.apply(&x, &mut ax);
        }
        None => {
            // Cold start at the lambda_max solution: 0, or for TV the best constant image.
            if let Reg::Tv(_) = reg {
                let c = best_constant(a, b, w, &mut ax);
                x.fill(c);
                ax.iter_mut().for_each(|v| *v *= c);
            }
        }
    }
    let mut y = x.clone();
    let mut z = vec![0.0; k];
    let mut v = vec![0.0; k];
    let mut grad = vec![0.0; k];
    let mut az = vec![0.0; n];
    let mut r = vec![0.0; n];
    let mut ay = ax.clone();
    let mut prox = Prox::new(reg, opts.nonnegative, k);
    let mut scratch = Vec::new();
    let resid = |ax: &[f64], r: &mut [f64]| {
        r.iter_mut()
            .zip(ax.iter().zip(b))
            .for_each(|(r, (a, b))| *r = a - b);
    };
    resid(&ax, &mut r);
    let mut fx = half_wsq(&r, w) + lambda * reg.value(&x, &mut scratch);
    if !fx.is_finite() {
        return Err(non_finite(solver, 0, "objective at the starting point"));
    }
    let mut history = History::new(opts.history);
    history.record(0, fx);

    let ticker = Ticker::new(control, opts);
    let mut theta = 1.0f64;
    let mut momentum = false;
    let mut restarts = 0usize;
    let mut last_dx2 = f64::INFINITY;
    let mut eps_factor = 1.0;
    let mut tightened = 0;
    let mut small_changes = 0;
    let mut retry = false;
    let mut iterations = 0usize;
    let mut stop = StopReason::MaxIter;

    for it in 1..=opts.max_iter {
        ticker.tick(it)?;
        iterations = it;
        // Gradient at y: A^T W (A y - b), unless y is the point of the previous iteration,
        // whose step was retried with a tighter prox (`grad` still holds its gradient).
        if !retry {
            r.iter_mut()
                .zip(ay.iter().zip(b))
                .for_each(|(r, (a, b))| *r = a - b);
            if let Some(w) = w {
                r.iter_mut().zip(w).for_each(|(r, w)| *r *= w);
            }
            a.adjoint(&r, &mut grad);
        }
        retry = false;

        // Proximal step with backtracking on L.
        let mut backtracks = 0;
        let rz = loop {
            let step = 1.0 / lip;
            v.iter_mut()
                .zip(y.iter().zip(&grad))
                .for_each(|(v, (y, g))| *v = y - step * g);
            let eps = eps_factor * (1e-6 * 0.5 * dot(&v, &v)).min(1e-2 * last_dx2);
            let rz = prox.apply(&v, lambda * step, eps, &mut z);
            a.apply(&z, &mut az);
            // Quadratic data term: f(z) <= f(y) + <grad, z - y> + L/2 ||z - y||^2 holds iff
            // ||W^1/2 A (z - y)||^2 <= L ||z - y||^2 (no cancellation, no extra product).
            let (mut dz2, mut da2) = (0.0, 0.0);
            for (z, y) in z.iter().zip(&y) {
                dz2 += (z - y) * (z - y);
            }
            match w {
                None => az
                    .iter()
                    .zip(&ay)
                    .for_each(|(p, q)| da2 += (p - q) * (p - q)),
                Some(w) => az
                    .iter()
                    .zip(&ay)
                    .zip(w)
                    .for_each(|((p, q), w)| da2 += w * (p - q) * (p - q)),
            }
            if !(da2.is_finite() && dz2.is_finite()) {
                return Err(non_finite(solver, it, "iterate"));
            }
            // `ay` comes from the momentum recurrence (or `c A 1` at the TV cold start), `az`
            // from a fresh product: they differ by rounding (measured up to ~1e-13 relative), so
            // below `slack` the test cannot tell a low L from rounding, and `z == y` (a prox
            // fixed point, e.g. TV's constant start on a constant scene) meets the bound
            // exactly. Without this, such steps drove L to infinity and the solve failed.
            let slack = ROUNDING_SLACK * (dot(&az, &az) + dot(&ay, &ay));
            if dz2 == 0.0 || da2 <= lip * dz2 * (1.0 + 1e-10) + slack {
                break rz;
            }
            backtracks += 1;
            if backtracks > 60 {
                return Err(ReconError::Unsolvable(format!(
                    "{solver}: the step-size search did not terminate (operator not linear?)"
                )));
            }
            lip = 1.2 * lip.max(da2 / dz2);
        };
        resid(&az, &mut r);
        let fz = half_wsq(&r, w) + lambda * rz;
        if !fz.is_finite() {
            return Err(non_finite(solver, it, "objective"));
        }

        if fz > fx {
            if momentum {
                // Function restart: reject z, restart from x without momentum.
                y.copy_from_slice(&x);
                ay.copy_from_slice(&ax);
                theta = 1.0;
                momentum = false;
                restarts += 1;
                history.record(it, fx);
                continue;
            }
            // A plain proximal-gradient step did not decrease F: exact arithmetic forbids this,
            // so we are at working precision, or the inexact prox needs to be tighter.
            if prox.inexact() && tightened < 3 {
                tightened += 1;
                eps_factor *= 1e-2;
                prox.tighten();
                retry = true;
                history.record(it, fx);
                continue;
            }
            stop = StopReason::Stalled;
            history.record(it, fx);
            break;
        }

        // Accept z. A tightened prox served one failed step: the next step starts afresh.
        prox.relax();
        tightened = 0;
        eps_factor = 1.0;
        // Gradient restart test and relative change.
        let (mut restart_dot, mut dx2) = (0.0, 0.0);
        for ((y, z), x) in y.iter().zip(&z).zip(&x) {
            restart_dot += (y - z) * (z - x);
            dx2 += (z - x) * (z - x);
        }
        let change = if dx2 == 0.0 {
            0.0
        } else {
            dx2.sqrt() / norm(&z).max(f64::MIN_POSITIVE)
        };
        last_dx2 = dx2;
        if restart_dot > 0.0 {
            restarts += 1;
            theta = 1.0;
            momentum = false;
            y.copy_from_slice(&z);
            ay.copy_from_slice(&az);
        } else {
            let theta_next = 0.5 * (1.0 + (1.0 + 4.0 * theta * theta).sqrt());
            let beta = (theta - 1.0) / theta_next;
            for ((y, z), x) in y.iter_mut().zip(&z).zip(&x) {
                *y = z + beta * (z - x);
            }
            for ((p, q), r) in ay.iter_mut().zip(&az).zip(&ax) {
                *p = q + beta * (q - r);
            }
            theta = theta_next;
            momentum = beta > 0.0;
        }
        std::mem::swap(&mut x, &mut z);
        std::mem::swap(&mut ax, &mut az);
        fx = fz;
        history.record(it, fx);
        if change <= opts.tol {
            small_changes += 1;
            if small_changes >= 3 || change == 0.0 {
                stop = StopReason::Converged;
                break;
            }
        } else {
            small_changes = 0;
        }
    }
    ticker.done();

    // Report.
    let (nonzeros, threshold) = match reg {
        Reg::Pixel => (count_nonzeros(&x, 0.0), 0.0),
        Reg::Ortho(..) => {
            reg.value(&x, &mut scratch);
            let thr = if opts.nonnegative { NONZERO_REL } else { 1e-10 };
            (count_nonzeros(&scratch, thr), thr)
        }
        Reg::Tv(_) => {
            reg.value(&x, &mut scratch);
            (count_tv_nonzeros(&x, &scratch), NONZERO_REL)
        }
    };
    let (objective_history, history_stride) = history.finish();
    Ok(Solution {
        report: SolveReport {
            solver,
            iterations,
            converged: matches!(stop, StopReason::Converged | StopReason::Stalled),
            stop,
            restarts,
            objective: fx,
            objective_history,
            history_stride,
            relative_residual: relative_residual(original, &x, original_b),
            seconds: start.elapsed().as_secs_f64(),
            nonzeros,
            nonzero_threshold: threshold,
            lambda,
            lambda_max,
            lipschitz: lip,
            inner_iterations: prox.inner,
            deflated: prep.is_deflated(),
            polish_iterations: 0,
        },
        t: x,
    })
}
}

/// `c = max(0, <A 1, W b> / ||W^1/2 A 1||^2)`, the best constant image; leaves `A 1` in `a1`.
pub(crate) fn best_constant(
    a: &dyn LinearOperator,
    b: &[f64],
    w: Option<&[f64]>,
    a1: &mut [f64],
) -> f64 {
    let ones = vec![1.0; a.cols()];
    a.apply(&ones, a1);
    let (mut eb, mut ee) = (0.0, 0.0);
    for (i, (&e, &b)) in a1.iter().zip(b).enumerate() {
        let wi = w.map_or(1.0, |w| w[i]);
        eb += wi * e * b;
        ee += wi * e * e;
    }
    let c = if ee > 0.0 { (eb / ee).max(0.0) } else { 0.0 };
    if c.is_finite() { c } else { 0.0 }
}

/// Pixels whose gradient magnitude exceeds `NONZERO_REL` times the largest pixel value (the
/// "jumps" a TV solution keeps); `g = D t`.
pub(crate) fn count_tv_nonzeros(t: &[f64], g: &[f64]) -> usize {
    let k = t.len();
    let scale = t.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if scale == 0.0 {
        return 0;
    }
    let thr = NONZERO_REL * scale;
    (0..k).filter(|&i| pair_norm(g[i], g[k + i]) > thr).count()
}

/// Coefficients below this fraction of the largest count as zero where the solver produces
/// only approximate zeros (iterative prox, primal-dual TV).
pub(crate) const NONZERO_REL: f64 = 1e-4;

#[cfg(test)]
mod simd_tests {
    use super::*;
    use crate::ops::HadamardOperator;
    use crate::simd::force_baseline;
    use crate::testutil::Rng;

    fn bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// The fused prox pass gives the bits of the two separate passes it replaces, on grids of
    /// one band and of several (band edges at every kind of row), with and without the clip.
    #[test]
    fn fused_prox_pass_matches_the_separate_passes_bit_for_bit() {
        let mut rng = Rng::new(11);
        for (w, h) in [
            (1usize, 1usize),
            (1, 9),
            (7, 1),
            (13, 7),
            (64, 64),
            (37, 130),
            (130, 70),
            (64, 200),
            (2048, 5),
        ] {
            let grid = Grid::new(w, h);
            let k = w * h;
            let v: Vec<f64> = (0..k).map(|_| rng.normal()).collect();
            let mut u0: Vec<f64> = (0..2 * k).map(|_| 0.1 * rng.normal()).collect();
            project_discs(&mut u0, 0.07);
            for nonneg in [true, false] {
                let (mut u1, mut u2) = (u0.clone(), u0.clone());
                let (mut o1, mut o2) = (vec![0.0; k], vec![0.0; k]);
                // Twice: the second pass starts from a dual the first one moved.
                for pass in 0..2 {
                    primal_from_dual(&u1, &v, grid, nonneg, &mut o1);
                    let s1 = tv_dual_ascent(&mut u1, &o1, grid, 0.07);
                    let s2 = tv_prox_pass(&mut u2, &v, grid, nonneg, 0.07, &mut o2);
                    assert!(
                        bits(&u1) == bits(&u2) && bits(&o1) == bits(&o2),
                        "{w}x{h} nonneg {nonneg} pass {pass}: fused pass differs"
                    );
                    assert_eq!(
                        [s1.0, s1.1, s1.2].map(f64::to_bits),
                        [s2.0, s2.1, s2.2].map(f64::to_bits),
                        "{w}x{h}: sums"
                    );
                }
                assert!(
                    bits(&u1) != bits(&u0) || k == 1,
                    "{w}x{h}: the passes moved the dual"
                );
            }
        }
    }

    /// The AVX2 and baseline copies of the dispatched loops give the same bits, kernel by kernel
    /// and through a whole TV solve (odd sizes exercise the tails of the vector loops). On a CPU
    /// without AVX2 both runs take the baseline copy and the test checks determinism only.
    #[test]
    fn avx2_and_baseline_copies_agree_bit_for_bit() {
        let mut rng = Rng::new(5);
        for (w, h) in [(1usize, 1usize), (3, 5), (13, 7), (64, 64), (37, 130)] {
            let grid = Grid::new(w, h);
            let k = w * h;
            let t: Vec<f64> = (0..k).map(|_| rng.uniform()).collect();
            let v: Vec<f64> = (0..k).map(|_| rng.normal()).collect();
            let u0: Vec<f64> = (0..2 * k).map(|_| 0.1 * rng.normal()).collect();
            let run = |baseline: bool| {
                force_baseline(baseline);
                let mut u = u0.clone();
                project_discs(&mut u, 0.05);
                let mut out = vec![0.0; k];
                let fused = tv_prox_pass(&mut u.clone(), &v, grid, true, 0.05, &mut out);
                let sums = tv_dual_ascent(&mut u, &t, grid, 0.05);
                let sums = (sums.0 + fused.0, sums.1 + fused.1, sums.2 + fused.2);
                let mut f = t.clone();
                f.resize(k.next_power_of_two(), 0.25);
                crate::fwht::fwht(&mut f);
                (
                    bits(&u),
                    bits(&out),
                    [sums.0.to_bits(), sums.1.to_bits(), sums.2.to_bits()],
                    bits(&f),
                )
            };
            let (wide, base) = (run(false), run(true));
            assert!(
                wide == base,
                "{w}x{h}: the AVX2 and baseline kernels differ"
            );
        }
        // A whole solve: TV on a 32x32 Hadamard subset.
        let spec = helmholtz_proto::PatternSpec::new(
            helmholtz_proto::Family::Hadamard {
                ordering: helmholtz_proto::HadamardOrdering::RussianDoll,
            },
            32,
            32,
            410,
            0,
        )
        .unwrap();
        let op = HadamardOperator::from_spec(&spec, 410).unwrap();
        let truth: Vec<f64> = (0..1024)
            .map(|i| {
                if (i % 32) > 10 && (i / 32) < 20 {
                    1.0
                } else {
                    0.2
                }
            })
            .collect();
        let mut b = vec![0.0; op.rows()];
        op.apply(&truth, &mut b);
        let opts = SolveOptions {
            lambda: Lambda::Relative(1e-3),
            max_iter: 60,
            ..SolveOptions::default()
        };
        let solve = |baseline: bool| {
            force_baseline(baseline);
            bits(
                &tv_fista(&op, Grid::new(32, 32), &b, &opts, &Control::new())
                    .unwrap()
                    .t,
            )
        };
        let (wide, base) = (solve(false), solve(true));
        force_baseline(false);
        assert!(
            wide == base,
            "a TV solve differs between the AVX2 and baseline copies"
        );
    }
}
