"""`gmt bench --sections engine`: ms per act step of the engine against K, on every path, one torch thread."""

from __future__ import annotations

import time

import numpy as np

from gmt.bench.harness import OBS_DIM, default_size_checkpoint


def bench_engine(Ks=(10, 20, 50, 100), batches=(1, 64), steps: int = 60) -> list[dict]:
    """ms per act step on the incremental and the recompute path, after a full history of warm-up; the native
    step with bf16 products too (`incremental_bf16`) where this CPU has them."""
    import torch

    from gmt.model import native as native_kernel
    from gmt.model.engine import PolicyEngine

    torch.set_num_threads(1)
    rows = []
    for K in Ks:
        ckpt = default_size_checkpoint(None, K=K)
        paths = [("incremental", True, None, "fp32"), ("incremental_torch", True, False, "fp32")]
        paths += [("incremental_bf16", True, None, "bf16")] if native_kernel.has_bf16() else []
        paths += [("recompute", False, None, "fp32")]
        for path, incremental, native, precision in paths:
            for B in batches:
                engine = PolicyEngine(ckpt, incremental=incremental, native=native, precision=precision)
                ctxs = [engine.new_context(i % 3, seed=i) for i in range(B)]
                obs = np.random.default_rng(0).normal(size=(B, OBS_DIM)).astype(np.float32)
                states = [engine.prepare_observation(o) for o in obs]
                # The recompute runs a fixed shape whatever the fill (a left-padded window of the whole receptive
                # field), so a short warm-up measures it at a full history; the native step scores only the
                # ring positions a token sees, so the incremental paths first fill the ring (K + 1 steps).
                warm = K + 2 if incremental else 3
                n = max(3, steps // (1 + (B * K) // 320)) if not incremental else steps
                for _ in range(warm):
                    engine.act(ctxs, states, prepared=True)
                t0 = time.perf_counter()
                for _ in range(n):
                    engine.act(ctxs, states, prepared=True)
                ms = (time.perf_counter() - t0) / n * 1000
                rows.append(
                    {
                        "K": K,
                        "path": path,
                        "batch": B,
                        "ms_per_step": round(ms, 3),
                        "acts_per_s": round(B / ms * 1000),
                    }
                )
    return rows
