//! The only place that speaks HTTP or gRPC. Handlers authenticate, validate, call the store or
//! the job queue, and map errors once (see [`error`]).

pub mod acquire;
pub mod error;
pub mod grpc;
pub mod images;
pub mod json;
pub mod openapi;
pub mod preview;
pub mod relight;
pub mod rest;
pub mod upload;
pub mod validate;
pub mod web;

use std::sync::Arc;

pub use error::ApiError;

use crate::auth::{self, CredentialError, Principal, Role};
use crate::jobs::JobNotifier;
use crate::limits::{Limits, RateLimiter};
use crate::recon::{self, Problem};
use crate::store::{ReconstructionRow, SessionRow, Store, StoreError, WriterLease};

/// Shared by every handler.
#[derive(Clone, Debug)]
pub struct AppState {
    pub store: Store,
    pub jobs: JobNotifier,
    pub limits: Arc<Limits>,
    rate: Arc<RateLimiter>,
    /// Decoded transport matrices of camera reconstructions, for relighting.
    pub transports: Arc<relight::TransportCache>,
    /// Relight and primal responses by ETag.
    pub responses: Arc<relight::ResponseCache>,
    /// The working-set budget of one transport reconstruction (its memory estimate), bytes.
    pub transport_memory: u64,
    /// The live previews being watched ([`crate::preview`]).
    pub previews: Arc<crate::preview::Watchers>,
}

/// Holds a session's upload lease (one writer per session, across every server process that
/// shares the database) until dropped: a heartbeat renews it while the stream is open, every
/// append checks it, and dropping the guard gives it back.
pub struct WriterGuard {
    pub lease: WriterLease,
    store: Store,
    heartbeat: tokio::task::JoinHandle<()>,
    released: bool,
}

impl WriterGuard {
    /// Gives the lease back before returning, so the writer's next stream (or another writer)
    /// finds the session free at once. (Dropping the guard also gives it back, a moment later.)
    pub async fn release(mut self) {
        self.heartbeat.abort();
        self.released = true;
        if let Err(e) = self.store.release_writer(&self.lease).await {
            tracing::warn!(session = %self.lease.session_id, error = %e, "could not release an upload lease");
        }
    }
}

impl Drop for WriterGuard {
    fn drop(&mut self) {
        self.heartbeat.abort();
        if self.released {
            return;
        }
        let (store, lease) = (self.store.clone(), self.lease.clone());
        if let Ok(rt) = tokio::runtime::Handle::try_current() {
            rt.spawn(async move {
                if let Err(e) = store.release_writer(&lease).await {
                    // It expires on its own after its ttl.
                    tracing::warn!(session = %lease.session_id, error = %e, "could not release an upload lease");
                }
            });
        }
    }
}

impl Principal {
    /// PERMISSION_DENIED / 403 unless the token carries `role`.
    pub fn require(&self, role: Role) -> Result<(), ApiError> {
        if self.roles.contains(role) {
            Ok(())
        } else {
            Err(ApiError::PermissionDenied(format!(
                "this needs the {role} role; this token (id {}) has {}",
                self.token_id, self.roles
            )))
        }
    }

    /// Like [`require`](Self::require), for calls any of several roles may make.
    pub fn require_any(&self, roles: &[Role]) -> Result<(), ApiError> {
        if roles.iter().any(|r| self.roles.contains(*r)) {
            return Ok(());
        }
        let names: Vec<&str> = roles.iter().map(|r| r.name()).collect();
        Err(ApiError::PermissionDenied(format!(
            "this needs one of the roles {}; this token (id {}) has {}",
            names.join(", "),
            self.token_id,
            self.roles
        )))
    }
}

impl AppState {
    pub fn new(store: Store, jobs: JobNotifier, limits: Limits) -> Self {
        AppState {
            store,
            jobs,
            limits: Arc::new(limits),
            rate: Arc::default(),
            transports: Arc::new(relight::TransportCache::new(2 << 30)),
            responses: Arc::new(relight::ResponseCache::new(64 << 20)),
            transport_memory: crate::recon::transport::DEFAULT_MEMORY_BUDGET as u64,
            previews: Arc::default(),
        }
    }

