"""Session ids from outside: decoded exactly once, never echoed when hostile, chosen by the client so that a
create whose answer was lost (a deadline, a broken connection) is retried into the same session."""

from __future__ import annotations

import asyncio

import grpc
import httpx
import numpy as np
import pytest

from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

OBS = np.random.default_rng(5).normal(size=17).astype(np.float32).tolist()


def _step(http, sid: str) -> int:
    return http.get(f"/sessions/{sid}").json()["step"]


def test_a_doubly_encoded_id_is_not_the_session(http):
    sid = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
    twice = "".join(f"%25{ord(c):02X}" for c in sid)  # decoded once: "%62%33...", which is no session's id
    r = http.post(f"/sessions/{twice}/act", json={"observation": OBS})
    assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"
    once = "".join(f"%{ord(c):02X}" for c in sid)  # decoded once: the id itself
    assert http.post(f"/sessions/{once}/act", json={"observation": OBS}).json()["step"] == 0
    assert _step(http, sid) == 1  # only the once-encoded act reached the session


def test_a_long_id_is_not_found_and_never_echoed(make_server):
    server = make_server()  # the default 1 MiB request limit: a 200k-character id fits in a message
    huge = "x" * 200_000
    with grpc.insecure_channel(server.target) as ch:
        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        with pytest.raises(grpc.RpcError) as e:
            stub.Act(pb.ActRequest(session_id=huge, values=pb.FloatVector(values=OBS)))
        assert e.value.code() == grpc.StatusCode.NOT_FOUND
        assert "200000 characters" in e.value.details() and len(e.value.details()) < 200
    with httpx.Client(base_url=server.url, timeout=30) as http:
        long_id = "y" * 10_000
        for r in (
            http.post(f"/sessions/{long_id}/act", json={"observation": OBS}),
            http.put(f"/sessions/{long_id}/goal", json={"goal": 0}),
            http.get(f"/sessions/{long_id}"),
        ):
            assert r.status_code == 404 and "x-session-id" not in r.headers
            assert long_id not in r.text and len(r.content) < 300
        # A hostile value elsewhere is cut short too (the model name is quoted in the answer).
        r = http.post("/sessions", json={"model": "m" * 100_000, "goal": 0})
        assert r.status_code == 404 and len(r.content) < 1500 and "characters cut" in r.text


def test_a_client_chosen_id_makes_create_idempotent_and_is_checked(http):
    body = {"model": "tiny-gmt", "goal": "medium", "seed": 8, "session_id": "bot-7.ep_1~a"}
    first = http.post("/sessions", json=body)
    assert first.status_code == 201 and first.json()["session_id"] == "bot-7.ep_1~a"
    http.post("/sessions/bot-7.ep_1~a/act", json={"observation": OBS, "step": 0})
    again = http.post("/sessions", json={**body, "goal": 1})  # goal 1 is "medium": the same request
    assert again.status_code == 201 and again.json()["step"] == 1  # the session the first call made
    other = http.post("/sessions", json={**body, "seed": 9})
    assert other.status_code == 409 and other.json()["error"]["code"] == "already_exists"
    for bad in (
        "",
        "a/b",
        "a b",
        "é",
        "z" * 129,
        ".",
        "..",
    ):  # dot segments: clients rewrite /sessions/../act
        r = http.post("/sessions", json={**body, "session_id": bad})
        assert r.status_code == 400 and "session_id" in r.json()["error"]["message"], bad
    for fine in ("...", ".a", "a.."):  # other dots are kept by HTTP clients: these sessions are reachable
        assert http.post("/sessions", json={**body, "session_id": fine}).status_code == 201, fine
        assert http.post(f"/sessions/{fine}/act", json={"observation": OBS, "step": 0}).status_code == 200, (
            fine
        )
    assert http.delete("/sessions/bot-7.ep_1~a").status_code == 204
    assert http.post("/sessions", json=body).json()["step"] == 0  # a closed id may be used again


def test_a_create_whose_deadline_expires_is_retried_into_the_same_session(make_server):
    server = make_server()
    store = server.core.store
    create = store.create

    async def slow_answer(session):  # the session is stored, then the answer is late
        await create(session)
        await asyncio.sleep(0.2)

    store.create = slow_answer
    with grpc.insecure_channel(server.target) as ch:
        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        ids = [f"late-{i}" for i in range(20)]
        for sid in ids:
            req = pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=0), session_id=sid)
            with pytest.raises(grpc.RpcError) as e:
                stub.CreateSession(req, timeout=0.05)
            assert e.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
            assert stub.CreateSession(req, timeout=30).session_id == sid  # the retry: the same session
    assert server.run(store.count()) == len(ids)  # one session per id, none orphaned


def test_after_the_store_lost_its_data_an_act_says_so(make_server, redis_clean):
    import redis

    server = make_server(redis_url=redis_clean)
    with httpx.Client(base_url=server.url, timeout=30) as http:
        kept = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
        closed = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
        http.delete(f"/sessions/{closed}")
        assert http.get(f"/sessions/{closed}").json()["error"]["message"] == f"session {closed!r} was closed"
        r = redis.Redis.from_url(redis_clean)
        r.flushall()  # the store loses everything (a restart without persistence, a failover gone wrong)
        r.close()
        answer = http.post(f"/sessions/{kept}/act", json={"observation": OBS})
        assert answer.status_code == 404
        assert "session store, which was reset (lost its data)" in answer.json()["error"]["message"]
        fresh = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0})  # service goes on
        assert (
            http.post(f"/sessions/{fresh.json()['session_id']}/act", json={"observation": OBS}).status_code
            == 200
        )
