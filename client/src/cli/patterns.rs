//! `helmholtz patterns`: pattern frames as PNGs for a projector or DMD.

use std::path::PathBuf;

use clap::Args;
use serde_json::json;

use crate::frames;

use super::Outcome;
use super::args::{SpecSource, spec_json, spec_summary};

#[derive(Debug, Clone, Args)]
pub struct PatternsArgs {
    #[command(flatten)]
    pub spec: SpecSource,
    /// First frame index.
    #[arg(long, default_value_t = 0)]
    pub first: u64,
    /// Number of frames to write.
    #[arg(long, default_value_t = 16)]
    pub count: u64,
    /// Output directory (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

pub(super) fn patterns_cmd(a: &PatternsArgs) -> anyhow::Result<Outcome> {
    let spec = a.spec.load()?;
    let paths = frames::write_frames(&spec, a.first, a.count, &a.out)?;
    let text = format!(
        "wrote {} frame(s) {}..{} of {} to {}\n",
        paths.len(),
        a.first,
        a.first + a.count,
        spec_summary(&spec),
        a.out.display()
    );
    Ok(Outcome {
        json: json!({ "spec": spec_json(&spec), "dir": a.out, "frames": paths }),
        text,
    })
}
