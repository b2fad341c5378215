//! The held-out error estimate of the correlators (module docs of [`super`], "Held-out error"):
//! the rows kept while streaming ([`Recorded`]), the training-only sums, the calibration
//! `c ~ a (p . t_tr) + b R + c0` fitted on C ([`Calibration`]) and the score on H.

use helmholtz_proto::Family;
use rayon::prelude::*;

use super::kernel::{count_ones, dot_bits, dot_values, nibble_table, sum_values};
use super::plan::{Plan, Shift};
use super::worker::Worker;
use super::{BATCH, GREY_BATCH, MAX_CALIBRATION, MAX_HELD_OUT, MEMORY_BUDGET};
use crate::holdout::{self, HeldOut, MIN_HELD_OUT, Score};

/// The rows kept while streaming for the held-out estimate (see the module docs): the held-out
/// rows H and the calibration rows C, each with its buckets (row-major, `channels` per row).
pub(super) struct Recorded {
    /// Fraction held out: `min(DEFAULT_FRACTION, MAX_HELD_OUT / n)`.
    pub(super) fraction: f64,
    /// Fraction used for calibration: `min(DEFAULT_FRACTION, MAX_CALIBRATION / n)`.
    pub(super) calibration_fraction: f64,
    /// Rows `n` of the problem.
    pub(super) rows: u64,
    /// Hadamard split pairs are held out together (the hashed unit is `row / 2`).
    pairs: bool,
    pub(super) held: Vec<u64>,
    pub(super) held_values: Vec<f64>,
    pub(super) calibration: Vec<u64>,
    pub(super) calibration_values: Vec<f64>,
}

impl Recorded {
    pub(super) fn new(plan: &Plan, rows: u64) -> Recorded {
        Recorded {
            fraction: holdout::DEFAULT_FRACTION.min(MAX_HELD_OUT as f64 / rows.max(1) as f64),
            calibration_fraction: holdout::DEFAULT_FRACTION
                .min(MAX_CALIBRATION as f64 / rows.max(1) as f64),
            rows,
            pairs: matches!(plan.family, Family::Hadamard { .. }),
            held: Vec::new(),
            held_values: Vec::new(),
            calibration: Vec::new(),
            calibration_values: Vec::new(),
        }
    }

    /// The hash key of row `row`'s unit (the row; Hadamard: its split pair).
    fn key(&self, row: u64) -> f64 {
        holdout::key(if self.pairs { row / 2 } else { row })
    }

    /// `Err`: why these rows give no estimate (too few held-out or calibration rows).
    pub(super) fn check(&self) -> Result<(), String> {
        let (held, calibration) = (self.held.len(), self.calibration.len());
        let percent = self.fraction * 100.0;
        if held < MIN_HELD_OUT {
            return Err(format!(
                "{} rows hold out only {held} at {percent:.3} %; at least {MIN_HELD_OUT} are \
                 needed for an error estimate",
                self.rows
            ));
        }
        if calibration < MIN_HELD_OUT {
            return Err(format!(
                "{} rows leave only {calibration} calibration rows at {:.3} %; at least \
                 {MIN_HELD_OUT} are needed to calibrate the held-out prediction",
                self.rows,
                self.calibration_fraction * 100.0
            ));
        }
        Ok(())
    }

    /// Keeps the held-out and calibration rows among `rows` (row-major, first row `first`).
    pub(super) fn add(&mut self, rows: &[f64], first: u64, m: usize) {
        let (f, g) = (self.fraction, self.fraction + self.calibration_fraction);
        for (i, c) in rows.chunks_exact(m).enumerate() {
            let row = first + i as u64;
            let key = self.key(row);
            if key < f {
                self.held.push(row);
                self.held_values.extend_from_slice(c);
            } else if key < g {
                self.calibration.push(row);
                self.calibration_values.extend_from_slice(c);
            }
        }
    }
}

/// Least-squares fit `c ~ gain (p . t_tr) + pattern_sum R + offset` of one channel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Calibration {
    pub(super) gain: f64,
    pub(super) pattern_sum: f64,
    pub(super) offset: f64,
}

