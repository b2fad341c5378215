"""Pattern specs: what a session declares instead of pattern pixels (proto/PATTERNS.md).

A :class:`PatternSpec` is the family, size, count, seed and the family's parameter. It converts
to and from the JSON form (the REST API's ``patterns``) and the protobuf form (gRPC), and
:meth:`PatternSpec.canonical` validates it as PATTERNS.md says (defaults filled in, the
Bernoulli fill quantised to a multiple of 2^-16), naming the offending field on error.

The adaptive families (``adaptive_haar``, ``adaptive_hadamard``) declare a basis, a square
power-of-two grid, a frame budget (``count``) and a stopping rule (``batch``, ``target_error``);
which basis function each split pair shows is chosen by the server during the session (gRPC
``Acquire``, :meth:`helmholtz.Client.acquire`), so their patterns need those indices
(:func:`helmholtz.adaptive_patterns`). ``adaptive_haar`` may also show its indices as single
frames (``frames="single"``, PATTERNS.md "Single frames"): index 0 as its pair, every other
index its P+ alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from fractions import Fraction
from typing import Any, Mapping, Optional

from ._proto.v1 import acquisition_pb2 as pb

__all__ = [
    "PatternSpec",
    "SpecError",
    "FAMILIES",
    "ADAPTIVE_FAMILIES",
    "ADAPTIVE_FRAMES",
    "ERROR_ESTIMATES",
    "HAAR_PERSISTENCE",
    "HADAMARD_PERSISTENCE",
    "ORDERINGS",
    "MAX_SIDE",
    "MAX_PIXELS",
    "MAX_COUNT",
    "FILL_BITS",
    "fill_quantum",
]

MAX_SIDE = 4096
MAX_PIXELS = 1 << 22
MAX_COUNT = 10_000_000
FILL_BITS = 16

#: PATTERNS.md's adaptive families: the server chooses the basis function of each split pair.
ADAPTIVE_FAMILIES = ("adaptive_haar", "adaptive_hadamard")
FAMILIES = ("raster", "bernoulli", "hadamard", "speckle", *ADAPTIVE_FAMILIES)
#: The adaptive families' ``persistence`` when a declaration leaves it out (PATTERNS.md).
HAAR_PERSISTENCE = 0.5
HADAMARD_PERSISTENCE = 0.0
#: What an adaptive planner's ``target_error`` compares with (PATTERNS.md, "Error estimate"):
#: ``measured`` (the default) or ``prediction`` (sessions stored before 2026-11-29).
ERROR_ESTIMATES = ("measured", "prediction")
_ESTIMATE_TO_PB = {
    "prediction": pb.ADAPTIVE_ERROR_ESTIMATE_PREDICTION,
    "measured": pb.ADAPTIVE_ERROR_ESTIMATE_MEASURED,
}
_PB_TO_ESTIMATE = {v: k for k, v in _ESTIMATE_TO_PB.items()}
_PB_TO_ESTIMATE[pb.ADAPTIVE_ERROR_ESTIMATE_UNSPECIFIED] = "measured"
#: How an adaptive session shows its indices (PATTERNS.md, "Single frames"): ``pairs`` (the
#: default, every index a split pair P+, P-) or ``single`` (adaptive_haar only: index 0 as its
#: pair, every other index its P+ alone).
ADAPTIVE_FRAMES = ("pairs", "single")
_PB_TO_FRAMES = {
    pb.ADAPTIVE_FRAMES_UNSPECIFIED: "pairs",
    pb.ADAPTIVE_FRAMES_PAIRS: "pairs",
    pb.ADAPTIVE_FRAMES_SINGLE: "single",
}
ORDERINGS = ("natural", "sequency", "zigzag", "russian_doll", "cake_cutting")

_FAMILY_TO_PB = {
    "raster": pb.PATTERN_FAMILY_RASTER,
    "bernoulli": pb.PATTERN_FAMILY_BERNOULLI,
    "hadamard": pb.PATTERN_FAMILY_HADAMARD,
    "speckle": pb.PATTERN_FAMILY_SPECKLE,
    "adaptive_haar": pb.PATTERN_FAMILY_ADAPTIVE_HAAR,
    "adaptive_hadamard": pb.PATTERN_FAMILY_ADAPTIVE_HADAMARD,
}
_PB_TO_FAMILY = {v: k for k, v in _FAMILY_TO_PB.items()}
_ORDERING_TO_PB = {
    "natural": pb.HADAMARD_ORDERING_NATURAL,
    "sequency": pb.HADAMARD_ORDERING_SEQUENCY,
    "zigzag": pb.HADAMARD_ORDERING_ZIGZAG,
    "russian_doll": pb.HADAMARD_ORDERING_RUSSIAN_DOLL,
    "cake_cutting": pb.HADAMARD_ORDERING_CAKE_CUTTING,
}
_PB_TO_ORDERING = {v: k for k, v in _ORDERING_TO_PB.items()}
_PB_TO_ORDERING[pb.HADAMARD_ORDERING_UNSPECIFIED] = "natural"

_PARAMS = {"raster": "block", "bernoulli": "fill", "hadamard": "ordering", "speckle": "grain"}
#: The protobuf ``params`` oneof member of each family.
_ONEOF = {**{f: f for f in _PARAMS}, "adaptive_haar": "adaptive", "adaptive_hadamard": "adaptive"}


class SpecError(ValueError):
    """A spec PATTERNS.md refuses; ``field`` names the offending field (as the server would)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


