//! `helmholtz patterns`: pattern frames for a projector or DMD, as PNGs or one NPY stack.

use std::path::PathBuf;

use clap::Args;
use serde_json::json;

use crate::frames;

use super::Outcome;
use super::args::{SpecSource, spec_json, spec_summary};

#[derive(Debug, Clone, Args)]
#[command(group(clap::ArgGroup::new("output").args(["out", "npy"]).required(true).multiple(true)))]
pub struct PatternsArgs {
    #[command(flatten)]
    pub spec: SpecSource,
    /// First frame index.
    #[arg(long, default_value_t = 0)]
    pub first: u64,
    /// Number of frames to write [default: every frame from --first to the spec's end].
    #[arg(long)]
    pub count: Option<u64>,
    /// Write each frame as an 8-bit grey PNG (frame_000000.png, ...) into this directory
    /// (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Write the frames as one NPY stack: float32 (count, height, width), the exact pattern
    /// values (0/1, or speckle levels in [0, 1]).
    #[arg(long, value_name = "FILE")]
    pub npy: Option<PathBuf>,
}

pub(super) fn patterns_cmd(a: &PatternsArgs) -> anyhow::Result<Outcome> {
    let spec = a.spec.load()?;
    let count = match a.count {
        Some(c) => c,
        None => spec.count().checked_sub(a.first).ok_or_else(|| {
            anyhow::anyhow!(
                "--first {} is past the spec's {} patterns",
                a.first,
                spec.count()
            )
        })?,
    };
    let outputs = a.out.is_some() as u64 + a.npy.is_some() as u64;
    let bar = frames_bar(count * outputs);
    let progress = |n: u64| bar.inc(n);
    let mut text = String::new();
    let mut json = json!({ "spec": spec_json(&spec), "first": a.first, "count": count });
    if let Some(dir) = &a.out {
        let paths = frames::write_frames(&spec, a.first, count, dir, &progress)?;
        text.push_str(&format!(
            "wrote {} frame(s) {}..{} of {} to {}\n",
            paths.len(),
            a.first,
            a.first + count,
            spec_summary(&spec),
            dir.display()
        ));
        json["dir"] = json!(dir);
        json["frames"] = json!(paths);
    }
    if let Some(path) = &a.npy {
        frames::write_npy_stack(&spec, a.first, count, path, &progress)?;
        text.push_str(&format!(
            "wrote frames {}..{} of {} to {} (float32, {count} x {} x {})\n",
            a.first,
            a.first + count,
            spec_summary(&spec),
            path.display(),
            spec.height(),
            spec.width()
        ));
        json["npy"] = json!(path);
    }
    bar.finish_and_clear();
    Ok(Outcome { json, text })
}

/// A frames progress bar on stderr, shown only when stderr is a terminal.
fn frames_bar(len: u64) -> indicatif::ProgressBar {
    use std::io::IsTerminal;
    if !std::io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{prefix:>10} [{bar:40.cyan/blue}] {human_pos}/{human_len} frames {per_sec} eta {eta}",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    bar.set_prefix("writing");
    bar
}
