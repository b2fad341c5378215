//! Adaptive sessions' issued batches: the basis indices the server chose, stored before the rig
//! sees them, in issue order. With the stored rows they make the session reproducible: the spec
//! resolved with the concatenated indices generates every pattern shown.

use std::sync::Arc;

use async_trait::async_trait;
use helmholtz_proto::PatternSpec;

use super::{SessionRow, StoreError, StoreRow, WriterLease};

/// One issued batch: frames `first_row + 2j`, `first_row + 2j + 1` show the split pair of basis
/// function `indices[j]`; with single frames (PATTERNS.md, "Single frames") frame `first_row + j`
/// shows index `j`'s `P+`, but for index 0's two frames.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct IssuedBatch {
    /// 0, 1, ... in issue order.
    pub number: u64,
    /// The batch's first frame: the previous batch's end.
    pub first_row: u64,
    pub indices: Vec<u32>,
}

impl IssuedBatch {
    /// The frame after the batch's last, in a session of `spec`.
    pub fn end_row(&self, spec: &PatternSpec) -> u64 {
        let first = spec.adaptive_indices_in(self.first_row).unwrap_or(0);
        spec.adaptive_rows(first + self.indices.len() as u64)
            .unwrap_or(self.first_row)
    }
}

/// Whether `batch` may follow the stored batches `stored` (their count and their end), or is
/// the same as one already stored at its number: `Ok(true)` to insert, `Ok(false)` when an equal
/// batch is stored (issuing is idempotent: a replay after a crash between storing and sending
/// issues it again), else the error.
pub(crate) fn check_next(
    session_id: &str,
    issued_rows: Option<u64>,
    stored: Option<IssuedBatch>,
    count: u64,
    batch: &IssuedBatch,
) -> Result<bool, StoreError> {
    let Some(issued) = issued_rows else {
        return Err(StoreError::NotAdaptive(session_id.to_string()));
    };
    if let Some(existing) = stored {
        return if existing == *batch {
            Ok(false)
        } else {
            Err(StoreError::Corrupt(format!(
                "session {session_id}: batch {} is stored with other indices than the planner chose now",
                batch.number
            )))
        };
    }
    if batch.number != count || batch.first_row != issued || batch.indices.is_empty() {
        return Err(StoreError::Corrupt(format!(
            "session {session_id}: batch {} at row {} does not follow the {count} stored batches ending at row {issued}",
            batch.number, batch.first_row
        )));
    }
    Ok(true)
}

/// The indices as stored: little-endian u32s.
pub(crate) fn indices_blob(indices: &[u32]) -> Vec<u8> {
    indices.iter().flat_map(|i| i.to_le_bytes()).collect()
}

/// A stored batch of either backend.
pub(crate) fn batch_from_row(row: &impl StoreRow) -> Result<IssuedBatch, StoreError> {
    let blob = row.bytes("indices");
    let pairs = row.int("pairs") as usize;
    if blob.len() != 4 * pairs {
        return Err(StoreError::Corrupt(format!(
            "adaptive batch {} holds {} bytes of indices for {pairs} pairs",
            row.int("number"),
            blob.len()
        )));
    }
    Ok(IssuedBatch {
        number: row.int("number") as u64,
        first_row: row.int("first_row") as u64,
        indices: blob
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes(b.try_into().expect("4")))
            .collect(),
    })
}

/// Issued batches as a backend stores them.
#[async_trait]
pub trait Batches: Send + Sync {
    /// Stores `batch` as the next of the adaptive session `session_id` and raises its issued
    /// rows to the batch's end `end_row` ([`IssuedBatch::end_row`]), in one transaction (with a `lease`, only while the lease is still
    /// this writer's). Storing a batch equal to one stored at its number changes nothing;
    /// one that does not continue the stored batches is [`StoreError::Corrupt`]. Returns the
    /// issued rows.
    async fn issue_batch(
        &self,
        session_id: &str,
        lease: Option<&WriterLease>,
        batch: &IssuedBatch,
        end_row: u64,
    ) -> Result<u64, StoreError>;

    /// The session's batches in issue order (empty for other families).
    async fn batches(&self, session_id: &str) -> Result<Vec<IssuedBatch>, StoreError>;

    /// The pattern spec that generates the session's stored rows: its declared spec, or for an
    /// adaptive session the spec resolved with every index issued so far.
    async fn resolved_spec(&self, session: &SessionRow) -> Result<PatternSpec, StoreError> {
        Ok(self.resolved_spec_and_rows(session).await?.0)
    }

    /// [`Batches::resolved_spec`] and the rows it generates: the declared count, or an adaptive
    /// session's issued rows (an adaptive session without a batch yet keeps its declared spec
    /// and generates no row).
    async fn resolved_spec_and_rows(
        &self,
        session: &SessionRow,
    ) -> Result<(PatternSpec, u64), StoreError> {
        if !session.spec.is_adaptive() {
            return Ok((session.spec.clone(), session.spec.count()));
        }
        let indices: Vec<u32> = self
            .batches(&session.id)
            .await?
            .into_iter()
            .flat_map(|b| b.indices)
            .collect();
        if indices.is_empty() {
            return Ok((session.spec.clone(), 0));
        }
        let rows = session
            .spec
            .adaptive_rows(indices.len() as u64)
            .expect("adaptive");
        let spec = session.spec.with_indices(Arc::from(indices)).map_err(|e| {
            StoreError::Corrupt(format!("session {}: stored indices: {e}", session.id))
        })?;
        Ok((spec, rows))
    }
}
