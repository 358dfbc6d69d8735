"""Real servers for the service tests: in-process (REST + gRPC on loopback port 0, in a thread) or `gmt serve`."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from gmt.service.core import Core
from gmt.service.redis_store import store_for
from gmt.service.server import Server
from gmt.service.settings import Settings

OBS_DIM = 17


class FakeClock:
    """A wall clock that moves only when told to."""

    def __init__(self, t: float = 1_000_000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, seconds: float) -> None:
        self.t += seconds


class RunningServer:
    """`gmt.service.server.Server` running its own event loop in a background thread."""

    def __init__(self, settings: Settings, clock=None) -> None:
        self.settings = settings
        clock = clock or time.time
        self.core = Core(settings, store=store_for(settings, clock), clock=clock)  # as `Server` builds it
        self.server = Server(settings, self.core)
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, name="test-server", daemon=True)

    def _main(self) -> None:
        async def run() -> None:
            self.loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            try:
                await self.server.start()
            except BaseException as e:
                self._error = e
                self._started.set()
                raise
            self._started.set()
            await self._stop.wait()
            await self.server.stop()

        try:
            asyncio.run(run())
        except BaseException as e:  # noqa: BLE001 - reported by start()
            self._error = self._error or e

    def start(self) -> RunningServer:
        self._thread.start()
        if not self._started.wait(60):
            raise TimeoutError("server did not start within 60 s")
        if self._error is not None:
            raise self._error
        return self

    def stop(self) -> None:
        if self._thread.is_alive():
            self.loop.call_soon_threadsafe(self._stop.set)
            self._thread.join(30)

    def run(self, coro):
        """Run a coroutine on the server's loop (e.g. `core.sweep()`) and return its result."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(30)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server.rest_port}"

    @property
    def target(self) -> str:
        return f"127.0.0.1:{self.server.grpc_port}"


def make_settings(**kw) -> Settings:
    """Settings for a loopback test server on free ports (environment ignored); `checkpoints` is required."""
    base = dict(
        host="127.0.0.1",
        rest_port=0,
        grpc_port=0,
        redis_url=None,
        auth_token=None,
        shutdown_grace_s=1.0,
    )
    return Settings(**{**base, **kw})


def clean_env(**extra: str) -> dict[str, str]:
    """This process's environment without any GMT_ setting (a test's servers see only what it gives), plus
    `extra`."""
    return {**{k: v for k, v in os.environ.items() if not k.startswith("GMT_")}, **extra}


def run_doc_block(script: str, cwd: Path) -> subprocess.CompletedProcess:
    """A doc's bash block run as a user would (`bash -euo pipefail`), this environment's `gmt` and `python` first on
    PATH, no GMT_ setting inherited; its output captured."""
    env = clean_env(PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    return subprocess.run(
        ["bash", "-euo", "pipefail", "-c", script],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )


# What a test cluster's replicas run with: a short shutdown grace, quiet logs.
CLUSTER_ENV = {"GMT_SHUTDOWN_GRACE_S": "1", "GMT_LOG_LEVEL": "WARNING"}


def exec_after(prelude: str, cmd: list[str]) -> list[str]:
    """`cmd` run by a small Python that first runs `prelude` (a change to the process: a signal, a limit) and then
    execs it, keeping the pid. Instead of `subprocess.Popen(preexec_fn=...)`, which runs Python between fork and
    exec and can deadlock the child while this process's threads (gRPC's) hold locks: seen once in CI."""
    return [sys.executable, "-c", f"{prelude}; import os, sys; os.execv(sys.argv[1], sys.argv[1:])", *cmd]


class ServeProcess:
    """`gmt serve` in a subprocess; a reader thread drains its JSON log lines and spots the "serving" line."""

    def __init__(
        self,
        *args: str,
        nofile: int | None = None,
        cwd: Path | None = None,
        env: dict[str, str] | None = None,
    ) -> None:
        exe = Path(sys.executable).parent / "gmt"
        env = clean_env(**(env or {}))  # tuning knobs (`settings.TUNING`) are environment variables only
        cmd = [str(exe), "serve", "--rest-port", "0", "--grpc-port", "0", "--log-format", "json", *args]

        if nofile:  # `ulimit -n nofile` in the child
            cmd = exec_after(
                f"import resource; resource.setrlimit(resource.RLIMIT_NOFILE, ({nofile}, {nofile}))", cmd
            )
        self.proc = subprocess.Popen(
            cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env, cwd=cwd
        )
        self.lines: list[dict] = []
        self.serving: dict | None = None
        self._ready = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for raw in self.proc.stderr:
            try:
                rec = json.loads(raw)
            except json.JSONDecodeError:
                rec = {"msg": raw.rstrip()}
            self.lines.append(rec)
            if rec.get("msg") == "serving":
                self.serving = rec
                self._ready.set()
        self._ready.set()  # exited

    def wait_serving(self, timeout: float = 60) -> dict:
        assert self._ready.wait(timeout), "gmt serve did not start in time"
        assert self.serving is not None, f"gmt serve exited: {self.lines}"
        return self.serving

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.serving['rest_port']}"

    def messages(self) -> list[str]:
        return [rec.get("msg", "") for rec in self.lines]

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(30)
