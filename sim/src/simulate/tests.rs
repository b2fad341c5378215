use super::*;
use helmholtz_proto::patterns::{Family, HadamardOrdering};

fn spec(family: Family, w: u32, h: u32, count: u64) -> PatternSpec {
    PatternSpec::new(family, w, h, count, 11).unwrap()
}

fn ramp_transport(k: usize, scale: f32) -> Vec<f32> {
    (0..k)
        .map(|p| scale * ((p * 7919) % 97) as f32 / 96.0)
        .collect()
}

/// The fast path equals the plain dot product with `fill_values`, for every family.
#[test]
fn bucket_signals_match_dot_products() {
    let families = [
        Family::Bernoulli { fill: 0.3 },
        Family::Hadamard {
            ordering: HadamardOrdering::Sequency,
        },
        Family::Raster { block: 3, scans: 4 },
        Family::Speckle { grain: 2 },
    ];
    for family in families {
        let s = spec(family.clone(), 16, 8, 64);
        let k = s.pixels();
        let t0 = ramp_transport(k, 1.0);
        let t1 = ramp_transport(k, 0.5).into_iter().rev().collect::<Vec<_>>();
        let c = bucket_signals(&s, &[&t0, &t1], None);
        let generator = PatternGenerator::new(&s);
        let mut p = vec![0.0f32; k];
        for i in 0..64 {
            generator.fill_values(i, &mut p);
            for (j, t) in [&t0, &t1].iter().enumerate() {
                let dot: f64 = p
                    .iter()
                    .zip(t.iter())
                    .map(|(&a, &b)| a as f64 * b as f64)
                    .sum();
                let got = c[i as usize * 2 + j];
                assert!(
                    (got - dot).abs() < 1e-9 * dot.abs().max(1.0),
                    "{family:?} {i} {j}"
                );
            }
        }
    }
}

/// Split Hadamard: y+ + y- = sum(t) on every row (imaging.md §3).
#[test]
fn hadamard_pairs_sum_to_total_transport() {
    let s = spec(
        Family::Hadamard {
            ordering: HadamardOrdering::Natural,
        },
        8,
        8,
        128,
    );
    let t = ramp_transport(64, 1.0);
    let total: f64 = t.iter().map(|&v| v as f64).sum();
    let c = bucket_signals(&s, &[&t], None);
    for pair in c.chunks(2) {
        assert!((pair[0] + pair[1] - total).abs() < 1e-9);
    }
    // Row 0 is all ones: P- is a dark frame.
    assert_eq!(c[1], 0.0);
}

#[test]
fn progress_counts_every_pattern() {
    let s = spec(Family::Bernoulli { fill: 0.5 }, 8, 8, 3000);
    let pb = ProgressBar::hidden();
    pb.set_length(3000);
    let t = vec![1.0f32; 64];
    bucket_signals(&s, &[&t], Some(&pb));
    assert_eq!(pb.position(), 3000);
}

fn constant(rows: usize, value: f64) -> Vec<f64> {
    vec![value; rows]
}

fn moments(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    (
        mean,
        v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0),
    )
}

/// Shot noise: for a constant signal c with N photons per pattern, v = Poisson(N)/alpha with
/// alpha = N/c, so E[v] = c and Var[v] = c²/N. Checked within 5 standard errors.
#[test]
fn shot_noise_statistics() {
    let rows = 100_000;
    for photons in [4.0, 150.0, 1.0e5] {
        let c = 5.0;
        let model = NoiseModel {
            photons: Some(photons),
            seed: 3,
            ..Default::default()
        };
        let (v, report) = apply_noise(&constant(rows, c), 1, &model);
        let (mean, var) = moments(&v);
        let expect_var = c * c / photons;
        let n = rows as f64;
        assert!(
            (mean - c).abs() < 5.0 * (expect_var / n).sqrt(),
            "N={photons}: mean {mean}"
        );
        // se(var) for Poisson scaled by 1/alpha²: sqrt((2λ² + λ)/n) / alpha².
        let alpha = photons / c;
        let se_var = ((2.0 * photons * photons + photons) / n).sqrt() / (alpha * alpha);
        assert!(
            (var - expect_var).abs() < 5.0 * se_var,
            "N={photons}: var {var} vs {expect_var}"
        );
        assert_eq!(report.channels[0].photons_per_unit, Some(alpha));
        // Effective SNR of pure shot noise at constant signal: 10 log10(N).
        assert!((report.channels[0].effective_snr_db - 10.0 * photons.log10()).abs() < 0.1);
    }
}

