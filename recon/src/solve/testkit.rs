//! Test-only operators and scenes for the solvers (independent of `ops/` and `transforms/`).

use crate::linop::{DenseOperator, LinearOperator, dot, norm};
use crate::testutil::Rng;

/// `n x k` Gaussian matrix with N(0, 1/n) entries.
pub(crate) fn gaussian(n: usize, k: usize, seed: u64) -> DenseOperator {
    let mut rng = Rng::new(seed);
    let s = 1.0 / (n as f64).sqrt();
    DenseOperator::new(n, k, (0..n * k).map(|_| s * rng.normal()).collect())
}

/// `n x k` 0/1 Bernoulli(q) matrix.
pub(crate) fn bernoulli(n: usize, k: usize, q: f64, seed: u64) -> DenseOperator {
    let mut rng = Rng::new(seed);
    DenseOperator::new(
        n,
        k,
        (0..n * k)
            .map(|_| if rng.uniform() < q { 1.0 } else { 0.0 })
            .collect(),
    )
}

/// Random `k x k` orthogonal matrix (Gram-Schmidt, twice, on Gaussian rows).
pub(crate) fn random_orthogonal(k: usize, seed: u64) -> DenseOperator {
    let mut rng = Rng::new(seed);
    let mut rows: Vec<Vec<f64>> = Vec::with_capacity(k);
    while rows.len() < k {
        let mut v: Vec<f64> = (0..k).map(|_| rng.normal()).collect();
        for _ in 0..2 {
            for r in &rows {
                let c = dot(&v, r);
                v.iter_mut().zip(r).for_each(|(v, r)| *v -= c * r);
            }
        }
        let nv = norm(&v);
        if nv > 1e-8 {
            v.iter_mut().for_each(|x| *x /= nv);
            rows.push(v);
        }
    }
    DenseOperator::new(k, k, rows.concat())
}

/// Scales every entry of an operator (materialised).
pub(crate) fn scaled(a: &DenseOperator, c: f64) -> DenseOperator {
    DenseOperator::new(a.rows(), a.cols(), a.data().iter().map(|v| v * c).collect())
}

/// Orthonormal 2D Haar wavelet on an `n x n` image (`n` a power of two), full depth.
/// `apply` = analysis (image -> coefficients), `adjoint` = synthesis (its inverse).
pub(crate) struct Haar2d {
    pub n: usize,
}

fn haar_fwd_1d(x: &mut [f64], m: usize, stride: usize, tmp: &mut [f64]) {
    let h = m / 2;
    let r = std::f64::consts::FRAC_1_SQRT_2;
    for j in 0..h {
        let (a, b) = (x[2 * j * stride], x[(2 * j + 1) * stride]);
        tmp[j] = (a + b) * r;
        tmp[h + j] = (a - b) * r;
    }
    for j in 0..m {
        x[j * stride] = tmp[j];
    }
}

fn haar_inv_1d(x: &mut [f64], m: usize, stride: usize, tmp: &mut [f64]) {
    let h = m / 2;
    let r = std::f64::consts::FRAC_1_SQRT_2;
    for j in 0..h {
        let (a, d) = (x[j * stride], x[(h + j) * stride]);
        tmp[2 * j] = (a + d) * r;
        tmp[2 * j + 1] = (a - d) * r;
    }
    for j in 0..m {
        x[j * stride] = tmp[j];
    }
}

impl LinearOperator for Haar2d {
    fn rows(&self) -> usize {
        self.n * self.n
    }
    fn cols(&self) -> usize {
        self.n * self.n
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        let n = self.n;
        y.copy_from_slice(x);
        let mut tmp = vec![0.0; n];
        let mut m = n;
        while m >= 2 {
            for r in 0..m {
                haar_fwd_1d(&mut y[r * n..], m, 1, &mut tmp);
            }
            for c in 0..m {
                haar_fwd_1d(&mut y[c..], m, n, &mut tmp);
            }
            m /= 2;
        }
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        let n = self.n;
        x.copy_from_slice(y);
        let mut tmp = vec![0.0; n];
        let mut m = 2;
        while m <= n {
            for c in 0..m {
                haar_inv_1d(&mut x[c..], m, n, &mut tmp);
            }
            for r in 0..m {
                haar_inv_1d(&mut x[r * n..], m, 1, &mut tmp);
            }
            m *= 2;
        }
    }
}

