"""What every section of `gmt bench` uses: a random-weight checkpoint of the default size, `gmt serve` and
redis-server in their own processes, resident memory, and the load generators (wrk with a Lua script for REST, a
client process for gRPC).
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

SESSIONS = (1, 16, 64, 256)
OBS_DIM, ACT_DIM = 17, 6


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


def start_server(
    checkpoint: Path,
    naive: bool,
    max_batch: int = 256,
    extra: tuple[str, ...] = (),
    tuning: dict[str, str] | None = None,
) -> tuple[subprocess.Popen, dict]:
    """`gmt serve` in its own process on free loopback ports; returns (process, its 'serving' log record).

    Args:
        checkpoint: What it serves.
        naive: Serve by the reference path (GMT_NAIVE).
        max_batch: GMT_MAX_BATCH.
        extra: More `gmt serve` flags.
        tuning: More tuning knobs, as GMT_* environment variables.
    """
    from gmt.cluster.supervisor import gmt_command

    args = [*gmt_command(), "serve", "-c", str(checkpoint), "--rest-port", "0", "--grpc-port", "0"]
    args += ["--log-level", "INFO", "--max-sessions", "4096", *extra]
    env = {k: v for k, v in os.environ.items() if not k.startswith("GMT_")}
    # Tuning knobs are environment variables only (`gmt.service.settings.TUNING`).
    env.update(
        GMT_LOG_LEVEL="INFO", GMT_MAX_BATCH=str(max_batch), GMT_NAIVE="1" if naive else "0", **(tuning or {})
    )
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
item_errors = 0
response = function(status, headers, body)
  if status >= 300 then
    statuses[status] = (statuses[status] or 0) + 1
    if first_body == "" then first_body = body end
  elseif body then
    local _, n = string.gsub(body, '"error":', "")
    if n > 0 then
      item_errors = item_errors + n
      -- the failed item, not the start of a long batch answer
      local at = string.find(body, '"error":', 1, true)
      if first_body == "" then first_body = string.sub(body, math.max(1, at - 80)) end
    end
  end
end
done = function(summary, latency, requests)
  local e = summary.errors
  local counts, body, items = {}, "", 0
  for _, t in ipairs(threads) do
    for k, v in pairs(t:get("statuses")) do table.insert(counts, string.format('"%d":%d', k, v)) end
    if body == "" then body = t:get("first_body") end
    items = items + t:get("item_errors")
  end
  body = string.gsub(string.sub(body, 1, 300), '[%c"\\\\]', " ")
  io.write(string.format('WRK {"requests":%d,"duration_us":%d,"errors":%d,"non2xx":%d,"p50_us":%d,"p99_us":%d,' ..
    '"error_kinds":{"connect":%d,"read":%d,"write":%d,"timeout":%d},"statuses":{%s},"item_errors":%d,' ..
    '"first_error_body":"%s"}\\n',
    summary.requests, summary.duration, e.connect + e.read + e.write + e.timeout, e.status,
    latency:percentile(50), latency:percentile(99), e.connect, e.read, e.write, e.timeout,
    table.concat(counts, ","), items, body))
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


def error_detail(r: dict) -> dict:
    """wrk's error kinds, non-2xx statuses and failed items of 200 answers, only when there were errors."""
    if not r["errors"] + r["non2xx"] + r["item_errors"]:
        return {}
    return {
        "error_kinds": r["error_kinds"],
        "statuses": r["statuses"],
        "item_errors": r["item_errors"],
        "first_error_body": r["first_error_body"],
    }


def open_sessions(url: str, model: str, n: int) -> list[str]:
    """Create `n` sessions of `model` over REST (goals round-robin, seed = index); their ids."""
    import httpx

    with httpx.Client(base_url=url, timeout=30) as c:
        return [
            c.post("/sessions", json={"model": model, "goal": i % 3, "seed": i}).json()["session_id"]
            for i in range(n)
        ]


def close_sessions(url: str, sids: list[str]) -> None:
    """Close the sessions over REST."""
    import httpx

    with httpx.Client(base_url=url, timeout=30) as c:
        for s in sids:
            c.delete(f"/sessions/{s}")


def obs_json() -> str:
    """One fixed HalfCheetah-sized observation as JSON."""
    return json.dumps([round(float(x), 4) for x in np.random.default_rng(0).normal(size=OBS_DIM) * 0.1])


