//! The worker pool: fixed OS threads that claim reconstruction jobs from the store and run the
//! numerics off the async runtime. Each running job has a heartbeat task that extends its lease;
//! losing the lease (or a cancel) stops the computation at its next check.
//!
//! A camera session's transport matrix runs in shards: the worker that holds the job chooses
//! the model once ([`transport::plan_transport`], or reuses the one stored by an earlier holder
//! that died), stores it with the shards (runs of the model's blocks of camera pixels), then
//! solves shards itself while idle workers of every process sharing the database take the
//! others (a worker looks for shards of running jobs before it claims a new job). Shards are
//! leased, heart-beaten and fenced like jobs. When every shard is done the holder assembles the
//! parts ([`transport::assemble_transport`]: the same T, bit for bit, as one process solving
//! every block) and completes the job.

use std::collections::HashMap;
use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use helmholtz_proto::rest::{Quality, Report};
use serde_json::Value;
use tokio::runtime::Handle;
use tokio::sync::Notify;

use crate::recon::transport::{
    self, CameraGrid, FrameSource, TransportConfig, TransportModel, TransportPart,
};
use crate::recon::{
    self, BucketBlock, BucketSource, Control, MethodConfig, Problem, ReconError, SourceError,
};
use crate::store::{CameraLayout, ClaimedJob, ClaimedShard, SessionRow, Store, StoredImage};

/// How the pool runs.
#[derive(Clone, Debug)]
pub struct PoolConfig {
    /// Number of worker threads (concurrent reconstructions).
    pub workers: usize,
    /// Lease length; the heartbeat renews it every third of it.
    pub lease: Duration,
    /// How often an idle worker looks for work when not woken.
    pub idle_poll: Duration,
    /// Most jobs of one lab running at once (0: no cap).
    pub max_running_per_lab: u32,
    /// Working-set budget of one reconstruction of a camera session (frame blocks, solutions,
    /// scratch): the transport solver picks its block of camera pixels to stay within it.
    pub memory_budget: usize,
    /// Memory all jobs running in this process may take together (their estimates), bytes: a
    /// worker claims only a job that fits what the running ones leave (any job when none runs).
    pub process_memory: u64,
    /// Camera pixels per shard of a transport job (a whole number of solver blocks; the blocks
    /// are cut to at most this many pixels): any worker sharing the database solves a shard.
    pub transport_shard_pixels: usize,
}

/// Default [`PoolConfig::transport_shard_pixels`].
pub const DEFAULT_TRANSPORT_SHARD_PIXELS: usize = 4096;

impl Default for PoolConfig {
    fn default() -> Self {
        PoolConfig {
            workers: 2,
            lease: Duration::from_secs(30),
            idle_poll: Duration::from_millis(500),
            max_running_per_lab: 0,
            memory_budget: transport::DEFAULT_MEMORY_BUDGET,
            process_memory: u64::MAX,
            transport_shard_pixels: DEFAULT_TRANSPORT_SHARD_PIXELS,
        }
    }
}

/// Running worker threads. Dropping it without `shutdown` leaves them running.
pub struct WorkerPool {
    threads: Vec<JoinHandle<()>>,
    stop: Arc<AtomicBool>,
    wake: Arc<Notify>,
    running: Running,
    shards: RunningShards,
    /// Forwards other processes' job notifications to `wake` (PostgreSQL).
    wakeups: Option<tokio::task::JoinHandle<()>>,
}

/// The jobs this process is computing, by id, with their cancellation handles.
type Running = Arc<Mutex<HashMap<i64, Arc<Control>>>>;

/// The shards this process is solving, by (job id, shard), with their cancellation handles.
type RunningShards = Arc<Mutex<HashMap<(i64, i64), Arc<Control>>>>;

/// The memory estimates of the jobs running in this process, summed; held while claiming, so
/// two workers never both claim into the same room.
type Reserved = Arc<Mutex<u64>>;

/// Wakes idle workers when a job is queued; stops a running job at once when it is cancelled.
#[derive(Clone, Debug)]
pub struct JobNotifier {
    wake: Arc<Notify>,
    running: Running,
    shards: RunningShards,
}

impl JobNotifier {
    pub fn job_queued(&self) {
        self.wake.notify_waiters();
    }

    /// Tells the worker computing job `id` (if it runs in this process) to stop at its next
    /// check; the store already says `cancelled`, so its result would be fenced out anyway.
    pub fn cancel_running(&self, id: i64) {
        if let Some(control) = self.running.lock().expect("running lock").get(&id) {
            control.cancel();
        }
        for ((job, _), control) in self.shards.lock().expect("shards lock").iter() {
            if *job == id {
                control.cancel();
            }
        }
    }
}

