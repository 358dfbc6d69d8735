"""gRPC streams and connections are bounded (docs/reliability.md, "Control streams that never read"):

- a raw HTTP/2 client (another process, tests/service/h2_attacks.py) with 10 connections x 10 Control streams
  that keep sending acts and never read an answer grows `gmt serve`'s RSS by less than 200 MB, the memory
  returns after it closes, and a fresh client is answered meanwhile (before the fix: +1 GB in about 3 s);
- the HTTP/2 settings the server announces are the configured ones (window, streams per connection), so the
  grpcio option names are the ones gRPC reads (it ignores unknown ones silently);
- a message larger than the window still arrives;
- a Control stream whose client takes no answer for GMT_GRPC_WRITE_TIMEOUT_S ends with RESOURCE_EXHAUSTED;
- one call past GMT_GRPC_MAX_CONCURRENT_RPCS answers RESOURCE_EXHAUSTED at once;
- a connection past GMT_GRPC_MAX_CONNECTIONS is closed at once, one that never completes its HTTP/2 handshake
  after GMT_GRPC_HANDSHAKE_TIMEOUT_S.

Every wait polls a condition with a deadline; nothing sleeps to synchronise.
"""

from __future__ import annotations

import asyncio
import json
import queue
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import grpc
import httpx
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from prometheus_client.parser import text_string_to_metric_families
from service_harness import OBS_DIM, ServeProcess

from gmt.bench.harness import rss_bytes
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

ATTACKS = Path(__file__).with_name("h2_attacks.py")
MB = 1 << 20
CONNECTIONS, STREAMS = 10, 10
FLOOD_S = 10  # the attack's length here (31 s in the report that found it; memory grew linearly)
GROWTH_LIMIT = 200 * MB
RELEASED_WITHIN = 50 * MB  # "released": RSS back within this of the baseline once the attacker is gone
FRESH_S = 5  # a fresh client's calls answer within this, attack under way


def act(sid: str, step: int | None = None) -> pb.ActRequest:
    return pb.ActRequest(session_id=sid, values=pb.FloatVector(values=[0.1] * OBS_DIM), step=step)


class Attack:
    """An attack client of h2_attacks.py in its own process; its JSON lines are collected by a thread."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(ATTACKS), *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self.records: list[dict] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.records.append(json.loads(line))

    def last(self, event: str) -> dict | None:
        return next((r for r in reversed(self.records) if r["event"] == event), None)

    def stop(self, timeout: float = 30) -> dict:
        """Close its stdin (it stops and reports) and return its final record."""
        if self.proc.poll() is None:
            self.proc.stdin.close()
        self.proc.wait(timeout)
        done = self.last("done")
        assert done is not None, f"the attack client reported nothing: {self.records[-3:]}"
        return done

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(30)


def closed_count(http: httpx.Client, transport: str, reason: str) -> float:
    text = http.get("/metrics").text
    return sum(
        s.value
        for family in text_string_to_metric_families(text)
        if family.name == "gmt_connections_closed"
        for s in family.samples
        if s.name.endswith("_total") and s.labels == {"transport": transport, "reason": reason}
    )


def fresh_client_answers(url: str, target: str, sid: str, step: int) -> dict[str, float]:
    """A new REST connection and a new gRPC channel: /healthz, gRPC health, a Control act and a unary act of
    `sid`; returns each call's seconds (each must answer within FRESH_S)."""
    took = {}
    with httpx.Client(base_url=url, timeout=FRESH_S) as http, grpc.insecure_channel(target) as channel:
        t = time.monotonic()
        assert http.get("/healthz").status_code == 200
        took["rest"] = time.monotonic() - t
        t = time.monotonic()
        health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=FRESH_S)
        assert health.status == health_pb2.HealthCheckResponse.SERVING
        took["grpc_health"] = time.monotonic() - t
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        t = time.monotonic()
        answers = list(stub.Control(iter([pb.ControlRequest(act=act(sid, step))]), timeout=FRESH_S))
        assert [a.act.step for a in answers] == [step], answers
        took["control"] = time.monotonic() - t
        t = time.monotonic()
        assert stub.Act(act(sid, step + 1), timeout=FRESH_S).step == step + 1
        took["act"] = time.monotonic() - t
    return took