    /// The working-set budget the workers give a transport reconstruction, bytes.
    pub fn with_transport_memory(mut self, bytes: u64) -> Self {
        self.transport_memory = bytes;
        self
    }

    /// Keeps at most `bytes` of decoded transport matrices in memory.
    pub fn with_transport_cache(mut self, bytes: usize) -> Self {
        self.transports = Arc::new(relight::TransportCache::new(bytes));
        self
    }

    /// The caller behind an `Authorization` header value (401 / UNAUTHENTICATED when there is
    /// none or it is not a valid token), charged one request against its rate limit (429 /
    /// RESOURCE_EXHAUSTED with a retry delay).
    pub async fn authenticate(&self, authorization: Option<&[u8]>) -> Result<Principal, ApiError> {
        let token = auth::token_from_authorization(authorization).map_err(|e| match e {
            CredentialError::Missing => ApiError::Unauthenticated(
                "missing credentials: send \"Authorization: Bearer <token>\" (helmholtz --token or HELMHOLTZ_TOKEN)".into(),
            ),
            CredentialError::Malformed(why) => ApiError::Unauthenticated(format!("malformed Authorization header: {why}")),
        })?;
        let principal = self
            .store
            .authenticate(&token)
            .await?
            .ok_or_else(|| ApiError::Unauthenticated("unknown or revoked token".into()))?;
        if let Err(wait) = self.rate.check(
            principal.token_id,
            self.limits.rate_per_second,
            self.limits.rate_burst,
        ) {
            metrics::counter!("helmholtz_rate_limited_total").increment(1);
            return Err(ApiError::ResourceExhausted {
                limit: "rate_per_second",
                message: format!(
                    "this token may make {} requests per second (bursts of {}); retry in {:.1} s",
                    self.limits.rate_per_second,
                    self.limits.rate_burst,
                    wait.as_secs_f64()
                ),
                retry_after: Some(wait.as_secs_f64().ceil().max(1.0) as u64),
            });
        }
        Ok(principal)
    }

    /// The caller's session `id`. Another lab's session is NOT_FOUND with exactly the message
    /// of a session that does not exist.
    pub async fn own_session(&self, caller: &Principal, id: &str) -> Result<SessionRow, ApiError> {
        match self.store.get_session(id).await? {
            Some(s) if s.lab == caller.lab => Ok(s),
            _ => Err(StoreError::SessionNotFound(id.to_string()).into()),
        }
    }

    /// The caller's reconstruction `id`; another lab's is NOT_FOUND like a missing one.
    pub async fn own_reconstruction(
        &self,
        caller: &Principal,
        id: i64,
    ) -> Result<ReconstructionRow, ApiError> {
        match self.store.get_reconstruction(id).await? {
            Some(r) if r.lab == caller.lab => Ok(r),
            _ => Err(StoreError::ReconstructionNotFound(id).into()),
        }
    }

    /// One uploader per session at a time, enforced in the database (so across server
    /// processes): another writer's concurrent stream is ABORTED naming the session. `writer`:
    /// the client's upload id (`x-helmholtz-writer`), whose new stream takes over from its own
    /// earlier one.
    pub async fn lock_writer(
        &self,
        session_id: &str,
        writer: &str,
    ) -> Result<WriterGuard, ApiError> {
        let lease = WriterLease {
            session_id: session_id.to_string(),
            holder: WriterLease::new_holder(),
            writer: writer.to_string(),
            ttl: self.limits.upload_lease,
        };
        if !self.store.acquire_writer(&lease).await? {
            metrics::counter!("helmholtz_upload_writer_conflicts_total").increment(1);
            return Err(ApiError::Aborted(format!(
                "session {session_id:?} has another writer: another upload to it is in progress (from another \
                 client or through another server process); one writer per session at a time. Nothing \
                 of this stream was stored; retry after that upload ends"
            )));
        }
        let heartbeat = tokio::spawn({
            let (store, lease) = (self.store.clone(), lease.clone());
            async move {
                let every = (lease.ttl / 3).max(std::time::Duration::from_millis(100));
                loop {
                    tokio::time::sleep(every).await;
                    match store.renew_writer(&lease).await {
                        Ok(true) => {}
                        // Lost (it expired and another writer took it): appends are refused.
                        Ok(false) => break,
                        Err(e) => {
                            tracing::warn!(session = %lease.session_id, error = %e, "upload lease renewal failed")
                        }
                    }
                }
            }
        });
        Ok(WriterGuard {
            lease,
            store: self.store.clone(),
            heartbeat,
            released: false,
        })
    }

