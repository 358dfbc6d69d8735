"""How steady the scripted Ant gait is at each speed, measured on the window a fast multi-switch judges.

Every 100 judges a segment over its last 75 steps (settle-in 25), against a tolerance of 10% of the goal's speed.
This holds the gait of one level (`--level`, re-targeted to each `--targets` speed: stride frequency moved by its
feed-forward slope, speed loop aimed at the target) for `--seeds` 1,000-step episodes and reports, per speed, the
spread of the 75-step means after step 100 (every 5th start) and the share of them within 10% of the speed held
over [100, 1000). A level whose held windows miss that often cannot pass a ten-segment cycle, and neither can a
GMT imitating it. Play the cycles themselves with `research/behaviour_protocol.py --levels LEVEL --commands ...`.

Usage:
    python -m research.gait_sweep --level behaviour/ant/slow --targets 0.35 0.45 0.55 0.65 0.75 --noise-scale 0
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import gymnasium as gym
import numpy as np
import torch

from gmt.common.segments import held_windows
from gmt.datagen.behaviour import load_behaviour

WINDOW = 75  # steps measured in an every-100 segment
FIRST = 100  # windows start after the hold's settle-in
EVERY = 5  # steps between window starts
LOW_FREQ = 0.5  # the loop's lowest stride frequency (Hz), as in the levels written for 0.45-0.65 m/s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--level", required=True, help="A gait level with a speed loop (no suffix).")
    ap.add_argument("--targets", nargs="+", type=float, required=True, help="Speeds (m/s) to hold.")
    ap.add_argument("--noise-scale", type=float, default=1.0, help="Multiplier of the level's action noise.")
    ap.add_argument("--seeds", type=int, default=8, help="Episodes per speed (reset seeds 0..).")
    args = ap.parse_args()
    torch.set_num_threads(1)
    env = gym.make("Ant-v5")
    policy = load_behaviour(args.level, env.action_space)
    base = policy.cfg
    if base.target_speed is None:
        ap.error(f"{args.level} has no speed loop (target_speed)")
    policy.noise_scale = args.noise_scale
    print("target  held (m/s)      75-step std  std/held  within 10%")
    for target in args.targets:
        freq = base.freq + base.ff_slope * (target - base.target_speed)
        cfg = replace(base, freq=freq, target_speed=target, freq_range=(LOW_FREQ, base.freq_range[1]))
        windows, held = [], []
        for seed in range(args.seeds):
            obs, _ = env.reset(seed=seed)
            rng = np.random.default_rng(seed)
            policy.cfg = cfg
            policy.start_episode()
            v = []
            for _ in range(1000):
                obs, _, terminated, truncated, info = env.step(policy.act(obs, rng))
                v.append(info["x_velocity"])
                if terminated or truncated:
                    break
            v = np.asarray(v)
            held.append(v[FIRST:].mean())
            windows.append(held_windows(v, first=FIRST, length=WINDOW, every=EVERY))
        w, mean = np.concatenate(windows), float(np.mean(held))
        share = np.mean(np.abs(w - mean) <= 0.1 * mean)
        print(
            f"{target:6.2f}  {mean:.3f} +- {np.std(held):.3f}  {w.std():11.4f}  {w.std() / mean:8.3f}  {share:10.3f}"
        )


if __name__ == "__main__":
    main()