/// Read noise at a requested SNR: the measured SNR is within 0.1 dB over 1e5 rows
/// (the variance estimate's relative error is ~sqrt(2/n) = 0.45 %, i.e. 0.02 dB).
#[test]
fn read_noise_hits_the_requested_snr() {
    let rows = 100_000;
    let clean: Vec<f64> = (0..rows)
        .map(|i| 10.0 + 3.0 * ((i as f64) * 0.01).sin())
        .collect();
    for snr in [0.0, 13.0, 40.0] {
        let model = NoiseModel {
            snr_db: Some(snr),
            seed: 9,
            dark: 0.7,
            ..Default::default()
        };
        let (v, report) = apply_noise(&clean, 1, &model);
        let measured = report.channels[0].effective_snr_db;
        assert!(
            (measured - snr).abs() < 0.1,
            "asked {snr} dB, got {measured}"
        );
        // The dark offset shifts the mean.
        let mean_diff = v.iter().zip(&clean).map(|(a, b)| a - b).sum::<f64>() / rows as f64;
        let sigma = report.channels[0].read_sigma.unwrap();
        assert!((mean_diff - 0.7).abs() < 5.0 * sigma / (rows as f64).sqrt());
    }
}

/// ADC: values sit on 2^bits levels of full_scale / (2^bits - 1), never above full scale;
/// a signal driven beyond full scale saturates.
#[test]
fn adc_quantises_and_saturates() {
    let rows = 20_000;
    let clean: Vec<f64> = (0..rows).map(|i| i as f64 / rows as f64).collect();
    let model = NoiseModel {
        adc_bits: Some(4),
        dark: 0.05,
        seed: 1,
        ..Default::default()
    };
    let (v, report) = apply_noise(&clean, 1, &model);
    let fs = report.channels[0].full_scale.unwrap();
    let max_clean = clean.iter().copied().fold(0.0, f64::max);
    assert!((fs - (1.1 * max_clean + 0.05)).abs() < 1e-12);
    let step = fs / 15.0;
    let mut levels: Vec<i64> = v
        .iter()
        .map(|&x| {
            let q = x / step;
            assert!((q - q.round()).abs() < 1e-9, "{x} is not on a level");
            assert!(x <= fs + 1e-12 && x >= 0.0);
            q.round() as i64
        })
        .collect();
    levels.dedup();
    levels.sort();
    levels.dedup();
    assert!(levels.len() <= 16);
    // The ramp (plus dark) spans 0.05..1.05 of fs = 1.15: levels 1..=14 all appear.
    assert!(levels.len() >= 14, "{levels:?}");
    assert_eq!(report.channels[0].saturated, 0);

    // Strong read noise pushes values past full scale: clipped and counted.
    let noisy = NoiseModel {
        snr_db: Some(0.0),
        ..model
    };
    let (v, report) = apply_noise(&clean, 1, &noisy);
    assert!(report.channels[0].saturated > 100);
    assert!(v.iter().all(|&x| x >= 0.0 && x <= fs));
    assert!(v.iter().filter(|&&x| x == fs).count() >= report.channels[0].saturated);
}

