//! Held-out rows: the error estimate every reconstruction reports, and what `auto` chooses by.
//!
//! A fixed, seed-free subset of the rows (patterns; for Hadamard split pairs, pairs) is left out
//! of a fit, and the fit's prediction of those buckets is scored by the **held-out relative
//! residual**
//!
//! `rho = ||c_H - c_hat_H|| / ||c_H - mean(c_H)||`
//!
//! over the held-out rows `H` (all channels pooled). The denominator is the spread of the held-out
//! buckets, not their size: 0/1 patterns put a huge common level into every bucket, and a
//! residual relative to `||c_H||` would look small for any image with the right mean. So
//! `rho = 1` means "no better than predicting the mean bucket", `rho = 0` a perfect prediction;
//! with measurement noise of variance `s^2` a perfect image scores about
//! `s / std(c_H)` (the noise floor), so `rho` estimates the image's error plus the noise.
//! Compare `rho` between methods on the same session, not across sessions: with 0/1 patterns
//! even the flat image `t = mean(t)` explains part of the spread (the pattern sums vary), so
//! the "no information" level is below 1 (about `sqrt(1 - ||mean(t)||^2 / ||t||^2)` for
//! Bernoulli(1/2)).
//!
//! Which rows are held out depends only on the row index (a SplitMix64 hash), so the same rows
//! are held out in every run, whatever the block sizes or the number of threads, and for
//! every method; and hashing, unlike every-tenth-row, does not alias with pattern orderings.

use helmholtz_proto::patterns::rng::stream_word;

/// Default fraction of rows held out (raised for small sessions, [`default_fraction`]).
pub const DEFAULT_FRACTION: f64 = 0.1;

/// The fraction held out when the request does not say: 10 %, raised up to 25 % so that small
/// sessions still hold out about 16 rows (a usable estimate) where they can.
pub fn default_fraction(rows: usize) -> f64 {
    (16.0 / rows.max(1) as f64).clamp(DEFAULT_FRACTION, 0.25)
}
/// The fraction `auto` holds out when the noise is `relative_noise` of the data's spread (the
/// session's own estimate, [`NoiseEstimate::relative`](crate::noise::NoiseEstimate::relative)):
/// [`DEFAULT_FRACTION`] up to half the spread, rising linearly to [`NOISY_FRACTION`] where the
/// noise is all of it. Two fits' held-out scores differ by noise of standard deviation
/// `2 sigma ||prediction difference|| / n` over `n` held-out rows; at 30 dB of the total bucket
/// power on Bernoulli rows (noise ~95 % of the spread) 10 % of 1,638 rows left fits 6-7 dB apart
/// indistinguishable (measured), while the fits themselves need fewer rows there (the weights
/// that noise asks for are heavy, and the served image is refitted on all rows).
pub fn noisy_fraction(relative_noise: f64) -> f64 {
    let r = ((relative_noise - 0.5) / 0.5).clamp(0.0, 1.0);
    DEFAULT_FRACTION + r * (NOISY_FRACTION - DEFAULT_FRACTION)
}
/// The most `auto` holds out of its own accord ([`noisy_fraction`]).
pub const NOISY_FRACTION: f64 = 0.5;
/// Fewer held-out rows than this give no usable estimate (the estimate of `rho` has a relative
/// standard error of about `1 / sqrt(2 |H|)`).
pub const MIN_HELD_OUT: usize = 8;
/// Salt of the hash that selects the rows (any constant; fixed forever so reports stay
/// comparable).
const SALT: u64 = 0x4845_4c44_4f55_5421; // "HELDOUT!"

