//! Camera sessions: the light transport matrix `T` (m camera pixels x k projector pixels).
//!
//! Frame `i` is `c_i = T p_i` (+ noise), so with `Y` (n frames x m camera pixels) `Y = A T^T`:
//! every camera pixel's column `y_j = A t_j` is one compressive problem and all of them share
//! the pattern operator `A` ([`crate::ops`]; Hadamard split pairs as differences,
//! Bernoulli and speckle conditioned by [`CentredOperator`]). Row `t_j` of `T` is the dual
//! image seen by camera pixel `j`.
//!
//! # How
//!
//! - **Blocks of camera pixels.** The frames are read one contiguous block of camera pixels at a
//!   time ([`FrameSource::read_pixels`]); the block size comes from `memory_budget_bytes`, which
//!   covers the operator, the frame block, the block's data and solutions, and the solver
//!   scratch of every thread ([`plan_memory`]). A session is never held whole.
//! - **Complete raster or Hadamard sets: the exact inverse**, stored sparse: a coefficient in
//!   the transform is kept when it stands out of the noise the data show, in its own row or in
//!   its mean over a tile of neighbouring camera pixels ([`exact_support`]; noise `sigma` from
//!   the median absolute finest diagonal Haar detail, `sigma = median |HH_1| / 0.6745`;
//!   threshold `sqrt(2 ln k) sigma`, for a tile mean `sqrt(2 ln k) sqrt(sum sigma_j^2) / n`,
//!   never below f32 resolution of the row's largest coefficient). A relight sums rows: light
//!   that many camera pixels share, each below its own noise (interreflections), adds up
//!   coherently when dropped, while the noise of what is kept averages out; so it is kept, at
//!   each row's own (unbiased) value. With the transform left to the data, one pass over the
//!   session estimates every candidate's full-light relight error ([`ExactChoice`]: the
//!   coherent sum of what it drops, plus the noise of what it keeps); the one keeping the fewest
//!   coefficients within 10 % of the lowest estimate is used, and the estimate is reported
//!   (`relight_error_estimate`).
//! - **Otherwise: l1 in an orthonormal transform** (`min 1/2 ||A Psi^T s - b||^2 + lambda ||s||_1`
//!   per row, [`batch`]: batched FISTA over many rows at once, chunks of rows over the rayon
//!   threads; random patterns by coordinate descent with an active set on `A Psi^T` held
//!   densely, [`batch::Dense`], 2-6x faster on 32x32 x 64x64 sessions at the same relight
//!   error), `lambda` a fraction of each row's own `lambda_max`. The data choose the transform
//!   and the fraction: on a sample of camera pixels (drawn with probability in proportion to the
//!   energy of their data, [`energy_sample`], so a scene lighting a third of the camera is
//!   judged on the lit pixels) each candidate
//!   transform is fitted along a warm-started path of fractions without the held-out rows
//!   ([`crate::holdout`]) and scored on them (a transform's path stops early when its score
//!   rises twice, or when it is 3x worse than another transform's best and not catching up).
//!   Held-out rows are hashed out of random
//!   designs; of a Hadamard subset they are the LAST measured pairs ([`holdout::tail`]): its
//!   rows are ordered coarse to fine, the unmeasured ones lie beyond the measured ones, and
//!   randomly held-out pairs (among the fitted ones) would be predicted well by any model that
//!   fits, whatever it puts in the unmeasured coefficients (they remain blind to error in the
//!   unmeasured coefficients, a test documents the case). The choice is the sparsest model
//!   (fewest nonzeros) whose held-out score is within one standard error of the best one (the
//!   error from the spread of the held-out rows' residuals): noise-free data otherwise pull the
//!   weight to the smallest one tried, where hundreds of tiny coefficients buy a fraction of a
//!   percent of held-out error. A Hadamard subset needs more: its tail pairs, one class of
//!   patterns at the end of the ordering, rated a Haar fit of a glossy scene as good as the
//!   pixel basis where its relit images were 45 % off against 3 %. There the transform is
//!   chosen by a [`LevelTest`] (half of the measured pairs in the scale orders the set measures
//!   only partly, where the unmeasured coefficients are, held out and predicted by a fit on the
//!   rest; near-ties go to the sparser transform), and the points are held to the total light
//!   they keep ([`subset_light_error`]: the sample rows' fitted sums against the measured
//!   all-on pair's; a lasso that drops a dense, dim interreflection loses it in every row, which
//!   a relight adds up) before the one-standard-error rule picks among them.
//!   A Hadamard subset's paths also run with every row's weight at least its noise floor
//!   ([`noise_floor`]: the universal threshold `sqrt(2 ln k) sigma`, `sigma` from the spread of
//!   the row's split-pair sums): a weight relative to the row's own `lambda_max` alone sits
//!   below the noise in a dim row (1 % frame noise: 420-490 nonzeros per row on sparse scenes
//!   where the complete set keeps 4). The floor is a candidate, not a rule: on a scene with a
//!   dense, dim interreflection it drops light from every row, and the light test rejects it.
//!   Bernoulli sessions get the same candidate, `sqrt(2 ln k) sigma sqrt(n p (1 - p))`, with one
//!   `sigma` for every row: the median over the sample pixels of their random-pattern moment
//!   estimates ([`random_noise_floor`]; a row's own estimate scatters 30x on bright sparse rows).
//!   Every lasso point is scored twice: as solved, and refitted by
//!   least squares on its own support ([`batch::refit_rows`], the relaxed lasso): the soft
//!   threshold shrinks every kept coefficient by the weight, so a larger weight (fewer
//!   coefficients) with the refit often predicts as well as a small one without it.
//!   The chosen (transform, fraction, refit) is applied to all camera
//!   pixels with all rows; the rows keep only their nonzero coefficients (the soft threshold
//!   zeroes the rest), so the stored size follows the scene's complexity. With `compact` (the
//!   default) every refitted point is also
//!   scored compacted ([`prune_rows`]: each row's smallest coefficients dropped while they hold
//!   at most [`PRUNE_SHARE`] of the point's held-out residual of the row's energy and of its
//!   light, refitted on what is left, and again, while its held-out score falls), a candidate of
//!   the rule above where its held-out score is no worse than the point's as solved: a
//!   lasso at a small weight keeps hundreds of tiny coefficients per row that buy almost
//!   nothing, which made a compressive `T` larger than the exact complete set's.
//!   `t >= 0` is not imposed (the prox would become iterative); the reported held-out error is
//!   that of the chosen model on the sample pixels. A Bernoulli session also reports the error
//!   of a full-light relight (`relight_error_estimate`, [`random_relight_error`]): its held-out
//!   frames' residuals summed over the camera, which a per-row residual cannot show (rows' errors
//!   add up coherently in a relight: 5x the held-out residual on the Cornell box), with a bound
//!   two jackknife standard errors above it. Where those few frames do not resolve it (their
//!   noise summed over the camera swamps it), cross-validation over every frame does
//!   ([`random_cv_relight_error`]), and with noisy frames a parametric bootstrap gives the
//!   error the noise alone makes ([`random_bootstrap_noise`]): the estimate is then at least
//!   that. A warning when the estimate is above 0.2. A Hadamard subset reports the same
//!   estimate ([`subset_relight_error`]) from the same problem one grid coarser, where the truth
//!   is known: the session's share of the pairs of the coarser grid it completes, fitted with
//!   the chosen model on every camera pixel, predicts all of them (a check across the levels of
//!   a Russian-doll set; each row's error of T, extrapolated from its measured scale orders, put
//!   it at 4-16x the relit error of half a set).
//!   The final fit of every row runs down a continuation path (its stages before the last
//!   solved to a tenth of the precision: they are warm starts; the larger fractions of
//!   [`LAMBDA_PATH`], each warm-starting the next), which converges in far fewer iterations than
//!   a cold start at a small weight.
//! - **A coarser projector grid** (`projector_binning` b, Hadamard sessions): Walsh function
//!   `(u, v)` is constant on `b x b` blocks when `b` divides `u` and `v`, and is then the coarse
//!   grid's `(u / b, v / b)`; those pairs, with data `(y+ - y-) / sqrt(k / b^2)`, measure the
//!   coarse `T` (each column the summed light of a block), the others are unused. A Russian-doll
//!   subset holds every block-constant pair of the grids it has finished, so half of one
//!   inverts exactly on the 2x2 blocks; the report names that grid ([`complete_binning`]).
//! - **Coarse-to-fine** (Peers et al. 2009, optional): each block (whole pairs of camera lines)
//!   first solves its 2x2-binned camera pixels (data averaged) down the continuation path, then
//!   every pixel starts from its parent's solution at the final weight only.
//! - **Three steps, one code path** (`shard.rs`): [`plan_transport`] validates, plans the memory
//!   (the blocks) and chooses the model, once, into a [`TransportModel`] (stored as JSON);
//!   [`solve_transport_blocks`] solves any run of its blocks into a [`TransportPart`] (stored as
//!   bytes); [`assemble_transport`] appends the parts in block order into `T` and the report.
//!   [`reconstruct_transport`] is the three in one process; a server runs the middle one in
//!   shards on many workers. A row of `T` depends only on its own camera pixel's frames and on
//!   the model (transform, weight, refit, `L`, solver chunk, iteration limits), never on the
//!   block or shard it is solved in, so the assembled `T` is the single call's bit for bit. The
//!   one process-dependent factor, the number of rayon threads (the bit-matrix products split
//!   their partial sums over threads), is recorded in the model and every part is solved on a
//!   pool of that size; the SIMD kernel (AVX-512 or portable, `HELMHOLTZ_SIMD`) must also be the
//!   same on every machine.

pub mod batch;
mod config;
pub mod light;
mod matrix;
mod shard;
#[cfg(test)]
mod tests;

use std::ops::Range;
use std::time::Instant;

use helmholtz_proto::{Family, PatternSpec};
use serde_json::{Value, json};

pub use config::{CANDIDATE_TRANSFORMS, DEFAULT_MEMORY_BUDGET, LAMBDA_PATH, TransportConfig};
pub use light::{Light, LightError};
use matrix::Builder;
pub use matrix::{TransportDecodeError, TransportMatrix};
pub use shard::{MemoryFigures, PartDecodeError, TransportModel, TransportPart};

use super::holdout::{self, Score};
use super::linop::{LinearOperator, spectral_norm};
use super::ops::{
    BernoulliOperator, CentredOperator, HadamardOperator, RasterOperator, RowSubset,
    SpeckleOperator,
};
use super::transforms::TransformKind;
use super::{Control, ReconError, Report, SourceError};
use batch::Shared;

/// The camera's pixel grid: `m = width * height` rows of `T`, row-major.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CameraGrid {
    pub width: u32,
    pub height: u32,
}

impl CameraGrid {
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// The frames of a session, read one block of camera pixels at a time (may re-read storage).
pub trait FrameSource {
    /// Frames 0..rows restricted to camera pixels `pixels` (row-major camera pixel indices):
    /// row-major `rows x pixels.len()` f32 values.
    fn read_pixels(&mut self, pixels: Range<usize>) -> Result<Vec<f32>, SourceError>;
}

/// Frames already in memory (`rows x m` f32, row-major): tests, benchmarks. Records the
/// largest request it served.
pub struct SliceFrames<'a> {
    frames: &'a [f32],
    pixels: usize,
    /// Requests served, in order.
    pub reads: Vec<Range<usize>>,
    /// Largest request in bytes (`rows * pixels.len() * 4`).
    pub largest_read_bytes: usize,
}

impl<'a> SliceFrames<'a> {
    pub fn new(frames: &'a [f32], pixels: usize) -> Self {
        assert!(
            pixels > 0 && frames.len().is_multiple_of(pixels),
            "frames must be rows x pixels"
        );
        SliceFrames {
            frames,
            pixels,
            reads: Vec::new(),
            largest_read_bytes: 0,
        }
    }
}

impl FrameSource for SliceFrames<'_> {
    fn read_pixels(&mut self, pixels: Range<usize>) -> Result<Vec<f32>, SourceError> {
        if pixels.end > self.pixels || pixels.start > pixels.end {
            return Err(SourceError(format!(
                "camera pixels {pixels:?} outside 0..{}",
                self.pixels
            )));
        }
        let rows = self.frames.len() / self.pixels;
        let mut out = Vec::with_capacity(rows * pixels.len());
        for frame in self.frames.chunks_exact(self.pixels) {
            out.extend_from_slice(&frame[pixels.clone()]);
        }
        self.largest_read_bytes = self.largest_read_bytes.max(out.len() * 4);
        self.reads.push(pixels);
        Ok(out)
    }
}

/// The family's operator, planned once; its rows are the "raw" rows (frames, or split pairs).
enum Raw {
    Hadamard(HadamardOperator),
    Raster(RasterOperator),
    Bernoulli(CentredOperator<BernoulliOperator>),
    Speckle(CentredOperator<SpeckleOperator>),
}

/// An operator a fit runs on and how its data come from raw rows.
enum Fitting {
    Plain(Box<dyn LinearOperator>),
    Centred(CentredOperator),
}

impl Fitting {
    fn op(&self) -> &dyn LinearOperator {
        match self {
            Fitting::Plain(op) => op.as_ref(),
            Fitting::Centred(op) => op,
        }
    }
    fn data(&self, raw: &[f64]) -> Vec<f64> {
        match self {
            Fitting::Plain(_) => raw.to_vec(),
            Fitting::Centred(op) => op.centre_data(raw),
        }
    }
}

struct Plan<'a> {
    spec: &'a PatternSpec,
    /// The projector grid `T` is reconstructed on: the session's, or coarser by `binning`.
    grid: (u32, u32),
    binning: u32,
    /// Binned Hadamard: the session's pair each row of the operator reads.
    pairs: Option<Vec<usize>>,
    /// Frames used (Hadamard: whole pairs).
    frames: usize,
    /// Frames every read returns per camera pixel (the session's rows).
    rows_read: usize,
    raw: Raw,
    exact: bool,
    /// Raster exact inverse: how often each pixel is lit.
    raster_counts: Option<Vec<f64>>,
}

impl<'a> Plan<'a> {
    fn new(spec: &'a PatternSpec, rows: usize, binning: u32) -> Result<Self, ReconError> {
        let k = spec.pixels();
        let unsolvable = |e: super::ops::OpError| ReconError::Unsolvable(e.to_string());
        let b = binning.max(1);
        if let Err(e) = config::check_binning(spec, b) {
            return Err(ReconError::Unsolvable(e.to_string()));
        }
        Ok(match spec.family() {
            Family::AdaptiveHaar { .. } => {
                return Err(ReconError::Unsolvable(
                    "transport (camera) reconstruction of adaptive_haar sessions is not supported: \
                     a camera rig's adaptive session should use adaptive_hadamard"
                        .into(),
                ));
            }
            // adaptive_hadamard: the Hadamard operator on the session's natural indices.
            Family::Hadamard { .. } | Family::AdaptiveHadamard { .. } => {
                let frames = rows - rows % 2;
                if frames == 0 {
                    return Err(ReconError::Unsolvable(
                        "Hadamard needs at least one P+/P- pair of frames; the session has 1 frame"
                            .into(),
                    ));
                }
                let op = HadamardOperator::from_spec(spec, frames as u64).map_err(unsolvable)?;
                let (op, pairs) = if b > 1 {
                    let (w, h, bu) = (spec.width() as usize, spec.height() as usize, b as usize);
                    // Walsh function (u, v) is constant on b x b blocks when b divides u and v,
                    // and then it is the coarse grid's (u / b, v / b).
                    let (mut natural, mut pairs) = (Vec::new(), Vec::new());
                    for (r, &n) in op.natural_indices().iter().enumerate() {
                        let (u, v) = (n / w, n % w);
                        if u % bu == 0 && v % bu == 0 {
                            natural.push((u / bu) * (w / bu) + v / bu);
                            pairs.push(r);
                        }
                    }
                    if natural.is_empty() {
                        return Err(ReconError::Unsolvable(format!(
                            "no measured pair is constant on {b}x{b} projector blocks: none measures the {}x{} grid",
                            w / bu,
                            h / bu
                        )));
                    }
                    (
                        HadamardOperator::with_natural(
                            spec.width() / b,
                            spec.height() / b,
                            natural,
                        ),
                        Some(pairs),
                    )
                } else {
                    (op, None)
                };
                let exact = op.rows() >= k / (b as usize * b as usize);
                Plan {
                    spec,
                    grid: (spec.width() / b, spec.height() / b),
                    binning: b,
                    pairs,
                    rows_read: rows,
                    frames,
                    raw: Raw::Hadamard(op),
                    exact,
                    raster_counts: None,
                }
            }
            Family::Raster { block, .. } => {
                let op = RasterOperator::from_spec(spec, rows as u64).map_err(unsolvable)?;
                let exact = *block == 1 && rows >= k;
                let raster_counts = exact.then(|| {
                    let mut c = vec![0.0; k];
                    op.adjoint(&vec![1.0; rows], &mut c);
                    c
                });
                Plan {
                    spec,
                    grid: (spec.width(), spec.height()),
                    binning: 1,
                    pairs: None,
                    rows_read: rows,
                    frames: rows,
                    raw: Raw::Raster(op),
                    exact,
                    raster_counts,
                }
            }
            Family::Bernoulli { .. } => {
                let op = BernoulliOperator::from_spec(spec, rows as u64).map_err(unsolvable)?;
                Plan {
                    spec,
                    grid: (spec.width(), spec.height()),
                    binning: 1,
                    pairs: None,
                    rows_read: rows,
                    frames: rows,
                    raw: Raw::Bernoulli(CentredOperator::augmented(Box::new(op))),
                    exact: false,
                    raster_counts: None,
                }
            }
            Family::Speckle { .. } => {
                let op = SpeckleOperator::from_spec(spec, rows as u64).map_err(unsolvable)?;
                Plan {
                    spec,
                    grid: (spec.width(), spec.height()),
                    binning: 1,
                    pairs: None,
                    rows_read: rows,
                    frames: rows,
                    raw: Raw::Speckle(CentredOperator::augmented(Box::new(op))),
                    exact: false,
                    raster_counts: None,
                }
            }
        })
    }

    fn k(&self) -> usize {
        self.grid.0 as usize * self.grid.1 as usize
    }

    /// The reconstruction's projector grid, as `usize`.
    fn size(&self) -> (usize, usize) {
        (self.grid.0 as usize, self.grid.1 as usize)
    }

    /// The session's pair operator row `r` reads.
    fn pair(&self, r: usize) -> usize {
        self.pairs.as_ref().map_or(r, |p| p[r])
    }

    /// Split-pair sums `y+ + y-` of camera pixel `col` of a frame block (`rows x width`), one
    /// per operator row.
    fn pair_sums(&self, frames: &[f32], width: usize, col: usize) -> Vec<f64> {
        (0..self.raw_rows())
            .map(|r| {
                let p = self.pair(r);
                frames[2 * p * width + col] as f64 + frames[(2 * p + 1) * width + col] as f64
            })
            .collect()
    }

    /// The operator the fits on all rows run on.
    fn op(&self) -> &dyn LinearOperator {
        match &self.raw {
            Raw::Hadamard(op) => op,
            Raw::Raster(op) => op,
            Raw::Bernoulli(op) => op,
            Raw::Speckle(op) => op,
        }
    }

    /// Raw rows: split pairs for Hadamard, frames otherwise.
    fn raw_rows(&self) -> usize {
        match &self.raw {
            Raw::Hadamard(op) => op.rows(),
            _ => self.frames,
        }
    }

