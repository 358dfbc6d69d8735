"""Sessions in Redis (a real redis-server on a free loopback port): codec, store semantics, replica failover."""

import asyncio
import dataclasses
import json

import httpx
import numpy as np
import pytest
from service_harness import RunningServer, ServeProcess, make_settings

from gmt.client.grpc import GrpcClient
from gmt.client.rest import RestClient
from gmt.model.checkpoint import load_checkpoint
from gmt.model.engine import PolicyEngine
from gmt.model.fixtures import tiny_checkpoint
from gmt.service import session_codec
from gmt.service.errors import Aborted, NotFound, ResourceExhausted, SessionExpired
from gmt.service.sessions import Session


@pytest.fixture(scope="module")
def cartpole(ckpt_root) -> PolicyEngine:
    return PolicyEngine(load_checkpoint(ckpt_root / "tiny-cartpole"))


def _same_stored(want, got) -> None:
    for f in dataclasses.fields(want):  # every field of the stored form survives, whatever is added later
        a, b = getattr(want, f.name), getattr(got, f.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b), f.name
        else:
            assert a == b, f.name


def test_codec_writes_what_changed_and_reads_back_exactly(cartpole):
    rng = np.random.default_rng(0)
    ctx = cartpole.new_context(1, action_mode="sample", seed=11, key="s1")
    session = Session("s1", "tiny-cartpole", ctx, 1.0, 2.0, request="tiny-cartpole|1|11|sample")
    stored = {k.encode(): v for k, v in session_codec.create_fields(session).items()}  # what Redis holds
    meta = json.loads(stored[b"meta"])  # plain JSON, no pickle anywhere
    assert meta["id"] == "s1" and meta["layout"]["H"] == cartpole.pool.H
    since = 0
    obs = rng.normal(size=(3 * cartpole.pool.H, 4)).astype(np.float32)
    for t, o in enumerate(obs[:-4]):  # past the held history: old records are overwritten in place
        if t == 5:
            cartpole.set_goal(ctx, 0, blend_steps=2)
            change = session_codec.change_fields(session, since)
            assert set(change) == {"ver", "st"}  # a goal change writes no step record
            stored.update({k.encode(): v for k, v in change.items()})
        cartpole.act([ctx], [o])
        change = session_codec.change_fields(session, since)
        assert set(change) == {"ver", "st", f"r:{t % cartpole.pool.H}"}  # an act writes its one record
        assert all(isinstance(v, bytes) and not v.startswith(b"\x80") for v in change.values())
        stored.update({k.encode(): v for k, v in change.items()})
        since = ctx.step
    back = session_codec.decode(stored)
    assert (back.id, back.model, back.created_at, back.last_used) == ("s1", "tiny-cartpole", 1.0, 2.0)
    assert back.request == session.request
    _same_stored(ctx.to_stored(), back.ctx)
    # Sampled actions continue identically in a context adopted from the stored form.
    twin = PolicyEngine(cartpole.ckpt)
    adopted = twin.from_stored(back.ctx, key="s1")
    original = [cartpole.act([ctx], [o])[0] for o in obs[-4:]]
    restored = [twin.act([adopted], [o])[0] for o in obs[-4:]]
    assert original == restored and ctx.version == adopted.version
    # A reset writes no record, and the steps after it are read back without the old episode's.
    cartpole.reset(ctx)
    stored.update({k.encode(): v for k, v in session_codec.change_fields(session, ctx.step + 4).items()})
    cartpole.act([ctx], [obs[0]])
    stored.update({k.encode(): v for k, v in session_codec.change_fields(session, 0).items()})
    _same_stored(ctx.to_stored(), session_codec.decode(stored).ctx)


