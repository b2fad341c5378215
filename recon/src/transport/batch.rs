//! Many right-hand sides at once: FISTA for
//! `min_s 1/2 ||A Psi^T s_j - b_j||^2 + lambda_j ||s_j[free..]||_1` for every row `j` of a block,
//! sharing the operator `A` and the orthonormal transform `Psi` (synthesis form; for an
//! orthonormal `Psi` it equals the analysis problem in `t_j = Psi^T s_j`, and the prox is the
//! exact soft threshold, so the rows come out sparse in `Psi`).
//!
//! The rows still iterating are kept contiguous (`active x k`), so every iteration is one
//! `apply_batch` and one `adjoint_batch` of `A` over all of them; a row that has converged is
//! written out and swapped out of the batch. A block is split into chunks of rows solved in
//! parallel (rayon), each chunk with its own scratch. Per row: momentum with the gradient
//! restart of O'Donoghue-Candes, stop after 3 consecutive steps with
//! `||s_k - s_{k-1}|| <= tol ||s_k||` or at `max_iter`. Step `1 / L` with `L >= ||A||^2` given
//! by the caller (power iteration with a margin; Hadamard split pairs: exactly 1).

use rayon::prelude::*;

use crate::linop::LinearOperator;
use crate::simd::avx2_dispatch;
use crate::{Control, ReconError};

/// What every row of a block shares.
pub(crate) struct Shared<'a> {
    pub op: &'a dyn LinearOperator,
    /// `A Psi^T` as dense columns: when given, every row is solved by coordinate descent on it
    /// ([`Dense`]) instead of FISTA on the operator (same problem, same stopping tolerance).
    pub dense: Option<&'a Dense>,
    pub psi: &'a dyn LinearOperator,
    /// `Psi = I` (skip the transforms).
    pub identity: bool,
    pub lipschitz: f64,
    /// Leading coefficients left unpenalised (the DC term of a wavelet or DCT).
    pub free: usize,
    pub max_iter: usize,
    pub tol: f64,
    /// The refit ([`refit_rows`]) without dense columns: CGLS to the least-squares fit on the
    /// support ([`cgls_chunk`]; Hadamard pairs, models of version 5 on), else a projected FISTA
    /// stopped by its step size (random patterns, and version 4 and older, solved as they were
    /// planned). Supports of orthonormal Hadamard rows are well conditioned; on random patterns
    /// CGLS to the same precision took far more iterations (measured on their dense columns:
    /// Cornell 32x32 x 64x64 from 25 % Bernoulli frames, 12 s -> 79 s).
    pub cgls_refit: bool,
}

impl Shared<'_> {
    pub(crate) fn k(&self) -> usize {
        self.op.cols()
    }
    pub(crate) fn n(&self) -> usize {
        self.op.rows()
    }

    /// `ys = Psi xs` row by row.
    pub fn forward(&self, xs: &[f64], ys: &mut [f64]) {
        if self.identity {
            ys.copy_from_slice(xs);
        } else {
            let k = self.k();
            for (x, y) in xs.chunks_exact(k).zip(ys.chunks_exact_mut(k)) {
                self.psi.apply(x, y);
            }
        }
    }

    /// `xs = Psi^T ys` row by row.
    pub fn inverse(&self, ys: &[f64], xs: &mut [f64]) {
        if self.identity {
            xs.copy_from_slice(ys);
        } else {
            let k = self.k();
            for (y, x) in ys.chunks_exact(k).zip(xs.chunks_exact_mut(k)) {
                self.psi.adjoint(y, x);
            }
        }
    }

    /// Bytes of scratch one row in a chunk needs while it iterates.
    pub fn scratch_bytes_per_row(k: usize, n: usize) -> usize {
        8 * (4 * k + 2 * n) + 64
    }
}

