"""`gmt bench --sections store-ab`: what the session store costs, for this checkout's last commit against a baseline
commit, in one run: each commit's server with sessions in memory and with them in Redis (its own redis-server:
bare, or with `replicated` as `make cluster` deploys it), all four up at once, the same loads in alternating rounds.

A ratio of two runs (the store section of each commit, one after the other) moves by 0.1-0.3 between runs here;
this section takes each round's Redis / memory ratio of each commit from the same minute.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
from pathlib import Path

from gmt.bench import harness
from gmt.bench.batching import commit_servers, over_commits

LOADS = ("rest", "rest_batch")


def bench_store_ab(
    checkpoint: Path,
    sessions: int = 256,
    seconds: float = 8.0,
    rounds: int = 6,
    baseline: str = "4bb58d0",
    current: str = "HEAD",
    replicated: bool = False,
) -> dict:
    """Four servers at once (`current` and `baseline`, each in memory and over its own Redis), `rounds` rounds of
    REST (one connection per session) then `POST /act` at `sessions` sessions, `seconds / 2` each.

    Returns the loads over their rounds per server (`servers`: {current | baseline}-{memory | redis}), and per
    commit and load the Redis / memory ratio of each round with their mean and standard deviation (`ratios`),
    and `difference`: current's mean ratio minus the baseline's, with its standard error.
    """
    per_round = max(seconds / 2, 1.0)
    tmp = Path(tempfile.mkdtemp(prefix="gmt-bench-store-ab-"))
    redis_procs, urls = [], {}
    for name in ("current", "baseline"):
        if replicated:
            procs, url = harness.replicated_redis(tmp / name)
            urls[name] = ("--redis-url", url, "--store-min-replicas", "1")
        else:
            proc, url = harness.redis_server()
            procs = [proc]
            urls[name] = ("--redis-url", url)
        redis_procs += procs
    servers = [f"{c}-{s}" for c in ("current", "baseline") for s in ("memory", "redis")]
    commits = {n: current if n.startswith("current") else baseline for n in servers}
    extra = {n: urls[n.split("-")[0]] for n in servers if n.endswith("redis")}
    rows: dict = {n: {load: [] for load in LOADS} for n in servers}
    try:
        with commit_servers(checkpoint, commits, extra) as procs:
            at = {
                n: (f"http://127.0.0.1:{info['rest_port']}", info["models"][0])
                for n, (_, info) in procs.items()
            }
            sids = {n: harness.open_sessions(url, model, sessions) for n, (url, model) in at.items()}
            for r in range(rounds):
                for n, (url, _) in at.items():
                    rows[n]["rest"].append(harness.bench_rest(url, sids[n], per_round))
                    rows[n]["rest_batch"].append(harness.bench_rest_batch(url, sids[n], per_round))
                print(
                    f"[bench] store-ab round {r + 1}/{rounds}: "
                    + ", ".join(
                        f"{n} REST {rows[n]['rest'][r]['acts_per_s']}/s POST /act {rows[n]['rest_batch'][r]['acts_per_s']}/s"
                        for n in at
                    ),
                    file=sys.stderr,
                )
            for n, (url, _) in at.items():
                harness.close_sessions(url, sids[n])
    finally:
        for p in redis_procs:
            p.terminate()
        for p in redis_procs:
            p.wait(30)
    out = over_commits(rows, checkpoint, sessions, (baseline, current), per_round, rounds)
    out["store"] = "replicated" if replicated else "redis"
    out["ratios"], out["difference"] = {}, {}
    for load in LOADS:
        per = {}
        for c in ("current", "baseline"):
            mem, red = rows[f"{c}-memory"][load], rows[f"{c}-redis"][load]
            r = [round(b["acts_per_s"] / a["acts_per_s"], 3) for a, b in zip(mem, red, strict=True)]
            sd = statistics.stdev(r) if len(r) > 1 else 0.0
            per[c] = {"rounds": r, "mean": round(statistics.mean(r), 3), "sd": round(sd, 3)}
        out["ratios"][load] = per
        se = (sum(per[c]["sd"] ** 2 for c in per) / rounds) ** 0.5
        out["difference"][load] = {
            "current_minus_baseline": round(per["current"]["mean"] - per["baseline"]["mean"], 3),
            "standard_error": round(se, 3),
        }
    return out
