"""`gmt bench --sections store`: the same server with sessions in memory and in a local redis-server (over loopback
TCP, over a Unix socket: the co-located deployment, and as `make cluster` deploys it: AOF `everysec`, one Redis
replica, `--store-min-replicas 1`), same load, measured in alternating rounds."""

from __future__ import annotations

import shutil
import statistics
import sys
import tempfile
from pathlib import Path

from gmt.bench.harness import (
    bench_rest,
    bench_rest_batch,
    close_sessions,
    open_sessions,
    redis_server,
    replicated_redis,
    start_server,
)


def bench_store(checkpoint: Path, sessions: int = 256, seconds: float = 8.0, rounds: int = 4) -> dict:
    """The four servers (memory, Redis over TCP, Redis over its Unix socket, a replicated Redis with AOF whose
    every write waits for its replica) run at once and take the same loads
    in turn, `rounds` times, `seconds / 2` each (so that the machine's drift, up to 2x between runs here, falls
    on all three alike): one session's REST p50, then REST one call per act (one connection per session) and
    `POST /act` at `sessions`.

    A load's figures are over its rounds: acts/s their mean (the rounds are equally long), p50 and p99 their
    medians, errors their sum; each round's are kept under `rounds`.
    """
    sock_dir = tempfile.mkdtemp(prefix="gmt-bench-redis-")
    sock = str(Path(sock_dir) / "redis.sock")
    redis, url = redis_server(unix_socket=sock)
    replicated, replicated_url = replicated_redis(Path(sock_dir))
    per_round = max(seconds / 2, 1.0)
    out: dict = {
        "model": str(checkpoint),
        "sessions": sessions,
        "seconds_per_round": per_round,
        "rounds": rounds,
    }
    stores = {
        "memory": (),
        "redis": ("--redis-url", url),
        "redis_unix": ("--redis-url", f"unix://{sock}?db=0"),
        "replicated": ("--redis-url", replicated_url, "--store-min-replicas", "1"),
    }
    procs: dict = {}
    rows: dict = {s: {"rest_1_session": [], "rest": [], "rest_batch": []} for s in stores}
    try:
        for store, extra in stores.items():
            proc, info = start_server(checkpoint, naive=False, extra=extra)
            procs[store] = (proc, f"http://127.0.0.1:{info['rest_port']}", info["models"][0])
        # One session first, alone on its server (the store's lone-session path), then `sessions` at once.
        ones = {s: open_sessions(base, model, 1) for s, (_, base, model) in procs.items()}
        for _ in range(rounds):
            for store, (_, base, _) in procs.items():
                rows[store]["rest_1_session"].append(bench_rest(base, ones[store], per_round))
        for store, (_, base, _) in procs.items():
            close_sessions(base, ones[store])
        many = {s: open_sessions(base, model, sessions) for s, (_, base, model) in procs.items()}
        for r in range(rounds):
            for store, (_, base, _) in procs.items():
                rows[store]["rest"].append(bench_rest(base, many[store], per_round))
                rows[store]["rest_batch"].append(bench_rest_batch(base, many[store], per_round))
            print(
                f"[bench] store round {r + 1}/{rounds}: "
                + ", ".join(
                    f"{s} 1 session p50 {rows[s]['rest_1_session'][r]['p50_ms']} ms, REST "
                    f"{rows[s]['rest'][r]['acts_per_s']}/s, POST /act {rows[s]['rest_batch'][r]['acts_per_s']}/s"
                    for s in stores
                ),
                file=sys.stderr,
            )
    finally:
        for proc, _, _ in procs.values():
            proc.terminate()
        for proc, _, _ in procs.values():
            proc.wait(30)
        for r in (redis, *replicated):
            r.terminate()
        for r in (redis, *replicated):
            r.wait(30)
        shutil.rmtree(sock_dir, ignore_errors=True)
    out["stores"] = {s: {load: over_rounds(r) for load, r in loads.items()} for s, loads in rows.items()}
    m = out["stores"]["memory"]
    for store, key in (
        ("redis", "redis_vs_memory"),
        ("redis_unix", "redis_unix_vs_memory"),
        ("replicated", "replicated_vs_memory"),
    ):
        r = out["stores"][store]
        out[key] = {
            "rest": round(r["rest"]["acts_per_s"] / m["rest"]["acts_per_s"], 3),
            "rest_batch": round(r["rest_batch"]["acts_per_s"] / m["rest_batch"]["acts_per_s"], 3),
            "p50_1_session_added_ms": round(r["rest_1_session"]["p50_ms"] - m["rest_1_session"]["p50_ms"], 3),
            "p50_1_session_added_ms_rounds": [
                round(a["p50_ms"] - b["p50_ms"], 3)
                for a, b in zip(r["rest_1_session"]["rounds"], m["rest_1_session"]["rounds"], strict=True)
            ],
        }
    return out


def over_rounds(rows: list[dict]) -> dict:
    """One load's figures over its rounds (see `bench_store`), the rounds kept."""
    return {
        "sessions": rows[0]["sessions"],
        "acts_per_s": round(statistics.mean(r["acts_per_s"] for r in rows), 1),
        "p50_ms": round(statistics.median(r["p50_ms"] for r in rows), 3),
        "p99_ms": round(statistics.median(r["p99_ms"] for r in rows), 3),
        "errors": sum(r["errors"] for r in rows),
        "rounds": rows,
    }
