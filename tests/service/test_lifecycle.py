"""Idle timeout, the session limit, micro-batching, deadlines and bearer auth, against real servers."""

import asyncio
import contextlib
import threading

import grpc
import httpx
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from prometheus_client.parser import text_string_to_metric_families
from service_harness import make_settings

from gmt.common.recording import read_recording
from gmt.model.checkpoint import load_checkpoint
from gmt.service.core import Core
from gmt.service.errors import SessionExpired
from gmt.service.redis_store import store_for
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc


def stub_for(server):
    return policy_pb2_grpc.PolicyServiceStub(grpc.insecure_channel(server.target))


def create(http, goal=0, model="tiny-gmt"):
    r = http.post("/sessions", json={"model": model, "goal": goal})
    assert r.status_code == 201, r.text
    return r.json()["session_id"]


def act(http, sid, obs):
    return http.post(f"/sessions/{sid}/act", json={"observation": np.asarray(obs).tolist()})


OBS_DIM = 17


def metric_samples(http, name: str) -> dict:
    """{(sample name, labels as a sorted tuple): value} of one metric family from GET /metrics."""
    text = http.get("/metrics").text
    out = {}
    for fam in text_string_to_metric_families(text):
        if fam.name == name:
            for s in fam.samples:
                out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


# ----- idle timeout -------------------------------------------------------------------------------------------
def test_idle_session_expires_with_a_clear_message(make_server, clock, observations):
    server = make_server(clock=clock, idle_timeout_s=10)
    stub = stub_for(server)
    with httpx.Client(base_url=server.url) as http:
        sid = create(http)
        g = stub.CreateSession(
            pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=0))
        ).session_id
        assert act(http, sid, observations[0]).status_code == 200
        clock.advance(9.5)
        assert act(http, sid, observations[1]).status_code == 200  # use restarts the idle timer
        clock.advance(9.5)
        assert act(http, sid, observations[2]).json()["step"] == 2
        clock.advance(10.5)
        r = act(http, sid, observations[3])
        assert r.status_code == 404
        assert r.json()["error"] == {
            "code": "not_found",
            "message": f"session '{sid}' expired: it was idle for more than the idle timeout of 10 s",
        }
        assert "expired" in http.get(f"/sessions/{sid}").json()["error"]["message"]  # and stays expired
        with pytest.raises(grpc.RpcError) as e:
            stub.Act(pb.ActRequest(session_id=g, values=pb.FloatVector(values=observations[0])))
        assert e.value.code() == grpc.StatusCode.NOT_FOUND and f"session '{g}' expired" in e.value.details()
        req = pb.ControlRequest(
            act=pb.ActRequest(session_id=sid, values=pb.FloatVector(values=observations[0]))
        )
        (out,) = list(stub.Control(iter([req])))
        assert out.error.code == "not_found" and "expired" in out.error.message
        # A fresh session on the same server works.
        assert act(http, create(http), observations[0]).status_code == 200


def test_sweeper_removes_idle_sessions(make_server, clock):
    server = make_server(clock=clock, idle_timeout_s=10)
    with httpx.Client(base_url=server.url) as http:
        sids = [create(http) for _ in range(3)]
        clock.advance(11)
        assert server.run(server.core.sweep()) == 3
        assert metric_samples(http, "gmt_live_sessions")[("gmt_live_sessions", ())] == 0
        assert all("expired" in http.get(f"/sessions/{s}").json()["error"]["message"] for s in sids)


class _GatedEngine:
    """An engine whose passes wait at a gate (an act under way for as long as the test likes)."""

    def __init__(self, engine) -> None:
        self._engine = engine
        self.gate, self.entered = threading.Event(), threading.Event()

    def __getattr__(self, name):
        return getattr(self._engine, name)

    def act(self, *args, **kw):
        self.entered.set()
        self.gate.wait(30)
        return self._engine.act(*args, **kw)


