//! Pattern-family measurement operators (matrix-free), planned once and applied many times.
//!
//! | family | operator | rows | product cost |
//! |---|---|---|---|
//! | bernoulli (any 0/1 family) | [`BernoulliOperator`] | patterns | `n k / 8` table look-ups, 2 threads |
//! | hadamard | [`HadamardOperator`] | frames / 2 (split pairs) | one FWHT, O(k log k) |
//! | raster | [`RasterOperator`] | patterns | O(k + n) |
//! | speckle | [`SpeckleOperator`] | patterns | dense f32, `n k / grain^2` multiply-adds |
//! | adaptive_hadamard | [`HadamardOperator`] (the session's natural indices) | split pairs | one FWHT |
//! | adaptive_haar | [`HaarSubsetOperator`] | split pairs | one Haar transform, O(k) |
//!
//! [`measurement_operator`] picks the right one for a spec. Hadamard operators act on the split-pair
//! differences `(y+ - y-) / sqrt(k)` ([`HadamardOperator::split_pairs`] builds them from frames), so
//! their rows are pairs, not frames. 0/1 families should be conditioned with [`CentredOperator`]
//! before a first-order solver (see its module docs for how).
//!
//! No operator allocates in its products once warm (scratch buffers come from a per-operator pool;
//! the trait takes `&self` and is `Sync`). Speeds: `ops::bench` (run with
//! `cargo test -p helmholtz-recon --lib ops::bench -- --ignored --nocapture --test-threads 1`).

pub mod bernoulli;
pub mod binned;
pub mod bits;
pub mod centred;
pub mod gather;
pub mod haar;
pub mod hadamard;
pub mod raster;
pub(crate) mod scratch;
pub mod speckle;
pub mod subset;

#[cfg(test)]
mod bench;
#[cfg(test)]
mod tests;

pub use bernoulli::{BernoulliOperator, BinaryOperator};
pub use binned::Binned;
pub use bits::BitMatrix;
pub use centred::CentredOperator;
pub use gather::{Gather, GatherStats};
pub use haar::HaarSubsetOperator;
pub use hadamard::{HadamardOperator, SplitPairs};
pub use raster::RasterOperator;
pub use speckle::SpeckleOperator;
pub use subset::RowSubset;

use helmholtz_proto::{Family, PatternSpec};

use super::linop::LinearOperator;

/// Largest pattern store one operator may plan (bits for binary families, f32 levels for
/// speckle): 4 GiB.
pub const MEMORY_LIMIT: usize = 4 << 30;

/// Why an operator cannot be planned.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OpError {
    #[error("{rows} rows requested but the spec declares {count}")]
    TooManyRows { rows: u64, count: u64 },
    #[error("the {0} family has grey levels, not bits")]
    NotBinary(&'static str),
    #[error("expected a {want} spec, got {got}")]
    WrongFamily {
        want: &'static str,
        got: &'static str,
    },
    #[error(
        "the operator would hold {bytes} bytes of patterns, over the {limit}-byte limit: \
         use fewer rows or a smaller image"
    )]
    TooLarge { bytes: usize, limit: usize },
    #[error(
        "the {0} spec is not resolved: an adaptive session's operator needs the pattern \
         indices the session showed"
    )]
    Unresolved(&'static str),
}

/// The basis indices of the first `frames / 2` pairs of a resolved adaptive spec.
pub(crate) fn adaptive_rows(spec: &PatternSpec, frames: u64) -> Result<Vec<usize>, OpError> {
    check_rows(spec, frames)?;
    let indices = spec
        .adaptive_indices()
        .ok_or(OpError::Unresolved(spec.family().name()))?;
    let pairs = (frames / 2) as usize;
    if pairs > indices.len() {
        return Err(OpError::TooManyRows {
            rows: frames,
            count: 2 * indices.len() as u64,
        });
    }
    Ok(indices[..pairs].iter().map(|&n| n as usize).collect())
}

pub(crate) fn check_rows(spec: &PatternSpec, rows: u64) -> Result<(), OpError> {
    if rows > spec.count() {
        return Err(OpError::TooManyRows {
            rows,
            count: spec.count(),
        });
    }
    Ok(())
}

pub(crate) fn check_memory(bytes: usize) -> Result<(), OpError> {
    if bytes > MEMORY_LIMIT {
        return Err(OpError::TooLarge {
            bytes,
            limit: MEMORY_LIMIT,
        });
    }
    Ok(())
}

/// The operator of the first `rows` frames of `spec` (rows in acquisition order):
/// Bernoulli -> [`BernoulliOperator`] (`rows` rows), Hadamard -> [`HadamardOperator`] (`rows / 2`
/// rows, on split-pair differences), raster -> [`RasterOperator`], speckle ->
/// [`SpeckleOperator`], adaptive_hadamard -> [`HadamardOperator`] and adaptive_haar ->
/// [`HaarSubsetOperator`] on the resolved spec's indices (`rows / 2` pairs). Errors for
/// `rows > spec.count()`, patterns over [`MEMORY_LIMIT`], or an unresolved adaptive spec.
pub fn try_measurement_operator(
    spec: &PatternSpec,
    rows: u64,
) -> Result<Box<dyn LinearOperator>, OpError> {
    Ok(match spec.family() {
        Family::Bernoulli { .. } => Box::new(BernoulliOperator::from_spec(spec, rows)?),
        Family::Hadamard { .. } | Family::AdaptiveHadamard { .. } => {
            Box::new(HadamardOperator::from_spec(spec, rows)?)
        }
        Family::AdaptiveHaar { .. } => Box::new(HaarSubsetOperator::from_spec(spec, rows)?),
        Family::Raster { .. } => Box::new(RasterOperator::from_spec(spec, rows)?),
        Family::Speckle { .. } => Box::new(SpeckleOperator::from_spec(spec, rows)?),
    })
}

/// [`try_measurement_operator`], panicking on an invalid request.
pub fn measurement_operator(spec: &PatternSpec, rows: u64) -> Box<dyn LinearOperator> {
    try_measurement_operator(spec, rows).unwrap_or_else(|e| panic!("measurement operator: {e}"))
}
