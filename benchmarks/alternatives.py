"""`gmt bench --sections alternatives`: what a user would deploy instead, when installed (the `bench` extra): the
same checkpoint behind Ray Serve (`gmt.bench.ray_app`), and the training speed of Hugging Face's
`DecisionTransformerModel` of the default size.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

from gmt.bench.harness import ACT_DIM, OBS_DIM, SESSIONS, bench_rest, open_sessions


def start_ray_serve(checkpoint: Path, path: str) -> tuple[subprocess.Popen, str]:
    """`gmt.bench.ray_app` in its own process on a free loopback port; returns (process, base URL)."""
    from gmt.cluster.supervisor import free_port

    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "gmt.bench.ray_app", str(checkpoint), str(port), path],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    for line in proc.stdout:
        if line.startswith("READY"):
            return proc, f"http://127.0.0.1:{port}"
    raise RuntimeError("the Ray Serve deployment exited before serving")


def bench_ray_serve(checkpoint: Path, sessions=SESSIONS, seconds: float = 8.0) -> dict:
    """Acts/s of the same checkpoint behind Ray Serve (`@serve.batch`), one wrk connection per session."""
    out: dict = {"model": str(checkpoint), "seconds_per_point": seconds}
    for path in ("recompute", "incremental"):
        proc, url = start_ray_serve(checkpoint, path)
        try:
            rows = []
            for n in sessions:
                sids = open_sessions(url, "gmt", n)
                rows.append(bench_rest(url, sids, seconds))
                print(f"[bench] ray serve ({path}) {n} sessions: {rows[-1]['acts_per_s']}/s", file=sys.stderr)
            out[path] = rows
        finally:
            proc.stdin.close()
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
    return out


def bench_hf_decision_transformer(steps: int = 20) -> dict:
    """Training steps/s of Hugging Face's DecisionTransformerModel of the default size (as `bench_training`)."""
    import torch
    from transformers import DecisionTransformerConfig, DecisionTransformerModel

    torch.set_num_threads(1)
    torch.manual_seed(0)
    B, T = 64, 20
    cfg = DecisionTransformerConfig(
        state_dim=OBS_DIM,
        act_dim=ACT_DIM,
        hidden_size=128,
        n_layer=3,
        n_head=1,
        n_inner=512,
        max_ep_len=1024,
        resid_pdrop=0.0,
        embd_pdrop=0.0,
        attn_pdrop=0.0,
        bos_token_id=0,  # GPT-2's 50256 lies outside this model's one-entry vocabulary
        eos_token_id=0,
    )
    model = DecisionTransformerModel(cfg)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    s, a = torch.randn(B, T, OBS_DIM), torch.rand(B, T, ACT_DIM) * 2 - 1
    r, rtg = torch.randn(B, T, 1), torch.randn(B, T, 1)
    ts, mask = torch.arange(T).repeat(B, 1), torch.ones(B, T, dtype=torch.long)
    for i in range(steps + 3):
        if i == 3:
            t0 = time.perf_counter()
        out = model(states=s, actions=a, rewards=r, returns_to_go=rtg, timesteps=ts, attention_mask=mask)
        loss = (out.action_preds - a).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return {
        "steps_per_s": round(steps / (time.perf_counter() - t0), 2),
        "params": sum(p.numel() for p in model.parameters()),
        "config": "hidden 128, 3 layers, 1 head, batch 64 x K 20, one thread, dropout 0",
    }


def bench_alternatives(checkpoint: Path, sessions=SESSIONS, seconds: float = 8.0) -> dict:
    """Ray Serve and Hugging Face's DecisionTransformerModel, when installed (the `bench` extra)."""
    out: dict = {}
    for name, module in (("ray_serve", "ray.serve"), ("hf_decision_transformer", "transformers")):
        try:
            __import__(module)
        except ImportError:
            out[name] = {"skipped": f"{module} is not installed (pip install '.[bench]')"}
    if "ray_serve" not in out:
        if shutil.which("wrk") is None:
            out["ray_serve"] = {"skipped": "wrk is not installed (apt-get install wrk)"}
        else:
            try:
                out["ray_serve"] = bench_ray_serve(checkpoint, sessions, seconds)
            except Exception as e:  # Ray could not start here: say why instead of failing the whole run
                out["ray_serve"] = {"skipped": f"Ray Serve did not run: {type(e).__name__}: {e}"}
    if "hf_decision_transformer" not in out:
        out["hf_decision_transformer"] = bench_hf_decision_transformer()
    return out
