//! Streaming correlators: GI, DGI (Ferri 2010), NGI (Sun 2012).
//!
//! One pass over the rows in source order. Patterns are regenerated from the spec (they are never
//! stored); the state is a fixed number of length-k accumulators per channel, whatever n.
//!
//! # Formulas
//!
//! `<.>` is the mean over the n rows used, `R_i` the sum of pattern i's pixel values.
//! - GI: `G(x) = <c p(x)> - <c><p(x)>`. Invariant under `c -> c - c0`; we accumulate the bucket
//!   shifted by the first row's value (per channel), which removes the large common part of
//!   `<c p(x)>` and `<c><p(x)>` before they are subtracted.
//! - DGI: `G_D(x) = <c p(x)> - (<c>/<R>) <R p(x)>`.
//! - NGI: `G_N(x) = <(c_i/R_i - <c>/<R>) p_i(x)> = <(c/R) p(x)> - (<c>/<R>) <p(x)>`.
//!   A row with `R_i = 0` is an all-off pattern (`p_i(x) = 0` for every x, patterns being
//!   non-negative): it has no `c_i/R_i` weight term (its term is 0 rather than 0/0), but it still
//!   counts in n, `<c>` and `<R>`.
//!
//! DGI and NGI are both invariant under `c -> c - a R` (any constant a); we accumulate with
//! `a = c_r / R_r` of the first row r with `R_r > 0`, for the same reason as the GI shift. (Rows
//! before r have `R = 0`, so their shifted value does not depend on a; a can be fixed late.)
//!
//! Expectations for Bernoulli(q) patterns (iid pixels): `E[G] = q(1-q) t`,
//! `E[G_D] = q(1-q) (t - mean(t))`, and to first order in 1/k `E[G_N] ~ (1-q)/k (t - mean(t))`.
//! Speckle levels are uniform on [0, 1), so `E[G] = t / 12`.
//!
//! With the pattern sum `R_i` computed from the known pattern (no reference detector), a
//! multiplicative source drift `g_i` enters GI and DGI identically to first order; DGI's gain over
//! GI is the removal of the `mean(t) * R_i` background term from the noise (Ferri 2010).
//!
//! # Kernel
//!
//! Every accumulator is `acc[x] += sum_i w_i p_i(x)` for some per-row weight `w_i`. Binary
//! families take 64 patterns at a time as packed bits. For each word of 64 pixels, 8 x 8 bit
//! transposes gather, for every pixel and every group g of 8 patterns, the byte of those 8
//! patterns' bits at that pixel; each byte indexes a table of the 256 subset sums of the 8
//! patterns' weights, so a pixel takes eight look-ups per 64 patterns. Table entries hold two
//! columns' sums (16 bytes), so one look-up serves two accumulators. Grey levels (speckle) use
//! plain multiply-adds over tiles of pixels, 8 patterns at a time. Rows are spread over worker
//! threads (rayon), each with its own accumulators, summed at the end.
//!
//! Measured (dev profile, 2-vCPU Xeon VM at 2.1 GHz shared with other builds, so noisy):
//! Bernoulli 128 x 128 and 256 x 256, one channel, GI or DGI, pattern generation included:
//! 5e9-9.5e9 pattern-pixel updates/s on one thread, 0.9e10-1.4e10 on two (`bench_throughput`).
//! About a third of the time is `PatternGenerator::fill_bits`.

use helmholtz_proto::{Family, PatternGenerator};
use rayon::prelude::*;
use serde_json::{Map, Value, json};

use super::stream::RowStream;
use super::{
    BucketSource, Control, DualImage, MethodConfig, Problem, ReconError, Reconstruction, Report,
};

/// Patterns per bit batch (one 64 x 64 bit tile per word of pixels).
const BATCH: usize = 64;
/// Patterns per grey-level batch.
const GREY_BATCH: usize = 8;
/// Pixels per tile in the grey-level kernel.
const GREY_TILE: usize = 512;
/// Pattern-pixel products (times columns) one worker handles per dispatch (~5-50 ms): bounds
/// the time to notice cancellation and the rows held in memory.
const DISPATCH_WORK: usize = 1 << 26;
/// Upper bound on the accumulator and scratch memory of all workers together.
const MEMORY_BUDGET: usize = 1 << 30;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Gi,
    Dgi,
    Ngi,
}

/// Overrides for tests (number of workers, rows per dispatch).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Tuning {
    pub workers: Option<usize>,
    pub dispatch_rows: Option<usize>,
}

/// Runs GI, DGI or NGI (see the module docs) over `problem.rows` rows of `source`.
///
/// Errors: [`ReconError::BadRows`] for a block that is not whole rows, out of order or past
/// `problem.rows`; [`ReconError::Unsolvable`] when fewer rows arrive (or `config` is not a
/// correlator); [`ReconError::Cancelled`] soon after `control.cancel()`.
pub fn run(
    problem: &Problem,
    config: &MethodConfig,
    source: &mut dyn BucketSource,
    control: &Control,
) -> Result<Reconstruction, ReconError> {
    run_tuned(problem, config, source, control, Tuning::default())
}

pub(crate) fn run_tuned(
    problem: &Problem,
    config: &MethodConfig,
    source: &mut dyn BucketSource,
    control: &Control,
    tuning: Tuning,
) -> Result<Reconstruction, ReconError> {
    let kind = match config {
        MethodConfig::Gi => Kind::Gi,
        MethodConfig::Dgi => Kind::Dgi,
        MethodConfig::Ngi => Kind::Ngi,
        other => {
            return Err(ReconError::Unsolvable(format!("{} is not a correlation method", other.name())));
        }
    };
    if problem.rows > problem.spec.count() {
        return Err(ReconError::Unsolvable(format!(
            "{} rows requested but the spec declares {}",
            problem.rows,
            problem.spec.count()
        )));
    }
    let mut stream = RowStream::new(source, control, problem.channels, problem.rows)?;
    let plan = Plan::new(problem, kind, tuning);
    let m = plan.m;
    let mut workers: Vec<Worker> = (0..plan.workers).map(|_| Worker::new(&plan)).collect();
    let mut shift = Shift { values: vec![0.0; m], fixed: false };

    let mut pending: Vec<f64> = Vec::new();
    let mut pending_first = 0u64;
    while let Some(block) = stream.next_block()? {
        pending.extend_from_slice(&block.values);
        let mut start = 0;
        while (pending.len() - start) / m >= plan.dispatch_rows {
            let end = start + plan.dispatch_rows * m;
            dispatch(
                &plan,
                &mut workers,
                &mut shift,
                &pending[start..end],
                pending_first,
                control,
            )?;
            pending_first += plan.dispatch_rows as u64;
            start = end;
            control.set_progress(pending_first as f64 / stream.total() as f64);
        }
        pending.drain(..start);
    }
    if !pending.is_empty() {
        dispatch(&plan, &mut workers, &mut shift, &pending, pending_first, control)?;
        pending_first += (pending.len() / m) as u64;
    }
    debug_assert_eq!(pending_first, stream.rows_seen());
    let result = finish(&plan, config, workers);
    control.set_progress(1.0);
    Ok(result)
}

