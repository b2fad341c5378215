//! The gRPC acquisition service (`helmholtz.v1.Acquisition`).

use helmholtz_proto::v1::{self, acquisition_server::Acquisition};
use helmholtz_proto::wire::{self, WireError};
use tonic::{Request, Response, Status, Streaming};

use super::{ApiError, AppState, validate};
use crate::store::{ReconstructionRow, SessionRow, SessionState};

/// Largest accepted gRPC message: 32 MiB (a session's ground truth on a 2048 x 2048 grid is
/// 16 MiB; upload chunks are typically 256 KiB).
pub const MAX_MESSAGE_BYTES: usize = 32 << 20;

#[derive(Clone, Debug)]
pub struct AcquisitionService {
    state: AppState,
}

impl AcquisitionService {
    pub fn new(state: AppState) -> Self {
        AcquisitionService { state }
    }

    pub fn into_server(self) -> v1::acquisition_server::AcquisitionServer<Self> {
        v1::acquisition_server::AcquisitionServer::new(self)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES)
    }
}

pub fn session_message(s: &SessionRow) -> v1::Session {
    v1::Session {
        session_id: s.id.clone(),
        rig: s.rig.clone(),
        patterns: Some((&s.spec).into()),
        detector: Some(v1::DetectorLayout { channels: s.channels.clone() }),
        metadata: s.metadata.iter().map(|(k, v)| (k.clone(), v.clone())).collect(),
        committed_rows: s.committed_rows,
        expected_rows: s.expected_rows,
        state: match s.state {
            SessionState::Open => v1::SessionState::Open as i32,
            SessionState::Finished => v1::SessionState::Finished as i32,
        },
        created_unix_ms: s.created_ms,
        has_ground_truth: s.has_ground_truth,
    }
}

fn reconstruction_message(r: &ReconstructionRow) -> v1::Reconstruction {
    v1::Reconstruction {
        reconstruction_id: r.id,
        session_id: r.session_id.clone(),
        method: r.method.clone(),
        params_json: r.params_json.clone(),
        state: r.state.clone(),
        progress: r.progress,
        rows: r.rows_used,
        seconds: r.seconds.unwrap_or(0.0),
        error: r.last_error.clone().unwrap_or_default(),
        report_json: r.report_json.clone().unwrap_or_default(),
    }
}

fn wire_error(e: WireError) -> ApiError {
    match e {
        WireError::Checksum { .. } => ApiError::DataLoss(e.to_string()),
        WireError::Ragged { .. } | WireError::NotFinite { .. } => ApiError::invalid("values_f64le", e.to_string()),
    }
}

#[tonic::async_trait]
impl Acquisition for AcquisitionService {
    async fn create_session(
        &self,
        request: Request<v1::CreateSessionRequest>,
    ) -> Result<Response<v1::CreateSessionResponse>, Status> {
        let new = validate::new_session(request.get_ref())?;
        let (session, created) = self.state.store.create_session(&new).await.map_err(ApiError::from)?;
        if created {
            tracing::info!(session = %session.id, rig = %session.rig, spec = %session.spec.to_json(), "session created");
        }
        Ok(Response::new(v1::CreateSessionResponse { session: Some(session_message(&session)), created }))
    }

    async fn upload_measurements(
        &self,
        request: Request<Streaming<v1::MeasurementChunk>>,
    ) -> Result<Response<v1::UploadResponse>, Status> {
        let mut stream = request.into_inner();
        let mut session: Option<(SessionRow, super::WriterGuard)> = None;
        let (mut written, mut skipped, mut committed) = (0u64, 0u64, 0u64);
        // Each chunk is validated and committed before the next is read: nothing is buffered,
        // and an error leaves every earlier chunk durable.
        while let Some(chunk) = stream.message().await? {
            if session.is_none() {
                validate::session_id(&chunk.session_id, "session_id")?;
                let row = self.state.store.session(&chunk.session_id).await.map_err(ApiError::from)?;
                let guard = self.state.lock_writer(&row.id)?;
                session = Some((row, guard));
            }
            let (row, _) = session.as_ref().expect("set above");
            if chunk.session_id != row.id {
                return Err(ApiError::invalid("session_id", "every chunk of a stream must name the same session").into());
            }
            let channels = row.channels.len();
            if chunk.channels as usize != channels {
                return Err(ApiError::invalid(
                    "channels",
                    format!("session {:?} has {channels} channels, chunk says {}", row.id, chunk.channels),
                )
                .into());
            }
            if chunk.values_f64le.is_empty() {
                return Err(ApiError::invalid("values_f64le", "chunk holds no rows").into());
            }
            let values = wire::decode_values(&chunk.values_f64le, channels, chunk.crc32c).map_err(wire_error)?;
            let outcome = self
                .state
                .store
                .append_rows(&row.id, chunk.start_row, channels, &values)
                .await
                .map_err(ApiError::from)?;
            written += outcome.written;
            skipped += outcome.skipped;
            committed = outcome.committed_rows;
        }
        if let Some((row, _)) = &session {
            tracing::debug!(session = %row.id, written, skipped, committed, "upload stream ended");
        }
        Ok(Response::new(v1::UploadResponse { committed_rows: committed, rows_written: written, rows_skipped: skipped }))
    }

    async fn get_upload_status(&self, request: Request<v1::SessionRef>) -> Result<Response<v1::UploadStatus>, Status> {
        let id = &request.get_ref().session_id;
        validate::session_id(id, "session_id")?;
        let s = self.state.store.session(id).await.map_err(ApiError::from)?;
        let m = session_message(&s);
        Ok(Response::new(v1::UploadStatus {
            session_id: s.id,
            committed_rows: s.committed_rows,
            expected_rows: s.expected_rows,
            state: m.state,
        }))
    }

    async fn finish_session(&self, request: Request<v1::SessionRef>) -> Result<Response<v1::Session>, Status> {
        let id = &request.get_ref().session_id;
        validate::session_id(id, "session_id")?;
        let s = self.state.store.finish_session(id).await.map_err(ApiError::from)?;
        Ok(Response::new(session_message(&s)))
    }

    async fn request_reconstruction(
        &self,
        request: Request<v1::ReconstructionRequest>,
    ) -> Result<Response<v1::Reconstruction>, Status> {
        let req = request.get_ref();
        validate::session_id(&req.session_id, "session_id")?;
        let params: serde_json::Value = if req.params_json.trim().is_empty() {
            serde_json::Value::Object(Default::default())
        } else {
            serde_json::from_str(&req.params_json)
                .map_err(|e| ApiError::invalid("params_json", format!("not JSON: {e}")))?
        };
        let row = self.state.request_reconstruction(&req.session_id, &req.method, &params).await?;
        Ok(Response::new(reconstruction_message(&row)))
    }

    async fn get_reconstruction(
        &self,
        request: Request<v1::ReconstructionRef>,
    ) -> Result<Response<v1::Reconstruction>, Status> {
        let row = self.state.store.reconstruction(request.get_ref().reconstruction_id).await.map_err(ApiError::from)?;
        Ok(Response::new(reconstruction_message(&row)))
    }
}