def bench_rest(
    url: str, sids: list[str], seconds: float, extra: dict | None = None, observation: list | None = None
) -> dict:
    """One call per act, one connection per session; `extra` adds fields to every act's body; `observation`:
    what every act sends (default `obs_json()`'s)."""
    ids = ",".join(f'"{s}"' for s in sids)
    more = "".join(f', "{k}": {json.dumps(v)}' for k, v in (extra or {}).items())
    obs = obs_json() if observation is None else json.dumps(observation, separators=(",", ":"))
    script = f"""
local ids = {{{ids}}}
local body = '{{"observation": {obs}{more}}}'
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
        **error_detail(r),
    }


def bench_rest_batch(url: str, sids: list[str], seconds: float, observation: list | None = None) -> dict:
    """Every session's observation in one `POST /act` call, one connection; `observation`: as `bench_rest`'s."""
    obs = json.loads(obs_json()) if observation is None else observation
    body = json.dumps({"requests": [{"session_id": s, "observation": obs} for s in sids]})
    # The routing key a game server (and gmt.client's act_many) sends: behind nginx every call goes to one replica.
    key = min(sids)
    script = f"""
local body = '{body}'
request = function()
  return wrk.format("POST", "/act", {{["Content-Type"] = "application/json", ["X-Session-Id"] = "{key}"}}, body)
