"""`gmt bench`: engine, serving and training figures as JSON, each beside the naive baseline of the same run.

Schema (top level): `machine` {cpu, cores, torch, platform, native_kernel}, `engine`, `serving`, `cluster`,
`failover`, `training`, `alternatives`.

- `engine`: [{K, path ("incremental" | "incremental_torch" | "recompute"), batch, ms_per_step, acts_per_s}] for
  a random-weight `window` model of the default size (3 layers, 128 wide, HalfCheetah shapes), one torch thread;
  `incremental` is the served path (the native kernel when it builds here), `incremental_torch` the same step
  in torch operations.
- `serving`: {model, servers: {naive | default: {rest | rest_batch | grpc_unary | grpc_stream: [{sessions,
  acts_per_s, p50_ms, p99_ms, errors}]}}, memory: {rss_per_session_bytes}}. REST load comes
  from wrk (one thread, one connection per session; `rest_batch` is one connection posting every session's
  observation to `POST /act`, p50/p99 per call); gRPC load from a separate client process.
- `cluster`: wrk's REST load through `gmt cluster` (nginx, two replicas, Redis with Sentinel): errors, latency,
  each replica's memory.
- `failover`: the Redis primary of `gmt cluster` killed under load (`gmt.service.failover`): {sessions, killed,
  promoted, resume_s, retried_answers (by kind), lost_sessions, sessions_unlike_twin, ...}.
- `training`: {steps_per_s, gflops_achieved, gemm_gflops: {fp32, bf16}} for the default model and batch.
- `store`: {stores: {memory | redis: {rest, rest_batch, rest_1_session}}, redis_vs_memory: {rest, rest_batch,
  p50_1_session_added_ms}}: the same server with sessions in memory and in a local redis-server, same run.
- `alternatives`: Ray Serve / Hugging Face Decision Transformer entries, or {"skipped": reason}.
"""

from __future__ import annotations

import asyncio
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

SESSIONS = (1, 16, 64, 256)
OBS_DIM, ACT_DIM = 17, 6


# ----- checkpoints ------------------------------------------------------------------------------------------
def default_size_checkpoint(directory: Path, K: int = 20, attention: str = "window", name: str = "bench-gmt"):
    """A random-weight checkpoint of the default training size with HalfCheetah-v5 shapes."""
    import torch

    from gmt.model.checkpoint import save_checkpoint
    from gmt.model.config import GMTConfig
    from gmt.model.fixtures import tiny_checkpoint
    from gmt.model.gmt import GMT

    ckpt = tiny_checkpoint(calibrated=True)
    torch.manual_seed(0)
    cfg = GMTConfig(
        obs_shape=(OBS_DIM,),
        act_dim=ACT_DIM,
        discrete_actions=False,
        n_goals=3,
        context_length=K,
        attention=attention,
    )
    ckpt.model, ckpt.name = GMT(cfg).eval(), name
    if directory is not None:
        save_checkpoint(ckpt, directory)
    return ckpt


# ----- engine -----------------------------------------------------------------------------------------------
def bench_engine(Ks=(10, 20, 50, 100), batches=(1, 64), steps: int = 60) -> list[dict]:
    """ms per act step on the incremental and the recompute path, after a full history of warm-up."""
    import torch

    from gmt.model.engine import PolicyEngine

    torch.set_num_threads(1)
    rows = []
    for K in Ks:
        ckpt = default_size_checkpoint(None, K=K)
        paths = (("incremental", True, None), ("incremental_torch", True, False), ("recompute", False, None))
        for path, incremental, native in paths:
            for B in batches:
                engine = PolicyEngine(ckpt, incremental=incremental, native=native)
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


# ----- serving ----------------------------------------------------------------------------------------------
def start_server(
    checkpoint: Path, naive: bool, max_batch: int = 256, extra: tuple[str, ...] = ()
) -> tuple[subprocess.Popen, dict]:
    """`gmt serve` in its own process on free loopback ports; returns (process, its 'serving' log record)."""
    exe = Path(sys.executable).parent / "gmt"
    args = [str(exe), "serve", "-c", str(checkpoint), "--rest-port", "0", "--grpc-port", "0"]
    args += ["--log-level", "INFO", "--max-batch", str(max_batch), "--max-sessions", "4096"]
    args += ["--naive"] if naive else []
    args += list(extra)
    env = {k: v for k, v in os.environ.items() if not k.startswith("GMT_")}
    env["GMT_LOG_LEVEL"] = "INFO"
    proc = subprocess.Popen(args, stderr=subprocess.PIPE, text=True, env=env)
    for line in proc.stderr:
        rec = json.loads(line) if line.startswith("{") else {}
        if rec.get("msg") == "serving":
            threading.Thread(target=lambda: [None for _ in proc.stderr], daemon=True).start()
            return proc, rec
    raise RuntimeError("gmt serve exited before serving")


