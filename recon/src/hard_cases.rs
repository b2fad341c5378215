//! Numerical-stability hard cases, through the public [`reconstruct`] path (what users get).
//!
//! Table-driven over method names: add a method to [`CORRELATION`], [`COMPRESSIVE`] (and
//! [`NONNEGATIVE`] if it keeps `t >= 0`) or [`EXACT`] and every case that applies runs it (a
//! new name falls under its list's bounds). Two cases list their methods with per-method
//! settings and take one more line each: `error_falls_as_rows_grow` (row counts) and
//! `a_512_by_512_hadamard_session_at_4_percent` (iteration caps).
//!
//! Every image goes through [`checked_image_with`]: the run succeeds, the report names the
//! method and the rows, the grid is right, every pixel is finite ([`assert_finite`]) and `>= 0`
//! for [`NONNEGATIVE`] methods. Bounds were measured first (the figures are printed with
//! `--nocapture`) and set with the margins stated next to them.
//!
//! Run: `cargo test -p helmholtz-recon --lib hard_cases` (~10 s of tests on 2 cores, dev profile).

use helmholtz_proto::{Family, HadamardOrdering, PatternGenerator, PatternSpec};
use helmholtz_sim::simulate::{NoiseModel, apply_noise, bucket_signals};
use serde_json::{Value, json};

use super::linop::LinearOperator;
use super::metrics::{fit_affine, pearson, psnr, relative_error};
use super::ops::HadamardOperator;
use super::{Control, MethodConfig, Problem, ReconError, Reconstruction, SliceSource, reconstruct};

/// One-pass correlators (estimate `t` up to a gain and an offset).
const CORRELATION: &[&str] = &["gi", "dgi", "ngi"];
/// Inverse-problem solvers (any family).
const COMPRESSIVE: &[&str] = &["cs", "tv", "lsq", "auto"];
/// Methods that promise `t >= 0`.
const NONNEGATIVE: &[&str] = &["cs", "tv", "auto"];
/// Exact inverses of complete raster / Hadamard sets.
const EXACT: &[&str] = &["direct"];

/// Every method that runs on any pattern family.
fn any_family() -> Vec<&'static str> {
    CORRELATION.iter().chain(COMPRESSIVE).copied().collect()
}

/// Every method (complete raster / Hadamard sets).
fn all_methods() -> Vec<&'static str> {
    CORRELATION
        .iter()
        .chain(EXACT)
        .chain(COMPRESSIVE)
        .copied()
        .collect()
}

fn is_correlation(method: &str) -> bool {
    CORRELATION.contains(&method)
}

// ---------------------------------------------------------------------------------------------
// Specs, scenes, buckets.

fn bernoulli(w: u32, h: u32, count: u64, fill: f64, seed: u64) -> PatternSpec {
    PatternSpec::new(Family::Bernoulli { fill }, w, h, count, seed).unwrap()
}

fn hadamard(w: u32, h: u32, count: u64) -> PatternSpec {
    let ordering = HadamardOrdering::RussianDoll;
    PatternSpec::new(Family::Hadamard { ordering }, w, h, count, 0).unwrap()
}

fn raster(w: u32, h: u32, block: u32, count: u64) -> PatternSpec {
    PatternSpec::new(Family::raster_covering(block, w, h, count), w, h, count, 0).unwrap()
}

/// Two flat rectangles (1.0 and 0.6) on a dim background (0.05), placed at fractions of the grid
/// so any size works: piecewise constant, sparse in wavelets and in TV.
fn blocks(w: usize, h: usize) -> Vec<f32> {
    let mut t = vec![0.05f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (fx, fy) = ((x as f64 + 0.5) / w as f64, (y as f64 + 0.5) / h as f64);
            if (0.12..0.45).contains(&fx) && (0.18..0.62).contains(&fy) {
                t[y * w + x] = 1.0;
            }
            if (0.55..0.88).contains(&fx) && (0.30..0.82).contains(&fy) {
                t[y * w + x] = 0.6;
            }
        }
    }
    t
}

/// Noiseless buckets `t . p_i` for every pattern of `spec`.
fn clean(spec: &PatternSpec, truth: &[f32]) -> Vec<f64> {
    bucket_signals(spec, &[truth], None)
}

// ---------------------------------------------------------------------------------------------
// Running a method and the checks every image gets.

fn solve(
    spec: &PatternSpec,
    buckets: &[f64],
    rows: u64,
    method: &str,
    params: &Value,
) -> Result<Reconstruction, ReconError> {
    let config =
        MethodConfig::parse(method, params).unwrap_or_else(|e| panic!("{method} {params}: {e}"));
    let problem = Problem {
        spec,
        channels: 1,
        rows,
    };
    let n = (rows as usize).min(buckets.len());
    reconstruct(
        &problem,
        &config,
        &mut SliceSource::new(&buckets[..n], 1, 997),
        &Control::new(),
    )
}

/// Panics naming the first non-finite pixel.
fn assert_finite(what: &str, image: &[f32]) {
    if let Some(i) = image.iter().position(|v| !v.is_finite()) {
        panic!("{what}: pixel {i} is {}", image[i]);
    }
}

/// Runs `method` with `params` on the first `rows` buckets and returns the image after the
/// checks every image gets: the run succeeds, the grid is the spec's, every pixel is finite and,
/// for [`NONNEGATIVE`] methods, `>= 0`.
fn checked_image_with(
    case: &str,
    spec: &PatternSpec,
    buckets: &[f64],
    rows: u64,
    method: &str,
    params: &Value,
) -> Vec<f32> {
    let what = format!("{case} / {method}");
    let r = solve(spec, buckets, rows, method, params)
        .unwrap_or_else(|e| panic!("{what}: expected an image, got the error {e:?}"));
    assert_eq!(
        r.report.method, method,
        "{what}: report names another method"
    );
    assert_eq!(r.report.rows_used, rows, "{what}: rows used");
    assert_eq!(r.images.len(), 1, "{what}: one channel in, one image out");
    let image = r.images.into_iter().next().unwrap();
    assert_eq!(
        (image.width, image.height),
        (spec.width(), spec.height()),
        "{what}: grid"
    );
    assert_eq!(image.data.len(), spec.pixels(), "{what}: pixel count");
    assert_finite(&what, &image.data);
    if NONNEGATIVE.contains(&method)
        && let Some(i) = image.data.iter().position(|&v| v < 0.0)
    {
        panic!("{what}: pixel {i} is negative ({})", image.data[i]);
    }
    image.data
}

