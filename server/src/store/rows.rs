//! Measured rows: append under a writer lease, overlap compared byte for byte, read back in
//! order.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use sqlx::Row;

use super::{Store, StoreError, now_ms};

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

/// The upload lease a writer holds (see [`Store::acquire_writer`]): every append under it
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

/// Where a chunk's overlap first differs from the stored rows.
fn first_difference(stored: &[u8], sent: &[u8], row_bytes: usize) -> Option<(u64, usize)> {
    let i = stored.iter().zip(sent).position(|(a, b)| a != b)?;
    Some(((i / row_bytes) as u64, i % row_bytes))
}

impl Store {
    /// Takes `lease`'s session for its holder unless another writer's live stream has it: true
    /// when taken (or already held by this holder, or by an earlier stream of the same writer,
    /// which is fenced off from then on).
    pub async fn acquire_writer(&self, lease: &WriterLease) -> Result<bool, StoreError> {
        let now = now_ms();
        let taken = sqlx::query(
            "INSERT INTO upload_leases (session_id, holder, writer, expires_ms) VALUES ($1, $2, $3, $4) \
             ON CONFLICT (session_id) DO UPDATE SET holder = excluded.holder, writer = excluded.writer, \
             expires_ms = excluded.expires_ms \
             WHERE upload_leases.expires_ms <= $5 OR upload_leases.holder = excluded.holder \
             OR (excluded.writer <> '' AND upload_leases.writer = excluded.writer)",
        )
        .bind(&lease.session_id)
        .bind(&lease.holder)
        .bind(&lease.writer)
        .bind(now + lease.ttl.as_millis() as i64)
        .bind(now)
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(taken == 1)
    }

    /// Extends `lease` by its ttl from now; false when it is no longer this holder's.
    pub async fn renew_writer(&self, lease: &WriterLease) -> Result<bool, StoreError> {
        let n = sqlx::query(
            "UPDATE upload_leases SET expires_ms = $3 WHERE session_id = $1 AND holder = $2",
        )
        .bind(&lease.session_id)
        .bind(&lease.holder)
        .bind(now_ms() + lease.ttl.as_millis() as i64)
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(n == 1)
    }

