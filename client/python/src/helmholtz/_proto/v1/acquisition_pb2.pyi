from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class PatternFamily(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    PATTERN_FAMILY_UNSPECIFIED: _ClassVar[PatternFamily]
    PATTERN_FAMILY_RASTER: _ClassVar[PatternFamily]
    PATTERN_FAMILY_BERNOULLI: _ClassVar[PatternFamily]
    PATTERN_FAMILY_HADAMARD: _ClassVar[PatternFamily]
    PATTERN_FAMILY_SPECKLE: _ClassVar[PatternFamily]
    PATTERN_FAMILY_ADAPTIVE_HAAR: _ClassVar[PatternFamily]
    PATTERN_FAMILY_ADAPTIVE_HADAMARD: _ClassVar[PatternFamily]

class HadamardOrdering(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    HADAMARD_ORDERING_UNSPECIFIED: _ClassVar[HadamardOrdering]
    HADAMARD_ORDERING_NATURAL: _ClassVar[HadamardOrdering]
    HADAMARD_ORDERING_SEQUENCY: _ClassVar[HadamardOrdering]
    HADAMARD_ORDERING_ZIGZAG: _ClassVar[HadamardOrdering]
    HADAMARD_ORDERING_RUSSIAN_DOLL: _ClassVar[HadamardOrdering]
    HADAMARD_ORDERING_CAKE_CUTTING: _ClassVar[HadamardOrdering]

class AdaptiveFrames(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ADAPTIVE_FRAMES_UNSPECIFIED: _ClassVar[AdaptiveFrames]
    ADAPTIVE_FRAMES_PAIRS: _ClassVar[AdaptiveFrames]
    ADAPTIVE_FRAMES_SINGLE: _ClassVar[AdaptiveFrames]

class AdaptiveErrorEstimate(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ADAPTIVE_ERROR_ESTIMATE_UNSPECIFIED: _ClassVar[AdaptiveErrorEstimate]
    ADAPTIVE_ERROR_ESTIMATE_PREDICTION: _ClassVar[AdaptiveErrorEstimate]
    ADAPTIVE_ERROR_ESTIMATE_MEASURED: _ClassVar[AdaptiveErrorEstimate]

class SampleFormat(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SAMPLE_FORMAT_UNSPECIFIED: _ClassVar[SampleFormat]
    SAMPLE_FORMAT_F64: _ClassVar[SampleFormat]
    SAMPLE_FORMAT_F32: _ClassVar[SampleFormat]
    SAMPLE_FORMAT_U16: _ClassVar[SampleFormat]

class SessionState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SESSION_STATE_UNSPECIFIED: _ClassVar[SessionState]
    SESSION_STATE_OPEN: _ClassVar[SessionState]
    SESSION_STATE_FINISHED: _ClassVar[SessionState]

class AdaptiveStop(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ADAPTIVE_STOP_UNSPECIFIED: _ClassVar[AdaptiveStop]
    ADAPTIVE_STOP_BUDGET: _ClassVar[AdaptiveStop]
    ADAPTIVE_STOP_TARGET_ERROR: _ClassVar[AdaptiveStop]
    ADAPTIVE_STOP_FINISHED: _ClassVar[AdaptiveStop]
PATTERN_FAMILY_UNSPECIFIED: PatternFamily
PATTERN_FAMILY_RASTER: PatternFamily
PATTERN_FAMILY_BERNOULLI: PatternFamily
PATTERN_FAMILY_HADAMARD: PatternFamily
PATTERN_FAMILY_SPECKLE: PatternFamily
PATTERN_FAMILY_ADAPTIVE_HAAR: PatternFamily
PATTERN_FAMILY_ADAPTIVE_HADAMARD: PatternFamily
HADAMARD_ORDERING_UNSPECIFIED: HadamardOrdering
HADAMARD_ORDERING_NATURAL: HadamardOrdering
HADAMARD_ORDERING_SEQUENCY: HadamardOrdering
HADAMARD_ORDERING_ZIGZAG: HadamardOrdering
HADAMARD_ORDERING_RUSSIAN_DOLL: HadamardOrdering
HADAMARD_ORDERING_CAKE_CUTTING: HadamardOrdering
ADAPTIVE_FRAMES_UNSPECIFIED: AdaptiveFrames
ADAPTIVE_FRAMES_PAIRS: AdaptiveFrames
ADAPTIVE_FRAMES_SINGLE: AdaptiveFrames
ADAPTIVE_ERROR_ESTIMATE_UNSPECIFIED: AdaptiveErrorEstimate
ADAPTIVE_ERROR_ESTIMATE_PREDICTION: AdaptiveErrorEstimate
ADAPTIVE_ERROR_ESTIMATE_MEASURED: AdaptiveErrorEstimate
SAMPLE_FORMAT_UNSPECIFIED: SampleFormat
SAMPLE_FORMAT_F64: SampleFormat
SAMPLE_FORMAT_F32: SampleFormat
SAMPLE_FORMAT_U16: SampleFormat
SESSION_STATE_UNSPECIFIED: SessionState
SESSION_STATE_OPEN: SessionState
SESSION_STATE_FINISHED: SessionState
ADAPTIVE_STOP_UNSPECIFIED: AdaptiveStop
ADAPTIVE_STOP_BUDGET: AdaptiveStop
ADAPTIVE_STOP_TARGET_ERROR: AdaptiveStop
ADAPTIVE_STOP_FINISHED: AdaptiveStop

class RasterParams(_message.Message):
    __slots__ = ("block", "scans")
    BLOCK_FIELD_NUMBER: _ClassVar[int]
    SCANS_FIELD_NUMBER: _ClassVar[int]
    block: int
    scans: int
    def __init__(self, block: _Optional[int] = ..., scans: _Optional[int] = ...) -> None: ...

class BernoulliParams(_message.Message):
    __slots__ = ("fill",)
    FILL_FIELD_NUMBER: _ClassVar[int]
    fill: float
    def __init__(self, fill: _Optional[float] = ...) -> None: ...

class HadamardParams(_message.Message):
    __slots__ = ("ordering",)
    ORDERING_FIELD_NUMBER: _ClassVar[int]
    ordering: HadamardOrdering
    def __init__(self, ordering: _Optional[_Union[HadamardOrdering, str]] = ...) -> None: ...

class SpeckleParams(_message.Message):
    __slots__ = ("grain",)
    GRAIN_FIELD_NUMBER: _ClassVar[int]
    grain: int
    def __init__(self, grain: _Optional[int] = ...) -> None: ...

class AdaptiveParams(_message.Message):
    __slots__ = ("batch", "target_error", "persistence", "error_estimate", "frames")
    BATCH_FIELD_NUMBER: _ClassVar[int]
    TARGET_ERROR_FIELD_NUMBER: _ClassVar[int]
    PERSISTENCE_FIELD_NUMBER: _ClassVar[int]
    ERROR_ESTIMATE_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    batch: int
    target_error: float
    persistence: float
    error_estimate: AdaptiveErrorEstimate
    frames: AdaptiveFrames
    def __init__(self, batch: _Optional[int] = ..., target_error: _Optional[float] = ..., persistence: _Optional[float] = ..., error_estimate: _Optional[_Union[AdaptiveErrorEstimate, str]] = ..., frames: _Optional[_Union[AdaptiveFrames, str]] = ...) -> None: ...

class PatternSpec(_message.Message):
    __slots__ = ("family", "width", "height", "count", "seed", "raster", "bernoulli", "hadamard", "speckle", "adaptive")
    FAMILY_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    COUNT_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    RASTER_FIELD_NUMBER: _ClassVar[int]
    BERNOULLI_FIELD_NUMBER: _ClassVar[int]
    HADAMARD_FIELD_NUMBER: _ClassVar[int]
    SPECKLE_FIELD_NUMBER: _ClassVar[int]
    ADAPTIVE_FIELD_NUMBER: _ClassVar[int]
    family: PatternFamily
    width: int
    height: int
    count: int
    seed: int
    raster: RasterParams
    bernoulli: BernoulliParams
    hadamard: HadamardParams
    speckle: SpeckleParams
    adaptive: AdaptiveParams
    def __init__(self, family: _Optional[_Union[PatternFamily, str]] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., count: _Optional[int] = ..., seed: _Optional[int] = ..., raster: _Optional[_Union[RasterParams, _Mapping]] = ..., bernoulli: _Optional[_Union[BernoulliParams, _Mapping]] = ..., hadamard: _Optional[_Union[HadamardParams, _Mapping]] = ..., speckle: _Optional[_Union[SpeckleParams, _Mapping]] = ..., adaptive: _Optional[_Union[AdaptiveParams, _Mapping]] = ...) -> None: ...

class CameraLayout(_message.Message):
    __slots__ = ("width", "height", "format")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    format: SampleFormat
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., format: _Optional[_Union[SampleFormat, str]] = ...) -> None: ...

class Direction(_message.Message):
    __slots__ = ("x", "y", "z")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class DetectorLayout(_message.Message):
    __slots__ = ("channels", "directions", "camera")
    CHANNELS_FIELD_NUMBER: _ClassVar[int]
    DIRECTIONS_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    channels: _containers.RepeatedScalarFieldContainer[str]
    directions: _containers.RepeatedCompositeFieldContainer[Direction]
    camera: CameraLayout
    def __init__(self, channels: _Optional[_Iterable[str]] = ..., directions: _Optional[_Iterable[_Union[Direction, _Mapping]]] = ..., camera: _Optional[_Union[CameraLayout, _Mapping]] = ...) -> None: ...

class GroundTruth(_message.Message):
    __slots__ = ("width", "height", "transport")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    TRANSPORT_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    transport: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., transport: _Optional[_Iterable[float]] = ...) -> None: ...

class Session(_message.Message):
    __slots__ = ("session_id", "rig", "patterns", "detector", "metadata", "committed_rows", "expected_rows", "state", "created_unix_ms", "has_ground_truth")
    class MetadataEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    RIG_FIELD_NUMBER: _ClassVar[int]
    PATTERNS_FIELD_NUMBER: _ClassVar[int]
    DETECTOR_FIELD_NUMBER: _ClassVar[int]
    METADATA_FIELD_NUMBER: _ClassVar[int]
    COMMITTED_ROWS_FIELD_NUMBER: _ClassVar[int]
    EXPECTED_ROWS_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    CREATED_UNIX_MS_FIELD_NUMBER: _ClassVar[int]
    HAS_GROUND_TRUTH_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    rig: str
    patterns: PatternSpec
    detector: DetectorLayout
    metadata: _containers.ScalarMap[str, str]
    committed_rows: int
    expected_rows: int
    state: SessionState
    created_unix_ms: int
    has_ground_truth: bool
    def __init__(self, session_id: _Optional[str] = ..., rig: _Optional[str] = ..., patterns: _Optional[_Union[PatternSpec, _Mapping]] = ..., detector: _Optional[_Union[DetectorLayout, _Mapping]] = ..., metadata: _Optional[_Mapping[str, str]] = ..., committed_rows: _Optional[int] = ..., expected_rows: _Optional[int] = ..., state: _Optional[_Union[SessionState, str]] = ..., created_unix_ms: _Optional[int] = ..., has_ground_truth: _Optional[bool] = ...) -> None: ...

class CreateSessionRequest(_message.Message):
    __slots__ = ("session_id", "rig", "patterns", "detector", "metadata", "ground_truth")
    class MetadataEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    RIG_FIELD_NUMBER: _ClassVar[int]
    PATTERNS_FIELD_NUMBER: _ClassVar[int]
    DETECTOR_FIELD_NUMBER: _ClassVar[int]
    METADATA_FIELD_NUMBER: _ClassVar[int]
    GROUND_TRUTH_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    rig: str
    patterns: PatternSpec
    detector: DetectorLayout
    metadata: _containers.ScalarMap[str, str]
    ground_truth: GroundTruth
    def __init__(self, session_id: _Optional[str] = ..., rig: _Optional[str] = ..., patterns: _Optional[_Union[PatternSpec, _Mapping]] = ..., detector: _Optional[_Union[DetectorLayout, _Mapping]] = ..., metadata: _Optional[_Mapping[str, str]] = ..., ground_truth: _Optional[_Union[GroundTruth, _Mapping]] = ...) -> None: ...

class CreateSessionResponse(_message.Message):
    __slots__ = ("session", "created")
    SESSION_FIELD_NUMBER: _ClassVar[int]
    CREATED_FIELD_NUMBER: _ClassVar[int]
    session: Session
    created: bool
    def __init__(self, session: _Optional[_Union[Session, _Mapping]] = ..., created: _Optional[bool] = ...) -> None: ...

class MeasurementChunk(_message.Message):
    __slots__ = ("session_id", "start_row", "channels", "values_f64le", "crc32c", "values_f32le", "values_u16le")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    START_ROW_FIELD_NUMBER: _ClassVar[int]
    CHANNELS_FIELD_NUMBER: _ClassVar[int]
    VALUES_F64LE_FIELD_NUMBER: _ClassVar[int]
    CRC32C_FIELD_NUMBER: _ClassVar[int]
    VALUES_F32LE_FIELD_NUMBER: _ClassVar[int]
    VALUES_U16LE_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    start_row: int
    channels: int
    values_f64le: bytes
    crc32c: int
    values_f32le: bytes
    values_u16le: bytes
    def __init__(self, session_id: _Optional[str] = ..., start_row: _Optional[int] = ..., channels: _Optional[int] = ..., values_f64le: _Optional[bytes] = ..., crc32c: _Optional[int] = ..., values_f32le: _Optional[bytes] = ..., values_u16le: _Optional[bytes] = ...) -> None: ...

class UploadResponse(_message.Message):
    __slots__ = ("committed_rows", "rows_written", "rows_skipped")
    COMMITTED_ROWS_FIELD_NUMBER: _ClassVar[int]
    ROWS_WRITTEN_FIELD_NUMBER: _ClassVar[int]
    ROWS_SKIPPED_FIELD_NUMBER: _ClassVar[int]
    committed_rows: int
    rows_written: int
    rows_skipped: int
    def __init__(self, committed_rows: _Optional[int] = ..., rows_written: _Optional[int] = ..., rows_skipped: _Optional[int] = ...) -> None: ...

class SessionRef(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class UploadStatus(_message.Message):
    __slots__ = ("session_id", "committed_rows", "expected_rows", "state")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    COMMITTED_ROWS_FIELD_NUMBER: _ClassVar[int]
    EXPECTED_ROWS_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    committed_rows: int
    expected_rows: int
    state: SessionState
    def __init__(self, session_id: _Optional[str] = ..., committed_rows: _Optional[int] = ..., expected_rows: _Optional[int] = ..., state: _Optional[_Union[SessionState, str]] = ...) -> None: ...

class ReconstructionRequest(_message.Message):
    __slots__ = ("session_id", "method", "params_json")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    METHOD_FIELD_NUMBER: _ClassVar[int]
    PARAMS_JSON_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    method: str
    params_json: str
    def __init__(self, session_id: _Optional[str] = ..., method: _Optional[str] = ..., params_json: _Optional[str] = ...) -> None: ...

class ReconstructionRef(_message.Message):
    __slots__ = ("reconstruction_id",)
    RECONSTRUCTION_ID_FIELD_NUMBER: _ClassVar[int]
    reconstruction_id: int
    def __init__(self, reconstruction_id: _Optional[int] = ...) -> None: ...

class Reconstruction(_message.Message):
    __slots__ = ("reconstruction_id", "session_id", "method", "params_json", "state", "progress", "rows", "seconds", "error", "report_json", "warnings")
    RECONSTRUCTION_ID_FIELD_NUMBER: _ClassVar[int]
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    METHOD_FIELD_NUMBER: _ClassVar[int]
    PARAMS_JSON_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    PROGRESS_FIELD_NUMBER: _ClassVar[int]
    ROWS_FIELD_NUMBER: _ClassVar[int]
    SECONDS_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    REPORT_JSON_FIELD_NUMBER: _ClassVar[int]
    WARNINGS_FIELD_NUMBER: _ClassVar[int]
    reconstruction_id: int
    session_id: str
    method: str
    params_json: str
    state: str
    progress: float
    rows: int
    seconds: float
    error: str
    report_json: str
    warnings: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, reconstruction_id: _Optional[int] = ..., session_id: _Optional[str] = ..., method: _Optional[str] = ..., params_json: _Optional[str] = ..., state: _Optional[str] = ..., progress: _Optional[float] = ..., rows: _Optional[int] = ..., seconds: _Optional[float] = ..., error: _Optional[str] = ..., report_json: _Optional[str] = ..., warnings: _Optional[_Iterable[str]] = ...) -> None: ...

class PreviewRequest(_message.Message):
    __slots__ = ("session_id", "channel", "every_rows", "every_ms")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    CHANNEL_FIELD_NUMBER: _ClassVar[int]
    EVERY_ROWS_FIELD_NUMBER: _ClassVar[int]
    EVERY_MS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    channel: str
    every_rows: int
    every_ms: int
    def __init__(self, session_id: _Optional[str] = ..., channel: _Optional[str] = ..., every_rows: _Optional[int] = ..., every_ms: _Optional[int] = ...) -> None: ...

class PreviewFrame(_message.Message):
    __slots__ = ("session_id", "channel", "rows", "expected_rows", "width", "height", "method", "values", "final")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    CHANNEL_FIELD_NUMBER: _ClassVar[int]
    ROWS_FIELD_NUMBER: _ClassVar[int]
    EXPECTED_ROWS_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    METHOD_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    FINAL_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    channel: str
    rows: int
    expected_rows: int
    width: int
    height: int
    method: str
    values: _containers.RepeatedScalarFieldContainer[float]
    final: bool
    def __init__(self, session_id: _Optional[str] = ..., channel: _Optional[str] = ..., rows: _Optional[int] = ..., expected_rows: _Optional[int] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., method: _Optional[str] = ..., values: _Optional[_Iterable[float]] = ..., final: _Optional[bool] = ...) -> None: ...

class AcquireOpen(_message.Message):
    __slots__ = ("session_id", "measured_rows", "known_batches")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    MEASURED_ROWS_FIELD_NUMBER: _ClassVar[int]
    KNOWN_BATCHES_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    measured_rows: int
    known_batches: int
    def __init__(self, session_id: _Optional[str] = ..., measured_rows: _Optional[int] = ..., known_batches: _Optional[int] = ...) -> None: ...

class AcquireRequest(_message.Message):
    __slots__ = ("open", "chunk")
    OPEN_FIELD_NUMBER: _ClassVar[int]
    CHUNK_FIELD_NUMBER: _ClassVar[int]
    open: AcquireOpen
    chunk: MeasurementChunk
    def __init__(self, open: _Optional[_Union[AcquireOpen, _Mapping]] = ..., chunk: _Optional[_Union[MeasurementChunk, _Mapping]] = ...) -> None: ...

class AcquireOpened(_message.Message):
    __slots__ = ("session", "committed_rows", "issued_rows")
    SESSION_FIELD_NUMBER: _ClassVar[int]
    COMMITTED_ROWS_FIELD_NUMBER: _ClassVar[int]
    ISSUED_ROWS_FIELD_NUMBER: _ClassVar[int]
    session: Session
    committed_rows: int
    issued_rows: int
    def __init__(self, session: _Optional[_Union[Session, _Mapping]] = ..., committed_rows: _Optional[int] = ..., issued_rows: _Optional[int] = ...) -> None: ...

class AdaptiveBatch(_message.Message):
    __slots__ = ("number", "first_row", "indices")
    NUMBER_FIELD_NUMBER: _ClassVar[int]
    FIRST_ROW_FIELD_NUMBER: _ClassVar[int]
    INDICES_FIELD_NUMBER: _ClassVar[int]
    number: int
    first_row: int
    indices: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, number: _Optional[int] = ..., first_row: _Optional[int] = ..., indices: _Optional[_Iterable[int]] = ...) -> None: ...

class AcquireAck(_message.Message):
    __slots__ = ("committed_rows", "rows_written", "rows_skipped")
    COMMITTED_ROWS_FIELD_NUMBER: _ClassVar[int]
    ROWS_WRITTEN_FIELD_NUMBER: _ClassVar[int]
    ROWS_SKIPPED_FIELD_NUMBER: _ClassVar[int]
    committed_rows: int
    rows_written: int
    rows_skipped: int
    def __init__(self, committed_rows: _Optional[int] = ..., rows_written: _Optional[int] = ..., rows_skipped: _Optional[int] = ...) -> None: ...

class AcquireDone(_message.Message):
    __slots__ = ("reason", "rows", "estimated_error")
    REASON_FIELD_NUMBER: _ClassVar[int]
    ROWS_FIELD_NUMBER: _ClassVar[int]
    ESTIMATED_ERROR_FIELD_NUMBER: _ClassVar[int]
    reason: AdaptiveStop
    rows: int
    estimated_error: float
    def __init__(self, reason: _Optional[_Union[AdaptiveStop, str]] = ..., rows: _Optional[int] = ..., estimated_error: _Optional[float] = ...) -> None: ...

class AcquireResponse(_message.Message):
    __slots__ = ("opened", "batch", "ack", "done")
    OPENED_FIELD_NUMBER: _ClassVar[int]
    BATCH_FIELD_NUMBER: _ClassVar[int]
    ACK_FIELD_NUMBER: _ClassVar[int]
    DONE_FIELD_NUMBER: _ClassVar[int]
    opened: AcquireOpened
    batch: AdaptiveBatch
    ack: AcquireAck
    done: AcquireDone
    def __init__(self, opened: _Optional[_Union[AcquireOpened, _Mapping]] = ..., batch: _Optional[_Union[AdaptiveBatch, _Mapping]] = ..., ack: _Optional[_Union[AcquireAck, _Mapping]] = ..., done: _Optional[_Union[AcquireDone, _Mapping]] = ...) -> None: ...