/// Everything fixed by the problem: pattern source, column layout, work split.
///
/// Columns: column 0 is the base, `sum_i b_i p_i(x)` with `b_i = 1` (GI, NGI) or `R_i` (DGI);
/// column 1 + ch is channel ch's `sum_i w_i p_i(x)`. Columns are stored in interleaved pairs
/// (`acc[(pair * padded + x) * 2 + lane]`, column = 2 pair + lane) so one 16-byte table entry
/// updates two columns at once.
struct Plan {
    generator: PatternGenerator,
    kind: Kind,
    family: Family,
    binary: bool,
    width: u32,
    height: u32,
    k: usize,
    /// 64-bit words per pattern.
    nw: usize,
    /// Words between consecutive patterns in the bit buffer (padded against cache aliasing).
    stride: usize,
    /// Accumulator length per column: nw * 64 (binary) or k (grey).
    padded: usize,
    m: usize,
    /// m + 1 columns, in ceil((m + 1) / 2) pairs.
    pairs: usize,
    workers: usize,
    dispatch_rows: usize,
    /// The CPU has a population-count instruction (x86-64 baseline does not).
    popcnt: bool,
}

impl Plan {
    fn new(problem: &Problem, kind: Kind, tuning: Tuning) -> Plan {
        let spec = problem.spec;
        let generator = PatternGenerator::new(spec);
        let family = spec.family().clone();
        let binary = family.is_binary();
        let k = spec.pixels();
        let nw = k.div_ceil(64);
        // Round to a cache line, and step off multiples of 4 KiB so the 64 words gathered for one
        // tile do not all fall into the same cache set.
        let mut stride = nw.div_ceil(8) * 8;
        if stride.is_multiple_of(512) {
            stride += 8;
        }
        let padded = if binary { nw * 64 } else { k };
        let m = problem.channels;
        let pairs = (m + 1).div_ceil(2);

        let per_worker =
            pairs * padded * 16 + if binary { BATCH * stride * 8 } else { GREY_BATCH * k * 4 };
        let threads = rayon::current_num_threads().max(1);
        let workers = tuning
            .workers
            .unwrap_or_else(|| threads.min((MEMORY_BUDGET / per_worker.max(1)).max(1)))
            .max(1);
        let granule = if binary { BATCH } else { GREY_BATCH };
        let per_worker_rows = (DISPATCH_WORK / (padded * (pairs + 1)).max(1)).clamp(1, 1 << 14);
        let dispatch_rows = tuning
            .dispatch_rows
            .unwrap_or(workers * per_worker_rows.div_ceil(granule) * granule)
            .max(1);
        Plan {
            generator,
            kind,
            family,
            binary,
            width: spec.width(),
            height: spec.height(),
            k,
            nw,
            stride,
            padded,
            m,
            pairs,
            workers,
            dispatch_rows,
            popcnt: has_popcnt(),
        }
    }

    /// Pattern sum `R` of row `row`, generated on its own (used once to fix the shift).
    fn pattern_sum(&self, row: u64) -> f64 {
        if self.binary {
            let mut words = vec![0u64; self.nw];
            self.generator.fill_bits(row, &mut words).expect("binary family");
            count_ones(&words, self.popcnt) as f64
        } else {
            let mut values = vec![0f32; self.k];
            self.generator.fill_values(row, &mut values);
            sum_values(&values)
        }
    }
}

/// The per-channel constant subtracted from the buckets: `c0` (GI) or `a` in `c - a R` (DGI, NGI).
struct Shift {
    values: Vec<f64>,
    fixed: bool,
}

impl Shift {
    /// Fixes the shift from the first rows if not yet done (`rows`: row-major buckets of rows
    /// `first..`).
    fn fix(&mut self, plan: &Plan, rows: &[f64], first: u64) {
        if self.fixed {
            return;
        }
        let m = plan.m;
        match plan.kind {
            Kind::Gi => {
                self.values.copy_from_slice(&rows[..m]);
                self.fixed = true;
            }
            Kind::Dgi | Kind::Ngi => {
                for (r, c) in rows.chunks_exact(m).enumerate() {
                    let sum = plan.pattern_sum(first + r as u64);
                    if sum > 0.0 {
                        for (s, &v) in self.values.iter_mut().zip(c) {
                            *s = v / sum;
                        }
                        self.fixed = true;
                        return;
                    }
                }
            }
        }
    }

    /// The shifted bucket `c'` of one channel, for a row with pattern sum `r`.
    #[inline]
    fn apply(&self, kind: Kind, channel: usize, c: f64, r: f64) -> f64 {
        match kind {
            Kind::Gi => c - self.values[channel],
            Kind::Dgi | Kind::Ngi => c - self.values[channel] * r,
        }
    }
}

/// Runs `rows` (row-major, first row `first`) through the workers, split into contiguous parts.
fn dispatch(
    plan: &Plan,
    workers: &mut [Worker],
    shift: &mut Shift,
    rows: &[f64],
    first: u64,
    control: &Control,
) -> Result<(), ReconError> {
    shift.fix(plan, rows, first);
    let shift = &*shift;
    let m = plan.m;
    let n = rows.len() / m;
    let granule = if plan.binary { BATCH } else { GREY_BATCH };
    let per = n.div_ceil(workers.len()).div_ceil(granule) * granule;
    let parts = n.div_ceil(per);
    if parts <= 1 {
        workers[0].process(plan, shift, rows, first, control);
    } else {
        workers[..parts].par_iter_mut().enumerate().for_each(|(w, worker)| {
            let lo = w * per;
            let hi = (lo + per).min(n);
            worker.process(plan, shift, &rows[lo * m..hi * m], first + lo as u64, control);
        });
    }
    if control.is_cancelled() {
        return Err(ReconError::Cancelled);
    }
    Ok(())
}

