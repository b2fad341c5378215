//! Sessions: idempotent creation, lookup, listing, finishing.

use std::collections::BTreeMap;

use async_trait::async_trait;

use super::StoreRow;
use helmholtz_proto::PatternSpec;

use super::{StoreError, parse_spec};

pub use helmholtz_proto::wire::SampleFormat;

/// A camera in place of bucket detectors: one frame of `width x height` per pattern.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct CameraLayout {
    pub width: u32,
    pub height: u32,
    pub format: SampleFormat,
}

impl CameraLayout {
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

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
    /// Bucket channel names (empty for a camera session).
    pub channels: Vec<String>,
    /// Unit vectors toward the bucket detectors, one per channel, or none.
    pub directions: Vec<[f64; 3]>,
    pub camera: Option<CameraLayout>,
    pub metadata: BTreeMap<String, String>,
    /// Simulated sessions: the transport the simulator used (width, height, row-major values:
    /// one image shared by all channels, one per channel, or a camera session's T, m x k).
    pub ground_truth: Option<(u32, u32, Vec<f32>)>,
}

/// A stored session (without its ground-truth pixels).
#[derive(Clone, Debug, PartialEq)]
pub struct SessionRow {
    pub id: String,
    pub lab: String,
    pub rig: String,
    pub spec: PatternSpec,
    /// Bucket channel names (empty for a camera session).
    pub channels: Vec<String>,
    pub directions: Vec<[f64; 3]>,
    pub camera: Option<CameraLayout>,
    pub metadata: BTreeMap<String, String>,
    pub expected_rows: u64,
    pub committed_rows: u64,
    pub state: SessionState,
    pub has_ground_truth: bool,
    pub created_ms: i64,
    pub finished_ms: Option<i64>,
}

impl SessionRow {
    /// Values per row: the channel count, or a camera frame's pixel count.
    pub fn row_values(&self) -> usize {
        self.camera
            .map(|c| c.pixels())
            .unwrap_or(self.channels.len())
    }
    pub fn sample_format(&self) -> SampleFormat {
        self.camera.map(|c| c.format).unwrap_or(SampleFormat::F64)
    }
    /// Bytes one stored row takes.
    pub fn row_bytes(&self) -> usize {
        self.row_values() * self.sample_format().bytes()
    }
}

/// Whether a stored session answers a repeated creation: `Ok` when `new` declares what is
/// stored, else the error naming what differs (or that the id is another lab's: ids are
/// global, and another lab's session is not described, not even that it differs).
pub(crate) fn same_declaration(existing: &SessionRow, new: &NewSession) -> Result<(), StoreError> {
    if existing.lab != new.lab {
        return Err(StoreError::SessionIdTaken(new.id.clone()));
    }
    let differs = if existing.rig != new.rig {
        Some("rig")
    } else if existing.spec != new.spec {
        Some("patterns")
    } else if existing.channels != new.channels
        || existing.camera != new.camera
        || existing.directions != new.directions
    {
        Some("detector")
    } else if existing.metadata != new.metadata {
        Some("metadata")
    } else if existing.has_ground_truth != new.ground_truth.is_some() {
        Some("ground_truth")
    } else {
        None
    };
    match differs {
        Some(field) => Err(StoreError::SessionConflict(new.id.clone(), field)),
        None => Ok(()),
    }
}

/// The error for a session that cannot be finished yet, if any. An adaptive session may finish
/// at any time: it then holds the rows measured so far (its count is a budget, not a promise).
pub(crate) fn finishable(session: &SessionRow) -> Result<(), StoreError> {
    if !session.spec.is_adaptive() && session.committed_rows != session.expected_rows {
        return Err(StoreError::Incomplete {
            id: session.id.clone(),
            committed: session.committed_rows,
            expected: session.expected_rows,
        });
    }
    Ok(())
}

/// Sessions as a backend stores them.
#[async_trait]
pub trait Sessions: Send + Sync {
    /// Creates the session, or returns the existing one if `new` declares the same thing
    /// ([`same_declaration`]), refusing a new session when its lab already holds `max_per_lab`
    /// ([`StoreError::Cap`]). The count and the insert are atomic, so concurrent creations never
    /// pass the cap together. Returns `(session, created)`.
    async fn create_session_capped(
        &self,
        new: &NewSession,
        max_per_lab: u64,
    ) -> Result<(SessionRow, bool), StoreError>;

    async fn get_session(&self, id: &str) -> Result<Option<SessionRow>, StoreError>;

    /// A lab's sessions, newest first.
    async fn list_sessions(&self, lab: &str, limit: u32) -> Result<Vec<SessionRow>, StoreError>;

    /// How many sessions a lab has.
    async fn count_sessions(&self, lab: &str) -> Result<u64, StoreError>;

    /// (sessions, rows) stored in all labs (for the operator's metrics).
    async fn count_all(&self) -> Result<(u64, u64), StoreError>;

    /// Marks the session finished once every declared row is committed (an adaptive session:
    /// at any time; [`finishable`]).
    /// Idempotent.
    async fn finish_session(&self, id: &str) -> Result<SessionRow, StoreError>;

    /// The simulator's transport for a simulated session.
    async fn ground_truth(&self, id: &str) -> Result<Option<(u32, u32, Vec<f32>)>, StoreError>;

    /// [`Sessions::create_session_capped`] without a cap.
    async fn create_session(&self, new: &NewSession) -> Result<(SessionRow, bool), StoreError> {
        self.create_session_capped(new, u64::MAX).await
    }

    async fn session(&self, id: &str) -> Result<SessionRow, StoreError> {
        self.get_session(id)
            .await?
            .ok_or_else(|| StoreError::SessionNotFound(id.to_string()))
    }
}

/// A session row of either backend (the columns of the backends' `SESSION_COLUMNS`).
pub(crate) fn session_from_row(row: &impl StoreRow) -> Result<SessionRow, StoreError> {
    let corrupt = |what: &str, e: serde_json::Error| StoreError::Corrupt(format!("{what}: {e}"));
    let name = row.text("sample_format");
    let format = SampleFormat::parse(&name)
        .ok_or_else(|| StoreError::Corrupt(format!("unknown sample format {name:?}")))?;
    let camera = match (
        row.int_or_null("camera_width"),
        row.int_or_null("camera_height"),
    ) {
        (Some(w), Some(h)) => Some(CameraLayout {
            width: w as u32,
            height: h as u32,
            format,
        }),
        _ => None,
    };
    Ok(SessionRow {
        directions: serde_json::from_str(&row.text("directions_json"))
            .map_err(|e| corrupt("directions", e))?,
        camera,
        id: row.text("id"),
        lab: row.text("lab"),
        rig: row.text("rig"),
        spec: parse_spec(&row.text("spec_json"))?,
        channels: serde_json::from_str(&row.text("channels_json"))
            .map_err(|e| corrupt("channels", e))?,
        metadata: serde_json::from_str(&row.text("metadata_json"))
            .map_err(|e| corrupt("metadata", e))?,
        expected_rows: row.int("expected_rows") as u64,
        committed_rows: row.int("committed_rows") as u64,
        state: if row.text("state") == "finished" {
            SessionState::Finished
        } else {
            SessionState::Open
        },
        has_ground_truth: row.flag("has_gt"),
        created_ms: row.int("created_ms"),
        finished_ms: row.int_or_null("finished_ms"),
    })
}
