//! The DCT's three paths timed against each other: the cosine matrix (O(N^2) per row, what
//! sides that are not powers of two used before), `rustdct`'s planned transform, and the
//! hand-written radix-2 path (powers of two only). Run with
//! `cargo test -p helmholtz-recon --lib transforms::dct_bench -- --ignored --nocapture`.
//!
//! Square images, forward + inverse per call, best of 5 interleaved rounds (each round times
//! every path of a side once, so load on the shared machine hits them alike).
//! Measured 2026-11-25 on 2 cores shared with other builds, dev profile (optimised).
//!
//! Three runs of the command above, one after the other (ms; ratio > 1: rustdct faster):
//!
//! ```text
//! side | matrix                  | rustdct              | radix-2             | matrix/rustdct | radix-2/rustdct
//!   48 | 0.173  0.099  0.162     | 0.130  0.116  0.135  | -                   | 1.3  0.9  1.2  | -
//!   64 | 0.305  0.310  0.353     | 0.104  0.105  0.115  | 0.098  0.103  0.093 | 2.9  3.0  3.1  | 0.94 0.98 0.81
//!   96 | 1.348  1.176  1.321     | 0.469  0.477  0.528  | -                   | 2.9  2.5  2.5  | -
//!  100 | 1.374  1.181  1.327     | 0.878  0.684  0.778  | -                   | 1.6  1.7  1.7  | -
//!  128 | 2.801  2.621  2.845     | 0.556  0.585  0.568  | 0.467  0.402  0.488 | 5.0  4.5  5.0  | 0.84 0.69 0.86
//!  200 | 10.694 10.326 6.297     | 3.007  2.893  1.606  | -                   | 3.6  3.6  3.9  | -
//!  256 | 21.392 22.511 21.757    | 3.797  3.966  3.562  | 2.538  3.616  3.182 | 5.6  5.7  6.1  | 0.67 0.91 0.89
//!  384 | 78.136 76.476 63.028    | 8.758  9.205  8.569  | -                   | 8.9  8.3  7.4  | -
//!  512 | 217.118 213.295 211.581 | 18.604 15.975 19.453 | 16.669 17.586 18.401| 11.7 13.4 10.9 | 0.90 1.10 0.95
//! ```
//!
//! rustdct beats the matrix from side 64 up (1.6x at 100 to 13x at 512) and is level with it at
//! 48; the radix-2 path is faster than rustdct on 64, 128 and 256 in every run and on 512 in two
//! of three (the third 10 % slower, within the spread of the runs).
//!
//! So `Dct2d::new` keeps the radix-2 path on powers of two and uses rustdct on the other sides.

use std::time::Instant;

use super::dct::DctPath;
use super::*;
use crate::linop::test_vector;

/// Best-so-far seconds per call; one sample runs calls for at least 30 ms.
fn sample(f: &mut dyn FnMut()) -> f64 {
    let t0 = Instant::now();
    let mut calls = 0u32;
    while t0.elapsed().as_secs_f64() < 0.03 || calls == 0 {
        f();
        calls += 1;
    }
    t0.elapsed().as_secs_f64() / calls as f64
}

#[test]
#[ignore]
fn bench_dct_paths() {
    println!("side | matrix | rustdct | radix-2 | matrix/rustdct | radix-2/rustdct (ms, fwd+inv)");
    for side in [48usize, 64, 96, 100, 128, 200, 256, 384, 512] {
        let k = side * side;
        let x = test_vector(k, 1);
        let mut paths = vec![
            ("matrix", Dct2d::with_matrices(side, side)),
            ("rustdct", Dct2d::with_paths(side, side, DctPath::Planned)),
        ];
        if side.is_power_of_two() {
            paths.push(("radix-2", Dct2d::with_paths(side, side, DctPath::Radix2)));
        }
        let mut best = vec![f64::INFINITY; paths.len()];
        let (mut c, mut back) = (vec![0.0; k], vec![0.0; k]);
        for _round in 0..5 {
            for (i, (_, t)) in paths.iter().enumerate() {
                let mut f = || {
                    t.apply(&x, &mut c);
                    t.adjoint(&c, &mut back);
                };
                f();
                best[i] = best[i].min(sample(&mut f));
            }
        }
        let ms: Vec<f64> = best.iter().map(|s| s * 1e3).collect();
        let radix = ms.get(2).copied();
        println!(
            "{side} | {:.3} | {:.3} | {} | {:.1}x | {}",
            ms[0],
            ms[1],
            radix.map_or("-".into(), |r| format!("{r:.3}")),
            ms[0] / ms[1],
            radix.map_or("-".into(), |r| format!("{:.2}x", r / ms[1])),
        );
    }
}