    /// Queues a reconstruction of the session's rows committed so far. `request` was parsed once
    /// at the edge ([`recon::Request::parse`]); here it is checked against the session (camera
    /// or buckets, rows, memory) and stored by name and canonical parameters.
    pub async fn request_reconstruction(
        &self,
        caller: &Principal,
        session_id: &str,
        request: &recon::Request,
    ) -> Result<ReconstructionRow, ApiError> {
        let session = self.own_session(caller, session_id).await?;
        let memory = match request {
            recon::Request::Transport(config) => {
                if session.camera.is_none() {
                    return Err(ApiError::FailedPrecondition(format!(
                        "session {session_id:?} has bucket detectors, not a camera; transport reconstructs camera sessions (use gi, dgi, ngi, direct, zero_filled, levels, lsq, cs, tv or auto)"
                    )));
                }
                if session.committed_rows == 0 {
                    return Err(ApiError::FailedPrecondition(format!(
                        "session {session_id:?} has no frames yet"
                    )));
                }
                let spec = self.store.resolved_spec(&session).await?;
                config
                    .check(&spec)
                    .map_err(|e| ApiError::FailedPrecondition(e.to_string()))?;
                // The solver sizes its blocks of camera pixels to stay within this.
                self.transport_memory
            }
            recon::Request::Bucket(config) => {
                if session.camera.is_some() {
                    return Err(ApiError::FailedPrecondition(format!(
                        "session {session_id:?} is a camera session: reconstruct its transport matrix with method \"transport\""
                    )));
                }
                let spec = self.store.resolved_spec(&session).await?;
                let problem = Problem {
                    spec: &spec,
                    channels: session.channels.len(),
                    rows: session.committed_rows,
                };
                config
                    .check(&problem)
                    .map_err(|e| ApiError::FailedPrecondition(e.to_string()))?;
                config.memory_estimate(&problem)
            }
        };
        if memory > self.limits.memory_budget {
            return Err(ApiError::MemoryBudget {
                estimate: memory,
                budget: self.limits.memory_budget,
            });
        }
        let row = self
            .store
            .enqueue_reconstruction_capped(
                &caller.lab,
                session_id,
                request.name(),
                &request.params_json().to_string(),
                session.committed_rows,
                3,
                self.limits.max_pending_jobs_per_lab,
                memory,
            )
            .await?;
        self.jobs.job_queued();
        Ok(row)
    }

    /// Cancels a queued or running reconstruction of the caller's lab; a running worker stops
    /// at its next cancellation check.
    pub async fn cancel_reconstruction(
        &self,
        caller: &Principal,
        id: i64,
    ) -> Result<ReconstructionRow, ApiError> {
        let r = self.own_reconstruction(caller, id).await?;
        if !self.store.cancel_job(id).await? {
            let now = self.store.reconstruction(id).await?;
            if now.state == "cancelled" {
                return Ok(now);
            }
            return Err(ApiError::FailedPrecondition(format!(
                "reconstruction {id} is {}; only queued or running reconstructions can be cancelled",
                now.state
            )));
        }
        self.jobs.cancel_running(r.id);
        tracing::info!(reconstruction = id, lab = %caller.lab, "reconstruction cancelled");
        Ok(self.store.reconstruction(id).await?)
    }
}
