//! Regularisation paths: `lambda = f * lambda_max` for decreasing fractions `f`, each solve
//! warm-started from the previous solution, `lambda_max` and the step-size constant computed
//! once (on the mean-deflated problem when deflation applies, as the solvers iterate on it).
//! Pure: the only side effect is progress on the [`Control`]. The `auto` method picks among the points (held-out error); nothing here chooses.

use std::time::Instant;

use super::condition::Prepared;
use super::grid::Grid;
use super::{
    Lambda, Solution, SolveOptions, SolveReport, check_problem, fista, is_zero_data, lambda_max_l1,
    lambda_max_l1_free, lambda_max_tv, lipschitz_of, tv, tv_fista, zero_solution,
};
use crate::linop::LinearOperator;
use crate::{Control, ReconError};

/// Which regulariser a path solves.
#[derive(Clone, Copy)]
pub enum Penalty<'a> {
    /// `lambda ||Psi t||_1` by [`fista`], `Psi` orthonormal or `None` (pixel basis).
    L1 { psi: Option<&'a dyn LinearOperator> },
    /// `lambda TV(t)` by [`tv_fista`] (the faster TV solver on our problems).
    Tv { grid: Grid },
    /// `lambda TV(t)` by the primal-dual [`tv`].
    TvPrimalDual { grid: Grid },
}

/// One point of a path.
#[derive(Clone, Debug)]
pub struct PathPoint {
    /// `lambda / lambda_max`.
    pub fraction: f64,
    pub lambda: f64,
    pub t: Vec<f64>,
    pub report: SolveReport,
    /// The prox's dual state at the end ([`super::Solution::dual`]): pass it with `t` to
    /// [`PathRunner::start_from`] to start a later point here.
    pub dual: Option<Vec<f64>>,
}

/// A solved path.
#[derive(Clone, Debug)]
pub struct RegPath {
    /// Of the problem actually solved (after deflation, if any).
    pub lambda_max: f64,
    pub deflated: bool,
    pub points: Vec<PathPoint>,
    pub seconds: f64,
}

/// `lambda_max` of the penalty ([`lambda_max_l1`] or [`lambda_max_tv`]) for `(A, b, W)` as given
/// (no deflation; [`solve_path`] reports the value for the problem it solves).
pub fn lambda_max(
    a: &dyn LinearOperator,
    penalty: Penalty,
    b: &[f64],
    weights: Option<&[f64]>,
    nonnegative: bool,
    free: usize,
) -> f64 {
    match penalty {
        Penalty::L1 { psi: Some(psi) } => {
            lambda_max_l1_free(a, Some(psi), b, weights, nonnegative, free)
        }
        Penalty::L1 { psi: None } => lambda_max_l1(a, None, b, weights, nonnegative),
        Penalty::Tv { grid } | Penalty::TvPrimalDual { grid } => lambda_max_tv(a, grid, b, weights),
    }
}

/// `count` fractions from 1 down to `min_ratio`, geometrically spaced (first 1, last
/// `min_ratio`). Empty if `count == 0` or `min_ratio` is not in `(0, 1]`.
pub fn geometric_fractions(count: usize, min_ratio: f64) -> Vec<f64> {
    if count == 0 || !(min_ratio > 0.0 && min_ratio <= 1.0) {
        return Vec::new();
    }
    if count == 1 {
        return vec![1.0];
    }
    let step = min_ratio.ln() / (count - 1) as f64;
    (0..count).map(|i| (step * i as f64).exp()).collect()
}

/// Solves the penalty at `lambda = f * lambda_max` for each of `fractions` in the given order
/// (pass them decreasing): point `i` starts from point `i - 1`'s solution (point 0 from
/// `opts.warm_start`). `opts.lambda` is ignored. Progress is split evenly over the points.
pub fn solve_path(
    a: &dyn LinearOperator,
    penalty: Penalty,
    b: &[f64],
    opts: &SolveOptions,
    fractions: &[f64],
    control: &Control,
) -> Result<RegPath, ReconError> {
    solve_path_until(a, penalty, b, opts, fractions, control, &mut |_| true)
}

