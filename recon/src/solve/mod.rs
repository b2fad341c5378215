//! Solvers for the compressive dual image: FISTA (l1 in an orthonormal transform or the pixel
//! basis, `t >= 0`), TV with `t >= 0` (primal-dual [`tv`] and accelerated [`tv_fista`]), CGLS
//! (least squares / Tikhonov), penalised Poisson ML by IRLS, and a warm-started
//! regularisation path.
//!
//! Every solver is generic over [`LinearOperator`] (`A`: n x k, rows = patterns, cols = pixels),
//! plans once (all work vectors are allocated before the first iteration), checks
//! [`Control::is_cancelled`] every iteration, and never returns NaN or infinity: inputs are
//! validated up front (clear [`ReconError::Unsolvable`] / [`ReconError::BadRows`]) and a
//! non-finite objective during the iterations stops the solve with [`ReconError::Unsolvable`].
//! `b = 0` (an all-dark scene) returns `t = 0` exactly.
//!
//! No hand-tuned step sizes: FISTA starts from `||W^1/2 A||^2` estimated by power iteration
//! ([`spectral_norm`]) and backtracks (Beck-Teboulle) if the estimate is low; the primal-dual TV
//! normalises `A` by its estimated norm and `D` by `sqrt(8)` and sets the primal/dual step ratio
//! from the problem's own scales. The regularisation weight is given either absolutely or as a
//! fraction of `lambda_max` ([`Lambda::Relative`]), which makes the defaults invariant to the
//! scaling of `A`, `b` and the weights: scaling `A` and `b` by `c` gives the same solution in
//! the same number of iterations (tested for 1e3 and 1e-3).
//!
//! Data term with per-row weights (`SolveOptions::weights`, `w_i >= 0`):
//! `1/2 ||W^1/2 (A t - b)||^2`. For Poisson (photon-counting) data the weights
//! `1 / max((A t)_i, floor)` make it the second-order approximation of the Poisson negative
//! log-likelihood, and [`poisson_irls`] re-solves with weights from the model until the fixed
//! point, which is the penalised Poisson ML estimate (`poisson.rs` explains why weights from the
//! raw counts are biased). Every solver here but CGLS keeps `t >= 0` exactly (FISTA and TV
//! prox/project onto the orthant every iteration), so photon-starved data never yields a
//! negative intensity.
//!
//! 0/1 patterns: a dominant common mode of the rows is deflated before iterating
//! ([`condition`], `SolveOptions::deflate_mean`), so first-order solvers converge in tens to
//! hundreds of iterations instead of thousands; a short polish on the exact objective follows.

use std::time::Instant;

use serde::Serialize;

use super::linop::{LinearOperator, dot, norm, spectral_norm, test_vector};
use super::{Control, ReconError};

mod cgls;
pub mod condition;
mod fista;
mod grid;
mod path;
mod poisson;
mod tv;

#[cfg(test)]
pub(crate) mod testkit;
#[cfg(test)]
mod tests;

pub use cgls::cgls;
pub use condition::{Deflation, MeanDeflated};
pub use fista::{fista, lambda_max_l1, lambda_max_l1_free, tv_fista};
pub use grid::{Grid, gradient_magnitudes, lambda_max_tv, tv_value};
pub use path::{
    PathPoint, PathRunner, Penalty, RegPath, geometric_fractions, lambda_max, solve_path,
    solve_path_until,
};
pub use poisson::{poisson_irls, poisson_weights};
pub use tv::tv;

/// The regularisation weight.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(rename_all = "snake_case", tag = "kind", content = "value")]
pub enum Lambda {
    /// `lambda` as is (units: objective per unit of `||Psi t||_1` or `TV(t)`).
    Absolute(f64),
    /// A fraction of `lambda_max` for this problem ([`lambda_max_l1`], [`lambda_max_tv`]):
    /// scale-free, the default.
    Relative(f64),
}

