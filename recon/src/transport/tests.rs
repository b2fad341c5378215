use helmholtz_proto::{Family, HadamardOrdering, PatternGenerator, PatternSpec};
use serde_json::json;

use super::*;
use crate::metrics::relative_error;

/// A synthetic `T` (m x k, row-major): camera pixel `(cx, cy)` sees a small bright blob at the
/// matching projector point plus a dimmer, wider halo around it (both Gaussian, cut off, so
/// every row is sparse and smooth); a few camera pixels see nothing.
fn synthetic_t(camera: CameraGrid, pw: usize, ph: usize) -> Vec<f32> {
    let (cw, ch) = (camera.width as usize, camera.height as usize);
    let k = pw * ph;
    let mut t = vec![0f32; cw * ch * k];
    for cy in 0..ch {
        for cx in 0..cw {
            let j = cy * cw + cx;
            if (cx * 7 + cy * 3) % 11 == 0 {
                continue;
            }
            let px = (cx as f64 + 0.5) * pw as f64 / cw as f64 - 0.3;
            let py = (cy as f64 + 0.5) * ph as f64 / ch as f64 - 0.2;
            let row = &mut t[j * k..(j + 1) * k];
            for y in 0..ph {
                for x in 0..pw {
                    let d2 = (x as f64 - px).powi(2) + (y as f64 - py).powi(2);
                    if d2 <= 16.0 {
                        row[y * pw + x] = (0.25 * (-d2 / 8.0).exp() + (-d2 / 1.28).exp()) as f32;
                    }
                }
            }
        }
    }
    t
}

/// Frames `c_i = T p_i` (rows x m), plus Gaussian noise of standard deviation `noise`.
fn frames(spec: &PatternSpec, t: &[f32], m: usize, noise: f64) -> Vec<f32> {
    let k = spec.pixels();
    let g = PatternGenerator::new(spec);
    let mut p = vec![0f32; k];
    let mut rng = crate::testutil::Rng::new(99);
    let mut out = Vec::with_capacity(spec.count() as usize * m);
    for i in 0..spec.count() {
        g.fill_values(i, &mut p);
        for row in t.chunks_exact(k) {
            let c: f64 = row.iter().zip(&p).map(|(a, b)| *a as f64 * *b as f64).sum();
            out.push((c + noise * rng.normal()) as f32);
        }
    }
    out
}

/// A Russian-doll Hadamard session of `pairs` split pairs on a `w x h` projector.
fn russian_doll(w: usize, h: usize, pairs: usize) -> PatternSpec {
    PatternSpec::new(
        Family::Hadamard {
            ordering: HadamardOrdering::RussianDoll,
        },
        w as u32,
        h as u32,
        2 * pairs as u64,
        0,
    )
    .unwrap()
}

/// The frames of `spec` noise-free and with Gaussian noise of `share` of their RMS.
fn clean_and_noisy(spec: &PatternSpec, t: &[f32], m: usize, share: f64) -> (Vec<f32>, Vec<f32>) {
    let clean = frames(spec, t, m, 0.0);
    let rms = (clean.iter().map(|v| (*v as f64).powi(2)).sum::<f64>() / clean.len() as f64).sqrt();
    let noisy = frames(spec, t, m, share * rms);
    (clean, noisy)
}

/// The zero-filled inverse `A^T d` of Hadamard split pairs, row by row (the baseline).
fn zero_filled(spec: &PatternSpec, f: &[f32], m: usize) -> Vec<f32> {
    let op = HadamardOperator::from_spec(spec, spec.count()).unwrap();
    let k = spec.pixels();
    let scale = 1.0 / (k as f64).sqrt();
    let mut out = Vec::with_capacity(m * k);
    let mut t = vec![0.0; k];
    for j in 0..m {
        let d: Vec<f64> = (0..op.rows())
            .map(|r| (f[2 * r * m + j] as f64 - f[(2 * r + 1) * m + j] as f64) * scale)
            .collect();
        op.adjoint(&d, &mut t);
        out.extend(t.iter().map(|&v| v as f32));
    }
    out
}

fn dense(t: &TransportMatrix) -> Vec<f32> {
    let (cw, ch) = t.camera();
    (0..(cw * ch) as usize).flat_map(|j| t.row(j)).collect()
}

fn run(
    spec: &PatternSpec,
    camera: CameraGrid,
    f: &[f32],
    config: &TransportConfig,
) -> (TransportMatrix, Report, SliceFrames<'static>) {
    let leaked: &'static [f32] = Box::leak(f.to_vec().into_boxed_slice());
    let mut source = SliceFrames::new(leaked, camera.pixels());
    let (t, r) = reconstruct_transport(
        spec,
        camera,
        spec.count(),
        config,
        &mut source,
        &Control::new(),
    )
    .unwrap();
    (t, r, source)
}

const CAM: CameraGrid = CameraGrid {
    width: 8,
    height: 8,
};

#[test]
fn a_complete_hadamard_set_reconstructs_to_f32_precision_and_stores_sparse() {
    let spec = PatternSpec::new(
        Family::Hadamard {
            ordering: HadamardOrdering::Sequency,
        },
        32,
        32,
        2048,
        0,
    )
    .unwrap();
    let truth = synthetic_t(CAM, 32, 32);
    let f = frames(&spec, &truth, CAM.pixels(), 0.0);
    let (t, report, _) = run(&spec, CAM, &f, &TransportConfig::default());
    let err = relative_error(&dense(&t), &truth);
    println!(
        "complete hadamard: rel err {err:e}, nnz {}, stored {} B, details {}",
        t.nonzeros(),
        t.stored_bytes(),
        json!(report.details)
    );
    assert!(err < 1e-5, "relative Frobenius error {err:e}");
    assert!(report.held_out.is_none() && report.held_out_unavailable.is_some());
    // Sparse: far fewer coefficients than m x k (each row is a blob in a 49-pixel halo).
    assert!(
        t.nonzeros() < CAM.pixels() * 200,
        "{} nonzeros",
        t.nonzeros()
    );
    assert_eq!(t.stored_bytes(), t.encode().len());
    assert_eq!(
        report.details["transform"], "identity",
        "the data should choose the pixel basis here"
    );
}

/// [`synthetic_t`] plus interreflected light: every camera pixel also sees a dim, smooth glow
/// from the whole projector (dense, each entry far below the direct blob's), smooth across the
/// camera too, about `share` of the total light.
fn interreflected_t(camera: CameraGrid, pw: usize, ph: usize, share: f64) -> Vec<f32> {
    let (cw, ch) = (camera.width as usize, camera.height as usize);
    let k = pw * ph;
    let mut t = synthetic_t(camera, pw, ph);
    let direct: f64 = t.iter().map(|v| *v as f64).sum();
    let mut glow = vec![0.0f64; t.len()];
    for cy in 0..ch {
        for cx in 0..cw {
            let (u, v) = (cx as f64 / cw as f64, cy as f64 / ch as f64);
            for y in 0..ph {
                for x in 0..pw {
                    let (a, b) = (x as f64 / pw as f64, y as f64 / ph as f64);
                    glow[(cy * cw + cx) * k + y * pw + x] = (1.0 + 0.6 * (3.0 * (a - u)).cos())
                        * (1.0 + 0.4 * (2.5 * (b + v)).sin())
                        * (0.5 + u);
                }
            }
        }
    }
    let total: f64 = glow.iter().sum();
    let scale = direct * share / (1.0 - share) / total;
    t.iter_mut()
        .zip(&glow)
        .for_each(|(v, g)| *v += (g * scale) as f32);
    t
}

/// `T^T c` of a dense row-major `T` (m x k).
fn relit(t: &[f32], light: &[f32], k: usize) -> Vec<f32> {
    let mut out = vec![0.0f64; k];
    for (row, &c) in t.chunks_exact(k).zip(light) {
        out.iter_mut()
            .zip(row)
            .for_each(|(o, v)| *o += *v as f64 * c as f64);
    }
    out.into_iter().map(|v| v as f32).collect()
}

#[test]
fn a_noisy_complete_set_keeps_the_interreflected_light_a_relight_sums() {
    // 32x32 projector, 16x16 camera; 20 % of the light interreflected, dense and dim; frame
    // noise 1 % of the frames' RMS.
    let camera = CameraGrid {
        width: 16,
        height: 16,
    };
    let (m, k) = (camera.pixels(), 1024);
    let spec = PatternSpec::new(
        Family::Hadamard {
            ordering: HadamardOrdering::Sequency,
        },
        32,
        32,
        2048,
        0,
    )
    .unwrap();
    let truth = interreflected_t(camera, 32, 32, 0.2);
    let clean = frames(&spec, &truth, m, 0.0);
    let rms = (clean.iter().map(|v| (*v as f64).powi(2)).sum::<f64>() / clean.len() as f64).sqrt();
    let f = frames(&spec, &truth, m, 0.01 * rms);
    let (t, report, _) = run(&spec, camera, &f, &TransportConfig::default());
    let plain = zero_filled(&spec, &f, m);
    let ours = dense(&t);
    let lights: Vec<(&str, Vec<f32>)> = vec![
        ("full", vec![1.0; m]),
        ("left half", (0..m).map(|j| f32::from(j % 16 < 8)).collect()),
        (
            "4x4 checker",
            (0..m)
                .map(|j| f32::from((j % 16 / 4 + j / 64) % 2 == 0))
                .collect(),
        ),
    ];
    let total = |t: &[f32]| t.iter().map(|v| *v as f64).sum::<f64>();
    let light_ratio = total(&ours) / total(&truth);
    println!(
        "transform {}, nnz/row {:.1} of {k}, total light {light_ratio:.5} (plain {:.5}), T error {:.4} (plain {:.4})",
        report.details["transform"],
        t.nonzeros() as f64 / m as f64,
        total(&plain) / total(&truth),
        relative_error(&ours, &truth),
        relative_error(&plain, &truth),
    );
    for (name, light) in &lights {
        let want = relit(&truth, light, k);
        let e_ours = relative_error(&t.relight(light), &want);
        let e_plain = relative_error(&relit(&plain, light, k), &want);
        println!("relit {name}: error {e_ours:.5} (plain inverse {e_plain:.5})");
        // Dropping coefficients can only remove noise from a relight if nothing coherent is
        // dropped with it: never worse than the plain inverse.
        assert!(
            e_ours < e_plain,
            "{name} relight error {e_ours} (plain inverse {e_plain})"
        );
    }
    assert!(
        (light_ratio - 1.0).abs() < 0.005,
        "total light {light_ratio} of the truth"
    );
    // The reported error of the full-light relight is calibrated: within 2x of the truth.
    let estimate = report.details["relight_error_estimate"]["relative"]
        .as_f64()
        .unwrap();
    let full = relative_error(&t.relight(&lights[0].1), &relit(&truth, &lights[0].1, k));
    println!("full-light relight error estimate {estimate:.5}, true {full:.5}");
    assert!(
        estimate > full / 2.0 && estimate < full * 2.0,
        "estimate {estimate} against the true {full}"
    );
    // Sparser than the plain inverse, and T itself no worse than it.
    assert!(t.nonzeros() < m * k / 2, "{} nonzeros", t.nonzeros());
    assert!(relative_error(&ours, &truth) < relative_error(&plain, &truth));
}

#[test]
fn a_complete_raster_set_with_noise_drops_what_is_below_the_noise() {
    let spec = PatternSpec::new(Family::Raster { block: 1, scans: 1 }, 32, 32, 1024, 0).unwrap();
    let truth = synthetic_t(CAM, 32, 32);
    let sigma = 1e-3;
    let f = frames(&spec, &truth, CAM.pixels(), sigma);
    let (t, report, _) = run(&spec, CAM, &f, &TransportConfig::default());
    let err = relative_error(&dense(&t), &truth);
    let estimated = report.details["noise_sigma_median"].as_f64().unwrap();
    println!(
        "raster + noise: rel err {err:e}, nnz {}, sigma {estimated:e}",
        t.nonzeros()
    );
    assert!(
        (estimated / sigma - 1.0).abs() < 0.2,
        "noise estimate {estimated:e} vs {sigma:e}"
    );
    // The noise alone is ||n|| / ||T|| = 1e-3 sqrt(k m) / ||T||; thresholding keeps the error
    // below the raw noise and drops nearly all pure-noise coefficients.
    let raw_noise = sigma * ((CAM.pixels() * 1024) as f64).sqrt()
        / truth
            .iter()
            .map(|v| (*v as f64).powi(2))
            .sum::<f64>()
            .sqrt();
    assert!(err < raw_noise, "error {err:e} vs raw noise {raw_noise:e}");
    assert!(
        t.nonzeros() < CAM.pixels() * 150,
        "{} nonzeros",
        t.nonzeros()
    );
}

#[test]
fn partial_hadamard_and_bernoulli_match_within_tolerance_with_held_out_error() {
    let truth = synthetic_t(CAM, 32, 32);
    let cases = [
        // Measured (noise-free): Hadamard 50 % 0.140 (zero-filled 0.201), 25 % 0.514 (the
        // complete 16x16 level: zero-filled 0.514, nothing finer is measured); Bernoulli 50 %
        // 0.0013, 25 % 0.0017.
        (
            Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll,
            },
            1024u64,
            0.16,
        ),
        (
            Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll,
            },
            512,
            0.53,
        ),
        (Family::Bernoulli { fill: 0.5 }, 512, 0.005),
        (Family::Bernoulli { fill: 0.5 }, 256, 0.005),
    ];
    for (family, count, tolerance) in cases {
        let spec = PatternSpec::new(family.clone(), 32, 32, count, 3).unwrap();
        let f = frames(&spec, &truth, CAM.pixels(), 0.0);
        let (t, report, _) = run(&spec, CAM, &f, &TransportConfig::default());
        let err = relative_error(&dense(&t), &truth);
        if family.name() == "hadamard" {
            // Never worse than the minimum-norm image, and clearly better where finer rows exist.
            let zf = relative_error(&zero_filled(&spec, &f, 64), &truth);
            println!("zero-filled: {zf:.4}");
            assert!(err < 1.01 * zf, "{count}: {err} vs zero-filled {zf}");
            if count == 1024 {
                assert!(err < 0.8 * zf, "{count}: {err} vs zero-filled {zf}");
            }
        }
        let held = report
            .held_out
            .as_ref()
            .and_then(|h| h.relative_residual)
            .expect("held-out error reported");
        println!(
            "{} {count}: rel err {err:.4}, held-out {held:.4}, transform {}, lambda {}, nnz/row {:.1}, iterations/row {}",
            family.name(),
            report.details["transform"],
            report.details["lambda"],
            t.nonzeros() as f64 / CAM.pixels() as f64,
            report.details["iterations_mean"]
        );
        assert!(
            err < tolerance,
            "{} {count}: relative error {err} over {tolerance}",
            family.name()
        );
        if family.name() == "bernoulli" {
            assert!(held < 0.01, "held-out {held}");
        }
    }
}

