//! The detector noise the data show, estimated from the session itself.
//!
//! - **Hadamard split pairs.** A pair shows `P+ = (1 + h)/2` and `P- = (1 - h)/2`, so
//!   `P+ + P- = 1` for every pair: the pair sums `s_r = y+ + y- = 1 . t + 2 dark` carry no image
//!   information and vary only by noise (and slow source drift). With independent frames
//!   `Var(y+ - y-) = Var(y+) + Var(y-) = Var(y+ + y-)`, for read noise (constant variance) and for
//!   shot noise alike (`Var(y) ~ g E[y]`, and `E[y+] + E[y-] = E[s]` is the same for every pair),
//!   so the spread of the sums *is* the noise of the differences the solvers fit. Drift is
//!   removed by differencing consecutive sums, and outliers by the median:
//!   `sigma_s = 1.4826 median|s_{r+1} - s_r| / sqrt(2)`; the data `d_r = (y+ - y-) / sqrt(k)` then
//!   have `sigma = sigma_s / sqrt(k)`.
//! - **Bernoulli patterns** (i.i.d. entries, fill `p`, variance `v = p (1 - p)`): with centred
//!   buckets `c_i = b_i - mean(b)` and centred rows `a~_i = a_i - p 1`,
//!   `E[c_i^2] = v ||t||^2 + sigma^2`, while for two different rows the noise is independent and
//!   `E[c_i c_j a~_i . a~_j] = v^2 ||t||^2`. Summed over all pairs `i != j`,
//!   `S = ||A~^T c||^2 - sum_i c_i^2 ||a~_i||^2` estimates `n (n - 1) v^2 ||t||^2` with no noise
//!   in it (method of moments; one adjoint product), so
//!   `sigma^2 = mean(c^2) - S / (n (n - 1) v)`. It is unbiased; its spread is largest when the
//!   noise is small against the image's own bucket spread (then the estimate is small and
//!   imprecise, but so is what it corrects), and it is reported with its standard error (the
//!   jackknife over rows: one more product).

use serde::Serialize;

use super::linop::LinearOperator;

/// One channel's noise estimate, in the units of the data the solvers fit (Hadamard: the
/// split-pair differences over `sqrt(k)`; Bernoulli: the buckets).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct NoiseEstimate {
    /// Standard deviation of one datum's noise.
    pub sigma: f64,
    /// Its standard error (sampling spread of the estimate itself).
    pub standard_error: f64,
    /// The data's own spread (standard deviation of the data about their mean), for scale.
    pub data_spread: f64,
    /// How it was estimated.
    pub source: &'static str,
    /// Rows (pairs) it used.
    pub rows: usize,
}

impl NoiseEstimate {
    /// The noise there surely is: `sigma` less two standard errors, at least 0. Decisions that
    /// trust the data less the noisier they are ([`auto`](crate::auto)) use this, so that an
    /// imprecise estimate on noise-free data (a peaky scene makes the Bernoulli moments noisy)
    /// does not make them timid.
    pub fn lower(&self) -> f64 {
        (self.sigma - 2.0 * self.standard_error).max(0.0)
    }

    /// [`lower`](Self::lower)` / data_spread`: 0 noise-free, 1 when the noise is all the data
    /// vary by.
    pub fn relative(&self) -> f64 {
        if self.data_spread > 0.0 {
            self.lower() / self.data_spread
        } else {
            0.0
        }
    }
}

impl NoiseEstimate {
    /// A noise the user declares (`auto`'s `read_noise`), in the data's units: exact as far as
    /// the estimate goes (standard error 0).
    pub fn declared(sigma: f64, data: &[f64]) -> NoiseEstimate {
        NoiseEstimate {
            sigma,
            standard_error: 0.0,
            data_spread: spread(data),
            source: DECLARED,
            rows: data.len(),
        }
    }
}

/// The `source` of a declared noise.
pub const DECLARED: &str = "declared by the request (read_noise)";