def test_never_reading_control_streams_keep_memory_bounded(ckpt_root):
    server = ServeProcess("--checkpoints", str(ckpt_root / "tiny-gmt"))
    attack = None
    try:
        info = server.wait_serving()
        pid, target = server.proc.pid, f"127.0.0.1:{info['grpc_port']}"
        with httpx.Client(base_url=server.url, timeout=30) as http, grpc.insecure_channel(target) as channel:
            stub = policy_pb2_grpc.PolicyServiceStub(channel)
            sids = [
                http.post("/sessions", json={"goal": 1}).json()["session_id"]
                for _ in range(CONNECTIONS * STREAMS)
            ]
            fresh = http.post("/sessions", json={"goal": 1}).json()["session_id"]
            for sid in sids:  # each session's history exists before the baseline
                stub.Act(act(sid), timeout=30)
            assert fresh_client_answers(server.url, target, fresh, 0)
            base = rss_bytes(pid)

            attack = Attack(
                "control-flood",
                "--port",
                str(info["grpc_port"]),
                "--connections",
                str(CONNECTIONS),
                "--streams",
                str(STREAMS),
                "--sessions",
                ",".join(sids),
                "--seconds",
                str(FLOOD_S + 30),  # stopped by us; a bound if we die
            )
            t0, peak, took = time.monotonic(), base, None
            while time.monotonic() - t0 < FLOOD_S:
                peak = max(peak, rss_bytes(pid))
                if peak - base > GROWTH_LIMIT:
                    break  # failed: stop before the machine runs out of memory
                progress = attack.last("progress")
                # Once every stream has filled its window (64 KiB), the attack is at full strength.
                if took is None and progress and progress["sent_bytes"] >= CONNECTIONS * STREAMS * 64_000:
                    took = fresh_client_answers(server.url, target, fresh, 1)
                time.sleep(0.1)  # the sampling period of the RSS, not a synchronisation
            done = attack.stop()
            assert peak - base < GROWTH_LIMIT, (
                f"RSS grew {(peak - base) / MB:.0f} MB in {time.monotonic() - t0:.1f} s "
                f"({done['sent_bytes'] / MB:.0f} MB sent by the attacker)"
            )
            assert took is not None, f"the attacker never filled its streams: {attack.records[-2:]}"
            assert max(took.values()) < FRESH_S, took
            # Every stream was open and sending: the client filled each one's window. The server announced the
            # configured window (no BDP growth) and streams per connection, and granted about that much.
            assert done["sent_bytes"] >= CONNECTIONS * STREAMS * 64_000, done
            assert done["settings"]["4"] == 64 * 1024 and done["settings"]["3"] == 1024, done
            assert done["sent_bytes"] < 64 * MB, done

            deadline, rss = time.monotonic() + 15, rss_bytes(pid)
            while rss - base > RELEASED_WITHIN and time.monotonic() < deadline:
                time.sleep(0.2)
                rss = rss_bytes(pid)
            assert rss - base <= RELEASED_WITHIN, (
                f"after the attack RSS stayed {(rss - base) / MB:.0f} MB above the baseline "
                f"(peak +{(peak - base) / MB:.0f} MB)"
            )
            print(
                f"\nRSS baseline {base / MB:.0f} MB, peak +{(peak - base) / MB:.0f} MB, after close "
                f"+{(rss - base) / MB:.0f} MB; attacker sent {done['sent_bytes'] / MB:.1f} MB; fresh client "
                + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in took.items())
            )
            assert fresh_client_answers(server.url, target, fresh, 3)
    finally:
        if attack is not None:
            attack.kill()
        server.kill()


