use super::*;
use crate::linop::{DenseOperator, adjoint_mismatch, norm, spectral_norm, test_vector};

const SIZES: [(usize, usize); 12] = [
    (1, 1),
    (2, 2),
    (1, 7),
    (7, 1),
    (3, 5),
    (8, 4),
    (16, 16),
    (64, 32),
    (33, 17),
    (100, 75),
    (158, 210),
    (256, 256),
];

fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

#[test]
fn orthonormal_transforms_invert_and_preserve_norms() {
    for kind in TransformKind::ALL {
        for (w, h) in SIZES {
            let t = kind.build(w, h);
            assert!(t.is_orthonormal());
            let what = format!("{} {w}x{h}", t.name());
            let k = w * h;
            assert_eq!((t.rows(), t.cols()), (k, k));
            assert!(adjoint_mismatch(t.as_ref(), 1) < 1e-12, "{what}");
            let x = test_vector(k, 7);
            let (mut c, mut back) = (vec![0.0; k], vec![0.0; k]);
            t.apply(&x, &mut c);
            t.adjoint(&c, &mut back);
            assert!(
                max_diff(&x, &back) < 1e-12,
                "{what}: inverse(forward(x)) != x"
            );
            assert!(
                (norm(&c) - norm(&x)).abs() < 1e-12 * norm(&x),
                "{what}: Parseval"
            );
            // And the other way round (Psi Psi^T = I).
            t.adjoint(&x, &mut c);
            t.apply(&c, &mut back);
            assert!(
                max_diff(&x, &back) < 1e-12,
                "{what}: forward(inverse(c)) != c"
            );
        }
    }
}

#[test]
fn small_transforms_are_orthogonal_matrices() {
    for kind in TransformKind::ALL {
        for (w, h) in [(8, 4), (5, 3), (6, 6)] {
            let t = kind.build(w, h);
            let d = DenseOperator::from_operator(t.as_ref());
            let k = w * h;
            for i in 0..k {
                for j in 0..k {
                    let s: f64 = (0..k)
                        .map(|c| d.data()[i * k + c] * d.data()[j * k + c])
                        .sum();
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!(
                        (s - want).abs() < 1e-13,
                        "{} {w}x{h} ({i},{j}) {s}",
                        t.name()
                    );
                }
            }
        }
    }
}

#[test]
fn haar_values_and_layout() {
    // [1, 2, 3, 4]: level 1 a = (3, 7)/sqrt 2, d = (-1, -1)/sqrt 2; level 2 a = 5, d = -2.
    let t = Wavelet2d::haar(4, 1);
    let mut c = vec![0.0; 4];
    t.apply(&[1.0, 2.0, 3.0, 4.0], &mut c);
    let r = 0.5f64.sqrt();
    assert!(max_diff(&c, &[5.0, -2.0, -r, -r]) < 1e-15, "{c:?}");
    // 2 x 2: approx = sum / 2, then (horizontal, vertical, diagonal) details.
    let t = Wavelet2d::haar(2, 2);
    let mut c = vec![0.0; 4];
    t.apply(&[1.0, 2.0, 3.0, 4.0], &mut c);
    // Rows: [1,2] -> [3/r2, -1/r2], [3,4] -> [7/r2, -1/r2]; columns: [5, -1; -2, 0].
    assert!(max_diff(&c, &[5.0, -1.0, -2.0, 0.0]) < 1e-15, "{c:?}");
    assert_eq!(t.coarse_band(), (1, 1));
    assert_eq!(Wavelet2d::haar(64, 8).levels(), 6);
    assert_eq!(Wavelet2d::haar(64, 8).coarse_band(), (1, 1));
    assert_eq!(Wavelet2d::haar(64, 8).with_levels(2).coarse_band(), (16, 2));
}

