"""The client: sessions and uploads over gRPC, reconstructions and images over REST.

One :class:`Client` talks to one server address (gRPC and REST share it) with one token. A
rig's token (role ``rig``) creates sessions and uploads; a reader's token (role ``reader``)
requests reconstructions and reads images. A token with both roles does everything.
"""

from __future__ import annotations

import base64
import io
import os
import queue
import secrets
import ssl
import threading
import time
import urllib.parse
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Mapping, Optional, Sequence, Union

import grpc
import numpy as np

from . import _http
from ._proto.v1 import acquisition_pb2 as pb
from ._proto.v1 import acquisition_pb2_grpc as pb_grpc
from .crc32c import crc32c
from .errors import (
    AcquireError,
    ApiError,
    HelmholtzError,
    ReconstructionFailed,
    RpcError,
    ServerUnreachable,
    UploadError,
)
from .patterns import adaptive_patterns
from .retry import Disposition, RetryPolicy, disposition
from .spec import PatternSpec

__all__ = [
    "Client",
    "Camera",
    "Session",
    "UploadStatus",
    "UploadReport",
    "AdaptiveReport",
    "Reconstruction",
    "WRITER_HEADER",
    "DEFAULT_CHUNK_BYTES",
    "MAX_CHUNK_BYTES",
    "STREAM_BYTES",
    "new_writer_id",
]

#: The gRPC metadata naming an upload's writer (server/src/api/grpc.rs): one id for every
#: stream of one upload, 1-64 characters of ``A-Z a-z 0-9 _ -``.
WRITER_HEADER = "x-helmholtz-writer"
#: Default payload per chunk (as the Rust client).
DEFAULT_CHUNK_BYTES = 256 * 1024
#: The most payload one chunk carries (the server's default ``max_chunk_bytes``).
MAX_CHUNK_BYTES = 8 << 20
#: The most payload one upload stream carries before it ends and the next starts: a stream that
#: ends OK confirms its rows, so a failure re-sends at most this much.
STREAM_BYTES = 64 << 20

_FORMATS: dict[str, "np.dtype[Any]"] = {"f64": np.dtype("<f8"), "f32": np.dtype("<f4"), "u16": np.dtype("<u2")}
_FORMAT_TO_PB = {"f64": pb.SAMPLE_FORMAT_F64, "f32": pb.SAMPLE_FORMAT_F32, "u16": pb.SAMPLE_FORMAT_U16}
_PB_TO_FORMAT = {v: k for k, v in _FORMAT_TO_PB.items()}
_PAYLOAD_FIELD = {"f64": "values_f64le", "f32": "values_f32le", "u16": "values_u16le"}

ProgressCallback = Callable[["Reconstruction"], None]
UploadProgress = Callable[[int, int], None]
#: The rig's measurement of one adaptive batch: the frames to show, ``(frames, side, side)``,
#: in; their rows, ``(frames, channels)`` (or ``(frames,)`` for one channel, or a camera's
#: ``(frames, height, width)``), out.
Measure = Callable[[np.ndarray], Any]


def new_writer_id() -> str:
    """A fresh writer id: 128 random bits in hex."""
    return secrets.token_hex(16)


@dataclass(frozen=True)
class Camera:
    """A camera in place of bucket detectors: every pattern's row is a ``width x height`` frame
    of ``format`` samples (``"f32"`` or ``"u16"``)."""

    width: int
    height: int
    format: str = "f32"

    @property
    def pixels(self) -> int:
        return self.width * self.height


@dataclass
class Session:
    """A session as the server holds it (from CreateSession, FinishSession or the REST view).

    Attributes:
        id: the session id.
        rig: the rig's name.
        spec: its :class:`PatternSpec` (canonical).
        channels: bucket channel names (empty for a camera session).
        directions: per bucket channel, the unit direction toward its detector (or empty).
        camera: the :class:`Camera` of a camera session, else None.
        metadata: free-form key/value pairs.
        committed_rows: rows stored so far (when this was read).
        expected_rows: rows the spec declares.
        state: ``"open"`` or ``"finished"``.
        created: for :meth:`Client.create_session`: False when it already existed.
    """

    id: str
    rig: str
    spec: PatternSpec
    channels: list[str]
    directions: list[tuple[float, float, float]]
    camera: Optional[Camera]
    metadata: dict[str, str]
    committed_rows: int
    expected_rows: int
    state: str
    created_unix_ms: int
    has_ground_truth: bool
    created: Optional[bool] = None

    @property
    def sample_format(self) -> str:
        """``"f64"`` for bucket sessions, the camera's format otherwise."""
        return self.camera.format if self.camera else "f64"

    @property
    def values_per_row(self) -> int:
        """Bucket channels, or a camera frame's pixels."""
        return self.camera.pixels if self.camera else len(self.channels)

    @property
    def row_shape(self) -> tuple[int, ...]:
        """The shape of one row as an ndarray: ``(channels,)`` or ``(height, width)``."""
        if self.camera:
            return (self.camera.height, self.camera.width)
        return (len(self.channels),)

    @classmethod
    def from_proto(cls, msg: pb.Session, created: Optional[bool] = None) -> "Session":
        det = msg.detector
        camera = None
        if det.HasField("camera"):
            camera = Camera(
                det.camera.width, det.camera.height, _PB_TO_FORMAT.get(det.camera.format, "f32")
            )
        return cls(
            id=msg.session_id,
            rig=msg.rig,
            spec=PatternSpec.from_proto(msg.patterns),
            channels=list(det.channels),
            directions=[(d.x, d.y, d.z) for d in det.directions],
            camera=camera,
            metadata=dict(msg.metadata),
            committed_rows=msg.committed_rows,
            expected_rows=msg.expected_rows,
            state="finished" if msg.state == pb.SESSION_STATE_FINISHED else "open",
            created_unix_ms=msg.created_unix_ms,
            has_ground_truth=msg.has_ground_truth,
            created=created,
        )

    @classmethod
    def from_view(cls, view: Mapping[str, Any]) -> "Session":
        """From the REST view (``GET /v1/sessions/{id}``)."""
        cam = view.get("camera")
        return cls(
            id=view["id"],
            rig=view["rig"],
            spec=PatternSpec.from_dict(view["patterns"]),
            channels=list(view.get("channels") or []),
            directions=[tuple(d) for d in view.get("directions") or []],  # type: ignore[misc]
            camera=Camera(cam["width"], cam["height"], cam["format"]) if cam else None,
            metadata=dict(view.get("metadata") or {}),
            committed_rows=view["committed_rows"],
            expected_rows=view["expected_rows"],
            state=view["state"],
            created_unix_ms=view.get("created_unix_ms", 0),
            has_ground_truth=bool(view.get("has_ground_truth")),
        )


@dataclass(frozen=True)
class UploadStatus:
    """Where a session's upload stands: the server's committed count is authoritative."""

    session_id: str
    committed_rows: int
    expected_rows: int
    state: str


@dataclass
class UploadReport:
    """What :meth:`Client.upload` did.

    Attributes:
        rows: rows given to upload.
        rows_sent: rows put on the wire, re-sends after a resume included.
        rows_written: rows the server newly stored.
        rows_matched: rows the server already held and compared equal to ours.
        confirmed_rows: rows ``0..confirmed_rows`` are stored with exactly our bytes.
        resumes: times the upload re-asked the committed count and resumed after a failure.
        committed_rows: the server's committed count at the end.
        expected_rows: rows the spec declares.
        last_error: the last failure that was retried, if any.
    """

    session_id: str
    writer_id: str
    rows: int = 0
    rows_sent: int = 0
    rows_written: int = 0
    rows_matched: int = 0
    confirmed_rows: int = 0
    resumes: int = 0
    committed_rows: int = 0
    expected_rows: int = 0
    chunks_sent: int = 0
    bytes_sent: int = 0
    seconds: float = 0.0
    last_error: Optional[str] = None