#[test]
fn relight_is_the_adjoint_of_primal_and_rows_are_relights_of_one_pixel() {
    let truth = synthetic_t(CAM, 32, 32);
    for kind in [
        TransformKind::Identity,
        TransformKind::Haar,
        TransformKind::Db4,
        TransformKind::Dct,
    ] {
        let t = TransportMatrix::from_dense((32, 32), (8, 8), kind, &truth, 1e-3);
        let p: Vec<f32> = crate::linop::test_vector(1024, 1)
            .iter()
            .map(|&v| v as f32)
            .collect();
        let c: Vec<f32> = crate::linop::test_vector(64, 2)
            .iter()
            .map(|&v| v as f32)
            .collect();
        let tp = t.primal(&p);
        let tc = t.relight(&c);
        let l: f64 = tp.iter().zip(&c).map(|(a, b)| *a as f64 * *b as f64).sum();
        let r: f64 = p.iter().zip(&tc).map(|(a, b)| *a as f64 * *b as f64).sum();
        let mismatch = (l - r).abs() / (l.abs() + r.abs());
        assert!(
            mismatch < 1e-5,
            "{}: <Tp, c> = {l}, <p, T^T c> = {r}",
            kind.name()
        );
        let mut e = vec![0f32; 64];
        e[13] = 1.0;
        let relit = t.relight(&e);
        let row = t.row(13);
        assert!(relative_error(&relit, &row) < 1e-6);
        // Stored with a small threshold, the matrix is close to the truth.
        assert!(relative_error(&dense(&t), &truth) < 0.02, "{}", kind.name());
    }
}

#[test]
fn encode_decode_round_trips_and_corrupt_bytes_are_refused() {
    let truth = synthetic_t(CAM, 32, 32);
    let t = TransportMatrix::from_dense((32, 32), (8, 8), TransformKind::Haar, &truth, 1e-4);
    let bytes = t.encode();
    assert_eq!(bytes.len(), t.stored_bytes());
    let back = TransportMatrix::decode(&bytes).unwrap();
    assert_eq!(back, t);
    assert_eq!(back.row(5), t.row(5));
    // One flipped bit anywhere: refused by the checksum (or the magic).
    for pos in [3, 12, 40, bytes.len() / 2, bytes.len() - 6, bytes.len() - 1] {
        let mut bad = bytes.clone();
        bad[pos] ^= 0x10;
        let e = TransportMatrix::decode(&bad).unwrap_err();
        assert!(
            matches!(
                e,
                TransportDecodeError::Checksum { .. } | TransportDecodeError::BadMagic
            ),
            "byte {pos}: {e}"
        );
    }
    assert!(matches!(
        TransportMatrix::decode(&bytes[..bytes.len() - 10]),
        Err(TransportDecodeError::Checksum { .. })
    ));
    assert!(matches!(
        TransportMatrix::decode(&bytes[..5]),
        Err(TransportDecodeError::TooShort(5))
    ));
    // A well-checksummed body with inconsistent counts is refused too.
    let mut forged = bytes[..bytes.len() - 4 - 8].to_vec();
    let crc = crc32c::crc32c(&forged);
    forged.extend_from_slice(&crc.to_le_bytes());
    assert!(
        matches!(
            TransportMatrix::decode(&forged),
            Err(TransportDecodeError::Inconsistent(_))
        ),
        "{:?}",
        TransportMatrix::decode(&forged)
    );
}

/// A 16x16 camera over a 16x16 projector, Bernoulli 50 %: 128 frames x 256 pixels = 128 KiB.
fn small_session() -> (PatternSpec, CameraGrid, Vec<f32>, Vec<f32>) {
    bernoulli_session(16)
}

/// A `side x side` camera over a 16x16 projector, 128 Bernoulli 50 % frames of
/// [`synthetic_t`], noise-free: spec, camera, truth and frames.
fn bernoulli_session(side: u32) -> (PatternSpec, CameraGrid, Vec<f32>, Vec<f32>) {
    let camera = CameraGrid {
        width: side,
        height: side,
    };
    let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 16, 16, 128, 5).unwrap();
    let truth = synthetic_t(camera, 16, 16);
    let f = frames(&spec, &truth, camera.pixels(), 0.0);
    (spec, camera, truth, f)
}

/// A 48x48 camera over a 32x32 projector: the complete Russian-doll Hadamard set and a quarter
/// of it in Bernoulli 50 % frames (256): camera, complete spec, Bernoulli spec.
fn complete_and_quarter_bernoulli_48() -> (CameraGrid, PatternSpec, PatternSpec) {
    let camera = CameraGrid {
        width: 48,
        height: 48,
    };
    let complete = russian_doll(32, 32, 1024);
    let bernoulli = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 32, 32, 256, 0).unwrap();
    (camera, complete, bernoulli)
}

/// The budget decides the blocks, never the result: blocked and unblocked `T` are the same bits.
/// (A camera of 64x64 over a 16x16 projector, 128 Bernoulli frames: the frames, 2 MiB, exceed
/// the small budget, while `A Psi^T` held densely, 260 KiB, fits a quarter of it, so both runs
/// solve by coordinate descent; a budget too small for it would solve by FISTA, another
/// iteration.)
#[test]
fn blocked_equals_unblocked_and_reads_stay_within_the_budget() {
    let (spec, camera, truth, f) = bernoulli_session(64);
    let frame_bytes = f.len() * 4;
    let budget = 1_500_000;
    assert!(
        frame_bytes > budget,
        "the session's frames ({frame_bytes} B) must exceed the budget"
    );
    let config = TransportConfig {
        sample_pixels: 2,
        ..TransportConfig::default()
    };
    let (whole, r1, s1) = run(
        &spec,
        camera,
        &f,
        &config.clone().with_memory_budget(64 << 20),
    );
    let (blocked, r2, s2) = run(
        &spec,
        camera,
        &f,
        &config.clone().with_memory_budget(budget),
    );
    println!(
        "unblocked: {}; blocked: {}",
        r1.details["memory"], r2.details["memory"]
    );
    assert_eq!(r1.details["memory"]["blocks"], 1);
    let blocks = r2.details["memory"]["blocks"].as_u64().unwrap();
    assert!(blocks >= 4, "{blocks} blocks");
    assert!(
        s2.largest_read_bytes <= budget,
        "a read of {} B over the {budget} B budget",
        s2.largest_read_bytes
    );
    assert!(r2.details["memory"]["working_set_bytes"].as_u64().unwrap() as usize <= budget);
    assert!(
        s2.reads.len() as u64 > blocks,
        "every block read separately (plus the sample)"
    );
    assert!(s1.largest_read_bytes > budget);
    assert_eq!(r1.details["transform"], r2.details["transform"]);
    assert_eq!(r1.details["lambda"], r2.details["lambda"]);
    for r in [&r1, &r2] {
        assert!(
            r.details["path"]
                .as_str()
                .unwrap()
                .contains("coordinate descent"),
            "{}",
            r.details["path"]
        );
    }
    assert!(
        whole == blocked,
        "blocked and unblocked differ: {} vs {}",
        relative_error(&dense(&whole), &dense(&blocked)),
        0
    );
    assert!(relative_error(&dense(&whole), &truth) < 0.1);
    // A budget that cannot hold one camera pixel is a clear error.
    let mut source = SliceFrames::new(&f, camera.pixels());
    let e = reconstruct_transport(
        &spec,
        camera,
        128,
        &config.clone().with_memory_budget(2_000),
        &mut source,
        &Control::new(),
    )
    .unwrap_err();
    assert!(
        e.to_string()
            .contains("memory budget of 2000 bytes is too small"),
        "{e}"
    );
}

#[test]
fn coarse_to_fine_solves_the_parents_first_and_stays_close() {
    let (spec, camera, truth, f) = small_session();
    // A budget too small for `A Psi^T` held densely: FISTA, where coarse-to-fine applies.
    let base = TransportConfig {
        transform: Some(TransformKind::Haar),
        lambda: Some(1e-3),
        ..TransportConfig::default()
    }
    .with_memory_budget(700_000);
    let (plain, rp, _) = run(
        &spec,
        camera,
        &f,
        &TransportConfig {
            coarse_to_fine: false,
            ..base.clone()
        },
    );
    let (c2f, rc, _) = run(
        &spec,
        camera,
        &f,
        &TransportConfig {
            coarse_to_fine: true,
            ..base
        },
    );
    let (ep, ec) = (
        relative_error(&dense(&plain), &truth),
        relative_error(&dense(&c2f), &truth),
    );
    println!(
        "plain: err {ep:.4}, {} iterations; coarse-to-fine: err {ec:.4}, {} iterations ({})",
        rp.iterations, rc.iterations, rc.details["coarse_to_fine"]
    );
    assert_eq!(rc.details["coarse_to_fine"]["used"], true);
    assert_eq!(rc.details["coarse_to_fine"]["parent_rows"], 64);
    // Measured: plain 0.102 (91,079 iterations), coarse-to-fine 0.174 (80,275 including 24,354
    // for the parents): here the parents' blur is a worse start than the continuation path
    // (neighbouring camera pixels see projector points a whole pixel apart).
    assert!(ep < 0.12 && ec < 2.0 * ep, "errors {ep} vs {ec}");
    // Where the rows are solved by coordinate descent, coarse-to-fine is declined, and said so.
    let (_, rd, _) = run(
        &spec,
        camera,
        &f,
        &TransportConfig {
            coarse_to_fine: true,
            ..base.with_memory_budget(64 << 20)
        },
    );
    assert_eq!(rd.details["coarse_to_fine"]["requested"], true);
    assert_eq!(rd.details["coarse_to_fine"]["used"], false);
    assert!(
        rd.details["notes"]
            .as_array()
            .is_some_and(|n| n.iter().any(|n| n
                .as_str()
                .is_some_and(|n| n.contains("coarse_to_fine off: random patterns")))),
        "{:?}",
        rd.details
    );
}

struct CancelAfter<'a> {
    inner: SliceFrames<'a>,
    control: &'a Control,
    reads: usize,
}

impl FrameSource for CancelAfter<'_> {
    fn read_pixels(&mut self, pixels: Range<usize>) -> Result<Vec<f32>, SourceError> {
        self.reads += 1;
        if self.reads == 6 {
            self.control.cancel();
        }
        self.inner.read_pixels(pixels)
    }
}

#[test]
fn cancellation_stops_between_blocks() {
    let (spec, camera, _, f) = small_session();
    let control = Control::new();
    let config = TransportConfig {
        sample_pixels: 4,
        ..TransportConfig::default()
    }
    .with_memory_budget(100_000);
    let mut source = CancelAfter {
        inner: SliceFrames::new(&f, camera.pixels()),
        control: &control,
        reads: 0,
    };
    let e = reconstruct_transport(&spec, camera, 128, &config, &mut source, &control).unwrap_err();
    assert!(matches!(e, ReconError::Cancelled), "{e}");
    assert!(
        source.reads <= 7,
        "{} reads after cancelling at the 6th",
        source.reads
    );
}

struct WrongLength;

impl FrameSource for WrongLength {
    fn read_pixels(&mut self, pixels: Range<usize>) -> Result<Vec<f32>, SourceError> {
        Ok(vec![0.0; pixels.len() * 3])
    }
}