/// One thread's accumulators and scratch.
struct Worker {
    /// `pairs` interleaved column pairs of length `padded` (see [`Plan`]).
    acc: Vec<[f64; 2]>,
    /// Bit batch: pattern j at `bits[j * stride..][..nw]`.
    bits: Vec<u64>,
    /// Grey batch: pattern j at `grey[j * k..][..k]`.
    grey: Vec<f32>,
    /// Per batch: `weights[c * BATCH + j]`, weight of pattern j in column c (0..2 pairs).
    weights: Vec<f64>,
    /// Per batch: 8 subset-sum tables per column pair.
    luts: Vec<[[f64; 2]; 256]>,
    rows: u64,
    sum_r: f64,
    /// Per channel: sum of shifted buckets, sum of raw buckets.
    sum_shifted: Vec<f64>,
    sum_raw: Vec<f64>,
}

impl Worker {
    fn new(plan: &Plan) -> Worker {
        Worker {
            acc: vec![[0.0; 2]; plan.pairs * plan.padded],
            bits: if plan.binary { vec![0; BATCH * plan.stride] } else { Vec::new() },
            grey: if plan.binary { Vec::new() } else { vec![0.0; GREY_BATCH * plan.k] },
            weights: vec![0.0; 2 * plan.pairs * BATCH],
            luts: if plan.binary { vec![[[0.0; 2]; 256]; plan.pairs * 8] } else { Vec::new() },
            rows: 0,
            sum_r: 0.0,
            sum_shifted: vec![0.0; plan.m],
            sum_raw: vec![0.0; plan.m],
        }
    }

    fn process(&mut self, plan: &Plan, shift: &Shift, rows: &[f64], first: u64, control: &Control) {
        let m = plan.m;
        let granule = if plan.binary { BATCH } else { GREY_BATCH };
        for (b, batch) in rows.chunks(granule * m).enumerate() {
            if control.is_cancelled() {
                return;
            }
            let first = first + (b * granule) as u64;
            if plan.binary {
                self.binary_batch(plan, shift, batch, first);
            } else {
                self.grey_batch(plan, shift, batch, first);
            }
        }
    }

    /// Weights of pattern j (bucket values `c`, pattern sum `r`) in every column; updates the
    /// scalar sums.
    fn set_weights(&mut self, plan: &Plan, shift: &Shift, j: usize, c: &[f64], r: f64) {
        self.rows += 1;
        self.sum_r += r;
        self.weights[j] = if plan.kind == Kind::Dgi { r } else { 1.0 };
        for (ch, &v) in c.iter().enumerate() {
            let s = shift.apply(plan.kind, ch, v, r);
            self.sum_shifted[ch] += s;
            self.sum_raw[ch] += v;
            let w = match plan.kind {
                Kind::Gi | Kind::Dgi => s,
                // R = 0: an all-off pattern, no weight term (its p(x) are all 0 anyway).
                Kind::Ngi => {
                    if r > 0.0 {
                        s / r
                    } else {
                        0.0
                    }
                }
            };
            self.weights[(1 + ch) * BATCH + j] = w;
        }
    }

    fn binary_batch(&mut self, plan: &Plan, shift: &Shift, batch: &[f64], first: u64) {
        let m = plan.m;
        let n = batch.len() / m;
        let (nw, stride) = (plan.nw, plan.stride);
        self.weights.fill(0.0);
        for j in 0..BATCH {
            let words = &mut self.bits[j * stride..j * stride + nw];
            if j < n {
                plan.generator.fill_bits(first + j as u64, words).expect("binary family");
                let r = count_ones(words, plan.popcnt) as f64;
                self.set_weights(plan, shift, j, &batch[j * m..(j + 1) * m], r);
            } else {
                words.fill(0);
            }
        }
        for p in 0..plan.pairs {
            let w0 = &self.weights[2 * p * BATCH..(2 * p + 1) * BATCH];
            let w1 = &self.weights[(2 * p + 1) * BATCH..(2 * p + 2) * BATCH];
            for g in 0..8 {
                build_lut(&w0[g * 8..g * 8 + 8], &w1[g * 8..g * 8 + 8], &mut self.luts[p * 8 + g]);
            }
        }
        bit_kernel(&self.bits, stride, nw, &self.luts, &mut self.acc, plan.padded);
    }

    fn grey_batch(&mut self, plan: &Plan, shift: &Shift, batch: &[f64], first: u64) {
        let m = plan.m;
        let k = plan.k;
        let n = batch.len() / m;
        self.weights.fill(0.0);
        for j in 0..n {
            let values = &mut self.grey[j * k..(j + 1) * k];
            plan.generator.fill_values(first + j as u64, values);
            let r = sum_values(values);
            self.set_weights(plan, shift, j, &batch[j * m..(j + 1) * m], r);
        }
        let mut local = [[0f64; 2]; GREY_TILE];
        for start in (0..k).step_by(GREY_TILE) {
            let len = GREY_TILE.min(k - start);
            for p in 0..plan.pairs {
                let local = &mut local[..len];
                local.fill([0.0; 2]);
                for j in 0..n {
                    let w =
                        [self.weights[2 * p * BATCH + j], self.weights[(2 * p + 1) * BATCH + j]];
                    let values = &self.grey[j * k + start..j * k + start + len];
                    for (a, &v) in local.iter_mut().zip(values) {
                        a[0] += w[0] * v as f64;
                        a[1] += w[1] * v as f64;
                    }
                }
                let acc = &mut self.acc[p * plan.padded + start..p * plan.padded + start + len];
                for (a, l) in acc.iter_mut().zip(local.iter()) {
                    a[0] += l[0];
                    a[1] += l[1];
                }
            }
        }
    }
}

/// `lut[s] = (sum of w0[b], sum of w1[b])` over the bits b set in s.
fn build_lut(w0: &[f64], w1: &[f64], lut: &mut [[f64; 2]; 256]) {
    lut[0] = [0.0; 2];
    for b in 0..8 {
        let half = 1usize << b;
        for s in 0..half {
            lut[half + s] = [lut[s][0] + w0[b], lut[s][1] + w1[b]];
        }
    }
}

