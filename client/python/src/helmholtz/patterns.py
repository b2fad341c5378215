"""The seed -> pattern generator of proto/PATTERNS.md, vectorised with numpy.

Pattern ``i`` of a spec is a pure function of ``(spec, i)``; the server rebuilds the same
patterns from the session's spec. What a projector shows:

>>> from helmholtz import PatternSpec, patterns
>>> spec = PatternSpec.hadamard(8, 8, ordering="sequency")
>>> frames = patterns(spec)            # float32, shape (128, 8, 8), values 0.0 / 1.0
>>> frames[0].all(), frames[1].any()   # frame 0 is all on, frame 1 all off
(True, False)

Binary families (raster, bernoulli, hadamard, the adaptive ones) give 0.0 / 1.0; speckle gives
``L / 2^24`` for 24-bit integer levels ``L`` (exact in float32). :func:`packed_bits` gives the
packed words of PATTERNS.md ("pixel p is bit p % 64 of word p / 64") and
:func:`speckle_levels` the integer levels, which is what the test vectors
(proto/tests/pattern_vectors.json) list.

An adaptive session's patterns (``adaptive_haar``, ``adaptive_hadamard``) also depend on the
basis indices the server chose (gRPC ``Acquire``): pair ``r`` (frames ``2r``, ``2r + 1``) shows
the split pair (P+, P-) of basis function ``indices[r]``. Pass them as ``indices=`` to
:func:`patterns` / :class:`PatternGenerator`, or render one batch's pairs with
:func:`adaptive_patterns`:

>>> spec = PatternSpec.adaptive_haar(4)
>>> adaptive_patterns(spec, [1]).astype(int)[0]   # P+ of Haar index 1: the left half on
array([[1, 1, 0, 0],
       [1, 1, 0, 0],
       [1, 1, 0, 0],
       [1, 1, 0, 0]])

With single frames (``PatternSpec.adaptive_haar(side, frames="single")``, PATTERNS.md "Single
frames") the sequence starts with index 0: frame 0 is its P+ (all on), frame 1 its P- (all
off, the dark level), and frame ``r + 1`` (``r >= 1``) the P+ of ``indices[r]`` alone; the first
``j >= 1`` indices take ``j + 1`` frames.

This module was ported from the pure-Python reference ``proto/tools/patterns_ref.py`` and
vectorised: Bernoulli uses the bit-sliced form (one OR/AND per fill digit over all words at
once), Hadamard computes the Walsh signs from popcounts, speckle draws one random word per cell.
"""

from __future__ import annotations

import hashlib
from functools import lru_cache
from typing import Optional, Sequence, Union

import numpy as np

from .spec import FILL_BITS, PatternSpec

__all__ = [
    "PatternGenerator",
    "adaptive_patterns",
    "basis_functions",
    "basis_gains",
    "patterns",
    "pattern",
    "packed_bits",
    "speckle_levels",
    "random_words",
    "ordering_table",
    "run_sha256",
]

GOLDEN = 0x9E3779B97F4A7C15
MUL1 = 0xBF58476D1CE4E5B9
MUL2 = 0x94D049BB133111EB

# Temporary random words per block of frames (bounds the memory of one step).
_BLOCK_WORDS = 1 << 21


def _u64(x: int) -> np.uint64:
    return np.uint64(x & 0xFFFFFFFFFFFFFFFF)


def random_words(seed: int, counters: np.ndarray) -> np.ndarray:
    """``random_word(seed, c)`` of PATTERNS.md for every counter (uint64, wrapping)."""
    c = np.asarray(counters, dtype=np.uint64)
    with np.errstate(over="ignore"):
        z = _u64(seed) + (c + np.uint64(1)) * _u64(GOLDEN)
        z = (z ^ (z >> np.uint64(30))) * _u64(MUL1)
        z = (z ^ (z >> np.uint64(27))) * _u64(MUL2)
    return z ^ (z >> np.uint64(31))


def _bitrev(x: np.ndarray, bits: int) -> np.ndarray:
    out = np.zeros_like(x)
    for b in range(bits):
        out |= ((x >> b) & 1) << (bits - 1 - b)
    return out