def test_settings_reach_http2(make_server):
    """Non-default values travel to the HTTP/2 SETTINGS frame and bound what a never-reading client sends."""
    s = make_server(grpc_window_bytes=16 * 1024, grpc_max_streams_per_connection=7)
    sid = httpx.post(f"{s.url}/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
    attack = Attack(
        "control-flood",
        "--port",
        str(s.server.grpc_port),
        "--connections",
        "1",
        "--streams",
        "3",
        "--sessions",
        sid,
        "--seconds",
        "5",  # the bytes are bounded by flow control, not by time; the time only has to cover a slow start
    )
    try:
        attack.proc.wait(60)
        done = attack.stop()
    finally:
        attack.kill()
    assert done["settings"]["4"] == 16 * 1024 and done["settings"]["3"] == 7, done
    # Three windows of unread commands, plus the commands the server read and answered until the client's own
    # 64 KiB window for answers filled (150 KB here; with BDP probing on it would be gigabytes).
    assert 3 * 16 * 1024 <= done["sent_bytes"] < 1 * MB, done


def test_a_message_larger_than_the_window_still_arrives(make_server):
    s = make_server(grpc_window_bytes=16 * 1024)
    big = pb.Observation(tensor=pb.Tensor(data=bytes(600_000), shape=[600_000], dtype="uint8"))
    with grpc.insecure_channel(s.target) as channel:
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        sid = stub.CreateSession(
            pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=0)), timeout=10
        ).session_id
        with pytest.raises(grpc.RpcError) as e:
            stub.Act(pb.ActRequest(session_id=sid, tensor=big.tensor), timeout=10)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, e.value.details()
        assert "shape" in e.value.details()
        control = [
            pb.ControlRequest(act=pb.ActRequest(session_id=sid, tensor=big.tensor)),
            pb.ControlRequest(act=act(sid, 0)),
        ]
        answers = list(stub.Control(iter(control), timeout=10))
        assert answers[0].error.code == "invalid_argument" and answers[1].act.step == 0, answers


def test_a_stream_whose_client_takes_no_answer_ends_resource_exhausted(make_server):
    s = make_server(grpc_write_timeout_s=1.0)
    requests: queue.SimpleQueue = queue.SimpleQueue()
    # bdp_probe off on the client too: with it, grpcio's client takes megabytes of answers its caller never read.
    with (
        httpx.Client(base_url=s.url, timeout=10) as http,
        grpc.insecure_channel(s.target, options=[("grpc.http2.bdp_probe", 0)]) as channel,
    ):
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        sid = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
        call = stub.Control(iter(requests.get, None))
        for _ in range(3000):  # about 1,000 answers fill the client's 64 KiB window
            requests.put(pb.ControlRequest(act=act(sid)))
        deadline = time.monotonic() + 30
        while closed_count(http, "grpc", "write_timeout") < 1:
            assert time.monotonic() < deadline, "the stream was not ended"
            time.sleep(0.05)
        answers = []
        with pytest.raises(grpc.RpcError) as e:
            for answer in call:
                answers.append(answer)
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, e.value.details()
        assert "took no answer" in e.value.details()
        assert 500 < len(answers) < 3000
        assert [a.act.step for a in answers] == list(range(len(answers)))
        requests.put(None)
        # Every applied act was answered (the answer whose write timed out included); the commands the server
        # had not read were dropped, and the session goes on from there.
        step = http.get(f"/sessions/{sid}").json()["step"]
        assert step == len(answers)
        again = list(stub.Control(iter([pb.ControlRequest(act=act(sid, step))]), timeout=10))
        assert again[0].act.step == step, again


def test_a_call_past_max_concurrent_rpcs_is_refused_at_once(make_server):
    s = make_server(grpc_max_concurrent_rpcs=2)
    with grpc.insecure_channel(s.target) as channel:
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        held = [stub.Control(iter(queue.SimpleQueue().get, None)) for _ in range(2)]
        for call in held:
            assert dict(call.initial_metadata())["x-served-by"]  # its handler runs
        t = time.monotonic()
        with pytest.raises(grpc.RpcError) as e:
            stub.ListModels(pb.ListModelsRequest(), timeout=10)
        # Refused, not queued: a queued call would end DEADLINE_EXCEEDED at its 10 s timeout.
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, e.value.details()
        assert time.monotonic() - t < 8
        held[0].cancel()
        deadline = time.monotonic() + 10
        while True:
            try:
                assert stub.ListModels(pb.ListModelsRequest(), timeout=10).models
                break
            except grpc.RpcError as err:
                assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and time.monotonic() < deadline
        held[1].cancel()


