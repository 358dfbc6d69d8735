"""SIGTERM to a real `gmt serve` while requests are in flight (REST acts, a gRPC act, a Control stream command,
an idle Control stream), docs/reliability.md "SIGTERM with requests in flight":

- readiness turns 503 at once; a new call answers `unavailable` (503 / UNAVAILABLE) or finds the port closed;
- every call in flight is answered in full (its act is applied and its answer arrives after the signal);
- Control streams end with UNAVAILABLE ("server is shutting down": reopen the stream elsewhere), an idle one at
  once, a busy one right after the answer of its command;
- the process exits 0, well within its grace period.

The acts are held in flight by the batcher: a session that acted a moment before still counts as acting, so the
batcher keeps each batch open for it for GMT_BATCH_WAIT_MS. The test waits for the server's `gmt_requests_in_flight` gauge to count them all before it
sends the signal, and for answers and statuses afterwards; it never sleeps to synchronise.
"""

from __future__ import annotations

import queue
import signal
import threading
import time

import grpc
import httpx
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families
from service_harness import OBS_DIM, ServeProcess

from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

N_REST = 6
BATCH_WAIT_MS = 4000  # how long the in-flight acts wait in the batcher: the window for the signal
GRACE_S = 15


def in_flight(http: httpx.Client) -> dict[str, float]:
    text = http.get("/metrics").text
    return {
        s.labels["transport"]: s.value
        for family in text_string_to_metric_families(text)
        if family.name == "gmt_requests_in_flight"
        for s in family.samples
    }


def queued(http: httpx.Client) -> float:
    """Acts waiting in the micro-batchers (past every check, held only by the batch wait)."""
    text = http.get("/metrics").text
    return sum(
        s.value
        for family in text_string_to_metric_families(text)
        if family.name == "gmt_batch_queued"
        for s in family.samples
    )


def hold_batches(http: httpx.Client, sid: str) -> None:
    """Make `sid` act once, then never again: for twice GMT_BATCH_WAIT_MS it counts as acting, so the batcher keeps
    the next batches open for GMT_BATCH_WAIT_MS waiting for it."""
    r = http.post(f"/sessions/{sid}/act", json={"observation": [0.0] * OBS_DIM, "step": 0})
    assert r.status_code == 200, r.text


