//! What is fixed before the pass: the pattern source, the column layout and the work split
//! ([`Plan`]), and the per-channel shift of the buckets ([`Shift`]; module docs of [`super`],
//! "Formulas").

use helmholtz_proto::{Family, PatternGenerator};

use super::kernel::{count_ones, has_popcnt, sum_values};
use super::{BATCH, DISPATCH_WORK, GREY_BATCH, Kind, MEMORY_BUDGET, Tuning};
use crate::Problem;

/// Everything fixed by the problem: pattern source, column layout, work split.
///
/// Columns: column 0 is the base, `sum_i b_i p_i(x)` with `b_i = 1` (GI, NGI) or `R_i` (DGI);
/// column 1 + ch is channel ch's `sum_i w_i p_i(x)`. Columns are stored in interleaved pairs
/// (`acc[(pair * padded + x) * 2 + lane]`, column = 2 pair + lane) so one 16-byte table entry
/// updates two columns at once.
pub(super) struct Plan {
    pub(super) generator: PatternGenerator,
    pub(super) kind: Kind,
    pub(super) family: Family,
    pub(super) binary: bool,
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) k: usize,
    /// 64-bit words per pattern.
    pub(super) nw: usize,
    /// Words between consecutive patterns in the bit buffer (padded against cache aliasing).
    pub(super) stride: usize,
    /// Accumulator length per column: nw * 64 (binary) or k (grey).
    pub(super) padded: usize,
    pub(super) m: usize,
    /// m + 1 columns, in ceil((m + 1) / 2) pairs.
    pub(super) pairs: usize,
    pub(super) workers: usize,
    /// Accumulator and scratch bytes of one worker.
    pub(super) worker_bytes: usize,
    pub(super) dispatch_rows: usize,
    /// The CPU has a population-count instruction (x86-64 baseline does not).
    pub(super) popcnt: bool,
}

impl Plan {
    pub(super) fn new(problem: &Problem, kind: Kind, tuning: Tuning) -> Plan {
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

        let per_worker = pairs * padded * 16
            + if binary {
                BATCH * stride * 8
            } else {
                GREY_BATCH * k * 4
            };
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
            worker_bytes: per_worker,
            dispatch_rows,
            popcnt: has_popcnt(),
        }
    }

    /// Pattern sum `R` of row `row`, generated on its own (used once to fix the shift).
    pub(super) fn pattern_sum(&self, row: u64) -> f64 {
        if self.binary {
            let mut words = vec![0u64; self.nw];
            self.generator
                .fill_bits(row, &mut words)
                .expect("binary family");
            count_ones(&words, self.popcnt) as f64
        } else {
            let mut values = vec![0f32; self.k];
            self.generator.fill_values(row, &mut values);
            sum_values(&values)
        }
    }
}

/// The per-channel constant subtracted from the buckets: `c0` (GI) or `a` in `c - a R` (DGI, NGI).
pub(super) struct Shift {
    pub(super) values: Vec<f64>,
    pub(super) fixed: bool,
}

impl Shift {
    /// Fixes the shift from the first rows if not yet done (`rows`: row-major buckets of rows
    /// `first..`).
    pub(super) fn fix(&mut self, plan: &Plan, rows: &[f64], first: u64) {
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
    pub(super) fn apply(&self, kind: Kind, channel: usize, c: f64, r: f64) -> f64 {
        match kind {
            Kind::Gi => c - self.values[channel],
            Kind::Dgi | Kind::Ngi => c - self.values[channel] * r,
        }
    }
}