impl Calibration {
    /// Fits on rows with features `u = p . t_tr`, `r = R` and buckets `c`. Solved on centred
    /// features (the common levels of u, R and c would swamp a raw 3 x 3 Gram system); a feature
    /// that is constant, or collinear with the other (e.g. `t_tr` proportional to 1 or 0), is
    /// dropped, u kept first. Always finite for finite input.
    pub(super) fn fit(u: &[f64], r: &[f64], c: &[f64]) -> Calibration {
        let n = c.len().max(1) as f64;
        let mean = |v: &[f64]| v.iter().sum::<f64>() / n;
        let (mu, mr, mc) = (mean(u), mean(r), mean(c));
        let (mut suu, mut srr, mut sur, mut suc, mut src) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for ((&u, &r), &c) in u.iter().zip(r).zip(c) {
            let (du, dr, dc) = (u - mu, r - mr, c - mc);
            suu += du * du;
            srr += dr * dr;
            sur += du * dr;
            suc += du * dc;
            src += dr * dc;
        }
        let det = suu * srr - sur * sur;
        let (gain, pattern_sum) = if suu > 0.0 && srr > 0.0 && det > 1e-9 * suu * srr {
            ((suc * srr - src * sur) / det, (src * suu - suc * sur) / det)
        } else if suu > 0.0 {
            (suc / suu, 0.0)
        } else if srr > 0.0 {
            (0.0, src / srr)
        } else {
            (0.0, 0.0)
        };
        Calibration {
            gain,
            pattern_sum,
            offset: mc - gain * mu - pattern_sum * mr,
        }
    }

    pub(super) fn predict(&self, u: f64, r: f64) -> f64 {
        self.gain * u + self.pattern_sum * r + self.offset
    }
}

/// The held-out estimate of one run.
pub(super) struct Estimate {
    pub(super) held_out: HeldOut,
    pub(super) calibration: Vec<Calibration>,
    /// Per channel, the training-only image.
    pub(super) training: Vec<Vec<f64>>,
}

/// The held-out estimate (module docs, "Held-out error"): training-only sums by subtracting the
/// held-out rows' share (computed by the kernel in `pool`, the spare workers) from `total`,
/// the training-only image, the calibration on C and the score on H. `Err`: why there is none.
pub(super) fn held_out_estimate(
    plan: &Plan,
    shift: &Shift,
    total: &Worker,
    mut pool: Vec<Worker>,
    record: &Recorded,
) -> Result<Estimate, String> {
    record.check()?;
    let m = plan.m;
    let (held, calibration) = (record.held.len(), record.calibration.len());

    // The held-out rows' share of every sum, spread over the spare workers.
    if pool.is_empty() {
        // One worker ran the pass (one thread, or the memory budget): one more is needed.
        if 2 * plan.worker_bytes > MEMORY_BUDGET {
            return Err(format!(
                "the held-out estimate needs a second set of accumulators ({} MiB), over the \
                 memory budget",
                plan.worker_bytes >> 20
            ));
        }
        pool.push(Worker::new(plan));
    } else {
        pool.iter_mut().for_each(Worker::reset);
    }
    let granule = if plan.binary { BATCH } else { GREY_BATCH };
    let per = held.div_ceil(pool.len()).div_ceil(granule) * granule;
    let parts = held.div_ceil(per);
    pool[..parts]
        .par_iter_mut()
        .enumerate()
        .for_each(|(w, worker)| {
            let (lo, hi) = (w * per, ((w + 1) * per).min(held));
            worker.process_rows(
                plan,
                shift,
                &record.held_values[lo * m..hi * m],
                &record.held[lo..hi],
            );
        });
    pool.truncate(parts);
    let mut train = pool.swap_remove(0);
    for w in &pool {
        train.merge(w);
    }
    drop(pool);
    train.complement_in(total);
    let training: Vec<Vec<f64>> = (0..m).map(|ch| train.image(plan, ch).collect()).collect();
    drop(train);

    // Features R and p . t_tr of the calibration rows, then the held-out rows.
    let rows: Vec<u64> = record
        .calibration
        .iter()
        .chain(&record.held)
        .copied()
        .collect();
    let features = row_features(plan, &training, &rows);
    let (fc, fh) = features.split_at(calibration * (m + 1));
    let feature = |f: &[f64], i: usize, ch: usize| f[i * (m + 1) + 1 + ch];
    let r_c: Vec<f64> = (0..calibration).map(|i| fc[i * (m + 1)]).collect();
    let mut score = Score::new(m);
    let fits: Vec<Calibration> = (0..m)
        .map(|ch| {
            let u: Vec<f64> = (0..calibration).map(|i| feature(fc, i, ch)).collect();
            let c: Vec<f64> = (0..calibration)
                .map(|i| record.calibration_values[i * m + ch])
                .collect();
            Calibration::fit(&u, &r_c, &c)
        })
        .collect();
    for i in 0..held {
        let r = fh[i * (m + 1)];
        for (ch, fit) in fits.iter().enumerate() {
            score.add(
                ch,
                record.held_values[i * m + ch],
                fit.predict(feature(fh, i, ch), r),
            );
        }
    }
    Ok(Estimate {
        held_out: score.finish(record.fraction),
        calibration: fits,
        training,
    })
}

