//! Measured rows through the local spool (`spool_and_upload`), and `helmholtz spool status` /
//! `helmholtz spool upload`.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::{Args, Subcommand};
use serde_json::json;

use crate::spool::{self, DrainReport, SpoolDir};
use crate::upload::{NewSession, SampleBuf, UploadOptions};

use super::Outcome;
use super::args::TransferArgs;

#[derive(Debug, Subcommand)]
pub enum SpoolCommand {
    /// Per spooled session: rows spooled, rows the server has committed (if reachable), rows
    /// pending, whether the producer finished, and the last upload error.
    Status(SpoolStatusArgs),
    /// Upload what is pending (every spooled session, or those named): rows not yet confirmed
    /// are sent and the server compares any it already holds byte for byte; then exit. Fully
    /// uploaded (and finished) sessions leave the spool; refused rows stay in it.
    Upload(SpoolUploadArgs),
}

#[derive(Debug, Clone, Args)]
pub struct SpoolStatusArgs {
    /// Sessions to show [default: every session in the spool].
    pub session_ids: Vec<String>,
}

#[derive(Debug, Clone, Args)]
pub struct SpoolUploadArgs {
    /// Sessions to upload [default: every session in the spool].
    pub session_ids: Vec<String>,
    #[command(flatten)]
    pub transfer: TransferArgs,
}

pub(super) fn upload_text(r: &DrainReport, spooled_before: u64) -> String {
    let mut s = format!(
        "spooled {} rows of session {} ({} were spooled by an earlier run); uploaded in {:.2} s: {} rows sent",
        r.spooled_rows, r.session_id, spooled_before, r.seconds, r.rows_sent
    );
    if r.resumes > 0 {
        s.push_str(&format!(", resumed {} time(s)", r.resumes));
    }
    s.push_str(&format!(
        "; server has {}/{} rows{}\n",
        r.committed_rows,
        r.expected_rows,
        if r.removed { "; spool cleared" } else { "" }
    ));
    s
}

/// Rows `start..end` of a session, made on demand (from memory, or rendered by a simulator).
pub type RowsFn<'a> = dyn Fn(u64, u64) -> anyhow::Result<SampleBuf> + Sync + 'a;

/// Spool writes of camera frames hold at most this many bytes (whatever --batch-rows says).
pub(super) const MAX_BATCH_BYTES: usize = 8 << 20;

/// Spools `values` (rows x channels, every row of the session from row 0) for `session` and
/// uploads them; see [`spool_and_upload_rows`].
#[allow(clippy::too_many_arguments)]
pub(super) async fn spool_and_upload(
    server: &str,
    spools: &SpoolDir,
    session: &NewSession,
    finish: bool,
    values: &[f64],
    batch_rows: u64,
    frame_rate: Option<f64>,
    opts: &UploadOptions,
) -> anyhow::Result<(DrainReport, u64)> {
    let ch = session.channel_count() as usize;
    let total = (values.len() / ch.max(1)) as u64;
    let rows = |start: u64, end: u64| {
        Ok(SampleBuf::F64(
            values[start as usize * ch..end as usize * ch].to_vec(),
        ))
    };
    spool_and_upload_rows(
        server, spools, session, finish, total, &rows, batch_rows, frame_rate, opts,
    )
    .await
}

