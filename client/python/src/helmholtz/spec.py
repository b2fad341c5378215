"""Pattern specs: what a session declares instead of pattern pixels (proto/PATTERNS.md).

A :class:`PatternSpec` is the family, size, count, seed and the family's parameter. It converts
to and from the JSON form (the REST API's ``patterns``) and the protobuf form (gRPC), and
:meth:`PatternSpec.canonical` validates it as PATTERNS.md says (defaults filled in, the
Bernoulli fill quantised to a multiple of 2^-16), naming the offending field on error.
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

FAMILIES = ("raster", "bernoulli", "hadamard", "speckle")
#: PATTERNS.md's adaptive families, which this package does not implement yet.
ADAPTIVE_FAMILIES = ("adaptive_haar", "adaptive_hadamard")
ORDERINGS = ("natural", "sequency", "zigzag", "russian_doll", "cake_cutting")

_FAMILY_TO_PB = {
    "raster": pb.PATTERN_FAMILY_RASTER,
    "bernoulli": pb.PATTERN_FAMILY_BERNOULLI,
    "hadamard": pb.PATTERN_FAMILY_HADAMARD,
    "speckle": pb.PATTERN_FAMILY_SPECKLE,
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
    :meth:`hadamard`, :meth:`speckle`) or directly; ``None`` parameters take the family's
    defaults. Only the parameter of the spec's own family may be set.

    Attributes:
        family: ``"raster"``, ``"bernoulli"``, ``"hadamard"`` or ``"speckle"``.
        width, height: the projector grid (pixels).
        count: patterns (frames) in the session; for Hadamard even, at most ``2 * width * height``.
        seed: random stream of bernoulli and speckle (ignored by the others).
        block, scans: raster block side and declared repeats of the scan.
        fill: bernoulli on-probability in (0, 1), quantised to a multiple of 2^-16.
        ordering: hadamard row ordering (one of :data:`ORDERINGS`).
        grain: speckle cell side.
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
        """True for the 0/1 families (raster, bernoulli, hadamard)."""
        return self.family != "speckle"

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
        if family not in _PARAMS:
            if family in ADAPTIVE_FAMILIES:
                raise SpecError(
                    "family",
                    f"{family} is not supported by this package yet: an adaptive session's patterns "
                    "are chosen by the server as it measures (gRPC Acquire); use the Rust client "
                    "(helmholtz simulate --adaptive, helmholtz_client::adaptive)",
                )
            raise SpecError("family", f"unknown family {family!r}; one of {', '.join(FAMILIES)}")
        pname = _PARAMS[family]
        allowed = {"family", "width", "height", "count", "seed", pname}
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
        for name in ("block", "scans", "fill", "ordering", "grain"):
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
        if which is not None and which != family:
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
        return cls.from_dict(raw)

    def with_count(self, count: int) -> "PatternSpec":
        """The same spec with another count (patterns do not depend on the count)."""
        return replace(self, count=count).canonical()
