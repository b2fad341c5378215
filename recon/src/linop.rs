//! Linear operators (pylops style): solvers take operators, never matrices.
//!
//! An operator `A` maps `x` (length `cols`) to `y = A x` (length `rows`) and back with its adjoint
//! `x = A^T y`. Implementations plan once (pack patterns, allocate scratch) and apply many times.
//! Every implementation must pass [`adjoint_mismatch`] (`<A x, y> = <x, A^T y>`) in its tests.

/// A real linear operator, `rows x cols`.
pub trait LinearOperator: Send + Sync {
    fn rows(&self) -> usize;
    fn cols(&self) -> usize;

    /// `y = A x`. `x.len() == cols`, `y.len() == rows`; `y` is overwritten.
    fn apply(&self, x: &[f64], y: &mut [f64]);

    /// `x = A^T y`. `y.len() == rows`, `x.len() == cols`; `x` is overwritten.
    fn adjoint(&self, y: &[f64], x: &mut [f64]);

    /// Many right-hand sides: `xs` holds `batch` vectors of length `cols` one after another,
    /// `ys` receives `batch` vectors of length `rows`. Override where batching pays (one pass
    /// over the patterns for all vectors).
    fn apply_batch(&self, xs: &[f64], ys: &mut [f64], batch: usize) {
        let (m, n) = (self.rows(), self.cols());
        assert_eq!(xs.len(), n * batch);
        assert_eq!(ys.len(), m * batch);
        for (x, y) in xs.chunks_exact(n).zip(ys.chunks_exact_mut(m)) {
            self.apply(x, y);
        }
    }

    /// Batched adjoint, laid out as [`LinearOperator::apply_batch`].
    fn adjoint_batch(&self, ys: &[f64], xs: &mut [f64], batch: usize) {
        let (m, n) = (self.rows(), self.cols());
        assert_eq!(ys.len(), m * batch);
        assert_eq!(xs.len(), n * batch);
        for (y, x) in ys.chunks_exact(m).zip(xs.chunks_exact_mut(n)) {
            self.adjoint(y, x);
        }
    }

    /// Whether a batched product costs less per vector than products one at a time (one pass
    /// over the patterns serving several vectors, or vectors run in parallel), so that
    /// several solvers gain by waiting for each other to batch their products
    /// ([`Gather`](super::ops::Gather)). `false` for the one-at-a-time default above; wrappers
    /// that pass batches through answer for the operator they wrap.
    fn batching_pays(&self) -> bool {
        false
    }
}

/// A dense row-major matrix: the reference every fast operator is checked against, and the
/// plain-product path where it wins (small sizes).
#[derive(Clone, Debug, PartialEq)]
pub struct DenseOperator {
    rows: usize,
    cols: usize,
    data: Vec<f64>,
}

impl DenseOperator {
    pub fn new(rows: usize, cols: usize, data: Vec<f64>) -> Self {
        assert_eq!(
            data.len(),
            rows * cols,
            "dense operator needs rows * cols values"
        );
        DenseOperator { rows, cols, data }
    }

    /// Materialises any operator column by column (tests and small problems only).
    pub fn from_operator(op: &dyn LinearOperator) -> Self {
        let (m, n) = (op.rows(), op.cols());
        let mut data = vec![0.0; m * n];
        let mut e = vec![0.0; n];
        let mut col = vec![0.0; m];
        for j in 0..n {
            e[j] = 1.0;
            op.apply(&e, &mut col);
            e[j] = 0.0;
            for i in 0..m {
                data[i * n + j] = col[i];
            }
        }
        DenseOperator {
            rows: m,
            cols: n,
            data,
        }
    }

    pub fn data(&self) -> &[f64] {
        &self.data
    }
}

