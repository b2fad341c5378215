//! One fit of the iterative methods, shared by the fixed-weight methods ([`super::compressive`])
//! and `auto` ([`super::auto`]): the operator and data a fit runs on (the offset-free form
//! `P A` when a constant offset of the buckets is fitted), the offset itself, the prediction of
//! held-out buckets, and one regularised solve with the method's data term.
//!
//! The dependency goes one way: `compressive` (the driver: loads the rows, plans the operator,
//! hands `auto` its channels) uses `auto` and this module; `auto` uses this module only.

use super::linop::LinearOperator;
use super::method::{Model, Noise};
use super::solve::{self, Grid, Penalty, Solution, SolveOptions};
use super::transforms::{TransformKind, sparsifying_transform};
use super::{Control, ReconError};

/// IRLS rounds of the Poisson data term (the weights settle in 3-4; measured in solve's tests).
const POISSON_ROUNDS: usize = 4;

/// `P A`, `P = I - 1 1^T / n`: the rows centred, so that a constant added to every bucket (a
/// dark level, ambient light) drops out of `||P (A t - c)||`. With 0/1 patterns whose sums vary
/// (Bernoulli) the image mean stays determined by the centred rows (through the spread of the
/// pattern sums), as well as any other image direction.
pub(crate) struct OffsetFree<'a> {
    a: &'a dyn LinearOperator,
}

impl LinearOperator for OffsetFree<'_> {
    fn rows(&self) -> usize {
        self.a.rows()
    }
    fn cols(&self) -> usize {
        self.a.cols()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.a.apply(x, y);
        centre(y);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        let mut z = y.to_vec();
        centre(&mut z);
        self.a.adjoint(&z, x);
    }
}

fn centre(v: &mut [f64]) {
    if !v.is_empty() {
        let m = v.iter().sum::<f64>() / v.len() as f64;
        v.iter_mut().for_each(|x| *x -= m);
    }
}

/// The operator and data a fit runs on: `(A, b)`, or `(P A, P b)` when the offset is fitted.
pub(crate) fn fitting<'a>(
    op: &'a dyn LinearOperator,
    b: &[f64],
    offset: bool,
) -> (Box<dyn LinearOperator + 'a>, Vec<f64>) {
    if offset {
        let mut c = b.to_vec();
        centre(&mut c);
        (Box::new(OffsetFree { a: op }), c)
    } else {
        (Box::new(op), b.to_vec())
    }
}

/// The least-squares offset of a fit: `d(t) = mean(b - A t) = mean(b) - mu . t`, `mu = A^T 1 / n`.
pub(crate) struct Offset {
    mean_b: f64,
    mu: Vec<f64>,
}

impl Offset {
    pub fn new(op: &dyn LinearOperator, b: &[f64]) -> Self {
        let n = op.rows().max(1) as f64;
        let mut mu = vec![0.0; op.cols()];
        op.adjoint(&vec![1.0 / n; op.rows()], &mut mu);
        Offset {
            mean_b: b.iter().sum::<f64>() / n,
            mu,
        }
    }
    pub fn at(&self, t: &[f64]) -> f64 {
        self.mean_b - super::linop::dot(&self.mu, t)
    }
}

/// Predicts held-out buckets: `A_H t (+ d(t))`, the offset fitted on the fitting rows.
pub(crate) struct Scorer<'a> {
    pub test: &'a dyn LinearOperator,
    pub offset: Option<Offset>,
}

impl Scorer<'_> {
    pub fn predict(&self, t: &[f64]) -> Vec<f64> {
        let mut y = predict(self.test, t);
        if let Some(o) = &self.offset {
            let d = o.at(t);
            y.iter_mut().for_each(|v| *v += d);
        }
        y
    }
}

/// `A t`.
pub(crate) fn predict(op: &dyn LinearOperator, t: &[f64]) -> Vec<f64> {
    let mut y = vec![0.0; op.rows()];
    op.apply(t, &mut y);
    y
}

/// One regularised fit with the method's data term.
pub(crate) fn fit_model(
    model: Model,
    (w, h): (usize, usize),
    op: &dyn LinearOperator,
    b: &[f64],
    noise: Noise,
    opts: &SolveOptions,
    control: &Control,
) -> Result<Solution, ReconError> {
    let psi = match model {
        Model::L1(kind) => Some(sparsifying_transform(kind, w, h)),
        Model::Tv => None,
    };
    let penalty = match model {
        Model::L1(_) => Penalty::L1 {
            psi: psi.as_deref(),
        },
        Model::Tv => Penalty::Tv {
            grid: Grid::new(w, h),
        },
    };
    let opts = &model_options(model, opts);
    match (noise, penalty) {
        (Noise::Poisson { photon }, penalty) => {
            solve::poisson_irls(op, penalty, b, photon, POISSON_ROUNDS, opts, control)
        }
        (Noise::Gaussian, Penalty::L1 { psi }) => solve::fista(op, psi, b, opts, control),
        (Noise::Gaussian, Penalty::Tv { grid } | Penalty::TvPrimalDual { grid }) => {
            solve::tv_fista(op, grid, b, opts, control)
        }
    }
}

/// The model's own solver settings: wavelet and DCT models leave their DC coefficient (the
/// image mean) unpenalised ([`SolveOptions::free_coefficients`]).
pub(crate) fn model_options(model: Model, opts: &SolveOptions) -> SolveOptions {
    let mut o = opts.clone();
    if let Model::L1(kind) = model
        && kind != TransformKind::Identity
    {
        o.free_coefficients = 1;
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_offset_free_operator_passes_the_adjoint_test_and_ignores_a_constant() {
        use crate::linop::{DenseOperator, adjoint_mismatch, test_vector};
        let a = DenseOperator::new(13, 7, test_vector(91, 4));
        let p = OffsetFree { a: &a };
        assert!(adjoint_mismatch(&p, 5) < 1e-12);
        // P (A t + d 1) = P A t: a constant added to every bucket is invisible.
        let t = test_vector(7, 6);
        let mut y = vec![0.0; 13];
        p.apply(&t, &mut y);
        let mut at = vec![0.0; 13];
        a.apply(&t, &mut at);
        let mut shifted: Vec<f64> = at.iter().map(|v| v + 5.0).collect();
        centre(&mut shifted);
        assert!(y.iter().zip(&shifted).all(|(a, b)| (a - b).abs() < 1e-12));
    }
}