/// [`checked_image_with`] with the method's default parameters (what a user gets by default).
fn checked_image(
    case: &str,
    spec: &PatternSpec,
    buckets: &[f64],
    rows: u64,
    method: &str,
) -> Vec<f32> {
    checked_image_with(case, spec, buckets, rows, method, &json!({}))
}

fn argmax(image: &[f32]) -> usize {
    (0..image.len()).fold(0, |best, i| if image[i] > image[best] { i } else { best })
}

/// Relative error after the best gain and offset (how correlators are judged).
fn fitted_error(image: &[f32], truth: &[f32]) -> f64 {
    let (a, b) = fit_affine(image, truth);
    let fitted: Vec<f32> = image.iter().map(|&v| (a * v as f64 + b) as f32).collect();
    relative_error(&fitted, truth)
}

/// The error a method is judged by: raw for methods that estimate `t` itself, after the affine
/// fit for correlators.
fn method_error(method: &str, image: &[f32], truth: &[f32]) -> f64 {
    if is_correlation(method) {
        fitted_error(image, truth)
    } else {
        relative_error(image, truth)
    }
}

/// `||A t - c|| / ||c||` over the first `rows` patterns of a binary spec.
fn data_residual(spec: &PatternSpec, rows: u64, image: &[f32], buckets: &[f64]) -> f64 {
    let predicted = bucket_signals(&spec.with_count(rows).unwrap(), &[image], None);
    let c = &buckets[..rows as usize];
    let r: f64 = predicted
        .iter()
        .zip(c)
        .map(|(p, c)| (p - c) * (p - c))
        .sum::<f64>()
        .sqrt();
    r / c.iter().map(|c| c * c).sum::<f64>().sqrt()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (&x, &y)| m.max((x as f64 - y as f64).abs()))
}

// ---------------------------------------------------------------------------------------------
// 1. 1 % sampling.

