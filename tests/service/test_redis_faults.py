"""Redis restarted (AOF) or paused mid-episode, no primary at all behind the sentinels, a step no replica holds:
the acts in between answer `unavailable` (quickly, naming the store), nothing acknowledged is lost, and the
episode then continues exactly like a twin that never saw the fault, without restarting the server."""

import os
import shutil
import signal
import subprocess
import time

import httpx
import numpy as np
import pytest
from service_harness import RunningServer, make_settings

from gmt.cluster import supervisor as cluster
from gmt.cluster.supervisor import free_port
from gmt.model.checkpoint import load_checkpoint
from gmt.model.engine import PolicyEngine
from gmt.service import session_codec

pytestmark = pytest.mark.skipif(
    shutil.which("redis-server") is None,
    reason="redis-server is not installed (apt-get install redis-server)",
)


def _start_redis(port: int, data_dir) -> subprocess.Popen:
    args = ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--save", ""]
    args += ["--appendonly", "yes", "--appendfsync", "always", "--dir", str(data_dir)]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, text=True)
    for line in proc.stdout:
        if "Ready to accept connections" in line:
            break
    assert proc.poll() is None, "redis-server did not start"
    return proc


def _act(http, sid, o, t):
    return http.post(f"/sessions/{sid}/act", json={"observation": o.tolist(), "step": t})


@pytest.mark.parametrize("fault", ["restart", "pause"])
def test_the_episode_survives_a_redis_fault_exactly(tmp_path, ckpt_root, fault):
    obs = np.random.default_rng(9).normal(size=(8, 17)).astype(np.float32)
    twin_engine = PolicyEngine(load_checkpoint(ckpt_root / "tiny-sampled"))
    twin = twin_engine.new_context(1, seed=4)
    want = [twin_engine.act([twin], [o])[0] for o in obs]

    port = free_port()
    redis = _start_redis(port, tmp_path)
    server = RunningServer(
        make_settings(checkpoints=[ckpt_root], redis_url=f"redis://127.0.0.1:{port}/0")
    ).start()
    try:
        with httpx.Client(base_url=server.url, timeout=30) as http:
            r = http.post("/sessions", json={"model": "tiny-sampled", "goal": 1, "seed": 4})
            sid = r.json()["session_id"]
            for t in range(4):
                np.testing.assert_array_equal(
                    np.float32(_act(http, sid, obs[t], t).json()["action"]), want[t]
                )
            if fault == "restart":
                redis.send_signal(signal.SIGTERM)  # a clean stop: the AOF holds every acknowledged write
                redis.wait(30)
                down = _act(http, sid, obs[4], 4)
                redis = _start_redis(port, tmp_path)
            else:
                os.kill(redis.pid, signal.SIGSTOP)
                try:
                    down = _act(http, sid, obs[4], 4)  # bounded by the store's 5 s socket timeout
                finally:
                    os.kill(redis.pid, signal.SIGCONT)
            assert down.status_code == 503 and down.json()["error"]["code"] == "unavailable", down.text
            assert "session store unreachable" in down.json()["error"]["message"]
            for t in range(4, 8):  # the same step again: nothing was lost or applied twice
                r = _act(http, sid, obs[t], t)
                assert r.status_code == 200, r.text
                np.testing.assert_array_equal(np.float32(r.json()["action"]), want[t])
    finally:
        server.stop()
        redis.terminate()
        redis.wait(10)


# ----- no primary at all (Sentinel); a step no replica holds --------------------------------------------------
def _spawn(args: list[str], log) -> subprocess.Popen:
    return subprocess.Popen(args, stdout=open(log, "ab"), stderr=subprocess.STDOUT)  # noqa: SIM115


def _redis_node(port: int, data_dir, *extra: str, aof: bool = True) -> subprocess.Popen:
    """redis-server on loopback (with `aof`, fsynced at every write), its log in `data_dir`; returns once it
    answers."""
    data_dir.mkdir(exist_ok=True)
    args = ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--save", ""]
    args += ["--appendonly", "yes", "--appendfsync", "always"] if aof else ["--appendonly", "no"]
    args += ["--dir", str(data_dir), "--repl-diskless-sync-delay", "0", *extra]
    proc = _spawn(args, data_dir / "redis.log")
    _poll(lambda: cluster._redis_ping("127.0.0.1", port), 10, f"redis-server on :{port} did not start", proc)
    return proc


def _poll(ready, timeout_s: float, what: str, proc=None) -> None:
    deadline = time.monotonic() + timeout_s
    while not ready():
        assert proc is None or proc.poll() is None, what
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def _stop(*procs: subprocess.Popen) -> None:
    for p in procs:
        if p.poll() is None:
            os.kill(p.pid, signal.SIGCONT)
            p.terminate()
    for p in procs:
        p.wait(10)


