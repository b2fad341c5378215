//! Speed of the operators against a dense product and a naive per-bit loop. Run with
//! `cargo test -p helmholtz-recon --lib ops::bench -- --ignored --nocapture --test-threads 1`
//! (the dev profile builds this crate at opt-level 3). Wall times are best-of-5; "cpu" is CPU time
//! per call over all threads, which shows contention from other work on the machine.

use std::time::Instant;

use helmholtz_proto::{Family, HadamardOrdering, PatternSpec};

use super::*;
use crate::linop::{DenseOperator, test_vector};
use crate::ops::bits::Kernel;

/// CPU nanoseconds used so far by all threads of this process (`/proc/self/task/*/schedstat`,
/// first field); robust to other work sharing the machine, unlike wall time.
pub(crate) fn cpu_ns() -> u64 {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return 0;
    };
    dir.filter_map(|e| e.ok())
        .filter_map(|e| std::fs::read_to_string(e.path().join("schedstat")).ok())
        .filter_map(|s| {
            s.split_whitespace()
                .next()
                .and_then(|v| v.parse::<u64>().ok())
        })
        .sum()
}

/// (wall seconds per call: best of 5 rounds of >= 40 ms each; CPU seconds per call, all threads,
/// over all rounds).
pub(crate) fn time2(mut f: impl FnMut()) -> (f64, f64) {
    f();
    let mut best = f64::INFINITY;
    let (c0, mut total_calls) = (cpu_ns(), 0u64);
    for _ in 0..5 {
        let t0 = Instant::now();
        let mut calls = 0u32;
        while t0.elapsed().as_secs_f64() < 0.04 || calls == 0 {
            f();
            calls += 1;
        }
        total_calls += calls as u64;
        best = best.min(t0.elapsed().as_secs_f64() / calls as f64);
    }
    (best, (cpu_ns() - c0) as f64 * 1e-9 / total_calls as f64)
}

/// Wall seconds per call (see [`time2`]).
fn time(f: impl FnMut()) -> f64 {
    time2(f).0
}

fn ms(s: f64) -> String {
    format!("{:.3} ms", s * 1e3)
}

/// Dense f64 matrix of the first `rows` rows of a bit matrix.
fn dense_of(bits: &BitMatrix, rows: usize) -> DenseOperator {
    let k = bits.cols();
    let mut data = vec![0.0; rows * k];
    for r in 0..rows {
        for c in 0..k {
            if bits.get(r, c) {
                data[r * k + c] = 1.0;
            }
        }
    }
    DenseOperator::new(rows, k, data)
}

fn naive_forward(bits: &BitMatrix, x: &[f64], y: &mut [f64]) {
    for (r, yr) in y.iter_mut().enumerate() {
        let mut s = 0.0;
        for (j, &xj) in x.iter().enumerate() {
            if bits.get(r, j) {
                s += xj;
            }
        }
        *yr = s;
    }
}

fn naive_adjoint(bits: &BitMatrix, y: &[f64], x: &mut [f64]) {
    x.fill(0.0);
    for (r, &yr) in y.iter().enumerate() {
        for (j, xj) in x.iter_mut().enumerate() {
            if bits.get(r, j) {
                *xj += yr;
            }
        }
    }
}

