//! `helmholtz reconstruct`, `cancel`, `status` and `fetch`: reconstructions and their images.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::bail;
use clap::Args;
use serde_json::{Value, json};

use crate::rest::{self, FetchTarget, ImageFormat, Reconstruction};
use crate::upload;

use super::Outcome;
use super::args::{ResultArgs, parse_params};

#[derive(Debug, Clone, Args)]
pub struct StatusArgs {
    /// Session to show; omit to list all sessions.
    #[arg(long = "session-id", value_name = "ID")]
    pub session_id: Option<String>,
    /// The session as a bare argument (the older form of --session-id).
    #[arg(value_name = "SESSION_ID", hide = true, conflicts_with = "session_id")]
    pub session_arg: Option<String>,
}

impl StatusArgs {
    /// The session asked for, by either form.
    pub fn session(&self) -> Option<&str> {
        self.session_id.as_deref().or(self.session_arg.as_deref())
    }
}

#[derive(Debug, Clone, Args)]
pub struct FetchArgs {
    /// Reconstruction id.
    #[arg(long, required_unless_present = "session", conflicts_with = "session")]
    pub reconstruction: Option<i64>,
    /// Session id: its latest finished reconstruction (`--session` is accepted too).
    #[arg(long = "session-id", alias = "session", value_name = "ID")]
    pub session: Option<String>,
    /// Image format [default: from --out's extension, else png].
    #[arg(long, value_enum)]
    pub format: Option<ImageFormat>,
    /// Detector channel [default: the server's default].
    #[arg(long)]
    pub channel: Option<String>,
    /// Output file.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

#[derive(Debug, Clone, Args)]
pub struct ReconstructArgs {
    /// Session to reconstruct.
    #[arg(long)]
    pub session_id: String,
    /// Method: gi (correlation), dgi (differential), ngi (normalised), direct (complete
    /// Hadamard/raster inverse), zero_filled / levels (Hadamard subsets), lsq, cs, tv, auto
    /// (the data choose the model by held-out error), or transport (camera sessions: the light
    /// transport matrix T, for relight and primal). Parameters: --params.
    #[arg(long)]
    pub method: String,
    #[command(flatten)]
    pub result: ResultArgs,
}

#[derive(Debug, Clone, Args)]
pub struct CancelArgs {
    /// Reconstruction id.
    #[arg(long)]
    pub reconstruction: i64,
}

fn recon_text(r: &Reconstruction) -> String {
    let mut s = format!(
        "reconstruction {} ({}) of session {}: {}",
        r.id, r.method, r.session_id, r.state
    );
    if r.is_terminal() {
        s.push_str(&format!(
            ", {} rows, {:.2} s",
            r.rows,
            r.seconds.unwrap_or(0.0)
        ));
    } else {
        s.push_str(&format!(" ({:.0}%)", r.progress * 100.0));
    }
    if let Some(e) = &r.error {
        s.push_str(&format!("\n  error: {e}"));
    }
    if let Some(report) = &r.report {
        for line in super::report::report_lines(report) {
            s.push_str("\n  ");
            s.push_str(&line);
        }
    }
    s.push('\n');
    s
}

fn timeout_of(secs: f64) -> anyhow::Result<Duration> {
    anyhow::ensure!(
        secs >= 0.0 && secs.is_finite(),
        "--timeout must be >= 0 seconds"
    );
    Ok(Duration::from_secs_f64(secs))
}

pub(super) fn output_format(format: Option<ImageFormat>, out: &Path) -> ImageFormat {
    format
        .or_else(|| ImageFormat::from_path(out))
        .unwrap_or(ImageFormat::Png)
}

/// After a reconstruction was requested: wait and save as the flags say.
pub(super) async fn finish_reconstruction(
    server: &str,
    rec: Reconstruction,
    result: &ResultArgs,
    progress: bool,
    json_out: &mut serde_json::Map<String, Value>,
    text: &mut String,
) -> anyhow::Result<()> {
    let rec = if result.wait || result.out.is_some() {
        let rec =
            rest::wait_reconstruction_with(server, rec.id, timeout_of(result.timeout)?, progress)
                .await?;
        if !rec.is_done() {
            json_out.insert("reconstruction".into(), serde_json::to_value(&rec)?);
            bail!(
                "reconstruction {} {}: {}",
                rec.id,
                rec.state,
                rec.error.as_deref().unwrap_or("no error message")
            );
        }
        rec
    } else {
        rec
    };
    text.push_str(&recon_text(&rec));
    json_out.insert("reconstruction".into(), serde_json::to_value(&rec)?);
    if let Some(out) = &result.out {
        let format = output_format(result.format, out);
        let report = rest::fetch(
            server,
            &FetchTarget::Reconstruction(rec.id),
            format,
            result.channel.as_deref(),
            out,
        )
        .await?;
        text.push_str(&format!(
            "saved {} ({} bytes)\n",
            out.display(),
            report.bytes
        ));
        json_out.insert("saved".into(), serde_json::to_value(&report)?);
    }
    Ok(())
}

pub(super) async fn status_cmd(server: &str, a: &StatusArgs) -> anyhow::Result<Outcome> {
    match a.session() {
        None => {
            let sessions = rest::list_sessions(server).await?;
            let mut text = if sessions.is_empty() {
                "no sessions\n".to_string()
            } else {
                String::new()
            };
            for s in &sessions {
                text.push_str(&format!(
                    "{:<32} {:<8} {:>9}/{:<9} rows  {}{}\n",
                    s.id,
                    s.state,
                    s.committed_rows,
                    s.expected_rows,
                    s.patterns.family().name(),
                    s.latest_reconstruction
                        .map(|r| format!("  latest reconstruction {r}"))
                        .unwrap_or_default()
                ));
            }
            Ok(Outcome {
                json: json!({ "sessions": sessions }),
                text,
            })
        }
        Some(id) => {
            let s = rest::get_session(server, id).await?;
            let mut text = format!(
                "session {} ({}): {}, {}/{} rows committed ({:.1}%)\n  rig {:?}, channels {}, ground truth: {}\n  patterns {}\n",
                s.id,
                s.state,
                if s.state == helmholtz_proto::rest::SessionState::Finished {
                    "finished"
                } else {
                    "accepting rows"
                },
                s.committed_rows,
                s.expected_rows,
                if s.expected_rows > 0 {
                    100.0 * s.committed_rows as f64 / s.expected_rows as f64
                } else {
                    0.0
                },
                s.rig,
                s.channels.join(","),
                if s.has_ground_truth { "yes" } else { "no" },
                serde_json::to_value(&s.patterns)?
            );
            let mut out = json!({ "session": s });
            if let Some(rid) = s.latest_reconstruction {
                let r = rest::get_reconstruction(server, rid).await?;
                text.push_str("latest ");
                text.push_str(&recon_text(&r));
                out["latest_reconstruction"] = serde_json::to_value(&r)?;
            } else {
                text.push_str("no reconstructions yet\n");
            }
            Ok(Outcome { json: out, text })
        }
    }
}

pub(super) async fn fetch_cmd(server: &str, a: &FetchArgs) -> anyhow::Result<Outcome> {
    let target = match (&a.reconstruction, &a.session) {
        (Some(id), _) => FetchTarget::Reconstruction(*id),
        (None, Some(s)) => FetchTarget::Session(s.clone()),
        (None, None) => bail!("give --reconstruction ID or --session ID"),
    };
    let format = output_format(a.format, &a.out);
    let report = rest::fetch(server, &target, format, a.channel.as_deref(), &a.out).await?;
    let text = format!(
        "saved {} ({} bytes, {})\n",
        report.path.display(),
        report.bytes,
        format.extension()
    );
    Ok(Outcome {
        json: serde_json::to_value(&report)?,
        text,
    })
}

pub(super) async fn reconstruct_cmd(
    server: &str,
    a: &ReconstructArgs,
    progress: bool,
) -> anyhow::Result<Outcome> {
    let params = parse_params(a.result.params.as_deref())?;
    let rec = upload::request_reconstruction(server, &a.session_id, &a.method, &params).await?;
    let mut out = serde_json::Map::new();
    let mut text = String::new();
    finish_reconstruction(server, rec, &a.result, progress, &mut out, &mut text).await?;
    Ok(Outcome {
        json: Value::Object(out),
        text,
    })
}

pub(super) async fn cancel_cmd(server: &str, a: &CancelArgs) -> anyhow::Result<Outcome> {
    let rec = rest::cancel_reconstruction(server, a.reconstruction).await?;
    Ok(Outcome {
        text: recon_text(&rec),
        json: serde_json::to_value(&rec)?,
    })
}

#[cfg(test)]
mod tests {
    use crate::cli::{Cli, parse};
    use clap::Parser;

    #[test]
    fn fetch_needs_exactly_one_target() {
        assert!(Cli::try_parse_from(["helmholtz", "fetch", "--out", "x.png"]).is_err());
        assert!(
            Cli::try_parse_from([
                "helmholtz",
                "fetch",
                "--reconstruction",
                "1",
                "--session",
                "s",
                "--out",
                "x.png"
            ])
            .is_err()
        );
        let cli = parse(&[
            "fetch",
            "--session",
            "s",
            "--out",
            "x.tiff",
            "--server",
            "http://h:1",
        ]);
        assert_eq!(cli.server, "http://h:1");
    }
}
