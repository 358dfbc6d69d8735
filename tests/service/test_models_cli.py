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
    out = gmt("models", "load", "tiny-gmt", str(root / "next" / "tiny-gmt-2"), *s)
    assert out.returncode == 0 and out.stdout.startswith(f"tiny-gmt {v2} loaded (serving"), out.stderr
    out = gmt("models", "promote", "tiny-gmt", v2, "--share", "0.1", *s)
    assert out.returncode == 0 and f"{v2}  serving  0         canary 0.1" in out.stdout, out.stdout
    out = gmt("models", "promote", "tiny-gmt", v2, *s)
    assert [line.split()[1:] for line in out.stdout.splitlines()[1:]] == [
        [v1, "serving", "0"],
        [v2, "serving", "0", "default"],
    ]
    out = gmt("models", "drain", "tiny-gmt", v1, *s)  # no session: unloaded at once
    assert out.returncode == 0 and v1 not in out.stdout
    out = gmt("models", "unload", "tiny-gmt", v2, *s)
    assert out.returncode == 0 and out.stdout.strip() == "MODEL  VERSION  STATE  SESSIONS  ROLE"
    out = gmt("models", "load", "tiny-gmt", "/etc", *s)
    assert out.returncode == 1 and out.stderr.startswith("error: permission_denied: '/etc' is not under")
    out = gmt("models", "list", "--server", "http://127.0.0.1:9")
    assert out.returncode == 1 and "error: unavailable: cannot reach http://127.0.0.1:9" in out.stderr


def test_gmt_models_is_a_base_install_command():
    code = "import sys, gmt.client.models; assert 'torch' not in sys.modules and 'fastapi' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
