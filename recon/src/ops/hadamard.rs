//! Partial orthonormal 2D Walsh-Hadamard operator, through the fast transform.
//!
//! `A = S H / sqrt(k)`: `H` the k x k Sylvester matrix (row n = the 2D pattern with natural index
//! `n = u W + v`, column `y W + x`), `S` selects the natural indices of the spec's first `m` rows
//! in its ordering. `apply(x) = S fwht(x) / sqrt(k)`, `adjoint(d) = fwht(S^T d) / sqrt(k)`
//! (the zero-filled inverse), O(k log k) each; `A A^T = I` exactly, `||A|| = 1`.
//!
//! Data: a split pair (frames 2r, 2r+1 showing `P+ = (1+h)/2`, `P- = (1-h)/2`) gives
//! `y+ - y- = h . t`, so the data for this operator is `d_r = (y+ - y-) / sqrt(k)` (a constant
//! dark level cancels), built by [`HadamardOperator::split_pairs`], which also reports the pair
//! sums `y+ + y- = 1 . t + 2 dark` (constant unless the source drifts or the gain changes).
//!
//! Dense or fast: `ops::bench` measures both at 10 % of the frames. The transform wins at every
//! size from 16 x 16 (under a microsecond against ~4 us for the dense product of the subsampled
//! matrix) to 256 x 256 (~0.3 ms against ~0.6 s), so there is no dense path.

use helmholtz_proto::patterns::HadamardPlan;
use helmholtz_proto::{Family, HadamardOrdering, PatternSpec};
use rayon::prelude::*;

use super::OpError;
use super::scratch::Pool;
use crate::fwht::fwht;
use crate::linop::LinearOperator;

/// First `m` rows (in an ordering) of the orthonormal 2D Walsh-Hadamard transform.
#[derive(Debug)]
pub struct HadamardOperator {
    width: u32,
    height: u32,
    ordering: HadamardOrdering,
    /// Natural index of each row.
    natural: Vec<usize>,
    scale: f64,
    pool: Pool,
}

/// Split-pair frames turned into operator data (see [`HadamardOperator::split_pairs`]).
#[derive(Clone, Debug, PartialEq)]
pub struct SplitPairs {
    /// `d_r = (y+ - y-) / sqrt(k)`: the data for [`HadamardOperator`].
    pub data: Vec<f64>,
    /// `s_r = y+ + y-`: `1 . t + 2 dark` for every pair if the source is stable.
    pub sums: Vec<f64>,
    /// Mean of `sums`.
    pub sum_mean: f64,
    /// Standard deviation of `sums` over their mean (drift / gain monitor; 0 when stable).
    pub sum_relative_spread: f64,
    /// The P- frame of natural row 0 is all-off: its value is the dark level (when measured).
    pub dark: Option<f64>,
}

impl HadamardOperator {
    /// `rows` Hadamard rows (not frames) of a `width x height` grid (powers of two) in `ordering`.
    pub fn new(width: u32, height: u32, ordering: HadamardOrdering, rows: usize) -> Self {
        assert!(
            width.is_power_of_two() && height.is_power_of_two(),
            "hadamard needs 2^a x 2^b"
        );
        let k = width as usize * height as usize;
        assert!(
            rows <= k,
            "{rows} hadamard rows requested, a {width}x{height} grid has {k}"
        );
        let plan = HadamardPlan::new(width, height, ordering);
        let natural = (0..rows as u64)
            .map(|r| plan.natural_index(r) as usize)
            .collect();
        HadamardOperator {
            width,
            height,
            ordering,
            natural,
            scale: 1.0 / (k as f64).sqrt(),
            pool: Pool::new(),
        }
    }

