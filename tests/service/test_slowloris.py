"""Half-open HTTP connections cannot take the server's descriptors (docs/reliability.md, "Slowloris"):

- `gmt serve` under a 1,024 descriptor limit, 1,100 connections from another process each sending a request's
  headers one byte a second: a fresh client's REST request and gRPC calls are answered within 5 s while they are
  open (before the fix: the process ran out of descriptors and neither transport answered), and afterwards the
  server is healthy and its descriptors are back;
- a request's headers (or body) that do not arrive within GMT_HEADER_TIMEOUT_S (GMT_BODY_TIMEOUT_S) answer 408 and
  the connection closes; an idle keep-alive connection is not cut by the header timeout;
- past GMT_REST_MAX_CONNECTIONS a new connection closes the oldest one without a request in progress (half-open
  or idle), never one with a request in progress; when every connection has one, the new connection is closed.

Every wait polls a condition with a deadline; sleeps only let a timeout under test elapse.
"""

from __future__ import annotations

import json
import os
import resource
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
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families
from service_harness import OBS_DIM, ServeProcess

from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

ATTACKS = Path(__file__).with_name("h2_attacks.py")
NOFILE = 1024
HALF_OPEN = 1100
SLOW_BODIES = 460
FRESH_S = 5


def samples(text: str, name: str) -> dict[tuple, float]:
    return {
        tuple(sorted(s.labels.items())): s.value
        for family in text_string_to_metric_families(text)
        if family.name == name
        for s in family.samples
        if not s.name.endswith("_created")
    }


