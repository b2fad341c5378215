//! Bucket rows: append with resume semantics, read back in order.

use sqlx::Row;

use super::{Store, StoreError};

/// What one append did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AppendOutcome {
    /// The authoritative committed count after this append.
    pub committed_rows: u64,
    /// Rows of the chunk that were new and are now durable.
    pub written: u64,
    /// Rows of the chunk that were already committed (overlap).
    pub skipped: u64,
}

impl Store {
    /// Appends `values` (rows x `channels`, already validated as finite) starting at `start_row`.
    ///
    /// The committed count is authoritative: rows below it are skipped, a start above it is a gap
    /// and writes nothing. The new rows and the new count commit in one transaction.
    pub async fn append_rows(
        &self,
        session_id: &str,
        start_row: u64,
        channels: usize,
        values: &[f64],
    ) -> Result<AppendOutcome, StoreError> {
        debug_assert!(channels > 0 && values.len().is_multiple_of(channels));
        let blob: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        self.append_raw(session_id, start_row, channels * 8, &blob)
            .await
    }

    /// Appends rows already encoded in the session's sample format (`row_bytes` bytes each,
    /// validated by the caller), with the resume semantics of [`Store::append_rows`].
    pub async fn append_raw(
        &self,
        session_id: &str,
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
        if end <= committed {
            return Ok(AppendOutcome {
                committed_rows: committed,
                written: 0,
                skipped: rows,
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
            skipped: skip,
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
