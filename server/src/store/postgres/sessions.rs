//! Sessions in PostgreSQL.

use async_trait::async_trait;
use sqlx::Row;

use super::{Postgres, begin, lab_lock};
use crate::store::sessions::session_from_row;
use crate::store::sessions::{finishable, same_declaration};
use crate::store::{
    NewSession, SampleFormat, SessionRow, SessionState, Sessions, StoreError, f32_to_le, le_to_f32,
};

const SESSION_COLUMNS: &str = "id, lab, rig, spec_json, channels_json, metadata_json, expected_rows, \
     committed_rows, state, gt_transport IS NOT NULL AS has_gt, created_ms, finished_ms, \
     camera_width, camera_height, sample_format, directions_json";

#[async_trait]
impl Sessions for Postgres {
    // The lab's advisory lock serialises its creations: the count and the insert are atomic
    // across every node.
    async fn create_session_capped(
        &self,
        new: &NewSession,
        max_per_lab: u64,
    ) -> Result<(SessionRow, bool), StoreError> {
        let (gt_w, gt_h, gt_blob) = match &new.ground_truth {
            Some((w, h, data)) => (Some(*w as i64), Some(*h as i64), Some(f32_to_le(data))),
            None => (None, None, None),
        };
        let mut tx = begin(&self.pool).await?;
        lab_lock(&mut tx, "sessions", &new.lab).await?;
        let exists = sqlx::query("SELECT 1 FROM sessions WHERE id = $1")
            .bind(&new.id)
            .fetch_optional(&mut *tx)
            .await?
            .is_some();
        if !exists {
            let held: i64 = sqlx::query("SELECT COUNT(*) FROM sessions WHERE lab = $1")
                .bind(&new.lab)
                .fetch_one(&mut *tx)
                .await?
                .get(0);
            if held as u64 >= max_per_lab {
                return Err(StoreError::Cap {
                    limit: "max_sessions_per_lab",
                    message: format!(
                        "lab {:?} holds {held} sessions (limit {max_per_lab}); no new session was created",
                        new.lab
                    ),
                });
            }
        }
        let inserted = sqlx::query(
            "INSERT INTO sessions (id, rig, spec_json, channels_json, metadata_json, expected_rows, \
             gt_width, gt_height, gt_transport, created_ms, lab, camera_width, camera_height, sample_format, directions_json, issued_rows) \
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, helmholtz_now_ms(), $10, $11, $12, $13, $14, $15) \
             ON CONFLICT (id) DO NOTHING",
        )
        .bind(&new.id)
        .bind(&new.rig)
        .bind(new.spec.to_json())
        .bind(serde_json::to_string(&new.channels).expect("json"))
        .bind(serde_json::to_string(&new.metadata).expect("json"))
        .bind(new.spec.count() as i64)
        .bind(gt_w)
        .bind(gt_h)
        .bind(gt_blob)
        .bind(&new.lab)
        .bind(new.camera.map(|c| c.width as i64))
        .bind(new.camera.map(|c| c.height as i64))
        .bind(new.camera.map(|c| c.format).unwrap_or(SampleFormat::F64).name())
        .bind(serde_json::to_string(&new.directions).expect("json"))
        // An adaptive session takes rows of its issued batches only: none yet.
        .bind(new.spec.is_adaptive().then_some(0i64))
        .execute(&mut *tx)
        .await?
        .rows_affected()
            == 1;
        tx.commit().await?;
        let existing = self
            .get_session(&new.id)
            .await?
            .ok_or_else(|| StoreError::SessionNotFound(new.id.clone()))?;
        if !inserted {
            same_declaration(&existing, new)?;
        }
        Ok((existing, inserted))
    }

    async fn get_session(&self, id: &str) -> Result<Option<SessionRow>, StoreError> {
        let sql = format!("SELECT {SESSION_COLUMNS} FROM sessions WHERE id = $1");
        let row = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        row.as_ref().map(session_from_row).transpose()
    }

    async fn list_sessions(&self, lab: &str, limit: u32) -> Result<Vec<SessionRow>, StoreError> {
        let sql = format!(
            "SELECT {SESSION_COLUMNS} FROM sessions WHERE lab = $2 ORDER BY created_ms DESC, id LIMIT $1"
        );
        let rows = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(limit as i64)
            .bind(lab)
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(session_from_row).collect()
    }

    async fn count_sessions(&self, lab: &str) -> Result<u64, StoreError> {
        let n: i64 = sqlx::query("SELECT COUNT(*) FROM sessions WHERE lab = $1")
            .bind(lab)
            .fetch_one(&self.pool)
            .await?
            .get(0);
        Ok(n as u64)
    }

    async fn count_all(&self) -> Result<(u64, u64), StoreError> {
        let row =
            sqlx::query("SELECT COUNT(*), COALESCE(SUM(committed_rows), 0)::BIGINT FROM sessions")
                .fetch_one(&self.pool)
                .await?;
        Ok((row.get::<i64, _>(0) as u64, row.get::<i64, _>(1) as u64))
    }

    async fn finish_session(&self, id: &str) -> Result<SessionRow, StoreError> {
        let session = self.session(id).await?;
        if session.state == SessionState::Finished {
            return Ok(session);
        }
        finishable(&session)?;
        sqlx::query("UPDATE sessions SET state = 'finished', finished_ms = helmholtz_now_ms() WHERE id = $1 AND state = 'open'")
            .bind(id)
            .execute(&self.pool)
            .await?;
        self.session(id).await
    }

    async fn ground_truth(&self, id: &str) -> Result<Option<(u32, u32, Vec<f32>)>, StoreError> {
        let row =
            sqlx::query("SELECT gt_width, gt_height, gt_transport FROM sessions WHERE id = $1")
                .bind(id)
                .fetch_optional(&self.bulk)
                .await?;
        let Some(row) = row else {
            return Err(StoreError::SessionNotFound(id.to_string()));
        };
        let blob: Option<Vec<u8>> = row.get("gt_transport");
        match blob {
            None => Ok(None),
            Some(blob) => Ok(Some((
                row.get::<i64, _>("gt_width") as u32,
                row.get::<i64, _>("gt_height") as u32,
                le_to_f32(&blob)?,
            ))),
        }
    }
}