/// `lambda_max_j = max_{i >= free} |(Psi A^T b_j)_i|` for every row (`bs`: rows x n), chunked
/// over the threads.
pub(crate) fn lambda_max(sh: &Shared, bs: &[f64], chunk: usize) -> Vec<f64> {
    let (k, n) = (sh.k(), sh.n());
    let rows = bs.len() / n.max(1);
    let mut out = vec![0.0; rows];
    if n == 0 {
        return out;
    }
    bs.par_chunks(chunk * n)
        .zip(out.par_chunks_mut(chunk))
        .for_each(|(b, o)| {
            let c = o.len();
            let mut g = vec![0.0; c * k];
            let mut s = vec![0.0; c * k];
            sh.op.adjoint_batch(b, &mut g, c);
            sh.forward(&g, &mut s);
            for (v, row) in o.iter_mut().zip(s.chunks_exact(k)) {
                *v = row.iter().skip(sh.free).fold(0.0f64, |m, x| m.max(x.abs()));
            }
        });
    out
}

/// Solves every row (`bs`: rows x n data, `lams`: rows weights, `s`: rows x k warm start in,
/// solution out) in chunks of `chunk` rows over the threads. Returns each row's iterations.
pub(crate) fn solve_rows(
    sh: &Shared,
    bs: &[f64],
    lams: &[f64],
    s: &mut [f64],
    chunk: usize,
    control: &Control,
) -> Result<Vec<usize>, ReconError> {
    in_chunks(sh, bs, lams, s, chunk, false, control)
}

/// The debiasing refit of a lasso solution (the relaxed lasso, Meinshausen 2007): every row's
/// least-squares fit on the support of its warm start `s` (the coefficients that are nonzero,
/// plus the free ones), no penalty, the rest held at zero; `s` in, refitted out. The soft
/// threshold shrinks every kept coefficient by `lambda`; at a weight large enough to keep only
/// the coefficients the data support, the refit removes that bias. Returns each row's iterations.
///
/// With `cgls_refit` (Hadamard pairs), rows solved on the operator (no [`Dense`] columns) are
/// refitted by conjugate gradients on the normal equations restricted to the support
/// ([`cgls_chunk`]), which reach the least-squares fit in at most as many iterations as the
/// support has coefficients (in exact arithmetic). The projected FISTA before it, stopped by its step size, stopped far from it
/// where progress was slow: on the noise-free slide from half a Hadamard set, 16 more refits
/// from where it had stopped lowered the held-out residual from 7.1e-6 to 6.1e-8 on the same
/// support.
pub(crate) fn refit_rows(
    sh: &Shared,
    bs: &[f64],
    s: &mut [f64],
    chunk: usize,
    control: &Control,
) -> Result<Vec<usize>, ReconError> {
    let (k, n) = (sh.k(), sh.n());
    let rows = s.len() / k.max(1);
    if sh.dense.is_some() || !sh.cgls_refit {
        let lams = vec![0.0; rows];
        return in_chunks(sh, bs, &lams, s, chunk, true, control);
    }
    assert_eq!(bs.len(), rows * n);
    let chunk = chunk.max(1);
    let mut iterations = vec![0usize; rows];
    let results: Vec<Result<(), ReconError>> = s
        .par_chunks_mut(chunk * k)
        .zip(bs.par_chunks(chunk * n.max(1)))
        .zip(iterations.par_chunks_mut(chunk))
        .map(|((s, b), it)| cgls_chunk(sh, b, s, it, control))
        .collect();
    results.into_iter().collect::<Result<Vec<()>, _>>()?;
    Ok(iterations)
}

