"""An act whose caller gives up mid-forward (gRPC deadline) and is retried at once with the same step never steps
twice: the first act runs to its end holding the session's lock, and the retry gets its stored answer.

The forward pass is slowed down (a sleep in the engine's worker thread, as a long batch under load would take), so
the deadline expires while it runs; other sessions keep `ActBatch` load on the same model meanwhile.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import grpc
import numpy as np
import pytest
from service_harness import RunningServer, make_settings

from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

MODEL = "tiny-sampled"  # sampled actions: a step taken twice shows in every later action
FORWARD_S = 0.01  # how long each forward pass takes here
SESSIONS, STEPS = 10, 30  # 300 deadline-hit retries per store


def _slow_forward(server: RunningServer) -> None:
    engine = server.core.registry.models[MODEL].engine
    act = engine.act

    def slow(*args, **kwargs):
        time.sleep(FORWARD_S)
        return act(*args, **kwargs)

    engine.act = slow


def _load(stub, stop: threading.Event, n: int = 40) -> int:
    """ActBatch over `n` sessions of the same model until `stop`; returns how many batches ran."""
    ids = [stub.CreateSession(pb.CreateSessionRequest(model=MODEL, goal=pb.GoalSelector(id=0))).session_id]
    ids += [
        stub.CreateSession(pb.CreateSessionRequest(model=MODEL, goal=pb.GoalSelector(id=i % 3))).session_id
        for i in range(n - 1)
    ]
    obs = pb.FloatVector(values=np.zeros(17, np.float32))
    batches = 0
    while not stop.is_set():
        stub.ActBatch(pb.ActBatchRequest(requests=[pb.ActRequest(session_id=s, values=obs) for s in ids]))
        batches += 1
    return batches


def _episode(stub, seed: int) -> tuple[int, int, int]:
    """One session acting STEPS times with a deadline that expires mid-forward, each retried at once with its
    step, beside a twin that never retries. Returns (deadline hits, answers unlike the twin's, steps taken)."""

    def create() -> str:
        req = pb.CreateSessionRequest(model=MODEL, goal=pb.GoalSelector(id=seed % 3), seed=seed)
        return stub.CreateSession(req).session_id

    sid, twin = create(), create()
    obs = np.random.default_rng(seed).normal(size=(STEPS, 17)).astype(np.float32)
    hits = unlike = 0
    for t in range(STEPS):
        req = pb.ActRequest(session_id=sid, values=pb.FloatVector(values=obs[t]), step=t)
        try:
            got = stub.Act(req, timeout=FORWARD_S / 5)
        except grpc.RpcError as e:
            assert e.code() == grpc.StatusCode.DEADLINE_EXCEEDED, e.details()
            hits += 1
            got = stub.Act(req, timeout=30)  # the retry, at once, with the same step
        want = stub.Act(
            pb.ActRequest(session_id=twin, values=pb.FloatVector(values=obs[t]), step=t), timeout=30
        )
        unlike += (list(got.action), got.step, got.goal) != (list(want.action), want.step, want.goal)
    return hits, unlike, stub.GetSession(pb.GetSessionRequest(session_id=sid)).step


@pytest.mark.parametrize("store", ["memory", "redis"])
def test_a_retry_after_a_deadline_mid_forward_never_steps_twice(store, ckpt_root, request):
    redis_url = request.getfixturevalue("redis_clean") if store == "redis" else None
    server = RunningServer(make_settings(checkpoints=[ckpt_root], redis_url=redis_url)).start()
    try:
        _slow_forward(server)
        with grpc.insecure_channel(server.target) as ch:
            stub = policy_pb2_grpc.PolicyServiceStub(ch)
            stop = threading.Event()
            with ThreadPoolExecutor(SESSIONS + 1) as pool:
                load = pool.submit(_load, stub, stop)
                results = list(pool.map(lambda s: _episode(stub, s), range(SESSIONS)))
                stop.set()
                assert load.result() > 0
    finally:
        server.stop()
    hits = sum(h for h, _, _ in results)
    assert hits >= 0.9 * SESSIONS * STEPS, (
        f"only {hits} deadlines expired mid-forward: the test lost its edge"
    )
    assert [u for _, u, _ in results] == [0] * SESSIONS  # every answer equals the twin's
    assert [s for _, _, s in results] == [STEPS] * SESSIONS  # no session stepped twice
