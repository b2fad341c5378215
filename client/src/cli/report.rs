//! A reconstruction's report as text: what the user needs to judge the image (the model `auto`
//! chose and its weight, the noise it measured and the image error it estimates, the held-out
//! error estimate, warnings, PSNR/SSIM when the session has
//! ground truth, time and memory). `--json` prints the whole report instead.

use helmholtz_proto::rest::{AutoChoice, Figure, Report, TransportQuality};
use serde_json::Value;

/// Indented lines describing `report` (no trailing newline on the last).
pub fn report_lines(report: &Report) -> Vec<String> {
    let mut lines = Vec::new();
    // auto: one choice per channel (details.auto[i], in channel order).
    if let Some(choices) = report.recon.details.get("auto").and_then(Value::as_array) {
        for (i, c) in choices.iter().enumerate() {
            let Ok(choice) = serde_json::from_value::<AutoChoice>(c.clone()) else {
                continue;
            };
            let channel = c
                .get("channel")
                .and_then(Value::as_str)
                .map(str::to_string)
                .unwrap_or_else(|| {
                    if choices.len() > 1 {
                        format!("channel {i}")
                    } else {
                        String::new()
                    }
                });
            lines.push(auto_line(&channel, &choice));
            if let Some(line) = noise_and_error_line(&choice) {
                lines.push(line);
            }
            for w in &choice.warnings {
                lines.push(format!("warning: {w}"));
            }
        }
    }
    // transport: the sparsifying transform and weight chosen for T.
    if let Some(transform) = report
        .recon
        .details
        .get("transform")
        .and_then(Value::as_str)
    {
        let details = &report.recon.details;
        let mut s = format!("transform {transform}");
        if let Some(l) = report.detail_f64("lambda") {
            s.push_str(&format!(", weight {l:.3e}"));
        }
        // A Hadamard subset's rows may be stored in another transform than the one fitted:
        // the coarse Haar coefficients the pairs measure completely, taken as measured.
        if let Some(stored) = details.get("stored_transform").and_then(Value::as_str)
            && stored != transform
        {
            s.push_str(&format!(", stored in {stored}"));
        }
        if details.get("coarse_exact").and_then(Value::as_bool) == Some(true) {
            s.push_str(" (coarse coefficients as measured)");
        }
        lines.push(s);
        if let Some(e) = details.get("error_estimate")
            && let Some(rel) = e.get("relative").and_then(Value::as_f64)
        {
            let mut s = format!("estimated error of T {rel:.3}");
            if let Some([lo, hi]) = e
                .get("range")
                .and_then(Value::as_array)
                .map(|r| [0, 1].map(|i| r.get(i).and_then(Value::as_f64).unwrap_or(f64::NAN)))
            {
                s.push_str(&format!(" ({lo:.3} to {hi:.3})"));
            }
            lines.push(s);
        }
        if let Some(e) = details.get("relight_error_estimate") {
            let rel = e.get("relative").and_then(Value::as_f64);
            let upper = e.get("upper").and_then(Value::as_f64);
            let unresolved = e.get("resolved").and_then(Value::as_bool) == Some(false);
            match (rel, upper) {
                // Not resolved by the held-out frames: the estimate is the frames' noise alone.
                (Some(rel), Some(upper)) if unresolved => lines.push(format!(
                    "estimated error of the full-light relight {rel:.4}, what the frames' noise alone makes (at most {upper:.4}: the held-out frames do not resolve more)"
                )),
                (Some(rel), Some(upper)) => lines.push(format!(
                    "estimated error of the full-light relight {rel:.4} (at most {upper:.4})"
                )),
                (Some(rel), None) => lines.push(format!(
                    "estimated error of the full-light relight {rel:.4}"
                )),
                // Not resolved from the held-out frames' scatter: only the bound is known.
                (None, Some(upper)) => lines.push(format!(
                    "error of the full-light relight at most {upper:.4} (the data do not resolve more)"
                )),
                (None, None) => {}
            }
        }
    }
    if let Some(warnings) = report
        .recon
        .details
        .get("warnings")
        .and_then(Value::as_array)
    {
        lines.extend(
            warnings
                .iter()
                .filter_map(Value::as_str)
                .map(|w| format!("warning: {w}")),
        );
    }
    match (&report.recon.held_out, &report.recon.held_out_unavailable) {
        (Some(h), _) => lines.push(match h.relative_residual {
            Some(r) => format!(
                "held-out error {r:.4} (relative residual on {} held-out rows; rms {:.4e} in bucket units)",
                h.rows, h.rms_residual
            ),
            None => format!(
                "held-out error: not defined (the {} held-out rows are all equal), rms {:.4e}",
                h.rows, h.rms_residual
            ),
        }),
        (None, Some(why)) => lines.push(format!("held-out error: unavailable ({why})")),
        (None, None) => {}
    }
    for q in report.channel_quality() {
        lines.push(format!(
            "vs ground truth{}: PSNR {} dB, SSIM {}, relative error {}; after a gain/offset fit {} dB (gain {:.3}, offset {:.3e})",
            if q.channel.is_empty() {
                String::new()
            } else {
                format!(" [{}]", q.channel)
            },
            figure(q.psnr_db, 2),
            figure(q.ssim, 3),
            figure(q.relative_error, 4),
            figure(q.psnr_fitted_db, 2),
            q.fit.scale,
            q.fit.offset
        ));
    }
    match report.transport_quality() {
        Some(TransportQuality::Scored {
            transport_relative_error,
            worst_row_relative_error,
            camera_dual_psnr_db,
            camera_dual_ssim,
        }) => lines.push(format!(
            "vs ground truth: T relative error {}, worst camera pixel {}, dual under the whole camera PSNR {} dB, SSIM {}",
            figure(*transport_relative_error, 4),
            figure(*worst_row_relative_error, 4),
            figure(*camera_dual_psnr_db, 2),
            figure(*camera_dual_ssim, 3)
        )),
        Some(TransportQuality::Unavailable { unavailable }) => {
            lines.push(format!("vs ground truth: not scored ({unavailable})"))
        }
        None => {}
    }
    let mut cost = vec![format!("{} iterations", report.recon.iterations)];
    if let Some(s) = report.seconds {
        cost.push(format!("{s:.2} s compute"));
    }
    if let Some(b) = report.peak_memory_bytes {
        cost.push(format!(
            "peak memory {:.1} MiB",
            b as f64 / (1 << 20) as f64
        ));
    }
    lines.push(cost.join(", "));
    lines
}