@pytest.fixture(params=["memory", "redis"])
def store_url(request):
    """Sessions in memory (None), or a real Redis's URL (skipped where redis-server is missing)."""
    return None if request.param == "memory" else request.getfixturevalue("redis_clean")


@contextlib.asynccontextmanager
async def _started_core(ckpt_root, clock, **settings):
    """A started `Core` over tiny-gmt with a 10 s idle timeout on the fake clock; closed after."""
    s = make_settings(checkpoints=[ckpt_root / "tiny-gmt"], idle_timeout_s=10, **settings)
    core = Core(s, store=store_for(s, clock), clock=clock)
    await core.start()
    try:
        yield core
    finally:
        await core.close()


def test_the_sweep_expires_no_session_with_an_act_under_way(store_url, ckpt_root, clock):
    """A session whose act started just before its idle timeout ran out is in use, not idle: a sweep meanwhile
    leaves it (and its engine slot) alone, the act is answered and stored, and the session acts on."""
    obs = np.zeros(OBS_DIM, dtype=np.float32)

    async def main():
        async with _started_core(ckpt_root, clock, redis_url=store_url) as core:
            sid = (await core.create_session("tiny-gmt", goal=0)).session_id
            assert (await core.act(sid, obs)).step == 0
            (batcher,) = core._batchers.values()
            batcher.inline_alone = False  # through the batcher, to be held in its pass
            batcher.engine = gated = _GatedEngine(batcher.engine)
            clock.advance(9.9)
            acting = asyncio.ensure_future(core.act(sid, obs))
            assert await asyncio.to_thread(gated.entered.wait, 10)
            clock.advance(0.2)  # its last answer is now older than the idle timeout
            expired = await core.sweep()
            other = (await core.create_session("tiny-gmt", goal=1)).session_id  # would take a freed slot
            gated.gate.set()
            answered = (await acting).step
            batcher.engine = gated._engine
            clock.advance(5)
            return expired, answered, (await core.act(sid, obs)).step, (await core.get_session(other)).step

    assert asyncio.run(main()) == (0, 1, 2, 0)


def test_the_sweep_frees_an_expired_sessions_engine_slot(store_url, ckpt_root, clock):
    """An idle session the sweep expires gives its engine slot back (the store's `on_remove`, while nothing uses it);
    a session in use keeps its own."""
    obs = np.zeros(OBS_DIM, dtype=np.float32)

    async def main():
        async with _started_core(ckpt_root, clock, redis_url=store_url) as core:
            idle, used = [(await core.create_session("tiny-gmt", goal=0)).session_id for _ in range(2)]
            for sid in (idle, used):
                await core.act(sid, obs)
            (batcher,) = core._batchers.values()
            held = set(batcher.engine.pool.keys)
            clock.advance(6)
            await core.act(used, obs)
            clock.advance(6)
            return (idle, used), held, await core.sweep(), set(batcher.engine.pool.keys)

    (idle, used), held, expired, after = asyncio.run(main())
    assert (held, expired, after) == ({idle, used}, 1, {used})


