//! Writes the benchmark results: `benchmarks.json` (raw), `benchmarks.md` (tables, plots).

use std::collections::BTreeMap;
use std::fmt::Write;
use std::path::Path;

use anyhow::Context;
use serde_json::json;

use super::Measurement;
use super::plot::{Curve, time_vs_psnr};

/// Writes the report of a run (`repeat` as given with `--repeat`, named in the command line it
/// reports).
pub fn write_with(
    dir: &Path,
    preset: &str,
    repeat: u32,
    contention: &serde_json::Value,
    results: &[Measurement],
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir.join("bench"))
        .with_context(|| format!("creating {}", dir.display()))?;
    let release = if cfg!(debug_assertions) {
        ""
    } else {
        "--release "
    };
    let repeat_arg = if repeat > 1 {
        format!(" --repeat {repeat}")
    } else {
        String::new()
    };
    let command = format!("cargo run {release}-p helmholtz-bench -- --preset {preset}{repeat_arg}");
    let mut machine = json!({
        "cores": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
        "rayon_threads": rayon::current_num_threads(),
        "os": std::env::consts::OS,
        "arch": std::env::consts::ARCH,
        "profile": if cfg!(debug_assertions) { "debug" } else { "release" },
    });
    super::machine::merge(&mut machine, contention);
    let raw =
        json!({ "command": command, "preset": preset, "machine": machine, "results": results });
    // The full grid is docs/benchmarks.{md,json}; the smaller presets get a suffix.
    let stem = if preset == "full" {
        "benchmarks".to_string()
    } else {
        format!("benchmarks-{preset}")
    };
    std::fs::write(
        dir.join(format!("{stem}.json")),
        serde_json::to_string_pretty(&raw)?,
    )?;

    let mut md = String::new();
    let _ = writeln!(md, "# Speed against error\n");
    let _ = writeln!(
        md,
        "Produced by `{command}` ({} cores, {} build; {}).",
        machine["cores"],
        machine["profile"].as_str().unwrap_or("?"),
        super::machine::sentence(&machine)
    );
    let _ = writeln!(
        md,
        "Raw figures: [`{stem}.json`]({stem}.json). Every row is one reconstruction by the service's own numerics on a simulated acquisition of a built-in scene (`helmholtz_sim::simulate`), scored against that scene. PSNR uses the scene's range as peak; \"held-out\" is the error estimate the service reports without ground truth (the held-out relative residual, `||c_H - c_hat_H|| / ||c_H - mean(c_H)||`; \"-\" where a method has none, e.g. the exact inverses); for the correlation methods (gi, dgi, ngi), which estimate t only up to scale and offset, the plotted/quality figure is after a least-squares affine fit (the raw PSNR is in the JSON). Times are wall-clock for the reconstruction alone (with `--repeat`, the median of the runs) (the patterns are regenerated from the seed inside it); memory is the peak heap growth during it.\n"
    );
    let mut panels: BTreeMap<String, Vec<&Measurement>> = BTreeMap::new();
    for m in results {
        let c = &m.case;
        panels
            .entry(format!(
                "{} {}x{}, noise: {}",
                c.family,
                c.size.0,
                c.size.1,
                c.noise.name()
            ))
            .or_default()
            .push(m);
    }
    for (title, ms) in &panels {
        let _ = writeln!(md, "## {title}\n");
        let mut curves: BTreeMap<String, Curve> = BTreeMap::new();
        for m in ms {
            let label = format!("{} ({})", m.case.method, m.case.scene);
            curves
                .entry(label.clone())
                .or_insert(Curve {
                    label,
                    points: vec![],
                })
                .points
                .push((m.seconds, m.quality_db()));
        }
        let file = format!(
            "bench/{preset}-{}.svg",
            title.replace([' ', ',', ':'], "_").replace("__", "_")
        );
        std::fs::write(
            dir.join(&file),
            time_vs_psnr(title, &curves.into_values().collect::<Vec<_>>()),
        )?;
        let _ = writeln!(md, "![time against PSNR: {title}]({file})\n");
        let _ = writeln!(
            md,
            "| scene | sampling | rows | method | seconds | PSNR dB | SSIM | raw PSNR dB | held-out | peak MiB | updates/s | auto's choice |"
        );
        let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|---|");
        for m in ms {
            let _ = writeln!(
                md,
                "| {} | {:.2} % | {} | {} | {:.4} | {} | {} | {} | {} | {} | {} | {} |",
                m.case.scene,
                m.case.ratio * 100.0,
                m.rows,
                m.case.method,
                m.seconds,
                num(m.quality_db(), 2),
                num(m.quality_ssim(), 3),
                num(m.psnr_db, 2),
                m.report["held_out"]["relative_residual"]
                    .as_f64()
                    .map(|v| format!("{v:.4}"))
                    .unwrap_or_else(|| "-".into()),
                m.peak_memory_bytes
                    .map(|b| format!("{:.1}", b as f64 / (1u64 << 20) as f64))
                    .unwrap_or_else(|| "-".into()),
                m.updates_per_second
                    .map(|u| format!("{u:.2e}"))
                    .unwrap_or_else(|| "-".into()),
                auto_choice(&m.report),
            );
            if let Some(e) = &m.error {
                let _ = writeln!(md, "| | | | | refused: {e} | | | | | | | |");
            }
        }
        md.push('\n');
    }
    std::fs::write(dir.join(format!("{stem}.md")), md)?;
    Ok(())
}

/// "tv f=0.001, 1820 kept, 64x64" for auto; empty for other methods.
fn auto_choice(report: &serde_json::Value) -> String {
    let Some(a) = report["details"]["auto"].get(0) else {
        return String::new();
    };
    let res = &a["resolution"]["supported"];
    format!(
        "{} f={} kept {} at {}x{}",
        a["model"].as_str().unwrap_or("?"),
        a["lambda_fraction"]
            .as_f64()
            .map(|f| format!("{f:.0e}"))
            .unwrap_or_default(),
        a["kept"],
        res[0],
        res[1]
    )
}

fn num(v: f64, digits: usize) -> String {
    if v.is_finite() {
        format!("{v:.digits$}")
    } else if v == f64::INFINITY {
        "inf".into()
    } else {
        "-".into()
    }
}