#[test]
#[ignore]
fn bench_bernoulli() {
    println!("threads: {}", rayon::current_num_threads());
    for side in [64u32, 128, 256] {
        let k = (side * side) as usize;
        let n = k / 10;
        let spec =
            PatternSpec::new(Family::Bernoulli { fill: 0.5 }, side, side, n as u64, 1).unwrap();
        let t0 = Instant::now();
        let op = BernoulliOperator::from_spec(&spec, n as u64).unwrap();
        let plan = t0.elapsed().as_secs_f64();
        let x = test_vector(k, 1);
        let yv = test_vector(n, 2);
        let (mut y, mut xo) = (vec![0.0; n], vec![0.0; k]);
        let (apply, apply_cpu) = time2(|| op.apply(&x, &mut y));
        let (adjoint, adjoint_cpu) = time2(|| op.adjoint(&yv, &mut xo));
        let xs = test_vector(4 * k, 3);
        let ys = test_vector(4 * n, 4);
        let (mut yb, mut xb) = (vec![0.0; 4 * n], vec![0.0; 4 * k]);
        let apply4 = time(|| op.apply_batch(&xs, &mut yb, 4)) / 4.0;
        let adjoint4 = time(|| op.adjoint_batch(&ys, &mut xb, 4)) / 4.0;
        let bits = op.patterns();
        let naive_f = time(|| naive_forward(bits, &x, &mut y));
        let naive_a = time(|| naive_adjoint(bits, &yv, &mut xo));
        // Dense f64: all rows up to 128 x 128 (215 MB); at 256 x 256 (3.4 GB) a tenth of the
        // rows, scaled by 10 (the product is linear in rows).
        let dense_rows = if side <= 128 { n } else { n / 10 };
        let dense = dense_of(bits, dense_rows);
        let mut yd = vec![0.0; dense_rows];
        let scale = n as f64 / dense_rows as f64;
        let dense_f = time(|| dense.apply(&x, &mut yd)) * scale;
        let dense_a = time(|| dense.adjoint(&yv[..dense_rows], &mut xo)) * scale;
        drop(dense);
        println!(
            "bernoulli {side}x{side} n={n} (10%): plan {}, {} MB | apply {} adjoint {} \
             (cpu {} / {}) | batch-4 per vector: apply {} adjoint {} | dense f64{}: apply {} adjoint {} | \
             naive per-bit: apply {} adjoint {}",
            ms(plan),
            op.memory_bytes() / 1_000_000,
            ms(apply),
            ms(adjoint),
            ms(apply_cpu),
            ms(adjoint_cpu),
            ms(apply4),
            ms(adjoint4),
            if dense_rows < n {
                " (from n/10 rows, x10)"
            } else {
                ""
            },
            ms(dense_f),
            ms(dense_a),
            ms(naive_f),
            ms(naive_a),
        );
        let centred = CentredOperator::augmented(Box::new(
            BernoulliOperator::from_spec(&spec, n as u64).unwrap(),
        ));
        let mut yc = vec![0.0; n + 1];
        let yc_in = test_vector(n + 1, 5);
        let c_apply = time(|| centred.apply(&x, &mut yc));
        let c_adjoint = time(|| centred.adjoint(&yc_in, &mut xo));
        let norm_p = crate::linop::spectral_norm(&op, 100, 1e-4);
        let norm_c = crate::linop::spectral_norm(&centred, 100, 1e-4);
        println!(
            "  centred + dc row (weight {:.3}): apply {} adjoint {}; ||P|| = {norm_p:.1}, \
             ||[A_c; w m]|| = {norm_c:.1}: step sizes {:.0}x larger",
            centred.dc_weight().unwrap(),
            ms(c_apply),
            ms(c_adjoint),
            (norm_p / norm_c).powi(2)
        );
    }
}

#[test]
#[ignore]
fn bench_hadamard() {
    println!("threads: {}", rayon::current_num_threads());
    for side in [16u32, 32, 64, 128, 256] {
        let k = (side * side) as usize;
        let m = k / 10;
        let spec = PatternSpec::new(
            Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll,
            },
            side,
            side,
            2 * k as u64,
            0,
        )
        .unwrap();
        let op = HadamardOperator::from_spec(&spec, 2 * m as u64).unwrap();
        let x = test_vector(k, 1);
        let yv = test_vector(m, 2);
        let (mut y, mut xo) = (vec![0.0; m], vec![0.0; k]);
        let apply = time(|| op.apply(&x, &mut y));
        let adjoint = time(|| op.adjoint(&yv, &mut xo));
        let xs = test_vector(4 * k, 3);
        let mut yb = vec![0.0; 4 * m];
        let apply4 = time(|| op.apply_batch(&xs, &mut yb, 4)) / 4.0;
        // Dense m x k (3.4 GB at 256 x 256: a tenth of the rows, scaled).
        let dense_rows = if side <= 128 { m } else { m / 10 };
        let mut data = vec![0.0; dense_rows * k];
        {
            let sub = HadamardOperator::new(side, side, HadamardOrdering::RussianDoll, dense_rows);
            let mut col = vec![0.0; dense_rows];
            let mut e = vec![0.0; k];
            for j in 0..k {
                e[j] = 1.0;
                sub.apply(&e, &mut col);
                e[j] = 0.0;
                for (r, v) in col.iter().enumerate() {
                    data[r * k + j] = *v;
                }
            }
        }
        let dense = DenseOperator::new(dense_rows, k, data);
        let scale = m as f64 / dense_rows as f64;
        let mut yd = vec![0.0; dense_rows];
        let dense_f = time(|| dense.apply(&x, &mut yd)) * scale;
        let dense_a = time(|| dense.adjoint(&yv[..dense_rows], &mut xo)) * scale;
        println!(
            "hadamard {side}x{side} m={m} (10% of frames): fwht apply {} adjoint {} \
             (batch-4 apply per vector {}) | dense f64{}: apply {} adjoint {} | {}",
            ms(apply),
            ms(adjoint),
            ms(apply4),
            if dense_rows < m {
                " (from m/10 rows, x10)"
            } else {
                ""
            },
            ms(dense_f),
            ms(dense_a),
            if dense_f < apply {
                "dense wins"
            } else {
                "fwht wins"
            },
        );
    }
}

