//! One error type for the API layer, mapped once to HTTP problem+json (RFC 9457) and once to
//! `tonic::Status`. Internal causes are logged, never sent. The HTTP body is the contract's
//! [`Problem`].

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use helmholtz_proto::rest::{PROBLEM_JSON, Problem};

use crate::store::StoreError;

#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// Bad input; `field` names it as the request spells it.
    #[error("{field}: {message}")]
    InvalidArgument { field: String, message: String },
    #[error("{0}")]
    NotFound(String),
    /// The id exists with a different declaration.
    #[error("{0}")]
    AlreadyExists(String),
    /// The request is valid but the resource is not in a state for it.
    #[error("{0}")]
    FailedPrecondition(String),
    /// A gap in rows or rows past the declared count.
    #[error("{0}")]
    OutOfRange(String),
    /// A checksum mismatch.
    #[error("{0}")]
    DataLoss(String),
    /// Another writer holds the session.
    #[error("{0}")]
    Aborted(String),
    /// No usable credential (missing, malformed, unknown or revoked token).
    #[error("{0}")]
    Unauthenticated(String),
    /// A valid token whose roles do not allow the call.
    #[error("{0}")]
    PermissionDenied(String),
    /// A cap or the request rate; `retry_after` seconds when waiting helps.
    #[error("{limit}: {message}")]
    ResourceExhausted {
        limit: &'static str,
        message: String,
        retry_after: Option<u64>,
    },
    /// A request body over the size limit.
    #[error("{limit}: {message}")]
    TooLarge {
        limit: &'static str,
        message: String,
    },
    /// A reconstruction whose estimated memory can never fit the process's budget.
    #[error(
        "this reconstruction needs an estimated {} MiB, more than the {} MiB all running \
         reconstructions may take together (--memory-budget-mib); use fewer rows, a smaller \
         pattern grid, or a cheaper method",
        estimate >> 20,
        budget >> 20
    )]
    MemoryBudget { estimate: u64, budget: u64 },
    /// A request body that stopped arriving (`--body-timeout-secs`).
    #[error("{0}")]
    Timeout(String),
    /// The database does not answer (lost connections, a pool waiting to reconnect): retry.
    #[error("the database does not answer; retry shortly (nothing of this request was stored)")]
    Unavailable(String),
    #[error("internal error")]
    Internal(String),
}

impl ApiError {
    pub fn invalid(field: impl Into<String>, message: impl Into<String>) -> Self {
        ApiError::InvalidArgument {
            field: field.into(),
            message: message.into(),
        }
    }

    fn slug(&self) -> (&'static str, &'static str) {
        match self {
            ApiError::InvalidArgument { .. } => ("invalid-argument", "Invalid argument"),
            ApiError::NotFound(_) => ("not-found", "Not found"),
            ApiError::AlreadyExists(_) => ("already-exists", "Conflicts with an existing resource"),
            ApiError::FailedPrecondition(_) => {
                ("failed-precondition", "Not possible in the current state")
            }
            ApiError::OutOfRange(_) => ("out-of-range", "Out of range"),
            ApiError::DataLoss(_) => ("data-loss", "Checksum mismatch"),
            ApiError::Aborted(_) => ("aborted", "Concurrent writer"),
            ApiError::Unauthenticated(_) => ("unauthenticated", "Unauthenticated"),
            ApiError::PermissionDenied(_) => ("permission-denied", "Permission denied"),
            ApiError::ResourceExhausted { .. } => ("resource-exhausted", "Limit reached"),
            ApiError::TooLarge { .. } => ("too-large", "Request too large"),
            ApiError::MemoryBudget { .. } => ("memory-budget", "Needs more memory than the budget"),
            ApiError::Timeout(_) => ("request-timeout", "Request timeout"),
            ApiError::Unavailable(_) => ("unavailable", "Database unavailable"),
            ApiError::Internal(_) => ("internal", "Internal error"),
        }
    }

