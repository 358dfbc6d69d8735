"""The scale-out topology for real (docs/cluster.md): `gmt cluster up` starts a Redis primary, two Redis
replicas and three sentinels, two `gmt serve` replicas and nginx with the shipped cluster/nginx.conf on free
loopback ports. nginx routes each session to one replica, and when that replica is killed (SIGKILL) while a
request is in flight, the clients' retries (with the expected step) continue the episode on the other one with
exactly the actions of an uninterrupted twin. (The Redis primary killed: tests/service/test_failover.py.)"""

from __future__ import annotations

import os
import re
import signal
import threading
import time
from pathlib import Path

import grpc
import httpx
import numpy as np
import orjson
import pytest
from service_harness import CLUSTER_ENV, clean_env

from gmt.client import base
from gmt.client.grpc import GrpcClient
from gmt.client.rest import RestClient
from gmt.cluster import supervisor as cluster
from gmt.model.fixtures import tiny_checkpoint
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

ROOT = Path(__file__).resolve().parents[2]
MODEL = "tiny-cheetah"
BATCH_WAIT_MS = 400  # an act waits this long for a session still acting (`pad`): the kill window
STEPS, KILL_AT = 8, 4

needs_programs = pytest.mark.skipif(
    cluster.find_executable("nginx") is None or cluster.find_executable("redis-server") is None,
    reason=f"nginx and redis-server are needed ({cluster.INSTALL_HINT})",
)


def _loopback_values(run_dir: Path) -> dict[str, str]:
    ports = [cluster.free_port() for _ in range(6)]
    return cluster.nginx_values(
        run_dir, "127.0.0.1", ports[0], ports[1], [tuple(ports[2:4]), tuple(ports[4:])]
    )


@pytest.mark.skipif(
    cluster.find_executable("nginx") is None, reason=f"nginx is needed ({cluster.INSTALL_HINT})"
)
def test_shipped_nginx_conf_passes_nginx_t(tmp_path):
    conf = tmp_path / "nginx" / "nginx.conf"
    conf.parent.mkdir()
    conf.write_text(cluster.render_nginx_conf(_loopback_values(tmp_path)))
    r = cluster.nginx_test(conf)
    assert r.returncode == 0, r.stderr
    assert "test is successful" in r.stderr


def test_the_template_and_compose_agree():
    """docker/compose.yaml fills exactly the placeholders of cluster/nginx.conf, and the native renderer too."""
    text = cluster.NGINX_TEMPLATE.read_text()
    placeholders = set(re.findall(r"\$\{(GMT_[A-Z0-9_]+)\}", text))
    assert set(_loopback_values(Path("/tmp"))) == placeholders
    compose = (ROOT / "docker" / "compose.yaml").read_text()
    nginx_service = compose[compose.index("\n  nginx:") : compose.index("\nvolumes:")]
    assert set(re.findall(r"^\s+(GMT_[A-Z0-9_]+):", nginx_service, flags=re.M)) == placeholders
    assert "GMT_AUTH_TOKEN: ${GMT_AUTH_TOKEN:?" in compose and '"--appendonly", "yes"' in compose
    assert "GMT_REPLICA_ID: gmt-1" in compose and "GMT_REPLICA_ID: gmt-2" in compose
    # The same store as `gmt cluster up`: every Redis server and sentinel of the native topology is a service,
    # the replicas follow the primary, the sentinels watch it with its quorum and timings, and the gmt replicas
    # reach it through all three sentinels, acknowledging a step once a Redis replica holds it.
    services = compose[compose.index("\nservices:") : compose.index("\n  gmt-1:")]
    for name in (*cluster.REDIS_NODES, *cluster.SENTINELS):
        assert f"\n  {name}:" in services, name
    assert services.count('"--replicaof", "redis", "6379"') == len(cluster.REDIS_NODES) - 1
    assert f"sentinel monitor gmt redis 6379 {cluster.SENTINEL_QUORUM}" in compose
    assert f"down-after-milliseconds gmt {cluster.SENTINEL_DOWN_AFTER_MS}" in compose
    assert f"failover-timeout gmt {cluster.SENTINEL_FAILOVER_TIMEOUT_MS}" in compose
    sentinels = ",".join(f"{n}:26379" for n in cluster.SENTINELS)
    assert f"GMT_REDIS_URL: redis+sentinel://{sentinels}/{cluster.SENTINEL_SERVICE}" in compose
    assert 'GMT_STORE_MIN_REPLICAS: "1"' in compose
    assert compose.count("condition: service_healthy") == 9  # replicas, sentinels, gmt, nginx wait for theirs
    with pytest.raises(cluster.ClusterError, match="without a value"):
        cluster.render_nginx_conf({"GMT_REST_1": "x"})