end
"""
    r = wrk(url, script, 1, seconds)
    answered = r["requests"] * len(sids) - r["item_errors"]  # items that failed alone are not acts
    return {
        "sessions": len(sids),
        "acts_per_s": round(answered / (r["duration_us"] / 1e6), 1),
        "p50_ms": r["p50_us"] / 1000,
        "p99_ms": r["p99_us"] / 1000,
        "errors": r["errors"] + r["non2xx"] + r["item_errors"],
        **error_detail(r),
    }


def grpc_client(target: str, sids: list[str], seconds: float, mode: str) -> dict:
    """Run in a separate process: one concurrent caller per session (`mode` "unary": unary Act, "stream": one
    Control stream each), or ("batch") one caller sending every session's act in one ActBatch (p50/p99 per call)."""
    import grpc

    from gmt.v1 import policy_pb2 as pb
    from gmt.v1 import policy_pb2_grpc

    obs = json.loads(obs_json())

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

            async def batch():
                nonlocal errors
                req = pb.ActBatchRequest(
                    requests=[pb.ActRequest(session_id=s, values=pb.FloatVector(values=obs)) for s in sids]
                )
                key = (("x-session-id", min(sids)),)
                while time.perf_counter() < stop:
                    t = time.perf_counter()
                    try:
                        r = await stub.ActBatch(req, metadata=key)
                        errors += sum(1 for x in r.results if x.WhichOneof("outcome") != "action")
                    except grpc.RpcError:
                        errors += len(sids)
                    lat.append(time.perf_counter() - t)

            t0 = time.perf_counter()
            if mode == "batch":
                await batch()
            else:
                await asyncio.gather(*((unary if mode == "unary" else stream)(s) for s in sids))
            wall = time.perf_counter() - t0
        ms = np.asarray(lat[len(lat) // 10 :]) * 1000  # drop the first tenth (warm-up)
        acts = len(lat) * len(sids) - errors if mode == "batch" else len(lat)
        return {
            "sessions": len(sids),
            "acts_per_s": round(acts / wall, 1),
            "p50_ms": round(float(np.percentile(ms, 50)), 3),
            "p99_ms": round(float(np.percentile(ms, 99)), 3),
            "errors": errors,
        }

    return asyncio.run(main())


def grpc_load(target: str, sids: list[str], seconds: float, mode: str) -> dict:
    """`grpc_client` in a separate process (so the load does not share this one's GIL); its figures."""
    code = (
        "import json,sys; from gmt.bench.harness import grpc_client; "
        "a=json.loads(sys.argv[1]); print(json.dumps(grpc_client(a['t'], a['s'], a['d'], a['m'])))"
    )
    arg = json.dumps({"t": target, "s": sids, "d": seconds, "m": mode})
    out = subprocess.run([sys.executable, "-c", code, arg], capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def cpp_toolchain_missing() -> list[str]:
    """The Debian packages this machine lacks to build the C++ client (`clients/cpp/build.sh --check`, which owns
    the list; empty: it can be built)."""
    build = Path(__file__).resolve().parents[1] / "clients" / "cpp" / "build.sh"
    if not build.exists():
        return ["a checkout (clients/cpp)"]
    return subprocess.run([str(build), "--check"], capture_output=True, text=True).stdout.split()


def cpp_control_client() -> Path | None:
    """The C++ Control-stream client (`clients/cpp`), built into build/cpp by clients/cpp/build.sh (again only when
    its inputs changed); None, with the reason on stderr, where it cannot be built."""
    root = Path(__file__).resolve().parents[1]
    build = root / "clients" / "cpp" / "build.sh"
    if missing := cpp_toolchain_missing():
        print(
            f"[bench] no C++ client: {', '.join(missing)} not installed (clients/cpp/build.sh)",
            file=sys.stderr,
        )
        return None
    done = subprocess.run([str(build), str(root / "build" / "cpp")], capture_output=True, text=True)
    lines = done.stdout.strip().splitlines()
    if done.returncode != 0 or not lines:
        tail = "\n".join(done.stderr.strip().splitlines()[-15:])
        print(f"[bench] the C++ client did not build:\n{tail}", file=sys.stderr)
        return None
    return Path(lines[-1])


def cpp_control_load(binary: Path, target: str, sid: str, seconds: float) -> dict:
    """One robot loop over the Control stream from the C++ client's process (`cpp_control_client`): acts/s over
    the seconds it ran, p50 and p99 (numpy's percentiles, the first tenth left out), errors, as `grpc_load` reports.

    Raises:
        RuntimeError: the client printed no result, its stream failed, or no act was answered.
    """
    obs = ",".join(str(v) for v in json.loads(obs_json()))
    done = subprocess.run(
        [str(binary), target, sid, "--obs", obs, "--seconds", str(seconds)],
        capture_output=True,
        text=True,
        errors="replace",
        timeout=seconds + 60,
    )
    try:
        out = json.loads(done.stdout.strip().splitlines()[-1])
    except (IndexError, ValueError):
        raise RuntimeError(
            f"the C++ client printed no result (exit {done.returncode}): {done.stderr[-2000:]}"
        ) from None
    if out["status"] != "OK" or out["stream_broken"] or not out["acts"]:
        raise RuntimeError(f"the C++ client's stream failed: {out}")
    return {
        "sessions": 1,
        "acts_per_s": round(out["acts"] / out["seconds"], 1),  # as grpc_client counts a stream's answers
        "p50_ms": out["p50_ms"],
        "p99_ms": out["p99_ms"],
        "errors": out["errors"],
    }


def redis_server(unix_socket: str | None = None) -> tuple[subprocess.Popen, str]:
    """A private redis-server on a free loopback port (no persistence): (process, URL).

    Args:
        unix_socket: Also listen on this Unix socket path (`unix://<path>?db=0` reaches it).
    """
    from gmt.cluster.supervisor import free_port

    port = free_port()
    extra = ["--unixsocket", unix_socket, "--unixsocketperm", "700"] if unix_socket else []
    proc = subprocess.Popen(
        [
            "redis-server",
            "--port",
            str(port),
            "--bind",
            "127.0.0.1",
            "--save",
            "",
            "--appendonly",
            "no",
            *extra,
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    for line in proc.stdout:
        if "Ready to accept connections" in line:
            threading.Thread(target=lambda: [None for _ in proc.stdout], daemon=True).start()
            return proc, f"redis://127.0.0.1:{port}/0"
    raise RuntimeError("redis-server exited before it was ready")


def replicated_redis(directory: Path) -> tuple[list[subprocess.Popen], str]:
    """A Redis primary and one replica as `make cluster` runs them (AOF on, `appendfsync everysec`, data under
    `directory`), the replica in sync: (both processes, the primary's URL). A server given
    `--store-min-replicas 1` then has every write acknowledged by the replica (WAIT)."""
    from gmt.cluster.supervisor import _replica_in_sync, free_port

    ports = [free_port(), free_port()]
    procs = []
    for i, port in enumerate(ports):
        d = directory / f"redis-{i}"
        d.mkdir(parents=True, exist_ok=True)
        cmd = ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--dir", str(d), "--save", ""]
        cmd += ["--appendonly", "yes", "--appendfsync", "everysec", "--repl-diskless-sync-delay", "0"]
        cmd += ["--replicaof", "127.0.0.1", str(ports[0])] if i else []
        procs.append(subprocess.Popen(cmd, stdout=subprocess.DEVNULL))
    deadline = time.monotonic() + 30
    while not _replica_in_sync("127.0.0.1", ports[1], ports[0]):
        if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
            for p in procs:
                p.kill()
            raise RuntimeError("the Redis replica never came in sync")
        time.sleep(0.05)
    return procs, f"redis://127.0.0.1:{ports[0]}/0"
