//! Shards of transport jobs in PostgreSQL. Every write for a shard's run carries
//! `AND attempt = ?`, the fence; a claim takes its shard `FOR UPDATE SKIP LOCKED` (claims on
//! many nodes never wait for each other nor take the same shard); times come from the
//! database's clock (`helmholtz_now_ms()`).

use async_trait::async_trait;
use sqlx::Row;

use super::{Postgres, begin};
use crate::store::shards::parts_in_order;
use crate::store::shards::shard_from_row;
use crate::store::{ClaimedShard, ShardRow, Shards, StoreError};

#[async_trait]
impl Shards for Postgres {
    async fn start_shards(
        &self,
        id: i64,
        job_attempt: i64,
        model_json: &str,
        shards: &[(u64, u64)],
    ) -> Result<Option<String>, StoreError> {
        let mut tx = begin(&self.pool).await?;
        // The job's row lock orders this against the job's other writes (a cancel, a claim).
        let job = sqlx::query(
            "SELECT max_attempts FROM jobs WHERE id = $1 AND attempt = $2 AND state = 'running' FOR UPDATE",
        )
        .bind(id)
        .bind(job_attempt)
        .fetch_optional(&mut *tx)
        .await?;
        let Some(job) = job else {
            tx.rollback().await?;
            return Ok(None);
        };
        let max_attempts: i64 = job.get(0);
        let stored: Option<String> =
            sqlx::query("SELECT transport_model FROM reconstructions WHERE id = $1 FOR UPDATE")
                .bind(id)
                .fetch_one(&mut *tx)
                .await?
                .get(0);
        if let Some(stored) = stored {
            tx.commit().await?;
            return Ok(Some(stored));
        }
        sqlx::query("UPDATE reconstructions SET transport_model = $2 WHERE id = $1")
            .bind(id)
            .bind(model_json)
            .execute(&mut *tx)
            .await?;
        for (i, (first, end)) in shards.iter().enumerate() {
            sqlx::query(
                "INSERT INTO transport_shards (reconstruction_id, shard, first_block, end_block, max_attempts, created_ms) \
                 VALUES ($1, $2, $3, $4, $5, helmholtz_now_ms()) ON CONFLICT DO NOTHING",
            )
            .bind(id)
            .bind(i as i64)
            .bind(*first as i64)
            .bind(*end as i64)
            .bind(max_attempts)
            .execute(&mut *tx)
            .await?;
        }
        // Wakes idle workers on every node (delivered at commit).
        sqlx::query("SELECT pg_notify($1, '')")
            .bind(super::JOBS_CHANNEL)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(Some(model_json.to_string()))
    }

