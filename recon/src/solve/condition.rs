//! Conditioning for 0/1 patterns: deflating the common mode.
//!
//! Bernoulli (and most non-negative) patterns share a large mean: `A = 1 mu^T + (A - 1 mu^T)`
//! has one singular value `~ sqrt(n) ||mu||` far above the bulk, so a first-order solver's step
//! `1 / ||A||^2` is tiny for everything but the image mean and it needs thousands of iterations.
//! The least-squares data term splits exactly into the centred rows and the mean row:
//!
//! `||A t - b||^2 = ||P (A t - b)||^2 + n (mu^T t - mean(b))^2`,  `P = I - 1 1^T / n`.
//!
//! [`MeanDeflated`] keeps both parts but gives the mean row the weight `alpha^2` instead of `n`,
//! with `alpha ||mu||` equal to the RMS norm of the centred rows: the operator
//! `[P A; alpha mu^T]` (`n + 1` rows) then has no outlying singular value. It is the centred
//! operator of the measurement operators ([`CentredOperator`] with the mean row of weight
//! `alpha`) over the row-weighted [`RowWeighted`] `W^1/2 A`. Noise-free data give
//! the same solution (both forms vanish at `A t = b`); with noise only the weight of the one
//! mean measurement changes (it is the best-determined one by far). Weights are folded in first
//! (`A <- W^1/2 A`, `b <- W^1/2 b`), so the deflated problem is unweighted.
//!
//! Detection costs one adjoint and one batched product with 4 random probes (Hutchinson estimate
//! of `||A||_F`): deflation applies only when the mean component is more than 3 times the RMS
//! row norm; centred operators (Gaussian, Hadamard differences) are left alone.

use crate::linop::{LinearOperator, norm, test_vector};
use crate::ops::CentredOperator;

/// Deflate when `sqrt(n) ||mu||` exceeds this multiple of the RMS centred row norm.
const DOMINANCE: f64 = 3.0;
const PROBES: usize = 4;

/// `W^1/2 A`, matrix-free over `A` (`A` itself without weights).
pub struct RowWeighted<'a> {
    a: &'a dyn LinearOperator,
    sqrt_w: Option<Vec<f64>>,
}

impl<'a> RowWeighted<'a> {
    pub fn new(a: &'a dyn LinearOperator, weights: Option<&[f64]>) -> Self {
        RowWeighted {
            a,
            sqrt_w: weights.map(|w| w.iter().map(|v| v.sqrt()).collect()),
        }
    }

    /// `W^1/2 b`.
    pub fn weigh(&self, b: &[f64]) -> Vec<f64> {
        match &self.sqrt_w {
            None => b.to_vec(),
            Some(s) => b.iter().zip(s).map(|(b, s)| b * s).collect(),
        }
    }
}

impl LinearOperator for RowWeighted<'_> {
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
            Some(_) => self.a.adjoint(&self.weigh(y), x),
        }
    }
}

/// `[P W^1/2 A; alpha mu^T]` (`n + 1` rows): the centred operator of `W^1/2 A` with the mean
/// row of weight `alpha` (module docs). Built by [`Deflation::operator`].
pub type MeanDeflated<'a> = CentredOperator<RowWeighted<'a>>;

/// What [`Deflation::detect`] decided for an operator and its weights. Detection costs one
/// adjoint and four products; a path passes the decision to its points (same operator, same
/// weights) through [`super::SolveOptions::deflation`] instead of measuring it again per point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Deflation {
    /// The mean does not dominate (or deflation was not asked for): solve as given.
    Off,
    /// Deflate with these measured values.
    On {
        alpha: f64,
        mu_norm: f64,
        dominance: f64,
    },
}

