//! A transport job in shards: the model stored once on the reconstruction, its blocks of camera
//! pixels split into shards that any worker sharing the database claims, leased, heart-beaten
//! and fenced by attempt exactly like jobs (every write for a shard's run carries
//! `AND attempt = ?`: a worker that lost its shard's lease can never overwrite). Only shards of
//! a running job are claimed, heart-beaten or completed: a cancelled or finished job's shards
//! stop at their next heartbeat.

use async_trait::async_trait;

use super::StoreRow;

use super::StoreError;

/// One shard as stored.
#[derive(Clone, Debug, PartialEq)]
pub struct ShardRow {
    pub reconstruction_id: i64,
    pub shard: i64,
    /// The model's blocks `first_block..end_block`.
    pub first_block: u64,
    pub end_block: u64,
    /// `queued`, `running`, `done` or `failed`.
    pub state: String,
    pub attempt: i64,
    /// The worker of the latest attempt.
    pub worker_id: Option<String>,
    pub last_error: Option<String>,
    /// Bytes of the stored part (done shards).
    pub part_bytes: Option<u64>,
    pub started_ms: Option<i64>,
    pub finished_ms: Option<i64>,
}

/// A shard this worker now holds: write its result with `attempt` as the fence.
#[derive(Clone, Debug)]
pub struct ClaimedShard {
    pub reconstruction_id: i64,
    pub shard: i64,
    pub attempt: i64,
    pub first_block: u64,
    pub end_block: u64,
    /// The job's memory estimate (reserved against the process's budget while solving).
    pub memory_bytes: u64,
    pub session_id: String,
    pub rows_used: u64,
    pub params_json: String,
    /// The reconstruction's stored model (JSON).
    pub model_json: String,
}

/// Shards of transport jobs as a backend stores them.
#[async_trait]
pub trait Shards: Send + Sync {
    /// Stores a transport reconstruction's model and its shards (ranges of the model's blocks,
    /// in order) unless it has a model already, atomically and only while run `job_attempt`
    /// holds the job; wakes idle workers on every node. Returns the model now stored: the
    /// earlier one when there was one (the model is chosen once: a later holder of the job,
    /// after the first died, reuses it and its shards, done ones included). `None`: this run no
    /// longer holds the job.
    async fn start_shards(
        &self,
        id: i64,
        job_attempt: i64,
        model_json: &str,
        shards: &[(u64, u64)],
    ) -> Result<Option<String>, StoreError>;

    /// The model stored on a reconstruction, if any.
    async fn transport_model(&self, id: i64) -> Result<Option<String>, StoreError>;

    /// Claims the next shard of a running job (oldest reconstruction first, shards in order),
    /// or one whose lease expired with attempts left; shards whose lease expired without
    /// attempts left are marked failed here. `only`: shards of that reconstruction alone.
    /// `max_memory`: the job's memory estimate must fit what the process has left.
    async fn claim_shard(
        &self,
        worker_id: &str,
        lease_ms: i64,
        max_memory: u64,
        only: Option<i64>,
    ) -> Result<Option<ClaimedShard>, StoreError>;

    /// Extends the shard's lease. False: the shard or its job is no longer this run's (stop).
    async fn heartbeat_shard(
        &self,
        id: i64,
        shard: i64,
        attempt: i64,
        lease_ms: i64,
    ) -> Result<bool, StoreError>;

    /// Stores the shard's encoded part and marks it done, if this run still holds it and the
    /// job still runs.
    async fn complete_shard(
        &self,
        id: i64,
        shard: i64,
        attempt: i64,
        part: &[u8],
    ) -> Result<bool, StoreError>;

    /// Records a failed run of a shard: `retry` queues it again while attempts are left;
    /// otherwise it fails for good (and with it the job, when its holder sees it).
    async fn fail_shard(
        &self,
        id: i64,
        shard: i64,
        attempt: i64,
        error: &str,
        retry: bool,
    ) -> Result<bool, StoreError>;

    /// Gives a running shard back without counting the attempt (graceful shutdown).
    async fn release_shard(&self, id: i64, shard: i64, attempt: i64) -> Result<bool, StoreError>;

    /// A reconstruction's shards, in order.
    async fn shards(&self, id: i64) -> Result<Vec<ShardRow>, StoreError>;

    /// The encoded parts of a reconstruction whose shards are all done, in shard order.
    async fn shard_parts(&self, id: i64) -> Result<Vec<Vec<u8>>, StoreError>;
}

/// The parts of `rows` (shard, state, part) in order, or why they are not all there.
pub(crate) fn parts_in_order(
    id: i64,
    rows: Vec<(i64, String, Option<Vec<u8>>)>,
) -> Result<Vec<Vec<u8>>, StoreError> {
    let mut out = Vec::with_capacity(rows.len());
    for (i, (shard, state, part)) in rows.into_iter().enumerate() {
        match part {
            Some(part) if state == "done" && shard == i as i64 => out.push(part),
            _ => {
                return Err(StoreError::Corrupt(format!(
                    "reconstruction {id}: shard {shard} is {state} without its part where shard {i} was due"
                )));
            }
        }
    }
    if out.is_empty() {
        return Err(StoreError::Corrupt(format!(
            "reconstruction {id} has no shards"
        )));
    }
    Ok(out)
}

/// A shard row of either backend.
pub(crate) fn shard_from_row(row: &impl StoreRow) -> ShardRow {
    ShardRow {
        reconstruction_id: row.int("reconstruction_id"),
        shard: row.int("shard"),
        first_block: row.int("first_block") as u64,
        end_block: row.int("end_block") as u64,
        state: row.text("state"),
        attempt: row.int("attempt"),
        worker_id: row.text_or_null("worker_id"),
        last_error: row.text_or_null("last_error"),
        part_bytes: row.int_or_null("part_bytes").map(|b| b as u64),
        started_ms: row.int_or_null("started_ms"),
        finished_ms: row.int_or_null("finished_ms"),
    }
}
