//! gRPC `Acquire`: the bidirectional stream of an adaptive session. The rig opens the session,
//! the server answers with the batches of pattern indices the rig does not hold, then every chunk
//! the rig sends is committed under the upload rules (and only inside the issued batches), acked,
//! and followed by the batches the planner issues from the new values ([`crate::adaptive`]).

use std::time::Instant;

use helmholtz_proto::v1::{self, acquire_request, acquire_response};
use tokio::sync::mpsc;
use tonic::{Request, Response, Status, Streaming};

use super::grpc::{AcquisitionService, next_message, session_message, writer_id};
use super::{ApiError, WriterGuard, validate};
use crate::adaptive::Acquisition;
use crate::auth::{Principal, Role};
use crate::recon::adaptive::StopReason;
use crate::store::{IssuedBatch, SessionRow, SessionState};

/// The server's messages of one `Acquire` call.
pub type AcquireStream =
    std::pin::Pin<Box<dyn futures::Stream<Item = Result<v1::AcquireResponse, Status>> + Send>>;

/// Messages queued toward the rig: a batch and its ack are small, and a rig that reads slowly
/// only slows its own stream.
const OUTBOX: usize = 16;

pub(super) async fn acquire(
    service: &AcquisitionService,
    request: Request<Streaming<v1::AcquireRequest>>,
) -> Result<Response<AcquireStream>, Status> {
    let caller = service.caller(&request, &[Role::Rig]).await?;
    let writer = writer_id(&request)?;
    let inbound = request.into_inner();
    let (tx, rx) = mpsc::channel(OUTBOX);
    let service = service.clone();
    metrics::counter!("helmholtz_adaptive_streams_total").increment(1);
    tokio::spawn(async move {
        let mut stream = Stream {
            service: &service,
            tx: &tx,
            guard: None,
        };
        let result = stream.run(&caller, &writer, inbound).await;
        if let Some(guard) = stream.guard.take() {
            guard.release().await;
        }
        if let Err(status) = result {
            let _ = tx.send(Err(status)).await;
        }
    });
    Ok(Response::new(Box::pin(
        tokio_stream::wrappers::ReceiverStream::new(rx),
    )))
}

/// The rig went away: nothing more to send.
struct Gone;

impl From<Gone> for Status {
    fn from(_: Gone) -> Status {
        Status::cancelled("the rig closed the stream")
    }
}

struct Stream<'s> {
    service: &'s AcquisitionService,
    tx: &'s mpsc::Sender<Result<v1::AcquireResponse, Status>>,
    /// The session's writer lease, from the open on.
    guard: Option<WriterGuard>,
}