/// Rows per task in [`row_features`]: the binary path streams every nibble table once per this
/// many rows (the tables, 32 bytes per pixel and channel, do not fit in cache).
const FEATURE_ROWS: usize = 32;

/// For each row of `rows`: `R`, then `p . t[ch]` for every channel (`m + 1` values per row,
/// row-major). Patterns are regenerated; rows are spread over the rayon threads.
fn row_features(plan: &Plan, t: &[Vec<f64>], rows: &[u64]) -> Vec<f64> {
    let (m, nw, k) = (plan.m, plan.nw, plan.k);
    // Binary: per channel, a table of the 16 subset sums of t over each nibble of pixels.
    let tables: Vec<Vec<[f64; 16]>> = if plan.binary {
        t.iter().map(|t| nibble_table(t, nw)).collect()
    } else {
        Vec::new()
    };
    let mut out = vec![0.0; rows.len() * (m + 1)];
    let chunks = out
        .par_chunks_mut((m + 1) * FEATURE_ROWS)
        .zip(rows.par_chunks(FEATURE_ROWS));
    chunks.for_each(|(out, rows)| {
        if plan.binary {
            let mut bits = vec![0u64; rows.len() * nw];
            for ((words, f), &row) in bits
                .chunks_exact_mut(nw)
                .zip(out.chunks_exact_mut(m + 1))
                .zip(rows)
            {
                plan.generator.fill_bits(row, words).expect("binary family");
                f[0] = count_ones(words, plan.popcnt) as f64;
            }
            let mut dots = vec![0.0; rows.len()];
            for (ch, table) in tables.iter().enumerate() {
                dot_bits(&bits, nw, table, &mut dots);
                for (f, &d) in out.chunks_exact_mut(m + 1).zip(&dots) {
                    f[1 + ch] = d;
                }
            }
        } else {
            let mut values = vec![0f32; k];
            for (f, &row) in out.chunks_exact_mut(m + 1).zip(rows) {
                plan.generator.fill_values(row, &mut values);
                f[0] = sum_values(&values);
                for (v, t) in f[1..].iter_mut().zip(t) {
                    *v = dot_values(&values, t);
                }
            }
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calibration_recovers_an_exact_fit_and_survives_collinearity() {
        let u: Vec<f64> = (0..50).map(|i| ((i * 37) % 11) as f64 + 1e6).collect();
        let r: Vec<f64> = (0..50).map(|i| ((i * 13) % 7) as f64 + 500.0).collect();
        let c: Vec<f64> = u
            .iter()
            .zip(&r)
            .map(|(u, r)| 2.0 * u - 3.0 * r + 7.0)
            .collect();
        let fit = Calibration::fit(&u, &r, &c);
        for (i, (&u, &r)) in u.iter().zip(&r).enumerate() {
            assert!((fit.predict(u, r) - c[i]).abs() < 1e-6, "{fit:?}");
        }
        assert!((fit.gain - 2.0).abs() < 1e-9 && (fit.pattern_sum + 3.0).abs() < 1e-9);
        // u proportional to R: one of them carries the fit.
        let u2: Vec<f64> = r.iter().map(|r| 0.5 * r).collect();
        let c2: Vec<f64> = r.iter().map(|r| 4.0 * r + 1.0).collect();
        let fit = Calibration::fit(&u2, &r, &c2);
        assert!(fit.gain.is_finite() && fit.pattern_sum.is_finite() && fit.offset.is_finite());
        for (i, (&u, &r)) in u2.iter().zip(&r).enumerate() {
            assert!((fit.predict(u, r) - c2[i]).abs() < 1e-9, "{fit:?}");
        }
        // Nothing varies: the mean.
        let fit = Calibration::fit(&[1.0; 4], &[2.0; 4], &[3.0; 4]);
        assert_eq!(
            fit,
            Calibration {
                gain: 0.0,
                pattern_sum: 0.0,
                offset: 3.0
            }
        );
    }
}
