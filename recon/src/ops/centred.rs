//! Conditioning of 0/1 pattern operators: remove the common mode.
//!
//! # Why
//!
//! Bernoulli(q) patterns `P` (n x k) are `q 1 1^T` plus zero-mean noise: the all-ones direction has
//! singular value about `q sqrt(n k)`, every other one about `sqrt(q (1-q)) (sqrt(k) +- sqrt(n))`.
//! At 128 x 128 and 10 % that is ~2600 against ~85: `||P||^2` is ~1000 times what the image detail
//! needs, so a first-order solver with step `1 / ||P||^2` crawls.
//!
//! # What
//!
//! With `m = P^T 1 / n` (mean pattern) and `cbar = mean(c)`:
//!
//! ```text
//! A_c = P - 1 m^T            (centred patterns; 1^T A_c = 0, so A_c t is orthogonal to 1)
//! b_c = c - cbar 1           (centred data)
//! ||P t - c||^2 = ||A_c t - b_c||^2 + n (m . t - cbar)^2      (exactly)
//! ```
//!
//! The second term is the *mean equation* `m . t = cbar`: the only information about the DC level
//! of `t`. [`CentredOperator`] is `A_c` (n rows), optionally followed by the mean row with a
//! weight `w` (n + 1 rows: `[A_c; w m^T]`, data `[b_c; w cbar]`, built by
//! [`CentredOperator::centre_data`]). Then
//!
//! - `w = sqrt(n)` ([`CentredOperator::exact_dc_weight`]) is exactly the original least-squares
//!   problem, and exactly as badly conditioned (the common mode is back);
//! - any `w > 0` has exactly the same solutions of `P t = c` (noise-free data), and
//!   `w = ||A_c|| / ||m||` ([`CentredOperator::augmented`]) keeps `||[A_c; w m^T]|| <= sqrt(2) ||A_c||`:
//!   the common mode no longer sets the step size.
//!
//! # How a solver should use it
//!
//! 1. `let op = CentredOperator::augmented(Box::new(p));` (one adjoint for `m`, 10-30 products for
//!    the balanced weight) and `let b = op.centre_data(&c);`.
//! 2. Run the solver on `(op, b)`: step `1 / spectral_norm(&op)^2`, regulariser and `t >= 0` on
//!    `t` as usual. Products cost one product of `P` plus O(k + n).
//! 3. With noisy data the balanced weight under-weights the mean equation (by `w^2 / n`) against
//!    the regulariser; finish with [`CentredOperator::fix_dc`] (a constant shift making
//!    `m . t = cbar` exact, O(k)), or re-weight with a few iterations at `w = sqrt(n)`.
//!
//! Without the mean row (`CentredOperator::new`) the solver sees only `A_c`, whose null space
//! contains (nearly) the constant image: recover the DC term afterwards with `fix_dc`.
//! Held-out residuals should be computed on the original `P` and `c` ([`CentredOperator::inner`]).
//!
//! The solvers' automatic mean deflation ([`crate::solve::condition`]) is this operator too:
//! `[A_c; alpha m^T]` of the row-weighted operator `W^1/2 P`, with the weight `alpha` it measures.
//! And the iterative methods' fit of a constant bucket offset (`fit::fitting`) runs on `A_c`
//! alone (no mean row), with the data `c - cbar` of [`CentredOperator::centre_data`].
//!
//! # Arithmetic
//!
//! Products centre the outputs of `P` (`A_c t = P t - mean(P t) 1`, and `A_c^T y = P^T (y -
//! mean(y) 1)`, the mean row folded into the same shift), which needs no mean pattern: `m` is
//! computed on first use (one adjoint) by the methods that need it ([`CentredOperator::fix_dc`],
//! the balanced weight, ...).

use std::sync::OnceLock;

use super::scratch::Pool;
use crate::linop::{LinearOperator, dot, norm, spectral_norm};

