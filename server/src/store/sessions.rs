//! Sessions: idempotent creation, lookup, listing, finishing.

use std::collections::BTreeMap;

use helmholtz_proto::PatternSpec;
use sqlx::Row;
use sqlx::sqlite::SqliteRow;

use super::{Store, StoreError, f32_to_le, le_to_f32, now_ms, parse_spec};

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SessionState {
    Open,
    Finished,
}

/// What a rig declares when it creates a session.
#[derive(Clone, Debug, PartialEq)]
pub struct NewSession {
    pub id: String,
    /// The lab that owns it (the creating token's).
    pub lab: String,
    pub rig: String,
    pub spec: PatternSpec,
    pub channels: Vec<String>,
    pub metadata: BTreeMap<String, String>,
    /// Simulated sessions: the transport the simulator used (width, height, row-major values).
    pub ground_truth: Option<(u32, u32, Vec<f32>)>,
}

/// A stored session (without its ground-truth pixels).
#[derive(Clone, Debug, PartialEq)]
pub struct SessionRow {
    pub id: String,
    pub lab: String,
    pub rig: String,
    pub spec: PatternSpec,
    pub channels: Vec<String>,
    pub metadata: BTreeMap<String, String>,
    pub expected_rows: u64,
    pub committed_rows: u64,
    pub state: SessionState,
    pub has_ground_truth: bool,
    pub created_ms: i64,
    pub finished_ms: Option<i64>,
}

const SESSION_COLUMNS: &str = "id, lab, rig, spec_json, channels_json, metadata_json, expected_rows, \
     committed_rows, state, gt_transport IS NOT NULL AS has_gt, created_ms, finished_ms";

fn session_from_row(row: &SqliteRow) -> Result<SessionRow, StoreError> {
    let corrupt = |what: &str, e: serde_json::Error| StoreError::Corrupt(format!("{what}: {e}"));
    Ok(SessionRow {
        id: row.get("id"),
        lab: row.get("lab"),
        rig: row.get("rig"),
        spec: parse_spec(row.get("spec_json"))?,
        channels: serde_json::from_str(row.get("channels_json")).map_err(|e| corrupt("channels", e))?,
        metadata: serde_json::from_str(row.get("metadata_json")).map_err(|e| corrupt("metadata", e))?,
        expected_rows: row.get::<i64, _>("expected_rows") as u64,
        committed_rows: row.get::<i64, _>("committed_rows") as u64,
        state: if row.get::<String, _>("state") == "finished" {
            SessionState::Finished
        } else {
            SessionState::Open
        },
        has_ground_truth: row.get::<bool, _>("has_gt"),
        created_ms: row.get("created_ms"),
        finished_ms: row.get("finished_ms"),
    })
}

impl Store {
    /// Creates the session, or returns the existing one if `new` declares the same thing.
    /// Returns `(session, created)`.
    pub async fn create_session(&self, new: &NewSession) -> Result<(SessionRow, bool), StoreError> {
        let (gt_w, gt_h, gt_blob) = match &new.ground_truth {
            Some((w, h, data)) => (Some(*w as i64), Some(*h as i64), Some(f32_to_le(data))),
            None => (None, None, None),
        };
        let inserted = sqlx::query(
            "INSERT INTO sessions (id, rig, spec_json, channels_json, metadata_json, expected_rows, \
             gt_width, gt_height, gt_transport, created_ms, lab) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11) \
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
        .bind(now_ms())
        .bind(&new.lab)
        .execute(&self.pool)
        .await?
        .rows_affected()
            == 1;
        let existing = self.get_session(&new.id).await?.ok_or_else(|| StoreError::SessionNotFound(new.id.clone()))?;
        if !inserted {
            if existing.lab != new.lab {
                // Ids are global; another lab's session is not described (not even that it differs).
                return Err(StoreError::SessionIdTaken(new.id.clone()));
            }
            let differs = if existing.rig != new.rig {
                Some("rig")
            } else if existing.spec != new.spec {
                Some("patterns")
            } else if existing.channels != new.channels {
                Some("detector")
            } else if existing.metadata != new.metadata {
                Some("metadata")
            } else if existing.has_ground_truth != new.ground_truth.is_some() {
                Some("ground_truth")
            } else {
                None
            };
            if let Some(field) = differs {
                return Err(StoreError::SessionConflict(new.id.clone(), field));
            }
        }
        Ok((existing, inserted))
    }

    pub async fn get_session(&self, id: &str) -> Result<Option<SessionRow>, StoreError> {
        let sql = format!("SELECT {SESSION_COLUMNS} FROM sessions WHERE id = $1");
        let row = sqlx::query(sqlx::AssertSqlSafe(sql)).bind(id).fetch_optional(&self.pool).await?;
        row.as_ref().map(session_from_row).transpose()
    }

    pub async fn session(&self, id: &str) -> Result<SessionRow, StoreError> {
        self.get_session(id).await?.ok_or_else(|| StoreError::SessionNotFound(id.to_string()))
    }

    /// A lab's sessions, newest first.
    pub async fn list_sessions(&self, lab: &str, limit: u32) -> Result<Vec<SessionRow>, StoreError> {
        let sql = format!("SELECT {SESSION_COLUMNS} FROM sessions WHERE lab = $2 ORDER BY created_ms DESC, id LIMIT $1");
        let rows = sqlx::query(sqlx::AssertSqlSafe(sql)).bind(limit as i64).bind(lab).fetch_all(&self.pool).await?;
        rows.iter().map(session_from_row).collect()
    }

    /// How many sessions a lab has.
    pub async fn count_sessions(&self, lab: &str) -> Result<u64, StoreError> {
        let n: i64 = sqlx::query("SELECT COUNT(*) FROM sessions WHERE lab = $1").bind(lab).fetch_one(&self.pool).await?.get(0);
        Ok(n as u64)
    }

    /// Total rows stored in all sessions (for the operator's metrics).
    pub async fn count_all(&self) -> Result<(u64, u64), StoreError> {
        let row = sqlx::query("SELECT COUNT(*), COALESCE(SUM(committed_rows), 0) FROM sessions").fetch_one(&self.pool).await?;
        Ok((row.get::<i64, _>(0) as u64, row.get::<i64, _>(1) as u64))
    }

    /// Marks the session finished once every declared row is committed. Idempotent.
    pub async fn finish_session(&self, id: &str) -> Result<SessionRow, StoreError> {
        let session = self.session(id).await?;
        if session.state == SessionState::Finished {
            return Ok(session);
        }
        if session.committed_rows != session.expected_rows {
            return Err(StoreError::Incomplete {
                id: id.to_string(),
                committed: session.committed_rows,
                expected: session.expected_rows,
            });
        }
        sqlx::query("UPDATE sessions SET state = 'finished', finished_ms = $2 WHERE id = $1 AND state = 'open'")
            .bind(id)
            .bind(now_ms())
            .execute(&self.pool)
            .await?;
        self.session(id).await
    }

    /// The simulator's transport for a simulated session.
    pub async fn ground_truth(&self, id: &str) -> Result<Option<(u32, u32, Vec<f32>)>, StoreError> {
        let row = sqlx::query("SELECT gt_width, gt_height, gt_transport FROM sessions WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        let Some(row) = row else { return Err(StoreError::SessionNotFound(id.to_string())) };
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
