//! Orthonormal 2D DCT-II on any `W x H`.
//!
//! `C_N[u][x] = a_u cos(pi (2x + 1) u / (2N))`, `a_0 = sqrt(1/N)`, `a_u = sqrt(2/N)`: orthogonal.
//! The 2D transform of a row-major image `X` (H x W) is `Y = C_H X C_W^T`, coefficient `(v, u)`
//! (vertical frequency v, horizontal u) at index `v W + u`; the inverse (= adjoint) is
//! `X = C_H^T Y C_W`. Separable: every row is transformed, then (through a transpose) every
//! column.
//!
//! Per axis, two paths:
//! - length a power of two: O(N log N) through a complex FFT of length N (Makhoul 1980: even
//!   samples forward, odd samples backward, one FFT, a twiddle). The FFT runs down the columns
//!   of the image, all of them at once ([`Fft::forward_lanes`]): every butterfly combines two
//!   whole rows, a vector operation however short the span; the left half of the columns are
//!   the real parts and the right half the imaginary parts of one complex transform per pair.
//!   The horizontal axis is transformed the same way between two transposes;
//! - any other length: `rustdct`'s planned DCT-II (forward) and DCT-III (inverse), O(N log N)
//!   per row, scaled to the orthonormal transform; applied to all rows of the axis (the vertical
//!   axis between two transposes).
//!
//! The cached `N x N` cosine matrix ([`Dct2d::with_matrices`], O(N^2) per row) remains as the
//! reference. [`Dct2d::with_paths`] picks a path for every axis (benchmarks, tests).
//!
//! Measured (`transforms::bench`, best of 5, forward and inverse): 128 x 128 0.066-0.088 ms
//! against 0.125-0.145 ms with the FFT run one row pair at a time (its early stages, spans of 1
//! to 4, do not vectorise) and 0.48-0.60 ms for the matrix; 512 x 512 5.8-5.9 ms against
//! 7.5-7.9 ms (two threads); 158 x 210 (then the matrix on both axes) 0.9-1.1 ms.
//! Images from 2^15 pixels up split the columns into stripes over threads.
//!
//! `transforms::dct_bench` times the three paths against each other (figures there): rustdct
//! beats the matrix by 1.6x (side 100) to 13x (side 512) from side 64 up, and is level with it
//! at 48 (0.9-1.3x); the radix-2 path is faster than rustdct on every power of two measured
//! (64-512: 0.67-0.98 of its time, once 1.10 at 512 in three runs), so it stays there.

use std::sync::Arc;

use rayon::prelude::*;
use rustdct::{DctPlanner, TransformType2And3};

use super::Transform;
use super::fft::Fft;
use crate::linop::LinearOperator;
use crate::ops::scratch::{Pool, Scratch};

/// Orthonormal DCT-II matrix, row-major `n x n`.
pub fn dct_matrix(n: usize) -> Vec<f64> {
    let mut c = vec![0.0; n * n];
    let nf = n as f64;
    for u in 0..n {
        let a = if u == 0 {
            (1.0 / nf).sqrt()
        } else {
            (2.0 / nf).sqrt()
        };
        for x in 0..n {
            // Reduce the angle's integer part exactly before the cosine: (2x + 1) u mod 4N.
            let m = ((2 * x + 1) * u) % (4 * n);
            c[u * n + x] = a * (std::f64::consts::PI * m as f64 / (2.0 * nf)).cos();
        }
    }
    c
}

/// Rows per parallel task.
const ROWS_PER_TASK: usize = 16;
/// Lanes (column pairs) per parallel task of the column-wise fast path.
const LANES_PER_TASK: usize = 32;
/// Blocks smaller than this (values) run on one thread.
const PARALLEL_MIN: usize = 1 << 15;

/// How an axis is transformed ([`Dct2d::with_paths`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DctPath {
    /// The cached `N x N` cosine matrix, O(N^2) per row (the reference).
    Matrix,
    /// The hand-written radix-2 FFT path down the columns; powers of two only (others fall
    /// back to [`DctPath::Planned`]).
    Radix2,
    /// `rustdct`'s planned DCT-II / DCT-III of any length, O(N log N) per row.
    Planned,
}

