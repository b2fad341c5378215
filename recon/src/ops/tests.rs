//! Operator tests: adjoints, equality with naive constructions from the pattern generator,
//! batching, conditioning.

use helmholtz_proto::{Family, HadamardOrdering, PatternGenerator, PatternSpec};

use super::*;
use crate::linop::{DenseOperator, adjoint_mismatch, dot, spectral_norm, test_vector};

fn spec(family: Family, w: u32, h: u32, count: u64, seed: u64) -> PatternSpec {
    PatternSpec::new(family, w, h, count, seed).unwrap()
}

/// The first `rows` patterns as a dense matrix, from `fill_values` (the definition).
fn naive_patterns(spec: &PatternSpec, rows: u64) -> DenseOperator {
    let g = PatternGenerator::new(spec);
    let k = spec.pixels();
    let mut p = vec![0f32; k];
    let mut data = Vec::with_capacity(rows as usize * k);
    for i in 0..rows {
        g.fill_values(i, &mut p);
        data.extend(p.iter().map(|&v| v as f64));
    }
    DenseOperator::new(rows as usize, k, data)
}

fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// Batched products equal one-by-one products.
fn check_batches(op: &dyn LinearOperator, what: &str) {
    let (m, n) = (op.rows(), op.cols());
    for batch in [1usize, 2, 3, 5, 8] {
        let xs = test_vector(n * batch, 11);
        let ys = test_vector(m * batch, 12);
        let mut got_y = vec![f64::NAN; m * batch];
        let mut got_x = vec![f64::NAN; n * batch];
        op.apply_batch(&xs, &mut got_y, batch);
        op.adjoint_batch(&ys, &mut got_x, batch);
        for b in 0..batch {
            let mut y = vec![0.0; m];
            let mut x = vec![0.0; n];
            op.apply(&xs[b * n..(b + 1) * n], &mut y);
            op.adjoint(&ys[b * m..(b + 1) * m], &mut x);
            let scale = 1.0 + y.iter().chain(&x).fold(0.0f64, |a, v| a.max(v.abs()));
            assert!(
                max_diff(&y, &got_y[b * m..(b + 1) * m]) <= 1e-12 * scale,
                "{what} batch {batch}"
            );
            assert!(
                max_diff(&x, &got_x[b * n..(b + 1) * n]) <= 1e-12 * scale,
                "{what} batch {batch}"
            );
        }
    }
}

/// `op` equals `want` entry by entry (materialised column by column).
fn check_equals(op: &dyn LinearOperator, want: &DenseOperator, tol: f64, what: &str) {
    assert_eq!(
        (op.rows(), op.cols()),
        (want.rows(), want.cols()),
        "{what} shape"
    );
    let got = DenseOperator::from_operator(op);
    assert!(
        max_diff(got.data(), want.data()) <= tol,
        "{what}: forward differs"
    );
    // And the adjoint against the transpose, through the dense operator's own adjoint.
    let y = test_vector(op.rows(), 5);
    let (mut a, mut b) = (vec![0.0; op.cols()], vec![0.0; op.cols()]);
    op.adjoint(&y, &mut a);
    want.adjoint(&y, &mut b);
    assert!(
        max_diff(&a, &b) <= tol * (1.0 + op.rows() as f64),
        "{what}: adjoint differs"
    );
}

#[test]
fn bernoulli_matches_the_generator() {
    // Pixel counts that are not multiples of 64, non-square grids, several fills.
    for (w, h, n, fill) in [
        (7u32, 5u32, 13u64, 0.5),
        (13, 11, 70, 0.5),
        (64, 1, 3, 0.3),
        (10, 10, 129, 0.95),
        (16, 16, 64, 0.5),
        (33, 3, 200, 0.05),
    ] {
        let s = spec(Family::Bernoulli { fill }, w, h, n + 5, 42);
        let op = BernoulliOperator::from_spec(&s, n).unwrap();
        let what = format!("bernoulli {w}x{h} n={n} q={fill}");
        check_equals(&op, &naive_patterns(&s, n), 1e-12, &what);
        assert!(adjoint_mismatch(&op, 3) < 1e-12, "{what}");
        check_batches(&op, &what);
        let want_sums: Vec<f64> = naive_patterns(&s, n)
            .data()
            .chunks_exact(s.pixels())
            .map(|r| r.iter().sum())
            .collect();
        assert_eq!(op.row_sums(), &want_sums[..]);
    }
}