/// A borrowed operator is an operator (so `&dyn LinearOperator` can stand where an owned one is
/// boxed).
impl<T: LinearOperator + ?Sized> LinearOperator for &T {
    fn rows(&self) -> usize {
        (**self).rows()
    }
    fn cols(&self) -> usize {
        (**self).cols()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        (**self).apply(x, y)
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        (**self).adjoint(y, x)
    }
    fn apply_batch(&self, xs: &[f64], ys: &mut [f64], batch: usize) {
        (**self).apply_batch(xs, ys, batch)
    }
    fn adjoint_batch(&self, ys: &[f64], xs: &mut [f64], batch: usize) {
        (**self).adjoint_batch(ys, xs, batch)
    }
    fn batching_pays(&self) -> bool {
        (**self).batching_pays()
    }
}

impl LinearOperator for DenseOperator {
    fn rows(&self) -> usize {
        self.rows
    }
    fn cols(&self) -> usize {
        self.cols
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        assert_eq!(x.len(), self.cols);
        assert_eq!(y.len(), self.rows);
        for (yi, row) in y.iter_mut().zip(self.data.chunks_exact(self.cols)) {
            *yi = row.iter().zip(x).map(|(a, b)| a * b).sum();
        }
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        assert_eq!(y.len(), self.rows);
        assert_eq!(x.len(), self.cols);
        x.fill(0.0);
        for (yi, row) in y.iter().zip(self.data.chunks_exact(self.cols)) {
            for (xj, a) in x.iter_mut().zip(row) {
                *xj += a * yi;
            }
        }
    }
}

pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

pub fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

/// Deterministic pseudo-random vector in [-1, 1) (SplitMix64), for adjoint tests and power
/// iterations without a rand dependency in the numerics.
pub fn test_vector(len: usize, seed: u64) -> Vec<f64> {
    (0..len)
        .map(|i| {
            let w = helmholtz_proto::patterns::rng::stream_word(seed, i as u64);
            (w >> 11) as f64 * (2.0 / (1u64 << 53) as f64) - 1.0
        })
        .collect()
}

/// `|<A x, y> - <x, A^T y>| / (|<A x, y>| + |<x, A^T y>|)` for random `x`, `y`: ~1e-15 for a
/// correct adjoint in f64.
pub fn adjoint_mismatch(op: &dyn LinearOperator, seed: u64) -> f64 {
    let x = test_vector(op.cols(), seed);
    let y = test_vector(op.rows(), seed.wrapping_add(1));
    let mut ax = vec![0.0; op.rows()];
    let mut aty = vec![0.0; op.cols()];
    op.apply(&x, &mut ax);
    op.adjoint(&y, &mut aty);
    let (l, r) = (dot(&ax, &y), dot(&x, &aty));
    let scale = l.abs() + r.abs();
    if scale == 0.0 {
        0.0
    } else {
        (l - r).abs() / scale
    }
}

/// Estimates the largest singular value `||A||_2` by power iteration on `A^T A` (the step size
/// of first-order solvers is `1 / ||A||^2`; no hand-tuned eigenvalue). Returns the estimate after
/// `iterations` steps or once it changes by less than `tol` relatively.
pub fn spectral_norm(op: &dyn LinearOperator, iterations: usize, tol: f64) -> f64 {
    let mut x = test_vector(op.cols(), 0x5eed);
    let mut ax = vec![0.0; op.rows()];
    let mut estimate = 0.0;
    for _ in 0..iterations.max(1) {
        let nx = norm(&x);
        if nx == 0.0 {
            return 0.0;
        }
        x.iter_mut().for_each(|v| *v /= nx);
        op.apply(&x, &mut ax);
        op.adjoint(&ax, &mut x);
        let next = norm(&x).sqrt();
        if (next - estimate).abs() <= tol * next {
            return next;
        }
        estimate = next;
    }
    estimate
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dense_adjoint_and_norm() {
        let a = DenseOperator::new(3, 2, vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        assert!(adjoint_mismatch(&a, 3) < 1e-14);
        let mut y = vec![0.0; 3];
        a.apply(&[1.0, -1.0], &mut y);
        assert_eq!(y, vec![-1.0, -1.0, -1.0]);
        // Singular values of [[1,2],[3,4],[5,6]]: 9.5255..., 0.5143...
        let s = spectral_norm(&a, 200, 1e-12);
        assert!((s - 9.525518091565107).abs() < 1e-9, "{s}");
        assert_eq!(DenseOperator::from_operator(&a), a);
    }
}