impl WorkerPool {
    pub fn start(store: Store, runtime: Handle, config: PoolConfig) -> WorkerPool {
        let stop = Arc::new(AtomicBool::new(false));
        let wake = Arc::new(Notify::new());
        let running: Running = Arc::default();
        let shards: RunningShards = Arc::default();
        let reserved: Reserved = Arc::default();
        // Jobs queued by other processes sharing the database wake the idle workers.
        let wakeups = (config.workers > 0).then(|| {
            let (store, wake) = (store.clone(), wake.clone());
            runtime.spawn(async move { store.forward_job_wakeups(wake).await })
        });
        let threads = (0..config.workers)
            .map(|n| {
                let worker = Worker {
                    // Unique across processes and machines sharing the database.
                    id: format!("{}-w{n}", crate::store::WriterLease::new_holder()),
                    store: store.clone(),
                    runtime: runtime.clone(),
                    config: config.clone(),
                    stop: stop.clone(),
                    wake: wake.clone(),
                    running: running.clone(),
                    shards: shards.clone(),
                    reserved: reserved.clone(),
                };
                std::thread::Builder::new()
                    .name(format!("recon-worker-{n}"))
                    .spawn(move || worker.run())
                    .expect("spawn worker thread")
            })
            .collect();
        WorkerPool {
            threads,
            stop,
            wake,
            running,
            shards,
            wakeups,
        }
    }

    pub fn notifier(&self) -> JobNotifier {
        JobNotifier {
            wake: self.wake.clone(),
            running: self.running.clone(),
            shards: self.shards.clone(),
        }
    }

    /// Stops taking work; running jobs are cancelled and their leases given back (not counted as
    /// an attempt), so the next start picks them up again.
    pub fn shutdown(self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(w) = &self.wakeups {
            w.abort();
        }
        for control in self.running.lock().expect("running lock").values() {
            control.cancel();
        }
        for control in self.shards.lock().expect("shards lock").values() {
            control.cancel();
        }
        self.wake.notify_waiters();
        for t in self.threads {
            let _ = t.join();
        }
    }
}

struct Worker {
    id: String,
    store: Store,
    runtime: Handle,
    config: PoolConfig,
    stop: Arc<AtomicBool>,
    wake: Arc<Notify>,
    running: Running,
    shards: RunningShards,
    reserved: Reserved,
}

impl Worker {
    /// Claims a shard of any running transport job whose memory estimate fits what the
    /// running work leaves, and reserves the estimate.
    fn claim_shard(&self) -> Result<Option<ClaimedShard>, crate::store::StoreError> {
        let mut reserved = self.reserved.lock().expect("reserved lock");
        let room = if *reserved == 0 {
            u64::MAX
        } else {
            self.config.process_memory.saturating_sub(*reserved)
        };
        let shard = self.runtime.block_on(self.store.claim_shard(
            &self.id,
            self.config.lease.as_millis() as i64,
            room,
            None,
        ))?;
        if let Some(shard) = &shard {
            *reserved += shard.memory_bytes;
        }
        Ok(shard)
    }

    /// Claims the next job that fits the room the running jobs' estimates leave in the
    /// process's budget (any job when none runs), and reserves its estimate.
    fn claim(&self) -> Result<Option<ClaimedJob>, crate::store::StoreError> {
        let mut reserved = self.reserved.lock().expect("reserved lock");
        let room = if *reserved == 0 {
            u64::MAX
        } else {
            self.config.process_memory.saturating_sub(*reserved)
        };
        let job = self.runtime.block_on(self.store.claim_job_within(
            &self.id,
            self.config.lease.as_millis() as i64,
            self.config.max_running_per_lab,
            room,
        ))?;
        if let Some(job) = &job {
            *reserved += job.memory_bytes;
        }
        Ok(job)
    }

    /// Gives a finished job's reservation back; the last job out returns freed heap pages to
    /// the system.
    fn unreserve(&self, bytes: u64) {
        let mut reserved = self.reserved.lock().expect("reserved lock");
        *reserved = reserved.saturating_sub(bytes);
        let idle = self.running.lock().expect("running lock").is_empty();
        drop(reserved);
        if idle {
            crate::alloc::release_free_memory();
        }
        // A job that did not fit may fit now.
        self.wake.notify_waiters();
    }

    fn run(self) {
        while !self.stop.load(Ordering::SeqCst) {
            // Shards of running transport jobs first: they finish work already started.
            match self.claim_shard() {
                Ok(Some(shard)) => {
                    let memory = shard.memory_bytes;
                    self.run_shard(shard);
                    self.unreserve(memory);
                    continue;
                }
                Ok(None) => {}
                Err(e) => {
                    tracing::error!(worker = %self.id, error = %e, "claiming a shard failed");
                }
            }
            match self.claim() {
                Ok(Some(job)) => {
                    let memory = job.memory_bytes;
                    self.run_job(job);
                    self.unreserve(memory);
                }
                Ok(None) => self.idle(),
                Err(e) => {
                    tracing::error!(worker = %self.id, error = %e, "claiming a job failed");
                    self.idle();
                }
            }
        }
    }

    fn idle(&self) {
        let wake = self.wake.clone();
        let poll = self.config.idle_poll;
        self.runtime.block_on(async move {
            tokio::select! {
                _ = wake.notified() => {}
                _ = tokio::time::sleep(poll) => {}
            }
        });
    }

