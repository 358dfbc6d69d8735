"""Every answer names the replica that gave it: REST `X-Served-By`, gRPC `x-served-by` metadata (initial, and
in the trailers of every status the server answers), errors, unknown routes and health checks included."""

import asyncio
import os
import socket

import grpc
import httpx
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from pydantic import ValidationError
from service_harness import make_settings

from gmt.service.rest.app import create_app
from gmt.service.settings import Settings
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc


def test_replica_id_defaults_to_host_and_pid_and_comes_from_the_environment(monkeypatch):
    monkeypatch.delenv("GMT_REPLICA_ID", raising=False)
    assert Settings().replica_id == f"{socket.gethostname()}:{os.getpid()}"
    monkeypatch.setenv("GMT_REPLICA_ID", "gmt-9")
    assert Settings().replica_id == "gmt-9"
    for bad in ("", "two words", "é", "x" * 129):
        with pytest.raises(ValidationError, match="replica_id"):
            Settings(replica_id=bad)


@pytest.fixture(scope="module")
def replica(ckpt_root):
    from service_harness import RunningServer

    s = RunningServer(
        make_settings(checkpoints=[ckpt_root], replica_id="r-7", max_request_bytes=4096, auth_token="tok")
    ).start()
    yield s
    s.stop()


def test_rest_answers_carry_x_served_by(replica):
    auth = {"Authorization": "Bearer tok"}
    with httpx.Client(base_url=replica.url, timeout=30) as http:
        answers = [
            http.get("/healthz"),
            http.get("/readyz"),
            http.get("/models", headers=auth),
            http.get("/models"),  # 401
            http.get("/no/such/route", headers=auth),  # 404
            http.post("/sessions", content=b"{", headers={**auth, "Content-Type": "application/json"}),  # 400
            http.post("/sessions", content=b"x" * 5000, headers=auth),  # 413
            http.get("/sessions/missing", headers=auth),  # 404 of the service
            http.delete("/healthz"),  # 405
            http.post("/sessions", content=b"x" * 5000),  # 401: auth is checked before the body is read
            http.get("/no/such/route"),  # 401: without the token no route is revealed
        ]
    assert [r.status_code for r in answers] == [200, 200, 200, 401, 404, 400, 413, 404, 405, 401, 401]
    assert [r.headers.get("x-served-by") for r in answers] == ["r-7"] * len(answers)


def test_rest_500_from_the_outermost_error_handler_carries_it_too(ckpt_root):
    app = create_app(make_settings(checkpoints=[ckpt_root], replica_id="r-8"))

    async def boom():
        raise RuntimeError("bug")

    app.add_api_route("/boom", boom)

    async def get() -> httpx.Response:
        transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)  # no lifespan: no core needed
        async with httpx.AsyncClient(transport=transport, base_url="http://replica") as client:
            return await client.get("/boom")

    r = asyncio.run(get())
    assert r.status_code == 500 and r.json()["error"]["code"] == "internal"
    assert r.headers["x-served-by"] == "r-8"


def test_grpc_calls_carry_x_served_by(replica):
    auth = (("authorization", "Bearer tok"),)
    with grpc.insecure_channel(replica.target) as channel:
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        _, call = stub.ListModels.with_call(pb.ListModelsRequest(), metadata=auth)
        assert ("x-served-by", "r-7") in call.initial_metadata()
        assert ("x-served-by", "r-7") in call.trailing_metadata()
        for md in ((), auth):  # refused by auth, then not found: both statuses of this server
            with pytest.raises(grpc.RpcError) as e:
                stub.GetSession(pb.GetSessionRequest(session_id="missing"), metadata=md)
            assert e.value.code() in (grpc.StatusCode.UNAUTHENTICATED, grpc.StatusCode.NOT_FOUND)
            assert ("x-served-by", "r-7") in e.value.initial_metadata()
            assert ("x-served-by", "r-7") in e.value.trailing_metadata()
        _, call = health_pb2_grpc.HealthStub(channel).Check.with_call(health_pb2.HealthCheckRequest())
        assert ("x-served-by", "r-7") in call.initial_metadata()
        sid = stub.CreateSession(
            pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=0)), metadata=auth
        ).session_id
        act = pb.ControlRequest(act=pb.ActRequest(session_id=sid, values=pb.FloatVector(values=[0.0] * 17)))
        stream = stub.Control(iter([act, act]), metadata=auth)
        assert ("x-served-by", "r-7") in stream.initial_metadata()
        assert [r.act.step for r in stream] == [0, 1]
