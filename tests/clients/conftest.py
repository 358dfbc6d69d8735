"""Real servers for the client tests: `gmt.service.server.Server` (REST + gRPC) on loopback port 0, in a thread."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import torch

from gmt.model.fixtures import tiny_checkpoint
from gmt.service.server import Server
from gmt.service.settings import Settings


class LiveServer:
    """Both transports over one core, on an event loop of their own in a background thread."""

    def __init__(self, settings: Settings) -> None:
        self.server = Server(settings)
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="client-test-server", daemon=True)
        self.thread.start()
        try:
            self._run(self.server.start())
        except BaseException:
            self._end_loop()
            raise
        self.rest_url = f"http://127.0.0.1:{self.server.rest_port}"
        self.grpc_target = f"127.0.0.1:{self.server.grpc_port}"

    def _run(self, coro, timeout: float = 60.0):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def _end_loop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(30)
        self.loop.close()

    def stop(self) -> None:
        """Shut both servers down gracefully and end the loop's thread."""
        try:
            self._run(self.server.stop())
        finally:
            self._end_loop()


def settings_for(checkpoints: Path, **kw) -> Settings:
    """Loopback, free ports, no auth, memory sessions (GMT_* environment variables overridden)."""
    base = dict(
        checkpoints=[checkpoints],
        host="127.0.0.1",
        rest_port=0,
        grpc_port=0,
        redis_url=None,
        auth_token=None,
        batch_wait_ms=0.0,
        shutdown_grace_s=0.0,
    )
    return Settings(**{**base, **kw})


@pytest.fixture(scope="session")
def ckpt_root(tmp_path_factory) -> Path:
    """checkpoints/ with tiny-gmt: HalfCheetah-v5, random weights, goals low/medium/high (means 0, 1, 2), K = 5."""
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("checkpoints")
    tiny_checkpoint(root / "tiny-gmt")
    return root


@pytest.fixture(scope="session")
def live_server(ckpt_root) -> Iterator[LiveServer]:
    """A server over tiny-gmt shared by the client tests."""
    srv = LiveServer(settings_for(ckpt_root))
    yield srv
    srv.stop()


@pytest.fixture
def start_server() -> Iterator[Callable[..., LiveServer]]:
    """start_server(checkpoints, **settings) -> a LiveServer, stopped when the test ends."""
    started: list[LiveServer] = []

    def start(checkpoints: Path, **kw) -> LiveServer:
        started.append(LiveServer(settings_for(checkpoints, **kw)))
        return started[-1]

    yield start
    for s in started:
        s.stop()


@pytest.fixture(scope="module")
def serve_root() -> Iterator[Callable[[Path], LiveServer]]:
    """Start a server over another checkpoints folder (stopped after the module)."""
    servers: list[LiveServer] = []

    def start(root: Path) -> LiveServer:
        servers.append(LiveServer(settings_for(root)))
        return servers[-1]

    yield start
    for srv in servers:
        srv.stop()
