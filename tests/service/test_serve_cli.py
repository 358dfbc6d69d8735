"""`gmt serve` as users run it: flags, environment, the no-model start, graceful SIGTERM."""

import signal
import subprocess
import sys
from pathlib import Path

import httpx
from service_harness import ServeProcess

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


def test_serve_without_checkpoints_says_so_and_stops_gracefully(tmp_path):
    p = ServeProcess("--checkpoints", str(tmp_path / "checkpoints"))
    try:
        info = p.wait_serving()
        assert info["models"] == [] and info["ready"] is False
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