/// The refit of one chunk of rows ([`refit_rows`]): CGLS (Hestenes-Stiefel conjugate gradients
/// on `P Psi A^T A Psi^T P s = P Psi A^T b`, `P` the support of the warm start `out`, plus the
/// free coefficients), from the warm start, every row in its own recurrence; the rows still
/// iterating share one `apply_batch` and one `adjoint_batch` per iteration, like
/// [`fista_chunk`]. A row stops when its normal-equation residual `||P Psi A^T r||` is at most
/// `tol^2` (at least 1e-13) of `||P Psi A^T b||` (its value at `s = 0`), or after `max_iter`
/// iterations. A row's result depends only on its own data and warm start (any chunk, block or
/// shard).
fn cgls_chunk(
    sh: &Shared,
    bs: &[f64],
    out: &mut [f64],
    iterations: &mut [usize],
    control: &Control,
) -> Result<(), ReconError> {
    let (k, n) = (sh.k(), sh.n());
    let rows = iterations.len();
    if rows == 0 || k == 0 {
        return Ok(());
    }
    let mut keep: Vec<bool> = out
        .chunks_exact(k)
        .flat_map(|row| {
            row.iter()
                .enumerate()
                .map(|(i, v)| i < sh.free || *v != 0.0)
        })
        .collect();
    let mut ids: Vec<usize> = (0..rows).collect();
    let mut s = out.to_vec();
    let mut x = vec![0.0; rows * k];
    let mut z = vec![0.0; rows * k];
    let mut r = vec![0.0; rows * n];
    let mut q = vec![0.0; rows * n];
    // `||z||^2` over the support, zeroing `z` off it.
    let norm2 = |z: &mut [f64], keep: &[bool]| {
        z.iter_mut()
            .zip(keep)
            .map(|(v, &kept)| {
                if !kept {
                    *v = 0.0;
                }
                *v * *v
            })
            .sum::<f64>()
    };
    // The masked gradient at s = 0, for the stopping rule.
    sh.op.adjoint_batch(bs, &mut x, rows);
    sh.forward(&x, &mut z);
    let mut reference: Vec<f64> = z
        .chunks_exact_mut(k)
        .zip(keep.chunks_exact(k))
        .map(|(z, keep)| norm2(z, keep))
        .collect();
    // r = b - A Psi^T s, z = P Psi A^T r, p = z.
    sh.inverse(&s, &mut x);
    sh.op.apply_batch(&x, &mut r, rows);
    r.iter_mut().zip(bs).for_each(|(r, b)| *r = b - *r);
    sh.op.adjoint_batch(&r, &mut x, rows);
    sh.forward(&x, &mut z);
    let mut gamma: Vec<f64> = z
        .chunks_exact_mut(k)
        .zip(keep.chunks_exact(k))
        .map(|(z, keep)| norm2(z, keep))
        .collect();
    let mut p = z.clone();
    // `tol^2`, but not below what f64 sums of `n` products resolve.
    let eps = (sh.tol * sh.tol).max(1e-13);
    let eps2 = eps * eps;
    let mut active = rows;
    let mut it = 0;
    loop {
        let done: Vec<usize> = (0..active)
            .filter(|&a| gamma[a] <= eps2 * reference[a] || !gamma[a].is_finite())
            .collect();
        retire(&done, &mut active, (&mut ids, &mut s, out), k, |a, last| {
            p.copy_within(last * k..(last + 1) * k, a * k);
            keep.copy_within(last * k..(last + 1) * k, a * k);
            r.copy_within(last * n..(last + 1) * n, a * n);
            gamma[a] = gamma[last];
            reference[a] = reference[last];
        });
        if active == 0 || it >= sh.max_iter {
            break;
        }
        if control.is_cancelled() {
            return Err(ReconError::Cancelled);
        }
        it += 1;
        let (ka, na) = (active * k, active * n);
        // q = A Psi^T p; the step along p.
        sh.inverse(&p[..ka], &mut x[..ka]);
        sh.op.apply_batch(&x[..ka], &mut q[..na], active);
        for a in 0..active {
            let qa = &q[a * n..(a + 1) * n];
            let qq: f64 = qa.iter().map(|v| v * v).sum();
            let alpha = if qq > 0.0 { gamma[a] / qq } else { 0.0 };
            s[a * k..(a + 1) * k]
                .iter_mut()
                .zip(&p[a * k..(a + 1) * k])
                .for_each(|(s, p)| *s += alpha * p);
            r[a * n..(a + 1) * n]
                .iter_mut()
                .zip(qa)
                .for_each(|(r, q)| *r -= alpha * q);
        }
        // z = P Psi A^T r; the next direction.
        sh.op.adjoint_batch(&r[..na], &mut x[..ka], active);
        sh.forward(&x[..ka], &mut z[..ka]);
        for a in 0..active {
            let row = a * k..(a + 1) * k;
            let g = norm2(&mut z[row.clone()], &keep[row.clone()]);
            let beta = if gamma[a] > 0.0 { g / gamma[a] } else { 0.0 };
            p[row.clone()]
                .iter_mut()
                .zip(&z[row])
                .for_each(|(p, z)| *p = z + beta * *p);
            gamma[a] = g;
            iterations[ids[a]] += 1;
        }
    }
    for a in 0..active {
        let id = ids[a];
        out[id * k..(id + 1) * k].copy_from_slice(&s[a * k..(a + 1) * k]);
    }
    Ok(())
}