    async fn transport_model(&self, id: i64) -> Result<Option<String>, StoreError> {
        let row = sqlx::query("SELECT transport_model FROM reconstructions WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.and_then(|r| r.get(0)))
    }

    async fn claim_shard(
        &self,
        worker_id: &str,
        lease_ms: i64,
        max_memory: u64,
        only: Option<i64>,
    ) -> Result<Option<ClaimedShard>, StoreError> {
        let mut tx = begin(&self.pool).await?;
        sqlx::query(
            "UPDATE transport_shards SET state = 'failed', finished_ms = helmholtz_now_ms(), \
             last_error = COALESCE(last_error, 'worker lost its lease') || ' (no attempts left)' \
             WHERE state = 'running' AND lease_until_ms < helmholtz_now_ms() AND attempt >= max_attempts",
        )
        .execute(&mut *tx)
        .await?;
        let claimed = sqlx::query(
            "WITH clock AS (SELECT helmholtz_now_ms() AS ms), \
             pick AS ( \
                 SELECT s.reconstruction_id, s.shard FROM transport_shards s JOIN jobs j ON j.id = s.reconstruction_id \
                 WHERE j.state = 'running' AND j.memory_bytes <= $3 \
                 AND ($4::BIGINT IS NULL OR s.reconstruction_id = $4) \
                 AND (s.state = 'queued' OR (s.state = 'running' AND s.lease_until_ms < (SELECT ms FROM clock) \
                      AND s.attempt < s.max_attempts)) \
                 ORDER BY s.reconstruction_id, s.shard LIMIT 1 \
                 FOR UPDATE OF s SKIP LOCKED) \
             UPDATE transport_shards t SET state = 'running', attempt = t.attempt + 1, \
             lease_until_ms = (SELECT ms FROM clock) + $1, worker_id = $2, started_ms = (SELECT ms FROM clock) \
             FROM pick WHERE t.reconstruction_id = pick.reconstruction_id AND t.shard = pick.shard \
             RETURNING t.reconstruction_id, t.shard, t.attempt, t.first_block, t.end_block",
        )
        .bind(lease_ms)
        .bind(worker_id)
        .bind(max_memory.min(i64::MAX as u64) as i64)
        .bind(only)
        .fetch_optional(&mut *tx)
        .await?;
        tx.commit().await?;
        let Some(row) = claimed else { return Ok(None) };
        let id: i64 = row.get("reconstruction_id");
        let job = sqlx::query(
            "SELECT r.session_id, r.rows_used, r.params_json, r.transport_model, j.memory_bytes \
             FROM reconstructions r JOIN jobs j ON j.id = r.id WHERE r.id = $1",
        )
        .bind(id)
        .fetch_one(&self.pool)
        .await?;
        Ok(Some(ClaimedShard {
            reconstruction_id: id,
            shard: row.get("shard"),
            attempt: row.get("attempt"),
            first_block: row.get::<i64, _>("first_block") as u64,
            end_block: row.get::<i64, _>("end_block") as u64,
            memory_bytes: job.get::<i64, _>("memory_bytes").max(0) as u64,
            session_id: job.get("session_id"),
            rows_used: job.get::<i64, _>("rows_used") as u64,
            params_json: job.get("params_json"),
            model_json: job
                .get::<Option<String>, _>("transport_model")
                .ok_or_else(|| {
                    StoreError::Corrupt(format!("reconstruction {id} has shards but no model"))
                })?,
        }))
    }

    async fn heartbeat_shard(
        &self,
        id: i64,
        shard: i64,
        attempt: i64,
        lease_ms: i64,
    ) -> Result<bool, StoreError> {
        let changed = sqlx::query(
            "UPDATE transport_shards SET lease_until_ms = helmholtz_now_ms() + $4 \
             WHERE reconstruction_id = $1 AND shard = $2 AND attempt = $3 AND state = 'running' \
             AND EXISTS (SELECT 1 FROM jobs WHERE id = $1 AND state = 'running')",
        )
        .bind(id)
        .bind(shard)
        .bind(attempt)
        .bind(lease_ms)
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(changed == 1)
    }

    async fn complete_shard(
        &self,
        id: i64,
        shard: i64,
        attempt: i64,
        part: &[u8],
    ) -> Result<bool, StoreError> {
        let changed = sqlx::query(
            "UPDATE transport_shards SET state = 'done', part = $4, finished_ms = helmholtz_now_ms(), lease_until_ms = NULL \
             WHERE reconstruction_id = $1 AND shard = $2 AND attempt = $3 AND state = 'running' \
             AND EXISTS (SELECT 1 FROM jobs WHERE id = $1 AND state = 'running')",
        )
        .bind(id)
        .bind(shard)
        .bind(attempt)
        .bind(part)
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(changed == 1)
    }

    async fn fail_shard(
        &self,
        id: i64,
        shard: i64,
        attempt: i64,
        error: &str,
        retry: bool,
    ) -> Result<bool, StoreError> {
        let changed = sqlx::query(
            "UPDATE transport_shards SET last_error = $4, lease_until_ms = NULL, \
             state = CASE WHEN $5 AND attempt < max_attempts THEN 'queued' ELSE 'failed' END, \
             finished_ms = CASE WHEN $5 AND attempt < max_attempts THEN NULL ELSE helmholtz_now_ms() END \
             WHERE reconstruction_id = $1 AND shard = $2 AND attempt = $3 AND state = 'running'",
        )
        .bind(id)
        .bind(shard)
        .bind(attempt)
        .bind(error)
        .bind(retry)
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(changed == 1)
    }

    async fn release_shard(&self, id: i64, shard: i64, attempt: i64) -> Result<bool, StoreError> {
        let changed = sqlx::query(
            "UPDATE transport_shards SET state = 'queued', attempt = attempt - 1, lease_until_ms = NULL \
             WHERE reconstruction_id = $1 AND shard = $2 AND attempt = $3 AND state = 'running'",
        )
        .bind(id)
        .bind(shard)
        .bind(attempt)
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(changed == 1)
    }

    async fn shards(&self, id: i64) -> Result<Vec<ShardRow>, StoreError> {
        let rows = sqlx::query(
            "SELECT reconstruction_id, shard, first_block, end_block, state, attempt, worker_id, last_error, \
             CAST(octet_length(part) AS BIGINT) AS part_bytes, started_ms, finished_ms \
             FROM transport_shards WHERE reconstruction_id = $1 ORDER BY shard",
        )
        .bind(id)
        .fetch_all(&self.pool)
        .await?;
        Ok(rows.iter().map(shard_from_row).collect())
    }

    async fn shard_parts(&self, id: i64) -> Result<Vec<Vec<u8>>, StoreError> {
        let rows = sqlx::query(
            "SELECT shard, state, part FROM transport_shards WHERE reconstruction_id = $1 ORDER BY shard",
        )
        .bind(id)
        .fetch_all(&self.bulk)
        .await?;
        parts_in_order(
            id,
            rows.iter()
                .map(|r| (r.get("shard"), r.get("state"), r.get("part")))
                .collect(),
        )
    }
}
