//! A small complex FFT for power-of-two lengths (split real / imaginary arrays), planned once:
//! iterative radix-2 decimation in time after a bit-reversal permutation, twiddles tabulated.
//! Used by the fast DCT; not a general-purpose FFT.

#[derive(Clone, Debug)]
pub(crate) struct Fft {
    n: usize,
    /// Bit-reversal permutation.
    rev: Vec<u32>,
    /// Forward twiddles per stage, contiguous: for the stage of span `half`, entries
    /// `half + j` (j < half) hold `cos(pi j / half)` and `-sin(pi j / half)`.
    cos: Vec<f64>,
    msin: Vec<f64>,
}

impl Fft {
    pub(crate) fn new(n: usize) -> Self {
        assert!(
            n.is_power_of_two(),
            "fft length must be a power of two, got {n}"
        );
        let bits = n.trailing_zeros();
        let rev = (0..n as u64)
            .map(|i| {
                if bits == 0 {
                    0
                } else {
                    (i.reverse_bits() >> (64 - bits)) as u32
                }
            })
            .collect();
        let (mut cos, mut msin) = (vec![0.0; n.max(1)], vec![0.0; n.max(1)]);
        let mut half = 1;
        while half < n {
            for j in 0..half {
                let a = std::f64::consts::PI * j as f64 / half as f64;
                cos[half + j] = a.cos();
                msin[half + j] = -a.sin();
            }
            half *= 2;
        }
        Fft { n, rev, cos, msin }
    }

    /// In place, `X[k] = sum_j x[j] exp(-2 pi i j k / n)` (unnormalised).
    pub(crate) fn forward(&self, re: &mut [f64], im: &mut [f64]) {
        let n = self.n;
        debug_assert!(re.len() == n && im.len() == n);
        for i in 0..n {
            let j = self.rev[i] as usize;
            if j > i {
                re.swap(i, j);
                im.swap(i, j);
            }
        }
        // Span 1 (twiddle 1) separately.
        let mut i = 0;
        while i + 1 < n {
            let (a, b) = (re[i], re[i + 1]);
            re[i] = a + b;
            re[i + 1] = a - b;
            let (a, b) = (im[i], im[i + 1]);
            im[i] = a + b;
            im[i + 1] = a - b;
            i += 2;
        }
        let mut half = 2;
        while half < n {
            let (cs, ss) = (&self.cos[half..2 * half], &self.msin[half..2 * half]);
            for (rc, ic) in re
                .chunks_exact_mut(2 * half)
                .zip(im.chunks_exact_mut(2 * half))
            {
                let (rl, rh) = rc.split_at_mut(half);
                let (il, ih) = ic.split_at_mut(half);
                for (((((rl, rh), il), ih), &c), &s) in rl
                    .iter_mut()
                    .zip(rh.iter_mut())
                    .zip(il.iter_mut())
                    .zip(ih.iter_mut())
                    .zip(cs)
                    .zip(ss)
                {
                    let (xr, xi) = (*rh, *ih);
                    let (tr, ti) = (xr * c - xi * s, xr * s + xi * c);
                    *rh = *rl - tr;
                    *ih = *il - ti;
                    *rl += tr;
                    *il += ti;
                }
            }
            half *= 2;
        }
    }

    /// In place, `x[j] = sum_k X[k] exp(+2 pi i j k / n)` (unnormalised: `n` times the inverse),
    /// by the swap trick.
    pub(crate) fn backward(&self, re: &mut [f64], im: &mut [f64]) {
        self.forward(im, re);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recon::linop::test_vector;

    #[test]
    fn matches_the_dft() {
        for n in [1usize, 2, 4, 8, 64] {
            let (xr, xi) = (test_vector(n, 1), test_vector(n, 2));
            let (mut re, mut im) = (xr.clone(), xi.clone());
            Fft::new(n).forward(&mut re, &mut im);
            for k in 0..n {
                let (mut sr, mut si) = (0.0, 0.0);
                for j in 0..n {
                    let a = -2.0 * std::f64::consts::PI * (j * k) as f64 / n as f64;
                    sr += xr[j] * a.cos() - xi[j] * a.sin();
                    si += xr[j] * a.sin() + xi[j] * a.cos();
                }
                assert!(
                    (re[k] - sr).abs() < 1e-12 && (im[k] - si).abs() < 1e-12,
                    "n {n} k {k}"
                );
            }
            Fft::new(n).backward(&mut re, &mut im);
            for j in 0..n {
                assert!((re[j] / n as f64 - xr[j]).abs() < 1e-13);
                assert!((im[j] / n as f64 - xi[j]).abs() < 1e-13);
            }
        }
    }
}
