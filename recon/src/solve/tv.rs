//! Isotropic TV with non-negativity by a primal-dual method (Chambolle-Pock / PDHG):
//!
//! `min_t 1/2 ||W^1/2 (A t - b)||^2 + lambda TV(t)  s.t.  t >= 0`,
//! `TV(t) = sum_i sqrt((D_x t)_i^2 + (D_y t)_i^2)` with forward differences and Neumann boundary
//! (the difference leaving the grid is 0), `t` row-major on a `width x height` grid.
//!
//! Saddle-point form with `K = [Ah; Dh]`, `Ah = W^1/2 A / a` (`a` = estimated `||W^1/2 A||`
//! times a 1.1 margin, so `||Ah|| <= 1`) and `Dh = D / sqrt(8)` (`||D||^2 <= 8`, so `||Dh|| <= 1`):
//! dividing the objective by `a^2` leaves `1/2 ||Ah t - bh||^2 + mu ||Dh t||_{2,1}` with
//! `bh = W^1/2 b / a`, `mu = lambda sqrt(8) / a^2`. Then `||K||^2 <= 2` and `tau sigma = 1/2`
//! satisfies the convergence condition `tau sigma ||K||^2 < 1` for any scaling of the problem.
//! Both dual proxes are closed-form (data: `q <- (q + sigma (Ah tbar - bh)) / (1 + sigma)`;
//! TV: projection onto the pointwise balls of radius `mu`); the primal prox is the clip to
//! `t >= 0`. Two operator products per iteration (`Ah tbar`, `Ah^T q`); `Ah t` and `Dh t` are
//! carried by the exact recursion `K t_{k+1} = (K tbar_{k+1} + K t_k) / 2`.
//!
//! Step ratio `tau / sigma` (`tau sigma = 1/2` fixed): the PDHG bound
//! `(||t0 - t*||^2 / tau + ||y0 - y*||^2 / sigma) / N` is smallest for
//! `tau / sigma = ||t0 - t*|| / ||y0 - y*||`, estimated scale-free as the RMS pixel value of the
//! start (or of the best constant image) over the radius `mu` of the TV dual discs (clamped to
//! [1e-6, 1e6]). Measured on a 64x64 photo from 10 % 0/1 patterns: 23 dB in 100 iterations
//! with this ratio, 16-20 dB with a ratio of 1 or with residual balancing (Goldstein et al.
//! 2015), which was dropped. Small `lambda` still needs many iterations (the problem becomes
//! ill-conditioned as `lambda -> 0`): [`super::tv_fista`] needs fewer there (128x128 photo,
//! 10 %, `lambda = 1e-3 lambda_max`, 200 iterations: 25.4 dB against 23.2 dB), and a
//! warm-started path (`solve_path`) helps both (4 x 50 iterations: 25.1 dB).
//!
//! Start: `t0` (clipped) or else the best constant image `c 1`, with the dual guesses
//! `q = Ah t0 - bh` (the optimal data dual for that `t`) and `p = mu Dh t0 / |Dh t0|` where the
//! gradient is nonzero. A dominant common mode of 0/1 rows is deflated first
//! ([`super::condition`]) and the result then polished on the exact objective by TV-FISTA
//! iterations (see `fista::polish_exact`).
//! Stops when `||t_k - t_{k-1}|| <= tol ||t_k||` on 3 consecutive iterations, or at `max_iter`.

use std::time::Instant;

use super::condition::Prepared;
use super::fista::{NONZERO_REL, Reg, count_tv_nonzeros, polish_exact, project_discs};
use super::grid::{Grid, check_grid, gradient, gradient_adjoint, lambda_max_tv, pair_norm};
use super::{
    History, Lambda, Solution, SolveOptions, SolveReport, StopReason, Ticker, check_problem,
    is_zero_data, lambda_without_solve, lipschitz_of, non_finite, relative_residual, zero_solution,
};
use crate::linop::{LinearOperator, dot, norm};
use crate::{Control, ReconError};

/// Margin on the power-iteration estimate of `||W^1/2 A||` (a lower bound).
const NORM_MARGIN: f64 = 1.1;

