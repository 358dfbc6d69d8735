"""Build the comparison table of docs/results.md from `gmt eval --json` files.

Usage: python tools/results_table.py ROW=PATH/eval.json [ROW=PATH/eval.json ...]
Prints one markdown row per file: successes out of seeds for every hold, ordered switch pair and multi-switch.
"""

from __future__ import annotations

import json
import sys


def main(args: list[str]) -> None:
    rows = [a.split("=", 1) for a in args]
    evals = [(name, json.load(open(path))) for name, path in rows]
    names = [c["name"] for c in evals[0][1]["conditions"]]
    print("| method, data | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for name, d in evals:
        by = {c["name"]: c for c in d["conditions"]}
        cells = [f"{by[n]['successes']}/{by[n]['episodes']}" if n in by else "-" for n in names]
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(sys.argv[1:])
