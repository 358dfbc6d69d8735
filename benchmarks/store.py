"""`gmt bench --sections store`: the same server with sessions in memory and in a local redis-server (over loopback
TCP, and over a Unix socket: the co-located deployment), same load."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from gmt.bench.harness import (
    bench_rest,
    bench_rest_batch,
    close_sessions,
    open_sessions,
    redis_server,
    start_server,
)


def bench_store(checkpoint: Path, sessions: int = 256, seconds: float = 8.0) -> dict:
    """One server with sessions in memory beside the same server with a Redis store, same run, same load: REST
    one call per act (one connection per session) and `POST /act` at `sessions`, and one session's REST p50."""
    sock_dir = tempfile.mkdtemp(prefix="gmt-bench-redis-")
    sock = str(Path(sock_dir) / "redis.sock")
    redis, url = redis_server(unix_socket=sock)
    out: dict = {"model": str(checkpoint), "sessions": sessions, "seconds_per_point": seconds, "stores": {}}
    stores = (
        ("memory", ()),
        ("redis", ("--redis-url", url)),
        ("redis_unix", ("--redis-url", f"unix://{sock}?db=0")),
    )
    try:
        for store, extra in stores:
            proc, info = start_server(checkpoint, naive=False, extra=extra)
            try:
                base = f"http://127.0.0.1:{info['rest_port']}"
                model = info["models"][0]
                one = open_sessions(base, model, 1)
                single = bench_rest(base, one, seconds)
                close_sessions(base, one)
                sids = open_sessions(base, model, sessions)
                res = {
                    "rest": bench_rest(base, sids, seconds),
                    "rest_batch": bench_rest_batch(base, sids, seconds),
                }
                close_sessions(base, sids)
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
        Path(sock).unlink(missing_ok=True)
        Path(sock_dir).rmdir()
    m = out["stores"]["memory"]
    for store, key in (("redis", "redis_vs_memory"), ("redis_unix", "redis_unix_vs_memory")):
        r = out["stores"][store]
        out[key] = {
            "rest": round(r["rest"]["acts_per_s"] / m["rest"]["acts_per_s"], 3),
            "rest_batch": round(r["rest_batch"]["acts_per_s"] / m["rest_batch"]["acts_per_s"], 3),
            "p50_1_session_added_ms": round(r["rest_1_session"]["p50_ms"] - m["rest_1_session"]["p50_ms"], 3),
        }
    return out
