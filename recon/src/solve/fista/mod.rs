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
//!   step the inexact prox failed, see [`Prox::tighten`]; when no step from a warm start
//!   succeeds, once more from the dual that ended the warm start's solve,
//!   [`SolveOptions::warm_dual`]; with [`SolveOptions::accelerated_prox`] the calls at a raised
//!   cap run the accelerated dual iteration, FGP, which the heavy weights need). With `Psi = I`
//!   the prox is exact and closed-form: `max(v - gamma, 0)`.
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
//!
//! Layout: this module holds the outer iteration ([`fista`], [`tv_fista`], the polish on the
//! exact objective) and `lambda_max` of the l1 problem; [`prox`] the proximal operators and
//! their dual state; [`tv_prox`] the fused, banded pass of the TV prox (with the two separate
//! passes it replaces, kept as the tests' reference).

mod prox;
mod tv_prox;

#[cfg(test)]
mod simd_tests;

use std::time::Instant;

use super::condition::Prepared;
use super::grid::{Grid, check_grid, lambda_max_tv, pair_norm};
use super::{
    History, Lambda, Solution, SolveOptions, SolveReport, StopReason, Ticker, check_orthonormal,
    check_problem, count_nonzeros, half_wsq, is_zero_data, lambda_without_solve, lipschitz_of,
    non_finite, relative_residual, zero_solution,
};
use crate::linop::{LinearOperator, dot, norm};
use crate::simd::avx2_dispatch;
use crate::{Control, ReconError};

#[cfg(test)]
pub(crate) use self::prox::simplex_threshold_from;
pub(crate) use self::prox::{Prox, Reg, project_discs, simplex_threshold};

/// `||A z - (A y)_recurrence||^2` below this fraction of `||A z||^2 + ||A y||^2` is rounding
/// (a relative difference of 1e-10, far above f64 rounding and far below any real step), not
/// evidence that the step-size constant `L` is too small.
const ROUNDING_SLACK: f64 = 1e-20;

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
    o.warm_dual = first.dual.clone();
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
    let total = opts.total.filter(|_| opts.nonnegative);
    match &opts.warm_start {
        Some(t0) => {
            x.copy_from_slice(t0);
            if opts.nonnegative {
                x.iter_mut().for_each(|v| *v = v.max(0.0));
            }
            if let Some(s) = total {
                let tau = simplex_threshold(&x, s);
                x.iter_mut().for_each(|v| *v = (*v - tau).max(0.0));
            }
            a.apply(&x, &mut ax);
        }
        None if total.is_some() => {
            // Cold start on the held total: the flat image of that light.
            x.fill(total.unwrap_or(0.0).max(0.0) / k as f64);
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
    prox.accelerated = opts.accelerated_prox;
    prox.hold_total(total);
    // The warm dual is the fallback of a first step that fails (below): started from it
    // always, the first steps of a point next to its neighbour are tiny and the relative-change
    // rule stopped the point there (measured: noise-free 10 % Hadamard pairs of the smooth
    // scene, TV points from f = 0.003 on stopped after 4 iterations, 2.4 dB lost).
    let mut warm_dual = opts.warm_dual.as_deref();
    let mut accepted = 0usize;
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
            // The first step from the cold start (neither a warm start nor its dual given)
            // may tighten further ([`COLD_FIRST_TIGHTENINGS`]).
            let cold_first = accepted == 0
                && opts.warm_start.is_none()
                && opts.warm_dual.is_none()
                && tightened < COLD_FIRST_TIGHTENINGS
                && lambda < heaviest_useful(a, b, w, reg, opts);
            if prox.inexact() && (tightened < 3 || cold_first) {
                tightened += 1;
                eps_factor *= 1e-2;
                prox.tighten();
                retry = true;
                history.record(it, fx);
                continue;
            }
            // No step from the warm start was accepted: the prox's zero dual may be what fails
            // (from a structured image its capped calls return little of it). Once more from the
            // dual that ended the warm start's own solve, with two more tightenings (caps of
            // 1,280 and 5,120 inner iterations: on the test's 128x128 noisy Hadamard rows the
            // step from the warm dual succeeded at the first, its duality gap 45 against 145
            // at 320 and 2,200 from the zero dual at 320).
            if accepted == 0
                && let Some(dual) = warm_dual.take()
                && lambda < heaviest_useful(a, b, w, reg, opts)
            {
                prox.start_dual(dual, 1.0 / lip);
                tightened = 1;
                retry = true;
                history.record(it, fx);
                continue;
            }
            stop = StopReason::Stalled;
            history.record(it, fx);
            break;
        }

        // Accept z. A tightened prox served one failed step: the next step starts afresh.
        accepted += 1;
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
        dual: prox.dual(lip),
    })
}
}

/// Tightenings of the prox (each 4x the inner-iteration cap: up to 5,120 for TV) the first
/// step from the cold start may take before the solve is called stalled; other steps take 3
/// (the usual end at working precision, where more would only cost). From a zero dual at a
/// heavy weight the prox needs far more inner iterations than the usual caps allow (measured:
/// 30 dB Bernoulli buckets of a 128x128 photo, TV at 0.4 `lambda_max` from the flat image: gaps
/// 92, 16, 4.0, 1.1 at caps 5 to 320, every step rejected, the solve stalled on the flat image,
/// 12.82 dB, objective 8.4610e6; with these two it converges, as the primal-dual does). Warm
/// starts keep 3: there the extra calls mostly confirmed stalls at a cost (`auto`'s Bregman
/// step on 10 % Hadamard pairs of the text page: 0.05 -> 0.36 s, the same image), though a
/// solve warm-started short of a heavy-weight minimum stalls too (the `tv` method's fit on all
/// rows of that photo at 0.4, from its held-out fit: 13.46 dB against the minimum's 13.69).
const COLD_FIRST_TIGHTENINGS: usize = 5;

/// The weight at and above which the solution is the flat image (TV) or the empty model (l1,
/// its free coefficients aside): `lambda_max` of the problem [`fista_core`] iterates on. There
/// a warm start that no step can lower is the minimum, and the fallback to the warm dual would
/// only spend its inner iterations confirming it (measured: a refit at `f = 1` of noisy 10 %
/// Hadamard pairs of the text page, 0.03 s before the fallback, 0.45 s with it).
fn heaviest_useful(
    a: &dyn LinearOperator,
    b: &[f64],
    w: Option<&[f64]>,
    reg: Reg,
    opts: &SolveOptions,
) -> f64 {
    match reg {
        Reg::Pixel => lambda_max_l1(a, None, b, w, opts.nonnegative),
        Reg::Ortho(psi, free) => lambda_max_l1_free(a, Some(psi), b, w, opts.nonnegative, free),
        Reg::Tv(grid) => lambda_max_tv(a, grid, b, w),
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
