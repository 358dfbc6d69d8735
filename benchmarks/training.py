"""`gmt bench --sections training`: optimiser steps/s of the default model and batch, and the GFLOP/s achieved
beside the measured matrix-product rate.
"""

from __future__ import annotations

import time

from gmt.bench.harness import ACT_DIM, OBS_DIM


def gemm_gflops(dtype) -> float:
    """Measured matrix-product rate of one thread (1024 x 1024 x 1024)."""
    import torch

    a, b = torch.randn(1024, 1024, dtype=dtype), torch.randn(1024, 1024, dtype=dtype)
    for _ in range(3):
        a @ b
    n, t0 = 10, time.perf_counter()
    for _ in range(n):
        a @ b
    return round(2 * 1024**3 * n / (time.perf_counter() - t0) / 1e9, 1)


def bench_training(steps: int = 20) -> dict:
    """Optimiser steps/s of the default model and batch (K = 20, batch 64) on one thread, and GFLOP/s."""
    import torch

    from gmt.model.config import GMTConfig
    from gmt.model.gmt import GMT

    torch.set_num_threads(1)
    cfg = GMTConfig(obs_shape=(OBS_DIM,), act_dim=ACT_DIM, discrete_actions=False, n_goals=4)
    model = GMT(cfg)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    B, T = 64, cfg.context_length
    g = torch.randint(0, 4, (B, T))
    s, a = torch.randn(B, T, OBS_DIM), torch.rand(B, T, ACT_DIM) * 2 - 1
    ts, v = torch.arange(T).repeat(B, 1), torch.ones(B, T, dtype=torch.bool)
    for i in range(steps + 3):
        if i == 3:
            t0 = time.perf_counter()
        pred, gl = model(g, s, a, ts, v)
        loss = (pred - a).pow(2).mean() + gl.logsumexp(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    sps = steps / (time.perf_counter() - t0)
    matmul_params = sum(p.numel() for n, p in model.named_parameters() if p.dim() == 2 and "emb" not in n)
    flops = 6 * matmul_params * B * 3 * T  # forward + backward of every token's matrix products
    return {
        "steps_per_s": round(sps, 2),
        "gflops_achieved": round(flops * sps / 1e9, 1),
        "gemm_gflops": {"fp32": gemm_gflops(torch.float32), "bf16": gemm_gflops(torch.bfloat16)},
        "note": "achieved counts only the matrix products (6 x params x tokens), not attention",
    }