def test_changes_built_together_are_the_changes_built_one_by_one(cartpole, engine, monkeypatch):
    rng = np.random.default_rng(3)
    sessions, since = [], []
    for eng, dim, name in (
        (engine, engine.pool.h_state.shape[2], "tiny-gmt"),
        (cartpole, 4, "tiny-cartpole"),
    ):
        for i in range(6):
            mode = eng.action_modes[i % len(eng.action_modes)]
            ctx = eng.new_context(i % 2, action_mode=mode, seed=i, key=f"{name}{i}")
            s = Session(f"{name}{i}", name, ctx, 1.0 + i, 2.5 + i / 3)
            for _ in range(3 + i):
                eng.act([ctx], [rng.normal(size=dim).astype(np.float32)])
            held = ctx.step
            if i == 1:  # blending toward a new goal, then one act
                eng.set_goal(ctx, 0, blend_steps=3)
            if i == 2:  # a reset: no record
                eng.reset(ctx)
            if i != 2:
                eng.act([ctx], [rng.normal(size=dim).astype(np.float32)])
            if i == 3:  # two acts since the held step: both records
                eng.act([ctx], [rng.normal(size=dim).astype(np.float32)])
            if i == 4:  # a goal change that relabelled held steps
                s.relabelled_from = held - 2
            sessions.append(s)
            since.append(held)
    want = [session_codec.change_fields(s, t) for s, t in zip(sessions, since, strict=True)]
    one_by_one = []
    real = session_codec.change_fields
    monkeypatch.setattr(session_codec, "change_fields", lambda s, t: one_by_one.append(s.id) or real(s, t))
    got = session_codec.change_fields_many(sessions, since)
    assert got == want  # the same fields, bit for bit
    # Only the changes that are not one act went one by one (reset, two acts, relabelled): 3 per pool.
    assert sorted(one_by_one) == sorted(f"{n}{i}" for n in ("tiny-gmt", "tiny-cartpole") for i in (2, 3, 4))


def test_a_save_entry_is_its_arguments_as_resp():
    from gmt.service import redis_scripts, resp

    fields = {f"r:{i}": bytes([i]) * (i + 1) for i in range(12)} | {"ver": b"7@1.5", "st": b"{}"}
    for lists in ([], [[b"tl-1", b"tl-2"]], [[b"a"], [b"b" * 300, b"", b"c"]]):
        for expect in (b"", b"6@1.5"):
            got, count = redis_scripts.save_entry(expect, fields, lists)
            args = [expect, len(fields), len(lists), *redis_scripts.flat(fields)]
            for values in lists:
                args += [len(values), *values]
            assert (got, count) == (resp.bulk(args), len(args))
            # ... and reads back as those arguments inside a whole command.
            back, _ = resp.parse(resp.command(count + 1, resp.bulk(["EVAL"]), got))
            assert back == [b"EVAL", *(a if isinstance(a, bytes) else str(a).encode() for a in args)]


def test_codec_refuses_foreign_and_broken_data(cartpole):
    with pytest.raises(session_codec.CodecError):
        session_codec.decode({b"meta": b"\x80\x04K\x01."})  # a pickle
    ctx = cartpole.new_context(1, key="s2")
    session = Session("s2", "tiny-cartpole", ctx, 1.0, 2.0)
    stored = dict(session_codec.create_fields(session))
    for o in np.zeros((3, 4), np.float32):
        cartpole.act([ctx], [o])
        stored.update(session_codec.change_fields(session, ctx.step - 1))
    assert session_codec.decode(stored).ctx.step == 3
    with pytest.raises(session_codec.CodecError, match="record of step 1 is missing"):
        session_codec.decode({k: v for k, v in stored.items() if k != "r:1"})
    with pytest.raises(session_codec.CodecError, match="slot 2 holds step 1"):
        session_codec.decode({**stored, "r:2": stored["r:1"]})
    meta = json.loads(stored["meta"])
    with pytest.raises(session_codec.CodecError, match="format v2 is not v3"):
        session_codec.decode({**stored, "meta": json.dumps({**meta, "v": 2}).encode()})


