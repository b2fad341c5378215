//! Adaptive acquisition: which basis functions an `adaptive_haar` / `adaptive_hadamard` session
//! shows next, decided batch by batch from the values measured so far.
//!
//! # The scheme (ABS-WP, Rousset et al. 2017, with a tree and a global ranking)
//!
//! Both bases are orthonormal on a `W x W` grid (`W = 2^m`, `k = W^2`), and both are multiscale:
//! every index `n` has a *level* `l(n)` ([`Basis::level`]): coefficient `c_n` is a function of
//! the image's block averages on `2^l x 2^l` blocks. Level `m` is the mean alone (index 0); level
//! `l < m` holds `3 * 4^(m-l-1)` coefficients (Haar: the details of support `2^(l+1)`;
//! Walsh-Hadamard: the rows with `min(tz(u), tz(v)) = l`, the Russian-doll level). A split pair
//! showing `P+ = [w > 0]`, `P- = [w < 0]` gives `y+ - y- = g_n c_n` (`g_n` = the Haar support side,
//! or `W` for Walsh-Hadamard, [`Basis::gain`]): an exact orthonormal coefficient, dark level
//! cancelled.
//!
//! After each observed batch the planner, per channel:
//! 1. forms the zero-filled image `x = sum over observed n of c_n psi_n` and its block averages
//!    `A_l` on `2^l` blocks, `l = 1..m` (exact if every coefficient of level `>= l` is observed);
//! 2. *predicts* every level-`l` coefficient from the bicubic 2x upsampling of `A_{l+1}` (a
//!    smooth guess of the image at level `l`'s resolution), transformed by the basis on that grid
//!    and rescaled by `2^l` to the full grid. Where the coarse image has an edge, the upsampling
//!    has one too, and the fine coefficients along it are predicted large;
//! 3. scores index `n` by `sum over channels of max(|p_{c,n}|, beta |c_{c,parent(n)}|) / ||c_c||`
//!    (each channel normalised by the norm of its observed coefficients), so one index serves
//!    every detector or camera pixel at once. `beta` is the spec's `persistence`: a detail that
//!    was measured large makes its children rank as if they were at least `beta` times its size
//!    (details persist across scales along an edge or a texture, which the bicubic guess from
//!    coarser block averages alone misses: along a step edge a Haar child is half its parent).
//!    The mean (index 0) passes nothing on.
//!
//! The next batch is the `B` not yet issued indices ranked by (parent issued first, score
//! descending, level descending, index ascending): a greedy choice of the largest predicted
//! coefficients (for an orthonormal basis the squared error of the zero-filled image is exactly the
//! energy of the unmeasured coefficients), kept tree-structured (a coefficient whose parent was
//! never issued only comes after all those whose parent was), and coarse-to-fine where the
//! prediction has nothing to say (before any value arrives, or on a flat scene).
//!
//! The estimated relative error of the zero-filled image is `sqrt(mean over channels of
//! E_c / S_c)`, which the stop rule `target_error` compares with. The spec's `error_estimate`
//! chooses its parts:
//! - `prediction` (sessions stored before 2026-11-29): `E_c` the predicted energy of the
//!   coefficients not yet issued, `S_c = ||c_c||^2`. The bicubic guess misses what the coarse levels
//!   do not show, so this reads a median 0.23-0.40 of the true error noise-free, and it ignores
//!   noise (about 0 of it at 30 dB on Haar: `docs/benchmarks-adaptive.md`).
//! - `measured` (the default): `E_c` is, for every coefficient not issued, its prediction scaled
//!   by its level's measured slope of values on predictions, squared, plus that level's measured
//!   mean squared miss; plus the noise of every coefficient issued (measured from the pair sums
//!   of equal supports). `S_c` counts only the coefficients that stand clear of their noise
//!   ([`estimate`] module docs).
//!
//! # Batches and latency
//!
//! At most [`LOOKAHEAD`] = 2 batches are issued and not yet observed: while the rig shows batch
//! `b + 1`, the planner decides batch `b + 2` from the values up to batch `b`. The decision (one
//! prediction per channel, O(k) for Haar and O(k log k) for Walsh-Hadamard, plus an O(k)
//! selection) must finish within one batch's display time. [`batch_pairs`] sizes automatic
//! batches as `max(16, ceil(k C / 1024), ceil(P / 128))` pairs (`C` channels, `P` the pair
//! budget). A batch of `k C / 1024` pairs lasts `k C / 1024 * 100 us` at 20 kHz binary frames,
//! about 100 ns per coefficient and channel; the decision measured by `bench --preset adaptive`
//! (`docs/benchmarks-adaptive.md`, one channel, a 2-core machine at load 6-7) costs a median
//! 0.3 ms at 128x128 (12-18 ns per coefficient; a 16-pair batch shows for 1.6 ms) and 2 ms at
//! 256x256 (a 64-pair batch: 6.4 ms). Under that load single decisions took up to 41 ms, longer
//! than a batch: the DMD then idles. The `P / 128` term caps the number of batches of large
//! budgets.
//!
//! # Determinism
//!
//! Everything is sequential IEEE binary64 arithmetic in a fixed order (`proto/PATTERNS.md`,
//! "The planner", states it operation by operation), with no hashing and no dependence on the
//! thread count, so [`replay`] of a stored session gives back its index sequence.