def fill_quantum(fill: float) -> int:
    """``Q = round_half_away_from_zero(fill * 2^16)`` on the exact binary64 value, clamped to
    ``1 ..= 65535``."""
    x = Fraction(fill) * (1 << FILL_BITS)
    q = math.floor(x)
    if x - q >= Fraction(1, 2):
        q += 1
    return min(max(q, 1), (1 << FILL_BITS) - 1)


def _is_uint(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


@dataclass(frozen=True)
class PatternSpec:
    """A session's illumination patterns, declared by spec (PATTERNS.md).

    Build one with the family constructors (:meth:`raster`, :meth:`bernoulli`,
    :meth:`hadamard`, :meth:`speckle`, :meth:`adaptive_haar`, :meth:`adaptive_hadamard`) or
    directly; ``None`` parameters take the family's defaults. Only the parameter(s) of the
    spec's own family may be set.

    Attributes:
        family: one of :data:`FAMILIES`.
        width, height: the projector grid (pixels).
        count: patterns (frames) in the session; for Hadamard even, at most ``2 * width * height``;
            for the adaptive families the frame budget (even, at most ``2 * width * height``;
            with single frames ``2 ..= width * height + 1``, odd or even).
        seed: random stream of bernoulli and speckle (ignored by the others).
        block, scans: raster block side and declared repeats of the scan.
        fill: bernoulli on-probability in (0, 1), quantised to a multiple of 2^-16.
        ordering: hadamard row ordering (one of :data:`ORDERINGS`).
        grain: speckle cell side.
        batch: adaptive families: split pairs (single frames: indices) per batch, 0 = sized by
            the server.
        target_error: adaptive families: stop once the server's estimated relative error is
            below this, 0.0 = spend the whole budget.
        persistence: adaptive families: how much a measured detail pulls its finer children
            forward in the planner's ranking (PATTERNS.md); ``None`` = the family's default
            (:data:`HAAR_PERSISTENCE`, :data:`HADAMARD_PERSISTENCE`).
        error_estimate: adaptive families: what ``target_error`` compares with, one of
            :data:`ERROR_ESTIMATES`; ``None`` = ``measured`` (the prediction plus the measured
            prediction miss and noise, PATTERNS.md "Error estimate").
        frames: adaptive_haar: ``"single"`` shows index 0 as its pair (all on, all off) and
            every other index as its P+ alone, one frame (PATTERNS.md "Single frames");
            ``None`` = pairs (every index a split pair, two frames). A canonical spec holds
            ``None`` for pairs (``"pairs"`` is accepted and canonicalised to ``None``).
    """

    family: str
    width: int
    height: int
    count: int
    seed: int = 0
    block: Optional[int] = None
    scans: Optional[int] = None
    fill: Optional[float] = None
    ordering: Optional[str] = None
    grain: Optional[int] = None
    batch: Optional[int] = None
    target_error: Optional[float] = None
    persistence: Optional[float] = None
    error_estimate: Optional[str] = None
    frames: Optional[str] = None

    # -- constructors ---------------------------------------------------------------------
    @classmethod
    def raster(
        cls, width: int, height: int, count: int, *, block: int = 1, scans: int = 1
    ) -> "PatternSpec":
        """One ``block x block`` block on at a time, scanned row by row (``scans`` repeats)."""
        return cls("raster", width, height, count, block=block, scans=scans).canonical()

    @classmethod
    def bernoulli(
        cls, width: int, height: int, count: int, *, fill: float = 0.5, seed: int = 0
    ) -> "PatternSpec":
        """Each pixel on with probability ``fill``, independently."""
        return cls("bernoulli", width, height, count, seed=seed, fill=fill).canonical()

    @classmethod
    def hadamard(
        cls, width: int, height: int, count: Optional[int] = None, *, ordering: str = "natural"
    ) -> "PatternSpec":
        """Walsh-Hadamard rows as split pairs P+, P-; ``count`` defaults to the complete set
        (``2 * width * height`` frames)."""
        if count is None:
            count = 2 * width * height
        return cls("hadamard", width, height, count, ordering=ordering).canonical()

    @classmethod
    def speckle(
        cls, width: int, height: int, count: int, *, grain: int = 1, seed: int = 0
    ) -> "PatternSpec":
        """Grey levels ``L / 2^24`` on cells of ``grain x grain`` pixels."""
        return cls("speckle", width, height, count, seed=seed, grain=grain).canonical()

    @classmethod
    def adaptive_haar(
        cls,
        side: int,
        count: Optional[int] = None,
        *,
        batch: int = 0,
        target_error: float = 0.0,
        persistence: Optional[float] = None,
        error_estimate: Optional[str] = None,
        frames: Optional[str] = None,
    ) -> "PatternSpec":
        """An adaptive session over the 2D Haar basis (Mallat layout) of a ``side x side`` grid
        (a power of two). ``count`` is the frame budget, two frames per split pair (default:
        the whole basis, ``2 * side * side``); ``batch`` split pairs per batch (0: the server
        sizes them); ``target_error`` > 0 stops early once the estimated error is below it;
        ``persistence`` weighs a measured detail in its children's ranking (default 0.5);
        ``error_estimate`` is what ``target_error`` compares with (default ``measured``).

        ``frames="single"`` shows one frame per index (PATTERNS.md "Single frames"): index 0
        as its pair (all on, all off: the light and the dark level), every other index its P+
        alone; ``count`` is then ``2 ..= side * side + 1`` (``count - 1`` indices; default the
        whole basis, ``side * side + 1``). ``None`` or ``"pairs"``: split pairs."""
        if count is None:
            count = side * side + 1 if frames == "single" else 2 * side * side
        return cls(
            "adaptive_haar",
            side,
            side,
            count,
            batch=batch,
            target_error=target_error,
            persistence=persistence,
            error_estimate=error_estimate,
            frames=frames,
        ).canonical()

    @classmethod
    def adaptive_hadamard(
        cls,
        side: int,
        count: Optional[int] = None,
        *,
        batch: int = 0,
        target_error: float = 0.0,
        persistence: Optional[float] = None,
        error_estimate: Optional[str] = None,
        frames: Optional[str] = None,
    ) -> "PatternSpec":
        """As :meth:`adaptive_haar`, over the Walsh-Hadamard basis (natural index);
        ``persistence`` defaults to 0. Always split pairs: ``frames="single"`` is refused
        (:class:`SpecError` on ``frames``; single frames need Haar's blocks)."""
        if count is None:
            count = 2 * side * side
        return cls(
            "adaptive_hadamard",
            side,
            side,
            count,
            batch=batch,
            target_error=target_error,
            persistence=persistence,
            error_estimate=error_estimate,
            frames=frames,
        ).canonical()

    # -- properties -----------------------------------------------------------------------
    @property
    def pixels(self) -> int:
        """``k = width * height``."""
        return self.width * self.height

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``: the shape of one pattern as an ndarray."""
        return (self.height, self.width)

    @property
    def binary(self) -> bool:
        """True for the 0/1 families (all but speckle)."""
        return self.family != "speckle"

    @property
    def adaptive(self) -> bool:
        """True for ``adaptive_haar`` and ``adaptive_hadamard``: the server chooses the basis
        function of each split pair during the session (:meth:`helmholtz.Client.acquire`)."""
        return self.family in ADAPTIVE_FAMILIES

    @property
    def single_frames(self) -> bool:
        """True for an adaptive spec showing single frames (``frames="single"``, PATTERNS.md
        "Single frames"): index 0 as its pair, every other index its P+ alone."""
        return self.adaptive and self.frames == "single"

    @property
    def adaptive_budget(self) -> int:
        """The most basis indices an adaptive spec's budget shows: ``count // 2`` split pairs,
        or with single frames ``count - 1`` (index 0 takes two frames).

        Raises:
            ValueError: not an adaptive spec.
        """
        self._need_adaptive()
        return self.count - 1 if self.single_frames else self.count // 2

    def adaptive_rows(self, indices: int) -> int:
        """Frames (rows) the first ``indices`` basis indices of an adaptive session take:
        ``2 * indices``, or with single frames ``R(j) = j + 1`` (``R(0) = 0``). A batch whose
        first index is the session's ``j``-th starts at row ``adaptive_rows(j)``.

        Raises:
            ValueError: not an adaptive spec.
        """
        self._need_adaptive()
        if not self.single_frames:
            return 2 * indices
        return indices + 1 if indices > 0 else 0

    def adaptive_indices_in(self, rows: int) -> int:
        """Basis indices whose frames all lie within the first ``rows`` frames (the inverse of
        :meth:`adaptive_rows`, rounding down).

        Raises:
            ValueError: not an adaptive spec.
        """
        self._need_adaptive()
        return max(rows - 1, 0) if self.single_frames else rows // 2

    def _need_adaptive(self) -> None:
        if not self.adaptive:
            raise ValueError(f"a {self.family} spec has no adaptive frame layout")

    # -- validation -----------------------------------------------------------------------
    def canonical(self) -> "PatternSpec":
        """This spec validated and canonicalised (defaults filled in, fill quantised).

        Raises:
            SpecError: naming the field PATTERNS.md refuses.
        """
        return PatternSpec.from_dict(self.to_dict(canonical=False))

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any]) -> "PatternSpec":
        """The canonical spec of a JSON-form mapping (``{"family": ..., "width": ...}``).

        Raises:
            SpecError: naming the offending field.
        """
        family = raw.get("family")
        if family not in FAMILIES:
            raise SpecError("family", f"unknown family {family!r}; one of {', '.join(FAMILIES)}")
        adaptive = family in ADAPTIVE_FAMILIES
        allowed = {"family", "width", "height", "count", "seed"}
        if adaptive:
            allowed |= {"batch", "target_error", "persistence", "error_estimate", "frames"}
        else:
            allowed.add(_PARAMS[family])
        if family == "raster":
            allowed.add("scans")
        for key in raw:
            if key not in allowed:
                raise SpecError(key, f"unknown field for a {family} spec")
        for key in ("width", "height", "count"):
            if key not in raw:
                raise SpecError(key, "is required")
        width, height, count = raw["width"], raw["height"], raw["count"]
        seed = raw.get("seed", 0)
        for key, v, top in (
            ("width", width, 2**32),
            ("height", height, 2**32),
            ("count", count, 2**64),
            ("seed", seed, 2**64),
        ):
            if not _is_uint(v) or v >= top:
                raise SpecError(key, f"must be an unsigned integer below 2^{top.bit_length() - 1}, got {v!r}")
        if not 1 <= width <= MAX_SIDE:
            raise SpecError("width", f"must be 1..={MAX_SIDE}, got {width}")
        if not 1 <= height <= MAX_SIDE:
            raise SpecError("height", f"must be 1..={MAX_SIDE}, got {height}")
        k = width * height
        if k > MAX_PIXELS:
            raise SpecError("width", f"{width}x{height} = {k} pixels; at most {MAX_PIXELS}")
        if not 1 <= count <= MAX_COUNT:
            raise SpecError("count", f"must be 1..={MAX_COUNT}, got {count}")
        out: dict[str, Any] = {"family": family}
        if adaptive:
            out.update(_adaptive_params(family, raw, width, height, count))
            out.update({"width": width, "height": height, "count": count, "seed": seed})
            return cls(**out)
        pname = _PARAMS[family]
        if family in ("raster", "speckle"):
            p = raw.get(pname, 1)
            if not _is_uint(p) or not 1 <= p <= max(width, height):
                raise SpecError(pname, f"must be 1..={max(width, height)}, got {p!r}")
            out[pname] = p
        elif family == "bernoulli":
            p = raw.get("fill", 0.5)
            if isinstance(p, bool) or not isinstance(p, (int, float)):
                raise SpecError("fill", f"must be a number, got {p!r}")
            p = float(p)
            if not 0.0 < p < 1.0:
                raise SpecError("fill", f"must be strictly between 0 and 1, got {p}")
            out["fill"] = fill_quantum(p) / (1 << FILL_BITS)
        else:
            p = raw.get("ordering", "natural")
            if p not in ORDERINGS:
                raise SpecError("ordering", f"unknown ordering {p!r}; one of {', '.join(ORDERINGS)}")
            if width & (width - 1):
                raise SpecError("width", f"must be a power of two for hadamard, got {width}")
            if height & (height - 1):
                raise SpecError("height", f"must be a power of two for hadamard, got {height}")
            if count % 2 or count > 2 * k:
                raise SpecError("count", f"must be even and at most 2 * width * height = {2 * k}")
            out["ordering"] = p
        if family == "raster":
            b = out["block"]
            blocks = -(-width // b) * -(-height // b)
            scans = raw.get("scans", 1)
            top = -(-MAX_COUNT // blocks)
            if not _is_uint(scans) or not 1 <= scans <= top:
                raise SpecError("scans", f"must be 1..={top}, got {scans!r}")
            if count > scans * blocks:
                raise SpecError(
                    "count",
                    f"{count} patterns but {scans} scan(s) of {blocks} blocks: declare scans to repeat",
                )
            out["scans"] = scans
        out.update({"width": width, "height": height, "count": count, "seed": seed})
        return cls(**out)

    def to_dict(self, canonical: bool = True) -> dict[str, Any]:
        """The JSON form, keys in the canonical order (canonicalised first unless told not)."""
        spec = self.canonical() if canonical else self
        out: dict[str, Any] = {"family": spec.family}
        for name in (
            "block",
            "scans",
            "fill",
            "ordering",
            "grain",
            "batch",
            "target_error",
            "persistence",
            "error_estimate",
            "frames",
        ):
            value = getattr(spec, name)
            if value is not None:
                out[name] = value
        out.update(
            {"width": spec.width, "height": spec.height, "count": spec.count, "seed": spec.seed}
        )
        return out

    # -- protobuf -------------------------------------------------------------------------
    def to_proto(self) -> pb.PatternSpec:
        """The ``helmholtz.v1.PatternSpec`` message of the canonical spec."""
        s = self.canonical()
        msg = pb.PatternSpec(
            family=_FAMILY_TO_PB[s.family],
            width=s.width,
            height=s.height,
            count=s.count,
            seed=s.seed,
        )
        if s.family == "raster":
            msg.raster.block = s.block or 1
            msg.raster.scans = s.scans or 1
        elif s.family == "bernoulli":
            msg.bernoulli.fill = float(s.fill if s.fill is not None else 0.5)
        elif s.family == "hadamard":
            msg.hadamard.ordering = _ORDERING_TO_PB[s.ordering or "natural"]
        elif s.adaptive:
            msg.adaptive.batch = s.batch or 0
            msg.adaptive.target_error = float(s.target_error or 0.0)
            msg.adaptive.persistence = float(s.persistence)
            msg.adaptive.error_estimate = _ESTIMATE_TO_PB[s.error_estimate]
            if s.frames == "single":
                # Pairs stay unset (0 = pairs): the message of every pairs spec is unchanged.
                msg.adaptive.frames = pb.ADAPTIVE_FRAMES_SINGLE
        else:
            msg.speckle.grain = s.grain or 1
        return msg

    @classmethod
    def from_proto(cls, msg: pb.PatternSpec) -> "PatternSpec":
        """The canonical spec of a protobuf message (proto3 zeros mean the defaults)."""
        family = _PB_TO_FAMILY.get(msg.family)
        if family is None:
            raise SpecError("family", f"unknown family {msg.family}")
        raw: dict[str, Any] = {
            "family": family,
            "width": msg.width,
            "height": msg.height,
            "count": msg.count,
            "seed": msg.seed,
        }
        which = msg.WhichOneof("params")
        if which is not None and which != _ONEOF[family]:
            raise SpecError("params", f"{which} parameters in a {family} spec")
        if family == "raster" and which:
            raw["block"] = msg.raster.block or 1
            raw["scans"] = msg.raster.scans or 1
        elif family == "bernoulli" and which and msg.bernoulli.HasField("fill"):
            raw["fill"] = msg.bernoulli.fill
        elif family == "hadamard" and which:
            raw["ordering"] = _PB_TO_ORDERING.get(msg.hadamard.ordering, "natural")
        elif family == "speckle" and which:
            raw["grain"] = msg.speckle.grain or 1
        elif family in ADAPTIVE_FAMILIES and which:
            raw["batch"] = msg.adaptive.batch
            raw["target_error"] = msg.adaptive.target_error
            if msg.adaptive.HasField("persistence"):
                raw["persistence"] = msg.adaptive.persistence
            estimate = _PB_TO_ESTIMATE.get(msg.adaptive.error_estimate)
            if estimate is None:
                raise SpecError(
                    "error_estimate", f"unknown AdaptiveErrorEstimate {msg.adaptive.error_estimate}"
                )
            raw["error_estimate"] = estimate
            frames = _PB_TO_FRAMES.get(msg.adaptive.frames)
            if frames is None:
                raise SpecError("frames", f"unknown AdaptiveFrames {msg.adaptive.frames}")
            raw["frames"] = frames
        return cls.from_dict(raw)

    def with_count(self, count: int) -> "PatternSpec":
        """The same spec with another count (patterns do not depend on the count)."""
        return replace(self, count=count).canonical()


def _adaptive_params(
    family: str, raw: Mapping[str, Any], width: int, height: int, count: int
) -> dict[str, Any]:
    """``batch``, ``target_error``, ``persistence``, ``error_estimate`` and ``frames`` of an
    adaptive spec, checked with its grid and budget (PATTERNS.md, adaptive families: the checks
    and their order are the server's). ``frames`` is ``"single"`` or None (pairs)."""
    frames = raw.get("frames", "pairs")
    if not isinstance(frames, str) or frames not in ADAPTIVE_FRAMES:
        raise SpecError("frames", f"unknown frames {frames!r}; one of {', '.join(ADAPTIVE_FRAMES)}")
    single = frames == "single"
    if single and family != "adaptive_haar":
        raise SpecError(
            "frames", "single frames are for adaptive_haar (a Walsh-Hadamard session shows pairs)"
        )
    if width & (width - 1):
        raise SpecError("width", f"{family} needs a power of two, got {width}")
    if height != width:
        raise SpecError(
            "height", f"{family} needs a square image (height = width = {width}), got {height}"
        )
    k = width * height
    if single:
        if not 2 <= count <= k + 1:
            raise SpecError(
                "count",
                f"{family} with single frames shows index 0 as two frames and every other index "
                f"as one: a budget of 2..={k + 1} frames (width * height + 1), got {count}",
            )
    elif count % 2 or count > 2 * k:
        raise SpecError(
            "count",
            f"{family} frames come in P+/P- pairs: an even budget up to 2 * width * height = "
            f"{2 * k}, got {count}",
        )
    batch = raw.get("batch", 0)
    if not _is_uint(batch) or batch >= 2**32:
        raise SpecError("batch", f"must be an unsigned integer below 2^32, got {batch!r}")
    if batch > k:
        raise SpecError("batch", f"must be 0 (automatic) or 1..={k} split pairs, got {batch}")
    target = _non_negative(raw, "target_error", 0.0, "0 = use the whole budget")
    default = HAAR_PERSISTENCE if family == "adaptive_haar" else HADAMARD_PERSISTENCE
    beta = _non_negative(raw, "persistence", default, "0 = rank by the prediction alone")
    estimate = raw.get("error_estimate", "measured")
    if estimate not in ERROR_ESTIMATES:
        raise SpecError(
            "error_estimate", f"unknown error estimate {estimate!r}; one of {', '.join(ERROR_ESTIMATES)}"
        )
    return {
        "batch": batch,
        "target_error": target,
        "persistence": beta,
        "error_estimate": estimate,
        "frames": "single" if single else None,
    }


def _non_negative(raw: Mapping[str, Any], key: str, default: float, zero: str) -> float:
    """``raw[key]`` (``default`` when absent) as a finite float >= 0, else the refusal naming
    ``key`` (as the server's, which refuses a null too); ``zero`` says what 0 means."""
    value = raw.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SpecError(key, f"must be a number, got {value!r}")
    try:
        value = float(value)
    except OverflowError:
        value = math.inf
    if not (math.isfinite(value) and value >= 0.0):
        raise SpecError(key, f"must be a finite number >= 0 ({zero}), got {value}")
    return value
