//! Caps on what one request, session or lab may use. Each refusal names the limit.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Service limits (`helmholtz-server serve --help` lists the flags).
#[derive(Clone, Debug, PartialEq)]
pub struct Limits {
    /// Largest gRPC message, bytes (a CreateSession with ground truth, an upload chunk).
    pub max_message_bytes: usize,
    /// Largest REST request body, bytes.
    pub max_body_bytes: usize,
    /// Largest upload chunk (one MeasurementChunk's values), bytes.
    pub max_chunk_bytes: usize,
    /// Most patterns (rows) one session may declare.
    pub max_patterns: u64,
    /// Most pixels (width x height) of one session's patterns.
    pub max_pixels: u64,
    /// Most pixels (width x height) of one camera frame.
    pub max_frame_pixels: u64,
    /// Most values of a session's ground truth (a camera session's T is m x k).
    pub max_ground_truth_values: u64,
    /// Most sessions one lab may hold.
    pub max_sessions_per_lab: u64,
    /// Most reconstructions one lab may have queued or running at once.
    pub max_pending_jobs_per_lab: u64,
    /// Most reconstructions of one lab running at once on the workers (0: no cap beyond the
    /// worker count); the others wait while other labs' jobs run.
    pub max_running_jobs_per_lab: u32,
    /// Sustained requests per second per token.
    pub rate_per_second: f64,
    /// Requests a token may make in a burst above the sustained rate.
    pub rate_burst: f64,
    /// An upload stream's hold on its session (one writer per session): renewed while the
    /// stream is open; a holder that dies frees the session after this long.
    pub upload_lease: Duration,
    /// An upload stream that sends no chunk for this long is closed (its committed rows stay).
    pub upload_idle: Duration,
    /// Memory the reconstructions running in this process may take together, bytes: a job whose
    /// estimate exceeds it is refused when requested; the workers start a job only while the
    /// estimates of the running ones leave room for it.
    pub memory_budget: u64,
}

/// Three quarters of the machine's memory (`MemTotal` of `/proc/meminfo`), else 8 GiB.
pub fn default_memory_budget() -> u64 {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| {
            let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
            let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
            Some(kib * 1024 / 4 * 3)
        })
        .unwrap_or(8 << 30)
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_message_bytes: 32 << 20,
            max_body_bytes: 1 << 20,
            max_chunk_bytes: 8 << 20,
            max_patterns: helmholtz_proto::patterns::MAX_COUNT,
            max_pixels: helmholtz_proto::patterns::MAX_PIXELS,
            max_frame_pixels: 256 * 256,
            max_ground_truth_values: 1 << 22,
            max_sessions_per_lab: 10_000,
            max_pending_jobs_per_lab: 1_000,
            max_running_jobs_per_lab: 0,
            rate_per_second: 100.0,
            rate_burst: 200.0,
            upload_lease: Duration::from_secs(10),
            upload_idle: Duration::from_secs(60),
            memory_budget: default_memory_budget(),
        }
    }
}

/// Token-bucket rate limiter keyed by token id.
#[derive(Debug, Default)]
pub struct RateLimiter {
    buckets: Mutex<HashMap<i64, (f64, Instant)>>,
}

impl RateLimiter {
    /// Takes one request from `key`'s bucket; `Err(wait)` when it is empty.
    pub fn check(&self, key: i64, rate: f64, burst: f64) -> Result<(), Duration> {
        if rate <= 0.0 {
            return Ok(());
        }
        let now = Instant::now();
        let burst = burst.max(1.0);
        let mut buckets = self.buckets.lock().expect("rate limiter lock");
        let (tokens, last) = buckets.entry(key).or_insert((burst, now));
        *tokens = (*tokens + now.duration_since(*last).as_secs_f64() * rate).min(burst);
        *last = now;
        if *tokens >= 1.0 {
            *tokens -= 1.0;
            Ok(())
        } else {
            Err(Duration::from_secs_f64((1.0 - *tokens) / rate))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bucket_allows_the_burst_then_refuses_with_a_wait() {
        let r = RateLimiter::default();
        for _ in 0..3 {
            r.check(1, 1.0, 3.0).unwrap();
        }
        let wait = r.check(1, 1.0, 3.0).unwrap_err();
        assert!(
            wait > Duration::from_millis(900) && wait <= Duration::from_secs(1),
            "{wait:?}"
        );
        r.check(2, 1.0, 3.0)
            .expect("another token has its own bucket");
    }
}
