//! `helmholtz upload`: a real rig's measurements from a CSV or NPY file.

use std::path::{Path, PathBuf};

use anyhow::bail;
use clap::Args;
use helmholtz_proto::PatternSpec;
use serde_json::json;

use crate::measurements::{self, Measurements};
use crate::spool::SpoolDir;
use crate::upload::{self, NewSession};

use super::Outcome;
use super::args::{SpecSource, TransferArgs, parse_metadata, spec_json, spec_summary};
use super::spool::{spool_and_upload, spool_and_upload_rows, upload_text};

#[derive(Debug, Clone, Args)]
pub struct UploadArgs {
    /// Session id (1-128 of A-Z a-z 0-9 . _ -). Created if new; re-running resumes.
    #[arg(long)]
    pub session_id: String,
    #[command(flatten)]
    pub spec: SpecSource,
    /// Measurements: CSV (one row per pattern, one column per channel, optional header of
    /// channel names, '#' comments) or NPY (shape (n,) or (n, channels); float or int). A camera
    /// rig's frames: NPY of shape (n, height, width), uint16 or float32, which makes a camera
    /// session (frames are read from the file batch by batch, never all at once).
    #[arg(long, value_name = "FILE")]
    pub values: PathBuf,
    /// Channel names, comma separated [default: the CSV header, else "bucket" for one column,
    /// else ch0,ch1,...].
    #[arg(long, value_delimiter = ',')]
    pub channels: Vec<String>,
    /// Rig name recorded with the session.
    #[arg(long, default_value = "rig")]
    pub rig: String,
    /// Extra session metadata, KEY=VALUE (repeatable).
    #[arg(long = "metadata", value_name = "KEY=VALUE")]
    pub metadata: Vec<String>,
    /// Finish the session after the upload (all rows of the spec must then be committed).
    #[arg(long)]
    pub finish: bool,
    /// Accept a file with fewer rows than the spec's count (upload a prefix, continue later).
    #[arg(long)]
    pub partial: bool,
    /// Rows per spool write: each batch is fsync'ed before it counts as measured.
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u64).range(1..))]
    pub batch_rows: u64,
    #[command(flatten)]
    pub transfer: TransferArgs,
}

fn channel_names(given: &[String], m: &Measurements) -> anyhow::Result<Vec<String>> {
    let names = if !given.is_empty() {
        given.to_vec()
    } else if let Some(header) = &m.names {
        header.clone()
    } else if m.channels == 1 {
        vec!["bucket".to_string()]
    } else {
        (0..m.channels).map(|c| format!("ch{c}")).collect()
    };
    anyhow::ensure!(
        names.len() == m.channels,
        "--channels names {} channel(s) ({}) but the file has {} column(s)",
        names.len(),
        names.join(","),
        m.channels
    );
    Ok(names)
}

/// Checks the file's rows against the spec: same count (or fewer with `partial`).
pub fn check_rows(
    file: &Path,
    rows: usize,
    spec: &PatternSpec,
    partial: bool,
) -> anyhow::Result<()> {
    let expected = spec.count();
    if rows as u64 > expected || (!partial && (rows as u64) < expected) {
        bail!(
            "{}: {rows} rows, but the spec declares {expected} patterns (one row per pattern){}",
            file.display(),
            if (rows as u64) < expected {
                "; pass --partial to upload a prefix"
            } else {
                ""
            }
        );
    }
    Ok(())
}

pub(super) async fn upload_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &UploadArgs,
    progress: bool,
) -> anyhow::Result<Outcome> {
    anyhow::ensure!(
        upload::valid_session_id(&a.session_id),
        "--session-id {:?}: use 1-128 of A-Z a-z 0-9 . _ -",
        a.session_id
    );
    let spec = a.spec.load()?;
    if let Some(frames) = measurements::npy_frames(&a.values)? {
        return upload_frames_cmd(server, spools, a, progress, spec, frames).await;
    }
    let m = measurements::read_measurements(&a.values)?;
    let names = channel_names(&a.channels, &m)?;
    check_rows(&a.values, m.rows, &spec, a.partial)?;
    let mut session =
        NewSession::new(a.session_id.clone(), spec.clone(), names.clone()).with_rig(a.rig.clone());
    session.metadata = parse_metadata(&a.metadata)?;
    let opts = a.transfer.options(progress)?;
    let mut text = format!(
        "session {} ({}; channels {})\n",
        a.session_id,
        spec_summary(&spec),
        names.join(",")
    );
    let (report, spooled_before) = spool_and_upload(
        server,
        spools,
        &session,
        a.finish,
        &m.values,
        a.batch_rows,
        None,
        &opts,
    )
    .await?;
    text.push_str(&upload_text(&report, spooled_before));
    if a.finish {
        anyhow::ensure!(
            report.finished,
            "session {}: {} of {} rows committed, so it cannot be finished",
            a.session_id,
            report.committed_rows,
            report.expected_rows
        );
        text.push_str(&format!(
            "session finished with {} rows\n",
            report.committed_rows
        ));
    }
    let out = json!({
        "session_id": a.session_id,
        "spec": spec_json(&spec),
        "channels": names,
        "file": a.values,
        "spooled_before": spooled_before,
        "upload": report,
        "finished": report.finished,
    });
    Ok(Outcome { json: out, text })
}

