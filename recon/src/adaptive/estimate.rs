//! The `measured` error estimate of an adaptive planner (`proto/PATTERNS.md`, "The planner",
//! "Error estimate"): the relative L2 error of the zero-filled image once every issued pair is
//! observed, from three measured parts instead of the prediction alone.
//!
//! - **Noise.** A split pair's sum `y+ + y-` is the light on the basis function's support, the
//!   same for every pair of one support but for noise; its difference `y+ - y-` carries the same
//!   noise variance (independent frames). So the spread of the sums within each support group
//!   (Walsh-Hadamard: every pair lights the whole grid; Haar: the three details of one block, and
//!   the mean with the three coarsest) measures the noise of every coefficient shown. Pooled per
//!   support size when that size has at least [`MIN_SIZE_DOF`] degrees of freedom (shot noise
//!   grows with the support's light), else over all sizes.
//! - **Prediction and miss.** A level-`l` prediction `p` is a function of the coarser levels
//!   only, so every measured coefficient `v` of level `l` is an honest sample of how the
//!   coefficients relate to their predictions. Per level (with at least [`MIN_LEVEL`] samples):
//!   the least-squares slope `a = sum v p / sum p^2` (at least 0; the bicubic guess can be too
//!   smooth, `a > 1`, or see edges that are not there, `a < 1`: on a piecewise-constant scene its
//!   ringing is all miss and `a = 0`), and the mean squared miss `(v - a p)^2 - noise`. An
//!   unmeasured coefficient counts `(a p)^2` plus its level's mean miss; finer levels without
//!   enough samples take the next coarser level's mean miss times the decay of the two finest
//!   measured levels (in `[1/16, 1]`), and no level takes more than the next coarser one.
//! - **Signal.** The denominator is the energy of the measured coefficients that stand clear of
//!   their noise (`v^2 > 25 noise`, each less its noise) and the mean's, not the raw energy, which
//!   under noise is mostly noise.
//!
//! Measured against the truth by `bench --preset adaptive` (docs/benchmarks-adaptive.md).

use super::Basis;

/// Degrees of freedom a support size needs before its own noise variance is used.
pub const MIN_SIZE_DOF: u64 = 32;
/// Measured coefficients a level needs before its mean miss is used.
pub const MIN_LEVEL: u64 = 8;
/// A measured coefficient counts as signal when its square exceeds this many noise variances.
pub const SIGNAL_CLEAR: f64 = 25.0;

/// Running state of the estimate (O(k (channels + 1)) memory for Haar, O(k) for Walsh-Hadamard).
#[derive(Debug)]
pub(super) struct Measured {
    channels: usize,
    /// Per index: its support group and its support size `s` (side `2^s`; the gain is `2^s`).
    group: Vec<u32>,
    size: Vec<u8>,
    /// Pairs observed per support group.
    count: Vec<u32>,
    /// Per channel and group (`ch * groups + g`): running mean of the pair sums.
    mean: Vec<f64>,
    groups: usize,
    /// Per channel and size (`ch * sizes + s`): pooled squared deviations of the sums from their
    /// group's running mean; per size: their degrees of freedom.
    squares: Vec<f64>,
    dof: Vec<u64>,
    sizes: usize,
    /// Per index: observed.
    observed: Vec<bool>,
}

impl Measured {
    pub fn new(basis: Basis, width: u32, channels: usize) -> Measured {
        let k = width as usize * width as usize;
        let m = width.trailing_zeros();
        let (group, size): (Vec<u32>, Vec<u8>) = (0..k as u32)
            .map(|n| match basis {
                Basis::Hadamard => (0, m as u8),
                Basis::Haar => {
                    let f = helmholtz_proto::HaarFunction::new(width, n);
                    let h = width >> f.scale;
                    let (pr, pc) = (f.y0 >> f.scale, f.x0 >> f.scale);
                    (h * h + pr * h + pc, f.scale as u8)
                }
            })
            .unzip();
        let groups = group.iter().map(|&g| g as usize + 1).max().unwrap_or(1);
        let sizes = m as usize + 1;
        Measured {
            channels,
            group,
            size,
            count: vec![0; groups],
            mean: vec![0.0; groups * channels],
            groups,
            squares: vec![0.0; sizes * channels],
            dof: vec![0; sizes],
            sizes,
            observed: vec![false; k],
        }
    }

    /// One observed pair showing index `n`: `sum(ch)` = `y+ + y-` of channel `ch`.
    pub fn observe(&mut self, n: u32, sum: impl Fn(usize) -> f64) {
        let n = n as usize;
        let g = self.group[n] as usize;
        let s = self.size[n] as usize;
        let c = self.count[g];
        for ch in 0..self.channels {
            let t = sum(ch);
            let mean = &mut self.mean[ch * self.groups + g];
            let old = *mean;
            *mean = old + (t - old) / (c as f64 + 1.0);
            if c > 0 {
                self.squares[ch * self.sizes + s] += (t - old) * (t - *mean);
            }
        }
        if c > 0 {
            self.dof[s] += 1;
        }
        self.count[g] = c + 1;
        self.observed[n] = true;
    }