#[test]
fn bernoulli_parallel_path_matches_naive() {
    // Large enough for the multithreaded split (and several table chunks).
    let s = spec(Family::Bernoulli { fill: 0.5 }, 48, 40, 300, 7);
    let op = BernoulliOperator::from_spec(&s, 300).unwrap();
    let dense = naive_patterns(&s, 300);
    let x = test_vector(s.pixels(), 1);
    let (mut a, mut b) = (vec![0.0; 300], vec![0.0; 300]);
    op.apply(&x, &mut a);
    dense.apply(&x, &mut b);
    assert!(max_diff(&a, &b) < 1e-11);
    let y = test_vector(300, 2);
    let (mut a, mut b) = (vec![0.0; s.pixels()], vec![0.0; s.pixels()]);
    op.adjoint(&y, &mut a);
    dense.adjoint(&y, &mut b);
    assert!(max_diff(&a, &b) < 1e-11);
    assert!(adjoint_mismatch(&op, 9) < 1e-12);
    check_batches(&op, "bernoulli 48x40");
}

#[test]
fn binary_operator_takes_any_binary_family() {
    // Raw Hadamard frames and raster blocks as packed bits.
    let s = spec(
        Family::Hadamard {
            ordering: HadamardOrdering::Zigzag,
        },
        8,
        4,
        64,
        0,
    );
    let op = BinaryOperator::from_spec(&s, 64).unwrap();
    check_equals(
        &op,
        &naive_patterns(&s, 64),
        1e-12,
        "hadamard frames as bits",
    );
    let s = spec(Family::Raster { block: 3, scans: 3 }, 10, 7, 30, 0);
    let op = BinaryOperator::from_spec(&s, 30).unwrap();
    check_equals(&op, &naive_patterns(&s, 30), 1e-12, "raster as bits");
    let s = spec(Family::Speckle { grain: 1 }, 4, 4, 3, 0);
    assert_eq!(
        BinaryOperator::from_spec(&s, 3).unwrap_err(),
        OpError::NotBinary("speckle")
    );
}

#[test]
fn hadamard_matches_split_pairs_in_every_ordering() {
    for (w, h) in [(1u32, 1u32), (8, 4), (4, 16), (16, 16), (2, 1)] {
        let k = (w * h) as u64;
        for ordering in HadamardOrdering::ALL {
            for frames in [2 * k, k, 2] {
                let frames = frames.max(2) / 2 * 2;
                let s = spec(Family::Hadamard { ordering }, w, h, 2 * k, 0);
                let op = HadamardOperator::from_spec(&s, frames).unwrap();
                let what = format!("hadamard {w}x{h} {ordering:?} frames={frames}");
                assert_eq!(op.rows() as u64, frames / 2);
                // Naive: row r = (P+ - P-) / sqrt(k) from the generator.
                let raw = naive_patterns(&s, frames);
                let kk = k as usize;
                let mut data = Vec::new();
                for r in 0..op.rows() {
                    let (plus, minus) =
                        (&raw.data()[2 * r * kk..], &raw.data()[(2 * r + 1) * kk..]);
                    data.extend((0..kk).map(|j| (plus[j] - minus[j]) / (k as f64).sqrt()));
                }
                let want = DenseOperator::new(op.rows(), kk, data);
                check_equals(&op, &want, 1e-12, &what);
                assert!(adjoint_mismatch(&op, 4) < 1e-12, "{what}");
                check_batches(&op, &what);
                // A A^T = I.
                let y = test_vector(op.rows(), 8);
                let (mut x, mut back) = (vec![0.0; kk], vec![0.0; op.rows()]);
                op.adjoint(&y, &mut x);
                op.apply(&x, &mut back);
                assert!(max_diff(&y, &back) < 1e-12, "{what}: A A^T != I");
            }
        }
    }
}

