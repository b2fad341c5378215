//! Reconstructs one simulated acquisition and prints time, PSNR and the report's solver figures:
//! a profiling aid for the numerics (the bench runs whole grids).
//!
//! `cargo run --release -p helmholtz-bench --example one -- hadamard 128 0.1 camera tv '{"max_iter":100}' [repeat] [none|snr30|poisson]`

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
    let truth = Target::builtin(&scene, n, n).expect("scene").transport(1.0);
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
        if std::env::var_os("ONE_REPORT").is_some() {
            let mut v = serde_json::to_value(&r.report.details).unwrap_or_default();
            strip(&mut v);
            println!("{}", serde_json::to_string_pretty(&v).unwrap_or_default());
        }
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
