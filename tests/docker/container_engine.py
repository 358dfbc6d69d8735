"""Which container engine can run here (docker first, as docker/lib.sh picks), and the image build that warms the
cache for tests/docker: started when the session's tests are collected, so that it overlaps the other tests."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOCKER = ROOT / "docker"
IMAGE = "localhost/gmt-service:test"


def engine() -> tuple[str | None, str]:
    """The engine that answers, or None and why neither does."""
    why = []
    for name in ("docker", "podman"):
        if shutil.which(name) is None:
            why.append(f"{name} is not installed")
            continue
        r = subprocess.run([name, "info"], capture_output=True, text=True, timeout=60)
        if r.returncode == 0:
            return name, ""
        why.append(f"`{name} info` failed: {(r.stderr.strip().splitlines() or ['?'])[-1]}")
    return None, "; ".join(why) + " (apt-get install podman runc mmdebstrap; .ci/run does)"


def build_env(name: str) -> dict[str, str]:
    """The environment docker/*.sh run in: this one without GMT_ settings, the engine and podman-compose named."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GMT_")}
    env.update(ENGINE=name, PODMAN_COMPOSE=str(Path(sys.executable).with_name("podman-compose")))
    return env


def start_prebuild(name: str) -> subprocess.Popen:
    """Build the local images and the test image in the background (its output in a temporary file). The tests
    still run both scripts themselves: after this they find every image built and reuse it."""
    log = tempfile.NamedTemporaryFile(prefix="gmt-prebuild-", suffix=".log", delete=False)
    script = f'set -e; base=$("{DOCKER}/local-images.sh" | cut -d" " -f1); IMAGE={IMAGE} BASE="$base" "{DOCKER}/image.sh"'
    return subprocess.Popen(["bash", "-c", script], env=build_env(name), stdout=log, stderr=subprocess.STDOUT)
