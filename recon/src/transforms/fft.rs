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

    /// Row `reversed(j)` of [`Fft::forward_lanes`]' input holds sample j.
    pub(crate) fn reversed(&self, j: usize) -> usize {
        self.rev[j] as usize
    }

    /// `lanes` transforms at once, in place, as [`Fft::forward`]: `re` and `im` hold `n` rows of
    /// `lanes` values, each lane one transform, its samples **in bit-reversed row order** (row
    /// [`Fft::reversed`]`(j)` holds sample j; the caller writes them there, so no permutation
    /// pass is needed). The output is in natural order. Every butterfly combines two whole rows,
    /// so the inner loops run over contiguous lanes (vectorised), whatever the stage.
    pub(crate) fn forward_lanes(&self, re: &mut [f64], im: &mut [f64], lanes: usize) {
        let n = self.n;
        debug_assert!(re.len() == n * lanes && im.len() == n * lanes);
        let mut half = 1;
        while half < n {
            for base in (0..n).step_by(2 * half) {
                for j in 0..half {
                    let (c, s) = (self.cos[half + j], self.msin[half + j]);
                    let (a, b) = ((base + j) * lanes, (base + j + half) * lanes);
                    let (rlo, rhi) = re.split_at_mut(b);
                    let (ilo, ihi) = im.split_at_mut(b);
                    let (ra, rb) = (&mut rlo[a..a + lanes], &mut rhi[..lanes]);
                    let (ia, ib) = (&mut ilo[a..a + lanes], &mut ihi[..lanes]);
                    if half == 1 {
                        // Twiddle 1 (as in `forward`: no multiplications).
                        butterflies::<false>(ra, rb, ia, ib, 1.0, 0.0);
                    } else {
                        butterflies::<true>(ra, rb, ia, ib, c, s);
                    }
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

/// Radix-2 butterflies on whole rows: `(a, b) <- (a + w b, a - w b)` lane by lane, with the
/// twiddle `w = c + i s` (`TWIDDLE`) or `w = 1`.
#[inline(always)]
fn butterflies<const TWIDDLE: bool>(
    ra: &mut [f64],
    rb: &mut [f64],
    ia: &mut [f64],
    ib: &mut [f64],
    c: f64,
    s: f64,
) {
    for (((ra, rb), ia), ib) in ra
        .iter_mut()
        .zip(rb.iter_mut())
        .zip(ia.iter_mut())
        .zip(ib.iter_mut())
    {
        let (xr, xi) = (*rb, *ib);
        let (tr, ti) = if TWIDDLE {
            (xr * c - xi * s, xr * s + xi * c)
        } else {
            (xr, xi)
        };
        *rb = *ra - tr;
        *ib = *ia - ti;
        *ra += tr;
        *ia += ti;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linop::test_vector;

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

    #[test]
    fn lanes_match_one_transform_at_a_time_bit_for_bit() {
        for n in [1usize, 2, 4, 8, 64] {
            let lanes = 5;
            let fft = Fft::new(n);
            let (xr, xi) = (test_vector(n * lanes, 3), test_vector(n * lanes, 4));
            let (mut re, mut im) = (vec![0.0; n * lanes], vec![0.0; n * lanes]);
            for j in 0..n {
                for l in 0..lanes {
                    re[fft.reversed(j) * lanes + l] = xr[l * n + j];
                    im[fft.reversed(j) * lanes + l] = xi[l * n + j];
                }
            }
            fft.forward_lanes(&mut re, &mut im, lanes);
            for l in 0..lanes {
                let (mut r1, mut i1) = (
                    xr[l * n..(l + 1) * n].to_vec(),
                    xi[l * n..(l + 1) * n].to_vec(),
                );
                fft.forward(&mut r1, &mut i1);
                for k in 0..n {
                    assert_eq!(
                        re[k * lanes + l].to_bits(),
                        r1[k].to_bits(),
                        "n {n} lane {l} k {k}"
                    );
                    assert_eq!(
                        im[k * lanes + l].to_bits(),
                        i1[k].to_bits(),
                        "n {n} lane {l} k {k}"
                    );
                }
            }
        }
    }
}