def test_no_act_starts_on_a_session_the_redis_sweep_is_expiring(ckpt_root, clock, redis_clean, tmp_path):
    """Over Redis the sweep holds a session's lock while it expires it: an act that arrives meanwhile waits, then
    finds the session expired; the session is expired (and its recording written) once, not again by the act."""
    obs = np.zeros(OBS_DIM, dtype=np.float32)

    async def main():
        async with _started_core(ckpt_root, clock, redis_url=redis_clean, record_dir=tmp_path) as core:
            sid = (await core.create_session("tiny-gmt", goal=0, record=True)).session_id
            for _ in range(2):
                await core.act(sid, obs)
            store, calls, gate, entered = core.store, [], asyncio.Event(), asyncio.Event()
            expire = store._expire

            async def held_first(s_id, s):  # the sweep's expiry waits at the gate
                calls.append(s_id)
                if len(calls) == 1:
                    entered.set()
                    await gate.wait()
                await expire(s_id, s)

            store._expire = held_first
            clock.advance(11)
            sweep = asyncio.ensure_future(core.sweep())
            await entered.wait()
            act = asyncio.ensure_future(core.act(sid, obs))
            lock = core._lock(sid)
            async with asyncio.timeout(
                10
            ):  # until the act waits on the lock, or (unlocked) has run to its end
                while not act.done() and not lock._waiters:
                    await asyncio.sleep(0)
            gate.set()
            expired = await sweep
            with pytest.raises(SessionExpired):
                await act
            return expired, calls

    expired, calls = asyncio.run(main())
    assert expired == 1 and len(calls) == 1
    rec = read_recording(tmp_path / f"{calls[0]}.json")
    assert rec.meta["ended_by"] == "expiry" and rec.steps == 2


# ----- session limit ------------------------------------------------------------------------------------------
def test_full_server_answers_429_and_resource_exhausted(make_server, clock, observations):
    server = make_server(clock=clock, max_sessions=3, idle_timeout_s=10)
    stub = stub_for(server)
    with httpx.Client(base_url=server.url) as http:
        sids = [create(http) for _ in range(3)]
        r = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0})
        assert r.status_code == 429
        assert r.json()["error"] == {
            "code": "resource_exhausted",
            "message": "server is full: 3 live sessions (maximum 3); close a session or retry later",
        }
        with pytest.raises(grpc.RpcError) as e:
            stub.CreateSession(pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=0)))
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "server is full" in e.value.details()
        assert all(act(http, s, observations[0]).status_code == 200 for s in sids)  # live sessions unaffected
        assert http.delete(f"/sessions/{sids[0]}").status_code == 204
        sids[0] = create(http)  # a closed session frees its place
        assert http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).status_code == 429
        clock.advance(11)  # idle sessions free theirs
        assert http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).status_code == 201


# ----- micro-batching -----------------------------------------------------------------------------------------
async def _act_all(url, sids, observations):
    async with httpx.AsyncClient(base_url=url, timeout=60) as c:
        rs = await asyncio.gather(
            *(
                c.post(f"/sessions/{s}/act", json={"observation": np.asarray(o).tolist()})
                for s, o in zip(sids, observations, strict=True)
            )
        )
    return rs


def test_concurrent_sessions_share_one_forward_pass(make_server, engine, ckpt_root):
    """Sessions acting together share one forward pass once each is acting (the batcher waits only for sessions
    answered within its acting window, so not in their first round)."""
    server = make_server(batch_wait_ms=10_000, max_batch=64)
    n, rounds = 8, 4
    rng = np.random.default_rng(3)
    obs = rng.normal(size=(rounds, n, OBS_DIM)).astype(np.float32)
    version = load_checkpoint(ckpt_root / "tiny-gmt").version
    key = (("model", "tiny-gmt"), ("version", version))
    small = ("gmt_batch_size_bucket", (("le", "4.0"), ("model", "tiny-gmt"), ("version", version)))
    with httpx.Client(base_url=server.url) as http:
        sids = [create(http, goal=i % 3) for i in range(n)]
        got = [asyncio.run(_act_all(server.url, sids, obs[t])) for t in range(2)]
        before = metric_samples(http, "gmt_batch_size")
        got += [asyncio.run(_act_all(server.url, sids, obs[t])) for t in range(2, rounds)]
        after = metric_samples(http, "gmt_batch_size")
    # All 8 requests of each later round went through one forward pass: 2 batches, 16 observations.
    assert after[("gmt_batch_size_count", key)] - before[("gmt_batch_size_count", key)] == 2
    assert after[("gmt_batch_size_sum", key)] - before[("gmt_batch_size_sum", key)] == 2 * n
    assert after[small] == before[small]
    # Batching changes nothing: every session's actions are the engine's for that session alone.
    for i in range(n):
        ctx = engine.new_context(i % 3)
        for t in range(rounds):
            want = engine.act([ctx], [obs[t, i]])[0]
            assert got[t][i].status_code == 200
            np.testing.assert_array_equal(np.float32(got[t][i].json()["action"]), want)