def rss_bytes(pid: int) -> int:
    """Resident memory of a process."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


# Counts wrk's error kinds separately, and every non-2xx answer by status with the first such body, so that an
# error under load can be named (wrk copies the per-thread tables to `done` with thread:get).
_WRK_DONE = """
local threads = {}
setup = function(thread) table.insert(threads, thread) end
statuses = {}
first_body = ""
response = function(status, headers, body)
  if status >= 300 then
    statuses[status] = (statuses[status] or 0) + 1
    if first_body == "" then first_body = body end
  end
end
done = function(summary, latency, requests)
  local e = summary.errors
  local counts, body = {}, ""
  for _, t in ipairs(threads) do
    for k, v in pairs(t:get("statuses")) do table.insert(counts, string.format('"%d":%d', k, v)) end
    if body == "" then body = t:get("first_body") end
  end
  body = string.gsub(string.sub(body, 1, 300), '[%c"\\\\]', " ")
  io.write(string.format('WRK {"requests":%d,"duration_us":%d,"errors":%d,"non2xx":%d,"p50_us":%d,"p99_us":%d,' ..
    '"error_kinds":{"connect":%d,"read":%d,"write":%d,"timeout":%d},"statuses":{%s},"first_error_body":"%s"}\\n',
    summary.requests, summary.duration, e.connect + e.read + e.write + e.timeout, e.status,
    latency:percentile(50), latency:percentile(99), e.connect, e.read, e.write, e.timeout,
    table.concat(counts, ","), body))
end
"""


def wrk(url: str, script: str, connections: int, seconds: float) -> dict:
    """Run wrk (one thread) with a Lua script; returns its figures."""
    with tempfile.NamedTemporaryFile("w", suffix=".lua", delete=False) as f:
        f.write(script + _WRK_DONE)
    try:
        out = subprocess.run(
            [
                "wrk",
                "-t",
                "1",
                "-c",
                str(connections),
                "-d",
                f"{max(1, round(seconds))}s",  # wrk takes whole seconds
                "--timeout",
                "10s",
                "-s",
                f.name,
                url,
            ],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    finally:
        os.unlink(f.name)
    rec = json.loads(next(line[4:] for line in out.splitlines() if line.startswith("WRK ")))
    return rec


def _error_detail(r: dict) -> dict:
    """wrk's error kinds and non-2xx statuses, only when there were errors."""
    if not r["errors"] + r["non2xx"]:
        return {}
    return {
        "error_kinds": r["error_kinds"],
        "statuses": r["statuses"],
        "first_error_body": r["first_error_body"],
    }


def _sessions(url: str, model: str, n: int) -> list[str]:
    import httpx

    with httpx.Client(base_url=url, timeout=30) as c:
        return [
            c.post("/sessions", json={"model": model, "goal": i % 3, "seed": i}).json()["session_id"]
            for i in range(n)
        ]


def _close(url: str, sids: list[str]) -> None:
    import httpx

    with httpx.Client(base_url=url, timeout=30) as c:
        for s in sids:
            c.delete(f"/sessions/{s}")


def _obs_json() -> str:
    return json.dumps([round(float(x), 4) for x in np.random.default_rng(0).normal(size=OBS_DIM) * 0.1])


def bench_rest(url: str, sids: list[str], seconds: float) -> dict:
    """One call per act, one connection per session."""
    ids = ",".join(f'"{s}"' for s in sids)
    script = f"""
local ids = {{{ids}}}
local body = '{{"observation": {_obs_json()}}}'
local i = 0
request = function()
  i = i + 1
  return wrk.format("POST", "/sessions/" .. ids[(i % #ids) + 1] .. "/act", {{["Content-Type"] = "application/json"}}, body)
end
"""
    r = wrk(url, script, len(sids), seconds)
    return {
        "sessions": len(sids),
        "acts_per_s": round(r["requests"] / (r["duration_us"] / 1e6), 1),
        "p50_ms": r["p50_us"] / 1000,
        "p99_ms": r["p99_us"] / 1000,
        "errors": r["errors"] + r["non2xx"],
        **_error_detail(r),
    }