    /// From a Hadamard spec and a number of *frames* (`frames / 2` complete pairs are used), or
    /// a resolved adaptive_hadamard spec (its natural indices, in the order shown).
    pub fn from_spec(spec: &PatternSpec, frames: u64) -> Result<Self, OpError> {
        if let Family::AdaptiveHadamard { .. } = spec.family() {
            let natural = super::adaptive_rows(spec, frames)?;
            return Ok(Self::with_natural(spec.width(), spec.height(), natural));
        }
        let Family::Hadamard { ordering } = *spec.family() else {
            return Err(OpError::WrongFamily {
                want: "hadamard",
                got: spec.family().name(),
            });
        };
        super::check_rows(spec, frames)?;
        Ok(Self::new(
            spec.width(),
            spec.height(),
            ordering,
            (frames / 2) as usize,
        ))
    }

    /// Rows with explicit natural indices `u W + v` (no repeats), e.g. an adaptive session's.
    /// Its `ordering()` reports `natural`.
    pub fn with_natural(width: u32, height: u32, natural: Vec<usize>) -> Self {
        let k = width as usize * height as usize;
        assert!(
            width.is_power_of_two() && height.is_power_of_two(),
            "hadamard needs 2^a x 2^b"
        );
        assert!(
            natural.iter().all(|&n| n < k),
            "natural index out of range 0..{k}"
        );
        HadamardOperator {
            width,
            height,
            ordering: HadamardOrdering::Natural,
            natural,
            scale: 1.0 / (k as f64).sqrt(),
            pool: Pool::new(),
        }
    }

    /// The operator of a subset of the rows, in the given order (e.g. the fitting rows of a
    /// hold-out split). `A A^T = I` still holds without repeats.
    pub fn select_rows(&self, rows: &[usize]) -> Self {
        HadamardOperator {
            width: self.width,
            height: self.height,
            ordering: self.ordering,
            natural: rows.iter().map(|&r| self.natural[r]).collect(),
            scale: self.scale,
            pool: Pool::new(),
        }
    }

    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn ordering(&self) -> HadamardOrdering {
        self.ordering
    }

    /// The finest grid any of these rows resolves: row `u W + v` is constant on blocks of
    /// `2^tz(v)` pixels along x and `2^tz(u)` along y (`tz` = trailing zeros; `h_n(x, y) =
    /// (-1)^popcount(n & (y W + x))`), so it resolves `W >> tz(v)` by `H >> tz(u)` (1 for 0).
    /// A subset of rows measures nothing finer than the largest of these.
    pub fn finest_resolution(&self) -> (usize, usize) {
        let (w, h) = (self.width as usize, self.height as usize);
        let resolve = |bits: usize, side: usize| {
            if bits == 0 {
                1
            } else {
                side >> bits.trailing_zeros()
            }
        };
        self.natural.iter().fold((1, 1), |(rx, ry), &n| {
            let (u, v) = (n / w, n % w);
            (rx.max(resolve(v, w)), ry.max(resolve(u, h)))
        })
    }

    /// Natural (Sylvester) index `u W + v` of each row.
    pub fn natural_indices(&self) -> &[usize] {
        &self.natural
    }

    /// Frames (one channel, in acquisition order: P+ of row 0, P- of row 0, P+ of row 1, ...) to
    /// data and monitors. Uses the first `2 * rows()` frames; panics if fewer are given.
    pub fn split_pairs(&self, frames: &[f64]) -> SplitPairs {
        self.split_pairs_channel(frames, 1, 0)
    }

