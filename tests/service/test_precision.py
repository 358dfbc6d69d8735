"""`gmt serve --precision bf16`: the served answers are the bf16 engine's, and a server that cannot run it says so."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
from service_harness import RunningServer, clean_env, make_settings

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


def test_serve_refuses_bf16_without_the_native_step_before_loading_anything(tmp_path):
    gmt = str(Path(sys.executable).parent / "gmt")
    args = [
        gmt,
        "serve",
        "--checkpoints",
        str(tmp_path),
        "--precision",
        "bf16",
        "--rest-port",
        "0",
        "--grpc-port",
        "0",
    ]
    done = subprocess.run(
        args, capture_output=True, text=True, env=clean_env(GMT_NATIVE="0", COLUMNS="300"), timeout=60
    )
    assert done.returncode == 2 and "AVX-512 BF16" in done.stderr and "--precision" in done.stderr, (
        done.stderr
    )