/// [`solve_path`] that shows each point to `keep_going` as soon as it is solved and stops the
/// path when it returns `false` (e.g. once a held-out error has passed its minimum). The
/// returned path holds the points solved so far, the last one included.
pub fn solve_path_until(
    a: &dyn LinearOperator,
    penalty: Penalty,
    b: &[f64],
    opts: &SolveOptions,
    fractions: &[f64],
    control: &Control,
    keep_going: &mut dyn FnMut(&PathPoint) -> bool,
) -> Result<RegPath, ReconError> {
    let start = Instant::now();
    let mut runner = PathRunner::new(a, penalty, b, opts)?;
    let (lo, hi) = opts.progress;
    let m = fractions.len().max(1) as f64;
    let mut points: Vec<PathPoint> = Vec::with_capacity(fractions.len());
    for (i, &fraction) in fractions.iter().enumerate() {
        let progress = (
            lo + (hi - lo) * i as f64 / m,
            lo + (hi - lo) * (i + 1) as f64 / m,
        );
        let point = runner.solve(fraction, progress, control)?;
        let more = keep_going(&point);
        points.push(point);
        if !more {
            break;
        }
    }
    Ok(RegPath {
        lambda_max: runner.lambda_max(),
        deflated: runner.deflated(),
        points,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// A path solved one point at a time, so that callers can interleave several paths (`auto`
/// runs its candidates side by side and drops the clearly worse ones early). `lambda_max` and
/// the step-size constant are computed once, on the problem the solvers iterate on (deflated if
/// it applies); each point is a full solve (deflated iterations, then the polish on the exact
/// objective: the polish matters to anyone scoring the points, because the deflated problem
/// weighs the mean row less and a small error in the image mean moves every predicted bucket
/// by `mean error x pattern sum`) started from the previous point.
pub struct PathRunner<'a> {
    a: &'a dyn LinearOperator,
    penalty: Penalty<'a>,
    b: &'a [f64],
    opts: SolveOptions,
    lmax: f64,
    deflated: bool,
    zero: bool,
    k: usize,
    last: Option<Vec<f64>>,
    /// The dual state that goes with `last` ([`SolveOptions::warm_dual`]).
    last_dual: Option<Vec<f64>>,
}

impl<'a> PathRunner<'a> {
    pub fn new(
        a: &'a dyn LinearOperator,
        penalty: Penalty<'a>,
        b: &'a [f64],
        opts: &SolveOptions,
    ) -> Result<Self, ReconError> {
        let (_, k) = check_problem(a, b, opts)?;
        let mut o = opts.clone();
        if is_zero_data(b, opts.weights.as_deref()) {
            return Ok(PathRunner {
                a,
                penalty,
                b,
                opts: o,
                lmax: 0.0,
                deflated: false,
                zero: true,
                k,
                last: None,
                last_dual: None,
            });
        }
        let prep = Prepared::with_decision(
            a,
            b,
            opts.weights.as_deref(),
            opts.deflate_mean,
            opts.deflation,
        );
        let (op, bb, w) = (prep.op(), prep.b(), prep.weights());
        let lmax = lambda_max(op, penalty, bb, w, opts.nonnegative, opts.free_coefficients);
        o.lipschitz = Some(lipschitz_of(op, w, opts.lipschitz)?);
        // Every point solves the same operator with the same weights: detect once.
        o.deflation = Some(prep.decision());
        let last = opts.warm_start.clone();
        let last_dual = opts.warm_dual.clone();
        Ok(PathRunner {
            a,
            penalty,
            b,
            opts: o,
            lmax,
            deflated: prep.is_deflated(),
            zero: false,
            k,
            last,
            last_dual,
        })
    }

    /// Of the problem actually solved (after deflation, if any); 0 for all-zero data.
    pub fn lambda_max(&self) -> f64 {
        self.lmax
    }

    /// The next point starts from `t` instead of the previous point's solution, with the prox's
    /// dual state `dual` that ended the solve of `t` ([`PathPoint::dual`]; `None`: from zero).
    pub fn start_from(&mut self, t: Vec<f64>, dual: Option<Vec<f64>>) {
        self.last = Some(t);
        self.last_dual = dual;
    }

    /// Whether the solvers iterate on the deflated problem.
    pub fn deflated(&self) -> bool {
        self.deflated
    }

    /// Solves at `lambda = fraction * lambda_max`, warm-started from the previous point.
    pub fn solve(
        &mut self,
        fraction: f64,
        progress: (f64, f64),
        control: &Control,
    ) -> Result<PathPoint, ReconError> {
        if !(fraction.is_finite() && fraction >= 0.0) {
            return Err(ReconError::Unsolvable(format!(
                "path fraction {fraction} is not finite and >= 0"
            )));
        }
        if self.zero {
            let Solution { t, report, .. } =
                zero_solution("path", self.k, 0.0, Some(0.0), 0.0, Instant::now());
            return Ok(PathPoint {
                fraction,
                lambda: 0.0,
                t,
                report,
                dual: None,
            });
        }
        let lambda = fraction * self.lmax;
        let mut o = self.opts.clone();
        o.lambda = Lambda::Absolute(lambda);
        o.progress = progress;
        o.warm_start = self.last.take();
        o.warm_dual = self.last_dual.take();
        let (a, b) = (self.a, self.b);
        let Solution {
            t,
            mut report,
            dual,
        } = match self.penalty {
            Penalty::L1 { psi } => fista(a, psi, b, &o, control)?,
            Penalty::Tv { grid } => tv_fista(a, grid, b, &o, control)?,
            Penalty::TvPrimalDual { grid } => tv(a, grid, b, &o, control)?,
        };
        report.lambda_max = Some(self.lmax);
        self.last = Some(t.clone());
        self.last_dual = dual.clone();
        Ok(PathPoint {
            fraction,
            lambda,
            t,
            report,
            dual,
        })
    }
}
