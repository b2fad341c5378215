"""Adaptive acquisition from Python (``Client.acquire``, gRPC ``Acquire``) against the real
server: a simulated rig runs adaptive sessions to their end and the stored session reconstructs
to the scene; the index sequence is what the server stores (``adaptive.json``) and what the
independent reference planner (proto/tools/patterns_ref.py) replays from the stored values; a
rig whose stream is cut, and one that restarts, resume with the indices of an uninterrupted
run; bad values are refused with nothing stored; refusals of the server are ``AcquireError``.
Single-frame sessions (``frames="single"``, PATTERNS.md "Single frames") run, resume and
reconstruct the same way with one frame per index."""

from __future__ import annotations

import importlib.util
import math
import sys
import time
from typing import Any, Optional

import grpc
import numpy as np
import pytest

import helmholtz as hz
from helmholtz._proto.v1 import acquisition_pb2 as pb
from helmholtz.crc32c import crc32c

from conftest import REPO_ROOT, CuttingProxy


def _reference() -> Any:
    """proto/tools/patterns_ref.py: PATTERNS.md's planner written independently (stdlib only)."""
    path = REPO_ROOT / "proto" / "tools" / "patterns_ref.py"
    spec = importlib.util.spec_from_file_location("patterns_ref", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("patterns_ref", module)
    spec.loader.exec_module(module)
    return module


REF = _reference()
DARK = 0.05


def scene(side: int, shift: float = 0.0) -> np.ndarray:
    """A smooth blob, an edge and a floor: what the projector lights (float64, (side, side))."""
    y, x = np.mgrid[0:side, 0:side] / (side - 1)
    blob = np.exp(-((x - 0.4 - shift) ** 2 + (y - 0.55) ** 2) / 0.05)
    return 0.2 + 0.6 * blob + 0.2 * (x > 0.7)


class Rig:
    """A noiseless bucket rig: bucket = sum(pattern * scene) + a dark level, per channel. It
    keeps every frame it was shown."""

    def __init__(self, *scenes: np.ndarray, dark: float = DARK, pairs: bool = True):
        self.t = np.stack([s.reshape(-1) for s in scenes], axis=1)  # (k, channels)
        self.dark = dark
        self.pairs = pairs  # split pairs: an even number of frames per batch
        self.shown: list[np.ndarray] = []

    def __call__(self, patterns: np.ndarray) -> np.ndarray:
        assert patterns.dtype == np.float32 and patterns.ndim == 3
        assert patterns.shape[0] > 0 and (patterns.shape[0] % 2 == 0 or not self.pairs)
        self.shown.append(patterns.copy())
        return patterns.reshape(len(patterns), -1).astype(np.float64) @ self.t + self.dark

    @property
    def frames(self) -> np.ndarray:
        return np.concatenate(self.shown)


def relative_error(image: np.ndarray, truth: np.ndarray) -> float:
    return float(np.linalg.norm(image - truth) / np.linalg.norm(truth))


def reconstruct(client: hz.Client, sid: str, method: str = "direct") -> np.ndarray:
    rec = client.wait(client.reconstruct(sid, method), timeout=120)
    return client.dual_image(rec)


def create(client: hz.Client, sid: str, spec: hz.PatternSpec, channels: int = 1) -> hz.Session:
    names = ["bucket"] if channels == 1 else [f"c{i}" for i in range(channels)]
    return client.create_session(sid, spec, channels=names)


def check_stored(client: hz.Client, sid: str, report: hz.AdaptiveReport, channels: int = 1) -> None:
    """The stored sequence is the rig's, replays (reference planner) from the stored values,
    and the stored rows are what the rig measured under the patterns of that sequence."""
    stored = client.adaptive_sequence(sid)
    assert stored["session_id"] == sid
    assert stored["indices"] == report.indices
    assert [b["number"] for b in stored["batches"]] == list(range(report.batches))
    assert sum(len(b["indices"]) for b in stored["batches"]) == len(report.indices)
    session = client.session(sid)
    spec = session.spec
    assert stored["issued_rows"] == spec.adaptive_rows(len(report.indices))
    before = 0
    for b in stored["batches"]:  # each batch starts at R(indices before it)
        assert b["first_row"] == spec.adaptive_rows(before), b
        before += len(b["indices"])
    values = client.measurements(sid)
    assert values.shape == (report.rows, channels)
    replayed = REF.replay(session.spec.to_dict(), channels, values.reshape(-1).tolist())
    assert replayed == report.indices, "the reference planner replays the stored sequence"


@pytest.mark.parametrize("family", hz.ADAPTIVE_FAMILIES)
def test_an_adaptive_session_runs_its_budget_and_direct_gives_the_scene(client, session_id, family) -> None:  # type: ignore[no-untyped-def]
    truth = scene(16)
    spec = hz.PatternSpec.from_dict({"family": family, "width": 16, "height": 16, "count": 512, "batch": 16})
    session = create(client, session_id, spec)
    rig = Rig(truth)
    report = client.acquire(session, rig)
    assert report.session_id == session_id
    assert (report.reason, report.rows, report.batches) == ("budget", 512, 16), report
    assert sorted(report.indices) == list(range(256)), "every basis function once"
    assert report.reconnects == 0 and report.measure_calls == 16
    assert report.frames_measured == 512 and report.rows_sent == 512
    assert report.rows_written == 512 and report.rows_matched == 0
    assert report.estimated_error is not None and report.estimated_error < 1e-9  # nothing left
    assert all(len(f) == 32 for f in rig.shown), "batches of 16 split pairs"
    # The rig was shown exactly the session's patterns, in order.
    assert np.array_equal(rig.frames, hz.patterns(spec, indices=report.indices))
    s = client.session(session_id)
    assert (s.state, s.committed_rows) == ("finished", 512)
    check_stored(client, session_id, report)
    image = reconstruct(client, session_id, "direct")
    assert image.shape == (16, 16)
    # The dark level cancels in the pair differences: the whole basis inverts exactly.
    error = relative_error(image, truth)
    assert error < 1e-5, f"{family}: direct on the whole basis, error {error}"


def test_a_quarter_of_the_basis_chosen_adaptively_gives_a_close_image(client, session_id) -> None:  # type: ignore[no-untyped-def]
    # 32x32, a budget of 256 split pairs (a quarter of the basis), batches sized by the server.
    truth = scene(32)
    spec = hz.PatternSpec.adaptive_haar(32, 512)
    session = create(client, session_id, spec)
    rig = Rig(truth)
    report = client.acquire(session, rig)
    assert (report.reason, report.rows, len(report.indices)) == ("budget", 512, 256), report
    assert np.array_equal(rig.frames, hz.patterns(spec, indices=report.indices))
    check_stored(client, session_id, report)
    image = reconstruct(client, session_id, "direct")
    error = relative_error(image, truth)
    # Measured: 0.0400 (the planner follows the blob and the edge); the first 256 Haar
    # functions in index order (coarse to fine, no adaptation) give 0.0735 on this scene.
    assert error < 0.045, f"direct on an adaptive quarter of the Haar basis: error {error}"
    w = hz.basis_functions(spec, list(range(256))).reshape(256, -1) / hz.basis_gains(spec, list(range(256)))[:, None]
    fixed = (w.T @ (w @ truth.reshape(-1))).reshape(32, 32)
    assert error < 0.6 * relative_error(fixed, truth), "the adaptive choice beats the fixed order"
    # The choice depends on the scene: another scene, another sequence.
    other = Rig(scene(32, shift=0.3))
    again = client.acquire(create(client, f"{session_id}-other", spec), other)
    assert again.indices != report.indices


def test_the_target_error_stops_the_session_early(client, session_id) -> None:  # type: ignore[no-untyped-def]
    truth = scene(32)
    spec = hz.PatternSpec.adaptive_hadamard(32, 2048, batch=32, target_error=0.05)
    report = client.acquire(create(client, session_id, spec), Rig(truth))
    assert report.reason == "target_error", report
    assert report.estimated_error is not None and report.estimated_error < 0.05
    assert report.rows == 2 * len(report.indices) < 2048
    s = client.session(session_id)
    assert (s.state, s.committed_rows) == ("finished", report.rows)
    check_stored(client, session_id, report)


def test_two_channels(client, session_id) -> None:  # type: ignore[no-untyped-def]
    spec = hz.PatternSpec.adaptive_haar(16, 200, batch=12)
    scenes = (scene(16), scene(16, shift=0.25))
    report = client.acquire(create(client, session_id, spec, channels=2), Rig(*scenes))
    assert (report.reason, report.rows) == ("budget", 200)
    check_stored(client, session_id, report, channels=2)


def test_a_camera_session(client, session_id) -> None:  # type: ignore[no-untyped-def]
    # A 2x2 camera in place of the bucket: each frame is T p for a transport T (4 x 64).
    spec = hz.PatternSpec.adaptive_hadamard(8, 128, batch=16)
    T = np.kron(np.random.default_rng(1).random((4, 4, 4)), np.ones((2, 2))).reshape(4, 64)
    shown: list[np.ndarray] = []

    def camera(patterns: np.ndarray) -> np.ndarray:
        frames = (patterns.reshape(len(patterns), -1) @ T.T).astype(np.float32).reshape(-1, 2, 2)
        shown.append(frames)
        return frames

    session = client.create_session(session_id, spec, camera=hz.Camera(2, 2, "f32"))
    report = client.acquire(session, camera)
    assert (report.reason, report.rows, report.batches) == ("budget", 128, 4), report
    assert np.array_equal(client.measurements(session), np.concatenate(shown))
    rec = client.wait(client.reconstruct(session, "transport"), timeout=120)
    relit = client.relight(rec, np.ones((2, 2)))  # T^T 1: the whole camera as the light
    want = T.sum(axis=0).reshape(8, 8)
    assert np.abs(relit - want).max() < 1e-4 * want.max(), np.abs(relit - want).max()


def single_frame_order_holds(spec: hz.PatternSpec, indices: list[int]) -> None:
    """PATTERNS.md "Single frames", Selection: index 0 first, then whole block splits (a
    block's x, y, xy details in a row), each block split after its parent block."""
    w = spec.width
    m = w.bit_length() - 1
    assert indices[0] == 0
    rest = indices[1:]
    split = {(m, 0, 0)}  # the root may be split at once
    done: set[tuple[int, int, int]] = set()
    for at in range(0, len(rest), 3):
        x = rest[at]
        r, c = divmod(x, w)
        s = m - (max(r, c).bit_length() - 1)
        h = w >> s
        assert c >= h and r < h, f"block splits open with their x detail, got {x}"
        block = (s, r % h, c % h)
        pr, pc = block[1], block[2]
        details = [pr * w + h + pc, (h + pr) * w + pc, (h + pr) * w + h + pc]
        assert rest[at : at + 3] == details[: len(rest) - at], (block, rest[at : at + 3])
        assert block in split and block not in done, f"block {block} split before its parent"
        done.add(block)
        if s >= 2:
            split |= {(s - 1, 2 * pr + dr, 2 * pc + dc) for dr in (0, 1) for dc in (0, 1)}


def test_a_single_frame_session_runs_its_budget_in_about_half_the_frames(client, session_id) -> None:  # type: ignore[no-untyped-def]
    # Needs the server's single-frame support (PATTERNS.md "Single frames").
    truth = scene(16)
    spec = hz.PatternSpec.adaptive_haar(16, frames="single", batch=16)
    assert spec.count == 257, "the whole basis: index 0's pair and 255 single frames"
    session = create(client, session_id, spec)
    assert session.spec == spec and session.expected_rows == 257
    rig = Rig(truth, pairs=False)
    report = client.acquire(session, rig)
    assert (report.reason, report.rows, report.batches) == ("budget", 257, 16), report
    assert sorted(report.indices) == list(range(256)), "every basis function once"
    single_frame_order_holds(spec, report.indices)
    assert report.reconnects == 0 and report.measure_calls == 16
    assert report.frames_measured == 257 and report.rows_sent == 257
    assert report.rows_written == 257 and report.rows_matched == 0
    # The first batch is index 0's pair and 15 single frames; the others 16 single frames.
    assert [len(f) for f in rig.shown] == [17] + [16] * 15
    assert rig.shown[0][0].all() and not rig.shown[0][1].any()
    assert np.array_equal(rig.frames, hz.patterns(spec, indices=report.indices))
    s = client.session(session_id)
    assert (s.state, s.committed_rows) == ("finished", 257)
    check_stored(client, session_id, report)
    # Noise-free, the frames give the values of split pairs: the whole basis inverts.
    image = reconstruct(client, session_id, "direct")
    error = relative_error(image, truth)
    assert error < 1e-5, f"direct on the whole basis from single frames, error {error}"


def test_a_single_frame_session_with_an_odd_budget_and_two_channels(client, session_id) -> None:  # type: ignore[no-untyped-def]
    # 32x32, 301 frames: index 0's pair and 299 single frames (an odd budget), batches sized
    # by the server; two channels.
    spec = hz.PatternSpec.adaptive_haar(32, 301, frames="single")
    scenes = (scene(32), scene(32, shift=0.25))
    rig = Rig(*scenes, pairs=False)
    report = client.acquire(create(client, session_id, spec, channels=2), rig)
    assert (report.reason, report.rows, len(report.indices)) == ("budget", 301, 300), report
    assert len(rig.shown[0]) == len(rig.shown[1]) + 1, "the first batch holds index 0's pair"
    single_frame_order_holds(spec, report.indices)
    assert np.array_equal(rig.frames, hz.patterns(spec, indices=report.indices))
    check_stored(client, session_id, report, channels=2)


def test_a_single_frame_session_resumes_after_a_cut_stream_and_a_restarted_rig(client, server, session_id) -> None:  # type: ignore[no-untyped-def]
    # The resume arithmetic with one frame per index: batch b of 16 indices starts at row
    # 16 b + 1 (b >= 1), the first one holds 17 rows.
    truth = scene(32)
    spec = hz.PatternSpec.adaptive_haar(32, 193, batch=16, frames="single")
    straight = client.acquire(create(client, f"{session_id}-straight", spec), Rig(truth, pairs=False))
    assert (straight.rows, len(straight.indices), straight.batches) == (193, 192, 12)

    proxy = CuttingProxy(server.address.split("://", 1)[1])
    try:
        with hz.Client(proxy.address, server.token) as via_proxy:
            session = create(via_proxy, f"{session_id}-cut", spec)
            rig = Rig(truth, pairs=False)

            def cutting(patterns: np.ndarray) -> np.ndarray:
                if len(rig.shown) == 3 and proxy.cuts == 0:
                    assert proxy.cut_all() > 0
                return rig(patterns)

            cut = via_proxy.acquire(session, cutting)
    finally:
        proxy.close()
    assert cut.reconnects >= 1, cut
    assert (cut.indices, cut.rows, cut.reason) == (straight.indices, 193, "budget")
    check_stored(client, f"{session_id}-cut", cut)

    sid = f"{session_id}-restart"
    session = create(client, sid, spec)
    calls = []

    def failing(patterns: np.ndarray) -> np.ndarray:
        calls.append(len(patterns))
        if len(calls) > 3:
            raise RuntimeError("the rig's lamp failed")
        return Rig(truth, pairs=False)(patterns)

    with pytest.raises(RuntimeError, match="lamp failed"):
        client.acquire(session, failing)
    assert calls[:3] == [17, 16, 16]
    s = client.session(sid)
    assert s.state == "open" and s.committed_rows == 17 + 2 * 16
    rig = Rig(truth, pairs=False)
    again = client.acquire(sid, rig)
    assert again.indices == straight.indices and again.rows == 193
    assert again.frames_measured == 193 - 49 and again.measure_calls == 9, again
    assert np.array_equal(rig.frames, hz.patterns(spec, indices=again.indices)[49:])
    check_stored(client, sid, again)
    # Bad rows of a single-frame batch are refused naming its frame count.
    other = create(client, f"{session_id}-short", spec)
    with pytest.raises(ValueError, match=r"holds 16 rows; 17 frames \(16 single-frame indices\)"):
        client.acquire(other, lambda p: Rig(truth, pairs=False)(p)[:-1])


def test_a_cut_stream_and_a_restarted_rig_resume_with_the_indices_of_an_uninterrupted_run(client, server, session_id) -> None:  # type: ignore[no-untyped-def]
    truth = scene(32)
    spec = hz.PatternSpec.adaptive_hadamard(32, 384, batch=16)
    straight = client.acquire(create(client, f"{session_id}-straight", spec), Rig(truth))
    assert straight.rows == 384

    # The network drops every connection while the rig measures batch 3.
    proxy = CuttingProxy(server.address.split("://", 1)[1])
    try:
        with hz.Client(proxy.address, server.token) as via_proxy:
            session = create(via_proxy, f"{session_id}-cut", spec)
            rig = Rig(truth)

            def cutting(patterns: np.ndarray) -> np.ndarray:
                if len(rig.shown) == 3 and proxy.cuts == 0:
                    assert proxy.cut_all() > 0
                return rig(patterns)

            cut = via_proxy.acquire(session, cutting)
    finally:
        proxy.close()
    assert cut.reconnects >= 1, cut
    assert cut.indices == straight.indices and cut.rows == straight.rows
    assert cut.reason == "budget"
    check_stored(client, f"{session_id}-cut", cut)

    # A rig whose lamp fails at batch 5: the error is the rig's own, the session stays open
    # with the rows measured so far.
    sid = f"{session_id}-restart"
    session = create(client, sid, spec)
    calls = []

    def failing(patterns: np.ndarray) -> np.ndarray:
        calls.append(len(patterns))
        if len(calls) > 5:
            raise RuntimeError("the rig's lamp failed")
        return Rig(truth)(patterns)

    with pytest.raises(RuntimeError, match="lamp failed"):
        client.acquire(session, failing)
    s = client.session(sid)
    assert s.state == "open" and s.committed_rows == 5 * 32
    # Started again from nothing (a new process): batches already stored are not shown again.
    rig = Rig(truth)
    again = client.acquire(sid, rig)
    assert again.indices == straight.indices and again.rows == 384
    assert again.frames_measured == 384 - 5 * 32, again
    assert np.array_equal(rig.frames, hz.patterns(spec, indices=again.indices)[5 * 32 :])
    check_stored(client, sid, again)
    # Acquiring a finished session ends at once with its whole sequence; nothing is measured.
    def never(patterns: np.ndarray) -> np.ndarray:
        raise AssertionError("a finished session measures nothing")

    done = client.acquire(sid, never)
    assert (done.indices, done.rows, done.frames_measured) == (straight.indices, 384, 0)


def test_bad_values_are_refused_with_nothing_stored(client, session_id) -> None:  # type: ignore[no-untyped-def]
    truth = scene(16)
    spec = hz.PatternSpec.adaptive_haar(16, 256, batch=8)
    session = create(client, session_id, spec)
    good = Rig(truth)

    def nan(patterns: np.ndarray) -> np.ndarray:
        values = good(patterns)
        values[3, 0] = math.nan
        return values

    with pytest.raises(ValueError, match=r"batch 0 \(rows 0\.\.16\).*row 3.*not finite"):
        client.acquire(session, nan)
    with pytest.raises(ValueError, match=r"holds 15 rows; 16 frames"):
        client.acquire(session, lambda p: good(p)[:-1])
    with pytest.raises(ValueError, match=r"\(rows, 1\)"):
        client.acquire(session, lambda p: np.repeat(good(p), 2, axis=1))
    with pytest.raises(ValueError, match="numbers"):
        client.acquire(session, lambda p: np.array(["x"] * len(p)))
    assert client.upload_status(session).committed_rows == 0, "nothing stored"
    assert client.measurements(session).shape[0] == 0
    stored = client.adaptive_sequence(session)
    assert stored["issued_rows"] == 32, "two batches of 8 pairs issued ahead, none measured"

    # The server refuses them too (a rig bypassing the checks): a raw Acquire stream.
    def raw(chunk: pb.MeasurementChunk) -> grpc.RpcError:
        for _ in range(100):
            requests = [
                pb.AcquireRequest(open=pb.AcquireOpen(session_id=session.id)),
                pb.AcquireRequest(chunk=chunk),
            ]
            responses = client._stub().Acquire(
                iter(requests), metadata=client._metadata(hz.new_writer_id())
            )
            with pytest.raises(grpc.RpcError) as e:
                for r in responses:
                    assert r.WhichOneof("message") != "ack", r
            # The previous stream (another writer) may hold the session a moment longer.
            if e.value.code() != grpc.StatusCode.ABORTED:
                return e.value
            time.sleep(0.05)
        raise AssertionError(f"the session stayed held: {e.value}")

    def chunk(values: np.ndarray, channels: int = 1) -> pb.MeasurementChunk:
        payload = np.ascontiguousarray(values, dtype="<f8").tobytes()
        return pb.MeasurementChunk(
            session_id=session.id, start_row=0, channels=channels,
            values_f64le=payload, crc32c=crc32c(payload),
        )

    rows = np.ones(16)
    rows[3] = math.nan
    e = raw(chunk(rows))
    assert e.code() == grpc.StatusCode.INVALID_ARGUMENT and "values_f64le" in e.details(), e
    e = raw(chunk(np.ones(34)))  # beyond the 32 issued rows
    assert e.code() == grpc.StatusCode.FAILED_PRECONDITION and e.details().startswith("start_row"), e
    e = raw(chunk(np.ones(16), channels=2))
    assert e.code() == grpc.StatusCode.INVALID_ARGUMENT and "channels" in e.details(), e
    assert client.upload_status(session).committed_rows == 0, "nothing stored"

    # The session is still whole: a good rig runs it to the end.
    report = client.acquire(session, good)
    assert (report.reason, report.rows) == ("budget", 256)
    check_stored(client, session.id, report)


def test_refusals_of_the_server_are_acquire_errors(client, server, session_id) -> None:  # type: ignore[no-untyped-def]
    def never(patterns: np.ndarray) -> np.ndarray:
        raise AssertionError("nothing to measure")

    plain = client.create_session(session_id, hz.PatternSpec.hadamard(8, 8), channels=["bucket"])
    with pytest.raises(ValueError, match="not an adaptive family"):
        client.acquire(plain, never)
    with pytest.raises(hz.AcquireError) as e:
        client.acquire(plain.id, never)  # by id: the server says so
    assert e.value.code_name == "FAILED_PRECONDITION" and e.value.message.startswith("session_id")
    assert e.value.committed_rows == 0 and not e.value.gave_up
    assert isinstance(e.value, hz.RpcError) and "adaptive acquisition of session" in str(e.value)
    with pytest.raises(hz.AcquireError) as e:
        client.acquire(f"{session_id}-nobody", never)
    assert e.value.code_name == "NOT_FOUND"

    spec = hz.PatternSpec.adaptive_haar(8, 32)
    mine = client.create_session(f"{session_id}-mine", spec, channels=["bucket"])
    with hz.Client(server.address, server.create_token("py-other-lab", "rig,reader")) as other:
        with pytest.raises(hz.AcquireError) as e:
            other.acquire(mine.id, never)
        assert e.value.code_name == "NOT_FOUND"
    with hz.Client(server.address, server.create_token("py", "reader")) as reader:
        with pytest.raises(hz.AcquireError) as e:
            reader.acquire(mine.id, never)
        assert e.value.code_name == "PERMISSION_DENIED"
    assert client.adaptive_sequence(mine)["issued_rows"] == 0, "no batch was issued to them"
    with pytest.raises(hz.ApiError) as api:
        client.adaptive_sequence(plain)
    assert api.value.status == 409


def test_an_unreachable_server_gives_up_after_retry_for(session_id) -> None:  # type: ignore[no-untyped-def]
    import socket

    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]
    # Nothing listens there any more.
    policy = hz.RetryPolicy(retry_for=1.0, backoff=hz.Backoff(initial=0.05, max=0.2))
    with hz.Client(f"http://127.0.0.1:{port}", "hz_none", retry=policy) as c:
        with pytest.raises(hz.AcquireError) as e:
            c.acquire(session_id, lambda p: p)
    assert e.value.gave_up and e.value.code_name == "UNAVAILABLE"
    assert e.value.report.reconnects >= 1