/// Spools rows `0..total` of `session` (made by `rows`, in the session's sample format) and
/// uploads them: rows an earlier run already spooled are checked to be the same (byte for byte)
/// and not written again; a background task drains the spool as batches of `batch_rows` land
/// (camera frames: at most 8 MiB a batch), paced at `frame_rate` rows per second if given.
/// Returns the drain report and the rows spooled before.
#[allow(clippy::too_many_arguments)]
pub(super) async fn spool_and_upload_rows(
    server: &str,
    spools: &SpoolDir,
    session: &NewSession,
    finish: bool,
    total: u64,
    rows: &RowsFn<'_>,
    batch_rows: u64,
    frame_rate: Option<f64>,
    opts: &UploadOptions,
) -> anyhow::Result<(DrainReport, u64)> {
    let id = &session.session_id;
    let spool = Arc::new(spools.create_or_open(session, finish)?);
    let row_bytes = spool.manifest().row_bytes();
    let have = spool.rows();
    anyhow::ensure!(
        have <= total,
        "the spool {} already holds {have} rows of session {id}, more than the {total} given now",
        spool.dir().display()
    );
    // The rows an earlier run spooled must be the ones given now.
    let base = spool.base_row();
    let step = (MAX_BATCH_BYTES / row_bytes).max(1) as u64;
    let mut row = base;
    while row < have {
        let end = (row + step).min(have);
        let held = spool.read_bytes(row, end)?;
        let given = rows(row, end)?.as_samples().encode();
        if let Some(i) = held.iter().zip(&given).position(|(a, b)| a != b) {
            bail!(
                "the spool {} holds different values for row {} of session {id} than the ones given now; \
                 upload the spooled session first (`helmholtz spool upload {id}`) or use another session id",
                spool.dir().display(),
                row + (i / row_bytes) as u64
            );
        }
        row = end;
    }
    if have < total {
        spool.unseal()?;
    }
    let batch_rows = if session.camera.is_some() {
        batch_rows.clamp(1, step)
    } else {
        batch_rows.max(1)
    };
    let drainer = tokio::spawn({
        let (spool, server, opts) = (spool.clone(), server.to_string(), opts.clone());
        async move { spool::drain(&server, spool, &opts, true).await }
    });
    let produce = async {
        let started = Instant::now();
        let mut next = have;
        while next < total {
            let end = (next + batch_rows).min(total);
            if let Some(rate) = frame_rate {
                // The batch is complete when its last pattern has been shown.
                let due = started + Duration::from_secs_f64((end - have) as f64 / rate);
                tokio::time::sleep_until(due.into()).await;
            }
            let batch = rows(next, end)?;
            let s = spool.clone();
            tokio::task::spawn_blocking(move || s.append_samples(batch.as_samples()))
                .await
                .context("spool writer panicked")??;
            next = end;
        }
        spool.seal()
    };
    if let Err(e) = produce.await {
        drainer.abort();
        return Err(e.context(format!(
            "spooling session {id} stopped at row {}; the rows spooled so far stay in {}",
            spool.rows(),
            spool.dir().display()
        )));
    }
    let report = drainer.await.context("upload task panicked")??;
    Ok((report, have))
}

/// One session's line of `helmholtz spool status`.
#[derive(Debug, serde::Serialize)]
struct SpoolEntry {
    session_id: String,
    #[serde(flatten)]
    info: Option<spool::SpoolInfo>,
    /// The server's committed count now (None if unreachable).
    committed_rows: Option<u64>,
    /// Spooled rows not yet confirmed stored on the server with the spool's bytes.
    pending_rows: Option<u64>,
    /// spooling (another process is writing or uploading it), pending, incomplete (its producer
    /// stopped before every row was measured), uploaded (every spooled row committed).
    status: String,
    server_error: Option<String>,
    error: Option<String>,
}

fn spool_ids(spools: &SpoolDir, given: &[String]) -> anyhow::Result<Vec<String>> {
    if given.is_empty() {
        spools.sessions()
    } else {
        Ok(given.to_vec())
    }
}