    fn run_job(&self, job: ClaimedJob) {
        let (id, attempt) = (job.id, job.attempt);
        let span = tracing::info_span!("job", id, attempt, method = %job.reconstruction.method);
        let _enter = span.enter();
        tracing::info!(session = %job.reconstruction.session_id, rows = job.reconstruction.rows_used, "job started");
        let control = Arc::new(Control::new());
        self.running
            .lock()
            .expect("running lock")
            .insert(id, control.clone());
        if self.stop.load(Ordering::SeqCst) {
            control.cancel();
        }
        let heartbeat = self.spawn_heartbeat(id, attempt, control.clone());
        let started = Instant::now();
        let heap_base = crate::alloc::live_bytes();
        crate::alloc::reset_peak();
        let outcome = std::panic::catch_unwind(AssertUnwindSafe(|| self.compute(&job, &control)))
            .unwrap_or_else(|panic| {
                let msg = panic
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_else(|| "unknown panic".into());
                Err(JobError::Internal(format!(
                    "reconstruction panicked: {msg}"
                )))
            });
        let seconds = started.elapsed().as_secs_f64();
        heartbeat.abort();
        self.running.lock().expect("running lock").remove(&id);
        let outcome_label = match &outcome {
            Ok(_) => "done",
            Err(JobError::Recon(ReconError::Cancelled)) if self.stop.load(Ordering::SeqCst) => {
                "released"
            }
            Err(JobError::Recon(ReconError::Cancelled)) => "cancelled",
            Err(_) => "failed",
        };
        metrics::histogram!("helmholtz_job_duration_seconds", "method" => job.reconstruction.method.clone(), "outcome" => outcome_label)
            .record(seconds);
        let store = &self.store;
        let result = match outcome {
            Ok(Computed {
                images,
                transport,
                mut report,
            }) => {
                // Process-wide: includes other jobs' live memory if several run at once.
                report.peak_memory_bytes = crate::alloc::installed()
                    .then(|| crate::alloc::peak_bytes().saturating_sub(heap_base) as u64);
                report.seconds = Some(seconds);
                // What the request estimated (and the workers reserved) against the budget.
                report.memory_estimate_bytes = Some(job.memory_bytes);
                match serde_json::to_string(&report) {
                    Ok(report) => self.runtime.block_on(store.complete_reconstruction(
                        id,
                        attempt,
                        &images,
                        transport.as_deref(),
                        &report,
                        seconds,
                    )),
                    Err(e) => self.runtime.block_on(store.fail_job(
                        id,
                        attempt,
                        &format!("internal error: writing the report: {e}"),
                        false,
                    )),
                }
            }
            Err(JobError::Recon(ReconError::Cancelled)) if self.stop.load(Ordering::SeqCst) => {
                self.runtime.block_on(store.release_job(id, attempt))
            }
            Err(JobError::Recon(ReconError::Cancelled)) => Ok(false),
            Err(JobError::Recon(ReconError::Source(e))) | Err(JobError::Source(e)) => self
                .runtime
                .block_on(store.fail_job(id, attempt, &e.to_string(), true)),
            Err(e) => self
                .runtime
                .block_on(store.fail_job(id, attempt, &e.to_string(), false)),
        };
        match result {
            Ok(true) => tracing::info!(seconds, "job ended"),
            Ok(false) if outcome_label == "cancelled" => {
                tracing::info!(seconds, "job stopped: cancelled")
            }
            Ok(false) => tracing::warn!(
                seconds,
                "job ended without its lease (cancelled or taken over)"
            ),
            Err(e) => tracing::error!(error = %e, "recording the job's end failed"),
        }
    }

    fn spawn_heartbeat(
        &self,
        id: i64,
        attempt: i64,
        control: Arc<Control>,
    ) -> tokio::task::JoinHandle<()> {
        let store = self.store.clone();
        let lease = self.config.lease;
        let stop = self.stop.clone();
        self.runtime.spawn(async move {
            loop {
                tokio::time::sleep(lease / 3).await;
                if stop.load(Ordering::SeqCst) {
                    control.cancel();
                }
                match store
                    .heartbeat(id, attempt, lease.as_millis() as i64, control.progress())
                    .await
                {
                    Ok(true) => {}
                    Ok(false) => {
                        tracing::warn!(id, attempt, "lease lost or job cancelled; stopping");
                        control.cancel();
                        return;
                    }
                    // A transient database error: keep the job; the lease has slack.
                    Err(e) => tracing::warn!(id, error = %e, "heartbeat failed"),
                }
            }
        })
    }