def test_a_bad_row_inside_a_batch_fails_only_its_own_request(make_server, tmp_path):
    """Three concurrent acts share one forward pass; the middle one passes validation (its normalised value is
    finite, 3e38, through a checkpoint whose first observation dimension has a vanishing spread) but its row
    overflows in the network: it alone fails, and its session stays where it was."""
    from gmt.model.checkpoint import save_checkpoint
    from gmt.model.engine import PolicyEngine
    from gmt.model.fixtures import tiny_checkpoint

    fragile = tiny_checkpoint()
    fragile.obs_norm.mean[0], fragile.obs_norm.std[0] = 0.0, 1e9 / 3e38  # x0 = 1e9 normalises to 3e38
    save_checkpoint(fragile, tmp_path / "tiny-gmt")
    # Two rounds together first, so that the batcher waits for all three (it waits only for sessions acting); the
    # three acts must reach the batcher within the wait (2 s: room for a slow machine); the lone retry below
    # waits it out too (the other two are acting), inside the client's 5 s timeout.
    server = make_server(checkpoints=[tmp_path], batch_wait_ms=2_000)
    warm = np.random.default_rng(5).normal(size=(2, 3, OBS_DIM)).astype(np.float32)
    warm[:, :, 0] = 0.0
    obs = np.random.default_rng(4).normal(size=(3, OBS_DIM)).astype(np.float32)
    obs[:, 0] = 0.0
    bad = obs[1].copy()
    bad[0] = 1e9  # within the accepted range
    key = (("model", "tiny-gmt"), ("version", load_checkpoint(tmp_path / "tiny-gmt").version))
    with httpx.Client(base_url=server.url) as http:
        sids = [create(http, goal=2) for _ in range(3)]
        for w in warm:
            assert [r.status_code for r in asyncio.run(_act_all(server.url, sids, w))] == [200] * 3
        before = metric_samples(http, "gmt_batch_size")
        rs = asyncio.run(_act_all(server.url, sids, [obs[0], bad, obs[2]]))
        assert [r.status_code for r in rs] == [200, 400, 200]
        assert rs[1].json()["error"]["code"] == "invalid_argument"
        batches = metric_samples(http, "gmt_batch_size")
        assert batches[("gmt_batch_size_count", key)] - before[("gmt_batch_size_count", key)] == 1
        assert batches[("gmt_batch_size_sum", key)] - before[("gmt_batch_size_sum", key)] == 3
        retry = act(http, sids[1], obs[1])  # the failed session is where it was: its step 2 again
        assert retry.status_code == 200 and retry.json()["step"] == 2
    engine = PolicyEngine(fragile)
    for i, r, o in ((0, rs[0], obs[0]), (2, rs[2], obs[2]), (1, retry, obs[1])):
        ctx = engine.new_context(2)
        for w in warm:
            engine.act([ctx], [w[i]])
        np.testing.assert_array_equal(np.float32(r.json()["action"]), engine.act([ctx], [o])[0])