@dataclass
class AdaptiveReport:
    """What :meth:`Client.acquire` did.

    Attributes:
        session_id: the session.
        writer_id: the writer id every stream of the acquisition carried.
        rows: rows (frames) the finished session holds: ``2 * len(indices)`` (single frames:
            ``len(indices) + 1``) unless the session was finished by hand mid-batch.
        indices: every basis index the server issued, in order (pair ``r``, frames ``2r`` and
            ``2r + 1``, shows basis function ``indices[r]``; single frames: frames 0 and 1
            show index 0, frame ``r + 1`` the P+ of ``indices[r]``); the session's whole
            sequence, also when this call resumed a session another run started.
        batches: batches issued (the server's count, as above).
        reason: why the server stopped: ``"budget"`` (the frame budget is spent),
            ``"target_error"`` (the estimated error reached the spec's target) or
            ``"finished"`` (the session was finished before the stopping rule held).
        estimated_error: the server's estimate of the image's relative error (None before any
            batch was measured).
        frames_measured: frames this call had the rig measure (``measure`` calls x frames).
        measure_calls: batches this call measured.
        reconnects: streams opened again after a dropped one.
        rows_sent: rows put on the wire, re-sends after a reconnect included.
        rows_written, rows_matched: rows the server newly stored / already held and compared
            equal (its acks).
        idle_seconds: time spent with every issued batch measured, waiting for the next one
            (a real rig's idle projector).
        seconds: the whole call.
        last_error: the last failure that was retried, if any.
    """

    session_id: str
    writer_id: str
    rows: int = 0
    indices: list[int] = field(default_factory=list)
    batches: int = 0
    reason: str = ""
    estimated_error: Optional[float] = None
    frames_measured: int = 0
    measure_calls: int = 0
    reconnects: int = 0
    rows_sent: int = 0
    rows_written: int = 0
    rows_matched: int = 0
    idle_seconds: float = 0.0
    seconds: float = 0.0
    last_error: Optional[str] = None


@dataclass
class Reconstruction:
    """A reconstruction job as ``GET /v1/reconstructions/{id}`` returns it.

    ``state`` is ``"queued"``, ``"running"``, ``"done"``, ``"failed"`` or ``"cancelled"``;
    ``progress`` is in [0, 1]; ``report`` is the report JSON (a dict) once done;
    ``warnings`` what the user should know about the result (e.g. the data cannot support the
    resolution asked for), from its report.
    """

    id: int
    session_id: str
    method: str
    params: Any
    state: str
    progress: float
    rows: int
    attempt: int = 0
    seconds: Optional[float] = None
    error: Optional[str] = None
    report: Optional[dict[str, Any]] = None
    warnings: list[str] = field(default_factory=list)
    created_unix_ms: int = 0
    started_unix_ms: Optional[int] = None
    finished_unix_ms: Optional[int] = None
    raw: dict[str, Any] = field(default_factory=dict, repr=False)

    @property
    def done(self) -> bool:
        return self.state == "done"

    @property
    def terminal(self) -> bool:
        """Done, failed or cancelled: it will not change any more."""
        return self.state in ("done", "failed", "cancelled")

    @classmethod
    def from_view(cls, view: Mapping[str, Any]) -> "Reconstruction":
        return cls(
            id=int(view["id"]),
            session_id=view["session_id"],
            method=view["method"],
            params=view.get("params"),
            state=view["state"],
            progress=float(view.get("progress") or 0.0),
            rows=int(view.get("rows") or 0),
            attempt=int(view.get("attempt") or 0),
            seconds=view.get("seconds"),
            error=view.get("error"),
            report=view.get("report"),
            warnings=list(view.get("warnings") or []),
            created_unix_ms=int(view.get("created_unix_ms") or 0),
            started_unix_ms=view.get("started_unix_ms"),
            finished_unix_ms=view.get("finished_unix_ms"),
            raw=dict(view),
        )


@dataclass
class PreviewFrame:
    """One frame of a session's live preview (:meth:`Client.watch_preview`): the dual image of
    the session's first ``rows`` rows by ``method`` (``"dgi"`` for bernoulli and speckle
    patterns, ``"zero_filled"`` for hadamard, ``"direct"`` for raster, unmeasured blocks 0).
    ``final``: every row is in; the last frame."""

    session_id: str
    channel: str
    rows: int
    expected_rows: int
    method: str
    image: np.ndarray
    final: bool

    @classmethod
    def from_event(cls, data: Mapping[str, Any]) -> "PreviewFrame":
        values = np.frombuffer(base64.b64decode(data["values_f32le"]), dtype="<f4")
        return cls(
            session_id=data["session_id"],
            channel=data["channel"],
            rows=int(data["rows"]),
            expected_rows=int(data["expected_rows"]),
            method=data["method"],
            image=values.reshape(int(data["height"]), int(data["width"])),
            final=bool(data["final"]),
        )


SessionRef = Union[Session, str]
ReconstructionRef = Union[Reconstruction, int]


def _session_id(session: SessionRef) -> str:
    return session.id if isinstance(session, Session) else str(session)


def _recon_id(reconstruction: ReconstructionRef) -> int:
    return reconstruction.id if isinstance(reconstruction, Reconstruction) else int(reconstruction)


def _quote(segment: str) -> str:
    return urllib.parse.quote(segment, safe="")


def _npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def _load_npy(data: bytes) -> np.ndarray:
    return np.load(io.BytesIO(data), allow_pickle=False)


def _split_address(address: str) -> tuple[str, Optional[str]]:
    """``scheme://[token@]host:port`` -> (address without the token, token)."""
    if "://" not in address:
        address = "http://" + address
    parts = urllib.parse.urlsplit(address)
    token = None
    netloc = parts.netloc
    if "@" in netloc:
        userinfo, netloc = netloc.rsplit("@", 1)
        user, _, password = userinfo.partition(":")
        token = urllib.parse.unquote(password or user) or None
    return urllib.parse.urlunsplit((parts.scheme, netloc, parts.path.rstrip("/"), "", "")), token


