//! The only place that speaks HTTP or gRPC. Handlers validate, call the store or the job queue,
//! and map errors once (see [`error`]).

pub mod error;
pub mod grpc;
pub mod images;
pub mod rest;
mod validate;

use std::collections::HashSet;
use std::sync::{Arc, Mutex};

use serde_json::Value;

pub use error::ApiError;

use crate::jobs::JobNotifier;
use crate::recon::{MethodConfig, Problem};
use crate::store::{ReconstructionRow, Store};

/// Shared by every handler.
#[derive(Clone, Debug)]
pub struct AppState {
    pub store: Store,
    pub jobs: JobNotifier,
    writers: Arc<Mutex<HashSet<String>>>,
}

/// Holds a session's single-writer slot until dropped.
pub struct WriterGuard {
    writers: Arc<Mutex<HashSet<String>>>,
    session_id: String,
}

impl Drop for WriterGuard {
    fn drop(&mut self) {
        self.writers.lock().expect("writers lock").remove(&self.session_id);
    }
}

impl AppState {
    pub fn new(store: Store, jobs: JobNotifier) -> Self {
        AppState { store, jobs, writers: Arc::default() }
    }

    /// One uploader per session at a time: a second concurrent stream is ABORTED.
    pub fn lock_writer(&self, session_id: &str) -> Result<WriterGuard, ApiError> {
        let mut writers = self.writers.lock().expect("writers lock");
        if !writers.insert(session_id.to_string()) {
            return Err(ApiError::Aborted(format!(
                "another upload to session {session_id:?} is in progress; retry after it ends"
            )));
        }
        Ok(WriterGuard { writers: self.writers.clone(), session_id: session_id.to_string() })
    }

    /// Validates and queues a reconstruction of the session's rows committed so far.
    pub async fn request_reconstruction(
        &self,
        session_id: &str,
        method: &str,
        params: &Value,
    ) -> Result<ReconstructionRow, ApiError> {
        let config = MethodConfig::parse(method, params)
            .map_err(|e| ApiError::invalid(e.field.clone(), e.message.clone()))?;
        let session = self.store.session(session_id).await?;
        let problem = Problem { spec: &session.spec, channels: session.channels.len(), rows: session.committed_rows };
        config.check(&problem).map_err(|e| ApiError::FailedPrecondition(e.to_string()))?;
        let row = self
            .store
            .enqueue_reconstruction(session_id, config.name(), &config.params_json().to_string(), session.committed_rows, 3)
            .await?;
        self.jobs.job_queued();
        Ok(row)
    }
}