/// What every iterative solver takes. `Default` is a sensible starting point for any scaling.
#[derive(Clone, Debug)]
pub struct SolveOptions {
    /// Upper bound on iterations (FISTA / PDHG / CG steps).
    pub max_iter: usize,
    /// Stop when the relative change of the iterate `||t_k - t_{k-1}|| / ||t_k||` falls below
    /// this (CGLS: when `||A^T r|| <= tol ||A^T b||`, or `tol ||A'^T b'||` of the mean-deflated
    /// problem when `deflate_mean` applies; see `cgls.rs`).
    pub tol: f64,
    /// Regularisation weight (ignored by CGLS, which takes `mu` as an argument).
    pub lambda: Lambda,
    /// Initial iterate (length `cols`); FISTA and TV clip it to `t >= 0`.
    pub warm_start: Option<Vec<f64>>,
    /// Per-row data weights `w_i >= 0` (length `rows`); `None` = all ones.
    pub weights: Option<Vec<f64>>,
    /// Enforce `t >= 0` (FISTA, TV). Light transport is never negative: default `true`.
    pub nonnegative: bool,
    /// `||W^1/2 A||_2^2` of the operator the solver iterates on (the mean-deflated one when
    /// deflation applies) if already known, as [`solve_path`] passes it; `None` = estimate it.
    /// FISTA backtracks from an underestimate; the primal-dual TV relies on it (10 % margin).
    pub lipschitz: Option<f64>,
    /// At most this many objective values are kept in the report (decimated by 2 as needed).
    pub history: usize,
    /// Progress is reported to the [`Control`] mapped into this range (a path splits [0, 1]).
    pub progress: (f64, f64),
    /// FISTA / TV: deflate a dominant common mode of the rows (0/1 patterns) before iterating
    /// ([`condition::MeanDeflated`]; a no-op for centred operators). CGLS iterates on the exact
    /// problem and uses the deflated problem only as its stopping yardstick. Default `true`.
    pub deflate_mean: bool,
    /// The deflation decision for this operator and these weights if already made
    /// ([`solve_path`] passes its own to every point); `None` = detect it (when
    /// `deflate_mean`). Must come from the same operator and weights.
    pub deflation: Option<condition::Deflation>,
    /// FISTA with `Psi`: the first this many coefficients of `Psi t` are left out of the l1
    /// penalty and of `lambda_max`. 1 for a full wavelet or DCT decomposition leaves the DC term
    /// (the image mean) unshrunk: it dwarfs every detail coefficient of a natural scene, so
    /// penalising it sets `lambda_max` by the mean, not by the detail. Default 0.
    pub free_coefficients: usize,
    /// FISTA / TV-FISTA: the proximal map's dual state where an earlier solve of the same
    /// operator and regulariser ended ([`Solution::dual`]), passed with that solve's image as
    /// `warm_start`. The iterative prox (TV, or non-negative l1 in a transform) starts from a
    /// zero dual; when no step from the warm start lowers the objective even with the tightest
    /// prox, it tries once more from this dual (which reproduces the warm start) before calling
    /// the point stalled. From a zero dual the capped calls return little of a structured image,
    /// and a path point next to its neighbour stopped there with the neighbour's image unchanged
    /// (measured: 10 % of the 128x128 photo's Hadamard pairs at 30 dB, the TV points at
    /// `f = 0.3` from the flat image and at `f = 0.17` from the `f = 0.1` one, 4 iterations
    /// each; `auto` chose by their stale scores and lost 1.1 dB). Ignored when its length does
    /// not match the regulariser's dual.
    pub warm_dual: Option<Vec<f64>>,
    /// TV-FISTA: a prox call whose inner-iteration cap was raised after a failed step runs the
    /// accelerated dual iteration (FGP) instead of the plain one. At heavy weights the plain
    /// iteration cannot make the prox exact enough for any step to be accepted, and the solve
    /// stalls short of its minimum (measured: 30 dB Bernoulli buckets of a 128x128 photo, the
    /// `tv` method at 0.4 `lambda_max`: fit on all rows stalled at objective 8.4186e6, 13.46 dB;
    /// with this 8.4056e6, the primal-dual solver's minimum, 13.66 dB). At light weights the cap
    /// is rarely raised and the images are the same. The fixed-weight `tv` method sets it; the
    /// default (`false`) keeps the plain iteration, which `auto`'s screening solves use
    /// (measured on 90 problems, 15 scenes x both families x no noise / 30 dB / Poisson: the
    /// same PSNR to 0.1 dB on 80, up to 0.4 dB lower on 4, 1.2 dB higher on 1; 10-100 % slower).
    pub accelerated_prox: bool,
    /// FISTA / TV-FISTA with `nonnegative`: hold `sum t = total` (every prox projects onto the
    /// scaled simplex, and the start is projected there). For designs with a row that measures
    /// the image's total with the others orthogonal to it (Hadamard pairs with the all-on
    /// pair, [`crate::compressive`]): at light weights the fit to noisy coefficients needs
    /// negative pixels, the constraint clips them, and the total rises to pay for it
    /// (measured: a nearly dark 32x32 scene from 300 pairs at 10 dB, `tv` 2.4 times the
    /// scene's light). `None` (the default): no such constraint.
    pub total: Option<f64>,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            max_iter: 500,
            tol: 1e-4,
            lambda: Lambda::Relative(1e-3),
            warm_start: None,
            weights: None,
            nonnegative: true,
            lipschitz: None,
            history: 256,
            progress: (0.0, 1.0),
            deflate_mean: true,
            deflation: None,
            free_coefficients: 0,
            warm_dual: None,
            accelerated_prox: false,
            total: None,
        }
    }
}

