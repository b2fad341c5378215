//! One simulated adaptive session, reconstructed by the given methods: PSNR, time and (with
//! `ONE_REPORT=1`) each report. A probe for the numerics on adaptive data (the bench runs grids).
//!
//! `cargo run --release -p helmholtz-bench --example adaptive_one -- haar|haar1f|hadamard 128 0.05 relief none|noisy|DB [PERSISTENCE] [direct,auto,...]`
//!
//! `haar1f` shows the Haar indices as single frames (`frames: "single"`). The noise is read noise
//! on every frame: `noisy` is the bench's 30 dB below a half-lit bucket, `DB` (a number) that many
//! dB below it. Method `auto_read_noise` is `auto` told the drawn sigma (`read_noise`).
//!
//! `ONE_ALPHA=1` (with `direct,auto`, noise-free) also prints the PSNR of `direct + alpha u` for
//! `u = auto - direct`, the fill-in of the coefficients no pair measured, and the oracle `alpha`.
//! `ONE_AUDIT=r` (with `direct,auto`, noise-free) asks what random audit pairs would say: `r`
//! times the pairs measured, drawn uniformly from the coefficients none measured (taken from the
//! truth), estimate the zero-filled image's error and the `alpha` of `auto`'s fill-in.

use std::time::Instant;

