"""How a model's speed change after a switch depends on where in its stride the switch finds it.

A legged gait's speed swings within each stride (Hopper's fast hop: ~2.0-2.9 m/s over ~80 steps), so a switch
to a slower goal lands at some point of that stride, and braking from some points takes longer. The evaluation
protocol (docs/architecture.md) switches at fixed steps, and its seeds start from nearly the same rest pose, so every episode of a
condition meets the switch at about the same point of the stride: a condition can pass or fail on where that
point happens to be. This plays the start of the every-N cycle (goal `--from-goal` for N steps, `--to-goal` for
N, then `--from-goal` again) with the third segment's switch moved by each offset in `--offsets`, and prints the
third segment's successes over 15 seeds (measured over [N/4, N) after its switch, as the protocol does).

Usage:
    python -m research.switch_phase runs/exp/hopper-planned [--every 200] [--offsets -60 -45 ... 60]
"""

from __future__ import annotations

import argparse
import warnings

import torch

from gmt.common.tables import markdown_table
from gmt.model.checkpoint import load_checkpoint
from gmt.model.evaluate import Condition, evaluate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", help="Checkpoint folder.")
    ap.add_argument("--every", type=int, default=200, help="Cycle length N in steps.")
    ap.add_argument("--offsets", type=int, nargs="+", default=list(range(-60, 61, 15)), help="Switch shifts.")
    ap.add_argument("--from-goal", type=int, default=0, help="Goal of the first and third segments.")
    ap.add_argument("--to-goal", type=int, help="Goal of the second segment (default: the highest).")
    ap.add_argument("--seeds", type=int, default=15, help="Episodes per offset (seeds 0..n-1).")
    ap.add_argument("--action-mode", help="The engine's action mode (default: the model's default).")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    torch.set_num_threads(1)
    ckpt = load_checkpoint(args.checkpoint)
    n, a = args.every, args.from_goal
    b = len(ckpt.goals) - 1 if args.to_goal is None else args.to_goal
    if min(args.offsets) <= -n:
        ap.error(f"offsets must be above -{n}")
    conds = [
        Condition(f"{d:+d}", "multi_switch", [(0, a), (n, b), (2 * n + d, a)], 3 * n + d)
        for d in args.offsets
    ]
    res = evaluate(
        ckpt,
        seeds=args.seeds,
        steps=3 * n + max(args.offsets),
        conditions=conds,
        progress=False,
        action_mode=args.action_mode,
    )
    rows = []
    for d, c in zip(args.offsets, res.to_dict()["conditions"], strict=True):
        third = c["segments"][2]
        rows.append(
            (
                f"{d:+d}",
                2 * n + d,
                f"{third['within']}/{args.seeds}",
                f"{third['achieved_mean']:.3f} ({third['achieved_std']:.3f})",
                f"{third['target']:.3f} ± {third['tolerance']:.3f}",
                c["terminated_early"],
            )
        )
    mode = args.action_mode or "the model's default"
    print(
        f"{args.checkpoint}: goal {a} -> {b} -> {a}, every {n}, third switch moved by each offset, {mode} actions\n"
    )
    print(markdown_table(("offset", "switch at", "third segment within", "mean (std)", "goal", "fell"), rows))


if __name__ == "__main__":
    main()