/// Why a solver stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    /// The stopping rule (relative change / normal-equation residual) was met.
    Converged,
    /// No further decrease of the objective is possible at working precision.
    Stalled,
    /// `max_iter` reached before the stopping rule.
    MaxIter,
    /// `b = 0` (all-dark scene): `t = 0` is an exact minimiser, returned without iterating.
    ZeroData,
}

/// What a solve reports (JSON-ready; every number finite).
#[derive(Clone, Debug, Serialize)]
pub struct SolveReport {
    pub solver: &'static str,
    pub iterations: usize,
    pub converged: bool,
    pub stop: StopReason,
    /// Momentum restarts (FISTA: gradient or function scheme); 0 for other solvers.
    pub restarts: usize,
    /// Final objective of the caller's problem (FISTA/TV: `1/2||W^1/2(At-b)||^2 + lambda R(t)`;
    /// CGLS: `||W^1/2(At-b)||^2 + mu ||t||^2`).
    pub objective: f64,
    /// Objective at iterations `0, stride, 2 stride, ...` (0 = the starting point) of the main
    /// iterations (of the mean-deflated objective when `deflated`; the polish is not included).
    /// FISTA's is non-increasing.
    pub objective_history: Vec<f64>,
    pub history_stride: usize,
    /// `||A t - b|| / ||b||` (unweighted; absolute if `b = 0`).
    pub relative_residual: f64,
    pub seconds: f64,
    /// The model size. FISTA: nonzero coefficients of `Psi t` (or of `t`); TV: pixels with a
    /// nonzero gradient magnitude `|grad t|_i` (the jumps kept); CGLS: nonzero pixels. Exact
    /// zeros where the solver produces them exactly (closed-form prox: pixel basis, CGLS);
    /// otherwise entries above `nonzero_threshold` times the largest coefficient (FISTA with
    /// `Psi`) or the largest pixel value (TV).
    pub nonzeros: usize,
    pub nonzero_threshold: f64,
    /// The absolute regularisation weight used (CGLS: `mu`).
    pub lambda: f64,
    /// `lambda_max` when it was computed (relative lambda or a path); omitted otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lambda_max: Option<f64>,
    /// Step-size constant of the last stage: FISTA's final `L` (>= `||W^1/2 A||^2`, backtracked),
    /// the primal-dual TV's estimate of `||W^1/2 A||^2`.
    pub lipschitz: f64,
    /// Inner iterations of the exact prox (FISTA with `Psi` and `t >= 0`, TV-FISTA).
    pub inner_iterations: usize,
    /// Whether the common mode of the rows was deflated ([`condition`]) for the main
    /// iterations; the result is then polished on the exact objective (FISTA / TV-FISTA
    /// iterations, counted in `iterations` and in `polish_iterations`). `objective`, `lambda`
    /// and `relative_residual` always refer to the caller's exact problem.
    pub deflated: bool,
    pub polish_iterations: usize,
}

