#!/usr/bin/env python3
"""Reference implementation of the Helmholtz seed -> pattern generator (proto/PATTERNS.md).

Pure Python 3.11, standard library only. It is written from PATTERNS.md, not from the Rust code,
and deliberately uses the *definitions* of the document where the Rust generator uses a fast
equivalent (e.g. the Bernoulli threshold comparison pixel by pixel instead of the bit-sliced
recurrence; 1D sequency found by counting sign changes and then checked against
bitrev(gray(s))), so that agreement between the two is evidence that the document is right.

Usage:
    python3 proto/tools/patterns_ref.py                 # print the test vectors (JSON) to stdout
    python3 proto/tools/patterns_ref.py --check FILE    # exit 1 unless FILE equals that output
    python3 proto/tools/patterns_ref.py --show SPEC_JSON INDEX [INDEX...]
                                                        # draw patterns of any spec, e.g.
        '{"family":"bernoulli","width":8,"height":8,"count":10,"seed":0}' 0 1

The committed output lives in proto/tests/pattern_vectors.json and is checked against the Rust
generator by proto/tests/pattern_vectors.rs.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import struct
import sys
from fractions import Fraction

MASK64 = (1 << 64) - 1

# ---------------------------------------------------------------------------------------------
# Limits (PATTERNS.md, "Common fields and limits")
# ---------------------------------------------------------------------------------------------
MAX_SIDE = 4096
MAX_PIXELS = 1 << 22
MAX_COUNT = 10_000_000
FILL_BITS = 16

ORDERINGS = ["natural", "sequency", "zigzag", "russian_doll", "cake_cutting"]


# ---------------------------------------------------------------------------------------------
# Random words (PATTERNS.md, "Random words")
# ---------------------------------------------------------------------------------------------
GOLDEN = 0x9E3779B97F4A7C15
MUL1 = 0xBF58476D1CE4E5B9
MUL2 = 0x94D049BB133111EB


def mix64(z: int) -> int:
    z = ((z ^ (z >> 30)) * MUL1) & MASK64
    z = ((z ^ (z >> 27)) * MUL2) & MASK64
    return z ^ (z >> 31)


def random_word(seed: int, c: int) -> int:
    """Word number c (0-based) of the SplitMix64 stream of `seed`."""
    return mix64((seed + (c + 1) * GOLDEN) & MASK64)


# ---------------------------------------------------------------------------------------------
# Spec: validation and canonical form (PATTERNS.md, "The spec")
# ---------------------------------------------------------------------------------------------
class SpecError(ValueError):
    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


def fill_quantum(fill: float) -> int:
    """Q = round(fill * 2^16), halves rounded away from zero, on the exact binary64 value."""
    x = Fraction(fill) * (1 << FILL_BITS)  # exact rational arithmetic, no rounding anywhere
    q = math.floor(x)
    if x - q >= Fraction(1, 2):
        q += 1
    return min(max(q, 1), (1 << FILL_BITS) - 1)


def _is_uint(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


ADAPTIVE = ("adaptive_haar", "adaptive_hadamard")


def canonical_adaptive(raw: dict) -> dict:
    """An adaptive spec (PATTERNS.md, "Adaptive families"), canonicalised."""
    allowed = {"family", "width", "height", "count", "seed", "batch", "target_error",
               "persistence", "error_estimate", "frames"}
    for key in raw:
        if key not in allowed:
            raise SpecError(key, "unknown field")
    for key in ("width", "height", "count"):
        if key not in raw:
            raise SpecError(key, "missing")
    width, height, count = raw["width"], raw["height"], raw["count"]
    seed, batch = raw.get("seed", 0), raw.get("batch", 0)
    target = raw.get("target_error", 0.0)
    beta = raw.get("persistence", 0.5 if raw["family"] == "adaptive_haar" else 0.0)
    estimate = raw.get("error_estimate", "measured")
    frames = raw.get("frames", "pairs")
    for key, v, top in (("width", width, 2**32), ("height", height, 2**32),
                        ("count", count, 2**64), ("seed", seed, 2**64), ("batch", batch, 2**32)):
        if not _is_uint(v) or v >= top:
            raise SpecError(key, f"not an unsigned integer of the right size: {v!r}")
    if not 1 <= width <= MAX_SIDE or width & (width - 1):
        raise SpecError("width", "must be a power of two")
    if height != width:
        raise SpecError("height", "must equal width")
    k = width * height
    if k > MAX_PIXELS:
        raise SpecError("width", "too many pixels")
    if frames not in ("pairs", "single"):
        raise SpecError("frames", "pairs or single")
    if frames == "single":
        # PATTERNS.md, "Single frames": index 0 takes two frames, every other index one.
        if raw["family"] != "adaptive_haar":
            raise SpecError("frames", "single frames are for adaptive_haar only")
        if not 2 <= count <= k + 1:
            raise SpecError("count", "single frames: 2 ..= width * height + 1")
    elif not 1 <= count <= MAX_COUNT or count % 2 or count > 2 * k:
        raise SpecError("count", "must be even and at most 2 * width * height")
    if batch > k:
        raise SpecError("batch", "at most width * height")
    if isinstance(target, bool) or not isinstance(target, (int, float)) \
            or not math.isfinite(target) or target < 0:
        raise SpecError("target_error", "a finite number >= 0")
    if isinstance(beta, bool) or not isinstance(beta, (int, float)) \
            or not math.isfinite(beta) or beta < 0:
        raise SpecError("persistence", "a finite number >= 0")
    if estimate not in ("prediction", "measured"):
        raise SpecError("error_estimate", "prediction or measured")
    out = {"family": raw["family"], "batch": batch, "target_error": float(target),
           "persistence": float(beta), "error_estimate": estimate}
    if frames == "single":  # stated only when single: older specs keep their canonical form
        out["frames"] = "single"
    out.update({"width": width, "height": height, "count": count, "seed": seed})
    return out


def canonical_spec(raw: dict) -> dict:
    """Validates a spec object and returns it canonicalised, keys in the canonical order."""
    if raw.get("family") in ADAPTIVE:
        return canonical_adaptive(raw)
    params = {"raster": ("block", 1), "bernoulli": ("fill", 0.5),
              "hadamard": ("ordering", "natural"), "speckle": ("grain", 1)}
    family = raw.get("family")
    if family not in params:
        raise SpecError("family", f"unknown family {family!r}")
    pname, pdefault = params[family]
    allowed = {"family", "width", "height", "count", "seed", pname}
    if family == "raster":
        allowed.add("scans")
    for key in raw:
        if key not in allowed:
            raise SpecError(key, "unknown field")
    for key in ("width", "height", "count"):
        if key not in raw:
            raise SpecError(key, "missing")
    width, height, count = raw["width"], raw["height"], raw["count"]
    seed = raw.get("seed", 0)
    p = raw.get(pname, pdefault)
    for key, v, top in (("width", width, 2**32), ("height", height, 2**32), ("count", count, 2**64),
                        ("seed", seed, 2**64)):
        if not _is_uint(v) or v >= top:
            raise SpecError(key, f"not an unsigned integer of the right size: {v!r}")
    if not 1 <= width <= MAX_SIDE:
        raise SpecError("width", "out of range")
    if not 1 <= height <= MAX_SIDE:
        raise SpecError("height", "out of range")
    k = width * height
    if k > MAX_PIXELS:
        raise SpecError("width", "too many pixels")
    if not 1 <= count <= MAX_COUNT:
        raise SpecError("count", "out of range")
    if family in ("raster", "speckle"):
        if not _is_uint(p) or not 1 <= p <= max(width, height):
            raise SpecError(pname, "out of range")
    elif family == "bernoulli":
        if isinstance(p, bool) or not isinstance(p, (int, float)):
            raise SpecError("fill", "not a number")
        p = float(p)
        if not 0.0 < p < 1.0:
            raise SpecError("fill", "must be in (0, 1)")
        p = fill_quantum(p) / (1 << FILL_BITS)
    else:
        if p not in ORDERINGS:
            raise SpecError("ordering", "unknown ordering")
        if width & (width - 1) or height & (height - 1):
            raise SpecError("width" if width & (width - 1) else "height", "not a power of two")
        if count % 2 or count > 2 * k:
            raise SpecError("count", "must be even and at most 2 * width * height")
    if family == "raster":
        scans = raw.get("scans", 1)
        blocks = -(-width // p) * -(-height // p)
        if not _is_uint(scans) or not 1 <= scans <= -(-MAX_COUNT // blocks):
            raise SpecError("scans", "out of range")
        if count > scans * blocks:
            raise SpecError("count", "more patterns than the declared scans of the blocks")
    out = {"family": family, pname: p}
    if family == "raster":
        out["scans"] = scans
    out.update({"width": width, "height": height, "count": count, "seed": seed})
    return out


def spec_json(spec: dict) -> str:
    """The canonical JSON text (no spaces). `fill` is a multiple of 2^-16: repr() is exact."""
    return json.dumps(spec, separators=(",", ":"))


def pixels(spec: dict) -> int:
    return spec["width"] * spec["height"]


def words_per_pattern(spec: dict) -> int:
    return (pixels(spec) + 63) // 64


# ---------------------------------------------------------------------------------------------
# Packing (PATTERNS.md, "Pixels and packing")
# ---------------------------------------------------------------------------------------------
def pack(on: list[bool]) -> list[int]:
    """Pixel p -> bit (p % 64) of word p // 64; unused high bits of the last word are 0."""
    words = [0] * ((len(on) + 63) // 64)
    for p, b in enumerate(on):
        if b:
            words[p // 64] |= 1 << (p % 64)
    return words


def words_hex(words: list[int]) -> str:
    """The words as little-endian bytes (8 per word), in hex: byte p // 8, bit p % 8 = pixel p."""
    return b"".join(w.to_bytes(8, "little") for w in words).hex()


# ---------------------------------------------------------------------------------------------
# raster
# ---------------------------------------------------------------------------------------------
def raster(spec: dict, i: int) -> list[bool]:
    w, h, b = spec["width"], spec["height"], spec["block"]
    bw, bh = -(-w // b), -(-h // b)
    blk = i % (bw * bh)
    bx, by = blk % bw, blk // bw
    return [bx * b <= x < (bx + 1) * b and by * b <= y < (by + 1) * b
            for y in range(h) for x in range(w)]


# ---------------------------------------------------------------------------------------------
# bernoulli
# ---------------------------------------------------------------------------------------------
def fill_digits(q: int) -> tuple[int, int]:
    """(d, odd): Q = odd * 2^(16 - d) with odd odd; the fill is odd / 2^d."""
    tz = (q & -q).bit_length() - 1
    return FILL_BITS - tz, q >> tz


def bernoulli(spec: dict, i: int) -> list[bool]:
    """The definition: pixel on iff V >= 2^d - odd, V built from d random words."""
    k, nw, seed = pixels(spec), words_per_pattern(spec), spec["seed"]
    q = round(spec["fill"] * (1 << FILL_BITS))  # canonical fill: exact multiple of 2^-16
    d, odd = fill_digits(q)
    threshold = (1 << d) - odd
    on = []
    for w in range(nw):
        base = ((i * nw + w) * d) & MASK64
        r = [random_word(seed, (base + j) & MASK64) for j in range(d)]
        for t in range(64):
            if w * 64 + t >= k:
                break
            v = 0
            for j in range(d):  # word base + 0 gives the most significant bit of V
                v = (v << 1) | ((r[j] >> t) & 1)
            on.append(v >= threshold)
    return on


def bernoulli_words_fast(spec: dict, i: int) -> list[int]:
    """The bit-sliced recurrence of PATTERNS.md; must equal pack(bernoulli(spec, i))."""
    k, nw, seed = pixels(spec), words_per_pattern(spec), spec["seed"]
    d, odd = fill_digits(round(spec["fill"] * (1 << FILL_BITS)))
    out = []
    for w in range(nw):
        base = ((i * nw + w) * d) & MASK64
        r = 0
        for j in reversed(range(d)):
            v = random_word(seed, (base + j) & MASK64)
            r = (v | r) if (odd >> (d - 1 - j)) & 1 else (v & r)
        out.append(r)
    if k % 64:
        out[-1] &= (1 << (k % 64)) - 1
    return out


# ---------------------------------------------------------------------------------------------
# hadamard
# ---------------------------------------------------------------------------------------------
def popcount(x: int) -> int:
    return bin(x).count("1")


def walsh_1d(n: int, length: int) -> list[int]:
    return [1 if popcount(n & x) % 2 == 0 else -1 for x in range(length)]


def sign_changes(v: list[int]) -> int:
    return sum(1 for a, b in zip(v, v[1:]) if a != b)


def bitrev(x: int, bits: int) -> int:
    return int(format(x, f"0{bits}b")[::-1], 2) if bits else 0


_SEQ_CACHE: dict[int, list[int]] = {}


def natural_of_sequency_table(length: int) -> list[int]:
    """table[s] = the natural index whose 1D Walsh function of `length` points has s sign
    changes, found by counting; checked against the closed form bitrev(gray(s))."""
    if length not in _SEQ_CACHE:
        bits = length.bit_length() - 1
        table = [0] * length
        for n in range(length):
            table[sign_changes(walsh_1d(n, length))] = n
        for s in range(length):
            assert table[s] == bitrev(s ^ (s >> 1), bits), (length, s)
        _SEQ_CACHE[length] = table
    return _SEQ_CACHE[length]


def bitlen(x: int) -> int:
    return x.bit_length()


def ordering_table(w: int, h: int, ordering: str) -> list[int]:
    """Row r of the ordering -> natural index n = u * W + v."""
    k = w * h
    if ordering == "natural":
        return list(range(k))
    if ordering == "sequency":
        return natural_of_sequency_table(k)[:]
    keys = {
        "zigzag": lambda su, sv: (su + sv, su),
        "russian_doll": lambda su, sv: (max(bitlen(su), bitlen(sv)), su + sv, su),
        "cake_cutting": lambda su, sv: ((su + 1) * (sv + 1), su),
    }[ordering]
    pairs = [(su, sv) for su in range(h) for sv in range(w)]
    assert len({keys(*p) for p in pairs}) == k, "keys must be injective"
    pairs.sort(key=lambda p: keys(*p))
    nat_h, nat_w = natural_of_sequency_table(h), natural_of_sequency_table(w)
    return [nat_h[su] * w + nat_w[sv] for su, sv in pairs]


def hadamard_frame(spec: dict, i: int, table: list[int]) -> tuple[int, int, bool]:
    """(row, natural index, positive) of frame i."""
    return i // 2, table[i // 2], i % 2 == 0


def hadamard(spec: dict, i: int, table: list[int]) -> list[bool]:
    w, h = spec["width"], spec["height"]
    _, n, positive = hadamard_frame(spec, i, table)
    u, v = divmod(n, w)
    col = walsh_1d(v, w)
    row = walsh_1d(u, h)
    return [(row[y] * col[x] == 1) == positive for y in range(h) for x in range(w)]


# ---------------------------------------------------------------------------------------------
# speckle
# ---------------------------------------------------------------------------------------------
def speckle_levels(spec: dict, i: int) -> list[int]:
    """24-bit integer grey levels L (the value shown is L / 2^24), row-major."""
    w, h, g, seed = spec["width"], spec["height"], spec["grain"], spec["seed"]
    cw, ch = -(-w // g), -(-h // g)
    cells = cw * ch
    out = []
    for y in range(h):
        for x in range(w):
            c = (y // g) * cw + x // g
            out.append(random_word(seed, (i * cells + c) & MASK64) >> 40)
    return out


# ---------------------------------------------------------------------------------------------
# adaptive_haar, adaptive_hadamard (PATTERNS.md, "Adaptive families")
# ---------------------------------------------------------------------------------------------
def log2(w: int) -> int:
    return w.bit_length() - 1


def haar_sign(w: int, n: int, x: int, y: int) -> int:
    """The Haar function with Mallat index n at pixel (x, y): +1, -1 or 0."""
    m = log2(w)
    if n == 0:
        return 1
    r, c = divmod(n, w)
    s = m - log2(max(r, c))
    h = w >> s
    x0, y0 = (c % h) << s, (r % h) << s
    dx, dy = x - x0, y - y0
    if not (0 <= dx < 1 << s and 0 <= dy < 1 << s):
        return 0
    half = 1 << (s - 1)
    return -1 if ((c >= h and dx >= half) != (r >= h and dy >= half)) else 1


def haar_scale(w: int, n: int) -> int:
    r, c = divmod(n, w)
    return log2(w) if n == 0 else log2(w) - log2(max(r, c))


def basis_sign(spec: dict, n: int, x: int, y: int) -> int:
    w = spec["width"]
    if spec["family"] == "adaptive_haar":
        return haar_sign(w, n, x, y)
    u, v = divmod(n, w)
    return 1 if (popcount(u & y) + popcount(v & x)) % 2 == 0 else -1


def single_frames(spec: dict) -> bool:
    """True for frames: "single" (PATTERNS.md, "Single frames")."""
    return spec.get("frames", "pairs") == "single"


def adaptive_frame(spec: dict, i: int) -> tuple[int, bool]:
    """(position r in the index sequence, positive) of frame i. Split pairs: frames 2r, 2r + 1
    show index r's P+, P-. Single frames: frames 0, 1 show index 0's P+, P-; frame r + 1
    (r >= 1) shows index r's P+."""
    if not single_frames(spec):
        return i // 2, i % 2 == 0
    if i < 2:
        return 0, i == 0
    return i - 1, True


def adaptive_frame_count(spec: dict, j: int) -> int:
    """Frames of the first j indices: 2j (pairs); R(0) = 0, R(j) = j + 1 (single)."""
    if not single_frames(spec):
        return 2 * j
    return j + 1 if j else 0


def basis_pattern(spec: dict, n: int, positive: bool) -> list[bool]:
    """P+ (pixel on <=> w_n = +1) or P- (pixel on <=> w_n = -1) of basis function n."""
    w, want = spec["width"], (1 if positive else -1)
    return [basis_sign(spec, n, x, y) == want for y in range(w) for x in range(w)]


def adaptive(spec: dict, i: int, indices: list[int]) -> list[bool]:
    r, positive = adaptive_frame(spec, i)
    return basis_pattern(spec, indices[r], positive)


def gain(spec: dict, n: int) -> float:
    w = spec["width"]
    return float(1 << haar_scale(w, n)) if spec["family"] == "adaptive_haar" else float(w)


def level(spec: dict, n: int) -> int:
    w = spec["width"]
    m = log2(w)
    if spec["family"] == "adaptive_haar":
        return m if n == 0 else haar_scale(w, n) - 1
    u, v = divmod(n, w)
    tz = lambda a: m if a == 0 else (a & -a).bit_length() - 1  # noqa: E731
    return min(tz(u), tz(v))


def parent(spec: dict, n: int):
    if n == 0:
        return None
    w = spec["width"]
    r, c = divmod(n, w)
    if spec["family"] == "adaptive_haar":
        h = w >> haar_scale(w, n)
        if h == 1:
            return 0
        up = lambda a: (h // 2 if a >= h else 0) + (a % h) // 2  # noqa: E731
        return up(r) * w + up(c)
    b = 1 << level(spec, n)
    return (r & ~b) * w + (c & ~b)


def fwht_list(x: list[float]) -> list[float]:
    x, h = x[:], 1
    while h < len(x):
        for i in range(len(x)):
            if i & h == 0:
                x[i], x[i + h] = x[i] + x[i + h], x[i] - x[i + h]
        h *= 2
    return x


def upsample(a: list[float], n: int) -> list[float]:
    """Bicubic 2x upsampling of an n x n array (rows, then columns; clamped indices)."""
    def step(x: list[float]) -> list[float]:
        at = lambda j: x[min(max(j, 0), n - 1)]  # noqa: E731
        out = []
        for j in range(n):
            out.append((((-3.0 * at(j - 2) + 29.0 * at(j - 1)) + 111.0 * at(j)) + -9.0 * at(j + 1))
                       * (1 / 128))
            out.append((((-9.0 * at(j - 1) + 111.0 * at(j)) + 29.0 * at(j + 1)) + -3.0 * at(j + 2))
                       * (1 / 128))
        return out
    rows = [step(a[i * n:(i + 1) * n]) for i in range(n)]
    cols = [step([rows[i][x] for i in range(n)]) for x in range(2 * n)]
    return [cols[x][y] for y in range(2 * n) for x in range(2 * n)]


def predict(spec: dict, v: list[float]) -> list[float]:
    w = spec["width"]
    m, k = log2(w), w * w
    p = [0.0] * k
    if m == 0:
        return p
    avg = {}
    if spec["family"] == "adaptive_haar":
        avg[m] = [v[0] * (1 / w)]
        for lv in range(m - 1, 0, -1):
            h, t = w >> (lv + 1), 2.0 ** -(lv + 1)
            out = [0.0] * (4 * h * h)
            for pr in range(h):
                for pc in range(h):
                    a = avg[lv + 1][pr * h + pc]
                    dx, dy = v[pr * w + h + pc], v[(h + pr) * w + pc]
                    dxy = v[(h + pr) * w + h + pc]
                    n2 = 2 * h
                    out[2 * pr * n2 + 2 * pc] = a + t * ((dx + dy) + dxy)
                    out[2 * pr * n2 + 2 * pc + 1] = a + t * ((dy - dx) - dxy)
                    out[(2 * pr + 1) * n2 + 2 * pc] = a + t * ((dx - dy) - dxy)
                    out[(2 * pr + 1) * n2 + 2 * pc + 1] = a + t * ((dxy - dx) - dy)
            avg[lv] = out
    else:
        for lv in range(1, m + 1):
            nl = w >> lv
            g = [v[((u << lv) * w) + (x << lv)] for u in range(nl) for x in range(nl)]
            avg[lv] = [a * (1 / w) for a in fwht_list(g)]
    for lv in range(m):
        n = w >> (lv + 1)
        up = upsample(avg[lv + 1], n)
        big = 2 * n
        if spec["family"] == "adaptive_haar":
            q = 2.0 ** (lv - 1)
            for pr in range(n):
                for pc in range(n):
                    a, b = up[2 * pr * big + 2 * pc], up[2 * pr * big + 2 * pc + 1]
                    c, d = up[(2 * pr + 1) * big + 2 * pc], up[(2 * pr + 1) * big + 2 * pc + 1]
                    p[pr * w + n + pc] = q * ((a - b) + (c - d))
                    p[(n + pr) * w + pc] = q * ((a + b) - (c + d))
                    p[(n + pr) * w + n + pc] = q * ((a - b) - (c - d))
        else:
            f = fwht_list(up)
            q = 2.0 ** (2 * lv - m)
            for u in range(big):
                for x in range(big):
                    if (u | x) & 1:
                        p[(u << lv) * w + (x << lv)] = f[u * big + x] * q
    p[0] = 0.0
    return p


def total_order(f: float) -> int:
    """An integer that orders binary64 values as IEEE 754 totalOrder does."""
    b = struct.unpack("<q", struct.pack("<d", f))[0]
    return b if b >= 0 else b ^ 0x7FFF_FFFF_FFFF_FFFF


def block_details(w: int, block: tuple[int, int, int]) -> tuple[int, int, int]:
    """The x, y and xy details of block (s, pr, pc) (PATTERNS.md, "Single frames")."""
    s, pr, pc = block
    h = w >> s
    return pr * w + h + pc, (h + pr) * w + pc, (h + pr) * w + h + pc


def block_of(w: int, n: int) -> tuple[tuple[int, int, int], int]:
    """The block of detail n != 0 and which of its details n is (0 = x, 1 = y, 2 = xy)."""
    s = haar_scale(w, n)
    h = w >> s
    r, c = divmod(n, w)
    kind = 2 if (r >= h and c >= h) else (1 if r >= h else 0)
    return (s, r % h, c % h), kind


def block_children(block: tuple[int, int, int]) -> list[tuple[int, int, int]]:
    """Top-left, top-right, bottom-left, bottom-right (none for s = 1)."""
    s, pr, pc = block
    if s < 2:
        return []
    return [(s - 1, 2 * pr + dr, 2 * pc + dc) for dr, dc in ((0, 0), (0, 1), (1, 0), (1, 1))]


class AdaptivePlanner:
    """The planner of PATTERNS.md, "The planner" (and "Single frames"), written from the text."""

    def __init__(self, spec: dict, channels: int):
        self.spec, self.c = canonical_spec(spec), channels
        w = self.spec["width"]
        self.k = w * w
        self.single = single_frames(self.spec)
        # The budget in indices: count / 2 split pairs, or count - 1 single-frame indices.
        per = self.spec["count"] - 1 if self.single else self.spec["count"] // 2
        self.budget = min(per, self.k)
        batch = self.spec["batch"]
        self.batch = batch if batch else max(16, -(-self.k * channels // 1024),
                                             -(-self.budget // 128))
        self.target = self.spec["target_error"]
        self.beta = self.spec["persistence"]
        # The parent whose measured detail a child inherits (PATTERNS.md: not the mean).
        self.detail_parent = [parent(self.spec, n) for n in range(self.k)]
        self.detail_parent = [None if q in (None, 0) else q for q in self.detail_parent]
        self.issued, self.order, self.outstanding = [False] * self.k, [], []
        self.v = [[0.0] * self.k for _ in range(channels)]
        self.energy = [0.0] * channels
        self.score = [0.0] * self.k
        self.estimate, self.stopped = None, False
        # The measured error estimate (PATTERNS.md, "Error estimate").
        self.measured = self.spec["error_estimate"] == "measured"
        m = log2(w)
        self.m = m
        self.size = [haar_scale(w, n) if self.spec["family"] == "adaptive_haar" else m
                     for n in range(self.k)]
        self.group = [support_group(self.spec, n) for n in range(self.k)]
        self.group_count = {}
        self.group_mean = [{} for _ in range(channels)]
        self.squares = [[0.0] * (m + 1) for _ in range(channels)]
        self.dof = [0] * (m + 1)
        self.observed = [False] * self.k
        # Single frames: the blocks not yet split, the block being split and how many of its
        # details were issued; per channel the dark level, each block's pair sum Q and each
        # decoded detail's y+ - y-; the (y+, y-) each index decoded to (for the self-checks).
        self.open = [(m, 0, 0)] if self.single and m >= 1 else []
        self.current, self.current_issued = None, 3
        self.dark = [0.0] * channels
        self.block_sum = {}
        self.diff = {}
        self.derived = {}

    def frames_of(self, first: int, n: int) -> int:
        """Frame values (per channel) of the n indices from position `first` on."""
        return adaptive_frame_count(self.spec, first + n) - adaptive_frame_count(self.spec, first)

    def values_needed(self) -> int:
        """Values (frames x channels) of the oldest outstanding batch."""
        first, n = self.outstanding[0]
        return self.frames_of(first, n) * self.c

    def block_score(self, block) -> float:
        x, y, xy = block_details(self.spec["width"], block)
        return (self.score[x] + self.score[y]) + self.score[xy]

    def select_single(self, size: int) -> list[int]:
        """PATTERNS.md, "Single frames", "Selection"."""
        w = self.spec["width"]
        chosen = []
        while len(chosen) < size:
            if not self.order and not chosen:
                chosen.append(0)
            elif self.current is not None and self.current_issued < 3:
                chosen.append(block_details(w, self.current)[self.current_issued])
                self.current_issued += 1
            elif self.open:
                best = max(self.open, key=lambda b: (total_order(self.block_score(b)), b[0],
                                                     -block_details(w, b)[0]))
                self.open.remove(best)
                self.open += block_children(best)
                self.current, self.current_issued = best, 1
                chosen.append(block_details(w, best)[0])
            else:
                break
        return chosen

    def poll(self):
        if len(self.outstanding) >= 2 or self.stopped or len(self.order) >= self.budget:
            return None
        if self.target > 0 and self.estimate is not None and self.estimate < self.target:
            self.stopped = True
            return None
        size = min(self.batch, self.budget - len(self.order))

        def key(n):
            par = parent(self.spec, n)
            eligible = par is None or self.issued[par]
            return (0 if eligible else 1, -self.score[n], -level(self.spec, n), n)
        if self.single:
            chosen = self.select_single(size)
            if not chosen:
                return None
        else:
            chosen = sorted((n for n in range(self.k) if not self.issued[n]), key=key)[:size]
        for n in chosen:
            assert not self.issued[n]
            self.issued[n] = True
        first = len(self.order)
        self.order += chosen
        self.outstanding.append((first, len(chosen)))
        return chosen

    def decode_single(self, first: int, pairs: int, frames: list[float]) -> list[list[tuple]]:
        """(y+, y-) per index and channel from single frames (PATTERNS.md, "Single frames",
        "Values"), in the order of the indices: a block's children get their pair sums as
        soon as its xy detail is decoded."""
        c, w = self.c, self.spec["width"]
        out = []
        for j in range(first, first + pairs):
            n = self.order[j]
            at = self.frames_of(first, j - first)  # the index's first frame in this batch
            ys = []
            if n == 0:
                root = (self.m, 0, 0)
                self.block_sum[root] = [0.0] * c
                for ch in range(c):
                    yp, ym = frames[at * c + ch], frames[(at + 1) * c + ch]
                    self.dark[ch] = ym
                    self.block_sum[root][ch] = yp + ym
                    ys.append((yp, ym))
            else:
                block, kind = block_of(w, n)
                q = self.block_sum[block]  # known: the parent's xy came first
                for ch in range(c):
                    yp = frames[at * c + ch]
                    ym = q[ch] - yp
                    ys.append((yp, ym))
                self.diff[n] = [yp - ym for yp, ym in ys]
                if kind == 2:
                    x, y, _ = block_details(w, block)
                    for child, (sx, sy, sxy) in zip(block_children(block),
                                                    ((1, 1, 1), (-1, 1, -1), (1, -1, -1),
                                                     (-1, -1, 1))):
                        sums = []
                        for ch in range(c):
                            two_dark = 2.0 * self.dark[ch]
                            big = q[ch] - two_dark
                            dx, dy, dxy = self.diff[x][ch], self.diff[y][ch], self.diff[n][ch]
                            acc = big + dx if sx > 0 else big - dx
                            acc = acc + dy if sy > 0 else acc - dy
                            acc = acc + dxy if sxy > 0 else acc - dxy
                            sums.append((acc * 0.25) + two_dark)
                        self.block_sum[child] = sums
            self.derived[n] = ys
            out.append(ys)
        return out

    def observe(self, frames: list[float]) -> None:
        first, pairs = self.outstanding[0]
        c = self.c
        assert len(frames) == self.values_needed() and all(math.isfinite(f) for f in frames)
        self.outstanding.pop(0)
        if self.single:
            ys = self.decode_single(first, pairs, frames)
        else:
            ys = [[(frames[2 * j * c + ch], frames[(2 * j + 1) * c + ch]) for ch in range(c)]
                  for j in range(pairs)]
        for j in range(pairs):
            n = self.order[first + j]
            for ch in range(c):
                val = (ys[j][ch][0] - ys[j][ch][1]) / gain(self.spec, n)
                self.v[ch][n] = val
                self.energy[ch] += val * val
            if self.measured:
                g, sz = self.group[n], self.size[n]
                cnt = self.group_count.get(g, 0)
                for ch in range(c):
                    t = ys[j][ch][0] + ys[j][ch][1]
                    old = self.group_mean[ch].get(g, 0.0)
                    new = old + (t - old) / (cnt + 1.0)
                    self.group_mean[ch][g] = new
                    if cnt > 0:
                        self.squares[ch][sz] += (t - old) * (t - new)
                if cnt > 0:
                    self.dof[sz] += 1
                self.group_count[g] = cnt + 1
                self.observed[n] = True
        self.score = [0.0] * self.k
        ratio, lit = 0.0, 0
        for ch in range(c):
            if self.energy[ch] == 0.0:
                continue
            norm, e = math.sqrt(self.energy[ch]), 0.0
            p = predict(self.spec, self.v[ch])
            v = self.v[ch]
            for n in range(self.k):
                size = abs(p[n])
                q = self.detail_parent[n]
                if self.beta > 0 and q is not None:
                    inherited = self.beta * abs(v[q])
                    if inherited > size:
                        size = inherited
                self.score[n] += size / norm
                if not self.issued[n]:
                    e += p[n] * p[n]
            if self.measured:
                ratio += self.relative_squared(ch, v, p)
            else:
                ratio += e / self.energy[ch]
            lit += 1
        self.estimate = math.sqrt(ratio / lit) if lit else None


    def pair_variance(self, ch: int, s: int) -> float:
        if self.dof[s] >= 32:
            return self.squares[ch][s] / self.dof[s]
        squares, dof = 0.0, 0
        for t in range(self.m + 1):
            squares += self.squares[ch][t]
            dof += self.dof[t]
        return squares / dof if dof > 0 else 0.0

    def relative_squared(self, ch: int, v: list[float], p: list[float]) -> float:
        var = [self.pair_variance(ch, s) / 4.0 ** s for s in range(self.m + 1)]
        levels = self.m + 1
        vp, pp, seen = [0.0] * levels, [0.0] * levels, [0] * levels
        noise, signal = 0.0, v[0] * v[0]
        for n in range(1, self.k):
            vn = var[self.size[n]]
            if self.issued[n]:
                noise += vn
            if self.observed[n]:
                lv = level(self.spec, n)
                vp[lv] += v[n] * p[n]
                pp[lv] += p[n] * p[n]
                seen[lv] += 1
                if v[n] * v[n] > 25.0 * vn:
                    signal += v[n] * v[n] - vn
        slope = [max(vp[lv] / pp[lv], 0.0) if seen[lv] >= 8 and pp[lv] > 0 else 1.0
                 for lv in range(levels)]
        miss = [0.0] * levels
        for n in range(1, self.k):
            if self.observed[n]:
                lv = level(self.spec, n)
                d = v[n] - slope[lv] * p[n]
                miss[lv] += d * d - var[self.size[n]]
        tau = level_misses(miss, seen)
        fill = 0.0
        for n in range(1, self.k):
            if not self.issued[n]:
                lv = level(self.spec, n)
                q = slope[lv] * p[n]
                fill += q * q + tau[lv]
        if not signal > 0:
            signal = self.energy[ch]
        return (fill + noise) / signal


def support_group(spec: dict, n: int) -> tuple:
    """Pairs of equal support share the key (PATTERNS.md, "Error estimate")."""
    w = spec["width"]
    if spec["family"] != "adaptive_hadamard":
        s = haar_scale(w, n)
        if s < log2(w):
            r, c = divmod(n, w)
            h = w >> s
            return (s, r % h, c % h)
        return (log2(w), 0, 0)
    return (0,)


def level_misses(miss: list[float], seen: list[int]) -> list[float]:
    """tau per level (PATTERNS.md, "Error estimate")."""
    levels = len(miss)
    tau = [0.0] * levels
    if levels < 2:
        return tau

    def resolved(lv):
        return max(miss[lv] / seen[lv], 0.0) if seen[lv] >= 8 else None
    finest = [resolved(lv) for lv in range(levels - 1) if resolved(lv) is not None][:2]
    rho = min(max(finest[0] / finest[1], 1.0 / 16.0), 1.0) \
        if len(finest) == 2 and finest[1] > 0 else 0.25
    above = None
    for lv in range(levels - 2, -1, -1):
        own = resolved(lv)
        if own is not None:
            t = own if above is None else min(own, above)
        elif above is not None:
            t = above * rho
        else:
            t = max(miss[lv] / seen[lv], 0.0) if seen[lv] > 0 else 0.0
        if own is not None or above is not None:
            above = t
        tau[lv] = t
    return tau


def replay(spec: dict, channels: int, frames: list[float]) -> list[int]:
    planner, queue, at = AdaptivePlanner(spec, channels), [], 0
    while True:
        while (b := planner.poll()) is not None:
            queue.append(b)
        if not queue:
            break
        queue.pop(0)
        need = planner.values_needed()  # 2 p C (pairs); (p + 1) C or p C (single frames)
        if len(frames) - at < need:
            break
        planner.observe(frames[at:at + need])
        at += need
    return planner.order


def simulate_adaptive(spec: dict, scenes: list[list[int]], dark: int, noise: int = 0) -> list[float]:
    """A simulated rig: shows what the planner asks, returns every frame value (integers, so
    the JSON is exact), each with an integer read noise uniform in [-noise, noise] from a fixed
    linear congruential sequence (one draw per frame value, frames in order, channels inner).

    Single frames: noise-free, every decoded (y+, y-) must be exactly the light of P+ and of
    the P- the rig never showed, plus the dark level (checked here)."""
    c = len(scenes)
    planner, queue, frames = AdaptivePlanner(spec, c), [], []
    state = 12345

    def light(pat: list[bool], t: list[int]) -> int:
        return sum(tv for on, tv in zip(pat, t) if on)
    while True:
        while (b := planner.poll()) is not None:
            queue.append(b)
        if not queue:
            break
        batch, values = queue.pop(0), []
        first, n_batch = planner.outstanding[0]
        assert planner.order[first:first + n_batch] == batch
        start = adaptive_frame_count(planner.spec, first)
        for i in range(start, start + planner.frames_of(first, n_batch)):
            r, positive = adaptive_frame(planner.spec, i)
            pat = basis_pattern(planner.spec, planner.order[r], positive)
            for t in scenes:
                state = (state * 6364136223846793005 + 1442695040888963407) % 2**64
                jitter = (state >> 33) % (2 * noise + 1) - noise if noise else 0
                values.append(float(dark + jitter + light(pat, t)))
        planner.observe(values)
        if planner.single and noise == 0:
            for n in batch:
                want = [(float(dark + light(basis_pattern(planner.spec, n, True), t)),
                         float(dark + light(basis_pattern(planner.spec, n, False), t)))
                        for t in scenes]
                assert planner.derived[n] == want, (n, planner.derived[n], want)
        frames += values
    if planner.single:
        check_single_order(planner.spec, planner.order)
    return frames


def check_single_order(spec: dict, order: list[int]) -> None:
    """A single-frame sequence is index 0, then whole block splits (x, y, xy in a row, the last
    one possibly cut by the budget), each block split after its parent block."""
    w = spec["width"]
    assert order[:1] == [0] and len(set(order)) == len(order)
    split = {(log2(w), 0, 0)} if w > 1 else set()  # blocks whose parent block was split
    for at in range(1, len(order), 3):
        block, kind = block_of(w, order[at])
        assert kind == 0 and block in split, (at, order[at])
        assert order[at:at + 3] == list(block_details(w, block))[:len(order) - at]
        split.update(block_children(block))


# ---------------------------------------------------------------------------------------------
# One pattern of any spec
# ---------------------------------------------------------------------------------------------
class Generator:
    def __init__(self, spec: dict, indices: list[int] | None = None):
        self.spec = canonical_spec(spec)
        self.table = None
        self.indices = indices
        if self.spec["family"] in ADAPTIVE:
            assert indices is not None, "an adaptive spec needs its indices"
        if self.spec["family"] == "hadamard":
            self.table = ordering_table(self.spec["width"], self.spec["height"],
                                        self.spec["ordering"])

    def bits(self, i: int) -> list[int]:
        f = self.spec["family"]
        if f == "raster":
            return pack(raster(self.spec, i))
        if f == "bernoulli":
            words = pack(bernoulli(self.spec, i))
            assert words == bernoulli_words_fast(self.spec, i), "the two Bernoulli forms differ"
            return words
        if f == "hadamard":
            return pack(hadamard(self.spec, i, self.table))
        if f in ADAPTIVE:
            return pack(adaptive(self.spec, i, self.indices))
        raise ValueError("speckle has grey levels, not bits")

    def frames(self) -> int | None:
        """An adaptive spec's frames for its indices: 2j split pairs, or j + 1 single frames
        (0 for none); None for the other families (their count is the spec's)."""
        if self.spec["family"] not in ADAPTIVE:
            return None
        return adaptive_frame_count(self.spec, len(self.indices))

    def levels(self, i: int) -> list[int]:
        assert self.spec["family"] == "speckle"
        return speckle_levels(self.spec, i)

    def run_sha256(self, start: int, n: int) -> str:
        """SHA-256 of patterns start..start+n: binary families as their packed words in
        little-endian bytes (8 per word), speckle as its levels in little-endian u32 (4 each)."""
        hasher = hashlib.sha256()
        for i in range(start, start + n):
            if self.spec["family"] == "speckle":
                hasher.update(b"".join(v.to_bytes(4, "little") for v in self.levels(i)))
            else:
                hasher.update(b"".join(w.to_bytes(8, "little") for w in self.bits(i)))
        return hasher.hexdigest()


# ---------------------------------------------------------------------------------------------
# CRC-32C and the bucket wire format (PATTERNS.md, "Bucket rows on the wire")
# ---------------------------------------------------------------------------------------------
def crc32c(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def encode_values(values: list[float]) -> bytes:
    return b"".join(struct.pack("<d", v) for v in values)


# ---------------------------------------------------------------------------------------------
# The vectors
# ---------------------------------------------------------------------------------------------
def vector(name: str, raw: dict, indices: list[int], runs: list[tuple[int, int]],
           note: str = "", basis: list[int] | None = None) -> dict:
    g = Generator(raw, basis)
    spec = g.spec
    out = {"name": name}
    if note:
        out["note"] = note
    out["input"] = raw
    out["spec"] = spec
    if basis is not None:
        out["basis_indices"] = basis
    out["pixels"] = pixels(spec)
    out["words_per_pattern"] = words_per_pattern(spec)
    fam = spec["family"]
    if fam == "bernoulli":
        q = round(spec["fill"] * (1 << FILL_BITS))
        d, odd = fill_digits(q)
        out["fill_quantum"] = q
        out["fill_digits"] = d
    pats = []
    for i in indices:
        e = {"index": i}
        if fam == "raster":
            w, h, b = spec["width"], spec["height"], spec["block"]
            e["block"] = i % (-(-w // b) * -(-h // b))
        if fam == "hadamard":
            row, n, pos = hadamard_frame(spec, i, g.table)
            e.update({"row": row, "natural": n, "positive": pos})
        if fam in ADAPTIVE:
            assert i < g.frames()
            r, positive = adaptive_frame(spec, i)  # pairs: (i / 2, i even)
            e.update({"pair": r, "basis_index": basis[r], "positive": positive})
        if fam == "speckle":
            e["levels"] = g.levels(i)
        else:
            e["bits_hex"] = words_hex(g.bits(i))
        pats.append(e)
    out["patterns"] = pats
    out["runs"] = [{"start": s, "count": n, "sha256": g.run_sha256(s, n)} for s, n in runs]
    return out


def replay_scene(w: int, shift: int) -> list[int]:
    """An edge, a bright square and a ramp, in integers (exact JSON)."""
    return [(3 * x + (40 if (x - shift) ** 2 + (y - 9) ** 2 < 20 else 0)
             + (25 if y > 12 else 0)) for y in range(w) for x in range(w)]


def replay_vector(fam: str, w: int, c: int, count: int, batch: int, target: float, dark: int,
                  beta, estimate, noise: int, single: bool = False) -> dict:
    """One simulated session, replayed: persistence None = the family's default (what a
    declaration without it gets); error estimate None = the default (measured); noise = the
    rig's integer read noise."""
    raw = {"family": fam, "width": w, "height": w, "count": count, "batch": batch,
           "target_error": target}
    if beta is not None:
        raw["persistence"] = beta
    if estimate is not None:
        raw["error_estimate"] = estimate
    if single:
        raw["frames"] = "single"
    scenes = [replay_scene(w, 6 + 4 * i) for i in range(c)]
    frames = simulate_adaptive(raw, scenes, dark, noise)
    order = replay(raw, c, frames)
    return {"spec": canonical_spec(raw), "channels": c, "dark": dark, "noise": noise,
            "frames": [int(f) for f in frames], "indices": order}


def build() -> dict:
    B = 1_000_000
    vectors = []

    # raster -------------------------------------------------------------------------------
    vectors.append(vector("raster 10x7 block 1", {"family": "raster", "width": 10, "height": 7,
                                                  "count": 140, "scans": 2},
                          [0, 1, 9, 10, 69, 70, 139], [(0, 140)],
                          "70 blocks: pattern 70 repeats pattern 0"))
    vectors.append(vector("raster 10x7 block 3", {"family": "raster", "width": 10, "height": 7,
                                                  "count": 30, "block": 3, "seed": 5,
                                                  "scans": 3},
                          [0, 1, 3, 4, 8, 11, 12, 29], [(0, 30)],
                          "4 x 3 blocks; the last column (x = 9) and row (y = 6) are partial;"
                          " two and a half scans"))
    vectors.append(vector("raster 16x3 block 5", {"family": "raster", "width": 16, "height": 3,
                                                  "count": 10, "block": 5, "scans": 3},
                          [0, 2, 3, 4], [(0, 10)],
                          "block taller than the image: 4 x 1 blocks, the last 1 pixel wide"))
    vectors.append(vector("raster 64x64 block 8", {"family": "raster", "width": 64,
                                                   "height": 64, "count": 64, "block": 8},
                          [0, 9, 63], [(0, 64)]))

    # bernoulli ----------------------------------------------------------------------------
    vectors.append(vector("bernoulli 8x8 fill 0.5 seed 0", {"family": "bernoulli", "width": 8,
                                                            "height": 8, "count": 2 * B},
                          [0, 1, 2, 63, B, B + 1], [(0, 256), (B, 64)],
                          "q = 0.5: pattern i of a 64-pixel spec is random word i itself"))
    vectors.append(vector("bernoulli 13x11 fill 0.5 seed 42",
                          {"family": "bernoulli", "width": 13, "height": 11, "count": MAX_COUNT,
                           "seed": 42, "fill": 0.5},
                          [0, 1, B - 1, B, MAX_COUNT - 1], [(0, 500), (B, 100)],
                          "143 pixels: 3 words, the last with 15 used bits"))
    vectors.append(vector("bernoulli 13x11 fill 0.3 seed 7",
                          {"family": "bernoulli", "width": 13, "height": 11, "count": 2 * B,
                           "seed": 7, "fill": 0.3},
                          [0, 1, 2, B, B + 7], [(0, 300), (B, 50)],
                          "Q = 19661 (odd): d = 16 words per 64 pixels"))
    vectors.append(vector("bernoulli 100x37 fill 0.95 seed 2^64-1",
                          {"family": "bernoulli", "width": 100, "height": 37, "count": 2 * B,
                           "seed": MASK64, "fill": 0.95},
                          [0, 1, B], [(0, 20), (B, 10)],
                          "Q = 62259; the largest seed, so seed + (c + 1) * GOLDEN wraps"))
    vectors.append(vector("bernoulli 17x5 fill 0.25", {"family": "bernoulli", "width": 17,
                                                       "height": 5, "count": 2 * B,
                                                       "seed": 3, "fill": 0.25},
                          [0, 1, B], [(0, 200)],
                          "Q = 16384 = 1 * 2^14: d = 2, on iff both bits are 1"))
    vectors.append(vector("bernoulli 17x5 fill 0.75", {"family": "bernoulli", "width": 17,
                                                       "height": 5, "count": 2 * B,
                                                       "seed": 3, "fill": 0.75},
                          [0, 1, B], [(0, 200)],
                          "Q = 49152 = 3 * 2^14: d = 2, on iff either bit is 1"))
    # Tiny fills: 64 patterns of 64 x 64 pixels hold a few on pixels; the patterns listed are
    # the first ones that have any, and the script checks that the run tells Q apart from Q - 1.
    for name, fill, note in (
            ("bernoulli 64x64 fill 1e-9 (clamped)", 1e-9, "Q clamps to 1: on iff V = 65535"),
            ("bernoulli 64x64 fill 2.5/65536 (rounds half up)", 2.5 / 65536,
             "fill * 2^16 = 2.5 exactly: Q = 3, not 2 (on iff V >= 65533)")):
        raw = {"family": "bernoulli", "width": 64, "height": 64, "count": 64, "seed": 11,
               "fill": fill}
        g = Generator(raw)
        lit = [i for i in range(64) if any(g.bits(i))][:2]
        v = vector(name, raw, lit, [(0, 64)], note)
        lower = dict(g.spec, fill=(round(g.spec["fill"] * 65536) - 1) / 65536)
        if lower["fill"] > 0:
            assert Generator(lower).run_sha256(0, 64) != v["runs"][0]["sha256"]
        else:
            assert lit, "no pixel on: the vector would not tell Q = 1 from Q = 0"
        vectors.append(v)

    # hadamard -----------------------------------------------------------------------------
    for w, h in ((8, 8), (16, 4), (2, 32)):
        k = w * h
        for o in ORDERINGS:
            vectors.append(vector(f"hadamard {w}x{h} {o}",
                                  {"family": "hadamard", "width": w, "height": h,
                                   "count": 2 * k, **({} if o == "natural" else {"ordering": o})},
                                  [0, 1, 2, 3, 6, 7, k - 1, 2 * k - 2, 2 * k - 1],
                                  [(0, 2 * k)]))
    vectors.append(vector("hadamard 1x1", {"family": "hadamard", "width": 1, "height": 1,
                                           "count": 2, "ordering": "zigzag"},
                          [0, 1], [(0, 2)], "the only row is all +1: P+ = 1, P- = 0"))
    vectors.append(vector("hadamard 32x16 russian_doll",
                          {"family": "hadamard", "width": 32, "height": 16, "count": 1024,
                           "ordering": "russian_doll", "seed": 99},
                          [0, 1, 2, 7, 31, 511, 1023], [(0, 1024)]))

    # adaptive -----------------------------------------------------------------------------
    for fam in ADAPTIVE:
        for w in (1, 4, 16):
            k = w * w
            order = [(n * 5 + 3) % k for n in range(k)] if w > 1 else [0]
            assert sorted(order) == list(range(k))
            vectors.append(vector(f"{fam} {w}x{w}", {"family": fam, "width": w, "height": w,
                                                     "count": 2 * k},
                                  sorted({i for i in (0, 1, 2, 3, 2 * k - 2, 2 * k - 1) if i < 2 * k}),
                                  [(0, 2 * k)],
                                  "basis_indices: the session's index sequence (5n + 3 mod k)",
                                  basis=order))
        vectors.append(vector(f"{fam} 32x32 partial", {"family": fam, "width": 32, "height": 32,
                                                       "count": 400, "batch": 10,
                                                       "target_error": 0.05},
                              [0, 1, 198, 199], [(0, 200)],
                              "100 of the 200 budgeted pairs shown",
                              basis=[(n * 37 + 11) % 1024 for n in range(100)]))
    # Single frames: the index sequence of a simulated session (index 0, then block splits).
    raw = {"family": "adaptive_haar", "frames": "single", "width": 16, "height": 16,
           "count": 257}
    order = replay(raw, 1, simulate_adaptive(raw, [replay_scene(16, 6)], 7))
    assert sorted(order) == list(range(256))
    assert Generator(raw, order).frames() == 257
    vectors.append(vector("adaptive_haar 16x16 single frames", raw, [0, 1, 2, 3, 4, 255, 256],
                          [(0, 257)],
                          "frames 0, 1: basis_indices[0]'s P+ and P-; frame r + 1: the P+ of "
                          "basis_indices[r] (pair = r); a complete set in k + 1 frames",
                          basis=order))

    # speckle ------------------------------------------------------------------------------
    vectors.append(vector("speckle 10x7 grain 3 seed 99",
                          {"family": "speckle", "width": 10, "height": 7, "count": 2 * B,
                           "seed": 99, "grain": 3},
                          [0, 1, B], [(0, 100)], "4 x 3 cells of 3 x 3 pixels, 12 words each"))
    vectors.append(vector("speckle 5x4 grain 1 seed 0",
                          {"family": "speckle", "width": 5, "height": 4, "count": 100},
                          [0, 1], [(0, 100)]))
    vectors.append(vector("speckle 33x20 grain 8 seed 2^64-1",
                          {"family": "speckle", "width": 33, "height": 20, "count": 2 * B,
                           "seed": MASK64, "grain": 8},
                          [0, B], [(0, 50)], "5 x 3 cells; the last cell column is 1 pixel wide"))

    # the pieces ---------------------------------------------------------------------------
    random_words = [{"seed": s, "counter": c, "word": f"{random_word(s, c):016x}"}
                    for s, c in ((0, 0), (0, 1), (0, 2), (1234567, 0), (1234567, 1),
                                 (42, B), (MASK64, 0), (7, MASK64), (7, MASK64 - 1))]
    fills = []
    for f in (0.5, 0.3, 0.95, 0.25, 0.75, 0.1, 0.300001, 1e-9, 0.999999999, 2.5 / 65536,
              1.5 / 65536, 65534.5 / 65536, 65535.5 / 65536, 1 / 3):
        q = fill_quantum(f)
        d, odd = fill_digits(q)
        fills.append({"fill": f, "fill_f64": struct.pack(">d", f).hex(), "quantum": q,
                      "digits": d, "odd": odd,
                      "canonical_fill": q / (1 << FILL_BITS)})
    orderings = []
    for w, h in ((4, 4), (8, 2), (1, 4)):
        for o in ORDERINGS:
            orderings.append({"width": w, "height": h, "ordering": o,
                              "natural": ordering_table(w, h, o)})
    wire = []
    for values, channels in (([1.0, -2.5], 1), ([0.0, 1.0, 3.25, -1e300, 2.0 ** -1074, 7.0], 3)):
        data = encode_values(values)
        wire.append({"values": values, "channels": channels, "bytes_hex": data.hex(),
                     "crc32c": f"{crc32c(data):08x}"})

    adaptive_replays = []
    for fam in ADAPTIVE:
        # persistence None: the family's default (what a declaration without it gets); the
        # error estimate None: the default (measured); noise: the rig's integer read noise.
        for w, c, count, batch, target, dark, beta, estimate, noise in (
                (16, 1, 160, 0, 0.0, 7, 0.0, None, 0), (16, 2, 200, 12, 0.0, 0, 0.0, None, 0),
                (8, 1, 128, 0, 0.0, 3, 0.0, None, 0), (16, 1, 512, 16, 0.02, 1, 0.0, None, 0),
                (16, 1, 512, 16, 0.02, 1, 0.0, "prediction", 0),
                (16, 1, 160, 0, 0.0, 7, None, None, 0), (16, 2, 200, 12, 0.0, 0, 1.0, None, 0),
                (32, 1, 256, 16, 0.0, 5, None, None, 0),
                (32, 1, 1024, 16, 0.12, 50, None, None, 60),
                (32, 2, 1024, 16, 0.12, 50, None, "prediction", 60),
                (32, 2, 1024, 16, 0.12, 50, None, None, 60)):
            adaptive_replays.append(replay_vector(fam, w, c, count, batch, target, dark, beta,
                                                  estimate, noise))
    # Single frames (adaptive_haar only): index 0 as frames 0 and 1, every other index one
    # frame; count - 1 indices, odd counts allowed, 8x8 with count 65 a complete set.
    stopped_early = 0
    for w, c, count, batch, target, dark, beta, estimate, noise in (
            (16, 1, 161, 0, 0.0, 7, None, None, 0), (16, 2, 150, 12, 0.0, 0, None, None, 0),
            (8, 1, 65, 0, 0.0, 3, None, None, 0), (32, 1, 300, 16, 0.0, 5, None, None, 0),
            (32, 1, 800, 16, 0.12, 50, None, None, 60),
            (32, 2, 700, 0, 0.0, 50, 1.0, "prediction", 60),
            # stopped by target_error: measured noise-free, prediction with read noise (with
            # single frames the measured estimate's noise part reads 0, so read noise counts as
            # prediction miss and the 32x32 session above never gets below 0.12)
            (16, 1, 257, 16, 0.05, 1, None, None, 0),
            (32, 1, 800, 16, 0.04, 50, None, "prediction", 60)):
        r = replay_vector("adaptive_haar", w, c, count, batch, target, dark, beta, estimate,
                          noise, single=True)
        assert len(r["frames"]) == adaptive_frame_count(r["spec"], len(r["indices"])) * c
        if count == w * w + 1 and target == 0:
            assert sorted(r["indices"]) == list(range(w * w))
        stopped_early += len(r["indices"]) < count - 1
        adaptive_replays.append(r)
    assert stopped_early == 2, stopped_early  # the last two

    return {
        "format": "helmholtz-pattern-vectors/1",
        "generated_by": "python3 proto/tools/patterns_ref.py",
        "definition": "proto/PATTERNS.md",
        "encoding": {
            "bits_hex": "packed words (pixel p = bit p % 64 of word p / 64, bits past k are 0) "
                        "as little-endian bytes, 8 per word, in hex; i.e. pixel p is bit "
                        "p % 8 (LSB first) of byte p / 8",
            "levels": "speckle: 24-bit integer grey levels L, row-major; the value is L / 2^24",
            "runs.sha256": "SHA-256 over patterns start .. start + count - 1 in order: binary "
                           "families as their packed words in little-endian bytes (8 per "
                           "word), speckle as its levels in little-endian u32 (4 bytes each)",
            "random_words.word": "random_word(seed, counter), 16 hex digits",
            "fills.fill_f64": "the requested fill's IEEE-754 binary64 bits, big-endian hex",
            "orderings.natural": "natural index u * W + v of each row of the ordering",
            "basis_indices": "adaptive families: the basis index of each split pair (frames "
                             "2r, 2r + 1 show basis_indices[r])",
            "basis_indices.single": "frames: single: frames 0 and 1 show the P+ and P- of "
                                    "basis_indices[0] (= 0), frame r + 1 (r >= 1) the P+ of "
                                    "basis_indices[r]; a pattern's pair is that r",
            "adaptive_replays": "adaptive sessions of a simulated rig: the frames (integers, "
                                "frame-major, channels inner; the scene's light plus the dark "
                                "level plus an integer read noise in [-noise, noise]) replay "
                                "through the planner to the issued indices; with frames: "
                                "single, index 0 as frames 0 and 1 and every other index as "
                                "one frame (its P+)",
        },
        "random_words": random_words,
        "fills": fills,
        "orderings": orderings,
        "wire": wire,
        "vectors": vectors,
        "adaptive_replays": adaptive_replays,
    }


# ---------------------------------------------------------------------------------------------
# Output: deterministic JSON, one pattern per line
# ---------------------------------------------------------------------------------------------
def dumps(obj, indent: int = 0) -> str:
    pad, inner = "  " * indent, "  " * (indent + 1)
    if isinstance(obj, dict):
        if all(not isinstance(v, (dict, list)) or (isinstance(v, list) and
               all(not isinstance(x, (dict, list)) for x in v)) for v in obj.values()) \
                and len(json.dumps(obj)) <= 200:
            return json.dumps(obj)
        if "index" in obj or "sha256" in obj:  # one pattern / run per line, however long
            return json.dumps(obj)
        items = [f"{inner}{json.dumps(k)}: {dumps(v, indent + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, list):
        if all(not isinstance(x, (dict, list)) for x in obj):
            return json.dumps(obj)
        items = [f"{inner}{dumps(v, indent + 1)}" for v in obj]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return json.dumps(obj)


def show(spec_text: str, indices: list[int]) -> None:
    g = Generator(json.loads(spec_text))
    s = g.spec
    print(spec_json(s))
    for i in indices:
        print(f"pattern {i}:")
        if s["family"] == "speckle":
            lv = g.levels(i)
            for y in range(s["height"]):
                print(" ".join(f"{lv[y * s['width'] + x]:06x}" for x in range(s["width"])))
        else:
            words = g.bits(i)
            print("  words:", " ".join(f"{w:016x}" for w in words))
            for y in range(s["height"]):
                row = ""
                for x in range(s["width"]):
                    p = y * s["width"] + x
                    row += "#" if (words[p // 64] >> (p % 64)) & 1 else "."
                print("  " + row)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", metavar="FILE", help="compare FILE with the generated vectors")
    ap.add_argument("--show", nargs="+", metavar="ARG", help="SPEC_JSON INDEX [INDEX...]")
    args = ap.parse_args()
    if args.show:
        show(args.show[0], [int(x) for x in args.show[1:]] or [0])
        return 0
    text = dumps(build()) + "\n"
    if args.check:
        with open(args.check, encoding="utf-8") as f:
            if f.read() != text:
                print(f"{args.check} differs from the reference output", file=sys.stderr)
                return 1
        print(f"{args.check}: identical")
        return 0
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
