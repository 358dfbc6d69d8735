"""`make demo` drives HalfCheetah against a running server, over REST and gRPC, with make serve's port variables."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from service_harness import RunningServer, make_settings

ROOT = Path(__file__).resolve().parents[2]
VENV = Path(sys.prefix)


@pytest.fixture(scope="module")
def cheetah():
    """A server with the shipped halfcheetah-gmt, on free loopback ports."""
    s = RunningServer(make_settings(checkpoints=[ROOT / "checkpoints" / "halfcheetah-gmt"])).start()
    yield s
    s.stop()


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
@pytest.mark.parametrize("transport", ["rest", "grpc"])
def test_make_demo_runs_the_goal_schedule_through_the_server(cheetah, transport, tmp_path):
    # The `run` extra is installed in this environment (dev includes it): -o skips make's pip install.
    ports = [f"REST_PORT={cheetah.server.rest_port}", f"GRPC_PORT={cheetah.server.grpc_port}"]
    cmd = ["make", "--no-print-directory", "-o", f"{VENV}/.installed-run", "demo", f"VENV={VENV}", *ports]
    cmd += [f"TRANSPORT={transport}", f"DEMO_OUT={tmp_path}"]
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    rest, grpc = cheetah.server.rest_port, cheetah.server.grpc_port
    via = f"--grpc localhost:{grpc} --stream" if transport == "grpc" else f"--server http://localhost:{rest}"
    assert via in r.stdout.splitlines()[0]
    rows = [line.split()[:3] for line in r.stdout.splitlines() if line[:1].isdigit()]
    assert rows == [["1", "(low)", "0-299"], ["2", "(high)", "300-599"], ["1", "(low)", "600-899"]]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode-0.csv", "episode-0.json", "episode-0.png"]