mod basis;
mod estimate;
#[cfg(test)]
mod tests;

use std::time::{Duration, Instant};

use helmholtz_proto::{ErrorEstimate, PatternSpec};

pub use basis::{Basis, Predictor};

/// Batches issued but not yet observed, at most.
pub const LOOKAHEAD: usize = 2;

/// Largest `k * channels` a planner holds values for (a camera session of 2^26 coefficient
/// values, 512 MiB of f64).
pub const MAX_VALUES: usize = 1 << 26;

/// One batch to show: index `first_pair + j` of the sequence shows basis function
/// `indices[j]`: as a split pair (frames `2 (first_pair + j)` and `2 (first_pair + j) + 1`), or
/// with single frames (PATTERNS.md, "Single frames") as one frame but for index 0's two.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Batch {
    /// 0 for the first batch of the session.
    pub number: u64,
    /// The sequence position of the batch's first index.
    pub first_pair: u64,
    /// The batch's first frame, and how many frames it shows.
    pub first_row: u64,
    pub rows: u64,
    pub indices: Vec<u32>,
}

/// Why a planner issues nothing more.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopReason {
    /// The frame budget (`count`) is used up, or every basis function was shown.
    Budget,
    /// The estimated relative error fell below `target_error`.
    TargetError,
}

#[derive(Debug, thiserror::Error)]
pub enum AdaptiveError {
    #[error(
        "the {0} family is not adaptive: only adaptive_haar and adaptive_hadamard have a planner"
    )]
    NotAdaptive(&'static str),
    #[error("an adaptive session needs at least one channel")]
    NoChannels,
    #[error(
        "{pixels} pattern pixels x {channels} channels = {values} coefficient values, over the \
         planner's limit of {limit}"
    )]
    TooLarge {
        pixels: usize,
        channels: usize,
        values: usize,
        limit: usize,
    },
    #[error("no batch is outstanding: values arrived before a batch was issued for them")]
    NothingOutstanding,
    #[error(
        "batch {batch} shows {pairs} basis functions in {rows} frames: expected {rows} frames x \
         {channels} channels = {expected} values, got {got}"
    )]
    WrongLength {
        batch: u64,
        pairs: usize,
        rows: u64,
        channels: usize,
        expected: usize,
        got: usize,
    },
    #[error("frame {frame} channel {channel} of batch {batch} is {value}: values must be finite")]
    NonFinite {
        batch: u64,
        frame: u64,
        channel: usize,
        value: f64,
    },
}

/// Automatic batch size in split pairs for `k` pattern pixels, `channels` channels and a budget
/// of `pairs` pairs: `max(16, ceil(k channels / 1024), ceil(pairs / 128))` (see the module docs).
pub fn auto_batch_pairs(k: u64, channels: u64, pairs: u64) -> u64 {
    16u64
        .max((k * channels).div_ceil(1024))
        .max(pairs.div_ceil(128))
}

/// Pairs per batch of an adaptive spec with `channels` channels: the declared `batch`, or
/// [`auto_batch_pairs`] when it is 0. `None` for other families.
pub fn batch_pairs(spec: &PatternSpec, channels: usize) -> Option<u64> {
    let (batch, _) = spec.family().adaptive_params()?;
    Some(if batch > 0 {
        batch as u64
    } else {
        auto_batch_pairs(
            spec.pixels() as u64,
            channels as u64,
            spec.adaptive_budget().expect("adaptive"),
        )
    })
}

/// Time spent deciding (predictions in [`Planner::observe`], selection in [`Planner::poll`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DecisionStats {
    /// Batches decided.
    pub batches: u64,
    pub total: Duration,
    /// The longest single decision (one observe's prediction plus the poll that follows it).
    pub max: Duration,
}

