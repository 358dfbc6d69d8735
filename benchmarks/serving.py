"""`gmt bench --sections serving`: acts/s and p50/p99 over every transport (REST one call per act, `POST /act`, gRPC
unary, the gRPC `Control` stream) for `GMT_NAIVE=1 gmt serve` and the default server, same checkpoint, same run.
"""

from __future__ import annotations

import sys
from pathlib import Path

from gmt.bench.harness import (
    SESSIONS,
    bench_rest,
    bench_rest_batch,
    close_sessions,
    grpc_load,
    open_sessions,
    rss_bytes,
    start_server,
)


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
                sids = open_sessions(url, model, n)
                res["rest"].append(bench_rest(url, sids, seconds))
                if n == max(sessions) and kind == "default":
                    out["memory"] = {"rss_per_session_bytes": (rss_bytes(proc.pid) - before) // n}
                res["rest_batch"].append(bench_rest_batch(url, sids, seconds))
                res["grpc_unary"].append(grpc_load(target, sids, seconds, "unary"))
                res["grpc_stream"].append(grpc_load(target, sids, seconds, "stream"))
                close_sessions(url, sids)
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