    /// Solves one claimed shard of a transport job and records the outcome, fenced by the
    /// shard's attempt: its part when solved; a transient failure (reading the frames) queues
    /// it again while attempts are left, any other fails it (and with it the job); a shutdown
    /// gives it back; a lost lease or a cancelled job stops it without a word.
    fn run_shard(&self, shard: ClaimedShard) {
        let (id, n, attempt) = (shard.reconstruction_id, shard.shard, shard.attempt);
        let span = tracing::info_span!("shard", job = id, shard = n, attempt);
        let _enter = span.enter();
        tracing::info!(
            blocks = ?(shard.first_block..shard.end_block),
            "shard started"
        );
        let control = Arc::new(Control::new());
        self.shards
            .lock()
            .expect("shards lock")
            .insert((id, n), control.clone());
        if self.stop.load(Ordering::SeqCst) {
            control.cancel();
        }
        let heartbeat = self.spawn_shard_heartbeat(id, n, attempt, control.clone());
        let started = Instant::now();
        let outcome =
            std::panic::catch_unwind(AssertUnwindSafe(|| self.solve_shard(&shard, &control)))
                .unwrap_or_else(|panic| {
                    let msg = panic
                        .downcast_ref::<String>()
                        .cloned()
                        .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_else(|| "unknown panic".into());
                    Err(JobError::Internal(format!("shard panicked: {msg}")))
                });
        let seconds = started.elapsed().as_secs_f64();
        heartbeat.abort();
        self.shards.lock().expect("shards lock").remove(&(id, n));
        let store = &self.store;
        let (label, result) = match outcome {
            Ok(part) => (
                "done",
                self.runtime
                    .block_on(store.complete_shard(id, n, attempt, &part)),
            ),
            Err(JobError::Recon(ReconError::Cancelled)) if self.stop.load(Ordering::SeqCst) => (
                "released",
                self.runtime.block_on(store.release_shard(id, n, attempt)),
            ),
            Err(JobError::Recon(ReconError::Cancelled)) => ("cancelled", Ok(false)),
            Err(JobError::Recon(ReconError::Source(e))) | Err(JobError::Source(e)) => (
                "failed",
                self.runtime.block_on(store.fail_shard(
                    id,
                    n,
                    attempt,
                    &format!("shard {n}: {e}"),
                    true,
                )),
            ),
            Err(e) => (
                "failed",
                self.runtime.block_on(store.fail_shard(
                    id,
                    n,
                    attempt,
                    &format!("shard {n}: {e}"),
                    false,
                )),
            ),
        };
        metrics::histogram!("helmholtz_shard_duration_seconds", "outcome" => label).record(seconds);
        match result {
            Ok(true) => tracing::info!(seconds, outcome = label, "shard ended"),
            Ok(false) => tracing::info!(
                seconds,
                outcome = label,
                "shard stopped (lease lost, job cancelled or ended)"
            ),
            Err(e) => tracing::error!(error = %e, "recording the shard's end failed"),
        }
        // The job's holder may be waiting for this shard.
        self.wake.notify_waiters();
    }

    /// The numerics of one shard: its blocks solved with the stored model, encoded.
    fn solve_shard(&self, shard: &ClaimedShard, control: &Control) -> Result<Vec<u8>, JobError> {
        let model = TransportModel::from_json(&shard.model_json)
            .map_err(|e| JobError::Internal(format!("stored transport model: {e}")))?;
        let session = self.session_for_recon(&shard.session_id)?;
        let camera = session.camera.ok_or_else(|| {
            JobError::Internal(format!(
                "session {:?} of a transport shard has no camera",
                session.id
            ))
        })?;
        let mut source = StoreFrames::new(
            &self.store,
            &self.runtime,
            &shard.session_id,
            shard.rows_used,
            camera,
        );
        let part = transport::solve_transport_blocks(
            &session.spec,
            &model,
            shard.first_block as usize..shard.end_block as usize,
            &mut source,
            control,
        )
        .map_err(JobError::Recon)?;
        Ok(part.encode())
    }

    fn spawn_shard_heartbeat(
        &self,
        id: i64,
        shard: i64,
        attempt: i64,
        control: Arc<Control>,
    ) -> tokio::task::JoinHandle<()> {
        let store = self.store.clone();
        let lease = self.config.lease;
        let stop = self.stop.clone();
        self.runtime.spawn(async move {
            loop {
                tokio::time::sleep(lease / 3).await;
                if stop.load(Ordering::SeqCst) {
                    control.cancel();
                }
                match store
                    .heartbeat_shard(id, shard, attempt, lease.as_millis() as i64)
                    .await
                {
                    Ok(true) => {}
                    Ok(false) => {
                        tracing::warn!(
                            id,
                            shard,
                            attempt,
                            "shard lease lost or job no longer running; stopping"
                        );
                        control.cancel();
                        return;
                    }
                    Err(e) => tracing::warn!(id, shard, error = %e, "shard heartbeat failed"),
                }
            }
        })
    }

    /// The session with the spec that generated its rows: an adaptive session's spec resolved
    /// with its stored index sequence ([`crate::store::Batches::resolved_spec`]).
    fn session_for_recon(&self, id: &str) -> Result<SessionRow, JobError> {
        let source = |e: crate::store::StoreError| JobError::Source(SourceError(e.to_string()));
        let mut session = self
            .runtime
            .block_on(self.store.session(id))
            .map_err(source)?;
        session.spec = self
            .runtime
            .block_on(self.store.resolved_spec(&session))
            .map_err(source)?;
        Ok(session)
    }

    /// Decodes the stored request (validated when it was queued) and dispatches it once.
    fn compute(&self, job: &ClaimedJob, control: &Control) -> Result<Computed, JobError> {
        let r = &job.reconstruction;
        let params: Value =
            serde_json::from_str(&r.params_json).map_err(|e| JobError::Internal(e.to_string()))?;
        let request = recon::Request::parse(&r.method, &params)
            .map_err(|e| JobError::Internal(format!("stored request: {e}")))?;
        let session = self.session_for_recon(&r.session_id)?;
        match (request, session.camera) {
            (recon::Request::Bucket(config), None) => {
                self.compute_buckets(job, &session, &config, control)
            }
            (recon::Request::Transport(config), Some(camera)) => {
                self.compute_transport(job, &session, camera, config, control)
            }
            (request, _) => Err(JobError::Internal(format!(
                "method {} does not fit session {:?}",
                request.name(),
                session.id
            ))),
        }
    }

