//! The job queue and results in PostgreSQL. Every write for a run carries `AND attempt = ?`,
//! the fence; times come from the database's clock (`helmholtz_now_ms()`), so leases mean the
//! same on every node.

use async_trait::async_trait;
use sqlx::Row;

use super::{Postgres, advisory_lock, begin, lab_lock};
use crate::store::jobs::recon_from_row;
use crate::store::{
    ClaimedJob, Jobs, ReconstructionRow, StoreError, StoredImage, f32_to_le, le_to_f32,
};

/// Largest blob of one stored transport part (a bytea value is materialised whole on both ends).
const TRANSPORT_PART_BYTES: usize = 8 << 20;

const RECON_COLUMNS: &str = "r.id, j.lab, r.session_id, r.method, r.params_json, r.rows_used, j.state, \
     j.progress, j.attempt, j.last_error, r.report_json, r.seconds, j.created_ms, j.started_ms, j.finished_ms";

#[async_trait]
impl Jobs for Postgres {
    #[allow(clippy::too_many_arguments)]
    async fn enqueue_reconstruction_capped(
        &self,
        lab: &str,
        session_id: &str,
        method: &str,
        params_json: &str,
        rows_used: u64,
        max_attempts: u32,
        max_pending: u64,
        memory_bytes: u64,
    ) -> Result<ReconstructionRow, StoreError> {
        // The lab's advisory lock makes the count and the insert atomic across every node.
        let mut tx = begin(&self.pool).await?;
        lab_lock(&mut tx, "jobs", lab).await?;
        let pending: i64 = sqlx::query(
            "SELECT COUNT(*) FROM jobs WHERE lab = $1 AND state IN ('queued', 'running')",
        )
        .bind(lab)
        .fetch_one(&mut *tx)
        .await?
        .get(0);
        if pending as u64 >= max_pending {
            return Err(StoreError::Cap {
                limit: "max_pending_jobs_per_lab",
                message: format!(
                    "lab {lab:?} has {pending} reconstructions queued or running (limit {max_pending}); wait for some to finish or cancel them"
                ),
            });
        }
        let id: i64 = sqlx::query(
            "INSERT INTO jobs (kind, state, run_at_ms, max_attempts, created_ms, lab, memory_bytes) \
             VALUES ('reconstruction', 'queued', helmholtz_now_ms(), $1, helmholtz_now_ms(), $2, $3) RETURNING id",
        )
        .bind(max_attempts as i64)
        .bind(lab)
        .bind(memory_bytes.min(i64::MAX as u64) as i64)
        .fetch_one(&mut *tx)
        .await?
        .get(0);
        sqlx::query(
            "INSERT INTO reconstructions (id, session_id, method, params_json, rows_used) VALUES ($1, $2, $3, $4, $5)",
        )
        .bind(id)
        .bind(session_id)
        .bind(method)
        .bind(params_json)
        .bind(rows_used as i64)
        .execute(&mut *tx)
        .await?;
        // Wakes idle workers on every node (delivered at commit; a hint, never the only way).
        sqlx::query("SELECT pg_notify($1, '')")
            .bind(super::JOBS_CHANNEL)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        self.reconstruction(id).await
    }