def closed_by_server(sock: socket.socket, timeout: float) -> float | None:
    """When (time.monotonic()) the server closes `sock` (after its HTTP/2 SETTINGS, if any); None if it is still
    open after `timeout`."""
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        sock.settimeout(left)
        try:
            if not sock.recv(1024):
                return time.monotonic()
        except TimeoutError:
            return None
        except ConnectionResetError:
            return time.monotonic()
    return None


def still_open(sock: socket.socket) -> bool:
    """Whether the server has not closed `sock` (what it sent so far, e.g. its HTTP/2 SETTINGS, is read)."""
    sock.setblocking(False)
    try:
        while True:
            if not sock.recv(65536):
                return False
    except BlockingIOError:
        return True
    except ConnectionResetError:
        return False
    finally:
        sock.setblocking(True)


def test_grpc_connection_cap_and_handshake_timeout(make_server):
    s = make_server(grpc_max_connections=3, grpc_handshake_timeout_s=4.0)
    port = s.server.grpc_port
    opened = time.monotonic()
    held = [socket.create_connection(("127.0.0.1", port)) for _ in range(3)]  # no HTTP/2 preface
    extra = socket.create_connection(("127.0.0.1", port))
    try:
        # Past the cap: closed at once, while the three held connections are still open (their handshake
        # timeout has not run out). Asserted by order, not by a short time bound.
        assert closed_by_server(extra, 30) is not None
        for sock in held:
            assert still_open(sock)
        for sock in held:  # the handshake timeout closes the others, after about four seconds
            when = closed_by_server(sock, 60)
            assert when is not None and 3.2 < when - opened < 60, when and when - opened
        with grpc.insecure_channel(s.target) as channel:
            health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=10)
            assert health.status == health_pb2.HealthCheckResponse.SERVING
    finally:
        for sock in [*held, extra]:
            sock.close()


class _NeverWritten:
    """A Control call's context whose client takes no answer: every write waits for ever."""

    def __init__(self) -> None:
        self.aborted: tuple | None = None
        self.writes = 0

    def time_remaining(self) -> None:
        return None

    async def write(self, _answer) -> None:
        self.writes += 1
        await asyncio.Event().wait()

    async def abort(self, code, details: str) -> None:
        self.aborted = (code, details)
        raise grpc.aio.AbortError()


def test_a_stream_ends_when_its_last_answer_is_never_taken(make_server):
    """The answer is written while the next command is awaited: when the client sends nothing more and never takes
    that answer, the stream still ends after --grpc-write-timeout-s (it does not wait for a next command)."""
    s = make_server(grpc_write_timeout_s=0.3)
    with httpx.Client(base_url=s.url, timeout=10) as http:
        sid = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
        step_before = http.get(f"/sessions/{sid}").json()["step"]
    context = _NeverWritten()

    async def one_command_then_silence():
        yield pb.ControlRequest(act=act(sid))
        await asyncio.Event().wait()  # the client keeps the stream open and sends nothing more

    async def control():
        with pytest.raises(grpc.aio.AbortError):
            async with asyncio.timeout(
                20
            ):  # not a timing assertion: without the wake-up it would wait for ever
                await s.server._grpc.servicer._control(one_command_then_silence(), context)

    s.run(control())
    assert context.writes == 1
    assert context.aborted is not None and context.aborted[0] == grpc.StatusCode.RESOURCE_EXHAUSTED
    with httpx.Client(base_url=s.url, timeout=10) as http:
        assert http.get(f"/sessions/{sid}").json()["step"] == step_before + 1  # the act was applied once