#[test]
fn haar_of_a_block_image_is_sparse() {
    // A dyadic 16 x 16 block on black, 64 x 64: levels 1-4 see only constant blocks; the 4 x 4
    // approximation has one nonzero, giving 3 details at level 5, 3 at level 6 and the 1 x 1
    // approximation: 7 coefficients.
    let (w, h) = (64, 64);
    let mut img = vec![0.0; w * h];
    for y in 16..32 {
        for x in 16..32 {
            img[y * w + x] = 3.0;
        }
    }
    let t = Wavelet2d::haar(w, h);
    let mut c = vec![0.0; w * h];
    t.apply(&img, &mut c);
    assert_eq!(count_above(&c, 1e-12), 7);
    // Against 16 x 16 x 1 = 256 nonzero pixels.
    assert_eq!(count_above(&img, 1e-12), 256);

    // Constant images: one coefficient on any grid (unbalanced Haar), value mean * sqrt(k).
    for (w, h) in SIZES {
        let t = Wavelet2d::haar(w, h);
        let img = vec![2.0; w * h];
        let mut c = vec![0.0; w * h];
        t.apply(&img, &mut c);
        assert_eq!(count_above(&c, 1e-12), 1, "haar {w}x{h}");
        assert!((c[0] - 2.0 * ((w * h) as f64).sqrt()).abs() < 1e-11);
    }

    // Non-dyadic size and an unaligned rectangle (104 x 78 = 8112 pixels on 200 x 150): the
    // nonzero coefficients follow the edges, a few per level and edge position.
    let (w, h) = (200, 150);
    let mut img = vec![0.0; w * h];
    for y in 23..101 {
        for x in 37..141 {
            img[y * w + x] = 1.0;
        }
    }
    let t = Wavelet2d::haar(w, h);
    let mut c = vec![0.0; w * h];
    t.apply(&img, &mut c);
    let kept = count_above(&c, 1e-12);
    assert!(kept * 5 < 8112, "{kept}");
}

#[test]
fn daubechies_filters_kill_polynomials() {
    // One level on a 1D signal: details vanish for polynomials of degree < vanishing moments,
    // except the last (taps / 2 - 1) ones where the periodic filter wraps.
    for (t, degree, taps) in [(Wavelet2d::db2(64, 1), 1, 4), (Wavelet2d::db4(64, 1), 3, 8)] {
        let t = t.with_levels(1);
        let x: Vec<f64> = (0..64)
            .map(|i| (i as f64 / 10.0).powi(degree) + 0.5)
            .collect();
        let mut c = vec![0.0; 64];
        t.apply(&x, &mut c);
        let details = &c[32..];
        let inner = &details[..32 - (taps / 2 - 1)];
        let scale = norm(&x);
        assert!(
            inner.iter().all(|d| d.abs() < 1e-11 * scale),
            "{}: {inner:?}",
            t.name()
        );
        assert!(details[31].abs() > 1e-3, "the wrap is not smooth");
    }
}

#[test]
fn smooth_images_prefer_smooth_wavelets_and_the_dct() {
    // A smooth periodic image: db4 and the DCT need far fewer coefficients than Haar.
    let (w, h) = (64, 64);
    let img: Vec<f64> = (0..w * h)
        .map(|p| {
            let (x, y) = ((p % w) as f64, (p / w) as f64);
            let tau = std::f64::consts::TAU;
            1.0 + (tau * x / w as f64).sin() * (tau * 2.0 * y / h as f64).cos()
        })
        .collect();
    let kept = |kind: TransformKind| {
        let t = kind.build(w, h);
        let mut c = vec![0.0; w * h];
        t.apply(&img, &mut c);
        count_above(&c, 1e-3 * norm(&c))
    };
    let (haar, db4, dct) = (
        kept(TransformKind::Haar),
        kept(TransformKind::Db4),
        kept(TransformKind::Dct),
    );
    println!("kept: haar {haar}, db4 {db4}, dct {dct}");
    assert!(db4 * 3 < haar, "db4 {db4} haar {haar}");
    assert!(dct * 3 < haar, "dct {dct} haar {haar}");
}

#[test]
fn dct_matches_the_formula() {
    for (w, h) in [(5usize, 3usize), (4, 4), (1, 6), (7, 2)] {
        let t = Dct2d::new(w, h);
        let x = test_vector(w * h, 3);
        let mut c = vec![0.0; w * h];
        t.apply(&x, &mut c);
        let pi = std::f64::consts::PI;
        for v in 0..h {
            for u in 0..w {
                let au = if u == 0 {
                    (1.0 / w as f64).sqrt()
                } else {
                    (2.0 / w as f64).sqrt()
                };
                let av = if v == 0 {
                    (1.0 / h as f64).sqrt()
                } else {
                    (2.0 / h as f64).sqrt()
                };
                let mut s = 0.0;
                for y in 0..h {
                    for xx in 0..w {
                        s += x[y * w + xx]
                            * (pi * (2 * xx + 1) as f64 * u as f64 / (2 * w) as f64).cos()
                            * (pi * (2 * y + 1) as f64 * v as f64 / (2 * h) as f64).cos();
                    }
                }
                assert!(
                    (c[v * w + u] - au * av * s).abs() < 1e-13,
                    "{w}x{h} ({u},{v})"
                );
            }
        }
    }
}