#[test]
fn hadamard_parallel_batch_and_large_sizes() {
    // 64 x 32: parallel batches; 256 x 256: parallel fwht inside.
    for (w, h) in [(64u32, 32u32), (256, 256)] {
        let k = (w * h) as u64;
        let s = spec(
            Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll,
            },
            w,
            h,
            2 * k,
            0,
        );
        let op = HadamardOperator::from_spec(&s, k / 5 * 2).unwrap();
        assert!(adjoint_mismatch(&op, 1) < 1e-12);
        check_batches(&op, "hadamard large");
    }
}

#[test]
fn split_pairs_cancel_the_dark_level_and_monitor_drift() {
    let (w, h) = (8u32, 8u32);
    let k = 64usize;
    let s = spec(
        Family::Hadamard {
            ordering: HadamardOrdering::Sequency,
        },
        w,
        h,
        128,
        0,
    );
    let frames = 40u64;
    let op = HadamardOperator::from_spec(&s, frames).unwrap();
    let t = crate::testutil::random_scene(k, 0.0, 1.0, 3);
    let raw = naive_patterns(&s, frames);
    let dark = 0.37;
    let mut buckets = vec![0.0; frames as usize];
    raw.apply(&t, &mut buckets);
    buckets.iter_mut().for_each(|c| *c += dark);
    let pairs = op.split_pairs(&buckets);
    let mut want = vec![0.0; op.rows()];
    op.apply(&t, &mut want);
    assert!(max_diff(&pairs.data, &want) < 1e-12);
    let total: f64 = t.iter().sum();
    assert!(
        pairs
            .sums
            .iter()
            .all(|s| (s - (total + 2.0 * dark)).abs() < 1e-9)
    );
    assert!(pairs.sum_relative_spread < 1e-12);
    // Sequency row 0 is natural row 0: its P- frame is all-off.
    assert!((pairs.dark.unwrap() - dark).abs() < 1e-12);

    // Drift: a 10 % gain ramp shows in the spread; channel selection.
    let mut two = Vec::new();
    for (i, c) in buckets.iter().enumerate() {
        two.push(0.0);
        two.push(c * (1.0 + 0.1 * i as f64 / frames as f64));
    }
    let drift = op.split_pairs_channel(&two, 2, 1);
    assert!(
        drift.sum_relative_spread > 0.02,
        "{}",
        drift.sum_relative_spread
    );
    assert_eq!(op.split_pairs_channel(&two, 2, 0).sum_mean, 0.0);
}

#[test]
fn raster_matches_the_generator() {
    for (w, h, block, n) in [
        (10u32, 7u32, 3u32, 30u64),
        (10, 7, 1, 70),
        (10, 7, 1, 25),
        (5, 9, 1, 100),
        (6, 6, 6, 2),
    ] {
        let s = spec(Family::raster_covering(block, w, h, n), w, h, n, 0);
        let op = RasterOperator::from_spec(&s, n).unwrap();
        let what = format!("raster {w}x{h} b{block} n={n}");
        check_equals(&op, &naive_patterns(&s, n), 1e-12, &what);
        assert!(adjoint_mismatch(&op, 2) < 1e-12, "{what}");
        check_batches(&op, &what);
    }
}

#[test]
fn speckle_matches_the_generator() {
    for (w, h, grain, n) in [
        (10u32, 7u32, 1u32, 20u64),
        (10, 7, 3, 20),
        (16, 16, 4, 50),
        (5, 3, 5, 4),
        (40, 40, 1, 60),
    ] {
        let s = spec(Family::Speckle { grain }, w, h, n, 9);
        let op = SpeckleOperator::from_spec(&s, n).unwrap();
        let what = format!("speckle {w}x{h} g{grain} n={n}");
        check_equals(&op, &naive_patterns(&s, n), 1e-12, &what);
        assert!(adjoint_mismatch(&op, 6) < 1e-12, "{what}");
        check_batches(&op, &what);
    }
}