def test_redis_store_semantics(redis_clean_any, engine, clock):
    from gmt.service.redis_store import RedisSessionStore

    redis_clean = redis_clean_any

    def new(sid: str, goal: int) -> Session:
        return Session(sid, "tiny-gmt", engine.new_context(goal, key=sid), clock(), clock())

    async def act(store, sid: str) -> Session:
        got = await store.get(sid)
        read = got.ctx.version
        if not isinstance(got.ctx, type(engine.new_context(0))):
            got.ctx = engine.from_stored(got.ctx, key=sid)
        engine.act([got.ctx], [np.zeros(17, np.float32)])
        got.last_used = clock()
        await store.save(got, read)
        return got

    async def scenario():
        a = RedisSessionStore(redis_clean, idle_timeout_s=10, max_sessions=2, clock=clock)
        b = RedisSessionStore(redis_clean, idle_timeout_s=10, max_sessions=2, clock=clock)  # a second replica
        try:
            await a.create(new("one", 0))
            await b.create(new("two", 2))
            with pytest.raises(ResourceExhausted, match=r"server is full: 2 live sessions \(maximum 2\)"):
                await a.create(new("three", 0))
            assert await a.count() == await b.count() == 2
            stale = await a.get("one")  # replica a holds "one" at step 0
            clock.advance(6)
            got = await act(b, "one")  # ... while replica b acts for it
            again = await (RedisSessionStore(redis_clean, 10, 2, clock)).get("one")
            assert again.ctx.step == 1 and np.array_equal(again.ctx.states, got.ctx.states)
            # The act was written over the store's own pipelined connection, on the URL's transport.
            assert b.commit.fast is not None and not b.commit.fast.closed
            assert (b.commit.fast.path is not None) == redis_clean.startswith("unix://")
            # Compare-and-set: a replica whose copy is old loses the race instead of overwriting.
            stale.ctx = engine.from_stored(stale.ctx, key="stale")
            engine.set_goal(stale.ctx, 1)
            with pytest.raises(Aborted, match="changed by another replica"):
                await a.save(stale, 0)
            assert (await a.get("one")).ctx.step == 1  # a dropped its copy and read the stored one
            assert (await b.get("one")).ctx.goal == 0
            clock.advance(6)  # "two" is now idle for 12 s, "one" for 6 s
            assert [s.id for s in await a.sweep()] == ["two"]
            with pytest.raises(SessionExpired, match="session 'two' expired"):
                await b.get("two")
            await a.create(new("three", 0))
            three = await b.get("three")
            await a.delete("three")
            three.ctx = engine.from_stored(three.ctx, key="three")
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


def test_a_turns_changes_are_encoded_together_and_one_that_cannot_be_fails_its_writer_alone(
    redis_clean, engine, clock
):
    """Writes queued in one turn of the loop, by different requests, are encoded in one go as their script call is
    sent (`RedisSessionStore._encode`); a change that cannot be encoded fails its own writer with `internal` (none
    hangs) while the turn's other writers are written, and its session writes again afterwards."""
    from gmt.service.errors import Internal
    from gmt.service.redis_store import RedisSessionStore

    async def scenario():
        store = RedisSessionStore(redis_clean, idle_timeout_s=10, max_sessions=8, clock=clock)
        encoded: list[list[str]] = []
        broken: set[str] = set()
        encode = store.commit._encode

        def watched(changes):
            encoded.append([c[0].id for c in changes])
            if broken & {c[0].id for c in changes}:
                raise ValueError("an unencodable change")
            return encode(changes)

        store.commit._encode = watched

        async def act(s):
            read = s.ctx.version
            if not isinstance(s.ctx, type(engine.new_context(0))):
                s.ctx = engine.from_stored(s.ctx, key=s.id)
            engine.act([s.ctx], [np.zeros(17, np.float32)])
            await store.save(s, read)

        async def stored_steps():
            fresh = RedisSessionStore(redis_clean, idle_timeout_s=10, max_sessions=8, clock=clock)
            try:
                return [(await fresh.get(sid)).ctx.step for sid in ("a", "b")]
            finally:
                await fresh.close()

        try:
            for sid in ("a", "b"):
                await store.create(Session(sid, "tiny-gmt", engine.new_context(0, key=sid), clock(), clock()))
            got = [await store.get(sid) for sid in ("a", "b")]
            await asyncio.gather(*(act(s) for s in got))  # two requests, one turn: one encoding, one call
            assert encoded == [["a", "b"]]
            broken.add("b")
            outcomes = await asyncio.gather(*(act(s) for s in got), return_exceptions=True)
            assert encoded[1:] == [["a", "b"], ["a"], ["b"]]  # together, then writer by writer
            assert outcomes[0] is None and type(outcomes[1]) is Internal
            assert "could not encode this request's write" in str(outcomes[1])
            assert await stored_steps() == [2, 1]  # a's write went; b's never reached Redis
            broken.clear()
            await act(await store.get("b"))  # b was let go here: read back at step 1, it writes again
            assert await stored_steps() == [2, 2]
        finally:
            await store.close()

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