fn auto_line(channel: &str, c: &AutoChoice) -> String {
    let mut s = String::from("auto");
    if !channel.is_empty() {
        s.push_str(&format!(" [{channel}]"));
    }
    s.push_str(&format!(": model {}", c.model));
    match (c.lambda, c.lambda_fraction) {
        (Some(l), Some(f)) => s.push_str(&format!(", weight {l:.3e} ({f:.3} of lambda_max)")),
        (Some(l), None) => s.push_str(&format!(", weight {l:.3e}")),
        _ => {}
    }
    if let Some(k) = c.kept {
        s.push_str(&format!(", {k} coefficients kept"));
    }
    if let Some(h) = c.held_out {
        s.push_str(&format!(", held-out {h:.4}"));
    }
    if let Some(r) = &c.reason {
        s.push_str(&format!(" ({r})"));
    }
    s
}

/// `auto`'s noise estimate and the error it estimates for its image, when reported.
fn noise_and_error_line(c: &AutoChoice) -> Option<String> {
    let mut parts = Vec::new();
    let noise = &c.extra.get("noise_estimate")?;
    if let Some(sigma) = noise.get("sigma").and_then(Value::as_f64) {
        let se = noise.get("standard_error").and_then(Value::as_f64);
        let source = noise
            .get("source")
            .and_then(Value::as_str)
            .map(|s| s.split(" (").next().unwrap_or(s))
            .unwrap_or("");
        parts.push(match se {
            Some(se) => format!("noise {sigma:.3e} +- {se:.1e} per datum ({source})"),
            None => format!("noise {sigma:.3e} per datum ({source})"),
        });
    }
    let error = c.extra.get("error_estimate");
    if let Some(e) = error
        .and_then(|e| e.get("relative_error"))
        .and_then(Value::as_f64)
    {
        let range = error
            .and_then(|e| e.get("relative_error_range"))
            .and_then(Value::as_array)
            .and_then(|r| Some((r.first()?.as_f64()?, r.get(1)?.as_f64()?)));
        parts.push(match range {
            Some((lo, hi)) => format!("estimated error {e:.3} of the image ({lo:.3} to {hi:.3})"),
            None => format!("estimated error {e:.3} of the image"),
        });
    }
    (!parts.is_empty()).then(|| parts.join(", "))
}

