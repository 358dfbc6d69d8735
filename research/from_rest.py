"""How fast a commanded behaviour agent gets going from rest, on the span the first segment of a cycle is judged.

Every cycle of the evaluation protocol starts from the reset pose with goal 0, and every 100 judges that first
segment over steps [25, 100). On Hopper and Walker2d (0.008 s per step) that is 0.2-0.8 s after a standing start,
so the lowest goal's speed must be reached almost at once. This plays a commanded snapshot from rest at each
`--commands` value (held from step 0) and prints the mean x-velocity over [`--start`, `--end`) per command, over
`--seeds` resets: the fastest start the agent has, whatever a planner or a GMT makes of it.

Usage:
    python -m research.from_rest --env Hopper-v5 --level behaviour/hopper-gmt/hopper/slow --commands 1.6 2.6 3.2
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
    args = ap.parse_args()
    if not 0 <= args.start < args.end:
        ap.error("need 0 <= --start < --end")
    torch.set_num_threads(1)
    env = gym.make(args.env)
    policy = load_behaviour(args.level, env.action_space)
    if getattr(policy, "command", None) is None:
        ap.error(f"{args.level} is not a commanded snapshot")
    policy.noise_scale = args.noise_scale
    print(f"command  mean x-velocity over [{args.start}, {args.end}) from rest (min, max)  falls")
    for command in args.commands:
        means, falls = [], 0
        for seed in range(args.seeds):
            obs, _ = env.reset(seed=seed)
            rng = np.random.default_rng(seed)
            policy.start_episode()
            policy.target = command
            v = []
            for _ in range(args.end):
                obs, _, terminated, _, info = env.step(policy.act(obs, rng))
                v.append(info["x_velocity"])
                if terminated:
                    falls += 1
                    break
            if not terminated:
                means.append(float(np.mean(v[args.start :])))
        row = f"{np.mean(means):.3f} ({min(means):.3f}, {max(means):.3f})" if means else "all fell"
        print(f"{command:7.2f}  {row:>44s}  {falls}")


if __name__ == "__main__":
    main()
