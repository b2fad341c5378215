//! Adaptive acquisition from the rig's side (gRPC `Acquire`): the server chooses the patterns,
//! batch by batch, from the values measured so far; [`acquire_adaptive`] shows each batch
//! through the rig's measurement callback and streams the rows back, until the server's
//! stopping rule ends the session.
//!
//! The rig keeps the rows it measured until the server acknowledges them. A dropped stream
//! (network, server restart, UNAVAILABLE, another stream of ours still holding the session) is
//! reopened with jittered backoff for as long as [`UploadOptions::retry_for`] allows without
//! progress; the server then says where it stands (its committed count) and re-sends the
//! batches not yet measured, and the rig re-sends its measured rows from there. The index
//! sequence is a deterministic function of the spec and the values, so a resumed session ends
//! with the indices an uninterrupted one would have.

use std::collections::VecDeque;
use std::ops::Range;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context;
use helmholtz_proto::v1::{self, acquire_request, acquire_response};
use helmholtz_proto::{PatternSpec, wire::SampleBuf};
use serde::Serialize;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Code, Status};

use crate::upload::{
    Disposition, RpcError, SampleFormat, UploadOptions, connect, disposition, encode_chunk,
    new_writer_id,
};

/// One batch to measure: frames `rows` (twice `indices.len()`, from an even row) show the split
/// pairs of `indices`; `spec` is the session's spec resolved with every index issued so far, so
/// `PatternGenerator::new(spec).fill_values(row, ..)` gives the pattern of any of these frames.
#[derive(Clone, Debug)]
pub struct BatchToMeasure<'a> {
    pub number: u64,
    pub rows: Range<u64>,
    pub indices: &'a [u32],
    pub spec: &'a PatternSpec,
}

/// What [`acquire_adaptive`] did.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct AdaptiveReport {
    pub session_id: String,
    /// Rows the finished session holds.
    pub rows: u64,
    /// Every basis index issued, in order (one per split pair).
    pub indices: Vec<u32>,
    pub batches: u64,
    /// Why the server stopped: "budget", "target_error" or "finished".
    pub reason: String,
    /// The server's estimate of the image's relative error.
    pub estimated_error: Option<f64>,
    /// Streams opened again after a dropped one.
    pub reconnects: u32,
    /// Rows put on the wire, re-sends after a reconnect included.
    pub rows_sent: u64,
    /// Time the rig spent with every issued batch measured, waiting for the next batch (a real
    /// rig's idle projector).
    pub idle_seconds: f64,
    pub seconds: f64,
}

/// The rig's state across streams.
struct Rig {
    session_id: String,
    declared: PatternSpec,
    channels: u32,
    format: SampleFormat,
    /// Every batch issued, by number.
    batches: Vec<v1::AdaptiveBatch>,
    /// Every index issued, in order.
    indices: Vec<u32>,
    /// `declared` resolved with `indices` (re-resolved as batches arrive).
    resolved: Option<PatternSpec>,
    /// Rows measured: `0..measured`.
    measured: u64,
    /// Measured rows the server has not acknowledged: (first row, payload of whole rows).
    unacked: VecDeque<(u64, Vec<u8>)>,
    committed: u64,
    report: AdaptiveReport,
}

/// How one stream ended.
enum StreamEnd {
    Done,
    Failed(Status),
}

