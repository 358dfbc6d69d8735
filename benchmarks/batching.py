"""`gmt bench --sections batching`: what idle sessions cost an acting one, and the 256-session figures, for this
checkout's last commit's server beside a baseline commit's server in the same run.

Both servers run at once and take the same loads in turn, in alternating rounds (the store section's method), so
that the machine's drift falls on both alike.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

from gmt.bench.harness import bench_rest, bench_rest_batch, close_sessions, open_sessions, start_server
from gmt.bench.store import over_rounds

# The import package `gmt` as pyproject.toml's package-dir builds it: (name inside gmt, folder in the repository).
_PACKAGE_DIRS = (
    ("v1", "proto/gmt/v1"),
    ("model", "model"),
    ("service", "service"),
    ("client", "clients"),
    ("common", "common"),
    ("datagen", "datagen"),
    ("bench", "benchmarks"),
)


def commit_tree(commit: str, into: Path) -> Path:
    """The repository at `commit` (`git archive` of the repository this module lives in) laid out as an import root
    (`<root>/gmt/...` as symbolic links), to put first on `PYTHONPATH`: a `gmt serve` of that commit from this
    environment. Returns the root."""
    repo = Path(__file__).resolve().parent.parent
    src = into / "src"
    src.mkdir(parents=True)
    archive = subprocess.run(
        ["git", "-C", str(repo), "archive", commit], capture_output=True, check=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
    pkg = into / "root" / "gmt"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").symlink_to(src / "proto/gmt/__init__.py")
    for name, folder in _PACKAGE_DIRS:
        (pkg / name).symlink_to(src / folder)
    return into / "root"


@contextlib.contextmanager
def commit_servers(
    checkpoint: Path, commits: dict[str, str], extra: dict[str, tuple[str, ...]] | None = None
) -> Iterator[dict]:
    """`gmt serve` of each named commit at once, each from its own `git archive` tree (all the same way: a server
    run from the editable install measured slower here than the same code run from such a tree), with `extra[name]`
    added to its command line: yields {name: (process, its 'serving' log record)}; the servers are stopped and the
    trees removed on leaving."""
    tmp = Path(tempfile.mkdtemp(prefix="gmt-bench-commits-"))
    procs: dict = {}
    trees: dict[str, Path] = {}
    try:
        for name, commit in commits.items():
            if commit not in trees:
                trees[commit] = commit_tree(commit, tmp / f"tree-{len(trees)}")
            root = trees[commit]
            old_path = os.environ.get("PYTHONPATH")
            os.environ["PYTHONPATH"] = str(root)
            try:
                procs[name] = start_server(checkpoint, naive=False, extra=(extra or {}).get(name, ()))
            finally:
                if old_path is None:
                    os.environ.pop("PYTHONPATH")
                else:
                    os.environ["PYTHONPATH"] = old_path
        yield procs
    finally:
        for proc, _ in procs.values():
            proc.terminate()
        for proc, _ in procs.values():
            proc.wait(30)
        shutil.rmtree(tmp, ignore_errors=True)


def over_commits(
    rows: dict, checkpoint: Path, sessions: int, commits: tuple[str, str], per_round: float, rounds: int
) -> dict:
    """A two-commit section's result: what ran (model, sessions, the (baseline, current) commits, rounds) and each
    server's loads over their rounds (`servers`: {current | baseline: {load: figures}})."""
    return {
        "model": str(checkpoint),
        "sessions": sessions,
        "baseline": commits[0],
        "current": commits[1],
        "seconds_per_round": per_round,
        "rounds": rounds,
        "servers": {s: {load: over_rounds(r) for load, r in by.items()} for s, by in rows.items()},
    }


def bench_batching(
    checkpoint: Path,
    sessions: int = 256,
    seconds: float = 8.0,
    rounds: int = 4,
    baseline: str = "4bb58d0",
    current: str = "HEAD",
) -> dict:
    """The servers of commits `current` (this checkout's last commit) and `baseline`, at once, same loads in alternating rounds of `seconds / 2`:

    - `alone`: one session acting over REST, no other session on the server;
    - `idle_neighbours`: the same session with `sessions - 1` idle sessions of its model beside it;
    - `rest` / `rest_batch`: `sessions` sessions acting (one connection each / all in one `POST /act`).

    Figures over rounds as in the store section (acts/s mean, p50 and p99 medians); `idle_vs_alone` is each
    server's p50 with idle neighbours over its p50 alone, `vs_baseline` current's acts/s over the baseline's.
    """
    per_round = max(seconds / 2, 1.0)
    loads = ("alone", "idle_neighbours", "rest", "rest_batch")
    rows: dict = {s: {load: [] for load in loads} for s in ("current", "baseline")}
    with commit_servers(checkpoint, {"baseline": baseline, "current": current}) as procs:
        urls = {
            s: (f"http://127.0.0.1:{info['rest_port']}", info["models"][0]) for s, (_, info) in procs.items()
        }
        ones = {s: open_sessions(url, model, 1) for s, (url, model) in urls.items()}
        for _ in range(rounds):
            for s, (url, _) in urls.items():
                rows[s]["alone"].append(bench_rest(url, ones[s], per_round))
        idle = {s: open_sessions(url, model, sessions - 1) for s, (url, model) in urls.items()}
        for _ in range(rounds):
            for s, (url, _) in urls.items():
                rows[s]["idle_neighbours"].append(bench_rest(url, ones[s], per_round))
        for r in range(rounds):
            for s, (url, _) in urls.items():
                everyone = ones[s] + idle[s]
                rows[s]["rest"].append(bench_rest(url, everyone, per_round))
                rows[s]["rest_batch"].append(bench_rest_batch(url, everyone, per_round))
            print(
                f"[bench] batching round {r + 1}/{rounds}: "
                + ", ".join(
                    f"{s}: alone p50 {rows[s]['alone'][r]['p50_ms']} ms, idle neighbours p50 "
                    f"{rows[s]['idle_neighbours'][r]['p50_ms']} ms, REST {rows[s]['rest'][r]['acts_per_s']}/s, "
                    f"POST /act {rows[s]['rest_batch'][r]['acts_per_s']}/s"
                    for s in urls
                ),
                file=sys.stderr,
            )
        for s, (url, _) in urls.items():
            close_sessions(url, ones[s] + idle[s])
    out = over_commits(rows, checkpoint, sessions, (baseline, current), per_round, rounds)
    cur, base = out["servers"]["current"], out["servers"]["baseline"]
    out["idle_vs_alone"] = {
        s: round(v["idle_neighbours"]["p50_ms"] / v["alone"]["p50_ms"], 3) for s, v in out["servers"].items()
    }
    out["vs_baseline"] = {
        load: round(cur[load]["acts_per_s"] / base[load]["acts_per_s"], 3) for load in ("rest", "rest_batch")
    }
    return out
