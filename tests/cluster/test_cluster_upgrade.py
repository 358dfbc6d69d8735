"""A rolling upgrade of `gmt cluster up` (docs/models.md): `cluster.upgrade` loads v2 on the replicas,
promotes it and drains v1, while one replica is killed (SIGKILL) in the middle of it. Sessions of both versions
continue exactly through nginx on the surviving replica: each answers the actions of a reference engine of its own
version."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from service_harness import CLUSTER_ENV, clean_env

from gmt.cluster import supervisor as cluster
from gmt.model.checkpoint import load_checkpoint
from gmt.model.engine import PolicyEngine
from gmt.model.fixtures import tiny_checkpoint

MODEL = "tiny-cheetah"
N, STEPS = 8, 4

pytestmark = pytest.mark.skipif(
    cluster.find_executable("nginx") is None or cluster.find_executable("redis-server") is None,
    reason=f"nginx and redis-server are needed ({cluster.INSTALL_HINT})",
)


@pytest.fixture(scope="module")
def running(tmp_path_factory):
    root = tmp_path_factory.mktemp("checkpoints")
    tiny_checkpoint(root / MODEL, name=MODEL, attention="window", calibrated=True, seed=0)
    tiny_checkpoint(root / "releases" / "v2", name=MODEL, attention="window", calibrated=True, seed=1)
    run_dir = tmp_path_factory.mktemp("run") / "cluster"
    env = clean_env(**CLUSTER_ENV)
    c = cluster.up(run_dir, rest_port=0, grpc_port=0, checkpoints=[root], env=env, timeout_s=90)
    yield c, root
    cluster.down(run_dir, timeout_s=10, quiet=True)


def reference(root: Path, path: str, seed: int, obs: np.ndarray) -> list[list[float]]:
    engine = PolicyEngine(load_checkpoint(root / path))
    ctx = engine.new_context(seed % 3, seed=seed)
    return [engine.act([ctx], [o])[0].tolist() for o in obs]


def act(http, sid: str, obs, step: int) -> list[float]:
    r = http.post(f"/sessions/{sid}/act", json={"observation": np.asarray(obs).tolist(), "step": step})
    assert r.status_code == 200, r.text
    return r.json()["action"]


def test_rolling_upgrade_with_a_replica_killed_midway(running):
    c, root = running
    v1, v2 = (load_checkpoint(root / p).version for p in (MODEL, "releases/v2"))
    rng = np.random.default_rng(8)
    obs = rng.normal(size=(3 * N, 2 * STEPS, 17)).astype(np.float32)
    steps: list[tuple[str, str, str]] = []
    victim = c.replica("gmt-2")

    def progress(step: str, name: str, detail: str) -> None:
        steps.append((step, name, detail))
        if (step, name) == ("load", "gmt-1"):  # v2 is on gmt-1 only: kill gmt-2 before it gets it
            os.kill(victim.pid, signal.SIGKILL)

    with httpx.Client(base_url=c.rest_url, timeout=30) as http:
        old, served = [], set()
        for i in range(2 * N):  # N sessions, more until both replicas hold some (1 in 2^15 to fail)
            if len(old) >= N and served == {"gmt-1", "gmt-2"}:
                break
            r = http.post("/sessions", json={"model": MODEL, "goal": i % 3, "seed": i})
            assert r.status_code == 201 and r.json()["model_version"] == v1, r.text
            old.append(r.json()["session_id"])
            served.add(http.get(f"/sessions/{old[-1]}").headers["x-served-by"])
        assert served == {"gmt-1", "gmt-2"}, served
        got = {sid: [act(http, sid, obs[i, t], t) for t in range(STEPS)] for i, sid in enumerate(old)}

        report = cluster.upgrade(root / "releases" / "v2", c.run_dir, progress=progress)
        assert report.version == v2 and report.done == ["gmt-1"] and list(report.failed) == ["gmt-2"]
        assert report.failed["gmt-2"].startswith("load: unavailable: cannot reach")
        assert steps == [("load", "gmt-1", v2), ("promote", "gmt-1", v2), ("drain", "gmt-1", v1)]

        new = []
        for i in range(N):
            r = http.post("/sessions", json={"model": MODEL, "goal": i % 3, "seed": i})
            assert r.status_code == 201 and r.json()["model_version"] == v2, r.text
            new.append(r.json()["session_id"])
        for i, sid in enumerate(new):
            assert [act(http, sid, obs[2 * N + i, t], t) for t in range(STEPS)] == reference(
                root, "releases/v2", i, obs[2 * N + i, :STEPS]
            )
        for i, sid in enumerate(old):  # half of them were gmt-2's: gmt-1 adopts them, on v1
            got[sid] += [act(http, sid, obs[i, t], t) for t in range(STEPS, 2 * STEPS)]
            assert got[sid] == reference(root, MODEL, i, obs[i]), f"session {i}"
            assert http.get(f"/sessions/{sid}").json()["model_version"] == v1

        survivor = f"http://127.0.0.1:{c.replica('gmt-1').rest_port}"
        with httpx.Client(base_url=survivor, timeout=30) as direct:
            table = {v["version"]: v["state"] for v in direct.get("/models").json()["models"][0]["versions"]}
            assert table == {v1: "draining", v2: "serving"}
            for sid in old:
                assert http.delete(f"/sessions/{sid}").status_code == 204
            deadline = time.monotonic() + 30
            while v1 in str(direct.get("/models").json()) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert [v["version"] for v in direct.get("/models").json()["models"][0]["versions"]] == [v2]

    # The command itself: gmt-1 is upgraded already (loading again is answered the loaded version), gmt-2 is gone.
    gmt = Path(sys.executable).parent / "gmt"
    env = clean_env()
    out = subprocess.run(
        [str(gmt), "cluster", "upgrade", str(root / "releases" / "v2"), "--run-dir", str(c.run_dir)],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert out.returncode == 1, out.stderr
    assert f"gmt-1: load {v2}" in out.stdout and "gmt-1: drain nothing to drain" in out.stdout
    assert out.stdout.startswith(f"cluster {c.run_dir}: gmt-1 http://127.0.0.1:"), (
        out.stdout
    )  # what it acts on
    assert "error: gmt-2 not upgraded: unavailable: cannot reach" in out.stderr
