//! CGLS: `min_t ||W^1/2 (A t - b)||^2 + mu ||t||^2` (least squares, or Tikhonov with `mu > 0`).
//!
//! Conjugate gradients on the normal equations `(A^T W A + mu I) t = A^T W b` without forming
//! them (Hestenes-Stiefel / Bjorck's CGLS with shift, as in Paige & Saunders' comparison): the
//! residual `r = b - A t` is updated by recurrence and `s = A^T W r - mu t` is recomputed from it
//! every step (never from `A^T A`), which keeps the method stable. Two operator products per
//! iteration. From `t0 = 0` and `mu = 0` it converges to the minimum-norm least-squares solution
//! (the iterates stay in the row space of `A`).
//!
//! Unconstrained: the solution may have negative entries (clip if needed); this is the baseline
//! and the `n >= k` method, not the non-negative one. `opts.lambda` and `opts.nonnegative` are
//! ignored. Stops when `||s|| <= tol ||A^T W b||` (relative normal-equation residual).

use std::time::Instant;

use super::{
    History, Solution, SolveOptions, SolveReport, StopReason, Ticker, check_problem,
    count_nonzeros, is_zero_data, non_finite, ratio_or_abs, zero_solution,
};
use crate::recon::linop::{LinearOperator, dot, norm};
use crate::recon::{Control, ReconError};

pub fn cgls(
    a: &dyn LinearOperator,
    b: &[f64],
    mu: f64,
    opts: &SolveOptions,
    control: &Control,
) -> Result<Solution, ReconError> {
    const SOLVER: &str = "cgls";
    let start = Instant::now();
    let (n, k) = check_problem(a, b, opts)?;
    if !(mu.is_finite() && mu >= 0.0) {
        return Err(ReconError::Unsolvable(format!(
            "mu must be finite and >= 0, not {mu}"
        )));
    }
    let w = opts.weights.as_deref();
    let wmul = |v: &mut [f64]| {
        if let Some(w) = w {
            v.iter_mut().zip(w).for_each(|(v, w)| *v *= w);
        }
    };
    if is_zero_data(b, w) {
        return Ok(zero_solution(SOLVER, k, mu, None, 0.0, start));
    }

    let mut x = opts.warm_start.clone().unwrap_or_else(|| vec![0.0; k]);
    let mut r = vec![0.0; n];
    let mut wr = vec![0.0; n];
    let mut q = vec![0.0; n];
    let mut s = vec![0.0; k];
    // Reference: ||A^T W b||.
    wr.copy_from_slice(b);
    wmul(&mut wr);
    a.adjoint(&wr, &mut s);
    let ref_norm = norm(&s);
    if !ref_norm.is_finite() {
        return Err(non_finite(SOLVER, 0, "A^T b"));
    }
    if ref_norm == 0.0 {
        // b is orthogonal to the range: the (minimum-norm) solution is 0.
        let mut sol = zero_solution(SOLVER, k, mu, None, 0.0, start);
        sol.report.stop = StopReason::Converged;
        sol.report.relative_residual = 1.0;
        sol.report.objective = dot(&wr, b);
        return Ok(sol);
    }
    // r = b - A x, s = A^T W r - mu x.
    a.apply(&x, &mut q);
    r.iter_mut()
        .zip(b.iter().zip(&q))
        .for_each(|(r, (b, q))| *r = b - q);
    wr.copy_from_slice(&r);
    wmul(&mut wr);
    a.adjoint(&wr, &mut s);
    s.iter_mut().zip(&x).for_each(|(s, x)| *s -= mu * x);
    let mut p = s.clone();
    let mut gamma = dot(&s, &s);
    let objective = |r: &[f64], wr: &[f64], x: &[f64]| dot(r, wr) + mu * dot(x, x);
    let mut history = History::new(opts.history);
    history.record(0, objective(&r, &wr, &x));

    let ticker = Ticker::new(control, opts);
    let mut iterations = 0;
    let mut stop = StopReason::MaxIter;
    if gamma.sqrt() <= opts.tol * ref_norm {
        // The start already solves it.
        stop = StopReason::Converged;
    } else {
        for it in 1..=opts.max_iter {
            ticker.tick(it)?;
            iterations = it;
            a.apply(&p, &mut q);
            let qwq = match w {
                None => dot(&q, &q),
                Some(w) => q.iter().zip(w).map(|(q, w)| w * q * q).sum(),
            };
            let delta = qwq + mu * dot(&p, &p);
            if !delta.is_finite() {
                return Err(non_finite(SOLVER, it, "search direction"));
            }
            if delta <= 0.0 {
                // p is in the null space with mu = 0: no further progress is possible.
                stop = StopReason::Stalled;
                break;
            }
            let alpha = gamma / delta;
            x.iter_mut().zip(&p).for_each(|(x, p)| *x += alpha * p);
            r.iter_mut().zip(&q).for_each(|(r, q)| *r -= alpha * q);
            wr.copy_from_slice(&r);
            wmul(&mut wr);
            a.adjoint(&wr, &mut s);
            s.iter_mut().zip(&x).for_each(|(s, x)| *s -= mu * x);
            let gamma_new = dot(&s, &s);
            if !gamma_new.is_finite() {
                return Err(non_finite(SOLVER, it, "normal-equation residual"));
            }
            history.record(it, objective(&r, &wr, &x));
            if gamma_new.sqrt() <= opts.tol * ref_norm {
                stop = StopReason::Converged;
                break;
            }
            let beta = gamma_new / gamma;
            gamma = gamma_new;
            p.iter_mut().zip(&s).for_each(|(p, s)| *p = s + beta * *p);
        }
    }
    ticker.done();

    // Exact final residual (the recurrence drifts slightly).
    a.apply(&x, &mut q);
    r.iter_mut()
        .zip(b.iter().zip(&q))
        .for_each(|(r, (b, q))| *r = b - q);
    let rel = ratio_or_abs(norm(&r), norm(b));
    wr.copy_from_slice(&r);
    wmul(&mut wr);
    let obj = objective(&r, &wr, &x);
    if !obj.is_finite() || x.iter().any(|v| !v.is_finite()) {
        return Err(non_finite(SOLVER, iterations, "solution"));
    }
    let (objective_history, history_stride) = history.finish();
    Ok(Solution {
        report: SolveReport {
            solver: SOLVER,
            iterations,
            converged: matches!(stop, StopReason::Converged | StopReason::Stalled),
            stop,
            restarts: 0,
            objective: obj,
            objective_history,
            history_stride,
            relative_residual: rel,
            seconds: start.elapsed().as_secs_f64(),
            nonzeros: count_nonzeros(&x, 0.0),
            nonzero_threshold: 0.0,
            lambda: mu,
            lambda_max: None,
            lipschitz: 0.0,
            inner_iterations: 0,
            deflated: false,
            polish_iterations: 0,
        },
        t: x,
    })
}
