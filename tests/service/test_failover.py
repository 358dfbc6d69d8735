"""The Redis primary killed (SIGKILL) under load, for real: `gmt cluster up` (a primary, two replicas, three
sentinels, two gmt replicas with --store-min-replicas 1, nginx), sessions acting over REST, gRPC unary and gRPC
Control streams, each act naming its step. A sentinel promotes a replica; acts resume within 5 s; meanwhile the
clients see only `unavailable` answers (retried with the same step); afterwards every session's actions equal
those of an uninterrupted twin (no acknowledged step lost or applied twice) and no session is lost."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from service_harness import CLUSTER_ENV, clean_env

from gmt.bench import failover
from gmt.client.grpc import GrpcClient
from gmt.client.rest import RestClient
from gmt.cluster import supervisor as cluster
from gmt.model.fixtures import tiny_checkpoint

MODEL = "tiny-cheetah"
GOALS = 3
RESUME_WITHIN_S = 5.0
# What a client may see while the store has no primary: the store's `unavailable`, over each way to act.
RETRIED = {"rest 503 unavailable", "grpc UNAVAILABLE", "stream unavailable (in-band)"}


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    root = tmp_path_factory.mktemp("checkpoints")
    tiny_checkpoint(root / MODEL, name=MODEL, attention="window", calibrated=True)  # sampled: seeds matter
    return root


@pytest.fixture
def running(ckpt, tmp_path):
    if cluster.find_executable("nginx") is None or cluster.find_executable("redis-server") is None:
        pytest.skip(f"nginx and redis-server are needed ({cluster.INSTALL_HINT})")
    env = clean_env(**CLUSTER_ENV)
    c = cluster.up(tmp_path / "cluster", rest_port=0, grpc_port=0, checkpoints=[ckpt], env=env, timeout_s=90)
    yield c
    cluster.down(c.run_dir, timeout_s=10, quiet=True)


def _client_episode(client, seed: int, obs: np.ndarray, stop: threading.Event, out: dict) -> None:
    """A session of the shipped Python client (it retries `unavailable` with the step), acting until `stop`."""
    try:
        with client.create_session(MODEL, 1, seed=seed) as s:
            out["episode"] = failover.Episode("client", s.id, 1, seed, obs)
            for o in obs:
                if stop.is_set():
                    break
                sent = time.monotonic()
                out["episode"].actions.append(np.asarray(s.act(o).action))
                out["episode"].sent.append(sent)
                out["episode"].answered.append(time.monotonic())
                stop.wait(0.05)  # pacing only
    except BaseException as e:  # noqa: BLE001 - reported by the test
        out["error"] = e


def test_primary_killed_under_load_no_acknowledged_step_is_lost(running, ckpt):
    rng = np.random.default_rng(3)
    kw = dict(timeout_s=30, retries=10, backoff_s=0.05)  # retries cover ~50 s of outage
    clients = [RestClient(running.rest_url, **kw), GrpcClient(running.grpc_target, stream=True, **kw)]
    stop, outs, threads = threading.Event(), [], []
    for i, client in enumerate(clients):
        outs.append({})
        obs = rng.normal(size=(400, 17)).astype(np.float32)
        args = (client, 100 + i, obs, stop, outs[-1])
        threads.append(threading.Thread(target=_client_episode, args=args, name=f"client-{i}"))
    # Sessions that act before the failover and then wait: they must still be there, where they were.
    idle = []
    with RestClient(running.rest_url) as rest:
        for seed in range(3):
            s = rest.create_session(MODEL, seed % GOALS, seed=seed)
            for o in rng.normal(size=(seed + 1, 17)).astype(np.float32):
                s.act(o)
            idle.append((s.id, seed + 1))
    primary_pid = running.pids["redis"]
    try:
        for t in threads:
            t.start()
        d = failover.run_drill(
            running, MODEL, sessions=12, obs_dim=17, goals=GOALS, pace_s=0.05, steps_before=5, steps_after=5
        )
        # The clients back off exponentially: let each act twice more after the kill (or fail).
        deadline = time.monotonic() + 30
        while not all("error" in o or o["episode"].answered_after(d.killed_at) >= 2 for o in outs):
            assert time.monotonic() < deadline, "a Python client did not act after the failover"
            time.sleep(0.05)
    finally:
        stop.set()
        for t in threads:
            t.join(60)
        for c in clients:
            c.close()

    summary = d.summary()
    assert d.killed == "redis" and not cluster._alive(primary_pid)
    assert d.promoted in ("redis-replica", "redis-replica-2"), summary
    assert not summary["failed_sessions"] and not d.lost, summary
    # The outage was seen, only as the store's `unavailable` (retried with the step), and acts resumed in time.
    assert sum(d.errors.values()) > 0 and set(d.errors) <= RETRIED, summary
    assert all("session store" in m for shapes in d.examples.values() for m in shapes), d.examples
    assert d.resume_s <= RESUME_WITHIN_S, summary
    assert sorted(e.kind for e in d.episodes) == sorted(failover.KINDS * 4)
    assert all(len(e.actions) >= 5 and e.answered_after(d.killed_at) >= 5 for e in d.episodes)

    # The shipped clients rode through it too, acting before and after the kill.
    assert not [o["error"] for o in outs if "error" in o], outs
    client_episodes = [o["episode"] for o in outs]
    for e in client_episodes:
        assert e.answered_after(d.killed_at) >= 2 and len(e.actions) > e.answered_after(d.killed_at), e.kind

    # Every action equals an uninterrupted twin's: nothing acknowledged was lost, nothing applied twice.
    episodes = d.episodes + client_episodes
    twins = failover.twin_actions(ckpt / MODEL, episodes)
    for e, want in zip(episodes, twins, strict=True):
        for t, (got, w) in enumerate(zip(e.actions, want, strict=True)):
            np.testing.assert_array_equal(got, w, err_msg=f"{e.kind} session {e.session_id} step {t}")
    assert len({tuple(e.actions[0]) for e in d.episodes}) == len(d.episodes)  # sampled: the seeds mattered

    with RestClient(running.rest_url) as rest:
        for sid, steps in idle:
            assert rest.get_session(sid).step == steps
