"""Sessions in Redis (a real redis-server on a free loopback port): codec, store semantics, replica failover."""

import asyncio
import dataclasses
import json

import httpx
import numpy as np
import pytest
from service_harness import RunningServer, ServeProcess, make_settings

from model.checkpoint import load_checkpoint
from model.engine import PolicyEngine
from service import session_codec
from service.errors import Aborted, NotFound, ResourceExhausted, SessionExpired
from service.sessions import Session


@pytest.fixture(scope="module")
def cartpole(ckpt_root) -> PolicyEngine:
    return PolicyEngine(load_checkpoint(ckpt_root / "tiny-cartpole"))


def test_codec_round_trip_keeps_every_field_and_the_actions_exact(cartpole):
    rng = np.random.default_rng(0)
    ctx = cartpole.new_context(1, action_mode="sample", seed=11, key="s1")
    obs = rng.normal(size=(9, 4)).astype(np.float32)
    for o in obs[:6]:
        cartpole.act([ctx], [o])
    cartpole.set_goal(ctx, 0, blend_steps=2)
    fields = session_codec.encode(Session("s1", "tiny-cartpole", ctx, 1.0, 2.0))
    meta = json.loads(fields["meta"])  # plain JSON, no pickle anywhere
    assert meta["id"] == "s1" and json.loads(fields["ctx"])["scalars"]["seed"] == 11
    assert all(isinstance(v, bytes) and not v.startswith(b"\x80") for v in fields.values())
    back = session_codec.decode({k.encode(): v for k, v in fields.items()})
    assert (back.id, back.model, back.created_at, back.last_used) == ("s1", "tiny-cartpole", 1.0, 2.0)
    want = ctx.to_stored()
    for f in dataclasses.fields(want):  # every field of the stored form survives, whatever is added later
        a, b = getattr(want, f.name), getattr(back.ctx, f.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b), f.name
        else:
            assert a == b, f.name
    # Sampled actions continue identically in a context adopted from the stored form.
    twin = PolicyEngine(cartpole.ckpt)
    adopted = twin.from_stored(back.ctx, key="s1")
    original = [cartpole.act([ctx], [o])[0] for o in obs[6:]]
    restored = [twin.act([adopted], [o])[0] for o in obs[6:]]
    assert original == restored and ctx.version == adopted.version


def test_codec_refuses_foreign_data():
    with pytest.raises(session_codec.CodecError):
        session_codec.decode({b"meta": b"\x80\x04K\x01."})  # a pickle
    meta = json.dumps(
        {"v": session_codec.FORMAT_VERSION, "id": "x", "model": "m", "created_at": 0, "last_used": 0}
    )
    bad = {"v": 2, "scalars": {"goal": 0}, "arrays": {}}
    with pytest.raises(session_codec.CodecError, match="do not match"):
        session_codec.decode({b"meta": meta.encode(), b"ctx": json.dumps(bad).encode()})


def test_redis_store_semantics(redis_clean, engine, clock):
    from service.redis_store import RedisSessionStore

    async def scenario():
        a = RedisSessionStore(redis_clean, idle_timeout_s=10, max_sessions=2, clock=clock)
        b = RedisSessionStore(redis_clean, idle_timeout_s=10, max_sessions=2, clock=clock)  # a second replica
        try:
            s1 = Session("one", "tiny-gmt", engine.new_context(0), clock(), clock())
            await a.create(s1)
            await b.create(Session("two", "tiny-gmt", engine.new_context(2), clock(), clock()))
            with pytest.raises(ResourceExhausted, match=r"server is full: 2 live sessions \(maximum 2\)"):
                await a.create(Session("three", "tiny-gmt", engine.new_context(0), clock(), clock()))
            assert await a.count() == await b.count() == 2
            got = await b.get("one")
            read = got.ctx.version
            got.ctx = engine.from_stored(got.ctx, key="one")
            engine.act([got.ctx], [np.zeros(17, np.float32)])
            clock.advance(6)
            got.last_used = clock()
            await b.save(got, read)
            again = await a.get("one")
            assert again.ctx.step == 1 and np.array_equal(again.ctx.states, got.ctx.states)
            # Compare-and-set: a replica that read the old version loses the race instead of overwriting.
            stale = Session("one", "tiny-gmt", engine.new_context(1), clock(), clock())
            with pytest.raises(Aborted, match="changed by another replica"):
                await a.save(stale, read)
            assert (await b.get("one")).ctx.goal == 0
            clock.advance(6)  # "two" is now idle for 12 s, "one" for 6 s
            assert [s.id for s in await a.sweep()] == ["two"]
            with pytest.raises(SessionExpired, match="session 'two' expired"):
                await b.get("two")
            await a.create(Session("three", "tiny-gmt", engine.new_context(0), clock(), clock()))
            three = await b.get("three")
            await a.delete("three")
            with pytest.raises(NotFound, match="closed or expired"):  # a write never revives it
                await b.save(three, three.ctx.version)
            with pytest.raises(NotFound, match="session 'three' was closed"):
                await b.get("three")
            clock.advance(20)
            with pytest.raises(SessionExpired):  # expired on access, without a sweep
                await a.get("one")
        finally:
            await a.close()
            await b.close()

    asyncio.run(scenario())