/// The adaptive planner of one session (see the module docs).
#[derive(Debug)]
pub struct Planner {
    basis: Basis,
    width: u32,
    channels: usize,
    /// Budget in split pairs (`min(count / 2, k)`).
    budget: u64,
    batch: u64,
    target_error: f64,
    /// The spec's `persistence`: weight of a measured parent detail in its children's scores.
    persistence: f64,
    /// Per index: its level and its parent (`u32::MAX` for none).
    level: Vec<u8>,
    parent: Vec<u32>,
    issued: Vec<bool>,
    order: Vec<u32>,
    /// Batches issued and not yet observed, oldest first: (number, first pair, pairs).
    outstanding: std::collections::VecDeque<(u64, u64, usize)>,
    batches: u64,
    observed: u64,
    /// Observed orthonormal coefficients, channel-major: `values[c k + n]` (0 where unobserved).
    values: Vec<f64>,
    /// Per channel: sum of squared observed coefficients, in observation order.
    energy: Vec<f64>,
    score: Vec<f64>,
    pred: Vec<f64>,
    predictor: Predictor,
    estimate: Option<f64>,
    stopped: Option<StopReason>,
    stats: DecisionStats,
    /// Prediction time of the last observe, added to the next poll's decision.
    pending: Duration,
    /// The state of the `measured` error estimate (`None`: the spec's estimate is `prediction`).
    measured: Option<estimate::Measured>,
    /// Single frames (PATTERNS.md, "Single frames"): the blocks and their light.
    single: Option<SingleFrames>,
}

/// A Haar block `(s, pr, pc)`: the `2^s x 2^s` square at row `pr`, column `pc` of its band.
type Block = (u32, u32, u32);

/// The state single frames add to a Haar planner: which blocks may be split, the block being
/// issued, and per channel the decoding of each frame's `y-` from its block's light
/// ([`SingleFrames::decode`]).
#[derive(Debug)]
struct SingleFrames {
    width: u32,
    /// Blocks not yet split whose parent is.
    open: Vec<Block>,
    /// The block being issued and how many of its details are.
    current: Option<([u32; 3], usize)>,
    decoder: SingleFrameDecoder,
}

/// Turns the frames of a single-frame session into the split pairs they stand for: per channel
/// the dark level, every block's pair sum `Q` (by the index of its `x` detail) and every
/// decoded detail's `y+ - y-` (PATTERNS.md, "Single frames", "Values").
#[derive(Clone, Debug)]
pub struct SingleFrameDecoder {
    width: u32,
    channels: usize,
    dark: Vec<f64>,
    /// `q[ch k + x]`: the pair sum of the block whose x detail is `x`.
    q: Vec<f64>,
    /// `d[ch k + n]`: `y+ - y-` of detail `n`.
    d: Vec<f64>,
}

/// The three details of block `(s, pr, pc)` on a `w x w` grid: `x`, `y`, `xy`.
fn block_details(w: u32, (s, pr, pc): Block) -> [u32; 3] {
    let h = w >> s;
    [pr * w + h + pc, (h + pr) * w + pc, (h + pr) * w + h + pc]
}

/// The block of Haar detail `n != 0` and which of its details `n` is (0 `x`, 1 `y`, 2 `xy`).
fn block_of(w: u32, n: u32) -> (Block, usize) {
    let f = helmholtz_proto::HaarFunction::new(w, n);
    let block = (f.scale, f.y0 >> f.scale, f.x0 >> f.scale);
    let which = match (f.split_x, f.split_y) {
        (true, false) => 0,
        (false, true) => 1,
        _ => 2,
    };
    (block, which)
}

impl SingleFrameDecoder {
    pub fn new(width: u32, channels: usize) -> SingleFrameDecoder {
        let k = width as usize * width as usize;
        SingleFrameDecoder {
            width,
            channels,
            dark: vec![0.0; channels],
            q: vec![0.0; channels * k],
            d: vec![0.0; channels * k],
        }
    }

    /// Frames each index takes: 2 for index 0 (all on, all off), 1 for the others.
    pub fn frames_of(n: u32) -> usize {
        if n == 0 { 2 } else { 1 }
    }