/// [`fista_chunk`] over chunks of `chunk` rows, in parallel.
fn in_chunks(
    sh: &Shared,
    bs: &[f64],
    lams: &[f64],
    s: &mut [f64],
    chunk: usize,
    refit: bool,
    control: &Control,
) -> Result<Vec<usize>, ReconError> {
    let (k, n) = (sh.k(), sh.n());
    let rows = lams.len();
    assert_eq!(bs.len(), rows * n);
    assert_eq!(s.len(), rows * k);
    let chunk = chunk.max(1);
    let mut iterations = vec![0usize; rows];
    if let Some(dense) = sh.dense {
        let results: Vec<Result<(), ReconError>> = s
            .par_chunks_mut(k)
            .zip(bs.par_chunks(n.max(1)))
            .zip(lams.par_iter())
            .zip(iterations.par_iter_mut())
            .map(|(((s, b), &lam), it)| {
                if control.is_cancelled() {
                    return Err(ReconError::Cancelled);
                }
                *it = dense.solve_row(sh, b, lam, s, refit);
                Ok(())
            })
            .collect();
        results.into_iter().collect::<Result<Vec<()>, _>>()?;
        return Ok(iterations);
    }
    let results: Vec<Result<(), ReconError>> = s
        .par_chunks_mut(chunk * k)
        .zip(bs.par_chunks(chunk * n.max(1)))
        .zip(lams.par_chunks(chunk))
        .zip(iterations.par_chunks_mut(chunk))
        .map(|(((s, b), l), it)| fista_chunk(sh, b, l, s, it, refit, control))
        .collect();
    results.into_iter().collect::<Result<Vec<()>, _>>()?;
    Ok(iterations)
}

#[inline(always)]
fn soft(v: f64, t: f64) -> f64 {
    if v > t {
        v - t
    } else if v < -t {
        v + t
    } else {
        0.0
    }
}

/// Retires the rows in slots `done` (ascending) of the `active` still iterating: each one's
/// iterate (row `a` of `s`) goes out to its original row `ids[a]` of `out`, and the last active
/// row moves into its slot, highest slot first so that a move never takes a retiring row;
/// `moved(a, last)` moves the caller's other per-row state the same way.
fn retire(
    done: &[usize],
    active: &mut usize,
    (ids, s, out): (&mut [usize], &mut [f64], &mut [f64]),
    k: usize,
    mut moved: impl FnMut(usize, usize),
) {
    for &a in done.iter().rev() {
        let id = ids[a];
        out[id * k..(id + 1) * k].copy_from_slice(&s[a * k..(a + 1) * k]);
        let last = *active - 1;
        if a != last {
            s.copy_within(last * k..(last + 1) * k, a * k);
            ids[a] = ids[last];
            moved(a, last);
        }
        *active -= 1;
    }
}