def test_grpc_deadline_is_respected_and_the_session_is_unchanged(make_server, observations):
    # Two sessions that acted together, then one request: the batcher would wait 20 s for the other, acting.
    server = make_server(batch_wait_ms=20_000)
    stub = stub_for(server)
    victim, twin = (
        stub.CreateSession(pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=1))).session_id
        for _ in range(2)
    )
    for o in observations[2:4]:
        futs = [
            stub.Act.future(pb.ActRequest(session_id=s, values=pb.FloatVector(values=o)))
            for s in (victim, twin)
        ]
        assert [f.result(timeout=30).step for f in futs] == [futs[0].result().step] * 2
    with pytest.raises(grpc.RpcError) as e:
        stub.Act(pb.ActRequest(session_id=victim, values=pb.FloatVector(values=observations[0])), timeout=0.3)
    assert e.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    # Had the server kept the timed-out request, the victim would be one step ahead of its twin.
    futs = [
        stub.Act.future(pb.ActRequest(session_id=s, values=pb.FloatVector(values=observations[1])))
        for s in (victim, twin)
    ]
    a, b = (f.result(timeout=30) for f in futs)
    assert a.step == b.step == 2 and list(a.action) == list(b.action)
    with httpx.Client(base_url=server.url) as http:
        samples = metric_samples(http, "gmt_request_duration_seconds")
    assert (
        samples[
            (
                "gmt_request_duration_seconds_count",
                (("code", "DEADLINE_EXCEEDED"), ("method", "Act"), ("transport", "grpc")),
            )
        ]
        == 1
    )


# ----- auth ---------------------------------------------------------------------------------------------------
def test_bearer_auth_on_both_transports(make_server, observations):
    server = make_server(auth_token="s3cret")
    good = {"Authorization": "Bearer s3cret"}
    with httpx.Client(base_url=server.url) as http:
        assert http.get("/healthz").status_code == 200 and http.get("/readyz").status_code == 200
        r = http.get("/models")
        assert r.status_code == 401 and r.headers["WWW-Authenticate"] == "Bearer"
        assert r.json()["error"] == {
            "code": "unauthenticated",
            "message": "missing bearer token: send 'Authorization: Bearer <token>'",
        }
        assert http.get("/metrics").status_code == 401
        victim, twin = (
            http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}, headers=good).json()["session_id"]
            for _ in range(2)
        )
        r = http.post(
            f"/sessions/{victim}/act",
            json={"observation": observations[0].tolist()},
            headers={"Authorization": "Bearer nope"},
        )
        assert r.status_code == 401 and r.json()["error"]["message"] == "invalid bearer token"
        a, b = (
            http.post(
                f"/sessions/{s}/act", json={"observation": observations[0].tolist()}, headers=good
            ).json()
            for s in (victim, twin)
        )
        assert a["step"] == b["step"] == 0 and a["action"] == b["action"]

    with grpc.insecure_channel(server.target) as ch:
        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        health = health_pb2_grpc.HealthStub(ch)
        assert (
            health.Check(health_pb2.HealthCheckRequest(service="")).status
            == health_pb2.HealthCheckResponse.SERVING
        )
        for md, msg in (
            (None, "missing bearer token"),
            ((("authorization", "Bearer nope"),), "invalid bearer token"),
        ):
            with pytest.raises(grpc.RpcError) as e:
                stub.ListModels(pb.ListModelsRequest(), metadata=md)
            assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED and msg in e.value.details()
            with pytest.raises(grpc.RpcError) as e:
                req = pb.ControlRequest(
                    act=pb.ActRequest(session_id=victim, values=pb.FloatVector(values=observations[1]))
                )
                list(stub.Control(iter([req]), metadata=md))
            assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
        md = (("authorization", "Bearer s3cret"),)
        a, b = (
            stub.Act(pb.ActRequest(session_id=s, values=pb.FloatVector(values=observations[1])), metadata=md)
            for s in (victim, twin)
        )
        assert a.step == b.step == 1 and list(a.action) == list(b.action)


