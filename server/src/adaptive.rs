//! Adaptive acquisition: the server side of the planner ([`recon::adaptive::Planner`]) for one
//! session's `Acquire` stream.
//!
//! The planner is deterministic in the values it has observed, so its state is never stored:
//! [`Acquisition::open`] rebuilds it from the session's stored rows (replaying it batch by batch,
//! reading the rows with a cursor, so memory stays bounded by the batches in flight), checks every
//! batch it issues again against the stored one, and stores those it issued beyond them (a server
//! that stopped between storing rows and storing the next batch). After each committed chunk,
//! [`Acquisition::advance`] observes every batch whose rows are all in and stores the batches the
//! planner then issues, before the caller sends them. The rule that makes the sequence
//! reproducible: after the planner is made and after every `observe`, `poll` until it returns
//! `None`; every batch so obtained is issued.

use std::collections::VecDeque;

use crate::api::ApiError;
use crate::recon::adaptive::{Batch, Planner, StopReason};
use crate::store::{IssuedBatch, SampleFormat, SessionRow, Store, StoreError, WriterLease};

/// Stored chunks read per store query.
const READ_CHUNKS: u32 = 8;

/// One session's planner and the rows it has not observed yet.
pub struct Acquisition {
    session_id: String,
    /// The session's declaration (how many frames a batch takes).
    spec: helmholtz_proto::PatternSpec,
    channels: usize,
    format: SampleFormat,
    /// `None` only while an observation runs on a blocking thread.
    planner: Option<Planner>,
    /// Issued batches whose rows the planner has not observed, oldest first.
    outstanding: VecDeque<IssuedBatch>,
    /// The next row to read: a stored chunk boundary.
    cursor: u64,
    /// Decoded rows `first row of the oldest outstanding batch .. cursor`, row-major.
    pending: Vec<f64>,
    /// The row `pending` starts at.
    pending_from: u64,
}

impl std::fmt::Debug for Acquisition {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Acquisition")
            .field("session_id", &self.session_id)
            .field("outstanding", &self.outstanding.len())
            .field("cursor", &self.cursor)
            .finish()
    }
}

/// A planner error: the spec and the values were validated before, so this is the server's
/// fault (or stored data that no longer replays).
fn planner_error(session: &str, e: impl std::fmt::Display) -> ApiError {
    ApiError::Internal(format!("session {session}: adaptive planner: {e}"))
}

impl Acquisition {
    /// Rebuilds the planner of `session` (an adaptive session) from its stored rows and
    /// batches under the writer `lease`, storing the batches the replay issues beyond the
    /// stored ones. A replayed batch that differs from the stored one is an internal error
    /// (logged): the stored session would no longer reproduce.
    pub async fn open(
        store: &Store,
        session: &SessionRow,
        lease: &WriterLease,
    ) -> Result<Acquisition, ApiError> {
        let channels = session.row_values();
        let planner =
            Planner::new(&session.spec, channels).map_err(|e| planner_error(&session.id, e))?;
        let mut acquisition = Acquisition {
            session_id: session.id.clone(),
            spec: session.spec.clone(),
            channels,
            format: session.sample_format(),
            planner: Some(planner),
            outstanding: VecDeque::new(),
            cursor: 0,
            pending: Vec::new(),
            pending_from: 0,
        };
        let mut stored: VecDeque<IssuedBatch> = store.batches(&session.id).await?.into();
        let stored_count = stored.len();
        acquisition
            .issue(store, lease, &mut stored, &mut Vec::new())
            .await?;
        acquisition
            .observe_committed(store, lease, &mut stored, &mut Vec::new())
            .await?;
        if let Some(extra) = stored.front() {
            let message = format!(
                "session {}: stored batch {} (of {stored_count}) was not issued again by the replay of the stored rows",
                session.id, extra.number
            );
            tracing::error!(session = %session.id, batch = extra.number, "adaptive replay differs from the stored batches");
            return Err(ApiError::Internal(message));
        }
        Ok(acquisition)
    }

    /// Observes every batch whose rows are now all committed and stores the batches the
    /// planner issues after them: the new batches, to send.
    pub async fn advance(
        &mut self,
        store: &Store,
        lease: &WriterLease,
    ) -> Result<Vec<IssuedBatch>, ApiError> {
        let mut issued = Vec::new();
        self.observe_committed(store, lease, &mut VecDeque::new(), &mut issued)
            .await?;
        Ok(issued)
    }