pub(super) async fn spool_status_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &SpoolStatusArgs,
) -> anyhow::Result<Outcome> {
    let mut entries = Vec::new();
    for id in spool_ids(spools, &a.session_ids)? {
        let mut entry = SpoolEntry {
            session_id: id.clone(),
            info: None,
            committed_rows: None,
            pending_rows: None,
            status: "error".into(),
            server_error: None,
            error: None,
        };
        match spools.inspect(&id) {
            Err(e) => entry.error = Some(format!("{e:#}")),
            Ok(info) => {
                match spool::probe_committed(server, &id).await {
                    Ok(c) => entry.committed_rows = Some(c),
                    Err(e) => entry.server_error = Some(e),
                }
                // Only rows the server confirmed with the spool's bytes count as uploaded; its
                // committed count alone proves nothing about whose rows it holds.
                let confirmed = info
                    .state
                    .confirmed_rows
                    .unwrap_or(0)
                    .min(info.spooled_rows)
                    .max(info.base_row);
                let pending = info.spooled_rows.saturating_sub(confirmed);
                entry.pending_rows = Some(pending);
                entry.status = if info.busy {
                    "spooling"
                } else if pending > 0 {
                    "pending"
                } else if !info.sealed {
                    "incomplete"
                } else {
                    "uploaded"
                }
                .into();
                entry.info = Some(info);
            }
        }
        entries.push(entry);
    }
    let mut text = if entries.is_empty() {
        format!("the spool {} holds no sessions\n", spools.root().display())
    } else {
        format!(
            "spool {}\n{:<32} {:>21} {:>10} {:>10}  status\n",
            spools.root().display(),
            "session",
            "spooled/expected",
            "committed",
            "pending"
        )
    };
    for e in &entries {
        match &e.info {
            None => text.push_str(&format!(
                "{:<32} error: {}\n",
                e.session_id,
                e.error.as_deref().unwrap_or("?")
            )),
            Some(info) => {
                text.push_str(&format!(
                    "{:<32} {:>21} {:>10} {:>10}  {}{}\n",
                    e.session_id,
                    format!("{}/{}", info.spooled_rows, info.expected_rows),
                    e.committed_rows
                        .map(|c| c.to_string())
                        .unwrap_or_else(|| "?".into()),
                    e.pending_rows.unwrap_or(0),
                    e.status,
                    if info.torn_bytes > 0 {
                        format!(
                            " (a torn tail of {} bytes, cut at the next open)",
                            info.torn_bytes
                        )
                    } else {
                        String::new()
                    }
                ));
                if let Some(err) = &info.state.last_error {
                    text.push_str(&format!("    last upload error: {err}\n"));
                }
                if let Some(err) = &e.server_error {
                    text.push_str(&format!("    server not asked: {err}\n"));
                }
            }
        }
    }
    Ok(Outcome {
        json: json!({ "spool": spools.root(), "sessions": entries }),
        text,
    })
}

pub(super) async fn spool_upload_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &SpoolUploadArgs,
) -> anyhow::Result<Outcome> {
    let opts = a.transfer.options(false)?;
    let mut reports = Vec::new();
    let mut failures = Vec::new();
    let mut text = String::new();
    for id in spool_ids(spools, &a.session_ids)? {
        let result = async {
            let spool = Arc::new(spools.open(&id)?);
            spool::drain(server, spool, &opts, false).await
        }
        .await;
        match result {
            Ok(r) => {
                text.push_str(&format!(
                    "{}: {} rows sent, server has {}/{} rows{}{}\n",
                    id,
                    r.rows_sent,
                    r.committed_rows,
                    r.expected_rows,
                    if r.finished { ", finished" } else { "" },
                    if r.removed {
                        ", spool cleared"
                    } else {
                        ", kept in the spool (its producer has not written every row)"
                    }
                ));
                reports.push(r);
            }
            Err(e) => {
                text.push_str(&format!("{id}: failed: {e:#}\n"));
                failures.push(format!("{id}: {e:#}"));
            }
        }
    }
    if reports.is_empty() && failures.is_empty() {
        text.push_str(&format!(
            "nothing to upload: the spool {} holds no sessions\n",
            spools.root().display()
        ));
    }
    if !failures.is_empty() {
        bail!(
            "{} of {} spooled session(s) not uploaded:\n{}",
            failures.len(),
            failures.len() + reports.len(),
            failures.join("\n")
        );
    }
    Ok(Outcome {
        json: json!({ "spool": spools.root(), "uploaded": reports }),
        text,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::{Cli, Command, parse};
    use clap::Parser;
    use std::path::Path;

    #[test]
    fn spool_commands_parse() {
        let cli = parse(&[
            "--spool",
            "/tmp/sp",
            "spool",
            "upload",
            "a",
            "b",
            "--retry-for",
            "5",
        ]);
        assert_eq!(cli.spool.as_deref(), Some(Path::new("/tmp/sp")));
        let Command::Spool(SpoolCommand::Upload(a)) = cli.command else {
            panic!()
        };
        assert_eq!(a.session_ids, ["a", "b"]);
        assert_eq!(a.transfer.retry_for, 5.0);
        let cli = parse(&["spool", "status"]);
        let Command::Spool(SpoolCommand::Status(a)) = cli.command else {
            panic!()
        };
        assert!(a.session_ids.is_empty());
        let cli = parse(&["simulate", "--scene", "usaf", "--count", "10"]);
        let Command::Simulate(a) = cli.command else {
            panic!()
        };
        assert_eq!((a.batch_rows, a.frame_rate), (1024, None));
        assert!(
            Cli::try_parse_from(["helmholtz", "simulate", "--scene", "u", "--batch-rows", "0"])
                .is_err()
        );
    }
}