    /// Raw data of camera pixel `col` of a frame block (`rows x width` f32).
    fn raw_column(&self, frames: &[f32], width: usize, col: usize) -> Vec<f64> {
        let at = |f: usize| frames[f * width + col] as f64;
        match &self.raw {
            Raw::Hadamard(op) => {
                // Binned: a block-constant pair's datum on the coarse grid, `sqrt(k / k_coarse)`
                // times its fine one: `(y+ - y-) / sqrt(k_coarse)`.
                let scale = 1.0 / (self.k() as f64).sqrt();
                (0..op.rows())
                    .map(|r| {
                        let p = self.pair(r);
                        (at(2 * p) - at(2 * p + 1)) * scale
                    })
                    .collect()
            }
            _ => (0..self.frames).map(at).collect(),
        }
    }

    /// The data of the full operator from raw data.
    fn fit_data(&self, raw: &[f64]) -> Vec<f64> {
        match &self.raw {
            Raw::Bernoulli(op) => op.centre_data(raw),
            Raw::Speckle(op) => op.centre_data(raw),
            _ => raw.to_vec(),
        }
    }

    /// Bytes the planned operator holds.
    fn op_bytes(&self) -> usize {
        let k = self.k();
        match &self.raw {
            Raw::Hadamard(op) => op.rows() * 8,
            Raw::Raster(_) => k * 4,
            Raw::Bernoulli(op) => op.inner().memory_bytes() + k * 8,
            Raw::Speckle(op) => op.inner().memory_bytes() + k * 8,
        }
    }

    /// Whether the rows of `op` (this plan's operator or its fitting rows) are solved by
    /// coordinate descent on `A Psi^T` held densely ([`batch::Dense`]): random patterns (no fast
    /// transform to apply them by) where it takes at most [`DENSE_MAX_BYTES`] and a quarter of
    /// the memory `budget`.
    fn dense_pays(&self, op: &dyn LinearOperator, budget: usize) -> bool {
        matches!(self.raw, Raw::Bernoulli(_) | Raw::Speckle(_))
            && batch::Dense::bytes(op.rows(), op.cols()) <= DENSE_MAX_BYTES.min(budget / 4)
    }

    /// Whether refits on the operator run CGLS ([`batch::Shared::cgls_refit`]): Hadamard pairs.
    fn cgls_refit(&self) -> bool {
        matches!(self.raw, Raw::Hadamard(_))
    }

    /// `L >= ||A||^2` for a fitting operator: 1 for Hadamard split pairs (orthonormal rows),
    /// else the power-iteration estimate with a 2 % margin.
    fn lipschitz(&self, op: &dyn LinearOperator) -> f64 {
        match &self.raw {
            Raw::Hadamard(_) => 1.0,
            _ => {
                let s = spectral_norm(op, 500, 1e-7);
                (s * s * 1.02).max(f64::MIN_POSITIVE)
            }
        }
    }

    /// Fitting operator on the `train` raw rows and the plain operator of the `test` rows.
    fn holdout_ops(
        &self,
        split: &holdout::Split,
    ) -> Result<(Fitting, Box<dyn LinearOperator>), ReconError> {
        let unsolvable = |e: super::ops::OpError| ReconError::Unsolvable(e.to_string());
        Ok(match &self.raw {
            Raw::Hadamard(op) => (
                Fitting::Plain(Box::new(op.select_rows(&split.train))),
                Box::new(op.select_rows(&split.test)),
            ),
            Raw::Bernoulli(op) => (
                Fitting::Centred(CentredOperator::augmented(Box::new(
                    op.inner().select_rows(&split.train),
                ))),
                Box::new(op.inner().select_rows(&split.test)),
            ),
            Raw::Raster(_) => {
                let full =
                    || RasterOperator::from_spec(self.spec, self.frames as u64).map_err(unsolvable);
                (
                    Fitting::Plain(Box::new(RowSubset::new(
                        Box::new(full()?) as Box<dyn LinearOperator>,
                        split.train.clone(),
                    ))),
                    Box::new(RowSubset::new(
                        Box::new(full()?) as Box<dyn LinearOperator>,
                        split.test.clone(),
                    )),
                )
            }
            Raw::Speckle(_) => {
                let full = || {
                    SpeckleOperator::from_spec(self.spec, self.frames as u64).map_err(unsolvable)
                };
                let train: Box<dyn LinearOperator> = Box::new(RowSubset::new(
                    Box::new(full()?) as Box<dyn LinearOperator>,
                    split.train.clone(),
                ));
                (
                    Fitting::Centred(CentredOperator::augmented(train)),
                    Box::new(RowSubset::new(
                        Box::new(full()?) as Box<dyn LinearOperator>,
                        split.test.clone(),
                    )),
                )
            }
        })
    }

    /// Exact inverse of raw data (complete sets only).
    fn exact_inverse(&self, raw: &[f64]) -> Vec<f64> {
        let mut t = vec![0.0; self.k()];
        self.op().adjoint(raw, &mut t);
        if let Some(counts) = &self.raster_counts {
            t.iter_mut().zip(counts).for_each(|(v, c)| *v /= c);
        }
        t
    }
}

/// How the working set is split (see [`plan_memory`]).
#[derive(Clone, Debug)]
struct MemoryPlan {
    budget: usize,
    fixed: usize,
    per_pixel: usize,
    scratch: usize,
    block_pixels: usize,
    chunk: usize,
}

/// Splits `budget` into the fixed part (operator, twice while the model is chosen on held-out
/// rows; transform and per-thread operator scratch), the solver scratch of every thread
/// (`threads x chunk` rows iterating at once) and the per-camera-pixel part of a block (its
/// frames as f32, raw and fitted data, solution, coarse-to-fine parent share).
fn plan_memory(
    plan: &Plan,
    budget: usize,
    m: usize,
    selecting: bool,
    coarse: bool,
) -> Result<MemoryPlan, ReconError> {
    let (k, n, raw_rows) = (plan.k(), plan.op().rows(), plan.raw_rows());
    let threads = rayon::current_num_threads().max(1);
    let copies = if selecting { 2 } else { 1 };
    let mut fixed = plan.op_bytes() * copies + 8 * k * (threads + 2);
    if !plan.exact && plan.dense_pays(plan.op(), budget) {
        // `A Psi^T` held densely ([`batch::Dense`]): the fitting rows' while the model is
        // chosen, then all rows'.
        fixed += batch::Dense::bytes(n, k) * copies;
    }
    let mut per_pixel = 4 * plan.frames + 8 * raw_rows + 8 * n + 8 * k;
    if plan.exact {
        // The block's rows, their coefficients and which of them are kept.
        per_pixel += 17 * k;
    } else if matches!(plan.raw, Raw::Hadamard(_)) {
        // The coarse coefficients a subset may measure completely ([`CoarseExact::apply`]: a
        // quarter of the row at most) and which of them are kept.
        per_pixel += (9 * k).div_ceil(4);
    }
    if coarse {
        per_pixel += (8 * n + 8 * k).div_ceil(4);
    }
    let scratch_row = if plan.exact {
        16 * k
    } else {
        Shared::scratch_bytes_per_row(k, n)
    };
    let mut chunk = 16usize;
    while chunk > 1 && fixed + threads * chunk * scratch_row + per_pixel > budget {
        chunk /= 2;
    }
    let scratch = threads * chunk * scratch_row;
    let need = fixed + scratch + per_pixel;
    if need > budget {
        return Err(ReconError::Unsolvable(format!(
            "the memory budget of {budget} bytes is too small for this session: one camera pixel at a time needs {need} bytes \
             ({fixed} for the {} operator, {scratch} solver scratch, {per_pixel} per camera pixel for {} frames and {k} projector pixels)",
            plan.spec.family().name(),
            plan.frames
        )));
    }
    let block_pixels = ((budget - fixed - scratch) / per_pixel).min(m).max(1);
    let chunk = chunk.min(block_pixels.div_ceil(threads)).max(1);
    Ok(MemoryPlan {
        budget,
        fixed,
        per_pixel,
        scratch,
        block_pixels,
        chunk,
    })
}

/// Reads camera pixels `range`, checking the length.
fn read(
    source: &mut dyn FrameSource,
    range: Range<usize>,
    rows: usize,
    largest: &mut usize,
) -> Result<Vec<f32>, ReconError> {
    let len = range.len();
    let values = source.read_pixels(range.clone())?;
    if values.len() != rows * len {
        return Err(ReconError::BadRows(format!(
            "the frame source returned {} values for camera pixels {range:?}, expected {rows} frames x {len} pixels = {} \
             (frames of the wrong length for the camera grid?)",
            values.len(),
            rows * len
        )));
    }
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(ReconError::BadRows(format!(
            "frame {} has a non-finite value at camera pixel {}",
            i / len,
            range.start + i % len
        )));
    }
    *largest = (*largest).max(values.len() * 4);
    Ok(values)
}

/// Up to 8 runs of camera pixels spread evenly over `0..m`, `sample` pixels in all.
fn sample_ranges(m: usize, sample: usize) -> Vec<Range<usize>> {
    let sample = sample.clamp(1, m);
    let runs = sample.min(8);
    let base = sample / runs;
    let mut out = Vec::with_capacity(runs);
    for r in 0..runs {
        let len = base + usize::from(r < sample % runs);
        let slot = (r * m / runs, (r + 1) * m / runs);
        let start = slot.0 + (slot.1 - slot.0).saturating_sub(len) / 2;
        out.push(start..(start + len).min(m));
    }
    out
}

/// The energy of a camera pixel's data: the sum of squares of its split-pair differences
/// (Hadamard), else of its frames about their mean.
fn data_energy(plan: &Plan, raw: &[f64]) -> f64 {
    match plan.raw {
        Raw::Hadamard(_) => raw.iter().map(|v| v * v).sum(),
        _ => {
            let mean = raw.iter().sum::<f64>() / raw.len().max(1) as f64;
            raw.iter().map(|v| (v - mean) * (v - mean)).sum()
        }
    }
}

/// The camera pixels the model is chosen on, `sample` of them in two halves: one drawn with
/// probability in proportion to the energy of their data (systematic sampling over the
/// cumulative energy, a deterministic function of the data; one pass over the session in blocks
/// of `block` pixels), so a scene that lights a third of the camera is judged on lit pixels,
/// the ones a relight sums; the other the evenly spread runs of [`sample_ranges`], so the
/// choice also sees the camera as it is (on energy alone, a 10 % Bernoulli session of the
/// relief chose a nearly dense pixel-basis fit that predicted the bright pixels' held-out rows
/// slightly better and was 7 dB worse in relighting). Sorted, each with its relative chance of
/// being drawn (`energy / total / 2 + 1 / m / 2`, for weighting back to the whole camera).
fn energy_sample(
    plan: &Plan,
    source: &mut dyn FrameSource,
    m: usize,
    block: usize,
    sample: usize,
    largest: &mut usize,
    control: &Control,
) -> Result<Vec<(usize, f64)>, ReconError> {
    let sample = sample.clamp(1, m);
    let mut energy = Vec::with_capacity(m);
    for r in blocks(m, block, None) {
        if control.is_cancelled() {
            return Err(ReconError::Cancelled);
        }
        let f = read(source, r.clone(), plan.rows_read, largest)?;
        for c in 0..r.len() {
            energy.push(data_energy(plan, &plan.raw_column(&f, r.len(), c)));
        }
    }
    let mut picked = vec![false; m];
    for j in sample_ranges(m, sample / 2).into_iter().flatten() {
        picked[j] = true;
    }
    let runs = picked.iter().filter(|p| **p).count();
    let mut count = runs;
    // Pixels heavier than the step are drawn once; the draw is repeated over the rest.
    while count < sample {
        let total: f64 = (0..m).filter(|&j| !picked[j]).map(|j| energy[j]).sum();
        if total <= 0.0 {
            break;
        }
        let want = sample - count;
        let step = total / want as f64;
        let mut next = 0.5 * step;
        let mut cum = 0.0;
        let before = count;
        for j in 0..m {
            if picked[j] || energy[j] <= 0.0 {
                continue;
            }
            cum += energy[j];
            if cum > next {
                picked[j] = true;
                count += 1;
                next += step * ((cum - next) / step).ceil().max(1.0);
            }
        }
        if count == before {
            break;
        }
    }
    if count < sample {
        // Too few pixels carry energy: the runs make up the rest.
        for j in sample_ranges(m, sample).into_iter().flatten() {
            if count < sample && !picked[j] {
                picked[j] = true;
                count += 1;
            }
        }
    }
    let total: f64 = energy.iter().sum();
    Ok((0..m)
        .filter(|&j| picked[j])
        .map(|j| {
            let share = if total > 0.0 { energy[j] / total } else { 0.0 };
            (j, 0.5 * share + 0.5 / m as f64)
        })
        .collect())
}

/// Raw data per camera pixel, and (Hadamard) split-pair sums per camera pixel.
type Columns = (Vec<Vec<f64>>, Vec<Vec<f64>>);

/// The raw data of camera pixels `picked` (sorted), read block by block, and (Hadamard) their
/// split-pair sums `y+ + y-` (empty otherwise).
fn read_columns(
    plan: &Plan,
    source: &mut dyn FrameSource,
    picked: &[usize],
    block: usize,
    largest: &mut usize,
) -> Result<Columns, ReconError> {
    let mut out = Vec::with_capacity(picked.len());
    let mut sums = Vec::new();
    let mut at = 0;
    while at < picked.len() {
        let start = picked[at];
        let end = (start + block.max(1)).min(picked[picked.len() - 1] + 1);
        let r = start..end;
        let f = read(source, r.clone(), plan.rows_read, largest)?;
        while at < picked.len() && picked[at] < end {
            let col = picked[at] - start;
            out.push(plan.raw_column(&f, r.len(), col));
            if matches!(plan.raw, Raw::Hadamard(_)) {
                sums.push(plan.pair_sums(&f, r.len(), col));
            }
            at += 1;
        }
    }
    Ok((out, sums))
}

/// The error of `T` from a Hadamard subset, estimated on the sample pixels (drawn in
/// proportion to `chance`): each row fitted with the chosen model on all measured pairs, its
/// error estimated as a bucket image's is ([`crate::auto::orthonormal_error`]: the residual on
/// the measured coefficients less the noise the pair sums show, plus the scene's energy in the
/// unmeasured coefficients extrapolated across the measured scale orders, against the row's
/// own), then pooled with weights `1 / chance` (the draw's inverse probability): the relative
/// error of the whole `T`. `None` for other families, or when no row could be judged.
#[allow(clippy::too_many_arguments)]
/// A Hadamard subset's relative error of T, pooled over sample pixels ([`subset_error`]).
struct SubsetError {
    relative: f64,
    range: (f64, f64),
    judged: usize,
}

/// The relative error of the rows `t` (one per sample pixel, fitted by any model on any of the
/// measured pairs) estimated from all the measured pairs `raws` (split-pair data of `op`'s rows)
/// and their sums: each row's residual on every measured coefficient less the noise its pair
/// sums show, plus the scene's energy in the unmeasured coefficients extrapolated from the
/// measured scale orders, against the row's own there (`auto::orthonormal_error`). Rows are
/// pooled by their squared norms with weights 1 / (their chance of being drawn). `None` when no
/// row can be judged (no noise estimate, or no energy).
fn subset_error(
    op: &HadamardOperator,
    (raws, sums, chance): (&[Vec<f64>], &[Vec<f64>], &[f64]),
    t: &[f64],
) -> Option<SubsetError> {
    let (pw, ph) = (op.width() as usize, op.height() as usize);
    let k = pw * ph;
    let measured = op.natural_indices();
    let scale = 1.0 / (k as f64).sqrt();
    let (mut e2, mut lo2, mut hi2, mut norm2, mut judged) = (0.0, 0.0, 0.0, 0.0, 0usize);
    for (((raw, sum), &e), row) in raws.iter().zip(sums).zip(chance).zip(t.chunks_exact(k)) {
        if e <= 0.0 {
            continue;
        }
        let noise = super::noise::from_pair_sums(sum, scale, raw);
        let Some(est) = super::auto::orthonormal_error(
            measured,
            noise.as_ref(),
            (op, raw, (pw, ph)),
            row,
            None,
        ) else {
            continue;
        };
        let (Some(rel), Some((lo, hi))) = (est.relative_error, est.relative_error_range) else {
            continue;
        };
        let n2: f64 = row.iter().map(|v| v * v).sum();
        let w = 1.0 / e;
        e2 += w * rel * rel * n2;
        lo2 += w * lo * lo * n2;
        hi2 += w * hi * hi * n2;
        norm2 += w * n2;
        judged += 1;
    }
    if judged == 0 || norm2 <= 0.0 {
        return None;
    }
    Some(SubsetError {
        relative: (e2 / norm2).sqrt(),
        range: ((lo2 / norm2).sqrt(), (hi2 / norm2).sqrt()),
        judged,
    })
}

/// A Hadamard subset's total-light error: how far the fitted rows' sums `1 . t_j` fall from the
/// measured ones (the all-on pattern, natural row 0, is a measured pair: `d_0 = 1 . t / sqrt(k)`),
/// summed over the sample pixels with weights 1 / their chance of being drawn, relative to the
/// measured sum; and the standard error of that ratio from the rows' noise (their pair sums).
/// Light a model drops in every row (a lasso shrinking a dense, dim interreflection) adds up in
/// every relight; a per-row error of T counts it once per row. `None` without the all-on pair.
fn subset_light_error(
    op: &HadamardOperator,
    (raws, sums, chance): (&[Vec<f64>], &[Vec<f64>], &[f64]),
    t: &[f64],
) -> Option<(f64, f64)> {
    let k = op.cols();
    let dc = op.natural_indices().iter().position(|&n| n == 0)?;
    let root = (k as f64).sqrt();
    let (mut fitted, mut measured, mut var) = (0.0, 0.0, 0.0);
    for (j, (raw, row)) in raws.iter().zip(t.chunks_exact(k)).enumerate() {
        if chance[j] <= 0.0 {
            continue;
        }
        let w = 1.0 / chance[j];
        fitted += w * row.iter().sum::<f64>();
        measured += w * root * raw[dc];
        if let Some(n) = super::noise::from_pair_sums(&sums[j], 1.0 / root, raw) {
            var += (w * root * n.sigma).powi(2);
        }
    }
    (measured > 0.0).then(|| ((fitted - measured).abs() / measured, var.sqrt() / measured))
}