@needs_programs
def test_a_replica_that_cannot_start_fails_up_and_leaves_nothing_running(tmp_path, monkeypatch):
    run_dir = tmp_path / "cluster"
    spawned, spawn = {}, cluster._spawn

    def recorded(name, *args, **kw):
        spawned[name] = spawn(name, *args, **kw)
        return spawned[name]

    monkeypatch.setattr(cluster, "_spawn", recorded)
    with pytest.raises(cluster.ClusterError, match=r"gmt-1 exited while starting(.|\n)*no-such-flag"):
        cluster.up(run_dir, rest_port=0, grpc_port=0, serve_args=["--no-such-flag"], timeout_s=60)
    assert not list(run_dir.glob("*.pid"))
    assert {*cluster.REDIS_NODES, *cluster.SENTINELS, "gmt-1"} <= set(spawned)
    assert not [name for name, pid in spawned.items() if cluster._alive(pid)]  # redis-server renames itself
    if Path("/proc/self").exists():  # redis-server and nginx, started before the replica failed, are gone
        left = [
            p for p in Path("/proc").glob("[0-9]*") if str(run_dir) in (cluster._cmdline(int(p.name)) or "")
        ]
        assert not left


# ----- a running cluster ---------------------------------------------------------------------------------------
def start_cluster(tmp_path_factory, serve_args: tuple[str, ...] = ()):
    """A cluster on free ports serving a tiny MODEL (skips where nginx or redis-server is missing)."""
    if cluster.find_executable("nginx") is None or cluster.find_executable("redis-server") is None:
        pytest.skip(f"nginx and redis-server are needed ({cluster.INSTALL_HINT})")
    root = tmp_path_factory.mktemp("checkpoints")
    tiny_checkpoint(root / MODEL, name=MODEL, attention="window", calibrated=True)
    run_dir = tmp_path_factory.mktemp("run") / "cluster"
    env = clean_env(**CLUSTER_ENV, GMT_BATCH_WAIT_MS=str(BATCH_WAIT_MS))
    return cluster.up(
        run_dir,
        rest_port=0,
        grpc_port=0,
        checkpoints=[root],
        serve_args=list(serve_args),
        env=env,
        timeout_s=90,
    )


@pytest.fixture(scope="module")
def running(tmp_path_factory):
    c = start_cluster(tmp_path_factory)
    yield c
    cluster.down(c.run_dir, timeout_s=10, quiet=True)


def rest_replica(http: httpx.Client, sid: str) -> str:
    return http.get(f"/sessions/{sid}").headers["x-served-by"]


def grpc_replica(stub, sid: str) -> str:
    _, call = stub.GetSession.with_call(
        pb.GetSessionRequest(session_id=sid), metadata=(("x-session-id", sid),)
    )
    return dict(call.initial_metadata())["x-served-by"]


