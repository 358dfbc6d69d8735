"""`gmt bench --sections stream`: one robot loop over the gRPC Control stream and `ActBatch` at many sessions,
for this checkout's last commit's server beside a baseline commit's server in the same run.

The load runs in a separate client process (grpc.aio, `harness.grpc_client`), started afresh for every round, and
the robot loop also from the C++ client (`clients/cpp`, where gRPC's C++ toolchain is installed): both
servers run at once from `git archive` trees and take the same loads in alternating rounds (the batching
section's method), so that the machine's drift falls on both alike.
"""

from __future__ import annotations

import sys
from pathlib import Path

from gmt.bench.batching import commit_servers, over_commits
from gmt.bench.harness import close_sessions, cpp_control_client, cpp_control_load, grpc_load, open_sessions

# The commit before the Control stream's and ActBatch's per-act work was cut (issue 58).
BASELINE = "a30586a"


def bench_stream(
    checkpoint: Path,
    sessions: int = 256,
    seconds: float = 8.0,
    rounds: int = 4,
    baseline: str = BASELINE,
    current: str = "HEAD",
) -> dict:
    """The servers of commits `current` and `baseline`, at once, same loads in alternating rounds of `seconds / 2`:

    - `control`: one session, one Control stream, one act at a time (a robot loop), from a separate process;
    - `control_cpp`: the same loop from the C++ client (`clients/cpp`; left out where it cannot be built);
    - `act_batch`: `sessions` sessions in one `ActBatch` call at a time (p50/p99 per call);
    - `control_all`: `sessions` sessions, one Control stream each, all acting at once.

    Figures over rounds as in the store section; `vs_baseline` is current over baseline: acts/s for both loads
    and the Control stream's p50 and p99 (below 1 is faster).
    """
    per_round = max(seconds / 2, 1.0)
    cpp = cpp_control_client()
    loads = ("control", *(("control_cpp",) if cpp else ()), "act_batch", "control_all")
    names = ("baseline", "current")
    rows: dict = {s: {load: [] for load in loads} for s in names}
    with commit_servers(checkpoint, {"baseline": baseline, "current": current}) as procs:
        servers = {
            s: (f"http://127.0.0.1:{info['rest_port']}", f"127.0.0.1:{info['grpc_port']}", info["models"][0])
            for s, (_, info) in procs.items()
        }
        ones = {s: open_sessions(url, model, 1) for s, (url, _, model) in servers.items()}
        for r in range(rounds):
            for s, (_, target, _) in servers.items():
                rows[s]["control"].append(grpc_load(target, ones[s], per_round, "stream"))
                if cpp:
                    rows[s]["control_cpp"].append(cpp_control_load(cpp, target, ones[s][0], per_round))
            print(
                f"[bench] stream round {r + 1}/{rounds}: "
                + ", ".join(
                    f"{s}: Control p50 {rows[s]['control'][r]['p50_ms']} ms"
                    + (f" (C++ {rows[s]['control_cpp'][r]['p50_ms']} ms)" if cpp else "")
                    for s in names
                ),
                file=sys.stderr,
            )
        many = {s: open_sessions(url, model, sessions - 1) for s, (url, _, model) in servers.items()}
        for r in range(rounds):
            for s, (_, target, _) in servers.items():
                rows[s]["act_batch"].append(grpc_load(target, ones[s] + many[s], per_round, "batch"))
                rows[s]["control_all"].append(grpc_load(target, ones[s] + many[s], per_round, "stream"))
            print(
                f"[bench] stream round {r + 1}/{rounds}: "
                + ", ".join(
                    f"{s}: ActBatch {rows[s]['act_batch'][r]['acts_per_s']}/s, "
                    f"Control x{sessions} {rows[s]['control_all'][r]['acts_per_s']}/s"
                    for s in names
                ),
                file=sys.stderr,
            )
        for s, (url, _, _) in servers.items():
            close_sessions(url, ones[s] + many[s])
    out = over_commits(rows, checkpoint, sessions, (baseline, current), per_round, rounds)
    cur, base = out["servers"]["current"], out["servers"]["baseline"]
    out["vs_baseline"] = {
        **{
            f"{load}_acts_per_s": round(cur[load]["acts_per_s"] / base[load]["acts_per_s"], 3)
            for load in loads
        },
        "control_p50": round(cur["control"]["p50_ms"] / base["control"]["p50_ms"], 3),
        "control_p99": round(cur["control"]["p99_ms"] / base["control"]["p99_ms"], 3),
    }
    if cpp:
        out["vs_baseline"]["control_cpp_p50"] = round(
            cur["control_cpp"]["p50_ms"] / base["control_cpp"]["p50_ms"], 3
        )
    return out
