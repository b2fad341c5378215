"""Helmholtz from Python: dual photography and computational ghost imaging with numpy.

>>> import helmholtz as hz
>>> client = hz.Client("http://127.0.0.1:8080", token="hz_...")
>>> spec = hz.PatternSpec.hadamard(16, 16, ordering="sequency")
>>> frames = hz.patterns(spec)                      # what the projector shows, (512, 16, 16)
>>> session = client.create_session("run-1", spec, channels=["bucket"])
>>> client.upload(session, buckets)                 # ndarray (512, 1), CRC-32C, resumable
>>> rec = client.wait(client.reconstruct(session, "auto"), progress=print)
>>> image = client.dual_image(rec)                  # float32 (16, 16)

An adaptive session (``hz.PatternSpec.adaptive_haar(side, count)``) lets the server choose the
patterns as the values arrive: ``client.acquire(session, measure)`` shows each batch through
``measure(patterns) -> rows`` until the server ends it (an :class:`AdaptiveReport`).

See the README for a walkthrough. Sessions and uploads go over gRPC (the rig's side);
reconstructions and images over REST (the reader's side). Errors are :class:`HelmholtzError`
subclasses: :class:`RpcError` carries the gRPC status code and message, :class:`ApiError`
the server's problem+json.
"""

from .client import (
    DEFAULT_CHUNK_BYTES,
    AdaptiveReport,
    MAX_CHUNK_BYTES,
    STREAM_BYTES,
    WRITER_HEADER,
    Camera,
    Client,
    PreviewFrame,
    Reconstruction,
    Session,
    UploadReport,
    UploadStatus,
    new_writer_id,
)
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
from .patterns import (
    PatternGenerator,
    adaptive_patterns,
    basis_functions,
    basis_gains,
    packed_bits,
    pattern,
    patterns,
    speckle_levels,
)
from .retry import Backoff, RetryPolicy
from .spec import ADAPTIVE_FAMILIES, ADAPTIVE_FRAMES, FAMILIES, ORDERINGS, PatternSpec, SpecError

__version__ = "0.1.0"

__all__ = [
    "ADAPTIVE_FAMILIES",
    "ADAPTIVE_FRAMES",
    "AcquireError",
    "AdaptiveReport",
    "ApiError",
    "Backoff",
    "Camera",
    "Client",
    "DEFAULT_CHUNK_BYTES",
    "FAMILIES",
    "HelmholtzError",
    "MAX_CHUNK_BYTES",
    "ORDERINGS",
    "PatternGenerator",
    "PatternSpec",
    "PreviewFrame",
    "Reconstruction",
    "ReconstructionFailed",
    "RetryPolicy",
    "RpcError",
    "STREAM_BYTES",
    "ServerUnreachable",
    "Session",
    "SpecError",
    "UploadError",
    "UploadReport",
    "UploadStatus",
    "WRITER_HEADER",
    "__version__",
    "adaptive_patterns",
    "basis_functions",
    "basis_gains",
    "crc32c",
    "new_writer_id",
    "packed_bits",
    "pattern",
    "patterns",
    "speckle_levels",
]
