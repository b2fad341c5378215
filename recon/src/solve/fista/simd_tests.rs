//! The fused TV prox pass against the separate passes, and the AVX2 against the baseline
//! copies of the dispatched loops: bit for bit.

use super::tv_prox::{primal_from_dual, tv_dual_ascent, tv_prox_pass};
use super::*;
use crate::ops::HadamardOperator;
use crate::simd::force_baseline;
use crate::testutil::Rng;

fn bits(v: &[f64]) -> Vec<u64> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// The fused prox pass gives the bits of the two separate passes it replaces, on grids of
/// one band and of several (band edges at every kind of row), with and without the clip.
#[test]
fn fused_prox_pass_matches_the_separate_passes_bit_for_bit() {
    let mut rng = Rng::new(11);
    for (w, h) in [
        (1usize, 1usize),
        (1, 9),
        (7, 1),
        (13, 7),
        (64, 64),
        (37, 130),
        (130, 70),
        (64, 200),
        (2048, 5),
    ] {
        let grid = Grid::new(w, h);
        let k = w * h;
        let v: Vec<f64> = (0..k).map(|_| rng.normal()).collect();
        let mut u0: Vec<f64> = (0..2 * k).map(|_| 0.1 * rng.normal()).collect();
        project_discs(&mut u0, 0.07);
        for nonneg in [true, false] {
            let (mut u1, mut u2) = (u0.clone(), u0.clone());
            let (mut o1, mut o2) = (vec![0.0; k], vec![0.0; k]);
            // Twice: the second pass starts from a dual the first one moved.
            for pass in 0..2 {
                primal_from_dual(&u1, &v, grid, nonneg, &mut o1);
                let s1 = tv_dual_ascent(&mut u1, &o1, grid, 0.07);
                let s2 = tv_prox_pass(&mut u2, &v, grid, nonneg, 0.07, &mut o2);
                assert!(
                    bits(&u1) == bits(&u2) && bits(&o1) == bits(&o2),
                    "{w}x{h} nonneg {nonneg} pass {pass}: fused pass differs"
                );
                assert_eq!(
                    [s1.0, s1.1, s1.2].map(f64::to_bits),
                    [s2.0, s2.1, s2.2].map(f64::to_bits),
                    "{w}x{h}: sums"
                );
            }
            assert!(
                bits(&u1) != bits(&u0) || k == 1,
                "{w}x{h}: the passes moved the dual"
            );
        }
    }
}

/// The AVX2 and baseline copies of the dispatched loops give the same bits, kernel by kernel
/// and through a whole TV solve (odd sizes exercise the tails of the vector loops). On a CPU
/// without AVX2 both runs take the baseline copy and the test checks determinism only.
#[test]
fn avx2_and_baseline_copies_agree_bit_for_bit() {
    let mut rng = Rng::new(5);
    for (w, h) in [(1usize, 1usize), (3, 5), (13, 7), (64, 64), (37, 130)] {
        let grid = Grid::new(w, h);
        let k = w * h;
        let t: Vec<f64> = (0..k).map(|_| rng.uniform()).collect();
        let v: Vec<f64> = (0..k).map(|_| rng.normal()).collect();
        let u0: Vec<f64> = (0..2 * k).map(|_| 0.1 * rng.normal()).collect();
        let run = |baseline: bool| {
            force_baseline(baseline);
            let mut u = u0.clone();
            project_discs(&mut u, 0.05);
            let mut out = vec![0.0; k];
            let fused = tv_prox_pass(&mut u.clone(), &v, grid, true, 0.05, &mut out);
            let sums = tv_dual_ascent(&mut u, &t, grid, 0.05);
            let sums = (sums.0 + fused.0, sums.1 + fused.1, sums.2 + fused.2);
            let mut f = t.clone();
            f.resize(k.next_power_of_two(), 0.25);
            crate::fwht::fwht(&mut f);
            (
                bits(&u),
                bits(&out),
                [sums.0.to_bits(), sums.1.to_bits(), sums.2.to_bits()],
                bits(&f),
            )
        };
        let (wide, base) = (run(false), run(true));
        assert!(
            wide == base,
            "{w}x{h}: the AVX2 and baseline kernels differ"
        );
    }
    // A whole solve: TV on a 32x32 Hadamard subset.
    let spec = helmholtz_proto::PatternSpec::new(
        helmholtz_proto::Family::Hadamard {
            ordering: helmholtz_proto::HadamardOrdering::RussianDoll,
        },
        32,
        32,
        410,
        0,
    )
    .unwrap();
    let op = HadamardOperator::from_spec(&spec, 410).unwrap();
    let truth: Vec<f64> = (0..1024)
        .map(|i| {
            if (i % 32) > 10 && (i / 32) < 20 {
                1.0
            } else {
                0.2
            }
        })
        .collect();
    let mut b = vec![0.0; op.rows()];
    op.apply(&truth, &mut b);
    let opts = SolveOptions {
        lambda: Lambda::Relative(1e-3),
        max_iter: 60,
        ..SolveOptions::default()
    };
    let solve = |baseline: bool| {
        force_baseline(baseline);
        bits(
            &tv_fista(&op, Grid::new(32, 32), &b, &opts, &Control::new())
                .unwrap()
                .t,
        )
    };
    let (wide, base) = (solve(false), solve(true));
    force_baseline(false);
    assert!(
        wide == base,
        "a TV solve differs between the AVX2 and baseline copies"
    );
}
