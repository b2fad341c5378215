//! A subset of the rows of any operator (hold-out splits, dropped rows).
//!
//! `S A` for a row selection `S`: `apply` runs the full product and gathers, `adjoint` scatters
//! into a zero vector of the full length and runs the full adjoint, so a product costs as much as
//! the full operator's. [`super::BernoulliOperator::select_rows`] and
//! [`super::HadamardOperator::select_rows`] build cheaper dedicated operators.

use super::scratch::Pool;
use crate::linop::LinearOperator;

pub struct RowSubset<A: LinearOperator + ?Sized = dyn LinearOperator> {
    inner: Box<A>,
    rows: Vec<usize>,
    pool: Pool,
}

impl<A: LinearOperator + ?Sized> RowSubset<A> {
    /// Rows `rows` of `inner`, in that order (repeats allowed). Panics on an index out of range.
    pub fn new(inner: Box<A>, rows: Vec<usize>) -> Self {
        let n = inner.rows();
        assert!(
            rows.iter().all(|&r| r < n),
            "row index out of range (operator has {n} rows)"
        );
        RowSubset {
            inner,
            rows,
            pool: Pool::new(),
        }
    }

    pub fn inner(&self) -> &A {
        &self.inner
    }

    pub fn selected(&self) -> &[usize] {
        &self.rows
    }
}

impl<A: LinearOperator + ?Sized> LinearOperator for RowSubset<A> {
    fn rows(&self) -> usize {
        self.rows.len()
    }
    fn cols(&self) -> usize {
        self.inner.cols()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        assert_eq!(y.len(), self.rows.len());
        let mut full = self.pool.take(self.inner.rows());
        self.inner.apply(x, &mut full);
        for (yi, &r) in y.iter_mut().zip(&self.rows) {
            *yi = full[r];
        }
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        assert_eq!(y.len(), self.rows.len());
        let mut full = self.pool.take(self.inner.rows());
        for (&yi, &r) in y.iter().zip(&self.rows) {
            full[r] += yi;
        }
        self.inner.adjoint(&full, x);
    }
}
