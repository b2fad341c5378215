//! One pass over the rows: [`dispatch`] splits each run of rows over the [`Worker`]s, each
//! with its own accumulators, which the kernels ([`super::kernel`]) update batch by batch.

use rayon::prelude::*;

use super::held_out::Recorded;
use super::kernel::{add2, bit_kernel, build_lut, count_ones, sum_values};
use super::plan::{Plan, Shift};
use super::{BATCH, GREY_BATCH, GREY_TILE, Kind};
use crate::{Control, ReconError};

/// Runs `rows` (row-major, first row `first`) through the workers, split into contiguous parts;
/// `record` keeps the held-out and calibration rows among them.
pub(super) fn dispatch(
    plan: &Plan,
    workers: &mut [Worker],
    shift: &mut Shift,
    record: Option<&mut Recorded>,
    rows: &[f64],
    first: u64,
    control: &Control,
) -> Result<(), ReconError> {
    if let Some(record) = record {
        record.add(rows, first, plan.m);
    }
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
        workers[..parts]
            .par_iter_mut()
            .enumerate()
            .for_each(|(w, worker)| {
                let lo = w * per;
                let hi = (lo + per).min(n);
                worker.process(
                    plan,
                    shift,
                    &rows[lo * m..hi * m],
                    first + lo as u64,
                    control,
                );
            });
    }
    if control.is_cancelled() {
        return Err(ReconError::Cancelled);
    }
    Ok(())
}

/// One thread's accumulators and scratch.
pub(super) struct Worker {
    /// `pairs` interleaved column pairs of length `padded` (see [`Plan`]).
    pub(super) acc: Vec<[f64; 2]>,
    /// Bit batch: pattern j at `bits[j * stride..][..nw]`.
    bits: Vec<u64>,
    /// Grey batch: pattern j at `grey[j * k..][..k]`.
    grey: Vec<f32>,
    /// Per batch: `weights[c * BATCH + j]`, weight of pattern j in column c (0..2 pairs).
    weights: Vec<f64>,
    /// Per batch: 8 subset-sum tables per column pair.
    luts: Vec<[[f64; 2]; 256]>,
    pub(super) rows: u64,
    pub(super) sum_r: f64,
    /// Per channel: sum of shifted buckets, sum of raw buckets.
    sum_shifted: Vec<f64>,
    pub(super) sum_raw: Vec<f64>,
}

impl Worker {
    pub(super) fn new(plan: &Plan) -> Worker {
        Worker {
            acc: vec![[0.0; 2]; plan.pairs * plan.padded],
            bits: if plan.binary {
                vec![0; BATCH * plan.stride]
            } else {
                Vec::new()
            },
            grey: if plan.binary {
                Vec::new()
            } else {
                vec![0.0; GREY_BATCH * plan.k]
            },
            weights: vec![0.0; 2 * plan.pairs * BATCH],
            luts: if plan.binary {
                vec![[[0.0; 2]; 256]; plan.pairs * 8]
            } else {
                Vec::new()
            },
            rows: 0,
            sum_r: 0.0,
            sum_shifted: vec![0.0; plan.m],
            sum_raw: vec![0.0; plan.m],
        }
    }

    pub(super) fn process(
        &mut self,
        plan: &Plan,
        shift: &Shift,
        rows: &[f64],
        first: u64,
        control: &Control,
    ) {
        let m = plan.m;
        let granule = if plan.binary { BATCH } else { GREY_BATCH };
        for (b, batch) in rows.chunks(granule * m).enumerate() {
            if control.is_cancelled() {
                return;
            }
            let first = first + (b * granule) as u64;
            if plan.binary {
                self.binary_batch(plan, shift, batch, |j| first + j as u64);
            } else {
                self.grey_batch(plan, shift, batch, |j| first + j as u64);
            }
        }
    }

    /// As [`Worker::process`], for rows `index` (any order) with buckets `values` (row-major).
    pub(super) fn process_rows(
        &mut self,
        plan: &Plan,
        shift: &Shift,
        values: &[f64],
        index: &[u64],
    ) {
        let m = plan.m;
        let granule = if plan.binary { BATCH } else { GREY_BATCH };
        for (batch, index) in values.chunks(granule * m).zip(index.chunks(granule)) {
            if plan.binary {
                self.binary_batch(plan, shift, batch, |j| index[j]);
            } else {
                self.grey_batch(plan, shift, batch, |j| index[j]);
            }
        }
    }