    /// Gives the lease back (if it is still this holder's).
    pub async fn release_writer(&self, lease: &WriterLease) -> Result<(), StoreError> {
        sqlx::query("DELETE FROM upload_leases WHERE session_id = $1 AND holder = $2")
            .bind(&lease.session_id)
            .bind(&lease.holder)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Appends `values` (rows x `channels`, already validated as finite) starting at `start_row`
    /// without a writer lease (tests and the demo's own sessions); see [`Store::append_raw`].
    pub async fn append_rows(
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

    /// Appends rows already encoded in the session's sample format (`row_bytes` bytes each,
    /// validated by the caller) starting at `start_row`. A row's identity is (session, index):
    ///
    /// - rows below the committed count must be byte for byte the stored ones, else the chunk
    ///   is refused ([`StoreError::RowMismatch`], naming the first differing row) and nothing
    ///   of it is stored;
    /// - a start above the committed count is a gap and writes nothing;
    /// - new rows into a finished session are refused;
    /// - with a `lease`, the append is refused unless the lease is still this writer's
    ///   (checked and renewed in the same transaction: a writer that lost its lease to another
    ///   cannot write after it).
    ///
    /// The new rows and the new count commit in one transaction.
    pub async fn append_raw(
        &self,
        session_id: &str,
        lease: Option<&WriterLease>,
        start_row: u64,
        row_bytes: usize,
        payload: &[u8],
    ) -> Result<AppendOutcome, StoreError> {
        debug_assert!(row_bytes > 0 && payload.len().is_multiple_of(row_bytes));
        let rows = (payload.len() / row_bytes) as u64;
        // BEGIN IMMEDIATE takes the write lock up front: read-then-write without upgrade failures.
        let mut tx = self.pool.begin_with("BEGIN IMMEDIATE").await?;
        let row =
            sqlx::query("SELECT committed_rows, expected_rows, state FROM sessions WHERE id = $1")
                .bind(session_id)
                .fetch_optional(&mut *tx)
                .await?
                .ok_or_else(|| StoreError::SessionNotFound(session_id.to_string()))?;
        if let Some(lease) = lease {
            let held = sqlx::query(
                "UPDATE upload_leases SET expires_ms = $3 WHERE session_id = $1 AND holder = $2",
            )
            .bind(session_id)
            .bind(&lease.holder)
            .bind(now_ms() + lease.ttl.as_millis() as i64)
            .execute(&mut *tx)
            .await?
            .rows_affected();
            if held != 1 {
                return Err(StoreError::WriterLost(session_id.to_string()));
            }
        }
        let committed = row.get::<i64, _>("committed_rows") as u64;
        let expected = row.get::<i64, _>("expected_rows") as u64;
        let state: String = row.get("state");
        if start_row > committed {
            return Err(StoreError::Gap {
                committed,
                start: start_row,
            });
        }
        let end = start_row + rows;
        if end > expected {
            return Err(StoreError::PastEnd { end, expected });
        }
        // The overlap: rows start_row..min(end, committed), compared with what is stored.
        let overlap_end = end.min(committed);
        if overlap_end > start_row {
            let chunks = sqlx::query(
                "SELECT start_row, row_count, data FROM measurement_chunks \
                 WHERE session_id = $1 AND start_row < $3 AND start_row + row_count > $2 ORDER BY start_row",
            )
            .bind(session_id)
            .bind(start_row as i64)
            .bind(overlap_end as i64)
            .fetch_all(&mut *tx)
            .await?;
            let mut next = start_row;
            for chunk in chunks {
                let c_start = chunk.get::<i64, _>("start_row") as u64;
                let c_rows = chunk.get::<i64, _>("row_count") as u64;
                let data: Vec<u8> = chunk.get("data");
                if c_start > next || data.len() as u64 != c_rows * row_bytes as u64 {
                    return Err(StoreError::Corrupt(format!(
                        "session {session_id}: stored chunk at row {c_start} does not continue row {next}"
                    )));
                }
                let hi = overlap_end.min(c_start + c_rows);
                let stored = &data
                    [(next - c_start) as usize * row_bytes..(hi - c_start) as usize * row_bytes];
                let sent = &payload[(next - start_row) as usize * row_bytes
                    ..(hi - start_row) as usize * row_bytes];
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
        }
        if end <= committed {
            tx.commit().await?; // the lease renewal
            return Ok(AppendOutcome {
                committed_rows: committed,
                written: 0,
                matched: rows,
            });
        }
        if state == "finished" {
            return Err(StoreError::Finished(session_id.to_string()));
        }
        let skip = committed - start_row;
        let blob = &payload[skip as usize * row_bytes..];
        sqlx::query("INSERT INTO measurement_chunks (session_id, start_row, row_count, data) VALUES ($1, $2, $3, $4)")
            .bind(session_id)
            .bind(committed as i64)
            .bind((end - committed) as i64)
            .bind(blob)
            .execute(&mut *tx)
            .await?;
        sqlx::query("UPDATE sessions SET committed_rows = $2 WHERE id = $1")
            .bind(session_id)
            .bind(end as i64)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(AppendOutcome {
            committed_rows: end,
            written: end - committed,
            matched: skip,
        })
    }

    /// Up to `max_chunks` stored chunks of the session whose rows start at or after `from_row`,
    /// in order, as (start_row, values) with values row-major (rows x channels).
    ///
    /// `from_row` must be a chunk boundary (0, or the end of a chunk returned before).
    pub async fn read_chunks(
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

    /// Like [`Store::read_chunks`] but undecoded: (start_row, row_count, bytes) with
    /// `sample_bytes` bytes per stored value.
    pub async fn read_raw_chunks(
        &self,
        session_id: &str,
        from_row: u64,
        max_chunks: u32,
        sample_bytes: usize,
    ) -> Result<Vec<(u64, u64, Vec<u8>)>, StoreError> {
        let rows = sqlx::query(
            "SELECT start_row, row_count, data FROM measurement_chunks \
             WHERE session_id = $1 AND start_row >= $2 ORDER BY start_row LIMIT $3",
        )
        .bind(session_id)
        .bind(from_row as i64)
        .bind(max_chunks as i64)
        .fetch_all(&self.pool)
        .await?;
        let mut out = Vec::with_capacity(rows.len());
        let mut expect = from_row;
        for row in rows {
            let start = row.get::<i64, _>("start_row") as u64;
            let count = row.get::<i64, _>("row_count") as u64;
            let data: Vec<u8> = row.get("data");
            if start != expect
                || !data.len().is_multiple_of(sample_bytes)
                || count == 0
                || !((data.len() / sample_bytes) as u64).is_multiple_of(count)
            {
                return Err(StoreError::Corrupt(format!(
                    "session {session_id}: chunk at row {start} does not continue row {expect}"
                )));
            }
            out.push((start, count, data));
            expect = start + count;
        }
        Ok(out)
    }

    /// Stored row `row` (`row_bytes` bytes in the session's format), or `None` past the
    /// committed rows.
    pub async fn read_row(
        &self,
        session_id: &str,
        row: u64,
        row_bytes: usize,
    ) -> Result<Option<Vec<u8>>, StoreError> {
        let found = sqlx::query(
            "SELECT start_row, row_count, data FROM measurement_chunks \
             WHERE session_id = $1 AND start_row <= $2 ORDER BY start_row DESC LIMIT 1",
        )
        .bind(session_id)
        .bind(row as i64)
        .fetch_optional(&self.pool)
        .await?;
        let Some(found) = found else { return Ok(None) };
        let (start, count) = (
            found.get::<i64, _>("start_row") as u64,
            found.get::<i64, _>("row_count") as u64,
        );
        if row >= start + count {
            return Ok(None);
        }
        let data: Vec<u8> = found.get("data");
        let offset = (row - start) as usize * row_bytes;
        data.get(offset..offset + row_bytes)
            .map(|b| Some(b.to_vec()))
            .ok_or_else(|| {
                StoreError::Corrupt(format!(
                    "session {session_id}: chunk at row {start} is shorter than its rows"
                ))
            })
    }
}