/// Drift: stationary std = drift, slow (lag-1 autocorrelation = exp(-1/L)).
#[test]
fn drift_is_a_slow_walk_with_the_requested_amplitude() {
    let rows = 400_000;
    let model = NoiseModel {
        drift: 0.05,
        drift_correlation: Some(40.0),
        seed: 21,
        ..Default::default()
    };
    let f = drift_factors(rows, &model);
    let x: Vec<f64> = f.iter().map(|v| v - 1.0).collect();
    let (mean, var) = moments(&x);
    // Effective sample size ~ n / (2L) = 5000: the std estimate is good to ~ 1-2 %.
    assert!(mean.abs() < 0.01, "mean {mean}");
    assert!((var.sqrt() - 0.05).abs() < 0.005, "std {}", var.sqrt());
    let lag1 = x.windows(2).map(|w| w[0] * w[1]).sum::<f64>() / (rows - 1) as f64 / var;
    assert!(
        (lag1 - (-1.0f64 / 40.0).exp()).abs() < 0.01,
        "lag-1 autocorrelation {lag1}"
    );
    // Applied multiplicatively to every channel of a row alike.
    let clean = [2.0, 4.0].repeat(1000);
    let model = NoiseModel {
        drift: 0.1,
        seed: 2,
        ..Default::default()
    };
    let (v, report) = apply_noise(&clean, 2, &model);
    for row in v.chunks(2) {
        assert!((row[1] / row[0] - 2.0).abs() < 1e-12);
    }
    assert!(report.drift_min < 1.0 && report.drift_max > 1.0);
}

#[test]
fn noise_is_deterministic_and_seeded() {
    let clean: Vec<f64> = (0..5000).map(|i| (i % 17) as f64).collect();
    let model = NoiseModel {
        drift: 0.02,
        photons: Some(1e3),
        snr_db: Some(30.0),
        dark: 0.1,
        adc_bits: Some(12),
        seed: 77,
        ..Default::default()
    };
    let (a, _) = apply_noise(&clean, 1, &model);
    let (b, _) = apply_noise(&clean, 1, &model);
    assert_eq!(a, b);
    let (c, _) = apply_noise(
        &clean,
        1,
        &NoiseModel {
            seed: 78,
            ..model.clone()
        },
    );
    assert_ne!(a, c);
    // Noiseless default is the identity.
    let (d, report) = apply_noise(&clean, 1, &NoiseModel::default());
    assert_eq!(d, clean);
    assert!(report.channels[0].effective_snr_db.is_infinite());
}

#[test]
fn noise_model_validation_names_flags() {
    let bad = NoiseModel {
        photons: Some(0.0),
        ..Default::default()
    };
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("--photons")
    );
    let bad = NoiseModel {
        adc_bits: Some(40),
        ..Default::default()
    };
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("--adc-bits")
    );
    assert!(NoiseModel::default().validate().is_ok());
}

/// End to end: the simulated buckets of a Bernoulli run correlate back to the scene (GI).
#[test]
fn simulated_bernoulli_run_correlates_to_the_scene() {
    let s = spec(Family::Bernoulli { fill: 0.5 }, 8, 8, 20_000);
    let t: Vec<f32> = (0..64)
        .map(|p| if p % 9 == 0 { 1.0 } else { 0.0 })
        .collect();
    let sim = simulate(
        &s,
        &[&t],
        &NoiseModel {
            photons: Some(1e4),
            ..Default::default()
        },
        None,
    );
    let generator = PatternGenerator::new(&s);
    let mut p = vec![0.0f32; 64];
    let mut sum_cp = vec![0.0f64; 64];
    let mut sum_p = vec![0.0f64; 64];
    let mut sum_c = 0.0;
    for i in 0..sim.rows {
        generator.fill_values(i as u64, &mut p);
        let c = sim.values[i];
        sum_c += c;
        for x in 0..64 {
            sum_cp[x] += c * p[x] as f64;
            sum_p[x] += p[x] as f64;
        }
    }
    let n = sim.rows as f64;
    let g: Vec<f64> = (0..64)
        .map(|x| sum_cp[x] / n - sum_c / n * sum_p[x] / n)
        .collect();
    // E[G] = q(1-q) t = t/4.
    for x in 0..64 {
        let expect = t[x] as f64 / 4.0;
        assert!(
            (g[x] - expect).abs() < 0.05,
            "pixel {x}: {} vs {expect}",
            g[x]
        );
    }
}
