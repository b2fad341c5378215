//! The gRPC acquisition service (`helmholtz.v1.Acquisition`).

use helmholtz_proto::v1::{self, acquisition_server::Acquisition};
use tonic::{Request, Response, Status, Streaming};

use super::{ApiError, AppState, validate};
use crate::auth::{Principal, Role};
use crate::store::{
    AppendOutcome, ReconstructionRow, SampleFormat, SessionRow, SessionState, StoreError,
    WriterLease,
};

#[derive(Clone, Debug)]
pub struct AcquisitionService {
    state: AppState,
}

impl AcquisitionService {
    pub fn new(state: AppState) -> Self {
        AcquisitionService { state }
    }

    /// The service with the message-size cap (`max_message_bytes`; a session's ground truth on
    /// a 2048 x 2048 grid is 16 MiB, upload chunks are typically 256 KiB).
    pub fn into_server(self) -> v1::acquisition_server::AcquisitionServer<Self> {
        let max = self.state.limits.max_message_bytes;
        v1::acquisition_server::AcquisitionServer::new(self)
            .max_decoding_message_size(max)
            .max_encoding_message_size(max)
    }

    /// The caller of a gRPC request, holding one of `roles` (or UNAUTHENTICATED /
    /// PERMISSION_DENIED / RESOURCE_EXHAUSTED).
    pub(super) async fn caller<T>(
        &self,
        request: &Request<T>,
        roles: &[Role],
    ) -> Result<Principal, ApiError> {
        let authorization = request
            .metadata()
            .get("authorization")
            .map(|v| v.as_bytes());
        let caller = self.state.authenticate(authorization).await?;
        caller.require_any(roles)?;
        Ok(caller)
    }

    /// The chunks of one upload stream, each validated and committed before the next is read;
    /// `session` holds the stream's session and writer lease from its first chunk on (the
    /// caller gives the lease back however this ends).
    async fn receive_chunks(
        &self,
        caller: &Principal,
        writer: &str,
        stream: &mut Streaming<v1::MeasurementChunk>,
        session: &mut Option<(SessionRow, super::WriterGuard)>,
    ) -> Result<v1::UploadResponse, Status> {
        let (mut written, mut matched, mut committed) = (0u64, 0u64, 0u64);
        let idle = self.state.limits.upload_idle;
        // Each chunk is validated and committed before the next is read: nothing is buffered,
        // and an error leaves every earlier chunk durable.
        loop {
            let Some(chunk) = next_message(stream, idle, "chunk").await? else {
                break;
            };
            if session.is_none() {
                validate::session_id(&chunk.session_id, "session_id")?;
                let row = self.state.own_session(caller, &chunk.session_id).await?;
                let guard = self.state.lock_writer(&row.id, writer).await?;
                if chunk.start_row > 0 || row.committed_rows > 0 {
                    metrics::counter!("helmholtz_upload_resumed_total").increment(1);
                }
                *session = Some((row, guard));
            }
            let (row, guard) = session.as_ref().expect("set above");
            if chunk.session_id != row.id {
                return Err(ApiError::invalid(
                    "session_id",
                    "every chunk of a stream must name the same session",
                )
                .into());
            }
            let outcome = self.commit_chunk(row, &guard.lease, &chunk).await?;
            written += outcome.written;
            matched += outcome.matched;
            committed = outcome.committed_rows;
        }
        if let Some((row, _)) = &session {
            tracing::debug!(session = %row.id, written, matched, committed, "upload stream ended");
        }
        Ok(v1::UploadResponse {
            committed_rows: committed,
            rows_written: written,
            rows_skipped: matched,
        })
    }
}

impl AcquisitionService {
    /// One chunk of `session`'s rows checked (channels, payload, checksum, values) and
    /// committed under `lease`: the rules every gRPC upload shares.
    pub(super) async fn commit_chunk(
        &self,
        session: &SessionRow,
        lease: &WriterLease,
        chunk: &v1::MeasurementChunk,
    ) -> Result<AppendOutcome, ApiError> {
        let channels = session.row_values();
        if chunk.channels as usize != channels {
            let what = if session.camera.is_some() {
                "pixels per frame"
            } else {
                "channels"
            };
            return Err(ApiError::invalid(
                "channels",
                format!(
                    "session {:?} has {channels} {what}, chunk says {}",
                    session.id, chunk.channels
                ),
            ));
        }
        let payload = checked_payload(chunk, session, self.state.limits.max_chunk_bytes)?;
        let outcome = self
            .state
            .store
            .append_raw(
                &session.id,
                Some(lease),
                chunk.start_row,
                session.row_bytes(),
                payload,
            )
            .await
            .map_err(|e| {
                if matches!(e, StoreError::RowMismatch { .. }) {
                    metrics::counter!("helmholtz_upload_row_mismatches_total").increment(1);
                }
                ApiError::from(e)
            })?;
        metrics::counter!("helmholtz_upload_rows_total").increment(outcome.written);
        metrics::counter!("helmholtz_upload_bytes_total")
            .increment(outcome.written * session.row_bytes() as u64);
        Ok(outcome)
    }

