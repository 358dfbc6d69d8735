"""Why a behaviour snapshot's episodes end early: the torso above or below the task's healthy height range.

Plays `--episodes` stochastic episodes per command (seeds 100+) of each snapshot and prints, for every episode that
terminated, the command, the step, the side of the healthy z-range the torso left by, and the torso's up-vector
z-component (1: upright, below 0: on its back). On Ant-v5 every termination of the commanded and per-level runs
measured so far was a bounce out of the top of (0.2, 1.0), not a flip onto the back.

Usage:
    python -m research.terminations --env Ant-v5 runs/behaviour/ant-05-10-s0/step_01500000 --commands 0.5 1.0
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from gmt.datagen.behaviour import load_behaviour


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("snapshots", nargs="+", type=Path, help="Snapshots without suffix (WORK_DIR/step_N).")
    ap.add_argument("--env", required=True, help="Gymnasium id, e.g. Ant-v5.")
    ap.add_argument("--commands", nargs="+", type=float, help="Commands to play a commanded snapshot at.")
    ap.add_argument("--episodes", type=int, default=12, help="Episodes per command.")
    args = ap.parse_args()
    torch.set_num_threads(1)
    env = gym.make(args.env)
    low, high = getattr(env.unwrapped, "_healthy_z_range", (-np.inf, np.inf))
    for path in args.snapshots:
        policy = load_behaviour(path, env.action_space)
        commands = args.commands if policy.command is not None and args.commands else [policy.command]
        ends, played = [], 0
        for command in commands:
            if command is not None:
                policy.command = command
            for seed in range(100, 100 + args.episodes):
                obs, _ = env.reset(seed=seed)
                policy.start_episode()
                rng = np.random.default_rng(seed)
                played += 1
                for t in range(1000):
                    obs, _, terminated, truncated, _ = env.step(policy.act(obs, rng))
                    if terminated:
                        torso = env.unwrapped.data.body("torso")
                        z, up = float(torso.xpos[2]), float(torso.xmat.reshape(3, 3)[2, 2])
                        side = "above" if z > high else "below" if z < low else "inside"
                        ends.append(f"{command} at {t}: {side} ({z:.2f} m, up {up:+.2f})")
                        break
                    if truncated:
                        break
        print(f"{path}: {len(ends)} of {played} ended early" + "".join(f"\n  {e}" for e in ends), flush=True)


if __name__ == "__main__":
    main()