#[test]
fn bad_sizes_are_clear_errors() {
    let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 16, 16, 128, 5).unwrap();
    let camera = CameraGrid {
        width: 4,
        height: 4,
    };
    let e = reconstruct_transport(
        &spec,
        camera,
        128,
        &TransportConfig::default(),
        &mut WrongLength,
        &Control::new(),
    )
    .unwrap_err();
    let text = e.to_string();
    assert!(
        matches!(e, ReconError::BadRows(_)) && text.contains("expected 128 frames x"),
        "{text}"
    );
    let e = reconstruct_transport(
        &spec,
        camera,
        129,
        &TransportConfig::default(),
        &mut WrongLength,
        &Control::new(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("129 frames requested"), "{e}");
    let e = reconstruct_transport(
        &spec,
        CameraGrid {
            width: 0,
            height: 4,
        },
        128,
        &TransportConfig::default(),
        &mut WrongLength,
        &Control::new(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("no pixels"), "{e}");
    // Frames from a source with a different camera width: the lengths disagree.
    let f = vec![0f32; 128 * 20];
    let mut source = SliceFrames::new(&f, 20);
    let e = reconstruct_transport(
        &spec,
        CameraGrid {
            width: 5,
            height: 5,
        },
        128,
        &TransportConfig::default(),
        &mut source,
        &Control::new(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("outside 0..20"), "{e}");
}

#[test]
fn params_parse_refuse_unknown_keys_and_round_trip() {
    let c = TransportConfig::parse(
        &json!({"transform": "db4", "lambda": 0.001, "max_iter": 50, "coarse_to_fine": true, "compact": true}),
    )
    .unwrap();
    assert_eq!(c.transform, Some(TransformKind::Db4));
    assert_eq!(c.max_iter, 50);
    assert!(c.coarse_to_fine);
    assert!(c.compact);
    assert_eq!(TransportConfig::parse(&c.params_json()).unwrap(), c);
    let d = TransportConfig::parse(&json!({})).unwrap();
    assert_eq!(d, TransportConfig::default());
    assert_eq!(TransportConfig::parse(&d.params_json()).unwrap(), d);
    assert_eq!(TransportConfig::parse(&serde_json::Value::Null).unwrap(), d);
    for (params, field) in [
        (json!({"bogus": 1}), "params.bogus"),
        (json!({"transform": "fourier"}), "params.transform"),
        (json!({"lambda": 2}), "params.lambda"),
        (json!({"max_iter": 0}), "params.max_iter"),
        (json!({"max_iter": "ten"}), "params.max_iter"),
        (json!({"holdout": 0.9}), "params.holdout"),
        (json!({"coarse_to_fine": 1}), "params.coarse_to_fine"),
        (json!({"compact": "yes"}), "params.compact"),
        (
            json!({"memory_budget_bytes": 5}),
            "params.memory_budget_bytes",
        ),
        (json!([1]), "params"),
    ] {
        let e = TransportConfig::parse(&params).unwrap_err();
        assert_eq!(e.field, field, "{params}: {e}");
    }
    assert_eq!(d.clone().with_memory_budget(1234).memory_budget_bytes, 1234);
}

/// Model-choice study (run by hand): every candidate's held-out score under two splits against
/// its true error on the sample pixels (the bench's scene; `STUDY=h50,b10` selects cases):
/// `cargo test -p helmholtz-recon --lib study_model_choice -- --ignored --nocapture`.
#[test]
#[ignore = "a study run by hand (minutes): prints, asserts nothing"]
fn study_model_choice() {
    use helmholtz_sim::{Camera, Relief};
    let (pw, ph) = (64u32, 64u32);
    let scene = Relief::demo(pw, ph, 7);
    let view = scene.view(&Camera::tilted(32, 32, 25.0));
    let m = view.pixels();
    let k = (pw * ph) as usize;
    let which = std::env::var("STUDY").unwrap_or_default();
    let rd = HadamardOrdering::RussianDoll;
    let cases = [
        ("h50", Family::Hadamard { ordering: rd }, k as u64),
        ("h25", Family::Hadamard { ordering: rd }, k as u64 / 2),
        ("b25", Family::Bernoulli { fill: 0.5 }, k as u64 / 4),
        ("b10", Family::Bernoulli { fill: 0.5 }, k as u64 / 10),
    ];
    for (name, family, count) in cases {
        if !which.is_empty() && !which.contains(name) {
            continue;
        }
        let spec = PatternSpec::new(family, pw, ph, count, 3).unwrap();
        let g = PatternGenerator::new(&spec);
        let mut p = vec![0f32; k];
        let mut f = Vec::new();
        for i in 0..count {
            g.fill_values(i, &mut p);
            let p64: Vec<f64> = p.iter().map(|&v| v as f64).collect();
            f.extend(view.render(&p64).into_iter().map(|v| v as f32));
        }
        let plan = Plan::new(&spec, count as usize, 1).unwrap();
        let pixels: Vec<usize> = sample_ranges(m, 64).into_iter().flatten().collect();
        let raws: Vec<Vec<f64>> = pixels.iter().map(|&j| plan.raw_column(&f, m, j)).collect();
        let truth: Vec<f64> = pixels.iter().flat_map(|&j| view.row(j)).collect();
        let rows = pixels.len();
        let raw_rows = plan.raw_rows();
        let random = holdout::split(raw_rows, 0.1).unwrap();
        let tail = holdout::tail(raw_rows, 0.1).unwrap();
        for (sname, split) in [("random", &random), ("tail", &tail)] {
            let (train, test) = plan.holdout_ops(split).unwrap();
            let mut bs = Vec::new();
            let mut observed = Vec::new();
            let mut full_bs = Vec::new();
            for raw in &raws {
                let tr: Vec<f64> = split.train.iter().map(|&i| raw[i]).collect();
                bs.extend(train.data(&tr));
                observed.push(split.test.iter().map(|&i| raw[i]).collect::<Vec<f64>>());
                full_bs.extend(plan.fit_data(raw));
            }
            let lipschitz = plan.lipschitz(train.op());
            let full_l = plan.lipschitz(plan.op());
            for kind in CANDIDATE_TRANSFORMS {
                let psi = kind.build(pw as usize, ph as usize);
                let sh = Shared {
                    op: train.op(),
                    dense: None,
                    psi: psi.as_ref(),
                    identity: kind == TransformKind::Identity,
                    lipschitz,
                    free: free_coefficients(kind),
                    max_iter: 300,
                    tol: 1e-4,
                    cgls_refit: true,
                };
                let shf = Shared {
                    op: plan.op(),
                    dense: None,
                    psi: psi.as_ref(),
                    identity: kind == TransformKind::Identity,
                    lipschitz: full_l,
                    free: free_coefficients(kind),
                    max_iter: 300,
                    tol: 1e-4,
                    cgls_refit: true,
                };
                let lam_max = batch::lambda_max(&sh, &bs, 8);
                let lam_full = batch::lambda_max(&shf, &full_bs, 8);
                let mut s = vec![0.0; rows * k];
                let mut sf = vec![0.0; rows * k];
                let mut t = vec![0.0; rows * k];
                let mut pred = vec![0.0; rows * test.rows()];
                for &frac in &LAMBDA_PATH {
                    let lams: Vec<f64> = lam_max.iter().map(|l| l * frac).collect();
                    batch::solve_rows(&sh, &bs, &lams, &mut s, 8, &Control::new()).unwrap();
                    sh.inverse(&s, &mut t);
                    test.apply_batch(&t, &mut pred, rows);
                    let mut score = Score::new(rows);
                    let mut per_row = Vec::new();
                    for (j, obs) in observed.iter().enumerate() {
                        let pr = &pred[j * test.rows()..(j + 1) * test.rows()];
                        score.add_channel(j, obs, pr);
                        per_row.push(
                            obs.iter()
                                .zip(pr)
                                .map(|(a, b)| (a - b).powi(2))
                                .sum::<f64>(),
                        );
                    }
                    let rho = score.finish(0.1).relative_residual.unwrap_or(f64::NAN);
                    let nnz = s.iter().filter(|v| **v != 0.0).count() as f64 / rows as f64;
                    let lams_f: Vec<f64> = lam_full.iter().map(|l| l * frac).collect();
                    batch::solve_rows(&shf, &full_bs, &lams_f, &mut sf, 8, &Control::new())
                        .unwrap();
                    let mut tf = vec![0.0; rows * k];
                    shf.inverse(&sf, &mut tf);
                    let nnz_f = sf.iter().filter(|v| **v != 0.0).count() as f64 / rows as f64;
                    let err_train = crate::metrics::relative_error(
                        &t.iter().map(|&v| v as f32).collect::<Vec<_>>(),
                        &truth.iter().map(|&v| v as f32).collect::<Vec<_>>(),
                    );
                    let err_full = crate::metrics::relative_error(
                        &tf.iter().map(|&v| v as f32).collect::<Vec<_>>(),
                        &truth.iter().map(|&v| v as f32).collect::<Vec<_>>(),
                    );
                    println!(
                        "{name} {sname:<6} {:<8} f={frac:<6} held-out {rho:.5} nnz {nnz:7.1} true(train) {err_train:.4} | full: true {err_full:.4} nnz {nnz_f:7.1}",
                        kind.name()
                    );
                }
            }
        }
    }
}

/// The data's choice against every fixed model it chooses from, judged by the truth the choice
/// never sees: the chosen model's error (after the refit on all rows) and the best fixed
/// model's, with its name.
fn choice_against_fixed(family: Family, count: u64) -> (f64, f64, String, f64, f64) {
    let truth = synthetic_t(CAM, 32, 32);
    let spec = PatternSpec::new(family.clone(), 32, 32, count, 3).unwrap();
    let f = frames(&spec, &truth, CAM.pixels(), 0.0);
    let (t, report, _) = run(&spec, CAM, &f, &TransportConfig::default());
    let chosen = relative_error(&dense(&t), &truth);
    let nnz = t.nonzeros() as f64 / CAM.pixels() as f64;
    let mut best = (f64::INFINITY, String::new());
    for kind in CANDIDATE_TRANSFORMS {
        for lambda in LAMBDA_PATH {
            let config = TransportConfig {
                transform: Some(kind),
                lambda: Some(lambda),
                ..TransportConfig::default()
            };
            let (tf, _, _) = run(&spec, CAM, &f, &config);
            let e = relative_error(&dense(&tf), &truth);
            if e < best.0 {
                best = (e, format!("{} f={lambda}", kind.name()));
            }
        }
    }
    let rows = if family.name() == "hadamard" {
        count as usize / 2
    } else {
        count as usize
    };
    let identifiable = crate::auto::identifiable_coefficients(rows, 1024);
    println!(
        "{} {count}: chosen {} f={} error {chosen:.4}, {nnz:.1} nonzeros/row (identifiable {identifiable:.0}); best fixed {} error {:.4}\n  selection best {} chosen {}",
        family.name(),
        report.details["transform"],
        report.details["lambda"],
        best.1,
        best.0,
        report.details["selection"]["best"],
        report.details["selection"]["chosen"],
    );
    (chosen, best.0, best.1, nnz, identifiable)
}

/// On Bernoulli rows (held-out rows hashed out) and on a Hadamard subset of a complete level and
/// a half (held-out pairs: the last measured ones), the chosen model's error is near the best
/// fixed model's.
#[test]
fn the_chosen_model_is_near_the_best_fixed_one_by_ground_truth() {
    for (family, count) in [
        (Family::Bernoulli { fill: 0.5 }, 256u64),
        (
            Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll,
            },
            768,
        ),
    ] {
        let name = format!("{} {count}", family.name());
        let (chosen, best, best_name, nnz, identifiable) = choice_against_fixed(family, count);
        assert!(
            chosen <= 1.25 * best,
            "{name}: chosen error {chosen} vs best fixed {best} ({best_name}); {nnz:.0} nonzeros per row ({identifiable:.0} identifiable)"
        );
    }
}

/// A known limitation of the model choice: half a Hadamard set of smooth rows. The held-out
/// pairs (the last measured ones) are predicted best by the pixel basis (held-out 0.0014 against
/// db4's 0.099), but db4 extrapolates the unmeasured pairs better (error 0.087 against 0.140):
/// the measured rows do not tell which model extrapolates. Also tried (2026-11-22): choosing the
/// transform by its extrapolation one Russian-doll level down, scored against the exact image of
/// the last complete level, fitted on the coarse grid (pixel basis 0.036, db4 0.187) or on the
/// full grid (0.036 against 0.145): with fewer rows the sparsest basis wins, so it picks the
/// pixel basis too. Run by hand; it fails today.
#[test]
#[ignore = "known limitation: the held-out model choice on Hadamard subsets of smooth rows"]
fn the_chosen_model_on_half_a_hadamard_set_of_smooth_rows() {
    let (chosen, best, best_name, _, _) = choice_against_fixed(
        Family::Hadamard {
            ordering: HadamardOrdering::RussianDoll,
        },
        1024,
    );
    assert!(
        chosen <= 1.25 * best,
        "chosen error {chosen} vs best fixed {best} ({best_name})"
    );
}

/// The refit is the least-squares solution on the warm start's support (a known answer): with
/// more rows than kept coefficients and noise-free data it recovers the sparse truth exactly,
/// where the lasso it starts from is shrunk by its weight; coefficients outside the support stay
/// zero, even where the truth is not zero.
#[test]
fn the_refit_is_least_squares_on_the_lasso_support() {
    use crate::linop::spectral_norm;
    use crate::solve::testkit::gaussian;
    use crate::transforms::TransformKind;
    let (n, k, rows) = (60, 128, 3);
    let a = gaussian(n, k, 11);
    let psi = TransformKind::Identity.build(k, 1);
    let l = spectral_norm(&a, 500, 1e-9).powi(2) * 1.02;
    let sh = Shared {
        op: &a,
        dense: None,
        psi: psi.as_ref(),
        identity: true,
        lipschitz: l,
        free: 0,
        max_iter: 20_000,
        tol: 1e-12,
        cgls_refit: true,
    };
    // Row r: 8 spikes of height 1..2 (rows 0 and 1), row 2 also one small spike of 1e-3 the
    // lasso drops.
    let mut truth = vec![0.0; rows * k];
    let mut rng = crate::testutil::Rng::new(5);
    for r in 0..rows {
        for j in 0..8 {
            truth[r * k + (j * 37 + r * 11) % k] = 1.0 + rng.uniform();
        }
    }
    truth[2 * k + 100] = 1e-3;
    let mut bs = vec![0.0; rows * n];
    for r in 0..rows {
        a.apply(&truth[r * k..(r + 1) * k], &mut bs[r * n..(r + 1) * n]);
    }
    let lam_max = batch::lambda_max(&sh, &bs, 2);
    let lams: Vec<f64> = lam_max.iter().map(|m| 0.05 * m).collect();
    let mut s = vec![0.0; rows * k];
    batch::solve_rows(&sh, &bs, &lams, &mut s, 2, &Control::new()).unwrap();
    let lasso_err = relative_error(
        &s.iter().map(|&v| v as f32).collect::<Vec<_>>(),
        &truth.iter().map(|&v| v as f32).collect::<Vec<_>>(),
    );
    let support: Vec<bool> = s.iter().map(|v| *v != 0.0).collect();
    assert!(
        !support[2 * k + 100],
        "the lasso at 5 % of lambda_max keeps the 1e-3 spike; pick a larger weight"
    );
    batch::refit_rows(&sh, &bs, &mut s, 2, &Control::new()).unwrap();
    for (i, (&v, &kept)) in s.iter().zip(&support).enumerate() {
        assert!(
            kept || v == 0.0,
            "coefficient {i} outside the support moved to {v}"
        );
    }
    for r in 0..rows {
        let row = r * k..(r + 1) * k;
        let err: f64 = s[row.clone()]
            .iter()
            .zip(&truth[row.clone()])
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            .sqrt();
        // Rows 0, 1: the truth lies on the support, so least squares recovers it (to the
        // iterative solve's tolerance); row 2: off by the dropped spike's 1e-3 (its least-squares
        // shadow on the support adds a little more).
        let bound = if r == 2 { 2e-3 } else { 1e-6 };
        assert!(
            err < bound,
            "row {r}: refit error {err:e}, lasso relative error {lasso_err:e}"
        );
    }
    assert!(
        lasso_err > 1e-2,
        "the lasso is shrunk: relative error {lasso_err:e}"
    );
    // At the default tolerance and iteration cap, the refit on the operator (CGLS) still reaches
    // the least-squares fit (the projected FISTA refit of version-4 models, which the message
    // shows, is not held to it).
    let mut lasso = vec![0.0; rows * k];
    batch::solve_rows(&sh, &bs, &lams, &mut lasso, 2, &Control::new()).unwrap();
    let defaults = TransportConfig::default();
    let refit_err = |cgls_refit: bool| {
        let at = Shared {
            max_iter: defaults.max_iter,
            tol: defaults.tol,
            cgls_refit,
            ..sh
        };
        let mut s = lasso.clone();
        batch::refit_rows(&at, &bs, &mut s, 2, &Control::new()).unwrap();
        (0..2)
            .map(|r| {
                let row = r * k..(r + 1) * k;
                s[row.clone()]
                    .iter()
                    .zip(&truth[row])
                    .map(|(a, b)| (a - b) * (a - b))
                    .sum::<f64>()
                    .sqrt()
            })
            .fold(0.0, f64::max)
    };
    let (cgls, fista) = (refit_err(true), refit_err(false));
    assert!(
        cgls < 1e-6,
        "CGLS refit at the default tolerance: error {cgls:e} (projected FISTA {fista:e})"
    );
}

/// Plans once, then solves the blocks in every grouping given (each shard from a fresh frame
/// source, in a shuffled order, its part through bytes), assembles, and checks `T` and the
/// report against one `reconstruct_transport` call. Returns the model.
fn shards_assemble_to_the_single_call(
    spec: &PatternSpec,
    camera: CameraGrid,
    f: &[f32],
    config: &TransportConfig,
    groupings: &dyn Fn(usize) -> Vec<Vec<Range<usize>>>,
) -> TransportModel {
    let (single, single_report, _) = run(spec, camera, f, config);
    let single_bytes = single.encode();
    let mut source = SliceFrames::new(f, camera.pixels());
    let model = plan_transport(
        spec,
        camera,
        spec.count(),
        config,
        &mut source,
        &Control::new(),
    )
    .unwrap();
    // The model is stored as JSON between the steps: it comes back the same, floats and all.
    let stored = TransportModel::from_json(&model.to_json()).unwrap();
    assert_eq!(stored, model);
    assert_eq!(stored.lipschitz.to_bits(), model.lipschitz.to_bits());
    let n = stored.block_count();
    let without_seconds = |r: &Report| {
        let mut r = r.clone();
        r.details.remove("seconds");
        serde_json::to_string(&r).unwrap()
    };
    let mut rng = crate::testutil::Rng::new(7);
    for grouping in groupings(n) {
        // Solved in a shuffled order, each in a process of its own as far as the numerics go.
        let mut order: Vec<usize> = (0..grouping.len()).collect();
        for i in (1..order.len()).rev() {
            let j = (rng.uniform() * (i + 1) as f64) as usize % (i + 1);
            order.swap(i, j);
        }
        let mut parts: Vec<TransportPart> = Vec::new();
        for &g in &order {
            let mut source = SliceFrames::new(f, camera.pixels());
            let part = solve_transport_blocks(
                spec,
                &stored,
                grouping[g].clone(),
                &mut source,
                &Control::new(),
            )
            .unwrap();
            // Only its own blocks' camera pixels were read.
            let pixels = stored.block_pixels(grouping[g].clone());
            assert!(
                source
                    .reads
                    .iter()
                    .all(|r| r.start >= pixels.start && r.end <= pixels.end),
                "{:?} read outside {pixels:?}",
                source.reads
            );
            let bytes = part.encode();
            let back = TransportPart::decode(&bytes).unwrap();
            assert_eq!(back, part);
            parts.push(back);
        }
        parts.sort_by_key(|p| p.blocks.start);
        let (t, report) = assemble_transport(&stored, &parts).unwrap();
        let bytes = t.encode();
        assert!(
            bytes == single_bytes,
            "grouping {grouping:?}: T differs from the single call"
        );
        assert_eq!(
            without_seconds(&report),
            without_seconds(&single_report),
            "grouping {grouping:?}"
        );
        // Parts missing or out of order are refused.
        if parts.len() > 1 {
            assert!(assemble_transport(&stored, &parts[1..]).is_err());
            let mut swapped = parts.clone();
            swapped.swap(0, 1);
            assert!(assemble_transport(&stored, &swapped).is_err());
        }
    }
    stored
}

/// One shard of everything; one block per shard; uneven runs (1, 3, 2, 1, 3, ...).
fn groupings(n: usize) -> Vec<Vec<Range<usize>>> {
    let mut uneven = Vec::new();
    let mut s = 0;
    for len in [1usize, 3, 2].iter().cycle() {
        if s >= n {
            break;
        }
        let e = (s + len).min(n);
        uneven.push(s..e);
        s = e;
    }
    vec![vec![0..n], (0..n).map(|b| b..b + 1).collect(), uneven]
}

#[test]
fn shards_of_an_exact_hadamard_set_assemble_to_the_single_process_t() {
    let spec = PatternSpec::new(
        Family::Hadamard {
            ordering: HadamardOrdering::Sequency,
        },
        32,
        32,
        2048,
        0,
    )
    .unwrap();
    let truth = synthetic_t(CAM, 32, 32);
    let f = frames(&spec, &truth, CAM.pixels(), 1e-3);
    let config = TransportConfig::default().with_memory_budget(300_000);
    let model = shards_assemble_to_the_single_call(&spec, CAM, &f, &config, &groupings);
    assert!(model.exact);
    assert!(model.block_count() >= 4, "{} blocks", model.block_count());
}

#[test]
fn shards_of_a_compressive_bernoulli_subset_assemble_to_the_single_process_t() {
    let (spec, camera, _, f) = small_session();
    let config = TransportConfig {
        sample_pixels: 4,
        ..TransportConfig::default()
    }
    .with_memory_budget(100_000);
    let model = shards_assemble_to_the_single_call(&spec, camera, &f, &config, &groupings);
    assert!(!model.exact && model.lambda.is_some());
    assert!(model.block_count() >= 4, "{} blocks", model.block_count());
}

/// A compacted model ([`prune_rows`], refitted each round) keeps the shard contract: parts
/// solved anywhere assemble to the single call's `T`, bit for bit. A model planned before
/// version 4 (no `prune`) is solved without compaction, as it was planned.
#[test]
fn shards_of_a_compacted_solve_assemble_to_the_single_process_t() {
    let (spec, camera, _, f) = bernoulli_session(32);
    let config = TransportConfig {
        sample_pixels: 16,
        compact: true,
        ..TransportConfig::default()
    }
    .with_memory_budget(1_500_000);
    let model = shards_assemble_to_the_single_call(&spec, camera, &f, &config, &groupings);
    assert!(
        !model.prune.is_empty() && model.refit,
        "{}",
        model.details["selection"]["chosen"]
    );
    let mut old: serde_json::Value = serde_json::from_str(&model.to_json()).unwrap();
    assert!(old.as_object_mut().unwrap().remove("prune").is_some());
    old["version"] = json!(3);
    let old = TransportModel::from_json(&old.to_string()).unwrap();
    assert!(old.prune.is_empty());
    let solve = |m: &TransportModel| {
        let mut source = SliceFrames::new(&f, camera.pixels());
        solve_transport_blocks(&spec, m, 0..m.block_count(), &mut source, &Control::new()).unwrap()
    };
    let (compacted, kept) = (solve(&model), solve(&old));
    assert!(
        compacted.value.len() < kept.value.len(),
        "compacted {} nonzeros, the version-3 model {}",
        compacted.value.len(),
        kept.value.len()
    );
}

/// The CGLS refit on the operator (a Hadamard subset) keeps the shard contract: parts solved
/// anywhere assemble to the single call's `T`, bit for bit. A model planned before version 5 is
/// refitted by the projected FISTA it was planned with.
#[test]
fn shards_of_a_refitted_hadamard_subset_assemble_to_the_single_process_t() {
    let camera = CameraGrid {
        width: 12,
        height: 12,
    };
    let spec = russian_doll(16, 16, 128);
    let truth = synthetic_t(camera, 16, 16);
    let f = frames(&spec, &truth, camera.pixels(), 1e-3);
    let config = TransportConfig {
        sample_pixels: 16,
        ..TransportConfig::default()
    }
    .with_memory_budget(400_000);
    let model = shards_assemble_to_the_single_call(&spec, camera, &f, &config, &groupings);
    assert!(
        model.refit && !model.dense && !model.coarse_exact,
        "{}",
        model.details["selection"]["chosen"]
    );
    assert!(model.block_count() >= 2, "{} blocks", model.block_count());
    let mut old: serde_json::Value = serde_json::from_str(&model.to_json()).unwrap();
    old["version"] = json!(4);
    let old = TransportModel::from_json(&old.to_string()).unwrap();
    let solve = |m: &TransportModel| {
        let mut source = SliceFrames::new(&f, camera.pixels());
        solve_transport_blocks(&spec, m, 0..m.block_count(), &mut source, &Control::new()).unwrap()
    };
    let (by_cgls, by_fista) = (solve(&model), solve(&old));
    assert!(by_cgls.refit_iterations > 0 && by_fista.refit_iterations > 0);
    assert_ne!(
        by_cgls, by_fista,
        "the version-4 model was refitted by CGLS too"
    );
}

/// Coordinate descent on the dense `A Psi^T` (random patterns where it fits the budget) keeps
/// the shard contract: parts solved anywhere assemble to the single call's `T`, bit for bit. A
/// model planned before version 3 (no `dense`) is solved by FISTA, as it was planned.
#[test]
fn shards_of_a_dense_coordinate_descent_solve_assemble_to_the_single_process_t() {
    let (spec, camera, _, f) = bernoulli_session(64);
    let config = TransportConfig {
        sample_pixels: 8,
        ..TransportConfig::default()
    }
    .with_memory_budget(1_500_000);
    let model = shards_assemble_to_the_single_call(&spec, camera, &f, &config, &groupings);
    assert!(model.dense, "{:?}", model.notes);
    assert!(model.block_count() >= 4, "{} blocks", model.block_count());
    let mut old: serde_json::Value = serde_json::from_str(&model.to_json()).unwrap();
    old.as_object_mut().unwrap().remove("dense");
    old["version"] = json!(2);
    let old = TransportModel::from_json(&old.to_string()).unwrap();
    assert!(!old.dense);
    let solve = |m: &TransportModel| {
        let mut source = SliceFrames::new(&f, camera.pixels());
        let part = solve_transport_blocks(&spec, m, 0..1, &mut source, &Control::new()).unwrap();
        let rows = m.block_pixels(0..1).len();
        assert!(part.iterations > 0 && rows > 0);
        part
    };
    let (by_cd, by_fista) = (solve(&model), solve(&old));
    assert_ne!(
        by_cd, by_fista,
        "the old model was solved by coordinate descent too"
    );
}

#[test]
fn shards_of_a_coarse_to_fine_solve_assemble_to_the_single_process_t() {
    let (spec, camera, _, f) = small_session();
    let config = TransportConfig {
        transform: Some(TransformKind::Haar),
        lambda: Some(1e-3),
        coarse_to_fine: true,
        ..TransportConfig::default()
    }
    .with_memory_budget(700_000);
    let model = shards_assemble_to_the_single_call(&spec, camera, &f, &config, &groupings);
    assert!(model.coarse, "{:?}", model.notes);
    assert!(model.block_count() >= 3, "{} blocks", model.block_count());
}

#[test]
fn smaller_blocks_and_shards_of_them_give_the_same_t() {
    // With coarse-to-fine requested too: declined here, the same T.
    let (spec, camera, _, f) = small_session();
    for coarse_to_fine in [false, true] {
        let config = TransportConfig {
            transform: Some(TransformKind::Haar),
            lambda: Some(1e-3),
            coarse_to_fine,
            sample_pixels: 4,
            ..TransportConfig::default()
        };
        let (single, _, _) = run(&spec, camera, &f, &config);
        let mut source = SliceFrames::new(&f, camera.pixels());
        let mut model =
            plan_transport(&spec, camera, 128, &config, &mut source, &Control::new()).unwrap();
        assert_eq!(model.block_count(), 1);
        model.limit_block_pixels(40);
        let shards = model.shards(100);
        assert!(shards.len() >= 3, "{shards:?} of {:?}", model.blocks);
        // Coordinate descent (random patterns, `A Psi^T` within the budget) declines
        // coarse-to-fine; `shards_of_a_coarse_to_fine_solve_...` covers it under FISTA.
        assert!(model.dense);
        assert!(!model.coarse);
        assert!(model.blocks.iter().all(|(a, b)| b - a <= 40));
        let parts: Vec<TransportPart> = shards
            .iter()
            .map(|s| {
                let mut source = SliceFrames::new(&f, camera.pixels());
                solve_transport_blocks(&spec, &model, s.clone(), &mut source, &Control::new())
                    .unwrap()
            })
            .collect();
        let (t, report) = assemble_transport(&model, &parts).unwrap();
        assert!(
            t.encode() == single.encode(),
            "coarse_to_fine {coarse_to_fine}"
        );
        assert_eq!(
            report.details["memory"]["blocks"].as_u64().unwrap() as usize,
            model.block_count()
        );
    }
}

#[test]
fn a_corrupt_part_is_refused() {
    let (spec, camera, _, f) = small_session();
    let config = TransportConfig {
        transform: Some(TransformKind::Haar),
        lambda: Some(1e-2),
        sample_pixels: 2,
        max_iter: 20,
        ..TransportConfig::default()
    };
    let mut source = SliceFrames::new(&f, camera.pixels());
    let model = plan_transport(&spec, camera, 128, &config, &mut source, &Control::new()).unwrap();
    let part = solve_transport_blocks(&spec, &model, 0..1, &mut source, &Control::new()).unwrap();
    let mut bytes = part.encode();
    assert_eq!(TransportPart::decode(&bytes).unwrap(), part);
    let mid = bytes.len() / 2;
    bytes[mid] ^= 1;
    assert!(matches!(
        TransportPart::decode(&bytes),
        Err(PartDecodeError::Checksum { .. })
    ));
    assert!(matches!(
        TransportPart::decode(b"HZTX\x01abcdabcd"),
        Err(PartDecodeError::BadMagic)
    ));
    // A model of another projector does not solve this session.
    let other = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 8, 8, 128, 5).unwrap();
    assert!(solve_transport_blocks(&other, &model, 0..1, &mut source, &Control::new()).is_err());
    // Blocks outside the model are refused.
    assert!(solve_transport_blocks(&spec, &model, 0..2, &mut source, &Control::new()).is_err());
}

