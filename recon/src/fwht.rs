//! Fast Walsh-Hadamard transform.
//!
//! [`fwht`] computes `y = H x` in place, `H` the unnormalised n x n Sylvester matrix
//! `H[i][j] = (-1)^popcount(i & j)` (natural order), in O(n log n). `H H = n I`, so applying it
//! twice gives `n x`, and the inverse is `fwht` followed by a division by `n`.
//!
//! Layout of the work: every stage with a butterfly span below [`BLOCK`] runs block by block (each
//! block stays in L1/L2 while all its small stages run); the remaining large spans are fused two
//! at a time (radix 4), so a length-2^22 transform makes about six passes over memory instead of
//! eleven. Lengths from [`PARALLEL_MIN`] up use rayon (blocks in parallel, then each large pass
//! split into independent index ranges).

use rayon::prelude::*;

use crate::simd::avx2_dispatch;

/// Elements per cache block (16 KiB of f64).
const BLOCK: usize = 1 << 11;
/// Shortest length worth spreading over threads.
const PARALLEL_MIN: usize = 1 << 16;
/// Smallest slice length one rayon task handles in a large-span pass.
const TASK: usize = 1 << 13;

/// In-place unnormalised fast Walsh-Hadamard transform in natural (Sylvester) order.
///
/// Panics unless `data.len()` is a power of two or zero (an empty slice is left as is).
pub fn fwht(data: &mut [f64]) {
    let n = data.len();
    if n <= 1 {
        return;
    }
    assert!(
        n.is_power_of_two(),
        "fwht needs a power-of-two length, got {n}"
    );
    if n <= BLOCK {
        fwht_small(data);
        return;
    }
    let parallel = n >= PARALLEL_MIN && rayon::current_num_threads() > 1;
    if parallel {
        data.par_chunks_mut(BLOCK).for_each(fwht_small);
    } else {
        data.chunks_mut(BLOCK).for_each(fwht_small);
    }
    let mut h = BLOCK;
    while h < n {
        if 4 * h <= n {
            for chunk in data.chunks_mut(4 * h) {
                let (a, rest) = chunk.split_at_mut(h);
                let (b, rest) = rest.split_at_mut(h);
                let (c, d) = rest.split_at_mut(h);
                radix4(a, b, c, d, parallel);
            }
            h *= 4;
        } else {
            for chunk in data.chunks_mut(2 * h) {
                let (a, b) = chunk.split_at_mut(h);
                radix2(a, b, parallel);
            }
            h *= 2;
        }
    }
}

avx2_dispatch! {
/// All stages of a short transform, radix 2 (the inner loops vectorise).
fn fwht_small(data: &mut [f64]) {
    let n = data.len();
    let mut h = 1;
    // Spans 1 and 2 together: each group of four is a 4-point transform.
    if n >= 4 {
        for q in data.chunks_exact_mut(4) {
            let (a, b, c, d) = (q[0] + q[1], q[0] - q[1], q[2] + q[3], q[2] - q[3]);
            q[0] = a + c;
            q[1] = b + d;
            q[2] = a - c;
            q[3] = b - d;
        }
        h = 4;
    }
    while h < n {
        for chunk in data.chunks_exact_mut(2 * h) {
            let (a, b) = chunk.split_at_mut(h);
            butterfly2(a, b);
        }
        h *= 2;
    }
}
}

#[inline]
fn butterfly2(a: &mut [f64], b: &mut [f64]) {
    for (x, y) in a.iter_mut().zip(b.iter_mut()) {
        let (s, d) = (*x + *y, *x - *y);
        *x = s;
        *y = d;
    }
}

avx2_dispatch! {
/// Spans h and 2h fused: quarters (a, b, c, d) of a 4h chunk.
fn butterfly4(a: &mut [f64], b: &mut [f64], c: &mut [f64], d: &mut [f64]) {
    for (((w, x), y), z) in a.iter_mut().zip(b.iter_mut()).zip(c.iter_mut()).zip(d.iter_mut()) {
        let (p, q, r, s) = (*w + *x, *w - *x, *y + *z, *y - *z);
        *w = p + r;
        *x = q + s;
        *y = p - r;
        *z = q - s;
    }
}
}

avx2_dispatch! {
fn butterfly2_wide(a: &mut [f64], b: &mut [f64]) {
    butterfly2(a, b)
}
}

fn radix2(a: &mut [f64], b: &mut [f64], parallel: bool) {
    if parallel && a.len() > TASK {
        a.par_chunks_mut(TASK)
            .zip(b.par_chunks_mut(TASK))
            .for_each(|(a, b)| butterfly2_wide(a, b));
    } else {
        butterfly2_wide(a, b);
    }
}

fn radix4(a: &mut [f64], b: &mut [f64], c: &mut [f64], d: &mut [f64], parallel: bool) {
    if parallel && a.len() > TASK {
        a.par_chunks_mut(TASK)
            .zip(b.par_chunks_mut(TASK))
            .zip(c.par_chunks_mut(TASK))
            .zip(d.par_chunks_mut(TASK))
            .for_each(|(((a, b), c), d)| butterfly4(a, b, c, d));
    } else {
        butterfly4(a, b, c, d);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::Rng;

    fn dense(x: &[f64]) -> Vec<f64> {
        let n = x.len();
        (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| {
                        if (i & j).count_ones() % 2 == 0 {
                            x[j]
                        } else {
                            -x[j]
                        }
                    })
                    .sum()
            })
            .collect()
    }

    fn random(n: usize, seed: u64) -> Vec<f64> {
        let mut rng = Rng::new(seed);
        (0..n).map(|_| rng.normal()).collect()
    }

    fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max)
    }

    #[test]
    fn matches_dense_sylvester_product() {
        // Below and at the block size (2^11), then one radix-2 (2^12) and one radix-4 (2^13) large
        // stage.
        for bits in [0u32, 1, 2, 3, 5, 8, 11, 12, 13] {
            let n = 1usize << bits;
            let x = random(n, 100 + bits as u64);
            let want = dense(&x);
            let mut got = x.clone();
            fwht(&mut got);
            // Each output is a sum of n terms of size ~1: rounding error ~ sqrt(n) * 1e-16.
            let tol = 1e-12 * n as f64;
            assert!(max_abs_diff(&got, &want) < tol, "n = {n}");
        }
    }

    #[test]
    fn twice_is_n_times_identity() {
        // Includes parallel lengths (>= PARALLEL_MIN) with both an odd and an even number of
        // large stages.
        for bits in [4u32, 10, 15, 16, 17, 20] {
            let n = 1usize << bits;
            let x = random(n, 7 + bits as u64);
            let mut y = x.clone();
            fwht(&mut y);
            fwht(&mut y);
            let want: Vec<f64> = x.iter().map(|v| v * n as f64).collect();
            assert!(max_abs_diff(&y, &want) < 1e-9 * n as f64, "n = {n}");
        }
    }

    #[test]
    fn delta_gives_a_hadamard_row() {
        let n = 1 << 12;
        let row = 1234;
        let mut x = vec![0.0; n];
        x[row] = 1.0;
        fwht(&mut x);
        for (j, v) in x.iter().enumerate() {
            let want = if (row & j).count_ones() % 2 == 0 {
                1.0
            } else {
                -1.0
            };
            assert_eq!(*v, want);
        }
    }

    #[test]
    #[should_panic(expected = "power-of-two")]
    fn rejects_other_lengths() {
        fwht(&mut [1.0, 2.0, 3.0]);
    }
}