    /// As [`HadamardOperator::split_pairs`] for channel `channel` of row-major
    /// `frames x channels` buckets.
    pub fn split_pairs_channel(
        &self,
        buckets: &[f64],
        channels: usize,
        channel: usize,
    ) -> SplitPairs {
        let m = self.natural.len();
        assert!(channel < channels, "channel {channel} of {channels}");
        assert!(
            buckets.len() >= 2 * m * channels,
            "need {} frames of {channels} channels",
            2 * m
        );
        let frame = |f: usize| buckets[f * channels + channel];
        let mut data = Vec::with_capacity(m);
        let mut sums = Vec::with_capacity(m);
        let mut dark = None;
        for (r, &n) in self.natural.iter().enumerate() {
            let (plus, minus) = (frame(2 * r), frame(2 * r + 1));
            data.push((plus - minus) * self.scale);
            sums.push(plus + minus);
            if n == 0 {
                dark = Some(minus);
            }
        }
        let sum_mean = if m > 0 {
            sums.iter().sum::<f64>() / m as f64
        } else {
            0.0
        };
        let var = if m > 0 {
            sums.iter()
                .map(|s| (s - sum_mean) * (s - sum_mean))
                .sum::<f64>()
                / m as f64
        } else {
            0.0
        };
        let sum_relative_spread = if sum_mean.abs() > 0.0 {
            var.sqrt() / sum_mean.abs()
        } else {
            0.0
        };
        SplitPairs {
            data,
            sums,
            sum_mean,
            sum_relative_spread,
            dark,
        }
    }

    fn forward_into(&self, x: &[f64], y: &mut [f64], work: &mut [f64]) {
        work.copy_from_slice(x);
        fwht(work);
        for (yi, &n) in y.iter_mut().zip(&self.natural) {
            *yi = work[n] * self.scale;
        }
    }

    fn adjoint_into(&self, y: &[f64], x: &mut [f64]) {
        x.fill(0.0);
        for (&yi, &n) in y.iter().zip(&self.natural) {
            x[n] += yi * self.scale;
        }
        fwht(x);
    }

    fn k(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Batches of small transforms run one vector per thread (a single transform below 2^16
    /// points is serial).
    fn parallel_batch(&self, batch: usize) -> bool {
        batch > 1 && self.k() >= 1 << 10 && self.k() < 1 << 16 && rayon::current_num_threads() > 1
    }
}

impl LinearOperator for HadamardOperator {
    fn rows(&self) -> usize {
        self.natural.len()
    }
    fn cols(&self) -> usize {
        self.k()
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        assert_eq!(x.len(), self.k());
        assert_eq!(y.len(), self.natural.len());
        let mut work = self.pool.take(self.k());
        self.forward_into(x, y, &mut work);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        assert_eq!(y.len(), self.natural.len());
        assert_eq!(x.len(), self.k());
        self.adjoint_into(y, x);
    }
    fn apply_batch(&self, xs: &[f64], ys: &mut [f64], batch: usize) {
        let (m, k) = (self.natural.len(), self.k());
        assert_eq!(xs.len(), k * batch);
        assert_eq!(ys.len(), m * batch);
        if m == 0 {
            return;
        }
        if self.parallel_batch(batch) {
            xs.par_chunks_exact(k)
                .zip(ys.par_chunks_exact_mut(m))
                .for_each(|(x, y)| {
                    let mut work = self.pool.take(k);
                    self.forward_into(x, y, &mut work);
                });
        } else {
            let mut work = self.pool.take(k);
            for (x, y) in xs.chunks_exact(k).zip(ys.chunks_exact_mut(m)) {
                self.forward_into(x, y, &mut work);
            }
        }
    }
    fn adjoint_batch(&self, ys: &[f64], xs: &mut [f64], batch: usize) {
        let (m, k) = (self.natural.len(), self.k());
        assert_eq!(ys.len(), m * batch);
        assert_eq!(xs.len(), k * batch);
        if m == 0 {
            xs.fill(0.0);
            return;
        }
        if self.parallel_batch(batch) {
            ys.par_chunks_exact(m)
                .zip(xs.par_chunks_exact_mut(k))
                .for_each(|(y, x)| self.adjoint_into(y, x));
        } else {
            for (y, x) in ys.chunks_exact(m).zip(xs.chunks_exact_mut(k)) {
                self.adjoint_into(y, x);
            }
        }
    }
    /// A batch runs its vectors on threads where one transform runs on one.
    fn batching_pays(&self) -> bool {
        self.parallel_batch(2)
    }
}