/// One chunk of rows (module docs). `out` holds the warm start and receives the solutions.
/// With `refit`, the coefficients that are zero in the warm start stay zero ([`refit_rows`]).
#[allow(clippy::too_many_arguments)]
fn fista_chunk(
    sh: &Shared,
    bs: &[f64],
    lams: &[f64],
    out: &mut [f64],
    iterations: &mut [usize],
    refit: bool,
    control: &Control,
) -> Result<(), ReconError> {
    let (k, n) = (sh.k(), sh.n());
    let rows = lams.len();
    if rows == 0 {
        return Ok(());
    }
    // Active rows, compacted: original index, iterate s, momentum point y, data b.
    let mut ids: Vec<usize> = (0..rows).collect();
    let mut s = out.to_vec();
    let mut y = out.to_vec();
    // The support each row keeps (refit only).
    let mut keep: Vec<bool> = if refit {
        out.chunks_exact(k)
            .flat_map(|row| {
                row.iter()
                    .enumerate()
                    .map(|(i, v)| i < sh.free || *v != 0.0)
            })
            .collect()
    } else {
        Vec::new()
    };
    let mut b = bs.to_vec();
    let mut lam: Vec<f64> = lams.to_vec();
    let mut momentum = vec![1.0f64; rows];
    let mut streak = vec![0u8; rows];
    let mut x = vec![0.0; rows * k];
    let mut g = vec![0.0; rows * k];
    let mut r = vec![0.0; rows * n];
    let inv_l = 1.0 / sh.lipschitz;
    let mut active = rows;
    let mut it = 0;
    while active > 0 && it < sh.max_iter {
        if control.is_cancelled() {
            return Err(ReconError::Cancelled);
        }
        it += 1;
        let (ka, na) = (active * k, active * n);
        // Gradient at y: Psi A^T (A Psi^T y - b).
        sh.inverse(&y[..ka], &mut x[..ka]);
        sh.op.apply_batch(&x[..ka], &mut r[..na], active);
        r[..na].iter_mut().zip(&b[..na]).for_each(|(r, b)| *r -= b);
        sh.op.adjoint_batch(&r[..na], &mut x[..ka], active);
        sh.forward(&x[..ka], &mut g[..ka]);
        let mut done = Vec::new();
        for a in 0..active {
            let row = a * k..(a + 1) * k;
            let (sr, yr, gr) = (&mut s[row.clone()], &mut y[row.clone()], &mut g[row]);
            let thresh = lam[a] * inv_l;
            let (mut restart_dot, mut diff2, mut new2) = (0.0, 0.0, 0.0);
            for i in 0..k {
                let v = yr[i] - gr[i] * inv_l;
                let new = if refit {
                    if keep[a * k + i] { v } else { 0.0 }
                } else if i < sh.free {
                    v
                } else {
                    soft(v, thresh)
                };
                let d = new - sr[i];
                restart_dot += (yr[i] - new) * d;
                diff2 += d * d;
                new2 += new * new;
                gr[i] = new;
            }
            let beta = if restart_dot > 0.0 {
                momentum[a] = 1.0;
                0.0
            } else {
                let next = 0.5 * (1.0 + (1.0 + 4.0 * momentum[a] * momentum[a]).sqrt());
                let beta = (momentum[a] - 1.0) / next;
                momentum[a] = next;
                beta
            };
            for i in 0..k {
                let new = gr[i];
                yr[i] = new + beta * (new - sr[i]);
                sr[i] = new;
            }
            iterations[ids[a]] += 1;
            if diff2 <= sh.tol * sh.tol * new2 {
                streak[a] += 1;
            } else {
                streak[a] = 0;
            }
            if streak[a] >= 3 {
                done.push(a);
            }
        }
        retire(&done, &mut active, (&mut ids, &mut s, out), k, |a, last| {
            y.copy_within(last * k..(last + 1) * k, a * k);
            b.copy_within(last * n..(last + 1) * n, a * n);
            if refit {
                keep.copy_within(last * k..(last + 1) * k, a * k);
            }
            lam[a] = lam[last];
            momentum[a] = momentum[last];
            streak[a] = streak[last];
        });
    }
    for a in 0..active {
        let id = ids[a];
        out[id * k..(id + 1) * k].copy_from_slice(&s[a * k..(a + 1) * k]);
    }
    Ok(())
}

