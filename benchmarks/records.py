"""`gmt bench --sections records`: what recording costs per act. One server (sessions in memory, then one over a
local redis-server) holds `sessions` recorded and `sessions` unrecorded sessions; REST acts (one call per act, one
connection per session, each act carrying a reward and an info as a recording client sends them) are measured on
the unrecorded set and on the recorded set in alternating rounds, same process, same load."""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from gmt.bench.harness import bench_rest, close_sessions, obs_json, redis_server, start_server

REPORT = {"reward": 1.25, "info": {"x_velocity": 1.25, "reward_ctrl": -0.1}}


def open_sessions(url: str, model: str, n: int, record: bool) -> list[str]:
    """`n` sessions (recorded or not), each stepped once so that later acts may carry a report."""
    import httpx

    obs = json.loads(obs_json())
    sids = []
    with httpx.Client(base_url=url, timeout=30) as c:
        for i in range(n):
            r = c.post("/sessions", json={"model": model, "goal": i % 3, "seed": i, "record": record})
            r.raise_for_status()
            sid = r.json()["session_id"]
            c.post(f"/sessions/{sid}/act", json={"observation": obs}).raise_for_status()
            sids.append(sid)
    return sids


def recorded_steps(url: str, sids: list[str]) -> int:
    """Steps held by the sessions' recordings (read back as .npz)."""
    import httpx

    from gmt.common.recording import Recording

    with httpx.Client(base_url=url, timeout=60) as c:
        return sum(
            Recording.from_npz(c.get(f"/sessions/{s}/recording?format=npz").content).steps for s in sids
        )


def bench_records(checkpoint: Path, sessions: int = 64, seconds: float = 8.0, rounds: int = 2) -> dict:
    """REST acts/s at `sessions` sessions, recorded and not, alternating `rounds` times, memory and Redis."""
    redis, redis_url = redis_server()
    out: dict = {"model": str(checkpoint), "sessions": sessions, "seconds_per_point": seconds, "stores": {}}
    try:
        for store, extra in (("memory", ()), ("redis", ("--redis-url", redis_url))):
            with tempfile.TemporaryDirectory(prefix="gmt-bench-rec-") as rec_dir:
                proc, info = start_server(checkpoint, naive=False, extra=(*extra, "--record-dir", rec_dir))
                try:
                    url = f"http://127.0.0.1:{info['rest_port']}"
                    model = info["models"][0]
                    sets = {flag: open_sessions(url, model, sessions, flag) for flag in (False, True)}
                    res: dict = {"plain": [], "recorded": []}
                    for _ in range(rounds):
                        for flag, name in ((False, "plain"), (True, "recorded")):
                            res[name].append(bench_rest(url, sets[flag], seconds, extra=REPORT))
                    res["recorded_steps"] = recorded_steps(url, sets[True])
                    for flag in (False, True):
                        close_sessions(url, sets[flag])
                    res["files_written"] = len(list(Path(rec_dir).glob("*.json")))
                finally:
                    proc.terminate()
                    proc.wait(30)
            mean = {k: sum(r["acts_per_s"] for r in res[k]) / rounds for k in ("plain", "recorded")}
            res["acts_per_s"] = {k: round(v, 1) for k, v in mean.items()}
            res["recorded_vs_plain"] = round(mean["recorded"] / mean["plain"], 3)
            out["stores"][store] = res
            print(
                f"[bench] records {store}: plain {mean['plain']:.0f}/s, recorded {mean['recorded']:.0f}/s "
                f"({res['recorded_vs_plain']}x)",
                file=sys.stderr,
            )
    finally:
        redis.terminate()
        redis.wait(30)
    return out