impl Stream<'_> {
    async fn send(&self, message: acquire_response::Message) -> Result<(), Gone> {
        self.tx
            .send(Ok(v1::AcquireResponse {
                message: Some(message),
            }))
            .await
            .map_err(|_| Gone)
    }

    async fn send_batch(&self, batch: &IssuedBatch) -> Result<(), Gone> {
        self.send(acquire_response::Message::Batch(v1::AdaptiveBatch {
            number: batch.number,
            first_row: batch.first_row,
            indices: batch.indices.clone(),
        }))
        .await
    }

    /// The whole call; `Ok` also when the rig went away.
    async fn run(
        &mut self,
        caller: &Principal,
        writer: &str,
        mut inbound: Streaming<v1::AcquireRequest>,
    ) -> Result<(), Status> {
        let state = self.service.state().clone();
        let idle = state.limits.upload_idle;
        let Some(first) = next_message(&mut inbound, idle, "message").await? else {
            return Ok(());
        };
        let Some(acquire_request::Message::Open(open)) = first.message else {
            return Err(ApiError::invalid(
                "open",
                "the first request of an Acquire stream must be `open`, naming the session",
            )
            .into());
        };
        validate::session_id(&open.session_id, "session_id")?;
        let session = state.own_session(caller, &open.session_id).await?;
        if !session.spec.is_adaptive() {
            return Err(ApiError::FailedPrecondition(format!(
                "session_id: session {:?} declares {} patterns, not an adaptive family \
                 (adaptive_haar, adaptive_hadamard): upload its rows with UploadMeasurements",
                session.id,
                session.spec.family().name()
            ))
            .into());
        }
        let guard = state.lock_writer(&session.id, writer).await?;
        let lease = guard.lease.clone();
        self.guard = Some(guard);
        let t0 = Instant::now();
        let mut acquisition = Acquisition::open(&state.store, &session, &lease).await?;
        metrics::histogram!("helmholtz_adaptive_replay_seconds").record(t0.elapsed().as_secs_f64());
        if open.measured_rows > acquisition.issued_rows() {
            return Err(ApiError::FailedPrecondition(format!(
                "measured_rows: the rig says it measured {} rows of session {:?}, but the server \
                 issued only {} (rows of another session, or of another run under this id?)",
                open.measured_rows,
                session.id,
                acquisition.issued_rows()
            ))
            .into());
        }
        tracing::info!(
            session = %session.id,
            committed = session.committed_rows,
            issued = acquisition.issued_rows(),
            measured = open.measured_rows,
            "adaptive acquisition opened"
        );
        self.send(acquire_response::Message::Opened(v1::AcquireOpened {
            session: Some(session_message(&session)),
            committed_rows: session.committed_rows,
            issued_rows: acquisition.issued_rows(),
        }))
        .await?;
        // Every batch the rig does not hold yet: it needs the whole sequence to resolve its spec.
        for batch in state
            .store
            .batches(&session.id)
            .await
            .map_err(ApiError::from)?
        {
            if batch.number >= open.known_batches {
                self.send_batch(&batch).await?;
            }
        }
        if session.state == SessionState::Finished || acquisition.stopped().is_some() {
            return self.done(&session, &acquisition).await;
        }
        while let Some(request) = next_message(&mut inbound, idle, "message").await? {
            let chunk = match request.message {
                Some(acquire_request::Message::Chunk(chunk)) => chunk,
                Some(acquire_request::Message::Open(_)) => {
                    return Err(ApiError::invalid(
                        "open",
                        "sent twice: a stream opens one session, then sends chunks",
                    )
                    .into());
                }
                None => return Err(ApiError::invalid("message", "empty request").into()),
            };
            if chunk.session_id != session.id {
                return Err(ApiError::invalid(
                    "session_id",
                    format!(
                        "every chunk of this stream must name session {:?}, the one opened",
                        session.id
                    ),
                )
                .into());
            }
            let outcome = self.service.commit_chunk(&session, &lease, &chunk).await?;
            self.send(acquire_response::Message::Ack(v1::AcquireAck {
                committed_rows: outcome.committed_rows,
                rows_written: outcome.written,
                rows_skipped: outcome.matched,
            }))
            .await?;
            let t0 = Instant::now();
            let issued = acquisition.advance(&state.store, &lease).await?;
            if !issued.is_empty() {
                metrics::histogram!("helmholtz_adaptive_decision_seconds")
                    .record(t0.elapsed().as_secs_f64());
            }
            for batch in &issued {
                self.send_batch(batch).await?;
            }
            if acquisition.stopped().is_some() {
                return self.done(&session, &acquisition).await;
            }
        }
        Ok(())
    }

    /// Finishes the session (once the stopping rule holds; a finished one stays as it is) and
    /// sends the last message.
    async fn done(&self, session: &SessionRow, acquisition: &Acquisition) -> Result<(), Status> {
        let store = &self.service.state().store;
        let finished = store
            .finish_session(&session.id)
            .await
            .map_err(ApiError::from)?;
        let reason = match acquisition.stopped() {
            Some(StopReason::Budget) => v1::AdaptiveStop::Budget,
            Some(StopReason::TargetError) => v1::AdaptiveStop::TargetError,
            None => v1::AdaptiveStop::Finished,
        };
        tracing::info!(
            session = %session.id,
            rows = finished.committed_rows,
            reason = reason.as_str_name(),
            estimated_error = ?acquisition.estimated_error(),
            "adaptive acquisition done"
        );
        self.send(acquire_response::Message::Done(v1::AcquireDone {
            reason: reason as i32,
            rows: finished.committed_rows,
            estimated_error: acquisition.estimated_error(),
        }))
        .await?;
        Ok(())
    }
}