class Client:
    """A client of one Helmholtz server.

    Args:
        address: the server, e.g. ``"http://127.0.0.1:8080"`` (gRPC and REST on one port;
            ``https://`` for TLS). A token may ride in the user part
            (``http://hz_...@127.0.0.1:8080``).
        token: the access token (default: the address's user part, else ``$HELMHOLTZ_TOKEN``).
        ca_file: PEM file of the lab's CA for ``https://`` (default: the system's roots).
        retry: how long idempotent calls and uploads keep retrying transient failures.

    Use it as a context manager (or call :meth:`close`) to close its gRPC channel.
    """

    def __init__(
        self,
        address: str,
        token: Optional[str] = None,
        *,
        ca_file: Optional[str] = None,
        retry: Optional[RetryPolicy] = None,
    ):
        self.address, address_token = _split_address(address)
        self.token = token or address_token or os.environ.get("HELMHOLTZ_TOKEN") or None
        self.retry = retry or RetryPolicy()
        parts = urllib.parse.urlsplit(self.address)
        if parts.scheme not in ("http", "https"):
            raise ValueError(f"address {address!r}: use http://host:port or https://host:port")
        self._tls = parts.scheme == "https"
        self._target = parts.netloc
        self._root_certs: Optional[bytes] = None
        ssl_context = None
        if ca_file is not None:
            with open(ca_file, "rb") as f:
                self._root_certs = f.read()
            ssl_context = ssl.create_default_context(cafile=ca_file)
        self._http = _http.Http(self.address, self.token, self.retry, ssl_context)
        self._lock = threading.Lock()
        self._channel: Optional[grpc.Channel] = None

    # -- plumbing -------------------------------------------------------------------------
    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        """Closes the gRPC channel (a later call opens a new one)."""
        with self._lock:
            if self._channel is not None:
                self._channel.close()
                self._channel = None

    def _new_channel(self) -> grpc.Channel:
        options = [
            ("grpc.max_receive_message_length", 64 << 20),
            ("grpc.max_send_message_length", -1),
            ("grpc.keepalive_time_ms", 10_000),
            ("grpc.keepalive_timeout_ms", 20_000),
            ("grpc.initial_reconnect_backoff_ms", 100),
            ("grpc.min_reconnect_backoff_ms", 100),
            ("grpc.max_reconnect_backoff_ms", 2_000),
        ]
        if self._tls:
            creds = grpc.ssl_channel_credentials(root_certificates=self._root_certs)
            return grpc.secure_channel(self._target, creds, options=options)
        return grpc.insecure_channel(self._target, options=options)

    def _stub(self) -> pb_grpc.AcquisitionStub:
        with self._lock:
            if self._channel is None:
                self._channel = self._new_channel()
            return pb_grpc.AcquisitionStub(self._channel)

    def _reset_channel(self) -> None:
        """After a transport failure: the next call connects afresh (a restarted server is
        found again at once instead of after the channel's reconnect backoff)."""
        self.close()

    def _metadata(self, writer: Optional[str] = None) -> list[tuple[str, str]]:
        md = []
        if self.token:
            md.append(("authorization", f"Bearer {self.token}"))
        if writer:
            md.append((WRITER_HEADER, writer))
        return md

    def _unary(self, method: str, request: Any, operation: str, *, retry: bool = True) -> Any:
        """An idempotent unary call, retrying retryable failures per the policy."""
        started = time.monotonic()
        attempt = 0
        while True:
            call = getattr(self._stub(), method)
            try:
                return call(request, metadata=self._metadata(), timeout=self.retry.rpc_timeout)
            except grpc.RpcError as e:
                err = RpcError.from_grpc(operation, e)
                if err.code == grpc.StatusCode.UNAVAILABLE:
                    self._reset_channel()
                elapsed = time.monotonic() - started
                if (
                    not retry
                    or disposition(err.code) is not Disposition.RETRY
                    or elapsed >= self.retry.retry_for
                ):
                    raise err from None
                time.sleep(min(self.retry.backoff.delay(attempt), self.retry.retry_for - elapsed))
                attempt += 1

    # -- service --------------------------------------------------------------------------
    def index(self) -> dict[str, Any]:
        """``GET /``: the service, its version, and the REST routes with their methods."""
        return self._http.request("GET", "/").json()

    def healthy(self) -> bool:
        """``GET /healthz`` (no token): True when the server and its database answer."""
        try:
            return self._http.request("GET", "/healthz", auth=False, retry=False).json().get(
                "status"
            ) == "serving"
        except HelmholtzError:
            return False

    # -- sessions (gRPC, role rig) --------------------------------------------------------
    def create_session(
        self,
        session_id: str,
        spec: PatternSpec,
        *,
        channels: Optional[Sequence[str]] = None,
        camera: Optional[Camera] = None,
        directions: Optional[Sequence[Sequence[float]]] = None,
        rig: str = "rig",
        metadata: Optional[Mapping[str, str]] = None,
        ground_truth: Optional[np.ndarray] = None,
    ) -> Session:
        """Declares a session (idempotent: the same declaration again returns the existing
        session with ``created`` False; a different one is ``ALREADY_EXISTS``).

        Args:
            session_id: 1-128 characters of ``A-Z a-z 0-9 . _ -``, chosen by the client.
            spec: the patterns the rig shows, in order.
            channels: bucket channel names (e.g. ``["bucket"]``); or give ``camera``.
            camera: a :class:`Camera` in place of bucket detectors.
            directions: per bucket channel, the unit direction toward its detector.
            ground_truth: a simulated scene's transport, to let the server score
                reconstructions: ``(height, width)`` (or ``(channels, height, width)``) of the
                pattern grid for buckets, ``(camera pixels, pattern pixels)`` for a camera.

        Raises:
            RpcError: e.g. ``INVALID_ARGUMENT`` naming the field, ``ALREADY_EXISTS``.
        """
        if (channels is None) == (camera is None):
            raise ValueError("give either channels (bucket detectors) or camera")
        if camera is not None and camera.format not in ("f32", "u16"):
            raise ValueError(f"camera frames are f32 or u16, not {camera.format!r}")
        detector = pb.DetectorLayout(channels=list(channels or []))
        for d in directions or []:
            detector.directions.add(x=float(d[0]), y=float(d[1]), z=float(d[2]))
        if camera is not None:
            detector.camera.CopyFrom(
                pb.CameraLayout(
                    width=camera.width, height=camera.height, format=_FORMAT_TO_PB[camera.format]
                )
            )
        request = pb.CreateSessionRequest(
            session_id=session_id,
            rig=rig,
            patterns=spec.to_proto(),
            detector=detector,
            metadata=dict(metadata or {}),
        )
        if ground_truth is not None:
            s = spec.canonical()
            gt = np.asarray(ground_truth, dtype=np.float32)
            request.ground_truth.CopyFrom(
                pb.GroundTruth(width=s.width, height=s.height, transport=gt.reshape(-1).tolist())
            )
        response = self._unary("CreateSession", request, f"creating session {session_id}")
        return Session.from_proto(response.session, created=response.created)

    def upload_status(self, session: SessionRef) -> UploadStatus:
        """The server's committed and expected row counts of a session."""
        sid = _session_id(session)
        s = self._unary(
            "GetUploadStatus", pb.SessionRef(session_id=sid), f"upload status of session {sid}"
        )
        return _status(s)

    def finish_session(self, session: SessionRef) -> Session:
        """Marks the session finished (every row of the spec must be committed; finishing twice
        is harmless)."""
        sid = _session_id(session)
        msg = self._unary("FinishSession", pb.SessionRef(session_id=sid), f"finishing session {sid}")
        return Session.from_proto(msg)

    # -- upload (gRPC, role rig) ----------------------------------------------------------
    def upload(
        self,
        session: SessionRef,
        values: np.ndarray,
        *,
        chunk_rows: Optional[int] = None,
        writer_id: Optional[str] = None,
        confirmed_rows: int = 0,
        retry_for: Optional[float] = None,
        progress: Optional[UploadProgress] = None,
    ) -> UploadReport:
        """Streams rows ``0..len(values)`` of a session, resuming after failures.

        ``values`` holds every row from row 0 (a prefix of the spec is fine; finish later):
        a bucket session's ``(rows, channels)`` array (or ``(rows,)`` for one channel), sent as
        float64; a camera session's frames ``(rows, height, width)`` in the session's format
        (float32, or uint16 counts; other dtypes are converted when that is exact for integers
        and rounded to float32 for floats).

        How it resumes (as the Rust client): rows are streamed from the first row not yet
        confirmed; the server compares rows it already holds byte for byte and refuses the
        chunk (``ALREADY_EXISTS``, naming the row) when they differ, so another writer's data
        is never taken for ours. After a retryable failure (``UNAVAILABLE``, ``ABORTED``,
        ``DEADLINE_EXCEEDED``, ...) it asks the server's committed count and resumes, with
        jittered exponential backoff, until ``retry_for`` seconds pass without progress.
        ``OUT_OF_RANGE`` / ``DATA_LOSS`` resync once. Every stream carries the writer id
        (``x-helmholtz-writer``): a new stream of the same upload takes the session over
        from its own stale stream, another writer's concurrent stream is refused (``ABORTED``).

        Args:
            session: the :class:`Session` (from :meth:`create_session`, which may be called
                again with the same declaration to resume), or its id (then the layout is read
                with ``GET /v1/sessions/{id}``, which needs the reader role).
            values: the rows, see above.
            chunk_rows: rows per chunk (default: about 256 KiB of payload).
            writer_id: the upload's writer id (default: a fresh random one).
            confirmed_rows: rows below this are known stored with these bytes: not re-sent.
            retry_for: seconds of failures without progress before giving up (default: the
                client's :class:`RetryPolicy`).
            progress: called as ``progress(rows_sent_up_to, total_rows)`` after each chunk.

        Raises:
            ValueError: a shape, dtype or value the session cannot take (nothing sent).
            UploadError: a fatal status (``INVALID_ARGUMENT``, ``ALREADY_EXISTS``,
                ``FAILED_PRECONDITION``, ...) or retryable ones for longer than ``retry_for``;
                with the rows confirmed so far.
        """
        if not isinstance(session, Session):
            session = self.session(session)
        rows = _rows_of(session, values)
        writer = writer_id or new_writer_id()
        return _Upload(self, session, rows, writer, chunk_rows, confirmed_rows, retry_for, progress).run()

    # -- adaptive acquisition (gRPC Acquire, role rig) ------------------------------------
    def acquire(
        self,
        session: SessionRef,
        measure: Measure,
        *,
        writer_id: Optional[str] = None,
        chunk_rows: Optional[int] = None,
        retry_for: Optional[float] = None,
        dtype: "np.typing.DTypeLike" = np.float32,
    ) -> AdaptiveReport:
        """Runs an adaptive session (family ``adaptive_haar`` or ``adaptive_hadamard``) to its
        end from the rig's side, over the bidirectional gRPC stream ``Acquire``.

        The server chooses the patterns: it sends batches of basis indices, and for each batch
        this calls ``measure(patterns)`` with the batch's frames as an ndarray ``(frames,
        side, side)`` of ``dtype`` (0.0 / 1.0; :func:`helmholtz.adaptive_patterns`). With split
        pairs (the default) a batch of ``p`` indices is ``2 p`` frames: frame ``2j`` is P+ of
        the batch's ``j``-th index, ``2j + 1`` its P-. With single frames (``adaptive_haar``
        with ``frames="single"``, PATTERNS.md "Single frames") every index is its P+ alone,
        but index 0, which opens the session as its pair: the first batch is ``p + 1`` frames
        (frame 0 all on, frame 1 all off, frame ``j + 1`` the P+ of its ``j``-th index, ``j >=
        1``), every later batch ``p`` (frame ``j`` the P+ of its ``j``-th index). Each batch
        starts at the row the server gives (``AdaptiveBatch.first_row``). ``measure``
        shows them in order and returns one row per frame: ``(frames, channels)`` bucket
        values (``(frames,)`` for one channel), or a camera session's ``(frames, height,
        width)``. The rows are checked (shape, finite values, as :meth:`upload`) and streamed
        back (CRC-32C); the server commits them, plans the next batches from them, and ends
        the session when its frame budget is spent or its estimated error reaches the spec's
        ``target_error``. ``measure`` is called from this thread, once per batch, in order.

        Resuming (as the Rust client's ``acquire_adaptive``): the rig keeps the rows it
        measured until the server acknowledges them. A dropped stream (``UNAVAILABLE``, a
        restarting server, ``ABORTED`` while our stale stream still holds the session, ...) is
        reopened with jittered backoff for as long as ``retry_for`` seconds pass without the
        committed count moving; the server then says where it stands and re-sends the batches
        not yet measured, and the rig re-sends its rows from the committed count. Calling
        ``acquire`` again after an exception (or from a restarted process) resumes the same
        way: batches already committed are not measured again. The index sequence is a
        deterministic function of the spec and the values, so a resumed session ends with the
        indices an uninterrupted one would have.

        Args:
            session: the :class:`Session` (from :meth:`create_session`) or its id.
            measure: the rig, see above.
            writer_id: the acquisition's writer id (default: a fresh random one).
            chunk_rows: rows per chunk (default: about 256 KiB of payload).
            retry_for: seconds of failures without progress before giving up (default: the
                client's :class:`RetryPolicy`).
            dtype: the dtype of the patterns given to ``measure``.

        Returns:
            An :class:`AdaptiveReport`: the session's index sequence, rows, batches and why
            the server stopped.

        Raises:
            ValueError: ``measure`` returned rows of the wrong shape or count, or a non-finite
                value (nothing of that batch is sent; rows of earlier batches stay stored), or
                the session is not adaptive.
            AcquireError: the server refused (``FAILED_PRECONDITION`` for a session of another
                family, ``NOT_FOUND`` for another lab's, ``PERMISSION_DENIED`` without the rig
                role, ``INVALID_ARGUMENT`` naming a field, ...), or retryable failures lasted
                longer than ``retry_for``; with the rows committed so far.
            HelmholtzError: the server's batches contradict each other (a batch re-sent with
                other indices, out of sequence).
        """
        if isinstance(session, Session) and not session.spec.adaptive:
            raise ValueError(
                f"session {session.id!r} declares {session.spec.family} patterns, not an adaptive "
                "family (adaptive_haar, adaptive_hadamard): upload its rows with upload()"
            )
        return _Acquisition(
            self,
            _session_id(session),
            measure,
            writer_id or new_writer_id(),
            chunk_rows,
            self.retry.retry_for if retry_for is None else retry_for,
            dtype,
        ).run()

    # -- sessions (REST, role reader) -----------------------------------------------------
    def session(self, session_id: str) -> Session:
        """``GET /v1/sessions/{id}``: the session's declaration and counts."""
        return Session.from_view(
            self._http.request("GET", f"/v1/sessions/{_quote(session_id)}").json()
        )

    def sessions(self, limit: int = 100) -> list[Session]:
        """``GET /v1/sessions``: the lab's sessions, newest first."""
        body = self._http.request("GET", "/v1/sessions", query={"limit": limit}).json()
        return [Session.from_view(v) for v in body["sessions"]]

    def measurements(self, session: SessionRef) -> np.ndarray:
        """``GET /v1/sessions/{id}/measurements.npy``: the committed rows exactly as stored:
        float64 ``(rows, channels)``, or a camera session's frames ``(rows, height, width)``."""
        sid = _session_id(session)
        return _load_npy(
            self._http.request("GET", f"/v1/sessions/{_quote(sid)}/measurements.npy").body
        )

    def adaptive_sequence(self, session: SessionRef) -> dict[str, Any]:
        """``GET /v1/sessions/{id}/adaptive.json``: an adaptive session's issued batches in
        order, ``{"session_id", "issued_rows", "indices", "batches": [{"number",
        "first_row", "indices"}]}``. With the spec, ``indices`` gives every pattern of the
        session (``hz.patterns(session.spec, indices=...)``); with :meth:`measurements`, what
        replays it.

        Raises:
            ApiError: 409 for a session of another family, 404 for an unknown one.
        """
        sid = _session_id(session)
        return self._http.request("GET", f"/v1/sessions/{_quote(sid)}/adaptive.json").json()

    # -- reconstructions (REST, role reader) ----------------------------------------------
    def reconstruct(
        self, session: SessionRef, method: str = "auto", params: Optional[Mapping[str, Any]] = None
    ) -> Reconstruction:
        """``POST /v1/sessions/{id}/reconstructions``: queues a reconstruction of the rows
        committed so far (not retried: each call queues a new job).

        ``method``: ``"auto"``, ``"gi"``, ``"dgi"``, ``"ngi"``, ``"direct"``, ``"lsq"``,
        ``"cs"``, ``"tv"``, ... for bucket sessions; ``"transport"`` for camera sessions
        (``GET /`` lists them). ``params``: the method's parameters (default ``{}``).

        Raises:
            ApiError: e.g. 400 with ``field`` naming a bad parameter, 409 for a method that does
                not fit the session.
        """
        sid = _session_id(session)
        body = {"method": method, "params": dict(params or {})}
        r = self._http.request(
            "POST", f"/v1/sessions/{_quote(sid)}/reconstructions", json_body=body, retry=False
        )
        return Reconstruction.from_view(r.json())

    def reconstruction(self, reconstruction: ReconstructionRef) -> Reconstruction:
        """``GET /v1/reconstructions/{id}``."""
        rid = _recon_id(reconstruction)
        return Reconstruction.from_view(
            self._http.request("GET", f"/v1/reconstructions/{rid}").json()
        )

    def reconstructions(self, session: SessionRef) -> list[Reconstruction]:
        """``GET /v1/sessions/{id}/reconstructions``."""
        sid = _session_id(session)
        body = self._http.request("GET", f"/v1/sessions/{_quote(sid)}/reconstructions").json()
        return [Reconstruction.from_view(v) for v in body["reconstructions"]]

    def wait(
        self,
        reconstruction: ReconstructionRef,
        *,
        timeout: float = 300.0,
        progress: Optional[ProgressCallback] = None,
        raise_on_failure: bool = True,
    ) -> Reconstruction:
        """Polls the reconstruction until it is done, failed or cancelled.

        ``progress`` is called with the :class:`Reconstruction` after every poll (its
        ``state`` and ``progress`` in [0, 1]), the last time with the finished one. Polls start
        at 50 ms and double up to 1 s. Transient failures to reach the server are retried until
        the timeout.

        Raises:
            ReconstructionFailed: it ended failed or cancelled (unless ``raise_on_failure`` is
                False: then it is returned).
            TimeoutError: not finished within ``timeout`` seconds.
            ApiError: the server refused the poll (e.g. 404).
        """
        rid = _recon_id(reconstruction)
        started = time.monotonic()
        poll = 0.05
        while True:
            try:
                view = self._http.request("GET", f"/v1/reconstructions/{rid}", retry=False).json()
            except (ServerUnreachable, ApiError) as e:
                # A server restarting or overloaded: poll again until the timeout. A problem the
                # server states (404, 400, ...) will not go away by waiting.
                transient = isinstance(e, ServerUnreachable) or e.status >= 500 or e.status == 429
                if not transient or time.monotonic() - started >= timeout:
                    raise
                time.sleep(min(poll, max(0.0, timeout - (time.monotonic() - started))))
                poll = min(poll * 2, 1.0)
                continue
            rec = Reconstruction.from_view(view)
            if progress is not None:
                progress(rec)
            if rec.terminal:
                if rec.state != "done" and raise_on_failure:
                    raise ReconstructionFailed(rec)
                return rec
            elapsed = time.monotonic() - started
            if elapsed >= timeout:
                raise TimeoutError(
                    f"reconstruction {rid} is still {rec.state} ({rec.progress:.0%}) after {timeout} s"
                )
            time.sleep(min(poll, timeout - elapsed))
            poll = min(poll * 2, 1.0)

    def cancel(self, reconstruction: ReconstructionRef) -> Reconstruction:
        """``POST /v1/reconstructions/{id}/cancel``: cancels a queued or running one."""
        rid = _recon_id(reconstruction)
        r = self._http.request("POST", f"/v1/reconstructions/{rid}/cancel", retry=False)
        return Reconstruction.from_view(r.json())

    def report(self, reconstruction: ReconstructionRef) -> dict[str, Any]:
        """The report JSON of a finished reconstruction (method, parameters, iterations,
        timings, the held-out error, quality against a simulated ground truth, ...).

        Raises:
            HelmholtzError: it is not done yet (no report).
        """
        rec = self.reconstruction(reconstruction)
        if rec.report is None:
            raise HelmholtzError(f"reconstruction {rec.id} is {rec.state}: no report yet")
        return rec.report

    def watch_preview(
        self,
        session: SessionRef,
        *,
        every_rows: Optional[int] = None,
        every_ms: Optional[int] = None,
        channel: Optional[str] = None,
    ) -> Iterator[PreviewFrame]:
        """``GET /v1/sessions/{id}/preview``: the session's live preview while it uploads, as
        :class:`PreviewFrame` s (server-sent events) with increasing ``rows``, a frame every
        ``every_rows`` new rows or ``every_ms`` milliseconds (default every 500 ms), ending with
        the ``final`` frame once every row is in. Stop early by breaking out of the loop (or
        closing the generator): the server's preview stops with it. Role rig or reader.

        Raises:
            ApiError: a bad parameter (400 naming ``every_rows``, ``every_ms`` or ``channel``),
                another lab's or an unknown session (404).
        """
        sid = _session_id(session)
        query = {"every_rows": every_rows, "every_ms": every_ms, "channel": channel}
        for name, data in self._http.events(f"/v1/sessions/{_quote(sid)}/preview", query=query):
            if name == "error":
                raise HelmholtzError(f"the preview of session {sid} stopped: {data.get('detail')}")
            if name == "preview":
                frame = PreviewFrame.from_event(data)
                yield frame
                if frame.final:
                    return

    def dual_image(
        self, reconstruction: ReconstructionRef, channel: Optional[str] = None
    ) -> np.ndarray:
        """``GET /v1/reconstructions/{id}/dual.npy``: the dual image (the scene as the
        projector sees it), float32 ``(height, width)`` of the pattern grid. ``channel``: a
        channel name or index (default the first; a camera session's dual image is ``T^T 1``
        under the whole camera)."""
        rid = _recon_id(reconstruction)
        r = self._http.request(
            "GET", f"/v1/reconstructions/{rid}/dual.npy", query={"channel": channel}
        )
        return _load_npy(r.body)

    def session_dual_image(self, session: SessionRef, channel: Optional[str] = None) -> np.ndarray:
        """``GET /v1/sessions/{id}/dual.npy``: the dual image of the session's latest finished
        reconstruction."""
        sid = _session_id(session)
        r = self._http.request("GET", f"/v1/sessions/{_quote(sid)}/dual.npy", query={"channel": channel})
        return _load_npy(r.body)

    def relight(
        self,
        reconstruction: ReconstructionRef,
        light: Union[np.ndarray, Mapping[str, Any], None] = None,
        *,
        preset: Optional[str] = None,
        weights: Optional[Mapping[str, float]] = None,
        **preset_params: float,
    ) -> np.ndarray:
        """``POST /v1/reconstructions/{id}/relight``: the dual image under a virtual light
        ``c'`` at the detector side, ``p' = T^T c'``, float32 ``(height, width)`` of the
        pattern grid.

        The light is one of:

        - an ndarray: a camera session's per-pixel weights, ``(camera height, camera width)``
          or flat (sent as an NPY body);
        - ``preset="full"`` (the default), ``preset="disc", x=..., y=..., radius=...`` or
          ``preset="stripe", x0=..., x1=...`` (camera pixel units);
        - ``weights={"r": 1.0, ...}``: a bucket session's per-channel weights;
        - a mapping: the JSON ``light`` object itself.

        Raises:
            ApiError: a light the session cannot take (400, ``field`` names it).
        """
        rid = _recon_id(reconstruction)
        path = f"/v1/reconstructions/{rid}/relight"
        if isinstance(light, np.ndarray):
            if preset or weights or preset_params:
                raise ValueError("give the light as an array or as a preset / weights, not both")
            body = _npy_bytes(np.asarray(light, dtype=np.float32))
            r = self._http.request(
                "POST", path, query={"format": "npy"}, body=body, content_type="application/x-npy"
            )
            return _load_npy(r.body)
        if light is not None:
            light_json: dict[str, Any] = dict(light)
        elif weights is not None:
            if preset or preset_params:
                raise ValueError("give weights or a preset, not both")
            light_json = {"weights": {k: float(v) for k, v in weights.items()}}
        else:
            light_json = {"preset": preset or "full", **preset_params}
        r = self._http.request("POST", path, query={"format": "npy"}, json_body={"light": light_json})
        return _load_npy(r.body)

    def primal(
        self,
        reconstruction: ReconstructionRef,
        pattern: Optional[np.ndarray] = None,
        *,
        pattern_index: Optional[int] = None,
        ambient: bool = True,
        with_error: bool = False,
    ) -> Any:
        """``POST /v1/reconstructions/{id}/primal``: the camera image ``T p (+ ambient)`` a
        projector pattern would give, float32 ``(camera height, camera width)``.

        Args:
            pattern: a projector-sized pattern ``(height, width)`` (or flat), any values.
            pattern_index: one of the session's own patterns instead (then the server also
                compares the prediction with the measured frame).
            ambient: add the estimated ambient (dark) level (default) or not.
            with_error: return ``(image, info)`` where ``info`` holds the server's
                ``relative_error``, ``psnr_db`` and ``measured_row`` against the measured frame
                (for ``pattern_index``; None otherwise).

        Raises:
            ApiError: e.g. 400 naming ``pattern_index`` or ``body``; 409 for a bucket session.
        """
        rid = _recon_id(reconstruction)
        path = f"/v1/reconstructions/{rid}/primal"
        query = {"format": "npy", "ambient": "include" if ambient else "exclude"}
        if (pattern is None) == (pattern_index is None):
            raise ValueError("give either pattern or pattern_index")
        if pattern is not None:
            body = _npy_bytes(np.asarray(pattern, dtype=np.float32))
            r = self._http.request(
                "POST", path, query=query, body=body, content_type="application/x-npy"
            )
        else:
            r = self._http.request(
                "POST", path, query=query, json_body={"pattern_index": int(pattern_index)}  # type: ignore[arg-type]
            )
        image = _load_npy(r.body)
        if not with_error:
            return image

        def header(name: str, kind: Callable[[str], Any]) -> Any:
            v = r.headers.get(name)
            return kind(v) if v is not None else None

        info = {
            "relative_error": header("x-helmholtz-relative-error", float),
            "psnr_db": header("x-helmholtz-psnr-db", float),
            "measured_row": header("x-helmholtz-measured-row", int),
        }
        return image, info


