"""Build the comparison tables of docs/results.md from `gmt eval --json` files.

Usage:
    python -m research.results_table ROW=PATH/eval.json [ROW=PATH/eval.json ...]
    python -m research.results_table --summary ROW=PATH/eval.json [...]

The first form prints one markdown row per file: successes out of seeds for every hold, ordered switch pair and
multi-switch. `--summary` prints one compact row per file (any task): the worst hold, the worst ordered switch
pair, all switch pairs together, and each multi-switch schedule.
"""

from __future__ import annotations

import json
import sys


def _cell(c: dict) -> str:
    return f"{c['successes']}/{c['episodes']}"


def full(evals: list[tuple[str, dict]]) -> None:
    """Every condition of the first file's protocol as a column."""
    names = [c["name"] for c in evals[0][1]["conditions"]]
    print("| method, data | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for name, d in evals:
        by = {c["name"]: c for c in d["conditions"]}
        cells = [_cell(by[n]) if n in by else "-" for n in names]
        print(f"| {name} | " + " | ".join(cells) + " |")


def summary(evals: list[tuple[str, dict]]) -> None:
    """Worst hold, worst switch pair, all pairs pooled, and every multi-switch schedule."""
    schedules = ["every 300", "every 200", "every 100"]
    print("| row | worst hold | worst switch | all switches | " + " | ".join(schedules) + " |")
    print("|---|---|---|---|" + "---|" * len(schedules))
    for name, d in evals:
        conds = d["conditions"]
        holds = [c for c in conds if c["name"].startswith("hold")]
        pairs = [c for c in conds if c["name"].startswith("switch")]
        by = {c["name"]: c for c in conds}
        worst_hold = min(holds, key=lambda c: c["successes"])
        worst_pair = min(pairs, key=lambda c: c["successes"])
        pooled = f"{sum(c['successes'] for c in pairs)}/{sum(c['episodes'] for c in pairs)}"
        cells = [
            f"{_cell(worst_hold)} ({worst_hold['name'].removeprefix('hold ')})",
            f"{_cell(worst_pair)} ({worst_pair['name'].removeprefix('switch ')})",
            pooled,
            *(_cell(by[s]) if s in by else "-" for s in schedules),
        ]
        print(f"| {name} | " + " | ".join(cells) + " |")


def main(args: list[str]) -> None:
    if not args or "--help" in args or "-h" in args:
        print(__doc__)
        return
    compact = "--summary" in args
    rows = [a.split("=", 1) for a in args if a != "--summary"]
    evals = [(name, json.load(open(path))) for name, path in rows]
    (summary if compact else full)(evals)


if __name__ == "__main__":
    main(sys.argv[1:])