    /// Index `n`'s frames (`frames_of(n)` frames x channels, row-major) as the split pair they
    /// stand for, per channel `(y+, y-)`. The sequence's order must be kept: index 0 first, and
    /// a detail after every detail of the coarser blocks containing it.
    pub fn decode(&mut self, n: u32, frames: &[f64], out: &mut Vec<(f64, f64)>) {
        let (w, c) = (self.width, self.channels);
        let k = w as usize * w as usize;
        out.clear();
        if n == 0 {
            for ch in 0..c {
                let (yp, ym) = (frames[ch], frames[c + ch]);
                self.dark[ch] = ym;
                if k > 1 {
                    self.q[ch * k + 1] = yp + ym;
                }
                out.push((yp, ym));
            }
            return;
        }
        let (block, which) = block_of(w, n);
        let [x, y, xy] = block_details(w, block);
        for (ch, &yp) in frames[..c].iter().enumerate() {
            let ym = self.q[ch * k + x as usize] - yp;
            self.d[ch * k + n as usize] = yp - ym;
            out.push((yp, ym));
        }
        let (s, pr, pc) = block;
        if which == 2 && s >= 2 {
            let children = [(0u32, 0u32), (0, 1), (1, 0), (1, 1)];
            for ch in 0..c {
                let base = ch * k;
                let two_dark = 2.0 * self.dark[ch];
                let l = self.q[base + x as usize] - two_dark;
                let (dx, dy, dxy) = (
                    self.d[base + x as usize],
                    self.d[base + y as usize],
                    self.d[base + xy as usize],
                );
                let sums = [
                    (((l + dx) + dy) + dxy) * 0.25 + two_dark,
                    (((l - dx) + dy) - dxy) * 0.25 + two_dark,
                    (((l + dx) - dy) - dxy) * 0.25 + two_dark,
                    (((l - dx) - dy) + dxy) * 0.25 + two_dark,
                ];
                for ((dr, dc), q) in children.iter().zip(sums) {
                    let [cx, _, _] = block_details(w, (s - 1, 2 * pr + dr, 2 * pc + dc));
                    self.q[base + cx as usize] = q;
                }
            }
        }
    }

    pub fn memory_bytes(&self) -> usize {
        8 * (self.dark.len() + self.q.len() + self.d.len())
    }
}

/// The variance of each decoded single frame's `y+ - y-` per unit read-noise variance of a
/// frame, for the indices of a single-frame session in their order (a split pair's: 2). Index
/// 0 is all on less all off (2). A detail of block `B` is `2 y+ - S_B`: `4 + var(S_B)`, its
/// frame independent of what came before. The block sums follow the decoder
/// ([`SingleFrameDecoder::decode`]): the grid's `S = y_on + y_off` (variance 2, covariance 1
/// with the dark frame `y_off`); a child's `S_c = a S_B + (s_x y_x + s_y y_y + s_xy y_xy) / 2 +
/// 3/2 y_off` with `a = (1 - s_x - s_y - s_xy) / 4` (`-1/2` for the top-left child, `1/2` for
/// the others), so `var(S_c) = a^2 var(S_B) + 3/4 + 9/4 + 3 a cov(S_B, y_off)` and
/// `cov(S_c, y_off) = a cov(S_B, y_off) + 3/2`. Deep blocks reach about 10 (measured:
/// `a_decoded_single_frame_carries_the_read_noise_these_variances_say`): the light of a block
/// is decoded, not measured, so its noise adds to every detail below it.
pub fn single_frame_pair_variances(width: u32, indices: &[u32]) -> Vec<f64> {
    let k = width as usize * width as usize;
    // (var, cov with the dark frame) of the block sum, keyed by the block's x detail.
    let mut sums = vec![(0.0f64, 0.0f64); k.max(2)];
    let mut out = Vec::with_capacity(indices.len());
    for &n in indices {
        if n == 0 {
            if k > 1 {
                sums[1] = (2.0, 1.0);
            }
            out.push(2.0);
            continue;
        }
        let (block, which) = block_of(width, n);
        let [x, _, _] = block_details(width, block);
        let (v, c) = sums[x as usize];
        out.push(4.0 + v);
        let (s, pr, pc) = block;
        if which == 2 && s >= 2 {
            for (i, (dr, dc)) in [(0u32, 0u32), (0, 1), (1, 0), (1, 1)]
                .into_iter()
                .enumerate()
            {
                let a = if i == 0 { -0.5 } else { 0.5 };
                let [cx, _, _] = block_details(width, (s - 1, 2 * pr + dr, 2 * pc + dc));
                sums[cx as usize] = (a * a * v + 3.0 + 3.0 * a * c, a * c + 1.5);
            }
        }
    }
    out
}