impl SupportNoise {
    /// A declared read noise `sigma` per frame: a split pair's `y+ - y-` has the variance
    /// `2 sigma^2`, known exactly (degrees of freedom as good as unlimited).
    pub fn declared(sigma: f64) -> SupportNoise {
        SupportNoise {
            pair_variance: 2.0 * sigma * sigma,
            dof: 1 << 40,
            groups: 0,
            source: DECLARED,
        }
    }
}

/// `1 / Phi^-1(3/4)`: the median absolute value of a standard normal times this is 1.
const MAD_TO_SIGMA: f64 = 1.482_602_218_505_602;

fn spread(x: &[f64]) -> f64 {
    let n = x.len().max(1) as f64;
    let mean = x.iter().sum::<f64>() / n;
    (x.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n).sqrt()
}

/// From Hadamard split-pair sums (see the module docs); `scale` maps a pair difference to the
/// solvers' datum (`1 / sqrt(k)`), `data` are those data (for the spread). `None` with fewer than
/// 3 pairs.
pub fn from_pair_sums(sums: &[f64], scale: f64, data: &[f64]) -> Option<NoiseEstimate> {
    if sums.len() < 3 {
        return None;
    }
    let mut d: Vec<f64> = sums.windows(2).map(|w| (w[1] - w[0]).abs()).collect();
    let mid = d.len() / 2;
    let (_, median, _) = d.select_nth_unstable_by(mid, f64::total_cmp);
    let sigma_s = MAD_TO_SIGMA * *median / std::f64::consts::SQRT_2;
    // The MAD of n Gaussian values has a relative standard error of about 1.17 / sqrt(n)
    // (consecutive differences are correlated; counted as n / 1.5 independent ones).
    let n_eff = (sums.len() as f64 - 1.0) / 1.5;
    let sigma = sigma_s * scale;
    Some(NoiseEstimate {
        sigma,
        standard_error: sigma * 1.17 / n_eff.sqrt(),
        data_spread: spread(data),
        source: "hadamard pair sums (y+ + y- is the same for every pair but for noise)",
        rows: sums.len(),
    })
}

/// The noise of split pairs whose patterns light supports of different sizes (the adaptive
/// families: a Haar function lights its `2^s x 2^s` block, a Walsh-Hadamard function the whole
/// grid). Pairs with the same support see the same light, `y+ + y- = <support, t> + 2 dark`, so
/// within a group of one support the sums differ by noise alone; their pooled variance is that of
/// one pair sum, which (independent frames, read noise) is also that of `y+ - y-`. The datum
/// `(y+ - y-) / g` of a pair with gain `g` then has the variance `pair_variance / g^2`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SupportNoise {
    /// Variance of one pair's `y+ + y-` (and `y+ - y-`): twice a frame's.
    pub pair_variance: f64,
    /// Degrees of freedom of the estimate: pairs less groups, over the groups of two or more.
    pub dof: usize,
    /// Supports shown by two or more pairs.
    pub groups: usize,
    pub source: &'static str,
}

impl SupportNoise {
    /// Relative standard error of [`pair_variance`](Self::pair_variance) (Gaussian noise:
    /// `sqrt(2 / dof)`).
    pub fn relative_standard_error(&self) -> f64 {
        (2.0 / self.dof.max(1) as f64).sqrt()
    }
}

impl SupportNoise {
    /// From a [`from_pair_sums`] estimate whose data are `(y+ - y-) * scale`: every pair lights
    /// the same support (Walsh-Hadamard pairs light the whole grid), and the median of the
    /// consecutive sums' differences ignores source drift, which a pooled spread would count as
    /// noise. `dof` is the one whose Gaussian `sqrt(2 / dof)` is the estimate's relative standard
    /// error as a variance (twice that of `sigma`).
    pub fn from_pair_estimate(e: &NoiseEstimate, scale: f64) -> SupportNoise {
        let relative = if e.sigma > 0.0 {
            2.0 * e.standard_error / e.sigma
        } else {
            0.0
        };
        let dof = if relative > 0.0 {
            (2.0 / (relative * relative)).round().max(1.0) as usize
        } else {
            e.rows.saturating_sub(1).max(1)
        };
        SupportNoise {
            pair_variance: (e.sigma / scale).powi(2),
            dof,
            groups: 1,
            source: "the drift-free spread of the pair sums y+ + y- (every pair lights the whole grid)",
        }
    }
}