def _status(s: pb.UploadStatus) -> UploadStatus:
    return UploadStatus(
        session_id=s.session_id,
        committed_rows=s.committed_rows,
        expected_rows=s.expected_rows,
        state="finished" if s.state == pb.SESSION_STATE_FINISHED else "open",
    )


def _rows_of(session: Session, values: np.ndarray) -> np.ndarray:
    """``values`` as a C-contiguous ``(rows, values_per_row)`` array of the session's wire
    dtype (little-endian), checked."""
    arr = np.asarray(values)
    per_row = session.values_per_row
    fmt = session.sample_format
    if session.camera is not None:
        cam = session.camera
        if arr.ndim == 3:
            if arr.shape[1:] != (cam.height, cam.width):
                raise ValueError(
                    f"frames of shape {arr.shape[1:]}; session {session.id!r} has a "
                    f"{cam.width}x{cam.height} camera: (rows, {cam.height}, {cam.width})"
                )
        elif not (arr.ndim == 2 and arr.shape[1] == per_row):
            raise ValueError(
                f"camera frames must be (rows, {cam.height}, {cam.width}), got shape {arr.shape}"
            )
    else:
        if arr.ndim == 1 and per_row == 1:
            arr = arr.reshape(-1, 1)
        if arr.ndim != 2 or arr.shape[1] != per_row:
            raise ValueError(
                f"bucket rows must be (rows, {per_row}) for the {per_row} channel(s) "
                f"{session.channels}, got shape {arr.shape}"
            )
    if arr.dtype.kind not in "fiub":
        raise ValueError(f"values must be numbers, got dtype {arr.dtype}")
    rows = arr.reshape(arr.shape[0], per_row)
    wire = _FORMATS[fmt]
    if fmt == "u16":
        if rows.dtype.kind == "f":
            if not np.all(np.isfinite(rows)) or np.any(rows != np.round(rows)):
                raise ValueError("u16 frames must hold whole numbers")
        if rows.size and (rows.min() < 0 or rows.max() > 65535):
            raise ValueError("u16 frames must hold values in 0..=65535")
        out = np.ascontiguousarray(rows, dtype=wire)
    else:
        out = np.ascontiguousarray(rows, dtype=wire)
        bad = ~np.isfinite(out)
        if bad.any():
            r, c = (int(x) for x in np.argwhere(bad)[0])
            raise ValueError(f"value at row {r}, column {c} is not finite ({out[r, c]})")
    if out.shape[0] > session.expected_rows > 0:
        raise ValueError(
            f"{out.shape[0]} rows given but session {session.id!r} expects {session.expected_rows}"
        )
    return out


