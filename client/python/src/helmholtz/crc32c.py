"""CRC-32C (Castagnoli), the checksum of every upload chunk, in numpy.

Parameters (PATTERNS.md, "Bucket rows on the wire"): reflected polynomial ``0x82F63B78``,
initial value ``0xFFFFFFFF``, final xor ``0xFFFFFFFF``; ``crc32c(b"123456789") == 0xE3069283``.

A byte-at-a-time CRC in pure Python runs at about 1 MB/s, too slow for camera frames. Here the
buffer is cut into ``L`` equal *lanes* that are run side by side: one vectorised table lookup
per 4-byte position updates all ``L`` lane registers at once (slicing-by-4). The CRC register
is affine in its input, so the lanes are then joined the way zlib's ``crc32_combine`` joins two
CRCs: the register of lane ``j`` is shifted past the ``m`` bytes of lane ``j + 1`` (a 32 x 32
matrix over GF(2), "append m zero bytes", built by repeated squaring) and xored with it. The
joins run as a tree, again vectorised over all pairs. The bytes past the last whole lane are
folded in the same way, recursively.

If the optional package ``google_crc32c`` (a C implementation) is installed it is used
instead; both give the same values (the tests compare this implementation with a bitwise one
and with the server's Rust implementation).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Union

import numpy as np

__all__ = ["crc32c", "crc32c_numpy", "crc32c_bitwise", "crc32c_combine"]

POLY = 0x82F63B78
_MASK = 0xFFFFFFFF

BytesLike = Union[bytes, bytearray, memoryview, np.ndarray]


def _make_tables() -> np.ndarray:
    """Slicing-by-4 tables: ``t[0]`` is the byte table, ``t[j][b]`` = ``t[0]`` shifted j bytes."""
    t0 = np.zeros(256, dtype=np.uint32)
    for b in range(256):
        c = b
        for _ in range(8):
            c = (c >> 1) ^ (POLY if c & 1 else 0)
        t0[b] = c
    tables = np.zeros((4, 256), dtype=np.uint32)
    tables[0] = t0
    for j in range(1, 4):
        prev = tables[j - 1]
        tables[j] = t0[prev & 0xFF] ^ (prev >> np.uint32(8))
    return tables


_TABLES = _make_tables()
_T0_LIST = [int(v) for v in _TABLES[0]]
_BITS = np.arange(32, dtype=np.uint32)


def _raw_bytewise(register: int, data: bytes) -> int:
    """The raw register after `data`, one byte at a time (for short pieces)."""
    t = _T0_LIST
    for byte in data:
        register = t[(register ^ byte) & 0xFF] ^ (register >> 8)
    return register


def _apply(columns: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The GF(2) matrix with `columns` (column b = the image of bit b) applied to each value."""
    bits = (values[..., None] >> _BITS) & np.uint32(1)
    picked = np.where(bits.astype(bool), columns, np.uint32(0))
    return np.bitwise_xor.reduce(picked, axis=-1).astype(np.uint32)


@lru_cache(maxsize=1)
def _one_zero_byte() -> np.ndarray:
    """The columns of "append one zero byte" to the raw register."""
    cols = np.uint32(1) << _BITS
    return (_TABLES[0][cols & np.uint32(0xFF)] ^ (cols >> np.uint32(8))).astype(np.uint32)


@lru_cache(maxsize=64)
def _zero_bytes(n: int) -> np.ndarray:
    """The columns of "append n zero bytes" (n >= 0), by repeated squaring."""
    result = np.uint32(1) << _BITS  # identity
    square = _one_zero_byte()
    while n:
        if n & 1:
            result = _apply(square, result)
        n >>= 1
        if n:
            square = _apply(square, square)
    return result


def _as_u8(data: BytesLike) -> np.ndarray:
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    return np.frombuffer(memoryview(data).cast("B"), dtype=np.uint8)


def _raw(register: int, buf: np.ndarray) -> int:
    """The raw (unconditioned) register after `buf`, starting from `register`."""
    n = buf.size
    if n < 512:
        return _raw_bytewise(register, buf.tobytes())
    # L lanes of m bytes each, m a multiple of 4: about sqrt(n) lanes, a power of two.
    lanes = 1 << min(14, max(1, (n.bit_length() - 1) // 2))
    m = (n // lanes) // 4 * 4
    if m == 0:
        return _raw_bytewise(register, buf.tobytes())
    head = buf[: lanes * m]
    # words[t] = the t-th 32-bit little-endian word of every lane (contiguous per step).
    words = np.ascontiguousarray(head.reshape(lanes, m).view("<u4").astype(np.uint32).T)
    regs = np.zeros(lanes, dtype=np.uint32)
    regs[0] = register
    t0, t1, t2, t3 = _TABLES
    ff, s8, s16, s24 = np.uint32(0xFF), np.uint32(8), np.uint32(16), np.uint32(24)
    for row in words:
        x = regs ^ row
        regs = t3[x & ff] ^ t2[(x >> s8) & ff] ^ t1[(x >> s16) & ff] ^ t0[x >> s24]
    # Join neighbouring lanes as a tree: (a, b) -> shift(a, len(b)) ^ b.
    length = m
    while regs.size > 1:
        shift = _zero_bytes(length)
        regs = _apply(shift, regs[0::2]) ^ regs[1::2]
        length *= 2
    return _raw(int(regs[0]), buf[lanes * m :])


def crc32c_numpy(data: BytesLike) -> int:
    """CRC-32C of `data` (bytes-like, or an ndarray's bytes in memory order), numpy only."""
    buf = _as_u8(data)
    return _raw(_MASK, buf) ^ _MASK


def crc32c_bitwise(data: bytes) -> int:
    """CRC-32C bit by bit, as PATTERNS.md defines it (slow: a reference for the tests)."""
    crc = _MASK
    for byte in bytes(data):
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (POLY if crc & 1 else 0)
    return crc ^ _MASK


def crc32c_combine(crc_a: int, crc_b: int, len_b: int) -> int:
    """The CRC-32C of ``a + b`` from ``crc32c(a)``, ``crc32c(b)`` and ``len(b)`` (as zlib's
    ``crc32_combine``)."""
    shifted = int(_apply(_zero_bytes(len_b), np.array([crc_a], dtype=np.uint32))[0])
    return shifted ^ crc_b


try:  # optional C implementation; never required
    import google_crc32c as _google_crc32c  # type: ignore[import-not-found]
except Exception:  # pragma: no cover - depends on the environment
    _google_crc32c = None


def crc32c(data: BytesLike) -> int:
    """CRC-32C of `data` (bytes-like, or an ndarray's bytes in memory order).

    Uses ``google_crc32c`` when it is installed, else :func:`crc32c_numpy`.
    """
    if _google_crc32c is not None:  # pragma: no cover - depends on the environment
        return int(_google_crc32c.value(_as_u8(data).tobytes()))
    return crc32c_numpy(data)