/// A solution and how it was found.
#[derive(Clone, Debug)]
pub struct Solution {
    pub t: Vec<f64>,
    pub report: SolveReport,
    /// FISTA / TV-FISTA with an iterative prox: its dual state at the end, in gradient units
    /// (the dual divided by the step: independent of the step size), for
    /// [`SolveOptions::warm_dual`] of a solve started from `t`. `None` otherwise.
    pub dual: Option<Vec<f64>>,
}

// ---------------------------------------------------------------------------------------------
// Shared plumbing.

/// `W^1/2 A` as an operator (for the power iteration); plain `A` without weights.
pub(crate) struct Weighted<'a> {
    pub a: &'a dyn LinearOperator,
    pub sqrt_w: Option<Vec<f64>>,
}

impl<'a> Weighted<'a> {
    pub fn new(a: &'a dyn LinearOperator, weights: Option<&[f64]>) -> Self {
        Weighted {
            a,
            sqrt_w: weights.map(|w| w.iter().map(|v| v.sqrt()).collect()),
        }
    }
}

impl LinearOperator for Weighted<'_> {
    fn rows(&self) -> usize {
        self.a.rows()
    }
    fn cols(&self) -> usize {
        self.a.cols()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.a.apply(x, y);
        if let Some(s) = &self.sqrt_w {
            y.iter_mut().zip(s).for_each(|(v, s)| *v *= s);
        }
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        match &self.sqrt_w {
            None => self.a.adjoint(y, x),
            Some(s) => {
                let ys: Vec<f64> = y.iter().zip(s).map(|(v, s)| v * s).collect();
                self.a.adjoint(&ys, x);
            }
        }
    }
}

/// `||W^1/2 A'||^2` of the operator the FISTA and TV solvers iterate on (`A' = A` with its
/// common mode deflated when `deflate_mean` and the rows have one, see [`condition`]): pass it
/// as [`SolveOptions::lipschitz`] to several solves on the same operator and weights so the
/// power iteration runs once.
pub fn step_constant(
    a: &dyn LinearOperator,
    weights: Option<&[f64]>,
    deflate_mean: bool,
) -> Result<f64, ReconError> {
    let zeros = vec![0.0; a.rows()];
    let prep = condition::Prepared::new(a, &zeros, weights, deflate_mean);
    lipschitz_of(prep.op(), prep.weights(), None)
}

/// `||W^1/2 A||^2`: from the options if given, else 20 power iterations (relative tol 1e-3).
/// The estimate is a lower bound (measured: within 2.5 % after 20 iterations on a 307 x 1024
/// Gaussian matrix, exact on deflated 0/1 patterns); FISTA backtracks and TV adds a 10 % margin.
/// 20 rather than more: each iteration costs two operator products, as much as a solver step.
pub(crate) fn lipschitz_of(
    a: &dyn LinearOperator,
    weights: Option<&[f64]>,
    given: Option<f64>,
) -> Result<f64, ReconError> {
    let l = match given {
        Some(l) => l,
        None => {
            let s = spectral_norm(&Weighted::new(a, weights), 20, 1e-3);
            s * s
        }
    };
    if !l.is_finite() || l < 0.0 {
        return Err(ReconError::Unsolvable(format!(
            "the measurement operator's norm is not finite ({l}): patterns or weights contain \
             NaN/inf or overflow"
        )));
    }
    Ok(l)
}