enum Axis {
    Planned {
        n: usize,
        dct: Arc<dyn TransformType2And3<f64>>,
        /// `a_k` of the orthonormal forward transform; the inverse's input scale is
        /// `a_0 * 2` for `k = 0` and `a_k` otherwise (rustdct's DCT-III halves its first term).
        a: Vec<f64>,
    },
    Matrix {
        n: usize,
        /// C (n x n) and C^T.
        c: Vec<f64>,
        ct: Vec<f64>,
    },
    Fast {
        n: usize,
        fft: Fft,
        /// Forward: `a_k cos(theta_k) / 2`, `a_k sin(theta_k) / 2`, theta_k = pi k / (2n).
        fc: Vec<f64>,
        fs: Vec<f64>,
        /// Inverse: `cos(theta_k)`, `sin(theta_k)`, `1 / (a_k n)`.
        cos: Vec<f64>,
        sin: Vec<f64>,
        inv_a: Vec<f64>,
    },
}

impl std::fmt::Debug for Axis {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (path, n) = match self {
            Axis::Planned { n, .. } => ("planned", n),
            Axis::Matrix { n, .. } => ("matrix", n),
            Axis::Fast { n, .. } => ("radix-2", n),
        };
        f.debug_struct("Axis")
            .field("path", &path)
            .field("n", n)
            .finish()
    }
}

impl Axis {
    fn new(n: usize, path: DctPath) -> Axis {
        if path == DctPath::Planned || (path == DctPath::Radix2 && !(n.is_power_of_two() && n >= 2))
        {
            let nf = n as f64;
            let a = (0..n)
                .map(|k| {
                    if k == 0 {
                        (1.0 / nf).sqrt()
                    } else {
                        (2.0 / nf).sqrt()
                    }
                })
                .collect();
            return Axis::Planned {
                n,
                dct: DctPlanner::new().plan_dct2(n),
                a,
            };
        }
        if path == DctPath::Radix2 {
            let nf = n as f64;
            let a = |k: usize| {
                if k == 0 {
                    (1.0 / nf).sqrt()
                } else {
                    (2.0 / nf).sqrt()
                }
            };
            let theta = |k: usize| std::f64::consts::PI * k as f64 / (2.0 * nf);
            Axis::Fast {
                n,
                fft: Fft::new(n),
                fc: (0..n).map(|k| a(k) * theta(k).cos() / 2.0).collect(),
                fs: (0..n).map(|k| a(k) * theta(k).sin() / 2.0).collect(),
                cos: (0..n).map(|k| theta(k).cos()).collect(),
                sin: (0..n).map(|k| theta(k).sin()).collect(),
                inv_a: (0..n).map(|k| 1.0 / (a(k) * nf)).collect(),
            }
        } else {
            let c = dct_matrix(n);
            let mut ct = vec![0.0; n * n];
            for i in 0..n {
                for j in 0..n {
                    ct[j * n + i] = c[i * n + j];
                }
            }
            Axis::Matrix { n, c, ct }
        }
    }

    fn n(&self) -> usize {
        match self {
            Axis::Planned { n, .. } | Axis::Matrix { n, .. } | Axis::Fast { n, .. } => *n,
        }
    }

    /// Transforms every row of `data` (`rows x n`, contiguous) in place.
    fn rows(&self, data: &mut [f64], forward: bool, pool: &Pool) {
        let n = self.n();
        let parallel = data.len() >= PARALLEL_MIN && rayon::current_num_threads() > 1;
        let task = |chunk: &mut [f64]| {
            let mut scratch = pool.take(match self {
                Axis::Planned { dct, .. } => dct.get_scratch_len(),
                Axis::Matrix { .. } => chunk.len(),
                Axis::Fast { .. } => 3 * n,
            });
            self.rows_serial(chunk, forward, &mut scratch);
        };
        if parallel {
            data.par_chunks_mut(ROWS_PER_TASK * n).for_each(task);
        } else {
            task(data);
        }
    }