/// The full-light relight error `||(T_hat - T)^T 1|| / ||T^T 1||` of a fit to random 0/1 frames
/// (fill `f`), estimated from its held-out frames, which the fit never saw. A held-out frame's
/// residual in camera pixel `j` is `r_ij = -(E p_i)_j + n_ij` (`E = T_hat - T`), so its sum over
/// the camera is `g_i = -e . p_i + noise`, `e = E^T 1` the error of the full-light relight; over
/// the frames `Var(g) = f (1 - f) ||e||^2 + m sigma^2`. The errors of neighbouring rows are
/// correlated (a lasso drops the same dim light in every row), so the relight error is not the
/// rows' errors summed in quadrature; this sees it.
///
/// The sum comes from the sample pixels ([`energy_sample`]) in clusters, each a run of
/// neighbouring pixels drawn together, weighted by `1 / pi_c` (`pi_c`, its chance of being
/// drawn): `g_i = sum_c R_ci`. That estimate's own scatter over draws of the sample,
/// `sum (1 - pi_c) / pi_c ||E_c||^2`, and the noise (`sigma` per camera pixel,
/// [`random_noise_sigma`]) are taken off:
/// `f (1 - f) ||e||^2 = Var(g) - sum_c (1 - pi_c) Var(R_c) - sum_c pi_c sum_(j in c) w_j^2 sigma^2`.
/// The norm `||T^T 1||` comes from the fitted sample rows the same way. The standard error is
/// the jackknife's over the held-out frames; `upper` is two of them above the estimate (taken
/// at 0 where it is negative: the fit chosen for its held-out score is the one these frames
/// favour most, so its estimate leans low, and on glossy spheres with 3 % frame noise it came
/// out below 0 by more than two standard errors, a bound of 0 against a true 0.0148), and
/// the estimate is `resolved` when it is more than two above 0 (otherwise it is the noise of
/// the few held-out frames, which the noise of the frames and the weights of dim pixels
/// amplify, and only `upper` says something). It is the error of the fit without the held-out
/// frames: the served fit, on all frames, is at least as good on average. `None` with fewer
/// than [`holdout::MIN_HELD_OUT`] held-out frames or no light.
fn random_relight_error(
    (observed, pred, h): (&[Vec<f64>], &[f64], usize),
    t: &[f64],
    k: usize,
    (picked, chance): (&[usize], &[f64]),
    fill: f64,
    sigma: f64,
) -> Option<RelightEstimate> {
    let residuals: Vec<Vec<f64>> = observed
        .iter()
        .enumerate()
        .map(|(c, o)| {
            o.iter()
                .zip(&pred[c * h..(c + 1) * h])
                .map(|(o, p)| o - p)
                .collect()
        })
        .collect();
    relight_from_residuals(&residuals, t, k, (picked, chance), fill, sigma)
}

/// [`random_relight_error`] from the sample rows' residuals on `h` frames no fit of theirs saw
/// (`residuals[c]`, observed less predicted), `t` the sample rows' fit (for the relight's norm).
fn relight_from_residuals(
    residuals: &[Vec<f64>],
    t: &[f64],
    k: usize,
    (picked, chance): (&[usize], &[f64]),
    fill: f64,
    sigma: f64,
) -> Option<RelightEstimate> {
    let rows = residuals.len();
    let h = residuals.first().map_or(0, Vec::len);
    let v = fill * (1.0 - fill);
    if h < holdout::MIN_HELD_OUT || rows == 0 || v <= 0.0 || !v.is_finite() {
        return None;
    }
    // Clusters: (pi_c, the weighted residuals R_c over the held-out frames).
    let mut clusters: Vec<(f64, Vec<f64>)> = Vec::new();
    let mut relit = vec![0.0; k];
    let (mut noise, mut relit_scatter) = (0.0, 0.0);
    let mut j = 0;
    while j < rows {
        let mut end = j + 1;
        while end < rows && picked[end] == picked[end - 1] + 1 {
            end += 1;
        }
        let mut rc = vec![0.0; h];
        let mut tc = vec![0.0; k];
        let (mut pis, mut w2) = (0.0, 0.0);
        for c in j..end {
            let pi = (rows as f64 * chance[c]).min(1.0);
            if pi <= 0.0 {
                continue;
            }
            let w = 1.0 / pi;
            rc.iter_mut()
                .zip(&residuals[c])
                .for_each(|(r, e)| *r += w * e);
            tc.iter_mut()
                .zip(&t[c * k..(c + 1) * k])
                .for_each(|(a, b)| *a += w * b);
            pis += pi;
            w2 += w * w;
        }
        let pi = (pis / (end - j) as f64).min(1.0);
        noise += pi * w2 * sigma * sigma;
        relit.iter_mut().zip(&tc).for_each(|(a, b)| *a += b);
        relit_scatter += (1.0 - pi) * tc.iter().map(|x| x * x).sum::<f64>();
        clusters.push((pi, rc));
        j = end;
    }
    let norm2 = relit.iter().map(|x| x * x).sum::<f64>() - relit_scatter;
    if norm2 <= 0.0 || !norm2.is_finite() {
        return None;
    }
    // `f (1 - f) ||e||^2` from all held-out frames and from all but each one (the jackknife),
    // each series' variance from its sums (centred first) less the dropped frame's terms.
    let hf = h as f64;
    let g: Vec<f64> = (0..h)
        .map(|i| clusters.iter().map(|c| c.1[i]).sum())
        .collect();
    let gm = Moments::new(&g);
    let cm: Vec<(f64, Moments)> = clusters
        .iter()
        .map(|(pi, rc)| (*pi, Moments::new(rc)))
        .collect();
    let estimate = |skip: Option<usize>| {
        let scatter: f64 = cm.iter().map(|(pi, m)| (1.0 - pi) * m.variance(skip)).sum();
        gm.variance(skip) - scatter - noise
    };
    let all = estimate(None);
    let drops: Vec<f64> = (0..h).map(|i| estimate(Some(i))).collect();
    let mean = drops.iter().sum::<f64>() / hf;
    let se = ((hf - 1.0) / hf * drops.iter().map(|d| (d - mean).powi(2)).sum::<f64>()).sqrt();
    let relative = |x: f64| (x.max(0.0) / v / norm2).sqrt();
    Some(RelightEstimate {
        relative: relative(all),
        upper: relative(all.max(0.0) + 2.0 * se),
        resolved: all > 2.0 * se,
        norm2,
        noise: None,
        folds: 0,
    })
}

/// Folds of the cross-validated relight error ([`random_cv_relight_error`]).
const RELIGHT_FOLDS: usize = 8;

/// The bound on a relight's relative error below which an unresolved held-out estimate is left
/// as it is: the folds cost a third of the reconstruction on a 64x64 x 32x32 Bernoulli session
/// (relief, noise-free: 30 s -> 45 s, where the bound was 0.0007) and would only refine a figure
/// already under 1 %.
const RELIGHT_CROSS_VALIDATE_ABOVE: f64 = 0.01;

/// A random-pattern session's sample rows and the chosen model, for the relight error's
/// cross-validation and bootstrap ([`random_cv_relight_error`], [`random_bootstrap_noise`]):
/// each sample row's raw data on every frame, the rows' camera pixels and chances of being
/// drawn ([`energy_sample`]), the patterns' fill and the frames' noise.
#[derive(Clone, Copy)]
struct RelightSample<'a, 'p> {
    plan: &'a Plan<'p>,
    model: &'a ModelChoice,
    raws: &'a [Vec<f64>],
    picked: &'a [usize],
    chance: &'a [f64],
    fill: f64,
    sigma: f64,
    config: &'a TransportConfig,
    chunk: usize,
    control: &'a Control,
}

/// The sample rows fitted with a chosen model on a random-pattern fitting operator `op` (data
/// `bs`, rows x `op.rows()`, of `frames` raw frames): down the continuation path from zero,
/// refitted and compacted as chosen, with the model's noise floor ([`random_noise_floor`] on
/// these frames). Returns the images (rows x k).
fn fit_sample(
    sample: &RelightSample,
    (op, bs, frames): (&dyn LinearOperator, &[f64], usize),
) -> Result<Vec<f64>, ReconError> {
    let RelightSample {
        plan,
        model,
        fill,
        sigma,
        config,
        chunk,
        control,
        ..
    } = *sample;
    let (pw, ph) = plan.size();
    let k = plan.k();
    let rows = bs.len() / op.rows().max(1);
    let psi = model.kind.build(pw, ph);
    let free = free_coefficients(model.kind);
    let mut sh = Shared {
        op,
        dense: None,
        psi: psi.as_ref(),
        identity: model.kind == TransformKind::Identity,
        lipschitz: plan.lipschitz(op),
        free,
        max_iter: config.max_iter,
        tol: config.tol,
        cgls_refit: plan.cgls_refit(),
    };
    let dense = plan
        .dense_pays(op, config.memory_budget_bytes)
        .then(|| batch::Dense::new(&sh));
    sh.dense = dense.as_ref();
    let floors = if model.floored {
        vec![random_floor(sigma, frames, fill, k); rows]
    } else {
        Vec::new()
    };
    let mut tally = Tally::default();
    let mut s = solve_block(
        &sh,
        (bs, &floors),
        model.lambda,
        None,
        chunk,
        &mut tally,
        control,
    )?;
    if model.refit {
        batch::refit_rows(&sh, bs, &mut s, chunk, control)?;
    }
    let ones = constant_coefficients(model.kind, (pw, ph));
    for &share in &model.prune {
        prune_rows(&mut s, k, share, free, &ones);
        batch::refit_rows(&sh, bs, &mut s, chunk, control)?;
    }
    let mut t = vec![0.0; rows * k];
    sh.inverse(&s, &mut t);
    Ok(t)
}

/// The chosen model's full-light relight error by cross-validation over every frame: the
/// frames fall in [`RELIGHT_FOLDS`] folds (frame `i` in fold `i mod folds`); the sample rows are
/// fitted with the chosen model on all folds but one ([`fit_sample`], each fold from zero: a
/// warm start from another fold's fit, which saw this fold's frames, leaked them, measured on
/// the Cornell box: 0.017 against a true 0.027, where cold folds gave 0.039) and predict that
/// one, so every frame's residual comes from a fit that never saw it, and the estimate of
/// [`random_relight_error`] runs on all `n` frames instead of the few held out for the
/// choice. Its scatter is the frames' noise summed over the camera (`m sigma^2` a frame) over
/// `sqrt(n)`: the choice's held-out frames alone (a sixteenth of 256) did not resolve the
/// Cornell box's 4 % relight error under 1 % frame noise. Each fold's fit has `1 - 1 / folds`
/// of the frames, so the estimate leans high. With noisy frames it carries the fit's own noise
/// ([`random_bootstrap_noise`]). `None` for anything but Bernoulli frames, or fewer than two
/// frames a fold.
fn random_cv_relight_error(sample: &RelightSample) -> Result<Option<RelightEstimate>, ReconError> {
    let RelightSample {
        plan,
        raws,
        picked,
        chance,
        fill,
        sigma,
        control,
        ..
    } = *sample;
    let Raw::Bernoulli(_) = &plan.raw else {
        return Ok(None);
    };
    let n = plan.raw_rows();
    let rows = raws.len();
    if rows == 0 || n < 2 * RELIGHT_FOLDS {
        return Ok(None);
    }
    let k = plan.k();
    let mut residuals = vec![vec![0.0; n]; rows];
    let mut relit_fit = vec![0.0; rows * k];
    for fold in 0..RELIGHT_FOLDS {
        if control.is_cancelled() {
            return Err(ReconError::Cancelled);
        }
        let split = holdout::Split {
            fraction: 1.0 / RELIGHT_FOLDS as f64,
            train: (0..n).filter(|i| i % RELIGHT_FOLDS != fold).collect(),
            test: (0..n).filter(|i| i % RELIGHT_FOLDS == fold).collect(),
        };
        let (train, test) = plan.holdout_ops(&split)?;
        let mut bs = Vec::with_capacity(rows * train.op().rows());
        for raw in raws {
            let train_raw: Vec<f64> = split.train.iter().map(|&i| raw[i]).collect();
            bs.extend(train.data(&train_raw));
        }
        let t = fit_sample(sample, (train.op(), &bs, split.train.len()))?;
        let h = test.rows();
        let mut pred = vec![0.0; rows * h];
        test.apply_batch(&t, &mut pred, rows);
        for (c, raw) in raws.iter().enumerate() {
            for (q, &i) in split.test.iter().enumerate() {
                residuals[c][i] = raw[i] - pred[c * h + q];
            }
        }
        let inv = 1.0 / RELIGHT_FOLDS as f64;
        relit_fit
            .iter_mut()
            .zip(&t)
            .for_each(|(a, b)| *a += inv * b);
    }
    let Some(estimate) =
        relight_from_residuals(&residuals, &relit_fit, k, (picked, chance), fill, sigma).map(|e| {
            RelightEstimate {
                folds: RELIGHT_FOLDS,
                ..e
            }
        })
    else {
        return Ok(None);
    };
    if sigma <= 0.0 {
        return Ok(Some(estimate));
    }
    let noise2 = random_bootstrap_noise(sample)?;
    Ok(Some(match noise2 {
        Some(noise2) => estimate.with_noise(noise2),
        None => estimate,
    }))
}