def descriptors(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


class Slowloris:
    """h2_attacks.py slowloris in its own process; its JSON lines are collected by a thread."""

    def __init__(self, port: int, connections: int, seconds: float, body: bool = False) -> None:
        self.proc = subprocess.Popen(
            [
                sys.executable,
                str(ATTACKS),
                "slowloris",
                "--port",
                str(port),
                "--connections",
                str(connections),
                "--interval",
                "1",
                "--seconds",
                str(seconds),
                *(["--body"] if body else []),
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self.records: list[dict] = []
        self.ready = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            rec = json.loads(line)
            self.records.append(rec)
            if rec["event"] == "ready":
                self.ready.set()
        self.ready.set()

    def stop(self) -> dict:
        if self.proc.poll() is None:
            self.proc.stdin.close()
        self.proc.wait(30)
        return next(r for r in reversed(self.records) if r["event"] == "done")

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(30)


def fresh_client(url: str, target: str, sid: str, step: int) -> dict[str, float]:
    """A new REST connection and a new gRPC channel: /healthz, an act, gRPC health and a gRPC act, each within
    FRESH_S; returns their seconds."""
    took = {}
    with httpx.Client(base_url=url, timeout=FRESH_S) as http, grpc.insecure_channel(target) as channel:
        t = time.monotonic()
        assert http.get("/healthz").status_code == 200
        r = http.post(f"/sessions/{sid}/act", json={"observation": [0.1] * OBS_DIM, "step": step})
        assert r.status_code == 200 and r.json()["step"] == step, r.text
        took["rest"] = time.monotonic() - t
        t = time.monotonic()
        health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=FRESH_S)
        assert health.status == health_pb2.HealthCheckResponse.SERVING
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        request = pb.ActRequest(session_id=sid, values=pb.FloatVector(values=[0.1] * OBS_DIM), step=step + 1)
        assert stub.Act(request, timeout=FRESH_S).step == step + 1
        took["grpc"] = time.monotonic() - t
    return took


def test_half_open_connections_under_a_descriptor_limit(ckpt_root):
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < HALF_OPEN + 64:
        pytest.skip(f"the attack client needs {HALF_OPEN + 64} descriptors; the hard limit is {hard}")
    # A header timeout far beyond the test's length: only evictions may make room (on a slow machine the default
    # 10 s could run out for the oldest attacking connections before the metrics are read).
    server = ServeProcess(
        "--checkpoints", str(ckpt_root / "tiny-gmt"), nofile=NOFILE, env={"GMT_HEADER_TIMEOUT_S": "120"}
    )
    attack = None
    try:
        info = server.wait_serving()
        pid, target = server.proc.pid, f"127.0.0.1:{info['grpc_port']}"
        sid = httpx.post(f"{server.url}/sessions", json={"goal": 1}).json()["session_id"]
        fresh_client(server.url, target, sid, 0)
        base_fds = descriptors(pid)

        attack = Slowloris(info["rest_port"], HALF_OPEN, seconds=40)
        assert attack.ready.wait(30), "the attack did not start"
        ready = attack.records[-1]
        assert ready["event"] == "ready" and ready["open"] + ready["refused"] == HALF_OPEN, ready
        t_ready = time.monotonic()
        took = fresh_client(server.url, target, sid, 2)
        within_s = time.monotonic() - t_ready
        # No header timeout (120 s) closed an attacking connection: the cap made room by closing the oldest
        # half-open ones, and kept descriptors for gRPC.
        assert info["descriptors"] == NOFILE
        assert info["rest_max_connections"] + info["grpc_max_connections"] < NOFILE
        metrics = httpx.get(f"{server.url}/metrics", timeout=FRESH_S).text
        closed = samples(metrics, "gmt_connections_closed")
        evicted = closed.get((("reason", "evicted"), ("transport", "rest")), 0)
        assert closed.get((("reason", "header_timeout"), ("transport", "rest")), 0) == 0, closed
        assert evicted >= HALF_OPEN - info["rest_max_connections"], closed
        assert samples(metrics, "gmt_rest_connections")[()] <= info["rest_max_connections"]
        assert descriptors(pid) < NOFILE - 64

        done = attack.stop()
        deadline = time.monotonic() + 15
        while descriptors(pid) > base_fds + 16:
            assert time.monotonic() < deadline, f"{descriptors(pid)} descriptors open, {base_fds} before"
            time.sleep(0.1)
        assert httpx.get(f"{server.url}/readyz", timeout=FRESH_S).status_code == 200
        fresh_client(server.url, target, sid, 4)
        print(
            f"\n{HALF_OPEN} half-open ({ready['refused']} refused at connect), {evicted:.0f} evicted, "
            f"{done['open']} still open when stopped; fresh client "
            + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in took.items())
            + f" ({within_s:.1f} s after the attack was open)"
        )
    finally:
        if attack is not None:
            attack.kill()
        server.kill()


def test_slow_bodies_under_a_descriptor_limit(ckpt_root):
    """Round 3: 460 connections that send whole headers with `Content-Length: 100000` and trickle the body denied
    every fresh REST client (0 of 20) under a 1,024-descriptor limit: a connection reading a body was never
    evictable. Here with no minimum rate and a body deadline beyond the test, so that only evictions make room."""
    server = ServeProcess(
        "--checkpoints",
        str(ckpt_root / "tiny-gmt"),
        nofile=NOFILE,
        env={"GMT_BODY_TIMEOUT_S": "120", "GMT_BODY_MIN_RATE": "0"},
    )
    attack = None
    try:
        info = server.wait_serving()
        target = f"127.0.0.1:{info['grpc_port']}"
        sid = httpx.post(f"{server.url}/sessions", json={"goal": 1}).json()["session_id"]
        attack = Slowloris(info["rest_port"], SLOW_BODIES, seconds=40, body=True)
        assert attack.ready.wait(30), "the attack did not start"
        assert attack.records[-1]["open"] + attack.records[-1]["refused"] == SLOW_BODIES
        for i in range(3):  # before: connection reset, every time
            fresh_client(server.url, target, sid, 2 * i)
        metrics = httpx.get(f"{server.url}/metrics", timeout=FRESH_S).text
        closed = samples(metrics, "gmt_connections_closed")
        assert closed.get((("reason", "evicted"), ("transport", "rest")), 0) >= 1, closed
        assert closed.get((("reason", "body_timeout"), ("transport", "rest")), 0) == 0, closed
        attack.stop()
    finally:
        if attack is not None:
            attack.kill()
        server.kill()


# In-process servers: the deadlines and the cap one by one.


def connect(port: int, data: bytes = b"") -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port))
    if data:
        sock.sendall(data)
    return sock