    /// A bucket session: one dual image per channel.
    fn compute_buckets(
        &self,
        job: &ClaimedJob,
        session: &SessionRow,
        config: &MethodConfig,
        control: &Control,
    ) -> Result<Computed, JobError> {
        let r = &job.reconstruction;
        let problem = Problem {
            spec: &session.spec,
            channels: session.channels.len(),
            rows: r.rows_used,
        };
        let mut source = StoreSource {
            store: &self.store,
            runtime: &self.runtime,
            session_id: &r.session_id,
            channels: session.channels.len(),
            next_row: 0,
            limit: r.rows_used,
            pending: Vec::new(),
        };
        let result =
            recon::reconstruct(&problem, config, &mut source, control).map_err(JobError::Recon)?;
        let mut report = Report {
            recon: result.report,
            ..Report::default()
        };
        if session.has_ground_truth {
            let truth = self
                .runtime
                .block_on(self.store.ground_truth(&r.session_id))
                .map_err(|e| JobError::Source(SourceError(e.to_string())))?;
            if let Some((w, h, truth)) = truth {
                report.quality = Some(Quality::Channels(recon::metrics::dual_quality(
                    &result.images,
                    &session.channels,
                    w,
                    h,
                    &truth,
                )));
            }
        }
        let images = result
            .images
            .into_iter()
            .zip(&session.channels)
            .enumerate()
            .map(|(i, (img, name))| StoredImage {
                channel_index: i as u32,
                channel_name: name.clone(),
                width: img.width,
                height: img.height,
                data: img.data,
            })
            .collect();
        Ok(Computed {
            images,
            transport: None,
            report,
        })
    }