def bench_rest_batch(url: str, sids: list[str], seconds: float) -> dict:
    """Every session's observation in one `POST /act` call, one connection."""
    obs = _obs_json()
    body = json.dumps({"requests": [{"session_id": s, "observation": json.loads(obs)} for s in sids]})
    script = f"""
local body = '{body}'
request = function()
  return wrk.format("POST", "/act", {{["Content-Type"] = "application/json"}}, body)
end
"""
    r = wrk(url, script, 1, seconds)
    calls = r["requests"] / (r["duration_us"] / 1e6)
    return {
        "sessions": len(sids),
        "acts_per_s": round(calls * len(sids), 1),
        "p50_ms": r["p50_us"] / 1000,
        "p99_ms": r["p99_us"] / 1000,
        "errors": r["errors"] + r["non2xx"],
        **_error_detail(r),
    }


def grpc_client(target: str, sids: list[str], seconds: float, mode: str) -> dict:
    """Run in a separate process: one concurrent caller per session (unary Act or one Control stream each)."""
    import grpc

    from gmt.v1 import policy_pb2 as pb
    from gmt.v1 import policy_pb2_grpc

    obs = json.loads(_obs_json())

    async def main():
        lat: list[float] = []
        errors = 0
        async with grpc.aio.insecure_channel(target) as ch:
            stub = policy_pb2_grpc.PolicyServiceStub(ch)
            stop = time.perf_counter() + seconds

            async def unary(sid):
                nonlocal errors
                req = pb.ActRequest(session_id=sid, values=pb.FloatVector(values=obs))
                while time.perf_counter() < stop:
                    t = time.perf_counter()
                    try:
                        await stub.Act(req, metadata=(("x-session-id", sid),))
                    except grpc.RpcError:
                        errors += 1
                    lat.append(time.perf_counter() - t)

            async def stream(sid):
                nonlocal errors
                req = pb.ControlRequest(act=pb.ActRequest(session_id=sid, values=pb.FloatVector(values=obs)))
                call = stub.Control(metadata=(("x-session-id", sid),))
                while time.perf_counter() < stop:
                    t = time.perf_counter()
                    await call.write(req)
                    r = await call.read()
                    if r.WhichOneof("result") != "act":
                        errors += 1
                    lat.append(time.perf_counter() - t)
                await call.done_writing()

            t0 = time.perf_counter()
            await asyncio.gather(*((unary if mode == "unary" else stream)(s) for s in sids))
            wall = time.perf_counter() - t0
        ms = np.asarray(lat[len(lat) // 10 :]) * 1000  # drop the first tenth (warm-up)
        return {
            "sessions": len(sids),
            "acts_per_s": round(len(lat) / wall, 1),
            "p50_ms": round(float(np.percentile(ms, 50)), 3),
            "p99_ms": round(float(np.percentile(ms, 99)), 3),
            "errors": errors,
        }

    return asyncio.run(main())


def _grpc_in_process(target: str, sids: list[str], seconds: float, mode: str) -> dict:
    code = (
        "import json,sys; from gmt.service.bench import grpc_client; "
        "a=json.loads(sys.argv[1]); print(json.dumps(grpc_client(a['t'], a['s'], a['d'], a['m'])))"
    )
    arg = json.dumps({"t": target, "s": sids, "d": seconds, "m": mode})
    out = subprocess.run([sys.executable, "-c", code, arg], capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def bench_serving(
    checkpoint: Path, sessions=SESSIONS, seconds: float = 8.0, servers=("naive", "default")
) -> dict:
    """Throughput and latency over every transport, for the naive and the default server, same checkpoint."""
    out: dict = {"model": str(checkpoint), "seconds_per_point": seconds, "servers": {}}
    for kind in servers:
        proc, info = start_server(checkpoint, naive=kind == "naive")
        try:
            url = f"http://127.0.0.1:{info['rest_port']}"
            target = f"127.0.0.1:{info['grpc_port']}"
            model = info["models"][0]
            res: dict = {"rest": [], "rest_batch": [], "grpc_unary": [], "grpc_stream": []}
            for n in sessions:
                before = rss_bytes(proc.pid)
                sids = _sessions(url, model, n)
                res["rest"].append(bench_rest(url, sids, seconds))
                if n == max(sessions) and kind == "default":
                    out["memory"] = {"rss_per_session_bytes": (rss_bytes(proc.pid) - before) // n}
                res["rest_batch"].append(bench_rest_batch(url, sids, seconds))
                res["grpc_unary"].append(_grpc_in_process(target, sids, seconds, "unary"))
                res["grpc_stream"].append(_grpc_in_process(target, sids, seconds, "stream"))
                _close(url, sids)
                print(
                    f"[bench] {kind} {n} sessions: "
                    + ", ".join(f"{k} {v[-1]['acts_per_s']}/s" for k, v in res.items()),
                    file=sys.stderr,
                )
            out["servers"][kind] = res
        finally:
            proc.terminate()
            proc.wait(30)
    return out


# ----- store ------------------------------------------------------------------------------------------------
def _redis_server() -> tuple[subprocess.Popen, str]:
    """A private redis-server on a free loopback port (no persistence): (process, URL)."""
    from gmt.service.cluster import free_port

    port = free_port()
    proc = subprocess.Popen(
        ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"],
        stdout=subprocess.PIPE,
        text=True,
    )
    for line in proc.stdout:
        if "Ready to accept connections" in line:
            threading.Thread(target=lambda: [None for _ in proc.stdout], daemon=True).start()
            return proc, f"redis://127.0.0.1:{port}/0"
    raise RuntimeError("redis-server exited before it was ready")


def bench_store(checkpoint: Path, sessions: int = 256, seconds: float = 8.0) -> dict:
    """One server with sessions in memory beside the same server with a Redis store, same run, same load: REST
    one call per act (one connection per session) and `POST /act` at `sessions`, and one session's REST p50."""
    redis, url = _redis_server()
    out: dict = {"model": str(checkpoint), "sessions": sessions, "seconds_per_point": seconds, "stores": {}}
    try:
        for store, extra in (("memory", ()), ("redis", ("--redis-url", url))):
            proc, info = start_server(checkpoint, naive=False, extra=extra)
            try:
                base = f"http://127.0.0.1:{info['rest_port']}"
                model = info["models"][0]
                one = _sessions(base, model, 1)
                single = bench_rest(base, one, seconds)
                _close(base, one)
                sids = _sessions(base, model, sessions)
                res = {
                    "rest": bench_rest(base, sids, seconds),
                    "rest_batch": bench_rest_batch(base, sids, seconds),
                }
                _close(base, sids)
                res["rest_1_session"] = single
                out["stores"][store] = res
                print(
                    f"[bench] {store}: REST {res['rest']['acts_per_s']}/s, POST /act {res['rest_batch']['acts_per_s']}/s,"
                    f" 1 session p50 {single['p50_ms']} ms",
                    file=sys.stderr,
                )
            finally:
                proc.terminate()
                proc.wait(30)
    finally:
        redis.terminate()
        redis.wait(30)
    m, r = out["stores"]["memory"], out["stores"]["redis"]
    out["redis_vs_memory"] = {
        "rest": round(r["rest"]["acts_per_s"] / m["rest"]["acts_per_s"], 3),
        "rest_batch": round(r["rest_batch"]["acts_per_s"] / m["rest_batch"]["acts_per_s"], 3),
        "p50_1_session_added_ms": round(r["rest_1_session"]["p50_ms"] - m["rest_1_session"]["p50_ms"], 3),
    }
    return out


# ----- cluster ----------------------------------------------------------------------------------------------
def bench_cluster(checkpoint: Path, sessions: int = 256, seconds: float = 120.0) -> dict:
    """REST load through nginx onto two replicas sharing Redis (`gmt cluster`): errors, latency, memory.

    Memory: each replica's RSS after start, with `sessions` live sessions after the load, after they all
    closed, and after a second wave of as many sessions acted again (slots are reused, so it should not grow).
    """
    from gmt.service import cluster

    run_dir = Path(tempfile.mkdtemp(prefix="gmt-cluster-"))
    c = cluster.up(
        run_dir, rest_port=0, grpc_port=0, checkpoints=[checkpoint], serve_args=["--max-sessions", "4096"]
    )
    try:
        pids = {r.name: r.pid for r in c.replicas}
        rss = lambda: {n: rss_bytes(p) for n, p in pids.items()}  # noqa: E731
        import httpx

        model = httpx.get(f"{c.rest_url}/models", timeout=30).json()["models"][0]["name"]
        base = rss()
        sids = _sessions(c.rest_url, model, sessions)
        load = bench_rest(c.rest_url, sids, seconds)
        peak = rss()
        _close(c.rest_url, sids)
        closed = rss()
        again = _sessions(c.rest_url, model, sessions)
        second = bench_rest(c.rest_url, again, min(seconds, 10.0))
        reused = rss()
        _close(c.rest_url, again)
    finally:
        cluster.down(run_dir, quiet=True)
        shutil.rmtree(run_dir, ignore_errors=True)
    total = lambda d: sum(d.values())  # noqa: E731
    return {
        "sessions": sessions,
        "seconds": seconds,
        "load": load,
        "second_wave": second,
        "rss_bytes": {"started": base, "live": peak, "closed": closed, "second_wave": reused},
        "rss_per_live_session_bytes": (total(peak) - total(base)) // sessions,
        "rss_growth_second_wave_bytes": total(reused) - total(peak),
    }


def bench_failover(checkpoint: Path, sessions: int = 64, steps: int = 20) -> dict:
    """The Redis primary of a `gmt cluster` killed (SIGKILL) while `sessions` sessions act as fast as they can
    (REST, gRPC unary and Control streams in turn): time to resume, retried answers by kind, sessions lost, and
    sessions whose actions differ from an uninterrupted twin's (`gmt.service.failover`)."""
    import httpx

    from gmt.service import cluster, failover

    run_dir = Path(tempfile.mkdtemp(prefix="gmt-failover-"))
    c = cluster.up(
        run_dir, rest_port=0, grpc_port=0, checkpoints=[checkpoint], serve_args=["--max-sessions", "4096"]
    )
    try:
        name = httpx.get(f"{c.rest_url}/models", timeout=30).json()["models"][0]["name"]
        spec = httpx.get(f"{c.rest_url}/models/{name}", timeout=30).json()
        d = failover.run_drill(
            c,
            name,
            sessions=sessions,
            obs_dim=int(np.prod(spec["observation_space"]["shape"])),
            goals=len(spec["goals"]),
            steps_before=steps,
            steps_after=steps,
        )
    finally:
        cluster.down(run_dir, quiet=True)
        shutil.rmtree(run_dir, ignore_errors=True)
    before = [a for e in d.episodes for a in e.answered if a <= d.killed_at]
    first = min(s for e in d.episodes for s in e.sent)
    out = d.summary(failover.twin_actions(checkpoint, d.episodes))
    out["acts_per_s_before_kill"] = round(len(before) / (d.killed_at - first), 1)
    return out


# ----- training ---------------------------------------------------------------------------------------------
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


def start_ray_serve(checkpoint: Path, path: str) -> tuple[subprocess.Popen, str]:
    """`gmt.service.bench_ray` in its own process on a free loopback port; returns (process, base URL)."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "gmt.service.bench_ray", str(checkpoint), str(port), path],
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
                sids = _sessions(url, "gmt", n)
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


def machine() -> dict:
    import torch

    cpu = platform.processor()
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    from gmt.model import native

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "platform": platform.platform(),
        "native_kernel": native.load() is not None,
    }


def _default(tmp: Path) -> Path:
    d = tmp / "bench-gmt"
    if not d.exists():
        default_size_checkpoint(d)
    return d


def run(
    checkpoint: Path | None, sections: tuple[str, ...], seconds: float, sessions: tuple[int, ...] = SESSIONS
) -> dict:
    """Every requested section; a temporary default-size `window` checkpoint when none is given."""
    result: dict = {"machine": machine()}
    tmp = Path(tempfile.mkdtemp(prefix="gmt-bench-"))
    try:
        if "engine" in sections:
            result["engine"] = bench_engine()
        if "serving" in sections:
            checkpoint = checkpoint or _default(tmp)
            if shutil.which("wrk") is None:
                result["serving"] = {"skipped": "wrk is not installed (apt-get install wrk)"}
            else:
                result["serving"] = bench_serving(checkpoint, sessions, seconds)
        if "store" in sections:
            if shutil.which("wrk") is None or shutil.which("redis-server") is None:
                result["store"] = {
                    "skipped": "wrk and redis-server are needed (apt-get install wrk redis-server)"
                }
            else:
                result["store"] = bench_store(checkpoint or _default(tmp), max(sessions), seconds)
        if "cluster" in sections:
            result["cluster"] = bench_cluster(
                checkpoint or _default(tmp), max(sessions), 120.0 if seconds >= 8 else seconds
            )
        if "failover" in sections:
            result["failover"] = bench_failover(checkpoint or _default(tmp), max(sessions))
        if "training" in sections:
            result["training"] = bench_training()
        if "alternatives" in sections:
            result["alternatives"] = bench_alternatives(checkpoint or _default(tmp), sessions, seconds)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return result


def to_markdown(result: dict) -> str:
    """The tables of docs/performance.md from a `run` result."""
    lines = []
    m = result.get("machine", {})
    lines += [f"Machine: {m.get('cpu')}, {m.get('cores')} cores, torch {m.get('torch')}.", ""]
    if "engine" in result:
        lines += ["### Engine: ms per act step (one torch thread, window model 3 x 128, full history)", ""]
        paths = ("incremental", "incremental_torch", "recompute")
        lines += ["| K | " + " | ".join(f"{p}, batch {b}" for b in (1, 64) for p in paths) + " |"]
        lines += ["|---|" + "---|" * 6]
        rows = {(r["K"], r["path"], r["batch"]): r["ms_per_step"] for r in result["engine"]}
        for K in sorted({r["K"] for r in result["engine"]}):
            cells = [rows.get((K, p, b), float("nan")) for b in (1, 64) for p in paths]
            lines.append(f"| {K} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
        lines.append("")
    serving = result.get("serving", {})
    if "servers" in serving:
        lines += ["### Serving: acts/s (p50 / p99 ms) by concurrent sessions", ""]
        servers = serving["servers"]
        transports = ("rest", "rest_batch", "grpc_unary", "grpc_stream")
        counts = [r["sessions"] for r in next(iter(servers.values()))["rest"]]
        lines += ["| server | transport | " + " | ".join(f"{n} sessions" for n in counts) + " |"]
        lines += ["|---|---|" + "---|" * len(counts)]
        for kind, res in servers.items():
            for tr in transports:
                cells = [
                    f"{r['acts_per_s']:.0f} ({r['p50_ms']:.1f} / {r['p99_ms']:.1f})" for r in res.get(tr, [])
                ]
                lines.append(f"| {kind} | {tr} | " + " | ".join(cells) + " |")
        if "naive" in servers and "default" in servers:
            lines += ["", "Ratio default / naive, acts/s:", ""]
            lines += ["| transport | " + " | ".join(f"{n} sessions" for n in counts) + " |"]
            lines += ["|---|" + "---|" * len(counts)]
            for tr in transports:
                base = {r["sessions"]: r["acts_per_s"] for r in servers["naive"]["rest"]}
                cells = [
                    f"{r['acts_per_s'] / max(base.get(r['sessions'], 1), 1e-9):.1f}x"
                    for r in servers["default"][tr]
                ]
                lines.append(f"| {tr} vs naive rest | " + " | ".join(cells) + " |")
        if "memory" in serving:
            lines += [
                "",
                f"Memory per live session (RSS growth): {serving['memory']['rss_per_session_bytes']} bytes.",
            ]
        lines.append("")
    if "training" in result:
        t = result["training"]
        lines += [
            "### Training (default model, batch 64 x K 20, one thread)",
            "",
            f"{t['steps_per_s']} steps/s, {t['gflops_achieved']} GFLOP/s achieved in the matrix products; measured "
            f"GEMM rate {t['gemm_gflops']['fp32']} GFLOP/s fp32, {t['gemm_gflops']['bf16']} GFLOP/s bf16.",
            "",
        ]
    alt = result.get("alternatives", {})
    if alt:
        lines += ["### What a user would deploy instead", ""]
        ray = alt.get("ray_serve", {})
        if "skipped" in ray:
            lines += [f"Ray Serve: skipped ({ray['skipped']}).", ""]
        elif ray:
            lines += [
                "Ray Serve with `@serve.batch` (same checkpoint, REST one call per act, wrk): acts/s (p50 / p99 ms)",
                "",
            ]
            counts = [r["sessions"] for r in next(v for k, v in ray.items() if isinstance(v, list))]
            lines += ["| engine inside Ray Serve | " + " | ".join(f"{n} sessions" for n in counts) + " |"]
            lines += ["|---|" + "---|" * len(counts)]
            for path in ("recompute", "incremental"):
                cells = [
                    f"{r['acts_per_s']:.0f} ({r['p50_ms']:.1f} / {r['p99_ms']:.1f})"
                    for r in ray.get(path, [])
                ]
                lines.append(f"| {path} | " + " | ".join(cells) + " |")
            lines.append("")
        hf = alt.get("hf_decision_transformer", {})
        if "skipped" in hf:
            lines += [f"Hugging Face DecisionTransformerModel: skipped ({hf['skipped']}).", ""]
        elif hf:
            lines += [
                f"Hugging Face DecisionTransformerModel ({hf['config']}, {hf['params']} parameters): "
                f"{hf['steps_per_s']} training steps/s.",
                "",
            ]
    return "\n".join(lines)
