//! Adaptive sessions' issued batches in PostgreSQL.

use async_trait::async_trait;
use sqlx::Row;

use super::rows::hold_lease;
use super::{Postgres, begin};
use crate::store::batches::{batch_from_row, check_next, indices_blob};
use crate::store::{Batches, IssuedBatch, StoreError, WriterLease};

#[async_trait]
impl Batches for Postgres {
    async fn issue_batch(
        &self,
        session_id: &str,
        lease: Option<&WriterLease>,
        batch: &IssuedBatch,
        end_row: u64,
    ) -> Result<u64, StoreError> {
        // The session's row lock serialises its batches and appends across every node.
        let mut tx = begin(&self.pool).await?;
        let row = sqlx::query("SELECT issued_rows FROM sessions WHERE id = $1 FOR UPDATE")
            .bind(session_id)
            .fetch_optional(&mut *tx)
            .await?
            .ok_or_else(|| StoreError::SessionNotFound(session_id.to_string()))?;
        let issued = row.get::<Option<i64>, _>("issued_rows").map(|v| v as u64);
        if let Some(lease) = lease {
            hold_lease(&mut tx, session_id, lease).await?;
        }
        let count: i64 =
            sqlx::query("SELECT COUNT(*)::BIGINT FROM adaptive_batches WHERE session_id = $1")
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
             VALUES ($1, $2, $3, $4, $5, helmholtz_now_ms())",
        )
        .bind(session_id)
        .bind(batch.number as i64)
        .bind(batch.first_row as i64)
        .bind(batch.indices.len() as i64)
        .bind(indices_blob(&batch.indices))
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