#[test]
fn a_part_solved_from_a_process_with_other_threads_is_the_same() {
    let (spec, camera, _, f) = small_session();
    let config = TransportConfig {
        transform: Some(TransformKind::Haar),
        lambda: Some(1e-3),
        sample_pixels: 4,
        ..TransportConfig::default()
    }
    .with_memory_budget(100_000);
    let mut source = SliceFrames::new(&f, camera.pixels());
    let model = plan_transport(&spec, camera, 128, &config, &mut source, &Control::new()).unwrap();
    let here = solve_transport_blocks(&spec, &model, 0..2, &mut source, &Control::new()).unwrap();
    // A caller on a pool of another size: the part is solved on a pool of the model's size.
    let threads = if model.threads == 1 { 2 } else { 1 };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let there = pool.install(|| {
        let mut source = SliceFrames::new(&f, camera.pixels());
        solve_transport_blocks(&spec, &model, 0..2, &mut source, &Control::new()).unwrap()
    });
    assert_eq!(
        TransportPart {
            seconds: 0.0,
            ..here
        },
        TransportPart {
            seconds: 0.0,
            ..there
        }
    );
}

#[test]
fn the_model_is_chosen_on_the_pixels_that_carry_light() {
    // A camera where only every fifth pixel sees anything (a sparse slide): the sample the
    // model is chosen on is drawn from those pixels, in proportion to their light.
    let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 16, 16, 64, 5).unwrap();
    let plan = Plan::new(&spec, 64, 1).unwrap();
    let m = 100;
    let g = PatternGenerator::new(&spec);
    let mut p = vec![0f32; 256];
    let mut frames = Vec::new();
    for i in 0..64 {
        g.fill_values(i, &mut p);
        for j in 0..m {
            frames.push(if j % 5 == 2 {
                p[j * 2] * (1.0 + j as f32) + p[j * 2 + 1]
            } else {
                0.0
            });
        }
    }
    let mut source = SliceFrames::new(&frames, m);
    let mut largest = 0;
    let drawn = energy_sample(&plan, &mut source, m, 7, 12, &mut largest, &Control::new()).unwrap();
    assert!(drawn.iter().all(|d| d.1 > 0.0));
    let picked: Vec<usize> = drawn.iter().map(|d| d.0).collect();
    assert_eq!(picked.len(), 12, "{picked:?}");
    // Half from the evenly spread runs, half drawn by energy: those all lit, and more of them
    // from the bright half of the lit pixels.
    let runs: Vec<usize> = sample_ranges(m, 6).into_iter().flatten().collect();
    let by_energy: Vec<usize> = picked
        .iter()
        .copied()
        .filter(|j| !runs.contains(j))
        .collect();
    assert_eq!(by_energy.len(), 6, "{picked:?}");
    assert!(by_energy.iter().all(|j| j % 5 == 2), "{picked:?}");
    assert!(
        by_energy.iter().filter(|&&j| j >= 50).count() > 3,
        "{picked:?}"
    );
    // A lit pixel's chance is above a dark one's.
    let chance = |j: usize| drawn.iter().find(|d| d.0 == j).map(|d| d.1);
    let (lit, dark) = (
        by_energy.iter().find_map(|&j| chance(j)).unwrap(),
        runs.iter()
            .filter(|j| *j % 5 != 2)
            .find_map(|&j| chance(j))
            .unwrap(),
    );
    assert!(lit > dark, "{lit} vs {dark}");
    // Their columns are read back as they are.
    let (columns, sums) = read_columns(&plan, &mut source, &picked, 7, &mut largest).unwrap();
    assert!(sums.is_empty(), "pair sums are for Hadamard sessions");
    for (&j, col) in picked.iter().zip(&columns) {
        let want: Vec<f64> = (0..64).map(|i| frames[i * m + j] as f64).collect();
        assert_eq!(col, &want);
    }
    // All dark: the evenly spread runs.
    let dark = vec![0f32; 64 * m];
    let mut source = SliceFrames::new(&dark, m);
    let picked =
        energy_sample(&plan, &mut source, m, 7, 12, &mut largest, &Control::new()).unwrap();
    assert_eq!(picked.len(), 12);
}