/// One stage of eight 8 x 8 bit transposes per byte column, on all lanes: rows `r` and `r + j`
/// (bit j of r clear) swap the bits at in-byte positions `i + j` of row r with those at `i` of
/// row r + j (`mask` selects the positions i with bit j clear).
#[inline(always)]
fn transpose_stage(rows: &mut [[u64; 8]; 8], j: usize, mask: u64) {
    for r in (0..8).filter(|r| r & j == 0) {
        let (lo, hi) = rows.split_at_mut(r + j);
        for (a, b) in lo[r].iter_mut().zip(hi[0].iter_mut()) {
            let t = ((*a >> j) ^ *b) & mask;
            *b ^= t;
            *a ^= t << j;
        }
    }
}

#[inline(always)]
fn add2(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] + b[0], a[1] + b[1]]
}

/// The bit kernel. For every word of 64 pixels: load the 64 patterns' words as
/// `rows[b][g]` = pattern `8g + b`, transpose every byte column as an 8 x 8 bit matrix (the
/// eight groups g in parallel lanes), after which byte c of `rows[b][g]` holds pixel `8c + b` of
/// patterns `8g..8g+8` (pattern `8g + i` at bit i): the index into table g of each column pair.
/// (A full 64 x 64 transpose is not needed, only these bytes.)
fn bit_kernel(
    bits: &[u64],
    stride: usize,
    nw: usize,
    luts: &[[[f64; 2]; 256]],
    acc: &mut [[f64; 2]],
    padded: usize,
) {
    let pairs = luts.len() / 8;
    let mut rows = [[0u64; 8]; 8];
    for w in 0..nw {
        for (b, row) in rows.iter_mut().enumerate() {
            for (g, v) in row.iter_mut().enumerate() {
                *v = bits[(8 * g + b) * stride + w];
            }
        }
        transpose_stage(&mut rows, 4, 0x0F0F_0F0F_0F0F_0F0F);
        transpose_stage(&mut rows, 2, 0x3333_3333_3333_3333);
        transpose_stage(&mut rows, 1, 0x5555_5555_5555_5555);
        // keys[b][g][c]: byte c of rows[b][g].
        let mut keys = [[[0u8; 8]; 8]; 8];
        for (kb, row) in keys.iter_mut().zip(&rows) {
            for (k, v) in kb.iter_mut().zip(row) {
                *k = v.to_le_bytes();
            }
        }
        for p in 0..pairs {
            let l: &[[[f64; 2]; 256]; 8] = luts[p * 8..p * 8 + 8].try_into().unwrap();
            let acc = &mut acc[p * padded + w * 64..p * padded + w * 64 + 64];
            for (b, k) in keys.iter().enumerate() {
                for c in 0..8 {
                    let key = |g: usize| k[g][c] as usize;
                    let s01 = add2(l[0][key(0)], l[1][key(1)]);
                    let s23 = add2(l[2][key(2)], l[3][key(3)]);
                    let s45 = add2(l[4][key(4)], l[5][key(5)]);
                    let s67 = add2(l[6][key(6)], l[7][key(7)]);
                    let a = &mut acc[8 * c + b];
                    *a = add2(*a, add2(add2(s01, s23), add2(s45, s67)));
                }
            }
        }
    }
}

fn has_popcnt() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("popcnt")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        true
    }
}

/// Set bits in `words`; `popcnt`: the CPU has the instruction (see [`has_popcnt`]).
fn count_ones(words: &[u64], popcnt: bool) -> u64 {
    #[cfg(target_arch = "x86_64")]
    if popcnt {
        #[target_feature(enable = "popcnt")]
        fn with_popcnt(words: &[u64]) -> u64 {
            words.iter().map(|w| w.count_ones() as u64).sum()
        }
        // SAFETY: the caller checked that the CPU has POPCNT.
        return unsafe { with_popcnt(words) };
    }
    let _ = popcnt;
    words.iter().map(|w| w.count_ones() as u64).sum()
}

/// Sum of grey levels in f64, eight running sums (not one long dependency chain).
fn sum_values(values: &[f32]) -> f64 {
    let mut lanes = [0f64; 8];
    let chunks = values.chunks_exact(8);
    let tail: f64 = chunks.remainder().iter().map(|&v| v as f64).sum();
    for c in chunks {
        for (l, &v) in lanes.iter_mut().zip(c) {
            *l += v as f64;
        }
    }
    lanes.iter().sum::<f64>() + tail
}