@needs_programs
def test_cluster_is_up_with_one_pid_file_per_process(running):
    assert sorted(p.stem for p in running.run_dir.glob("*.pid")) == [
        "gmt-1",
        "gmt-2",
        "nginx",
        "redis",
        "redis-replica",
        "redis-replica-2",
        "sentinel-1",
        "sentinel-2",
        "sentinel-3",
    ]
    for name, pid in running.pids.items():
        assert int((running.run_dir / f"{name}.pid").read_text()) == pid
        assert cluster._is_ours(name, pid), name
    # The store: both Redis replicas in sync, every sentinel naming the primary (loopback, quorum 2, 1 s), and the
    # gmt replicas reaching it through the sentinels, acknowledging a step once a Redis replica holds it.
    assert running.primary() == "redis"
    primary_port = running.ports["redis"]
    assert all(
        cluster._replica_in_sync("127.0.0.1", running.ports[n], primary_port) for n in cluster.REDIS_NODES[1:]
    )
    for name in cluster.SENTINELS:
        assert cluster._sentinel_ready("127.0.0.1", running.ports[name], primary_port, 2), name
        conf = (running.run_dir / name / "sentinel.conf").read_text()
        assert "bind 127.0.0.1\n" in conf and "down-after-milliseconds gmt 1000" in conf
    sentinels = ",".join(f"127.0.0.1:{running.ports[n]}" for n in cluster.SENTINELS)
    assert running.redis_url == f"redis+sentinel://{sentinels}/gmt"
    for name in cluster.REPLICAS:
        cmd = cluster._cmdline(running.pids[name])
        assert f"--redis-url {running.redis_url}" in cmd and "--store-min-replicas 1" in cmd
    r = httpx.get(f"{running.rest_url}/readyz")
    assert r.status_code == 200 and r.headers["x-served-by"] in ("gmt-1", "gmt-2")
    r = httpx.get(f"{running.rest_url}/no/such/route")
    assert r.status_code == 404 and r.headers["x-served-by"] in ("gmt-1", "gmt-2")
    with pytest.raises(cluster.ClusterError, match="already runs"):
        cluster.up(running.run_dir, rest_port=0, grpc_port=0)


@needs_programs
def test_each_session_sticks_to_one_replica_over_rest_and_grpc(running):
    obs = np.zeros(17, dtype=np.float32).tolist()
    rest_seen, grpc_seen = set(), set()
    with (
        httpx.Client(base_url=running.rest_url, timeout=30) as http,
        grpc.insecure_channel(running.grpc_target) as channel,
    ):
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        for i in range(24):  # until both replicas served sessions over both transports (1 in 2^20 to fail)
            sid = http.post("/sessions", json={"model": MODEL, "goal": 0}).json()["session_id"]
            rest = {rest_replica(http, sid) for _ in range(3)}
            rest.add(http.get("/models", headers={"X-Session-Id": sid}).headers["x-served-by"])
            over_grpc = {grpc_replica(stub, sid) for _ in range(3)}
            if i < 2:  # acts, and a Control stream, go where the reads went
                r = http.post(f"/sessions/{sid}/act", json={"observation": obs, "step": 0})
                assert r.status_code == 200, r.text
                rest.add(r.headers["x-served-by"])
                act = pb.ControlRequest(act=pb.ActRequest(session_id=sid, values=pb.FloatVector(values=obs)))
                stream = stub.Control(iter([act]), metadata=(("x-session-id", sid),))
                assert [a.act.step for a in stream] == [1]
                over_grpc.add(dict(stream.initial_metadata())["x-served-by"])
            assert len(rest) == 1 and len(over_grpc) == 1, (rest, over_grpc)
            rest_seen |= rest
            grpc_seen |= over_grpc
            http.delete(f"/sessions/{sid}")
            if rest_seen == grpc_seen == {"gmt-1", "gmt-2"}:
                break
    assert rest_seen == grpc_seen == {"gmt-1", "gmt-2"}


class Recorder(httpx.HTTPTransport):
    """Records (path, status, X-Served-By) of every answer."""

    def __init__(self) -> None:
        super().__init__()
        self.answers: list[tuple[str, int, str | None]] = []

    def handle_request(self, request):
        r = super().handle_request(request)
        self.answers.append((request.url.path, r.status_code, r.headers.get("x-served-by")))
        return r


def held_by_victim(url: str, rest: int, grpc: int, timeout_s: float = 30.0) -> None:
    """Return once the replica at `url` reports at least `rest` REST and `grpc` gRPC requests in flight."""
    pattern = re.compile(r'^gmt_requests_in_flight\{transport="(rest|grpc)"\} (\S+)$', re.M)
    deadline = time.monotonic() + timeout_s
    with httpx.Client(base_url=url, timeout=5) as c:
        while time.monotonic() < deadline:
            now = {k: float(v) for k, v in pattern.findall(c.get("/metrics").text)}
            if now.get("rest", 0) >= rest and now.get("grpc", 0) >= grpc:
                return
    raise AssertionError(f"the acts never reached {url}: in flight {now}")


