"""`gmt bench --sections device`: a checkpoint's engine and server on a device (`gmt serve --device`) against the
default CPU path, same checkpoint, same run.

- `engine`: ms per act step in process, at each batch, of the default engine (the native step on the CPU, one
  torch thread) and of the device engine (the batched torch step, its key/value pool on the device), after a
  full history of warm-up.
- `served`: two `gmt serve` processes up at once, the default and `--device`, each with `sessions` sessions:
  `POST /act` (every session's observation in one call, one connection) at each count, and REST one call per act
  (one connection per session) up to 256 sessions, in alternating rounds; the device server's `GMT_MAX_BATCH` is
  the largest count, so a batch is never split.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from gmt.bench import harness
from gmt.bench.store import over_rounds

REST_UP_TO = 256  # one connection per session beyond this measures wrk and the accept queue, not the server


def _engine_rows(checkpoint: Path, batches: tuple[int, ...], device: str, steps: int) -> list[dict]:
    import torch

    from gmt.model.checkpoint import load_checkpoint
    from gmt.model.engine import PolicyEngine

    torch.set_num_threads(1)
    rows = []
    for path, kwargs in (
        ("default", {}),
        ("device", {"device": device, "native": False, "n_slots": max(batches)}),
    ):
        ckpt = load_checkpoint(checkpoint)  # its own copy: an engine moves the model to its device
        engine = PolicyEngine(ckpt, **kwargs)
        kernel = engine.describe().kernel
        obs_one = np.asarray(_observation(ckpt), dtype=np.float32)
        for B in batches:
            ctxs = [engine.new_context(i % engine.n_goals, seed=i) for i in range(B)]
            states = [engine.prepare_observation(obs_one) for _ in range(B)]
            for _ in range(engine.K + 2):  # a full ring, so every step attends over K steps
                engine.act(ctxs, states, prepared=True)
            n = max(3, steps // (1 + B // 256))
            t0 = time.perf_counter()
            for _ in range(n):
                engine.act(ctxs, states, prepared=True)  # answers come back to the host: the step is complete
            ms = (time.perf_counter() - t0) / n * 1000
            for c in ctxs:
                engine.release(c)
            rows.append(
                {
                    "path": path,
                    "device": kwargs.get("device", "cpu"),
                    "kernel": kernel,
                    "batch": B,
                    "ms_per_step": round(ms, 3),
                    "acts_per_s": round(B / ms * 1000),
                }
            )
            print(
                f"[bench] engine {path} ({kernel}) batch {B}: {ms:.3f} ms, {rows[-1]['acts_per_s']}/s",
                file=sys.stderr,
            )
        del engine
    return rows


def _observation(ckpt) -> list:
    """One fixed observation of the checkpoint's shape (bytes in 0..255 for image models)."""
    x = np.random.default_rng(0).normal(size=tuple(ckpt.config.obs_shape))
    if ckpt.observation_space.get("dtype") == "uint8":
        return np.abs(x * 64).clip(0, 255).astype(np.uint8).tolist()
    return [round(float(v), 4) for v in x * 0.1]


def bench_device(
    checkpoint: Path,
    sessions: tuple[int, ...] = (1, 16, 64, 256),
    seconds: float = 8.0,
    device: str = "auto",
    rounds: int = 2,
    steps: int = 40,
) -> dict:
    """The engine and the server on `device` against the default CPU path, same checkpoint, same run.

    Returns `engine` (rows per device and batch), `served` ({cpu | device: {rest_batch | rest: [{sessions,
    acts_per_s, p50_ms, p99_ms, errors, rounds}]}}) and `device_vs_cpu` (acts/s ratios per load and count, and the
    one-session p50 ratio).
    """
    import torch

    from gmt.model.checkpoint import load_checkpoint
    from gmt.model.engine import resolve_device

    device = resolve_device(device)
    ckpt = load_checkpoint(checkpoint)
    out: dict = {
        "model": ckpt.name,
        "device": device,
        "device_name": torch.cuda.get_device_name(device) if device.startswith("cuda") else "cpu",
        "sessions": list(sessions),
        "seconds_per_point": seconds,
        "rounds": rounds,
        "engine": _engine_rows(checkpoint, tuple(sessions), device, steps),
    }
    obs = _observation(ckpt)
    del ckpt
    top = max(sessions)
    body = len(json.dumps({"session_id": "x" * 40, "observation": obs}))  # an item of `POST /act`, roughly
    big = ("--max-request-bytes", str(max(1 << 20, 2 * body * top)))
    servers = {
        "cpu": harness.start_server(checkpoint, naive=False, extra=big),
        "device": harness.start_server(
            checkpoint, naive=False, max_batch=top, extra=(*big, "--device", device)
        ),
    }
    served: dict = {name: {"rest_batch": [], "rest": []} for name in servers}
    try:
        at = {
            n: (f"http://127.0.0.1:{info['rest_port']}", info["models"][0])
            for n, (_, info) in servers.items()
        }
        for count in sessions:
            sids = {n: harness.open_sessions(url, model, count) for n, (url, model) in at.items()}
            loads = ["rest_batch", *(["rest"] if count <= REST_UP_TO else [])]
            per: dict = {(n, load): [] for n in servers for load in loads}
            for r in range(rounds):
                order = list(servers) if r % 2 == 0 else list(reversed(servers))
                for load in loads:
                    for n in order:
                        url = at[n][0]
                        fn = harness.bench_rest_batch if load == "rest_batch" else harness.bench_rest
                        per[n, load].append(fn(url, sids[n], seconds / rounds, observation=obs))
            for (n, load), rows in per.items():
                served[n][load].append(over_rounds(rows))
            for n, (url, _) in at.items():
                harness.close_sessions(url, sids[n])
            print(
                f"[bench] served {count} sessions: "
                + ", ".join(
                    f"{n} {load} {served[n][load][-1]['acts_per_s']}/s" for n in servers for load in loads
                ),
                file=sys.stderr,
            )
    finally:
        for proc, _ in servers.values():
            proc.terminate()
            proc.wait(30)
    out["served"] = served
    ratios: dict = {}
    for load in ("rest_batch", "rest"):
        ratios[load] = {
            str(c["sessions"]): round(d["acts_per_s"] / c["acts_per_s"], 3) if c["acts_per_s"] else None
            for c, d in zip(served["cpu"][load], served["device"][load], strict=True)
        }
    one = [
        (c, d)
        for c, d in zip(served["cpu"]["rest"], served["device"]["rest"], strict=True)
        if c["sessions"] == 1
    ]
    if one:
        ratios["p50_1_session"] = round(one[0][1]["p50_ms"] / one[0][0]["p50_ms"], 3)
    out["device_vs_cpu"] = ratios
    return out