/// Sums the workers and turns the sums into images and a report.
fn finish(plan: &Plan, config: &MethodConfig, mut workers: Vec<Worker>) -> Reconstruction {
    let mut total = workers.swap_remove(0);
    for w in &workers {
        total.rows += w.rows;
        total.sum_r += w.sum_r;
        for (a, b) in total.sum_shifted.iter_mut().zip(&w.sum_shifted) {
            *a += b;
        }
        for (a, b) in total.sum_raw.iter_mut().zip(&w.sum_raw) {
            *a += b;
        }
        total.acc.par_iter_mut().zip(w.acc.par_iter()).for_each(|(a, b)| *a = add2(*a, *b));
    }
    let n = total.rows as f64;
    let (k, padded, m) = (plan.k, plan.padded, plan.m);
    let column = |c: usize| {
        let pair = &total.acc[(c / 2) * padded..(c / 2) * padded + k];
        pair.iter().map(move |v| v[c % 2])
    };
    // Column 0: sum_i p_i(x) (GI, NGI) or sum_i R_i p_i(x) (DGI).
    let base: Vec<f64> = column(0).collect();
    let mut images = Vec::with_capacity(m);
    for ch in 0..m {
        // Coefficient of the base column.
        let beta = match plan.kind {
            Kind::Gi => total.sum_shifted[ch] / n,
            Kind::Dgi | Kind::Ngi => {
                if total.sum_r > 0.0 {
                    total.sum_shifted[ch] / total.sum_r
                } else {
                    0.0
                }
            }
        };
        let data = column(1 + ch).zip(&base).map(|(a, &b)| ((a - beta * b) / n) as f32).collect();
        images.push(DualImage { width: plan.width, height: plan.height, data });
    }

    let mut details = Map::new();
    details.insert("family".into(), json!(plan.family.name()));
    details.insert(
        "mean_bucket".into(),
        Value::Array(total.sum_raw.iter().map(|s| json!(s / n)).collect()),
    );
    details.insert("mean_pattern_sum".into(), json!(total.sum_r / n));
    match plan.family {
        Family::Bernoulli { fill: q } => {
            details.insert("fill".into(), json!(q));
            let gain = match plan.kind {
                Kind::Gi | Kind::Dgi => q * (1.0 - q),
                Kind::Ngi => (1.0 - q) / k as f64,
            };
            details.insert("expected_gain".into(), json!(gain));
            let form = match plan.kind {
                Kind::Gi => "expected_gain * t",
                Kind::Dgi => "expected_gain * (t - mean(t))",
                Kind::Ngi => "expected_gain * (t - mean(t)), to first order in 1/k",
            };
            details.insert("expected_form".into(), json!(form));
        }
        Family::Speckle { .. } if plan.kind == Kind::Gi => {
            details.insert("expected_gain".into(), json!(1.0 / 12.0));
            details.insert("expected_form".into(), json!("expected_gain * t"));
        }
        _ => {}
    }
    Reconstruction {
        images,
        report: Report {
            method: config.name().into(),
            params: config.params_json(),
            rows_used: total.rows,
            iterations: 1,
            details,
            ..Report::default()
        },
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // index loops read best in the reference computations
mod tests {
    use super::*;
    use crate::recon::testutil::{
        self, BlockList, CancelAfter, Rng, pearson, random_scene, simulate,
    };
    use crate::recon::{BucketBlock, SliceSource};
    use helmholtz_proto::{HadamardOrdering, PatternSpec};

    fn bernoulli(w: u32, h: u32, count: u64, fill: f64, seed: u64) -> PatternSpec {
        PatternSpec::new(Family::Bernoulli { fill }, w, h, count, seed).unwrap()
    }

    fn solve(
        spec: &PatternSpec,
        config: &MethodConfig,
        buckets: &[f64],
        channels: usize,
        rows: u64,
        tuning: Tuning,
        block_rows: usize,
    ) -> Reconstruction {
        let problem = Problem { spec, channels, rows };
        let mut src = SliceSource::new(&buckets[..rows as usize * channels], channels, block_rows);
        run_tuned(&problem, config, &mut src, &Control::new(), tuning).unwrap()
    }

    fn image(r: &Reconstruction, ch: usize) -> Vec<f64> {
        testutil::to_f64(&r.images[ch].data)
    }

    /// The formulas evaluated directly from dense patterns (f64, no shift, no kernel).
    fn dense_reference(
        spec: &PatternSpec,
        kind: Kind,
        buckets: &[f64],
        m: usize,
        n: u64,
    ) -> Vec<Vec<f64>> {
        let generator = PatternGenerator::new(spec);
        let k = spec.pixels();
        let mut p = vec![0f32; k];
        let (mut sc, mut sr) = (vec![0.0; m], 0.0);
        let mut sp = vec![0.0; k];
        let mut srp = vec![0.0; k];
        let mut scp = vec![vec![0.0; k]; m];
        let mut sqp = vec![vec![0.0; k]; m]; // sum (c/R) p
        for i in 0..n {
            generator.fill_values(i, &mut p);
            let r: f64 = p.iter().map(|&v| v as f64).sum();
            sr += r;
            for x in 0..k {
                sp[x] += p[x] as f64;
                srp[x] += r * p[x] as f64;
            }
            for ch in 0..m {
                let c = buckets[i as usize * m + ch];
                sc[ch] += c;
                for x in 0..k {
                    scp[ch][x] += c * p[x] as f64;
                    if r > 0.0 {
                        sqp[ch][x] += c / r * p[x] as f64;
                    }
                }
            }
        }
        let n = n as f64;
        (0..m)
            .map(|ch| {
                (0..k)
                    .map(|x| match kind {
                        Kind::Gi => scp[ch][x] / n - (sc[ch] / n) * (sp[x] / n),
                        Kind::Dgi => scp[ch][x] / n - (sc[ch] / sr) * (srp[x] / n),
                        Kind::Ngi => sqp[ch][x] / n - (sc[ch] / sr) * (sp[x] / n),
                    })
                    .collect()
            })
            .collect()
    }

    const CONFIGS: [(MethodConfig, Kind); 3] = [
        (MethodConfig::Gi, Kind::Gi),
        (MethodConfig::Dgi, Kind::Dgi),
        (MethodConfig::Ngi, Kind::Ngi),
    ];

    #[test]
    fn byte_column_transpose_gives_the_lut_keys() {
        let mut rng = Rng::new(5);
        let mut rows = [[0u64; 8]; 8];
        for v in rows.iter_mut().flatten() {
            *v = rng.next_u64();
        }
        let orig = rows;
        transpose_stage(&mut rows, 4, 0x0F0F_0F0F_0F0F_0F0F);
        transpose_stage(&mut rows, 2, 0x3333_3333_3333_3333);
        transpose_stage(&mut rows, 1, 0x5555_5555_5555_5555);
        // Byte c of rows[b][g], bit i = pixel 8c + b of pattern 8g + i (= orig[i][g]).
        for b in 0..8 {
            for g in 0..8 {
                for c in 0..8 {
                    for i in 0..8 {
                        let got = (rows[b][g] >> (8 * c + i)) & 1;
                        let want = (orig[i][g] >> (8 * c + b)) & 1;
                        assert_eq!(got, want, "b {b} g {g} c {c} i {i}");
                    }
                }
            }
        }
    }

    #[test]
    fn lut_holds_subset_sums() {
        let w0 = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0];
        let w1 = [-1.0; 8];
        let mut lut = [[0.0; 2]; 256];
        build_lut(&w0, &w1, &mut lut);
        for (s, v) in lut.iter().enumerate() {
            assert_eq!(*v, [s as f64, -(s.count_ones() as f64)]);
        }
    }

    /// Kernel, tails and worker split against the dense formulas, for every binary family and
    /// speckle, at k not a multiple of 64, with partial batches, 1-3 workers and odd block sizes.
    #[test]
    fn matches_dense_formulas_every_family() {
        let specs = [
            bernoulli(10, 7, 1000, 0.5, 1),
            bernoulli(9, 9, 1000, 0.3, 2),
            PatternSpec::new(Family::Raster { block: 3 }, 10, 7, 1000, 0).unwrap(),
            // Hadamard: frame 1 (P- of natural row 0) is all-off, exercising R = 0 in NGI.
            PatternSpec::new(
                Family::Hadamard { ordering: HadamardOrdering::Natural },
                16,
                8,
                256,
                0,
            )
            .unwrap(),
            PatternSpec::new(Family::Speckle { grain: 2 }, 11, 6, 1000, 3).unwrap(),
        ];
        for spec in &specs {
            let k = spec.pixels();
            let scenes = [random_scene(k, 0.0, 1.0, 10), random_scene(k, 0.5, 2.0, 11)];
            let n = 237.min(spec.count());
            let mut buckets = simulate(spec, &scenes, n, |i| 1.0 + 0.01 * (i % 7) as f64, 0.3);
            // Add some noise so nothing is an accidental identity.
            let mut rng = Rng::new(99);
            for b in buckets.iter_mut() {
                *b += 0.05 * rng.normal();
            }
            for (config, kind) in &CONFIGS {
                let want = dense_reference(spec, *kind, &buckets, 2, n);
                for (workers, dispatch, block) in [(1, 1000, 1000), (3, 70, 13), (2, 64, 1)] {
                    let tuning = Tuning { workers: Some(workers), dispatch_rows: Some(dispatch) };
                    let got = solve(spec, config, &buckets, 2, n, tuning, block);
                    for ch in 0..2 {
                        let g = image(&got, ch);
                        let scale = want[ch].iter().fold(0.0f64, |a, v| a.max(v.abs()));
                        for x in 0..k {
                            // f32 output: 1e-6 of the image's scale.
                            assert!(
                                (g[x] - want[ch][x]).abs() <= 1e-6 * scale,
                                "{} {:?} workers {workers}: ch {ch} px {x}: {} vs {}",
                                spec.family().name(),
                                kind,
                                g[x],
                                want[ch][x]
                            );
                        }
                    }
                    assert_eq!(got.report.rows_used, n);
                }
            }
        }
    }

    /// The seed's appendix: Bernoulli(1/2) patterns, GI converges to t/4.
    ///
    /// Error model. Write p_j = 1/2 + s_j with s_j = +-1/2 iid (E s^2 = 1/4, E s^4 = 1/16) and
    /// A = c - E c = sum_j t_j s_j. To leading order in 1/n, G(x) - t(x)/4 is the mean of n iid
    /// copies of A s_x - t(x)/4, whose variance is
    ///     E[A^2 s_x^2] - (t_x/4)^2 = t_x^2/16 + (1/16) sum_{j != x} t_j^2 - t_x^2/16
    ///                              = (||t||^2 - t_x^2) / 16.
    /// Summing over the k pixels: E||G - t/4||^2 = (k - 1) ||t||^2 / (16 n).
    /// (The O(1/n) bias of the sample covariance, -t/(4n), adds O(||t||^2/n^2): negligible.)
    /// The squared error is a sum of k nearly independent terms (the pixel errors have
    /// covariance t_x t_y/(16 n), a rank-one part worth 1/k of the total), so its relative
    /// spread is about sqrt(2/k) = 0.088 at k = 256, i.e. 0.044 on the norm. We require the
    /// norm within +-25% (over 5 sigma) of its prediction: too small an error fails too.
    #[test]
    fn gi_converges_to_quarter_t_at_the_predicted_rate() {
        let (w, h) = (16u32, 16u32);
        let k = (w * h) as usize;
        let n_max = 65536u64;
        let spec = bernoulli(w, h, n_max, 0.5, 2024);
        let t = random_scene(k, 0.0, 1.0, 7);
        let t_norm2: f64 = t.iter().map(|v| v * v).sum();
        let buckets = simulate(&spec, std::slice::from_ref(&t), n_max, |_| 1.0, 0.0);
        let mut errors = Vec::new();
        for n in [4096u64, 16384, 65536] {
            let r = solve(&spec, &MethodConfig::Gi, &buckets, 1, n, Tuning::default(), 5000);
            let g = image(&r, 0);
            let err = g.iter().zip(&t).map(|(a, b)| (a - b / 4.0).powi(2)).sum::<f64>().sqrt();
            let predicted = ((k - 1) as f64 * t_norm2 / (16.0 * n as f64)).sqrt();
            let ratio = err / predicted;
            assert!((0.75..1.25).contains(&ratio), "n {n}: error {err}, predicted {predicted}");
            assert_eq!(r.report.details["expected_gain"], json!(0.25));
            errors.push(err);
        }
        // 4x the rows halves the error: each norm is within 25% of its prediction, so each
        // ratio lies in [0.5 * 0.75 / 1.25, 0.5 * 1.25 / 0.75] = [0.3, 0.83]; typically ~0.5.
        for pair in errors.windows(2) {
            let ratio = pair[1] / pair[0];
            assert!((0.3..0.83).contains(&ratio), "error ratio {ratio} for 4x rows");
        }
    }

    /// Noise model for the correlation with the scene: per pixel the estimate is
    /// gain * (t + e), Var(e) ~ V / (n sigma^2) with V the variance of the part of the bucket
    /// uncorrelated with p(x) that the method leaves in: GI keeps Var(c) = sigma^2 ||t||^2,
    /// DGI/NGI remove the mean(t) R_i part, leaving sigma^2 ||t - mean t||^2. Then
    /// rho = 1 / sqrt(1 + Var(e) / var(t)). We allow the noise variance 50% above the model.
    fn predicted_rho(noise_var: f64, signal_var: f64) -> f64 {
        1.0 / (1.0 + 1.5 * noise_var / signal_var).sqrt()
    }

    #[test]
    fn correlators_see_the_scene_with_the_expected_gain() {
        let (w, h) = (16u32, 16u32);
        let k = (w * h) as usize;
        let n = 20000u64;
        let q = 0.5;
        let spec = bernoulli(w, h, n, q, 77);
        let t = random_scene(k, 0.0, 1.0, 8);
        let mean = t.iter().sum::<f64>() / k as f64;
        let var = t.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / k as f64;
        let norm2: f64 = t.iter().map(|v| v * v).sum();
        let centred2: f64 = t.iter().map(|v| (v - mean).powi(2)).sum();
        let buckets = simulate(&spec, std::slice::from_ref(&t), n, |_| 1.0, 0.0);
        let centred: Vec<f64> = t.iter().map(|v| v - mean).collect();
        for (config, kind) in &CONFIGS {
            let r = solve(&spec, config, &buckets, 1, n, Tuning::default(), 4096);
            let g = image(&r, 0);
            let rho = pearson(&g, &t);
            let noise = match kind {
                Kind::Gi => norm2 / n as f64,
                _ => centred2 / n as f64,
            };
            let floor = predicted_rho(noise, var);
            assert!(rho > floor, "{kind:?}: rho {rho} <= {floor}");
            // Gain: least-squares slope of G on t (DGI/NGI: on t - mean t, their expectation).
            let (target, gain) = match kind {
                Kind::Gi => (&t, q * (1.0 - q)),
                Kind::Dgi => (&centred, q * (1.0 - q)),
                Kind::Ngi => (&centred, (1.0 - q) / k as f64),
            };
            let g32: Vec<f32> = g.iter().map(|&v| v as f32).collect();
            let tt: Vec<f32> = target.iter().map(|&v| v as f32).collect();
            let (a, _) = crate::recon::metrics::fit_affine(&tt, &g32);
            assert!((a / gain - 1.0).abs() < 0.1, "{kind:?}: slope {a}, expected {gain}");
            assert_eq!(r.report.details["expected_gain"], json!(gain));
            if *kind != Kind::Gi {
                // Offset: DGI/NGI estimate t - mean t, so the image mean is ~0.
                let gm = g.iter().sum::<f64>() / k as f64;
                assert!(gm.abs() < 0.05 * gain * mean, "{kind:?}: mean {gm}");
            }
        }
    }

    /// Weakly absorbing scene (t in [0.8, 1]) under a slow multiplicative source drift
    /// (+-5% ramp, plus 1% jitter). Noise variances per pixel in units of t (see
    /// `predicted_rho`): GI ||t||^2 / n, DGI ||t - mean t||^2 / n, plus for both the drift term
    /// Var(g) (k q mean t)^2 / (sigma^2 n) (R_i is computed, not measured, so DGI cannot cancel
    /// g_i; it removes the far larger mean(t) R_i background). Predictions here:
    /// GI rho ~ 0.46, DGI ~ 0.76, NGI ~ DGI.
    #[test]
    fn dgi_beats_gi_under_drift_and_background() {
        let (w, h) = (16u32, 16u32);
        let k = (w * h) as usize;
        let n = 20000u64;
        let spec = bernoulli(w, h, n, 0.5, 5);
        let t = random_scene(k, 0.8, 1.0, 9);
        let mut jitter = Rng::new(4);
        let gains: Vec<f64> =
            (0..n).map(|i| 0.95 + 0.1 * i as f64 / n as f64 + 0.01 * jitter.normal()).collect();
        let buckets = simulate(&spec, std::slice::from_ref(&t), n, |i| gains[i as usize], 0.0);

        let mean = t.iter().sum::<f64>() / k as f64;
        let var = t.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / k as f64;
        let gm = gains.iter().sum::<f64>() / n as f64;
        let gvar = gains.iter().map(|g| (g - gm).powi(2)).sum::<f64>() / n as f64;
        let drift = gvar * (k as f64 * 0.5 * mean).powi(2) / (0.25 * n as f64);
        let norm2: f64 = t.iter().map(|v| v * v).sum();
        let centred2: f64 = t.iter().map(|v| (v - mean).powi(2)).sum();

        let rho = |config: &MethodConfig| {
            let r = solve(&spec, config, &buckets, 1, n, Tuning::default(), 1000);
            pearson(&image(&r, 0), &t)
        };
        let (gi, dgi, ngi) =
            (rho(&MethodConfig::Gi), rho(&MethodConfig::Dgi), rho(&MethodConfig::Ngi));
        let model = |noise: f64| 1.0 / (1.0 + noise / var).sqrt();
        let (gi_model, dgi_model) =
            (model(norm2 / n as f64 + drift), model(centred2 / n as f64 + drift));
        assert!(dgi > gi + 0.15, "dgi {dgi} vs gi {gi}");
        assert!(ngi > gi + 0.15, "ngi {ngi} vs gi {gi}");
        // Both near their models. Over 8 pattern seeds rho spread by ~0.06 (GI) and ~0.02
        // (DGI) around means 0.44 and 0.75; allow about 3.5 and 5 of those.
        assert!((gi - gi_model).abs() < 0.2, "gi {gi}, model {gi_model}");
        assert!((dgi - dgi_model).abs() < 0.1, "dgi {dgi}, model {dgi_model}");
    }

    #[test]
    fn speckle_gi_gain_is_one_twelfth() {
        let (w, h) = (12u32, 10u32);
        let k = (w * h) as usize;
        let n = 20000u64;
        let spec = PatternSpec::new(Family::Speckle { grain: 1 }, w, h, n, 31).unwrap();
        let t = random_scene(k, 0.0, 1.0, 12);
        let buckets = simulate(&spec, std::slice::from_ref(&t), n, |_| 1.0, 0.0);
        let r = solve(&spec, &MethodConfig::Gi, &buckets, 1, n, Tuning::default(), 3000);
        let g = image(&r, 0);
        // Uniform levels: sigma^2 = 1/12, E p^4 - sigma^4... noise var ~ E[(A s)^2]/sigma^4 / n
        // = ||t||^2 / n (as for Bernoulli, up to the kurtosis of one term).
        let mean = t.iter().sum::<f64>() / k as f64;
        let var = t.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / k as f64;
        let norm2: f64 = t.iter().map(|v| v * v).sum();
        assert!(pearson(&g, &t) > predicted_rho(norm2 / n as f64, var));
        let g32: Vec<f32> = g.iter().map(|&v| v as f32).collect();
        let t32: Vec<f32> = t.iter().map(|&v| v as f32).collect();
        let (a, _) = crate::recon::metrics::fit_affine(&t32, &g32);
        assert!((a * 12.0 - 1.0).abs() < 0.1, "slope {a}");
    }

    #[test]
    fn channels_are_independent_and_block_size_does_not_matter() {
        let spec = bernoulli(20, 13, 3000, 0.25, 8);
        let k = spec.pixels();
        let scenes = [
            random_scene(k, 0.0, 1.0, 1),
            random_scene(k, 0.0, 5.0, 2),
            random_scene(k, 0.0, 0.1, 3),
        ];
        let n = 3000;
        let all = simulate(&spec, &scenes, n, |_| 1.0, 2.0);
        for (config, _) in &CONFIGS {
            let multi = solve(&spec, config, &all, 3, n, Tuning::default(), 1000);
            assert_eq!(multi.images.len(), 3);
            for (ch, scene) in scenes.iter().enumerate() {
                let single_buckets: Vec<f64> = all.iter().skip(ch).step_by(3).copied().collect();
                for block in [1usize, 7, 3000] {
                    let single =
                        solve(&spec, config, &single_buckets, 1, n, Tuning::default(), block);
                    let (a, b) = (image(&multi, ch), image(&single, 0));
                    let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                    let diff = a.iter().zip(&b).fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
                    assert!(diff <= 1e-6 * scale, "{config:?} ch {ch} block {block}: {diff}");
                }
                assert!(pearson(&image(&multi, ch), scene) > 0.8);
            }
            let mb = multi.report.details["mean_bucket"].as_array().unwrap();
            assert_eq!(mb.len(), 3);
        }
    }

    #[test]
    fn malformed_blocks_are_bad_rows() {
        let spec = bernoulli(8, 8, 100, 0.5, 1);
        let problem = Problem { spec: &spec, channels: 2, rows: 10 };
        let block = |first_row: u64, len: usize| BucketBlock { first_row, values: vec![1.0; len] };
        let cases: Vec<(Vec<BucketBlock>, &str)> = vec![
            (vec![block(0, 7)], "multiple"),
            (vec![block(0, 4), block(3, 4)], "expected row 2"),
            (vec![block(1, 4)], "expected row 0"),
            (vec![block(0, 22)], "run past"),
            (vec![block(0, 16), block(8, 6)], "run past"),
            (
                vec![BucketBlock { first_row: 0, values: vec![1.0, 2.0, f64::NAN, 4.0] }],
                "row 1 channel 0",
            ),
        ];
        for (blocks, want) in cases {
            let mut src = BlockList(blocks.into());
            let err = run(&problem, &MethodConfig::Gi, &mut src, &Control::new()).unwrap_err();
            match err {
                ReconError::BadRows(msg) => assert!(msg.contains(want), "{msg}"),
                other => panic!("expected BadRows, got {other:?}"),
            }
        }
        // Too few rows: Unsolvable.
        let mut src = BlockList(vec![block(0, 8)].into());
        let err = run(&problem, &MethodConfig::Dgi, &mut src, &Control::new()).unwrap_err();
        assert!(matches!(err, ReconError::Unsolvable(_)), "{err:?}");
        // Zero channels.
        let bad = Problem { spec: &spec, channels: 0, rows: 10 };
        let mut src = BlockList(Default::default());
        assert!(matches!(
            run(&bad, &MethodConfig::Gi, &mut src, &Control::new()),
            Err(ReconError::BadRows(_))
        ));
    }

    #[test]
    fn cancellation_stops_the_run() {
        let spec = bernoulli(64, 64, 4096, 0.5, 1);
        let buckets = vec![1.0; 4096];
        let problem = Problem { spec: &spec, channels: 1, rows: 4096 };
        // Cancelled before the start.
        let control = Control::new();
        control.cancel();
        let mut src = SliceSource::new(&buckets, 1, 128);
        assert!(matches!(
            run(&problem, &MethodConfig::Gi, &mut src, &control),
            Err(ReconError::Cancelled)
        ));
        // Cancelled while running (after 3 blocks), with dispatches smaller than the blocks.
        let control = Control::new();
        let mut src = CancelAfter {
            inner: SliceSource::new(&buckets, 1, 128),
            control: &control,
            after: 3,
            seen: 0,
        };
        let tuning = Tuning { workers: None, dispatch_rows: Some(64) };
        let res = run_tuned(&problem, &MethodConfig::Ngi, &mut src, &control, tuning);
        assert!(matches!(res, Err(ReconError::Cancelled)), "{res:?}");
        assert!(control.progress() > 0.0 && control.progress() < 1.0, "{}", control.progress());
    }

    #[test]
    fn progress_reaches_one() {
        let spec = bernoulli(8, 8, 1000, 0.5, 1);
        let buckets = vec![1.0; 1000];
        let problem = Problem { spec: &spec, channels: 1, rows: 1000 };
        let control = Control::new();
        let mut src = SliceSource::new(&buckets, 1, 100);
        let r = run(&problem, &MethodConfig::Gi, &mut src, &control).unwrap();
        assert_eq!(control.progress(), 1.0);
        assert_eq!(r.report.method, "gi");
        assert_eq!(r.report.iterations, 1);
        // Constant buckets carry no correlation: G = 0 exactly thanks to the shift.
        assert!(r.images[0].data.iter().all(|&v| v == 0.0));
    }

    /// CPU seconds used by this process so far (all threads), from /proc/self/stat.
    fn cpu_seconds() -> f64 {
        let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
        let fields: Vec<&str> = stat.rsplit(')').next().unwrap_or("").split_whitespace().collect();
        let ticks = |i: usize| fields.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        // After the command name: state is field 0, utime 11, stime 12 (clock ticks, 100 Hz).
        (ticks(11) + ticks(12)) / 100.0
    }

    /// Throughput of the correlators, pattern generation included: pattern-pixel updates per
    /// wall second, and per CPU second (per core; robust when other work shares the machine).
    /// Run with
    /// `cargo test -p helmholtz-server --lib recon::correlate::tests::bench -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn bench_throughput() {
        for (family, w, h, n, m) in [
            (Family::Bernoulli { fill: 0.5 }, 256u32, 256u32, 32768u64, 1usize),
            (Family::Bernoulli { fill: 0.5 }, 128, 128, 131072, 1),
            (Family::Bernoulli { fill: 0.5 }, 256, 256, 16384, 3),
            (Family::Speckle { grain: 1 }, 128, 128, 4096, 1),
        ] {
            let spec = PatternSpec::new(family.clone(), w, h, n, 1).unwrap();
            let mut rng = Rng::new(1);
            let buckets: Vec<f64> = (0..n as usize * m).map(|_| rng.uniform()).collect();
            for config in [MethodConfig::Gi, MethodConfig::Dgi] {
                let problem = Problem { spec: &spec, channels: m, rows: n };
                let mut src = SliceSource::new(&buckets, m, 4096);
                let (t0, c0) = (std::time::Instant::now(), cpu_seconds());
                run(&problem, &config, &mut src, &Control::new()).unwrap();
                let (wall, cpu) = (t0.elapsed().as_secs_f64(), cpu_seconds() - c0);
                let updates = n as f64 * spec.pixels() as f64;
                println!(
                    "{} {w}x{h} n={n} channels={m} {}: {wall:.3} s wall, {cpu:.2} s cpu: \
                     {:.2e} updates/s wall ({} threads), {:.2e} updates/s per cpu-second",
                    family.name(),
                    config.name(),
                    updates / wall,
                    rayon::current_num_threads(),
                    updates / cpu,
                );
            }
        }
    }
}