/// A resolved single-frame session's first `rows` frames (`channels` per frame) as the split
/// pairs they stand for: `2` frames an index, `y+` then `y-`, for every index whose frames are
/// all in `rows` (PATTERNS.md, "Single frames"). Every method reconstructs a single-frame session
/// from these, with [`pair_spec`].
pub fn single_frames_as_pairs(spec: &PatternSpec, channels: usize, frames: &[f64]) -> Vec<f64> {
    let indices = spec.adaptive_indices().unwrap_or(&[]);
    let rows = (frames.len() / channels.max(1)) as u64;
    let whole = (spec.adaptive_indices_in(rows).unwrap_or(0) as usize).min(indices.len());
    let mut decoder = SingleFrameDecoder::new(spec.width(), channels);
    let mut out = Vec::with_capacity(2 * whole * channels);
    let mut pair = Vec::with_capacity(channels);
    let mut at = 0usize;
    for &n in &indices[..whole] {
        let take = SingleFrameDecoder::frames_of(n) * channels;
        decoder.decode(n, &frames[at..at + take], &mut pair);
        at += take;
        out.extend(pair.iter().map(|p| p.0));
        out.extend(pair.iter().map(|p| p.1));
    }
    out
}

/// The split-pair spec a resolved single-frame spec stands for: the same declaration with
/// `frames: pairs` and a budget of `2 (count - 1)` frames, resolved with the same indices (what
/// [`single_frames_as_pairs`] returns the frames of). Other specs are returned as they are.
pub fn pair_spec(spec: &PatternSpec) -> PatternSpec {
    if !spec.adaptive_single() {
        return spec.clone();
    }
    let budget = spec.adaptive_budget().expect("adaptive");
    let pairs = PatternSpec::new(
        spec.family()
            .clone()
            .with_frames(helmholtz_proto::AdaptiveFrames::Pairs),
        spec.width(),
        spec.height(),
        2 * budget,
        spec.seed(),
    )
    .expect("a single-frame budget of count - 1 indices is a valid pair budget");
    match spec.adaptive_indices() {
        Some(indices) => pairs
            .with_indices(indices.into())
            .expect("the same indices fit the same budget"),
        None => pairs,
    }
}

impl Planner {
    /// `channels`: bucket channels, or camera pixels (width*height) for a camera session. The
    /// spec's indices, if it is resolved, are ignored: the planner decides them.
    pub fn new(spec: &PatternSpec, channels: usize) -> Result<Planner, AdaptiveError> {
        let basis = Basis::of(spec).ok_or(AdaptiveError::NotAdaptive(spec.family().name()))?;
        if channels == 0 {
            return Err(AdaptiveError::NoChannels);
        }
        let k = spec.pixels();
        let values = k.saturating_mul(channels);
        if values > MAX_VALUES {
            return Err(AdaptiveError::TooLarge {
                pixels: k,
                channels,
                values,
                limit: MAX_VALUES,
            });
        }
        let (_, target_error) = spec.family().adaptive_params().expect("adaptive");
        let width = spec.width();
        let level = (0..k as u32).map(|n| basis.level(width, n) as u8).collect();
        let parent = (0..k as u32)
            .map(|n| basis.parent(width, n).unwrap_or(u32::MAX))
            .collect();
        Ok(Planner {
            basis,
            width,
            channels,
            budget: spec.adaptive_budget().expect("adaptive").min(k as u64),
            batch: batch_pairs(spec, channels).expect("adaptive"),
            target_error,
            persistence: spec.family().adaptive_persistence().expect("adaptive"),
            level,
            parent,
            issued: vec![false; k],
            order: Vec::new(),
            outstanding: Default::default(),
            batches: 0,
            observed: 0,
            values: vec![0.0; values],
            energy: vec![0.0; channels],
            score: vec![0.0; k],
            pred: vec![0.0; k],
            predictor: Predictor::new(basis, width),
            estimate: None,
            stopped: None,
            stats: DecisionStats::default(),
            pending: Duration::ZERO,
            measured: match spec.family().adaptive_error_estimate() {
                Some(ErrorEstimate::Measured) => {
                    Some(estimate::Measured::new(basis, width, channels))
                }
                _ => None,
            },
            single: spec.adaptive_single().then(|| SingleFrames {
                width,
                open: if width > 1 {
                    vec![(width.trailing_zeros(), 0, 0)]
                } else {
                    Vec::new()
                },
                current: None,
                decoder: SingleFrameDecoder::new(width, channels),
            }),
        })
    }

    /// True when the session shows single frames (PATTERNS.md, "Single frames").
    pub fn single_frames(&self) -> bool {
        self.single.is_some()
    }

    /// Frames the first `indices` indices of the sequence take.
    fn rows_of(&self, indices: u64) -> u64 {
        match (&self.single, indices) {
            (None, j) => 2 * j,
            (Some(_), 0) => 0,
            (Some(_), j) => j + 1,
        }
    }