use helmholtz_proto::{AdaptiveFrames, Family};
use helmholtz_recon::{self as recon, Control, MethodConfig, Problem, SliceSource, metrics};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: &str| a.get(i).cloned().unwrap_or_else(|| d.to_string());
    let (haar, single) = match arg(1, "haar").as_str() {
        "haar" => (true, false),
        "haar1f" => (true, true),
        "hadamard" => (false, false),
        other => panic!("basis {other:?}: haar, haar1f or hadamard"),
    };
    let size: u32 = arg(2, "128").parse().expect("size");
    let ratio: f64 = arg(3, "0.05").parse().expect("ratio");
    let scene = arg(4, "relief");
    let snr_db = match arg(5, "none").as_str() {
        "none" => None,
        "noisy" => Some(30.0),
        db => Some(
            db.parse::<f64>()
                .unwrap_or_else(|_| panic!("noise {db:?}: none, noisy or a number of dB")),
        ),
    };
    let persistence = a
        .get(6)
        .filter(|p| !p.is_empty() && *p != "default")
        .map(|p| p.parse::<f64>().expect("persistence"));
    let methods = arg(7, "direct,auto");
    let mut family = Family::adaptive(haar, 0, 0.0, persistence);
    if single {
        family = family.with_frames(AdaptiveFrames::Single);
    }
    let (spec, frames, truth, sigma) =
        helmholtz_bench::adaptive::probe_session_at(&scene, size, ratio, snr_db, family)
            .expect("session");
    {
        let (planner, _) = recon::adaptive::replay(&spec, 1, &frames).expect("the session replays");
        println!(
            "planner: {} pairs, estimated error {:?}, stop {:?}",
            planner.observed_pairs(),
            planner.estimated_error(),
            planner.finished()
        );
    }
    let problem = Problem {
        spec: &spec,
        channels: 1,
        rows: frames.len() as u64,
    };
    let mut images: Vec<(String, Vec<f32>)> = Vec::new();
    for method in methods.split(',') {
        let config = match method {
            "auto_read_noise" => {
                MethodConfig::parse("auto", &serde_json::json!({ "read_noise": sigma }))
            }
            m => MethodConfig::parse(m, &serde_json::Value::Null),
        }
        .expect("method");
        let started = Instant::now();
        let r = recon::reconstruct(
            &problem,
            &config,
            &mut SliceSource::new(&frames, 1, 4096),
            &Control::new(),
        )
        .expect("reconstruct");
        let s = started.elapsed().as_secs_f64();
        let img = &r.images[0].data;
        let norm = |v: &mut dyn Iterator<Item = f64>| v.map(|x| x * x).sum::<f64>().sqrt();
        println!(
            "{method:<8} relative L2 error {:.4}",
            norm(&mut img.iter().zip(&truth).map(|(a, b)| (a - b) as f64))
                / norm(&mut truth.iter().map(|&b| b as f64))
        );
        let mean = |v: &[f32]| v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64;
        println!(
            "{method:<8} {:>7.2} dB  {s:>7.3} s  ({} frames; mean {:.4} against {:.4}, max {:.3})",
            metrics::psnr(img, &truth),
            frames.len(),
            mean(img),
            mean(&truth),
            img.iter().copied().fold(f32::NEG_INFINITY, f32::max)
        );
        images.push((method.to_string(), img.clone()));
        if helmholtz_bench::env_flag("ONE_REPORT") {
            println!(
                "{}",
                serde_json::to_string_pretty(&r.report.details).unwrap()
            );
        }
    }
    let get = |name: &str| images.iter().find(|(m, _)| m == name).map(|(_, v)| v);
    // Probe: audit coefficients. `ONE_AUDIT=r`: a share `r` of the pair budget drawn at random
    // from the coefficients no pair measured (noise-free truth), as a planner could reserve
    // them. From them alone: the zero-filled image's error (their mean energy times the count
    // of unmeasured coefficients) and the scale `alpha` of `auto`'s fill-in they support,
    // against the truth over all unmeasured coefficients.
    if let Some(share) = std::env::var("ONE_AUDIT")
        .ok()
        .and_then(|v| v.parse::<f64>().ok())
    {
        use helmholtz_recon::linop::LinearOperator;
        let (planner, _) = recon::adaptive::replay(&spec, 1, &frames).expect("replays");
        let k = (size * size) as usize;
        let full: Box<dyn LinearOperator> = if haar {
            Box::new(recon::ops::HaarSubsetOperator::new(size, (0..k).collect()))
        } else {
            Box::new(recon::ops::HadamardOperator::with_natural(
                size,
                size,
                (0..k).collect(),
            ))
        };
        let coef = |img: &[f32]| {
            let x: Vec<f64> = img.iter().map(|&v| v as f64).collect();
            let mut c = vec![0.0; k];
            full.apply(&x, &mut c);
            c
        };
        let mut measured = vec![false; k];
        planner
            .indices()
            .iter()
            .for_each(|&n| measured[n as usize] = true);
        let unmeasured: Vec<usize> = (0..k).filter(|&n| !measured[n]).collect();
        let t = coef(&truth);
        let truth_energy: f64 = t.iter().map(|v| v * v).sum();
        let true_u: f64 = unmeasured.iter().map(|&n| t[n] * t[n]).sum();
        let audit_n = ((planner.indices().len() as f64 * share).round() as usize).max(1);
        // A fixed pseudo-random draw of the unmeasured coefficients.
        let mut order: Vec<(u64, usize)> = unmeasured
            .iter()
            .map(|&n| {
                (
                    (n as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0x5851_F42D,
                    n,
                )
            })
            .collect();
        order.sort_unstable();
        let audit: Vec<usize> = order.iter().take(audit_n).map(|p| p.1).collect();
        let scale = unmeasured.len() as f64 / audit.len() as f64;
        let est_u: f64 = audit.iter().map(|&n| t[n] * t[n]).sum::<f64>() * scale;
        println!(
            "audit {} of {} unmeasured: zero-filled error estimate {:.4}, true {:.4}, planner {:?}",
            audit.len(),
            unmeasured.len(),
            (est_u / truth_energy).sqrt(),
            (true_u / truth_energy).sqrt(),
            planner.estimated_error()
        );
        if let (Some(d), Some(au)) = (get("direct"), get("auto")) {
            let (cd, ca) = (coef(d), coef(au));
            let alpha = |set: &[usize]| {
                let (mut um, mut uu) = (0.0, 0.0);
                for &n in set {
                    let u = ca[n] - cd[n];
                    um += u * (t[n] - cd[n]);
                    uu += u * u;
                }
                um / uu
            };
            println!(
                "alpha of auto's fill-in: audit {:.3}, all unmeasured {:.3}",
                alpha(&audit),
                alpha(&unmeasured)
            );
        }
    }
    // Probe: the fill-in `u = auto - direct` scaled by alpha (noise-free, `direct` holds the
    // measured coefficients exactly and `auto` the same plus its model's fill-in).
    if helmholtz_bench::env_flag("ONE_ALPHA")
        && let (Some(d), Some(au)) = (get("direct"), get("auto"))
    {
        let u: Vec<f64> = au.iter().zip(d).map(|(a, b)| (*a - *b) as f64).collect();
        let miss: Vec<f64> = truth.iter().zip(d).map(|(t, b)| (*t - *b) as f64).collect();
        let uu: f64 = u.iter().map(|x| x * x).sum();
        let um: f64 = u.iter().zip(&miss).map(|(x, y)| x * y).sum();
        let best = um / uu;
        let mut line = format!("oracle alpha {best:.3}:");
        for alpha in [0.0, 0.25, 0.5, 0.75, 1.0, best] {
            let img: Vec<f32> = d
                .iter()
                .zip(&u)
                .map(|(b, x)| ((*b as f64 + alpha * x).max(0.0)) as f32)
                .collect();
            line += &format!(" {alpha:.2} -> {:.2} dB", metrics::psnr(&img, &truth));
        }
        println!("{line}");
    }
}
