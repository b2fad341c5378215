//! Measured rows: append under a writer lease, overlap compared byte for byte, read back in
//! order.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use async_trait::async_trait;

use super::StoreRow;

use super::StoreError;

/// What one append did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AppendOutcome {
    /// The authoritative committed count after this append.
    pub committed_rows: u64,
    /// Rows of the chunk that were new and are now durable.
    pub written: u64,
    /// Rows of the chunk that were already committed and compared byte for byte equal to the
    /// stored ones (overlap after a resume).
    pub matched: u64,
}

/// The upload lease a writer holds (see [`Rows::acquire_writer`]): every append under it
/// checks, in the append's own transaction, that the lease is still this writer's.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WriterLease {
    pub session_id: String,
    /// This stream's id (unique across processes: see [`WriterLease::new_holder`]).
    pub holder: String,
    /// The client's upload id (empty when it sent none): a new stream of the same writer takes
    /// the session over from its own earlier stream (a connection cut without the server
    /// noticing), and that stream's appends are then refused.
    pub writer: String,
    /// How long the lease lasts without a renewal.
    pub ttl: Duration,
}

impl WriterLease {
    /// A holder id unique across processes and machines sharing a database: the process id,
    /// the start time in nanoseconds, a random number and a per-process counter.
    pub fn new_holder() -> String {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let nanos = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        format!(
            "{}-{nanos:x}-{:016x}-{}",
            std::process::id(),
            rand::random::<u64>(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        )
    }
}

/// A stored chunk of rows as a backend reads it: (start_row, row_count, bytes).
pub type RawChunk = (u64, u64, Vec<u8>);

/// An append of rows `start_row..end` against a session with `committed` of `expected` rows
/// stored: refuses a gap and rows past the declared end; returns the end of the overlap with
/// the stored rows (`start_row..overlap_end` must be compared, [`compare_overlap`]).
pub(crate) fn check_bounds(
    committed: u64,
    expected: u64,
    start_row: u64,
    end: u64,
) -> Result<u64, StoreError> {
    if start_row > committed {
        return Err(StoreError::Gap {
            committed,
            start: start_row,
        });
    }
    if end > expected {
        return Err(StoreError::PastEnd { end, expected });
    }
    Ok(end.min(committed))
}

/// An adaptive session (`issued` set) takes rows of its issued batches only: rows up to `end`
/// must have been issued.
pub(crate) fn check_issued(
    session_id: &str,
    issued: Option<u64>,
    end: u64,
) -> Result<(), StoreError> {
    match issued {
        Some(issued) if end > issued => Err(StoreError::NotIssued {
            session: session_id.to_string(),
            end,
            issued,
        }),
        _ => Ok(()),
    }
}

/// Compares an append's rows `start_row..overlap_end` (of a chunk `start_row..end` whose bytes
/// are `payload`) byte for byte with the stored `chunks` that hold them, in order.
#[allow(clippy::too_many_arguments)]
pub(crate) fn compare_overlap(
    session_id: &str,
    committed: u64,
    start_row: u64,
    overlap_end: u64,
    end: u64,
    chunks: &[RawChunk],
    row_bytes: usize,
    payload: &[u8],
) -> Result<(), StoreError> {
    let mut next = start_row;
    for (c_start, c_rows, data) in chunks {
        let (c_start, c_rows) = (*c_start, *c_rows);
        if c_start > next || data.len() as u64 != c_rows * row_bytes as u64 {
            return Err(StoreError::Corrupt(format!(
                "session {session_id}: stored chunk at row {c_start} does not continue row {next}"
            )));
        }
        let hi = overlap_end.min(c_start + c_rows);
        let stored =
            &data[(next - c_start) as usize * row_bytes..(hi - c_start) as usize * row_bytes];
        let sent = &payload
            [(next - start_row) as usize * row_bytes..(hi - start_row) as usize * row_bytes];
        if let Some((row, byte)) = first_difference(stored, sent, row_bytes) {
            return Err(StoreError::RowMismatch {
                session: session_id.to_string(),
                row: next + row,
                byte,
                start: start_row,
                end,
            });
        }
        next = hi;
    }
    if next != overlap_end {
        return Err(StoreError::Corrupt(format!(
            "session {session_id}: stored chunks end at row {next}, not at the committed count {committed}"
        )));
    }
    Ok(())
}

/// Where a chunk's overlap first differs from the stored rows.
fn first_difference(stored: &[u8], sent: &[u8], row_bytes: usize) -> Option<(u64, usize)> {
    let i = stored.iter().zip(sent).position(|(a, b)| a != b)?;
    Some(((i / row_bytes) as u64, i % row_bytes))
}

/// Checks that chunks read from `from_row` on continue each other and hold whole values of
/// `sample_bytes` bytes.
pub(crate) fn check_chunks(
    session_id: &str,
    from_row: u64,
    chunks: &[RawChunk],
    sample_bytes: usize,
) -> Result<(), StoreError> {
    let mut expect = from_row;
    for (start, count, data) in chunks {
        if *start != expect
            || !data.len().is_multiple_of(sample_bytes)
            || *count == 0
            || !((data.len() / sample_bytes) as u64).is_multiple_of(*count)
        {
            return Err(StoreError::Corrupt(format!(
                "session {session_id}: chunk at row {start} does not continue row {expect}"
            )));
        }
        expect = start + count;
    }
    Ok(())
}

/// Row `row` (`row_bytes` bytes) out of the chunk that starts at or before it, or `None` past
/// the chunk.
pub(crate) fn row_of_chunk(
    session_id: &str,
    (start, count, data): &RawChunk,
    row: u64,
    row_bytes: usize,
) -> Result<Option<Vec<u8>>, StoreError> {
    if row >= start + count {
        return Ok(None);
    }
    let offset = (row - start) as usize * row_bytes;
    data.get(offset..offset + row_bytes)
        .map(|b| Some(b.to_vec()))
        .ok_or_else(|| {
            StoreError::Corrupt(format!(
                "session {session_id}: chunk at row {start} is shorter than its rows"
            ))
        })
}

/// Measured rows as a backend stores them.
#[async_trait]
pub trait Rows: Send + Sync {
    /// Takes `lease`'s session for its holder unless another writer's live stream has it: true
    /// when taken (or already held by this holder, or by an earlier stream of the same writer,
    /// which is fenced off from then on).
    async fn acquire_writer(&self, lease: &WriterLease) -> Result<bool, StoreError>;