#[test]
fn fast_dct_equals_the_matrix_dct() {
    for (w, h) in [
        (2usize, 2usize),
        (4, 8),
        (64, 32),
        (16, 5),
        (256, 256),
        (2, 1),
        (1, 4),
        // Odd lane counts on either fast axis (a lane without an imaginary partner), and large
        // images whose lanes split into stripes on threads, with an odd width on the fast axis.
        (3, 16),
        (16, 3),
        (128, 128),
        (255, 256),
        (256, 255),
        (1, 2),
    ] {
        let (fast, slow) = (Dct2d::new(w, h), Dct2d::with_matrices(w, h));
        let x = test_vector(w * h, 9);
        let (mut a, mut b) = (vec![0.0; w * h], vec![0.0; w * h]);
        fast.apply(&x, &mut a);
        slow.apply(&x, &mut b);
        assert!(max_diff(&a, &b) < 1e-12, "{w}x{h} forward");
        fast.adjoint(&x, &mut a);
        slow.adjoint(&x, &mut b);
        assert!(max_diff(&a, &b) < 1e-12, "{w}x{h} inverse");
    }
}

/// `C_N` by its definition, `C[u][x] = a_u cos(pi (2x + 1) u / (2N))`, row-major.
fn dct_definition(n: usize) -> Vec<f64> {
    let pi = std::f64::consts::PI;
    let mut c = vec![0.0; n * n];
    for u in 0..n {
        let a = if u == 0 {
            1.0 / n as f64
        } else {
            2.0 / n as f64
        }
        .sqrt();
        for x in 0..n {
            c[u * n + x] = a * (pi * (2 * x + 1) as f64 * u as f64 / (2 * n) as f64).cos();
        }
    }
    c
}

/// `Y = C_H X C_W^T` (forward) or `X = C_H^T Y C_W` (inverse) by the O(N^2)-per-axis sums.
fn dct_by_definition(x: &[f64], w: usize, h: usize, forward: bool) -> Vec<f64> {
    let (cw, ch) = (dct_definition(w), dct_definition(h));
    let at = |c: &[f64], n: usize, i: usize, j: usize| {
        if forward { c[i * n + j] } else { c[j * n + i] }
    };
    // Along rows, then along columns.
    let mut r = vec![0.0; w * h];
    for y in 0..h {
        for u in 0..w {
            r[y * w + u] = (0..w).map(|xx| at(&cw, w, u, xx) * x[y * w + xx]).sum();
        }
    }
    let mut out = vec![0.0; w * h];
    for v in 0..h {
        for u in 0..w {
            out[v * w + u] = (0..h).map(|y| at(&ch, h, v, y) * r[y * w + u]).sum();
        }
    }
    out
}

#[test]
fn dct_on_sides_that_are_not_powers_of_two_matches_the_definition() {
    use super::dct::DctPath;
    for (w, h, path) in [
        (48usize, 100usize, DctPath::Radix2),
        (100, 48, DctPath::Radix2),
        (97, 97, DctPath::Radix2),
        (200, 3, DctPath::Radix2),
        (64, 96, DctPath::Radix2),
        (1, 97, DctPath::Radix2),
        // The planned transform forced on powers of two too.
        (64, 32, DctPath::Planned),
        (2, 1, DctPath::Planned),
    ] {
        let t = Dct2d::with_paths(w, h, path);
        let x = test_vector(w * h, 11);
        let mut c = vec![0.0; w * h];
        t.apply(&x, &mut c);
        let d = max_diff(&c, &dct_by_definition(&x, w, h, true));
        assert!(d < 1e-12, "{w}x{h} {path:?} forward: {d:e}");
        let mut back = vec![0.0; w * h];
        t.adjoint(&x, &mut back);
        let d = max_diff(&back, &dct_by_definition(&x, w, h, false));
        assert!(d < 1e-12, "{w}x{h} {path:?} inverse: {d:e}");
        // Orthonormal: the inverse undoes the forward transform.
        t.adjoint(&c, &mut back);
        let d = max_diff(&back, &x);
        assert!(d < 1e-12, "{w}x{h} {path:?} round trip: {d:e}");
    }
}