class _StreamFailed(Exception):
    def __init__(self, error: RpcError):
        self.error = error


class _Upload:
    """One upload (client/src/upload/mod.rs `upload_rows_as`, in Python)."""

    def __init__(
        self,
        client: Client,
        session: Session,
        rows: np.ndarray,
        writer: str,
        chunk_rows: Optional[int],
        confirmed: int,
        retry_for: Optional[float],
        progress: Optional[UploadProgress],
    ):
        self.client = client
        self.session = session
        self.rows = rows
        self.writer = writer
        self.total = rows.shape[0]
        self.row_bytes = rows.shape[1] * rows.dtype.itemsize
        per_chunk = chunk_rows if chunk_rows is not None else DEFAULT_CHUNK_BYTES // max(1, self.row_bytes)
        self.chunk_rows = max(1, min(per_chunk, MAX_CHUNK_BYTES // max(1, self.row_bytes)))
        self.rows_a_stream = max(1, max(STREAM_BYTES // max(1, self.row_bytes), self.chunk_rows) // self.chunk_rows) * self.chunk_rows
        self.confirmed = min(max(0, confirmed), self.total)
        self.policy = client.retry
        self.retry_for = self.policy.retry_for if retry_for is None else retry_for
        self.progress = progress
        self.report = UploadReport(
            session_id=session.id, writer_id=writer, rows=self.total, confirmed_rows=self.confirmed
        )
        self.field = _PAYLOAD_FIELD[session.sample_format]

    def _fail(self, err: RpcError, *, committed: int, gave_up: bool = False) -> UploadError:
        self.report.seconds = time.monotonic() - self.started
        return UploadError(
            err.operation,
            err.code,
            err.message,
            confirmed_rows=self.confirmed,
            committed_rows=committed,
            total_rows=self.total,
            report=self.report,
            gave_up=gave_up,
        )

    def _chunks(
        self, start: int, end: int, counters: dict[str, int], local: list[BaseException]
    ) -> Iterator[pb.MeasurementChunk]:
        """The chunks of rows start..end, made as gRPC takes them (in its thread). An exception
        here (e.g. from the progress callback) ends the stream early and is kept in `local`
        to be raised by the caller: never taken for a failure of the server."""
        sid, channels = self.session.id, self.rows.shape[1]
        for a in range(start, end, self.chunk_rows):
            b = min(end, a + self.chunk_rows)
            try:
                payload = self.rows[a:b].tobytes()
                chunk = pb.MeasurementChunk(
                    session_id=sid, start_row=a, channels=channels, crc32c=crc32c(payload)
                )
                setattr(chunk, self.field, payload)
            except BaseException as e:  # noqa: BLE001 - re-raised by _stream
                local.append(e)
                return
            yield chunk
            counters["rows"] += b - a
            counters["chunks"] += 1
            counters["bytes"] += len(payload)
            if self.progress is not None:
                try:
                    self.progress(b, self.total)
                except BaseException as e:  # noqa: BLE001 - re-raised by _stream
                    local.append(e)
                    return

    def _stream(self, start: int, end: int) -> pb.UploadResponse:
        counters = {"rows": 0, "chunks": 0, "bytes": 0}
        local: list[BaseException] = []
        stub = self.client._stub()
        try:
            response = stub.UploadMeasurements(
                self._chunks(start, end, counters, local),
                metadata=self.client._metadata(self.writer),
            )
            if local:
                raise local[0]
            return response
        except grpc.RpcError as e:
            if local:
                raise local[0] from None
            err = RpcError.from_grpc(f"uploading to session {self.session.id}", e)
            if err.code == grpc.StatusCode.UNAVAILABLE:
                self.client._reset_channel()
            raise _StreamFailed(err) from None
        finally:
            self.report.rows_sent += counters["rows"]
            self.report.chunks_sent += counters["chunks"]
            self.report.bytes_sent += counters["bytes"]

    def run(self) -> UploadReport:
        self.started = time.monotonic()
        sid = self.session.id
        asked = False
        failing_since: Optional[float] = None
        best_committed = 0
        committed = 0
        stream_length = self.rows_a_stream
        attempt = 0
        resync_used = False

        def back_off_or_fail(err: RpcError) -> None:
            nonlocal failing_since, attempt
            now = time.monotonic()
            if failing_since is None:
                failing_since = now
            if now - failing_since >= self.retry_for:
                raise self._fail(err, committed=committed, gave_up=True)
            self.report.last_error = str(err)
            remaining = self.retry_for - (now - failing_since)
            time.sleep(max(0.0, min(self.policy.backoff.delay(attempt), remaining)))
            attempt += 1

        while self.confirmed < self.total or not asked:
            # 1. Where does the server stand? (one attempt; failures back off here)
            try:
                status = self.client._unary(
                    "GetUploadStatus",
                    pb.SessionRef(session_id=sid),
                    f"upload status of session {sid}",
                    retry=False,
                )
            except RpcError as err:
                if disposition(err.code) is Disposition.FATAL:
                    raise self._fail(err, committed=committed) from None
                back_off_or_fail(err)
                continue
            committed = status.committed_rows
            if committed > best_committed:
                if asked:
                    failing_since, attempt = None, 0
                best_committed = committed
            if not asked:
                asked = True
                self.report.expected_rows = status.expected_rows
                if status.expected_rows and self.total > status.expected_rows:
                    raise ValueError(
                        f"{self.total} rows given but session {sid} expects {status.expected_rows}"
                    )
            self.report.committed_rows = committed
            if self.confirmed >= self.total:
                break
            if status.state == pb.SESSION_STATE_FINISHED and self.total > committed:
                raise self._fail(
                    RpcError(
                        f"uploading to session {sid}",
                        grpc.StatusCode.FAILED_PRECONDITION,
                        f"the session is finished with {committed} rows; rows "
                        f"{committed}..{self.total} were never stored and never will be",
                    ),
                    committed=committed,
                )
            # 2. Stream from the first unconfirmed row (the server compares what it has).
            start = min(self.confirmed, committed)
            end = min(start + stream_length, self.total)
            try:
                response = self._stream(start, end)
            except _StreamFailed as failed:
                failure = failed.error
                d = disposition(failure.code)
                if d is Disposition.FATAL or (d is Disposition.RESYNC_ONCE and resync_used):
                    raise self._fail(failure, committed=committed) from None
                if d is Disposition.RESYNC_ONCE:
                    resync_used = True
                    self.report.last_error = str(failure)
                else:
                    back_off_or_fail(failure)
                self.report.resumes += 1
                stream_length = max(
                    self.chunk_rows, stream_length // 2 // self.chunk_rows * self.chunk_rows
                )
                continue
            self.report.rows_written += response.rows_written
            self.report.rows_matched += response.rows_skipped
            self.report.committed_rows = response.committed_rows
            committed = response.committed_rows
            stream_length = min(stream_length * 2, self.rows_a_stream)
            if end > self.confirmed:
                self.confirmed = end
                self.report.confirmed_rows = end
                failing_since, attempt, resync_used = None, 0, False
        self.report.seconds = time.monotonic() - self.started
        return self.report


_STOP_REASONS = {
    pb.ADAPTIVE_STOP_BUDGET: "budget",
    pb.ADAPTIVE_STOP_TARGET_ERROR: "target_error",
    pb.ADAPTIVE_STOP_FINISHED: "finished",
}


#: How long a rig's failure waits for the server to commit the rows already sent.
_DRAIN_SECONDS = 5.0


class _StreamEnded(Exception):
    """One Acquire stream ended without ``done``: the status says why."""

    def __init__(self, error: RpcError):
        self.error = error


class _Acquisition:
    """One adaptive acquisition (client/src/adaptive.rs `acquire_adaptive`, in Python): the
    rig's state across the streams it opens."""

    def __init__(
        self,
        client: Client,
        session_id: str,
        measure: Measure,
        writer: str,
        chunk_rows: Optional[int],
        retry_for: float,
        dtype: "np.typing.DTypeLike",
    ):
        self.client = client
        self.sid = session_id
        self.measure = measure
        self.writer = writer
        self.chunk_rows = chunk_rows
        self.retry_for = retry_for
        self.dtype = dtype
        self.policy = client.retry
        self.operation = f"adaptive acquisition of session {session_id}"
        #: The session as the server's `opened` gave it (spec, channels, camera).
        self.session: Optional[Session] = None
        #: Every batch issued, by number: (first_row, indices).
        self.batches: list[tuple[int, list[int]]] = []
        #: The frames (rows) of each batch in `batches`: two per index, or with single frames
        #: one per index plus one for index 0's pair.
        self.batch_rows: list[int] = []
        self.seen: set[int] = set()
        #: Rows 0..measured are measured (or stored by the server already).
        self.measured = 0
        #: Measured rows the server has not acknowledged: (first row, rows array).
        self.unacked: list[tuple[int, np.ndarray]] = []
        self.committed = 0
        self.report = AdaptiveReport(session_id=session_id, writer_id=writer)

    # -- the batches ----------------------------------------------------------------------
    def _batch(self, b: pb.AdaptiveBatch) -> None:
        """A batch from the server: a new one extends the sequence; one sent again (after a
        reopen) must equal the one held."""
        indices = list(b.indices)
        if b.number < len(self.batches):
            if self.batches[b.number] != (b.first_row, indices):
                raise HelmholtzError(
                    f"{self.operation}: the server sent batch {b.number} again with other indices"
                )
            return
        assert self.session is not None
        spec = self.session.spec
        # The server's first_row is authoritative; the rig's layout must agree with it (else
        # the rows of the batch would land on other frames).
        before = sum(len(ix) for _, ix in self.batches)
        end = self.batches[-1][0] + self.batch_rows[-1] if self.batches else 0
        if b.number != len(self.batches) or b.first_row != end or not indices:
            raise HelmholtzError(
                f"{self.operation}: the server sent batch {b.number} at row {b.first_row}; the "
                f"rig expected batch {len(self.batches)} at row {end}"
            )
        k = spec.pixels
        for r, n in enumerate(indices):
            if not 0 <= n < k or n in self.seen:
                raise HelmholtzError(
                    f"{self.operation}: batch {b.number} holds basis index {n}, out of range "
                    f"0..{k} or already shown"
                )
            if spec.single_frames and (n == 0) != (before + r == 0):
                raise HelmholtzError(
                    f"{self.operation}: batch {b.number} holds basis index {n} at position "
                    f"{before + r} of a single-frame session, which shows index 0 first (and "
                    "only there)"
                )
            self.seen.add(n)
        self.batches.append((b.first_row, indices))
        self.batch_rows.append(
            spec.adaptive_rows(before + len(indices)) - spec.adaptive_rows(before)
        )

    def _next_to_measure(self) -> Optional[int]:
        """The first issued batch with rows not yet measured (nor stored by the server)."""
        done = max(self.measured, self.committed)
        for number, (first, _) in enumerate(self.batches):
            if first + self.batch_rows[number] > done:
                return number
        return None

    def _measure(self, number: int) -> None:
        """Shows batch `number` through the rig and keeps its new rows (checked)."""
        assert self.session is not None
        first, indices = self.batches[number]
        frames = self.batch_rows[number]
        patterns = adaptive_patterns(self.session.spec, indices, dtype=self.dtype)
        assert patterns.shape[0] == frames
        values = self.measure(patterns)
        self.report.measure_calls += 1
        self.report.frames_measured += frames
        where = f"the measurement of batch {number} (rows {first}..{first + frames})"
        try:
            rows = _rows_of(self.session, values)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
        if rows.shape[0] != frames:
            what = "single-frame indices" if self.session.spec.single_frames else "split pairs"
            raise ValueError(
                f"{where} holds {rows.shape[0]} rows; {frames} frames ({len(indices)} {what}) "
                "were shown: one row per frame"
            )
        keep = max(self.measured, self.committed, first) - first
        if keep < frames:
            self.unacked.append((first + keep, rows[keep:]))
        self.measured = first + frames

    # -- acknowledgements and sending -----------------------------------------------------
    def _acknowledged(self, committed: int) -> None:
        self.committed = max(self.committed, committed)
        while self.unacked and self.unacked[0][0] + self.unacked[0][1].shape[0] <= self.committed:
            self.unacked.pop(0)

    def _send(self, outbox: "queue.Queue[Optional[pb.AcquireRequest]]", entries: list[tuple[int, np.ndarray]]) -> None:
        """Queues the rows of `entries` at or past the committed count, in chunks."""
        assert self.session is not None
        field_name = _PAYLOAD_FIELD[self.session.sample_format]
        for start, rows in entries:
            per_row = rows.shape[1]
            row_bytes = per_row * rows.dtype.itemsize
            step = self.chunk_rows or DEFAULT_CHUNK_BYTES // max(1, row_bytes)
            step = max(1, min(step, MAX_CHUNK_BYTES // max(1, row_bytes)))
            for a in range(max(0, self.committed - start), rows.shape[0], step):
                b = min(rows.shape[0], a + step)
                payload = rows[a:b].tobytes()
                chunk = pb.MeasurementChunk(
                    session_id=self.sid, start_row=start + a, channels=per_row, crc32c=crc32c(payload)
                )
                setattr(chunk, field_name, payload)
                outbox.put(pb.AcquireRequest(chunk=chunk))
                self.report.rows_sent += b - a

    # -- one stream -----------------------------------------------------------------------
    def _stream(self) -> bool:
        """One Acquire stream: True at the server's `done`; `_StreamEnded` when it ends
        otherwise. A ValueError of the rig's measurement, or a contradiction of the server's,
        ends it and propagates."""
        outbox: "queue.Queue[Optional[pb.AcquireRequest]]" = queue.Queue()
        outbox.put(
            pb.AcquireRequest(
                open=pb.AcquireOpen(
                    session_id=self.sid,
                    measured_rows=self.measured,
                    known_batches=len(self.batches),
                )
            )
        )

        def requests() -> Iterator[pb.AcquireRequest]:
            while True:
                item = outbox.get()
                if item is None:
                    return
                yield item

        call = self.client._stub().Acquire(requests(), metadata=self.client._metadata(self.writer))
        try:
            return self._converse(call, outbox)
        except (_StreamEnded, HelmholtzError):
            raise
        except Exception:
            # The rig's own failure (its measurement raised, or returned rows we refuse): rows
            # already sent are real; let the server commit them before the error propagates.
            self._drain(call, outbox)
            raise
        finally:
            outbox.put(None)
            call.cancel()

    def _drain(self, call: Any, outbox: "queue.Queue[Optional[pb.AcquireRequest]]") -> None:
        """Half-closes the stream and reads the server's acks until it ends (at most
        `_DRAIN_SECONDS`)."""
        outbox.put(None)
        timer = threading.Timer(_DRAIN_SECONDS, call.cancel)
        timer.start()
        try:
            for response in call:
                if response.WhichOneof("message") == "ack":
                    self._acknowledged(response.ack.committed_rows)
                    self.report.rows_written += response.ack.rows_written
                    self.report.rows_matched += response.ack.rows_skipped
        except grpc.RpcError:
            pass
        finally:
            timer.cancel()

    def _converse(self, call: Any, outbox: "queue.Queue[Optional[pb.AcquireRequest]]") -> bool:
        opened = False
        while True:
            if opened:
                number = self._next_to_measure()
                if number is not None:
                    before = len(self.unacked)
                    self._measure(number)
                    self._send(outbox, self.unacked[before:])
                    continue
            waited = time.monotonic()
            try:
                response = next(call)
            except StopIteration:
                raise _StreamEnded(
                    RpcError(
                        self.operation,
                        grpc.StatusCode.UNAVAILABLE,
                        "the server ended the stream before the acquisition was done",
                    )
                ) from None
            except grpc.RpcError as e:
                raise _StreamEnded(RpcError.from_grpc(self.operation, e)) from None
            if opened:
                self.report.idle_seconds += time.monotonic() - waited
            which = response.WhichOneof("message")
            if which == "opened":
                o = response.opened
                self.session = Session.from_proto(o.session)
                if not self.session.spec.adaptive:
                    raise ValueError(
                        f"session {self.sid!r} declares {self.session.spec.family} patterns, "
                        "not an adaptive family"
                    )
                if self.measured > o.issued_rows:
                    raise HelmholtzError(
                        f"{self.operation}: the server issued {o.issued_rows} rows, the rig "
                        f"measured {self.measured}"
                    )
                opened = True
                self._acknowledged(o.committed_rows)
                # Measured rows the server does not hold yet: send them again.
                self._send(outbox, self.unacked)
            elif which == "batch":
                self._batch(response.batch)
            elif which == "ack":
                a = response.ack
                self._acknowledged(a.committed_rows)
                self.report.rows_written += a.rows_written
                self.report.rows_matched += a.rows_skipped
            elif which == "done":
                d = response.done
                self.report.rows = d.rows
                self.report.reason = _STOP_REASONS.get(d.reason, "unknown")
                self.report.estimated_error = (
                    d.estimated_error if d.HasField("estimated_error") else None
                )
                self._acknowledged(d.rows)
                return True

    def run(self) -> AdaptiveReport:
        started = time.monotonic()
        progress_at = started
        attempt = 0
        resync_used = False
        while True:
            before = self.committed
            try:
                if self._stream():
                    break
            except _StreamEnded as ended:
                err = ended.error
                if err.code == grpc.StatusCode.UNAVAILABLE:
                    self.client._reset_channel()
                if self.committed > before:
                    progress_at, attempt, resync_used = time.monotonic(), 0, False
                d = disposition(err.code)
                fatal = d is Disposition.FATAL or (d is Disposition.RESYNC_ONCE and resync_used)
                gave_up = time.monotonic() - progress_at >= self.retry_for
                if fatal or gave_up:
                    self._finish(started)
                    raise AcquireError(
                        err.operation,
                        err.code,
                        err.message,
                        committed_rows=self.committed,
                        report=self.report,
                        gave_up=gave_up and not fatal,
                    ) from None
                if d is Disposition.RESYNC_ONCE:
                    resync_used = True
                self.report.last_error = str(err)
                remaining = self.retry_for - (time.monotonic() - progress_at)
                time.sleep(max(0.0, min(self.policy.backoff.delay(attempt), remaining)))
                attempt += 1
                self.report.reconnects += 1
        self._finish(started)
        return self.report

    def _finish(self, started: float) -> None:
        self.report.indices = [n for _, indices in self.batches for n in indices]
        self.report.batches = len(self.batches)
        self.report.seconds = time.monotonic() - started