    async fn get_reconstruction(&self, id: i64) -> Result<Option<ReconstructionRow>, StoreError> {
        let sql = format!(
            "SELECT {RECON_COLUMNS} FROM reconstructions r JOIN jobs j ON j.id = r.id WHERE r.id = $1"
        );
        let row = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.as_ref().map(recon_from_row))
    }

    async fn session_reconstructions(
        &self,
        session_id: &str,
    ) -> Result<Vec<ReconstructionRow>, StoreError> {
        let sql = format!(
            "SELECT {RECON_COLUMNS} FROM reconstructions r JOIN jobs j ON j.id = r.id \
             WHERE r.session_id = $1 ORDER BY r.id DESC"
        );
        let rows = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(session_id)
            .fetch_all(&self.pool)
            .await?;
        Ok(rows.iter().map(recon_from_row).collect())
    }

    async fn latest_done(&self, session_id: &str) -> Result<Option<i64>, StoreError> {
        let row = sqlx::query(
            "SELECT r.id FROM reconstructions r JOIN jobs j ON j.id = r.id \
             WHERE r.session_id = $1 AND j.state = 'done' ORDER BY j.finished_ms DESC, r.id DESC LIMIT 1",
        )
        .bind(session_id)
        .fetch_optional(&self.pool)
        .await?;
        Ok(row.map(|r| r.get(0)))
    }

    async fn claim_job_within(
        &self,
        worker_id: &str,
        lease_ms: i64,
        max_running_per_lab: u32,
        max_memory: u64,
    ) -> Result<Option<ClaimedJob>, StoreError> {
        // One claim at a time across all nodes: the fairness order and the per-lab cap are
        // decided on a consistent count of running jobs. SKIP LOCKED keeps a claim from waiting
        // on a job row another transaction is writing (a heartbeat, a cancel).
        let mut tx = begin(&self.pool).await?;
        advisory_lock(&mut tx, "claim").await?;
        sqlx::query(
            "UPDATE jobs SET state = 'failed', finished_ms = helmholtz_now_ms(), \
             last_error = COALESCE(last_error, 'worker lost its lease') || ' (no attempts left)' \
             WHERE state = 'running' AND lease_until_ms < helmholtz_now_ms() AND attempt >= max_attempts",
        )
        .execute(&mut *tx)
        .await?;
        let claimed = sqlx::query(
            "WITH clock AS (SELECT helmholtz_now_ms() AS ms), \
             lab_load AS ( \
                 SELECT lab, \
                        COUNT(*) FILTER (WHERE state = 'running' AND lease_until_ms >= (SELECT ms FROM clock)) AS running, \
                        MAX(started_ms) AS last_start \
                 FROM jobs WHERE lab IN (SELECT DISTINCT lab FROM jobs WHERE state IN ('queued', 'running')) \
                 GROUP BY lab), \
             pick AS ( \
                 SELECT j.id FROM jobs j JOIN lab_load l ON l.lab = j.lab \
                 WHERE j.run_at_ms <= (SELECT ms FROM clock) AND \
                 (j.state = 'queued' OR (j.state = 'running' AND j.lease_until_ms < (SELECT ms FROM clock) AND j.attempt < j.max_attempts)) \
                 AND ($3 <= 0 OR l.running < $3) AND j.memory_bytes <= $4 \
                 ORDER BY l.running, COALESCE(l.last_start, 0), j.priority DESC, j.run_at_ms, j.id LIMIT 1 \
                 FOR UPDATE OF j SKIP LOCKED) \
             UPDATE jobs SET state = 'running', attempt = attempt + 1, \
             lease_until_ms = (SELECT ms FROM clock) + $1, worker_id = $2, started_ms = (SELECT ms FROM clock), progress = 0 \
             FROM pick WHERE jobs.id = pick.id \
             RETURNING jobs.id, jobs.attempt, jobs.memory_bytes",
        )
        .bind(lease_ms)
        .bind(worker_id)
        .bind(max_running_per_lab as i64)
        .bind(max_memory.min(i64::MAX as u64) as i64)
        .fetch_optional(&mut *tx)
        .await?;
        tx.commit().await?;
        let Some(row) = claimed else { return Ok(None) };
        let id: i64 = row.get("id");
        let attempt: i64 = row.get("attempt");
        let memory_bytes: i64 = row.get("memory_bytes");
        Ok(Some(ClaimedJob {
            id,
            attempt,
            memory_bytes: memory_bytes.max(0) as u64,
            reconstruction: self.reconstruction(id).await?,
        }))
    }

    async fn heartbeat(
        &self,
        id: i64,
        attempt: i64,
        lease_ms: i64,
        progress: f64,
    ) -> Result<bool, StoreError> {
        let changed = sqlx::query(
            "UPDATE jobs SET lease_until_ms = helmholtz_now_ms() + $3, progress = $4 \
             WHERE id = $1 AND attempt = $2 AND state = 'running'",
        )
        .bind(id)
        .bind(attempt)
        .bind(lease_ms)
        .bind(progress)
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(changed == 1)
    }

    async fn complete_reconstruction(
        &self,
        id: i64,
        attempt: i64,
        images: &[StoredImage],
        transport: Option<&[u8]>,
        report_json: &str,
        seconds: f64,
    ) -> Result<bool, StoreError> {
        let mut tx = begin(&self.pool).await?;
        let fenced = sqlx::query(
            "UPDATE jobs SET state = 'done', progress = 1, finished_ms = helmholtz_now_ms(), lease_until_ms = NULL \
             WHERE id = $1 AND attempt = $2 AND state = 'running'",
        )
        .bind(id)
        .bind(attempt)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        if fenced != 1 {
            tx.rollback().await?;
            return Ok(false);
        }
        sqlx::query("UPDATE reconstructions SET report_json = $2, seconds = $3 WHERE id = $1")
            .bind(id)
            .bind(report_json)
            .bind(seconds)
            .execute(&mut *tx)
            .await?;
        // T is stored whole below: the parts of its shards (if it was solved in shards) are
        // dropped, their rows (who solved what, when) kept.
        sqlx::query("UPDATE transport_shards SET part = NULL WHERE reconstruction_id = $1")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        for image in images {
            sqlx::query(
                "INSERT INTO dual_images (reconstruction_id, channel_index, channel_name, width, height, data) \
                 VALUES ($1, $2, $3, $4, $5, $6)",
            )
            .bind(id)
            .bind(image.channel_index as i64)
            .bind(&image.channel_name)
            .bind(image.width as i64)
            .bind(image.height as i64)
            .bind(f32_to_le(&image.data))
            .execute(&mut *tx)
            .await?;
        }
        for (part, data) in transport
            .unwrap_or_default()
            .chunks(TRANSPORT_PART_BYTES)
            .enumerate()
        {
            sqlx::query(
                "INSERT INTO transports (reconstruction_id, part, data) VALUES ($1, $2, $3)",
            )
            .bind(id)
            .bind(part as i64)
            .bind(data)
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        Ok(true)
    }

    async fn transport(&self, id: i64) -> Result<Option<Vec<u8>>, StoreError> {
        let parts =
            sqlx::query("SELECT data FROM transports WHERE reconstruction_id = $1 ORDER BY part")
                .bind(id)
                .fetch_all(&self.bulk)
                .await?;
        if parts.is_empty() {
            return Ok(None);
        }
        let mut out = Vec::new();
        for p in parts {
            out.extend_from_slice(&p.get::<Vec<u8>, _>("data"));
        }
        Ok(Some(out))
    }

    async fn fail_job(
        &self,
        id: i64,
        attempt: i64,
        error: &str,
        retry: bool,
    ) -> Result<bool, StoreError> {
        let changed = sqlx::query(
            "UPDATE jobs SET last_error = $3, lease_until_ms = NULL, \
             state = CASE WHEN $4 AND attempt < max_attempts THEN 'queued' ELSE 'failed' END, \
             finished_ms = CASE WHEN $4 AND attempt < max_attempts THEN NULL ELSE helmholtz_now_ms() END, \
             run_at_ms = helmholtz_now_ms() + 1000 * attempt \
             WHERE id = $1 AND attempt = $2 AND state = 'running'",
        )
        .bind(id)
        .bind(attempt)
        .bind(error)
        .bind(retry)
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(changed == 1)
    }

    async fn release_job(&self, id: i64, attempt: i64) -> Result<bool, StoreError> {
        let changed = sqlx::query(
            "UPDATE jobs SET state = 'queued', attempt = attempt - 1, lease_until_ms = NULL, worker_id = NULL \
             WHERE id = $1 AND attempt = $2 AND state = 'running'",
        )
        .bind(id)
        .bind(attempt)
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(changed == 1)
    }

    async fn cancel_job(&self, id: i64) -> Result<bool, StoreError> {
        let changed = sqlx::query(
            "UPDATE jobs SET state = 'cancelled', finished_ms = helmholtz_now_ms(), lease_until_ms = NULL \
             WHERE id = $1 AND state IN ('queued', 'running')",
        )
        .bind(id)
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(changed == 1)
    }

    async fn pending_jobs_for_lab(&self, lab: &str) -> Result<u64, StoreError> {
        let n: i64 = sqlx::query(
            "SELECT COUNT(*) FROM jobs WHERE lab = $1 AND state IN ('queued', 'running')",
        )
        .bind(lab)
        .fetch_one(&self.pool)
        .await?
        .get(0);
        Ok(n as u64)
    }

    async fn queue_depth(&self) -> Result<(u64, u64), StoreError> {
        let row = sqlx::query(
            "SELECT COUNT(*) FILTER (WHERE state = 'queued'), COUNT(*) FILTER (WHERE state = 'running') FROM jobs \
             WHERE state IN ('queued', 'running')",
        )
        .fetch_one(&self.pool)
        .await?;
        Ok((row.get::<i64, _>(0) as u64, row.get::<i64, _>(1) as u64))
    }

    async fn pending_jobs(&self) -> Result<i64, StoreError> {
        Ok(
            sqlx::query("SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running')")
                .fetch_one(&self.pool)
                .await?
                .get(0),
        )
    }

    async fn dual_images(&self, reconstruction_id: i64) -> Result<Vec<StoredImage>, StoreError> {
        let rows = sqlx::query(
            "SELECT channel_index, channel_name, width, height, data FROM dual_images \
             WHERE reconstruction_id = $1 ORDER BY channel_index",
        )
        .bind(reconstruction_id)
        .fetch_all(&self.bulk)
        .await?;
        rows.iter()
            .map(|row| {
                Ok(StoredImage {
                    channel_index: row.get::<i64, _>("channel_index") as u32,
                    channel_name: row.get("channel_name"),
                    width: row.get::<i64, _>("width") as u32,
                    height: row.get::<i64, _>("height") as u32,
                    data: le_to_f32(&row.get::<Vec<u8>, _>("data"))?,
                })
            })
            .collect()
    }
}
