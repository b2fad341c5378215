//! Sparsifying transforms and total variation on `W x H` images (row-major, `k = W H`).
//!
//! Every transform is a [`LinearOperator`] `Psi: image -> coefficients` (and a [`Transform`], which
//! adds a name and whether it is orthonormal). For the orthonormal ones `adjoint` is the inverse,
//! so a synthesis model `t = Psi^T s` and an analysis model `s = Psi t` use the same object.
//!
//! | kind | type | sizes | boundary | cost |
//! |---|---|---|---|---|
//! | identity | [`Identity`] | any | - | O(k) |
//! | Haar | [`Wavelet2d::haar`] | any (unbalanced Haar on odd lengths) | none needed | O(k) |
//! | db2 / db4 | [`Wavelet2d::db2`], [`Wavelet2d::db4`] | any (odd length: last sample passes) | periodic | O(k L) |
//! | DCT-II | [`Dct2d`] | any | the DCT's own (even symmetric) | O(k log k): radix-2 FFT on power-of-two axes, rustdct on the others |
//! | gradient (TV) | [`Gradient`] | any | Neumann | O(k), `\|\|D\|\|^2 <= 8` |
//!
//! Wavelets run to full depth (1 x 1 approximation) unless capped with `Wavelet2d::with_levels`;
//! see [`wavelet`] for the exact construction on odd and non-power-of-two sizes.
//! [`count_above`] counts kept coefficients for reports.

pub mod dct;
mod fft;
pub mod tv;
pub mod wavelet;

#[cfg(test)]
mod bench;
#[cfg(test)]
mod dct_bench;
#[cfg(test)]
mod tests;

pub use dct::Dct2d;
pub use tv::{Gradient, isotropic_tv};
pub use wavelet::Wavelet2d;

use serde::{Deserialize, Serialize};

use super::linop::LinearOperator;

/// A sparsifying transform: an operator with a name for reports.
pub trait Transform: LinearOperator {
    fn name(&self) -> &'static str;
    /// `Psi^T Psi = Psi Psi^T = I` (then `adjoint` is the inverse).
    fn is_orthonormal(&self) -> bool;
}

/// The pixel basis (a sparse scene is sparse as it is).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Identity {
    len: usize,
}

impl Identity {
    pub fn new(len: usize) -> Self {
        Identity { len }
    }
}

impl LinearOperator for Identity {
    fn rows(&self) -> usize {
        self.len
    }
    fn cols(&self) -> usize {
        self.len
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        y.copy_from_slice(x);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        x.copy_from_slice(y);
    }
    fn apply_batch(&self, xs: &[f64], ys: &mut [f64], _batch: usize) {
        ys.copy_from_slice(xs);
    }
    fn adjoint_batch(&self, ys: &[f64], xs: &mut [f64], _batch: usize) {
        xs.copy_from_slice(ys);
    }
}

impl Transform for Identity {
    fn name(&self) -> &'static str {
        "identity"
    }
    fn is_orthonormal(&self) -> bool {
        true
    }
}

/// The orthonormal sparsifying transforms by name (for `auto` candidates and reports).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TransformKind {
    Identity,
    Haar,
    Db2,
    Db4,
    Dct,
}

impl TransformKind {
    pub const ALL: [TransformKind; 5] = [
        TransformKind::Identity,
        TransformKind::Haar,
        TransformKind::Db2,
        TransformKind::Db4,
        TransformKind::Dct,
    ];

    pub fn name(self) -> &'static str {
        match self {
            TransformKind::Identity => "identity",
            TransformKind::Haar => "haar",
            TransformKind::Db2 => "db2",
            TransformKind::Db4 => "db4",
            TransformKind::Dct => "dct",
        }
    }

    /// The transform for a `width x height` image (planning: O(k), DCT O(W^2 + H^2)).
    pub fn build(self, width: usize, height: usize) -> Box<dyn Transform> {
        match self {
            TransformKind::Identity => Box::new(Identity::new(width * height)),
            TransformKind::Haar => Box::new(Wavelet2d::haar(width, height)),
            TransformKind::Db2 => Box::new(Wavelet2d::db2(width, height)),
            TransformKind::Db4 => Box::new(Wavelet2d::db4(width, height)),
            TransformKind::Dct => Box::new(Dct2d::new(width, height)),
        }
    }
}

/// [`TransformKind::build`] as a plain operator.
pub fn sparsifying_transform(
    kind: TransformKind,
    width: usize,
    height: usize,
) -> Box<dyn LinearOperator> {
    match kind {
        TransformKind::Identity => Box::new(Identity::new(width * height)),
        TransformKind::Haar => Box::new(Wavelet2d::haar(width, height)),
        TransformKind::Db2 => Box::new(Wavelet2d::db2(width, height)),
        TransformKind::Db4 => Box::new(Wavelet2d::db4(width, height)),
        TransformKind::Dct => Box::new(Dct2d::new(width, height)),
    }
}

/// Number of coefficients with `|c| > threshold` (the "kept" count of a sparse model).
pub fn count_above(coefficients: &[f64], threshold: f64) -> usize {
    coefficients.iter().filter(|c| c.abs() > threshold).count()
}