def test_replica_dies_and_another_answers_exactly_as_it_would_have(redis_clean, ckpt_root, engine, cartpole):
    rng = np.random.default_rng(5)
    obs = rng.normal(size=(10, 17)).astype(np.float32)
    cobs = rng.normal(size=(10, 4)).astype(np.float32)
    # What one uninterrupted replica answers: the engine, step by step (goal switch with a blend at step 3).
    ctx = engine.new_context(0)
    cctx = cartpole.new_context(1, action_mode="sample", seed=5)
    want, cwant = [], []
    for t in range(10):
        if t == 3:
            engine.set_goal(ctx, 2, blend_steps=4)
        want.append(engine.act([ctx], [obs[t]])[0])
        cwant.append(cartpole.act([cctx], [cobs[t]])[0])

    a = ServeProcess("--checkpoints", str(ckpt_root), "--redis-url", redis_clean)
    try:
        a.wait_serving()
        with httpx.Client(base_url=a.url) as http:
            sid = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
            body = {"model": "tiny-cartpole", "goal": 1, "action_mode": "sample", "seed": 5}
            csid = http.post("/sessions", json=body).json()["session_id"]
            for t in range(5):
                if t == 3:
                    assert (
                        http.put(f"/sessions/{sid}/goal", json={"goal": 2, "blend_steps": 4}).status_code
                        == 200
                    )
                r = http.post(f"/sessions/{sid}/act", json={"observation": obs[t].tolist()}).json()
                np.testing.assert_array_equal(np.float32(r["action"]), want[t])
                c = http.post(f"/sessions/{csid}/act", json={"observation": cobs[t].tolist()}).json()
                assert c["action"] == cwant[t]
    finally:
        a.kill()  # SIGKILL: no goodbye, no flush
    assert a.proc.returncode == -9

    b = RunningServer(make_settings(checkpoints=[ckpt_root], redis_url=redis_clean)).start()
    try:
        with httpx.Client(base_url=b.url) as http:
            s = http.get(f"/sessions/{sid}").json()
            assert s["step"] == 5 and s["goal"] == 2 and s["blend_remaining"] == 2
            for t in range(5, 10):
                r = http.post(f"/sessions/{sid}/act", json={"observation": obs[t].tolist()})
                assert r.status_code == 200 and r.json()["step"] == t
                np.testing.assert_array_equal(np.float32(r.json()["action"]), want[t])
                c = http.post(f"/sessions/{csid}/act", json={"observation": cobs[t].tolist()}).json()
                assert c["action"] == cwant[t]
            assert len(set(cwant)) > 1  # sampling really happened, so the generator state mattered
    finally:
        b.stop()
    # A replica that does not serve the session's model says so.
    c = RunningServer(make_settings(checkpoints=[ckpt_root / "tiny-gmt"], redis_url=redis_clean)).start()
    try:
        with httpx.Client(base_url=c.url) as http:
            r = http.post(f"/sessions/{csid}/act", json={"observation": cobs[0].tolist()})
            assert r.status_code == 409 and r.json()["error"] == {
                "code": "failed_precondition",
                "message": f"session '{csid}' runs model 'tiny-cartpole', which this server does not serve",
            }
    finally:
        c.stop()


def test_with_a_shared_store_a_replica_holds_a_slot_only_for_sessions_it_acts_for(redis_clean, ckpt_root):
    s = RunningServer(make_settings(checkpoints=[ckpt_root], redis_url=redis_clean)).start()
    try:
        pool = s.core.registry.get("tiny-gmt").engine.pool
        with httpx.Client(base_url=s.url) as http:
            sid = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
            assert pool.live == 0  # creating it stored it; a proxy may route its acts to another replica
            r = http.post(f"/sessions/{sid}/act", json={"observation": [0.0] * 17})
            assert r.status_code == 200 and pool.live == 1
            assert http.delete(f"/sessions/{sid}").status_code == 204 and pool.live == 0
    finally:
        s.stop()