    /// A camera session: the transport matrix T (stored encoded), its dual image under the whole
    /// camera as the light (`T^T 1`, channel "camera"), and the ambient image (channel
    /// "ambient": what the camera sees that no projector pixel explains, e.g. dark level and
    /// room light, `mean frame - T mean pattern`).
    fn compute_transport(
        &self,
        job: &ClaimedJob,
        session: &SessionRow,
        camera: CameraLayout,
        config: TransportConfig,
        control: &Control,
    ) -> Result<Computed, JobError> {
        let r = &job.reconstruction;
        let heap_base = crate::alloc::live_bytes();
        let config = config.with_memory_budget(self.config.memory_budget);
        let grid = CameraGrid {
            width: camera.width,
            height: camera.height,
        };
        let mut source = StoreFrames::new(
            &self.store,
            &self.runtime,
            &r.session_id,
            r.rows_used,
            camera,
        );
        let store_error =
            |e: crate::store::StoreError| JobError::Source(SourceError(e.to_string()));
        // The model is chosen once: a holder after one that died reuses the stored one.
        let stored = self
            .runtime
            .block_on(self.store.transport_model(job.id))
            .map_err(store_error)?;
        let model_json = match stored {
            Some(json) => json,
            None => {
                let mut model = transport::plan_transport(
                    &session.spec,
                    grid,
                    r.rows_used,
                    &config,
                    &mut source,
                    control,
                )
                .map_err(JobError::Recon)?;
                let shard_pixels = self.config.transport_shard_pixels.max(1);
                model.limit_block_pixels(shard_pixels);
                let shards: Vec<(u64, u64)> = model
                    .shards(shard_pixels)
                    .into_iter()
                    .map(|s| (s.start as u64, s.end as u64))
                    .collect();
                let json = model.to_json();
                match self
                    .runtime
                    .block_on(self.store.start_shards(job.id, job.attempt, &json, &shards))
                    .map_err(store_error)?
                {
                    Some(stored) => stored,
                    // The job is no longer this run's.
                    None => return Err(JobError::Recon(ReconError::Cancelled)),
                }
            }
        };
        // Idle workers of this process (those of other processes hear the database).
        self.wake.notify_waiters();
        let model = TransportModel::from_json(&model_json)
            .map_err(|e| JobError::Internal(format!("stored transport model: {e}")))?;
        let progress0 = if model.exact { 0.0 } else { 0.2 };
        control.set_progress(progress0);
        // Solve shards of this job while there are any to claim, then wait for those that
        // others hold (the job's heartbeat keeps running meanwhile).
        let rows = loop {
            if control.is_cancelled() {
                return Err(JobError::Recon(ReconError::Cancelled));
            }
            let own = self
                .runtime
                .block_on(self.store.claim_shard(
                    &self.id,
                    self.config.lease.as_millis() as i64,
                    u64::MAX,
                    Some(job.id),
                ))
                .map_err(store_error)?;
            if let Some(shard) = own {
                // Within this job's own memory reservation.
                self.run_shard(shard);
                continue;
            }
            let rows = self
                .runtime
                .block_on(self.store.shards(job.id))
                .map_err(store_error)?;
            if let Some(failed) = rows.iter().find(|s| s.state == "failed") {
                return Err(JobError::Recon(ReconError::Unsolvable(format!(
                    "shard {} of {} (camera pixels of blocks {}..{}) failed after {} attempt(s): {}",
                    failed.shard,
                    rows.len(),
                    failed.first_block,
                    failed.end_block,
                    failed.attempt,
                    failed.last_error.as_deref().unwrap_or("no error recorded")
                ))));
            }
            if rows.is_empty() {
                return Err(JobError::Internal(format!(
                    "transport reconstruction {} has a model but no shards",
                    job.id
                )));
            }
            let done = rows.iter().filter(|s| s.state == "done").count();
            control.set_progress(
                progress0 + (1.0 - progress0) * done as f64 / rows.len().max(1) as f64,
            );
            if done == rows.len() {
                break rows;
            }
            let wake = self.wake.clone();
            let poll = self.config.idle_poll.min(Duration::from_millis(250));
            self.runtime.block_on(async move {
                tokio::select! {
                    _ = wake.notified() => {}
                    _ = tokio::time::sleep(poll) => {}
                }
            });
        };
        let parts = self
            .runtime
            .block_on(self.store.shard_parts(job.id))
            .map_err(store_error)?
            .iter()
            .map(|bytes| TransportPart::decode(bytes))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| JobError::Internal(format!("stored shard part: {e}")))?;
        let (t, result_report) =
            transport::assemble_transport(&model, &parts).map_err(JobError::Recon)?;
        // One pass over the frames per block, besides this worker's own (model choice, ambient).
        source.passes += model.block_count() as u64;
        let shard_workers = rows
            .iter()
            .filter_map(|s| s.worker_id.as_deref())
            .collect::<std::collections::BTreeSet<_>>()
            .len();
        let shard_figures = serde_json::json!({
            "count": rows.len(),
            "blocks": model.block_count(),
            "workers": shard_workers,
            "attempts": rows.iter().map(|s| s.attempt).sum::<i64>(),
            "solve_seconds": parts.iter().map(|p| p.seconds).sum::<f64>(),
            "model_seconds": model.seconds,
        });
        let ambient = source
            .ambient(&session.spec, &t, control)
            .map_err(JobError::Recon)?;
        let m = camera.pixels();
        let summed = t.relight(&vec![1.0; m]);
        // The reconstruction's own peak, before the ground truth (m x k) is loaded to score it.
        let working_peak =
            crate::alloc::installed().then(|| crate::alloc::peak_bytes().saturating_sub(heap_base));
        let mut report = Report {
            recon: result_report,
            ..Report::default()
        };
        // The service's figures of a transport run, beside the solver's own details.
        let details = &mut report.recon.details;
        if let Some(peak) = working_peak {
            details.insert("reconstruction_peak_bytes".into(), peak.into());
        }
        details.insert("shards".into(), shard_figures);
        let ambient_mean = ambient.iter().map(|&v| v as f64).sum::<f64>() / m as f64;
        details.insert("ambient_mean".into(), ambient_mean.into());
        details.insert("frame_passes".into(), source.passes.into());
        if session.has_ground_truth {
            let truth = self
                .runtime
                .block_on(self.store.ground_truth(&r.session_id))
                .map_err(|e| JobError::Source(SourceError(e.to_string())))?;
            if let Some((w, h, truth)) = truth {
                report.quality = Some(Quality::Transport(recon::metrics::transport_quality(
                    &t, &summed, w, h, &truth,
                )));
            }
        }
        let (pw, ph) = t.projector();
        let images = vec![
            StoredImage {
                channel_index: 0,
                channel_name: "camera".into(),
                width: pw,
                height: ph,
                data: summed,
            },
            StoredImage {
                channel_index: 1,
                channel_name: "ambient".into(),
                width: camera.width,
                height: camera.height,
                data: ambient,
            },
        ];
        Ok(Computed {
            images,
            transport: Some(t.encode()),
            report,
        })
    }
}

/// What a finished job stores.
struct Computed {
    images: Vec<StoredImage>,
    /// A camera session's encoded T.
    transport: Option<Vec<u8>>,
    /// The numerics' report and the quality; the job adds its time and memory.
    report: Report,
}

/// A camera session's stored frames, read a block of camera pixels at a time (one pass over
/// the stored chunks per block, a few chunks in memory at once).
struct StoreFrames<'a> {
    store: &'a Store,
    runtime: &'a Handle,
    session_id: &'a str,
    rows: u64,
    camera: CameraLayout,
    /// Passes made over the stored frames.
    passes: u64,
}

/// Stored chunks read per query: one, so the frames in memory beyond the solver's block are a
/// single upload chunk (at most `max_chunk_bytes`).
const CHUNKS_PER_PAGE: u32 = 1;

impl<'a> StoreFrames<'a> {
    fn new(
        store: &'a Store,
        runtime: &'a Handle,
        session_id: &'a str,
        rows: u64,
        camera: CameraLayout,
    ) -> Self {
        StoreFrames {
            store,
            runtime,
            session_id,
            rows,
            camera,
            passes: 0,
        }
    }

