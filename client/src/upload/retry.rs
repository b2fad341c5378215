//! Retrying: jittered exponential backoff, the retry policy of idempotent calls, the retry loop
//! of unary calls, and how a failed call's status is classified and reported.

use std::future::Future;
use std::time::{Duration, Instant};

use serde::Serialize;
use tonic::{Code, Status};

use crate::auth::Grpc;

use super::grpc::connect;

/// Jittered exponential backoff: attempt `n` waits `min(max, initial · multiplier^n)` scaled by a
/// uniform factor in `[1 - jitter, 1]` (so concurrent clients do not retry in lock step).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Backoff {
    pub initial: Duration,
    pub max: Duration,
    pub multiplier: f64,
    /// In [0, 1]: 0 = no jitter, 1 = "full jitter".
    pub jitter: f64,
}

impl Default for Backoff {
    fn default() -> Self {
        Backoff {
            initial: Duration::from_millis(100),
            max: Duration::from_secs(5),
            multiplier: 2.0,
            jitter: 0.5,
        }
    }
}

impl Backoff {
    /// The un-jittered ceiling of attempt `attempt` (0-based).
    pub fn ceiling(&self, attempt: u32) -> Duration {
        let secs = self.initial.as_secs_f64() * self.multiplier.powi(attempt.min(64) as i32);
        Duration::from_secs_f64(secs.min(self.max.as_secs_f64()))
    }

    /// The delay before retry `attempt`, given `unit` uniform in [0, 1).
    pub fn delay(&self, attempt: u32, unit: f64) -> Duration {
        let jitter = self.jitter.clamp(0.0, 1.0);
        self.ceiling(attempt)
            .mul_f64(1.0 - jitter * unit.clamp(0.0, 1.0))
    }

    /// [`Backoff::delay`] with a fresh uniform draw.
    pub fn random_delay(&self, attempt: u32) -> Duration {
        self.delay(attempt, rand::random::<f64>())
    }
}

/// How long idempotent calls keep retrying retryable failures.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RetryPolicy {
    /// Give up once failures have gone on this long without progress.
    pub retry_for: Duration,
    pub backoff: Backoff,
    /// Deadline of one unary call.
    pub rpc_timeout: Duration,
    /// Deadline of establishing a connection.
    pub connect_timeout: Duration,
}

impl Default for RetryPolicy {
    fn default() -> Self {
        RetryPolicy {
            retry_for: Duration::from_secs(60),
            backoff: Backoff::default(),
            rpc_timeout: Duration::from_secs(30),
            connect_timeout: Duration::from_secs(5),
        }
    }
}

/// A gRPC call refused by the server or failed in transport.
#[derive(Debug, thiserror::Error)]
#[error("{operation}: {} ({}){}", message_or_description(.message, *.code), code_name(*.code), hint(*.code))]
pub struct RpcError {
    pub operation: String,
    pub code: Code,
    pub message: String,
}

impl RpcError {
    pub fn new(operation: impl Into<String>, status: &Status) -> Self {
        let id = crate::auth::request_id(status).map(|id| format!(" [request id {id}]"));
        RpcError {
            operation: operation.into(),
            code: status.code(),
            message: format!("{}{}", status.message(), id.unwrap_or_default()),
        }
    }
}

fn message_or_description(message: &str, code: Code) -> String {
    if message.is_empty() {
        code.description().to_string()
    } else {
        message.to_string()
    }
}

fn hint(code: Code) -> &'static str {
    match code {
        Code::Unavailable => "; is the server running at that address?",
        Code::AlreadyExists => {
            "; the server holds other data under this id: pick another --session-id (or repeat the original declaration)"
        }
        _ => "",
    }
}

/// The canonical gRPC name of a status code, e.g. `INVALID_ARGUMENT`.
pub fn code_name(code: Code) -> &'static str {
    match code {
        Code::Ok => "OK",
        Code::Cancelled => "CANCELLED",
        Code::Unknown => "UNKNOWN",
        Code::InvalidArgument => "INVALID_ARGUMENT",
        Code::DeadlineExceeded => "DEADLINE_EXCEEDED",
        Code::NotFound => "NOT_FOUND",
        Code::AlreadyExists => "ALREADY_EXISTS",
        Code::PermissionDenied => "PERMISSION_DENIED",
        Code::ResourceExhausted => "RESOURCE_EXHAUSTED",
        Code::FailedPrecondition => "FAILED_PRECONDITION",
        Code::Aborted => "ABORTED",
        Code::OutOfRange => "OUT_OF_RANGE",
        Code::Unimplemented => "UNIMPLEMENTED",
        Code::Internal => "INTERNAL",
        Code::Unavailable => "UNAVAILABLE",
        Code::DataLoss => "DATA_LOSS",
        Code::Unauthenticated => "UNAUTHENTICATED",
    }
}

