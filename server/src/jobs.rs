//! The worker pool: fixed OS threads that claim reconstruction jobs from the store and run the
//! numerics off the async runtime. Each running job has a heartbeat task that extends its lease;
//! losing the lease (or a cancel) stops the computation at its next check.

use std::collections::HashMap;
use std::panic::AssertUnwindSafe;
use std::sync::{Arc, Mutex};
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use tokio::runtime::Handle;
use tokio::sync::Notify;

use crate::recon::{self, BucketBlock, BucketSource, Control, MethodConfig, Problem, ReconError, SourceError};
use crate::store::{ClaimedJob, StoredImage, Store};

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
}

impl Default for PoolConfig {
    fn default() -> Self {
        PoolConfig { workers: 2, lease: Duration::from_secs(30), idle_poll: Duration::from_millis(500), max_running_per_lab: 0 }
    }
}

/// Running worker threads. Dropping it without `shutdown` leaves them running.
pub struct WorkerPool {
    threads: Vec<JoinHandle<()>>,
    stop: Arc<AtomicBool>,
    wake: Arc<Notify>,
    running: Running,
}

/// The jobs this process is computing, by id, with their cancellation handles.
type Running = Arc<Mutex<HashMap<i64, Arc<Control>>>>;

/// Wakes idle workers when a job is queued; stops a running job at once when it is cancelled.
#[derive(Clone, Debug)]
pub struct JobNotifier {
    wake: Arc<Notify>,
    running: Running,
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
    }
}

impl WorkerPool {
    pub fn start(store: Store, runtime: Handle, config: PoolConfig) -> WorkerPool {
        let stop = Arc::new(AtomicBool::new(false));
        let wake = Arc::new(Notify::new());
        let running: Running = Arc::default();
        let threads = (0..config.workers.max(1))
            .map(|n| {
                let worker = Worker {
                    id: format!("{}-{n}", std::process::id()),
                    store: store.clone(),
                    runtime: runtime.clone(),
                    config: config.clone(),
                    stop: stop.clone(),
                    wake: wake.clone(),
                    running: running.clone(),
                };
                std::thread::Builder::new()
                    .name(format!("recon-worker-{n}"))
                    .spawn(move || worker.run())
                    .expect("spawn worker thread")
            })
            .collect();
        WorkerPool { threads, stop, wake, running }
    }

    pub fn notifier(&self) -> JobNotifier {
        JobNotifier { wake: self.wake.clone(), running: self.running.clone() }
    }