def pad(padding, steps: int, barrier: threading.Barrier) -> None:
    """`padding` acts `steps` times beside the episodes, then waits at their barrier and never acts again: it still
    counts as acting on its replica (for a second), so the acts after the barrier wait BATCH_WAIT_MS for it (the
    window in which the test kills the replica)."""
    for _ in range(steps):
        padding.act(np.zeros(17))
    barrier.wait(30)


def _episode(session, obs, barrier, timings, out, errors) -> None:
    try:
        for t, o in enumerate(obs):
            if t == KILL_AT:
                barrier.wait(30)
                t0 = time.monotonic()
            out.append(session.act(o))
            if t == KILL_AT:
                timings.append(time.monotonic() - t0)
    except BaseException as e:  # noqa: BLE001 - reported by the test
        errors.append(e)


@needs_programs
def test_replica_killed_mid_request_the_episode_continues_exactly_on_the_other(running, monkeypatch):
    victim, survivor = "gmt-1", "gmt-2"
    rng = np.random.default_rng(21)
    obs = {"rest": rng.normal(size=(STEPS, 17)), "grpc": rng.normal(size=(STEPS, 17))}
    seeds = {"rest": 5, "grpc": 6}
    recorder = Recorder()
    backoffs: dict[str, list[float]] = {}  # the clients' retry delays, by episode thread
    sleep = time.sleep

    def recorded_sleep(seconds: float) -> None:
        backoffs.setdefault(threading.current_thread().name, []).append(seconds)
        sleep(seconds)

    monkeypatch.setattr(base.time, "sleep", recorded_sleep)  # base.time is the time module
    kw = dict(timeout_s=30, retries=4, backoff_s=0.1)
    with (
        RestClient(running.rest_url, transport=recorder, **kw) as rest,
        GrpcClient(running.grpc_target, stream=True, **kw) as stream_client,
        httpx.Client(base_url=running.rest_url, timeout=30) as http,
        grpc.insecure_channel(running.grpc_target) as channel,
    ):
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        # Uninterrupted twins: the same seeds and observations, before anything is killed.
        want = {}
        for kind, client in (("rest", rest), ("grpc", stream_client)):
            with client.create_session(MODEL, 1, seed=seeds[kind]) as twin:
                want[kind] = [twin.act(o).action for o in obs[kind]]
        # Sessions that nginx routes to the victim (REST by path, gRPC by x-session-id), plus a padding session
        # there that acts beside them and stops right before step KILL_AT (`pad`), so that the batcher holds the
        # in-flight acts waiting for it (a batch waits only for sessions that are acting).
        sessions = {}
        padding = None
        for _ in range(40):
            if len(sessions) == 2 and padding is not None:
                break
            kind = "rest" if "rest" not in sessions else "grpc" if "grpc" not in sessions else "padding"
            client = stream_client if kind == "grpc" else rest
            s = client.create_session(MODEL, 1, seed=seeds.get(kind, 0))
            where = grpc_replica(stub, s.id) if kind == "grpc" else rest_replica(http, s.id)
            if where != victim:
                s.close()
            elif kind == "padding":
                padding = s
            else:
                sessions[kind] = s
        assert len(sessions) == 2 and padding is not None, "no session was routed to the victim"

        barrier = threading.Barrier(4)
        got = {k: [] for k in sessions}
        timings, errors = [], []
        threads = [
            threading.Thread(target=_episode, args=(s, obs[k], barrier, timings, got[k], errors), name=k)
            for k, s in sessions.items()
        ]
        threads.append(threading.Thread(target=pad, args=(padding, KILL_AT, barrier)))
        for t in threads:
            t.start()
        barrier.wait(30)
        t_release = time.monotonic()
        # Kill once both acts of step KILL_AT are in flight on the victim (held in its batcher): its gauge says so.
        held_by_victim(f"http://127.0.0.1:{running.replica(victim).rest_port}", rest=1, grpc=1)
        held_for = time.monotonic() - t_release
        victim_pid = running.pids[victim]
        os.kill(victim_pid, signal.SIGKILL)
        for t in threads:
            t.join(60)
        assert not errors, errors
        assert not cluster._alive(victim_pid)

        for kind in sessions:
            assert [r.step for r in got[kind]] == list(range(STEPS)), kind
            for t, (g, w) in enumerate(zip(got[kind], want[kind], strict=True)):
                np.testing.assert_array_equal(g.action, w, err_msg=f"{kind} step {t}")
        assert min(timings) >= held_for  # each act of step KILL_AT was waiting when the victim died
        assert set(backoffs) == {
            "rest",
            "grpc",
        }  # both clients retried (502; reset stream), a few times at most
        assert all(1 <= len(v) <= 4 for v in backoffs.values()), backoffs
        assert len({tuple(a.action) for a in got["rest"]}) == STEPS  # sampled: the seeds mattered

        # REST: the act in flight came back from nginx as a 502 (the victim died holding it); the client sent
        # it again, with its step, and the survivor answered it and every later one.
        acts = [(status, by) for path, status, by in recorder.answers if path.endswith("/act")]
        rest_acts = acts[-(STEPS + 1) :]
        assert rest_acts[: KILL_AT + 1] == [(200, victim)] * KILL_AT + [(502, "nginx")]
        assert rest_acts[KILL_AT + 1 :] == [(200, survivor)] * (STEPS - KILL_AT)
        # No session lost: both are where their episodes left them, now on the survivor.
        for kind, s in sessions.items():
            assert rest.get_session(s.id).step == STEPS
            where = grpc_replica(stub, s.id) if kind == "grpc" else rest_replica(http, s.id)
            assert where == survivor
            s.close()
        padding.close()


