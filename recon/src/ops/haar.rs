//! Subsampled orthonormal 2D Haar operator: the measurements of an `adaptive_haar` session.
//!
//! `A = S W`: `W` the orthonormal 2D Haar transform of the `W x W` grid in Mallat layout
//! ([`Wavelet2d::haar`], whose coefficient `n` is the pattern family's Haar function `n`,
//! `proto/PATTERNS.md`), `S` selects the session's indices in acquisition order.
//! `apply(x) = S W x`, `adjoint(d) = W^T S^T d` (the zero-filled inverse), O(k) each; `A A^T = I`
//! without repeated indices, `||A|| = 1`.
//!
//! Data: split pair `r` shows `P+ = [psi > 0]`, `P- = [psi < 0]` of Haar function `n_r`, whose
//! orthonormal form is the sign pattern over its support side `g = 2^s`, so
//! `d_r = (y+ - y-) / g` ([`crate::adaptive::pair_coefficients`]); a constant dark level cancels.

use helmholtz_proto::{Family, HaarFunction, PatternSpec};

use super::OpError;
use super::scratch::Pool;
use crate::linop::LinearOperator;
use crate::transforms::wavelet::Wavelet2d;

/// Rows = chosen Haar coefficients of a square power-of-two grid.
#[derive(Debug)]
pub struct HaarSubsetOperator {
    wavelet: Wavelet2d,
    indices: Vec<usize>,
    pool: Pool,
}

impl HaarSubsetOperator {
    /// Coefficients `indices` (Mallat positions, no repeats) of a `width x width` grid.
    pub fn new(width: u32, indices: Vec<usize>) -> Self {
        assert!(width.is_power_of_two(), "haar subset needs a power of two");
        let k = width as usize * width as usize;
        assert!(
            indices.iter().all(|&n| n < k),
            "haar index out of range 0..{k}"
        );
        HaarSubsetOperator {
            wavelet: Wavelet2d::haar(width as usize, width as usize),
            indices,
            pool: Pool::new(),
        }
    }

    /// From a resolved `adaptive_haar` spec and a number of *frames* (`frames / 2` pairs).
    pub fn from_spec(spec: &PatternSpec, frames: u64) -> Result<Self, OpError> {
        if !matches!(spec.family(), Family::AdaptiveHaar { .. }) {
            return Err(OpError::WrongFamily {
                want: "adaptive_haar",
                got: spec.family().name(),
            });
        }
        let indices = super::adaptive_rows(spec, frames)?;
        Ok(Self::new(spec.width(), indices))
    }

    /// The operator of a subset of the rows, in the given order (e.g. a hold-out split).
    pub fn select_rows(&self, rows: &[usize]) -> Self {
        let w = self.wavelet.width() as u32;
        Self::new(w, rows.iter().map(|&r| self.indices[r]).collect())
    }

    /// Mallat index of each row.
    pub fn indices(&self) -> &[usize] {
        &self.indices
    }

    /// The finest grid any row resolves: a Haar detail of support side `2^s` is constant on
    /// blocks of `2^(s-1)` pixels, the scaling function on the whole image (`(1, 1)` with no
    /// detail). Detail finer than this is not measured anywhere (`auto` reports it).
    pub fn finest_resolution(&self) -> (usize, usize) {
        let w = self.wavelet.width();
        let finest = self
            .indices
            .iter()
            .filter(|&&n| n != 0)
            .map(|&n| HaarFunction::new(w as u32, n as u32).scale)
            .min();
        let side = finest.map_or(1, |s| w >> (s - 1));
        (side, side)
    }
}

impl LinearOperator for HaarSubsetOperator {
    fn rows(&self) -> usize {
        self.indices.len()
    }
    fn cols(&self) -> usize {
        self.wavelet.cols()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        assert_eq!(y.len(), self.indices.len());
        let mut full = self.pool.take(self.cols());
        self.wavelet.apply(x, &mut full);
        for (yi, &n) in y.iter_mut().zip(&self.indices) {
            *yi = full[n];
        }
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        assert_eq!(y.len(), self.indices.len());
        let mut full = self.pool.take(self.cols());
        full.fill(0.0);
        for (&yi, &n) in y.iter().zip(&self.indices) {
            full[n] += yi;
        }
        self.wavelet.adjoint(&full, x);
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use helmholtz_proto::PatternGenerator;

    use super::*;
    use crate::linop::{DenseOperator, adjoint_mismatch};

    #[test]
    fn adjoint_identity_and_orthonormal_rows() {
        let op = HaarSubsetOperator::new(16, vec![0, 255, 17, 3, 128, 64, 1, 200]);
        assert!(adjoint_mismatch(&op, 3) < 1e-12);
        let dense = DenseOperator::from_operator(&op);
        for a in 0..op.rows() {
            for b in 0..op.rows() {
                let s: f64 = (0..256)
                    .map(|j| dense.data()[a * 256 + j] * dense.data()[b * 256 + j])
                    .sum();
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((s - want).abs() < 1e-12, "rows {a} {b}: {s}");
            }
        }
    }

    /// Row `r` of the operator is the pattern family's Haar function, signs over `2^s`, and
    /// `P+ - P-` of the generated split pair is its sign pattern.
    #[test]
    fn rows_are_the_pattern_functions() {
        let w = 8u32;
        let indices: Vec<u32> = (0..64).collect();
        let spec = PatternSpec::new(Family::adaptive(true, 0, 0.0, None), w, w, 128, 0)
            .unwrap()
            .with_indices(Arc::from(indices))
            .unwrap();
        let op = HaarSubsetOperator::from_spec(&spec, 128).unwrap();
        let dense = DenseOperator::from_operator(&op);
        let generator = PatternGenerator::new(&spec);
        let (mut plus, mut minus) = (vec![0f32; 64], vec![0f32; 64]);
        for n in 0..64u32 {
            let f = HaarFunction::new(w, n);
            generator.fill_values(2 * n as u64, &mut plus);
            generator.fill_values(2 * n as u64 + 1, &mut minus);
            for p in 0..64 {
                let sign = f.sign(p % w, p / w) as f64;
                let got = dense.data()[n as usize * 64 + p as usize];
                assert!((got - sign / f.side() as f64).abs() < 1e-12, "n {n} p {p}");
                assert_eq!((plus[p as usize] - minus[p as usize]) as f64, sign);
            }
        }
    }
}
