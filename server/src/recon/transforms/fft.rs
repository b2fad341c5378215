//! A small complex FFT for power-of-two lengths (split real / imaginary arrays), planned once:
//! iterative radix-2 decimation in time after a bit-reversal permutation, twiddles tabulated.
//! Used by the fast DCT; not a general-purpose FFT.

#[derive(Clone, Debug)]
pub(crate) struct Fft {
    n: usize,
    /// Bit-reversal permutation.
    rev: Vec<u32>,
    /// `cos(2 pi j / n)`, `-sin(2 pi j / n)` for j < n / 2 (forward twiddles).
    cos: Vec<f64>,
    msin: Vec<f64>,
}

impl Fft {
    pub(crate) fn new(n: usize) -> Self {
        assert!(n.is_power_of_two(), "fft length must be a power of two, got {n}");
        let bits = n.trailing_zeros();
        let rev = (0..n as u64)
            .map(|i| if bits == 0 { 0 } else { (i.reverse_bits() >> (64 - bits)) as u32 })
            .collect();
        let (mut cos, mut msin) = (Vec::with_capacity(n / 2), Vec::with_capacity(n / 2));
        for j in 0..n / 2 {
            let a = 2.0 * std::f64::consts::PI * j as f64 / n as f64;
            cos.push(a.cos());
            msin.push(-a.sin());
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
            let stride = n / (2 * half);
            for start in (0..n).step_by(2 * half) {
                let (rl, rh) = re[start..start + 2 * half].split_at_mut(half);
                let (il, ih) = im[start..start + 2 * half].split_at_mut(half);
                for j in 0..half {
                    let (c, s) = (self.cos[j * stride], self.msin[j * stride]);
                    let (xr, xi) = (rh[j], ih[j]);
                    let (tr, ti) = (xr * c - xi * s, xr * s + xi * c);
                    rh[j] = rl[j] - tr;
                    ih[j] = il[j] - ti;
                    rl[j] += tr;
                    il[j] += ti;
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
                assert!((re[k] - sr).abs() < 1e-12 && (im[k] - si).abs() < 1e-12, "n {n} k {k}");
            }
            Fft::new(n).backward(&mut re, &mut im);
            for j in 0..n {
                assert!((re[j] / n as f64 - xr[j]).abs() < 1e-13);
                assert!((im[j] / n as f64 - xi[j]).abs() < 1e-13);
            }
        }
    }
}
