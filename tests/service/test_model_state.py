"""A promoted version survives a restart (docs/models.md, "After a restart"): one server keeps each model's default
and canary in a file beside its checkpoint roots, replicas sharing Redis keep them in the store; a restarted
server loads and serves them again."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from service_harness import clean_env

from gmt.model.checkpoint import load_checkpoint
from gmt.model.fixtures import tiny_checkpoint
from gmt.service.model_state import STATE_FILE

MODEL = "tiny-gmt"
GMT = str(Path(sys.executable).parent / "gmt")


@pytest.fixture
def roots(tmp_path):
    """checkpoints/ serving tiny-gmt v1, with two releases of it one level down (not served at start)."""
    root = tmp_path / "checkpoints"
    tiny_checkpoint(root / MODEL, seed=0)
    tiny_checkpoint(root / "releases" / "v2", seed=1)
    tiny_checkpoint(root / "releases" / "v3", seed=2)
    return root


def version(root: Path, sub: str) -> str:
    return load_checkpoint(root / sub).version


def model(url: str) -> tuple[dict, str]:
    """tiny-gmt's entry of `GET /models`, and where the server keeps model state."""
    body = httpx.get(f"{url}/models", timeout=30).json()
    (m,) = [m for m in body["models"] if m["name"] == MODEL]
    return m, body["model_state"]


def rollout(url: str) -> None:
    """Load v2 and v3, promote v2, make v3 a 25% canary."""
    with httpx.Client(base_url=url, timeout=60) as http:
        for sub in ("releases/v2", "releases/v3"):
            assert http.post(f"/models/{MODEL}/versions", json={"path": sub}).status_code == 201
        v2, v3 = [v["version"] for v in model(url)[0]["versions"][1:]]
        assert http.put(f"/models/{MODEL}/default", json={"version": v2}).status_code == 200
        assert http.put(f"/models/{MODEL}/default", json={"version": v3, "share": 0.25}).status_code == 200


def test_a_promotion_survives_a_restart_of_one_server(make_server, roots):
    v1, v2, v3 = version(roots, MODEL), version(roots, "releases/v2"), version(roots, "releases/v3")
    first = make_server(checkpoints=[roots])
    assert model(first.url)[0]["default_version"] == v1
    rollout(first.url)
    first.stop()
    saved = json.loads((roots / STATE_FILE).read_text())["models"][MODEL]
    assert (saved["default"]["version"], saved["canary"]["version"], saved["canary"]["share"]) == (
        v2,
        v3,
        0.25,
    )

    again = make_server(checkpoints=[roots])
    m, where = model(again.url)
    assert where == "file"
    assert (m["default_version"], m["canary"]) == (v2, {"version": v3, "share": 0.25})
    assert {v["version"] for v in m["versions"]} == {v1, v2, v3}
    r = httpx.post(
        f"{again.url}/sessions", json={"model": MODEL, "goal": 0, "session_id": "s" * 12}, timeout=30
    )
    assert r.status_code == 201 and r.json()["model_version"] in (v2, v3)
    out = subprocess.run(
        [GMT, "models", "list", "--server", again.url],
        capture_output=True,
        text=True,
        env=clean_env(),
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert f"{v2}" in out.stdout and "default" in out.stdout and "kept across restarts" in out.stdout


def test_a_drained_canary_and_an_unloaded_model_are_forgotten(make_server, roots):
    v1, v3 = version(roots, MODEL), version(roots, "releases/v3")
    first = make_server(checkpoints=[roots])
    rollout(first.url)
    assert httpx.post(f"{first.url}/models/{MODEL}/versions/{v3}/drain", timeout=30).status_code == 200
    assert (
        httpx.put(f"{first.url}/models/{MODEL}/default", json={"version": v1}, timeout=30).status_code == 200
    )
    first.stop()
    again = make_server(checkpoints=[roots])
    m, _ = model(again.url)
    assert (m["default_version"], m["canary"]) == (v1, None)


def test_a_saved_version_whose_checkpoint_is_gone_leaves_the_one_found_at_start(make_server, roots, caplog):
    v1 = version(roots, MODEL)
    first = make_server(checkpoints=[roots])
    rollout(first.url)
    first.stop()
    for sub in ("releases/v2", "releases/v3"):
        for f in (roots / sub).iterdir():
            f.unlink()
        (roots / sub).rmdir()
    with caplog.at_level(logging.ERROR, logger="gmt.model_state"):
        again = make_server(checkpoints=[roots])
    assert model(again.url)[0]["default_version"] == v1
    assert any("no checkpoint of version" in getattr(r, "error", "") for r in caplog.records)


def test_a_restarted_replica_serves_what_the_cluster_promoted(make_server, roots, redis_clean):
    """Two replicas share Redis: the one that promoted stops, a new one starts and serves the promoted default
    (from the store: no state file is written)."""
    v2, v3 = version(roots, "releases/v2"), version(roots, "releases/v3")
    a = make_server(checkpoints=[roots], redis_url=redis_clean)
    rollout(a.url)
    a.stop()
    assert not (roots / STATE_FILE).exists()
    b = make_server(checkpoints=[roots], redis_url=redis_clean)
    m, where = model(b.url)
    assert where == "redis"
    assert (m["default_version"], m["canary"]) == (v2, {"version": v3, "share": 0.25})


def test_a_server_on_one_checkpoint_directory_keeps_no_state(make_server, roots):
    """A root that is itself a checkpoint directory is never written to: nothing is kept, and `GET /models` says so."""
    server = make_server(checkpoints=[roots / MODEL])
    assert model(server.url)[1] == "off"
    r = httpx.put(f"{server.url}/models/{MODEL}/default", json={"version": version(roots, MODEL)}, timeout=30)
    assert (
        r.status_code == 200
        and not (roots / STATE_FILE).exists()
        and not (roots / MODEL / STATE_FILE).exists()
    )