    /// Stops taking work; running jobs are cancelled and their leases given back (not counted as
    /// an attempt), so the next start picks them up again.
    pub fn shutdown(self) {
        self.stop.store(true, Ordering::SeqCst);
        for control in self.running.lock().expect("running lock").values() {
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
}

impl Worker {
    fn run(self) {
        let lease_ms = self.config.lease.as_millis() as i64;
        while !self.stop.load(Ordering::SeqCst) {
            match self.runtime.block_on(self.store.claim_job(&self.id, lease_ms, self.config.max_running_per_lab)) {
                Ok(Some(job)) => self.run_job(job),
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
        self.running.lock().expect("running lock").insert(id, control.clone());
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
                Err(JobError::Internal(format!("reconstruction panicked: {msg}")))
            });
        let seconds = started.elapsed().as_secs_f64();
        heartbeat.abort();
        self.running.lock().expect("running lock").remove(&id);
        let outcome_label = match &outcome {
            Ok(_) => "done",
            Err(JobError::Recon(ReconError::Cancelled)) if self.stop.load(Ordering::SeqCst) => "released",
            Err(JobError::Recon(ReconError::Cancelled)) => "cancelled",
            Err(_) => "failed",
        };
        metrics::histogram!("helmholtz_job_duration_seconds", "method" => job.reconstruction.method.clone(), "outcome" => outcome_label)
            .record(seconds);
        let store = &self.store;
        let result = match outcome {
            Ok((images, mut report)) => {
                if crate::alloc::installed() {
                    // Process-wide: includes other jobs' live memory if several run at once.
                    report["peak_memory_bytes"] = json!(crate::alloc::peak_bytes().saturating_sub(heap_base));
                }
                report["seconds"] = json!(seconds);
                let report = report.to_string();
                self.runtime.block_on(store.complete_reconstruction(id, attempt, &images, &report, seconds))
            }
            Err(JobError::Recon(ReconError::Cancelled)) if self.stop.load(Ordering::SeqCst) => {
                self.runtime.block_on(store.release_job(id, attempt))
            }
            Err(JobError::Recon(ReconError::Cancelled)) => Ok(false),
            Err(JobError::Recon(ReconError::Source(e))) | Err(JobError::Source(e)) => {
                self.runtime.block_on(store.fail_job(id, attempt, &e.to_string(), true))
            }
            Err(e) => self.runtime.block_on(store.fail_job(id, attempt, &e.to_string(), false)),
        };
        match result {
            Ok(true) => tracing::info!(seconds, "job ended"),
            Ok(false) if outcome_label == "cancelled" => tracing::info!(seconds, "job stopped: cancelled"),
            Ok(false) => tracing::warn!(seconds, "job ended without its lease (cancelled or taken over)"),
            Err(e) => tracing::error!(error = %e, "recording the job's end failed"),
        }
    }

    fn spawn_heartbeat(&self, id: i64, attempt: i64, control: Arc<Control>) -> tokio::task::JoinHandle<()> {
        let store = self.store.clone();
        let lease = self.config.lease;
        let stop = self.stop.clone();
        self.runtime.spawn(async move {
            loop {
                tokio::time::sleep(lease / 3).await;
                if stop.load(Ordering::SeqCst) {
                    control.cancel();
                }
                match store.heartbeat(id, attempt, lease.as_millis() as i64, control.progress()).await {
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

    fn compute(&self, job: &ClaimedJob, control: &Control) -> Result<(Vec<StoredImage>, Value), JobError> {
        let r = &job.reconstruction;
        let session = self.runtime.block_on(self.store.session(&r.session_id)).map_err(|e| JobError::Source(SourceError(e.to_string())))?;
        let params: Value = serde_json::from_str(&r.params_json).map_err(|e| JobError::Internal(e.to_string()))?;
        let config = MethodConfig::parse(&r.method, &params).map_err(|e| JobError::Internal(e.to_string()))?;
        let problem = Problem { spec: &session.spec, channels: session.channels.len(), rows: r.rows_used };
        let mut source = StoreSource {
            store: &self.store,
            runtime: &self.runtime,
            session_id: &r.session_id,
            channels: session.channels.len(),
            next_row: 0,
            limit: r.rows_used,
            pending: Vec::new(),
        };
        let result = recon::reconstruct(&problem, &config, &mut source, control).map_err(JobError::Recon)?;
        let mut report = serde_json::to_value(&result.report).map_err(|e| JobError::Internal(e.to_string()))?;
        if session.has_ground_truth {
            let truth = self.runtime.block_on(self.store.ground_truth(&r.session_id)).map_err(|e| JobError::Source(SourceError(e.to_string())))?;
            if let Some((w, h, truth)) = truth {
                report["quality"] = quality(&result.images, &session.channels, w, h, &truth);
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
        Ok((images, report))
    }
}

/// Quality against the simulator's ground truth, per channel: raw PSNR/SSIM, and PSNR after the
/// least-squares affine fit (correlation methods estimate t only up to scale and offset).
/// `truth` holds one image shared by every channel, or one per channel.
fn quality(images: &[recon::DualImage], channels: &[String], w: u32, h: u32, truth: &[f32]) -> Value {
    let k = w as usize * h as usize;
    let per_channel: Vec<Value> = images
        .iter()
        .zip(channels)
        .enumerate()
        .filter(|(_, (img, _))| img.width == w && img.height == h)
        .map(|(c, (img, name))| {
            let truth = if truth.len() >= (c + 1) * k && truth.len() > k { &truth[c * k..(c + 1) * k] } else { &truth[..k] };
            let (a, b) = recon::metrics::fit_affine(&img.data, truth);
            let fitted: Vec<f32> = img.data.iter().map(|&v| (a * v as f64 + b) as f32).collect();
            json!({
                "channel": name,
                "psnr_db": finite_or_null(recon::metrics::psnr(&img.data, truth)),
                "ssim": finite_or_null(recon::metrics::ssim(&img.data, truth, w as usize, h as usize)),
                "relative_error": finite_or_null(recon::metrics::relative_error(&img.data, truth)),
                "psnr_fitted_db": finite_or_null(recon::metrics::psnr(&fitted, truth)),
                "ssim_fitted": finite_or_null(recon::metrics::ssim(&fitted, truth, w as usize, h as usize)),
                "fit": {"scale": a, "offset": b},
            })
        })
        .collect();
    Value::Array(per_channel)
}

fn finite_or_null(v: f64) -> Value {
    if v.is_finite() { json!(v) } else if v == f64::INFINITY { json!("inf") } else { Value::Null }
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
                return Err(SourceError(format!("rows end at {} before {}", self.next_row, self.limit)));
            }
            page.reverse();
            self.pending = page;
        }
        let (start, mut values) = self.pending.pop().expect("non-empty");
        let rows = (values.len() / self.channels) as u64;
        let end = (start + rows).min(self.limit);
        values.truncate(((end - start) as usize) * self.channels);
        self.next_row = start + rows;
        Ok(Some(BucketBlock { first_row: start, values }))
    }
}
