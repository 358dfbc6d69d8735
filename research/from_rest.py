"""How fast a commanded behaviour agent gets going from rest, on the span the first segment of a cycle is judged.

Every cycle of the evaluation protocol starts from the reset pose with goal 0, and every 100 judges that first
segment over steps [25, 100). On Hopper and Walker2d (0.008 s per step) that is 0.2-0.8 s after a standing start,
so the lowest goal's speed must be reached almost at once. This plays a commanded snapshot from rest at each
`--commands` value (held from step 0) and prints the mean x-velocity over [`--start`, `--end`) per command, over
`--seeds` resets: the fastest start the agent has, whatever a planner or a GMT makes of it.

With `--then C` the command drops to C after `--switch-at` steps and the episode runs on to `--steps`: whether
a sprint from standing can be caught by the level's own command (falls and the steps they happened at).

Usage:
    python -m research.from_rest --env Hopper-v5 --level behaviour/hopper-gmt/hopper/slow --commands 1.6 2.6 3.2
    python -m research.from_rest --env Hopper-v5 --level behaviour/hopper-gmt/hopper/slow --commands 4.2 --then 1.6 \
        --switch-at 60 --steps 600
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
import torch

from gmt.datagen.behaviour import load_behaviour


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", required=True, help="Gymnasium id, e.g. Hopper-v5.")
    ap.add_argument("--level", required=True, help="A commanded snapshot (no suffix).")
    ap.add_argument("--commands", nargs="+", type=float, required=True, help="Commands to start with (m/s).")
    ap.add_argument("--start", type=int, default=25, help="First measured step (every 100's settle-in).")
    ap.add_argument("--end", type=int, default=100, help="End of the measured span (exclusive).")
    ap.add_argument("--seeds", type=int, default=10, help="Episodes per command (reset seeds 0..).")
    ap.add_argument("--noise-scale", type=float, default=1.0, help="Multiplier of the agent's action noise.")
    ap.add_argument("--then", type=float, help="Command after --switch-at steps (default: keep the first).")
    ap.add_argument("--switch-at", type=int, default=100, help="Step at which --then takes over.")
    ap.add_argument(
        "--steps", type=int, help="Steps per episode (default --end); falls are counted over them."
    )
    args = ap.parse_args()
    steps = args.steps or args.end
    if not 0 <= args.start < args.end <= steps:
        ap.error("need 0 <= --start < --end <= --steps")
    if args.then is not None and not 0 < args.switch_at < steps:
        ap.error("need 0 < --switch-at < --steps")
    torch.set_num_threads(1)
    env = gym.make(args.env)
    policy = load_behaviour(args.level, env.action_space)
    if getattr(policy, "command", None) is None:
        ap.error(f"{args.level} is not a commanded snapshot")
    policy.noise_scale = args.noise_scale
    then = "" if args.then is None else f", then {args.then:g} from step {args.switch_at}"
    print(
        f"command  mean x-velocity over [{args.start}, {args.end}) from rest (min, max)  falls in {steps} steps{then}"
    )
    for command in args.commands:
        means, fell_at = [], []
        for seed in range(args.seeds):
            obs, _ = env.reset(seed=seed)
            rng = np.random.default_rng(seed)
            policy.start_episode()
            v = []
            for t in range(steps):
                policy.target = command if args.then is None or t < args.switch_at else args.then
                obs, _, terminated, _, info = env.step(policy.act(obs, rng))
                v.append(info["x_velocity"])
                if terminated:
                    fell_at.append(t + 1)
                    break
            if len(v) >= args.end:
                means.append(float(np.mean(v[args.start : args.end])))
        row = f"{np.mean(means):.3f} ({min(means):.3f}, {max(means):.3f})" if means else "all fell"
        where = f" (at {', '.join(map(str, fell_at))})" if fell_at and steps > args.end else ""
        print(f"{command:7.2f}  {row:>44s}  {len(fell_at)}{where}")


if __name__ == "__main__":
    main()
