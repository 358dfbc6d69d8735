"""Evaluate a checkpoint under inference variants the product does not offer, to test a diagnosis.

`gmt eval` plays the evaluation protocol (docs/architecture.md) as the server would act. Two questions about a model that misses the bar
need the same protocol with one thing changed:

- `--restart`: at every goal switch the session's context is cleared (as `POST /sessions/{id}/reset` with the new
  goal would), so the model meets the switch exactly as it met a pool-started training episode: an empty
  context at a state another level visited. If the model failed because of its old-goal context, this passes.
  Like the server's reset it also restarts the session's step, so the sampled action noise after a switch
  repeats the episode's first steps' draws.
- `--cap X`: the largest action-noise standard deviation `sample` adds (`gmt.model.sampling.SAMPLE_STD_CAP`, 0.1),
  to see whether the capped noise, not the model, sets a goal's speed.

It also prints, per hold, the share of its 150-step windows from step 200 on that are within the goal's
tolerance: how steady the held gait is where a 200-step cycle would measure it, the model's counterpart of the
last column of `research/data_transients.py`.

Usage:
    python -m research.eval_variants runs/exp/hopper-settled-t75 --restart --json results/X.json
    python -m research.eval_variants runs/exp/hopper-settled-t75 --cap 0.25 --first-seed 15
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np
import torch

import gmt.model.evaluate as evaluate_module
import gmt.model.sampling as sampling_module
from gmt.common.segments import held_windows, tolerance, within
from gmt.model.checkpoint import load_checkpoint
from gmt.model.engine import PolicyEngine


class RestartAtSwitch(PolicyEngine):
    """A `PolicyEngine` whose `set_goal` clears the context and starts it afresh with the new goal."""

    def set_goal(self, ctx, goal: int, blend_steps: int = 0) -> None:
        self.reset(ctx, goal)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", help="Checkpoint folder.")
    ap.add_argument("--restart", action="store_true", help="Clear the context at every goal switch.")
    ap.add_argument(
        "--cap", type=float, default=sampling_module.SAMPLE_STD_CAP, help="Cap of the sampled noise std."
    )
    ap.add_argument("--first-seed", type=int, default=0, help="Seeds first..first+14 (the protocol: 0).")
    ap.add_argument("--json", type=Path, help="Write the evaluation JSON (gmt eval's schema) here.")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    torch.set_num_threads(1)
    sampling_module.SAMPLE_STD_CAP = args.cap  # read when an engine is built
    if args.restart:
        evaluate_module.PolicyEngine = RestartAtSwitch
    judge, seen = evaluate_module.judge, {}

    def keep_signal(ckpt, conds, seeds, signal, *rest):
        seen["signal"] = signal  # [conditions x seeds, steps] per-step statistic, NaN after a fall
        return judge(ckpt, conds, seeds, signal, *rest)

    evaluate_module.judge = keep_signal
    ckpt = load_checkpoint(args.checkpoint)
    seeds = list(range(args.first_seed, args.first_seed + 15))
    res = evaluate_module.evaluate(ckpt, seeds=seeds, progress=False)
    out = res.to_dict()
    steady = {}
    for ci, c in enumerate(out["conditions"]):
        if c["kind"] != "hold":
            continue
        goal = ckpt.goals[c["schedule"][0][1]]
        v = seen["signal"][ci * len(seeds) : (ci + 1) * len(seeds)]  # [seeds, steps]
        m = held_windows(v)  # [windows, seeds]; a window reaching past a fall is NaN and fails
        steady[c["name"]] = float(np.mean(within(m, goal.mean, tolerance(goal, ckpt.goals))))
    out["held_windows_within"] = steady
    out["variant"] = {
        "restart_at_switch": args.restart,
        "sample_std_cap": args.cap,
        "first_seed": args.first_seed,
    }
    print(f"{args.checkpoint}: {out['variant']}")
    for c in out["conditions"]:
        segs = " ".join(f"{s['achieved_mean']:.2f} ({s['achieved_std']:.2f})" for s in c["segments"])
        print(f"  {c['name']:12s} {c['successes']:2d}/15  fell {c['terminated_early']:2d}  {segs}")
    print(
        "  held gait, share of 150-step windows from step 200 within tolerance: "
        + ", ".join(f"{k} {v:.2f}" for k, v in steady.items())
    )
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
