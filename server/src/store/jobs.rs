//! The job queue (lease + heartbeat + fencing) and reconstruction results.
//!
//! A claim moves one queued job, or a running job whose lease expired and has attempts left, to
//! `running` with `attempt + 1`. Every later write for that run carries the attempt as its
//! fence: a worker that lost its lease (it stalled, or another worker took the job over) can
//! never overwrite.

use async_trait::async_trait;

use super::StoreRow;

use super::StoreError;

/// A reconstruction and the state of its job.
#[derive(Clone, Debug, PartialEq)]
pub struct ReconstructionRow {
    pub id: i64,
    /// The lab of its session.
    pub lab: String,
    pub session_id: String,
    pub method: String,
    pub params_json: String,
    pub rows_used: u64,
    pub state: String,
    pub progress: f64,
    pub attempt: i64,
    pub last_error: Option<String>,
    pub report_json: Option<String>,
    pub seconds: Option<f64>,
    pub created_ms: i64,
    pub started_ms: Option<i64>,
    pub finished_ms: Option<i64>,
}

/// A job this worker now holds: write results with `attempt` as the fence.
#[derive(Clone, Debug)]
pub struct ClaimedJob {
    pub id: i64,
    pub attempt: i64,
    /// The job's estimated peak memory, bytes (reserved against the process's budget).
    pub memory_bytes: u64,
    pub reconstruction: ReconstructionRow,
}

/// One stored dual image.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredImage {
    pub channel_index: u32,
    pub channel_name: String,
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

/// The job queue and results as a backend stores them.
#[async_trait]
pub trait Jobs: Send + Sync {
    /// Queues a reconstruction of the first `rows_used` rows of a session unless the lab already
    /// has `max_pending` jobs queued or running ([`StoreError::Cap`]): the count and the insert
    /// are atomic, so concurrent requests never pass the cap together. `memory_bytes`: the
    /// job's estimated peak memory, which a worker must have room for to claim it.
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
    ) -> Result<ReconstructionRow, StoreError>;

    async fn get_reconstruction(&self, id: i64) -> Result<Option<ReconstructionRow>, StoreError>;

    /// A session's reconstructions, newest first.
    async fn session_reconstructions(
        &self,
        session_id: &str,
    ) -> Result<Vec<ReconstructionRow>, StoreError>;

    /// The newest finished reconstruction of a session.
    async fn latest_done(&self, session_id: &str) -> Result<Option<i64>, StoreError>;

    /// Claims the next runnable job whose memory estimate is at most `max_memory` bytes (what
    /// the claiming process's budget has left), fairly across labs: among runnable jobs, the
    /// lab with the fewest running jobs goes first, then the lab served least recently (so one
    /// lab's backlog alternates with every other lab's jobs instead of draining first), then
    /// priority and age. A lab already running `max_running_per_lab` jobs (0: no cap) is
    /// skipped. Running jobs whose lease expired are taken over while they have attempts left;
    /// those out of attempts are marked failed here.
    async fn claim_job_within(
        &self,
        worker_id: &str,
        lease_ms: i64,
        max_running_per_lab: u32,
        max_memory: u64,
    ) -> Result<Option<ClaimedJob>, StoreError>;

    /// Extends the lease and records progress. False means the job is no longer ours (fenced
    /// out or cancelled): stop computing.
    async fn heartbeat(
        &self,
        id: i64,
        attempt: i64,
        lease_ms: i64,
        progress: f64,
    ) -> Result<bool, StoreError>;

    /// Stores the result and marks the job done, atomically, if this run still holds the job.
    async fn complete_reconstruction(
        &self,
        id: i64,
        attempt: i64,
        images: &[StoredImage],
        transport: Option<&[u8]>,
        report_json: &str,
        seconds: f64,
    ) -> Result<bool, StoreError>;

    /// A camera reconstruction's encoded transport matrix, if it has one.
    async fn transport(&self, id: i64) -> Result<Option<Vec<u8>>, StoreError>;

    /// Records a failed run. `retry` puts the job back in the queue if attempts are left
    /// (transient causes); otherwise it fails for good (the input cannot be solved).
    async fn fail_job(
        &self,
        id: i64,
        attempt: i64,
        error: &str,
        retry: bool,
    ) -> Result<bool, StoreError>;

    /// Gives a running job back to the queue without counting the attempt (graceful shutdown).
    async fn release_job(&self, id: i64, attempt: i64) -> Result<bool, StoreError>;

    /// Cancels a queued or running job; a running worker notices at its next heartbeat.
    async fn cancel_job(&self, id: i64) -> Result<bool, StoreError>;

    /// A lab's jobs waiting or running.
    async fn pending_jobs_for_lab(&self, lab: &str) -> Result<u64, StoreError>;

    /// Jobs by state: (queued, running).
    async fn queue_depth(&self) -> Result<(u64, u64), StoreError>;

    /// Number of jobs waiting or running.
    async fn pending_jobs(&self) -> Result<i64, StoreError>;

    /// Dual images of a reconstruction, by channel.
    async fn dual_images(&self, reconstruction_id: i64) -> Result<Vec<StoredImage>, StoreError>;

    /// [`Jobs::enqueue_reconstruction_capped`] without a cap or a memory estimate.
    async fn enqueue_reconstruction(
        &self,
        lab: &str,
        session_id: &str,
        method: &str,
        params_json: &str,
        rows_used: u64,
        max_attempts: u32,
    ) -> Result<ReconstructionRow, StoreError> {
        self.enqueue_reconstruction_capped(
            lab,
            session_id,
            method,
            params_json,
            rows_used,
            max_attempts,
            u64::MAX,
            0,
        )
        .await
    }

    async fn reconstruction(&self, id: i64) -> Result<ReconstructionRow, StoreError> {
        self.get_reconstruction(id)
            .await?
            .ok_or(StoreError::ReconstructionNotFound(id))
    }

    /// [`Jobs::claim_job_within`] whatever the job's memory estimate.
    async fn claim_job(
        &self,
        worker_id: &str,
        lease_ms: i64,
        max_running_per_lab: u32,
    ) -> Result<Option<ClaimedJob>, StoreError> {
        self.claim_job_within(worker_id, lease_ms, max_running_per_lab, u64::MAX)
            .await
    }
}

/// A reconstruction row of either backend (the backends' `RECON_COLUMNS`).
pub(crate) fn recon_from_row(row: &impl StoreRow) -> ReconstructionRow {
    ReconstructionRow {
        id: row.int("id"),
        lab: row.text("lab"),
        session_id: row.text("session_id"),
        method: row.text("method"),
        params_json: row.text("params_json"),
        rows_used: row.int("rows_used") as u64,
        state: row.text("state"),
        progress: row.real("progress"),
        attempt: row.int("attempt"),
        last_error: row.text_or_null("last_error"),
        report_json: row.text_or_null("report_json"),
        seconds: row.real_or_null("seconds"),
        created_ms: row.int("created_ms"),
        started_ms: row.int_or_null("started_ms"),
        finished_ms: row.int_or_null("finished_ms"),
    }
}
