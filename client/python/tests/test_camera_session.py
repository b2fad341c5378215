"""A camera session from Python: frames ``c = T p`` of a known light transport matrix T
(8x8 projector, 8x8 camera, the complete Hadamard set), the ``transport`` method, relighting
(``T^T c'``) and primal images (``T p``) against T."""

from __future__ import annotations

import numpy as np
import pytest

import helmholtz as hz

# T is recovered from a noise-free complete set: the frames are rounded to float32 (relative
# 6e-8) and the server inverts them and relights in float32, so what it gives agrees with the
# known T to float32 precision (about 1e-7 relative in the 2-norm, measured). 1e-6 leaves a
# margin of 10x; a wrong T, pattern, ordering or axis gives errors of order 1.
TOLERANCE = 1e-6


def relative_error(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.linalg.norm(got - want) / np.linalg.norm(want))


@pytest.fixture(scope="module")
def camera_run(client):  # type: ignore[no-untyped-def]
    side, cam = 8, hz.Camera(8, 8, "f32")
    spec = hz.PatternSpec.hadamard(side, side, ordering="zigzag")
    rng = np.random.default_rng(2026)
    m, k = cam.pixels, spec.pixels
    # A known transport: every camera pixel sees a bright 2x2 spot of the projector (its
    # direct light) and a little of everything else (inter-reflection), constant on 2x2 cells of
    # projector pixels. (The server tells signal from noise by the finest Haar details of each
    # row and drops coefficients below that noise: a T that varied at random from pixel to
    # pixel would look like noise to it; real scenes vary smoothly.)
    cells = 0.01 + 0.1 * rng.random((m, side // 2, side // 2))
    spots = rng.permutation(np.repeat(np.arange((side // 2) ** 2), m // (side // 2) ** 2))
    cells.reshape(m, -1)[np.arange(m), spots] += 0.89
    T = np.kron(cells, np.ones((2, 2))).reshape(m, k)
    ambient = 0.02
    frames_p = hz.patterns(spec).reshape(spec.count, k).astype(np.float64)
    frames = (frames_p @ T.T + ambient).astype(np.float32).reshape(spec.count, cam.height, cam.width)
    session_id = f"camera-{rng.integers(1 << 62):x}"
    session = client.create_session(session_id, spec, camera=cam, rig="python-camera")
    assert session.camera == cam and session.values_per_row == 64
    report = client.upload(session, frames, chunk_rows=16)
    assert report.confirmed_rows == spec.count and report.chunks_sent == 8
    stored = client.measurements(session)
    assert stored.dtype == np.float32 and stored.shape == frames.shape
    assert stored.tobytes() == frames.tobytes()
    client.finish_session(session)
    seen: list[float] = []
    rec = client.wait(client.reconstruct(session, "transport"), timeout=120,
                      progress=lambda r: seen.append(r.progress))
    assert seen and seen[-1] == 1.0
    return session, spec, cam, T, ambient, rec


def test_transport_reconstruction_and_report(client, camera_run) -> None:  # type: ignore[no-untyped-def]
    session, spec, cam, T, ambient, rec = camera_run
    assert rec.method == "transport" and rec.done
    report = client.report(rec)
    assert report["method"] == "transport" and report["rows_used"] == spec.count
    assert report["details"]["path"].startswith("exact inverse of a complete set"), report
    assert abs(report["details"]["ambient_mean"] - ambient) < 1e-6  # the split pairs' dark level
    # The dual image of a camera session is T^T 1: the scene under the whole camera.
    dual = client.dual_image(rec)
    assert dual.shape == (spec.height, spec.width)
    assert relative_error(dual.astype(np.float64).reshape(-1), T.sum(axis=0)) < TOLERANCE


def test_relight_with_a_camera_sized_light(client, camera_run) -> None:  # type: ignore[no-untyped-def]
    session, spec, cam, T, ambient, rec = camera_run
    light = np.random.default_rng(7).random((cam.height, cam.width))
    relit = client.relight(rec, light)
    assert relit.dtype == np.float32 and relit.shape == (spec.height, spec.width)
    want = T.T @ light.astype(np.float32).astype(np.float64).reshape(-1)
    assert relative_error(relit.astype(np.float64).reshape(-1), want) < TOLERANCE
    # A preset: camera columns 2 <= x < 5 lit.
    stripe = client.relight(rec, preset="stripe", x0=2, x1=5)
    mask = np.zeros((cam.height, cam.width))
    mask[:, 2:5] = 1.0
    want = T.T @ mask.reshape(-1)
    assert relative_error(stripe.astype(np.float64).reshape(-1), want) < TOLERANCE
    assert np.array_equal(client.relight(rec, mask), stripe)


def test_primal_images(client, camera_run) -> None:  # type: ignore[no-untyped-def]
    session, spec, cam, T, ambient, rec = camera_run
    # One of the session's own patterns: T p + ambient, and the server's comparison with the
    # measured frame.
    image, info = client.primal(rec, pattern_index=37, with_error=True)
    assert image.shape == (cam.height, cam.width) and image.dtype == np.float32
    p = hz.pattern(spec, 37).astype(np.float64).reshape(-1)
    want = T @ p + ambient
    assert relative_error(image.astype(np.float64).reshape(-1), want) < TOLERANCE
    assert info["measured_row"] == 37 and info["relative_error"] < TOLERANCE
    # Any pattern, without the ambient level.
    q = np.random.default_rng(11).random((spec.height, spec.width))
    image = client.primal(rec, q, ambient=False)
    want = T @ q.astype(np.float32).astype(np.float64).reshape(-1)
    assert relative_error(image.astype(np.float64).reshape(-1), want) < TOLERANCE
    with_ambient = client.primal(rec, q)
    assert abs(float(np.mean(with_ambient - image)) - ambient) < 1e-4


def test_u16_frames_are_stored_exactly(client, session_id) -> None:  # type: ignore[no-untyped-def]
    spec = hz.PatternSpec.hadamard(4, 4)
    session = client.create_session(session_id, spec, camera=hz.Camera(3, 2, "u16"))
    frames = np.random.default_rng(1).integers(0, 65536, (spec.count, 2, 3)).astype(np.int64)
    client.upload(session, frames)
    stored = client.measurements(session)
    assert stored.dtype == np.uint16 and stored.shape == (spec.count, 2, 3)
    assert np.array_equal(stored, frames)
    with pytest.raises(ValueError, match="0..=65535"):
        client.upload(session, frames + 70000)
