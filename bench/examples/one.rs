//! Reconstructs one simulated acquisition and prints time, PSNR and the report's solver figures:
//! a profiling aid for the numerics (the bench runs whole grids).
//!
//! `cargo run --release -p helmholtz-bench --example one -- hadamard 128 0.1 camera tv '{"max_iter":100}' [repeat] [none|snr30|poisson]`
//!
//! The scene is a built-in name or a PNG path. `ONE_REPORT=1` prints the report's details.
//! `ONE_RISK=1` (random families) prints the image's mean squared prediction error on 20,000
//! fresh noise-free rows of the same family (another seed): what held-out rows estimate, less
//! their noise.
//! `ONE_GROUPS=1` (Hadamard split pairs) prints, per scale order `jx + jy` of the measured
//! coefficients, the data's energy, the noise drawn, and the image's residual and error there;
//! with `ONE_JS_SIGMA=s` (or `report`: `auto`'s noise estimate, two standard errors high) also
//! the PSNR of the image after a per-order James-Stein consistency step (the residual put back
//! by each group's factor): `ONE_JS_GROUP` (fewest coefficients a group, 8), `ONE_JS_MIN` (a
//! factor below it counts 0; 0), `ONE_JS_LEVEL=1` (group by Russian-doll level instead),
//! `ONE_JS_DC=1` (the mean's coefficient a group of its own; else left out). `auto` applies
//! such a step itself since 2026-11-29 ([`helmholtz_recon::auto::Consistency`]); the probe
//! measures it on any method's image.

use std::time::Instant;

use helmholtz_bench::{Case, Noise};
use helmholtz_recon::{self as recon, Control, MethodConfig, Problem, SliceSource, metrics};
use helmholtz_sim::Target;
use helmholtz_sim::simulate;