fn figure(f: Figure, decimals: usize) -> String {
    if f.0.is_finite() {
        format!("{:.*}", decimals, f.0)
    } else if f.0 == f64::INFINITY {
        "inf".into()
    } else {
        "n/a".into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn an_auto_report_shows_model_weight_held_out_warnings_and_psnr() {
        let report: Report = serde_json::from_value(json!({
            "method": "auto", "params": {}, "rows_used": 400, "iterations": 1234,
            "details": {"auto": [{
                "model": "db4", "lambda": 0.0123, "lambda_fraction": 0.1, "kept": 310,
                "held_out": 0.0421,
                "warnings": ["too few rows for 64x64: 400 rows predict held-out buckets better at 32x32"],
                "noise_estimate": {"sigma": 1.5, "standard_error": 0.05, "data_spread": 30.0, "rows": 400,
                                   "source": "hadamard pair sums (y+ + y- is the same for every pair but for noise)"},
                "error_estimate": {"relative_error": 0.12, "relative_error_range": [0.1, 0.15], "rms_error": 0.05, "basis": "..."}
            }]},
            "held_out": {"rows": 40, "fraction": 0.1, "relative_residual": 0.0421,
                         "per_channel": [0.0421], "rms_residual": 0.5},
            "quality": [{"channel": "bucket", "psnr_db": 24.5, "ssim": 0.81, "relative_error": 0.12,
                         "psnr_fitted_db": 25.0, "ssim_fitted": 0.82, "fit": {"scale": 0.97, "offset": 0.01}}],
            "seconds": 1.5, "peak_memory_bytes": 3145728
        }))
        .unwrap();
        let text = report_lines(&report).join("\n");
        for want in [
            "auto: model db4, weight 1.230e-2 (0.100 of lambda_max), 310 coefficients kept, held-out 0.0421",
            "warning: too few rows for 64x64",
            "noise 1.500e0 +- 5.0e-2 per datum (hadamard pair sums), estimated error 0.120 of the image (0.100 to 0.150)",
            "held-out error 0.0421 (relative residual on 40 held-out rows",
            "vs ground truth [bucket]: PSNR 24.50 dB, SSIM 0.810",
            "gain 0.970",
            "1234 iterations, 1.50 s compute, peak memory 3.0 MiB",
        ] {
            assert!(text.contains(want), "{want:?} missing from:\n{text}");
        }
    }

    #[test]
    fn a_bernoulli_transport_report_shows_the_relight_bound_when_the_estimate_is_not_resolved() {
        let relight = |e: Value| {
            let report: Report = serde_json::from_value(json!({
                "method": "transport", "params": {}, "rows_used": 64, "iterations": 0,
                "details": {"transform": "haar", "lambda": 0.5, "relight_error_estimate": e},
            }))
            .unwrap();
            report_lines(&report).join("\n")
        };
        let text = relight(json!({"relative": null, "upper": 0.09, "resolved": false}));
        assert!(
            text.contains(
                "error of the full-light relight at most 0.0900 (the data do not resolve more)"
            ),
            "{text}"
        );
        assert!(!text.contains("stored in"), "{text}");
        let text = relight(json!({"relative": 0.031, "upper": 0.05, "resolved": true}));
        assert!(
            text.contains("estimated error of the full-light relight 0.0310 (at most 0.0500)"),
            "{text}"
        );
        let text = relight(
            json!({"relative": 0.0027, "upper": 0.043, "resolved": false, "noise": 0.0027}),
        );
        assert!(
            text.contains(
                "estimated error of the full-light relight 0.0027, what the frames' noise alone makes (at most 0.0430: the held-out frames do not resolve more)"
            ),
            "{text}"
        );
    }

    #[test]
    fn a_transport_report_shows_its_transform_and_t_error_and_an_unavailable_held_out() {
        let report: Report = serde_json::from_value(json!({
            "method": "transport", "params": {}, "rows_used": 64, "iterations": 0,
            "details": {"transform": "identity", "lambda": 0.5,
                        "stored_transform": "haar", "coarse_exact": true,
                        "error_estimate": {"relative": 0.31, "range": [0.2, 0.9]},
                        "relight_error_estimate": {"relative": 0.0042},
                        "warnings": ["the measured pairs cannot support T at 32x32"]},
            "held_out": null, "held_out_unavailable": "complete set: nothing to hold out",
            "quality": {"transport_relative_error": 0.032, "worst_row_relative_error": 0.2,
                        "camera_dual_psnr_db": "inf", "camera_dual_ssim": null}
        }))
        .unwrap();
        let text = report_lines(&report).join("\n");
        for want in [
            "transform identity, weight 5.000e-1, stored in haar (coarse coefficients as measured)",
            "estimated error of T 0.310 (0.200 to 0.900)",
            "estimated error of the full-light relight 0.0042",
            "warning: the measured pairs cannot support T at 32x32",
            "held-out error: unavailable (complete set: nothing to hold out)",
            "T relative error 0.0320, worst camera pixel 0.2000, dual under the whole camera PSNR inf dB, SSIM n/a",
        ] {
            assert!(text.contains(want), "{want:?} missing from:\n{text}");
        }
    }
}