    /// Transforms every column of `data` (`n` rows of `width` values) in place; only for the
    /// fast path ([`Axis::is_fast`]). The columns are the FFT's lanes
    /// ([`Fft::forward_lanes`]): the first `ceil(width / 2)` columns are the real parts, the
    /// others the imaginary parts of one complex transform per lane (Makhoul's reordering, the
    /// FFT and the twiddle as in [`dct_pair`] / [`idct_pair`], on whole rows). Large images split
    /// the lanes into stripes, one per task.
    fn columns(&self, data: &mut [f64], width: usize, forward: bool, pool: &Pool) {
        let Axis::Fast { n, fft, .. } = self else {
            unreachable!("columns() runs on the fast path only")
        };
        let n = *n;
        debug_assert_eq!(data.len(), n * width);
        let p = width.div_ceil(2);
        let stripes = if data.len() >= PARALLEL_MIN && rayon::current_num_threads() > 1 {
            p.div_ceil(LANES_PER_TASK)
        } else {
            1
        };
        let bounds = |i: usize| (i * p / stripes, (i + 1) * p / stripes);
        // Phase 1, per stripe of lanes: read the columns into bit-reversed rows of (re, im), FFT.
        let mut buffers: Vec<_> = (0..stripes)
            .map(|i| {
                let (l0, l1) = bounds(i);
                (pool.take(n * (l1 - l0)), pool.take(n * (l1 - l0)))
            })
            .collect();
        let src: &[f64] = data;
        let phase1 = |i: usize, (re, im): &mut (Scratch, Scratch)| {
            let (l0, l1) = bounds(i);
            self.load_lanes(fft, src, width, l0, l1, forward, re, im);
            if forward {
                fft.forward_lanes(re, im, l1 - l0);
            } else {
                fft.forward_lanes(im, re, l1 - l0);
            }
        };
        if stripes > 1 {
            buffers
                .par_iter_mut()
                .enumerate()
                .for_each(|(i, b)| phase1(i, b));
        } else {
            phase1(0, &mut buffers[0]);
        }
        // Phase 2, per row: write the transformed columns back.
        let store = |k: usize, row: &mut [f64]| {
            for (i, (re, im)) in buffers.iter().enumerate() {
                let (l0, l1) = bounds(i);
                self.store_lanes(row, k, width, l0, l1, forward, re, im);
            }
        };
        if stripes > 1 {
            data.par_chunks_mut(width)
                .enumerate()
                .for_each(|(k, row)| store(k, row));
        } else {
            data.chunks_mut(width)
                .enumerate()
                .for_each(|(k, row)| store(k, row));
        }
    }

    /// Phase 1 of [`Axis::columns`] for lanes `l0..l1`: lane `l` pairs column `l` (real part)
    /// with column `p + l` (imaginary part, 0 past the last column), `p = ceil(width / 2)`.
    /// Forward: Makhoul's reordering (`v[j] = x[2j]`, `v[n-1-j] = x[2j+1]`); inverse: the
    /// pre-twiddle of [`idct_pair`]. Rows land in bit-reversed order.
    #[allow(clippy::too_many_arguments)]
    fn load_lanes(
        &self,
        fft: &Fft,
        src: &[f64],
        width: usize,
        l0: usize,
        l1: usize,
        forward: bool,
        re: &mut [f64],
        im: &mut [f64],
    ) {
        let Axis::Fast {
            n, cos, sin, inv_a, ..
        } = self
        else {
            unreachable!()
        };
        let n = *n;
        let p = width.div_ceil(2);
        let lanes = l1 - l0;
        // Columns p + l0 .. p + l1 that exist (the last lane has no partner when width is odd).
        let q = (width - p).min(l1).saturating_sub(l0);
        let part = |row: usize| {
            let r = &src[row * width..(row + 1) * width];
            (&r[l0..l1], &r[p + l0..p + l0 + q])
        };
        if forward {
            for j in 0..n {
                // Sample j of v is x[2j] for j < n/2, x[2(n-1-j)+1] otherwise.
                let from = if j < n / 2 {
                    2 * j
                } else {
                    2 * (n - 1 - j) + 1
                };
                let (a, b) = part(from);
                let at = fft.reversed(j) * lanes;
                re[at..at + lanes].copy_from_slice(a);
                im[at..at + q].copy_from_slice(b);
                im[at + q..at + lanes].fill(0.0);
            }
        } else {
            for k in 0..n {
                let (ia, c, s) = (inv_a[k], cos[k], sin[k]);
                let (x1, x2) = part(k);
                let at = fft.reversed(k) * lanes;
                let (re, im) = (&mut re[at..at + lanes], &mut im[at..at + lanes]);
                if k == 0 {
                    // U[n] = 0: V[0] = U[0].
                    for l in 0..lanes {
                        let a1 = x1[l] * ia;
                        let a2 = if l < q { x2[l] * ia } else { 0.0 };
                        let (rv1, iv1) = (c * a1 + s * 0.0, s * a1 - c * 0.0);
                        let (rv2, iv2) = (c * a2 + s * 0.0, s * a2 - c * 0.0);
                        re[l] = rv1 - iv2;
                        im[l] = iv1 + rv2;
                    }
                    continue;
                }
                let ib = inv_a[n - k];
                let (y1, y2) = part(n - k);
                for l in 0..q {
                    let (a1, a2) = (x1[l] * ia, x2[l] * ia);
                    let (b1, b2) = (y1[l] * ib, y2[l] * ib);
                    let (rv1, iv1) = (c * a1 + s * b1, s * a1 - c * b1);
                    let (rv2, iv2) = (c * a2 + s * b2, s * a2 - c * b2);
                    re[l] = rv1 - iv2;
                    im[l] = iv1 + rv2;
                }
                for l in q..lanes {
                    let (a1, b1) = (x1[l] * ia, y1[l] * ib);
                    let (rv1, iv1) = (c * a1 + s * b1, s * a1 - c * b1);
                    re[l] = rv1;
                    im[l] = iv1;
                }
            }
        }
    }