impl Deflation {
    /// Measures the mean component of `W^1/2 A`; `On` if it dominates (see module docs).
    pub fn detect(a: &dyn LinearOperator, weights: Option<&[f64]>) -> Self {
        let (n, k) = (a.rows(), a.cols());
        if n < 2 || k == 0 {
            return Deflation::Off;
        }
        let sqrt_w: Option<Vec<f64>> = weights.map(|w| w.iter().map(|v| v.sqrt()).collect());
        // mu = A_w^T 1 / n.
        let ones: Vec<f64> = match &sqrt_w {
            None => vec![1.0 / n as f64; n],
            Some(s) => s.iter().map(|s| s / n as f64).collect(),
        };
        let mut mean_row = vec![0.0; k];
        a.adjoint(&ones, &mut mean_row);
        let mu_norm = norm(&mean_row);
        if !(mu_norm.is_finite() && mu_norm > 0.0) {
            return Deflation::Off;
        }
        // ||A_w||_F^2 by Hutchinson with uniform [-1, 1) probes (E g g^T = I / 3).
        let mut xs = Vec::with_capacity(PROBES * k);
        for p in 0..PROBES {
            xs.extend(test_vector(k, 0xdef1 + p as u64));
        }
        let mut ys = vec![0.0; PROBES * n];
        a.apply_batch(&xs, &mut ys, PROBES);
        if let Some(s) = &sqrt_w {
            for y in ys.chunks_exact_mut(n) {
                y.iter_mut().zip(s).for_each(|(v, s)| *v *= s);
            }
        }
        let frob2 = 3.0 * ys.iter().map(|v| v * v).sum::<f64>() / PROBES as f64;
        let mean2 = n as f64 * mu_norm * mu_norm;
        // Centred Frobenius norm; the estimate can undershoot the mean part slightly.
        let centred2 = (frob2 - mean2).max(1e-3 * frob2);
        let rms_row = (centred2 / n as f64).sqrt();
        let dominance = (mean2.sqrt()) / rms_row.max(f64::MIN_POSITIVE);
        if !(dominance.is_finite() && dominance > DOMINANCE) {
            return Deflation::Off;
        }
        Deflation::On {
            alpha: rms_row / mu_norm,
            mu_norm,
            dominance,
        }
    }

    /// The deflated operator of `W^1/2 A` (`None` when `Off`); the decision must come from the
    /// same operator and weights.
    pub fn operator<'a>(
        &self,
        a: &'a dyn LinearOperator,
        weights: Option<&[f64]>,
    ) -> Option<MeanDeflated<'a>> {
        match *self {
            Deflation::Off => None,
            Deflation::On { alpha, .. } => Some(
                CentredOperator::new(Box::new(RowWeighted::new(a, weights))).with_dc_weight(alpha),
            ),
        }
    }

    /// An upper bound on `||W^1/2 A||^2` from `||A'||^2` (the deflated operator's), `n` rows:
    /// `A^T W A = A'^T A' + (n - alpha^2) mu mu^T`. `deflated` itself when `Off`.
    pub fn undeflated_lipschitz(&self, n: usize, deflated: f64) -> f64 {
        match *self {
            Deflation::Off => deflated,
            Deflation::On { alpha, mu_norm, .. } => {
                deflated + (n as f64 - alpha * alpha).max(0.0) * mu_norm * mu_norm
            }
        }
    }
}

/// The right-hand side of the deflated problem: `[P W^1/2 b; alpha mean(W^1/2 b)]`.
pub fn deflated_rhs(op: &MeanDeflated, b: &[f64]) -> Vec<f64> {
    op.centre_data(&op.inner().weigh(b))
}

/// The problem a solver iterates on: the caller's `(A, b, W)`, or its deflated form.
pub(crate) struct Prepared<'a> {
    a: &'a dyn LinearOperator,
    deflated: Option<MeanDeflated<'a>>,
    decision: Deflation,
    b: Vec<f64>,
    weights: Option<&'a [f64]>,
}

impl<'a> Prepared<'a> {
    pub fn new(
        a: &'a dyn LinearOperator,
        b: &[f64],
        weights: Option<&'a [f64]>,
        deflate: bool,
    ) -> Self {
        Self::with_decision(a, b, weights, deflate, None)
    }

