"""Errors as Python exceptions: gRPC errors carry the status code and message, REST errors the
server's problem+json."""

from __future__ import annotations

import socket

import grpc
import numpy as np
import pytest

import helmholtz as hz


@pytest.fixture(scope="module")
def finished_bucket(client):  # type: ignore[no-untyped-def]
    spec = hz.PatternSpec.hadamard(4, 4)
    session = client.create_session(f"errors-{np.random.default_rng().integers(1 << 60):x}", spec,
                                    channels=["r", "g"])
    frames = hz.patterns(spec).reshape(spec.count, -1).astype(np.float64)
    client.upload(session, np.stack([frames.sum(1), frames[:, 0]], axis=1))
    return session, client.wait(client.reconstruct(session, "direct"), timeout=60)


def test_rest_problems_name_the_field(client, finished_bucket) -> None:  # type: ignore[no-untyped-def]
    session, rec = finished_bucket
    with pytest.raises(hz.ApiError) as e:
        client.dual_image(rec, channel="blue")
    err = e.value
    assert err.status == 400 and err.field == "channel"
    assert err.type == "/problems/invalid-argument" and err.title == "Invalid argument"
    assert "blue" in err.detail and err.problem["field"] == "channel"

    with pytest.raises(hz.ApiError) as e:
        client.relight(rec, weights={"nope": 1.0})
    assert e.value.status == 400 and e.value.field == "light.weights.nope"

    with pytest.raises(hz.ApiError) as e:
        client.relight(rec, preset="disc", x=1, y=1, radius=1)
    assert e.value.field == "light.preset", e.value  # a bucket session has no camera

    with pytest.raises(hz.ApiError) as e:
        client.reconstruct(session, "tv", {"lambda": "much"})
    assert e.value.status == 400 and e.value.field is not None and "lambda" in e.value.field

    with pytest.raises(hz.ApiError) as e:
        client.reconstruct(session, "no-such-method")
    assert e.value.status == 400 and e.value.field == "method"

    with pytest.raises(hz.ApiError) as e:
        client.primal(rec, pattern_index=0)
    assert e.value.status == 409 and e.value.type == "/problems/failed-precondition"

    with pytest.raises(hz.ApiError) as e:
        client.reconstruction(10**12)
    assert e.value.status == 404 and e.value.field is None and e.value.type == "/problems/not-found"


def test_camera_relight_problems(client, session_id) -> None:  # type: ignore[no-untyped-def]
    spec = hz.PatternSpec.hadamard(4, 4)
    session = client.create_session(session_id, spec, camera=hz.Camera(2, 2, "f32"))
    client.upload(session, hz.patterns(spec)[:, :2, :2])
    rec = client.wait(client.reconstruct(session, "transport"), timeout=60)
    with pytest.raises(hz.ApiError) as e:
        client.relight(rec, preset="disc", x=1, y=1)  # no radius
    assert e.value.status == 400 and e.value.field == "light.radius"
    with pytest.raises(hz.ApiError) as e:
        client.relight(rec, np.ones((3, 3)))
    assert e.value.field == "body" and "2x2" in e.value.detail
    with pytest.raises(hz.ApiError) as e:
        client.primal(rec, pattern_index=spec.count)
    assert e.value.field == "pattern_index"


def test_grpc_errors_carry_code_and_message(server, client) -> None:  # type: ignore[no-untyped-def]
    spec = hz.PatternSpec.hadamard(4, 4)
    with pytest.raises(hz.RpcError) as e:
        client.create_session("has space", spec, channels=["a"])
    assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.code_name == "INVALID_ARGUMENT" and "session_id" in e.value.message
    with pytest.raises(hz.RpcError) as e:
        client.upload_status("never-declared")
    assert e.value.code == grpc.StatusCode.NOT_FOUND


def test_tokens_and_roles(server, session_id) -> None:  # type: ignore[no-untyped-def]
    spec = hz.PatternSpec.hadamard(4, 4)
    with hz.Client(server.address, "hz_not_a_token") as nobody:
        with pytest.raises(hz.RpcError) as e:
            nobody.create_session(session_id, spec, channels=["a"])
        assert e.value.code == grpc.StatusCode.UNAUTHENTICATED
        with pytest.raises(hz.ApiError) as e2:
            nobody.index()
        assert e2.value.status == 401 and e2.value.type == "/problems/unauthenticated"
    with hz.Client(server.address, server.create_token("py", "reader")) as reader:
        with pytest.raises(hz.RpcError) as e:
            reader.create_session(session_id, spec, channels=["a"])
        assert e.value.code == grpc.StatusCode.PERMISSION_DENIED
        assert reader.index()["service"] == "helmholtz"
    # Another lab does not see this lab's sessions.
    with hz.Client(server.address, server.token) as rig:
        rig.create_session(session_id, spec, channels=["a"])
    with hz.Client(server.address, server.create_token("other-lab", "rig,reader")) as stranger:
        with pytest.raises(hz.ApiError) as e2:
            stranger.session(session_id)
        assert e2.value.status == 404


def test_no_server_is_server_unreachable() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    c = hz.Client(f"http://127.0.0.1:{port}", "hz_x", retry=hz.RetryPolicy(retry_for=0.3))
    with pytest.raises(hz.ServerUnreachable):
        c.index()
    with pytest.raises(hz.RpcError) as e:
        c.upload_status("s")
    assert e.value.code == grpc.StatusCode.UNAVAILABLE