#[test]
fn a_hadamard_subset_reports_the_error_its_unmeasured_coefficients_carry() {
    // Half and a quarter of a Russian-doll set: the held-out pairs (the last measured) cannot
    // see what no pair measured, so the held-out error reads near 0 while T is far off; the
    // reported estimate counts the unmeasured coefficients, and the report warns when T is
    // not supported.
    let camera = CameraGrid {
        width: 16,
        height: 16,
    };
    let m = camera.pixels();
    let truth = interreflected_t(camera, 32, 32, 0.2);
    // The extrapolation assumes a natural scene's power-law decay across scale orders; these
    // rows (Gaussian blobs and a smooth glow) decay faster at the fine end, where a quarter of
    // the set stops, so there it runs high (measured 3.0x): never low.
    for (pairs, warned, high) in [(512u64, false, 2.0), (256, true, 4.0)] {
        let spec = PatternSpec::new(
            Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll,
            },
            32,
            32,
            2 * pairs,
            0,
        )
        .unwrap();
        let f = frames(&spec, &truth, m, 0.0);
        let (t, report, _) = run(&spec, camera, &f, &TransportConfig::default());
        let err = relative_error(&dense(&t), &truth);
        let estimate = report.details["error_estimate"]["relative"]
            .as_f64()
            .unwrap();
        let held = report.held_out.as_ref().unwrap().relative_residual.unwrap();
        println!(
            "{pairs} pairs: T error {err:.4}, estimate {estimate:.4}, held-out {held:.5}, warnings {}",
            report
                .details
                .get("warnings")
                .map_or("none".into(), |w| w.to_string())
        );
        assert!(
            estimate > err / 2.0 && estimate < err * high,
            "estimate {estimate} against the true {err}"
        );
        if warned {
            // Where T is far off, the held-out score alone reads it as nearly right.
            assert!(held < err / 5.0, "held-out {held} against the true {err}");
        }
        assert_eq!(
            report.details.contains_key("warnings"),
            warned,
            "{pairs} pairs"
        );
    }
}

#[test]
fn moments_give_the_variance_with_and_without_each_value() {
    let x = [3.0, -1.5, 1e6 + 2.0, 0.25, 7.0, 1e6];
    let direct = |v: &[f64]| {
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        v.iter().map(|a| (a - mean).powi(2)).sum::<f64>() / (v.len() - 1) as f64
    };
    let m = Moments::new(&x);
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * b.abs().max(1.0);
    assert!(close(m.variance(None), direct(&x)));
    for i in 0..x.len() {
        let rest: Vec<f64> = (0..x.len()).filter(|&j| j != i).map(|j| x[j]).collect();
        assert!(close(m.variance(Some(i)), direct(&rest)), "without {i}");
    }
}

#[test]
fn a_bernoulli_session_estimates_its_relight_error_from_the_held_out_frames() {
    // Rendered scenes, 16x16 projector x 24x24 camera, 25 % Bernoulli frames. The lasso drops
    // the same dim interreflected light in many rows of the Cornell box: a full-light relight
    // adds those errors up, and the held-out relative residual, per row, does not see it.
    let camera = CameraGrid {
        width: 24,
        height: 24,
    };
    let m = camera.pixels();
    let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 16, 16, 64, 3).unwrap();
    let cornell = helmholtz_sim::RenderedTransport::cornell((16, 16), (24, 24), 1);
    let glossy = helmholtz_sim::RenderedTransport::glossy((16, 16), (24, 24), 1);
    // (scene, noise, how the estimate is resolved, whether it is within 2x of the truth).
    for (name, scene, noise, source, within) in [
        (
            "cornell",
            &cornell,
            0.0,
            "the choice's held-out frames",
            true,
        ),
        (
            "cornell",
            &cornell,
            0.01,
            "the choice's held-out frames",
            true,
        ),
        // The glints' error under noise is below what the choice's 16 held-out frames resolve;
        // cross-validation over all 64 does, with fits on 56 frames, where sparse recovery
        // of this 16x16 scene is failing: the estimate leans high (3.8x, measured).
        (
            "glossy",
            &glossy,
            0.01,
            "cross-validation over every frame in 8 folds",
            false,
        ),
    ] {
        let truth: Vec<f32> = scene.matrix().iter().map(|&v| v as f32).collect();
        let clean = frames(&spec, &truth, m, 0.0);
        let rms =
            (clean.iter().map(|v| (*v as f64).powi(2)).sum::<f64>() / clean.len() as f64).sqrt();
        let f = frames(&spec, &truth, m, noise * rms);
        let (t, report, _) = run(&spec, camera, &f, &TransportConfig::default());
        let [full, ..] = relight_errors(&dense(&t), &truth, camera, 256);
        let est = &report.details["relight_error_estimate"];
        let held = report.held_out.as_ref().unwrap().relative_residual.unwrap();
        println!("{name} noise {noise}: relit full {full:.4}, held-out {held:.4}, estimate {est}");
        let upper = est["upper"].as_f64().unwrap();
        assert!(upper >= full, "{name}: bound {upper} under the true {full}");
        assert_eq!(est["resolved"], json!(true), "{name} {noise}");
        assert_eq!(est["held_out"], json!(source), "{name} {noise}");
        let r = est["relative"]
            .as_f64()
            .unwrap_or_else(|| panic!("{name} {noise}: no estimate in {est}"));
        // Within 2x where the issue's target holds; where cross-validation leans high, no
        // more than 5x (the known lean, not a claim of calibration).
        let factor = if within { 2.0 } else { 5.0 };
        assert!(
            r > full / 2.0 && r < full * factor,
            "{name} {noise}: {r} against the true {full}"
        );
        // The fit's own noise is estimated where the choice's held-out frames do not resolve
        // the error of noisy frames, and the estimate is at least that.
        let fit_noise = est["noise"].as_f64();
        assert_eq!(
            fit_noise.is_some(),
            source.starts_with("cross"),
            "{name} {noise}: {est}"
        );
        assert!(fit_noise.is_none_or(|n| n <= r), "{name} {noise}: {est}");
        if name == "cornell" {
            assert!(held < full / 2.0, "held-out {held} against the true {full}");
            // T is not supported at this resolution, and the report says so.
            assert!(full > 0.2);
            assert!(report.details.contains_key("warnings"), "{name} {noise}");
        }
    }
}

#[test]
fn a_held_out_relight_bound_does_not_read_zero_where_the_estimate_falls_below_it() {
    // Eight sample pixels (runs of one, each drawn with chance 1/2) and 24 held-out frames
    // whose residuals vary by far less than the noise the caller expects (sigma 3 against a
    // spread of 1): the variance left after the noise is taken off is far below 0, more than
    // two standard errors (the jackknife's, over the frames). What the frames say is that the
    // error is small, not that it is 0: the bound is two standard errors above 0. (The chosen
    // fit's estimate leans low like this; on glossy spheres at 3 % frame noise the bound read
    // 0 against a true relight error of 0.0148.)
    let (rows, h, k) = (8usize, 24usize, 4usize);
    let picked: Vec<usize> = (0..rows).map(|r| 2 * r).collect();
    let chance = vec![0.5 / rows as f64; rows];
    let mut rng = crate::testutil::Rng::new(11);
    let residuals: Vec<Vec<f64>> = (0..rows)
        .map(|_| (0..h).map(|_| rng.normal()).collect())
        .collect();
    let t = vec![1.0; rows * k];
    let est = relight_from_residuals(&residuals, &t, k, (&picked, &chance), 0.5, 3.0).unwrap();
    assert!(!est.resolved);
    assert_eq!(est.relative, 0.0);
    assert!(
        est.upper > 0.0 && est.upper.is_finite(),
        "the bound reads {}",
        est.upper
    );
    // The same residuals with the noise they have: the bound is at least as high.
    let fair = relight_from_residuals(&residuals, &t, k, (&picked, &chance), 0.5, 1.0).unwrap();
    assert!(
        fair.upper >= est.upper,
        "{} against {}",
        fair.upper,
        est.upper
    );
    // Against an unresolved cross-validation, the choice's estimate stays, with the lower of
    // the two bounds and the cross-validation's noise; a resolved one replaces it.
    let cv = RelightEstimate {
        noise: Some(0.01),
        folds: RELIGHT_FOLDS,
        ..est
    };
    let both = fair.or_cross_validated(Some(cv));
    assert_eq!(both.upper, est.upper.min(fair.upper));
    assert_eq!(
        (both.relative, both.folds, both.noise),
        (fair.relative, 0, Some(0.01))
    );
    let resolved = RelightEstimate {
        resolved: true,
        ..cv
    };
    assert_eq!(fair.or_cross_validated(Some(resolved)).folds, RELIGHT_FOLDS);
}

/// Camera light `light` (0 every pixel, 1 the left half, 2 a checkerboard) at pixel `j` of a
/// camera `width` pixels wide.
fn judged_light(light: usize, j: usize, width: usize) -> f64 {
    let (x, y) = (j % width, j / width);
    let on = match light {
        0 => true,
        1 => 2 * x < width,
        _ => (x + y) % 2 == 0,
    };
    if on { 1.0 } else { 0.0 }
}

/// Relative errors of the relit images under the full, left-half and checkerboard camera
/// lights ([`judged_light`]) of `t` against `truth` (dense m x k).
fn relight_errors(t: &[f32], truth: &[f32], camera: CameraGrid, k: usize) -> [f64; 3] {
    let m = camera.pixels();
    std::array::from_fn(|light| {
        let c: Vec<f32> = (0..m)
            .map(|j| judged_light(light, j, camera.width as usize) as f32)
            .collect();
        relative_error(&relit(t, &c, k), &relit(truth, &c, k))
    })
}