    /// Back to the state of [`Worker::new`] (scratch left as is).
    pub(super) fn reset(&mut self) {
        self.acc.fill([0.0; 2]);
        self.rows = 0;
        self.sum_r = 0.0;
        self.sum_shifted.fill(0.0);
        self.sum_raw.fill(0.0);
    }

    /// Adds `other`'s sums to these.
    pub(super) fn merge(&mut self, other: &Worker) {
        self.rows += other.rows;
        self.sum_r += other.sum_r;
        for (a, b) in self.sum_shifted.iter_mut().zip(&other.sum_shifted) {
            *a += b;
        }
        for (a, b) in self.sum_raw.iter_mut().zip(&other.sum_raw) {
            *a += b;
        }
        self.acc
            .par_iter_mut()
            .zip(other.acc.par_iter())
            .for_each(|(a, b)| *a = add2(*a, *b));
    }

    /// Replaces these sums (a subset of the rows) by `total`'s minus these: the other rows' sums.
    pub(super) fn complement_in(&mut self, total: &Worker) {
        self.rows = total.rows - self.rows;
        self.sum_r = total.sum_r - self.sum_r;
        for (a, b) in self.sum_shifted.iter_mut().zip(&total.sum_shifted) {
            *a = b - *a;
        }
        for (a, b) in self.sum_raw.iter_mut().zip(&total.sum_raw) {
            *a = b - *a;
        }
        self.acc
            .par_iter_mut()
            .zip(total.acc.par_iter())
            .for_each(|(a, b)| *a = [b[0] - a[0], b[1] - a[1]]);
    }

    /// Channel `ch`'s image from these sums, by the formulas of the module docs (one code path
    /// for the served and the training-only image).
    pub(super) fn image<'a>(&'a self, plan: &'a Plan, ch: usize) -> impl Iterator<Item = f64> + 'a {
        let n = self.rows as f64;
        // Coefficient of the base column.
        let beta = match plan.kind {
            Kind::Gi => self.sum_shifted[ch] / n,
            Kind::Dgi | Kind::Ngi => {
                if self.sum_r > 0.0 {
                    self.sum_shifted[ch] / self.sum_r
                } else {
                    0.0
                }
            }
        };
        let (k, padded) = (plan.k, plan.padded);
        let column = move |c: usize| {
            let pair = &self.acc[(c / 2) * padded..(c / 2) * padded + k];
            pair.iter().map(move |v| v[c % 2])
        };
        // Column 0: sum_i p_i(x) (GI, NGI) or sum_i R_i p_i(x) (DGI).
        column(1 + ch)
            .zip(column(0))
            .map(move |(a, b)| (a - beta * b) / n)
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

    /// One batch of up to [`BATCH`] rows; row j of the batch is pattern `row(j)`.
    fn binary_batch(
        &mut self,
        plan: &Plan,
        shift: &Shift,
        batch: &[f64],
        row: impl Fn(usize) -> u64,
    ) {
        let m = plan.m;
        let n = batch.len() / m;
        let (nw, stride) = (plan.nw, plan.stride);
        self.weights.fill(0.0);
        for j in 0..BATCH {
            let words = &mut self.bits[j * stride..j * stride + nw];
            if j < n {
                plan.generator
                    .fill_bits(row(j), words)
                    .expect("binary family");
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
                build_lut(
                    &w0[g * 8..g * 8 + 8],
                    &w1[g * 8..g * 8 + 8],
                    &mut self.luts[p * 8 + g],
                );
            }
        }
        bit_kernel(
            &self.bits,
            stride,
            nw,
            &self.luts,
            &mut self.acc,
            plan.padded,
        );
    }

    /// One batch of up to [`GREY_BATCH`] rows; row j of the batch is pattern `row(j)`.
    fn grey_batch(
        &mut self,
        plan: &Plan,
        shift: &Shift,
        batch: &[f64],
        row: impl Fn(usize) -> u64,
    ) {
        let m = plan.m;
        let k = plan.k;
        let n = batch.len() / m;
        self.weights.fill(0.0);
        for j in 0..n {
            let values = &mut self.grey[j * k..(j + 1) * k];
            plan.generator.fill_values(row(j), values);
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
                    let w = [
                        self.weights[2 * p * BATCH + j],
                        self.weights[(2 * p + 1) * BATCH + j],
                    ];
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