    /// Extends `lease` by its ttl from now; false when it is no longer this holder's.
    async fn renew_writer(&self, lease: &WriterLease) -> Result<bool, StoreError>;

    /// Gives the lease back (if it is still this holder's).
    async fn release_writer(&self, lease: &WriterLease) -> Result<(), StoreError>;

    /// Appends rows already encoded in the session's sample format (`row_bytes` bytes each,
    /// validated by the caller) starting at `start_row`. A row's identity is (session, index):
    ///
    /// - rows below the committed count must be byte for byte the stored ones, else the chunk
    ///   is refused ([`StoreError::RowMismatch`], naming the first differing row) and nothing
    ///   of it is stored;
    /// - a start above the committed count is a gap and writes nothing;
    /// - new rows into a finished session are refused;
    /// - an adaptive session takes rows of its issued batches only ([`check_issued`]);
    /// - with a `lease`, the append is refused unless the lease is still this writer's
    ///   (checked and renewed in the same transaction: a writer that lost its lease to another
    ///   cannot write after it).
    ///
    /// The new rows and the new count commit in one transaction ([`check_bounds`] and
    /// [`compare_overlap`] hold the checks every backend shares).
    async fn append_raw(
        &self,
        session_id: &str,
        lease: Option<&WriterLease>,
        start_row: u64,
        row_bytes: usize,
        payload: &[u8],
    ) -> Result<AppendOutcome, StoreError>;

    /// Up to `max_chunks` stored chunks whose rows start at or after `from_row` (a chunk
    /// boundary), in order and undecoded, `sample_bytes` bytes per stored value
    /// ([`check_chunks`]).
    async fn read_raw_chunks(
        &self,
        session_id: &str,
        from_row: u64,
        max_chunks: u32,
        sample_bytes: usize,
    ) -> Result<Vec<RawChunk>, StoreError>;

    /// Stored row `row` (`row_bytes` bytes in the session's format), or `None` past the
    /// committed rows.
    async fn read_row(
        &self,
        session_id: &str,
        row: u64,
        row_bytes: usize,
    ) -> Result<Option<Vec<u8>>, StoreError>;

    /// Appends `values` (rows x `channels`, already validated as finite) starting at
    /// `start_row` without a writer lease (tests and the demo's own sessions); see
    /// [`Rows::append_raw`].
    async fn append_rows(
        &self,
        session_id: &str,
        start_row: u64,
        channels: usize,
        values: &[f64],
    ) -> Result<AppendOutcome, StoreError> {
        debug_assert!(channels > 0 && values.len().is_multiple_of(channels));
        let blob: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        self.append_raw(session_id, None, start_row, channels * 8, &blob)
            .await
    }

    /// [`Rows::read_raw_chunks`] of an f64 session, decoded: (start_row, values) with values
    /// row-major (rows x channels).
    async fn read_chunks(
        &self,
        session_id: &str,
        from_row: u64,
        max_chunks: u32,
    ) -> Result<Vec<(u64, Vec<f64>)>, StoreError> {
        let raw = self
            .read_raw_chunks(session_id, from_row, max_chunks, 8)
            .await?;
        Ok(raw
            .into_iter()
            .map(|(start, _, data)| {
                (
                    start,
                    data.chunks_exact(8)
                        .map(|b| f64::from_le_bytes(b.try_into().expect("8")))
                        .collect(),
                )
            })
            .collect())
    }
}

/// A stored chunk of either backend (`start_row, row_count, data`).
pub(crate) fn raw_chunk(row: &impl StoreRow) -> RawChunk {
    (
        row.int("start_row") as u64,
        row.int("row_count") as u64,
        row.bytes("data"),
    )
}
