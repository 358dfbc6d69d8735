"""clients/cpp: the C++ Control-stream client, built with clients/cpp/build.sh and run against a real server;
docs/clients.md's "From C++" block run as written."""

from __future__ import annotations

import json
import re
import socket
import subprocess
from pathlib import Path

import grpc
import httpx
import numpy as np
import pytest
from service_harness import run_doc_block

from gmt.bench.harness import cpp_control_client, cpp_toolchain_missing
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

OBS = [round(0.05 * (i % 7) - 0.15, 2) for i in range(17)]  # HalfCheetah-v5: 17 values


@pytest.fixture(scope="module")
def control_loop() -> Path:
    """The client as `gmt bench` builds it (build/cpp; skipped where gRPC's C++ toolchain is not installed)."""
    if missing := cpp_toolchain_missing():
        pytest.skip(f"gRPC's C++ toolchain is not installed ({', '.join(missing)}; see clients/cpp/build.sh)")
    binary = cpp_control_client()
    assert binary is not None and binary.exists()
    return binary


def run(binary: Path, *args: str) -> tuple[int, dict]:
    done = subprocess.run([str(binary), *args], capture_output=True, text=True, timeout=60)
    return done.returncode, json.loads(done.stdout) if done.stdout else {"stderr": done.stderr}


def new_session(live_server, seed: int) -> str:
    with httpx.Client(base_url=live_server.rest_url, timeout=10) as http:
        r = http.post("/sessions", json={"model": "tiny-gmt", "goal": 1, "seed": seed})
        assert r.status_code == 201, r.text
        return r.json()["session_id"]


def test_the_cpp_client_gets_the_actions_a_python_client_gets(control_loop, live_server):
    """Two sessions with the same seed and goal, driven with the same observations, one from C++, one from Python
    (grpcio): the same actions, bit for bit (printed with 9 significant digits, enough for a float32)."""
    ours, theirs = new_session(live_server, seed=7), new_session(live_server, seed=7)
    obs = ",".join(str(v) for v in OBS)
    rc, out = run(control_loop, live_server.grpc_target, ours, "--obs", obs, "--acts", "6", "--print-actions")
    assert rc == 0, out
    assert out["acts"] == 6 and out["errors"] == 0 and out["status"] == "OK", out
    assert 0 < out["p50_ms"] <= out["p99_ms"]
    with grpc.insecure_channel(live_server.grpc_target) as channel:
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        act = pb.ControlRequest(act=pb.ActRequest(session_id=theirs, values=pb.FloatVector(values=OBS)))
        expected = [list(a.act.action) for a in stub.Control(iter([act] * 6), timeout=30)]
    assert len(expected[0]) == 6  # HalfCheetah's action size
    np.testing.assert_array_equal(np.asarray(out["actions"], np.float32), np.asarray(expected, np.float32))
    with httpx.Client(base_url=live_server.rest_url, timeout=10) as http:
        assert http.get(f"/sessions/{ours}").json()["step"] == 6


def test_the_cpp_client_reports_an_unknown_session_and_a_wrong_observation(control_loop, live_server):
    rc, out = run(control_loop, live_server.grpc_target, "no-such-session", "--obs", "0.1", "--acts", "2")
    assert rc == 1 and out["acts"] == 2 and out["errors"] == 2, out
    assert out["first_error"].startswith("not_found: ") and "no-such-session" in out["first_error"], out
    sid = new_session(live_server, seed=1)
    rc, out = run(control_loop, live_server.grpc_target, sid, "--obs", "0.1,0.2", "--acts", "1")
    assert rc == 1 and out["errors"] == 1, out
    assert (
        out["first_error"].startswith("invalid_argument: ") and "2 values, expected 17" in out["first_error"]
    )
    rc, out = run(
        control_loop, live_server.grpc_target, sid, "--obs", ",".join(str(v) for v in OBS), "--acts", "1"
    )
    assert rc == 0 and out["errors"] == 0, out  # the session stayed usable


def test_the_cpp_client_runs_for_a_time_and_reports_an_unreachable_server(control_loop, live_server):
    sid = new_session(live_server, seed=2)
    obs = ",".join(str(v) for v in OBS)
    rc, out = run(control_loop, live_server.grpc_target, sid, "--obs", obs, "--seconds", "0.5")
    assert rc == 0 and out["acts"] > 10 and out["errors"] == 0 and not out["stream_broken"], out
    assert 0.5 <= out["seconds"] < 5 and out["p50_ms"] <= out["p99_ms"]
    with httpx.Client(base_url=live_server.rest_url, timeout=10) as http:
        assert http.get(f"/sessions/{sid}").json()["step"] == out["acts"]
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    rc, out = run(control_loop, f"127.0.0.1:{port}", sid, "--obs", obs, "--acts", "3")
    assert rc == 1 and out["acts"] == 0 and out["stream_broken"], out
    assert out["p50_ms"] is None and out["status"].startswith("UNAVAILABLE: "), out


@pytest.mark.parametrize(
    "args, message",
    [
        (["--obs", "1,x", "--acts", "1"], "not a number: 'x'"),
        (["--obs", "1,2,", "--acts", "1"], "a comma-separated list of numbers"),
        (["--obs", "1", "--acts", "10x"], "--acts must be a whole number"),
        (["--obs", "1", "--acts", "0"], "--acts must be a whole number"),
        (["--obs", "1", "--seconds", "inf"], "--seconds must be a number"),
        (["--obs", "1", "--seconds", "5s"], "--seconds must be a number"),
        (["--obs", "1"], "one of --acts and --seconds"),
        (["--obs", "1", "--acts", "1", "--seconds", "1"], "one of --acts and --seconds"),
        (["--acts", "1"], "--obs is required"),
        (["--obs", "1", "--acts", "1", "--fast"], "unknown or incomplete option --fast"),
    ],
)
def test_the_cpp_client_refuses_bad_arguments(control_loop, args, message):
    done = subprocess.run([str(control_loop), "127.0.0.1:1", "s", *args], capture_output=True, text=True)
    assert done.returncode == 2 and message in done.stderr, done.stderr
    assert done.stdout == ""


def test_the_docs_block_runs_as_written(control_loop, live_server):
    """docs/clients.md's "From C++" block, against this module's server: its ports for localhost:8000 / :50051 and
    tiny-gmt (HalfCheetah-v5's shapes) for halfcheetah-gmt are the only changes."""
    root = Path(__file__).resolve().parents[2]
    doc = (root / "docs" / "clients.md").read_text()
    block = re.search(r"## From C\+\+\n.*?```bash\n(.*?)```", doc, re.S).group(1)
    host = live_server.rest_url.removeprefix("http://")
    for a, b in (
        ("localhost:8000", host),
        ("localhost:50051", live_server.grpc_target),
        ("halfcheetah-gmt", "tiny-gmt"),
    ):
        block = block.replace(a, b)
    done = run_doc_block(block, root)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["acts"] == 200 and out["errors"] == 0 and out["status"] == "OK" and len(out["actions"]) == 200
    assert all(len(a) == 6 for a in out["actions"])
