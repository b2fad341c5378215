"""Retrying, as the Rust client does (client/src/upload/retry.rs): jittered exponential backoff,
how long idempotent calls keep trying, and how a gRPC status is classified.
"""

from __future__ import annotations

import enum
import random
from dataclasses import dataclass, field

import grpc

__all__ = ["Backoff", "RetryPolicy", "Disposition", "disposition"]


@dataclass(frozen=True)
class Backoff:
    """Attempt ``n`` waits ``min(max, initial * multiplier^n)`` seconds scaled by a uniform factor
    in ``[1 - jitter, 1]`` (so concurrent clients do not retry in lock step)."""

    initial: float = 0.1
    max: float = 5.0
    multiplier: float = 2.0
    jitter: float = 0.5

    def ceiling(self, attempt: int) -> float:
        """The un-jittered delay of attempt ``attempt`` (0-based), seconds."""
        return min(self.max, self.initial * self.multiplier ** min(attempt, 64))

    def delay(self, attempt: int, unit: float | None = None) -> float:
        """The delay before retry ``attempt`` given ``unit`` uniform in [0, 1) (drawn if None)."""
        u = random.random() if unit is None else min(max(unit, 0.0), 1.0)
        jitter = min(max(self.jitter, 0.0), 1.0)
        return self.ceiling(attempt) * (1.0 - jitter * u)


@dataclass(frozen=True)
class RetryPolicy:
    """How long idempotent calls and uploads keep retrying retryable failures.

    Attributes:
        retry_for: give up once failures have gone on this long (seconds) without progress.
        backoff: the delays between attempts.
        rpc_timeout: deadline of one unary gRPC call, seconds.
        http_timeout: deadline of one REST request, seconds.
    """

    retry_for: float = 60.0
    backoff: Backoff = field(default_factory=Backoff)
    rpc_timeout: float = 30.0
    http_timeout: float = 300.0


class Disposition(enum.Enum):
    """What to do after a failed call."""

    #: Transient: back off, re-ask the committed count, resume.
    RETRY = "retry"
    #: The server's count disagrees with ours (OUT_OF_RANGE) or a chunk was damaged in transit
    #: (DATA_LOSS): re-ask the count once and resume; a second time in a row is fatal.
    RESYNC_ONCE = "resync_once"
    #: The request itself is wrong: retrying cannot help.
    FATAL = "fatal"


_RETRY = {
    grpc.StatusCode.UNAVAILABLE,
    grpc.StatusCode.DEADLINE_EXCEEDED,
    grpc.StatusCode.INTERNAL,
    grpc.StatusCode.UNKNOWN,
    grpc.StatusCode.ABORTED,
    grpc.StatusCode.RESOURCE_EXHAUSTED,
    grpc.StatusCode.CANCELLED,
}
_RESYNC = {grpc.StatusCode.OUT_OF_RANGE, grpc.StatusCode.DATA_LOSS}


def disposition(code: grpc.StatusCode) -> Disposition:
    """Classifies a gRPC status code for retrying (the Rust client's table)."""
    if code in _RETRY:
        return Disposition.RETRY
    if code in _RESYNC:
        return Disposition.RESYNC_ONCE
    return Disposition.FATAL
