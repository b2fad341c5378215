"""The upload contract from Python: resume from the server's count, overlap compared byte for
byte, one writer per session (``x-helmholtz-writer``), retries through a cut connection,
checksums, and local checks before anything is sent."""

from __future__ import annotations

import threading
import zlib

import grpc
import numpy as np
import pytest

import helmholtz as hz
from helmholtz._proto.v1 import acquisition_pb2 as pb
from helmholtz._proto.v1 import acquisition_pb2_grpc as pb_grpc

from conftest import CuttingProxy, wait_until


def bucket_session(client, session_id, rows=256, channels=("a", "b")):  # type: ignore[no-untyped-def]
    spec = hz.PatternSpec.bernoulli(8, 8, rows, seed=3)
    session = client.create_session(session_id, spec, channels=list(channels))
    values = np.random.default_rng(zlib.crc32(session_id.encode())).standard_normal((rows, len(channels)))
    return session, values


def test_resume_after_a_partial_upload(client, session_id) -> None:  # type: ignore[no-untyped-def]
    session, values = bucket_session(client, session_id)
    first = client.upload(session, values[:100], chunk_rows=32)
    assert first.committed_rows == 100 and first.rows_written == 100
    assert client.upload_status(session).committed_rows == 100
    # A new call with all rows: rows 0..100 are compared (not trusted), the rest written. (By
    # session id: the layout is read with GET /v1/sessions/{id}.)
    second = client.upload(session.id, values, chunk_rows=32)
    assert (second.rows_matched, second.rows_written) == (100, 156)
    assert second.committed_rows == second.confirmed_rows == 256
    # Rows known to be stored are not re-sent at all.
    third = client.upload(session, values, confirmed_rows=256)
    assert third.rows_sent == 0 and third.committed_rows == 256
    assert np.array_equal(client.measurements(session), values)


def test_an_overlapping_upload_with_other_values_is_refused(client, session_id) -> None:  # type: ignore[no-untyped-def]
    session, values = bucket_session(client, session_id)
    client.upload(session, values[:200])
    changed = values.copy()
    changed[150, 1] += 1.0
    with pytest.raises(hz.UploadError) as e:
        client.upload(session, changed, chunk_rows=64)
    err = e.value
    assert err.code == grpc.StatusCode.ALREADY_EXISTS and err.code_name == "ALREADY_EXISTS"
    assert "150" in err.message, err.message
    # Rows count as confirmed only when a stream that carried them ended OK: this one did not.
    assert not err.gave_up and err.confirmed_rows == 0 and err.total_rows == 256
    # Nothing of the refused chunk (or after it) was stored; the stored rows are the first ones.
    assert client.upload_status(session).committed_rows == 200
    assert np.array_equal(client.measurements(session), values[:200])


def test_one_writer_at_a_time(server, client, session_id) -> None:  # type: ignore[no-untyped-def]
    session, values = bucket_session(client, session_id)
    channel = grpc.insecure_channel(server.address.split("://", 1)[1])
    stub = pb_grpc.AcquisitionStub(channel)
    release = threading.Event()

    def chunk(start: int, end: int) -> pb.MeasurementChunk:
        payload = values[start:end].astype("<f8").tobytes()
        return pb.MeasurementChunk(
            session_id=session.id, start_row=start, channels=2, values_f64le=payload,
            crc32c=hz.crc32c(payload),
        )

    def held_open():  # type: ignore[no-untyped-def]
        yield chunk(0, 10)
        release.wait(30)
        yield chunk(10, 20)

    other = stub.UploadMeasurements.future(
        held_open(), metadata=[("authorization", f"Bearer {server.token}"), (hz.WRITER_HEADER, "rig-other")]
    )
    try:
        wait_until(lambda: client.upload_status(session).committed_rows == 10, what="the first chunk")
        # A second writer is refused while that stream is open (ABORTED is retryable, so the
        # upload retries for retry_for seconds, then gives up) and stores nothing.
        with pytest.raises(hz.UploadError) as e:
            client.upload(session, values, writer_id="rig-mine", retry_for=1.0)
        assert e.value.code == grpc.StatusCode.ABORTED and e.value.gave_up
        assert "another writer" in e.value.message, e.value.message
        assert client.upload_status(session).committed_rows == 10
        # The same writer id (a new stream of the same upload) takes the session over from its
        # own stale stream, whose later chunks are then refused.
        report = client.upload(session, values, writer_id="rig-other")
        assert report.committed_rows == 256 and report.rows_matched == 10
    finally:
        release.set()
    with pytest.raises(grpc.RpcError) as stale:
        other.result(timeout=30)
    assert stale.value.code() == grpc.StatusCode.ABORTED
    channel.close()
    assert np.array_equal(client.measurements(session), values)


