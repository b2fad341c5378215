//! Deterministic random numbers for the noise model: counter-based streams (one per noise stage
//! and row) so the result does not depend on the number of threads, and exact samplers for the
//! Poisson and normal distributions.

use helmholtz_proto::patterns::rng::{GOLDEN, mix64};

/// SplitMix64 (Steele, Lea, Flood 2014), the generator behind the pattern seeds too.
#[derive(Clone, Debug)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        SplitMix64 { state: seed }
    }

    /// An independent stream for (`seed`, `stage`, `index`): e.g. one per noise stage and row.
    pub fn stream(seed: u64, stage: u64, index: u64) -> Self {
        let s = mix64(seed.wrapping_add(stage.wrapping_add(1).wrapping_mul(GOLDEN)));
        SplitMix64::new(mix64(s ^ index.wrapping_mul(0xD1B5_4A32_D192_ED03)))
    }

    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(GOLDEN);
        mix64(self.state)
    }

    /// Uniform in [0, 1) with 53 random bits.
    #[inline]
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Standard normal (Box-Muller; the second value is discarded to keep streams simple).
    pub fn normal(&mut self) -> f64 {
        // 1 - u is in (0, 1]: the log is finite.
        let r = (-2.0 * (1.0 - self.uniform()).ln()).sqrt();
        r * (std::f64::consts::TAU * self.uniform()).cos()
    }

    /// Poisson with mean `lambda` >= 0: multiplication (inversion) below 10, Hörmann's PTRS
    /// transformed rejection above (exact for any mean; the same algorithm numpy uses).
    pub fn poisson(&mut self, lambda: f64) -> f64 {
        if lambda.is_nan() || lambda <= 0.0 {
            return 0.0;
        }
        if lambda < 10.0 {
            let limit = (-lambda).exp();
            let mut k = 0.0;
            let mut prod = self.uniform();
            while prod > limit {
                k += 1.0;
                prod *= self.uniform();
            }
            return k;
        }
        self.poisson_ptrs(lambda)
    }

    /// W. Hörmann, "The transformed rejection method for generating Poisson random variables",
    /// Insurance: Mathematics and Economics 12 (1993) 39-45, algorithm PTRS (valid for mean >= 10).
    fn poisson_ptrs(&mut self, lambda: f64) -> f64 {
        let slam = lambda.sqrt();
        let loglam = lambda.ln();
        let b = 0.931 + 2.53 * slam;
        let a = -0.059 + 0.02483 * b;
        let inv_alpha = 1.1239 + 1.1328 / (b - 3.4);
        let vr = 0.9277 - 3.6224 / (b - 2.0);
        loop {
            let u = self.uniform() - 0.5;
            let v = self.uniform();
            let us = 0.5 - u.abs();
            let k = ((2.0 * a / us + b) * u + lambda + 0.43).floor();
            if us >= 0.07 && v <= vr {
                return k;
            }
            if k < 0.0 || (us < 0.013 && v > us) {
                continue;
            }
            if v.ln() + inv_alpha.ln() - (a / (us * us) + b).ln()
                <= -lambda + k * loglam - ln_gamma(k + 1.0)
            {
                return k;
            }
        }
    }
}

/// ln Γ(x) for x > 0 by the Stirling series after shifting x >= 7 (error < 1e-14 there).
pub fn ln_gamma(x: f64) -> f64 {
    #[allow(clippy::excessive_precision)] // numpy's published coefficients
    const A: [f64; 10] = [
        8.333333333333333e-02,
        -2.777777777777778e-03,
        7.936507936507937e-04,
        -5.952380952380952e-04,
        8.417508417508418e-04,
        -1.917526917526918e-03,
        6.410256410256410e-03,
        -2.955065359477124e-02,
        1.796443723688307e-01,
        -1.39243221690590e+00,
    ];
    if x == 1.0 || x == 2.0 {
        return 0.0;
    }
    let mut x0 = x;
    let mut n = 0;
    if x < 7.0 {
        n = (7.0 - x.floor()) as i32;
        x0 = x + n as f64;
    }
    let x2 = 1.0 / (x0 * x0);
    let mut gl0 = A[9];
    for k in (0..9).rev() {
        gl0 = gl0 * x2 + A[k];
    }
    let mut gl = gl0 / x0 + 0.5 * std::f64::consts::TAU.ln() + (x0 - 0.5) * x0.ln() - x0;
    for _ in 0..n {
        x0 -= 1.0;
        gl -= x0.ln();
    }
    gl
}

