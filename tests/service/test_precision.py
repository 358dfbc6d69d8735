"""`gmt serve --precision bf16`: the served answers are the bf16 engine's; models the native step does not serve stay
fp32 beside them; a version restored after a restart keeps bf16 (the refusals: test_serve_cli.py)."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from service_harness import RunningServer, make_settings

from gmt.model import native
from gmt.model.checkpoint import load_checkpoint
from gmt.model.engine import PolicyEngine
from gmt.model.fixtures import tiny_checkpoint


@pytest.mark.skipif(
    not native.has_bf16(), reason="this CPU has no AVX-512 BF16: the bfloat16 products are not built"
)
def test_a_bf16_server_answers_what_a_bf16_engine_answers(tmp_path):
    ckpt_dir = tmp_path / "tiny-window"
    tiny_checkpoint(ckpt_dir, name="tiny-window", attention="window", seed=4)
    ckpt = load_checkpoint(ckpt_dir)
    engines = {p: PolicyEngine(ckpt, precision=p) for p in ("bf16", "fp32")}
    twins = {p: e.new_context(2, "mean", seed=9) for p, e in engines.items()}
    server = RunningServer(make_settings(checkpoints=[ckpt_dir], precision="bf16")).start()
    try:
        with httpx.Client(base_url=server.url, timeout=30) as http:
            r = http.post(
                "/sessions", json={"model": "tiny-window", "goal": 2, "seed": 9, "action_mode": "mean"}
            )
            r.raise_for_status()
            sid = r.json()["session_id"]
            rng = np.random.default_rng(3)
            apart = 0.0
            for _ in range(12):
                obs = rng.normal(size=ckpt.config.obs_shape).astype(np.float32)
                r = http.post(f"/sessions/{sid}/act", json={"observation": obs.tolist()})
                r.raise_for_status()
                served = np.asarray(r.json()["action"], np.float32)
                want = {
                    p: e.act([twins[p]], [e.prepare_observation(obs)], True)[0] for p, e in engines.items()
                }
                np.testing.assert_array_equal(served, want["bf16"])
                apart = max(apart, float(np.abs(served - want["fp32"]).max()))
            assert apart > 0  # not the fp32 answers
    finally:
        server.stop()


@pytest.mark.skipif(
    not native.has_bf16(), reason="this CPU has no AVX-512 BF16: the bfloat16 products are not built"
)
def test_models_the_native_step_does_not_serve_stay_fp32_and_a_restored_version_keeps_bf16(tmp_path):
    """On a bf16 server a full-attention model loads (in fp32, as it would anywhere) instead of being refused; a
    version promoted before a restart comes back in bf16 like the versions found at start."""
    roots = tmp_path / "checkpoints"
    tiny_checkpoint(roots / "tiny-window", name="tiny-window", attention="window", seed=4)
    tiny_checkpoint(roots / "releases" / "v2", name="tiny-window", attention="window", seed=5)
    tiny_checkpoint(roots / "tiny-full", name="tiny-full", seed=6)  # full attention: no native step
    settings = make_settings(checkpoints=[roots], precision="bf16")
    first = RunningServer(settings).start()
    try:
        precision = {m.name: m.engine.precision for m in first.core.registry.models.values()}
        assert precision == {"tiny-window": "bf16", "tiny-full": "fp32"}
        with httpx.Client(base_url=first.url, timeout=60) as http:
            r = http.post("/models/tiny-window/versions", json={"path": "releases/v2"})
            assert r.status_code == 201, r.text
            v2 = r.json()["version"]
            assert http.put("/models/tiny-window/default", json={"version": v2}).status_code == 200
    finally:
        first.stop()
    again = RunningServer(settings).start()
    try:
        restored = again.core.registry.find("tiny-window", v2)
        assert restored is not None and restored.engine.precision == "bf16"
    finally:
        again.stop()