def test_health_reflection_and_readiness_without_models(make_server, tmp_path):
    from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

    empty = make_server(checkpoints=[tmp_path / "nothing-here"])
    with httpx.Client(base_url=empty.url) as http:
        assert http.get("/healthz").json() == {"status": "ok"}
        r = http.get("/readyz")
        assert r.status_code == 503 and r.json()["ready"] is False and r.json()["reason"] == "no model loaded"
        r = http.post("/sessions", json={"goal": 0})
        assert r.status_code == 503 and r.json()["error"]["message"] == "no model is loaded on this server"
    with grpc.insecure_channel(empty.target) as ch:
        h = health_pb2_grpc.HealthStub(ch).Check(
            health_pb2.HealthCheckRequest(service="gmt.v1.PolicyService")
        )
        assert h.status == health_pb2.HealthCheckResponse.NOT_SERVING
        services = ProtoReflectionDescriptorDatabase(ch).get_services()
        assert "gmt.v1.PolicyService" in services and "grpc.health.v1.Health" in services
        with pytest.raises(grpc.RpcError) as e:
            policy_pb2_grpc.PolicyServiceStub(ch).CreateSession(
                pb.CreateSessionRequest(goal=pb.GoalSelector(id=0))
            )
        assert e.value.code() == grpc.StatusCode.UNAVAILABLE


def test_calls_on_one_session_are_applied_one_at_a_time(make_server, engine):
    server = make_server(batch_wait_ms=5)
    obs = np.random.default_rng(9).normal(size=(6, OBS_DIM)).astype(np.float32)
    with httpx.Client(base_url=server.url) as http:
        sid = create(http, goal=1)
        rs = asyncio.run(_act_all(server.url, [sid] * 6, obs))
        assert http.get(f"/sessions/{sid}").json()["step"] == 6
    steps = [r.json()["step"] for r in rs]
    assert sorted(steps) == list(range(6))  # each call saw the context its predecessor left
    ctx = engine.new_context(1)
    for i in np.argsort(steps):  # the order the server applied them in
        np.testing.assert_array_equal(np.float32(rs[i].json()["action"]), engine.act([ctx], [obs[i]])[0])


def test_openapi_lists_exactly_the_designed_routes(http):
    spec = http.get("/openapi.json").json()
    routes = {(m.upper(), p) for p, ops in spec["paths"].items() for m in ops}
    assert routes == {
        ("GET", "/models"),
        ("GET", "/models/{name}"),
        ("POST", "/sessions"),
        ("GET", "/sessions"),  # the console's listing (docs/ui.md)
        ("GET", "/sessions/{session_id}"),
        ("GET", "/sessions/{session_id}/events"),  # the console's event stream
        ("POST", "/sessions/{session_id}/act"),
        ("POST", "/act"),
        ("PUT", "/sessions/{session_id}/goal"),
        ("POST", "/sessions/{session_id}/reset"),
        ("DELETE", "/sessions/{session_id}"),
        ("GET", "/sessions/{session_id}/timeline"),
        ("GET", "/sessions/{session_id}/recording"),
        ("GET", "/healthz"),
        ("GET", "/readyz"),
        ("GET", "/metrics"),
        ("POST", "/models/{name}/versions"),  # model management (docs/models.md)
        ("PUT", "/models/{name}/default"),
        ("POST", "/models/{name}/versions/{version}/drain"),
        ("DELETE", "/models/{name}/versions/{version}"),
    }
    assert http.get("/docs").status_code == 200


def test_the_openapi_document_resolves_every_reference_with_and_without_models(make_server, tmp_path):
    """The act routes declare their bodies outside FastAPI's body models: the schemas they refer to are in the
    document whether or not a model is loaded."""
    import json
    import re

    for server in (make_server(), make_server(checkpoints=[tmp_path / "nothing-here"])):
        with httpx.Client(base_url=server.url) as http:
            doc = http.get("/openapi.json").json()
        refs = set(re.findall(r'"#/components/schemas/([^"]+)"', json.dumps(doc)))
        assert {"ActItem", "Tensor"} <= refs  # from the act bodies
        assert refs <= set(doc["components"]["schemas"]), refs - set(doc["components"]["schemas"])
        for path in ("/act", "/sessions/{session_id}/act"):
            assert doc["paths"][path]["post"]["requestBody"]["content"]["application/json"]["schema"]