/// Primal-dual TV with `t >= 0` (see the module docs).
pub fn tv(
    a: &dyn LinearOperator,
    grid: Grid,
    b: &[f64],
    opts: &SolveOptions,
    control: &Control,
) -> Result<Solution, ReconError> {
    const SOLVER: &str = "tv-pdhg";
    let start = Instant::now();
    let (_, k) = check_problem(a, b, opts)?;
    check_grid(grid, k)?;
    if is_zero_data(b, opts.weights.as_deref()) {
        return Ok(zero_solution(
            SOLVER,
            k,
            lambda_without_solve(opts.lambda),
            None,
            0.0,
            start,
        ));
    }
    let (original, original_b) = (a, b);
    let prep = Prepared::with_decision(
        a,
        b,
        opts.weights.as_deref(),
        opts.deflate_mean,
        opts.deflation,
    );
    let (a, b, w) = (prep.op(), prep.b(), prep.weights());
    let n = a.rows();
    let (lambda, lambda_max) = match opts.lambda {
        Lambda::Absolute(l) => (l, None),
        Lambda::Relative(f) => {
            let m = lambda_max_tv(a, grid, b, w);
            (f * m, Some(m))
        }
    };
    if !lambda.is_finite() {
        return Err(ReconError::Unsolvable(format!(
            "lambda is not finite ({lambda}): the operator or data overflow"
        )));
    }
    let lip = lipschitz_of(a, w, opts.lipschitz)?;
    if lip == 0.0 {
        return Err(ReconError::Unsolvable(
            "the measurement operator is zero (every pattern dark, or all weights zero): \
             nothing can be recovered"
                .into(),
        ));
    }
    let anorm = lip.sqrt() * NORM_MARGIN;
    let inv = 1.0 / anorm;
    let dscale = 1.0 / 8f64.sqrt();
    let sw: Option<Vec<f64>> = w.map(|w| w.iter().map(|v| v.sqrt()).collect());
    let mu = lambda * 8f64.sqrt() / (anorm * anorm);
    let bh: Vec<f64> = match &sw {
        None => b.iter().map(|v| v * inv).collect(),
        Some(s) => b.iter().zip(s).map(|(v, s)| v * s * inv).collect(),
    };
    // Normalised operator Ah = W^1/2 A / a and its adjoint.
    let mut scratch_n = vec![0.0; n];
    let apply_h = |x: &[f64], y: &mut [f64]| {
        a.apply(x, y);
        match &sw {
            None => y.iter_mut().for_each(|v| *v *= inv),
            Some(s) => y.iter_mut().zip(s).for_each(|(v, s)| *v *= s * inv),
        }
    };
    let mut adjoint_h = |q: &[f64], x: &mut [f64]| {
        match &sw {
            None => scratch_n.iter_mut().zip(q).for_each(|(o, q)| *o = q * inv),
            Some(s) => scratch_n
                .iter_mut()
                .zip(q.iter().zip(s))
                .for_each(|(o, (q, s))| *o = q * s * inv),
        }
        a.adjoint(&scratch_n, x);
    };

    // Work vectors, allocated once.
    let mut t = vec![0.0; k];
    let mut at = vec![0.0; n];
    let t_scale = match &opts.warm_start {
        Some(t0) => {
            t.copy_from_slice(t0);
            if opts.nonnegative {
                t.iter_mut().for_each(|v| *v = v.max(0.0));
            }
            apply_h(&t, &mut at);
            norm(&t) / (k as f64).sqrt()
        }
        None => {
            // Cold start from the best constant image (the lambda_max solution).
            let ones = vec![1.0; k];
            apply_h(&ones, &mut at);
            let ee = dot(&at, &at);
            let c = if ee > 0.0 {
                (dot(&at, &bh) / ee).max(0.0)
            } else {
                0.0
            };
            let c = if c.is_finite() { c } else { 0.0 };
            t.fill(c);
            at.iter_mut().for_each(|v| *v *= c);
            c
        }
    };
    let mut t_old = vec![0.0; k];
    let mut tbar = vec![0.0; k];
    let mut kty = vec![0.0; k];
    let mut tmp_k = vec![0.0; k];
    let mut atbar = vec![0.0; n];
    let mut q = vec![0.0; n];
    let mut dt = vec![0.0; 2 * k];
    let mut dtbar = vec![0.0; 2 * k];
    let mut p = vec![0.0; 2 * k];
    gradient(&t, grid, &mut dt);
    dt.iter_mut().for_each(|v| *v *= dscale);
    q.iter_mut()
        .zip(at.iter().zip(&bh))
        .for_each(|(q, (a, b))| *q = a - b);
    if mu > 0.0 {
        for i in 0..k {
            let m = pair_norm(dt[i], dt[k + i]);
            if m > 0.0 {
                p[i] = mu * dt[i] / m;
                p[k + i] = mu * dt[k + i] / m;
            }
        }
    }
    let objective = |at: &[f64], dt: &[f64]| -> f64 {
        let data: f64 = at
            .iter()
            .zip(&bh)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>();
        let tvh: f64 = (0..k).map(|i| pair_norm(dt[i], dt[k + i])).sum();
        anorm * anorm * 0.5 * data + lambda * tvh / dscale
    };
    let mut fx = objective(&at, &dt);
    if !fx.is_finite() {
        return Err(non_finite(SOLVER, 0, "objective at the starting point"));
    }
    let mut history = History::new(opts.history);
    history.record(0, fx);

    // Step ratio tau / sigma = (primal scale) / (dual scale): the RMS pixel value over the
    // radius of the TV dual discs (or the RMS data residual when lambda = 0).
    let y_scale = if mu > 0.0 {
        mu
    } else {
        norm(&q) / (n as f64).sqrt()
    };
    let ratio = if t_scale > 0.0 && y_scale > 0.0 {
        (t_scale / y_scale).clamp(1e-6, 1e6)
    } else {
        1.0
    };
    let tau = (0.5 * ratio).sqrt();
    let sigma = (0.5 / ratio).sqrt();

    let ticker = Ticker::new(control, opts);
    let mut small_changes = 0;
    let mut iterations = 0;
    let mut stop = StopReason::MaxIter;
    let inv1 = 1.0 / (1.0 + sigma);
    for it in 1..=opts.max_iter {
        ticker.tick(it)?;
        iterations = it;
        // Primal step: t <- clip(t - tau K^T y), tbar = 2 t_new - t_old.
        adjoint_h(&q, &mut kty);
        gradient_adjoint(&p, grid, &mut tmp_k);
        kty.iter_mut()
            .zip(&tmp_k)
            .for_each(|(v, d)| *v += dscale * d);
        t_old.copy_from_slice(&t);
        if opts.nonnegative {
            t.iter_mut()
                .zip(&kty)
                .for_each(|(t, g)| *t = (*t - tau * g).max(0.0));
        } else {
            t.iter_mut().zip(&kty).for_each(|(t, g)| *t -= tau * g);
        }
        tbar.iter_mut()
            .zip(t.iter().zip(&t_old))
            .for_each(|(b, (n, o))| *b = 2.0 * n - o);

        // K tbar, and K t_new = (K tbar + K t_old) / 2 (exact recursion).
        apply_h(&tbar, &mut atbar);
        gradient(&tbar, grid, &mut dtbar);
        dtbar.iter_mut().for_each(|v| *v *= dscale);

        // Dual steps.
        for i in 0..n {
            q[i] = (q[i] + sigma * (atbar[i] - bh[i])) * inv1;
            at[i] = 0.5 * (atbar[i] + at[i]);
        }
        for i in 0..k {
            p[i] += sigma * dtbar[i];
            p[k + i] += sigma * dtbar[k + i];
            dt[i] = 0.5 * (dtbar[i] + dt[i]);
            dt[k + i] = 0.5 * (dtbar[k + i] + dt[k + i]);
        }
        project_discs(&mut p, mu);

        let d2: f64 = t.iter().zip(&t_old).map(|(a, b)| (a - b) * (a - b)).sum();
        fx = objective(&at, &dt);
        if !(fx.is_finite() && d2.is_finite()) {
            return Err(non_finite(SOLVER, it, "iterate"));
        }
        history.record(it, fx);
        let change = if d2 == 0.0 {
            0.0
        } else {
            d2.sqrt() / norm(&t).max(f64::MIN_POSITIVE)
        };
        if change <= opts.tol {
            small_changes += 1;
            if small_changes >= 3 {
                stop = StopReason::Converged;
                break;
            }
        } else {
            small_changes = 0;
        }
    }
    ticker.done();

    // Exact final figures (the carried A t, D t are recursions).
    let mut at_exact = vec![0.0; n];
    a.apply(&t, &mut at_exact);
    let mut r: Vec<f64> = at_exact.iter().zip(b).map(|(a, b)| a - b).collect();
    if let Some(w) = w {
        r.iter_mut().zip(w).for_each(|(r, w)| *r *= w.sqrt());
    }
    let mut g = vec![0.0; 2 * k];
    gradient(&t, grid, &mut g);
    let tv_t: f64 = (0..k).map(|i| pair_norm(g[i], g[k + i])).sum();
    let objective = 0.5 * dot(&r, &r) + lambda * tv_t;
    if !objective.is_finite() {
        return Err(non_finite(SOLVER, iterations, "final objective"));
    }
    let (objective_history, history_stride) = history.finish();
    let first = Solution {
        report: SolveReport {
            solver: SOLVER,
            iterations,
            converged: stop == StopReason::Converged,
            stop,
            restarts: 0,
            objective,
            objective_history,
            history_stride,
            relative_residual: relative_residual(original, &t, original_b),
            seconds: start.elapsed().as_secs_f64(),
            nonzeros: count_tv_nonzeros(&t, &g),
            nonzero_threshold: NONZERO_REL,
            lambda,
            lambda_max,
            lipschitz: lip,
            inner_iterations: 0,
            deflated: prep.is_deflated(),
            polish_iterations: 0,
        },
        t,
        dual: None,
    };
    polish_exact(
        first,
        &prep,
        original,
        original_b,
        Reg::Tv(grid),
        opts,
        control,
        SOLVER,
        start,
    )
}