#[cfg(test)]
mod tests {
    use super::*;

    fn moments(samples: &[f64]) -> (f64, f64) {
        let n = samples.len() as f64;
        let mean = samples.iter().sum::<f64>() / n;
        let var = samples.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
        (mean, var)
    }

    #[test]
    fn ln_gamma_matches_factorials() {
        let mut fact = 1.0f64;
        for n in 1..60 {
            fact *= n as f64;
            let got = ln_gamma(n as f64 + 1.0);
            assert!((got - fact.ln()).abs() < 1e-10 * fact.ln().max(1.0), "{n}");
        }
        // Γ(1/2) = sqrt(pi)
        assert!((ln_gamma(0.5) - std::f64::consts::PI.sqrt().ln()).abs() < 1e-12);
    }

    /// Mean and variance of n samples within 5 standard errors: se(mean) = sqrt(λ/n),
    /// se(var) = sqrt((2λ² + λ) / n) (fourth central moment of Poisson = 3λ² + λ).
    #[test]
    fn poisson_mean_and_variance_within_five_standard_errors() {
        let n = 200_000;
        for (i, &lambda) in [0.3, 3.0, 9.99, 10.0, 47.5, 1.0e3, 1.0e6, 3.0e9]
            .iter()
            .enumerate()
        {
            let mut rng = SplitMix64::stream(42, 7, i as u64);
            let s: Vec<f64> = (0..n).map(|_| rng.poisson(lambda)).collect();
            assert!(s.iter().all(|&k| k >= 0.0 && k.fract() == 0.0));
            let (mean, var) = moments(&s);
            let se_mean = (lambda / n as f64).sqrt();
            let se_var = ((2.0 * lambda * lambda + lambda) / n as f64).sqrt();
            assert!(
                (mean - lambda).abs() < 5.0 * se_mean,
                "λ={lambda}: mean {mean}"
            );
            assert!((var - lambda).abs() < 5.0 * se_var, "λ={lambda}: var {var}");
        }
    }

    /// The PTRS branch has the exact Poisson pmf: chi-square over k in [lambda ± 3 sd] at λ = 25.
    #[test]
    fn poisson_pmf_chi_square() {
        let lambda: f64 = 25.0;
        let n = 400_000;
        let mut rng = SplitMix64::new(99);
        let (lo, hi) = (10usize, 40usize);
        let mut counts = vec![0usize; hi - lo + 1];
        let mut outside = 0usize;
        for _ in 0..n {
            let k = rng.poisson(lambda) as usize;
            if (lo..=hi).contains(&k) {
                counts[k - lo] += 1
            } else {
                outside += 1
            }
        }
        let pmf = |k: usize| (-lambda + k as f64 * lambda.ln() - ln_gamma(k as f64 + 1.0)).exp();
        let mut chi2 = 0.0;
        let mut p_in = 0.0;
        for (j, &c) in counts.iter().enumerate() {
            let e = pmf(lo + j) * n as f64;
            p_in += pmf(lo + j);
            chi2 += (c as f64 - e).powi(2) / e;
        }
        let e_out = (1.0 - p_in) * n as f64;
        chi2 += (outside as f64 - e_out).powi(2) / e_out;
        // 31 + 1 bins -> 31 degrees of freedom; P(chi2 > 61) ≈ 1e-3.
        assert!(chi2 < 61.0, "chi2 = {chi2}");
    }

    #[test]
    fn normal_moments() {
        let mut rng = SplitMix64::new(5);
        let s: Vec<f64> = (0..200_000).map(|_| rng.normal()).collect();
        let (mean, var) = moments(&s);
        assert!(mean.abs() < 5.0 / (200_000f64).sqrt());
        assert!((var - 1.0).abs() < 5.0 * (2.0 / 200_000f64).sqrt());
    }

    #[test]
    fn streams_are_deterministic_and_distinct() {
        let a: Vec<u64> = (0..4)
            .map(|_| SplitMix64::stream(1, 2, 3).next_u64())
            .collect();
        assert!(a.windows(2).all(|w| w[0] == w[1]));
        assert_ne!(
            SplitMix64::stream(1, 2, 3).next_u64(),
            SplitMix64::stream(1, 2, 4).next_u64()
        );
        assert_ne!(
            SplitMix64::stream(1, 2, 3).next_u64(),
            SplitMix64::stream(1, 3, 3).next_u64()
        );
    }
}