#[test]
#[ignore]
fn bench_other_families() {
    for side in [64u32, 128] {
        let k = (side * side) as usize;
        let n = k / 10;
        for family in [
            Family::Speckle { grain: 1 },
            Family::Speckle { grain: 4 },
            Family::Raster { block: 1, scans: 1 },
        ] {
            let spec = PatternSpec::new(family.clone(), side, side, n as u64, 1).unwrap();
            let t0 = Instant::now();
            let op = measurement_operator(&spec, n as u64);
            let plan = t0.elapsed().as_secs_f64();
            let x = test_vector(k, 1);
            let yv = test_vector(n, 2);
            let (mut y, mut xo) = (vec![0.0; n], vec![0.0; k]);
            let apply = time(|| op.apply(&x, &mut y));
            let adjoint = time(|| op.adjoint(&yv, &mut xo));
            let xs = test_vector(4 * k, 3);
            let mut yb = vec![0.0; 4 * n];
            let apply4 = time(|| op.apply_batch(&xs, &mut yb, 4)) / 4.0;
            println!(
                "{family:?} {side}x{side} n={n}: plan {} apply {} adjoint {} batch-4 apply per vector {}",
                ms(plan),
                ms(apply),
                ms(adjoint),
                ms(apply4)
            );
        }
    }
}

/// The packed-bit kernels side by side at the 128 x 128, 10 % size: the portable byte-table
/// kernel with one vector and batches of 2 and 4, and (where the CPU has AVX-512F) the nibble
/// kernel, forward (`A x`, 1,638 x 16,384 bits) and adjoint (`A^T y`, the transpose). Wall time
/// per vector (best of 5) and CPU time per vector (all threads).
#[test]
#[ignore]
fn bench_bits_kernel() {
    let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 128, 128, 1638, 1).unwrap();
    let op = BernoulliOperator::from_spec(&spec, 1638).unwrap();
    let (a, at) = (op.patterns(), op.patterns().transpose());
    let (n, k) = (a.rows(), a.cols());
    let pool = crate::ops::scratch::Pool::new();
    let mut runs = vec![
        (Kernel::Bytes, 1usize),
        (Kernel::Bytes, 2),
        (Kernel::Bytes, 4),
    ];
    if crate::simd::avx512() {
        runs.push((Kernel::Nibbles, 1));
    }
    for (kernel, batch) in runs {
        let xs = test_vector(batch * k, 3);
        let ys = test_vector(batch * n, 4);
        let (mut yb, mut xb) = (vec![0.0; batch * n], vec![0.0; batch * k]);
        let (fw, fc) = time2(|| a.matvec_batch_with(&xs, &mut yb, batch, &pool, kernel));
        let (aw, ac) = time2(|| at.matvec_batch_with(&ys, &mut xb, batch, &pool, kernel));
        let b = batch as f64;
        println!(
            "bits 1638x16384 {kernel:?} batch {batch}: per vector apply {} (cpu {}) adjoint {} (cpu {})",
            ms(fw / b),
            ms(fc / b),
            ms(aw / b),
            ms(ac / b)
        );
    }
}