/// The support key and gain of `adaptive_haar` function `n` on a `width`-wide grid, for
/// [`from_support_groups`]: pairs of equal keys light the same block (siblings; the scaling
/// function and the coarsest details), so their sums `y+ + y-` differ by noise alone; the gain
/// is the support's side `2^s` (the pair's `y+ - y-` over it is the orthonormal coefficient).
pub fn haar_support(width: u32, n: u32) -> (u64, f64) {
    let f = helmholtz_proto::HaarFunction::new(width, n);
    (
        ((f.scale as u64) << 48) | ((f.y0 as u64) << 24) | f.x0 as u64,
        (1u64 << f.scale) as f64,
    )
}

/// The share of a linear inverse's variation about its mean that is noise: `noise` (the summed
/// noise variances of the measured coefficients other than the mean) over `energy` (those
/// coefficients' summed squares, noise included). About 0 noise-free, 1 when the image varies by
/// its noise alone; it can read above 1 where the noise estimate is high by chance. `None` when
/// nothing but the mean was measured.
pub fn noise_share(noise: f64, energy: f64) -> Option<f64> {
    (energy > 0.0 && noise.is_finite()).then(|| noise / energy)
}

/// [`SupportNoise`] from the pairs' sums `y+ + y-` and a key per pair that is equal exactly for
/// pairs of the same support. `None` when no support was shown twice.
pub fn from_support_groups(sums: &[f64], support: &[u64]) -> Option<SupportNoise> {
    let mut order: Vec<usize> = (0..sums.len().min(support.len())).collect();
    order.sort_by_key(|&r| support[r]);
    let (mut squares, mut dof, mut groups) = (0.0, 0usize, 0usize);
    for group in order.chunk_by(|&a, &b| support[a] == support[b]) {
        if group.len() < 2 {
            continue;
        }
        let mean = group.iter().map(|&r| sums[r]).sum::<f64>() / group.len() as f64;
        squares += group.iter().map(|&r| (sums[r] - mean).powi(2)).sum::<f64>();
        dof += group.len() - 1;
        groups += 1;
    }
    (dof > 0).then(|| SupportNoise {
        pair_variance: squares / dof as f64,
        dof,
        groups,
        source: "pair sums y+ + y- of pairs lighting the same support (the same light but for noise)",
    })
}

/// Fewest pixels for [`from_random_rows`]: the moments are exact only as `k` grows (the
/// sample fill and the centring add terms of order `1 / k`); on a 2x2 grid (16 distinct
/// patterns) noise-free buckets gave sigma 0.29 +- 0.06 against a data spread of 0.61.
pub const MIN_RANDOM_PIXELS: usize = 256;