/// `M = A Psi^T` (n data rows x k coefficients) held densely, one coefficient's column (`n`
/// values) after another, with the columns' squared norms: the l1 problem of every row solved by
/// cyclic coordinate descent with an active set (Friedman, Hastie and Tibshirani 2010, glmnet's
/// "active set" strategy): sweeps over the coefficients that are nonzero (and the free ones)
/// until a sweep moves them by at most `tol ||s||`, then one pass of the optimality conditions
/// over all the others (`|M_c^T r| <= lambda` for a coefficient at zero); the ones that violate
/// them join the active set and the sweeps go on. A row's model keeps a few hundred of `k`
/// coefficients, so a sweep costs `4 n` per active coefficient (a dot and an update of the
/// residual) where a FISTA iteration costs two products with `A` (`2 n k`) and two transforms.
/// Measured on 25 % Bernoulli rows of a 32x32 projector: 40-120 sweeps per row over the
/// continuation path (about 150 active of 256 rows: still ill-conditioned there), 2-6x less
/// time than FISTA at the same relight error (docs/benchmark-notes.md).
///
/// Used where `A` is a random pattern operator (no fast transform) and `M` fits the memory plan
/// ([`Dense::bytes`]). A row's solution depends only on its data, weight and warm start, so it is
/// the same in any block, shard or chunk; the optimality check's product with `A^T` follows the
/// operator's threading, recorded in the model like every other product.
pub(crate) struct Dense {
    n: usize,
    k: usize,
    cols: Vec<f64>,
    norms: Vec<f64>,
}

/// The fewest violators of the optimality conditions that join the active set in one pass.
const DENSE_MIN_JOIN: usize = 16;

/// Rows of `M` built per batched adjoint.
const DENSE_BUILD_BATCH: usize = 64;

impl Dense {
    /// Bytes `M` takes for `n` data rows and `k` coefficients.
    pub fn bytes(n: usize, k: usize) -> usize {
        8 * (n * k + k)
    }

    /// Builds `M` from the operator and transform of `sh`: row `j` of `M` is `Psi A^T e_j`.
    pub fn new(sh: &Shared) -> Dense {
        let (n, k) = (sh.n(), sh.k());
        let mut cols = vec![0.0; n * k];
        for j0 in (0..n).step_by(DENSE_BUILD_BATCH) {
            let c = DENSE_BUILD_BATCH.min(n - j0);
            let mut e = vec![0.0; c * n];
            for i in 0..c {
                e[i * n + j0 + i] = 1.0;
            }
            let mut g = vec![0.0; c * k];
            sh.op.adjoint_batch(&e, &mut g, c);
            let mut row = vec![0.0; c * k];
            sh.forward(&g, &mut row);
            for i in 0..c {
                for (col, v) in row[i * k..(i + 1) * k].iter().enumerate() {
                    cols[col * n + j0 + i] = *v;
                }
            }
        }
        let norms = cols.chunks_exact(n.max(1)).map(|c| dot(c, c)).collect();
        Dense { n, k, cols, norms }
    }

