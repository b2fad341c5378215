"""Errors of the client: every failure of a call is a :class:`HelmholtzError`.

- :class:`RpcError`: a gRPC call failed; ``code`` (a ``grpc.StatusCode``), ``code_name``
  (e.g. ``"ALREADY_EXISTS"``) and the server's ``message``.
- :class:`UploadError`: an upload stopped (an :class:`RpcError`), with the rows confirmed
  stored so far.
- :class:`AcquireError`: an adaptive acquisition stopped (an :class:`RpcError`), with the
  server's committed count and what was done so far.
- :class:`ApiError`: a REST call failed; the server's problem+json (RFC 9457) as attributes:
  ``status``, ``type``, ``title``, ``detail``, ``field`` (the offending input of a 400),
  ``limit`` (the limit a 413 / 429 ran into), and the whole body as ``problem``.
- :class:`ServerUnreachable`: no HTTP answer at all (connection refused, reset, timed out).
- :class:`ReconstructionFailed`: a reconstruction ended failed or cancelled.

Local mistakes (a wrong array shape, a non-finite value, a bad spec) are ``ValueError`` /
``TypeError`` (:class:`helmholtz.SpecError` for specs), raised before anything is sent.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping, Optional

import grpc

if TYPE_CHECKING:  # pragma: no cover
    from .client import Reconstruction

__all__ = [
    "HelmholtzError",
    "RpcError",
    "UploadError",
    "AcquireError",
    "ApiError",
    "ServerUnreachable",
    "ReconstructionFailed",
]


class HelmholtzError(Exception):
    """Base class of every error the client raises for a failed call."""


class RpcError(HelmholtzError):
    """A gRPC call the server refused, or that failed in transport.

    Attributes:
        operation: what was being done, e.g. ``"creating session s1"``.
        code: the ``grpc.StatusCode``.
        code_name: its canonical name, e.g. ``"INVALID_ARGUMENT"``.
        message: the server's message (or the transport's).
    """

    def __init__(self, operation: str, code: grpc.StatusCode, message: str):
        self.operation = operation
        self.code = code
        self.code_name = code.name
        self.message = message
        super().__init__(f"{operation}: {message or code.name} ({code.name})")

    @classmethod
    def from_grpc(cls, operation: str, error: grpc.RpcError) -> "RpcError":
        """From a ``grpc.RpcError`` (a failed call)."""
        code = error.code() if hasattr(error, "code") else grpc.StatusCode.UNKNOWN
        details = error.details() if hasattr(error, "details") else str(error)
        return cls(operation, code or grpc.StatusCode.UNKNOWN, details or "")


class UploadError(RpcError):
    """An upload that stopped: a fatal status, or retryable ones for longer than allowed.

    Attributes (besides :class:`RpcError`'s):
        confirmed_rows: rows ``0..confirmed_rows`` of the array are stored on the server with
            exactly these bytes (each was written or compared equal by a stream that ended OK).
        committed_rows: the server's committed count when last asked.
        report: the :class:`helmholtz.UploadReport` so far.
    """

    def __init__(
        self,
        operation: str,
        code: grpc.StatusCode,
        message: str,
        *,
        confirmed_rows: int,
        committed_rows: int,
        total_rows: int,
        report: Any = None,
        gave_up: bool = False,
    ):
        super().__init__(operation, code, message)
        self.confirmed_rows = confirmed_rows
        self.committed_rows = committed_rows
        self.total_rows = total_rows
        self.report = report
        self.gave_up = gave_up
        what = "gave up (retrying did not help)" if gave_up else "failed"
        self.args = (
            f"{operation}: {message or code.name} ({code.name}); upload {what}, "
            f"{confirmed_rows} of {total_rows} rows confirmed stored",
        )


class AcquireError(RpcError):
    """An adaptive acquisition (:meth:`helmholtz.Client.acquire`) that stopped: a status the
    server gives for the request itself (``INVALID_ARGUMENT``, ``NOT_FOUND``,
    ``FAILED_PRECONDITION``, ``PERMISSION_DENIED``, ...), or retryable ones for longer than
    allowed (``gave_up``).

    Attributes (besides :class:`RpcError`'s):
        committed_rows: rows ``0..committed_rows`` are durably stored (the server's count when
            last heard); calling ``acquire`` again resumes from there.
        report: the :class:`helmholtz.AdaptiveReport` so far (indices received, batches, ...).
        gave_up: True when retrying did not help within the retry window.
    """

    def __init__(
        self,
        operation: str,
        code: grpc.StatusCode,
        message: str,
        *,
        committed_rows: int,
        report: Any = None,
        gave_up: bool = False,
    ):
        super().__init__(operation, code, message)
        self.committed_rows = committed_rows
        self.report = report
        self.gave_up = gave_up
        what = "gave up (retrying did not help)" if gave_up else "stopped"
        self.args = (
            f"{operation}: {message or code.name} ({code.name}); acquisition {what} with "
            f"{committed_rows} rows committed",
        )


class ApiError(HelmholtzError):
    """A REST call answered with an error; the server's problem+json as attributes.

    Attributes:
        status: the HTTP status (400, 404, 409, ...).
        type: the problem type, e.g. ``"/problems/invalid-argument"``.
        title: e.g. ``"Invalid argument"``.
        detail: the server's explanation.
        field: the offending input (``"light.radius"``, ``"channel"``, ...) of a 400, or None.
        limit: the limit a 413 / 429 ran into, or None.
        retry_after: seconds the server asked to wait before retrying (429), or None.
        problem: the whole problem body (a dict; empty when the body was not problem+json).
        method, url: the request.
    """

    def __init__(
        self,
        method: str,
        url: str,
        status: int,
        problem: Mapping[str, Any],
        body_text: str = "",
    ):
        self.method = method
        self.url = url
        self.status = status
        self.problem = dict(problem)
        self.type: Optional[str] = self.problem.get("type")
        self.title: Optional[str] = self.problem.get("title")
        self.detail: Optional[str] = self.problem.get("detail") or (body_text or None)
        self.field: Optional[str] = self.problem.get("field")
        self.limit: Optional[str] = self.problem.get("limit")
        #: Seconds the server asked to wait (``Retry-After``), if any.
        self.retry_after: Optional[float] = None
        where = f" (field {self.field})" if self.field else ""
        super().__init__(
            f"{method} {url}: {status} {self.title or ''}: {self.detail or ''}{where}".replace(
                " : ", ": "
            )
        )


class ServerUnreachable(HelmholtzError):
    """No HTTP answer: the server is not reachable at that address (or stopped answering)."""

    def __init__(self, method: str, url: str, reason: str):
        self.method = method
        self.url = url
        self.reason = reason
        super().__init__(f"{method} {url}: no answer ({reason}); is the server running there?")


class ReconstructionFailed(HelmholtzError):
    """A reconstruction that ended ``failed`` or ``cancelled``; ``reconstruction`` is it."""

    def __init__(self, reconstruction: "Reconstruction"):
        self.reconstruction = reconstruction
        super().__init__(
            f"reconstruction {reconstruction.id} ({reconstruction.method}) is "
            f"{reconstruction.state}: {reconstruction.error or 'no error given'}"
        )