    /// Phase 2 of [`Axis::columns`]: row `k` of the result, lanes `l0..l1`, from the transformed
    /// (re, im) rows (forward: the twiddle of [`dct_pair`]; inverse: the reordering undone).
    #[allow(clippy::too_many_arguments)]
    fn store_lanes(
        &self,
        row: &mut [f64],
        k: usize,
        width: usize,
        l0: usize,
        l1: usize,
        forward: bool,
        re: &[f64],
        im: &[f64],
    ) {
        let Axis::Fast { n, fc, fs, .. } = self else {
            unreachable!()
        };
        let n = *n;
        let p = width.div_ceil(2);
        let lanes = l1 - l0;
        let q = (width - p).min(l1).saturating_sub(l0);
        let (lo, hi) = row.split_at_mut(p);
        let (x1, x2) = (&mut lo[l0..l1], &mut hi[l0..l0 + q]);
        let r = |j: usize| {
            (
                &re[j * lanes..(j + 1) * lanes],
                &im[j * lanes..(j + 1) * lanes],
            )
        };
        if forward {
            let m = if k == 0 { 0 } else { n - k };
            let ((a, b), (c, d)) = (r(k), r(m));
            let (f, g) = (fc[k], fs[k]);
            for l in 0..lanes {
                x1[l] = f * (a[l] + c[l]) + g * (b[l] - d[l]);
            }
            for l in 0..q {
                x2[l] = f * (b[l] + d[l]) + g * (c[l] - a[l]);
            }
        } else {
            // x[2j] = v[j], x[2j+1] = v[n-1-j].
            let j = if k.is_multiple_of(2) {
                k / 2
            } else {
                n - 1 - k / 2
            };
            let (a, b) = r(j);
            x1.copy_from_slice(a);
            x2.copy_from_slice(&b[..q]);
        }
    }

    fn is_fast(&self) -> bool {
        matches!(self, Axis::Fast { .. })
    }