/// Fast 0/1 patterns for timing at realistic sizes: row `i` is `(1 + (H D)_{r_i}) / 2` with `H`
/// the k x k Walsh-Hadamard matrix, `D` random signs and `r_i` distinct random rows (not 0):
/// half-on pseudo-random patterns with the common mode of Bernoulli(1/2), O(k log k) products.
pub(crate) struct FastBinary {
    k: usize,
    signs: Vec<f64>,
    rows: Vec<usize>,
}

impl FastBinary {
    pub(crate) fn new(n: usize, k: usize, seed: u64) -> Self {
        assert!(k.is_power_of_two() && n < k);
        let mut rng = Rng::new(seed);
        let signs = (0..k)
            .map(|_| if rng.uniform() < 0.5 { -1.0 } else { 1.0 })
            .collect();
        let mut perm: Vec<usize> = (1..k).collect();
        for i in (1..perm.len()).rev() {
            let j = (rng.next_u64() % (i as u64 + 1)) as usize;
            perm.swap(i, j);
        }
        perm.truncate(n);
        FastBinary {
            k,
            signs,
            rows: perm,
        }
    }
}

impl LinearOperator for FastBinary {
    fn rows(&self) -> usize {
        self.rows.len()
    }
    fn cols(&self) -> usize {
        self.k
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        let mut w: Vec<f64> = x.iter().zip(&self.signs).map(|(x, s)| x * s).collect();
        crate::fwht::fwht(&mut w);
        let sum: f64 = x.iter().sum();
        for (y, &r) in y.iter_mut().zip(&self.rows) {
            *y = 0.5 * (sum + w[r]);
        }
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        let mut w = vec![0.0; self.k];
        for (&v, &r) in y.iter().zip(&self.rows) {
            w[r] = v;
        }
        crate::fwht::fwht(&mut w);
        let sum: f64 = y.iter().sum();
        for ((x, w), s) in x.iter_mut().zip(&w).zip(&self.signs) {
            *x = 0.5 * (sum + w * s);
        }
    }
}

/// Piecewise-constant `n x n` scene: background 0.2, two rectangles and a disc at other levels
/// (edges not aligned to dyadic blocks).
pub(crate) fn blocks_scene(n: usize) -> Vec<f64> {
    let f = n as f64;
    let mut t = vec![0.2; n * n];
    for y in 0..n {
        for x in 0..n {
            let (xf, yf) = (x as f64, y as f64);
            let i = y * n + x;
            if xf >= 0.15 * f && xf < 0.55 * f && yf >= 0.2 * f && yf < 0.45 * f {
                t[i] = 1.0;
            }
            if xf >= 0.45 * f && xf < 0.8 * f && yf >= 0.6 * f && yf < 0.9 * f {
                t[i] = 0.6;
            }
            let (dx, dy) = (xf - 0.7 * f, yf - 0.3 * f);
            if dx * dx + dy * dy < (0.12 * f) * (0.12 * f) {
                t[i] = 0.0;
            }
        }
    }
    t
}

/// `||x - y|| / ||y||`.
pub(crate) fn rel_err(x: &[f64], y: &[f64]) -> f64 {
    let d: f64 = x
        .iter()
        .zip(y)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        .sqrt();
    d / norm(y)
}

/// Wraps an operator and raises the cancel flag after `after` forward products.
pub(crate) struct CancelAfterApplies<'a> {
    pub inner: &'a dyn LinearOperator,
    pub control: &'a crate::Control,
    pub after: usize,
    pub count: std::sync::atomic::AtomicUsize,
}

impl LinearOperator for CancelAfterApplies<'_> {
    fn rows(&self) -> usize {
        self.inner.rows()
    }
    fn cols(&self) -> usize {
        self.inner.cols()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        let c = self
            .count
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed)
            + 1;
        if c >= self.after {
            self.control.cancel();
        }
        self.inner.apply(x, y);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        self.inner.adjoint(y, x);
    }
}