def _bitlen(x: np.ndarray) -> np.ndarray:
    out = np.zeros_like(x)
    for b in range(int(x.max(initial=0)).bit_length()):
        out += (x >> b) > 0
    return out


def _natural_of_sequency(length: int) -> np.ndarray:
    """table[s] = the natural index of the length-``length`` Walsh function with s sign changes."""
    s = np.arange(length, dtype=np.int64)
    return _bitrev(s ^ (s >> 1), length.bit_length() - 1)


@lru_cache(maxsize=32)
def _ordering_table_cached(width: int, height: int, ordering: str) -> np.ndarray:
    k = width * height
    if ordering == "natural":
        table = np.arange(k, dtype=np.int64)
    elif ordering == "sequency":
        table = _natural_of_sequency(k)
    else:
        su = np.repeat(np.arange(height, dtype=np.int64), width)
        sv = np.tile(np.arange(width, dtype=np.int64), height)
        if ordering == "zigzag":
            rank = np.lexsort((su, su + sv))
        elif ordering == "russian_doll":
            rank = np.lexsort((su, su + sv, np.maximum(_bitlen(su), _bitlen(sv))))
        elif ordering == "cake_cutting":
            rank = np.lexsort((su, (su + 1) * (sv + 1)))
        else:
            raise ValueError(f"unknown ordering {ordering!r}")
        nat_h, nat_w = _natural_of_sequency(height), _natural_of_sequency(width)
        table = nat_h[su[rank]] * width + nat_w[sv[rank]]
    table.setflags(write=False)
    return table


def ordering_table(width: int, height: int, ordering: str) -> np.ndarray:
    """``order(r)`` for every row ``r``: the natural index ``u * W + v`` of Hadamard row ``r``."""
    return _ordering_table_cached(width, height, ordering)


def _fill_digits(q: int) -> tuple[int, int]:
    tz = (q & -q).bit_length() - 1
    return FILL_BITS - tz, q >> tz


IndexList = Union[Sequence[int], np.ndarray]


def _check_indices(spec: PatternSpec, indices: IndexList, *, session: bool = True) -> np.ndarray:
    """The basis indices of an adaptive spec as int64, each in ``0..k``; a ``session``'s
    sequence is checked as the server resolves a spec (also none twice, at most the budget's
    ``count / 2`` pairs, or with single frames ``count - 1`` indices starting with index 0)."""
    if not spec.adaptive:
        raise ValueError(f"only the adaptive families take basis indices, not {spec.family}")
    arr = np.asarray(indices)
    if arr.ndim != 1 or (arr.size and arr.dtype.kind not in "iu"):
        raise ValueError(f"basis indices must be a 1-D sequence of integers, got {arr.dtype} {arr.shape}")
    arr = arr.astype(np.int64)
    k = spec.pixels
    if session and arr.size > spec.adaptive_budget:
        what = "single-frame indices" if spec.single_frames else "split pairs"
        raise ValueError(
            f"{arr.size} indices, but a budget of {spec.count} frames holds "
            f"{spec.adaptive_budget} {what}"
        )
    if session and spec.single_frames and arr.size and arr[0] != 0:
        raise ValueError(
            f"a single-frame session starts with index 0 (its pair measures the light and the "
            f"dark level), got {int(arr[0])} first"
        )
    bad = (arr < 0) | (arr >= k)
    if bad.any():
        r = int(np.argmax(bad))
        raise ValueError(f"index {int(arr[r])} of pair {r} is out of range 0..{k}")
    if session and np.unique(arr).size != arr.size:
        seen: set[int] = set()
        for r, n in enumerate(arr.tolist()):
            if n in seen:
                raise ValueError(f"index {n} of pair {r} was already shown")
            seen.add(n)
    return arr


