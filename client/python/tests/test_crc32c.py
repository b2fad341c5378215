"""CRC-32C: known vectors, the bitwise definition, the combine rule, and the server's own
(Rust ``crc32c`` crate) values on random data."""

from __future__ import annotations

import json
import re

import grpc
import numpy as np
import pytest

import helmholtz as hz
from helmholtz._proto.v1 import acquisition_pb2 as pb
from helmholtz._proto.v1 import acquisition_pb2_grpc as pb_grpc
from helmholtz.crc32c import crc32c_bitwise, crc32c_combine, crc32c_numpy

from conftest import REPO_ROOT


def test_check_value_and_published_vectors() -> None:
    assert crc32c_numpy(b"123456789") == 0xE3069283
    assert hz.crc32c(b"123456789") == 0xE3069283
    assert crc32c_bitwise(b"123456789") == 0xE3069283
    assert crc32c_numpy(b"") == 0
    # RFC 3720 (iSCSI) B.4: 32 bytes of zeros, of 0xFF, ascending and descending.
    assert crc32c_numpy(bytes(32)) == 0x8A9136AA
    assert crc32c_numpy(b"\xff" * 32) == 0x62A8AB43
    assert crc32c_numpy(bytes(range(32))) == 0x46DD794E
    assert crc32c_numpy(bytes(range(31, -1, -1))) == 0x113FDB5C


def test_wire_vectors_of_patterns_md() -> None:
    vectors = json.loads((REPO_ROOT / "proto" / "tests" / "pattern_vectors.json").read_text())
    assert vectors["wire"], "no wire vectors"
    for w in vectors["wire"]:
        data = np.asarray(w["values"], dtype="<f8").tobytes()
        assert data.hex() == w["bytes_hex"]
        assert crc32c_numpy(data) == int(w["crc32c"], 16)


@pytest.mark.parametrize(
    "n", [1, 7, 63, 511, 512, 513, 1000, 2047, 4096, 4099, 65536, 65536 * 3 + 13]
)
def test_lanes_agree_with_the_bitwise_definition(n: int) -> None:
    # Lengths around the lane sizes (whole lanes, a tail, recursion into the tail).
    data = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    assert crc32c_numpy(data) == crc32c_bitwise(data)


def test_arrays_are_checksummed_as_their_bytes() -> None:
    a = np.random.default_rng(3).standard_normal((100, 7))
    assert crc32c_numpy(a) == crc32c_bitwise(a.tobytes())
    assert crc32c_numpy(memoryview(a.tobytes())) == crc32c_numpy(a)


def test_combine_is_the_crc_of_the_concatenation() -> None:
    rng = np.random.default_rng(5)
    for la, lb in [(0, 5), (5, 0), (1, 1), (100, 1000), (4097, 12345)]:
        a = rng.integers(0, 256, la, dtype=np.uint8).tobytes()
        b = rng.integers(0, 256, lb, dtype=np.uint8).tobytes()
        assert crc32c_combine(crc32c_numpy(a), crc32c_numpy(b), lb) == crc32c_numpy(a + b)


def test_matches_the_servers_rust_crc32c_on_random_data(server, client, session_id) -> None:  # type: ignore[no-untyped-def]
    """Chunks with a wrong checksum are refused with DATA_LOSS naming the payload's CRC as the
    server (the Rust crc32c crate) computes it: that must be ours, for any length."""
    spec = hz.PatternSpec.hadamard(4, 4)
    client.create_session(session_id, spec, camera=hz.Camera(4, 4, "u16"))
    stub = pb_grpc.AcquisitionStub(grpc.insecure_channel(server.address.split("://", 1)[1]))
    rng = np.random.default_rng(42)
    for n in [2, 1000, 4096 + 6, 65536 + 2, 1 << 20]:
        payload = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        ours = crc32c_numpy(payload)
        chunk = pb.MeasurementChunk(
            session_id=session_id, start_row=0, channels=16, values_u16le=payload,
            crc32c=ours ^ 0xFFFFFFFF,
        )
        with pytest.raises(grpc.RpcError) as e:
            stub.UploadMeasurements(iter([chunk]), metadata=[("authorization", f"Bearer {server.token}")])
        assert e.value.code() == grpc.StatusCode.DATA_LOSS, e.value.details()
        m = re.search(r"payload has (0x[0-9a-f]{8})", e.value.details())
        assert m, e.value.details()
        assert int(m.group(1), 16) == ours, f"{n} bytes: server {m.group(1)}, ours {ours:#010x}"
    assert client.upload_status(session_id).committed_rows == 0