/// What the frames' noise alone does to the chosen model's full-light relight, by a
/// parametric bootstrap: the sample rows fitted on every frame (`t`), frames simulated from
/// that fit with white noise of the estimated `sigma` (`P t + sigma z`, `z` a fixed
/// pseudo-random stream per camera pixel), fitted again the same way; the squared norm of the
/// relight of the difference, as the rows' squared differences summed with weights `1 / pi_c`
/// (each row is fitted on its own noise). It sees the noise a fit on the support passes on,
/// and what noise does to the support (coefficients it brings in, or hides), where the held-out
/// frames cannot resolve the error because the noise summed over the camera swamps it
/// (measured at 1 % frame noise, 32x32 x 48x48, 25 %: the slide 0.0017 against a true 0.0013,
/// glossy 0.0025 against 0.0049; the least-squares variance on the fixed support,
/// `sigma^2 tr((M_S^T M_S)^-1)`, gave 0.0007 and 0.0015). It does not see the light the fit
/// `t` has already lost to the noise, so it leans low. `None` without Bernoulli frames.
fn random_bootstrap_noise(sample: &RelightSample) -> Result<Option<f64>, ReconError> {
    let RelightSample {
        plan,
        raws,
        picked,
        chance,
        sigma,
        ..
    } = *sample;
    let Raw::Bernoulli(op) = &plan.raw else {
        return Ok(None);
    };
    let rows = raws.len();
    let (k, n) = (plan.k(), op.inner().rows());
    let frames = plan.raw_rows();
    let fitting = plan.op();
    let data = |raws: &mut dyn Iterator<Item = Vec<f64>>| -> Vec<f64> {
        raws.flat_map(|raw| plan.fit_data(&raw)).collect()
    };
    let bs = data(&mut raws.iter().cloned());
    let t = fit_sample(sample, (fitting, &bs, frames))?;
    let mut simulated = vec![0.0; rows * n];
    op.inner().apply_batch(&t, &mut simulated, rows);
    for (c, row) in simulated.chunks_exact_mut(n).enumerate() {
        let seed = BOOTSTRAP_SEED ^ picked[c] as u64;
        for (i, v) in row.iter_mut().enumerate() {
            let word = |j: u64| helmholtz_proto::patterns::rng::stream_word(seed, j);
            let u1 = ((word(2 * i as u64) >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
            let u2 = ((word(2 * i as u64 + 1) >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
            *v += sigma * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
        }
    }
    let bs_sim = data(&mut simulated.chunks_exact(n).map(<[f64]>::to_vec));
    let t_sim = fit_sample(sample, (fitting, &bs_sim, frames))?;
    // Each row is fitted on its own noise: the rows' differences are independent, and the
    // relight's squared norm is their squared norms summed (weighted by `1 / pi`), which the
    // cross terms of one draw would only scatter (to below 0, measured).
    let rows_f = rows as f64;
    let noise2 = t_sim
        .chunks_exact(k)
        .zip(t.chunks_exact(k))
        .zip(chance)
        .map(|((a, b), &e)| {
            let pi = (rows_f * e).min(1.0);
            let d2: f64 = a.iter().zip(b).map(|(a, b)| (a - b) * (a - b)).sum();
            if pi > 0.0 { d2 / pi } else { 0.0 }
        })
        .sum();
    Ok(Some(noise2))
}

/// Seed of [`random_bootstrap_noise`]'s noise (any fixed value: a report is reproducible).
const BOOTSTRAP_SEED: u64 = 0x6865_6c6d_686f_6c74;

/// A series centred on its mean, with its sum and sum of squares: its sample variance, with
/// or without one value (the jackknife), in constant time.
struct Moments {
    centred: Vec<f64>,
    s1: f64,
    s2: f64,
}

impl Moments {
    fn new(x: &[f64]) -> Self {
        let mean = x.iter().sum::<f64>() / x.len().max(1) as f64;
        let centred: Vec<f64> = x.iter().map(|a| a - mean).collect();
        let s1 = centred.iter().sum();
        let s2 = centred.iter().map(|a| a * a).sum();
        Moments { centred, s1, s2 }
    }

    /// The sample variance without value `skip`, if any.
    fn variance(&self, skip: Option<usize>) -> f64 {
        let n = self.centred.len() as f64;
        let (s1, s2, n) = match skip {
            Some(i) => {
                let x = self.centred[i];
                (self.s1 - x, self.s2 - x * x, n - 1.0)
            }
            None => (self.s1, self.s2, n),
        };
        (s2 - s1 * s1 / n) / (n - 1.0)
    }
}

/// A relight error estimate ([`random_relight_error`]).
#[derive(Clone, Copy, Debug)]
struct RelightEstimate {
    /// The relative error of a full-light relight.
    relative: f64,
    /// Two standard errors above it (above 0 where it is below 0).
    upper: f64,
    /// The error stands out of the estimate's own scatter (`relative` above two standard
    /// errors): otherwise `relative` is noise and only `upper` says something.
    resolved: bool,
    /// The relight's squared norm the estimate is relative to.
    norm2: f64,
    /// The frames' noise the fit carries into the relight, relative ([`random_bootstrap_noise`]).
    noise: Option<f64>,
    /// Cross-validation folds the residuals came from ([`random_cv_relight_error`]); 0: the
    /// choice's held-out frames.
    folds: usize,
}

impl RelightEstimate {
    /// With the fit's own noise, of squared norm `noise2` ([`random_bootstrap_noise`]).
    fn with_noise(self, noise2: f64) -> Self {
        RelightEstimate {
            noise: (self.norm2 > 0.0).then(|| (noise2.max(0.0) / self.norm2).sqrt()),
            ..self
        }
    }

    /// An unresolved held-out estimate (`self`, the choice's) against the cross-validated one:
    /// the latter where it is resolved, else the former with the cross-validation's noise and
    /// the lower of the two bounds. Each bound is two standard errors above its estimate (taken
    /// at 0 where negative), so neither reads 0 while its frames scatter, and the lower holds
    /// with at least 95 % where each holds with 97.7 %. The cross-validation's, on every frame,
    /// is the tighter one where the noise swamps both estimates (32x32 x 48x48 rendered scenes
    /// from 25 % of the frames at 1 % and 3 % frame noise: 0.043-0.22 against the choice's
    /// 0.053-0.42, every one above the true relight error, measured).
    fn or_cross_validated(self, cv: Option<RelightEstimate>) -> RelightEstimate {
        let Some(cv) = cv else {
            return self;
        };
        if cv.resolved {
            cv
        } else {
            RelightEstimate {
                noise: cv.noise,
                upper: self.upper.min(cv.upper),
                ..self
            }
        }
    }

    /// The reported relative error: the held-out estimate where it is resolved, at least the
    /// fit's noise; where it is not, the fit's noise (the part of the error that is known to be
    /// there; `upper` bounds the rest).
    fn reported(&self) -> Option<f64> {
        match (self.resolved, self.noise) {
            (true, noise) => Some(self.relative.max(noise.unwrap_or(0.0))),
            (false, Some(noise)) if noise > 0.0 => Some(noise),
            _ => None,
        }
    }

    /// As reported: `relative` ([`RelightEstimate::reported`]), `upper` (at least the noise),
    /// `resolved`, and `noise` when estimated.
    fn to_json(self) -> Value {
        let mut out = json!({
            "relative": self.reported(),
            "upper": self.upper.max(self.noise.unwrap_or(0.0)),
            "resolved": self.resolved,
            "held_out": if self.folds > 0 {
                format!("cross-validation over every frame in {} folds", self.folds)
            } else {
                "the choice's held-out frames".to_string()
            },
        });
        if let Some(noise) = self.noise {
            out["noise"] = json!(noise);
        }
        out
    }
}

/// A Hadamard subset's test of how a model fills in what no pair measured. The scale orders
/// ([`auto::hadamard_level`]) a set measures partly (a Russian-doll set stopped inside a
/// level) are where the unmeasured coefficients are; half of the measured pairs in those
/// orders, chosen by a hash of their index, are held out, and the model, fitted on the rest
/// (every coarser order and the other half), predicts them, as the whole set must predict the
/// unmeasured ones. The usual held-out pairs, the last measured, are one class of patterns at
/// the end of the ordering: a model coherent with the finest Walsh patterns (a wavelet)
/// predicted them as well as the pixel basis where its T was 12x further off.
///
/// [`auto::hadamard_level`]: super::auto::hadamard_level
struct LevelTest {
    train: HadamardOperator,
    test: HadamardOperator,
    /// Training data of the sample pixels, row-major.
    data: Vec<f64>,
    /// The sample pixels' held-out data.
    observed: Vec<Vec<f64>>,
    /// The sample pixels' noise floors ([`noise_floor`]).
    floors: Vec<f64>,
    size: (usize, usize),
}

impl LevelTest {
    /// `None` when the pairs are too few to halve.
    fn new(plan: &Plan, raws: &[Vec<f64>], floors: &[f64]) -> Result<Option<Self>, ReconError> {
        let Raw::Hadamard(op) = &plan.raw else {
            return Ok(None);
        };
        let size = plan.size();
        let k = plan.k();
        let order = |n: usize| super::auto::hadamard_level(n, size) as usize;
        let top = order(k - 1);
        let (mut measured, mut total) = (vec![0usize; top + 1], vec![0usize; top + 1]);
        (0..k).for_each(|n| total[order(n)] += 1);
        op.natural_indices()
            .iter()
            .for_each(|&n| measured[order(n)] += 1);
        let partial = |n: usize| {
            let l = order(n);
            measured[l] > 0 && measured[l] < total[l]
        };
        let (mut train, mut test) = (Vec::new(), Vec::new());
        for (i, &n) in op.natural_indices().iter().enumerate() {
            if partial(n) && holdout::is_held_out(i as u64, 0.5) {
                test.push(i);
            } else {
                train.push(i);
            }
        }
        if test.len() < holdout::MIN_HELD_OUT || train.len() < holdout::MIN_HELD_OUT {
            return Ok(None);
        }
        let split = holdout::Split {
            fraction: test.len() as f64 / op.rows() as f64,
            train,
            test,
        };
        Ok(Some(LevelTest {
            train: op.select_rows(&split.train),
            test: op.select_rows(&split.test),
            data: raws
                .iter()
                .flat_map(|raw| split.train.iter().map(|&i| raw[i]))
                .collect(),
            observed: raws
                .iter()
                .map(|raw| split.test.iter().map(|&i| raw[i]).collect())
                .collect(),
            floors: floors.to_vec(),
            size,
        }))
    }

    /// The relative residual (pooled over the sample pixels) of transform `kind` at weight
    /// `lambda` (a fraction of each row's lambda_max), refitted or not, on the second half.
    fn score(
        &self,
        kind: TransformKind,
        (lambda, refit, floored): (f64, bool, bool),
        config: &TransportConfig,
        chunk: usize,
        control: &Control,
    ) -> Result<Option<f64>, ReconError> {
        let (pw, ph) = self.size;
        let k = pw * ph;
        let rows = self.observed.len();
        let psi = kind.build(pw, ph);
        let sh = Shared {
            op: &self.train,
            dense: None,
            psi: psi.as_ref(),
            identity: kind == TransformKind::Identity,
            lipschitz: 1.0,
            free: free_coefficients(kind),
            max_iter: config.max_iter,
            tol: config.tol,
            cgls_refit: true,
        };
        let lams = weights(
            &batch::lambda_max(&sh, &self.data, chunk),
            lambda,
            if floored { &self.floors } else { &[] },
        );
        let mut s = vec![0.0; rows * k];
        batch::solve_rows(&sh, &self.data, &lams, &mut s, chunk, control)?;
        if refit {
            batch::refit_rows(&sh, &self.data, &mut s, chunk, control)?;
        }
        let mut t = vec![0.0; rows * k];
        sh.inverse(&s, &mut t);
        let h = self.test.rows();
        let mut pred = vec![0.0; rows * h];
        self.test.apply_batch(&t, &mut pred, rows);
        let (mut r2, mut o2) = (0.0f64, 0.0f64);
        for (obs, p) in self.observed.iter().zip(pred.chunks_exact(h)) {
            for (o, p) in obs.iter().zip(p) {
                r2 += (o - p) * (o - p);
                o2 += o * o;
            }
        }
        Ok((o2 > 0.0).then(|| (r2 / o2).sqrt()))
    }
}

/// The sample rows fitted with the chosen `model` on the pairs of `op` (the plan's or some of
/// them; `raws`, each sample pixel's data on those pairs, `floors` their noise floors, empty when
/// the model has none, `sigmas` their noise, at `picked` of a camera `camera_width` wide): the
/// rows' images (rows x k) and each row's count of nonzero stored coefficients.
fn fit_subset_sample(
    plan: &Plan,
    model: &ModelChoice,
    (op, raws, floors): (&HadamardOperator, &[Vec<f64>], &[f64]),
    (picked, camera_width, sigmas): (&[usize], usize, &[f64]),
    config: &TransportConfig,
    chunk: usize,
    control: &Control,
) -> Result<(Vec<f64>, Vec<usize>), ReconError> {
    let (pw, ph) = plan.size();
    let ModelChoice {
        kind,
        lambda,
        refit,
        floored: _,
        coarse,
        ref prune,
    } = *model;
    let psi = kind.build(pw, ph);
    let sh = Shared {
        op,
        dense: None,
        psi: psi.as_ref(),
        identity: kind == TransformKind::Identity,
        lipschitz: 1.0,
        free: free_coefficients(kind),
        max_iter: config.max_iter,
        tol: config.tol,
        cgls_refit: true,
    };
    let bs: Vec<f64> = raws.iter().flatten().copied().collect();
    let mut tally = Tally::default();
    let mut s = solve_block(&sh, (&bs, floors), lambda, None, chunk, &mut tally, control)?;
    if refit {
        batch::refit_rows(&sh, &bs, &mut s, chunk, control)?;
    }
    let mut t = vec![0.0; s.len()];
    let k = op.cols();
    match coarse.then(|| CoarseExact::new(plan, op)).flatten() {
        Some(step) => {
            step.apply(
                op,
                &bs,
                &mut s,
                &|row, img| sh.inverse(row, img),
                sigmas,
                (picked, camera_width),
            );
            let ones = constant_coefficients(TransformKind::Haar, (pw, ph));
            for &share in prune {
                prune_rows(
                    &mut s,
                    k,
                    share,
                    free_coefficients(TransformKind::Haar),
                    &ones,
                );
            }
            step.images(&s, &mut t);
        }
        None => {
            let ones = constant_coefficients(kind, (pw, ph));
            for &share in prune {
                prune_rows(&mut s, k, share, free_coefficients(kind), &ones);
                if refit {
                    batch::refit_rows(&sh, &bs, &mut s, chunk, control)?;
                }
            }
            sh.inverse(&s, &mut t);
        }
    }
    let nonzeros = s
        .chunks_exact(k)
        .map(|row| row.iter().filter(|v| **v != 0.0).count())
        .collect();
    Ok((t, nonzeros))
}

/// The noise floors of the sample rows under `model` ([`noise_floor`]; empty without one).
fn subset_floors(
    model: &ModelChoice,
    (raws, sums): (&[Vec<f64>], &[Vec<f64>]),
    k: usize,
) -> Vec<f64> {
    if model.floored {
        raws.iter()
            .zip(sums)
            .map(|(raw, sum)| noise_floor(sum, raw, k))
            .collect()
    } else {
        Vec::new()
    }
}

/// A Hadamard subset's error estimate of T (`details.error_estimate`): the sample pixels (`raws`,
/// their pair sums `sums`, their chance of being drawn `chance`) fitted with the chosen model on
/// all measured pairs (`t`, [`fit_subset_sample`]), judged by [`subset_error`].
fn hadamard_subset_error(
    op: &HadamardOperator,
    (raws, sums, chance): (&[Vec<f64>], &[Vec<f64>], &[f64]),
    t: &[f64],
) -> Option<Value> {
    let pooled = subset_error(op, (raws, sums, chance), t)?;
    let (rel, (lo, hi), judged) = (pooled.relative, pooled.range, pooled.judged);
    Some(json!({
        "relative": rel,
        "range": [lo, hi],
        "sample_pixels": judged,
        "basis": "relative error of T (Frobenius) on the sample pixels, each row fitted with the chosen model on all measured pairs: its residual on the measured coefficients less the noise its pair sums show, plus the scene's energy in the unmeasured coefficients extrapolated from the measured scale orders (a power law), against the row's own; pooled with weights 1 / (the pixel's chance of being drawn)",
    }))
}

/// Camera pixels the relight check of a Hadamard subset fits ([`subset_relight_error`]): every
/// one up to this many, else every `ceil(m / this)`-th.
const RELIGHT_CHECK_PIXELS: usize = 4096;

/// A Hadamard subset's full-light relight error `||(T_hat - T)^T 1|| / ||T^T 1||`, from the same
/// problem one grid coarser, where the truth is known: a subset measures a coarser grid
/// completely ([`complete_binning`], `b x b` projector blocks: a Russian-doll half, every pair
/// of the 16x16 grid of a 32x32 set); the same share of that grid's pairs, in the session's
/// order (for a Russian-doll set, the coarse grid's own Russian-doll subset), fitted with the
/// chosen model, predicts all of them, as the session's pairs must predict its unmeasured
/// coefficients. The relative error of that relight (every coarse coefficient's residual
/// summed over the camera, less the noise, plus twice the noise the fit absorbed: Stein, each
/// row's degrees of freedom its stored nonzeros) stands for the session's. What the model gets
/// wrong is measured rather than extrapolated: on a sparse scene a model fills the
/// unmeasured coefficients to a percent, which no energy extrapolation (known to a factor)
/// could show, and a zero-filled grid misses all of their energy. A relight's error is not its
/// rows' errors in quadrature (a model errs alike in neighbouring rows), and the 64 sample
/// pixels of the model choice, weighted back to the camera, left the coherent sum in their
/// own scatter (estimates of 0 against 0.46): the check fits every camera pixel, up to
/// [`RELIGHT_CHECK_PIXELS`] (beyond, an even stride of them, each standing for its stride),
/// read `block` pixels at a time. A coarser grid is easier (fewer unknowns per row), so it
/// leans low: on the 32x32 x 48x48 relief and rendered scenes from 25 %, 37.5 %, 50 % and 75 %
/// of a Russian-doll set, noise-free and at 1 % and 3 % frame noise, within 2x of the true
/// relit error on 34 of the 43 it resolves, below half on 9 (the relief 0.14-0.4x, the slide
/// 0.2-0.25x; docs/benchmark-notes.md); the
/// coarse grid's model misses a smaller share of its unmeasured energy than the session's
/// (amplitude, relief from 50 %: 0.018 against 0.144; slide 0.010 against 0.040; Cornell box
/// 0.23 against 0.54; glossy 0.058 against 0.044), while the unmeasured share of the energy
/// is alike on both grids.
///
/// `None` on a binned plan, when no coarser grid is complete, when its share would leave fewer
/// than [`holdout::MIN_HELD_OUT`] pairs on either side, or the relight has no energy.
#[allow(clippy::too_many_arguments)]
fn subset_relight_error(
    plan: &Plan,
    model: &ModelChoice,
    source: &mut dyn FrameSource,
    (m, camera_width, block): (usize, usize, usize),
    largest: &mut usize,
    config: &TransportConfig,
    chunk: usize,
    control: &Control,
) -> Result<Option<Value>, ReconError> {
    let Raw::Hadamard(op) = &plan.raw else {
        return Ok(None);
    };
    if plan.binning != 1 || m == 0 {
        return Ok(None);
    }
    let Some(b) = complete_binning(op, plan.grid) else {
        return Ok(None);
    };
    let coarse = Plan::new(plan.spec, plan.rows_read, b)?;
    let (Raw::Hadamard(cop), Some(pairs)) = (&coarse.raw, &coarse.pairs) else {
        return Ok(None);
    };
    let (k, kc, nc) = (plan.k(), coarse.k(), cop.rows());
    let na = (op.rows() as f64 / k as f64 * kc as f64).round() as usize;
    if nc < kc || na < holdout::MIN_HELD_OUT || nc - na < holdout::MIN_HELD_OUT {
        return Ok(None);
    }
    let first: Vec<usize> = (0..na).collect();
    let analogue = cop.select_rows(&first);
    let stride = m.div_ceil(RELIGHT_CHECK_PIXELS);
    let weight = stride as f64;
    let pixels: Vec<usize> = (stride / 2..m).step_by(stride).collect();
    let bf = b as f64;
    // Summed over the camera: the misses, the data, the noise variance and what the fits absorbed.
    let (mut missed, mut data) = (vec![0.0; nc], vec![0.0; nc]);
    let (mut noise, mut absorbed) = (0.0, 0.0);
    for group in pixels.chunks(block.max(1)) {
        let (raws, sums) = read_columns(plan, source, group, block, largest)?;
        let coarse_raws: Vec<Vec<f64>> = raws
            .iter()
            .map(|raw| pairs.iter().map(|&p| bf * raw[p]).collect())
            .collect();
        let coarse_sigmas: Vec<f64> = raws
            .iter()
            .zip(&sums)
            .map(|(raw, sum)| bf * pair_sigma(sum, raw, k))
            .collect();
        let analogue_raws: Vec<Vec<f64>> = coarse_raws.iter().map(|r| r[..na].to_vec()).collect();
        let analogue_sums: Vec<Vec<f64>> = sums
            .iter()
            .map(|sum| pairs[..na].iter().map(|&p| sum[p]).collect())
            .collect();
        let floors = subset_floors(model, (&analogue_raws, &analogue_sums), kc);
        let (fit, nonzeros) = fit_subset_sample(
            &coarse,
            model,
            (&analogue, &analogue_raws, &floors),
            (group, camera_width, &coarse_sigmas),
            config,
            chunk,
            control,
        )?;
        let mut predicted = vec![0.0; group.len() * nc];
        cop.apply_batch(&fit, &mut predicted, group.len());
        for (c, (raw, p)) in coarse_raws
            .iter()
            .zip(predicted.chunks_exact(nc))
            .enumerate()
        {
            missed
                .iter_mut()
                .zip(raw.iter().zip(p))
                .for_each(|(a, (o, p))| *a += weight * (o - p));
            data.iter_mut().zip(raw).for_each(|(a, o)| *a += weight * o);
            let s2 = weight * weight * coarse_sigmas[c] * coarse_sigmas[c];
            noise += s2;
            absorbed += 2.0 * s2 * nonzeros[c].min(na) as f64;
        }
    }
    let energy = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>() - nc as f64 * noise;
    let norm2 = energy(&data);
    if norm2 <= 0.0 || !norm2.is_finite() {
        return Ok(None);
    }
    let error2 = energy(&missed) + absorbed;
    // Its standard error from the noise of the summed residuals (variance `noise` each):
    // `Var sum (e_i + n_i)^2 = sum 4 e_i^2 noise + 2 noise^2`. Below two of them the noise summed
    // over the camera swamps the error (a slide at 3 % frame noise, where two thirds of the
    // camera is dark but noisy, read 0 against a true 1.0 %): only the bound is known.
    let se = (4.0 * noise * error2.max(0.0) + 2.0 * nc as f64 * noise * noise).sqrt();
    let resolved = error2 > 2.0 * se;
    let relative = |e2: f64| (e2.max(0.0) / norm2).sqrt();
    Ok(Some(json!({
        "relative": resolved.then(|| relative(error2)),
        "upper": relative(error2.max(0.0) + 2.0 * se),
        "resolved": resolved,
        "light": "full (every camera pixel at 1)",
        "coarse_grid": [coarse.grid.0, coarse.grid.1],
        "coarse_pairs": [na, nc],
        "camera_pixels": pixels.len(),
        "basis": "the same problem on the coarser grid the measured pairs complete (coarse_grid), where the truth is known: its first pairs in the session's order, the session's share of them (coarse_pairs), fitted with the chosen model on every camera pixel (camera_pixels: beyond 4096, an even stride), predicting all of its pairs; the relative error of that full-light relight (the residuals summed over the camera, less their noise, plus twice the noise the fits absorbed: each row's stored nonzeros of its noise); a coarser grid is easier, so it leans low; upper: two standard errors (of the summed residuals' noise) above it; resolved: it stands more than two standard errors above 0, else relative is null and only upper is known",
    })))
}

/// Noise of an image from its finest diagonal Haar details (2x2 blocks), robustly:
/// `median |(a - b - c + d) / 2| / 0.6745` (Donoho-Johnstone). The same `sigma` holds in every
/// orthonormal basis for white noise.
fn noise_sigma(t: &[f64], w: usize, h: usize) -> f64 {
    let mut d = Vec::with_capacity((w / 2) * (h / 2));
    for y in (0..h - h % 2).step_by(2) {
        for x in (0..w - w % 2).step_by(2) {
            let (a, b, c, e) = (
                t[y * w + x],
                t[y * w + x + 1],
                t[(y + 1) * w + x],
                t[(y + 1) * w + x + 1],
            );
            d.push(((a - b - c + e) * 0.5).abs());
        }
    }
    if d.is_empty() {
        return 0.0;
    }
    let mid = d.len() / 2;
    let (_, median, _) = d.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *median / 0.6745
}

/// The keep threshold of an exact row (module docs).
fn exact_threshold(s: &[f64], sigma: f64, k: usize) -> f64 {
    let max = s.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    ((2.0 * (k as f64).ln()).sqrt() * sigma).max(max * f32::EPSILON as f64 * 0.5)
}

/// What a transform's kept coefficients do to the full-light relight of an exact set (the sum
/// of all rows): what is dropped adds up coherently, what is kept brings its noise. The dropped
/// part is summed separately over the two halves of a camera checkerboard: their noise is
/// independent and their coherent parts alike, so `4 <d_a, d_b>` estimates the square of the
/// dropped light without any noise estimate (the transform is orthonormal: these norms are the
/// relight's). The kept noise is `sum_j kept_j sigma_j^2`.
struct ExactChoice {
    kind: TransformKind,
    kept: usize,
    dropped: [Vec<f64>; 2],
    kept_noise: f64,
    relit: Vec<f64>,
}

impl ExactChoice {
    fn new(kind: TransformKind, k: usize) -> Self {
        ExactChoice {
            kind,
            kept: 0,
            dropped: [vec![0.0; k], vec![0.0; k]],
            kept_noise: 0.0,
            relit: vec![0.0; k],
        }
    }

    /// Rows `s` with their noise, kept coefficients and checkerboard half.
    fn add(&mut self, s: &[f64], sigmas: &[f64], keep: &[bool], half: &[bool]) {
        let k = self.relit.len();
        for (((row, kept), sigma), &h) in s
            .chunks_exact(k)
            .zip(keep.chunks_exact(k))
            .zip(sigmas)
            .zip(half)
        {
            let dropped = &mut self.dropped[usize::from(h)];
            let mut n = 0usize;
            for (i, (&v, &kp)) in row.iter().zip(kept).enumerate() {
                if kp {
                    self.relit[i] += v;
                    n += 1;
                } else {
                    dropped[i] += v;
                }
            }
            self.kept += n;
            self.kept_noise += n as f64 * sigma * sigma;
        }
    }

    /// The estimated mean square error of the full-light relight.
    fn relight_mse(&self) -> f64 {
        let cross: f64 = self.dropped[0]
            .iter()
            .zip(&self.dropped[1])
            .map(|(a, b)| a * b)
            .sum();
        (4.0 * cross).max(0.0) + self.kept_noise
    }

    fn relit_norm2(&self) -> f64 {
        self.relit.iter().map(|v| v * v).sum()
    }

    /// [`ExactChoice::relight_mse`] relative to the relight's norm.
    fn relative_relight_error(&self) -> f64 {
        let norm2 = self.relit_norm2();
        if norm2 > 0.0 {
            (self.relight_mse() / norm2).sqrt()
        } else {
            0.0
        }
    }
}

/// Which coefficients of a block's exact rows are kept (module docs): `s` holds the block's
/// rows (`sigmas.len()` rows of `k` transform coefficients), the block is camera pixels
/// `first..` of a camera `width` pixels wide. A coefficient is kept in a row when it stands
/// out of that row's noise ([`exact_threshold`]), or when the mean over a square tile of
/// camera pixels around the row (sides 2, 4, 8, ... up to the block, fine to coarse) of what
/// is not kept yet stands out of the mean's own noise `sqrt(sum sigma_j^2) / n`: light that
/// many neighbouring camera pixels share (interreflections, a smooth halo) is kept in every row
/// of the tile, at each row's own unbiased value, even where every single row's share is below
/// its noise. (What single rows keep is left out of the means: one bright row does not make a
/// coefficient kept in all its neighbours.) A relight sums rows,
/// so what is dropped adds up coherently while the noise of what is kept averages out.
fn exact_support(s: &[f64], sigmas: &[f64], k: usize, first: usize, width: usize) -> Vec<bool> {
    let pixels: Vec<usize> = (first..first + sigmas.len()).collect();
    exact_support_at(s, sigmas, (k, k), &pixels, width)
}

/// [`exact_support`] for rows of `k` coefficients out of a transform of `universe` (the
/// threshold's `sqrt(2 ln universe)`) at camera pixels `pixels` (any, in any order: a tile's
/// members are the rows that fall in it).
fn exact_support_at(
    s: &[f64],
    sigmas: &[f64],
    (k, universe): (usize, usize),
    pixels: &[usize],
    width: usize,
) -> Vec<bool> {
    let len = sigmas.len();
    let z = (2.0 * (universe as f64).ln()).sqrt();
    let mut keep = vec![false; len * k];
    let mut floors = Vec::with_capacity(len);
    for (c, row) in s.chunks_exact(k).enumerate() {
        let tau = exact_threshold(row, sigmas[c], universe);
        let max = row.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        floors.push(max * f32::EPSILON as f64 * 0.5);
        keep[c * k..(c + 1) * k]
            .iter_mut()
            .zip(row)
            .for_each(|(kp, v)| *kp = v.abs() > tau);
    }
    if len < 2 {
        return keep;
    }
    let width = width.max(1);
    let first = pixels.iter().copied().min().unwrap_or(0);
    let last = pixels.iter().copied().max().unwrap_or(0);
    let lines = last / width - first / width + 1;
    let extent = width.max(lines);
    let mut mean = vec![0.0; k];
    let mut g = 2usize;
    loop {
        // Tiles of g x g camera pixels on the camera's grid (clipped to the block).
        let mut tiles: std::collections::BTreeMap<(usize, usize), Vec<usize>> = Default::default();
        for (c, &j) in pixels.iter().enumerate() {
            tiles
                .entry((j / width / g, j % width / g))
                .or_default()
                .push(c);
        }
        for members in tiles.values().filter(|m| m.len() >= 2) {
            let n = members.len() as f64;
            mean.iter_mut().for_each(|v| *v = 0.0);
            let mut var = 0.0;
            let mut floor = 0.0f64;
            for &c in members {
                // What is not kept yet: the residual the finer tests left.
                mean.iter_mut()
                    .zip(&s[c * k..(c + 1) * k])
                    .zip(&keep[c * k..(c + 1) * k])
                    .for_each(|((a, b), kept)| {
                        if !kept {
                            *a += b
                        }
                    });
                var += sigmas[c] * sigmas[c];
                floor = floor.max(floors[c]);
            }
            let tau = (z * var.sqrt() / n).max(floor);
            for (i, v) in mean.iter().enumerate() {
                if (v / n).abs() > tau {
                    for &c in members {
                        keep[c * k + i] = true;
                    }
                }
            }
        }
        if g >= extent {
            break;
        }
        g *= 2;
    }
    keep
}

/// The Haar coefficients a Hadamard subset measures completely. A Russian-doll subset that
/// holds every Walsh function constant on `b x b` projector blocks ([`complete_binning`]) is a
/// complete orthonormal set of the block-constant images, and so are the Haar coefficients
/// coarser than the finest `log2 b` levels (the top-left `(w / b) x (h / b)` block of the
/// Mallat layout); every other measured Walsh function and every finer Haar function is
/// orthogonal to them. So those coefficients of `Psi A^T b` are exact (plus the noise of their
/// pairs, `sigma` each), whatever a model does with the finer ones. A lasso at a weight above
/// the noise zeroes the dim light every row has a little of (an interreflection), one below it
/// keeps hundreds of noise coefficients; here they are taken as measured and kept as a
/// complete set's are ([`exact_support_at`]: above the noise in their row, or in their mean
/// over a tile of neighbouring camera pixels), and the model supplies only the finer
/// coefficients. The rows are then Haar coefficients, whatever transform the model was
/// fitted in.
///
/// The model's finer coefficients are held to the same test at [`FINE_THRESHOLD_SHARE`] of its
/// thresholds (`fine_test`, model version 6): a finer Haar coefficient is kept only where it
/// stands out of that share of the rows' noise (in its row, or in the mean over a tile of
/// neighbours). Without it the rows kept every coefficient of the model's image above the f32
/// resolution, more than a complete set at the same noise keeps. A finer Haar function sums to
/// zero, so dropping one never moves a row's total light. Noise-free the threshold is the rows'
/// f32 resolution, as before.
struct CoarseExact {
    /// Mallat-layout indices of the measured coefficients (the first is the DC).
    positions: Vec<usize>,
    /// Per Mallat index: measured (one of `positions`).
    is_coarse: Vec<bool>,
    haar: Box<dyn crate::transforms::Transform>,
    /// The finer coefficients held to the complete set's noise test at
    /// [`FINE_THRESHOLD_SHARE`] of its thresholds (version 6 on).
    fine_test: bool,
}

impl CoarseExact {
    /// For the pairs of `op` (on the plan's grid), if they measure a coarser grid completely
    /// and not the plan's own.
    fn new(plan: &Plan, op: &HadamardOperator) -> Option<Self> {
        if op.rows() >= plan.k() {
            return None;
        }
        let b = complete_binning(op, plan.grid)? as usize;
        let (w, h) = plan.size();
        let positions: Vec<usize> = (0..h / b)
            .flat_map(|y| (0..w / b).map(move |x| y * w + x))
            .collect();
        let mut is_coarse = vec![false; w * h];
        positions.iter().for_each(|&i| is_coarse[i] = true);
        Some(CoarseExact {
            positions,
            is_coarse,
            haar: TransformKind::Haar.build(w, h),
            fine_test: true,
        })
    }

    /// Rows fitted to data `bs` (rows x n, the plain Hadamard data of `op`) in place: in, the
    /// fitted coefficients, whose images `image` gives; out, their Haar coefficients with the
    /// measured ones from the data, kept where they stand out of their rows' noise `sigmas`
    /// (in a row, or in a tile of the camera pixels `pixels` of a camera `width` wide) and
    /// zero elsewhere; the DC always (it is free in every fit). The finer ones below the row's
    /// f32 resolution (rounding of a transform of a sparse image) are zero, and with
    /// `fine_test` those the same noise test would not keep. Beyond the rows it
    /// holds the measured coefficients (`9 k / b^2` bytes a row) and two images.
    fn apply(
        &self,
        op: &dyn LinearOperator,
        bs: &[f64],
        rows: &mut [f64],
        image: &dyn Fn(&[f64], &mut [f64]),
        sigmas: &[f64],
        (pixels, width): (&[usize], usize),
    ) {
        let (k, n) = (op.cols(), op.rows());
        let kc = self.positions.len();
        let mut coarse = vec![0.0; sigmas.len() * kc];
        let (mut g, mut z) = (vec![0.0; k], vec![0.0; k]);
        for (c, (row, out)) in rows
            .chunks_exact_mut(k)
            .zip(coarse.chunks_exact_mut(kc))
            .enumerate()
        {
            op.adjoint(&bs[c * n..(c + 1) * n], &mut g);
            self.haar.apply(&g, &mut z);
            out.iter_mut()
                .zip(&self.positions)
                .for_each(|(v, &i)| *v = z[i]);
            image(row, &mut g);
            self.haar.apply(&g, row);
            let floor = row.iter().fold(0.0f64, |m, v| m.max(v.abs())) * f32::EPSILON as f64 * 0.5;
            row.iter_mut()
                .filter(|v| v.abs() <= floor)
                .for_each(|v| *v = 0.0);
        }
        let keep = exact_support_at(&coarse, sigmas, (kc, k), pixels, width);
        for ((row, c), kept) in rows
            .chunks_exact_mut(k)
            .zip(coarse.chunks_exact(kc))
            .zip(keep.chunks_exact(kc))
        {
            for (j, &i) in self.positions.iter().enumerate() {
                row[i] = if kept[j] || j == 0 { c[j] } else { 0.0 };
            }
        }
        if self.fine_test {
            let scaled: Vec<f64> = sigmas.iter().map(|s| s * FINE_THRESHOLD_SHARE).collect();
            let fine = exact_support_at(rows, &scaled, (k, k), pixels, width);
            for (row, kept) in rows.chunks_exact_mut(k).zip(fine.chunks_exact(k)) {
                for ((v, &kept), &coarse) in row.iter_mut().zip(kept).zip(&self.is_coarse) {
                    if !kept && !coarse {
                        *v = 0.0;
                    }
                }
            }
        }
    }

    /// Images `t` of Haar rows `u`.
    fn images(&self, u: &[f64], t: &mut [f64]) {
        let k = self.haar.cols();
        for (a, b) in u.chunks_exact(k).zip(t.chunks_exact_mut(k)) {
            self.haar.adjoint(a, b);
        }
    }
}

/// The share of a complete set's keep thresholds ([`exact_support_at`]) a model's finer
/// coefficients are held to where the coarse ones are taken as measured ([`CoarseExact`]).
/// Measured with `bench/examples/transport_one hadamard 32 CAM RATIO NOISE` (Russian-doll
/// subsets; relief, Cornell and glossy scenes; 37.5-75 % of the pairs; 0.1-3 % frame noise;
/// 2026-12-02, docs/benchmark-notes.md): at the full thresholds (1) the relief from 75 % at
/// 3 % noise relit 11 % worse than with every coefficient kept (0.0131 against 0.0118, full
/// light; 21.6 nonzeros per row against 27.2, where the complete set keeps 30.4); at the
/// noise of one coefficient (0.27 = `1 / sqrt(2 ln 1024)`) the Cornell box from 75 % at 0.1 %
/// stored 381.8 per row against the complete set's 373.2; at 0.5 every session measured stores
/// no more than its complete set and relights within 5 % of keeping everything (most of them
/// the same or better).
const FINE_THRESHOLD_SHARE: f64 = 0.5;

fn free_coefficients(kind: TransformKind) -> usize {
    usize::from(kind != TransformKind::Identity)
}

/// The session's blocks of camera pixels: contiguous ranges of at most `block` pixels; with
/// `lines_of`, whole pairs of camera lines of that width.
fn blocks(m: usize, block: usize, lines_of: Option<usize>) -> Vec<Range<usize>> {
    let step = match lines_of {
        Some(w) => ((block / w) & !1).max(2) * w,
        None => block.max(1),
    };
    (0..m).step_by(step).map(|s| s..(s + step).min(m)).collect()
}

/// The 2x2 parents of a block of whole camera lines (`pixels` pixels of width `w`): for every
/// parent, its children's local indices.
fn parents(pixels: usize, w: usize) -> Vec<Vec<usize>> {
    let h = pixels / w;
    let mut out = Vec::new();
    for py in 0..h.div_ceil(2) {
        for px in 0..w.div_ceil(2) {
            let mut children = Vec::with_capacity(4);
            for y in 2 * py..(2 * py + 2).min(h) {
                for x in 2 * px..(2 * px + 2).min(w) {
                    children.push(y * w + x);
                }
            }
            out.push(children);
        }
    }
    out
}

/// Relative standard error of a held-out relative residual `sqrt(sum e / spread)` from its
/// rows' squared residuals `e`: the sum's standard error `sqrt(H var(e))` over the sum, halved
/// for the square root (delta method). 0 for fewer than two rows or a zero sum.
fn relative_standard_error(e: &[f64]) -> f64 {
    let h = e.len();
    let sum: f64 = e.iter().sum();
    if h < 2 || sum <= 0.0 {
        return 0.0;
    }
    let mean = sum / h as f64;
    let var = e.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (h - 1) as f64;
    0.5 * (h as f64 * var).sqrt() / sum
}

/// A fitted point is also scored compacted ([`prune_rows`]) at this share of its own held-out
/// residual relative to the data: the RMS of its held-out residuals over the RMS of a training
/// datum as measured (a Bernoulli frame's held-out relative residual `rho`; not the held-out
/// pairs' own norm, which for a Hadamard subset are its weakest pairs, 0.11 on an adaptive set
/// whose T is 0.006 off). Dropping energy `(rho / 3)^2` adds about 5 % to an error of `rho`
/// where the dropped part is independent of it.
const PRUNE_SHARE: f64 = 1.0 / 3.0;

/// A refitted point is compacted and refitted again while its held-out residual falls, up to
/// this many rounds, each at the share of the point as solved ([`PRUNE_SHARE`] of its
/// held-out residual; [`prune_rows`]); a round that drops nothing still refits, from where the
/// last refit stopped (the coordinate-descent refit on dense columns stops short of the
/// least-squares fit; the CGLS refit of Hadamard pairs reaches it, and such a round then
/// changes nothing and ends the rounds).
const PRUNE_ROUNDS: usize = 16;

/// The coefficients of the constant image in `kind` (`Psi 1`): a row's sum (its full-light
/// relight) is `s . Psi 1`.
fn constant_coefficients(kind: TransformKind, (pw, ph): (usize, usize)) -> Vec<f64> {
    let mut ones = vec![0.0; pw * ph];
    kind.build(pw, ph).apply(&vec![1.0; pw * ph], &mut ones);
    ones
}

/// Compacts rows of `k` stored coefficients: in each row the smallest nonzero coefficients
/// (after the first `free`, which are never dropped) go, smallest first, while the dropped
/// energy stays within `share^2` of the row's and the dropped part's sum (its share of a
/// full-light relight, `s . ones`, `ones` = [`constant_coefficients`]) within `share` of the
/// row's absolute sum `sum |s_i ones_i|`. A lasso fitted at a small weight keeps hundreds of
/// tiny coefficients that buy a fraction of its error; this keeps the error within about
/// `sqrt(1 + share^2 / rho^2)` of its own and every row's light within `share`, which a relight
/// adds up (the pixel basis, where every coefficient carries light, is held by the sum; in a
/// wavelet basis only the free coefficient does). Ties go to the lower index. Returns the
/// coefficients dropped.
fn prune_rows(s: &mut [f64], k: usize, share: f64, free: usize, ones: &[f64]) -> usize {
    let mut dropped = 0;
    let mut order: Vec<usize> = Vec::new();
    for row in s.chunks_exact_mut(k) {
        let energy: f64 = row.iter().map(|v| v * v).sum();
        let light: f64 = row.iter().zip(ones).map(|(v, o)| (v * o).abs()).sum();
        order.clear();
        order.extend((free..k).filter(|&i| row[i] != 0.0));
        order.sort_by(|&a, &b| row[a].abs().total_cmp(&row[b].abs()).then(a.cmp(&b)));
        let (mut e, mut sum) = (0.0, 0.0);
        let (energy_budget, light_budget) = (share * share * energy, share * light);
        for &i in &order {
            let v = row[i];
            if e + v * v > energy_budget || (sum + v * ones[i]).abs() > light_budget {
                break;
            }
            e += v * v;
            sum += v * ones[i];
            row[i] = 0.0;
            dropped += 1;
        }
    }
    dropped
}

/// What the model choice decided for the iterative path.
#[derive(Clone, Debug)]
struct ModelChoice {
    kind: TransformKind,
    lambda: f64,
    refit: bool,
    /// Every row's weight at least its noise floor ([`noise_floor`]).
    floored: bool,
    /// The coefficients the pairs measure completely taken as measured ([`CoarseExact`]).
    coarse: bool,
    /// The stored rows compacted at these shares in turn ([`prune_rows`]), each round refitted
    /// where the point is (and its coefficients are the fitted transform's).
    prune: Vec<f64>,
}

/// Level-test residuals ([`LevelTest`]) within 10 % of the lowest plus this are a tie: both
/// predict the held-out pairs to 0.1 % of their norm, and the sparser transform is chosen.
const LEVEL_TIE: f64 = 1e-3;

/// A Hadamard subset's points must keep the total light within this (relative) or three
/// standard errors of its noise, whichever is larger ([`choose_model`]).
const LIGHT_TOLERANCE: f64 = 0.005;

/// One point of the model choice's paths, scored.
struct Point {
    kind: TransformKind,
    lambda: f64,
    refit: bool,
    /// Held-out relative residual on the sample pixels (infinite when there is none).
    held_out: f64,
    /// Its standard error.
    se: f64,
    /// Mean nonzeros per row.
    nonzeros: f64,
    score: Score,
    /// A Hadamard subset's total-light error and its standard error ([`subset_light_error`]).
    light: Option<(f64, f64)>,
    /// Every row's weight at least its noise floor ([`noise_floor`]).
    floored: bool,
    /// The coefficients the pairs measure completely taken as measured ([`CoarseExact`]).
    coarse: bool,
    /// A random-pattern session's full-light relight error ([`random_relight_error`]).
    relight: Option<RelightEstimate>,
    /// Compacted at these shares in turn ([`ModelChoice::prune`]).
    prune: Vec<f64>,
}

/// One candidate of the model choice, as reported.
#[derive(Clone, Debug, serde::Serialize)]
struct Candidate {
    transform: &'static str,
    lambda: f64,
    held_out: Option<f64>,
    /// Standard error of `held_out` (from the spread of the held-out rows' residuals).
    held_out_se: Option<f64>,
    /// A Hadamard subset's estimated relative error of T ([`subset_error`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    error_estimate: Option<f64>,
    /// A Hadamard subset's relative total-light error ([`subset_light_error`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    light_error: Option<f64>,
    /// A random-pattern session's full-light relight error ([`RelightEstimate::to_json`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    relight_error_estimate: Option<Value>,
    iterations_mean: f64,
    nonzeros_mean: f64,
    /// Least-squares refit on the lasso's support ([`batch::refit_rows`]).
    refit: bool,
    /// Every row's weight at least its noise floor ([`noise_floor`]).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    noise_floor: bool,
    /// The Haar coefficients the pairs measure completely taken as measured ([`CoarseExact`]).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    coarse_exact: bool,
    /// The point compacted at these shares in turn ([`prune_rows`]).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    prune: Vec<f64>,
}

/// Counters of the iterative solve, as reported.
#[derive(Default)]
struct Tally {
    iterations: u64,
    iterations_max: usize,
    parent_iterations: u64,
    parent_rows: u64,
    /// Of the least-squares refit on the support, when chosen.
    refit_iterations: u64,
}

/// Reconstructs `T` from the first `rows` frames of a camera session (module docs): the model
/// ([`plan_transport`]), every block solved ([`solve_transport_blocks`]), then assembled
/// ([`assemble_transport`]). A sharded reconstruction runs the same three steps, the blocks in
/// shards on any number of workers.
pub fn reconstruct_transport(
    spec: &PatternSpec,
    camera: CameraGrid,
    rows: u64,
    config: &TransportConfig,
    source: &mut dyn FrameSource,
    control: &Control,
) -> Result<(TransportMatrix, Report), ReconError> {
    let plan = validate(spec, camera, rows, config.projector_binning)?;
    let model = plan_with(&plan, camera, config, source, control)?;
    let part = solve_with(&plan, &model, 0..model.blocks.len(), source, control)?;
    assemble_transport(&model, std::slice::from_ref(&part))
}

/// Checks the request and plans the family's operator.
fn validate(
    spec: &PatternSpec,
    camera: CameraGrid,
    rows: u64,
    binning: u32,
) -> Result<Plan<'_>, ReconError> {
    let m = camera.pixels();
    if m == 0 {
        return Err(ReconError::Unsolvable(format!(
            "the camera grid {}x{} has no pixels",
            camera.width, camera.height
        )));
    }
    if rows == 0 {
        return Err(ReconError::Unsolvable("the session has no frames".into()));
    }
    if rows > spec.count() {
        return Err(ReconError::Unsolvable(format!(
            "{rows} frames requested but the spec declares {}",
            spec.count()
        )));
    }
    Plan::new(spec, rows as usize, binning)
}

/// The first step of a reconstruction of `T` (module docs): validation, the memory plan (the
/// blocks of camera pixels), and the model chosen on the sample pixels. The model is chosen
/// once; every block is then solved with it ([`solve_transport_blocks`]), in one process or in
/// shards on many.
pub fn plan_transport(
    spec: &PatternSpec,
    camera: CameraGrid,
    rows: u64,
    config: &TransportConfig,
    source: &mut dyn FrameSource,
    control: &Control,
) -> Result<TransportModel, ReconError> {
    let plan = validate(spec, camera, rows, config.projector_binning)?;
    plan_with(&plan, camera, config, source, control)
}

fn plan_with(
    plan: &Plan,
    camera: CameraGrid,
    config: &TransportConfig,
    source: &mut dyn FrameSource,
    control: &Control,
) -> Result<TransportModel, ReconError> {
    let start = Instant::now();
    let m = camera.pixels();
    let k = plan.k();
    let (pw, ph) = plan.size();
    let n_read = plan.rows_read;
    let selecting = !plan.exact;
    let mut coarse = config.coarse_to_fine && !plan.exact && m > 1;
    let mut notes: Vec<String> = Vec::new();
    let mut mem = plan_memory(plan, config.memory_budget_bytes, m, selecting, coarse)?;
    if coarse && mem.block_pixels < (2 * camera.width as usize).min(m) {
        notes.push(format!(
            "coarse_to_fine off: a block of {} camera pixels under the memory budget is less than two camera lines",
            mem.block_pixels
        ));
        coarse = false;
        mem = plan_memory(plan, config.memory_budget_bytes, m, selecting, false)?;
    }
    if coarse && plan.dense_pays(plan.op(), config.memory_budget_bytes) {
        notes.push(
            "coarse_to_fine off: random patterns are solved by coordinate descent on A Psi^T held densely, where a \
             parent's solution is a worse start than the continuation path (measured: 64x64 projector, 32x32 camera, \
             25 % Bernoulli, 59 s and T error 0.087 against 20 s and 0.0007 without)"
                .to_string(),
        );
        coarse = false;
        mem = plan_memory(plan, config.memory_budget_bytes, m, selecting, false)?;
    }
    let mut largest = 0usize;
    // At most half a block: the model choice also holds each sample pixel's image and
    // predictions besides what a block pixel needs.
    let sample = config
        .sample_pixels
        .min((mem.block_pixels / 2).max(1))
        .min(m);
    let mut details = serde_json::Map::new();
    let mut held_out = None;
    let mut held_out_unavailable = None;
    let mut floor_sigma = None;

    let (transform, lambda, refit, noise_floor, coarse_exact, prune) = if plan.exact {
        let transform = match config.transform {
            Some(t) => t,
            None => {
                // The transform whose kept coefficients relight the camera best
                // ([`ExactChoice`]): one pass over the session in the solve's blocks.
                let mut choices: Vec<ExactChoice> = CANDIDATE_TRANSFORMS
                    .iter()
                    .map(|&kind| ExactChoice::new(kind, k))
                    .collect();
                let psis: Vec<_> = CANDIDATE_TRANSFORMS
                    .iter()
                    .map(|kind| kind.build(pw, ph))
                    .collect();
                let w = camera.width as usize;
                for r in blocks(m, mem.block_pixels, None) {
                    if control.is_cancelled() {
                        return Err(ReconError::Cancelled);
                    }
                    let f = read(source, r.clone(), n_read, &mut largest)?;
                    let ts: Vec<Vec<f64>> = (0..r.len())
                        .map(|c| plan.exact_inverse(&plan.raw_column(&f, r.len(), c)))
                        .collect();
                    drop(f);
                    let sig: Vec<f64> = ts.iter().map(|t| noise_sigma(t, pw, ph)).collect();
                    let half: Vec<bool> = r.clone().map(|j| (j % w + j / w) % 2 == 1).collect();
                    let mut s = vec![0.0; r.len() * k];
                    for (choice, psi) in choices.iter_mut().zip(&psis) {
                        for (t, row) in ts.iter().zip(s.chunks_exact_mut(k)) {
                            psi.apply(t, row);
                        }
                        let keep = exact_support(&s, &sig, k, r.start, w);
                        choice.add(&s, &sig, &keep, &half);
                    }
                }
                let best_mse = choices
                    .iter()
                    .map(ExactChoice::relight_mse)
                    .fold(f64::INFINITY, f64::min);
                let norm2 = choices
                    .iter()
                    .map(ExactChoice::relit_norm2)
                    .fold(0.0, f64::max);
                // Within 10 % of the best relight error (or at f32 resolution): the fewest kept.
                let within = (best_mse * 1.21).max(norm2 * 1e-14);
                let best = choices
                    .iter()
                    .filter(|c| c.relight_mse() <= within)
                    .min_by_key(|c| c.kept)
                    .expect("the best is within");
                details.insert(
                    "selection".into(),
                    json!({
                        "rule": "among the transforms whose estimated full-light relight error is within 10 % of the lowest, the one keeping the fewest coefficients (kept: above the noise of their row, or of their mean over a camera tile); the estimate is the dropped part's coherent sum (the product of its sums over the two halves of a camera checkerboard, free of their independent noise) plus the noise of what is kept",
                        "candidates": choices.iter().map(|c| json!({
                            "transform": c.kind.name(),
                            "kept": c.kept,
                            "relight_error_estimate": c.relative_relight_error(),
                        })).collect::<Vec<_>>(),
                    }),
                );
                details.insert(
                    "relight_error_estimate".into(),
                    json!({
                        "light": "full (every camera pixel at 1)",
                        "relative": best.relative_relight_error(),
                    }),
                );
                best.kind
            }
        };
        held_out_unavailable = Some(
            "a complete raster or Hadamard set is inverted exactly: every coefficient comes from its own rows alone, so no \
             other row predicts a held-out one"
                .to_string(),
        );
        (transform, None, false, false, false, Vec::new())
    } else {
        control.set_progress(0.0);
        let chosen = choose_model(
            plan,
            config,
            source,
            (m, camera.width as usize),
            sample,
            &mem,
            &mut largest,
            &mut details,
            &mut held_out,
            &mut held_out_unavailable,
            &mut floor_sigma,
            control,
        )?;
        (
            chosen.kind,
            Some(chosen.lambda),
            chosen.refit,
            chosen.floored,
            chosen.coarse,
            chosen.prune,
        )
    };
    if control.is_cancelled() {
        return Err(ReconError::Cancelled);
    }
    let lipschitz = if plan.exact {
        1.0
    } else {
        plan.lipschitz(plan.op())
    };
    control.set_progress(if plan.exact { 0.0 } else { 0.2 });
    let blocks = blocks(m, mem.block_pixels, coarse.then_some(camera.width as usize))
        .into_iter()
        .map(|r| (r.start, r.end))
        .collect();
    Ok(TransportModel {
        version: TransportModel::VERSION,
        projector: plan.grid,
        camera: (camera.width, camera.height),
        rows: plan.rows_read as u64,
        exact: plan.exact,
        transform,
        lambda,
        refit,
        lipschitz,
        coarse,
        coarse_requested: config.coarse_to_fine,
        chunk: mem.chunk,
        threads: rayon::current_num_threads().max(1),
        max_iter: config.max_iter,
        tol: config.tol,
        blocks,
        memory: MemoryFigures {
            budget: mem.budget,
            fixed: mem.fixed,
            per_pixel: mem.per_pixel,
            scratch: mem.scratch,
            block_pixels: mem.block_pixels,
        },
        params: config.params_json(),
        details,
        notes,
        held_out,
        held_out_unavailable,
        largest_read_bytes: largest as u64,
        seconds: start.elapsed().as_secs_f64(),
        noise_floor,
        floor_sigma: if noise_floor { floor_sigma } else { None },
        binning: plan.binning,
        coarse_exact,
        dense: !plan.exact && plan.dense_pays(plan.op(), mem.budget),
        prune,
    })
}

/// The second step (module docs): solves blocks `blocks` (indices into the model's blocks) of
/// camera pixels with the model, reading their frames from `source`. Parts of disjoint blocks
/// can be solved in any order, in any process; each row depends only on its own block's frames
/// and the model. Runs on as many rayon threads as the planning process had (the split of a
/// sum over threads is part of the arithmetic), in a pool of its own when this process has
/// another number. Progress goes from the model's start (0.2 after a model choice) to 1 over
/// these blocks.
pub fn solve_transport_blocks(
    spec: &PatternSpec,
    model: &TransportModel,
    blocks: Range<usize>,
    source: &mut (dyn FrameSource + Send),
    control: &Control,
) -> Result<TransportPart, ReconError> {
    model.check_spec(spec)?;
    let plan = validate(spec, model.camera_grid(), model.rows, model.binning)?;
    if plan.exact != model.exact {
        return Err(ReconError::Unsolvable(
            "the stored transport model does not fit this session's frames (exact inverse or not)"
                .into(),
        ));
    }
    if rayon::current_num_threads().max(1) == model.threads {
        return solve_with(&plan, model, blocks, source, control);
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(model.threads)
        .build()
        .map_err(|e| ReconError::Unsolvable(format!("a pool of {} threads: {e}", model.threads)))?;
    pool.install(|| {
        let source: &mut dyn FrameSource = source;
        solve_with(&plan, model, blocks, source, control)
    })
}

fn solve_with(
    plan: &Plan,
    model: &TransportModel,
    blocks: Range<usize>,
    source: &mut dyn FrameSource,
    control: &Control,
) -> Result<TransportPart, ReconError> {
    let start = Instant::now();
    if blocks.start >= blocks.end || blocks.end > model.blocks.len() {
        return Err(ReconError::Unsolvable(format!(
            "blocks {blocks:?} of a transport model with {} blocks",
            model.blocks.len()
        )));
    }
    let k = plan.k();
    let (pw, ph) = plan.size();
    let n_read = plan.rows_read;
    let camera = model.camera_grid();
    let transform = model.transform;
    let psi = transform.build(pw, ph);
    let mut shared = Shared {
        op: plan.op(),
        dense: None,
        psi: psi.as_ref(),
        identity: transform == TransformKind::Identity,
        lipschitz: model.lipschitz,
        free: free_coefficients(transform),
        max_iter: model.max_iter,
        tol: model.tol,
        cgls_refit: model.version >= 5 && plan.cgls_refit(),
    };
    let dense = model.dense.then(|| batch::Dense::new(&shared));
    shared.dense = dense.as_ref();
    let coarse_exact = match &plan.raw {
        Raw::Hadamard(op) if model.coarse_exact => {
            let mut step = CoarseExact::new(plan, op).ok_or_else(|| {
                ReconError::Unsolvable(
                    "the stored transport model takes coarse Haar coefficients as measured, and this session's pairs do not measure them"
                        .into(),
                )
            })?;
            // A model planned before version 6 keeps the finer coefficients it kept then.
            step.fine_test = model.version >= 6;
            Some(step)
        }
        _ if model.coarse_exact => {
            return Err(ReconError::Unsolvable(
                "the stored transport model takes coarse Haar coefficients as measured, which only Hadamard pairs do"
                    .into(),
            ));
        }
        _ => None,
    };
    let stored = model.stored_transform();
    let ones = constant_coefficients(stored, (pw, ph));
    let mut builder = Builder::new(plan.grid, (camera.width, camera.height), stored);
    let progress0 = if model.exact { 0.0 } else { 0.2 };
    let mut tally = Tally::default();
    let mut largest = 0usize;
    let mut sigmas = Vec::new();
    let count = blocks.len();
    for (done, bi) in blocks.clone().enumerate() {
        if control.is_cancelled() {
            return Err(ReconError::Cancelled);
        }
        let (b0, b1) = model.blocks[bi];
        let range = b0..b1;
        let frames = read(source, range.clone(), n_read, &mut largest)?;
        let len = range.len();
        if model.exact {
            let mut s = vec![0.0; len * k];
            let mut block_sigmas = Vec::with_capacity(len);
            for (c, row) in s.chunks_exact_mut(k).enumerate() {
                let t = plan.exact_inverse(&plan.raw_column(&frames, len, c));
                block_sigmas.push(noise_sigma(&t, pw, ph));
                psi.apply(&t, row);
            }
            drop(frames);
            let keep = exact_support(&s, &block_sigmas, k, b0, camera.width as usize);
            for (row, kept) in s.chunks_exact(k).zip(keep.chunks_exact(k)) {
                builder.push_kept(row, kept);
            }
            sigmas.extend(block_sigmas);
        } else {
            let n = plan.op().rows();
            let mut bs = Vec::with_capacity(len * n);
            let mut floors = Vec::new();
            let mut row_sigmas = Vec::new();
            for c in 0..len {
                let raw = plan.raw_column(&frames, len, c);
                if coarse_exact.is_some() {
                    row_sigmas.push(pair_sigma(&plan.pair_sums(&frames, len, c), &raw, k));
                }
                if model.noise_floor {
                    floors.push(match (&plan.raw, model.floor_sigma) {
                        (Raw::Bernoulli(op), Some(sigma)) => random_noise_floor(op, sigma),
                        _ => noise_floor(&plan.pair_sums(&frames, len, c), &raw, k),
                    });
                }
                bs.extend(plan.fit_data(&raw));
            }
            drop(frames);
            let mut s = solve_block(
                &shared,
                (&bs, &floors),
                model.lambda.ok_or_else(|| {
                    ReconError::Unsolvable("the stored transport model has no weight".into())
                })?,
                model.coarse.then_some(camera.width as usize),
                model.chunk,
                &mut tally,
                control,
            )?;
            if model.refit {
                let it = batch::refit_rows(&shared, &bs, &mut s, model.chunk, control)?;
                tally.refit_iterations += it.iter().sum::<usize>() as u64;
            }
            if let Some(step) = &coarse_exact {
                let pixels: Vec<usize> = range.clone().collect();
                step.apply(
                    shared.op,
                    &bs,
                    &mut s,
                    &|row, img| shared.inverse(row, img),
                    &row_sigmas,
                    (&pixels, camera.width as usize),
                );
            }
            for &share in &model.prune {
                prune_rows(&mut s, k, share, free_coefficients(stored), &ones);
                if model.refit && coarse_exact.is_none() {
                    let it = batch::refit_rows(&shared, &bs, &mut s, model.chunk, control)?;
                    tally.refit_iterations += it.iter().sum::<usize>() as u64;
                }
            }
            for row in s.chunks_exact(k) {
                builder.push_row(row, 0.0);
            }
        }
        control.set_progress(progress0 + (1.0 - progress0) * (done + 1) as f64 / count as f64);
    }
    let (row_ptr, index, value) = builder.into_rows();
    Ok(TransportPart {
        blocks,
        row_ptr,
        index,
        value,
        sigmas,
        iterations: tally.iterations,
        iterations_max: tally.iterations_max as u64,
        parent_iterations: tally.parent_iterations,
        parent_rows: tally.parent_rows,
        refit_iterations: tally.refit_iterations,
        largest_read_bytes: largest as u64,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The third step (module docs): the model and the parts of all its blocks, in block order
/// (parts may group blocks in any way), into `T` and the report. The report's `seconds` is the
/// planning's plus every part's (compute time, whatever ran in parallel).
pub fn assemble_transport(
    model: &TransportModel,
    parts: &[TransportPart],
) -> Result<(TransportMatrix, Report), ReconError> {
    let m = model.camera.0 as usize * model.camera.1 as usize;
    let k = model.projector.0 as usize * model.projector.1 as usize;
    let inconsistent = |why: String| ReconError::Unsolvable(format!("assembling T: {why}"));
    let mut next = 0usize;
    for p in parts {
        if p.blocks.start != next || p.blocks.end <= p.blocks.start {
            return Err(inconsistent(format!(
                "a part of blocks {:?} where block {next} was due",
                p.blocks
            )));
        }
        let pixels = model
            .blocks
            .get(p.blocks.start..p.blocks.end)
            .ok_or_else(|| inconsistent(format!("blocks {:?} out of range", p.blocks)))?
            .iter()
            .map(|(a, b)| b - a)
            .sum::<usize>();
        if p.rows() != pixels {
            return Err(inconsistent(format!(
                "the part of blocks {:?} has {} rows for {pixels} camera pixels",
                p.blocks,
                p.rows()
            )));
        }
        next = p.blocks.end;
    }
    if next != model.blocks.len() {
        return Err(inconsistent(format!(
            "parts cover blocks 0..{next} of {}",
            model.blocks.len()
        )));
    }
    let mut builder = Builder::new(model.projector, model.camera, model.stored_transform());
    let mut tally = Tally::default();
    let mut largest = model.largest_read_bytes;
    let mut sigmas = Vec::new();
    let mut seconds = model.seconds;
    for p in parts {
        builder.append_rows(&p.row_ptr, &p.index, &p.value);
        tally.iterations += p.iterations;
        tally.iterations_max = tally.iterations_max.max(p.iterations_max as usize);
        tally.parent_iterations += p.parent_iterations;
        tally.parent_rows += p.parent_rows;
        tally.refit_iterations += p.refit_iterations;
        largest = largest.max(p.largest_read_bytes);
        sigmas.extend_from_slice(&p.sigmas);
        seconds += p.seconds;
    }
    let matrix = builder.finish();
    let mut details = model.details.clone();
    let stored = matrix.stored_bytes();
    details.insert("transform".into(), json!(model.transform.name()));
    details.insert(
        "stored_transform".into(),
        json!(model.stored_transform().name()),
    );
    details.insert("coarse_exact".into(), json!(model.coarse_exact));
    details.insert("lambda".into(), json!(model.lambda));
    details.insert("refit".into(), json!(model.refit));
    details.insert("prune".into(), json!(model.prune));
    details.insert(
        "projector".into(),
        json!([model.projector.0, model.projector.1]),
    );
    details.insert("camera".into(), json!([model.camera.0, model.camera.1]));
    details.insert(
        "path".into(),
        json!(if model.exact {
            "exact inverse of a complete set, coefficients below the noise dropped"
        } else {
            if model.dense {
                "l1 in an orthonormal transform, coordinate descent per camera pixel on A Psi^T held densely"
            } else {
                "l1 in an orthonormal transform, batched FISTA over the camera pixels"
            }
        }),
    );
    details.insert("stored_bytes".into(), json!(stored));
    details.insert("dense_f32_bytes".into(), json!(m * k * 4));
    details.insert("nonzeros".into(), json!(matrix.nonzeros()));
    details.insert(
        "nonzeros_per_row".into(),
        json!(matrix.nonzeros() as f64 / m as f64),
    );
    details.insert("seconds".into(), json!(seconds));
    if model.exact {
        sigmas.sort_by(|a, b| a.total_cmp(b));
        details.insert(
            "noise_sigma_median".into(),
            json!(sigmas.get(sigmas.len() / 2).copied().unwrap_or(0.0)),
        );
    } else {
        details.insert(
            "iterations_mean".into(),
            json!(tally.iterations as f64 / m as f64),
        );
        details.insert("iterations_max".into(), json!(tally.iterations_max));
        details.insert(
            "refit_iterations_mean".into(),
            json!(tally.refit_iterations as f64 / m as f64),
        );
        details.insert("lipschitz".into(), json!(model.lipschitz));
    }
    details.insert(
        "coarse_to_fine".into(),
        json!({
            "requested": model.coarse_requested,
            "used": model.coarse,
            "parent_rows": tally.parent_rows,
            "parent_iterations": tally.parent_iterations,
        }),
    );
    let mem = &model.memory;
    let largest_block = model.blocks.iter().map(|(a, b)| b - a).max().unwrap_or(0);
    details.insert(
        "memory".into(),
        json!({
            "budget_bytes": mem.budget,
            "working_set_bytes": mem.fixed + mem.scratch + mem.per_pixel * largest_block,
            "fixed_bytes": mem.fixed,
            "solver_scratch_bytes": mem.scratch,
            "bytes_per_camera_pixel": mem.per_pixel,
            "block_pixels": mem.block_pixels,
            "blocks": model.blocks.len(),
            "largest_read_bytes": largest,
        }),
    );
    if !model.notes.is_empty() {
        details.insert("notes".into(), json!(model.notes));
    }
    let report = Report {
        method: "transport".into(),
        params: model.params.clone(),
        rows_used: model.rows,
        iterations: tally.iterations + tally.parent_iterations + tally.refit_iterations,
        details,
        held_out: model.held_out.clone(),
        held_out_unavailable: model.held_out_unavailable.clone(),
    };
    Ok((matrix, report))
}

/// The continuation path down to `lambda`: the larger fractions of [`LAMBDA_PATH`], then
/// `lambda` itself (each solve warm-starts the next; a cold solve at a small weight is slow).
/// Every row's l1 weight: `frac` of its own `lambda_max`, never below its noise floor (when
/// `floors` has one per row).
fn weights(lam_max: &[f64], frac: f64, floors: &[f64]) -> Vec<f64> {
    lam_max
        .iter()
        .enumerate()
        .map(|(j, l)| (l * frac).max(floors.get(j).copied().unwrap_or(0.0)))
        .collect()
}

/// A Hadamard row's noise floor on its l1 weight: `sqrt(2 ln k) sigma`, with `sigma` the noise
/// of its data (`(y+ - y-) / sqrt(k)`) from the spread of its split-pair sums `y+ + y-`
/// ([`super::noise::from_pair_sums`]), the universal threshold (Donoho-Johnstone): pure noise
/// stays below it in every coefficient of an orthonormal transform with high probability (the
/// rows are orthonormal, so each coefficient's noise is at most `sigma`). A weight relative to
/// the row's own `lambda_max` alone is below the noise in a dim row, where it fitted hundreds
/// of noise coefficients (1 % frame noise: 420-810 per row where the complete set keeps 4-128).
/// 0 without a noise estimate.
fn noise_floor(sums: &[f64], raw: &[f64], k: usize) -> f64 {
    pair_sigma(sums, raw, k) * (2.0 * (k as f64).ln()).sqrt()
}

/// The noise of a Hadamard row's data (and of each coefficient of an orthonormal transform)
/// from its split-pair sums ([`super::noise::from_pair_sums`]); 0 without an estimate.
fn pair_sigma(sums: &[f64], raw: &[f64], k: usize) -> f64 {
    super::noise::from_pair_sums(sums, 1.0 / (k as f64).sqrt(), raw).map_or(0.0, |n| n.sigma)
}

/// A Bernoulli session's noise floor on every row's weight: `sqrt(2 ln k) sigma sqrt(n p (1 - p))`,
/// `sqrt(n p (1 - p))` the norm of a centred pattern column (the noise's spread in every
/// coefficient of an orthonormal transform) and `sigma` the frames' noise: the median over the
/// sample pixels of their random-pattern moment estimates ([`super::noise::from_random_rows`]),
/// which are near the truth on dim rows and scatter by 30x on bright sparse ones (glossy scene:
/// 0 to 11.7 where the frame noise was 0.4).
fn random_noise_floor(op: &CentredOperator<BernoulliOperator>, sigma: f64) -> f64 {
    let inner = op.inner();
    let (n, k) = (inner.rows(), inner.cols());
    let p = inner.row_sums().iter().sum::<f64>() / (n as f64 * k as f64).max(1.0);
    random_floor(sigma, n, p, k)
}

/// [`random_noise_floor`] for `n` frames of fill `p` over `k` pixels.
fn random_floor(sigma: f64, n: usize, p: f64, k: usize) -> f64 {
    sigma * (n as f64 * p * (1.0 - p)).sqrt() * (2.0 * (k as f64).ln()).sqrt()
}

/// The median of the sample rows' frame-noise estimates (random patterns), if any row has one.
fn random_noise_sigma(op: &CentredOperator<BernoulliOperator>, raws: &[Vec<f64>]) -> Option<f64> {
    let mut sigmas: Vec<f64> = raws
        .iter()
        .filter_map(|raw| super::noise::from_random_rows(op.inner(), raw).map(|e| e.sigma))
        .collect();
    if sigmas.is_empty() {
        return None;
    }
    let mid = sigmas.len() / 2;
    let (_, median, _) = sigmas.select_nth_unstable_by(mid, f64::total_cmp);
    Some(*median)
}

fn continuation(lambda: f64) -> Vec<f64> {
    let mut path: Vec<f64> = LAMBDA_PATH
        .iter()
        .copied()
        .filter(|&l| l > lambda * 1.0001)
        .collect();
    path.push(lambda);
    path
}

/// The smallest binning `b` (a power of two, at least 2) at which a Hadamard subset's pairs
/// hold every Walsh function constant on `b x b` blocks of the `grid`: a complete set on the
/// coarse grid, which `projector_binning = b` inverts exactly. `None` when no grid coarser than
/// one pixel is complete.
fn complete_binning(op: &HadamardOperator, (w, h): (u32, u32)) -> Option<u32> {
    let (wu, hu) = (w as usize, h as usize);
    let mut b = 2usize;
    while b < wu.max(hu) && wu % b == 0 && hu % b == 0 {
        let blocks = (wu / b) * (hu / b);
        let measured = op
            .natural_indices()
            .iter()
            .filter(|&&n| (n / wu) % b == 0 && (n % wu) % b == 0)
            .count();
        if measured == blocks && blocks > 1 {
            return Some(b as u32);
        }
        b *= 2;
    }
    None
}

/// The largest dense `A Psi^T` a random-pattern session's rows are solved on ([`batch::Dense`]);
/// larger ones are solved by FISTA on the packed patterns. 1,638 frames of a 128x128 projector
/// (10 %) take 214 MiB.
const DENSE_MAX_BYTES: usize = 256 << 20;

/// Estimated relative error of `T` from a Hadamard subset above which the report warns.
const SUBSET_ERROR_WARNING: f64 = 0.2;

/// How much looser than `tol` the stages of a continuation path before its last are solved.
const WARM_STAGE_TOL_FACTOR: f64 = 10.0;

/// Solves rows along `path` (fractions of each row's `lambda_max`), warm-starting `s`; every
/// stage but the last to [`WARM_STAGE_TOL_FACTOR`] times the tolerance (they are warm starts).
/// Returns the iterations of every row summed over the path.
fn solve_path(
    sh: &Shared,
    (bs, floors): (&[f64], &[f64]),
    path: &[f64],
    s: &mut [f64],
    chunk: usize,
    control: &Control,
) -> Result<Vec<usize>, ReconError> {
    let lam_max = batch::lambda_max(sh, bs, chunk);
    let mut total = vec![0usize; lam_max.len()];
    // The stages before the last only warm-start the next: solved to a tenth of the precision.
    let loose = Shared {
        tol: sh.tol * WARM_STAGE_TOL_FACTOR,
        ..*sh
    };
    for (stage, &frac) in path.iter().enumerate() {
        let lams = weights(&lam_max, frac, floors);
        let at = if stage + 1 < path.len() { &loose } else { sh };
        let it = batch::solve_rows(at, bs, &lams, s, chunk, control)?;
        total.iter_mut().zip(&it).for_each(|(t, i)| *t += i);
    }
    Ok(total)
}

/// Solves one block's rows (`bs`: pixels x n) along the continuation path; with `coarse` (the
/// camera width), the 2x2 parents go down the path first and every pixel then starts from its
/// parent's solution at the final weight. Returns the coefficients (pixels x k).
fn solve_block(
    sh: &Shared,
    (bs, floors): (&[f64], &[f64]),
    lambda: f64,
    coarse: Option<usize>,
    chunk: usize,
    tally: &mut Tally,
    control: &Control,
) -> Result<Vec<f64>, ReconError> {
    let (k, n) = (sh.op.cols(), sh.op.rows());
    let pixels = bs.len() / n.max(1);
    let mut s = vec![0.0; pixels * k];
    let path = match coarse {
        None => continuation(lambda),
        Some(w) => {
            let groups = parents(pixels, w);
            let mut pb = vec![0.0; groups.len() * n];
            for (g, children) in groups.iter().enumerate() {
                let row = &mut pb[g * n..(g + 1) * n];
                for &c in children {
                    row.iter_mut()
                        .zip(&bs[c * n..(c + 1) * n])
                        .for_each(|(a, b)| *a += b);
                }
                let inv = 1.0 / children.len() as f64;
                row.iter_mut().for_each(|v| *v *= inv);
            }
            // A parent's datum is its children's mean: its noise, their mean noise over the
            // square root of their number.
            let parent_floors: Vec<f64> = if floors.is_empty() {
                Vec::new()
            } else {
                groups
                    .iter()
                    .map(|ch| {
                        let n = ch.len() as f64;
                        ch.iter().map(|&c| floors[c]).sum::<f64>() / n / n.sqrt()
                    })
                    .collect()
            };
            let mut ps = vec![0.0; groups.len() * k];
            let it = solve_path(
                sh,
                (&pb, &parent_floors),
                &continuation(lambda),
                &mut ps,
                chunk,
                control,
            )?;
            tally.parent_iterations += it.iter().sum::<usize>() as u64;
            tally.parent_rows += groups.len() as u64;
            for (g, children) in groups.iter().enumerate() {
                for &c in children {
                    s[c * k..(c + 1) * k].copy_from_slice(&ps[g * k..(g + 1) * k]);
                }
            }
            vec![lambda]
        }
    };
    let it = solve_path(sh, (bs, floors), &path, &mut s, chunk, control)?;
    tally.iterations += it.iter().sum::<usize>() as u64;
    tally.iterations_max = tally
        .iterations_max
        .max(it.iter().copied().max().unwrap_or(0));
    Ok(s)
}

/// The data choose the transform and the weight: every candidate along its path, fitted on the
/// sample pixels without the held-out rows, scored on them (module docs).
#[allow(clippy::too_many_arguments)]
fn choose_model(
    plan: &Plan,
    config: &TransportConfig,
    source: &mut dyn FrameSource,
    (m, camera_width): (usize, usize),
    sample: usize,
    mem: &MemoryPlan,
    largest: &mut usize,
    details: &mut serde_json::Map<String, Value>,
    held_out: &mut Option<holdout::HeldOut>,
    held_out_unavailable: &mut Option<String>,
    floor_sigma: &mut Option<f64>,
    control: &Control,
) -> Result<ModelChoice, ReconError> {
    let (pw, ph) = plan.size();
    let k = plan.k();
    let fraction = config
        .holdout
        .unwrap_or_else(|| holdout::default_fraction(plan.raw_rows()));
    // Hadamard subsets are ordered (coarse patterns first): hold out the last measured pairs.
    let ordered = matches!(plan.raw, Raw::Hadamard(_));
    let split = match if ordered {
        holdout::tail(plan.raw_rows(), fraction)
    } else {
        holdout::split(plan.raw_rows(), fraction)
    } {
        Ok(s) => s,
        Err(why) => {
            let transform = config.transform.unwrap_or(TransformKind::Haar);
            let lambda = config.lambda.unwrap_or(1e-3);
            *held_out_unavailable = Some(why.clone());
            details.insert(
                "selection".into(),
                json!({"rule": format!("defaults (no held-out rows: {why})")}),
            );
            return Ok(ModelChoice {
                kind: transform,
                lambda,
                refit: false,
                floored: false,
                coarse: false,
                prune: Vec::new(),
            });
        }
    };
    let drawn = energy_sample(plan, source, m, mem.block_pixels, sample, largest, control)?;
    let picked: Vec<usize> = drawn.iter().map(|d| d.0).collect();
    let chance: Vec<f64> = drawn.iter().map(|d| d.1).collect();
    let (raws, sums) = read_columns(plan, source, &picked, mem.block_pixels, largest)?;
    let rows = raws.len();
    let (train, test) = plan.holdout_ops(&split)?;
    let n = train.op().rows();
    let mut bs = Vec::with_capacity(rows * n);
    let mut observed = Vec::with_capacity(rows);
    // The mean square of a training datum as measured (the scale compaction's share is taken
    // against, [`PRUNE_SHARE`]).
    let (mut datum2, mut data) = (0.0f64, 0usize);
    for raw in &raws {
        let train_raw: Vec<f64> = split.train.iter().map(|&i| raw[i]).collect();
        datum2 += train_raw.iter().map(|v| v * v).sum::<f64>();
        data += train_raw.len();
        bs.extend(train.data(&train_raw));
        observed.push(split.test.iter().map(|&i| raw[i]).collect::<Vec<f64>>());
    }
    let datum2 = datum2 / data.max(1) as f64;
    let lipschitz = plan.lipschitz(train.op());
    let transforms: Vec<TransformKind> = config
        .transform
        .map_or(CANDIDATE_TRANSFORMS.to_vec(), |t| vec![t]);
    let lambdas: Vec<f64> = config.lambda.map_or(LAMBDA_PATH.to_vec(), |l| vec![l]);
    let chunk = mem
        .chunk
        .min(rows.div_ceil(rayon::current_num_threads().max(1)))
        .max(1);
    let mut candidates = Vec::new();
    let mut pruned = Vec::new();
    // A Hadamard subset's held-out pairs are its last measured ones: they cannot see how a
    // model fills in what no pair measured. There the transforms are compared on the partly
    // measured scale orders ([`LevelTest`]) and the points are held to the light they keep
    // ([`subset_light_error`]).
    let subset_op = match &plan.raw {
        Raw::Hadamard(op) if sums.len() == raws.len() => Some(op),
        _ => None,
    };
    // A Hadamard subset's or a Bernoulli session's rows: every weight at least the row's
    // noise floor.
    let floors: Vec<f64> = match (subset_op, &plan.raw) {
        (Some(_), _) => raws
            .iter()
            .zip(&sums)
            .map(|(raw, sum)| noise_floor(sum, raw, k))
            .collect(),
        (None, Raw::Bernoulli(op)) => {
            random_noise_sigma(op, &raws).map_or_else(Vec::new, |sigma| {
                *floor_sigma = Some(sigma);
                vec![random_noise_floor(op, sigma); raws.len()]
            })
        }
        _ => Vec::new(),
    };
    // A Bernoulli session's held-out frames see the relight error ([`random_relight_error`]).
    let random_fill = match &plan.raw {
        Raw::Bernoulli(op) => {
            let inner = op.inner();
            let cells = (inner.rows() * inner.cols()).max(1) as f64;
            Some(inner.row_sums().iter().sum::<f64>() / cells)
        }
        _ => None,
    };
    // The frames' noise: the Bernoulli floor's (none found: noise-free).
    let relight_sigma = floor_sigma.unwrap_or(0.0);
    let level = match subset_op {
        Some(_) => LevelTest::new(plan, &raws, &floors)?,
        None => None,
    };
    // A subset's training pairs, for the coefficients they measure completely ([`CoarseExact`]),
    // with every sample pixel's noise.
    let coarse = subset_op.and_then(|op| CoarseExact::new(plan, &op.select_rows(&split.train)));
    let sample_sigmas: Vec<f64> = match subset_op {
        Some(_) => raws
            .iter()
            .zip(&sums)
            .map(|(raw, sum)| pair_sigma(sum, raw, k))
            .collect(),
        None => Vec::new(),
    };
    // (transform, level-test residual, nonzeros of the point it was tested at).
    let mut level_scores: Vec<(TransformKind, f64, f64)> = Vec::new();
    let mut scored: Vec<Point> = Vec::new();
    // A Hadamard subset's paths run twice: with every row's weight at least its noise floor
    // ([`noise_floor`]: a dim row otherwise keeps hundreds of noise coefficients) and without
    // (the floor drops light that lies below the noise in every row but adds up in a relight,
    // a dense interreflection; the light test below sees it).
    let floor_options: &[bool] = if !floors.is_empty() {
        &[false, true]
    } else {
        &[false]
    };
    let steps = (transforms.len() * lambdas.len() * floor_options.len()) as f64;
    let mut step = 0usize;
    for &kind in &transforms {
        let psi = kind.build(pw, ph);
        // The constant image's coefficients, for the light a compaction may drop ([`prune_rows`]).
        let kind_ones = constant_coefficients(kind, (pw, ph));
        let mut sh = Shared {
            op: train.op(),
            dense: None,
            psi: psi.as_ref(),
            identity: kind == TransformKind::Identity,
            lipschitz,
            free: free_coefficients(kind),
            max_iter: config.max_iter,
            tol: config.tol,
            cgls_refit: plan.cgls_refit(),
        };
        let dense = plan
            .dense_pays(train.op(), mem.budget)
            .then(|| batch::Dense::new(&sh));
        sh.dense = dense.as_ref();
        let lam_max = batch::lambda_max(&sh, &bs, chunk);
        let mut t = vec![0.0; rows * k];
        let h = test.rows();
        let mut pred = vec![0.0; rows * h];
        let smallest = lambdas.iter().copied().fold(f64::INFINITY, f64::min);
        for &floored in floor_options {
            // A floor below every weight of the path changes nothing (noise-free data).
            if floored && floors.iter().zip(&lam_max).all(|(f, l)| *f <= l * smallest) {
                continue;
            }
            let row_floors: &[f64] = if floored { &floors } else { &[] };
            let mut s = vec![0.0; rows * k];
            let mut worse = 0;
            let mut best_here = f64::INFINITY;
            for &frac in &lambdas {
                let lams = weights(&lam_max, frac, row_floors);
                let it = batch::solve_rows(&sh, &bs, &lams, &mut s, chunk, control)?;
                // The lasso point, then its least-squares refit on the same support (which
                // continues nothing: the path goes on from the lasso point).
                let mut refitted = s.clone();
                let refit_it = batch::refit_rows(&sh, &bs, &mut refitted, chunk, control)?;
                let mut value = f64::INFINITY;
                for (refit, coefficients, iterations) in
                    [(false, &s, &it), (true, &refitted, &refit_it)]
                {
                    // As fitted, and (where the training pairs measure a coarser grid
                    // completely) with those coefficients as measured ([`CoarseExact`]).
                    for with_coarse in [false, true] {
                        // The stored coefficients.
                        let mut u = match (&coarse, with_coarse) {
                            (None, true) => continue,
                            (Some(step), true) => {
                                let mut u = coefficients.clone();
                                step.apply(
                                    train.op(),
                                    &bs,
                                    &mut u,
                                    &|row, img| sh.inverse(row, img),
                                    &sample_sigmas,
                                    (&picked, camera_width),
                                );
                                u
                            }
                            _ => coefficients.clone(),
                        };
                        // As solved, then compacted at a share of its own held-out residual
                        // ([`prune_rows`]).
                        let mut prune: Vec<f64> = Vec::new();
                        let mut last = f64::INFINITY;
                        let mut solved = f64::INFINITY;
                        // Only a refitted point as fitted is compacted: without the refit,
                        // dropping a lasso point's smallest coefficients is only a larger
                        // threshold, which the path already tries (on an adaptive Hadamard set
                        // a compacted lasso point with the coarse coefficients as measured
                        // predicted the held-out pairs as well and had 2.6x the T error).
                        let rounds = if config.compact && refit && !with_coarse {
                            PRUNE_ROUNDS
                        } else {
                            0
                        };
                        loop {
                            match (&coarse, with_coarse) {
                                (Some(step), true) => step.images(&u, &mut t),
                                _ => sh.inverse(&u, &mut t),
                            }
                            let nnz = u.iter().filter(|v| **v != 0.0).count() as f64 / rows as f64;
                            test.apply_batch(&t, &mut pred, rows);
                            let mut score = Score::new(rows);
                            // Squared residual of every held-out row, summed over the sample
                            // pixels: their spread gives the standard error of the score.
                            let mut per_row = vec![0.0; h];
                            for (j, obs) in observed.iter().enumerate() {
                                let p = &pred[j * h..(j + 1) * h];
                                score.add_channel(j, obs, p);
                                per_row
                                    .iter_mut()
                                    .zip(obs.iter().zip(p))
                                    .for_each(|(e, (o, p))| *e += (o - p) * (o - p));
                            }
                            let rho = score.finish(split.fraction).relative_residual;
                            let se = rho.map(|r| r * relative_standard_error(&per_row));
                            let estimate = subset_op
                                .and_then(|op| subset_error(op, (&raws, &sums, &chance), &t))
                                .map(|e| e.relative);
                            let light = subset_op
                                .and_then(|op| subset_light_error(op, (&raws, &sums, &chance), &t));
                            let relight = random_fill.and_then(|fill| {
                                random_relight_error(
                                    (&observed, &pred, h),
                                    &t,
                                    k,
                                    (&picked, &chance),
                                    fill,
                                    relight_sigma,
                                )
                            });
                            candidates.push(Candidate {
                                transform: kind.name(),
                                lambda: frac,
                                held_out: rho,
                                held_out_se: se,
                                error_estimate: estimate,
                                light_error: light.map(|l| l.0),
                                relight_error_estimate: relight.map(RelightEstimate::to_json),
                                iterations_mean: iterations.iter().sum::<usize>() as f64
                                    / rows as f64,
                                nonzeros_mean: nnz,
                                refit,
                                noise_floor: floored,
                                coarse_exact: with_coarse,
                                prune: prune.clone(),
                            });
                            let v = rho.unwrap_or(f64::INFINITY);
                            // The path's stopping rule sees the points as solved.
                            if prune.is_empty() {
                                value = value.min(v);
                                solved = v;
                            }
                            // A compacted point competes only where the held-out rows do not
                            // see it predict worse than the point as solved: what it dropped
                            // was spurious (on the weak held-out pairs of an adaptive Hadamard
                            // set a compacted lasso point 4 % worse, within their standard
                            // error, was chosen for its sparsity at 6x the T error). The report
                            // lists it either way.
                            if prune.is_empty() || v <= solved {
                                scored.push(Point {
                                    kind,
                                    lambda: frac,
                                    refit,
                                    held_out: v,
                                    se: se.unwrap_or(0.0),
                                    nonzeros: nnz,
                                    score,
                                    light,
                                    floored,
                                    coarse: with_coarse,
                                    relight,
                                    prune: prune.clone(),
                                });
                            }
                            // Another round while the last one predicted the held-out rows better,
                            // each at the share of the point as solved.
                            let share = match rho {
                                Some(r)
                                    if prune.len() < rounds
                                        && r.is_finite()
                                        && r > 0.0
                                        && r < last
                                        && datum2 > 0.0 =>
                                {
                                    last = r;
                                    // The held-out residual's RMS against a training datum's
                                    // (not against the held-out data's own: the held-out pairs
                                    // of a Hadamard subset are its weakest).
                                    let rms = (per_row.iter().sum::<f64>()
                                        / (rows * h).max(1) as f64
                                        / datum2)
                                        .sqrt();
                                    prune.first().copied().unwrap_or(rms * PRUNE_SHARE)
                                }
                                _ => break,
                            };
                            // Prune, then refit (also where nothing more goes: the held-out
                            // rows decide whether the refit had converged).
                            prune_rows(&mut u, k, share, free_coefficients(kind), &kind_ones);
                            batch::refit_rows(&sh, &bs, &mut u, chunk, control)?;
                            prune.push(share);
                        }
                    }
                }
                step += 1;
                control.set_progress(0.2 * step as f64 / steps);
                // Down the path: stop once the held-out error has risen twice in a row, or once
                // it is more than 3x the best of the transforms before and its last step bought
                // less than a quarter (it is not catching up).
                let others = scored
                    .iter()
                    .filter(|c| c.kind != kind && c.prune.is_empty())
                    .map(|c| c.held_out)
                    .fold(f64::INFINITY, f64::min);
                if value > 3.0 * others && value > 0.75 * best_here {
                    if !pruned.contains(&kind.name()) {
                        pruned.push(kind.name());
                    }
                    break;
                }
                if value < best_here {
                    best_here = value;
                    worse = 0;
                } else {
                    worse += 1;
                    if worse >= 2 {
                        break;
                    }
                }
            }
        }
    }
    if let Some(level) = &level {
        for &kind in &transforms {
            // At the weight (and refit, and floor) the held-out pairs like best for this
            // transform, as fitted (the coarse coefficients taken as measured change nothing
            // the level test or the held-out pairs see).
            let Some(at) = scored
                .iter()
                .filter(|c| c.kind == kind && !c.coarse && c.prune.is_empty())
                .min_by(|a, b| a.held_out.total_cmp(&b.held_out))
            else {
                continue;
            };
            if let Some(v) = level.score(
                kind,
                (at.lambda, at.refit, at.floored),
                config,
                chunk,
                control,
            )? {
                level_scores.push((kind, v, at.nonzeros));
            }
        }
    }
    let identifiable = super::auto::identifiable_coefficients(plan.op().rows(), k);
    // A Hadamard subset: the transform that fills in partly measured scale orders best
    // ([`LevelTest`]); within it, the points that keep the total light (the fitted rows' sum
    // within max(0.5 %, three standard errors of its noise) of the measured one:
    // [`subset_light_error`]; if none does, the one nearest), and among those the one the
    // held-out pairs choose.
    let by_level = !level_scores.is_empty();
    // Within a transform (or all): the points that keep the light (subsets), the best held-out
    // score among them, and the sparsest point within one standard error of it.
    fn pick(pool: Vec<&Point>, subset: bool) -> Option<(&Point, &Point)> {
        let mut eligible = pool;
        if subset {
            let keeps = |c: &Point| {
                c.light
                    .is_some_and(|(e, se)| e <= (3.0 * se).max(LIGHT_TOLERANCE))
            };
            if eligible.iter().any(|c| keeps(c)) {
                eligible.retain(|c| keeps(c));
            } else if let Some(nearest) = eligible
                .iter()
                .filter_map(|c| c.light.map(|l| l.0))
                .min_by(f64::total_cmp)
            {
                eligible.retain(|c| c.light.is_some_and(|l| l.0 <= nearest));
            }
        }
        // Compaction ([`prune_rows`]) refines a fit, it does not choose the basis: compacted
        // points compete only in the transform of the best point as solved (on noise-free
        // sparse rows a compacted wavelet fit predicted to 1.4e-6 where the pixel basis, with a
        // fifth of its coefficients, did to 2.2e-6: both exact).
        if let Some(basis) = eligible
            .iter()
            .filter(|c| c.prune.is_empty())
            .min_by(|a, b| a.held_out.total_cmp(&b.held_out))
            .map(|c| c.kind)
        {
            eligible.retain(|c| c.prune.is_empty() || c.kind == basis);
        }
        let best = *eligible
            .iter()
            .min_by(|a, b| a.held_out.total_cmp(&b.held_out))?;
        // The sparsest model within one standard error of the best held-out score (ties: the
        // larger weight, which comes first along each path, then the lower score: a lasso
        // point and its refit keep the same coefficients).
        let within = best.held_out + best.se;
        let chosen = *eligible
            .iter()
            .filter(|c| c.held_out <= within)
            .min_by(|a, b| {
                a.nonzeros
                    .total_cmp(&b.nonzeros)
                    .then(b.lambda.total_cmp(&a.lambda))
                    .then(a.held_out.total_cmp(&b.held_out))
            })?;
        Some((best, chosen))
    }
    let subset = subset_op.is_some();
    // Of the transforms whose level-test residual is within 10 % (plus [`LEVEL_TIE`]) of the
    // lowest, the sparsest at its tested point.
    let transform_by_level = level_scores
        .iter()
        .map(|l| l.1)
        .min_by(f64::total_cmp)
        .and_then(|lowest| {
            level_scores
                .iter()
                .filter(|l| l.1 <= lowest * 1.1 + LEVEL_TIE)
                .min_by(|a, b| a.2.total_cmp(&b.2))
                .map(|l| l.0)
        });
    let (best, chosen) = pick(
        scored
            .iter()
            .filter(|c| transform_by_level.is_none_or(|t| c.kind == t))
            .collect(),
        subset,
    )
    .expect("at least one candidate");
    let choice = ModelChoice {
        kind: chosen.kind,
        lambda: chosen.lambda,
        refit: chosen.refit,
        floored: chosen.floored,
        coarse: chosen.coarse,
        prune: chosen.prune.clone(),
    };
    let (transform, lambda, refit, floored, coarse_exact) = (
        chosen.kind,
        chosen.lambda,
        chosen.refit,
        chosen.floored,
        chosen.coarse,
    );
    *held_out = Some(chosen.score.finish(split.fraction));
    // A Bernoulli session's relight error by cross-validation over every frame, with the fit's
    // own noise ([`random_cv_relight_error`]); the choice's held-out frames where it cannot run.
    let relight = match random_fill {
        // Resolved by the choice's held-out frames, or bounded below
        // [`RELIGHT_CROSS_VALIDATE_ABOVE`]: nothing to add.
        Some(_)
            if chosen
                .relight
                .is_some_and(|r| r.resolved || r.upper <= RELIGHT_CROSS_VALIDATE_ABOVE) =>
        {
            chosen.relight
        }
        Some(fill) => {
            let cv = random_cv_relight_error(&RelightSample {
                plan,
                model: &choice,
                raws: &raws,
                picked: &picked,
                chance: &chance,
                fill,
                sigma: relight_sigma,
                config,
                chunk,
                control,
            })?;
            match chosen.relight {
                Some(est) => Some(est.or_cross_validated(cv)),
                None => cv,
            }
        }
        None => chosen.relight,
    };
    if let Some(est) = relight {
        let mut reported = est.to_json();
        reported["light"] = json!("full (every camera pixel at 1)");
        reported["basis"] = json!(
            "the chosen model fitted without the held-out frames, on the sample pixels in runs of neighbours, each run weighted by 1 / its chance of being drawn: the variance over the held-out frames of the residuals summed over the camera, less the sample's own scatter and the frames' noise, over the patterns' variance f (1 - f); upper: two jackknife standard errors (over the held-out frames) above it (above 0 where it is negative), or the cross-validation's bound where that is lower; resolved: the estimate is more than two standard errors above 0; the fit without the held-out frames is on average worse than the served one, so both lean high; held_out: where the choice's held-out frames did not resolve the error, cross-validation over every frame (each fold fitted on the others: fits on 7/8 of the frames, so it leans higher still where the frames are near the fewest a sparse fit needs); noise (noisy frames, where the held-out frames did not resolve it): the error the frames' noise alone makes, by a parametric bootstrap (the sample rows fitted on every frame, frames simulated from that fit with the estimated noise, fitted again: the relight of the difference; it does not see light the fit already lost, so it leans low); relative: the held-out estimate where resolved, at least the noise; where unresolved, the noise (null without it), which upper bounds with the rest"
        );
        details.insert("relight_error_estimate".into(), reported);
        if let Some(relative) = est.reported().filter(|&r| r > SUBSET_ERROR_WARNING) {
            details.insert(
                "warnings".into(),
                json!([format!(
                    "the frames cannot support T at {}x{}: the estimated relative error of a full-light relight is {:.2}; measure more frames",
                    plan.grid.0, plan.grid.1, relative
                )]),
            );
        }
    }
    let coarser = match &plan.raw {
        Raw::Hadamard(op) => complete_binning(op, plan.grid),
        _ => None,
    };
    // A Hadamard subset's sample rows fitted with the choice on every measured pair (the error
    // of T), and its full-light relight error from the coarser grid it completes.
    let subset_fit = match subset_op {
        Some(op) => Some(fit_subset_sample(
            plan,
            &choice,
            (op, &raws, if choice.floored { &floors } else { &[] }),
            (&picked, camera_width, &sample_sigmas),
            config,
            chunk,
            control,
        )?),
        None => None,
    };
    if subset_op.is_some()
        && let Some(estimate) = subset_relight_error(
            plan,
            &choice,
            source,
            (m, camera_width, mem.block_pixels),
            largest,
            config,
            chunk,
            control,
        )?
    {
        details.insert("relight_error_estimate".into(), estimate);
    }
    if let (Some(op), Some((t, _))) = (subset_op, &subset_fit)
        && let Some(estimate) = hadamard_subset_error(op, (&raws, &sums, &chance), t)
    {
        if let Some(rel) = estimate["relative"].as_f64()
            && rel > SUBSET_ERROR_WARNING
        {
            let offer = coarser.map_or_else(
                || "reconstruct on a coarser projector grid".to_string(),
                |b| {
                    format!(
                        "reconstruct with params {{\"projector_binning\": {b}}}: the measured pairs are a complete set on the \
                         {}x{} grid of {b}x{b} projector blocks, which they invert exactly",
                        plan.grid.0 / b,
                        plan.grid.1 / b
                    )
                },
            );
            details.insert(
                "warnings".into(),
                json!([format!(
                    "the measured pairs cannot support T at {}x{}: its estimated relative error is {rel:.2} (most of it in \
                     the finer Hadamard coefficients no pair measured); measure more pairs, or {offer}",
                    plan.grid.0,
                    plan.grid.1
                )]),
            );
        }
        details.insert("error_estimate".into(), estimate);
    }
    if let Some(b) = coarser {
        details.insert(
            "coarser".into(),
            json!({
                "projector_binning": b,
                "projector": [plan.grid.0 / b, plan.grid.1 / b],
                "basis": "the finest grid of b x b projector blocks on which the measured pairs are a complete set: params {\"projector_binning\": b} reconstructs T there by the exact inverse",
            }),
        );
    }

    details.insert(
        "selection".into(),
        json!({
            "rule": if by_level {
                "the transform that fills in the partly measured scale orders best, of those within 10 % + 0.001 of the best the one with the fewest nonzeros (level_test: each transform at its best held-out weight, fitted without half of the measured pairs in the scale orders the set measures only partly, where the unmeasured coefficients are, predicting that half, as the whole set must predict the unmeasured ones; the held-out pairs, the last measured, are one class of patterns and cannot see that); within it, the points that keep the total light (light_error: the fitted rows' sums against the measured all-on pair's, weighted by 1 / the pixel's chance of being drawn, within max(0.5 %, three standard errors of its noise); if none does, the nearest), and among those the fewest nonzeros whose held-out relative residual is within one standard error of the lowest (with params compact, every refitted point also compacted: prune, its smallest coefficients dropped within a third of its held-out residual's RMS over a measured datum's, of each row's energy and of its light, and refitted, a candidate only where its held-out residual is no higher than the point's as solved)"
            } else {
                "the fewest nonzeros among the candidates (every lasso point and its least-squares refit on the same support, with params compact, each refit also compacted: prune, its smallest coefficients dropped within a third of its held-out residual's RMS over a measured datum's, of each row's energy and of its light, and refitted, a candidate only where its held-out residual is no higher than the refit's as solved) whose held-out relative residual on the sample pixels is within one standard error of the lowest (the one-standard-error rule)"
            },
            "identifiable_per_row_l1": if identifiable.is_finite() { json!(identifiable.round()) } else { Value::Null },
            "held_out_rows": if ordered {
                format!("the last {} of the {} measured split pairs (Hadamard rows are ordered: the unmeasured ones lie beyond them)", split.test.len(), plan.raw_rows())
            } else {
                format!("{} of {} rows, chosen by a hash of the row index", split.test.len(), plan.raw_rows())
            },
            "sample_pixels": rows,
            "pruned": pruned,
            "sample": "camera pixels drawn with probability in proportion to the energy of their data (systematic, deterministic)",
            "best": {"transform": best.kind.name(), "lambda": best.lambda, "refit": best.refit, "held_out": best.held_out, "standard_error": best.se, "nonzeros_mean": best.nonzeros},
            "chosen": {"transform": transform.name(), "lambda": lambda, "refit": refit, "noise_floor": floored, "coarse_exact": coarse_exact, "prune": &chosen.prune, "held_out": chosen.held_out, "light_error": chosen.light.map(|l| l.0), "nonzeros_mean": chosen.nonzeros},
            "level_test": level_scores.iter().map(|(kind, v, nnz)| json!({"transform": kind.name(), "relative_residual": v, "nonzeros_mean": nnz})).collect::<Vec<_>>(),
            "candidates": candidates,
        }),
    );
    Ok(choice)
}