/// Validates sizes and finiteness shared by all solvers; returns `(rows, cols)`.
pub(crate) fn check_problem(
    a: &dyn LinearOperator,
    b: &[f64],
    opts: &SolveOptions,
) -> Result<(usize, usize), ReconError> {
    let (n, k) = (a.rows(), a.cols());
    if n == 0 || k == 0 {
        return Err(ReconError::Unsolvable(format!(
            "empty problem: {n} measurements of {k} pixels"
        )));
    }
    if b.len() != n {
        return Err(ReconError::BadRows(format!(
            "{} measurements for an operator with {n} rows",
            b.len()
        )));
    }
    if let Some(i) = b.iter().position(|v| !v.is_finite()) {
        return Err(ReconError::BadRows(format!(
            "measurement {i} is not finite ({})",
            b[i]
        )));
    }
    if let Some(w) = &opts.weights {
        if w.len() != n {
            return Err(ReconError::Unsolvable(format!(
                "{} weights for {n} measurements",
                w.len()
            )));
        }
        if let Some(i) = w.iter().position(|v| !v.is_finite() || *v < 0.0) {
            return Err(ReconError::Unsolvable(format!(
                "weight {i} is {}: weights must be finite and >= 0",
                w[i]
            )));
        }
    }
    if let Some(t0) = &opts.warm_start {
        if t0.len() != k {
            return Err(ReconError::Unsolvable(format!(
                "warm start has {} values for {k} pixels",
                t0.len()
            )));
        }
        if t0.iter().any(|v| !v.is_finite()) {
            return Err(ReconError::Unsolvable(
                "warm start contains NaN or infinity".into(),
            ));
        }
    }
    if !(opts.tol.is_finite() && opts.tol >= 0.0) {
        return Err(ReconError::Unsolvable(format!(
            "tol must be finite and >= 0, not {}",
            opts.tol
        )));
    }
    let (lo, hi) = opts.progress;
    if !(lo.is_finite() && hi.is_finite()) {
        return Err(ReconError::Unsolvable(
            "progress range must be finite".into(),
        ));
    }
    match opts.lambda {
        Lambda::Absolute(l) | Lambda::Relative(l) if !(l.is_finite() && l >= 0.0) => {
            return Err(ReconError::Unsolvable(format!(
                "lambda must be finite and >= 0, not {l}"
            )));
        }
        _ => {}
    }
    Ok((n, k))
}

/// `Psi` must be square `k x k` and orthonormal (`Psi^T Psi = I`, checked on a random vector).
pub(crate) fn check_orthonormal(psi: &dyn LinearOperator, k: usize) -> Result<(), ReconError> {
    if psi.rows() != k || psi.cols() != k {
        return Err(ReconError::Unsolvable(format!(
            "the sparsifying transform is {} x {}, expected an orthonormal {k} x {k}",
            psi.rows(),
            psi.cols()
        )));
    }
    let x = test_vector(k, 0x0b7a);
    let mut s = vec![0.0; k];
    let mut back = vec![0.0; k];
    psi.apply(&x, &mut s);
    psi.adjoint(&s, &mut back);
    let err = norm(&back.iter().zip(&x).map(|(a, b)| a - b).collect::<Vec<_>>()) / norm(&x);
    let energy = (norm(&s) / norm(&x) - 1.0).abs();
    if !(err <= 1e-8 && energy <= 1e-8) {
        return Err(ReconError::Unsolvable(format!(
            "the sparsifying transform is not orthonormal (||Psi^T Psi x - x|| / ||x|| = {err:.2e})"
        )));
    }
    Ok(())
}

/// `1/2 sum w_i r_i^2`.
pub(crate) fn half_wsq(r: &[f64], w: Option<&[f64]>) -> f64 {
    0.5 * match w {
        None => dot(r, r),
        Some(w) => r.iter().zip(w).map(|(r, w)| w * r * r).sum(),
    }
}

/// `||x|| / ||y||`, or `||x||` when `y = 0` (never NaN).
pub(crate) fn ratio_or_abs(x: f64, y: f64) -> f64 {
    if y > 0.0 { x / y } else { x }
}

/// Counts entries above `rel * max|c|` (`rel = 0`: exact nonzeros).
pub(crate) fn count_nonzeros(c: &[f64], rel: f64) -> usize {
    let m = c.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if m == 0.0 {
        return 0;
    }
    let thr = rel * m;
    c.iter().filter(|v| v.abs() > thr).count()
}