#[test]
fn measurement_operator_picks_and_checks() {
    let cases = [
        (Family::Bernoulli { fill: 0.5 }, 100u64, 100usize),
        (
            Family::Hadamard {
                ordering: HadamardOrdering::Natural,
            },
            100,
            50,
        ),
        (Family::Raster { block: 2, scans: 4 }, 100, 100),
        (Family::Speckle { grain: 2 }, 100, 100),
    ];
    for (family, rows, want_rows) in cases {
        let s = spec(family.clone(), 16, 16, 200, 1);
        let op = measurement_operator(&s, rows);
        assert_eq!((op.rows(), op.cols()), (want_rows, 256), "{family:?}");
        assert!(adjoint_mismatch(op.as_ref(), 1) < 1e-12);
        let err = try_measurement_operator(&s, 201).err().unwrap();
        assert_eq!(
            err,
            OpError::TooManyRows {
                rows: 201,
                count: 200
            }
        );
        assert!(err.to_string().contains("201 rows requested"));
    }
    // Memory refusal: speckle 2048 x 2048 with 1000 patterns is 16 GB of levels.
    let s = spec(Family::Speckle { grain: 1 }, 2048, 2048, 1000, 1);
    assert!(matches!(
        try_measurement_operator(&s, 1000),
        Err(OpError::TooLarge { .. })
    ));
    // Wrong families for the specific constructors.
    let b = spec(Family::Bernoulli { fill: 0.5 }, 4, 4, 4, 1);
    assert!(matches!(
        HadamardOperator::from_spec(&b, 2),
        Err(OpError::WrongFamily { .. })
    ));
    assert!(matches!(
        RasterOperator::from_spec(&b, 2),
        Err(OpError::WrongFamily { .. })
    ));
    assert!(matches!(
        SpeckleOperator::from_spec(&b, 2),
        Err(OpError::WrongFamily { .. })
    ));
}

/// Eigenvalues of a symmetric matrix (cyclic Jacobi), ascending.
fn symmetric_eigenvalues(mut a: Vec<f64>, n: usize) -> Vec<f64> {
    for _sweep in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i * n + j] * a[i * n + j])
            .sum();
        if off < 1e-22 * (0..n).map(|i| a[i * n + i] * a[i * n + i]).sum::<f64>() {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                let theta = (a[q * n + q] - a[p * n + p]) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (akp, akq) = (a[k * n + p], a[k * n + q]);
                    a[k * n + p] = c * akp - s * akq;
                    a[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[p * n + k], a[q * n + k]);
                    a[p * n + k] = c * apk - s * aqk;
                    a[q * n + k] = s * apk + c * aqk;
                }
            }
        }
    }
    let mut ev: Vec<f64> = (0..n).map(|i| a[i * n + i]).collect();
    ev.sort_by(|x, y| x.partial_cmp(y).unwrap());
    ev
}

/// Eigenvalues of `A A^T` (ascending).
fn gram_eigenvalues(op: &dyn LinearOperator) -> Vec<f64> {
    let d = DenseOperator::from_operator(op);
    let (m, k) = (op.rows(), op.cols());
    let mut g = vec![0.0; m * m];
    for i in 0..m {
        for j in 0..m {
            g[i * m + j] = dot(&d.data()[i * k..(i + 1) * k], &d.data()[j * k..(j + 1) * k]);
        }
    }
    symmetric_eigenvalues(g, m)
}

#[test]
fn centring_conditions_bernoulli_patterns() {
    let (n, w, h) = (100u64, 32u32, 32u32);
    let s = spec(Family::Bernoulli { fill: 0.5 }, w, h, n, 5);
    let p = BernoulliOperator::from_spec(&s, n).unwrap();
    let ev_p = gram_eigenvalues(&p);
    let cond_p = (ev_p[n as usize - 1] / ev_p[0]).sqrt();

    let centred = CentredOperator::new(Box::new(BernoulliOperator::from_spec(&s, n).unwrap()));
    assert!(adjoint_mismatch(&centred, 1) < 1e-12);
    let aug = CentredOperator::augmented(Box::new(BernoulliOperator::from_spec(&s, n).unwrap()));
    assert!(adjoint_mismatch(&aug, 2) < 1e-12);
    check_batches(&aug, "centred + dc row");
    check_batches(&centred, "centred");
    // [A_c; w m^T] has n + 1 rows and rank n: one zero eigenvalue, condition over the rest.
    let ev_a = gram_eigenvalues(&aug);
    assert!(ev_a[0].abs() < 1e-8 * ev_a[n as usize], "{ev_a:?}");
    let cond_aug = (ev_a[n as usize] / ev_a[1]).sqrt();

    let norm_p = spectral_norm(&p, 500, 1e-9);
    let norm_c = spectral_norm(&centred, 500, 1e-9);
    let norm_aug = spectral_norm(&aug, 500, 1e-9);
    println!(
        "cond P = {cond_p:.2}, cond [A_c; w m] = {cond_aug:.2}; ||P|| = {norm_p:.1}, ||A_c|| = {norm_c:.1}, ||aug|| = {norm_aug:.1}"
    );
    // ||P|| ~ q sqrt(nk) = 160, ||A_c|| ~ 0.5 (sqrt(k) + sqrt(n)) = 21.
    assert!(norm_p > 6.0 * norm_c, "{norm_p} vs {norm_c}");
    assert!(norm_aug <= 2f64.sqrt() * norm_c * 1.01);
    assert!(cond_aug * 4.0 < cond_p, "{cond_aug} vs {cond_p}");
    assert!((norm_p - ev_p[n as usize - 1].sqrt()).abs() < 1e-6 * norm_p);
}

