"""Act latency of one session over REST, unary gRPC and the gRPC Control stream. Prints JSON.

Usage: python benchmarks/bench_serve.py [--steps 500] [--checkpoint checkpoints/halfcheetah-gmt ...]

Starts `gmt serve` in a subprocess (so that client and server do not share a GIL) on free loopback ports,
serving a tiny random-weight checkpoint (K = 5, 2 layers, 32 wide), a random-weight checkpoint of the default
training size (K = 20, 3 layers, 128 wide), and every checkpoint given, all with HalfCheetah-v5 shapes.
Latency is client-side wall time per act, after a warm-up; the server runs one inference thread.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import grpc
import httpx
import numpy as np
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc


def make_checkpoints(root: Path) -> None:
    """tiny-gmt and default-size-gmt (random weights) under `root`."""
    import torch

    from model.checkpoint import save_checkpoint
    from model.config import GMTConfig
    from model.fixtures import tiny_checkpoint
    from model.gmt import GMT

    tiny = tiny_checkpoint(root / "tiny-gmt")
    torch.manual_seed(0)
    cfg = GMTConfig(obs_shape=(17,), act_dim=6, discrete_actions=False, n_goals=3)  # the training defaults
    tiny.model, tiny.name = GMT(cfg).eval(), "default-size-gmt"
    save_checkpoint(tiny, root / "default-size-gmt")


def start_server(checkpoint_dirs: list[Path]) -> tuple[subprocess.Popen, dict]:
    exe = Path(sys.executable).parent / "gmt"
    args = [str(exe), "serve", "--rest-port", "0", "--grpc-port", "0", "--log-format", "json"]
    for d in checkpoint_dirs:
        args += ["--checkpoints", str(d)]
    env = {k: v for k, v in os.environ.items() if not k.startswith("GMT_")}
    proc = subprocess.Popen(args, stderr=subprocess.PIPE, text=True, env=env)
    for line in proc.stderr:
        rec = json.loads(line) if line.startswith("{") else {}
        if rec.get("msg") == "serving":
            threading.Thread(target=lambda: [None for _ in proc.stderr], daemon=True).start()  # keep draining
            return proc, rec
    raise RuntimeError("gmt serve exited before serving")


def summary(seconds: list[float]) -> dict:
    ms = np.asarray(seconds) * 1000.0
    return {
        "n": len(ms),
        "p50_ms": round(float(np.percentile(ms, 50)), 3),
        "p99_ms": round(float(np.percentile(ms, 99)), 3),
        "mean_ms": round(float(ms.mean()), 3),
    }


def bench_rest(url: str, model: str, obs: np.ndarray, warmup: int) -> dict:
    with httpx.Client(base_url=url, timeout=30) as c:
        sid = c.post("/sessions", json={"model": model, "goal": 0}).json()["session_id"]
        times = []
        for i, o in enumerate(obs):
            body = {"observation": o.tolist()}
            t = time.perf_counter()
            r = c.post(f"/sessions/{sid}/act", json=body)
            dt = time.perf_counter() - t
            r.raise_for_status()
            if i >= warmup:
                times.append(dt)
        c.delete(f"/sessions/{sid}")
    return summary(times)


def bench_grpc_unary(stub, model: str, obs: np.ndarray, warmup: int) -> dict:
    sid = stub.CreateSession(pb.CreateSessionRequest(model=model, goal=pb.GoalSelector(id=0))).session_id
    times = []
    for i, o in enumerate(obs):
        req = pb.ActRequest(session_id=sid, values=pb.FloatVector(values=o))
        t = time.perf_counter()
        stub.Act(req)
        dt = time.perf_counter() - t
        if i >= warmup:
            times.append(dt)
    stub.CloseSession(pb.CloseSessionRequest(session_id=sid))
    return summary(times)


def bench_grpc_stream(stub, model: str, obs: np.ndarray, warmup: int) -> dict:
    sid = stub.CreateSession(pb.CreateSessionRequest(model=model, goal=pb.GoalSelector(id=0))).session_id
    q: queue.Queue = queue.Queue()

    def commands():
        while (item := q.get()) is not None:
            yield item

    answers = stub.Control(commands())
    times = []
    for i, o in enumerate(obs):
        req = pb.ControlRequest(act=pb.ActRequest(session_id=sid, values=pb.FloatVector(values=o)))
        t = time.perf_counter()
        q.put(req)
        r = next(answers)
        dt = time.perf_counter() - t
        assert r.WhichOneof("result") == "act", r
        if i >= warmup:
            times.append(dt)
    q.put(None)
    stub.CloseSession(pb.CloseSessionRequest(session_id=sid))
    return summary(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=500, help="Measured acts per transport and model.")
    p.add_argument("--warmup", type=int, default=50)
    p.add_argument(
        "--checkpoint", type=Path, action="append", default=[], help="Also benchmark this checkpoint."
    )
    args = p.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="gmt-bench-"))
    try:
        make_checkpoints(tmp)
        dirs = [tmp] + [c for c in args.checkpoint if (c / "gmt.json").is_file()]
        proc, info = start_server(dirs)
        try:
            url = f"http://127.0.0.1:{info['rest_port']}"
            obs = np.random.default_rng(0).normal(size=(args.steps + args.warmup, 17)).astype(np.float32)
            results = {}
            with grpc.insecure_channel(f"127.0.0.1:{info['grpc_port']}") as ch:
                stub = policy_pb2_grpc.PolicyServiceStub(ch)
                for model in info["models"]:
                    results[model] = {
                        "rest": bench_rest(url, model, obs, args.warmup),
                        "grpc_unary": bench_grpc_unary(stub, model, obs, args.warmup),
                        "grpc_stream": bench_grpc_stream(stub, model, obs, args.warmup),
                    }
        finally:
            proc.terminate()
            proc.wait(30)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(
        json.dumps(
            {
                "benchmark": "act latency, one session, client wall time",
                "machine": {
                    "cpu_count": os.cpu_count(),
                    "platform": platform.platform(),
                    "python": sys.version.split()[0],
                },
                "server": {"inference_threads": 1, "batch_wait_ms": 2.0, "max_batch": 64},
                "steps": args.steps,
                "models": results,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
