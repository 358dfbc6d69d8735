"""Screen a commanded PPO run's kept snapshots the way a GMT will be judged: against their own held speeds.

`gmt data commanded` keeps the snapshot with the fewest falls and the smallest error against the *commanded*
speeds. A GMT trained on a snapshot's data is judged against the data's goal means instead (what the snapshot
actually holds), on a cycle that starts from rest. This plays each snapshot's holds (`--hold-seeds` episodes per
command, steps [100, 1000)) and its every-N cycle from rest (`--seeds` episodes), judges the cycle's segments
against those held speeds with the GMT protocol's tolerance and settle-in (`play_schedule`), and flags snapshots whose two extreme
goals' bands overlap (one speed would then pass both). Export the one you choose with
`gmt data commanded ... --select-only --snapshot STEP`, then play it fully with `research/behaviour_protocol.py`.

Usage:
    python -m research.screen_commanded --env Hopper-v5 --work-dir runs/behaviour/hopper-16-26 --commands 1.6 2.6
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import torch

from gmt.common.segments import tolerance, within
from gmt.datagen.behaviour import load_behaviour
from gmt.datagen.train_commanded import cycle_schedule, play_schedule
from research.behaviour_protocol import hold_mean


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", required=True, help="Gymnasium id, e.g. Hopper-v5.")
    ap.add_argument("--work-dir", type=Path, required=True, help="The run's --work-dir (step_*.safetensors).")
    ap.add_argument(
        "--commands", nargs="+", type=float, required=True, help="The levels' commands, slowest first."
    )
    ap.add_argument("--every", type=int, default=200, help="Cycle length in steps.")
    ap.add_argument("--seeds", type=int, default=8, help="Cycle episodes per snapshot.")
    ap.add_argument("--hold-seeds", type=int, default=4, help="Hold episodes per command (seeds from 100).")
    ap.add_argument("--from-step", type=int, default=0, help="Skip snapshots before this training step.")
    ap.add_argument("--steps", nargs="+", type=int, help="Screen only these training steps (default: all).")
    args = ap.parse_args()
    torch.set_num_threads(1)
    env = gym.make(args.env)
    schedule = cycle_schedule(args.commands, args.every)
    segment_goals = [args.commands.index(c) for _, c in schedule]
    name = f"every {args.every}"
    snaps = sorted(args.work_dir.glob("step_*.safetensors"))
    print("| snapshot | held speeds (m/s) | bands | " + name + " | falls | segments within | first segment |")
    print("|---|---|---|---|---|---|---|")
    for path in snaps:
        train_step = int(path.stem.removeprefix("step_"))
        if train_step < args.from_step or (args.steps and train_step not in args.steps):
            continue
        policy = load_behaviour(path.with_suffix(""), env.action_space)
        held = [hold_mean(env, policy, c, range(100, 100 + args.hold_seeds)) for c in args.commands]
        if any(np.isnan(held)):
            print(f"| {train_step:,} | fell in every hold of a level | | | | | |", flush=True)
            continue
        goals = [SimpleNamespace(id=i, name=str(i), mean=m) for i, m in enumerate(held)]
        lo, hi = goals[0], goals[-1]
        overlap = lo.mean + tolerance(lo, goals) >= hi.mean - tolerance(hi, goals)
        ok = falls = 0
        seg_ok, first = np.zeros(len(schedule), dtype=int), []
        for seed in range(args.seeds):
            out = play_schedule(env, policy, schedule, seed, np.random.default_rng(seed))
            falls += out["fell"]
            hits = [
                not out["fell"] and bool(within(m, goals[g].mean, tolerance(goals[g], goals)))
                for m, g in zip(out["speeds"], segment_goals, strict=True)
            ]
            seg_ok += hits
            ok += all(hits)
            first.append(out["speeds"][0])
        print(
            f"| {train_step:,} | {' / '.join(f'{m:.3f}' for m in held)} | {'overlap' if overlap else 'apart'} "
            f"| {ok}/{args.seeds} | {falls} | {', '.join(map(str, seg_ok))} | {np.nanmean(first):.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