    /// Frames of every batch issued so far.
    pub fn issued_rows(&self) -> u64 {
        self.rows_of(self.order.len() as u64)
    }

    pub fn basis(&self) -> Basis {
        self.basis
    }

    /// Pairs per full batch.
    pub fn batch_pairs(&self) -> u64 {
        self.batch
    }

    /// The next batch if one may be issued now (fewer than [`LOOKAHEAD`] outstanding, budget
    /// left, stop rule not met), else `None`. A deterministic function of the spec and the values
    /// observed so far.
    pub fn poll(&mut self) -> Option<Batch> {
        if self.outstanding.len() >= LOOKAHEAD || self.stopped.is_some() {
            return None;
        }
        let issued = self.order.len() as u64;
        if issued >= self.budget {
            return None;
        }
        if self.target_error > 0.0 && self.estimate.is_some_and(|e| e < self.target_error) {
            self.stopped = Some(StopReason::TargetError);
            return None;
        }
        let start = Instant::now();
        let size = self.batch.min(self.budget - issued) as usize;
        let indices = if self.single.is_some() {
            self.select_blocks(size)
        } else {
            self.select(size)
        };
        if indices.is_empty() {
            return None;
        }
        for &n in &indices {
            self.issued[n as usize] = true;
        }
        self.order.extend_from_slice(&indices);
        let first_row = self.rows_of(issued);
        let batch = Batch {
            number: self.batches,
            first_pair: issued,
            first_row,
            rows: self.rows_of(issued + indices.len() as u64) - first_row,
            indices,
        };
        self.outstanding
            .push_back((batch.number, issued, batch.indices.len()));
        self.batches += 1;
        let took = start.elapsed() + std::mem::take(&mut self.pending);
        self.stats.batches += 1;
        self.stats.total += took;
        self.stats.max = self.stats.max.max(took);
        Some(batch)
    }

