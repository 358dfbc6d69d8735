"""Model benchmarks: training steps/s (fp32 vs bf16) and engine act throughput by batch size. Prints JSON.

Usage: python benchmarks/bench_model.py [--threads 2] [--steps 30]
Runs on a random-weight model of the default size (3 layers, 128 wide, K = 20) with HalfCheetah-v5 shapes.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from model.checkpoint import Checkpoint
from model.config import GMTConfig, TrainConfig
from model.engine import PolicyEngine
from model.fixtures import tiny_checkpoint
from model.gmt import GMT
from model.losses import gmt_loss
from model.masking import mask_goals
from model.train import make_optimizer


def train_steps_per_s(bf16: bool, steps: int, batch: int = 64) -> float:
    cfg = GMTConfig(obs_shape=(17,), act_dim=6, discrete_actions=False, n_goals=4)
    model = GMT(cfg).train()
    opt = make_optimizer(model, TrainConfig())
    g = torch.Generator().manual_seed(0)
    B, K = batch, cfg.context_length
    goals, states = torch.randint(0, 4, (B, K), generator=g), torch.randn(B, K, 17, generator=g)
    actions, ts = torch.rand(B, K, 6, generator=g) * 2 - 1, torch.arange(K).repeat(B, 1)
    valid = torch.ones(B, K, dtype=torch.bool)
    t0 = 0.0
    for i in range(steps + 5):
        if i == 5:
            t0 = time.perf_counter()
        gin = mask_goals(goals, valid, "token", 0.5, cfg.mask_token, g)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            pred, gl = model(gin, states, actions, ts, valid)
        loss = gmt_loss(pred, gl, actions, goals, valid, False).total
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return steps / (time.perf_counter() - t0)


def engine_throughput(batch: int, steps: int) -> dict:
    small = tiny_checkpoint()
    cfg = GMTConfig(obs_shape=(17,), act_dim=6, discrete_actions=False, n_goals=3)
    ckpt = Checkpoint(**{**small.__dict__, "model": GMT(cfg).eval()})
    engine = PolicyEngine(ckpt)
    ctxs = [engine.new_context(i % 3) for i in range(batch)]
    obs = list(np.random.default_rng(0).normal(size=(batch, 17)))
    for _ in range(cfg.context_length):  # fill the contexts: steady-state cost
        engine.act(ctxs, obs)
    t0 = time.perf_counter()
    for _ in range(steps):
        engine.act(ctxs, obs)
    dt = (time.perf_counter() - t0) / steps
    per_ctx = sum(
        a.nbytes
        for a in (
            ctxs[0].goals,
            ctxs[0].blend_to,
            ctxs[0].blend_w,
            ctxs[0].states,
            ctxs[0].actions,
            ctxs[0].timesteps,
        )
    )
    return {
        "batch": batch,
        "ms_per_batch": round(dt * 1e3, 3),
        "actions_per_s": round(batch / dt, 1),
        "context_bytes": per_ctx,
    }


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--steps", type=int, default=30)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    out = {
        "threads": args.threads,
        "train_steps_per_s": {
            "fp32": round(train_steps_per_s(False, args.steps), 2),
            "bf16": round(train_steps_per_s(True, args.steps), 2),
        },
        "engine": [engine_throughput(b, max(5, args.steps)) for b in (1, 16, 64, 256)],
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