    fn rows_serial(&self, data: &mut [f64], forward: bool, scratch: &mut [f64]) {
        match self {
            Axis::Planned { n, dct, a } => {
                for row in data.chunks_exact_mut(*n) {
                    if forward {
                        dct.process_dct2_with_scratch(row, scratch);
                        row.iter_mut().zip(a).for_each(|(v, a)| *v *= a);
                    } else {
                        row.iter_mut().zip(a).for_each(|(v, a)| *v *= a);
                        row[0] *= 2.0;
                        dct.process_dct3_with_scratch(row, scratch);
                    }
                }
            }
            Axis::Matrix { n, c, ct } => {
                let out = &mut scratch[..data.len()];
                // Forward: each row x -> C x = x^T C^T, i.e. out = data C^T; inverse: data C.
                gemm(data, if forward { ct } else { c }, *n, out);
                data.copy_from_slice(out);
            }
            Axis::Fast {
                n,
                fft,
                fc,
                fs,
                cos,
                sin,
                inv_a,
            } => {
                let n = *n;
                let (re, rest) = scratch.split_at_mut(n);
                let (im, zero) = rest.split_at_mut(n);
                let mut rows = data.chunks_exact_mut(n);
                loop {
                    let (x1, x2): (&mut [f64], &mut [f64]) = match (rows.next(), rows.next()) {
                        (Some(a), Some(b)) => (a, b),
                        (Some(a), None) => {
                            zero.fill(0.0);
                            (a, &mut zero[..])
                        }
                        _ => break,
                    };
                    if forward {
                        dct_pair(fft, fc, fs, x1, x2, re, im);
                    } else {
                        idct_pair(fft, cos, sin, inv_a, x1, x2, re, im);
                    }
                }
            }
        }
    }
}

/// Orthonormal DCT-II of two rows at once (in place).
fn dct_pair(
    fft: &Fft,
    fc: &[f64],
    fs: &[f64],
    x1: &mut [f64],
    x2: &mut [f64],
    re: &mut [f64],
    im: &mut [f64],
) {
    let n = x1.len();
    for j in 0..n / 2 {
        re[j] = x1[2 * j];
        re[n - 1 - j] = x1[2 * j + 1];
        im[j] = x2[2 * j];
        im[n - 1 - j] = x2[2 * j + 1];
    }
    fft.forward(re, im);
    // Z = V1 + i V2; V1[k] = (Z[k] + conj Z[n-k]) / 2, V2[k] = (Z[k] - conj Z[n-k]) / 2i;
    // X[k] = a_k Re(exp(-i theta_k) V[k]).
    for k in 0..n {
        let m = if k == 0 { 0 } else { n - k };
        let (a, b, c, d) = (re[k], im[k], re[m], im[m]);
        x1[k] = fc[k] * (a + c) + fs[k] * (b - d);
        x2[k] = fc[k] * (b + d) + fs[k] * (c - a);
    }
}

/// Inverse (orthonormal DCT-III) of two rows at once (in place).
#[allow(clippy::too_many_arguments)]
fn idct_pair(
    fft: &Fft,
    cos: &[f64],
    sin: &[f64],
    inv_a: &[f64],
    x1: &mut [f64],
    x2: &mut [f64],
    re: &mut [f64],
    im: &mut [f64],
) {
    let n = x1.len();
    // Unnormalised coefficients U = X / a (with the 1/n of the inverse FFT folded in);
    // V[k] = exp(i theta_k) (U[k] - i U[n-k]), U[n] = 0; Z = V1 + i V2.
    for k in 0..n {
        let (a1, a2) = (x1[k] * inv_a[k], x2[k] * inv_a[k]);
        let (b1, b2) = if k == 0 {
            (0.0, 0.0)
        } else {
            (x1[n - k] * inv_a[n - k], x2[n - k] * inv_a[n - k])
        };
        let (c, s) = (cos[k], sin[k]);
        let (rv1, iv1) = (c * a1 + s * b1, s * a1 - c * b1);
        let (rv2, iv2) = (c * a2 + s * b2, s * a2 - c * b2);
        re[k] = rv1 - iv2;
        im[k] = iv1 + rv2;
    }
    fft.backward(re, im);
    for j in 0..n / 2 {
        x1[2 * j] = re[j];
        x1[2 * j + 1] = re[n - 1 - j];
        x2[2 * j] = im[j];
        x2[2 * j + 1] = im[n - 1 - j];
    }
}