    /// Single frames: up to `size` indices by whole block splits (PATTERNS.md, "Single frames",
    /// "Selection"): index 0 first, then the current block's next detail, else the open block
    /// with the largest summed score becomes the current one (its children open).
    fn select_blocks(&mut self, size: usize) -> Vec<u32> {
        let single = self.single.as_mut().expect("single frames");
        let w = single.width;
        let mut out = Vec::with_capacity(size);
        while out.len() < size {
            if self.order.is_empty() && out.is_empty() {
                out.push(0);
                continue;
            }
            if let Some((details, next)) = &mut single.current
                && *next < 3
            {
                out.push(details[*next]);
                *next += 1;
                continue;
            }
            let score = &self.score;
            let block_score = |b: Block| {
                let [x, y, xy] = block_details(w, b);
                (score[x as usize] + score[y as usize]) + score[xy as usize]
            };
            let Some((at, _)) = single.open.iter().enumerate().max_by(|p, q| {
                let (a, b) = (*p.1, *q.1);
                block_score(a)
                    .total_cmp(&block_score(b))
                    .then(a.0.cmp(&b.0))
                    .then(block_details(w, b)[0].cmp(&block_details(w, a)[0]))
            }) else {
                break;
            };
            let block = single.open.swap_remove(at);
            let (s, pr, pc) = block;
            if s >= 2 {
                for (dr, dc) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    single.open.push((s - 1, 2 * pr + dr, 2 * pc + dc));
                }
            }
            let details = block_details(w, block);
            out.push(details[0]);
            single.current = Some((details, 1));
        }
        out
    }

    /// The `size` best indices not yet issued, in rank order.
    fn select(&self, size: usize) -> Vec<u32> {
        let key = |&a: &u32, &b: &u32| {
            let eligible = |n: u32| {
                let p = self.parent[n as usize];
                p == u32::MAX || self.issued[p as usize]
            };
            eligible(b)
                .cmp(&eligible(a))
                .then_with(|| self.score[b as usize].total_cmp(&self.score[a as usize]))
                .then_with(|| self.level[b as usize].cmp(&self.level[a as usize]))
                .then_with(|| a.cmp(&b))
        };
        let mut candidates: Vec<u32> = (0..self.issued.len() as u32)
            .filter(|&n| !self.issued[n as usize])
            .collect();
        if candidates.len() > size {
            candidates.select_nth_unstable_by(size - 1, key);
            candidates.truncate(size);
        }
        candidates.sort_unstable_by(key);
        candidates
    }

    /// Values of the oldest outstanding batch, whole: its frames ([`Batch::rows`]: `2 *
    /// indices.len()`, or with single frames one an index but two for index 0) x channels,
    /// row-major (frame 0 channel 0, frame 0 channel 1, ...). Nothing is kept if they are refused.
    pub fn observe(&mut self, frames: &[f64]) -> Result<(), AdaptiveError> {
        let &(number, first_pair, pairs) = self
            .outstanding
            .front()
            .ok_or(AdaptiveError::NothingOutstanding)?;
        let c = self.channels;
        let first_row = self.rows_of(first_pair);
        let rows = self.rows_of(first_pair + pairs as u64) - first_row;
        let expected = rows as usize * c;
        if frames.len() != expected {
            return Err(AdaptiveError::WrongLength {
                batch: number,
                pairs,
                rows,
                channels: c,
                expected,
                got: frames.len(),
            });
        }
        if let Some(p) = frames.iter().position(|v| !v.is_finite()) {
            return Err(AdaptiveError::NonFinite {
                batch: number,
                frame: first_row + (p / c) as u64,
                channel: p % c,
                value: frames[p],
            });
        }
        let start = Instant::now();
        self.outstanding.pop_front();
        let k = self.issued.len();
        let mut pair: Vec<(f64, f64)> = Vec::with_capacity(c);
        let mut at = 0usize;
        for j in 0..pairs {
            let n = self.order[first_pair as usize + j];
            match &mut self.single {
                Some(single) => {
                    let take = SingleFrameDecoder::frames_of(n) * c;
                    single.decoder.decode(n, &frames[at..at + take], &mut pair);
                    at += take;
                }
                None => {
                    pair.clear();
                    pair.extend((0..c).map(|ch| (frames[at + ch], frames[at + c + ch])));
                    at += 2 * c;
                }
            }
            let gain = self.basis.gain(self.width, n);
            for (ch, &(yp, ym)) in pair.iter().enumerate() {
                let v = (yp - ym) / gain;
                self.values[ch * k + n as usize] = v;
                self.energy[ch] += v * v;
            }
            if let Some(measured) = &mut self.measured {
                measured.observe(n, |ch| pair[ch].0 + pair[ch].1);
            }
        }
        self.observed += pairs as u64;
        self.update_predictions();
        self.pending = start.elapsed();
        Ok(())
    }

    /// Scores and the estimated error from the values observed so far.
    fn update_predictions(&mut self) {
        let k = self.issued.len();
        self.score.iter_mut().for_each(|s| *s = 0.0);
        let (mut ratio_sum, mut lit) = (0.0, 0usize);
        for ch in 0..self.channels {
            let energy = self.energy[ch];
            if energy == 0.0 {
                continue;
            }
            let norm = energy.sqrt();
            self.predictor
                .predict(&self.values[ch * k..(ch + 1) * k], &mut self.pred);
            let values = &self.values[ch * k..(ch + 1) * k];
            let mut unissued = 0.0;
            for n in 0..k {
                let p = self.pred[n];
                let mut size = p.abs();
                let parent = self.parent[n];
                if self.persistence > 0.0 && parent != u32::MAX && parent != 0 {
                    let inherited = self.persistence * values[parent as usize].abs();
                    if inherited > size {
                        size = inherited;
                    }
                }
                self.score[n] += size / norm;
                if !self.issued[n] {
                    unissued += p * p;
                }
            }
            ratio_sum += match &self.measured {
                None => unissued / energy,
                Some(m) => {
                    m.relative_squared(ch, values, &self.pred, &self.issued, &self.level, energy)
                }
            };
            lit += 1;
        }
        self.estimate = (lit > 0).then(|| (ratio_sum / lit as f64).sqrt());
    }

    /// Split pairs issued so far.
    pub fn issued_pairs(&self) -> u64 {
        self.order.len() as u64
    }

    /// Split pairs whose values were observed.
    pub fn observed_pairs(&self) -> u64 {
        self.observed
    }

    /// `Some` once no further batch will ever be issued and none is outstanding.
    pub fn finished(&self) -> Option<StopReason> {
        if !self.outstanding.is_empty() {
            return None;
        }
        if self.stopped.is_some() {
            return self.stopped;
        }
        if self.issued_pairs() >= self.budget {
            return Some(StopReason::Budget);
        }
        if self.target_error > 0.0 && self.estimate.is_some_and(|e| e < self.target_error) {
            return Some(StopReason::TargetError);
        }
        None
    }

    /// Every index issued so far, in order.
    pub fn indices(&self) -> &[u32] {
        &self.order
    }

    /// The planner's estimate of the relative L2 error of the image once every issued pair is
    /// observed (see the module docs); `None` before any value arrived or while every channel is
    /// dark.
    pub fn estimated_error(&self) -> Option<f64> {
        self.estimate
    }

    /// Observed orthonormal coefficients of channel `channel`, indexed by basis index (0 where
    /// not observed).
    pub fn coefficients(&self, channel: usize) -> &[f64] {
        let k = self.issued.len();
        &self.values[channel * k..(channel + 1) * k]
    }

    /// Channel `channel`'s image with every unobserved coefficient set to its prediction from
    /// the observed ones (the bicubic guess of the module docs) instead of 0: the zero-filled
    /// inverse made smooth where nothing was measured. Row-major `W x W`.
    pub fn predicted_image(&mut self, channel: usize) -> Vec<f64> {
        let k = self.issued.len();
        let values = &self.values[channel * k..(channel + 1) * k];
        let mut pred = vec![0.0; k];
        self.predictor.predict(values, &mut pred);
        let mut observed = vec![false; k];
        let observed_pairs = self.observed as usize;
        for &n in &self.order[..observed_pairs] {
            observed[n as usize] = true;
        }
        let mut c: Vec<f64> = (0..k)
            .map(|n| if observed[n] { values[n] } else { pred[n] })
            .collect();
        let w = self.width as usize;
        match self.basis {
            Basis::Haar => {
                use crate::linop::LinearOperator;
                let mut x = vec![0.0; k];
                crate::transforms::wavelet::Wavelet2d::haar(w, w).adjoint(&c, &mut x);
                x
            }
            Basis::Hadamard => {
                crate::fwht::fwht(&mut c);
                c.iter().map(|v| v / w as f64).collect()
            }
        }
    }

    pub fn decision_stats(&self) -> DecisionStats {
        self.stats
    }

    /// Bytes the planner holds: O(k (channels + 6)), independent of the session's length.
    pub fn memory_bytes(&self) -> usize {
        let k = self.issued.len();
        8 * (self.values.len() + self.energy.len() + self.score.len() + self.pred.len())
            + k * (1 + 4 + 1)
            + 4 * self.order.capacity()
            + self.predictor.memory_bytes()
            + self.measured.as_ref().map_or(0, |m| m.memory_bytes())
            + self
                .single
                .as_ref()
                .map_or(0, |s| s.decoder.memory_bytes() + 12 * s.open.capacity())
    }

    /// The noise of one pair difference `y+ - y-` of channel `channel` (a standard deviation in
    /// frame units) that the pair sums of equal supports show, with its degrees of freedom:
    /// `None` for the `prediction` estimate or before any support was shown twice.
    pub fn pair_noise(&self, channel: usize) -> Option<(f64, u64)> {
        self.measured
            .as_ref()?
            .pooled_pair_variance(channel)
            .map(|(v, dof)| (v.sqrt(), dof))
    }
}