/// From a Bernoulli session's raw rows (i.i.d. 0/1 entries, see the module docs): `op` is `A`
/// as the patterns are (not centred), `b` the buckets. `None` with fewer than 16 rows, fewer
/// than [`MIN_RANDOM_PIXELS`] pixels or degenerate patterns.
pub fn from_random_rows(op: &dyn LinearOperator, b: &[f64]) -> Option<NoiseEstimate> {
    let (n, k) = (op.rows(), op.cols());
    if n < 16 || k < MIN_RANDOM_PIXELS || b.len() != n {
        return None;
    }
    let mut row_sums = vec![0.0; n];
    op.apply(&vec![1.0; k], &mut row_sums);
    let p = row_sums.iter().sum::<f64>() / (n * k) as f64;
    let v = p * (1.0 - p);
    if v.is_nan() || v <= 0.0 {
        return None;
    }
    let nf = n as f64;
    let mean = b.iter().sum::<f64>() / nf;
    let c: Vec<f64> = b.iter().map(|v| v - mean).collect();
    // A~^T c = A^T c - p 1 (1^T c) = A^T c (the centred data sum to 0).
    let mut g = vec![0.0; k];
    op.adjoint(&c, &mut g);
    let total = g.iter().map(|x| x * x).sum::<f64>();
    // ||a~_i||^2 = (1 - p)^2 |a_i| + p^2 (k - |a_i|).
    let norm2: Vec<f64> = row_sums
        .iter()
        .map(|s| (1.0 - p).powi(2) * s + p * p * (k as f64 - s))
        .collect();
    let diag = c.iter().zip(&norm2).map(|(ci, q)| ci * ci * q).sum::<f64>();
    let pairs = nf * (nf - 1.0);
    let signal = (total - diag) / (pairs * v); // estimates v ||t||^2
    let sum_c2 = c.iter().map(|x| x * x).sum::<f64>();
    let mean_c2 = sum_c2 / nf;
    let var = mean_c2 - signal;
    // Standard error by the jackknife over rows (the asymptotic formula undershoots on small
    // or peaky problems): leaving row i out removes `2 c_i (a~_i . g - c_i ||a~_i||^2)` from
    // S, where `a~_i . g = (A g)_i - p 1 . g` (one more product).
    let mut ag = vec![0.0; n];
    op.apply(&g, &mut ag);
    let sum_g = g.iter().sum::<f64>();
    let leave_out: Vec<f64> = (0..n)
        .map(|i| {
            let cross = ag[i] - p * sum_g - c[i] * norm2[i];
            let s_i = total - diag - 2.0 * c[i] * cross;
            let m = nf - 1.0;
            (sum_c2 - c[i] * c[i]) / m - s_i / (m * (m - 1.0) * v)
        })
        .collect();
    let jack_mean = leave_out.iter().sum::<f64>() / nf;
    let se_var = ((nf - 1.0) / nf
        * leave_out
            .iter()
            .map(|x| (x - jack_mean) * (x - jack_mean))
            .sum::<f64>())
    .sqrt();
    let sigma = var.max(0.0).sqrt();
    // Delta method, floored where sigma is 0: sd(sigma) ~ se_var / (2 sigma) or sqrt(se_var).
    let standard_error = if sigma > 0.0 {
        (se_var / (2.0 * sigma)).min(se_var.sqrt())
    } else {
        se_var.sqrt()
    };
    Some(NoiseEstimate {
        sigma,
        standard_error,
        data_spread: mean_c2.sqrt(),
        source: "random-pattern moments (bucket variance less the image's share, which pairs of different rows measure noise-free)",
        rows: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linop::DenseOperator;

    /// A standard normal from two uniforms (Box-Muller on a SplitMix64 stream).
    pub(super) fn normals(n: usize, seed: u64) -> Vec<f64> {
        let mut s = seed;
        let mut next = move || {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| {
                let (u, v) = (next().max(1e-300), next());
                (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
            })
            .collect()
    }

    /// Pairs of one support share their light: the pooled spread of their sums is the noise,
    /// whatever the supports' light; a support shown once tells nothing.
    #[test]
    fn support_groups_pool_the_spread_of_equal_light() {
        let noise = normals(4000, 5);
        let sigma = 3.0;
        // 1000 supports of very different light, four pairs each; and one shown once.
        let mut sums: Vec<f64> = (0..4000)
            .map(|r| 1e4 * ((r / 4) as f64).sqrt() + sigma * noise[r])
            .collect();
        let mut support: Vec<u64> = (0..4000).map(|r| (r / 4) as u64).collect();
        sums.push(-5e6);
        support.push(7777);
        let e = from_support_groups(&sums, &support).unwrap();
        assert_eq!((e.groups, e.dof), (1000, 3000));
        let rel = (e.pair_variance.sqrt() / sigma - 1.0).abs();
        assert!(rel < 3.0 * e.relative_standard_error() / 2.0, "{e:?}");
        // Exact light: no noise.
        let exact: Vec<f64> = support.iter().map(|&s| s as f64 * 2.5).collect();
        assert_eq!(
            from_support_groups(&exact, &support).unwrap().pair_variance,
            0.0
        );
        assert!(from_support_groups(&[1.0, 2.0], &[0, 1]).is_none());
    }

    /// Walsh-Hadamard pairs all light the whole grid: one support group. A 20 % drift of the
    /// source over the session inflates the pooled spread of the sums, not the drift-free
    /// estimate carried over from the pair sums.
    #[test]
    fn whole_grid_pairs_take_the_drift_free_noise() {
        let n = 4000;
        let sigma_s = 2.0;
        let e = normals(n, 21);
        let sums: Vec<f64> = (0..n)
            .map(|r| 300.0 * (1.0 + 0.2 * r as f64 / n as f64) + sigma_s * e[r])
            .collect();
        let scale = 1.0 / 32.0;
        let data: Vec<f64> = e.iter().map(|v| v * sigma_s * scale).collect();
        let est = from_pair_sums(&sums, scale, &data).unwrap();
        let carried = SupportNoise::from_pair_estimate(&est, scale);
        let pooled = from_support_groups(&sums, &vec![0; n]).unwrap();
        let rel = |v: f64| (v.sqrt() / sigma_s - 1.0).abs();
        assert!(
            rel(carried.pair_variance) < 3.0 * carried.relative_standard_error() / 2.0,
            "{carried:?}"
        );
        assert!(rel(pooled.pair_variance) > 1.0, "{pooled:?}");
        // Its standard error as a variance is twice sigma's.
        let want = 2.0 * est.standard_error / est.sigma;
        assert!((carried.relative_standard_error() / want - 1.0).abs() < 0.05);
    }

    #[test]
    fn pair_sums_give_the_noise_of_the_differences_despite_drift() {
        let k = 1024.0f64;
        let sigma_y = 3.0;
        let n = 4000;
        let e = normals(2 * n, 5);
        // A slow 5 % drift of the total light: the sums trend, the estimate must not see it.
        let sums: Vec<f64> = (0..n)
            .map(|r| {
                500.0 * (1.0 + 0.05 * r as f64 / n as f64) + sigma_y * (e[2 * r] + e[2 * r + 1])
            })
            .collect();
        let data: Vec<f64> = (0..n)
            .map(|r| sigma_y * (e[2 * r] - e[2 * r + 1]) / k.sqrt())
            .collect();
        let est = from_pair_sums(&sums, 1.0 / k.sqrt(), &data).unwrap();
        let truth = sigma_y * 2f64.sqrt() / k.sqrt();
        assert!(
            (est.sigma / truth - 1.0).abs() < 4.0 * est.standard_error / truth,
            "{} vs {truth} (se {})",
            est.sigma,
            est.standard_error
        );
        assert!(est.standard_error / truth < 0.05);
        // Noise-free sums: zero.
        let flat = vec![500.0; 10];
        assert_eq!(from_pair_sums(&flat, 1.0, &data[..10]).unwrap().sigma, 0.0);
        assert!(from_pair_sums(&flat[..2], 1.0, &data[..2]).is_none());
    }

    #[test]
    fn random_rows_separate_the_noise_from_the_image() {
        let (n, k) = (1500usize, 400usize);
        // i.i.d. 0/1 rows from a hash.
        let a: Vec<f64> = (0..n * k)
            .map(|i| {
                let z = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
                ((z ^ (z >> 29)).wrapping_mul(0xBF58_476D_1CE4_E5B9) >> 63) as f64
            })
            .collect();
        let op = DenseOperator::new(n, k, a);
        let t: Vec<f64> = (0..k).map(|i| ((i * 37 % 101) as f64) / 100.0).collect();
        let mut clean = vec![0.0; n];
        op.apply(&t, &mut clean);
        let e = normals(n, 9);
        for sigma in [0.0, 1.0, 4.0, 20.0] {
            let b: Vec<f64> = clean.iter().zip(&e).map(|(c, e)| c + sigma * e).collect();
            let est = from_random_rows(&op, &b).unwrap();
            println!(
                "sigma {sigma}: estimate {:.3} +- {:.3}",
                est.sigma, est.standard_error
            );
            assert!(
                (est.sigma - sigma).abs() < 3.0 * est.standard_error + 0.1 * sigma,
                "sigma {sigma}: estimate {} +- {}",
                est.sigma,
                est.standard_error
            );
        }
    }
}
