//! Transform speeds. Run with
//! `cargo test -p helmholtz-recon --lib transforms::bench -- --ignored --nocapture`.

use std::time::Instant;

use super::*;
use crate::linop::test_vector;

fn time(mut f: impl FnMut()) -> f64 {
    f();
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let t0 = Instant::now();
        let mut calls = 0u32;
        while t0.elapsed().as_secs_f64() < 0.04 || calls == 0 {
            f();
            calls += 1;
        }
        best = best.min(t0.elapsed().as_secs_f64() / calls as f64);
    }
    best
}

#[test]
#[ignore]
fn bench_transforms() {
    for (w, h) in [
        (64usize, 64usize),
        (128, 128),
        (158, 210),
        (256, 256),
        (512, 512),
    ] {
        let k = w * h;
        let x = test_vector(k, 1);
        let mut c = vec![0.0; k];
        let mut line = format!("{w}x{h}:");
        for kind in TransformKind::ALL {
            let t = kind.build(w, h);
            let f = time(|| t.apply(&x, &mut c));
            let i = time(|| t.adjoint(&x, &mut c));
            line += &format!(" {} {:.3}/{:.3} ms", kind.name(), f * 1e3, i * 1e3);
        }
        let t = Dct2d::with_matrices(w, h);
        let f = time(|| t.apply(&x, &mut c));
        line += &format!(" dct-matrix {:.3} ms", f * 1e3);
        let d = Gradient::new(w, h);
        let mut g = vec![0.0; 2 * k];
        let f = time(|| d.apply(&x, &mut g));
        let gg = test_vector(2 * k, 2);
        let i = time(|| d.adjoint(&gg, &mut c));
        line += &format!(
            " | gradient {:.3}/{:.3} ms (forward/adjoint)",
            f * 1e3,
            i * 1e3
        );
        println!("{line}");
    }
}
