"""`gmt serve` as users run it: flags, environment, the no-model start, graceful SIGTERM, a taken port."""

import asyncio
import signal
import socket
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from service_harness import ServeProcess, clean_env, make_settings

from gmt.service.core import Core
from gmt.service.grpc.server import GrpcServer
from gmt.service.memory import YOUNG_THRESHOLD
from gmt.service.settings import Settings


def test_settings_from_environment_and_flags(monkeypatch, tmp_path):
    monkeypatch.setenv("GMT_CHECKPOINTS", f"{tmp_path}/a, {tmp_path}/b")
    monkeypatch.setenv("GMT_MAX_SESSIONS", "7")
    monkeypatch.setenv("GMT_AUTH_TOKEN", "t0k")
    s = Settings()
    assert [p.name for p in s.checkpoints] == ["a", "b"] and s.max_sessions == 7 and s.token == "t0k"
    assert "t0k" not in repr(s)
    assert Settings(max_sessions=3).max_sessions == 3  # flags (init arguments) win over the environment
    monkeypatch.setenv("GMT_AUTH_TOKEN", "")
    assert Settings().token is None


def test_every_setting_has_a_row_in_the_configuration_table():
    doc = (Path(__file__).parents[2] / "docs" / "serving.md").read_text()
    table = doc.split("## Configuration", 1)[1]
    missing = [name for name in Settings.model_fields if f"`GMT_{name.upper()}`" not in table]
    assert not missing, f"docs/serving.md, Configuration: no row for {missing}"


def test_serve_without_checkpoints_says_so_and_stops_gracefully(tmp_path):
    p = ServeProcess("--checkpoints", str(tmp_path / "checkpoints"))
    try:
        info = p.wait_serving()
        assert info["models"] == [] and info["ready"] is False
        # `gmt serve` hides its startup objects from the garbage collector and collects young objects less often
        # (in-process test servers do neither).
        assert info["gc_frozen_objects"] > 10_000, info["gc_frozen_objects"]
        assert info["gc_young_threshold"] == YOUNG_THRESHOLD
        warning = next(r for r in p.lines if r.get("msg", "").startswith("no model loaded"))
        assert warning["level"] == "warning" and warning["checkpoints"] == [str(tmp_path / "checkpoints")]
        r = httpx.get(f"{p.url}/readyz")
        assert r.status_code == 503 and r.json()["reason"] == "no model loaded"
        assert httpx.get(f"{p.url}/healthz").status_code == 200
        p.proc.send_signal(signal.SIGTERM)
        assert p.proc.wait(30) == 0
        assert p.messages()[-1] == "stopped"
    finally:
        p.kill()


def test_serve_help_lists_the_flags():
    gmt = str(Path(sys.executable).parent / "gmt")
    out = subprocess.run([gmt, "serve", "--help"], capture_output=True, text=True, check=True).stdout
    for flag in (
        "--checkpoints",
        "--rest-port",
        "--grpc-port",
        "--max-sessions",
        "--idle-timeout",
        "--auth-token",
        "--replica-id",
    ):
        assert flag in out


def _held_port(reuseport: bool = False) -> socket.socket:
    """A loopback socket listening on a free port (with SO_REUSEPORT, as gRPC servers bind, when asked)."""
    s = socket.socket()
    if reuseport:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    s.bind(("127.0.0.1", 0))
    s.listen()
    return s


@pytest.mark.parametrize("transport", ["rest", "grpc"])
def test_a_taken_port_fails_in_a_few_lines_naming_the_port_and_how_to_change_it(transport, tmp_path):
    gmt = str(Path(sys.executable).parent / "gmt")
    env = clean_env()
    with _held_port() as held:
        port = held.getsockname()[1]
        ports = {"rest": "0", "grpc": "0", transport: str(port)}
        cmd = [gmt, "serve", "--host", "127.0.0.1", "--checkpoints", str(tmp_path)]
        cmd += ["--rest-port", ports["rest"], "--grpc-port", ports["grpc"]]
        r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) <= 5, r.stderr
    assert "Traceback" not in r.stderr
    name = {"rest": "REST", "grpc": "gRPC"}[transport]
    assert f"cannot listen for {name} on 127.0.0.1:{port}: Address already in use" in lines[0]
    for hint in (
        f"--{transport}-port",
        f"GMT_{transport.upper()}_PORT",
        f"make serve {transport.upper()}_PORT=",
    ):
        assert hint in r.stderr


def test_grpc_does_not_join_a_port_another_server_holds_with_so_reuseport(ckpt_root):
    # grpcio binds with SO_REUSEPORT by default, so a second server would share the port with the first.
    with _held_port(reuseport=True) as held:
        port = held.getsockname()[1]
        core = Core(make_settings(checkpoints=[ckpt_root]))

        async def bind() -> None:
            GrpcServer(core, "127.0.0.1", port)

        with pytest.raises((RuntimeError, OSError)):
            asyncio.run(bind())


def test_an_interface_this_machine_does_not_have_names_the_host_flag(tmp_path):
    gmt = str(Path(sys.executable).parent / "gmt")
    env = clean_env()
    cmd = [
        gmt,
        "serve",
        "--host",
        "::2",
        "--rest-port",
        "0",
        "--grpc-port",
        "0",
        "--checkpoints",
        str(tmp_path),
    ]
    r = subprocess.run(
        cmd, capture_output=True, text=True, env=env, timeout=120
    )  # bind only: nothing is sent
    assert r.returncode == 1 and "Traceback" not in r.stderr
    first, hint = r.stderr.strip().splitlines()
    assert first.startswith("error: cannot listen for REST on [::2]:0: ")
    assert "--host" in hint and "GMT_HOST" in hint and "port" not in hint


def serve_refused(tmp_path, *flags: str, **env: str) -> subprocess.CompletedProcess:
    """`gmt serve` with `flags` over an empty checkpoint directory, on free ports (a refusal comes first)."""
    gmt = str(Path(sys.executable).parent / "gmt")
    args = [gmt, "serve", "--checkpoints", str(tmp_path), *flags, "--rest-port", "0", "--grpc-port", "0"]
    return subprocess.run(
        args, capture_output=True, text=True, env=clean_env(COLUMNS="300", **env), timeout=60
    )


@pytest.mark.parametrize(
    ("device", "message"),
    [
        ("tpu", "String should match pattern"),
        *([("cuda", "torch sees no CUDA GPU here")] if not __import__("torch").cuda.is_available() else []),
    ],
)
def test_serve_refuses_a_device_it_cannot_use_before_loading_anything(tmp_path, device, message):
    done = serve_refused(tmp_path, "--device", device)
    assert done.returncode == 2 and message in done.stderr and "device" in done.stderr, done.stderr


def test_serve_refuses_bf16_without_the_native_step_before_loading_anything(tmp_path):
    done = serve_refused(tmp_path, "--precision", "bf16", GMT_NATIVE="0")
    assert done.returncode == 2 and "AVX-512 BF16" in done.stderr and "--precision" in done.stderr, (
        done.stderr
    )