/// `out = a b`: `a` is `m x p` (rows back to back), `b` is `p x p`, row-major. Each output row
/// is a sum of rows of `b`, four at a time (the inner loop is a vectorised multiply-add).
fn gemm(a: &[f64], b: &[f64], p: usize, out: &mut [f64]) {
    let q = p;
    for (ai, o) in a.chunks_exact(p).zip(out.chunks_exact_mut(q)) {
        o.fill(0.0);
        let mut j = 0;
        while j + 4 <= p {
            let (a0, a1, a2, a3) = (ai[j], ai[j + 1], ai[j + 2], ai[j + 3]);
            let b0 = &b[j * q..(j + 1) * q];
            let b1 = &b[(j + 1) * q..(j + 2) * q];
            let b2 = &b[(j + 2) * q..(j + 3) * q];
            let b3 = &b[(j + 3) * q..(j + 4) * q];
            for ((((ov, &x0), &x1), &x2), &x3) in o.iter_mut().zip(b0).zip(b1).zip(b2).zip(b3) {
                *ov += (a0 * x0 + a1 * x1) + (a2 * x2 + a3 * x3);
            }
            j += 4;
        }
        while j < p {
            let aj = ai[j];
            for (ov, &x) in o.iter_mut().zip(&b[j * q..(j + 1) * q]) {
                *ov += aj * x;
            }
            j += 1;
        }
    }
}

/// `t[x * h + y] = data[y * w + x]` (`data` is `h x w`).
pub(crate) fn transpose(data: &[f64], w: usize, h: usize, t: &mut [f64]) {
    const B: usize = 32;
    for y0 in (0..h).step_by(B) {
        for x0 in (0..w).step_by(B) {
            for y in y0..(y0 + B).min(h) {
                for x in x0..(x0 + B).min(w) {
                    t[x * h + y] = data[y * w + x];
                }
            }
        }
    }
}

#[derive(Debug)]
pub struct Dct2d {
    width: usize,
    height: usize,
    x: Axis,
    y: Axis,
    pool: Pool,
}

impl Dct2d {
    /// The radix-2 path on power-of-two axes, rustdct's planned transform on the others.
    pub fn new(width: usize, height: usize) -> Self {
        Self::with_paths(width, height, DctPath::Radix2)
    }

    /// Matrix products on every axis (the reference for the fast paths; benchmarks).
    pub fn with_matrices(width: usize, height: usize) -> Self {
        Self::with_paths(width, height, DctPath::Matrix)
    }

    /// Every axis on `path` ([`DctPath::Radix2`] falls back to the planned transform on axes
    /// that are not powers of two).
    pub fn with_paths(width: usize, height: usize, path: DctPath) -> Self {
        assert!(width > 0 && height > 0, "dct needs a non-empty image");
        Dct2d {
            width,
            height,
            x: Axis::new(width, path),
            y: Axis::new(height, path),
            pool: Pool::new(),
        }
    }

    pub fn width(&self) -> usize {
        self.width
    }
    pub fn height(&self) -> usize {
        self.height
    }

    fn run(&self, input: &[f64], out: &mut [f64], forward: bool) {
        let (w, h) = (self.width, self.height);
        assert_eq!(input.len(), w * h);
        assert_eq!(out.len(), w * h);
        out.copy_from_slice(input);
        // A fast axis runs on columns (vectorised over them), a matrix axis on rows: the
        // horizontal axis needs a transpose there and back when fast, the vertical one when not.
        if self.y.is_fast() {
            self.y.columns(out, w, forward, &self.pool);
        }
        if w > 1 {
            if self.x.is_fast() && h > 1 {
                let mut t = self.pool.take(w * h);
                transpose(out, w, h, &mut t);
                self.x.columns(&mut t, h, forward, &self.pool);
                transpose(&t, h, w, out);
            } else {
                self.x.rows(out, forward, &self.pool);
            }
        }
        if h > 1 && !self.y.is_fast() {
            let mut t = self.pool.take(w * h);
            transpose(out, w, h, &mut t);
            self.y.rows(&mut t, forward, &self.pool);
            transpose(&t, h, w, out);
        }
    }
}

impl LinearOperator for Dct2d {
    fn rows(&self) -> usize {
        self.width * self.height
    }
    fn cols(&self) -> usize {
        self.width * self.height
    }
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.run(x, y, true);
    }
    fn adjoint(&self, y: &[f64], x: &mut [f64]) {
        self.run(y, x, false);
    }
}

impl Transform for Dct2d {
    fn name(&self) -> &'static str {
        "dct"
    }
    fn is_orthonormal(&self) -> bool {
        true
    }
}