/// `helmholtz upload` of a camera rig's frames (a 3-D NPY file): a camera session, spooled and
/// uploaded batch by batch straight from the file.
async fn upload_frames_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &UploadArgs,
    progress: bool,
    spec: PatternSpec,
    frames: measurements::NpyFrames,
) -> anyhow::Result<Outcome> {
    anyhow::ensure!(
        a.channels.is_empty(),
        "--channels does not apply to camera frames ({} is an NPY of shape ({}, {}, {}))",
        a.values.display(),
        frames.rows,
        frames.height,
        frames.width
    );
    check_rows(&a.values, frames.rows as usize, &spec, a.partial)?;
    let mut session = NewSession::camera(
        a.session_id.clone(),
        spec.clone(),
        frames.width,
        frames.height,
        frames.format,
    )
    .with_rig(a.rig.clone());
    session.metadata = parse_metadata(&a.metadata)?;
    session.validate()?;
    let opts = a.transfer.options(progress)?;
    let rows = |start: u64, end: u64| frames.read(start, end);
    let (report, spooled_before) = spool_and_upload_rows(
        server,
        spools,
        &session,
        a.finish,
        frames.rows,
        &rows,
        a.batch_rows,
        None,
        &opts,
    )
    .await?;
    let mut text = format!(
        "session {} ({}; camera {}x{} {:?} frames)\n",
        a.session_id,
        spec_summary(&spec),
        frames.width,
        frames.height,
        frames.format
    );
    text.push_str(&upload_text(&report, spooled_before));
    if a.finish {
        anyhow::ensure!(
            report.finished,
            "session {}: {} of {} rows committed, so it cannot be finished",
            a.session_id,
            report.committed_rows,
            report.expected_rows
        );
        text.push_str(&format!(
            "session finished with {} frames\n",
            report.committed_rows
        ));
    }
    let out = json!({
        "session_id": a.session_id,
        "spec": spec_json(&spec),
        "camera": {"width": frames.width, "height": frames.height},
        "file": a.values,
        "spooled_before": spooled_before,
        "upload": report,
        "finished": report.finished,
    });
    Ok(Outcome { json: out, text })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn row_count_checks_name_the_file() {
        let spec: PatternSpec =
            serde_json::from_str(r#"{"family":"raster","width":4,"height":4,"count":16}"#).unwrap();
        let f = Path::new("run7.csv");
        assert!(check_rows(f, 16, &spec, false).is_ok());
        let e = check_rows(f, 15, &spec, false).unwrap_err().to_string();
        assert!(
            e.contains("run7.csv")
                && e.contains("15 rows")
                && e.contains("16 patterns")
                && e.contains("--partial"),
            "{e}"
        );
        assert!(check_rows(f, 15, &spec, true).is_ok());
        assert!(check_rows(f, 17, &spec, true).is_err());
    }

    #[test]
    fn channel_names_follow_header_or_flags() {
        let m = Measurements {
            rows: 1,
            channels: 2,
            names: Some(vec!["n".into(), "s".into()]),
            values: vec![1.0, 2.0],
        };
        assert_eq!(channel_names(&[], &m).unwrap(), ["n", "s"]);
        assert_eq!(
            channel_names(&["a".into(), "b".into()], &m).unwrap(),
            ["a", "b"]
        );
        assert!(channel_names(&["a".into()], &m).is_err());
        let m = Measurements { names: None, ..m };
        assert_eq!(channel_names(&[], &m).unwrap(), ["ch0", "ch1"]);
    }
}
