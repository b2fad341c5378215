"""The pattern generator is bit-exact with PATTERNS.md: every entry of
proto/tests/pattern_vectors.json (which the Rust generator is tested against too)."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

import helmholtz as hz
from helmholtz.patterns import (
    PatternGenerator,
    adaptive_patterns,
    basis_functions,
    basis_gains,
    ordering_table,
    random_words,
)
from helmholtz._proto.v1 import acquisition_pb2 as pb
from helmholtz.spec import ADAPTIVE_FAMILIES, HAAR_PERSISTENCE, SpecError, fill_quantum

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
def test_adaptive_patterns_and_runs(vector: dict) -> None:
    spec = hz.PatternSpec.from_dict(vector["input"])
    assert spec.to_dict() == vector["spec"] and spec.adaptive
    assert spec.pixels == vector["pixels"]
    indices = vector["basis_indices"]
    gen = PatternGenerator(spec, indices)
    assert gen.words_per_pattern == vector["words_per_pattern"]
    assert gen.frames == spec.adaptive_rows(len(indices))
    every = adaptive_patterns(spec, indices)
    assert every.shape == (gen.frames, spec.height, spec.width)
    for p in vector["patterns"]:
        i = p["index"]
        if spec.single_frames:  # frames 0, 1: index 0's pair; frame r + 1: the r-th index's P+
            position, positive = max(i - 1, 0), i != 1
        else:
            position, positive = i // 2, i % 2 == 0
        # "pair" is the position in the index sequence (for single frames too).
        assert (p["pair"], p["basis_index"], p["positive"]) == (position, indices[position], positive)
        assert gen.packed_bits(i, i + 1)[0].astype("<u8").tobytes().hex() == p["bits_hex"], i
        bits = np.unpackbits(
            np.frombuffer(bytes.fromhex(p["bits_hex"]), np.uint8), bitorder="little"
        )[: spec.pixels]
        assert np.array_equal(every[i].reshape(-1), bits.astype(np.float32)), i
        assert np.array_equal(hz.pattern(spec, i, indices=indices), every[i])
    for run in vector["runs"]:
        assert gen.run_sha256(run["start"], run["count"]) == run["sha256"], run
        words = gen.packed_bits(run["start"], run["start"] + run["count"])
        bits = np.unpackbits(words.astype("<u8").view(np.uint8), axis=1, bitorder="little")
        frames = every[run["start"] : run["start"] + run["count"]]
        assert np.array_equal(frames.reshape(len(frames), -1), bits[:, : spec.pixels])


@pytest.mark.parametrize("family", ADAPTIVE_FAMILIES)
def test_adaptive_bases_are_orthogonal_split_pairs(family: str) -> None:
    spec = hz.PatternSpec.from_dict({"family": family, "width": 8, "height": 8, "count": 128})
    everything = list(range(64))
    w = basis_functions(spec, everything).reshape(64, -1).astype(np.float64)
    g = basis_gains(spec, everything)
    # Orthonormal once divided by the gains: the coefficient of a pair is (y+ - y-) / g_n.
    assert np.allclose((w / g[:, None]) @ (w / g[:, None]).T, np.eye(64), atol=1e-12)
    frames = adaptive_patterns(spec, everything).reshape(128, -1)
    assert np.array_equal(frames[0::2] - frames[1::2], w)
    assert np.array_equal(frames[0::2] + frames[1::2], (w != 0).astype(np.float32))
    # PATTERNS.md's worked Haar examples (W = 4).
    if family == "adaptive_haar":
        four = hz.PatternSpec.adaptive_haar(4)
        w4 = basis_functions(four, [1, 6, 15])
        assert w4[0].tolist() == [[1, 1, -1, -1]] * 4
        assert w4[1].tolist() == [[0, 0, 0, 0], [0, 0, 0, 0], [1, -1, 0, 0], [1, -1, 0, 0]]
        assert w4[2].tolist() == [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, -1], [0, 0, -1, 1]]
        assert basis_gains(four, [0, 1, 6, 15]).tolist() == [4.0, 4.0, 2.0, 2.0]


@pytest.mark.parametrize("replay", VECTORS["adaptive_replays"], ids=lambda r: f"{r['spec']['family']}-{r['spec']['width']}-{r['channels']}ch-{r['spec']['count']}")
def test_adaptive_replay_frames_are_the_patterns_on_the_vectors_scene(replay: dict) -> None:
    # The simulated rig of the vectors (patterns_ref.build: an edge, a bright square and a ramp,
    # a dark level d, an integer read noise in [-noise, noise]) measured these frames; ours give
    # the same integers, frame for frame, but for that noise.
    spec = hz.PatternSpec.from_dict(replay["spec"])
    w, c = spec.width, replay["channels"]
    y, x = np.mgrid[0:w, 0:w]
    scenes = [
        3 * x + np.where((x - (6 + 4 * i)) ** 2 + (y - 9) ** 2 < 20, 40, 0) + np.where(y > 12, 25, 0)
        for i in range(c)
    ]
    frames = np.asarray(replay["frames"], dtype=np.int64).reshape(-1, c)
    indices = replay["indices"][: spec.adaptive_indices_in(len(frames))]
    pats = adaptive_patterns(spec, indices, dtype=np.int64)
    assert len(pats) == len(frames) == spec.adaptive_rows(len(indices))
    pats = pats.reshape(len(frames), -1)
    sums = np.stack([pats @ t.reshape(-1) for t in scenes], axis=1)
    dark = frames - sums - replay["dark"]
    assert (np.abs(dark) <= replay["noise"]).all(), "the dark level and the rig's noise alone"
    assert replay["noise"] == 0 or dark.std() > replay["noise"] / 3, "the noise is there"


def test_adaptive_specs_need_their_indices() -> None:
    spec = hz.PatternSpec.adaptive_hadamard(4, 8)
    with pytest.raises(ValueError, match="indices"):
        hz.patterns(spec)
    with pytest.raises(ValueError, match="already shown"):
        hz.patterns(spec, indices=[1, 2, 1])
    with pytest.raises(ValueError, match="out of range"):
        adaptive_patterns(spec, [16])
    with pytest.raises(ValueError, match="split pairs"):
        hz.patterns(spec, indices=[0, 1, 2, 3, 4])  # a budget of 8 frames is 4 pairs
    with pytest.raises(ValueError, match="only the adaptive families"):
        hz.patterns(hz.PatternSpec.hadamard(4, 4), indices=[0])
    assert hz.patterns(spec, indices=[5, 0]).shape == (4, 4, 4)
    with pytest.raises(IndexError):
        hz.patterns(spec, 0, 6, indices=[5, 0])


SINGLE_4X4 = [0, 1, 4, 5, 2, 8, 10, 3, 9, 11, 6, 12, 14, 7, 13, 15]
"""A whole single-frame session on 4 x 4 in block order (PATTERNS.md "Single frames"): index 0,
the root block's details x, y, xy (1, 4, 5), then the four quadrant blocks' (2, 8, 10), (3, 9,
11), (6, 12, 14), (7, 13, 15)."""


def test_single_frame_patterns_are_index_0s_pair_then_one_p_plus_per_index() -> None:
    spec = hz.PatternSpec.adaptive_haar(4, frames="single")
    assert (spec.frames, spec.count, spec.single_frames) == ("single", 17, True)
    frames = adaptive_patterns(spec, [0, 1, 4, 5])
    assert frames.shape == (5, 4, 4) and frames.dtype == np.float32
    assert frames[0].all() and not frames[1].any(), "index 0: all on, then all off"
    plus = adaptive_patterns(hz.PatternSpec.adaptive_haar(4), [1, 4, 5])[0::2]
    assert np.array_equal(frames[2:], plus), "then the P+ of indices 1, 4, 5 alone"
    assert frames[2].astype(int).tolist() == [[1, 1, 0, 0]] * 4
    assert frames[3].astype(int).tolist() == [[1, 1, 1, 1]] * 2 + [[0, 0, 0, 0]] * 2
    assert frames[4].astype(int).tolist() == [[1, 1, 0, 0]] * 2 + [[0, 0, 1, 1]] * 2
    # A later batch (no index 0) is one frame per index.
    assert np.array_equal(adaptive_patterns(spec, [2, 8, 10]), adaptive_patterns(spec, SINGLE_4X4)[5:8])
    # The frame layout R(j): R(0) = 0, R(j) = j + 1; a batch starting at the j-th index
    # starts at frame R(j).
    assert [spec.adaptive_rows(j) for j in range(5)] == [0, 2, 3, 4, 5]
    assert [spec.adaptive_indices_in(r) for r in range(6)] == [0, 0, 1, 2, 3, 4]
    assert spec.adaptive_budget == 16
    pairs = hz.PatternSpec.adaptive_haar(4)
    assert ([pairs.adaptive_rows(j) for j in range(3)], pairs.adaptive_budget) == ([0, 2, 4], 16)
    with pytest.raises(ValueError, match="adaptive"):
        hz.PatternSpec.hadamard(4, 4).adaptive_rows(1)

    # The generator over a session's whole sequence: 17 frames, packed bits alike.
    gen = PatternGenerator(spec, SINGLE_4X4)
    assert gen.frames == 17
    every = gen.values()
    assert np.array_equal(every, hz.patterns(spec, indices=SINGLE_4X4))
    assert np.array_equal(every, adaptive_patterns(spec, SINGLE_4X4))
    assert np.array_equal(every[:5], frames)
    for i in range(17):
        assert np.array_equal(hz.pattern(spec, i, indices=SINGLE_4X4), every[i])
    bits = np.unpackbits(gen.packed_bits().astype("<u8").view(np.uint8), axis=1, bitorder="little")
    assert np.array_equal(bits[:, :16], every.reshape(17, 16))
    assert PatternGenerator(spec, []).frames == 0
    assert hz.patterns(spec, indices=[0]).shape == (2, 4, 4)
    with pytest.raises(IndexError):
        hz.patterns(spec, 0, 6, indices=[0, 1, 4, 5])

    # The budget counts indices (count - 1), a session starts with index 0, and only there.
    with pytest.raises(ValueError, match="single-frame indices"):
        hz.patterns(spec.with_count(4), indices=[0, 1, 4, 5])
    assert hz.patterns(spec.with_count(5), indices=[0, 1, 4, 5]).shape == (5, 4, 4)
    with pytest.raises(ValueError, match="starts with index 0"):
        hz.patterns(spec, indices=[1, 4, 5])
    with pytest.raises(ValueError, match="index 0 at position 2"):
        adaptive_patterns(spec, [1, 4, 0])


def test_single_frames_give_the_split_pair_values_noise_free() -> None:
    # PATTERNS.md "Single frames", Values: y- = Q(B) - y+ with the blocks' pair sums Q derived
    # from index 0's pair and each split block's details: on a noiseless rig the values of
    # the split-pair session of the same indices, from 17 frames instead of 32.
    spec = hz.PatternSpec.adaptive_haar(4, frames="single")
    scene = np.random.default_rng(3).random(16)
    dark = 0.25
    y = adaptive_patterns(spec, SINGLE_4X4).reshape(17, 16).astype(np.float64) @ scene + dark
    pairs = adaptive_patterns(hz.PatternSpec.adaptive_haar(4), SINGLE_4X4).reshape(32, 16)
    want = pairs.astype(np.float64) @ scene + dark
    w, dark_frame = 4, y[1]
    q = {(2, 0, 0): y[0] + y[1]}  # Q(root)
    got = [(y[0], y[1])]
    frame = 2
    for s, pr, pc in [(2, 0, 0), (1, 0, 0), (1, 0, 1), (1, 1, 0), (1, 1, 1)]:
        h = w >> s
        details = (pr * w + h + pc, (h + pr) * w + pc, (h + pr) * w + h + pc)
        assert [SINGLE_4X4[frame - 1 + j] for j in range(3)] == list(details)
        d = []
        for _ in details:
            plus = y[frame]
            minus = q[(s, pr, pc)] - plus
            got.append((plus, minus))
            d.append(plus - minus)
            frame += 1
        if s >= 2:
            light = q[(s, pr, pc)] - 2.0 * dark_frame
            dx, dy, dxy = d
            for (dr, dc), sign in zip(((0, 0), (0, 1), (1, 0), (1, 1)), ((1, 1, 1), (-1, 1, -1), (1, -1, -1), (-1, -1, 1))):
                q[(s - 1, 2 * pr + dr, 2 * pc + dc)] = (
                    (((light + sign[0] * dx) + sign[1] * dy) + sign[2] * dxy) * 0.25
                ) + 2.0 * dark_frame
    assert frame == 17
    assert np.allclose(np.asarray(got).reshape(-1), want, rtol=0, atol=1e-12)


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
        # The adaptive families (the server's own refusals, proto/src/patterns/spec.rs).
        (dict(family="adaptive_haar", width=12, height=12, count=8), "width"),
        (dict(family="adaptive_hadamard", width=16, height=8, count=8), "height"),
        (dict(family="adaptive_hadamard", width=8, height=8, count=7), "count"),
        (dict(family="adaptive_haar", width=8, height=8, count=130), "count"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, batch=65), "batch"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, batch=-1), "batch"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, target_error=-1), "target_error"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, target_error=float("nan")), "target_error"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, target_error="0.1"), "target_error"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, persistence=-0.5), "persistence"),
        (dict(family="adaptive_hadamard", width=8, height=8, count=8, persistence=float("inf")), "persistence"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, persistence="0.5"), "persistence"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, error_estimate="oracle"), "error_estimate"),
        (dict(family="adaptive_hadamard", width=8, height=8, count=8, ordering="natural"), "ordering"),
        (dict(family="hadamard", width=8, height=8, count=8, batch=4), "batch"),
        # frames (PATTERNS.md "Single frames"): adaptive_haar only, pairs or single; a
        # single-frame budget is 2 ..= k + 1 frames.
        (dict(family="adaptive_hadamard", width=8, height=8, count=8, frames="single"), "frames"),
        (dict(family="adaptive_hadamard", width=12, height=12, count=8, frames="single"), "frames"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, frames="triple"), "frames"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, frames="Single"), "frames"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, frames=None), "frames"),
        (dict(family="adaptive_haar", width=8, height=8, count=8, frames=2), "frames"),
        (dict(family="hadamard", width=8, height=8, count=8, frames="single"), "frames"),
        (dict(family="adaptive_haar", width=8, height=8, count=1, frames="single"), "count"),
        (dict(family="adaptive_haar", width=8, height=8, count=66, frames="single"), "count"),
        (dict(family="adaptive_haar", width=8, height=8, count=7, frames="pairs"), "count"),
        (dict(family="adaptive_haar", width=8, height=8, count=65, frames="pairs"), "count"),
        (dict(family="adaptive_haar", width=12, height=12, count=9, frames="single"), "width"),
        (dict(family="adaptive_haar", width=8, height=8, count=9, frames="single", batch=65), "batch"),
    ]
    for raw, field in cases:
        with pytest.raises(hz.SpecError) as e:
            hz.PatternSpec.from_dict(raw)
        assert e.value.field == field, (raw, e.value)
    # The constructors: adaptive_hadamard refuses single frames, naming the field.
    with pytest.raises(hz.SpecError) as e:
        hz.PatternSpec.adaptive_hadamard(8, 64, frames="single")
    assert e.value.field == "frames" and "adaptive_haar" in str(e.value)
    with pytest.raises(hz.SpecError) as e:
        hz.PatternSpec.adaptive_haar(8, 66, frames="single")
    assert e.value.field == "count" and "2..=65" in str(e.value)
    with pytest.raises(hz.SpecError) as e:
        hz.PatternSpec("adaptive_hadamard", 8, 8, 9, frames="single").canonical()
    assert e.value.field == "frames"


def test_single_frame_specs_json_form() -> None:
    spec = hz.PatternSpec.adaptive_haar(128, 3277, frames="single")
    # PATTERNS.md's canonical key order: frames after error_estimate, stated only when single.
    assert list(spec.to_dict()) == [
        "family", "batch", "target_error", "persistence", "error_estimate", "frames",
        "width", "height", "count", "seed",
    ]
    assert spec.to_dict()["frames"] == "single"
    assert json.dumps(spec.to_dict(), separators=(",", ":")) == (
        '{"family":"adaptive_haar","batch":0,"target_error":0.0,"persistence":0.5,'
        '"error_estimate":"measured","frames":"single","width":128,"height":128,"count":3277,"seed":0}'
    )
    assert hz.PatternSpec.from_dict(spec.to_dict()) == spec
    assert hz.PatternSpec.from_dict(json.loads(json.dumps(spec.to_dict()))) == spec
    # Odd and even budgets, 2 ..= k + 1 (the whole basis by default).
    assert hz.PatternSpec.adaptive_haar(8, frames="single").count == 65
    for count in (2, 3, 64, 65):
        assert hz.PatternSpec.adaptive_haar(8, count, frames="single").count == count
    # Pairs (explicit or left out) is the old canonical form, without frames.
    pairs = hz.PatternSpec.from_dict(
        {"family": "adaptive_haar", "width": 8, "height": 8, "count": 64, "frames": "pairs"}
    )
    assert pairs.frames is None and not pairs.single_frames
    assert pairs == hz.PatternSpec.adaptive_haar(8, 64) == hz.PatternSpec.adaptive_haar(8, 64, frames="pairs")
    assert "frames" not in pairs.to_dict()
    hadamard = hz.PatternSpec.adaptive_hadamard(8, 64, frames="pairs")
    assert hadamard.frames is None and "frames" not in hadamard.to_dict()
    # The server's session JSON (GET /v1/sessions/{id}) parses back.
    view = {
        "id": "s", "rig": "", "patterns": spec.to_dict(), "channels": ["bucket"],
        "committed_rows": 0, "expected_rows": 3277, "state": "open",
    }
    assert hz.Session.from_view(view).spec == spec


def test_single_frame_specs_protobuf_form() -> None:
    spec = hz.PatternSpec.adaptive_haar(16, 101, batch=8, target_error=0.02, frames="single")
    msg = spec.to_proto()
    assert msg.adaptive.frames == pb.ADAPTIVE_FRAMES_SINGLE
    assert hz.PatternSpec.from_proto(msg) == spec
    again = pb.PatternSpec()
    again.ParseFromString(msg.SerializeToString())
    assert hz.PatternSpec.from_proto(again) == spec
    # Pairs: unset (0) on the wire, as before the field; PAIRS and unset both read as pairs.
    pairs = hz.PatternSpec.adaptive_haar(16, 100)
    assert pairs.to_proto().adaptive.frames == pb.ADAPTIVE_FRAMES_UNSPECIFIED
    explicit = pairs.to_proto()
    explicit.adaptive.frames = pb.ADAPTIVE_FRAMES_PAIRS
    assert hz.PatternSpec.from_proto(explicit) == pairs == hz.PatternSpec.from_proto(pairs.to_proto())
    # Refusals name the field.
    unknown = spec.to_proto()
    unknown.adaptive.frames = 7
    with pytest.raises(SpecError) as e:
        hz.PatternSpec.from_proto(unknown)
    assert e.value.field == "frames"
    walsh = hz.PatternSpec.adaptive_hadamard(16, 100).to_proto()
    walsh.adaptive.frames = pb.ADAPTIVE_FRAMES_SINGLE
    with pytest.raises(SpecError) as e:
        hz.PatternSpec.from_proto(walsh)
    assert e.value.field == "frames"
    odd_pairs = spec.to_proto()
    odd_pairs.adaptive.frames = pb.ADAPTIVE_FRAMES_PAIRS
    with pytest.raises(SpecError) as e:
        hz.PatternSpec.from_proto(odd_pairs)  # 101 frames are not whole pairs
    assert e.value.field == "count"


def test_protobuf_form_round_trips() -> None:
    for spec in [
        hz.PatternSpec.raster(10, 7, 30, block=3, scans=3),
        hz.PatternSpec.bernoulli(13, 11, 100, fill=0.3, seed=2**64 - 1),
        hz.PatternSpec.hadamard(16, 4, ordering="cake_cutting"),
        hz.PatternSpec.speckle(33, 20, 50, grain=8, seed=99),
        hz.PatternSpec.adaptive_haar(32, 400, batch=10, target_error=0.05),
        hz.PatternSpec.adaptive_haar(32, 400, persistence=0.0),
        hz.PatternSpec.adaptive_hadamard(16),
        hz.PatternSpec.adaptive_hadamard(16, persistence=1.5),
        hz.PatternSpec.adaptive_hadamard(16, target_error=0.1, error_estimate="prediction"),
        hz.PatternSpec.adaptive_haar(16, 257, frames="single"),
        hz.PatternSpec.adaptive_haar(16, 30, batch=4, persistence=0.0, frames="single"),
    ]:
        assert hz.PatternSpec.from_proto(spec.to_proto()) == spec
    # proto3 zeros (and no params at all) are the adaptive defaults; an explicit persistence
    # of 0 is kept.
    assert hz.PatternSpec.adaptive_haar(8, 64, persistence=0.0).to_proto().adaptive.HasField("persistence")
    bare = hz.PatternSpec.from_proto(
        hz.PatternSpec.adaptive_haar(8, 64).to_proto().__class__(family=5, width=8, height=8, count=64)
    )
    assert bare.to_dict() == {
        "family": "adaptive_haar", "batch": 0, "target_error": 0.0, "persistence": 0.5,
        "error_estimate": "measured", "width": 8, "height": 8, "count": 64, "seed": 0,
    }
    wrong = hz.PatternSpec.adaptive_hadamard(8).to_proto()
    wrong.hadamard.ordering = 1
    with pytest.raises(SpecError) as e:
        hz.PatternSpec.from_proto(wrong)
    assert e.value.field == "params"


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


@pytest.mark.parametrize("family", ADAPTIVE_FAMILIES)
def test_the_server_canonicalises_adaptive_specs_as_this_package_does(client, session_id, family) -> None:  # type: ignore[no-untyped-def]
    spec = hz.PatternSpec(family, 8, 8, 40, target_error=0.05)
    s = client.create_session(f"{session_id}-{family}", spec, channels=["bucket"])
    assert s.created is True and s.spec.adaptive
    assert s.spec == spec.canonical()
    assert s.spec.to_dict() == {
        "family": family, "batch": 0, "target_error": 0.05,
        "persistence": HAAR_PERSISTENCE if family == "adaptive_haar" else 0.0,
        "error_estimate": "measured", "width": 8, "height": 8, "count": 40, "seed": 0,
    }
    assert client.session(s.id).spec == spec.canonical()


def test_the_server_canonicalises_single_frame_specs_as_this_package_does(client, session_id) -> None:  # type: ignore[no-untyped-def]
    # Needs the server's single-frame support (PATTERNS.md "Single frames").
    spec = hz.PatternSpec.adaptive_haar(8, 41, target_error=0.05, frames="single")
    s = client.create_session(session_id, spec, channels=["bucket"])
    assert s.created is True and s.spec.single_frames
    assert s.spec == spec  # gRPC: AdaptiveParams.frames
    assert s.expected_rows == 41
    view = client.session(session_id)  # REST: the canonical JSON states "frames": "single"
    assert view.spec == spec and view.spec.to_dict()["frames"] == "single"
    # A pairs spec keeps its old canonical form (no frames key) on the server too.
    pairs = client.create_session(f"{session_id}-pairs", hz.PatternSpec.adaptive_haar(8, 40), channels=["bucket"])
    assert pairs.spec.frames is None and "frames" not in client.session(pairs.id).spec.to_dict()