/// The best of `start` and every candidate transform at weights 1e-2, 1e-3 and 1e-4 by the RMS
/// of the relit errors against `truth` (an oracle's choice): (name, RMS error).
fn best_candidate(
    start: (String, f64),
    (spec, camera, f): (&PatternSpec, CameraGrid, &[f32]),
    truth: &[f32],
    k: usize,
) -> (String, f64) {
    let mut best = start;
    for kind in CANDIDATE_TRANSFORMS {
        for lambda in [1e-2, 1e-3, 1e-4] {
            let config = TransportConfig {
                transform: Some(kind),
                lambda: Some(lambda),
                ..TransportConfig::default()
            };
            let (t, _, _) = run(spec, camera, f, &config);
            let e = rms(&relight_errors(&dense(&t), truth, camera, k));
            if e < best.1 {
                best = (format!("{} {lambda}", kind.name()), e);
            }
        }
    }
    best
}

fn rms(e: &[f64]) -> f64 {
    (e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64).sqrt()
}

#[test]
fn a_hadamard_subset_relights_within_1_5x_of_the_best_candidate_model() {
    // Half of a Russian-doll set of two rendered scenes: a glossy one (glints and a caustic:
    // a few bright projector pixels per camera pixel) and a Cornell-like box (85 % of T is a
    // dense, dim interreflection). The held-out pairs, the last measured, rated a Haar fit as
    // good as the pixel basis on the glossy scene, where its relit images were 45 % off
    // against 3 %; an identity lasso at a large weight drops the dim light of the box from
    // every row (total light 0.77). The chosen model's relit images (full, left-half and
    // checkerboard camera lights) must be within 1.5x of the best of every candidate transform
    // at every weight and the plain zero-filled inverse, each chosen by an oracle.
    let camera = CameraGrid {
        width: 24,
        height: 24,
    };
    let (pw, ph) = (32usize, 32usize);
    let k = pw * ph;
    let spec = PatternSpec::new(
        Family::Hadamard {
            ordering: HadamardOrdering::RussianDoll,
        },
        pw as u32,
        ph as u32,
        k as u64,
        0,
    )
    .unwrap();
    let m = camera.pixels();
    let scenes = [
        (
            "glossy",
            helmholtz_sim::RenderedTransport::glossy((pw, ph), (24, 24), 1),
        ),
        (
            "cornell",
            helmholtz_sim::RenderedTransport::cornell((pw, ph), (24, 24), 1),
        ),
    ];
    for (name, scene) in scenes {
        let truth = scene.dense();
        let f = frames(&spec, &truth, m, 0.0);
        let (t, report, _) = run(&spec, camera, &f, &TransportConfig::default());
        let chosen = relight_errors(&dense(&t), &truth, camera, k);
        let light = t
            .relight(&vec![1.0; m])
            .iter()
            .map(|v| *v as f64)
            .sum::<f64>()
            / truth.iter().map(|v| *v as f64).sum::<f64>();
        let oracle = (
            "zero-filled".to_string(),
            rms(&relight_errors(
                &zero_filled(&spec, &f, m),
                &truth,
                camera,
                k,
            )),
        );
        let oracle = best_candidate(oracle, (&spec, camera, &f), &truth, k);
        println!(
            "{name}: chosen {} {} (relit {chosen:.4?}, total light {light:.4}), oracle {} {:.4}",
            report.details["transform"], report.details["lambda"], oracle.0, oracle.1
        );
        assert!(
            rms(&chosen) <= 1.5 * oracle.1,
            "{name}: relit errors {chosen:?} against the oracle's {oracle:?}"
        );
        assert!((light - 1.0).abs() < 0.01, "{name}: total light {light}");
    }
}

/// What the noisy-subset tests compare: a scene's complete Russian-doll set (32x32 projector,
/// 24x24 camera) with Gaussian frame noise of 1 % of the frames' RMS, and its first half (the
/// same frames, the same noise), with the half's relit errors, its total light against the
/// truth's, and the relit errors of the same half noise-free.
struct HalfOfNoisySet {
    t_complete: TransportMatrix,
    t: TransportMatrix,
    report: Report,
    errors: [f64; 3],
    clean_errors: [f64; 3],
    light: f64,
}

fn half_of_noisy_set(scene: &helmholtz_sim::RenderedTransport) -> HalfOfNoisySet {
    let camera = CameraGrid {
        width: 24,
        height: 24,
    };
    let k = 32 * 32;
    let m = camera.pixels();
    let (complete, half) = (russian_doll(32, 32, k), russian_doll(32, 32, k / 2));
    let truth = scene.dense();
    let (clean, noisy) = clean_and_noisy(&complete, &truth, m, 0.01);
    let (t_complete, _, _) = run(&complete, camera, &noisy, &TransportConfig::default());
    // The subset's frames are the complete set's first ones.
    let f = &noisy[..half.count() as usize * m];
    let (t, report, _) = run(&half, camera, f, &TransportConfig::default());
    let errors = relight_errors(&dense(&t), &truth, camera, k);
    let light = t
        .relight(&vec![1.0; m])
        .iter()
        .map(|v| *v as f64)
        .sum::<f64>()
        / truth.iter().map(|v| *v as f64).sum::<f64>();
    let (t_clean, _, _) = run(
        &half,
        camera,
        &clean[..f.len()],
        &TransportConfig::default(),
    );
    let clean_errors = relight_errors(&dense(&t_clean), &truth, camera, k);
    HalfOfNoisySet {
        t_complete,
        t,
        report,
        errors,
        clean_errors,
        light,
    }
}

#[test]
fn a_noisy_hadamard_subset_of_sparse_rows_stores_no_more_than_the_complete_set() {
    // Rendered scenes whose rows are sparse (glints and a caustic; a slide at a grazing angle),
    // frames with Gaussian noise of 1 % of their RMS. A weight relative to each row's own
    // lambda_max alone sits below the noise in dim rows: half a Russian-doll set stored
    // 420-490 nonzeros per row where the complete set keeps 4. With every row's weight at
    // least its noise floor (a candidate the model choice weighs), the subset must store no
    // more than the complete set of the same scene, keep the total light, and relight within
    // 1.5x of the model chosen without the floor would (which these scenes' sparse rows do
    // not need).
    let scenes = [
        (
            "glossy",
            helmholtz_sim::RenderedTransport::glossy((32, 32), (24, 24), 1),
        ),
        (
            "slide",
            helmholtz_sim::RenderedTransport::slide((32, 32), (24, 24), 1),
        ),
    ];
    for (name, scene) in scenes {
        let HalfOfNoisySet {
            t_complete,
            t,
            report,
            errors,
            clean_errors,
            light,
        } = half_of_noisy_set(&scene);
        let chosen = &report.details["selection"]["chosen"];
        // The best point without the floor, refitted at the chosen transform and weight.
        let unfloored = report.details["selection"]["candidates"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|c| c["transform"] == chosen["transform"] && c.get("noise_floor").is_none())
            .map(|c| c["nonzeros_mean"].as_f64().unwrap())
            .fold(f64::INFINITY, f64::min);
        println!(
            "{name}: subset {} nonzeros ({chosen}), complete {}, sparsest unfloored point {unfloored:.1} per row; relit {errors:.4?}, total light {light:.4}",
            t.nonzeros(),
            t_complete.nonzeros()
        );
        assert_eq!(chosen["noise_floor"], true, "{name}: {chosen}");
        assert!(
            t.nonzeros() <= t_complete.nonzeros(),
            "{name}: the subset stores {} nonzeros, the complete set {}",
            t.nonzeros(),
            t_complete.nonzeros()
        );
        assert!((light - 1.0).abs() < 0.01, "{name}: total light {light}");
        // Relit as well as the noise-free subset's (the same pairs, the same model choice).
        assert!(
            rms(&errors) <= 1.5 * rms(&clean_errors) + 0.005,
            "{name}: relit {errors:?} against the noise-free subset's {clean_errors:?}"
        );
    }
}

#[test]
fn a_noisy_hadamard_subset_keeps_a_dim_interreflection_from_its_coarse_pairs_in_less_than_the_complete_set()
 {
    // The rendered Cornell box: every camera pixel sees its bright spot and a dim
    // interreflection from the whole box, below the noise in every single row. Frames with
    // Gaussian noise of 1 % of their RMS. Half a Russian-doll set stored 660-815 nonzeros per
    // row where the complete set keeps about 130 (a weight below the noise keeps the noise; the
    // floor drops the interreflection, a quarter of the light). Half the set is complete on
    // 2x2 projector blocks: those Haar coefficients are taken as measured and kept as the
    // complete set keeps its coefficients (in a row, or in a tile of camera pixels), the
    // model fills in only the finer ones. The subset must store no more than the complete
    // set, keep the total light, and relight as well as the same pairs do noise-free.
    let HalfOfNoisySet {
        t_complete,
        t,
        report,
        errors,
        clean_errors,
        light,
    } = half_of_noisy_set(&helmholtz_sim::RenderedTransport::cornell(
        (32, 32),
        (24, 24),
        1,
    ));
    let chosen = &report.details["selection"]["chosen"];
    println!(
        "cornell: subset {} nonzeros ({chosen}), complete {}; relit {errors:.4?}, noise-free {clean_errors:.4?}, total light {light:.4}",
        t.nonzeros(),
        t_complete.nonzeros()
    );
    assert_eq!(chosen["coarse_exact"], true, "{chosen}");
    assert_eq!(report.details["stored_transform"], "haar");
    assert!(
        t.nonzeros() <= t_complete.nonzeros(),
        "the subset stores {} nonzeros, the complete set {}",
        t.nonzeros(),
        t_complete.nonzeros()
    );
    assert!((light - 1.0).abs() < 0.01, "total light {light}");
    assert!(
        rms(&errors) <= 1.5 * rms(&clean_errors) + 0.005,
        "relit {errors:?} against the noise-free subset's {clean_errors:?}"
    );
}

#[test]
fn a_noisy_bernoulli_session_of_sparse_rows_stores_no_more_than_the_complete_set() {
    // 25 % Bernoulli frames with Gaussian noise of 1 % of their RMS, 48x48 camera. Without a
    // floor the dim rows fitted their noise (glossy 384 nonzeros per row, slide 190, where the
    // complete set keeps 3.8 and 4.2). The floor comes from the frames' noise, the sample
    // pixels' median moment estimate (per row it scatters 30x on bright sparse rows); it must
    // be chosen, store no more than the complete noisy set, and relight within 1.5x (+0.005)
    // of the noise-free session. (At a 24x24 camera glossy stores 1.4x the complete set's.)
    let (camera, complete, bernoulli) = complete_and_quarter_bernoulli_48();
    let (pw, ph) = (32usize, 32usize);
    let k = pw * ph;
    let m = camera.pixels();
    let scenes = [
        (
            "glossy",
            helmholtz_sim::RenderedTransport::glossy((pw, ph), (48, 48), 1),
        ),
        (
            "slide",
            helmholtz_sim::RenderedTransport::slide((pw, ph), (48, 48), 1),
        ),
    ];
    for (name, scene) in scenes {
        let truth = scene.dense();
        let clean = frames(&bernoulli, &truth, m, 0.0);
        let frame_rms =
            (clean.iter().map(|v| (*v as f64).powi(2)).sum::<f64>() / clean.len() as f64).sqrt();
        let noisy = frames(&bernoulli, &truth, m, 0.01 * frame_rms);
        let (t, report, _) = run(&bernoulli, camera, &noisy, &TransportConfig::default());
        let chosen = &report.details["selection"]["chosen"];
        let errors = relight_errors(&dense(&t), &truth, camera, k);
        let (t_clean, _, _) = run(&bernoulli, camera, &clean, &TransportConfig::default());
        let clean_errors = relight_errors(&dense(&t_clean), &truth, camera, k);
        let complete_frames = frames(&complete, &truth, m, 0.01 * frame_rms);
        let (t_complete, _, _) = run(
            &complete,
            camera,
            &complete_frames,
            &TransportConfig::default(),
        );
        println!(
            "{name}: {} nonzeros ({chosen}), complete set {}; relit {errors:.4?}, noise-free {clean_errors:.4?}",
            t.nonzeros(),
            t_complete.nonzeros()
        );
        assert_eq!(chosen["noise_floor"], true, "{name}: {chosen}");
        assert!(
            t.nonzeros() <= t_complete.nonzeros(),
            "{name}: stores {} nonzeros, the complete set {}",
            t.nonzeros(),
            t_complete.nonzeros()
        );
        assert!(
            rms(&errors) <= 1.5 * rms(&clean_errors) + 0.005,
            "{name}: relit {errors:?} against the noise-free session's {clean_errors:?}"
        );
    }
}