    /// Calls `visit(row, frame bytes)` for rows 0..rows in order.
    fn each_frame(
        &mut self,
        mut visit: impl FnMut(u64, &[u8]) -> Result<(), ReconError>,
    ) -> Result<(), ReconError> {
        self.passes += 1;
        let row_bytes = self.camera.pixels() * self.camera.format.bytes();
        let mut next = 0u64;
        while next < self.rows {
            let page = self
                .runtime
                .block_on(self.store.read_raw_chunks(
                    self.session_id,
                    next,
                    CHUNKS_PER_PAGE,
                    self.camera.format.bytes(),
                ))
                .map_err(|e| ReconError::Source(SourceError(e.to_string())))?;
            if page.is_empty() {
                return Err(ReconError::Source(SourceError(format!(
                    "frames end at row {next} before {}",
                    self.rows
                ))));
            }
            for (start, count, data) in page {
                for (i, frame) in data
                    .chunks_exact(row_bytes)
                    .enumerate()
                    .take(count as usize)
                {
                    let row = start + i as u64;
                    if row >= self.rows {
                        return Ok(());
                    }
                    visit(row, frame)?;
                }
                next = start + count;
            }
        }
        Ok(())
    }

    /// `mean frame - T mean pattern` over the rows used.
    fn ambient(
        &mut self,
        spec: &helmholtz_proto::PatternSpec,
        t: &transport::TransportMatrix,
        control: &Control,
    ) -> Result<Vec<f32>, ReconError> {
        let m = self.camera.pixels();
        let format = self.camera.format;
        let mut sum = vec![0f64; m];
        let mut decoded = Vec::with_capacity(m);
        self.each_frame(|_, frame| {
            decoded.clear();
            format.decode_f32(frame, &mut decoded);
            sum.iter_mut()
                .zip(&decoded)
                .for_each(|(s, v)| *s += *v as f64);
            Ok(())
        })?;
        if control.is_cancelled() {
            return Err(ReconError::Cancelled);
        }
        let k = spec.pixels();
        let generator = helmholtz_proto::PatternGenerator::new(spec);
        let mut mean_pattern = vec![0f64; k];
        let mut pattern = vec![0f32; k];
        for i in 0..self.rows {
            generator.fill_values(i, &mut pattern);
            mean_pattern
                .iter_mut()
                .zip(&pattern)
                .for_each(|(a, p)| *a += *p as f64);
        }
        let n = self.rows as f64;
        // A T on a coarser projector grid (`projector_binning`): each column is a block's
        // summed light, so the pattern's block means light it.
        let (tw, th) = t.projector();
        let b = (spec.width() / tw.max(1)) as usize;
        let mean_pattern: Vec<f32> = if b > 1 {
            let (w, cw) = (spec.width() as usize, tw as usize);
            let mut coarse = vec![0f64; cw * th as usize];
            for (i, v) in mean_pattern.iter().enumerate() {
                coarse[(i / w / b) * cw + (i % w) / b] += v;
            }
            let per = n * (b * b) as f64;
            coarse.iter().map(|v| (v / per) as f32).collect()
        } else {
            mean_pattern.iter().map(|v| (v / n) as f32).collect()
        };
        let explained = t.primal(&mean_pattern);
        Ok(sum
            .iter()
            .zip(explained)
            .map(|(s, e)| (s / n) as f32 - e)
            .collect())
    }
}

impl FrameSource for StoreFrames<'_> {
    fn read_pixels(&mut self, pixels: std::ops::Range<usize>) -> Result<Vec<f32>, SourceError> {
        let m = self.camera.pixels();
        if pixels.end > m || pixels.start > pixels.end {
            return Err(SourceError(format!(
                "camera pixels {pixels:?} outside 0..{m}"
            )));
        }
        let format = self.camera.format;
        let sb = format.bytes();
        let mut out = Vec::with_capacity(self.rows as usize * pixels.len());
        let range = pixels.start * sb..pixels.end * sb;
        self.each_frame(|_, frame| {
            format.decode_f32(&frame[range.clone()], &mut out);
            Ok(())
        })
        .map_err(|e| match e {
            ReconError::Source(s) => s,
            other => SourceError(other.to_string()),
        })?;
        Ok(out)
    }
}

#[derive(Debug, thiserror::Error)]
enum JobError {
    #[error(transparent)]
    Recon(ReconError),
    #[error(transparent)]
    Source(SourceError),
    #[error("internal error: {0}")]
    Internal(String),
}

/// Streams a session's stored chunks to the numerics, a page of chunks at a time, stopping at
/// the reconstruction's row count.
struct StoreSource<'a> {
    store: &'a Store,
    runtime: &'a Handle,
    session_id: &'a str,
    channels: usize,
    next_row: u64,
    limit: u64,
    pending: Vec<(u64, Vec<f64>)>,
}