def _haar_signs(side: int, n: np.ndarray) -> np.ndarray:
    """+1 / -1 / 0 (int8, shape (len(n), side, side)) of the 2D Haar functions with Mallat
    indices ``n`` (PATTERNS.md, adaptive_haar)."""
    m = side.bit_length() - 1
    r, c = n // side, n % side
    # s = m - floor(log2(max(r, c))); the scaling function (n = 0) has s = m.
    s = np.where(n == 0, m, m - (_bitlen(np.maximum(r, c)) - 1))
    h = side >> s
    x0, y0 = (c % h) << s, (r % h) << s
    size = (1 << s)[:, None, None]
    half = size // 2
    xs = np.arange(side, dtype=np.int64)
    dx = xs[None, None, :] - x0[:, None, None]
    dy = xs[None, :, None] - y0[:, None, None]
    inside = (dx >= 0) & (dx < size) & (dy >= 0) & (dy < size)
    negative = ((c >= h)[:, None, None] & (dx >= half)) ^ ((r >= h)[:, None, None] & (dy >= half))
    out = np.where(negative, -1, 1).astype(np.int8)
    out[~inside] = 0
    return out


def _walsh_signs(side: int, n: np.ndarray) -> np.ndarray:
    """+1 / -1 (int8) of the 2D Walsh-Hadamard functions with natural indices ``n = u W + v``:
    ``(-1)^(popcount(u & y) + popcount(v & x))``."""
    u, v = n // side, n % side
    xs = np.arange(side, dtype=np.int64)
    pu = np.bitwise_count(u[:, None] & xs[None, :]) & 1
    pv = np.bitwise_count(v[:, None] & xs[None, :]) & 1
    odd = pu[:, :, None] ^ pv[:, None, :]
    return (1 - 2 * odd.astype(np.int8)).astype(np.int8)


def basis_functions(spec: PatternSpec, indices: IndexList) -> np.ndarray:
    """The basis functions ``w_n`` of an adaptive spec for basis indices ``indices``: int8
    ``(len(indices), side, side)`` of +1 / -1 (and 0 outside a Haar function's support).
    ``P+ - P- = w_n``; the orthonormal function is ``w_n / g_n`` (:func:`basis_gains`)."""
    spec = spec.canonical()
    n = _check_indices(spec, indices, session=False)
    if spec.family == "adaptive_haar":
        return _haar_signs(spec.width, n)
    return _walsh_signs(spec.width, n)


