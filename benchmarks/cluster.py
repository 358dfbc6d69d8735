"""`gmt bench --sections cluster` and `--sections soak`: REST load through `gmt cluster` (nginx, gmt replicas, Redis
with Sentinel).

- `cluster`: scale-out: one in-memory `gmt serve` beside clusters of 1, 2, ... replicas, same run, same load.
- `soak`: two replicas under a long load: errors, latency, each replica's memory through two waves of sessions.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

from gmt.bench.harness import (
    bench_rest,
    bench_rest_batch,
    close_sessions,
    open_sessions,
    rss_bytes,
    start_server,
)


def bench_scaleout(
    checkpoint: Path, sessions: int = 256, seconds: float = 8.0, replicas: tuple[int, ...] = (1, 2)
) -> dict:
    """REST (one call per act, one connection per session) and `POST /act` load against one in-memory server and
    against `gmt cluster` with each number of replicas behind nginx (Redis with Sentinel, WAIT for one Redis
    replica), in one run: acts/s, p50/p99, errors. Every process shares this machine's cores."""
    import httpx

    from gmt.cluster import supervisor as cluster

    out: dict = {"sessions": sessions, "seconds_per_point": seconds, "cores": os.cpu_count(), "points": []}

    def load(url: str) -> dict:
        model = httpx.get(f"{url}/models", timeout=30).json()["models"][0]["name"]
        sids = open_sessions(url, model, sessions)
        try:
            return {
                "rest": bench_rest(url, sids, seconds),
                "rest_batch": bench_rest_batch(url, sids, seconds),
            }
        finally:
            close_sessions(url, sids)

    proc, info = start_server(checkpoint, naive=False)
    try:
        out["points"].append(
            {
                "deployment": "one gmt serve, sessions in memory",
                **load(f"http://127.0.0.1:{info['rest_port']}"),
            }
        )
    finally:
        proc.terminate()
        proc.wait(30)
    for n in replicas:
        run_dir = Path(tempfile.mkdtemp(prefix="gmt-cluster-"))
        c = cluster.up(
            run_dir,
            rest_port=0,
            grpc_port=0,
            replicas=n,
            checkpoints=[checkpoint],
            serve_args=["--max-sessions", "4096"],
        )
        try:
            out["points"].append(
                {"deployment": f"make cluster, {n} replica(s) behind nginx", **load(c.rest_url)}
            )
        finally:
            cluster.down(run_dir, quiet=True)
            shutil.rmtree(run_dir, ignore_errors=True)
        print(f"[bench] cluster {n} replica(s): {out['points'][-1]['rest']['acts_per_s']}/s", file=sys.stderr)
    return out


def bench_cluster(checkpoint: Path, sessions: int = 256, seconds: float = 120.0) -> dict:
    """REST load through nginx onto two replicas sharing Redis (`gmt cluster`): errors, latency, memory.

    Memory: each replica's RSS after start, with `sessions` live sessions after the load, after they all
    closed, and after a second wave of as many sessions acted again (slots are reused, so it should not grow).
    """
    from gmt.cluster import supervisor as cluster

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
        sids = open_sessions(c.rest_url, model, sessions)
        load = bench_rest(c.rest_url, sids, seconds)
        peak = rss()
        close_sessions(c.rest_url, sids)
        closed = rss()
        again = open_sessions(c.rest_url, model, sessions)
        second = bench_rest(c.rest_url, again, min(seconds, 10.0))
        reused = rss()
        close_sessions(c.rest_url, again)
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
