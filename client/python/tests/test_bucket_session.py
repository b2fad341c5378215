"""A full bucket session driven from Python against the real server: declare, upload, finish,
``auto``, wait with a progress callback, and the dual image as an ndarray bit for bit equal to
the REST ``dual.npy``."""

from __future__ import annotations

import urllib.request

import numpy as np

import helmholtz as hz


def scene(side: int) -> np.ndarray:
    """A smooth gradient with a bright disc: the transport of each projector pixel."""
    y, x = np.mgrid[0:side, 0:side] / (side - 1)
    disc = ((x - 0.6) ** 2 + (y - 0.4) ** 2 < 0.08).astype(np.float64)
    return 0.2 + 0.3 * x + 0.1 * y + 0.5 * disc


def raw_get(server, path: str) -> bytes:  # type: ignore[no-untyped-def]
    req = urllib.request.Request(
        server.address + path, headers={"Authorization": f"Bearer {server.token}"}
    )
    with urllib.request.urlopen(req, timeout=30) as r:
        return r.read()


def test_bucket_session_end_to_end(server, client, session_id) -> None:  # type: ignore[no-untyped-def]
    side = 16
    spec = hz.PatternSpec.hadamard(side, side, ordering="sequency")
    frames = hz.patterns(spec)
    assert frames.shape == (2 * side * side, side, side)
    truth = scene(side)
    ambient = 0.05
    buckets = frames.reshape(len(frames), -1).astype(np.float64) @ truth.reshape(-1) + ambient
    buckets = buckets[:, None]  # (rows, 1 channel)

    session = client.create_session(
        session_id, spec, channels=["bucket"], rig="python-test", metadata={"lens": "50mm"}
    )
    assert session.created is True and session.expected_rows == spec.count
    assert session.channels == ["bucket"] and session.camera is None
    # Declaring again with the same declaration is idempotent.
    again = client.create_session(
        session_id, spec, channels=["bucket"], rig="python-test", metadata={"lens": "50mm"}
    )
    assert again.created is False

    sent = []
    report = client.upload(session, buckets, chunk_rows=100, progress=lambda a, n: sent.append((a, n)))
    assert (report.rows_written, report.rows_matched) == (spec.count, 0)
    assert report.confirmed_rows == report.committed_rows == spec.count
    assert report.chunks_sent == 6 and report.resumes == 0
    assert sent[-1] == (spec.count, spec.count)
    status = client.upload_status(session)
    assert (status.committed_rows, status.expected_rows, status.state) == (spec.count, spec.count, "open")
    assert client.finish_session(session).state == "finished"
    # The stored rows are ours, bit for bit.
    stored = client.measurements(session)
    assert stored.dtype == np.float64 and stored.shape == buckets.shape
    assert stored.tobytes() == buckets.astype("<f8").tobytes()

    calls: list[hz.Reconstruction] = []
    queued = client.reconstruct(session, "auto")
    assert queued.state in ("queued", "running", "done") and queued.method == "auto"
    done = client.wait(queued, timeout=120, progress=calls.append)
    assert done.done and done.rows == spec.count
    assert calls, "the progress callback was never called"
    assert calls[-1].state == "done" and calls[-1].progress == 1.0
    assert all(0.0 <= c.progress <= 1.0 for c in calls)
    assert all(c.state in ("queued", "running", "done") for c in calls)
    assert all(c.id == queued.id for c in calls)

    image = client.dual_image(done)
    assert image.dtype == np.float32 and image.shape == (side, side)
    raw = raw_get(server, f"/v1/reconstructions/{done.id}/dual.npy")
    from_rest = np.load(__import__("io").BytesIO(raw), allow_pickle=False)
    assert from_rest.dtype == image.dtype and from_rest.shape == image.shape
    assert raw.endswith(image.tobytes()), "dual_image() differs from the REST dual.npy bytes"
    assert image.tobytes() == from_rest.tobytes()
    assert client.session_dual_image(session).tobytes() == image.tobytes()
    # A complete Hadamard set: auto takes the exact inverse; the split pairs cancel the ambient.
    assert np.max(np.abs(image - truth)) < 1e-5 * np.max(truth), np.max(np.abs(image - truth))

    report_json = client.report(done)
    assert report_json["method"] == "auto" and report_json["rows_used"] == spec.count
    assert report_json == done.report
    assert report_json["details"]["auto"][0]["model"] == "direct", report_json["details"]

    # Bucket sessions relight by channel weights.
    doubled = client.relight(done, weights={"bucket": 2.0})
    assert np.array_equal(doubled, (2.0 * image.astype(np.float64)).astype(np.float32))
    assert np.array_equal(client.relight(done), image)  # preset "full": every channel at 1

    listed = client.reconstructions(session)
    assert [r.id for r in listed] == [done.id]
    assert client.session(session_id).state == "finished"


def test_the_server_runs_on_the_requested_store(server) -> None:  # type: ignore[no-untyped-def]
    # "... data in sqlite:/tmp/.../helmholtz.sqlite, ..." or "... data in postgres://...".
    store = server.banner.split(" data in ", 1)[1].split(",", 1)[0]
    if server.database_url:
        assert store.startswith("postgres://"), server.banner
    else:
        assert store == f"sqlite:{server.data_dir / 'helmholtz.sqlite'}", server.banner


def test_the_index_lists_the_routes_this_package_uses(client) -> None:  # type: ignore[no-untyped-def]
    index = client.index()
    assert index["service"] == "helmholtz"
    routes = index["routes"]
    for route in [
        "GET /v1/sessions/{id}",
        "POST /v1/sessions/{id}/reconstructions",
        "GET /v1/reconstructions/{id}",
        "POST /v1/reconstructions/{id}/cancel",
        "POST /v1/reconstructions/{id}/relight",
        "POST /v1/reconstructions/{id}/primal",
    ]:
        assert any(r.startswith(route) for r in routes), f"{route} not in GET /: {routes}"
    # The file routes list the files they serve ({file}: a|b|c).
    for route, files in [
        ("GET /v1/sessions/{id}/{file}", ["measurements.npy", "dual.png", "dual.tiff", "dual.npy"]),
        ("GET /v1/reconstructions/{id}/{file}", ["dual.png", "dual.tiff", "dual.npy"]),
    ]:
        line = next((r for r in routes if r.startswith(route)), None)
        assert line is not None, f"{route} not in GET /: {routes}"
        served = line.split("({file}: ", 1)[1].rstrip(")").split("|")
        for f in files:
            assert f in served, f"{f} not served by {line}"
    post = next(r for r in routes if r.startswith("POST /v1/sessions/{id}/reconstructions"))
    for method in ("auto", "dgi", "transport"):
        assert method in post, post
    assert client.healthy()
