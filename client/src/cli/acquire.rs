//! `helmholtz acquire`: a real rig's rows read from stdin as they arrive.

use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::Args;
use serde_json::json;

use crate::spool::{self, SpoolDir};
use crate::upload::{self, NewSession};

use super::Outcome;
use super::args::{SpecSource, TransferArgs, parse_metadata, spec_json, spec_summary};
use super::spool::upload_text;

#[derive(Debug, Clone, Args)]
pub struct AcquireArgs {
    /// Session id (1-128 of A-Z a-z 0-9 . _ -). Created if new; re-running continues it.
    #[arg(long)]
    pub session_id: String,
    #[command(flatten)]
    pub spec: SpecSource,
    /// Channel names, comma separated (one number per channel on each line).
    #[arg(long, value_delimiter = ',', default_value = "bucket")]
    pub channels: Vec<String>,
    /// Rig name recorded with the session.
    #[arg(long, default_value = "rig")]
    pub rig: String,
    /// Extra session metadata, KEY=VALUE (repeatable).
    #[arg(long = "metadata", value_name = "KEY=VALUE")]
    pub metadata: Vec<String>,
    /// Finish the session at the end of input (every row of the spec must then be in).
    #[arg(long)]
    pub finish: bool,
    /// Rows per spool write: each batch is fsync'ed before it counts as measured.
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u64).range(1..))]
    pub batch_rows: u64,
    /// Spool the rows read so far once the first of them has waited this long.
    #[arg(long, default_value_t = 200)]
    pub flush_ms: u64,
    /// The pattern index of the first row on stdin [default: where the session continues: the
    /// end of this session's spool, else the server's committed count]. Given, it must agree
    /// with the spool (a spool holding unsent rows fixes where the next row goes) and must not
    /// leave a gap after the server's rows; rows before the server's count are compared with
    /// the stored ones.
    #[arg(long)]
    pub start_row: Option<u64>,
    #[command(flatten)]
    pub transfer: TransferArgs,
}

/// One line of rig output: `channels` finite numbers; `None` for a blank or comment line.
fn parse_row_line(line: &str, number: u64, channels: usize) -> anyhow::Result<Option<Vec<f64>>> {
    let text = line.split('#').next().unwrap_or("").trim();
    if text.is_empty() {
        return Ok(None);
    }
    let fields: Vec<&str> = text
        .split([',', ';', '\t', ' '])
        .map(str::trim)
        .filter(|f| !f.is_empty())
        .collect();
    anyhow::ensure!(
        fields.len() == channels,
        "stdin line {number}: {} value(s), expected {channels} (one per channel)",
        fields.len()
    );
    fields
        .iter()
        .enumerate()
        .map(|(c, f)| {
            let v: f64 = f.parse().map_err(|_| {
                anyhow::anyhow!(
                    "stdin line {number}, column {}: {f:?} is not a number",
                    c + 1
                )
            })?;
            anyhow::ensure!(
                v.is_finite(),
                "stdin line {number}, column {}: {f:?} is not a finite number",
                c + 1
            );
            Ok(v)
        })
        .collect::<anyhow::Result<Vec<f64>>>()
        .map(Some)
}

pub(super) async fn acquire_cmd(
    server: &str,
    spools: &SpoolDir,
    a: &AcquireArgs,
) -> anyhow::Result<Outcome> {
    use tokio::io::AsyncBufReadExt;
    anyhow::ensure!(
        upload::valid_session_id(&a.session_id),
        "--session-id {:?}: use 1-128 of A-Z a-z 0-9 . _ -",
        a.session_id
    );
    anyhow::ensure!(
        !a.channels.is_empty() && a.channels.iter().all(|c| !c.trim().is_empty()),
        "--channels: empty channel name"
    );
    let spec = a.spec.load()?;
    let opts = a.transfer.options(false)?;
    let mut session = NewSession::new(a.session_id.clone(), spec.clone(), a.channels.clone())
        .with_rig(a.rig.clone());
    session.metadata = parse_metadata(&a.metadata)?;
    let ch = a.channels.len();
    let spool = Arc::new(spools.create_or_open(&session, a.finish)?);
    let first_row = acquire_start_row(server, &spool, a.start_row).await?;
    let spooled_before = spool.rows() - spool.base_row();
    spool.unseal()?;
    let drainer = tokio::spawn({
        let (spool, server, opts) = (spool.clone(), server.to_string(), opts.clone());
        async move { spool::drain(&server, spool, &opts, true).await }
    });
    let flush_after = Duration::from_millis(a.flush_ms);
    let produce = async {
        let mut lines = tokio::io::BufReader::new(tokio::io::stdin()).lines();
        let mut pending: Vec<f64> = Vec::new();
        let mut oldest: Option<tokio::time::Instant> = None;
        let mut number = 0u64;
        let flush = |pending: &mut Vec<f64>| {
            let batch = std::mem::take(pending);
            let s = spool.clone();
            async move {
                if !batch.is_empty() {
                    tokio::task::spawn_blocking(move || s.append(&batch))
                        .await
                        .context("spool writer panicked")??;
                }
                anyhow::Ok(())
            }
        };
        loop {
            let next = match oldest {
                Some(t) => {
                    match tokio::time::timeout_at(t + flush_after, lines.next_line()).await {
                        Ok(line) => line,
                        Err(_) => {
                            flush(&mut pending).await?;
                            oldest = None;
                            continue;
                        }
                    }
                }
                None => lines.next_line().await,
            };
            let Some(line) = next.context("reading stdin")? else {
                break;
            };
            number += 1;
            let row = match parse_row_line(&line, number, ch) {
                Ok(Some(row)) => row,
                Ok(None) => continue,
                Err(e) => {
                    // The rows before the bad line are measured data: keep them.
                    flush(&mut pending).await?;
                    return Err(e);
                }
            };
            pending.extend(row);
            oldest.get_or_insert_with(tokio::time::Instant::now);
            if (pending.len() / ch) as u64 >= a.batch_rows {
                flush(&mut pending).await?;
                oldest = None;
            }
        }
        flush(&mut pending).await?;
        spool.seal()
    };
    if let Err(e) = produce.await {
        drainer.abort();
        return Err(e.context(format!(
            "acquisition of session {} stopped with {} rows spooled in {} (uploaded by `helmholtz spool upload`; \
             a re-run continues after them)",
            a.session_id,
            spool.rows(),
            spool.dir().display()
        )));
    }
    let report = drainer.await.context("upload task panicked")??;
    let mut text = format!(
        "session {} ({}; channels {}); rows on stdin from row {first_row}\n",
        a.session_id,
        spec_summary(&spec),
        a.channels.join(",")
    );
    text.push_str(&upload_text(&report, spooled_before));
    if a.finish {
        anyhow::ensure!(
            report.finished,
            "session {}: {} of {} rows in, so it cannot be finished; run acquire again with the missing rows",
            a.session_id,
            report.committed_rows,
            report.expected_rows
        );
        text.push_str(&format!(
            "session finished with {} rows\n",
            report.committed_rows
        ));
    }
    Ok(Outcome {
        json: json!({
            "session_id": a.session_id,
            "spec": spec_json(&spec),
            "channels": a.channels,
            "spooled_before": spooled_before,
            "first_row": first_row,
            "upload": report,
            "finished": report.finished,
        }),
        text,
    })
}