#[test]
fn one_percent_sampling_gives_a_finite_image_not_an_error() {
    let (w, h) = (64, 64);
    let truth = blocks(w, h);
    let rows = 41; // 1 % of 4096
    let spec = bernoulli(w as u32, h as u32, rows, 0.5, 11);
    let c = clean(&spec, &truth);
    for method in any_family() {
        let image = checked_image("1 % sampling", &spec, &c, rows, method);
        let peak = image.iter().fold(0.0f64, |m, &v| m.max((v as f64).abs()));
        let corr = pearson(&image, &truth);
        eprintln!("1 % sampling / {method}: peak {peak:.3e}, pearson {corr:.3}");
        assert!(peak > 0.0, "{method}: an all-zero image from non-zero data");
        // A sign or index error would anti- or de-correlate. Measured 0.066-0.095 for the
        // correlators (expected ~ sqrt(n / k) = 0.1 at this size), cs 0.26, tv 0.64, lsq 0.06
        // (the minimum-norm image of 41 rows); so only the sign is a stable claim here.
        assert!(corr > 0.0, "{method}: pearson {corr:.3}");
        if !is_correlation(method) {
            // The solvers must explain the 41 measurements (n << k, noise-free). Measured:
            // cs 5.9e-4, tv 1.7e-4, lsq 1.5e-6 (relative residual); bound 17x the worst.
            let fit = data_residual(&spec, rows, &image, &c);
            eprintln!("1 % sampling / {method}: data residual {fit:.2e}");
            assert!(
                fit < 1e-2,
                "{method}: the image does not explain the data ({fit:.2e})"
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 2. n = k and n > k.

#[test]
fn complete_and_overcomplete_bernoulli_recover_the_scene() {
    let (w, h) = (32, 32);
    let k = w * h;
    let truth = blocks(w, h);
    let spec = bernoulli(w as u32, h as u32, 2 * k as u64, 0.5, 3);
    let c = clean(&spec, &truth);
    for rows in [k as u64, 2 * k as u64] {
        let over = rows == 2 * k as u64;
        for &method in COMPRESSIVE {
            let image = checked_image("n >= k", &spec, &c, rows, method);
            let err = relative_error(&image, &truth);
            eprintln!("n = {rows}, k = {k} / {method}: relative error {err:.3e}");
            // Measured (noise-free, default parameters):
            // - lsq, n = 2k: 3.5e-4. The centred 0/1 rows have condition ~6 and CGLS stops at
            //   tol = 1e-4 of the (deflated) normal residual, so ~tol x condition; bound 1e-3.
            //   (Before the fix in solve/cgls.rs: 0.12, "converged" after 7 iterations.)
            // - lsq, n = k: 7.3e-2. A square random 0/1 matrix has condition ~2k; the default
            //   200 CGLS iterations do not resolve its smallest singular directions (2000 reach
            //   1.3e-2). An honest limit of plain least squares at n = k, not a bug; bound 0.15.
            // - tv: 6.1e-3 / 5.8e-3, cs (db4): 4.2e-2 / 2.2e-2: the bias of lambda = 3e-3 / 1e-3
            //   of lambda_max, which does not shrink with n; bounds 1.5x-1.7x.
            let bound = match (method, over) {
                ("lsq", true) => 1e-3,
                ("lsq", false) => 0.15,
                ("tv", _) => 0.01,
                (_, true) => 0.035,
                (_, false) => 0.06,
            };
            assert!(
                err < bound,
                "n = {rows} / {method}: relative error {err:.3e} >= {bound:e}"
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 3. Duplicated patterns.

#[test]
fn duplicated_patterns_stay_finite_and_exact() {
    // Raster 16 x 16, three full scans plus half a fourth: every pattern repeats, unevenly.
    let (w, h) = (16, 16);
    let truth = blocks(w, h);
    let spec = raster(w as u32, h as u32, 1, 3 * 256 + 128);
    let c = clean(&spec, &truth);
    for method in all_methods() {
        let image = checked_image("repeated raster", &spec, &c, spec.count(), method);
        let err = method_error(method, &image, &truth);
        eprintln!("repeated raster / {method}: error {err:.3e}");
        // Measured: direct and lsq 0 (exact); tv 4.5e-3, cs 9.2e-3 (regularisation bias);
        // correlators 0.107 after the affine fit: half the pixels are lit 4 times and half 3,
        // so <p(x)> differs between them and GI's background term is uneven (expected).
        let bound = match method {
            "direct" | "lsq" => 1e-6,
            "tv" => 0.01,
            m if is_correlation(m) => 0.15,
            _ => 0.02,
        };
        assert!(
            err < bound,
            "repeated raster / {method}: error {err:.3e} >= {bound:e}"
        );
    }
    // Bernoulli 2 x 2: 16 possible patterns, so 64 rows repeat each ~4 times and include
    // all-off patterns (R = 0, NGI's 0/0 case).
    let truth = vec![0.2f32, 1.0, 0.5, 0.8];
    let spec = bernoulli(2, 2, 64, 0.5, 9);
    let c = clean(&spec, &truth);
    let generator = PatternGenerator::new(&spec);
    let mut p = vec![0f32; 4];
    let dark_patterns = (0..64)
        .filter(|&i| {
            generator.fill_values(i, &mut p);
            p.iter().all(|&v| v == 0.0)
        })
        .count();
    assert!(dark_patterns > 0, "the case needs all-off patterns");
    for method in any_family() {
        let image = checked_image("bernoulli 2x2", &spec, &c, spec.count(), method);
        let err = method_error(method, &image, &truth);
        eprintln!("bernoulli 2x2 ({dark_patterns} all-off) / {method}: error {err:.3e} {image:?}");
        // Measured: lsq 0, cs 1.1e-3, tv 1.8e-3; correlators 0.05-0.12 after the fit (64 rows).
        let bound = match method {
            "lsq" => 1e-6,
            m if is_correlation(m) => 0.2,
            _ => 5e-3,
        };
        assert!(
            err < bound,
            "bernoulli 2x2 / {method}: error {err:.3e} >= {bound:e}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// 4. All-dark scene.

#[test]
fn an_all_dark_scene_is_exactly_zero_for_every_method() {
    let specs = [
        bernoulli(16, 16, 200, 0.5, 1),
        raster(16, 16, 1, 256),
        hadamard(16, 16, 512),
        PatternSpec::new(Family::Speckle { grain: 2 }, 16, 16, 200, 4).unwrap(),
    ];
    for spec in &specs {
        let zeros = vec![0.0; spec.count() as usize];
        let complete = matches!(
            spec.family(),
            Family::Raster { .. } | Family::Hadamard { .. }
        );
        let methods = if complete {
            all_methods()
        } else {
            any_family()
        };
        for method in methods {
            let case = format!("all dark {}", spec.family().name());
            let image = checked_image(&case, spec, &zeros, spec.count(), method);
            assert!(
                image.iter().all(|&v| v == 0.0),
                "{case} / {method}: {image:?}"
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 5. A single bright pixel on black.

/// A `w x h` scene of `bg` with one pixel of `value` at `(x, y)`.
fn point(w: usize, h: usize, x: usize, y: usize, value: f32, bg: f32) -> Vec<f32> {
    let mut t = vec![bg; w * h];
    t[y * w + x] = value;
    t
}

#[test]
fn a_single_bright_pixel_is_located() {
    let (w, h) = (32, 32);
    let (x, y) = (21, 9);
    let at = y * w + x;
    let truth = point(w, h, x, y, 1.0, 0.0);
    let cases = [
        (bernoulli(32, 32, 512, 0.5, 21), any_family()),
        (hadamard(32, 32, 2048), all_methods()),
        (raster(32, 32, 1, 1024), all_methods()),
    ];
    for (spec, methods) in &cases {
        let complete = !matches!(spec.family(), Family::Bernoulli { .. });
        let c = clean(spec, &truth);
        for &method in methods {
            let case = format!("bright pixel {}", spec.family().name());
            let image = checked_image(&case, spec, &c, spec.count(), method);
            let err = method_error(method, &image, &truth);
            eprintln!(
                "{case} / {method}: argmax {}, value {:.4}, error {err:.3e}",
                argmax(&image),
                image[at]
            );
            assert_eq!(
                argmax(&image),
                at,
                "{case} / {method}: the brightest pixel is elsewhere"
            );
            // Measured: on the complete sets direct and lsq are exact, cs 4.1e-3, tv 3.6e-3;
            // at 50 % Bernoulli cs 3.7e-3, tv 3.4e-3 (sparsity and t >= 0 pin the point), lsq
            // 0.70 (the minimum-norm image spreads it), correlators ~0.81 (noise at 512 rows).
            if !is_correlation(method) && (complete || NONNEGATIVE.contains(&method)) {
                assert!(err < 0.01, "{case} / {method}: error {err:.3e}");
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 6. A 1e4 dynamic range.

#[test]
fn a_specular_highlight_1e4_times_the_background() {
    let (w, h) = (32, 32);
    let (x, y) = (7, 25);
    let at = y * w + x;
    let truth = point(w, h, x, y, 1e4, 1.0);
    let cases = [
        (bernoulli(32, 32, 2048, 0.5, 23), any_family()),
        (hadamard(32, 32, 2048), all_methods()),
    ];
    for (spec, methods) in &cases {
        let c = clean(spec, &truth);
        for &method in methods {
            let case = format!("1e4 highlight {}", spec.family().name());
            let image = checked_image(&case, spec, &c, spec.count(), method);
            let mut bg: Vec<f32> = image
                .iter()
                .enumerate()
                .filter(|&(i, _)| i != at)
                .map(|(_, &v)| v)
                .collect();
            bg.sort_by(f32::total_cmp);
            let (lo, median) = (bg[0], bg[bg.len() / 2]);
            eprintln!(
                "{case} / {method}: argmax {}, highlight {:.2}, background min {lo:.4} median {median:.4}",
                argmax(&image),
                image[at]
            );
            assert_eq!(
                argmax(&image),
                at,
                "{case} / {method}: the highlight is elsewhere"
            );
            if is_correlation(method) {
                // Correlators estimate t up to gain and offset, and the highlight's own
                // fluctuations swamp a background 1e4 times fainter (GI on Bernoulli: background
                // from -200 to +200); finite and located is the claim.
                continue;
            }
            // Measured: highlight within 0.4 % (cs 9975, tv 9963, lsq/direct 10000); background
            // median 0.90-1.11 (cs, the l1 bias; tv 1.06; lsq/direct 1.00), minimum >= 0 (lsq
            // 0.61, cs exact zeros). Bounds: 1 %, 15 %, no negative pixel.
            let peak_err = (image[at] as f64 - 1e4).abs() / 1e4;
            assert!(
                peak_err < 0.01,
                "{case} / {method}: highlight {}",
                image[at]
            );
            assert!(
                (median as f64 - 1.0).abs() < 0.15,
                "{case} / {method}: background median {median}"
            );
            assert!(lo >= 0.0, "{case} / {method}: negative background {lo}");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 7. 10 photons per pattern.

#[test]
fn ten_photons_per_pattern() {
    let noise = NoiseModel {
        photons: Some(10.0),
        seed: 17,
        ..NoiseModel::default()
    };
    // Measured pearson with the truth: Bernoulli 16 x 16, 4096 rows: 0.71-0.77 (every method);
    // Hadamard 16 x 16 complete: 0.32-0.36 (a split pair's difference is a few photons).
    for (spec, methods, bound) in [
        (bernoulli(16, 16, 4096, 0.5, 31), any_family(), 0.6),
        (hadamard(16, 16, 512), all_methods(), 0.25),
    ] {
        let (w, h) = (spec.width() as usize, spec.height() as usize);
        let truth = blocks(w, h);
        let (c, report) = apply_noise(&clean(&spec, &truth), 1, &noise);
        // The data really are ~10 counted photons per pattern.
        let alpha = report.channels[0].photons_per_unit.unwrap();
        let counts: Vec<f64> = c.iter().map(|&v| v * alpha).collect();
        assert!(
            counts
                .iter()
                .all(|&n| (n - n.round()).abs() < 1e-6 && n >= 0.0)
        );
        let mean = counts.iter().sum::<f64>() / counts.len() as f64;
        assert!((mean - 10.0).abs() < 0.5, "{mean} photons per pattern");
        let snr = report.channels[0].effective_snr_db;
        for &method in &methods {
            let case = format!("10 photons {} {w}x{h} ({snr:.1} dB)", spec.family().name());
            let image = checked_image(&case, &spec, &c, spec.count(), method);
            let corr = pearson(&image, &truth);
            eprintln!("{case} / {method}: pearson {corr:.3}");
            assert!(
                corr > bound,
                "{case} / {method}: pearson {corr:.3} <= {bound}"
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 8. Dark offset and source drift.

#[test]
fn hadamard_split_pairs_cancel_the_dark_level_under_drift() {
    let (w, h) = (32, 32);
    let truth = blocks(w, h);
    let spec = hadamard(32, 32, 2048);
    let c0 = clean(&spec, &truth);
    let dark = 2.0 * c0.iter().sum::<f64>() / c0.len() as f64; // twice the mean signal
    let with = |drift: f64| {
        let noise = NoiseModel {
            drift,
            dark,
            seed: 3,
            ..NoiseModel::default()
        };
        apply_noise(&c0, 1, &noise).0
    };
    let (dark_only, dark_drift) = (with(0.0), with(0.02));
    for method in all_methods() {
        let reference = checked_image("hadamard clean", &spec, &c0, spec.count(), method);
        let shifted = checked_image("hadamard dark", &spec, &dark_only, spec.count(), method);
        let drifted = checked_image(
            "hadamard dark + 2 % drift",
            &spec,
            &dark_drift,
            spec.count(),
            method,
        );
        let (e0, e_dark, e_drift) = (
            method_error(method, &reference, &truth),
            method_error(method, &shifted, &truth),
            method_error(method, &drifted, &truth),
        );
        eprintln!(
            "hadamard / {method}: error clean {e0:.3e}, dark {e_dark:.3e}, dark + drift {e_drift:.3e}"
        );
        // The dark level cancels in y+ - y-: measured bit-identical images for direct and the
        // solvers; the correlators' gain and offset change, their fitted error does not.
        if is_correlation(method) {
            assert!(
                (e_dark - e0).abs() < 1e-6,
                "{method}: dark changed the fitted error"
            );
        } else {
            let d = relative_error(&shifted, &reference);
            assert!(
                d < 1e-9,
                "{method}: a dark level changed the image by {d:e}"
            );
        }
        // 2 % drift: measured 2.6e-2 (direct, lsq, correlators), cs 2.4e-2, tv 1.1e-2.
        assert!(
            e_drift < 0.05,
            "{method}: error {e_drift:.3e} under 2 % drift"
        );
    }
    // The direct report measures the dark level (P- of the all-ones row) and monitors drift.
    let details = |c: &[f64]| {
        solve(&spec, c, spec.count(), "direct", &json!({}))
            .unwrap()
            .report
            .details
    };
    let number = |d: &serde_json::Map<String, Value>, key: &str| d[key][0].as_f64().unwrap();
    let (stable, drifting) = (details(&dark_only), details(&dark_drift));
    eprintln!("direct details: stable {stable:?}, drifting {drifting:?}");
    assert!((number(&stable, "dark_level") - dark).abs() < 1e-9 * dark);
    assert!((number(&drifting, "dark_level") - dark).abs() < 1e-9 * dark);
    // Pair sums g_r (1 . t) + 2 dark: exactly constant without drift; measured rel. std 8.1e-3
    // with 2 % drift (diluted by the dark level: 0.02 / 3 expected).
    assert!(number(&stable, "pair_sum_rel_std") < 1e-12);
    assert!(number(&drifting, "pair_sum_rel_std") > 4e-3);
}

#[test]
fn dgi_and_ngi_are_robust_to_drift_with_a_dark_offset() {
    let (w, h) = (32, 32);
    let truth = blocks(w, h);
    let spec = bernoulli(32, 32, 4096, 0.5, 41);
    let c0 = clean(&spec, &truth);
    let mean = c0.iter().sum::<f64>() / c0.len() as f64;
    // A dark offset of 20 % of the mean signal and a 2 % drift.
    let noise = NoiseModel {
        drift: 0.02,
        dark: 0.2 * mean,
        seed: 3,
        ..NoiseModel::default()
    };
    let c = apply_noise(&c0, 1, &noise).0;
    let error = |c: &[f64], method: &str| {
        fitted_error(
            &checked_image("drift", &spec, c, spec.count(), method),
            &truth,
        )
    };
    let gi = error(&c, "gi");
    for method in ["dgi", "ngi"] {
        let (e0, e) = (error(&c0, method), error(&c, method));
        eprintln!(
            "bernoulli dark + drift / {method}: fitted error clean {e0:.3e}, dark + drift {e:.3e} (gi {gi:.3e})"
        );
        // Measured: clean 0.355, dark + drift 0.391 (x1.10), gi 0.452 on the same data.
        assert!(e < 1.2 * e0, "{method}: {e:.3e} vs clean {e0:.3e}");
        assert!(e < 0.95 * gi, "{method}: {e:.3e} vs gi {gi:.3e}");
    }
    // Not asserted, measured: with a dark offset of twice the mean signal DGI and NGI degrade
    // (0.355 -> 0.530) while GI is exactly invariant to offsets: both formulas assume c ~ R,
    // so the dark level should be subtracted first. Not a numerical defect.
}

// ---------------------------------------------------------------------------------------------
// 9. Clipped (saturated) buckets.

/// Clips `c` at `lo + fraction (hi - lo)` (an ADC saturating on the brightest patterns).
fn saturate(c: &[f64], fraction: f64) -> (Vec<f64>, usize) {
    let (lo, hi) = c
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let level = lo + fraction * (hi - lo);
    (
        c.iter().map(|&v| v.min(level)).collect(),
        c.iter().filter(|&&v| v > level).count(),
    )
}

#[test]
fn clipped_buckets() {
    let (w, h) = (32, 32);
    let truth = blocks(w, h);
    for (spec, methods) in [
        (bernoulli(32, 32, 2048, 0.5, 51), any_family()),
        (hadamard(32, 32, 2048), all_methods()),
        (raster(32, 32, 1, 1024), all_methods()),
    ] {
        let (c, clipped) = saturate(&clean(&spec, &truth), 0.75);
        assert!(clipped > 0);
        for &method in &methods {
            let case = format!(
                "clipped {} ({clipped} of {} saturated)",
                spec.family().name(),
                c.len()
            );
            let image = checked_image(&case, &spec, &c, spec.count(), method);
            let corr = pearson(&image, &truth);
            eprintln!(
                "{case} / {method}: pearson {corr:.3}, error {:.3}",
                method_error(method, &image, &truth)
            );
            // Measured: correlators 0.745-0.987, the others 0.982-1.000 (Hadamard: only the
            // all-ones P+ frame and one more saturate: a wrong mean, a right shape).
            let bound = if is_correlation(method) { 0.65 } else { 0.9 };
            assert!(
                corr > bound,
                "{case} / {method}: pearson {corr:.3} <= {bound}"
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 10. A constant scene.

#[test]
fn a_constant_scene_is_recovered_as_constant() {
    let level = 0.7f32;
    let truth = vec![level; 32 * 32];
    // Rows: "enough" for least squares (2k Bernoulli rows, a complete raster) and a quarter of
    // the Hadamard rows (its first row is the constant).
    for (spec, methods, rows) in [
        (bernoulli(32, 32, 2048, 0.5, 61), any_family(), 2048),
        (hadamard(32, 32, 2048), any_family(), 512),
        (hadamard(32, 32, 2048), all_methods(), 2048),
        (raster(32, 32, 1, 1024), all_methods(), 1024),
    ] {
        let c = clean(&spec, &truth);
        for &method in &methods {
            let case = format!("constant {} rows {rows}", spec.family().name());
            let image = checked_image(&case, &spec, &c, rows, method);
            let dev = max_abs_diff(&image, &truth) / level as f64;
            let peak = image.iter().fold(0.0f64, |m, &v| m.max((v as f64).abs()));
            eprintln!("{case} / {method}: max relative deviation {dev:.2e}, peak {peak:.3e}");
            match method {
                // G_D and G_N subtract the mean image by construction: c_i = level R_i gives
                // exactly 0 (measured 0.0 everywhere); GI is noise around a constant.
                "dgi" | "ngi" => assert!(peak < 1e-6, "{case} / {method}: {peak:e}"),
                "gi" => {}
                // Measured: tv 0 (its cold start is the best constant), lsq 1.2e-3 (Bernoulli
                // n = 2k) / 0, direct 0, cs 1.0e-3 (the l1 bias on the one DC coefficient).
                _ => assert!(dev < 5e-3, "{case} / {method}: max deviation {dev:.2e}"),
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 11. Bernoulli fill 0.95.

#[test]
fn nearly_white_patterns_fill_095() {
    let truth = blocks(32, 32);
    let spec = bernoulli(32, 32, 1024, 0.95, 71);
    let c = clean(&spec, &truth);
    for method in any_family() {
        let image = checked_image("fill 0.95", &spec, &c, spec.count(), method);
        let corr = pearson(&image, &truth);
        eprintln!(
            "fill 0.95 / {method}: pearson {corr:.3}, error {:.3e}",
            method_error(method, &image, &truth)
        );
        // Measured: gi 0.61, dgi/ngi 0.69 (E[G] ~ q(1-q) = 0.0475: weak signal), cs 0.999,
        // tv 1.000, lsq 0.995 (n = k).
        let bound = if is_correlation(method) { 0.5 } else { 0.95 };
        assert!(
            corr > bound,
            "fill 0.95 / {method}: pearson {corr:.3} <= {bound}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// 12. Non-square and non-power-of-two grids.

/// `truth` averaged over `b x b` blocks (edge blocks smaller), spread back over the blocks.
fn block_means(truth: &[f32], w: usize, h: usize, b: usize) -> Vec<f32> {
    let mut out = vec![0f32; w * h];
    for by in (0..h).step_by(b) {
        for bx in (0..w).step_by(b) {
            let cells: Vec<usize> = (by..(by + b).min(h))
                .flat_map(|y| (bx..(bx + b).min(w)).map(move |x| y * w + x))
                .collect();
            let mean = cells.iter().map(|&i| truth[i] as f64).sum::<f64>() / cells.len() as f64;
            cells.iter().for_each(|&i| out[i] = mean as f32);
        }
    }
    out
}

#[test]
fn non_square_and_non_power_of_two_grids() {
    let speckle = PatternSpec::new(Family::Speckle { grain: 1 }, 48, 20, 960, 5).unwrap();
    for (spec, methods, rows) in [
        (bernoulli(48, 20, 960, 0.5, 81), any_family(), 480),
        (speckle, any_family(), 960),
        (raster(24, 40, 1, 960), all_methods(), 960),
        (raster(24, 40, 3, 8 * 14), all_methods(), 8 * 14),
        (hadamard(64, 16, 2048), all_methods(), 2048),
        (hadamard(64, 16, 2048), any_family(), 512),
    ] {
        let (w, h) = (spec.width() as usize, spec.height() as usize);
        let truth = blocks(w, h);
        let c = clean(&spec, &truth);
        let complete = rows == 2 * (w * h) as u64
            || matches!(spec.family(), Family::Raster { block: 1, .. }) && rows == (w * h) as u64;
        for &method in &methods {
            let case = format!("{} {w}x{h} rows {rows}", spec.family().name());
            let image = checked_image(&case, &spec, &c, rows, method);
            let corr = pearson(&image, &truth);
            let err = method_error(method, &image, &truth);
            eprintln!("{case} / {method}: pearson {corr:.3}, error {err:.3e}");
            // Measured minimum over everything: 0.463 (gi, 48 x 20 Bernoulli at 50 %).
            assert!(corr > 0.4, "{case} / {method}: pearson {corr:.3}");
            if complete && !NONNEGATIVE.contains(&method) {
                // Complete sets: direct, lsq and the fitted correlators are exact (measured 0).
                assert!(err < 1e-6, "{case} / {method}: error {err:.3e}");
            }
        }
        if let Family::Raster { block, .. } = *spec.family() {
            // direct on 3 x 3 blocks (8 x 14 blocks, the last row 1 pixel high): block means.
            let image = checked_image("raster blocks", &spec, &c, rows, "direct");
            let want = block_means(&truth, w, h, block as usize);
            let d = max_abs_diff(&image, &want);
            assert!(
                d < 1e-6,
                "raster block {block}: direct differs from the block means by {d:e}"
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 13. 512 x 512.

/// Split-pair frames of the first `pairs` rows of a Hadamard spec for `truth`, through the fast
/// transform (simulating pattern by pattern would cost k n = 5e9 operations here):
/// `y+- = (1 . t +- h . t) / 2`, `h . t = sqrt(k) (A t)_r` for the orthonormal operator `A`.
fn hadamard_frames(spec: &PatternSpec, truth: &[f32], pairs: usize) -> Vec<f64> {
    let Family::Hadamard { ordering } = *spec.family() else {
        panic!("a hadamard spec")
    };
    let op = HadamardOperator::new(spec.width(), spec.height(), ordering, pairs);
    let t: Vec<f64> = truth.iter().map(|&v| v as f64).collect();
    let mut d = vec![0.0; pairs];
    op.apply(&t, &mut d);
    let (sum, root_k) = (t.iter().sum::<f64>(), (spec.pixels() as f64).sqrt());
    d.iter()
        .flat_map(|&d| [(sum + root_k * d) / 2.0, (sum - root_k * d) / 2.0])
        .collect()
}

#[test]
fn a_512_by_512_hadamard_session_at_4_percent() {
    let (w, h) = (512usize, 512usize);
    let truth = blocks(w, h);
    let pairs = w * h / 25;
    let spec = hadamard(w as u32, h as u32, 2 * pairs as u64);
    let c = hadamard_frames(&spec, &truth, pairs);
    // The fast simulation agrees with the generator's patterns (first and last frames).
    let generator = PatternGenerator::new(&spec);
    let mut p = vec![0f32; w * h];
    for f in [0, 1, 2, 3, 2 * pairs - 2, 2 * pairs - 1] {
        generator.fill_values(f as u64, &mut p);
        let want: f64 = p
            .iter()
            .zip(&truth)
            .map(|(&a, &b)| a as f64 * b as f64)
            .sum();
        assert!(
            (want - c[f]).abs() <= 1e-9 * want.abs().max(1.0),
            "frame {f}: {want} vs {}",
            c[f]
        );
    }
    // Measured (dev profile, 2 shared cores): tv 30 iterations 27.0 dB in ~4 s; cs 30
    // iterations 27.2 dB in ~1.3 s; lsq 25.5 dB in 0.05 s (A A^T = I: one step). A constant
    // image scores ~8 dB here; bound 24 dB.
    for (method, params) in [
        ("tv", json!({"max_iter": 30})),
        ("cs", json!({"max_iter": 30})),
        ("lsq", json!({})),
    ] {
        let start = std::time::Instant::now();
        let image = checked_image_with("512x512", &spec, &c, spec.count(), method, &params);
        let db = psnr(&image, &truth);
        eprintln!(
            "512x512, 4 % / {method}: {db:.2} dB in {:.2} s",
            start.elapsed().as_secs_f64()
        );
        assert!(db > 24.0, "512x512 / {method}: {db:.2} dB");
    }
}

// ---------------------------------------------------------------------------------------------
// Error falls as rows grow.

#[test]
fn error_falls_as_rows_grow() {
    let truth = blocks(32, 32);
    let spec = bernoulli(32, 32, 8192, 0.5, 91);
    let c = clean(&spec, &truth);
    // Measured errors (raw; dgi after the affine fit):
    //   cs  256/512/1024: 0.392, 0.142, 0.042   tv 256/512/1024: 7.8e-3, 6.7e-3, 5.4e-3
    //   lsq 256/512/1024: 0.697, 0.565, 0.056   dgi 512/2048/8192: 0.649, 0.454, 0.263
    // The smallest step is tv's x0.86; each step must cut the error by at least 5 %.
    let table: [(&str, [u64; 3]); 4] = [
        ("cs", [256, 512, 1024]),
        ("tv", [256, 512, 1024]),
        ("lsq", [256, 512, 1024]),
        ("dgi", [512, 2048, 8192]),
    ];
    for (method, rows) in table {
        let errors: Vec<f64> = rows
            .iter()
            .map(|&n| {
                method_error(
                    method,
                    &checked_image("rows grow", &spec, &c, n, method),
                    &truth,
                )
            })
            .collect();
        eprintln!("rows grow / {method}: {rows:?} -> {errors:.3?}");
        for i in 1..3 {
            assert!(
                errors[i] < 0.95 * errors[i - 1],
                "{method}: error {:.3e} at {} rows, {:.3e} at {}",
                errors[i - 1],
                rows[i - 1],
                errors[i],
                rows[i]
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 15. The hard cases under noise: 1 % sampling, a nearly dark scene, a 1e4 highlight.

/// Read noise at `snr_db` of the buckets' rms, and its standard deviation.
fn read_noise(c: &[f64], snr_db: f64, seed: u64) -> (Vec<f64>, f64) {
    let rms = (c.iter().map(|v| v * v).sum::<f64>() / c.len() as f64).sqrt();
    let noise = NoiseModel {
        snr_db: Some(snr_db),
        seed,
        ..NoiseModel::default()
    };
    (apply_noise(c, 1, &noise).0, rms / 10f64.powf(snr_db / 20.0))
}

/// `auto`'s noise estimate against the noise put in (`sigma` in the data's units).
fn check_noise_estimate(case: &str, spec: &PatternSpec, c: &[f64], sigma: f64) {
    let r = solve(spec, c, spec.count(), "auto", &json!({})).unwrap();
    let est = &r.report.details["noise_estimate"][0];
    let (got, se) = (
        est["sigma"].as_f64().unwrap(),
        est["standard_error"].as_f64().unwrap(),
    );
    eprintln!("{case}: noise estimate {got:.4e} +- {se:.1e}, put in {sigma:.4e}");
    assert!(
        (got - sigma).abs() < 4.0 * se + 0.1 * sigma,
        "{case}: noise estimate {got:.4e} +- {se:.1e}, put in {sigma:.4e}"
    );
    assert_eq!(r.report.details["auto"][0]["noise_estimate"], *est);
}

#[test]
fn the_hard_cases_under_noise() {
    // 1 % sampling at 30 dB: finite, non-negative, positively correlated (Bernoulli rows, and
    // Russian-doll pairs, where `auto` checks its weight by Stein's risk).
    let truth = blocks(64, 64);
    for spec in [bernoulli(64, 64, 41, 0.5, 11), hadamard(64, 64, 82)] {
        let (c, _) = read_noise(&clean(&spec, &truth), 30.0, 3);
        let case = format!("1 % sampling, 30 dB {}", spec.family().name());
        for method in any_family() {
            let image = checked_image(&case, &spec, &c, spec.count(), method);
            let corr = pearson(&image, &truth);
            eprintln!("{case} / {method}: pearson {corr:.3}");
            assert!(corr > 0.0, "{case} / {method}: pearson {corr:.3}");
        }
    }

    // A nearly dark scene: one block at 1e-3 of full scale on black, 10 dB read noise (the
    // noise is a third of the buckets' rms). Finite, non-negative, and no method invents
    // light: the image's total stays within a few times the truth's.
    let mut dim = vec![0.0f32; 32 * 32];
    for y in 10..18 {
        for x in 12..22 {
            dim[y * 32 + x] = 1e-3;
        }
    }
    let total: f64 = dim.iter().map(|&v| v as f64).sum();
    for spec in [bernoulli(32, 32, 600, 0.5, 5), hadamard(32, 32, 600)] {
        let (c, sigma) = read_noise(&clean(&spec, &dim), 10.0, 4);
        let case = format!("nearly dark, 10 dB {}", spec.family().name());
        for method in any_family() {
            let image = checked_image(&case, &spec, &c, 600, method);
            if is_correlation(method) {
                continue;
            }
            let sum: f64 = image.iter().map(|&v| v as f64).sum();
            eprintln!("{case} / {method}: total {sum:.4e} (truth {total:.4e})");
            assert!(
                (sum - total).abs() < 0.5 * total,
                "{case} / {method}: total light {sum:.4e}, truth {total:.4e}"
            );
        }
        // Hadamard data are pair differences over sqrt(k): sigma sqrt(2) / sqrt(k).
        let sigma = match spec.family() {
            Family::Hadamard { .. } => sigma * 2f64.sqrt() / 32.0,
            _ => sigma,
        };
        check_noise_estimate(&case, &spec, &c, sigma);
    }

    // A highlight 1e4 times the background at 30 dB: located by every method.
    let at = 25 * 32 + 7;
    let truth = point(32, 32, 7, 25, 1e4, 1.0);
    for (spec, methods) in [
        (bernoulli(32, 32, 2048, 0.5, 23), any_family()),
        (hadamard(32, 32, 2048), all_methods()),
    ] {
        let (c, sigma) = read_noise(&clean(&spec, &truth), 30.0, 6);
        let case = format!("1e4 highlight, 30 dB {}", spec.family().name());
        for &method in &methods {
            let image = checked_image(&case, &spec, &c, spec.count(), method);
            assert_eq!(
                argmax(&image),
                at,
                "{case} / {method}: the highlight is elsewhere"
            );
        }
        // Hadamard data are pair differences over sqrt(k): sigma sqrt(2) / sqrt(k).
        let sigma = match spec.family() {
            Family::Hadamard { .. } => sigma * 2f64.sqrt() / 32.0,
            _ => sigma,
        };
        check_noise_estimate(&case, &spec, &c, sigma);
    }
}

/// Found 2026-12-03: on the nearly dark scene of [`the_hard_cases_under_noise`] from 600
/// Russian-doll frames (300 pairs, 32x32) at 10 dB, `cs` and `tv` at their default weights
/// (1e-3 of `lambda_max`) gave 2.4 times the scene's light (0.191 against 0.080; `lsq` 0.071,
/// `auto` 0.093): the fit to the noisy coefficients needs negative pixels, the non-negativity
/// clips them, and the total rose to pay for it. The all-on pair measures the total, and
/// `cs` and `tv` now hold it ([`crate::solve::SolveOptions::total`]): the image's light is
/// that datum's, to rounding.
#[test]
fn default_cs_and_tv_keep_the_light_of_a_nearly_dark_scene_from_noisy_hadamard_pairs() {
    let mut dim = vec![0.0f32; 32 * 32];
    for y in 10..18 {
        for x in 12..22 {
            dim[y * 32 + x] = 1e-3;
        }
    }
    let total: f64 = dim.iter().map(|&v| v as f64).sum();
    let spec = hadamard(32, 32, 600);
    let (c, _) = read_noise(&clean(&spec, &dim), 10.0, 4);
    // The all-on pair's difference over sqrt(k), times sqrt(k): what the pairs say the light is.
    let measured = c[0] - c[1];
    for method in ["cs", "tv"] {
        let image = checked_image("nearly dark, 10 dB hadamard", &spec, &c, 600, method);
        let sum: f64 = image.iter().map(|&v| v as f64).sum();
        eprintln!("{method}: total {sum:.4e}, measured {measured:.4e}, truth {total:.4e}");
        assert!(
            (sum - total).abs() < 0.5 * total,
            "{method}: total light {sum:.4e}, truth {total:.4e}"
        );
        assert!(
            (sum - measured).abs() < 1e-5 * measured.abs(),
            "{method}: total light {sum:.6e}, the all-on pair measures {measured:.6e}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Unsolvable requests.

#[test]
fn unsolvable_requests_say_why() {
    let b = bernoulli(16, 16, 100, 0.5, 1);
    let s = PatternSpec::new(Family::Speckle { grain: 1 }, 16, 16, 100, 1).unwrap();
    let r = raster(16, 16, 1, 300);
    let hd = hadamard(16, 16, 512);
    let values = vec![0.25; 600];
    let cases: Vec<(&PatternSpec, u64, usize, Vec<&str>, &str)> = vec![
        // (spec, rows requested, rows the source holds, methods, the message names ...)
        (&b, 0, 0, all_methods(), "no committed rows"),
        (&r, 0, 0, all_methods(), "no committed rows"),
        (
            &b,
            101,
            100,
            all_methods(),
            "101 rows requested but the spec declares 100",
        ),
        (
            &b,
            100,
            100,
            EXACT.to_vec(),
            "this session's patterns are bernoulli",
        ),
        (
            &s,
            100,
            100,
            EXACT.to_vec(),
            "this session's patterns are speckle",
        ),
        (
            &r,
            255,
            255,
            EXACT.to_vec(),
            "direct needs a complete raster scan: 256 rows, have 255",
        ),
        (
            &hd,
            510,
            510,
            EXACT.to_vec(),
            "direct needs the complete Hadamard set: 512 frames",
        ),
        // One frame of a split pair: no difference to solve on.
        (
            &hd,
            1,
            1,
            EXACT.to_vec(),
            "direct needs the complete Hadamard set",
        ),
        (&hd, 1, 1, COMPRESSIVE.to_vec(), "at least one P+/P- pair"),
        // The source ends early.
        (
            &b,
            100,
            60,
            any_family(),
            "the source ended after 60 of 100 rows",
        ),
        (
            &r,
            300,
            10,
            all_methods(),
            "the source ended after 10 of 300 rows",
        ),
    ];
    for (spec, rows, held, methods, expected) in cases {
        for method in methods {
            let what = format!(
                "{} rows {rows} (source {held}) / {method}",
                spec.family().name()
            );
            match solve(spec, &values[..held], rows, method, &json!({})) {
                Err(ReconError::Unsolvable(message)) => {
                    eprintln!("{what}: {message}");
                    assert!(
                        message.contains(expected),
                        "{what}: {message:?} does not say {expected:?}"
                    );
                }
                other => panic!("{what}: expected Unsolvable({expected:?}), got {other:?}"),
            }
        }
    }
    // The correlators take a single frame: a one-row covariance is exactly 0, so the image is
    // the zero image (finite), not an error.
    for &method in CORRELATION {
        let image = checked_image("one hadamard frame", &hd, &values, 1, method);
        assert!(image.iter().all(|&v| v == 0.0), "{method}: {image:?}");
    }
}