def read_until_closed(sock: socket.socket, timeout: float) -> tuple[bytes, float | None]:
    """Everything the server sends until it closes `sock`, and when it closed it (None: still open)."""
    deadline, out = time.monotonic() + timeout, b""
    while (left := deadline - time.monotonic()) > 0:
        sock.settimeout(left)
        try:
            data = sock.recv(65536)
        except TimeoutError:
            break
        except ConnectionResetError:
            return out, time.monotonic()
        if not data:
            return out, time.monotonic()
        out += data
    return out, None


def answer(sock: socket.socket, request: bytes) -> bytes:
    """Send a whole request on a keep-alive connection and read its (content-length) answer."""
    sock.sendall(request)
    sock.settimeout(10)
    out = b""
    while b"\r\n\r\n" not in out:
        out += sock.recv(65536)
    head, _, body = out.partition(b"\r\n\r\n")
    length = int(
        next(
            v
            for k, _, v in (h.partition(b":") for h in head.split(b"\r\n"))
            if k.lower() == b"content-length"
        )
    )
    while len(body) < length:
        body += sock.recv(65536)
    return head


HEALTHZ = b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n"
BODY = b'{"model": "tiny-gmt", "goal": 0}'
POST_HEAD = (
    b"POST /sessions HTTP/1.1\r\nHost: t\r\ncontent-type: application/json\r\ncontent-length: %d\r\n\r\n"
    % len(BODY)
)


def wait_for_body_phase(s, count: int) -> None:
    """Until `count` connections of the server have sent their headers and wait in their body."""
    deadline = time.monotonic() + 10
    while sum(c.phase == "body" for c in list(s.server._uvicorn.server_state.connections)) < count:
        assert time.monotonic() < deadline, "the server did not read the request's headers"
        time.sleep(0.01)


def read_answer_head(sock: socket.socket) -> bytes:
    out = b""
    sock.settimeout(10)
    while b"\r\n\r\n" not in out:
        data = sock.recv(65536)
        assert data, out
        out += data
    return out


def closed_count(s, reason: str) -> float:
    text = generate_latest(s.core.metrics.registry).decode()
    return samples(text, "gmt_connections_closed").get((("reason", reason), ("transport", "rest")), 0)


def test_headers_not_received_in_time_answer_408(make_server):
    s = make_server(header_timeout_s=1.0)
    port = s.server.rest_port
    t0 = time.monotonic()
    silent = connect(port)
    partial = connect(port, b"GET /healthz HTTP/1.1\r\nHost: t\r\n")
    for sock in (silent, partial):
        out, when = read_until_closed(sock, 30)
        assert when is not None and 0.9 < when - t0 < 30, (out, when and when - t0)
        assert out.startswith(b"HTTP/1.1 408 "), out
        assert json.loads(out.partition(b"\r\n\r\n")[2])["error"]["code"] == "request_timeout"
        assert b"x-served-by: " in out.lower()
        sock.close()
    assert closed_count(s, "header_timeout") == 2


def test_a_body_not_received_in_time_answers_408(make_server):
    s = make_server(body_timeout_s=1.0)
    t0 = time.monotonic()  # before connecting: the server's clock may start as soon as the bytes arrive
    sock = connect(s.server.rest_port, POST_HEAD + BODY[:1])
    out, when = read_until_closed(sock, 30)
    sock.close()
    assert when is not None and 0.9 < when - t0 < 30
    assert out.startswith(b"HTTP/1.1 408 "), out
    assert closed_count(s, "body_timeout") == 1
    with httpx.Client(base_url=s.url) as http:  # the server goes on
        assert http.get("/healthz").status_code == 200


