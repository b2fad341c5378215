//! The proximal operators of FISTA's regularisers, with the dual state kept between calls
//! (module docs of [`super`]): closed-form for the l1 of pixels and for an orthonormal `Psi`
//! without the constraint, the dual projected-gradient iteration otherwise.

use super::tv_prox::{primal_from_dual_serial, tv_prox_pass};
use crate::linop::LinearOperator;
use crate::simd::avx2_dispatch;
use crate::solve::grid::{Grid, gradient, pair_norm};

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

/// Proximal operator of `gamma R(t) (+ i_C(t))`, with its dual state kept between calls
/// (warm start); `C` is `t >= 0`, or with a held total ([`Prox::hold_total`]) the scaled
/// simplex `t >= 0, sum t = S`. Closed-form for `Pixel` and for `Ortho` without the constraint;
/// otherwise the dual projected-gradient iteration of the module docs (step `1 / ||G||^2`: 1
/// for `Psi`, 1/8 for `D`; dual set: the box `|u_j| <= gamma`, or the pointwise discs
/// `|p_i| <= gamma`), whose primal point is `P_C(v - G^T u)` for any closed convex `C` (the
/// gap `gamma R(t) - u . G t` is the same).
pub(crate) struct Prox<'a> {
    reg: Reg<'a>,
    nonneg: bool,
    /// `S` of `sum t = S` ([`Prox::hold_total`]), and the last simplex threshold (the next
    /// call's guess, [`simplex_threshold_from`]).
    total: Option<f64>,
    tau: f64,
    /// `v - tau`, the prox input shifted by the simplex projection's threshold (TV with a
    /// held total).
    shifted: Vec<f64>,
    u: Vec<f64>,
    pub(crate) s: Vec<f64>,
    tmp: Vec<f64>,
    pub(crate) inner: usize,
    pub(crate) last_gap: f64,
    /// Inner-iteration cap per call: [`MAX_INNER`] (TV) or [`MAX_INNER_ORTHO`], raised by
    /// [`Prox::tighten`].
    cap: usize,
    /// Calls with a raised cap run [`Prox::fgp_tv`] (TV only; [`SolveOptions::accelerated_prox`]).
    ///
    /// [`SolveOptions::accelerated_prox`]: crate::solve::SolveOptions::accelerated_prox
    pub(crate) accelerated: bool,
}

impl<'a> Prox<'a> {
    pub(crate) fn new(reg: Reg<'a>, nonneg: bool, k: usize) -> Self {
        let m = reg.coeffs(k);
        Prox {
            reg,
            nonneg,
            total: None,
            tau: f64::NEG_INFINITY,
            shifted: Vec::new(),
            u: vec![0.0; m],
            s: vec![0.0; m],
            tmp: vec![0.0; k],
            inner: 0,
            last_gap: 0.0,
            cap: Self::base_cap(reg),
            accelerated: false,
        }
    }

    /// Holds `sum t = total` besides `t >= 0` (ignored without the constraint; a total `<= 0`
    /// leaves only `t = 0`).
    pub(crate) fn hold_total(&mut self, total: Option<f64>) {
        self.total = total.filter(|_| self.nonneg);
        if self.total.is_some() && matches!(self.reg, Reg::Tv(_)) {
            self.shifted = vec![0.0; self.tmp.len()];
        }
    }