#[test]
fn centred_objective_splits_exactly() {
    // ||P t - c||^2 = ||A_c t - b_c||^2 + n (m.t - cbar)^2, and with w = sqrt(n) the augmented
    // residual equals the original one.
    let (n, w, h) = (77u64, 13u32, 9u32);
    let s = spec(Family::Bernoulli { fill: 0.3 }, w, h, n, 2);
    let p = BernoulliOperator::from_spec(&s, n).unwrap();
    let k = s.pixels();
    let t = test_vector(k, 1);
    let c: Vec<f64> = test_vector(n as usize, 2)
        .iter()
        .map(|v| 10.0 + v)
        .collect();
    let mut pt = vec![0.0; n as usize];
    p.apply(&t, &mut pt);
    let full: f64 = pt.iter().zip(&c).map(|(a, b)| (a - b) * (a - b)).sum();

    let centred = CentredOperator::new(Box::new(BernoulliOperator::from_spec(&s, n).unwrap()));
    let b = centred.centre_data(&c);
    let mut at = vec![0.0; n as usize];
    centred.apply(&t, &mut at);
    let centred_part: f64 = at.iter().zip(&b).map(|(a, b)| (a - b) * (a - b)).sum();
    let cbar = CentredOperator::<dyn LinearOperator>::data_mean(&c);
    let dc = centred.dc_residual(&t, cbar);
    assert!((full - (centred_part + n as f64 * dc * dc)).abs() < 1e-9 * full);
    // Columns of A_c are orthogonal to 1.
    assert!(at.iter().sum::<f64>().abs() < 1e-10);

    let exact = centred.with_dc_weight((n as f64).sqrt());
    let b = exact.centre_data(&c);
    let mut at = vec![0.0; n as usize + 1];
    exact.apply(&t, &mut at);
    let aug: f64 = at.iter().zip(&b).map(|(a, b)| (a - b) * (a - b)).sum();
    assert!((full - aug).abs() < 1e-9 * full);
    assert_eq!(exact.exact_dc_weight(), (n as f64).sqrt());

    // fix_dc makes the mean equation hold.
    let mut t2 = t.clone();
    exact.fix_dc(&mut t2, cbar);
    assert!(exact.dc_residual(&t2, cbar).abs() < 1e-12);
    let shifts: Vec<f64> = t2.iter().zip(&t).map(|(a, b)| a - b).collect();
    assert!(shifts.iter().all(|v| (v - shifts[0]).abs() < 1e-12));
}

#[test]
fn centred_wraps_boxed_dyn_operators() {
    let s = spec(Family::Raster { block: 2, scans: 1 }, 6, 6, 9, 0);
    let boxed: Box<dyn LinearOperator> = measurement_operator(&s, 9);
    let c: CentredOperator = CentredOperator::new(boxed).with_dc_weight(2.0);
    assert_eq!(c.rows(), 10);
    assert!(adjoint_mismatch(&c, 1) < 1e-12);
    // Raster block 2 on 6 x 6: every pattern lights 4 pixels, each pixel lit once in 9 rows.
    assert!(
        c.mean_pattern()
            .iter()
            .all(|&m| (m - 1.0 / 9.0).abs() < 1e-15)
    );
}

