"""`--precision bf16` against fp32 on the shipped HalfCheetah model: two servers up at once, rounds alternated (one
session's Control-stream and REST p50, 256 sessions over REST and `POST /act`), then the bf16 engine's actions along
the fp32 policy's own episodes (the largest difference per step).

Run from the repository root: `python -m research.precision [ROUNDS]` (docs/performance.md, "bf16 products").
"""

import json
import statistics
import sys
from pathlib import Path

import numpy as np

from gmt.bench.harness import bench_rest, bench_rest_batch, grpc_load, open_sessions, start_server

CHECKPOINT = Path("checkpoints/halfcheetah-gmt")


def served(rounds: int) -> dict:
    servers = {}
    try:
        for p in ("fp32", "bf16"):
            proc, info = start_server(CHECKPOINT, naive=False, extra=("--precision", p))
            url, model = f"http://127.0.0.1:{info['rest_port']}", info["models"][0]
            target = f"127.0.0.1:{info['grpc_port']}"
            servers[p] = (proc, url, target, open_sessions(url, model, 1), open_sessions(url, model, 256))
        out: dict = {p: {} for p in servers}
        for r in range(rounds):
            for p, (_, url, target, one, many) in servers.items():
                figures = {
                    "control_p50_ms": grpc_load(target, one, 4, "stream")["p50_ms"],
                    "rest_1_session_p50_ms": bench_rest(url, one, 3)["p50_ms"],
                    "rest_256_acts_per_s": bench_rest(url, many, 4)["acts_per_s"],
                    "post_act_256_acts_per_s": bench_rest_batch(url, many, 4)["acts_per_s"],
                }
                for k, v in figures.items():
                    out[p].setdefault(k, []).append(v)
            print(r, json.dumps({p: {k: v[-1] for k, v in f.items()} for p, f in out.items()}), flush=True)
        return out
    finally:
        for proc, *_ in servers.values():
            proc.terminate()


def along_episodes(steps: int = 1000) -> dict:
    import gymnasium as gym
    import torch

    from gmt.model.checkpoint import load_checkpoint
    from gmt.model.engine import PolicyEngine

    torch.set_num_threads(1)
    ckpt = load_checkpoint(CHECKPOINT)
    engines = {p: PolicyEngine(ckpt, precision=p) for p in ("fp32", "bf16")}
    out = {}
    for g in range(len(ckpt.goals)):
        env = gym.make(ckpt.env_id, max_episode_steps=steps)
        obs, _ = env.reset(seed=g)
        ctxs = {p: e.new_context(g, "mean", seed=g) for p, e in engines.items()}
        diffs = []
        for _ in range(steps):
            a = {
                p: np.asarray(e.act([ctxs[p]], [e.prepare_observation(obs)], True)[0])
                for p, e in engines.items()
            }
            diffs.append(float(np.abs(a["fp32"] - a["bf16"]).max()))
            obs, _, terminated, truncated, _ = env.step(a["fp32"])  # the fp32 policy drives
            if terminated or truncated:
                break
        d = np.array(diffs)
        out[f"goal {g}"] = {
            "median": float(np.median(d)),
            "p99": float(np.quantile(d, 0.99)),
            "max": float(d.max()),
        }
    return out


if __name__ == "__main__":
    figures = served(int(sys.argv[1]) if len(sys.argv) > 1 else 3)
    medians = {p: {k: statistics.median(v) for k, v in f.items()} for p, f in figures.items()}
    print(
        json.dumps(
            {"served": figures, "medians": medians, "actions_along_episodes": along_episodes()}, indent=1
        )
    )