def _twin(ckpt_root, obs, goal=1, seed=4):
    engine = PolicyEngine(load_checkpoint(ckpt_root / "tiny-sampled"))
    ctx = engine.new_context(goal, seed=seed)
    return [engine.act([ctx], [o])[0] for o in obs]


def test_no_primary_at_all_answers_unavailable_and_service_resumes_when_one_is_back(tmp_path, ckpt_root):
    obs = np.random.default_rng(10).normal(size=(8, 17)).astype(np.float32)
    want = _twin(ckpt_root, obs)
    port = free_port()
    primary = _redis_node(port, tmp_path / "primary")
    sentinels, ports = [], [free_port() for _ in range(3)]
    server = None
    try:
        for i, p in enumerate(ports):
            work = tmp_path / f"sentinel-{i}"
            work.mkdir()
            (work / "sentinel.conf").write_text(cluster.sentinel_conf("127.0.0.1", p, port, work))
            sentinels.append(
                _spawn(["redis-server", str(work / "sentinel.conf"), "--sentinel"], work / "log")
            )
        for p in ports:
            _poll(
                lambda p=p: cluster._sentinel_primary("127.0.0.1", p) == port, 20, "a sentinel is not ready"
            )
        url = "redis+sentinel://" + ",".join(f"127.0.0.1:{p}" for p in ports) + f"/{cluster.SENTINEL_SERVICE}"
        server = RunningServer(make_settings(checkpoints=[ckpt_root], redis_url=url)).start()
        with httpx.Client(base_url=server.url, timeout=30) as http:
            r = http.post("/sessions", json={"model": "tiny-sampled", "goal": 1, "seed": 4})
            sid = r.json()["session_id"]
            for t in range(4):
                np.testing.assert_array_equal(
                    np.float32(_act(http, sid, obs[t], t).json()["action"]), want[t]
                )
            primary.kill()  # SIGKILL; no replica to promote
            primary.wait(10)
            # Each act answers 503 `unavailable` naming the store, quickly: first the refused connection, then
            # (once the sentinels agree it is down) that no sentinel names a primary.
            seen, deadline = [], time.monotonic() + 15
            while not any("No master found" in m for m in seen):
                assert time.monotonic() < deadline, seen
                t0 = time.monotonic()
                r = _act(http, sid, obs[4], 4)
                assert time.monotonic() - t0 < 6, "an act waited past the store's 5 s socket timeout"
                assert r.status_code == 503 and r.json()["error"]["code"] == "unavailable", r.text
                assert r.json()["error"]["message"].startswith("session store unreachable")
                seen.append(r.json()["error"]["message"])
                time.sleep(0.1)
            primary = _redis_node(
                port, tmp_path / "primary"
            )  # back, from its AOF; the server was not restarted
            deadline = time.monotonic() + 15
            while (r := _act(http, sid, obs[4], 4)).status_code != 200:
                assert r.status_code == 503 and r.json()["error"]["code"] == "unavailable", r.text
                assert time.monotonic() < deadline, "acts did not resume once the primary was back"
                time.sleep(0.1)
            for t in range(4, 8):
                r = r if t == 4 else _act(http, sid, obs[t], t)
                assert r.status_code == 200, r.text
                np.testing.assert_array_equal(np.float32(r.json()["action"]), want[t])
    finally:
        if server is not None:
            server.stop()
        _stop(primary, *sentinels)