#[test]
fn projector_binning_inverts_the_block_constant_pairs_of_a_subset_exactly() {
    // A quarter (or more) of a Russian-doll set on a 32x32 projector holds every Walsh function
    // constant on 2x2 blocks: the complete set of the 16x16 grid. With projector_binning 2 the
    // coarse T (each column the light of a 2x2 block) comes out exact (the full-resolution fit
    // of a quarter is 77 % off); the report offers the finest complete grid.
    let camera = CameraGrid {
        width: 12,
        height: 12,
    };
    let (pw, ph, b) = (32usize, 32usize, 2usize);
    let (k, kc) = (pw * ph, (pw / b) * (ph / b));
    let m = camera.pixels();
    let spec_of = |pairs: usize| {
        PatternSpec::new(
            Family::Hadamard {
                ordering: HadamardOrdering::RussianDoll,
            },
            pw as u32,
            ph as u32,
            2 * pairs as u64,
            0,
        )
        .unwrap()
    };
    let scene = helmholtz_sim::RenderedTransport::cornell((pw, ph), (12, 12), 1);
    let truth = scene.dense();
    let binned: Vec<f32> = truth
        .chunks_exact(k)
        .flat_map(|row| {
            let mut out = vec![0f64; kc];
            for (i, v) in row.iter().enumerate() {
                out[(i / pw / b) * (pw / b) + (i % pw) / b] += *v as f64;
            }
            out.into_iter().map(|v| v as f32)
        })
        .collect();
    let config = TransportConfig {
        projector_binning: b as u32,
        ..TransportConfig::default()
    };
    // (pairs, complete on the 16x16 grid, the grid the full-resolution report offers).
    for (pairs, complete, offer) in [(k / 2, true, 2), (k / 4, true, 2), (k / 8, false, 4)] {
        let spec = spec_of(pairs);
        let f = frames(&spec, &truth, m, 0.0);
        let (t, report, _) = run(&spec, camera, &f, &config);
        assert_eq!(t.projector(), ((pw / b) as u32, (ph / b) as u32));
        let err = relative_error(&dense(&t), &binned);
        let (_, full, _) = run(&spec, camera, &f, &TransportConfig::default());
        println!(
            "{pairs} pairs: binned T error {err:.2e} ({}); the full-resolution report offers {}",
            report.details["path"], full.details["coarser"]["projector_binning"]
        );
        assert_eq!(full.details["coarser"]["projector_binning"], offer);
        if complete {
            // The exact inverse, less the coefficients it finds below the noise (noise-free,
            // the f32 rounding; measured 8.5e-4 on this scene's dense, dim interreflection).
            assert_eq!(
                report.details["path"],
                "exact inverse of a complete set, coefficients below the noise dropped"
            );
            assert!(err < 1e-3, "binned T error {err}");
        } else {
            // An eighth: complete on 8x8 only; at 16x16 a compressive fit, not exact.
            assert!(err > 1e-3 && err < 0.5, "binned T error {err}");
        }
    }
    // Other families, and factors that do not tile the grid, are refused naming the field.
    let bernoulli = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 32, 32, 64, 0).unwrap();
    let e = config.check(&bernoulli).unwrap_err();
    assert_eq!(e.field, "params.projector_binning", "{e}");
    let e = TransportConfig {
        projector_binning: 64,
        ..TransportConfig::default()
    }
    .check(&spec_of(k / 2))
    .unwrap_err();
    assert_eq!(e.field, "params.projector_binning", "{e}");
    let e = TransportConfig::parse(&json!({"projector_binning": 3})).unwrap_err();
    assert_eq!(e.field, "params.projector_binning", "{e}");
}

#[test]
fn a_bernoulli_session_relights_within_1_5x_of_the_best_candidate_model() {
    // 25 % Bernoulli frames of two rendered scenes (glints and a caustic; a Cornell-like box
    // with a dense, dim interreflection), noise-free. The chosen model's relit images (full,
    // left-half and checkerboard camera lights) must be within 1.5x of the best of every
    // candidate transform at weights 1e-2, 1e-3 and 1e-4, each chosen by an oracle. (The
    // minimum-norm least-squares solution, the issue's other baseline, is 0.39-0.85 off on
    // these scenes: it cannot be the best.)
    let camera = CameraGrid {
        width: 16,
        height: 16,
    };
    let (pw, ph) = (32usize, 32usize);
    let k = pw * ph;
    let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 32, 32, 256, 0).unwrap();
    let m = camera.pixels();
    let scenes = [
        (
            "glossy",
            helmholtz_sim::RenderedTransport::glossy((pw, ph), (16, 16), 1),
        ),
        (
            "cornell",
            helmholtz_sim::RenderedTransport::cornell((pw, ph), (16, 16), 1),
        ),
    ];
    for (name, scene) in scenes {
        let truth = scene.dense();
        let f = frames(&spec, &truth, m, 0.0);
        let (t, report, _) = run(&spec, camera, &f, &TransportConfig::default());
        let chosen = relight_errors(&dense(&t), &truth, camera, k);
        let oracle = best_candidate(
            (String::new(), f64::INFINITY),
            (&spec, camera, &f),
            &truth,
            k,
        );
        println!(
            "{name}: chosen {} {} (relit {chosen:.4?}), oracle {} {:.4}",
            report.details["transform"], report.details["lambda"], oracle.0, oracle.1
        );
        assert!(
            rms(&chosen) <= 1.5 * oracle.1,
            "{name}: relit errors {chosen:?} against the oracle's {oracle:?}"
        );
    }
}

/// Half a 32x32 Russian-doll set (and a quarter: exactly the 16x16 level) measures every Haar
/// coefficient coarser than the finest level: those of `Psi A^T A t` are those of `Psi t`,
/// whatever `t` is ([`CoarseExact`]), and no others are.
#[test]
fn a_subset_complete_on_blocks_measures_the_coarse_haar_coefficients_exactly() {
    let (w, h) = (32usize, 32usize);
    let k = w * h;
    for share in [2, 4] {
        let spec = russian_doll(w, h, k / share);
        let plan = Plan::new(&spec, spec.count() as usize, 1).unwrap();
        let Raw::Hadamard(op) = &plan.raw else {
            panic!("a Hadamard plan")
        };
        let step = CoarseExact::new(&plan, op).expect("complete on 2x2");
        assert_eq!(step.positions.len(), k / 4);
        let psi = TransformKind::Haar.build(w, h);
        let mut rng = crate::testutil::Rng::new(5);
        let t: Vec<f64> = (0..k).map(|_| rng.normal()).collect();
        let mut y = vec![0.0; op.rows()];
        op.apply(&t, &mut y);
        let mut back = vec![0.0; k];
        op.adjoint(&y, &mut back);
        let (mut z, mut truth) = (vec![0.0; k], vec![0.0; k]);
        psi.apply(&back, &mut z);
        psi.apply(&t, &mut truth);
        for &i in &step.positions {
            assert!(
                (z[i] - truth[i]).abs() < 1e-9,
                "1/{share}: coefficient {i}: {} against {}",
                z[i],
                truth[i]
            );
        }
        // The finer coefficients are not all measured.
        let off: f64 = (0..k)
            .filter(|i| !step.positions.contains(i))
            .map(|i| (z[i] - truth[i]).powi(2))
            .sum();
        assert!(
            off > 1.0,
            "1/{share}: the finer coefficients are measured too ({off})"
        );
    }
}

/// A Bernoulli session's fitting operator (centred; 16x16 projector, 96 frames), the Haar
/// transform and the fitting data of three camera pixels of [`synthetic_t`] (noise-free).
fn bernoulli_rows() -> (PatternSpec, Vec<Vec<f64>>) {
    let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 16, 16, 96, 4).unwrap();
    let camera = CameraGrid {
        width: 3,
        height: 1,
    };
    let t = synthetic_t(camera, 16, 16);
    let f = frames(&spec, &t, 3, 0.0);
    let plan = Plan::new(&spec, 96, 1).unwrap();
    let rows = (0..3)
        .map(|c| plan.fit_data(&plan.raw_column(&f, 3, c)))
        .collect();
    (spec, rows)
}

/// `1/2 ||M s - b||^2 + lambda ||s[free..]||_1` for one row.
fn lasso_objective(dense: &batch::Dense, b: &[f64], s: &[f64], lam: f64, free: usize) -> f64 {
    let fit = dense.product(s);
    let r2: f64 = fit.iter().zip(b).map(|(f, b)| (f - b) * (f - b)).sum();
    0.5 * r2 + lam * s[free..].iter().map(|v| v.abs()).sum::<f64>()
}

/// Coordinate descent on the dense `A Psi^T` ([`batch::Dense`]) solves the problem FISTA on the
/// operator solves (a known answer: both, run from zero to a tight tolerance on a Bernoulli
/// session's rows in the Haar basis, reach the same lasso solution and the same refit), and its
/// solution meets the lasso's optimality conditions: `|g_c| <= lambda` where `s_c = 0`,
/// `g_c = lambda sign(s_c)` elsewhere, `g_c = 0` for the free DC coefficient, with
/// `g = Psi A^T (b - A Psi^T s)` computed by the operator, not by the dense columns.
#[test]
fn coordinate_descent_on_the_dense_system_solves_the_lasso_fista_solves() {
    let (spec, rows) = bernoulli_rows();
    let plan = Plan::new(&spec, 96, 1).unwrap();
    let op = plan.op();
    let k = op.cols();
    let kind = TransformKind::Haar;
    let psi = kind.build(16, 16);
    let free = free_coefficients(kind);
    let fista = Shared {
        op,
        dense: None,
        psi: psi.as_ref(),
        identity: false,
        lipschitz: plan.lipschitz(op),
        free,
        max_iter: 400_000,
        tol: 1e-13,
        cgls_refit: true,
    };
    let dense = batch::Dense::new(&fista);
    let cd = Shared {
        dense: Some(&dense),
        ..fista
    };
    // The dense columns are the operator: M s = A Psi^T s.
    let mut rng = crate::testutil::Rng::new(3);
    let s: Vec<f64> = (0..k).map(|_| rng.uniform() - 0.5).collect();
    let mut x = vec![0.0; k];
    psi.adjoint(&s, &mut x);
    let mut want = vec![0.0; op.rows()];
    op.apply(&x, &mut want);
    let got = dense.product(&s);
    let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for (g, w) in got.iter().zip(&want) {
        assert!(
            (g - w).abs() <= 1e-12 * scale,
            "M s {g} against A Psi^T s {w}"
        );
    }
    let bs: Vec<f64> = rows.iter().flatten().copied().collect();
    let lams: Vec<f64> = batch::lambda_max(&fista, &bs, 3)
        .iter()
        .map(|l| 0.02 * l)
        .collect();
    let mut by_fista = vec![0.0; 3 * k];
    let mut by_cd = vec![0.0; 3 * k];
    batch::solve_rows(&fista, &bs, &lams, &mut by_fista, 3, &Control::new()).unwrap();
    let sweeps = batch::solve_rows(&cd, &bs, &lams, &mut by_cd, 3, &Control::new()).unwrap();
    let n = op.rows();
    for r in 0..3 {
        let (sf, sc) = (&by_fista[r * k..(r + 1) * k], &by_cd[r * k..(r + 1) * k]);
        let b = &bs[r * n..(r + 1) * n];
        let (of, oc) = (
            lasso_objective(&dense, b, sf, lams[r], free),
            lasso_objective(&dense, b, sc, lams[r], free),
        );
        assert!(
            (of - oc).abs() <= 1e-9 * of,
            "row {r}: objective {oc} by coordinate descent ({} sweeps), {of} by FISTA",
            sweeps[r]
        );
        let big = sf.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (c, (a, b)) in sf.iter().zip(sc).enumerate() {
            assert!(
                (a - b).abs() <= 1e-6 * big,
                "row {r} coefficient {c}: {b} by coordinate descent, {a} by FISTA"
            );
        }
        let mut fit = vec![0.0; k];
        psi.adjoint(sc, &mut fit);
        let mut pred = vec![0.0; n];
        op.apply(&fit, &mut pred);
        let res: Vec<f64> = b.iter().zip(&pred).map(|(b, p)| b - p).collect();
        let mut back = vec![0.0; k];
        op.adjoint(&res, &mut back);
        let mut g = vec![0.0; k];
        psi.apply(&back, &mut g);
        let lam = lams[r];
        for c in 0..k {
            let ok = if c < free {
                g[c].abs() <= 1e-6 * lam
            } else if sc[c] == 0.0 {
                g[c].abs() <= lam * (1.0 + 1e-6)
            } else {
                (g[c] - lam * sc[c].signum()).abs() <= 1e-6 * lam
            };
            assert!(
                ok,
                "row {r} coefficient {c}: s {}, gradient {} against lambda {lam}",
                sc[c], g[c]
            );
        }
    }
    batch::refit_rows(&fista, &bs, &mut by_fista, 3, &Control::new()).unwrap();
    batch::refit_rows(&cd, &bs, &mut by_cd, 3, &Control::new()).unwrap();
    let big = by_fista.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for (i, (a, b)) in by_fista.iter().zip(&by_cd).enumerate() {
        assert!(
            (a - b).abs() <= 1e-6 * big,
            "refit coefficient {i}: {b} by coordinate descent, {a} by FISTA"
        );
    }
}

/// A row solved by coordinate descent depends on its own data, weight and warm start alone: the
/// same bits solved with other rows or alone (any block, shard or chunk), and with the AVX2 copy
/// of the sweep or the baseline one.
#[test]
fn a_coordinate_descent_row_is_the_same_alone_in_a_batch_and_on_either_instruction_set() {
    let (spec, rows) = bernoulli_rows();
    let plan = Plan::new(&spec, 96, 1).unwrap();
    let op = plan.op();
    let (n, k) = (op.rows(), op.cols());
    let psi = TransformKind::Haar.build(16, 16);
    let mut sh = Shared {
        op,
        dense: None,
        psi: psi.as_ref(),
        identity: false,
        lipschitz: plan.lipschitz(op),
        free: 1,
        max_iter: 300,
        tol: 1e-4,
        cgls_refit: true,
    };
    let dense = batch::Dense::new(&sh);
    sh.dense = Some(&dense);
    let bs: Vec<f64> = rows.iter().flatten().copied().collect();
    let lams: Vec<f64> = batch::lambda_max(&sh, &bs, 3)
        .iter()
        .map(|l| 0.01 * l)
        .collect();
    let mut all = vec![0.0; 3 * k];
    batch::solve_rows(&sh, &bs, &lams, &mut all, 2, &Control::new()).unwrap();
    for baseline in [true, false] {
        crate::simd::force_baseline(baseline);
        let mut alone = vec![0.0; k];
        batch::solve_rows(
            &sh,
            &bs[n..2 * n],
            &lams[1..2],
            &mut alone,
            1,
            &Control::new(),
        )
        .unwrap();
        assert!(
            alone
                .iter()
                .zip(&all[k..2 * k])
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "row 1 alone (baseline copies: {baseline}) differs from row 1 among three"
        );
    }
    crate::simd::force_baseline(false);
}

