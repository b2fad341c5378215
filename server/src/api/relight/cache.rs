//! Decoded transport matrices and encoded answers, each within a byte budget.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};

use axum::body::Bytes;

use super::super::{ApiError, AppState};
use crate::recon::transport::TransportMatrix;

/// Decoded transport matrices by reconstruction id, within a byte budget.
#[derive(Debug)]
pub struct TransportCache {
    budget: usize,
    /// Most recently used last.
    entries: Mutex<Vec<(i64, Arc<TransportMatrix>, usize)>>,
}

impl TransportCache {
    pub fn new(budget: usize) -> Self {
        TransportCache {
            budget,
            entries: Mutex::new(Vec::new()),
        }
    }

    /// The decoded T of a finished camera reconstruction (decoded off the async threads).
    pub async fn get(&self, state: &AppState, id: i64) -> Result<Arc<TransportMatrix>, ApiError> {
        {
            let mut entries = self.entries.lock().expect("transport cache");
            if let Some(pos) = entries.iter().position(|(i, _, _)| *i == id) {
                let e = entries.remove(pos);
                let t = e.1.clone();
                entries.push(e);
                return Ok(t);
            }
        }
        let bytes = state.store.transport(id).await?.ok_or_else(|| {
            ApiError::Internal(format!(
                "reconstruction {id} is done but has no stored transport matrix"
            ))
        })?;
        let size = bytes.len();
        let t = tokio::task::spawn_blocking(move || TransportMatrix::decode(&bytes))
            .await
            .map_err(|e| ApiError::Internal(e.to_string()))?
            .map_err(|e| {
                ApiError::Internal(format!(
                    "stored transport matrix of reconstruction {id}: {e}"
                ))
            })?;
        let t = Arc::new(t);
        let mut entries = self.entries.lock().expect("transport cache");
        if !entries.iter().any(|(i, _, _)| *i == id) {
            entries.push((id, t.clone(), size));
            while entries.len() > 1 && entries.iter().map(|e| e.2).sum::<usize>() > self.budget {
                entries.remove(0);
            }
        }
        Ok(t)
    }
}

/// Encoded responses by ETag, within a byte budget (oldest dropped first).
#[derive(Debug)]
pub struct ResponseCache {
    budget: usize,
    inner: Mutex<(HashMap<String, CachedResponse>, VecDeque<String>, usize)>,
}

#[derive(Clone, Debug)]
pub struct CachedResponse {
    pub(super) bytes: Bytes,
    pub(super) mime: &'static str,
    /// Extra response headers (e.g. a primal image's error figures).
    pub(super) headers: Vec<(&'static str, String)>,
}

impl ResponseCache {
    pub fn new(budget: usize) -> Self {
        ResponseCache {
            budget,
            inner: Mutex::new((HashMap::new(), VecDeque::new(), 0)),
        }
    }

    pub(super) fn get(&self, etag: &str) -> Option<CachedResponse> {
        self.inner
            .lock()
            .expect("response cache")
            .0
            .get(etag)
            .cloned()
    }

    pub(super) fn put(&self, etag: String, response: CachedResponse) {
        if response.bytes.len() > self.budget {
            return;
        }
        let mut inner = self.inner.lock().expect("response cache");
        let (map, order, used) = &mut *inner;
        if map.contains_key(&etag) {
            return;
        }
        *used += response.bytes.len();
        map.insert(etag.clone(), response);
        order.push_back(etag);
        while *used > self.budget {
            let Some(old) = order.pop_front() else { break };
            if let Some(r) = map.remove(&old) {
                *used -= r.bytes.len();
            }
        }
    }
}
