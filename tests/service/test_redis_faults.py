"""Redis restarted (AOF) or paused mid-episode: the act in between answers `unavailable`, nothing is lost, and
the episode then continues exactly like a twin that never saw the fault."""

import os
import shutil
import signal
import socket
import subprocess

import httpx
import numpy as np
import pytest
from service_harness import RunningServer, make_settings

from model.checkpoint import load_checkpoint
from model.engine import PolicyEngine

pytestmark = pytest.mark.skipif(
    shutil.which("redis-server") is None,
    reason="redis-server is not installed (apt-get install redis-server)",
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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

    port = _free_port()
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