/// The hash key of row `i` as a fraction in [0, 1).
pub fn key(i: u64) -> f64 {
    (stream_word(SALT, i) >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Whether row `i` is held out at `fraction`.
pub fn is_held_out(i: u64, fraction: f64) -> bool {
    key(i) < fraction
}

/// Rows `0..rows` split into the fitted (`train`) and held-out (`test`) rows, both increasing.
#[derive(Clone, Debug, PartialEq)]
pub struct Split {
    pub fraction: f64,
    pub train: Vec<usize>,
    pub test: Vec<usize>,
}

/// Splits `rows` rows, holding out `fraction` of them. `Err` says why no estimate is possible:
/// fewer than [`MIN_HELD_OUT`] held-out rows, or nothing left to fit.
pub fn split(rows: usize, fraction: f64) -> Result<Split, String> {
    let (mut train, mut test) = (Vec::with_capacity(rows), Vec::new());
    for i in 0..rows {
        if is_held_out(i as u64, fraction) {
            test.push(i);
        } else {
            train.push(i);
        }
    }
    if test.len() < MIN_HELD_OUT {
        return Err(format!(
            "{rows} rows hold out only {} at {:.0} %; at least {MIN_HELD_OUT} are needed for an error estimate",
            test.len(),
            fraction * 100.0
        ));
    }
    if train.len() < MIN_HELD_OUT {
        return Err(format!(
            "{rows} rows leave only {} to fit after holding out {}",
            train.len(),
            test.len()
        ));
    }
    Ok(Split {
        fraction,
        train,
        test,
    })
}

/// Rows `0..rows` split so that the held-out rows are the LAST `fraction` of them (at least
/// [`MIN_HELD_OUT`]): for ordered designs (Hadamard subsets taken in sequency or Russian-doll
/// order) the rows a session did not measure lie beyond the measured ones, so a model is judged
/// by how well it predicts measured rows beyond those it was fitted on, which is the task the
/// unmeasured rows set it. (Randomly held-out rows of such a design lie among the fitted ones and
/// are predicted well by any model that fits, whatever it does with the unmeasured rows.)
pub fn tail(rows: usize, fraction: f64) -> Result<Split, String> {
    let test_len = ((rows as f64 * fraction).round() as usize).max(MIN_HELD_OUT);
    if test_len + MIN_HELD_OUT > rows {
        return Err(format!(
            "{rows} rows cannot hold out the last {test_len} and still leave {MIN_HELD_OUT} to fit"
        ));
    }
    let cut = rows - test_len;
    Ok(Split {
        fraction: test_len as f64 / rows as f64,
        train: (0..cut).collect(),
        test: (cut..rows).collect(),
    })
}

/// Accumulates `||c - c_hat||^2` and the centred `||c - mean(c)||^2` over held-out rows, per
/// channel (Welford-free: two-pass is not possible when streaming, so the spread is accumulated
/// around the first value seen, which is exact in exact arithmetic and avoids the cancellation
/// of `sum c^2 - n mean^2` when the buckets share a large common level).
#[derive(Clone, Debug, Default)]
pub struct Score {
    rows: usize,
    residual2: Vec<f64>,
    /// Per channel: reference value, sum of (c - ref), sum of (c - ref)^2.
    reference: Vec<Option<f64>>,
    sum: Vec<f64>,
    sum2: Vec<f64>,
}

impl Score {
    pub fn new(channels: usize) -> Self {
        Score {
            rows: 0,
            residual2: vec![0.0; channels],
            reference: vec![None; channels],
            sum: vec![0.0; channels],
            sum2: vec![0.0; channels],
        }
    }

    /// Adds one held-out row's observed and predicted value of channel `ch` (call once per
    /// channel per row; rows are counted on channel 0).
    pub fn add(&mut self, ch: usize, observed: f64, predicted: f64) {
        if ch == 0 {
            self.rows += 1;
        }
        let r = observed - predicted;
        self.residual2[ch] += r * r;
        let reference = *self.reference[ch].get_or_insert(observed);
        let d = observed - reference;
        self.sum[ch] += d;
        self.sum2[ch] += d * d;
    }

    /// Adds a whole channel's held-out rows at once.
    pub fn add_channel(&mut self, ch: usize, observed: &[f64], predicted: &[f64]) {
        assert_eq!(observed.len(), predicted.len());
        for (&o, &p) in observed.iter().zip(predicted) {
            self.add(ch, o, p);
        }
    }

    fn spread2(&self, ch: usize) -> f64 {
        let n = self.rows.max(1) as f64;
        (self.sum2[ch] - self.sum[ch] * self.sum[ch] / n).max(0.0)
    }

    /// The report; `fraction` is the fraction held out.
    pub fn finish(&self, fraction: f64) -> HeldOut {
        let ratio = |num: f64, den: f64| -> Option<f64> {
            if num == 0.0 {
                Some(0.0)
            } else if den > 0.0 {
                Some((num / den).sqrt())
            } else {
                None
            }
        };
        let channels = self.residual2.len();
        let per_channel = (0..channels)
            .map(|ch| ratio(self.residual2[ch], self.spread2(ch)))
            .collect();
        let num: f64 = self.residual2.iter().sum();
        let den: f64 = (0..channels).map(|ch| self.spread2(ch)).sum();
        HeldOut {
            rows: self.rows,
            fraction,
            relative_residual: ratio(num, den),
            per_channel,
            rms_residual: (num / (self.rows.max(1) * channels.max(1)) as f64).sqrt(),
        }
    }
}

/// The held-out error estimate as reported (`Report::held_out`): the contract's type.
pub use helmholtz_proto::rest::HeldOut;

/// `||obs - pred|| / ||obs - mean(obs)||` of one vector (see the module docs); `None` as in
/// [`HeldOut::relative_residual`].
pub fn relative_residual(observed: &[f64], predicted: &[f64]) -> Option<f64> {
    let mut s = Score::new(1);
    s.add_channel(0, observed, predicted);
    s.finish(0.0).relative_residual
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_is_deterministic_disjoint_and_near_the_fraction() {
        let s = split(20_000, 0.1).unwrap();
        assert_eq!(s.train.len() + s.test.len(), 20_000);
        let held = s.test.len() as f64 / 20_000.0;
        // Binomial: sd = sqrt(0.09 / 20000) = 0.0021; 5 sd.
        assert!((held - 0.1).abs() < 0.011, "held out {held}");
        assert_eq!(s, split(20_000, 0.1).unwrap());
        let mut all: Vec<usize> = s.train.iter().chain(&s.test).copied().collect();
        all.sort_unstable();
        assert!(all.iter().enumerate().all(|(i, &v)| i == v));
        // A prefix of the rows holds out the same rows (a grown session keeps its held-out rows).
        let prefix = split(5_000, 0.1).unwrap();
        assert_eq!(
            prefix.test,
            s.test
                .iter()
                .copied()
                .filter(|&i| i < 5_000)
                .collect::<Vec<_>>()
        );
        // Unrelated to parity (Hadamard frames come in pairs; orderings have structure).
        let odd = s.test.iter().filter(|&&i| i % 2 == 1).count() as f64 / s.test.len() as f64;
        assert!((odd - 0.5).abs() < 0.05, "odd share {odd}");
    }

    #[test]
    fn tail_holds_out_the_last_rows() {
        let s = tail(1000, 0.1).unwrap();
        assert_eq!(s.test, (900..1000).collect::<Vec<_>>());
        assert_eq!(s.train, (0..900).collect::<Vec<_>>());
        // At least MIN_HELD_OUT rows, and something left to fit.
        assert_eq!(tail(40, 0.1).unwrap().test.len(), MIN_HELD_OUT);
        assert!(tail(15, 0.1).is_err());
    }

    #[test]
    fn too_few_rows_is_said() {
        let e = split(20, 0.1).unwrap_err();
        assert!(e.contains("at least 8"), "{e}");
        assert!(split(100, 0.999).is_err());
    }

    #[test]
    fn residual_is_relative_to_the_spread_not_the_level() {
        let level = 1e9;
        let obs: Vec<f64> = (0..100).map(|i| level + (i % 7) as f64).collect();
        let mean = obs.iter().sum::<f64>() / 100.0;
        // Predicting the mean scores 1, however large the common level.
        let flat = vec![mean; 100];
        assert!((relative_residual(&obs, &flat).unwrap() - 1.0).abs() < 1e-6);
        assert_eq!(relative_residual(&obs, &obs), Some(0.0));
        let half: Vec<f64> = obs.iter().map(|&o| mean + 0.5 * (o - mean)).collect();
        assert!((relative_residual(&obs, &half).unwrap() - 0.5).abs() < 1e-6);
        // All-dark: exact prediction is 0, a wrong one has no scale.
        assert_eq!(relative_residual(&[0.0; 10], &[0.0; 10]), Some(0.0));
        assert_eq!(relative_residual(&[0.0; 10], &[1.0; 10]), None);
    }

    #[test]
    fn channels_pool() {
        let mut s = Score::new(2);
        for i in 0..10 {
            let o = i as f64;
            s.add(0, o, o);
            s.add(1, o, 4.5);
        }
        let h = s.finish(0.1);
        assert_eq!(h.rows, 10);
        assert_eq!(h.per_channel[0], Some(0.0));
        assert!((h.per_channel[1].unwrap() - 1.0).abs() < 1e-12);
        assert!((h.relative_residual.unwrap() - 0.5f64.sqrt()).abs() < 1e-12);
    }
}
