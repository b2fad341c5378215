//! Adaptive sessions' issued batches in SQLite.

use async_trait::async_trait;
use sqlx::Row;

use super::Sqlite;
use super::rows::hold_lease;
use crate::store::batches::{batch_from_row, check_next, indices_blob};
use crate::store::{Batches, IssuedBatch, StoreError, WriterLease, now_ms};

#[async_trait]
impl Batches for Sqlite {
    async fn issue_batch(
        &self,
        session_id: &str,
        lease: Option<&WriterLease>,
        batch: &IssuedBatch,
        end_row: u64,
    ) -> Result<u64, StoreError> {
        // BEGIN IMMEDIATE: the checks and the insert under the write lock, like an append.
        let mut tx = self.pool.begin_with("BEGIN IMMEDIATE").await?;
        let row = sqlx::query("SELECT issued_rows FROM sessions WHERE id = $1")
            .bind(session_id)
            .fetch_optional(&mut *tx)
            .await?
            .ok_or_else(|| StoreError::SessionNotFound(session_id.to_string()))?;
        let issued = row.get::<Option<i64>, _>("issued_rows").map(|v| v as u64);
        if let Some(lease) = lease {
            hold_lease(&mut tx, session_id, lease).await?;
        }
        let count: i64 = sqlx::query("SELECT COUNT(*) FROM adaptive_batches WHERE session_id = $1")
            .bind(session_id)
            .fetch_one(&mut *tx)
            .await?
            .get(0);
        let stored = sqlx::query(
            "SELECT number, first_row, pairs, indices FROM adaptive_batches WHERE session_id = $1 AND number = $2",
        )
        .bind(session_id)
        .bind(batch.number as i64)
        .fetch_optional(&mut *tx)
        .await?
        .as_ref()
        .map(batch_from_row)
        .transpose()?;
        if !check_next(session_id, issued, stored, count as u64, batch)? {
            tx.commit().await?; // the lease renewal
            return Ok(issued.unwrap_or(0));
        }
        sqlx::query(
            "INSERT INTO adaptive_batches (session_id, number, first_row, pairs, indices, issued_ms) \
             VALUES ($1, $2, $3, $4, $5, $6)",
        )
        .bind(session_id)
        .bind(batch.number as i64)
        .bind(batch.first_row as i64)
        .bind(batch.indices.len() as i64)
        .bind(indices_blob(&batch.indices))
        .bind(now_ms())
        .execute(&mut *tx)
        .await?;
        let end = end_row;
        sqlx::query("UPDATE sessions SET issued_rows = $2 WHERE id = $1")
            .bind(session_id)
            .bind(end as i64)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(end)
    }

    async fn batches(&self, session_id: &str) -> Result<Vec<IssuedBatch>, StoreError> {
        sqlx::query(
            "SELECT number, first_row, pairs, indices FROM adaptive_batches \
             WHERE session_id = $1 ORDER BY number",
        )
        .bind(session_id)
        .fetch_all(&self.pool)
        .await?
        .iter()
        .map(batch_from_row)
        .collect()
    }
}