impl BucketSource for StoreSource<'_> {
    fn next_block(&mut self) -> Result<Option<BucketBlock>, SourceError> {
        if self.next_row >= self.limit {
            return Ok(None);
        }
        if self.pending.is_empty() {
            let mut page = self
                .runtime
                .block_on(self.store.read_chunks(self.session_id, self.next_row, 64))
                .map_err(|e| SourceError(e.to_string()))?;
            if page.is_empty() {
                return Err(SourceError(format!(
                    "rows end at {} before {}",
                    self.next_row, self.limit
                )));
            }
            page.reverse();
            self.pending = page;
        }
        let (start, mut values) = self.pending.pop().expect("non-empty");
        let rows = (values.len() / self.channels) as u64;
        let end = (start + rows).min(self.limit);
        values.truncate(((end - start) as usize) * self.channels);
        self.next_row = start + rows;
        Ok(Some(BucketBlock {
            first_row: start,
            values,
        }))
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use helmholtz_proto::{Family, PatternGenerator, PatternSpec};

    use super::*;
    use crate::store::{NewSession, SampleFormat};

    /// Frames of a camera whose pixel `j` sees a blob of the projector near its own place.
    fn frames(spec: &PatternSpec, cw: usize, ch: usize) -> Vec<f32> {
        let (pw, ph) = (spec.width() as usize, spec.height() as usize);
        let k = pw * ph;
        let mut t = vec![0f32; cw * ch * k];
        for cy in 0..ch {
            for cx in 0..cw {
                let (px, py) = (
                    (cx as f64 + 0.5) * pw as f64 / cw as f64,
                    (cy as f64 + 0.5) * ph as f64 / ch as f64,
                );
                for y in 0..ph {
                    for x in 0..pw {
                        let d2 = (x as f64 - px).powi(2) + (y as f64 - py).powi(2);
                        t[(cy * cw + cx) * k + y * pw + x] = (-d2 / 2.0).exp() as f32;
                    }
                }
            }
        }
        let g = PatternGenerator::new(spec);
        let mut p = vec![0f32; k];
        let mut out = Vec::new();
        for i in 0..spec.count() {
            g.fill_values(i, &mut p);
            for row in t.chunks_exact(k) {
                out.push(row.iter().zip(&p).map(|(a, b)| a * b).sum::<f32>());
            }
        }
        out
    }

    /// On the embedded database, two worker threads of one process: the transport job runs in
    /// shards (the other worker, woken by the in-process notifier, takes some), and the stored T
    /// is the one `reconstruct_transport` makes in one call, bit for bit.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_transport_job_in_shards_stores_the_single_call_t() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).await.unwrap();
        let spec = PatternSpec::new(Family::Bernoulli { fill: 0.5 }, 16, 16, 192, 3).unwrap();
        let (cw, ch) = (16usize, 8usize);
        let f = frames(&spec, cw, ch);
        let camera = CameraLayout {
            width: cw as u32,
            height: ch as u32,
            format: SampleFormat::F32,
        };
        store
            .create_session(&NewSession {
                id: "cam".into(),
                lab: "default".into(),
                rig: "bench".into(),
                spec: spec.clone(),
                channels: Vec::new(),
                directions: Vec::new(),
                camera: Some(camera),
                metadata: BTreeMap::new(),
                ground_truth: None,
            })
            .await
            .unwrap();
        let bytes: Vec<u8> = f.iter().flat_map(|v| v.to_le_bytes()).collect();
        store
            .append_raw("cam", None, 0, cw * ch * 4, &bytes)
            .await
            .unwrap();
        store.finish_session("cam").await.unwrap();
        let params = r#"{"sample_pixels": 8}"#;
        let r = store
            .enqueue_reconstruction("default", "cam", "transport", params, 192, 3)
            .await
            .unwrap();
        let config = PoolConfig {
            workers: 2,
            idle_poll: Duration::from_millis(50),
            transport_shard_pixels: 16,
            ..PoolConfig::default()
        };
        let memory_budget = config.memory_budget;
        let pool = WorkerPool::start(store.clone(), Handle::current(), config);
        let deadline = Instant::now() + Duration::from_secs(120);
        let done = loop {
            let row = store.reconstruction(r.id).await.unwrap();
            if row.state == "done" || row.state == "failed" {
                break row;
            }
            assert!(Instant::now() < deadline, "still {}", row.state);
            tokio::time::sleep(Duration::from_millis(50)).await;
        };
        tokio::task::spawn_blocking(move || pool.shutdown())
            .await
            .unwrap();
        assert_eq!(done.state, "done", "{:?}", done.last_error);
        let shards = store.shards(r.id).await.unwrap();
        assert_eq!(shards.len(), 8, "{shards:?}");
        assert!(
            shards
                .iter()
                .all(|s| s.state == "done" && s.part_bytes.is_none())
        );
        let workers: std::collections::BTreeSet<_> =
            shards.iter().filter_map(|s| s.worker_id.clone()).collect();
        assert_eq!(workers.len(), 2, "{workers:?}");
        let stored = store.transport(r.id).await.unwrap().unwrap();

        let config = TransportConfig::parse(&serde_json::from_str(params).unwrap())
            .unwrap()
            .with_memory_budget(memory_budget);
        let mut source = transport::SliceFrames::new(&f, cw * ch);
        let grid = CameraGrid {
            width: cw as u32,
            height: ch as u32,
        };
        let (t, report) = transport::reconstruct_transport(
            &spec,
            grid,
            192,
            &config,
            &mut source,
            &Control::new(),
        )
        .unwrap();
        assert!(
            stored == t.encode(),
            "the sharded T differs from one call's"
        );
        let stored_report: Report =
            serde_json::from_str(done.report_json.as_deref().unwrap()).unwrap();
        assert_eq!(
            stored_report.recon.details["selection"],
            report.details["selection"]
        );
        assert_eq!(stored_report.recon.iterations, report.iterations);
        assert_eq!(stored_report.recon.held_out, report.held_out);
    }
}
