//! `helmholtz preview`: watch a session's live preview while it uploads (gRPC `WatchPreview`).

use std::io::Write;
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use serde_json::json;

use crate::preview::{PreviewOptions, watch_preview};

use super::Outcome;

#[derive(Debug, Clone, Args)]
pub struct PreviewArgs {
    /// Session to watch.
    #[arg(long = "session-id", alias = "session", value_name = "ID")]
    pub session_id: String,
    /// Bucket sessions: the detector channel by name or index [default: the first]. Camera
    /// sessions are previewed as the sum over their pixels: leave it out.
    #[arg(long)]
    pub channel: Option<String>,
    /// A frame every this many new rows [default: no row trigger].
    #[arg(long, default_value_t = 0)]
    pub every_rows: u64,
    /// A frame every this many milliseconds while rows arrive (50-600000) [default: 500 when
    /// --every-rows is not given].
    #[arg(long, default_value_t = 0)]
    pub every_ms: u32,
    /// Write the last frame's image: .npy (float32, height x width) or .png (8-bit, min to max).
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
}

/// One line per frame as it arrives (unless `json`), then the last frame's summary.
pub async fn preview_cmd(
    server: &str,
    a: &PreviewArgs,
    json_mode: bool,
) -> anyhow::Result<Outcome> {
    if let Some(out) = &a.out {
        let ext = out.extension().and_then(|e| e.to_str()).unwrap_or("");
        if !matches!(ext, "npy" | "png") {
            bail!("--out {}: write a .npy or .png file", out.display());
        }
    }
    let options = PreviewOptions {
        channel: a.channel.clone().unwrap_or_default(),
        every_rows: a.every_rows,
        every_ms: a.every_ms,
    };
    let mut frames = watch_preview(server, &a.session_id, &options).await?;
    let mut count = 0u64;
    let mut last = None;
    while let Some(frame) = frames
        .message()
        .await
        .map_err(|s| anyhow::anyhow!("{}: {}", s.code(), s.message()))
        .context("the preview stream")?
    {
        count += 1;
        if !json_mode {
            let (lo, hi) = frame
                .values
                .iter()
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
                    (lo.min(v), hi.max(v))
                });
            let _ = writeln!(
                std::io::stdout(),
                "rows {}/{} ({:.0} %)  {} {}x{} channel {}  min {lo:.4e} max {hi:.4e}{}",
                frame.rows,
                frame.expected_rows,
                100.0 * frame.rows as f64 / frame.expected_rows.max(1) as f64,
                frame.method,
                frame.width,
                frame.height,
                frame.channel,
                if frame.r#final { "  final" } else { "" }
            );
        }
        let done = frame.r#final;
        last = Some(frame);
        if done {
            break;
        }
    }
    let Some(frame) = last else {
        bail!(
            "the server ended the preview of {} without a frame",
            a.session_id
        );
    };
    if !frame.r#final {
        bail!(
            "the preview of {} ended at row {} of {} without its final frame",
            a.session_id,
            frame.rows,
            frame.expected_rows
        );
    }
    if let Some(out) = &a.out {
        let bytes = if out.extension().is_some_and(|e| e == "npy") {
            helmholtz_proto::npy::write_f32(
                &[frame.height as u64, frame.width as u64],
                &frame.values,
            )
        } else {
            let (lo, hi) = frame
                .values
                .iter()
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
                    (lo.min(v), hi.max(v))
                });
            let span = if hi > lo { hi - lo } else { 1.0 };
            let grey: Vec<u8> = frame
                .values
                .iter()
                .map(|&v| ((v - lo) / span * 255.0).round() as u8)
                .collect();
            helmholtz_proto::png::encode_grey8(frame.width, frame.height, &grey)?
        };
        std::fs::write(out, bytes).with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(Outcome {
        json: json!({
            "session_id": frame.session_id,
            "channel": frame.channel,
            "frames": count,
            "rows": frame.rows,
            "expected_rows": frame.expected_rows,
            "method": frame.method,
            "width": frame.width,
            "height": frame.height,
            "final": frame.r#final,
            "out": a.out.as_ref().map(|p| p.display().to_string()),
        }),
        text: format!(
            "session {}: {} frames, final image of {} rows ({}){}",
            frame.session_id,
            count,
            frame.rows,
            frame.method,
            a.out
                .as_ref()
                .map(|p| format!(", written to {}", p.display()))
                .unwrap_or_default()
        ),
    })
}