#[test]
fn empty_operators_are_harmless() {
    let s = spec(Family::Bernoulli { fill: 0.5 }, 9, 7, 10, 1);
    let op = BernoulliOperator::from_spec(&s, 0).unwrap();
    assert_eq!((op.rows(), op.cols()), (0, 63));
    let mut x = vec![f64::NAN; 63];
    op.adjoint(&[], &mut x);
    assert!(x.iter().all(|&v| v == 0.0));
    op.apply(&test_vector(63, 1), &mut []);
    let c = CentredOperator::new(Box::new(op));
    assert!(c.mean_pattern().iter().all(|&v| v == 0.0));
    let h = spec(
        Family::Hadamard {
            ordering: HadamardOrdering::Natural,
        },
        4,
        4,
        32,
        0,
    );
    let op = HadamardOperator::from_spec(&h, 1).unwrap();
    assert_eq!(op.rows(), 0);
    let mut x = vec![f64::NAN; 16];
    op.adjoint(&[], &mut x);
    assert!(x.iter().all(|&v| v == 0.0));
}

#[test]
fn row_selections_match_the_full_operator() {
    let pick = vec![5usize, 0, 17, 17, 3];
    let check = |full: &dyn LinearOperator, sub: &dyn LinearOperator, what: &str| {
        let d = DenseOperator::from_operator(full);
        let k = full.cols();
        let want: Vec<f64> = pick
            .iter()
            .flat_map(|&r| d.data()[r * k..(r + 1) * k].to_vec())
            .collect();
        check_equals(sub, &DenseOperator::new(pick.len(), k, want), 1e-12, what);
        assert!(adjoint_mismatch(sub, 3) < 1e-12, "{what}");
    };
    let s = spec(Family::Bernoulli { fill: 0.4 }, 11, 9, 40, 3);
    let full = BernoulliOperator::from_spec(&s, 40).unwrap();
    check(&full, &full.select_rows(&pick), "bernoulli select");
    let h = spec(
        Family::Hadamard {
            ordering: HadamardOrdering::CakeCutting,
        },
        8,
        4,
        64,
        0,
    );
    let full = HadamardOperator::from_spec(&h, 64).unwrap();
    check(&full, &full.select_rows(&pick), "hadamard select");
    let sub = RowSubset::new(measurement_operator(&s, 40), pick.clone());
    check(sub.inner(), &sub, "generic subset");
}

#[test]
fn hadamard_finest_resolution_bounds_every_row() {
    let (w, h) = (32usize, 16usize);
    for ordering in [HadamardOrdering::RussianDoll, HadamardOrdering::Zigzag] {
        for pairs in [1usize, 4, 64, 100, 512] {
            let op = HadamardOperator::new(w as u32, h as u32, ordering, pairs);
            let (rx, ry) = op.finest_resolution();
            let (bx, by) = (w / rx, h / ry);
            let mut e = vec![0.0; pairs];
            let mut p = vec![0.0; w * h];
            let mut finest = (w, h);
            for r in 0..pairs {
                e.fill(0.0);
                e[r] = 1.0;
                op.adjoint(&e, &mut p);
                // Constant on bx x by blocks...
                for y in 0..h {
                    for x in 0..w {
                        assert_eq!(
                            p[y * w + x],
                            p[(y / by * by) * w + x / bx * bx],
                            "{ordering:?} {pairs} row {r}"
                        );
                    }
                }
                // ...and the bound is attained by some row: track each row's own finest block.
                let own_x = (1..=w)
                    .filter(|b| w % b == 0)
                    .rev()
                    .find(|&b| (0..w * h).all(|i| p[i] == p[(i / w) * w + (i % w) / b * b]))
                    .unwrap();
                let own_y = (1..=h)
                    .filter(|b| h % b == 0)
                    .rev()
                    .find(|&b| (0..w * h).all(|i| p[i] == p[((i / w) / b * b) * w + i % w]))
                    .unwrap();
                finest = (finest.0.min(own_x), finest.1.min(own_y));
            }
            assert_eq!(
                (w / finest.0, h / finest.1),
                (rx, ry),
                "{ordering:?} {pairs}: the bound is tight"
            );
        }
    }
    let full = HadamardOperator::new(w as u32, h as u32, HadamardOrdering::Natural, w * h);
    assert_eq!(full.finest_resolution(), (w, h));
}