def test_an_upload_resumes_through_cut_connections(server, client, session_id) -> None:  # type: ignore[no-untyped-def]
    session, values = bucket_session(client, session_id, rows=2000, channels=("a",) * 1)
    proxy = CuttingProxy(server.address.split("://", 1)[1])
    cut_at = {500, 1200}
    lock = threading.Lock()

    def progress(sent: int, total: int) -> None:
        with lock:
            hits = [c for c in cut_at if sent >= c]
            for c in hits:
                cut_at.discard(c)
            if hits:
                proxy.cut_all()

    try:
        with hz.Client(proxy.address, server.token) as through_proxy:
            report = through_proxy.upload(session, values, chunk_rows=50, progress=progress)
    finally:
        proxy.close()
    assert proxy.cuts >= 2 and not cut_at
    assert report.resumes >= 2, report
    assert report.last_error is not None, report
    assert report.committed_rows == report.confirmed_rows == 2000
    assert report.rows_sent > 2000  # rows of the cut streams were sent again
    assert np.array_equal(client.measurements(session), values)


def test_a_server_that_is_not_there_yet_is_waited_for(server, client, session_id) -> None:  # type: ignore[no-untyped-def]
    session, values = bucket_session(client, session_id, rows=64, channels=("a",))
    # A port where nothing listens: UNAVAILABLE, retried until retry_for, then UploadError.
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with hz.Client(f"http://127.0.0.1:{port}", server.token,
                   retry=hz.RetryPolicy(retry_for=1.0)) as nowhere:
        with pytest.raises(hz.UploadError) as e:
            nowhere.upload(session, values)
    assert e.value.code == grpc.StatusCode.UNAVAILABLE and e.value.gave_up
    assert e.value.confirmed_rows == 0


def test_a_finished_session_takes_no_more_rows(client, session_id) -> None:  # type: ignore[no-untyped-def]
    session, values = bucket_session(client, session_id, rows=64, channels=("a",))
    client.upload(session, values)
    client.finish_session(session)
    assert client.finish_session(session).state == "finished"  # finishing twice is harmless
    # The same rows again: compared, nothing new; fine.
    assert client.upload(session, values).rows_matched == 64
    other = hz.PatternSpec.bernoulli(8, 8, 64, seed=3)
    with pytest.raises(hz.RpcError) as e:
        client.create_session(session.id, other, channels=["a", "b"])
    assert e.value.code == grpc.StatusCode.ALREADY_EXISTS


def test_finishing_early_is_refused(client, session_id) -> None:  # type: ignore[no-untyped-def]
    session, values = bucket_session(client, session_id, rows=64, channels=("a",))
    client.upload(session, values[:10])
    with pytest.raises(hz.RpcError) as e:
        client.finish_session(session)
    assert e.value.code == grpc.StatusCode.FAILED_PRECONDITION


def test_bad_arrays_are_refused_before_anything_is_sent(client, session_id) -> None:  # type: ignore[no-untyped-def]
    session, values = bucket_session(client, session_id)
    bad = values.copy()
    bad[17, 0] = np.nan
    with pytest.raises(ValueError, match="row 17, column 0"):
        client.upload(session, bad)
    with pytest.raises(ValueError, match=r"\(rows, 2\)"):
        client.upload(session, values[:, :1])
    with pytest.raises(ValueError, match="expects 256"):
        client.upload(session, np.zeros((257, 2)))
    assert client.upload_status(session).committed_rows == 0
