"""`gmt models` against a real server: list, load, promote (and a canary), drain, unload; errors as `error: ...`."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from service_harness import clean_env

from gmt.model.checkpoint import load_checkpoint
from gmt.model.fixtures import tiny_checkpoint

GMT = str(Path(sys.executable).parent / "gmt")


def gmt(*args: str) -> subprocess.CompletedProcess:
    env = clean_env()
    return subprocess.run([GMT, *args], capture_output=True, text=True, env=env, timeout=120)


def test_gmt_models_drives_a_rollout(make_server, tmp_path):
    root = tmp_path / "checkpoints"
    tiny_checkpoint(root / "tiny-gmt")
    tiny_checkpoint(root / "next" / "tiny-gmt-2", seed=3)
    v1, v2 = load_checkpoint(root / "tiny-gmt").version, load_checkpoint(root / "next" / "tiny-gmt-2").version
    server = make_server(checkpoints=[root])
    s = ("--server", server.url)
    out = gmt("models", "list", *s)
    assert out.returncode == 0 and out.stdout.split("\n")[1].split() == [
        "tiny-gmt",
        v1,
        "serving",
        "0",
        "default",
    ]
    assert out.stderr.startswith(f"server {server.url} (--server or GMT_SERVER)")
    out = gmt("models", "load", "tiny-gmt", str(root / "next" / "tiny-gmt-2"), *s)
    assert out.returncode == 0 and out.stdout.startswith(f"tiny-gmt {v2} loaded (serving"), out.stderr
    out = gmt("models", "load", "tiny-gmt", str(root / "next" / "tiny-gmt-2"), *s)  # again: said, not silent
    assert out.returncode == 0 and out.stdout.startswith(f"tiny-gmt {v2} was already loaded"), out.stdout
    out = gmt("models", "promote", "tiny-gmt", v2, "--share", "0.1", *s)
    assert out.returncode == 0 and f"{v2}  serving  0         canary 0.1" in out.stdout, out.stdout
    out = gmt("models", "promote", "tiny-gmt", v2, *s)
    assert f"promoting tiny-gmt {v2} to the default on {server.url} (default was {v1})" in out.stderr
    assert [line.split()[1:] for line in out.stdout.splitlines()[1:-1]] == [
        [v1, "serving", "0"],
        [v2, "serving", "0", "default"],
    ]
    assert out.stdout.splitlines()[-1].startswith("defaults and canaries are kept across restarts (in a file")
    out = gmt("models", "drain", "tiny-gmt", v1, *s)  # no session: unloaded at once
    assert out.returncode == 0 and v1 not in out.stdout
    assert f"draining tiny-gmt {v1} (0 session(s)) on {server.url}" in out.stderr
    out = gmt("models", "unload", "tiny-gmt", v2, *s)  # the only version left: a server keeps one (409)
    assert out.returncode == 1 and f"unloading tiny-gmt {v2} (0 session(s)) on" in out.stderr
    assert "is the only version this server serves: load another before unloading it" in out.stderr
    out = gmt("models", "load", "tiny-gmt", "/etc", *s)
    assert out.returncode == 1 and "\nerror: permission_denied: '/etc' is not under" in out.stderr
    out = gmt("models", "list", "--server", "http://127.0.0.1:9")
    assert out.returncode == 1 and "error: unavailable: cannot reach http://127.0.0.1:9" in out.stderr


def test_gmt_models_is_a_base_install_command():
    code = "import sys, gmt.client.models; assert 'torch' not in sys.modules and 'fastapi' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def test_gmt_models_copy_makes_a_second_version(make_server, tmp_path):
    """A copy under a new version name loads as a second version of the model (the same weights)."""
    root = tmp_path / "checkpoints"
    tiny_checkpoint(root / "tiny-gmt")
    out = gmt(
        "models", "copy", str(root / "tiny-gmt"), str(root / "releases" / "tiny-gmt-v2"), "--version", "v2"
    )
    assert out.returncode == 0 and out.stdout.startswith(
        f"wrote {root / 'releases' / 'tiny-gmt-v2'} (version v2"
    ), out
    assert load_checkpoint(root / "releases" / "tiny-gmt-v2").version == "v2"
    server = make_server(checkpoints=[root])
    out = gmt("models", "load", "tiny-gmt", "releases/tiny-gmt-v2", "--server", server.url)
    assert out.returncode == 0 and out.stdout.startswith("tiny-gmt v2 loaded (serving"), out.stderr
    again = gmt(
        "models", "copy", str(root / "tiny-gmt"), str(root / "releases" / "tiny-gmt-v2"), "--version", "v2"
    )
    assert again.returncode == 1 and "exists" in again.stderr


def test_gmt_models_with_an_admin_token_that_is_not_the_auth_token(make_server, tmp_path):
    """The admin token lists the versions too (it sees everything): `promote` names the default it replaces and
    prints the versions after acting."""
    root = tmp_path / "checkpoints"
    tiny_checkpoint(root / "tiny-gmt")
    v1 = load_checkpoint(root / "tiny-gmt").version
    server = make_server(checkpoints=[root], auth_token="user", admin_token="root")
    out = gmt("models", "promote", "tiny-gmt", v1, "--server", server.url, "--token", "root")
    assert out.returncode == 0, out.stderr
    assert f"(default was {v1})" in out.stderr and "cannot list" not in out.stderr
    assert out.stdout.splitlines()[1].split()[1:] == [v1, "serving", "0", "default"]
    out = gmt("models", "promote", "tiny-gmt", v1, "--server", server.url, "--token", "user")
    assert out.returncode == 1 and "error: unauthenticated" in out.stderr
