"""Fixtures of the service tests: tiny checkpoints, a shared server, clients, a fake clock."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import grpc
import httpx
import numpy as np
import pytest
from service_harness import OBS_DIM, FakeClock, RunningServer, make_settings

from gmt.cluster.supervisor import free_port
from gmt.model.checkpoint import load_checkpoint
from gmt.model.engine import PolicyEngine
from gmt.model.fixtures import tiny_checkpoint
from gmt.v1 import policy_pb2_grpc


@pytest.fixture(scope="session")
def ckpt_root(tmp_path_factory) -> Path:
    """checkpoints/ with tiny-gmt (HalfCheetah-v5, 3 goals, K = 5), tiny-cartpole (discrete actions) and
    tiny-sampled (tiny-gmt's weights with a calibrated action noise: sampled actions by default)."""
    root = tmp_path_factory.mktemp("checkpoints")
    tiny_checkpoint(root / "tiny-gmt")
    tiny_checkpoint(root / "tiny-sampled", name="tiny-sampled", calibrated=True)
    tiny_checkpoint(root / "tiny-cartpole", env_id="CartPole-v1", name="tiny-cartpole")
    return root


@pytest.fixture(scope="session")
def engine(ckpt_root) -> PolicyEngine:
    """A reference engine over the same tiny-gmt checkpoint the servers load."""
    return PolicyEngine(load_checkpoint(ckpt_root / "tiny-gmt"))


@pytest.fixture(scope="module")
def server(ckpt_root):
    """A default server over both tiny checkpoints."""
    s = RunningServer(make_settings(checkpoints=[ckpt_root], max_request_bytes=64 * 1024)).start()
    yield s
    s.stop()


@pytest.fixture
def http(server):
    with httpx.Client(base_url=server.url, timeout=30) as c:
        yield c


@pytest.fixture
def stub(server):
    with grpc.insecure_channel(server.target) as ch:
        yield policy_pb2_grpc.PolicyServiceStub(ch)


@pytest.fixture
def observations() -> np.ndarray:
    """Twelve float32 observations for tiny-gmt."""
    return np.random.default_rng(7).normal(size=(12, OBS_DIM)).astype(np.float32)


@pytest.fixture
def make_server(ckpt_root):
    """Start a dedicated server: `make_server(clock=..., **settings)`; stopped after the test."""
    started = []

    def make(clock=None, **kw) -> RunningServer:
        kw.setdefault("checkpoints", [ckpt_root])
        s = RunningServer(make_settings(**kw), clock=clock).start()
        started.append(s)
        return s

    yield make
    for s in started:
        s.stop()


@pytest.fixture
def clock() -> FakeClock:
    """A fake wall clock to inject into a server."""
    return FakeClock()


@pytest.fixture(scope="module")
def redis_server(tmp_path_factory):
    """A real redis-server for the module on a free loopback port and a Unix socket: (redis:// URL, unix:// URL)
    (skipped where none is installed)."""
    exe = shutil.which("redis-server")
    if exe is None:
        pytest.skip("redis-server is not installed (apt-get install redis-server; .ci/run installs it)")
    port = free_port()
    where = tmp_path_factory.mktemp("redis")
    sock = where / "redis.sock"
    proc = subprocess.Popen(
        [exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"]
        + ["--unixsocket", str(sock), "--unixsocketperm", "700"],
        cwd=where,
        stdout=subprocess.PIPE,
        text=True,
    )
    for line in proc.stdout:  # ends at EOF if redis exits
        if "Ready to accept connections" in line:
            break
    assert proc.poll() is None, "redis-server did not start"
    yield f"redis://127.0.0.1:{port}/0", f"unix://{sock}?db=0"
    proc.terminate()
    proc.wait(10)


@pytest.fixture(scope="module")
def redis_url(redis_server):
    """The module's redis-server over loopback TCP."""
    return redis_server[0]


@pytest.fixture
def redis_clean(redis_url):
    """`redis_url`, emptied."""
    import redis

    r = redis.Redis.from_url(redis_url)
    r.flushall()
    r.close()
    return redis_url


@pytest.fixture(params=["tcp", "unix"])
def redis_clean_any(request, redis_server, redis_clean):
    """`redis_clean` reached over loopback TCP, then over its Unix socket (both take the fast path)."""
    return redis_server[0] if request.param == "tcp" else redis_server[1]