/// Decimating objective history: keeps at most `cap` values (cap >= 2) at a uniform stride.
pub(crate) struct History {
    cap: usize,
    stride: usize,
    values: Vec<f64>,
}

impl History {
    pub fn new(cap: usize) -> Self {
        History {
            cap: cap.max(2),
            stride: 1,
            values: Vec::new(),
        }
    }
    /// Records the objective at iteration `it` (0 = start) if it falls on the stride.
    pub fn record(&mut self, it: usize, value: f64) {
        if !it.is_multiple_of(self.stride) {
            return;
        }
        if self.values.len() >= self.cap {
            let kept: Vec<f64> = self.values.iter().step_by(2).copied().collect();
            self.values = kept;
            self.stride *= 2;
            if !it.is_multiple_of(self.stride) {
                return;
            }
        }
        self.values.push(value);
    }
    pub fn finish(self) -> (Vec<f64>, usize) {
        (self.values, self.stride)
    }
}

/// Progress reporting and cancellation, checked once per iteration.
pub(crate) struct Ticker<'a> {
    control: &'a Control,
    lo: f64,
    span: f64,
    max_iter: usize,
}

impl<'a> Ticker<'a> {
    pub fn new(control: &'a Control, opts: &SolveOptions) -> Self {
        let (lo, hi) = opts.progress;
        Ticker {
            control,
            lo,
            span: hi - lo,
            max_iter: opts.max_iter.max(1),
        }
    }
    pub fn tick(&self, it: usize) -> Result<(), ReconError> {
        if self.control.is_cancelled() {
            return Err(ReconError::Cancelled);
        }
        self.control
            .set_progress(self.lo + self.span * (it as f64 / self.max_iter as f64));
        Ok(())
    }
    pub fn done(&self) {
        self.control.set_progress(self.lo + self.span);
    }
}

pub(crate) fn non_finite(solver: &str, it: usize, what: &str) -> ReconError {
    ReconError::Unsolvable(format!(
        "{solver} diverged: non-finite {what} at iteration {it} (operator or data out of \
         floating-point range?)"
    ))
}

/// The `b = 0` answer: `t = 0` has objective 0, the minimum of every objective here.
pub(crate) fn zero_solution(
    solver: &'static str,
    k: usize,
    lambda: f64,
    lambda_max: Option<f64>,
    lipschitz: f64,
    start: Instant,
) -> Solution {
    Solution {
        t: vec![0.0; k],
        report: SolveReport {
            solver,
            iterations: 0,
            converged: true,
            stop: StopReason::ZeroData,
            restarts: 0,
            objective: 0.0,
            objective_history: vec![0.0],
            history_stride: 1,
            relative_residual: 0.0,
            seconds: start.elapsed().as_secs_f64(),
            nonzeros: 0,
            nonzero_threshold: 0.0,
            lambda,
            lambda_max,
            lipschitz,
            inner_iterations: 0,
            deflated: false,
            polish_iterations: 0,
        },
        dual: None,
    }
}

/// `||A t - b|| / ||b||` (unweighted; absolute if `b = 0`).
pub(crate) fn relative_residual(a: &dyn LinearOperator, t: &[f64], b: &[f64]) -> f64 {
    let mut at = vec![0.0; a.rows()];
    a.apply(t, &mut at);
    let r: f64 = at
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt();
    ratio_or_abs(r, norm(b))
}

/// `W b = 0`: every weighted measurement is zero, so `t = 0` (objective 0) is a minimiser.
pub(crate) fn is_zero_data(b: &[f64], w: Option<&[f64]>) -> bool {
    match w {
        None => b.iter().all(|&v| v == 0.0),
        Some(w) => b.iter().zip(w).all(|(&b, &w)| b * w == 0.0),
    }
}

/// The absolute lambda for a report when no solve was needed.
pub(crate) fn lambda_without_solve(l: Lambda) -> f64 {
    match l {
        Lambda::Absolute(v) => v,
        Lambda::Relative(_) => 0.0,
    }
}