def test_an_idle_keep_alive_connection_outlives_the_header_timeout(make_server):
    s = make_server(header_timeout_s=0.5, keep_alive_s=30)
    sock = connect(s.server.rest_port)
    try:
        assert answer(sock, HEALTHZ).startswith(b"HTTP/1.1 200")
        time.sleep(1.0)  # twice the header timeout, idle between requests (the behaviour under test)
        assert answer(sock, HEALTHZ).startswith(b"HTTP/1.1 200")
    finally:
        sock.close()
    assert closed_count(s, "header_timeout") == 0


def test_the_cap_closes_the_oldest_connection_without_a_request_in_progress(make_server):
    s = make_server(rest_max_connections=3, header_timeout_s=60, body_timeout_s=60, body_min_rate=0)
    port = s.server.rest_port
    half_open = connect(port, b"GET /healthz HTTP/1.1\r\nHost: t\r\n")
    busy = connect(port, POST_HEAD + BODY[:1])
    wait_for_body_phase(s, 1)
    idle = connect(port)
    assert answer(idle, HEALTHZ).startswith(b"HTTP/1.1 200")  # then idle, keep-alive
    newer = [connect(port)]
    _, when = read_until_closed(half_open, 5)
    assert when is not None, "the oldest half-open connection was not closed"
    newer.append(connect(port))
    _, when = read_until_closed(idle, 5)
    assert when is not None, "the idle keep-alive connection was not closed"
    newer.append(connect(port))
    _, when = read_until_closed(newer[0], 5)
    assert when is not None, "the oldest new connection was not closed"
    assert closed_count(s, "evicted") == 3
    # The connection with a request in progress was never chosen: its request completes.
    busy.sendall(BODY[1:])
    assert read_answer_head(busy).startswith(b"HTTP/1.1 201"), "the busy request was not answered"
    for sock in (half_open, busy, idle, *newer):
        sock.close()


def test_past_the_cap_with_every_request_being_answered_the_new_connection_is_closed(make_server):
    s = make_server(rest_max_connections=1, body_min_rate=0)
    with httpx.Client(base_url=s.url) as http:
        sid = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
    # An event stream: its request is being answered for as long as the session lives.
    events = connect(
        s.server.rest_port, b"GET /sessions/%s/events HTTP/1.1\r\nHost: t\r\n\r\n" % sid.encode()
    )
    assert read_answer_head(events).startswith(b"HTTP/1.1 200")
    extra = connect(s.server.rest_port)
    _, when = read_until_closed(extra, 5)
    extra.close()
    assert when is not None, "the connection past the cap was not closed"
    assert closed_count(s, "over_limit") == 1
    events.close()


def test_a_body_below_the_minimum_rate_answers_408(make_server):
    """A body trickled at 1 byte a second is cut after its first seconds, long before GMT_BODY_TIMEOUT_S."""
    s = make_server(body_timeout_s=60, body_min_rate=500)
    head = b"POST /sessions HTTP/1.1\r\nHost: t\r\ncontent-type: application/json\r\ncontent-length: 100000\r\n\r\n"
    sock = connect(s.server.rest_port, head + b"{")
    out, when = b"", None
    for _ in range(20):  # one byte a second until the server closes
        more, when = read_until_closed(sock, 1.0)
        out += more
        if when is not None:
            break
        try:
            sock.sendall(b" ")
        except OSError:
            break
    sock.close()
    assert out.startswith(b"HTTP/1.1 408 "), out
    assert b"500 bytes/s" in out
    assert closed_count(s, "body_rate") == 1
    with httpx.Client(base_url=s.url) as http:
        assert http.get("/healthz").status_code == 200


def connect_from(source: str, port: int, data: bytes = b"") -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), source_address=(source, 0))
    if data:
        sock.sendall(data)
    return sock


SLOW_HEAD = (
    b"POST /sessions HTTP/1.1\r\nHost: t\r\ncontent-type: application/json\r\ncontent-length: 100000\r\n\r\n{"
)