    /// `M s` (the fitted data of coefficients `s`), from the dense columns.
    #[cfg(test)]
    pub fn product(&self, s: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; self.n];
        for (c, &v) in s.iter().enumerate() {
            axpy(v, self.col(c), &mut out);
        }
        out
    }

    fn col(&self, c: usize) -> &[f64] {
        &self.cols[c * self.n..(c + 1) * self.n]
    }

    /// One row: `min 1/2 ||M s - b||^2 + lam ||s[free..]||_1` from the warm start `s` (with
    /// `refit`: least squares on the warm start's support and the free coefficients, the rest
    /// held at zero). At most `max_sweeps` sweeps; returns the sweeps made.
    pub fn solve_row(&self, sh: &Shared, b: &[f64], lam: f64, s: &mut [f64], refit: bool) -> usize {
        let (free, max_sweeps, tol) = (sh.free, sh.max_iter, sh.tol);
        let (n, k) = (self.n, self.k);
        let mut x = vec![0.0; k];
        let mut g = vec![0.0; k];
        debug_assert_eq!(b.len(), n);
        debug_assert_eq!(s.len(), k);
        let mut r = b.to_vec();
        for (c, &v) in s.iter().enumerate() {
            if v != 0.0 {
                axpy(-v, self.col(c), &mut r);
            }
        }
        let mut active: Vec<usize> = (0..k).filter(|&c| c < free || s[c] != 0.0).collect();
        let mut in_active = vec![false; k];
        active.iter().for_each(|&c| in_active[c] = true);
        let mut sweeps = 0;
        loop {
            // Sweeps over the active set until it settles.
            while sweeps < max_sweeps {
                sweeps += 1;
                let (moved2, norm2) = sweep(
                    &self.cols,
                    &self.norms,
                    n,
                    &active,
                    s,
                    &mut r,
                    lam,
                    if refit { k } else { free },
                );
                if moved2 <= tol * tol * norm2 {
                    break;
                }
            }
            if refit || sweeps >= max_sweeps {
                return sweeps;
            }
            // Coefficients the sweeps set to zero leave the active set (the check below brings
            // back any that should not be zero).
            active.retain(|&c| {
                let keep = c < free || s[c] != 0.0;
                in_active[c] = keep;
                keep
            });
            // The optimality conditions of the coefficients held at zero: the worst violators
            // join, at most as many as are active (and at least [`DENSE_MIN_JOIN`]), so that
            // the first pass from an empty model does not bring in every coefficient the data
            // correlate with.
            // The gradient `M^T r = Psi A^T r` by the operator (cheaper than k columns' dots).
            sh.op.adjoint(&r, &mut x);
            sh.forward(&x, &mut g);
            let mut violators: Vec<(f64, usize)> = (free..k)
                .filter(|&c| !in_active[c] && self.norms[c] > 0.0)
                .filter_map(|c| {
                    let excess = g[c].abs() - lam;
                    (excess > 0.0).then_some((excess / self.norms[c].sqrt(), c))
                })
                .collect();
            if violators.is_empty() {
                return sweeps;
            }
            let join = active.len().max(DENSE_MIN_JOIN);
            if violators.len() > join {
                violators
                    .select_nth_unstable_by(join, |a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
                violators.truncate(join);
            }
            for (_, c) in violators {
                in_active[c] = true;
                active.push(c);
            }
            active.sort_unstable();
        }
    }
}

avx2_dispatch! {
/// One sweep of coordinate descent over `active` (coefficients below `free` unpenalised):
/// updates `s` and the residual `r`; returns the sweep's squared change and the squared norm
/// of the active coefficients.
#[allow(clippy::too_many_arguments)]
fn sweep(
    cols: &[f64],
    norms: &[f64],
    n: usize,
    active: &[usize],
    s: &mut [f64],
    r: &mut [f64],
    lam: f64,
    free: usize,
) -> (f64, f64) {
    let (mut moved2, mut norm2) = (0.0, 0.0);
    for &c in active {
        let d = norms[c];
        if d <= 0.0 {
            continue;
        }
        let col = &cols[c * n..(c + 1) * n];
        let old = s[c];
        let z = old + dot(col, r) / d;
        let new = if c < free { z } else { soft(z, lam / d) };
        if new != old {
            axpy(old - new, col, r);
            s[c] = new;
            moved2 += (new - old) * (new - old);
        }
        norm2 += new * new;
    }
    (moved2, norm2)
}
}

/// `a . b`, eight partial sums (vectorised).
#[inline(always)]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += x[i] * y[i];
        }
    }
    acc.iter().sum::<f64>() + tail
}

/// `y += alpha x`.
#[inline(always)]
fn axpy(alpha: f64, x: &[f64], y: &mut [f64]) {
    y.iter_mut().zip(x).for_each(|(y, x)| *y += alpha * x);
}