def basis_gains(spec: PatternSpec, indices: IndexList) -> np.ndarray:
    """The gains ``g_n`` (float64) of basis indices: the orthonormal coefficient of a pair is
    ``(y+ - y-) / g_n``. ``W`` for every Walsh-Hadamard function and Haar's scaling function,
    ``2^s`` for a Haar function of support ``2^s x 2^s``."""
    spec = spec.canonical()
    n = _check_indices(spec, indices, session=False)
    side = spec.width
    if spec.family == "adaptive_hadamard":
        return np.full(n.shape, float(side))
    m = side.bit_length() - 1
    s = np.where(n == 0, m, m - (_bitlen(np.maximum(n // side, n % side)) - 1))
    return np.ldexp(1.0, s)


def _opens_session(spec: PatternSpec, indices: np.ndarray) -> bool:
    """Single frames: whether ``indices`` open the session (start with index 0, shown as its
    pair); index 0 anywhere else is refused. Always False for split pairs."""
    if not spec.single_frames:
        return False
    later = indices[1:] == 0
    if later.any():
        r = 1 + int(np.argmax(later))
        raise ValueError(
            f"index 0 at position {r}: a single-frame session shows index 0 first (as its pair)"
        )
    return bool(indices.size) and int(indices[0]) == 0


def _frame_count(spec: PatternSpec, n: int, opens: bool) -> int:
    """Frames of ``n`` indices: ``2 n`` split pairs; single frames ``n``, plus one for index
    0's pair when they open the session."""
    if not spec.single_frames:
        return 2 * n
    return n + 1 if opens and n else n


def _frame_positions(spec: PatternSpec, i: np.ndarray, opens: bool) -> tuple[np.ndarray, np.ndarray]:
    """For frame numbers ``i`` (counted from the first of the indices): the position of the
    index each frame shows and whether it is the P+ (True) or the P- frame.

    Split pairs: frame ``2j`` is the P+ of index ``j``, ``2j + 1`` its P-. Single frames
    (PATTERNS.md "Single frames"): frames 0 and 1 of a session's first indices show index 0's
    P+ and P-, frame ``r + 1`` the P+ of index ``r``; indices that do not open the session show
    frame ``r`` the P+ of index ``r``."""
    if not spec.single_frames:
        return i // 2, i % 2 == 0
    if opens:
        return np.maximum(i - 1, 0), i != 1
    return i, np.ones(i.shape, dtype=bool)


def adaptive_patterns(
    spec: PatternSpec, indices: IndexList, dtype: "np.typing.DTypeLike" = np.float32
) -> np.ndarray:
    """The frames of basis ``indices`` of an adaptive spec, what a projector shows for one
    batch of an adaptive session, as ``(frames, side, side)`` of ``dtype`` (float32 by
    default). Bit-exact with the server (PATTERNS.md, adaptive families).

    Split pairs: ``2 * len(indices)`` frames, frame ``2j`` the P+ of ``indices[j]`` (on where
    ``w = +1``), frame ``2j + 1`` its P- (on where ``w = -1``).

    Single frames (``spec.frames == "single"``, PATTERNS.md "Single frames"): one frame per
    index, its P+, except index 0 (the first index of the session, so the first of its first
    batch), which shows its pair: all on, then all off (the dark level). The first batch
    ``[0, n1, n2, ...]`` gives ``len(indices) + 1`` frames (all on, all off, P+ of ``n1``, ...),
    every later batch ``len(indices)``.

    Raises:
        ValueError: not an adaptive spec, an index out of ``0..side*side``, or (single frames)
            index 0 anywhere but first.
    """
    spec = spec.canonical()
    n = _check_indices(spec, indices, session=False)
    opens = _opens_session(spec, n)
    i = np.arange(_frame_count(spec, n.size, opens), dtype=np.int64)
    pos, positive = _frame_positions(spec, i, opens)
    w = basis_functions(spec, n)[pos]
    want = np.where(positive, 1, -1).astype(np.int8)
    return (w == want[:, None, None]).astype(dtype)


class PatternGenerator:
    """Patterns of one spec. ``PatternGenerator(spec).values(start, stop)`` is
    :func:`patterns`; the generator keeps the spec's tables for repeated calls.

    An adaptive spec needs its session's basis ``indices`` (one per split pair, in order, as
    ``GET /v1/sessions/{id}/adaptive.json`` or :attr:`helmholtz.AdaptiveReport.indices` give
    them): it then has ``2 * len(indices)`` frames, or with single frames ``len(indices) + 1``
    (frame 0 all on, frame 1 all off, frame ``r + 1`` the P+ of ``indices[r]``)."""

    def __init__(self, spec: PatternSpec, indices: Optional[IndexList] = None):
        self.spec = spec.canonical()
        s = self.spec
        self.k = s.pixels
        self.words_per_pattern = (self.k + 63) // 64
        self._table: Optional[np.ndarray] = None
        self.indices: Optional[np.ndarray] = None
        if s.family == "hadamard":
            self._table = ordering_table(s.width, s.height, s.ordering or "natural")
        if s.adaptive:
            if indices is None:
                raise ValueError(
                    f"a {s.family} spec's patterns depend on the basis indices the server chose: "
                    "give indices= (or use adaptive_patterns)"
                )
            self.indices = _check_indices(s, indices)
            _opens_session(s, self.indices)  # index 0 first, and only there
        elif indices is not None:
            raise ValueError(f"only the adaptive families take basis indices, not {s.family}")

    @property
    def frames(self) -> int:
        """Frames this generator gives: the spec's count, or for an adaptive spec the frames of
        its indices (two per index; single frames ``len(indices) + 1``)."""
        if self.indices is not None:
            return self.spec.adaptive_rows(int(self.indices.size))
        return self.spec.count

    def _check_range(self, start: int, stop: Optional[int]) -> tuple[int, int]:
        count = self.frames
        if stop is None:
            stop = count
        if not (0 <= start <= stop <= count):
            what = "the spec's" if self.indices is None else "the indices'"
            raise IndexError(f"patterns {start}..{stop} are outside {what} 0..{count}")
        return int(start), int(stop)

    def _block(self, per_frame: int) -> int:
        return max(1, _BLOCK_WORDS // max(1, per_frame))

    # -- binary families as booleans ------------------------------------------------------
    def _on(self, start: int, stop: int) -> np.ndarray:
        """Boolean (n, H, W): which pixels are on in frames start..stop (binary families)."""
        s = self.spec
        h, w = s.height, s.width
        i = np.arange(start, stop, dtype=np.int64)
        if s.family == "raster":
            b = s.block or 1
            bw, bh = -(-w // b), -(-h // b)
            blk = i % (bw * bh)
            bx, by = blk % bw, blk // bw
            xs = np.arange(w) // b
            ys = np.arange(h) // b
            return (ys[None, :, None] == by[:, None, None]) & (xs[None, None, :] == bx[:, None, None])
        if s.family == "hadamard":
            assert self._table is not None
            n = self._table[i // 2]
            u, v = n // w, n % w
            positive = (i % 2) == 0
            pu = np.bitwise_count(u[:, None] & np.arange(h)[None, :]) & 1
            pv = np.bitwise_count(v[:, None] & np.arange(w)[None, :]) & 1
            plus = (pu[:, :, None] ^ pv[:, None, :]) == 0
            return plus == positive[:, None, None]
        if s.family == "bernoulli":
            words = self._bernoulli_words(start, stop)
            bits = np.unpackbits(words.astype("<u8").view(np.uint8), axis=1, bitorder="little")
            return bits[:, : self.k].astype(bool).reshape(-1, h, w)
        if self.indices is not None:
            # A session's sequence: with single frames it opens with index 0 (checked).
            pos, positive = _frame_positions(s, i, opens=True)
            signs = basis_functions(s, self.indices[pos])
            want = np.where(positive, 1, -1).astype(np.int8)
            return signs == want[:, None, None]
        raise ValueError("speckle patterns have grey levels, not bits")

    def _bernoulli_words(self, start: int, stop: int) -> np.ndarray:
        s = self.spec
        q = round((s.fill if s.fill is not None else 0.5) * (1 << FILL_BITS))
        d, odd = _fill_digits(q)
        nw = self.words_per_pattern
        i = np.arange(start, stop, dtype=np.uint64)
        base = (i[:, None] * np.uint64(nw) + np.arange(nw, dtype=np.uint64)[None, :]) * np.uint64(d)
        r = np.zeros(base.shape, dtype=np.uint64)
        for j in reversed(range(d)):
            v = random_words(s.seed, base + np.uint64(j))
            r = (v | r) if (odd >> (d - 1 - j)) & 1 else (v & r)
        if self.k % 64:
            r[:, -1] &= np.uint64((1 << (self.k % 64)) - 1)
        return r

    # -- public ---------------------------------------------------------------------------
    def packed_bits(self, start: int = 0, stop: Optional[int] = None) -> np.ndarray:
        """Packed words (n, ceil(k / 64)) uint64 of binary frames: pixel p = bit p % 64 of word
        p / 64, bits past k are 0."""
        start, stop = self._check_range(start, stop)
        if self.spec.family == "bernoulli":
            return self._bernoulli_words(start, stop)
        nw = self.words_per_pattern
        out = np.zeros((stop - start, nw), dtype=np.uint64)
        step = self._block(self.k)
        for a in range(start, stop, step):
            b = min(stop, a + step)
            on = self._on(a, b).reshape(b - a, self.k)
            padded = np.zeros((b - a, nw * 64), dtype=bool)
            padded[:, : self.k] = on
            out[a - start : b - start] = (
                np.packbits(padded, axis=1, bitorder="little").view("<u8").astype(np.uint64)
            )
        return out

    def speckle_levels(self, start: int = 0, stop: Optional[int] = None) -> np.ndarray:
        """Speckle grey levels (n, H, W) uint32: ``L = random_word(seed, i * C + cell) >> 40``."""
        start, stop = self._check_range(start, stop)
        s = self.spec
        if s.family != "speckle":
            raise ValueError(f"a {s.family} spec has no grey levels")
        g = s.grain or 1
        cw, ch = -(-s.width // g), -(-s.height // g)
        cells = cw * ch
        cell = (np.arange(s.height)[:, None] // g) * cw + (np.arange(s.width)[None, :] // g)
        i = np.arange(start, stop, dtype=np.uint64)
        counters = i[:, None] * np.uint64(cells) + np.arange(cells, dtype=np.uint64)[None, :]
        with np.errstate(over="ignore"):
            levels = (random_words(s.seed, counters) >> np.uint64(40)).astype(np.uint32)
        return levels[:, cell]

    def values(
        self, start: int = 0, stop: Optional[int] = None, dtype: "np.typing.DTypeLike" = np.float32
    ) -> np.ndarray:
        """Frames ``start..stop`` as an ndarray (n, height, width) of ``dtype`` (float32 by
        default): 0/1 for binary families, ``L / 2^24`` for speckle."""
        start, stop = self._check_range(start, stop)
        s = self.spec
        out = np.empty((stop - start, s.height, s.width), dtype=dtype)
        step = self._block(self.k + 16 * self.words_per_pattern)
        for a in range(start, stop, step):
            b = min(stop, a + step)
            if s.family == "speckle":
                out[a - start : b - start] = self.speckle_levels(a, b) * (1.0 / (1 << 24))
            else:
                out[a - start : b - start] = self._on(a, b)
        return out

    def run_sha256(self, start: int, count: int) -> str:
        """SHA-256 of frames start..start+count as PATTERNS.md's test vectors hash them."""
        h = hashlib.sha256()
        if self.spec.family == "speckle":
            h.update(self.speckle_levels(start, start + count).astype("<u4").tobytes())
        else:
            h.update(self.packed_bits(start, start + count).astype("<u8").tobytes())
        return h.hexdigest()


def patterns(
    spec: PatternSpec,
    start: int = 0,
    stop: Optional[int] = None,
    dtype: "np.typing.DTypeLike" = np.float32,
    *,
    indices: Optional[IndexList] = None,
) -> np.ndarray:
    """Frames ``start..stop`` (default: all ``spec.count``) of ``spec`` as an ndarray
    ``(n, height, width)``, ready for a projector: 0.0 / 1.0 for the binary families,
    ``L / 2^24`` for speckle. Bit-exact with the server's generator (PATTERNS.md). An adaptive
    spec needs its session's basis ``indices`` (then it has ``2 * len(indices)`` frames, or
    with single frames ``len(indices) + 1``).

    Raises:
        SpecError: the spec is invalid.
        ValueError: an adaptive spec without indices, or bad indices.
        IndexError: the range leaves ``0..spec.count``.
    """
    return PatternGenerator(spec, indices).values(start, stop, dtype)


def pattern(
    spec: PatternSpec,
    index: int,
    dtype: "np.typing.DTypeLike" = np.float32,
    *,
    indices: Optional[IndexList] = None,
) -> np.ndarray:
    """Frame ``index`` of ``spec`` as an ndarray ``(height, width)``."""
    return PatternGenerator(spec, indices).values(index, index + 1, dtype)[0]


def packed_bits(
    spec: PatternSpec,
    start: int = 0,
    stop: Optional[int] = None,
    *,
    indices: Optional[IndexList] = None,
) -> np.ndarray:
    """:meth:`PatternGenerator.packed_bits` of ``spec``."""
    return PatternGenerator(spec, indices).packed_bits(start, stop)


def speckle_levels(spec: PatternSpec, start: int = 0, stop: Optional[int] = None) -> np.ndarray:
    """:meth:`PatternGenerator.speckle_levels` of ``spec``."""
    return PatternGenerator(spec).speckle_levels(start, stop)


def run_sha256(
    spec: PatternSpec, start: int, count: int, *, indices: Optional[IndexList] = None
) -> str:
    """:meth:`PatternGenerator.run_sha256` of ``spec``."""
    return PatternGenerator(spec, indices).run_sha256(start, count)
