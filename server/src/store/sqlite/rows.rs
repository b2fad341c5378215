//! Measured rows in SQLite.

use async_trait::async_trait;
use sqlx::Row;

use super::Sqlite;
use crate::store::rows::raw_chunk;
use crate::store::rows::{check_bounds, check_chunks, check_issued, compare_overlap, row_of_chunk};
use crate::store::{AppendOutcome, RawChunk, Rows, StoreError, WriterLease, now_ms};

#[async_trait]
impl Rows for Sqlite {
    async fn acquire_writer(&self, lease: &WriterLease) -> Result<bool, StoreError> {
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

    async fn renew_writer(&self, lease: &WriterLease) -> Result<bool, StoreError> {
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

    async fn release_writer(&self, lease: &WriterLease) -> Result<(), StoreError> {
        sqlx::query("DELETE FROM upload_leases WHERE session_id = $1 AND holder = $2")
            .bind(&lease.session_id)
            .bind(&lease.holder)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    async fn append_raw(
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
        let row = sqlx::query(
            "SELECT committed_rows, expected_rows, state, issued_rows FROM sessions WHERE id = $1",
        )
        .bind(session_id)
        .fetch_optional(&mut *tx)
        .await?
        .ok_or_else(|| StoreError::SessionNotFound(session_id.to_string()))?;
        if let Some(lease) = lease {
            hold_lease(&mut tx, session_id, lease).await?;
        }
        let committed = row.get::<i64, _>("committed_rows") as u64;
        let expected = row.get::<i64, _>("expected_rows") as u64;
        let state: String = row.get("state");
        let end = start_row + rows;
        let overlap_end = check_bounds(committed, expected, start_row, end)?;
        let issued = row.get::<Option<i64>, _>("issued_rows").map(|v| v as u64);
        check_issued(session_id, issued, end)?;
        if overlap_end > start_row {
            let chunks: Vec<RawChunk> = sqlx::query(
                "SELECT start_row, row_count, data FROM measurement_chunks \
                 WHERE session_id = $1 AND start_row < $3 AND start_row + row_count > $2 ORDER BY start_row",
            )
            .bind(session_id)
            .bind(start_row as i64)
            .bind(overlap_end as i64)
            .fetch_all(&mut *tx)
            .await?
            .iter()
            .map(raw_chunk)
            .collect();
            compare_overlap(
                session_id,
                committed,
                start_row,
                overlap_end,
                end,
                &chunks,
                row_bytes,
                payload,
            )?;
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

    async fn read_raw_chunks(
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
        let chunks: Vec<RawChunk> = rows.iter().map(raw_chunk).collect();
        check_chunks(session_id, from_row, &chunks, sample_bytes)?;
        Ok(chunks)
    }

    async fn read_row(
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
        row_of_chunk(session_id, &raw_chunk(&found), row, row_bytes)
    }
}

/// Renews `lease` inside `tx` (an append's or a batch's own transaction): refused
/// ([`StoreError::WriterLost`]) unless the lease is still this holder's.
pub(super) async fn hold_lease(
    tx: &mut sqlx::SqliteConnection,
    session_id: &str,
    lease: &WriterLease,
) -> Result<(), StoreError> {
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
    Ok(())
}