    /// `v` shifted by the threshold of `P_C(v - D^T u)` (the primal point's input), for a TV
    /// pass that then clips at 0: `clip(v - tau - D^T u) = P_C(v - D^T u)`.
    fn shift_for(&mut self, u: &[f64], v: &[f64], grid: Grid) {
        let total = self.total.expect("a held total");
        primal_from_dual_serial(u, v, grid, &mut self.tmp);
        let tau = simplex_threshold_from(&self.tmp, total, self.tau);
        self.tau = tau;
        self.shifted
            .iter_mut()
            .zip(v)
            .for_each(|(s, &v)| *s = v - tau);
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

    /// Starts the dual iteration from `dual` (in gradient units, [`Prox::dual`]) for steps of
    /// size `step`; ignored unless the prox is iterative and the lengths match. The first call
    /// projects it onto the dual set of its own weight.
    pub(crate) fn start_dual(&mut self, dual: &[f64], step: f64) {
        if self.inexact() && dual.len() == self.u.len() && step.is_finite() && step > 0.0 {
            self.u
                .iter_mut()
                .zip(dual)
                .for_each(|(u, &d)| *u = if d.is_finite() { d * step } else { 0.0 });
        }
    }

    /// The dual state in gradient units (divided by the step `1 / lip`): at a fixed point
    /// `x = prox(x - g / lip)` it satisfies `G^T u = -g / lip` (TV without the constraint), so
    /// `u * lip` does not depend on the step. `None` when the prox is closed-form.
    pub(crate) fn dual(&self, lip: f64) -> Option<Vec<f64>> {
        self.inexact()
            .then(|| self.u.iter().map(|&u| u * lip).collect())
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
                if let Some(total) = self.total {
                    // On the simplex `||t||_1 = S`: the prox is the projection.
                    let tau = simplex_threshold_from(v, total, self.tau);
                    self.tau = tau;
                    out.iter_mut()
                        .zip(v)
                        .for_each(|(o, &v)| *o = (v - tau).max(0.0));
                } else if self.nonneg {
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
                    let tau = match self.total {
                        Some(total) => {
                            out.iter_mut()
                                .zip(v.iter().zip(&self.tmp))
                                .for_each(|(o, (&v, &pu))| *o = v - pu);
                            self.tau = simplex_threshold_from(out, total, self.tau);
                            self.tau
                        }
                        None => 0.0,
                    };
                    out.iter_mut()
                        .zip(v.iter().zip(&self.tmp))
                        .for_each(|(o, (&v, &pu))| *o = (v - pu - tau).max(0.0));
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
            Reg::Tv(grid) if self.accelerated && self.cap > MAX_INNER => {
                project_discs(&mut self.u, gamma);
                self.fgp_tv(v, grid, gamma, eps, out)
            }
            Reg::Tv(grid) => {
                project_discs(&mut self.u, gamma);
                let mut j = 0;
                loop {
                    // out = clip(v - D^T u); then s = D out, the gap at u, and the ascent step
                    // u <- proj(u + s / 8) (the step is kept even when we stop: it only
                    // improves the next warm start), all in one pass ([`tv_prox_pass`]).
                    // With a held total `v` is shifted first ([`Prox::shift_for`]).
                    let (l1, us, mag) = if self.total.is_some() {
                        let u = std::mem::take(&mut self.u);
                        self.shift_for(&u, v, grid);
                        self.u = u;
                        tv_prox_pass(&mut self.u, &self.shifted, grid, true, gamma, out)
                    } else {
                        tv_prox_pass(&mut self.u, v, grid, self.nonneg, gamma, out)
                    };
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

impl Prox<'_> {
    /// The TV prox by the accelerated dual iteration (FGP, Beck-Teboulle 2009: the projected
    /// gradient step of the plain iteration taken at an extrapolated point), for calls whose
    /// cap was raised ([`Prox::tighten`]): there the plain iteration's `O(1/j)` needs thousands
    /// of passes. The extrapolated point can leave the discs, where the gap of the fused pass
    /// bounds nothing, so every [`FGP_CHECK`] iterations (and at the cap) one plain pass from
    /// the current (feasible) iterate gives the primal candidate and its gap; the call ends
    /// there as the plain one does, with that pass's ascent step kept.
    fn fgp_tv(&mut self, v: &[f64], grid: Grid, gamma: f64, eps: f64, out: &mut [f64]) -> f64 {
        let m = self.u.len();
        let mut r = self.u.clone();
        let mut prev = self.u.clone();
        let mut check = vec![0.0; m];
        let mut theta = 1.0f64;
        let mut j = 0;
        loop {
            // r <- proj(r + D t(r) / 8): the next iterate, from the extrapolated point.
            if self.total.is_some() {
                self.shift_for(&r, v, grid);
                tv_prox_pass(&mut r, &self.shifted, grid, true, gamma, out);
            } else {
                tv_prox_pass(&mut r, v, grid, self.nonneg, gamma, out);
            }
            j += 1;
            self.inner += 1;
            let next = 0.5 * (1.0 + (1.0 + 4.0 * theta * theta).sqrt());
            let beta = (theta - 1.0) / next;
            theta = next;
            // u_j = r (now feasible); r <- u_j + beta (u_j - u_{j-1}); prev <- u_j.
            for (rv, p) in r.iter_mut().zip(prev.iter_mut()) {
                let u = *rv;
                *rv = u + beta * (u - *p);
                *p = u;
            }
            if j % FGP_CHECK == 0 || j >= self.cap {
                check.copy_from_slice(&prev);
                let (l1, us, mag) = if self.total.is_some() {
                    self.shift_for(&check, v, grid);
                    tv_prox_pass(&mut check, &self.shifted, grid, true, gamma, out)
                } else {
                    tv_prox_pass(&mut check, v, grid, self.nonneg, gamma, out)
                };
                self.inner += 1;
                let gap = gamma * l1 - us;
                self.last_gap = gap;
                if gap <= eps || gap <= 1e-13 * (gamma * l1 + mag) || j >= self.cap {
                    std::mem::swap(&mut self.u, &mut check);
                    return l1;
                }
            }
        }
    }
}

/// The threshold `tau` of the projection onto the scaled simplex `{t >= 0, sum t = s}`:
/// `P(z) = max(z - tau, 0)` with `sum max(z - tau, 0) = s`. For `s <= 0` (or no finite entry)
/// the largest entry, so that `P(z) = 0`.
pub(crate) fn simplex_threshold(z: &[f64], s: f64) -> f64 {
    simplex_threshold_from(z, s, f64::NEG_INFINITY)
}

/// [`simplex_threshold`] started from a guess (the previous call's threshold, in a prox whose
/// input moves little between calls). `f(tau) = sum max(z - tau, 0) - s` is convex and
/// decreasing, so a Newton step from any guess lands at or below the root, and Newton steps
/// from below rise to it monotonically, the set `z > tau` only shrinking (Michelot 1986: each
/// step is the mean excess over the entries still above), ending when it stops changing. From
/// a good guess that is two or three passes; from none (`-inf`: every entry) a few more.
pub(crate) fn simplex_threshold_from(z: &[f64], s: f64, guess: f64) -> f64 {
    let top = z.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if s.is_nan() || s <= 0.0 || !top.is_finite() {
        return top;
    }
    // Branch-free sums over the entries above `tau`, in eight lanes (so they vectorise).
    let above = |tau: f64| {
        let (mut sum, mut count) = ([0.0f64; 8], [0.0f64; 8]);
        let chunks = z.chunks_exact(8);
        let rest = chunks.remainder();
        for c in chunks {
            for l in 0..8 {
                let m = if c[l] > tau { 1.0 } else { 0.0 };
                sum[l] += m * c[l];
                count[l] += m;
            }
        }
        for &v in rest {
            let m = if v > tau { 1.0 } else { 0.0 };
            sum[0] += m * v;
            count[0] += m;
        }
        (sum.iter().sum::<f64>(), count.iter().sum::<f64>())
    };
    // A guess at or above the top has no entry above it: start from every entry.
    let mut tau = if guess.is_finite() && guess < top {
        guess
    } else {
        f64::NEG_INFINITY
    };
    let mut first = true;
    loop {
        let (sum, count) = above(tau);
        let next = (sum - s) / count;
        // From below, a step that does not rise ends it; the first step (the guess may lie
        // above the root) is always taken.
        if !first && next <= tau {
            return tau;
        }
        first = false;
        tau = next;
    }
}

/// Accelerated TV prox iterations between two gap checks ([`Prox::fgp_tv`]).
const FGP_CHECK: usize = 10;

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
