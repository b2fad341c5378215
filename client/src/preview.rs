//! Watching a session's live preview over gRPC (`WatchPreview`): progressive dual images of the
//! rows the server has committed so far, while the session uploads.

use std::time::Duration;

use anyhow::Context;
use helmholtz_proto::v1;
use tonic::Streaming;

/// How often frames come: every `every_rows` new rows or `every_ms` milliseconds (0: the
/// server's default, 500 ms when both are 0).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PreviewOptions {
    /// Bucket sessions: the channel by name or index (empty: the first). Camera sessions: empty.
    pub channel: String,
    pub every_rows: u64,
    pub every_ms: u32,
}

/// Opens the preview stream of `session_id` on `server` (an address, with the token as its
/// user part). Frames arrive with increasing row counts; the last has `final` set. Dropping the
/// stream stops the server's preview.
pub async fn watch_preview(
    server: &str,
    session_id: &str,
    options: &PreviewOptions,
) -> anyhow::Result<Streaming<v1::PreviewFrame>> {
    let mut client = crate::upload::connect(server, Duration::from_secs(10))?;
    let request = v1::PreviewRequest {
        session_id: session_id.to_string(),
        channel: options.channel.clone(),
        every_rows: options.every_rows,
        every_ms: options.every_ms,
    };
    let stream = client
        .watch_preview(request)
        .await
        .map_err(|s| anyhow::anyhow!("{}: {}", s.code(), s.message()))
        .with_context(|| format!("watching the preview of session {session_id}"))?
        .into_inner();
    Ok(stream)
}