    pub(super) fn state(&self) -> &AppState {
        &self.state
    }
}

/// The next message of a client stream, or ABORTED once it stays silent for `idle` (the rows
/// committed so far stay); `what` names the message in that error ("chunk", "message").
pub(super) async fn next_message<T>(
    stream: &mut Streaming<T>,
    idle: std::time::Duration,
    what: &str,
) -> Result<Option<T>, Status> {
    tokio::time::timeout(idle, stream.message())
        .await
        .map_err(|_| {
            ApiError::Aborted(format!(
                "no {what} for {} s: the stream is closed (the rows it committed stay; resume from the committed count)",
                idle.as_secs()
            ))
        })?
}

/// The metadata naming an upload's writer: one id for every stream of one client upload.
pub const WRITER_HEADER: &str = "x-helmholtz-writer";

/// The upload's writer id from [`WRITER_HEADER`] (empty when not sent).
pub(super) fn writer_id<T>(request: &Request<T>) -> Result<String, ApiError> {
    validate::writer_id(request.metadata().get(WRITER_HEADER).map(|v| v.as_bytes()))
}

pub fn session_message(s: &SessionRow) -> v1::Session {
    v1::Session {
        session_id: s.id.clone(),
        rig: s.rig.clone(),
        patterns: Some((&s.spec).into()),
        detector: Some(v1::DetectorLayout {
            channels: s.channels.clone(),
            directions: s
                .directions
                .iter()
                .map(|d| v1::Direction {
                    x: d[0],
                    y: d[1],
                    z: d[2],
                })
                .collect(),
            camera: s.camera.map(|c| v1::CameraLayout {
                width: c.width,
                height: c.height,
                format: c.format.to_proto() as i32,
            }),
        }),
        metadata: s
            .metadata
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect(),
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
        warnings: super::rest::report_warnings(r),
    }
}

/// The chunk's payload in the session's sample format, checked (exactly that payload set, whole
/// rows, checksum, finite floats, size cap): the bytes to store as they are.
fn checked_payload<'c>(
    chunk: &'c v1::MeasurementChunk,
    session: &SessionRow,
    max_chunk: usize,
) -> Result<&'c [u8], ApiError> {
    let format = session.sample_format();
    let payloads = [
        ("values_f64le", SampleFormat::F64, &chunk.values_f64le),
        ("values_f32le", SampleFormat::F32, &chunk.values_f32le),
        ("values_u16le", SampleFormat::U16, &chunk.values_u16le),
    ];
    let (field, _, bytes) = payloads
        .iter()
        .find(|(_, f, _)| *f == format)
        .expect("every format has a field");
    if let Some((other, _, _)) = payloads
        .iter()
        .find(|(_, f, b)| *f != format && !b.is_empty())
    {
        let kind = if session.camera.is_some() {
            "camera"
        } else {
            "bucket"
        };
        return Err(ApiError::invalid(
            *other,
            format!(
                "session {:?} is a {kind} session of {} samples: send them in {field} only",
                session.id,
                format.name()
            ),
        ));
    }
    if bytes.is_empty() {
        return Err(ApiError::invalid(*field, "chunk holds no rows"));
    }
    if bytes.len() > max_chunk {
        return Err(ApiError::TooLarge {
            limit: "max_chunk_bytes",
            message: format!(
                "{field} holds {} bytes; chunks may hold at most {max_chunk} bytes (send fewer rows per chunk)",
                bytes.len()
            ),
        });
    }
    let actual = crc32c::crc32c(bytes);
    if actual != chunk.crc32c {
        metrics::counter!("helmholtz_checksum_failures_total").increment(1);
        return Err(ApiError::DataLoss(format!(
            "crc32c mismatch: chunk says {:#010x}, payload has {actual:#010x}",
            chunk.crc32c
        )));
    }
    validate::stored_rows(field, bytes, session)?;
    Ok(bytes)
}

fn preview_message(f: crate::preview::Frame) -> v1::PreviewFrame {
    v1::PreviewFrame {
        session_id: f.session_id,
        channel: f.channel,
        rows: f.rows,
        expected_rows: f.expected_rows,
        width: f.width,
        height: f.height,
        method: f.method.into(),
        values: f.values,
        r#final: f.last,
    }
}

/// The frames of one `WatchPreview` call; dropping it (the watcher went away) stops the preview.
pub type PreviewStream =
    std::pin::Pin<Box<dyn futures::Stream<Item = Result<v1::PreviewFrame, Status>> + Send>>;

#[tonic::async_trait]
impl Acquisition for AcquisitionService {
    type WatchPreviewStream = PreviewStream;
    type AcquireStream = super::acquire::AcquireStream;

    async fn acquire(
        &self,
        request: Request<Streaming<v1::AcquireRequest>>,
    ) -> Result<Response<Self::AcquireStream>, Status> {
        super::acquire::acquire(self, request).await
    }