    /// Rows of every batch issued so far.
    pub fn issued_rows(&self) -> u64 {
        self.planner().issued_rows()
    }

    /// Why the acquisition is over: the planner's stopping rule holds and every issued batch is
    /// measured.
    pub fn stopped(&self) -> Option<StopReason> {
        let planner = self.planner();
        planner.finished().filter(|_| self.outstanding.is_empty())
    }

    /// The planner's estimate of the image's relative error.
    pub fn estimated_error(&self) -> Option<f64> {
        self.planner().estimated_error()
    }

    fn planner(&self) -> &Planner {
        self.planner
            .as_ref()
            .expect("the planner is back after each observation")
    }

    /// Polls the planner until it has nothing more to issue. Each batch is checked against
    /// the next of `stored` (a replay), or, past them, stored durably and pushed to `issued`.
    async fn issue(
        &mut self,
        store: &Store,
        lease: &WriterLease,
        stored: &mut VecDeque<IssuedBatch>,
        issued: &mut Vec<IssuedBatch>,
    ) -> Result<(), ApiError> {
        let planner = self.planner.as_mut().expect("planner present");
        while let Some(batch) = planner.poll() {
            let batch = issued_batch(batch);
            match stored.pop_front() {
                Some(s) if s == batch => {}
                Some(s) => {
                    tracing::error!(
                        session = %self.session_id,
                        batch = batch.number,
                        "adaptive replay differs from the stored batches"
                    );
                    return Err(ApiError::Internal(format!(
                        "session {}: the replay of the stored rows issues batch {} at row {} with other indices than stored (stored at row {})",
                        self.session_id, batch.number, batch.first_row, s.first_row
                    )));
                }
                None => {
                    store
                        .issue_batch(
                            &self.session_id,
                            Some(lease),
                            &batch,
                            batch.end_row(&self.spec),
                        )
                        .await?;
                    metrics::counter!("helmholtz_adaptive_batches_total").increment(1);
                    issued.push(batch.clone());
                }
            }
            self.outstanding.push_back(batch);
        }
        Ok(())
    }

    /// Reads the committed rows from the cursor on and observes each outstanding batch they
    /// complete (then issues what the planner chooses next), until the rows run out.
    async fn observe_committed(
        &mut self,
        store: &Store,
        lease: &WriterLease,
        stored: &mut VecDeque<IssuedBatch>,
        issued: &mut Vec<IssuedBatch>,
    ) -> Result<(), ApiError> {
        let sample_bytes = self.format.bytes();
        loop {
            let chunks = store
                .read_raw_chunks(&self.session_id, self.cursor, READ_CHUNKS, sample_bytes)
                .await?;
            if chunks.is_empty() {
                return Ok(());
            }
            for (start, count, data) in chunks {
                if start != self.cursor {
                    return Err(StoreError::Corrupt(format!(
                        "session {}: stored chunk at row {start} does not continue row {}",
                        self.session_id, self.cursor
                    ))
                    .into());
                }
                self.pending.extend(self.format.decode_f64(&data));
                self.cursor = start + count;
                while let Some(batch) = self.outstanding.front() {
                    let batch_end = batch.end_row(&self.spec);
                    if batch_end > self.cursor {
                        break;
                    }
                    let end = (batch_end - self.pending_from) as usize * self.channels;
                    let frames: Vec<f64> = self.pending.drain(..end).collect();
                    self.pending_from = batch_end;
                    self.outstanding.pop_front();
                    self.observe(frames).await?;
                    self.issue(store, lease, stored, issued).await?;
                }
            }
        }
    }

    /// One batch's frames into the planner, on a blocking thread (the planner's update is CPU
    /// work the async runtime that serves uploads must not wait for).
    async fn observe(&mut self, frames: Vec<f64>) -> Result<(), ApiError> {
        let mut planner = self.planner.take().expect("planner present");
        let (planner, result) = tokio::task::spawn_blocking(move || {
            let result = planner.observe(&frames);
            (planner, result)
        })
        .await
        .map_err(|e| ApiError::Internal(format!("adaptive planner task: {e}")))?;
        self.planner = Some(planner);
        result.map_err(|e| planner_error(&self.session_id, e))
    }
}

fn issued_batch(b: Batch) -> IssuedBatch {
    IssuedBatch {
        number: b.number,
        first_row: b.first_row,
        indices: b.indices,
    }
}
