"""Recorded sessions survive a replica's kill -9 (the topology of tests/cluster/test_cluster.py, with
--record-dir shared by both replicas): a REST session and a gRPC Control-stream session, each with a goal change made
by a curl-style call, are recording when the replica serving them is killed with an act of each in flight; the
clients retry on the other replica, and each recording holds every answered step exactly once (the retried step
too), with the answered actions, the goals, the reports, and the timeline with its effective steps."""

from __future__ import annotations

import os
import signal
import threading

import grpc
import httpx
import numpy as np
import pytest
from test_cluster import MODEL, grpc_replica, held_by_victim, pad, rest_replica, start_cluster

from gmt.client.grpc import GrpcClient
from gmt.client.rest import RestClient
from gmt.cluster import supervisor as cluster
from gmt.common.recording import read_recording
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

STEPS, CHANGE_AT, KILL_AT = 10, 3, 6
BATCH_WAIT_MS = 400  # an act waits this long for a session still acting: the kill window


@pytest.fixture(scope="module")
def recording_cluster(tmp_path_factory):
    record_dir = tmp_path_factory.mktemp("recordings")
    c = start_cluster(tmp_path_factory, ("--record-dir", str(record_dir)))
    yield c, record_dir
    cluster.down(c.run_dir, timeout_s=10, quiet=True)


def _report(t: int) -> dict:
    """What the client reports with the act of step t: the outcome of action t - 1 (none at step 0)."""
    return {"reward": float(t), "info": {"x_velocity": -t}} if t else {}


def _episode(session, obs, start, barrier, out, errors) -> None:
    """Act from step `start` to the end; wait at the barrier before the act of KILL_AT."""
    try:
        for t in range(start, len(obs)):
            if t == KILL_AT:
                barrier.wait(30)
            out.append(session.act(obs[t], **_report(t)))
    except BaseException as e:  # noqa: BLE001 - reported by the test
        errors.append(e)


def test_replica_killed_mid_episode_the_recordings_hold_every_answered_step_once(recording_cluster):
    running, record_dir = recording_cluster
    victim, survivor = "gmt-1", "gmt-2"
    rng = np.random.default_rng(39)
    obs = {
        "rest": rng.normal(size=(STEPS, 17)).astype(np.float32),
        "grpc": rng.normal(size=(STEPS, 17)).astype(np.float32),
    }
    kw = dict(timeout_s=30, retries=4, backoff_s=0.1)
    with (
        RestClient(running.rest_url, **kw) as rest,
        GrpcClient(running.grpc_target, stream=True, **kw) as stream_client,
        httpx.Client(base_url=running.rest_url, timeout=30) as http,
        grpc.insecure_channel(running.grpc_target) as channel,
    ):
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        sessions, padding = {}, None
        for i in range(
            40
        ):  # recorded sessions routed to the victim, and a padding one that holds its batcher (`pad`)
            if len(sessions) == 2 and padding is not None:
                break
            kind = "rest" if "rest" not in sessions else "grpc" if "grpc" not in sessions else "padding"
            client = stream_client if kind == "grpc" else rest
            s = client.create_session(MODEL, 1, seed=i, record=kind != "padding")
            where = grpc_replica(stub, s.id) if kind == "grpc" else rest_replica(http, s.id)
            if where != victim:
                s.close()
            elif kind == "padding":
                padding = s
            else:
                assert s.info.recording
                sessions[kind] = s
        assert len(sessions) == 2 and padding is not None, "no session was routed to the victim"

        # Steps 0..CHANGE_AT-1, then a goal change by a curl-style call (REST: PUT; gRPC: a unary SetGoal).
        got = {k: [] for k in sessions}
        for kind, s in sessions.items():
            for t in range(CHANGE_AT):
                got[kind].append(s.act(obs[kind][t], **_report(t)))
        r = http.put(f"/sessions/{sessions['rest'].id}/goal", json={"goal": 2})
        assert r.status_code == 200 and r.json()["effective_step"] == CHANGE_AT
        changed = stub.SetGoal(
            pb.SetGoalRequest(session_id=sessions["grpc"].id, goal=pb.GoalSelector(name="low")),
            metadata=(("x-session-id", sessions["grpc"].id),),
        )
        assert changed.effective_step == CHANGE_AT

        barrier = threading.Barrier(4)
        errors: list[BaseException] = []
        threads = [
            threading.Thread(target=_episode, args=(s, obs[k], CHANGE_AT, barrier, got[k], errors), name=k)
            for k, s in sessions.items()
        ]
        threads.append(threading.Thread(target=pad, args=(padding, KILL_AT - CHANGE_AT, barrier)))
        for t in threads:
            t.start()
        barrier.wait(30)
        held_by_victim(f"http://127.0.0.1:{running.replica(victim).rest_port}", rest=1, grpc=1)
        victim_pid = running.pids[victim]
        os.kill(victim_pid, signal.SIGKILL)
        for t in threads:
            t.join(60)
        assert not errors, errors
        assert not cluster._alive(victim_pid)

        for kind, s in sessions.items():
            answers = got[kind]
            assert [a.step for a in answers] == list(range(STEPS)), kind
            assert rest_replica(http, s.id) == survivor
            rec = http.get(f"/sessions/{s.id}/recording").json()
            # Every answered step exactly once, in order, with what was answered and reported.
            assert rec["steps"] == STEPS and rec["t"] == list(range(STEPS)), (kind, rec["t"])
            assert rec["actions"] == [a.action.astype(np.float64).tolist() for a in answers], kind
            np.testing.assert_array_equal(np.asarray(rec["observations"], np.float32), obs[kind])
            new_goal = 2 if kind == "rest" else 0
            assert (
                rec["goals"]
                == [a.goal for a in answers]
                == [1] * CHANGE_AT + [new_goal] * (STEPS - CHANGE_AT)
            )
            assert rec["rewards"] == [float(t) for t in range(1, STEPS)] + [None], kind
            assert rec["infos"]["x_velocity"] == [float(-t) for t in range(1, STEPS)] + [None], kind
            timeline = http.get(f"/sessions/{s.id}/timeline").json()
            assert [(e["step"], e["goal"], e["by"]) for e in timeline["goals"]] == [
                (0, 1, "create"),
                (CHANGE_AT, new_goal, "rest" if kind == "rest" else "grpc"),
            ]
            s.close()  # on the survivor: it writes the recording into the shared directory
            written = read_recording(record_dir / f"{s.id}.json")
            assert written.meta["ended_by"] == "close" and written.steps == STEPS
            assert written.arrays["t"].tolist() == list(range(STEPS))
            np.testing.assert_array_equal(written.arrays["actions"], np.stack([a.action for a in answers]))
        padding.close()