def test_a_large_many_session_call_passes_through_nginx(running):
    """A `POST /act` of 96 sessions (~15 KB, more than nginx keeps in memory by default) and its answer pass
    through nginx, whose workers cannot write temporary files in a private run directory (they answered 500)."""
    with httpx.Client(base_url=running.rest_url, timeout=30) as http:
        sids = [
            http.post("/sessions", json={"model": MODEL, "goal": 0}).json()["session_id"] for _ in range(96)
        ]
        body = {"requests": [{"session_id": s, "observation": [0.1] * 17} for s in sids]}
        assert len(orjson.dumps(body)) > 12_000
        r = http.post("/act", json=body, headers={"X-Session-Id": min(sids)})
        assert r.status_code == 200, r.text[:300]
        assert [x.get("step") for x in r.json()["results"]] == [0] * len(sids)
        for s in sids:
            http.delete(f"/sessions/{s}")


@needs_programs
def test_cluster_down_stops_exactly_its_processes(running):
    pids = dict(running.pids)
    outcome = cluster.down(running.run_dir, timeout_s=10, quiet=True)
    stopped = {name: "stopped" for name in (*cluster.SENTINELS, *cluster.REDIS_NODES, "nginx", "gmt-2")}
    assert outcome == {**stopped, "gmt-1": "not running"}
    assert not list(running.run_dir.glob("*.pid"))
    assert not any(cluster._alive(pid) for pid in pids.values())
    assert (running.run_dir / "redis" / "appendonlydir").is_dir()  # Redis kept an AOF
    assert cluster.down(running.run_dir, quiet=True) == {}


@pytest.mark.parametrize("n", [1, 3])
def test_the_nginx_template_serves_any_number_of_replicas(tmp_path, n):
    """`gmt cluster up --replicas N` renders one upstream server line per replica, for both transports."""
    replicas = [(9000 + i, 9100 + i) for i in range(n)]
    text = cluster.render_nginx_conf(cluster.nginx_values(tmp_path, "127.0.0.1", 8000, 50051, replicas))
    for kind, ports in (("gmt_rest", [r for r, _ in replicas]), ("gmt_grpc", [g for _, g in replicas])):
        block = text[text.index(f"upstream {kind} {{") :]
        block = block[: block.index("}")]
        assert re.findall(r"server 127\.0\.0\.1:(\d+) ", block) == [str(p) for p in ports]
    if cluster.find_executable("nginx") is not None:
        (tmp_path / "nginx.conf").write_text(text)
        (tmp_path / "nginx").mkdir()
        assert cluster.nginx_test(tmp_path / "nginx.conf").returncode == 0