def test_a_relabelling_switch_is_stored_whole_and_another_replica_continues_exactly(redis_clean, tmp_path):
    """A goal change that relabels past steps (`switch_relabel_steps`) rewrites records the store already holds:
    the write must carry them, or a replica adopting the session rebuilds it from the old goal tokens."""
    tiny_checkpoint(
        tmp_path / "tiny-relabel", name="tiny-relabel", attention="window", switch_relabel_steps=4
    )
    ckpt = load_checkpoint(tmp_path / "tiny-relabel")
    obs = np.random.default_rng(8).normal(size=(12, 17)).astype(np.float32)
    twin, plain = PolicyEngine(ckpt), PolicyEngine(ckpt, switch_relabel_steps=0)
    ctx, pctx = twin.new_context(0), plain.new_context(0)
    want, unrelabelled = [], []
    for t in range(12):
        if t == 6:
            assert twin.set_goal(ctx, 2) == 4
            plain.set_goal(pctx, 2)
        want.append(twin.act([ctx], [obs[t]])[0])
        unrelabelled.append(plain.act([pctx], [obs[t]])[0])
    assert not np.array_equal(np.stack(want[6:]), np.stack(unrelabelled[6:]))  # the relabelling matters

    settings = dict(checkpoints=[tmp_path], redis_url=redis_clean)
    a, b = RunningServer(make_settings(**settings)).start(), RunningServer(make_settings(**settings)).start()
    try:
        # The model spec says so, over both transports and through both clients.
        with RestClient(a.url) as rc, GrpcClient(a.target) as gc:
            assert rc.get_model("tiny-relabel").switch_relabel_steps == 4
            assert gc.get_model("tiny-relabel").switch_relabel_steps == 4
        with httpx.Client(base_url=a.url) as ha, httpx.Client(base_url=b.url) as hb:
            sid = ha.post("/sessions", json={"model": "tiny-relabel", "goal": 0}).json()["session_id"]
            for t in range(12):
                http = ha if t < 8 else hb  # b adopts the session from the store at step 8
                if t == 6:
                    assert ha.put(f"/sessions/{sid}/goal", json={"goal": 2}).status_code == 200
                r = http.post(f"/sessions/{sid}/act", json={"observation": obs[t].tolist(), "step": t})
                assert r.status_code == 200, r.text
                assert r.headers["x-served-by"] == http.get("/healthz").headers["x-served-by"]
                np.testing.assert_array_equal(np.float32(r.json()["action"]), want[t])
    finally:
        a.stop()
        b.stop()


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


def test_the_sweep_keeps_the_keys_of_a_session_in_use_from_their_ttl(redis_clean, engine, clock):
    """Acts do not set the keys' TTL (`redis_scripts.SAVE`); the replica's sweep sets it again for every session it
    served since its last sweep: the session hash and the lists beside it, so a session in use never loses them."""
    import redis

    from gmt.service.redis_store import RedisSessionStore

    async def scenario() -> tuple:
        store = RedisSessionStore(redis_clean, idle_timeout_s=10, max_sessions=4, clock=clock)
        try:
            ctx = engine.new_context(0, key="kept")
            await store.create(Session("kept", "tiny-gmt", ctx, clock(), clock()))
            keys = [store.layout.session("kept"), *store.layout.lists("kept")]
            with redis.Redis.from_url(redis_clean) as r:
                held = [k for k in keys if r.exists(k)]
                for k in held:
                    r.pexpire(k, 5_000)  # as if the session had been created long ago
                got = await store.get("kept")
                read = got.ctx.version
                if not isinstance(got.ctx, type(ctx)):
                    got.ctx = engine.from_stored(got.ctx, key="kept")
                engine.act([got.ctx], [np.zeros(17, np.float32)])
                clock.advance(1)
                got.last_used = clock()
                await store.save(got, read)
                after_act = [r.pttl(k) for k in held]
                await store.sweep()
                after_sweep = [r.pttl(k) for k in held]
        finally:
            await store.close()
        return held, after_act, after_sweep, store.layout.ttl_ms

    held, after_act, after_sweep, ttl_ms = asyncio.run(scenario())
    assert held and held[0].endswith(":s")
    assert all(0 < t <= 5_000 for t in after_act)  # the act left the TTL alone
    assert all(ttl_ms - 5_000 < t <= ttl_ms for t in after_sweep)  # the sweep set it again


def test_a_remote_store_keeps_more_smaller_passes_in_flight(ckpt_root, redis_clean):
    """Over Redis (writes that wait for another process) a model's batcher takes a quarter of the acting sessions
    per pass, in memory half (`REMOTE_STORE_PARTS`, measured in docs/performance.md)."""
    import time

    from gmt.service.batcher import REMOTE_STORE_PARTS
    from gmt.service.core import Core

    async def parts(redis_url):
        core = Core(make_settings(checkpoints=[ckpt_root / "tiny-gmt"], redis_url=redis_url), clock=time.time)
        await core.start()
        try:
            return core.store.remote, [b.parts for b in core._batchers.values()]
        finally:
            await core.close()

    assert asyncio.run(parts(redis_clean)) == (True, [REMOTE_STORE_PARTS])
    assert asyncio.run(parts(None)) == (False, [2])
