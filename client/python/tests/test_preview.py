"""The live preview from Python (server-sent events of ``GET /v1/sessions/{id}/preview``)
against the real server: frames arrive while another thread uploads in chunks, with increasing
row counts, and the final frame is the server's own DGI of the finished session."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

import helmholtz as hz


def test_preview_frames_arrive_while_uploading(client, session_id) -> None:  # type: ignore[no-untyped-def]
    side, count, chunk = 16, 1024, 128
    spec = hz.PatternSpec.bernoulli(side, side, count, seed=3)
    frames = hz.patterns(spec).reshape(count, -1).astype(np.float64)
    y, x = np.mgrid[0:side, 0:side] / (side - 1)
    truth = 0.2 + 0.5 * ((x - 0.5) ** 2 + (y - 0.5) ** 2 < 0.1)
    buckets = (frames @ truth.reshape(-1))[:, None]
    session = client.create_session(session_id, spec, channels=["bucket"])

    uploaded = threading.Event()

    def rig() -> None:
        for end in range(chunk, count + 1, chunk):
            client.upload(session, buckets[:end], confirmed_rows=end - chunk)
            time.sleep(0.05)
        uploaded.set()
        client.finish_session(session)

    seen = []
    thread = threading.Thread(target=rig)
    watch = client.watch_preview(session, every_rows=chunk)
    thread.start()
    for frame in watch:
        seen.append((frame, uploaded.is_set()))
    thread.join()

    rows = [f.rows for f, _ in seen]
    assert rows == sorted(set(rows)) and rows[-1] == count, rows
    assert sum(1 for f, done in seen if not done and not f.final) >= 2, rows
    last = seen[-1][0]
    assert last.final and last.method == "dgi" and last.image.shape == (side, side)
    dgi = client.dual_image(client.wait(client.reconstruct(session, "dgi")))
    assert float(np.abs(last.image - dgi).max() / np.abs(dgi).max()) < 1e-4


def test_a_bad_preview_parameter_names_the_field(client, session_id) -> None:  # type: ignore[no-untyped-def]
    session = client.create_session(session_id, hz.PatternSpec.bernoulli(8, 8, 64), channels=["b"])
    with pytest.raises(hz.ApiError) as e:
        next(client.watch_preview(session, every_ms=5))
    assert e.value.status == 400 and e.value.field == "every_ms"