fn main() {
    helmholtz_alloc::retain_freed_memory();
    let a: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: &str| a.get(i).cloned().unwrap_or_else(|| d.to_string());
    let family = arg(1, "hadamard");
    let n: u32 = arg(2, "128").parse().expect("size");
    let ratio: f64 = arg(3, "0.1").parse().expect("ratio");
    let scene = arg(4, "camera");
    let method = arg(5, "tv");
    let params: serde_json::Value = serde_json::from_str(&arg(6, "null")).expect("params JSON");
    let repeat: usize = arg(7, "1").parse().expect("repeat");
    let noise = match arg(8, "none").as_str() {
        "none" => Noise::None,
        "snr30" => Noise::Snr30,
        "poisson" => Noise::Poisson,
        other => panic!("noise {other:?}: none, snr30 or poisson"),
    };
    let case = Case {
        scene: scene.clone(),
        size: (n, n),
        ratio,
        family,
        noise,
        method: method.clone(),
    };
    let spec = case.spec();
    let truth = Target::load(&scene, n, n).expect("scene").transport(1.0);
    let sim = simulate::simulate(&spec, &[&truth], &noise.model(), None);
    let config = MethodConfig::parse(&method, &params).expect("method");
    let problem = Problem {
        spec: &spec,
        channels: 1,
        rows: spec.count(),
    };
    for _ in 0..repeat {
        let mut source = SliceSource::new(&sim.values, 1, 4096);
        let started = Instant::now();
        let r = recon::reconstruct(&problem, &config, &mut source, &Control::new())
            .expect("reconstruct");
        let s = started.elapsed().as_secs_f64();
        let img = &r.images[0].data;
        let mean = |v: &[f32]| v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64;
        println!(
            "image mean {:.4} (truth {:.4}), min {:.4}, max {:.4}",
            mean(img),
            mean(&truth),
            img.iter().copied().fold(f32::INFINITY, f32::min),
            img.iter().copied().fold(f32::NEG_INFINITY, f32::max)
        );
        // The slope of the image on the truth (1: the right physical units).
        let (mi, mt) = (mean(img), mean(&truth));
        let (mut cov, mut var, mut var_img) = (0.0, 0.0, 0.0);
        for (&x, &t) in img.iter().zip(&truth) {
            cov += (x as f64 - mi) * (t as f64 - mt);
            var += (t as f64 - mt) * (t as f64 - mt);
            var_img += (x as f64 - mi) * (x as f64 - mi);
        }
        let err: f64 = img
            .iter()
            .zip(&truth)
            .map(|(&x, &t)| (x as f64 - t as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        let norm: f64 = img.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
        // And the slope of the truth on the image (1: no rescaling of the image predicts the
        // truth better; what the fitted PSNR's gain is).
        println!(
            "gain {:.3}  truth-on-image slope {:.3}  true relative error {:.4}",
            cov / var,
            cov / var_img,
            err / norm
        );
        println!(
            "{:.4} s  {:.2} dB  ssim {:.3}  iterations {}  held-out {:?}",
            s,
            metrics::psnr(img, &truth),
            metrics::ssim(img, &truth, n as usize, n as usize),
            r.report.iterations,
            r.report.held_out.as_ref().map(|h| h.relative_residual)
        );
        // The image's bits, hashed (FNV-1a): "the same image" means bit for bit.
        let hash = img.iter().fold(0xcbf2_9ce4_8422_2325_u64, |h, v| {
            v.to_bits()
                .to_le_bytes()
                .iter()
                .fold(h, |h, &b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3))
        });
        println!("image bits fnv1a {hash:016x}");
        if helmholtz_bench::env_flag("ONE_GROUPS") {
            // ONE_JS_SIGMA=report: the report's noise estimate, two standard errors high.
            let reported = serde_json::to_value(&r.report.details).ok().and_then(|v| {
                let n = &v["auto"][0]["noise_estimate"];
                Some(n["sigma"].as_f64()? + 2.0 * n["standard_error"].as_f64()?)
            });
            groups(&spec, &sim.values, img, &truth, reported);
        }
        if helmholtz_bench::env_flag("ONE_RISK") {
            // The image's prediction error on fresh rows of the same family (another seed),
            // noise-free: what held-out rows estimate, plus their noise.
            let fresh = helmholtz_proto::PatternSpec::new(spec.family().clone(), n, n, 20_000, 7)
                .expect("ONE_RISK needs a random family (bernoulli, speckle)");
            let image: Vec<f32> = img.to_vec();
            let quiet = Noise::None.model();
            let a = simulate::simulate(&fresh, &[&truth], &quiet, None).values;
            let b = simulate::simulate(&fresh, &[&image], &quiet, None).values;
            let risk = a
                .iter()
                .zip(&b)
                .map(|(x, y)| (x - y) * (x - y))
                .sum::<f64>()
                / a.len() as f64;
            println!(
                "fresh-row risk {risk:.3} (mean squared noise-free prediction error over {} rows)",
                a.len()
            );
        }
        if helmholtz_bench::env_flag("ONE_REPORT") {
            let mut v = serde_json::to_value(&r.report.details).unwrap_or_default();
            strip(&mut v);
            println!("{}", serde_json::to_string_pretty(&v).unwrap_or_default());
        }
    }
}

/// Hadamard split pairs: per scale order `jx + jy` of the measured coefficients, their count,
/// and per coefficient the data's energy, the noise drawn, the image's residual on the data
/// (over the noise drawn: 1 is a fit within the noise), and the image's error there.
fn groups(
    spec: &helmholtz_proto::PatternSpec,
    values: &[f64],
    img: &[f32],
    truth: &[f32],
    reported: Option<f64>,
) {
    use helmholtz_recon::linop::LinearOperator;
    let Ok(op) = helmholtz_recon::ops::HadamardOperator::from_spec(spec, values.len() as u64)
    else {
        return;
    };
    let (w, h) = (spec.width() as usize, spec.height() as usize);
    let k = (w * h) as f64;
    let d: Vec<f64> = values
        .chunks_exact(2)
        .map(|p| (p[0] - p[1]) / k.sqrt())
        .collect();
    let to64 = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<_>>();
    let (mut pi, mut pt) = (vec![0.0; op.rows()], vec![0.0; op.rows()]);
    op.apply(&to64(img), &mut pi);
    op.apply(&to64(truth), &mut pt);
    let level = |n: usize| helmholtz_recon::auto::hadamard_level(n, (w, h));
    let mut g = std::collections::BTreeMap::<u32, [f64; 5]>::new();
    for (i, &n) in op.natural_indices().iter().enumerate() {
        let e = g.entry(level(n)).or_default();
        e[0] += 1.0;
        e[1] += d[i] * d[i];
        e[2] += (d[i] - pt[i]).powi(2);
        e[3] += (d[i] - pi[i]).powi(2);
        e[4] += (pi[i] - pt[i]).powi(2);
    }
    // The image's residual on the measured coefficients put back per group of orders (at least
    // 8 coefficients) by its positive-part James-Stein factor, with the noise `ONE_JS_SIGMA`
    // (per coefficient, in the units of d): what a per-order consistency step would give.
    let sigma = std::env::var("ONE_JS_SIGMA")
        .ok()
        .and_then(|v| match v.as_str() {
            "report" => reported,
            v => v.parse::<f64>().ok(),
        });
    if let Some(sigma) = sigma {
        let min_factor: f64 = std::env::var("ONE_JS_MIN")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(0.0);
        let by_level = helmholtz_bench::env_flag("ONE_JS_LEVEL");
        let rd = |n: usize| {
            let (u, v) = (n / w, n % w);
            let tz = |a: usize| {
                if a == 0 {
                    w.trailing_zeros()
                } else {
                    a.trailing_zeros()
                }
            };
            tz(u).min(tz(v))
        };
        let order: Vec<u32> = op
            .natural_indices()
            .iter()
            .map(|&n| if by_level { 20 - rd(n) } else { level(n) })
            .collect();
        let dc_too = helmholtz_bench::env_flag("ONE_JS_DC");
        let mut rows: Vec<usize> = (0..op.rows())
            .filter(|&r| op.natural_indices()[r] != 0)
            .collect();
        rows.sort_by_key(|&r| order[r]);
        let min_group: usize = std::env::var("ONE_JS_GROUP")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(8);
        let mut groups: Vec<Vec<usize>> = Vec::new();
        for run in rows.chunk_by(|&a, &c| order[a] == order[c]) {
            match groups.last_mut() {
                Some(last) if last.len() < min_group => last.extend_from_slice(run),
                _ => groups.push(run.to_vec()),
            }
        }
        if let Some(r) = op.natural_indices().iter().position(|&n| n == 0)
            && dc_too
        {
            groups.insert(0, vec![r]);
        }
        let mut back = vec![0.0; op.rows()];
        let mut factors = Vec::new();
        for g in &groups {
            let e: f64 = g.iter().map(|&r| (d[r] - pi[r]).powi(2)).sum();
            let f = (1.0 - (g.len() as f64 - 2.0).max(1.0) * sigma * sigma / e).max(0.0);
            let f = if f < min_factor { 0.0 } else { f };
            factors.push(format!("{}:{:.2}", order[g[0]], f));
            g.iter().for_each(|&r| back[r] = f * (d[r] - pi[r]));
        }
        let mut add = vec![0.0; img.len()];
        op.adjoint(&back, &mut add);
        let fixed: Vec<f32> = img
            .iter()
            .zip(&add)
            .map(|(&x, &a)| (x as f64 + a).max(0.0) as f32)
            .collect();
        println!(
            "consistency: {:.2} dB (factors {})",
            helmholtz_recon::metrics::psnr(&fixed, truth),
            factors.join(" ")
        );
    }
    println!("order  n  data/n  noise/n  residual/noise  error/noise");
    for (l, e) in g {
        println!(
            "{l:>5} {:>4} {:.3e} {:.3e} {:.3} {:.3}",
            e[0],
            e[1] / e[0],
            e[2] / e[0],
            e[3] / e[2],
            e[4] / e[2]
        );
    }
}

/// Drops the long arrays (objective histories, paths) so the report fits a terminal.
fn strip(v: &mut serde_json::Value) {
    match v {
        serde_json::Value::Object(m) => {
            m.retain(|_, x| !matches!(x, serde_json::Value::Array(a) if a.len() > 8 && a.iter().all(|e| e.is_number())));
            m.values_mut().for_each(strip);
        }
        serde_json::Value::Array(a) => a.iter_mut().for_each(strip),
        _ => {}
    }
}