/// `A_c = P - 1 m^T`, optionally with the weighted mean row `w m^T` appended (module docs).
pub struct CentredOperator<A: LinearOperator + ?Sized = dyn LinearOperator> {
    inner: Box<A>,
    /// `m = P^T 1 / n` and `||m||`, computed on first use.
    mean: OnceLock<(Vec<f64>, f64)>,
    dc_weight: Option<f64>,
    pool: Pool,
}

impl<A: LinearOperator + ?Sized> std::fmt::Debug for CentredOperator<A> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CentredOperator")
            .field("rows", &self.inner.rows())
            .field("cols", &self.inner.cols())
            .field("dc_weight", &self.dc_weight)
            .finish()
    }
}

impl<A: LinearOperator + ?Sized> CentredOperator<A> {
    /// `A_c` alone (n rows). The mean pattern is computed (one adjoint) when first needed.
    pub fn new(inner: Box<A>) -> Self {
        CentredOperator {
            inner,
            mean: OnceLock::new(),
            dc_weight: None,
            pool: Pool::new(),
        }
    }

    /// `(m, ||m||)`.
    fn mean(&self) -> &(Vec<f64>, f64) {
        self.mean.get_or_init(|| {
            let (n, k) = (self.inner.rows(), self.inner.cols());
            let mut mean = vec![0.0; k];
            if n > 0 {
                self.inner.adjoint(&vec![1.0; n], &mut mean);
                mean.iter_mut().for_each(|v| *v /= n as f64);
            }
            let mean_norm = norm(&mean);
            (mean, mean_norm)
        })
    }

    /// `[A_c; w m^T]` with the balanced weight `w = ||A_c|| / ||m||`, `||A_c||` estimated by
    /// power iteration to 1 % (a weight needs no more; ~10-30 products of `P`). If the solver
    /// computes `||A_c||` anyway, `CentredOperator::new(p).with_dc_weight(c.balanced_dc_weight(norm))`
    /// saves the iterations.
    pub fn augmented(inner: Box<A>) -> Self {
        let centred = Self::new(inner);
        let w = centred.balanced_dc_weight(spectral_norm(&centred, 100, 1e-2));
        centred.with_dc_weight(w)
    }

    /// `centred_norm / ||m||` (1 if `m = 0`): the mean row as strong as the strongest centred
    /// direction.
    pub fn balanced_dc_weight(&self, centred_norm: f64) -> f64 {
        let mean_norm = self.mean().1;
        if mean_norm > 0.0 && centred_norm > 0.0 {
            centred_norm / mean_norm
        } else {
            1.0
        }
    }

    /// Appends (or re-weights) the mean row with weight `w` (see the module docs).
    pub fn with_dc_weight(mut self, w: f64) -> Self {
        assert!(
            w.is_finite() && w > 0.0,
            "dc weight must be positive, got {w}"
        );
        self.dc_weight = Some(w);
        self
    }

    /// Removes the mean row.
    pub fn without_dc_row(mut self) -> Self {
        self.dc_weight = None;
        self
    }

    /// The weight of the mean row, if present.
    pub fn dc_weight(&self) -> Option<f64> {
        self.dc_weight
    }

    /// `sqrt(n)`: the weight that reproduces the uncentred least-squares objective exactly.
    pub fn exact_dc_weight(&self) -> f64 {
        (self.inner.rows() as f64).sqrt()
    }

    /// The wrapped (uncentred) operator `P`.
    pub fn inner(&self) -> &A {
        &self.inner
    }

    pub fn into_inner(self) -> Box<A> {
        self.inner
    }

    /// `m = P^T 1 / n`.
    pub fn mean_pattern(&self) -> &[f64] {
        &self.mean().0
    }

    /// Mean of the data, `cbar`.
    pub fn data_mean(c: &[f64]) -> f64 {
        if c.is_empty() {
            0.0
        } else {
            c.iter().sum::<f64>() / c.len() as f64
        }
    }