def test_a_step_no_replica_holds_is_never_acknowledged(tmp_path, ckpt_root):
    import redis

    obs = np.random.default_rng(11).normal(size=(8, 17)).astype(np.float32)
    want = _twin(ckpt_root, obs)
    port, replica_port = free_port(), free_port()
    primary = _redis_node(port, tmp_path / "primary", aof=False)  # no fsync to slow the replica's answers
    replica = _redis_node(
        replica_port, tmp_path / "replica", "--replicaof", "127.0.0.1", str(port), aof=False
    )
    server = None
    try:
        _poll(
            lambda: cluster._replica_in_sync("127.0.0.1", replica_port, port), 10, "the replica did not sync"
        )
        settings = make_settings(
            checkpoints=[ckpt_root],
            redis_url=f"redis://127.0.0.1:{port}/0",
            store_min_replicas=1,
            store_wait_timeout_s=2.0,  # the writes before the SIGSTOP must be acknowledged, on a slow machine too
        )
        server = RunningServer(settings).start()
        with httpx.Client(base_url=server.url, timeout=30) as http, redis.Redis(port=port) as r:
            created = http.post("/sessions", json={"model": "tiny-sampled", "goal": 1, "seed": 4})
            assert created.status_code == 201, created.text
            sid = created.json()["session_id"]
            for t in range(4):
                got = _act(http, sid, obs[t], t)
                assert got.status_code == 200, got.text
                np.testing.assert_array_equal(np.float32(got.json()["action"]), want[t])
            os.kill(replica.pid, signal.SIGSTOP)
            down = _act(http, sid, obs[4], 4)
            assert down.status_code == 503 and down.json()["error"]["code"] == "unavailable", down.text
            assert "reached 0 of the 1 Redis replica(s) required" in down.json()["error"]["message"]
            # The primary holds step 4 (the retry could be answered from it), but no replica does: the retry is
            # not acknowledged either.
            assert session_codec.decode(r.hgetall(f"gmt:{{{sid}}}:s")).ctx.step == 5
            again = _act(http, sid, obs[4], 4)
            assert again.status_code == 503 and "Redis replica" in again.json()["error"]["message"], (
                again.text
            )
            # A session created meanwhile is refused, and not left behind to hold a slot.
            created = http.post("/sessions", json={"model": "tiny-sampled", "goal": 0})
            assert created.status_code == 503 and created.json()["error"]["code"] == "unavailable"
            assert r.zrange("gmt:live", 0, -1) == [sid.encode()]
            os.kill(replica.pid, signal.SIGCONT)
            deadline = time.monotonic() + 30
            while (got := _act(http, sid, obs[4], 4)).status_code != 200:
                assert got.status_code == 503, got.text
                assert time.monotonic() < deadline, "acts did not resume once the replica was back"
                time.sleep(0.05)
            for t in range(4, 8):
                got = got if t == 4 else _act(http, sid, obs[t], t)
                assert got.status_code == 200 and got.json()["step"] == t, got.text
                np.testing.assert_array_equal(np.float32(got.json()["action"]), want[t])
    finally:
        if server is not None:
            server.stop()
        _stop(replica, primary)


def test_writes_sent_while_a_wait_is_in_flight_share_the_next_wait(tmp_path, engine):
    """Group commit with `min_replicas`: the replica is paused, so the first write's WAIT stays in flight; four more
    writes, each in a turn of its own, go out at once without a WAIT of their own; once the replica resumes, one
    WAIT covers all four. Every write is acknowledged, and Redis ran 5 scripts but 2 WAITs (before: 5 and 5)."""
    import asyncio

    import redis

    from gmt.service.redis_store import RedisSessionStore
    from gmt.service.sessions import Session

    port, replica_port = free_port(), free_port()
    primary = _redis_node(port, tmp_path / "primary", aof=False)
    replica = _redis_node(
        replica_port, tmp_path / "replica", "--replicaof", "127.0.0.1", str(port), aof=False
    )
    try:
        _poll(
            lambda: cluster._replica_in_sync("127.0.0.1", replica_port, port), 10, "the replica did not sync"
        )

        async def scenario() -> list:
            store = RedisSessionStore(
                f"redis://127.0.0.1:{port}/0", 60, 10, time.time, min_replicas=1, wait_timeout_s=20
            )

            async def stepped(sid: str) -> tuple[Session, int]:
                got = await store.get(sid)
                read = got.ctx.version
                got.ctx = engine.from_stored(got.ctx, key=sid) if hasattr(got.ctx, "states") else got.ctx
                engine.act([got.ctx], [np.zeros(17, np.float32)])
                return got, read

            sids = [f"s{i}" for i in range(5)]
            for sid in sids:
                await store.create(
                    Session(sid, "tiny-gmt", engine.new_context(0, key=sid), time.time(), time.time())
                )
                await store.save(*await stepped(sid))  # (the first write opens the store's own connection)
            with redis.Redis(port=port) as r:
                r.config_resetstat()
                os.kill(replica.pid, signal.SIGSTOP)
                try:
                    saves = []
                    for sid in sids:
                        saves.append(asyncio.ensure_future(store.save(*await stepped(sid))))
                        await asyncio.sleep(0)  # the next write in a turn of its own
                        await asyncio.sleep(0)
                    assert store.commit.waiting_on is not None and len(store.commit.uncovered) == 4
                finally:
                    os.kill(replica.pid, signal.SIGCONT)
                results = await asyncio.gather(*saves, return_exceptions=True)
                stats = r.info("commandstats")
            await store.close()
            return [results, stats["cmdstat_eval"]["calls"], stats["cmdstat_wait"]["calls"]]

        results, evals, waits = asyncio.run(scenario())
        assert results == [None] * 5
        assert (evals, waits) == (5, 2)
    finally:
        _stop(primary, replica)