#[test]
fn compaction_drops_the_smallest_coefficients_within_the_energy_and_light_budgets() {
    // Rows of 64 coefficients with magnitudes spread over four decades, in the pixel basis
    // (every coefficient carries light) and in Haar (only the free first one does).
    let (pw, ph) = (8usize, 8usize);
    let k = pw * ph;
    let mut rng = 0x2545F4914F6CDD1Du64;
    let mut next = || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        (rng >> 11) as f64 / (1u64 << 53) as f64
    };
    for kind in [TransformKind::Identity, TransformKind::Haar] {
        let ones = constant_coefficients(kind, (pw, ph));
        let free = free_coefficients(kind);
        let rows: Vec<f64> = (0..3 * k)
            .map(|i| {
                let v = 10f64.powf(-4.0 * next());
                // Some exact zeros; signed in Haar, positive light in the pixel basis.
                if i % 7 == 3 {
                    0.0
                } else if kind == TransformKind::Haar && next() < 0.5 {
                    -v
                } else {
                    v
                }
            })
            .collect();
        for share in [1e-3, 1e-2, 0.1] {
            let mut pruned = rows.clone();
            let dropped = prune_rows(&mut pruned, k, share, free, &ones);
            let mut counted = 0;
            for (before, after) in rows.chunks_exact(k).zip(pruned.chunks_exact(k)) {
                let energy: f64 = before.iter().map(|v| v * v).sum();
                let light: f64 = before.iter().zip(&ones).map(|(v, o)| (v * o).abs()).sum();
                let gone: Vec<usize> = (0..k)
                    .filter(|&i| before[i] != 0.0 && after[i] == 0.0)
                    .collect();
                counted += gone.len();
                // Nothing else changes; the free coefficients stay.
                for i in 0..k {
                    assert!(after[i] == before[i] || gone.contains(&i));
                }
                assert!(gone.iter().all(|&i| i >= free));
                let e: f64 = gone.iter().map(|&i| before[i] * before[i]).sum();
                let sum: f64 = gone.iter().map(|&i| before[i] * ones[i]).sum();
                assert!(e <= share * share * energy, "{kind:?} {share}: energy");
                assert!(sum.abs() <= share * light, "{kind:?} {share}: light");
                // Smallest first, and as many as the budgets allow: the next smallest kept
                // coefficient would break one.
                let largest_gone = gone.iter().map(|&i| before[i].abs()).fold(0.0, f64::max);
                let kept: Vec<usize> = (free..k).filter(|&i| after[i] != 0.0).collect();
                assert!(kept.iter().all(|&i| after[i].abs() >= largest_gone));
                if let Some(&next) = kept
                    .iter()
                    .min_by(|&&a, &&b| after[a].abs().total_cmp(&after[b].abs()).then(a.cmp(&b)))
                {
                    let v = before[next];
                    assert!(
                        e + v * v > share * share * energy
                            || (sum + v * ones[next]).abs() > share * light,
                        "{kind:?} {share}: coefficient {next} ({v}) fits both budgets"
                    );
                }
            }
            assert_eq!(dropped, counted);
            assert!(dropped > 0, "{kind:?} {share}: nothing dropped");
        }
    }
}

#[test]
fn a_noise_free_bernoulli_session_compacted_stores_no_more_than_the_complete_set() {
    // 25 % Bernoulli frames, noise-free, a 48x48 camera over a 32x32 projector: the demo
    // relief (a diffuse height field, about 44 nonzeros per row in the complete set). The lasso
    // at the chosen weight keeps small spurious coefficients (66 per row), more than the
    // complete set's exact rows. Compacted and refitted ([`prune_rows`], `compact`, the
    // default), the fit must be chosen, store no more than the complete set, and relight no
    // worse than the fit that keeps them (`compact: false`).
    let (camera, complete, bernoulli) = complete_and_quarter_bernoulli_48();
    let (pw, ph) = (32usize, 32usize);
    let k = pw * ph;
    let m = camera.pixels();
    let relief = helmholtz_sim::Relief::demo(32, 32, 7);
    let scenes = [(
        "relief",
        relief
            .view(&helmholtz_sim::Camera::tilted(48, 48, 25.0))
            .dense(),
    )];
    let keep_all = TransportConfig {
        compact: false,
        ..TransportConfig::default()
    };
    let compact = TransportConfig::default();
    for (name, truth) in scenes {
        let f = frames(&bernoulli, &truth, m, 0.0);
        let (t, report, _) = run(&bernoulli, camera, &f, &compact);
        let (t_all, _, _) = run(&bernoulli, camera, &f, &keep_all);
        let complete_frames = frames(&complete, &truth, m, 0.0);
        let (t_complete, _, _) = run(
            &complete,
            camera,
            &complete_frames,
            &TransportConfig::default(),
        );
        let errors = relight_errors(&dense(&t), &truth, camera, k);
        let all_errors = relight_errors(&dense(&t_all), &truth, camera, k);
        println!(
            "{name}: {} nonzeros (prune {}), without compaction {}, complete set {}; relit {errors:.5?}, without {all_errors:.5?}",
            t.nonzeros(),
            report.details["prune"],
            t_all.nonzeros(),
            t_complete.nonzeros()
        );
        // The case is real: without compaction the session stores more than the complete set.
        assert!(t_all.nonzeros() > t_complete.nonzeros(), "{name}");
        assert!(
            report.details["prune"]
                .as_array()
                .is_some_and(|p| !p.is_empty()),
            "{name}: {}",
            report.details["selection"]["chosen"]
        );
        assert!(
            t.nonzeros() <= t_complete.nonzeros(),
            "{name}: stores {} nonzeros, the complete set {}",
            t.nonzeros(),
            t_complete.nonzeros()
        );
        assert!(
            rms(&errors) <= 1.1 * rms(&all_errors) + 1e-5,
            "{name}: relit {errors:?} against {all_errors:?} without compaction"
        );
    }
}

#[test]
fn a_noisy_hadamard_subset_stores_no_more_than_the_complete_set_and_keeps_its_light() {
    // Half a Russian-doll set of the demo relief (32x32 projector, 48x48 camera) at 1 % frame
    // noise: the chosen model takes the coarse Haar coefficients as measured ([`CoarseExact`])
    // and supplies the finer ones. Before model version 6 it kept every finer coefficient of
    // the model's image above the f32 resolution, more per row than the complete set at the
    // same noise keeps; now they are held to the complete set's noise test at
    // [`FINE_THRESHOLD_SHARE`] of its thresholds. The stored T must
    // be no larger than the complete set's, relight no worse than the same model replayed as
    // version 5, and keep every row's total light (finer Haar functions sum to zero).
    let (camera, complete, _) = complete_and_quarter_bernoulli_48();
    let k = 32 * 32;
    let m = camera.pixels();
    let truth = helmholtz_sim::Relief::demo(32, 32, 7)
        .view(&helmholtz_sim::Camera::tilted(48, 48, 25.0))
        .dense();
    let noisy = |spec: &PatternSpec| {
        let clean = frames(spec, &truth, m, 0.0);
        let rms =
            (clean.iter().map(|v| (*v as f64).powi(2)).sum::<f64>() / clean.len() as f64).sqrt();
        frames(spec, &truth, m, 0.01 * rms)
    };
    let half = russian_doll(32, 32, 512);
    let f = noisy(&half);
    let config = TransportConfig::default();
    let mut source = SliceFrames::new(&f, m);
    let model = plan_transport(
        &half,
        camera,
        half.count(),
        &config,
        &mut source,
        &Control::new(),
    )
    .unwrap();
    assert!(
        model.coarse_exact,
        "the case needs the coarse coefficients taken as measured: {}",
        model.details["selection"]["chosen"]
    );
    let mut old: serde_json::Value = serde_json::from_str(&model.to_json()).unwrap();
    old["version"] = json!(5);
    let old = TransportModel::from_json(&old.to_string()).unwrap();
    let solve = |m: &TransportModel| {
        let mut source = SliceFrames::new(&f, camera.pixels());
        let part =
            solve_transport_blocks(&half, m, 0..m.block_count(), &mut source, &Control::new())
                .unwrap();
        assemble_transport(m, std::slice::from_ref(&part))
            .unwrap()
            .0
    };
    let (t, t5) = (solve(&model), solve(&old));
    let (t_complete, _, _) = run(&complete, camera, &noisy(&complete), &config);
    let (errors, errors5) = (
        relight_errors(&dense(&t), &truth, camera, k),
        relight_errors(&dense(&t5), &truth, camera, k),
    );
    println!(
        "{} nonzeros (version 5: {}), complete set {}; relit {errors:.5?}, version 5 {errors5:.5?}",
        t.nonzeros(),
        t5.nonzeros(),
        t_complete.nonzeros()
    );
    // The case is real: the model as version 5 stores more than the complete set.
    assert!(t5.nonzeros() > t_complete.nonzeros());
    assert!(
        t.nonzeros() <= t_complete.nonzeros(),
        "stores {} nonzeros, the complete set {}",
        t.nonzeros(),
        t_complete.nonzeros()
    );
    for (e, e5) in errors.iter().zip(&errors5) {
        assert!(
            *e <= 1.02 * e5 + 1e-5,
            "relit {errors:?} against {errors5:?}"
        );
    }
    let (d, d5) = (dense(&t), dense(&t5));
    for (j, (row, row5)) in d.chunks_exact(k).zip(d5.chunks_exact(k)).enumerate() {
        let (s, s5) = (
            row.iter().map(|v| *v as f64).sum::<f64>(),
            row5.iter().map(|v| *v as f64).sum::<f64>(),
        );
        let scale = row5.iter().map(|v| v.abs() as f64).sum::<f64>().max(1e-30);
        assert!(
            (s - s5).abs() <= 1e-5 * scale,
            "row {j}: light {s} against {s5}"
        );
    }
}

/// A rendered scene by name (`cornell`, `glossy`, `slide`; seed 1).
fn rendered(
    name: &str,
    projector: (usize, usize),
    camera: (usize, usize),
) -> helmholtz_sim::RenderedTransport {
    match name {
        "cornell" => helmholtz_sim::RenderedTransport::cornell(projector, camera, 1),
        "glossy" => helmholtz_sim::RenderedTransport::glossy(projector, camera, 1),
        "slide" => helmholtz_sim::RenderedTransport::slide(projector, camera, 1),
        _ => panic!("no rendered scene {name}"),
    }
}

#[test]
fn a_hadamard_subset_reports_its_relight_error_from_the_same_problem_one_grid_coarser() {
    // Rendered scenes (interreflections, glints and a caustic, a sparse slide), 32x32
    // projector, 24x24 camera; the first half and the first quarter of a Russian-doll set,
    // noise-free and with frame noise of 1 % of the frames' RMS. A subset reported only an
    // error of T (each row's unmeasured part extrapolated from its measured scale orders):
    // 4-16x the full-light relight error of half a set. The relight's own estimate comes from
    // the same share of the coarser grid the pairs complete, fitted with the chosen model and
    // judged against all of that grid's pairs. A coarser grid is easier, so it leans low:
    // within 2x of the truth, and above half of it but on the slide's half set, whose error lies
    // in the finest diagonal Walsh functions, which the coarser grid's easier problem
    // predicts better (0.24x at a true 1.0 %, measured on a 48x48 camera; the relief, not
    // here, leans as low: 0.14-0.4x).
    let camera = CameraGrid {
        width: 24,
        height: 24,
    };
    let (pw, ph) = (32, 32);
    let k = pw * ph;
    let m = camera.pixels();
    for name in ["cornell", "glossy", "slide"] {
        let truth = rendered(name, (pw, ph), (24, 24)).dense();
        for share in [2, 4] {
            let spec = russian_doll(pw, ph, k / share);
            let (clean, noisy) = clean_and_noisy(&spec, &truth, m, 0.01);
            for (noise, f) in [("noise-free", &clean), ("1 % noise", &noisy)] {
                let (t, report, _) = run(&spec, camera, f, &TransportConfig::default());
                let estimate = &report.details["relight_error_estimate"];
                // Where the noise summed over the camera swamps it, only the bound.
                let est = estimate["relative"]
                    .as_f64()
                    .or_else(|| estimate["upper"].as_f64())
                    .unwrap();
                let full = relight_errors(&dense(&t), &truth, camera, k)[0];
                let ratio = est / full;
                println!(
                    "{name} 1/{share} {noise}: full-light relight error {full:.4}, estimate {est:.4} ({ratio:.2}x; {})",
                    estimate["coarse_pairs"]
                );
                assert_eq!(
                    estimate["coarse_grid"],
                    json!([16, 16]),
                    "{name}: {estimate}"
                );
                assert!(est > 0.0, "{name} 1/{share} {noise}: {estimate}");
                let low = if name == "slide" && share == 2 {
                    0.15
                } else {
                    0.5
                };
                assert!(
                    (low..=2.0).contains(&ratio),
                    "{name} 1/{share} {noise}: estimate {est} against a true {full}"
                );
            }
        }
    }
}

#[test]
fn a_noise_free_quarter_set_on_a_small_projector_claims_no_error_it_cannot_see() {
    // The rendered Cornell box on an 8x8 projector, 48x48 camera, the first quarter of a
    // Russian-doll set (complete on the 4x4 grid), noise-free: the chosen model zero-fills the
    // finer coefficients. The range of a sample row's unmeasured error had two ends equal but
    // for rounding (one through the square of a square root), and its clamp panicked; and with
    // no scale order of 8 measured coefficients to extrapolate from, the reported T error was
    // 1e-17 against a true 0.86. The error of the unmeasured part is unknown there: no error
    // estimate rather than a wrong one (and no relight estimate: a quarter of the 4x4 grid's
    // pairs is too few to fit).
    let camera = CameraGrid {
        width: 48,
        height: 48,
    };
    let scene = helmholtz_sim::RenderedTransport::cornell((8, 8), (48, 48), 1);
    let truth = scene.dense();
    let spec = russian_doll(8, 8, 16);
    let f = frames(&spec, &truth, camera.pixels(), 0.0);
    let (t, report, _) = run(&spec, camera, &f, &TransportConfig::default());
    let t_error = relative_error(&dense(&t), &truth);
    assert!(t_error > 0.5, "the zero-filled T is {t_error} off");
    assert!(
        report.details.get("error_estimate").is_none(),
        "{:?}",
        report.details.get("error_estimate")
    );
    assert!(report.details.get("relight_error_estimate").is_none());
}