/// Replays a stored session: poll/observe alternately over `frames` (whole batches only; a
/// trailing partial batch is ignored), returning the planner and the index sequence it issued
/// (including the batches issued but not observed).
pub fn replay(
    spec: &PatternSpec,
    channels: usize,
    frames: &[f64],
) -> Result<(Planner, Vec<u32>), AdaptiveError> {
    let mut planner = Planner::new(spec, channels)?;
    let mut queue = std::collections::VecDeque::new();
    let mut at = 0usize;
    loop {
        while let Some(batch) = planner.poll() {
            queue.push_back(batch);
        }
        let Some(batch) = queue.pop_front() else {
            break;
        };
        let need = batch.rows as usize * channels;
        if frames.len() - at < need {
            break;
        }
        planner.observe(&frames[at..at + need])?;
        at += need;
    }
    let indices = planner.indices().to_vec();
    Ok((planner, indices))
}

/// The orthonormal coefficient data of a resolved adaptive spec's first `pairs` pairs:
/// `(y+ - y-) / g_n` per pair and channel, pair-major (pair 0 channel 0, pair 0 channel 1, ...).
/// `frames` holds at least `2 pairs` frames x `channels`.
pub fn pair_coefficients(
    spec: &PatternSpec,
    indices: &[u32],
    channels: usize,
    frames: &[f64],
) -> Vec<f64> {
    let basis = Basis::of(spec).expect("adaptive spec");
    let c = channels;
    let mut out = Vec::with_capacity(indices.len() * c);
    for (j, &n) in indices.iter().enumerate() {
        let gain = basis.gain(spec.width(), n);
        for ch in 0..c {
            out.push((frames[2 * j * c + ch] - frames[(2 * j + 1) * c + ch]) / gain);
        }
    }
    out
}