    /// [`Prepared::new`] with the deflation decision already made for this operator and these
    /// weights (`known`, from [`Prepared::decision`]); `None` detects. `deflate == false` never
    /// deflates.
    pub fn with_decision(
        a: &'a dyn LinearOperator,
        b: &[f64],
        weights: Option<&'a [f64]>,
        deflate: bool,
        known: Option<Deflation>,
    ) -> Self {
        let decision = match (deflate, known) {
            (false, _) => Deflation::Off,
            (true, None) => Deflation::detect(a, weights),
            (true, Some(d)) => d,
        };
        match decision.operator(a, weights) {
            Some(d) => Prepared {
                a,
                b: deflated_rhs(&d, b),
                deflated: Some(d),
                decision,
                weights: None,
            },
            None => Prepared {
                a,
                deflated: None,
                decision,
                b: b.to_vec(),
                weights,
            },
        }
    }
    pub fn op(&self) -> &dyn LinearOperator {
        match &self.deflated {
            Some(d) => d,
            None => self.a,
        }
    }
    pub fn b(&self) -> &[f64] {
        &self.b
    }
    pub fn weights(&self) -> Option<&[f64]> {
        self.weights
    }
    pub fn is_deflated(&self) -> bool {
        self.deflated.is_some()
    }
    /// The deflation decision, to pass to later solves on the same operator and weights.
    pub fn decision(&self) -> Deflation {
        self.decision
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linop::{DenseOperator, adjoint_mismatch, dot, spectral_norm};
    use crate::solve::testkit::{bernoulli, gaussian};

    #[test]
    fn deflation_is_exact_and_conditions_bernoulli() {
        let (n, k) = (60, 200);
        let a = bernoulli(n, k, 0.5, 4);
        let decision = Deflation::detect(&a, None);
        let Deflation::On { dominance, .. } = decision else {
            panic!("0/1 patterns have a dominant mean")
        };
        let d = decision.operator(&a, None).unwrap();
        assert!(adjoint_mismatch(&d, 9) < 1e-13);
        assert!(dominance > 5.0, "{dominance}");
        // Same zero set: A t = b  <=>  A' t = b'.
        let t = test_vector(k, 5);
        let mut b = vec![0.0; n];
        a.apply(&t, &mut b);
        let bd = deflated_rhs(&d, &b);
        let mut at = vec![0.0; n + 1];
        d.apply(&t, &mut at);
        let r: f64 = at
            .iter()
            .zip(&bd)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        assert!(r < 1e-10 * norm(&bd), "{r}");
        // The outlying singular value is gone: ||A'|| is close to the centred bulk.
        let s_raw = spectral_norm(&a, 200, 1e-10);
        let s_def = spectral_norm(&d, 200, 1e-10);
        let centred: Vec<f64> = {
            let dd = DenseOperator::from_operator(&d);
            dd.data()[..n * k].to_vec()
        };
        let s_c = spectral_norm(&DenseOperator::new(n, k, centred), 200, 1e-10);
        println!("||A|| {s_raw:.2}, ||A'|| {s_def:.2}, ||PA|| {s_c:.2}");
        assert!(s_raw > 3.0 * s_def && s_def < 1.5 * s_c);
        // Weighted: the deflated problem equals deflating W^1/2 A.
        let w: Vec<f64> = (0..n).map(|i| 0.5 + (i % 3) as f64).collect();
        let decision = Deflation::detect(&a, Some(&w));
        let Deflation::On { alpha, .. } = decision else {
            panic!("weighted 0/1 patterns have a dominant mean")
        };
        let dw = decision.operator(&a, Some(&w)).unwrap();
        assert_eq!(dw.dc_weight(), Some(alpha));
        assert!(adjoint_mismatch(&dw, 2) < 1e-13);
        let y = test_vector(n, 8);
        let bw = deflated_rhs(&dw, &y);
        let ys: Vec<f64> = y.iter().zip(&w).map(|(y, w)| y * w.sqrt()).collect();
        let m = ys.iter().sum::<f64>() / n as f64;
        assert!((bw[n] - alpha * m).abs() < 1e-12 && (bw[0] - (ys[0] - m)).abs() < 1e-12);
        assert!(dot(&bw[..n], &vec![1.0; n]).abs() < 1e-10);
    }

    #[test]
    fn centred_operators_are_left_alone() {
        assert_eq!(
            Deflation::detect(&gaussian(50, 120, 3), None),
            Deflation::Off
        );
    }
}
