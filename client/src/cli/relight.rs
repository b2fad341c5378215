//! `helmholtz relight`, `primal` and `normals`: what a reconstructed transport predicts.

use std::path::PathBuf;

use anyhow::bail;
use clap::Args;

use crate::rest::{self, ImageFormat};

use super::Outcome;
use super::reconstruct::output_format;

#[derive(Debug, Clone, Args)]
#[command(group(clap::ArgGroup::new("light_source").required(true).args(["full", "disc", "stripe", "weights", "light"])))]
pub struct RelightArgs {
    /// Reconstruction id.
    #[arg(long)]
    pub reconstruction: i64,
    /// Every camera pixel lit.
    #[arg(long)]
    pub full: bool,
    /// A disc of camera pixels: centre X,Y and radius R (camera pixel units).
    #[arg(long, value_name = "X,Y,R")]
    pub disc: Option<String>,
    /// Camera columns X0 <= x < X1 lit.
    #[arg(long, value_name = "X0,X1")]
    pub stripe: Option<String>,
    /// Bucket sessions: a weight per detector channel, e.g. n=1,e=0.5.
    #[arg(long, value_name = "NAME=W,...")]
    pub weights: Option<String>,
    /// A camera-sized light image (.png or .npy), sent as it is.
    #[arg(long, value_name = "FILE")]
    pub light: Option<PathBuf>,
    /// Image format of the result [default: from --out's extension, else png].
    #[arg(long, value_enum)]
    pub format: Option<ImageFormat>,
    /// Output file.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

#[derive(Debug, Clone, Args)]
#[command(group(clap::ArgGroup::new("pattern_source").required(true).args(["pattern_index", "pattern"])))]
pub struct PrimalArgs {
    /// Reconstruction id.
    #[arg(long)]
    pub reconstruction: i64,
    /// A measured pattern of the session (0-based): the server also scores the prediction
    /// against the measured frame.
    #[arg(long, value_name = "I")]
    pub pattern_index: Option<u64>,
    /// Any projector-sized pattern image (.png or .npy), sent as it is.
    #[arg(long, value_name = "FILE")]
    pub pattern: Option<PathBuf>,
    /// Image format of the result [default: from --out's extension, else png].
    #[arg(long, value_enum)]
    pub format: Option<ImageFormat>,
    /// Output file.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

#[derive(Debug, Clone, Args)]
pub struct NormalsArgs {
    /// Reconstruction id.
    #[arg(long)]
    pub reconstruction: i64,
    /// png (an RGB normal map) or npy [default: from --out's extension, else png].
    #[arg(long, value_enum)]
    pub format: Option<ImageFormat>,
    /// Output file.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

/// `N` comma-separated numbers of flag `flag`.
fn numbers<const N: usize>(text: &str, flag: &str, form: &str) -> anyhow::Result<[f64; N]> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| anyhow::anyhow!("{flag} {text:?}: expected {form} (numbers)"))?;
    values
        .try_into()
        .map_err(|_| anyhow::anyhow!("{flag} {text:?}: expected {form}"))
}

/// The light `relight` sends, from its flags.
pub fn light_of(a: &RelightArgs) -> anyhow::Result<rest::Light> {
    use rest::Light;
    Ok(if a.full {
        Light::Full
    } else if let Some(d) = &a.disc {
        let [x, y, radius] = numbers::<3>(d, "--disc", "X,Y,R")?;
        Light::Disc { x, y, radius }
    } else if let Some(st) = &a.stripe {
        let [x0, x1] = numbers::<2>(st, "--stripe", "X0,X1")?;
        Light::Stripe { x0, x1 }
    } else if let Some(w) = &a.weights {
        Light::Weights(rest::parse_weights(w)?)
    } else if let Some(path) = &a.light {
        Light::Image(path.clone())
    } else {
        bail!("give one of --full, --disc, --stripe, --weights or --light")
    })
}

/// The pattern `primal` sends, from its flags.
pub fn pattern_of(a: &PrimalArgs) -> anyhow::Result<rest::PatternInput> {
    match (a.pattern_index, &a.pattern) {
        (Some(i), _) => Ok(rest::PatternInput::Index(i)),
        (None, Some(path)) => Ok(rest::PatternInput::Image(path.clone())),
        (None, None) => bail!("give --pattern-index I or --pattern FILE"),
    }
}

fn saved_text(report: &rest::ImageReport) -> String {
    format!(
        "saved {} ({} bytes{})\n",
        report.path.display(),
        report.bytes,
        report
            .content_type
            .as_deref()
            .map(|c| format!(", {c}"))
            .unwrap_or_default()
    )
}

pub(super) async fn relight_cmd(server: &str, a: &RelightArgs) -> anyhow::Result<Outcome> {
    let light = light_of(a)?;
    let format = output_format(a.format, &a.out);
    let report = rest::relight(server, a.reconstruction, &light, format, &a.out).await?;
    Ok(Outcome {
        text: saved_text(&report),
        json: serde_json::to_value(&report)?,
    })
}

pub(super) async fn primal_cmd(server: &str, a: &PrimalArgs) -> anyhow::Result<Outcome> {
    let pattern = pattern_of(a)?;
    let format = output_format(a.format, &a.out);
    let report = rest::primal(server, a.reconstruction, &pattern, format, &a.out).await?;
    let mut text = saved_text(&report);
    if report.relative_error.is_some() || report.psnr_db.is_some() {
        let show = |v: Option<f64>, unit: &str| {
            v.map(|v| format!("{v:.6}{unit}"))
                .unwrap_or_else(|| "?".to_string())
        };
        text.push_str(&format!(
            "prediction vs the measured frame: relative error {}, PSNR {}\n",
            show(report.relative_error, ""),
            show(report.psnr_db, " dB")
        ));
    }
    Ok(Outcome {
        text,
        json: serde_json::to_value(&report)?,
    })
}

pub(super) async fn normals_cmd(server: &str, a: &NormalsArgs) -> anyhow::Result<Outcome> {
    let format = output_format(a.format, &a.out);
    let report = rest::normals(server, a.reconstruction, format, &a.out).await?;
    Ok(Outcome {
        text: saved_text(&report),
        json: serde_json::to_value(&report)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::{Cli, Command, parse};
    use clap::Parser;

    #[test]
    fn relight_primal_normals_cancel_flags() {
        let light = |args: &[&str]| {
            let mut all = vec!["relight", "--reconstruction", "4", "--out", "r.png"];
            all.extend_from_slice(args);
            let Command::Relight(a) = parse(&all).command else {
                panic!("not relight")
            };
            light_of(&a)
        };
        use rest::Light;
        assert_eq!(light(&["--full"]).unwrap(), Light::Full);
        assert_eq!(
            light(&["--disc", "10,12.5,3"]).unwrap(),
            Light::Disc {
                x: 10.0,
                y: 12.5,
                radius: 3.0
            }
        );
        assert_eq!(
            light(&["--stripe", "0,8"]).unwrap(),
            Light::Stripe { x0: 0.0, x1: 8.0 }
        );
        assert_eq!(
            light(&["--weights", "n=1,e=0.5"]).unwrap(),
            Light::Weights(vec![("n".into(), 1.0), ("e".into(), 0.5)])
        );
        assert_eq!(
            light(&["--light", "l.npy"]).unwrap(),
            Light::Image("l.npy".into())
        );
        assert!(
            light(&["--disc", "1,2"])
                .unwrap_err()
                .to_string()
                .contains("X,Y,R")
        );
        assert!(light(&["--stripe", "a,b"]).is_err());
        // Exactly one light.
        for args in [
            vec!["relight", "--reconstruction", "4", "--out", "r.png"],
            vec![
                "relight",
                "--reconstruction",
                "4",
                "--out",
                "r.png",
                "--full",
                "--stripe",
                "0,1",
            ],
        ] {
            assert!(Cli::try_parse_from(std::iter::once("helmholtz").chain(args)).is_err());
        }
        let Command::Primal(a) = parse(&[
            "primal",
            "--reconstruction",
            "2",
            "--pattern-index",
            "7",
            "--out",
            "p.tiff",
        ])
        .command
        else {
            panic!()
        };
        assert_eq!(pattern_of(&a).unwrap(), rest::PatternInput::Index(7));
        assert_eq!(output_format(a.format, &a.out), ImageFormat::Tiff);
        assert!(
            Cli::try_parse_from([
                "helmholtz",
                "primal",
                "--reconstruction",
                "2",
                "--out",
                "p.png"
            ])
            .is_err()
        );
        assert!(
            Cli::try_parse_from([
                "helmholtz",
                "primal",
                "--reconstruction",
                "2",
                "--pattern-index",
                "1",
                "--pattern",
                "x.png",
                "--out",
                "p.png"
            ])
            .is_err()
        );
        let Command::Normals(a) =
            parse(&["normals", "--reconstruction", "3", "--out", "n.npy"]).command
        else {
            panic!()
        };
        assert_eq!(output_format(a.format, &a.out), ImageFormat::Npy);
        let Command::Cancel(a) = parse(&["cancel", "--reconstruction", "9"]).command else {
            panic!()
        };
        assert_eq!(a.reconstruction, 9);
    }
}