/// Runs the adaptive acquisition of session `session_id` (created with an adaptive family)
/// on `server`: `measure` is called once per batch with the frames to show and returns their
/// rows (row-major, the session's channels or camera pixels a row, in its sample format). Ends
/// when the server finishes the session. A failure the server reports about the request
/// (a bad value, another lab's session, ...) ends it at once with an [`RpcError`]; dropped
/// streams are reopened (see the module docs).
pub async fn acquire_adaptive<F>(
    server: &str,
    session: &v1::Session,
    opts: &UploadOptions,
    mut measure: F,
) -> anyhow::Result<AdaptiveReport>
where
    F: FnMut(&BatchToMeasure<'_>) -> anyhow::Result<SampleBuf>,
{
    let started = Instant::now();
    let declared = PatternSpec::try_from(&session.patterns.unwrap_or_default())
        .map_err(|e| anyhow::anyhow!("session {}: its spec: {e}", session.session_id))?;
    anyhow::ensure!(
        declared.is_adaptive(),
        "session {} declares {} patterns, not an adaptive family",
        session.session_id,
        declared.family().name()
    );
    let detector = session.detector.clone().unwrap_or_default();
    let (channels, format) = match &detector.camera {
        Some(c) => (
            c.width * c.height,
            SampleFormat::from_proto(
                v1::SampleFormat::try_from(c.format).unwrap_or(v1::SampleFormat::F32),
            )
            .unwrap_or(SampleFormat::F32),
        ),
        None => (detector.channels.len() as u32, SampleFormat::F64),
    };
    let mut rig = Rig {
        session_id: session.session_id.clone(),
        declared,
        channels,
        format,
        batches: Vec::new(),
        indices: Vec::new(),
        resolved: None,
        measured: 0,
        unacked: VecDeque::new(),
        committed: 0,
        report: AdaptiveReport {
            session_id: session.session_id.clone(),
            ..Default::default()
        },
    };
    let writer = new_writer_id();
    let policy = opts.policy();
    let mut attempt = 0u32;
    let mut progress_at = Instant::now();
    loop {
        let before = rig.committed;
        let end = rig.stream(server, &writer, opts, &mut measure).await?;
        match end {
            StreamEnd::Done => break,
            StreamEnd::Failed(status) => {
                if rig.committed > before {
                    progress_at = Instant::now();
                    attempt = 0;
                }
                let operation = format!("adaptive acquisition of session {}", rig.session_id);
                if disposition(status.code()) == Disposition::Fatal
                    || progress_at.elapsed() >= policy.retry_for
                {
                    return Err(anyhow::Error::new(RpcError::new(operation, &status)))
                        .with_context(|| format!("{} rows committed", rig.committed));
                }
                tracing::warn!(code = ?status.code(), message = status.message(), committed = rig.committed, "adaptive stream dropped; reopening");
                tokio::time::sleep(policy.backoff.random_delay(attempt)).await;
                attempt += 1;
                rig.report.reconnects += 1;
            }
        }
    }
    rig.report.indices = rig.indices;
    rig.report.batches = rig.batches.len() as u64;
    rig.report.seconds = started.elapsed().as_secs_f64();
    Ok(rig.report)
}

impl Rig {
    /// One `Acquire` stream, until the server's `done` or a failure (returned as the status; an
    /// error of the rig's own is returned as `Err`).
    async fn stream<F>(
        &mut self,
        server: &str,
        writer: &str,
        opts: &UploadOptions,
        measure: &mut F,
    ) -> anyhow::Result<StreamEnd>
    where
        F: FnMut(&BatchToMeasure<'_>) -> anyhow::Result<SampleBuf>,
    {
        let mut client = connect(server, opts.connect_timeout)?;
        let (tx, rx) = tokio::sync::mpsc::channel::<v1::AcquireRequest>(4);
        let open = v1::AcquireRequest {
            message: Some(acquire_request::Message::Open(v1::AcquireOpen {
                session_id: self.session_id.clone(),
                measured_rows: self.measured,
                known_batches: self.batches.len() as u64,
            })),
        };
        tx.send(open).await.expect("the receiver is alive");
        let mut request = tonic::Request::new(ReceiverStream::new(rx));
        if let Ok(value) = writer.parse() {
            request.metadata_mut().insert("x-helmholtz-writer", value);
        }
        let mut inbound = match client.acquire(request).await {
            Ok(response) => response.into_inner(),
            Err(status) => return Ok(StreamEnd::Failed(status)),
        };
        // The server's messages, read by a task of their own so that sending rows never waits
        // for this loop to read an ack (and the server never waits for us to read).
        let (in_tx, mut in_rx) = tokio::sync::mpsc::unbounded_channel();
        let reader = tokio::spawn(async move {
            loop {
                let next = inbound.message().await;
                let end = !matches!(next, Ok(Some(_)));
                if in_tx.send(next).is_err() || end {
                    return;
                }
            }
        });
        let result = self.converse(&tx, &mut in_rx, opts, measure).await;
        reader.abort();
        result
    }

    async fn converse<F>(
        &mut self,
        tx: &tokio::sync::mpsc::Sender<v1::AcquireRequest>,
        inbound: &mut tokio::sync::mpsc::UnboundedReceiver<
            Result<Option<v1::AcquireResponse>, Status>,
        >,
        opts: &UploadOptions,
        measure: &mut F,
    ) -> anyhow::Result<StreamEnd>
    where
        F: FnMut(&BatchToMeasure<'_>) -> anyhow::Result<SampleBuf>,
    {
        let mut opened = false;
        loop {
            // Measure the next issued batch as soon as there is one (and the stream is open).
            if opened && let Some(batch) = self.next_to_measure() {
                let rows = self.measure_batch(&batch, measure)?;
                let first = self.unacked.len();
                self.unacked.push_back(rows);
                if self.send_from(tx, first, opts).await.is_err() {
                    return Ok(self.closed(inbound).await);
                }
                continue;
            }
            let waited = Instant::now();
            let Some(next) = inbound.recv().await else {
                return Ok(StreamEnd::Failed(Status::unavailable("the stream ended")));
            };
            if opened {
                self.report.idle_seconds += waited.elapsed().as_secs_f64();
            }
            let message = match next {
                Ok(Some(m)) => m.message,
                Ok(None) => {
                    return Ok(StreamEnd::Failed(Status::unavailable(
                        "the server ended the stream before the acquisition was done",
                    )));
                }
                Err(status) => return Ok(StreamEnd::Failed(status)),
            };
            match message {
                Some(acquire_response::Message::Opened(o)) => {
                    opened = true;
                    self.acknowledged(o.committed_rows);
                    anyhow::ensure!(
                        self.measured <= o.issued_rows,
                        "the server issued {} rows of session {}, the rig measured {}",
                        o.issued_rows,
                        self.session_id,
                        self.measured
                    );
                    // Measured rows the server does not hold yet: send them again.
                    if self.send_from(tx, 0, opts).await.is_err() {
                        return Ok(self.closed(inbound).await);
                    }
                }
                Some(acquire_response::Message::Batch(b)) => self.batch(b)?,
                Some(acquire_response::Message::Ack(a)) => self.acknowledged(a.committed_rows),
                Some(acquire_response::Message::Done(d)) => {
                    self.report.rows = d.rows;
                    self.report.estimated_error = d.estimated_error;
                    self.report.reason = match v1::AdaptiveStop::try_from(d.reason) {
                        Ok(v1::AdaptiveStop::Budget) => "budget",
                        Ok(v1::AdaptiveStop::TargetError) => "target_error",
                        Ok(v1::AdaptiveStop::Finished) => "finished",
                        _ => "unknown",
                    }
                    .into();
                    return Ok(StreamEnd::Done);
                }
                None => {}
            }
        }
    }

    /// The sending side closed (the call ended): the server's status says why.
    async fn closed(
        &mut self,
        inbound: &mut tokio::sync::mpsc::UnboundedReceiver<
            Result<Option<v1::AcquireResponse>, Status>,
        >,
    ) -> StreamEnd {
        while let Some(next) = inbound.recv().await {
            match next {
                Ok(Some(m)) => match m.message {
                    Some(acquire_response::Message::Ack(a)) => self.acknowledged(a.committed_rows),
                    Some(acquire_response::Message::Batch(b)) => {
                        if let Err(e) = self.batch(b) {
                            return StreamEnd::Failed(Status::internal(e.to_string()));
                        }
                    }
                    _ => {}
                },
                Ok(None) => break,
                Err(status) => return StreamEnd::Failed(status),
            }
        }
        StreamEnd::Failed(Status::new(Code::Unavailable, "the stream closed"))
    }

    /// A batch from the server: new ones extend the sequence; one sent again (after a reopen)
    /// must equal the one we hold.
    fn batch(&mut self, b: v1::AdaptiveBatch) -> anyhow::Result<()> {
        match self.batches.get(b.number as usize) {
            Some(known) => anyhow::ensure!(
                *known == b,
                "the server sent batch {} of session {} again with other indices",
                b.number,
                self.session_id
            ),
            None => {
                let end = self.batches.last().map_or(0, |l| self.batch_end(l));
                anyhow::ensure!(
                    b.number == self.batches.len() as u64
                        && b.first_row == end
                        && !b.indices.is_empty(),
                    "the server sent batch {} at row {}; the rig expected batch {} at row {end}",
                    b.number,
                    b.first_row,
                    self.batches.len()
                );
                self.indices.extend_from_slice(&b.indices);
                self.resolved = None;
                self.batches.push(b);
            }
        }
        Ok(())
    }

    /// The committed count moved: rows below it are durable and dropped here.
    fn acknowledged(&mut self, committed: u64) {
        self.committed = self.committed.max(committed);
        let row_bytes = self.row_bytes() as u64;
        while let Some((start, payload)) = self.unacked.front() {
            if start + payload.len() as u64 / row_bytes <= self.committed {
                self.unacked.pop_front();
            } else {
                break;
            }
        }
    }

    fn row_bytes(&self) -> usize {
        self.channels as usize * self.format.bytes()
    }

    /// The frame after `batch`'s last: two frames an index, or with single frames one but
    /// index 0's two (PATTERNS.md, "Single frames").
    fn batch_end(&self, batch: &v1::AdaptiveBatch) -> u64 {
        let first = self
            .declared
            .adaptive_indices_in(batch.first_row)
            .expect("adaptive");
        self.declared
            .adaptive_rows(first + batch.indices.len() as u64)
            .expect("adaptive")
    }

    /// The first issued batch not yet measured.
    fn next_to_measure(&self) -> Option<v1::AdaptiveBatch> {
        self.batches
            .iter()
            .find(|b| self.batch_end(b) > self.measured)
            .cloned()
    }

    /// The rig's rows of `batch` (from the first row not measured), checked.
    fn measure_batch<F>(
        &mut self,
        batch: &v1::AdaptiveBatch,
        measure: &mut F,
    ) -> anyhow::Result<(u64, Vec<u8>)>
    where
        F: FnMut(&BatchToMeasure<'_>) -> anyhow::Result<SampleBuf>,
    {
        if self.resolved.is_none() {
            let spec = self
                .declared
                .with_indices(Arc::from(self.indices.as_slice()))
                .map_err(|e| anyhow::anyhow!("resolving the session's spec: {e}"))?;
            self.resolved = Some(spec);
        }
        let rows = batch.first_row..self.batch_end(batch);
        let spec = self.resolved.as_ref().expect("resolved above");
        let values = measure(&BatchToMeasure {
            number: batch.number,
            rows: rows.clone(),
            indices: &batch.indices,
            spec,
        })
        .with_context(|| format!("measuring batch {} (rows {rows:?})", batch.number))?;
        let samples = values.as_samples();
        anyhow::ensure!(
            samples.format() == self.format,
            "the measurement of batch {} is {}; session {} takes {}",
            batch.number,
            samples.format().name(),
            self.session_id,
            self.format.name()
        );
        let want = (rows.end - rows.start) as usize * self.channels as usize;
        anyhow::ensure!(
            samples.len() == want,
            "the measurement of batch {} holds {} values; {} rows of {} values were shown",
            batch.number,
            samples.len(),
            rows.end - rows.start,
            self.channels
        );
        if let Some(i) = samples.first_non_finite() {
            anyhow::bail!(
                "the measurement of batch {} has a non-finite value at row {}",
                batch.number,
                rows.start + (i / self.channels as usize) as u64
            );
        }
        // Only the rows not measured before (a batch is measured whole, once).
        let skip = (self.measured.max(rows.start) - rows.start) as usize * self.channels as usize;
        let payload = samples.encode_range(skip, samples.len());
        let first = rows.start + (skip / self.channels as usize) as u64;
        self.measured = rows.end;
        Ok((first, payload))
    }

    /// Sends the unacknowledged rows from entry `from` on (those at or past the committed
    /// count), in chunks; `Err` when the call has ended.
    async fn send_from(
        &mut self,
        tx: &tokio::sync::mpsc::Sender<v1::AcquireRequest>,
        from: usize,
        opts: &UploadOptions,
    ) -> Result<(), ()> {
        let row_bytes = self.row_bytes();
        let per_chunk = opts.rows_per_chunk_of(self.channels as usize, self.format) * row_bytes;
        let mut chunks = Vec::new();
        for (start, payload) in self.unacked.iter().skip(from) {
            let skip_rows = self.committed.saturating_sub(*start);
            let skip = (skip_rows as usize * row_bytes).min(payload.len());
            let mut offset = skip;
            while offset < payload.len() {
                let end = (offset + per_chunk).min(payload.len());
                let row = start + (offset / row_bytes) as u64;
                chunks.push(encode_chunk(
                    &self.session_id,
                    self.channels,
                    self.format,
                    row,
                    payload[offset..end].to_vec(),
                ));
                offset = end;
            }
        }
        for chunk in chunks {
            let rows = (crate::upload::chunk_payload_len(&chunk) / row_bytes) as u64;
            let request = v1::AcquireRequest {
                message: Some(acquire_request::Message::Chunk(chunk)),
            };
            tx.send(request).await.map_err(|_| ())?;
            self.report.rows_sent += rows;
        }
        Ok(())
    }
}
