"""The pattern generator is bit-exact with PATTERNS.md: every entry of
proto/tests/pattern_vectors.json (which the Rust generator is tested against too)."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

import helmholtz as hz
from helmholtz.patterns import PatternGenerator, ordering_table, random_words
from helmholtz.spec import ADAPTIVE_FAMILIES, SpecError, fill_quantum

from conftest import REPO_ROOT

VECTORS = json.loads((REPO_ROOT / "proto" / "tests" / "pattern_vectors.json").read_text())
ADAPTIVE = [v for v in VECTORS["vectors"] if v["spec"]["family"] in ADAPTIVE_FAMILIES]
FIXED = [v for v in VECTORS["vectors"] if v["spec"]["family"] not in ADAPTIVE_FAMILIES]


def test_the_vectors_file_is_the_one_expected() -> None:
    assert VECTORS["format"] == "helmholtz-pattern-vectors/1"
    assert len(VECTORS["vectors"]) >= 30
    families = {v["spec"]["family"] for v in VECTORS["vectors"]}
    assert families == {"raster", "bernoulli", "hadamard", "speckle", *ADAPTIVE_FAMILIES}


@pytest.mark.parametrize("vector", ADAPTIVE, ids=lambda v: v["name"])
def test_adaptive_families_are_refused_naming_the_family(vector: dict) -> None:
    # Not implemented here yet (their patterns follow the server's choices): a clear refusal.
    with pytest.raises(SpecError) as e:
        hz.PatternSpec.from_dict(vector["input"])
    assert e.value.field == "family" and "not supported by this package yet" in e.value.message


def test_random_words() -> None:
    for rw in VECTORS["random_words"]:
        got = random_words(rw["seed"], np.array([rw["counter"]], dtype=np.uint64))[0]
        assert f"{int(got):016x}" == rw["word"], rw


def test_fill_quantisation() -> None:
    for f in VECTORS["fills"]:
        fill = struct.unpack(">d", bytes.fromhex(f["fill_f64"]))[0]
        assert fill_quantum(fill) == f["quantum"], f
        spec = hz.PatternSpec.bernoulli(8, 8, 10, fill=fill)
        assert spec.fill == f["canonical_fill"], f


def test_orderings() -> None:
    for o in VECTORS["orderings"]:
        assert ordering_table(o["width"], o["height"], o["ordering"]).tolist() == o["natural"], o


@pytest.mark.parametrize("vector", FIXED, ids=lambda v: v["name"])
def test_patterns_and_runs(vector: dict) -> None:
    spec = hz.PatternSpec.from_dict(vector["input"])
    assert spec.to_dict() == vector["spec"]
    assert spec.pixels == vector["pixels"]
    gen = PatternGenerator(spec)
    assert gen.words_per_pattern == vector["words_per_pattern"]
    for p in vector["patterns"]:
        i = p["index"]
        frame = hz.pattern(spec, i)
        assert frame.shape == (spec.height, spec.width) and frame.dtype == np.float32
        if "levels" in p:
            levels = gen.speckle_levels(i, i + 1)[0]
            assert levels.reshape(-1).tolist() == p["levels"]
            assert np.array_equal(frame, (levels / 2.0**24).astype(np.float32))
        else:
            words = gen.packed_bits(i, i + 1)[0]
            assert words.astype("<u8").tobytes().hex() == p["bits_hex"], i
            bits = np.unpackbits(
                np.frombuffer(bytes.fromhex(p["bits_hex"]), np.uint8), bitorder="little"
            )[: spec.pixels]
            assert np.array_equal(frame.reshape(-1), bits.astype(np.float32)), i
    for run in vector["runs"]:
        assert gen.run_sha256(run["start"], run["count"]) == run["sha256"], run
        # The ndarray of a whole run agrees with the hashed form.
        if run["count"] <= 256:
            values = hz.patterns(spec, run["start"], run["start"] + run["count"])
            if spec.family == "speckle":
                levels = gen.speckle_levels(run["start"], run["start"] + run["count"])
                assert np.array_equal(values, (levels / 2.0**24).astype(np.float32))
            else:
                words = gen.packed_bits(run["start"], run["start"] + run["count"])
                bits = np.unpackbits(words.astype("<u8").view(np.uint8), axis=1, bitorder="little")
                assert np.array_equal(values.reshape(len(values), -1), bits[:, : spec.pixels])


def test_a_complete_hadamard_set_is_orthogonal() -> None:
    spec = hz.PatternSpec.hadamard(8, 4, ordering="zigzag")
    frames = hz.patterns(spec).reshape(spec.count, -1).astype(np.float64)
    h = frames[0::2] - frames[1::2]  # the +-1 rows
    assert np.array_equal(h @ h.T, spec.pixels * np.eye(spec.pixels))
    assert np.array_equal(frames[0::2] + frames[1::2], np.ones((spec.pixels, spec.pixels)))


def test_specs_are_validated_naming_the_field() -> None:
    cases = [
        (dict(family="hadamard", width=6, height=8, count=2), "width"),
        (dict(family="hadamard", width=8, height=8, count=3), "count"),
        (dict(family="bernoulli", width=8, height=8, count=10, fill=1.0), "fill"),
        (dict(family="raster", width=8, height=8, count=65), "count"),
        (dict(family="raster", width=8, height=8, count=10, fill=0.5), "fill"),
        (dict(family="speckle", width=0, height=8, count=10), "width"),
        (dict(family="laser", width=8, height=8, count=10), "family"),
        (dict(family="speckle", width=8, height=8), "count"),
    ]
    for raw, field in cases:
        with pytest.raises(hz.SpecError) as e:
            hz.PatternSpec.from_dict(raw)
        assert e.value.field == field, (raw, e.value)


def test_protobuf_form_round_trips() -> None:
    for spec in [
        hz.PatternSpec.raster(10, 7, 30, block=3, scans=3),
        hz.PatternSpec.bernoulli(13, 11, 100, fill=0.3, seed=2**64 - 1),
        hz.PatternSpec.hadamard(16, 4, ordering="cake_cutting"),
        hz.PatternSpec.speckle(33, 20, 50, grain=8, seed=99),
    ]:
        assert hz.PatternSpec.from_proto(spec.to_proto()) == spec


def test_ranges_past_the_count_are_refused() -> None:
    spec = hz.PatternSpec.hadamard(4, 4)
    with pytest.raises(IndexError):
        hz.patterns(spec, 0, spec.count + 1)


def test_the_server_canonicalises_specs_as_this_package_does(client, session_id) -> None:  # type: ignore[no-untyped-def]
    spec = hz.PatternSpec("bernoulli", 13, 11, 100, seed=7, fill=0.3)
    s = client.create_session(session_id, spec, channels=["bucket"])
    assert s.created is True
    assert s.spec == spec.canonical()
    assert s.spec.fill == 0.3000030517578125
    assert client.session(session_id).spec == spec.canonical()