/// What to do after a failed call.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Disposition {
    /// Transient: back off, re-ask the committed count, resume.
    Retry,
    /// The server's count disagrees with ours (a gap, OUT_OF_RANGE) or a chunk was damaged in
    /// transit (DATA_LOSS): re-ask the count once and resume; a second time in a row is fatal.
    ResyncOnce,
    /// The request itself is wrong: retrying cannot help.
    Fatal,
}

/// Classifies a gRPC status code for retrying.
pub fn disposition(code: Code) -> Disposition {
    match code {
        Code::Unavailable
        | Code::DeadlineExceeded
        | Code::Internal
        | Code::Unknown
        | Code::Aborted
        | Code::ResourceExhausted
        | Code::Cancelled => Disposition::Retry,
        Code::OutOfRange | Code::DataLoss => Disposition::ResyncOnce,
        _ => Disposition::Fatal,
    }
}

/// Runs an idempotent unary call, retrying retryable failures per `policy`.
pub(super) async fn unary<T, F, Fut>(
    server: &str,
    policy: &RetryPolicy,
    operation: &str,
    mut call: F,
) -> anyhow::Result<T>
where
    F: FnMut(Grpc) -> Fut,
    Fut: Future<Output = Result<tonic::Response<T>, Status>>,
{
    let started = Instant::now();
    let mut attempt = 0u32;
    loop {
        let client = connect(server, policy.connect_timeout)?;
        let status = match tokio::time::timeout(policy.rpc_timeout, call(client)).await {
            Ok(Ok(response)) => return Ok(response.into_inner()),
            Ok(Err(status)) => status,
            Err(_) => {
                Status::deadline_exceeded(format!("no answer within {:?}", policy.rpc_timeout))
            }
        };
        if disposition(status.code()) != Disposition::Retry
            || started.elapsed() >= policy.retry_for
            || crate::tls::is_certificate_error(&status)
        {
            return Err(RpcError::new(operation, &status).into());
        }
        let remaining = policy.retry_for.saturating_sub(started.elapsed());
        tokio::time::sleep(policy.backoff.random_delay(attempt).min(remaining)).await;
        attempt += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_grows_caps_and_jitters_within_bounds() {
        let b = Backoff::default();
        let ceilings: Vec<Duration> = (0..10).map(|n| b.ceiling(n)).collect();
        assert_eq!(ceilings[0], Duration::from_millis(100));
        assert_eq!(ceilings[1], Duration::from_millis(200));
        assert_eq!(ceilings[5], Duration::from_millis(3200));
        assert_eq!(ceilings[6], Duration::from_secs(5));
        assert!(ceilings.windows(2).all(|w| w[0] <= w[1]));
        for n in 0..10 {
            assert_eq!(b.delay(n, 0.0), b.ceiling(n));
            assert_eq!(
                b.delay(n, 0.999_999_999).as_millis(),
                b.ceiling(n).as_millis() / 2
            );
            for _ in 0..100 {
                let d = b.random_delay(n);
                assert!(d <= b.ceiling(n) && d >= b.ceiling(n) / 2);
            }
        }
        assert_eq!(b.ceiling(1000), Duration::from_secs(5));
        let none = Backoff { jitter: 0.0, ..b };
        assert_eq!(none.delay(3, 0.7), none.ceiling(3));
    }

    #[test]
    fn status_codes_are_classified() {
        for c in [
            Code::Unavailable,
            Code::DeadlineExceeded,
            Code::Internal,
            Code::Unknown,
            Code::Aborted,
        ] {
            assert_eq!(disposition(c), Disposition::Retry, "{c:?}");
        }
        for c in [Code::OutOfRange, Code::DataLoss] {
            assert_eq!(disposition(c), Disposition::ResyncOnce, "{c:?}");
        }
        for c in [
            Code::InvalidArgument,
            Code::FailedPrecondition,
            Code::NotFound,
            Code::AlreadyExists,
        ] {
            assert_eq!(disposition(c), Disposition::Fatal, "{c:?}");
        }
    }

    #[test]
    fn rpc_errors_read_well() {
        let e = RpcError::new(
            "finishing session s",
            &Status::failed_precondition("12 of 64 rows committed"),
        );
        assert_eq!(
            e.to_string(),
            "finishing session s: 12 of 64 rows committed (FAILED_PRECONDITION)"
        );
        let e = RpcError::new("x", &Status::unavailable(""));
        assert!(e.to_string().contains("UNAVAILABLE") && e.to_string().contains("server running"));
    }
}
