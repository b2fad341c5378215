//! One fit of the iterative methods, shared by the fixed-weight methods ([`super::compressive`])
//! and `auto` ([`super::auto`]): the operator and data a fit runs on (the offset-free form
//! `P A`, the centred rows, when a constant offset of the buckets is fitted), the offset
//! itself, the prediction of held-out buckets, and one regularised solve with the method's data
//! term.
//!
//! The dependency goes one way: `compressive` (the driver: loads the rows, plans the operator,
//! hands `auto` its channels) uses `auto` and this module; `auto` uses this module only.

use super::linop::LinearOperator;
use super::method::{Model, Noise};
use super::ops::CentredOperator;
use super::solve::{self, Grid, Penalty, Solution, SolveOptions};
use super::transforms::{TransformKind, sparsifying_transform};
use super::{Control, ReconError};

/// IRLS rounds of the Poisson data term (the weights settle in 3-4; measured in solve's tests).
const POISSON_ROUNDS: usize = 4;

/// The operator and data a fit runs on: `(A, b)`, or `(P A, P b)` when the offset is fitted,
/// `P = I - 1 1^T / n`: the rows centred ([`CentredOperator`] without its mean row), so that a
/// constant added to every bucket (a dark level, ambient light) drops out of `||P (A t - c)||`.
/// With 0/1 patterns whose sums vary (Bernoulli) the image mean stays determined by the
/// centred rows (through the spread of the pattern sums), as well as any other image direction.
pub(crate) fn fitting<'a>(
    op: &'a dyn LinearOperator,
    b: &[f64],
    offset: bool,
) -> (Box<dyn LinearOperator + 'a>, Vec<f64>) {
    if offset {
        let centred = CentredOperator::new(Box::new(op));
        let c = centred.centre_data(b);
        (Box::new(centred), c)
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
        let b = test_vector(13, 5);
        let (p, pb) = fitting(&a, &b, true);
        assert!(adjoint_mismatch(p.as_ref(), 5) < 1e-12);
        // P b: the data centred.
        let mean = b.iter().sum::<f64>() / 13.0;
        assert!(
            pb.iter()
                .zip(&b)
                .all(|(p, b)| (p - (b - mean)).abs() < 1e-15)
        );
        // P (A t + d 1) = P A t: a constant added to every bucket is invisible.
        let t = test_vector(7, 6);
        let mut y = vec![0.0; 13];
        p.apply(&t, &mut y);
        let mut at = vec![0.0; 13];
        a.apply(&t, &mut at);
        let mut shifted: Vec<f64> = at.iter().map(|v| v + 5.0).collect();
        let m = shifted.iter().sum::<f64>() / 13.0;
        shifted.iter_mut().for_each(|v| *v -= m);
        assert!(y.iter().zip(&shifted).all(|(a, b)| (a - b).abs() < 1e-12));
        // Without the offset: A and b as they are.
        let (q, qb) = fitting(&a, &b, false);
        let mut z = vec![0.0; 13];
        q.apply(&t, &mut z);
        assert_eq!((z, qb), (at, b));
    }
}