    fn http_status(&self) -> StatusCode {
        match self {
            ApiError::InvalidArgument { .. } => StatusCode::BAD_REQUEST,
            ApiError::NotFound(_) => StatusCode::NOT_FOUND,
            ApiError::AlreadyExists(_) | ApiError::FailedPrecondition(_) | ApiError::Aborted(_) => {
                StatusCode::CONFLICT
            }
            ApiError::OutOfRange(_) => StatusCode::RANGE_NOT_SATISFIABLE,
            ApiError::DataLoss(_) => StatusCode::UNPROCESSABLE_ENTITY,
            ApiError::Unauthenticated(_) => StatusCode::UNAUTHORIZED,
            ApiError::PermissionDenied(_) => StatusCode::FORBIDDEN,
            ApiError::ResourceExhausted { .. } => StatusCode::TOO_MANY_REQUESTS,
            ApiError::TooLarge { .. } | ApiError::MemoryBudget { .. } => {
                StatusCode::PAYLOAD_TOO_LARGE
            }
            ApiError::Timeout(_) => StatusCode::REQUEST_TIMEOUT,
            ApiError::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    fn log_internal(&self) {
        match self {
            ApiError::Internal(cause) => tracing::error!(%cause, "internal error"),
            ApiError::Unavailable(cause) => tracing::warn!(%cause, "database unavailable"),
            _ => {}
        }
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        match e {
            StoreError::SessionNotFound(_) | StoreError::ReconstructionNotFound(_) => {
                ApiError::NotFound(e.to_string())
            }
            StoreError::SessionConflict(..)
            | StoreError::SessionIdTaken(_)
            | StoreError::RowMismatch { .. } => ApiError::AlreadyExists(e.to_string()),
            StoreError::WriterLost(_) => ApiError::Aborted(e.to_string()),
            StoreError::Cap { limit, message } => ApiError::ResourceExhausted {
                limit,
                message,
                retry_after: None,
            },
            StoreError::Gap { .. } | StoreError::PastEnd { .. } => {
                ApiError::OutOfRange(e.to_string())
            }
            StoreError::Finished(_)
            | StoreError::Incomplete { .. }
            | StoreError::NotIssued { .. }
            | StoreError::NotAdaptive(_) => ApiError::FailedPrecondition(e.to_string()),
            StoreError::Db(_) if e.is_unavailable() => ApiError::Unavailable(e.to_string()),
            StoreError::Corrupt(_)
            | StoreError::Db(_)
            | StoreError::Migrate(_)
            | StoreError::UnsupportedUrl => ApiError::Internal(e.to_string()),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        self.log_internal();
        let status = self.http_status();
        let (slug, title) = self.slug();
        let mut body = Problem::new(slug, title, status.as_u16(), self.to_string());
        if let ApiError::InvalidArgument { field, .. } = &self {
            body.field = Some(field.clone());
        }
        if let ApiError::ResourceExhausted { limit, .. } | ApiError::TooLarge { limit, .. } = &self
        {
            body.limit = Some(limit.to_string());
        }
        if let ApiError::MemoryBudget { estimate, budget } = &self {
            body.limit = Some("memory_budget".into());
            body.estimate_bytes = Some(*estimate);
            body.limit_bytes = Some(*budget);
        }
        let body = serde_json::to_string(&body).expect("a problem serializes");
        let mut response = (status, body).into_response();
        let headers = response.headers_mut();
        headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
        if let ApiError::ResourceExhausted {
            retry_after: Some(s),
            ..
        } = &self
        {
            headers.insert(header::RETRY_AFTER, HeaderValue::from(*s));
        }
        if let ApiError::Unauthenticated(_) = &self {
            headers.insert(
                header::WWW_AUTHENTICATE,
                HeaderValue::from_static("Bearer realm=\"helmholtz\""),
            );
        }
        response
    }
}

impl From<ApiError> for tonic::Status {
    fn from(e: ApiError) -> Self {
        e.log_internal();
        let message = e.to_string();
        match e {
            ApiError::InvalidArgument { .. } => tonic::Status::invalid_argument(message),
            ApiError::NotFound(_) => tonic::Status::not_found(message),
            ApiError::AlreadyExists(_) => tonic::Status::already_exists(message),
            ApiError::FailedPrecondition(_) => tonic::Status::failed_precondition(message),
            ApiError::OutOfRange(_) => tonic::Status::out_of_range(message),
            ApiError::DataLoss(_) => tonic::Status::data_loss(message),
            ApiError::Aborted(_) => tonic::Status::aborted(message),
            ApiError::Unauthenticated(_) => tonic::Status::unauthenticated(message),
            ApiError::PermissionDenied(_) => tonic::Status::permission_denied(message),
            ApiError::ResourceExhausted { retry_after, .. } => {
                let mut status = tonic::Status::resource_exhausted(message);
                if let Some(s) = retry_after
                    && let Ok(v) = s.to_string().parse()
                {
                    status.metadata_mut().insert("retry-after", v);
                }
                status
            }
            ApiError::TooLarge { .. } | ApiError::MemoryBudget { .. } => {
                tonic::Status::resource_exhausted(message)
            }
            ApiError::Timeout(_) => tonic::Status::deadline_exceeded(message),
            ApiError::Unavailable(_) => tonic::Status::unavailable(message),
            ApiError::Internal(_) => tonic::Status::internal(message),
        }
    }
}