#[test]
fn dct_of_a_constant_has_one_coefficient() {
    for (w, h) in SIZES {
        let t = Dct2d::new(w, h);
        let img = vec![0.7; w * h];
        let mut c = vec![0.0; w * h];
        t.apply(&img, &mut c);
        assert_eq!(count_above(&c, 1e-12), 1, "{w}x{h}");
        assert!((c[0] - 0.7 * ((w * h) as f64).sqrt()).abs() < 1e-12);
    }
}

#[test]
fn gradient_adjoint_norm_and_tv() {
    for (w, h) in SIZES {
        let d = Gradient::new(w, h);
        assert_eq!((d.rows(), d.cols()), (2 * w * h, w * h));
        assert!(adjoint_mismatch(&d, 2) < 1e-12, "{w}x{h}");
        // Constant image: zero gradient, zero TV.
        assert_eq!(d.tv(&vec![4.2; w * h]), 0.0);
    }
    // ||D||^2 <= 8, close to 8 on a large grid.
    let d = Gradient::new(64, 64);
    let n2 = spectral_norm(&d, 2000, 1e-10).powi(2);
    assert!(n2 <= Gradient::NORM_SQ_BOUND + 1e-9 && n2 > 7.9, "{n2}");
    let d = Gradient::new(3, 2);
    let dense = DenseOperator::from_operator(&d);
    // Row (0, 0) of gx: u[0][1] - u[0][0].
    assert_eq!(&dense.data()[..6], &[-1.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
    // Row (0, 0) of gy (index 6): u[1][0] - u[0][0]; last-row gy rows are zero.
    assert_eq!(
        &dense.data()[6 * 6..7 * 6],
        &[-1.0, 0.0, 0.0, 1.0, 0.0, 0.0]
    );
    assert!(dense.data()[9 * 6..].iter().all(|&v| v == 0.0));
}

#[test]
fn tv_of_a_step_edge_is_length_times_jump() {
    for (w, h, edge, jump) in [
        (10usize, 7usize, 4usize, 2.5f64),
        (64, 32, 31, -1.0),
        (5, 100, 1, 0.25),
    ] {
        let img: Vec<f64> = (0..w * h)
            .map(|p| if p % w >= edge { jump } else { 0.0 })
            .collect();
        let d = Gradient::new(w, h);
        assert!(
            (d.tv(&img) - h as f64 * jump.abs()).abs() < 1e-12,
            "{w}x{h}"
        );
        assert!((d.tv_anisotropic(&img) - h as f64 * jump.abs()).abs() < 1e-12);
        // The same edge horizontal.
        let img: Vec<f64> = (0..w * h)
            .map(|p| if p / w >= edge { jump } else { 0.0 })
            .collect();
        assert!((d.tv(&img) - w as f64 * jump.abs()).abs() < 1e-12);
    }
    // Isotropic, not anisotropic: a single bright pixel at (1, 1) of 3 x 3 has gradients
    // (1, 1) at (1, 1), (-1, 0) at (0, 1) and (0, -1) at (1, 0): TV = sqrt(2) + 2.
    let mut img = vec![0.0; 9];
    img[4] = 1.0;
    let d = Gradient::new(3, 3);
    assert!((d.tv(&img) - (2f64.sqrt() + 2.0)).abs() < 1e-15);
    assert_eq!(d.tv_anisotropic(&img), 4.0);
}

#[test]
fn count_above_counts_strictly() {
    assert_eq!(count_above(&[0.0, -1.0, 0.5, 2.0, -0.5], 0.5), 2);
    assert_eq!(count_above(&[], 0.0), 0);
    assert_eq!(count_above(&[1e-300], 0.0), 1);
}

#[test]
fn identity_and_kinds() {
    let t = TransformKind::Identity.build(3, 4);
    assert_eq!(t.name(), "identity");
    assert!(adjoint_mismatch(t.as_ref(), 1) < 1e-15);
    for kind in TransformKind::ALL {
        assert_eq!(kind.build(4, 4).name(), kind.name());
        let op = sparsifying_transform(kind, 6, 2);
        assert_eq!((op.rows(), op.cols()), (12, 12));
    }
    assert_eq!(
        serde_json::to_string(&TransformKind::Db4).unwrap(),
        "\"db4\""
    );
}