def test_a_full_server_evicts_the_slow_bodies_of_a_peer_past_its_share(make_server):
    """One peer (127.0.0.2) fills the server with connections that sent their headers and trickle a body: a fresh
    client from another address is served (the hog's oldest body is closed for it); while the server is full,
    a new connection of the hog takes the place of one of its own, never the fresh client's. Before: body-phase connections were never evictable, and the
    fresh client was refused."""
    s = make_server(
        rest_max_connections=8, rest_max_connections_per_peer=4, body_timeout_s=60, body_min_rate=0
    )
    port = s.server.rest_port
    hog = [connect_from("127.0.0.2", port, SLOW_HEAD) for _ in range(8)]
    wait_for_body_phase(s, 8)
    with httpx.Client(base_url=s.url, timeout=10) as http:
        assert http.get("/healthz").status_code == 200  # its connection stays open, idle: the server is full
        _, when = read_until_closed(hog[0], 5)
        assert when is not None, "the hog's oldest slow body was not closed"
        assert closed_count(s, "evicted") == 1
        more = connect_from("127.0.0.2", port, SLOW_HEAD)  # past its share of a full server: it pays itself
        _, when = read_until_closed(hog[1], 5)
        assert when is not None, "the hog's new connection did not take the place of its own oldest one"
        assert closed_count(s, "evicted") == 2
        assert http.get("/healthz").status_code == 200  # the fresh client's connection was not taken for it
        assert closed_count(s, "evicted") == 2
    for c in (*hog, more):
        c.close()


def test_body_phase_connections_are_evicted_when_nothing_else_can_be(make_server):
    s = make_server(rest_max_connections=2, body_timeout_s=60, body_min_rate=0)
    port = s.server.rest_port
    slow = [connect(port, SLOW_HEAD) for _ in range(2)]
    wait_for_body_phase(s, 2)
    with httpx.Client(base_url=s.url, timeout=10) as http:
        assert http.get("/healthz").status_code == 200
    _, when = read_until_closed(slow[0], 5)
    assert when is not None, "the oldest slow body was not closed for the new connection"
    for c in slow:
        c.close()


@pytest.mark.parametrize(
    "request_head, status, code",
    [
        (b"POST /sessions HTTP/1.1\r\nHost: t\r\nContent-Length: -1\r\n\r\n", 400, "invalid_argument"),
        (b"POST /sessions HTTP/1.1\r\nHost: t\r\nContent-Length: abc\r\n\r\n", 400, "invalid_argument"),
        (b"GET /healthz HTTP/1.1\r\nHost: t\r\nX-Big: " + b"a" * 70_000 + b"\r\n\r\n", 431, None),
        (b"GET /healthz?" + b"q" * 70_000 + b" HTTP/1.1\r\nHost: t\r\n\r\n", 431, None),
    ],
    ids=["negative length", "non-numeric length", "huge header", "huge url"],
)
def test_requests_that_are_not_http_or_too_large_answer_in_the_error_envelope(
    make_server, request_head, status, code
):
    """uvicorn answers unparsable requests in plain text and puts no bound on the head (httptools has none)."""
    s = make_server()
    sock = connect(s.server.rest_port, request_head)
    out, when = read_until_closed(sock, 30)
    sock.close()
    assert when is not None and out.startswith(b"HTTP/1.1 %d " % status), out[:200]
    head, _, body = out.partition(b"\r\n\r\n")
    assert b"content-type: application/json" in head.lower() and b"x-served-by: " in head.lower()
    error = json.loads(body)["error"]
    assert error["code"] == (code or "request_header_fields_too_large"), error
    assert ("65536 bytes" if status == 431 else "malformed HTTP request") in error["message"]
    with httpx.Client(base_url=s.url) as http:  # the server goes on; a large head under the bound is fine
        assert http.get("/healthz", headers={"x-big": "a" * 60_000}).status_code == 200
