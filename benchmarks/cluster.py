"""`gmt bench --sections cluster`: REST load through `gmt cluster` (nginx, two replicas, Redis with Sentinel): errors,
latency, each replica's memory.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from gmt.bench.harness import bench_rest, close_sessions, open_sessions, rss_bytes


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