/// Where the rows `acquire` reads on stdin go: the pattern index of the first one. Rows are
/// never renumbered silently: a spool holding rows continues after them; an empty one continues
/// at the server's committed count (or `--start-row`). Refused when stdin's rows cannot be
/// aligned with what the spool and the server hold.
async fn acquire_start_row(
    server: &str,
    spool: &spool::Spool,
    given: Option<u64>,
) -> anyhow::Result<u64> {
    let id = spool.session_id();
    let server_rows = match spool::probe_status(server, id).await {
        Ok(Some(s)) if s.state == helmholtz_proto::v1::SessionState::Finished as i32 => bail!(
            "session {id} is finished with {} rows: it takes no more rows, so nothing was read from stdin \
             (acquire into a new --session-id){}",
            s.committed_rows,
            if spool.is_empty() {
                String::new()
            } else {
                format!(
                    "; the spool {} still holds {} unsent row(s), kept",
                    spool.dir().display(),
                    spool.rows() - spool.base_row()
                )
            }
        ),
        Ok(s) => Ok(s.map_or(0, |s| s.committed_rows)),
        Err(e) => Err(e),
    };
    if !spool.is_empty() {
        let next = spool.rows();
        if let Some(g) = given.filter(|g| *g != next) {
            bail!(
                "--start-row {g}: the spool {} holds unsent rows of session {id} up to row {next}, so the next \
                 row on stdin is row {next}; upload them first (`helmholtz spool upload {id}`) or give --start-row {next}",
                spool.dir().display()
            );
        }
        if let Ok(c) = server_rows
            && c > next
        {
            bail!(
                "session {id}: the server holds {c} rows but the spool {} ends at row {next}; the rows on stdin \
                 cannot be aligned (another writer added rows?). Upload the spool first (`helmholtz spool upload {id}`)",
                spool.dir().display()
            );
        }
        return Ok(next);
    }
    let row = match (given, &server_rows) {
        (Some(g), Ok(c)) if g > *c => bail!(
            "--start-row {g}: session {id} holds {c} rows on the server, so row {g} would leave a gap; \
             stdin must continue at row {c} or earlier (rows before {c} are compared with the stored ones)"
        ),
        (Some(g), _) => g,
        (None, Ok(c)) => *c,
        (None, Err(e)) => bail!(
            "session {id}: cannot ask the server where the session's rows continue ({e}); nothing was read \
             from stdin. Start again when the server is reachable, or give --start-row N (the pattern index \
             of stdin's first row; 0 for a new session)"
        ),
    };
    spool.start_at(row)?;
    Ok(row)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rig_lines_parse_or_say_where_they_are_wrong() {
        assert_eq!(
            parse_row_line(" 1.5, -2 # note", 1, 2).unwrap(),
            Some(vec![1.5, -2.0])
        );
        assert_eq!(parse_row_line("3\t4", 1, 2).unwrap(), Some(vec![3.0, 4.0]));
        assert_eq!(parse_row_line("  # only a comment", 1, 2).unwrap(), None);
        assert_eq!(parse_row_line("", 1, 2).unwrap(), None);
        let e = parse_row_line("1,2,3", 7, 2).unwrap_err().to_string();
        assert!(
            e.contains("line 7") && e.contains("3 value(s), expected 2"),
            "{e}"
        );
        let e = parse_row_line("1,x", 8, 2).unwrap_err().to_string();
        assert!(
            e.contains("line 8, column 2") && e.contains("not a number"),
            "{e}"
        );
        let e = parse_row_line("1,NaN", 9, 2).unwrap_err().to_string();
        assert!(
            e.contains("line 9, column 2") && e.contains("finite"),
            "{e}"
        );
    }
}