    /// The data for this operator: `c - cbar` (n values), then `w cbar` if the mean row is on.
    pub fn centre_data(&self, c: &[f64]) -> Vec<f64> {
        assert_eq!(c.len(), self.inner.rows(), "one bucket per pattern");
        let mean = Self::data_mean(c);
        let mut b: Vec<f64> = c.iter().map(|v| v - mean).collect();
        if let Some(w) = self.dc_weight {
            b.push(w * mean);
        }
        b
    }

    /// Shifts `t` by a constant so that the mean equation `m . t = cbar` holds exactly (the DC
    /// term; `cbar` from [`CentredOperator::data_mean`] of the raw buckets). Returns the shift.
    pub fn fix_dc(&self, t: &mut [f64], cbar: f64) -> f64 {
        let mean = self.mean_pattern();
        let total: f64 = mean.iter().sum();
        if total == 0.0 {
            return 0.0;
        }
        let shift = (cbar - dot(mean, t)) / total;
        t.iter_mut().for_each(|v| *v += shift);
        shift
    }

    /// Residual of the mean equation, `m . t - cbar`.
    pub fn dc_residual(&self, t: &[f64], cbar: f64) -> f64 {
        dot(self.mean_pattern(), t) - cbar
    }
}

impl<A: LinearOperator + ?Sized> LinearOperator for CentredOperator<A> {
    fn rows(&self) -> usize {
        self.inner.rows() + usize::from(self.dc_weight.is_some())
    }
    fn cols(&self) -> usize {
        self.inner.cols()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.apply_batch(x, y, 1);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        self.adjoint_batch(y, x, 1);
    }
    fn apply_batch(&self, xs: &[f64], ys: &mut [f64], batch: usize) {
        let (n, k, rows) = (self.inner.rows(), self.inner.cols(), self.rows());
        assert_eq!(xs.len(), k * batch);
        assert_eq!(ys.len(), rows * batch);
        if self.dc_weight.is_none() {
            self.inner.apply_batch(xs, ys, batch);
        } else {
            // Compact the inner outputs (n per vector), then spread to n + 1 from the back.
            self.inner.apply_batch(xs, &mut ys[..n * batch], batch);
            for b in (0..batch).rev() {
                ys.copy_within(b * n..(b + 1) * n, b * rows);
            }
        }
        for y in ys.chunks_exact_mut(rows.max(1)).take(batch) {
            // mean(P x) = m . x.
            let m = mean_of(&y[..n]);
            y[..n].iter_mut().for_each(|v| *v -= m);
            if let Some(w) = self.dc_weight {
                y[n] = w * m;
            }
        }
    }
    fn adjoint_batch(&self, ys: &[f64], xs: &mut [f64], batch: usize) {
        let (n, k, rows) = (self.inner.rows(), self.inner.cols(), self.rows());
        assert_eq!(ys.len(), rows * batch);
        assert_eq!(xs.len(), k * batch);
        // A_c^T y + w y_n m = P^T (y - mean(y) 1 + w y_n 1 / n).
        let mut z = self.pool.take(n * batch);
        for (zb, y) in z
            .chunks_exact_mut(n.max(1))
            .zip(ys.chunks_exact(rows.max(1)))
        {
            let m = mean_of(&y[..n]);
            let shift = match self.dc_weight {
                Some(w) => w * y[n] / n as f64 - m,
                None => -m,
            };
            zb.iter_mut().zip(&y[..n]).for_each(|(z, v)| *z = v + shift);
        }
        if batch == 1 {
            self.inner.adjoint(&z, xs);
        } else {
            self.inner.adjoint_batch(&z, xs, batch);
        }
    }
    fn batching_pays(&self) -> bool {
        self.inner.batching_pays()
    }
}

/// `mean(v)`, 0 for no values.
fn mean_of(v: &[f64]) -> f64 {
    if v.is_empty() {
        0.0
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}