    /// Noise variance of one pair difference `y+ - y-` of channel `ch` and support size `s`
    /// (0 before any support was shown twice).
    pub fn pair_variance(&self, ch: usize, s: usize) -> f64 {
        if self.dof[s] >= MIN_SIZE_DOF {
            return self.squares[ch * self.sizes + s] / self.dof[s] as f64;
        }
        let (mut squares, mut dof) = (0.0, 0u64);
        for t in 0..self.sizes {
            squares += self.squares[ch * self.sizes + t];
            dof += self.dof[t];
        }
        if dof > 0 { squares / dof as f64 } else { 0.0 }
    }

    /// The pair-difference noise variance of channel `ch` pooled over every support size, with
    /// its degrees of freedom; `None` before any support was shown twice.
    pub fn pooled_pair_variance(&self, ch: usize) -> Option<(f64, u64)> {
        let dof: u64 = self.dof.iter().sum();
        let squares: f64 = self.squares[ch * self.sizes..(ch + 1) * self.sizes]
            .iter()
            .sum();
        (dof > 0).then(|| (squares / dof as f64, dof))
    }

    /// The squared relative error of channel `ch`: `values` its observed coefficients (0 where
    /// not observed), `pred` their predictions, `energy` the summed squares of the observed
    /// coefficients.
    pub fn relative_squared(
        &self,
        ch: usize,
        values: &[f64],
        pred: &[f64],
        issued: &[bool],
        level: &[u8],
        energy: f64,
    ) -> f64 {
        let k = values.len();
        // Coefficient noise variance per support size: the pair's over the gain 2^s squared.
        let var: Vec<f64> = (0..self.sizes)
            .map(|s| self.pair_variance(ch, s) / (4f64).powi(s as i32))
            .collect();
        let levels = self.sizes; // levels 0 ..= m; level m is the mean alone
        // Per level, the least-squares slope of the measured values on their predictions.
        let mut vp = vec![0.0; levels];
        let mut pp = vec![0.0; levels];
        let mut seen = vec![0u64; levels];
        let mut noise = 0.0;
        let mut signal = values[0] * values[0];
        for n in 1..k {
            let v_n = var[self.size[n] as usize];
            if issued[n] {
                noise += v_n;
            }
            if self.observed[n] {
                let l = level[n] as usize;
                vp[l] += values[n] * pred[n];
                pp[l] += pred[n] * pred[n];
                seen[l] += 1;
                let v2 = values[n] * values[n];
                if v2 > SIGNAL_CLEAR * v_n {
                    signal += v2 - v_n;
                }
            }
        }
        let slope: Vec<f64> = (0..levels)
            .map(|l| {
                if seen[l] >= MIN_LEVEL && pp[l] > 0.0 {
                    (vp[l] / pp[l]).max(0.0)
                } else {
                    1.0
                }
            })
            .collect();
        let mut miss = vec![0.0; levels];
        for n in 1..k {
            if self.observed[n] {
                let l = level[n] as usize;
                let d = values[n] - slope[l] * pred[n];
                miss[l] += d * d - var[self.size[n] as usize];
            }
        }
        let tau = level_misses(&miss, &seen);
        let mut fill = 0.0;
        for n in 1..k {
            if !issued[n] {
                let l = level[n] as usize;
                let p = slope[l] * pred[n];
                fill += p * p + tau[l];
            }
        }
        let signal = if signal > 0.0 { signal } else { energy };
        (fill + noise) / signal
    }

    pub fn memory_bytes(&self) -> usize {
        self.group.len() * (4 + 1 + 1)
            + 4 * self.count.len()
            + 8 * (self.mean.len() + self.squares.len() + self.dof.len())
    }
}

/// The mean squared miss added per unmeasured coefficient of each level `0 ..= m` (`m` the mean's
/// level, always 0), from the per-level sums `miss` over `seen` measured coefficients (module
/// docs).
pub(super) fn level_misses(miss: &[f64], seen: &[u64]) -> Vec<f64> {
    let levels = miss.len();
    let mut tau = vec![0.0; levels];
    if levels < 2 {
        return tau;
    }
    let resolved = |l: usize| (seen[l] >= MIN_LEVEL).then(|| (miss[l] / seen[l] as f64).max(0.0));
    // The decay between the two finest resolved levels.
    let mut fine = (0..levels - 1).filter_map(|l| resolved(l).map(|t| (l, t)));
    let rho = match (fine.next(), fine.next()) {
        (Some((_, a)), Some((_, b))) if b > 0.0 => (a / b).clamp(1.0 / 16.0, 1.0),
        _ => 0.25,
    };
    let mut above: Option<f64> = None;
    for l in (0..levels - 1).rev() {
        let own = resolved(l);
        let t = match (own, above) {
            (Some(t), Some(a)) => t.min(a),
            (Some(t), None) => t,
            (None, Some(a)) => a * rho,
            (None, None) if seen[l] > 0 => (miss[l] / seen[l] as f64).max(0.0),
            (None, None) => 0.0,
        };
        if own.is_some() || above.is_some() {
            above = Some(t);
        }
        tau[l] = t;
    }
    tau
}