def wait_until(condition, timeout_s: float, what: str):
    """Poll `condition()` (each call is a round trip to the server) until it returns a truthy value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
    pytest.fail(f"timed out waiting for {what}")


class Stream:
    """A Control stream fed from a queue; answers and the final status are recorded with their arrival time."""

    def __init__(self, stub, sid: str) -> None:
        self.requests: queue.SimpleQueue = queue.SimpleQueue()
        self.call = stub.Control(iter(self.requests.get, None), metadata=(("x-session-id", sid),))
        self.answers: list[tuple[float, pb.ControlResponse]] = []
        self.status: tuple[float, grpc.StatusCode, str] | None = None
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        try:
            for answer in self.call:
                self.answers.append((time.monotonic(), answer))
            self.status = (time.monotonic(), grpc.StatusCode.OK, "")
        except grpc.RpcError as e:
            self.status = (time.monotonic(), e.code(), e.details() or "")

    def close(self) -> None:
        self.requests.put(None)
        self.call.cancel()


def test_sigterm_answers_requests_in_flight_and_exits_0(ckpt_root):
    proc = ServeProcess(
        "--checkpoints",
        str(ckpt_root / "tiny-gmt"),
        env={"GMT_BATCH_WAIT_MS": str(BATCH_WAIT_MS), "GMT_SHUTDOWN_GRACE_S": str(GRACE_S)},
    )
    streams: list[Stream] = []
    try:
        info = proc.wait_serving()
        target = f"127.0.0.1:{info['grpc_port']}"
        obs = np.random.default_rng(3).normal(size=(N_REST + 2, OBS_DIM)).astype(np.float32)
        with (
            httpx.Client(base_url=proc.url, timeout=60) as http,
            grpc.insecure_channel(target) as channel,
        ):
            stub = policy_pb2_grpc.PolicyServiceStub(channel)
            sids = [
                http.post("/sessions", json={"goal": 1, "seed": i}).json()["session_id"]
                for i in range(N_REST + 4)
            ]
            rest_sids, unary_sid, busy_sid, idle_sid = sids[:N_REST], *sids[N_REST : N_REST + 3]
            hold_batches(http, sids[-1])

            idle = Stream(stub, idle_sid)  # open, waiting for its first command
            streams.append(idle)
            assert dict(idle.call.initial_metadata())["x-served-by"]  # the server runs its handler

            answers: dict[str, tuple[float, object]] = {}

            def rest_act(i: int) -> None:
                with httpx.Client(base_url=proc.url, timeout=60) as own:  # a connection of its own
                    r = own.post(
                        f"/sessions/{rest_sids[i]}/act", json={"observation": obs[i].tolist(), "step": 0}
                    )
                answers[rest_sids[i]] = (time.monotonic(), r)

            def grpc_act() -> None:
                req = pb.ActRequest(session_id=unary_sid, values=pb.FloatVector(values=obs[N_REST]), step=0)
                try:
                    a = stub.Act(req, timeout=60)
                except grpc.RpcError as e:
                    a = e
                answers[unary_sid] = (time.monotonic(), a)

            threads = [threading.Thread(target=rest_act, args=(i,)) for i in range(N_REST)]
            threads.append(threading.Thread(target=grpc_act))
            for t in threads:
                t.start()
            busy = Stream(stub, busy_sid)
            streams.append(busy)
            busy.requests.put(
                pb.ControlRequest(
                    act=pb.ActRequest(session_id=busy_sid, values=pb.FloatVector(values=obs[N_REST + 1]))
                )
            )
            # Every act is in the server, unanswered: N_REST over REST, the unary act and the stream's command,
            # all past the server's checks and waiting in the batcher (in flight alone could be before them).
            wait_until(
                lambda: in_flight(http) == {"rest": N_REST, "grpc": 2} and queued(http) == N_REST + 2,
                BATCH_WAIT_MS / 1000,
                "acts queued",
            )
            signalled = time.monotonic()
            proc.proc.send_signal(signal.SIGTERM)

            # Shutting down: not ready, and new calls are refused (or the port is already closed).
            def not_ready():
                try:
                    return http.get("/readyz").status_code == 503
                except httpx.TransportError:
                    return True

            wait_until(not_ready, 10, "readiness to turn 503")
            try:
                with httpx.Client(base_url=proc.url, timeout=10) as fresh:
                    r = fresh.post(f"/sessions/{sids[-1]}/act", json={"observation": obs[0].tolist()})
                assert r.status_code == 503 and r.json()["error"]["code"] == "unavailable", r.text
            except httpx.TransportError:
                pass  # the listener is closed
            with pytest.raises(grpc.RpcError) as e:
                stub.GetSession(pb.GetSessionRequest(session_id=sids[-1]), timeout=10)
            assert e.value.code() == grpc.StatusCode.UNAVAILABLE

            for t in threads:
                t.join(GRACE_S + 30)
            busy.thread.join(GRACE_S + 30)
            idle.thread.join(GRACE_S + 30)

        # Every call in flight was answered in full, after the signal.
        for sid in rest_sids:
            at, r = answers[sid]
            assert r.status_code == 200, r.text
            assert r.json()["step"] == 0 and len(r.json()["action"]) == 6 and at > signalled
        at, a = answers[unary_sid]
        assert isinstance(a, pb.ActResponse) and a.step == 0 and at > signalled, a
        ((at, answer),) = busy.answers
        assert answer.WhichOneof("result") == "act" and answer.act.step == 0 and at > signalled, answer
        # Then the streams ended UNAVAILABLE, the idle one before any act was answered.
        acts_answered = min(t for t, _ in answers.values())
        for stream in (busy, idle):
            assert stream.status is not None and stream.status[1] == grpc.StatusCode.UNAVAILABLE, (
                stream.status
            )
            assert "server is shutting down" in stream.status[2]
        assert idle.answers == [] and signalled < idle.status[0] < acts_answered

        # The process exits 0, well within its grace period.
        assert proc.proc.wait(GRACE_S + 30) == 0
        messages = proc.messages()
        assert "shutting down" in messages and messages[-1] == "stopped", messages[-5:]
        assert not [m for m in proc.lines if m.get("level") in ("ERROR", "CRITICAL")], proc.lines
    finally:
        for s in streams:
            s.close()
        proc.kill()


def test_calls_still_running_when_the_grace_period_ends_answer_unavailable(ckpt_root):
    """An act held longer than the grace period (here by a 20 s batch wait against 1 s of grace) is cut off: REST
    answers 503 unavailable from the replica (uvicorn alone would answer 500), gRPC answers UNAVAILABLE; the
    process still exits 0, soon after the grace period."""
    proc = ServeProcess(
        "--checkpoints",
        str(ckpt_root / "tiny-gmt"),
        env={"GMT_BATCH_WAIT_MS": "20000", "GMT_SHUTDOWN_GRACE_S": "1"},
    )
    try:
        info = proc.wait_serving()
        with (
            httpx.Client(base_url=proc.url, timeout=60) as http,
            grpc.insecure_channel(f"127.0.0.1:{info['grpc_port']}") as channel,
        ):
            stub = policy_pb2_grpc.PolicyServiceStub(channel)
            sids = [http.post("/sessions", json={"goal": 0}).json()["session_id"] for _ in range(3)]
            hold_batches(http, sids[2])
            out: dict[str, object] = {}

            def rest_act() -> None:
                with httpx.Client(base_url=proc.url, timeout=60) as own:
                    out["rest"] = own.post(f"/sessions/{sids[0]}/act", json={"observation": [0.0] * OBS_DIM})

            def grpc_act() -> None:
                try:
                    out["grpc"] = stub.Act(
                        pb.ActRequest(session_id=sids[1], values=pb.FloatVector(values=[0.0] * OBS_DIM)),
                        timeout=60,
                    )
                except grpc.RpcError as e:
                    out["grpc"] = e

            threads = [threading.Thread(target=rest_act), threading.Thread(target=grpc_act)]
            for t in threads:
                t.start()
            wait_until(lambda: queued(http) == 2, 20, "acts queued in the batcher")
            proc.proc.send_signal(signal.SIGTERM)
            for t in threads:
                t.join(60)
        r = out["rest"]
        assert r.status_code == 503 and r.headers["x-served-by"], r.text
        assert r.json()["error"] == {
            "code": "unavailable",
            "message": "server shut down before this request was answered; retry it",
        }
        assert r.headers["x-session-id"] == sids[0]
        assert isinstance(out["grpc"], grpc.RpcError) and out["grpc"].code() == grpc.StatusCode.UNAVAILABLE
        assert proc.proc.wait(30) == 0
        assert "Exception in ASGI application\n" not in proc.messages()
    finally:
        proc.kill()