    async fn watch_preview(
        &self,
        request: Request<v1::PreviewRequest>,
    ) -> Result<Response<Self::WatchPreviewStream>, Status> {
        let caller = self.caller(&request, &[Role::Rig, Role::Reader]).await?;
        let req = request.get_ref();
        validate::session_id(&req.session_id, "session_id")?;
        let session = self.state.own_session(&caller, &req.session_id).await?;
        let watch = crate::preview::Watch::parse(
            &session,
            Some(&req.channel),
            req.every_rows,
            req.every_ms as u64,
        )?;
        let frames = crate::preview::watch(
            self.state.store.clone(),
            &self.state.previews,
            session,
            watch,
        )?;
        let stream = futures::StreamExt::map(
            tokio_stream::wrappers::ReceiverStream::new(frames),
            |frame| frame.map(preview_message).map_err(Status::from),
        );
        Ok(Response::new(Box::pin(stream)))
    }

    async fn create_session(
        &self,
        request: Request<v1::CreateSessionRequest>,
    ) -> Result<Response<v1::CreateSessionResponse>, Status> {
        let caller = self.caller(&request, &[Role::Rig]).await?;
        let new = validate::new_session(request.get_ref(), &caller.lab, &self.state.limits)?;
        let (session, created) = self
            .state
            .store
            .create_session_capped(&new, self.state.limits.max_sessions_per_lab)
            .await
            .map_err(ApiError::from)?;
        if created {
            tracing::info!(session = %session.id, lab = %session.lab, rig = %session.rig, spec = %session.spec.to_json(), "session created");
        }
        Ok(Response::new(v1::CreateSessionResponse {
            session: Some(session_message(&session)),
            created,
        }))
    }

    async fn upload_measurements(
        &self,
        request: Request<Streaming<v1::MeasurementChunk>>,
    ) -> Result<Response<v1::UploadResponse>, Status> {
        let caller = self.caller(&request, &[Role::Rig]).await?;
        let writer = writer_id(&request)?;
        let mut stream = request.into_inner();
        let mut session: Option<(SessionRow, super::WriterGuard)> = None;
        let result = self
            .receive_chunks(&caller, &writer, &mut stream, &mut session)
            .await;
        if let Some((_, guard)) = session {
            guard.release().await;
        }
        result.map(Response::new)
    }

    async fn get_upload_status(
        &self,
        request: Request<v1::SessionRef>,
    ) -> Result<Response<v1::UploadStatus>, Status> {
        let caller = self.caller(&request, &[Role::Rig, Role::Reader]).await?;
        let id = &request.get_ref().session_id;
        validate::session_id(id, "session_id")?;
        let s = self.state.own_session(&caller, id).await?;
        let m = session_message(&s);
        Ok(Response::new(v1::UploadStatus {
            session_id: s.id,
            committed_rows: s.committed_rows,
            expected_rows: s.expected_rows,
            state: m.state,
        }))
    }

    async fn finish_session(
        &self,
        request: Request<v1::SessionRef>,
    ) -> Result<Response<v1::Session>, Status> {
        let caller = self.caller(&request, &[Role::Rig]).await?;
        let id = &request.get_ref().session_id;
        validate::session_id(id, "session_id")?;
        self.state.own_session(&caller, id).await?;
        let s = self
            .state
            .store
            .finish_session(id)
            .await
            .map_err(ApiError::from)?;
        Ok(Response::new(session_message(&s)))
    }

    async fn request_reconstruction(
        &self,
        request: Request<v1::ReconstructionRequest>,
    ) -> Result<Response<v1::Reconstruction>, Status> {
        let caller = self.caller(&request, &[Role::Reader]).await?;
        let req = request.get_ref();
        validate::session_id(&req.session_id, "session_id")?;
        let params: serde_json::Value = if req.params_json.trim().is_empty() {
            serde_json::Value::Object(Default::default())
        } else {
            serde_json::from_str(&req.params_json)
                .map_err(|e| ApiError::invalid("params_json", format!("not JSON: {e}")))?
        };
        let request = crate::recon::Request::parse(&req.method, &params)
            .map_err(|e| ApiError::invalid(e.field, e.message))?;
        let row = self
            .state
            .request_reconstruction(&caller, &req.session_id, &request)
            .await?;
        Ok(Response::new(reconstruction_message(&row)))
    }

    async fn get_reconstruction(
        &self,
        request: Request<v1::ReconstructionRef>,
    ) -> Result<Response<v1::Reconstruction>, Status> {
        let caller = self.caller(&request, &[Role::Reader]).await?;
        let row = self
            .state
            .own_reconstruction(&caller, request.get_ref().reconstruction_id)
            .await?;
        Ok(Response::new(reconstruction_message(&row)))
    }

    async fn cancel_reconstruction(
        &self,
        request: Request<v1::ReconstructionRef>,
    ) -> Result<Response<v1::Reconstruction>, Status> {
        let caller = self.caller(&request, &[Role::Reader]).await?;
        let row = self
            .state
            .cancel_reconstruction(&caller, request.get_ref().reconstruction_id)
            .await?;
        Ok(Response::new(reconstruction_message(&row)))
    }
}
