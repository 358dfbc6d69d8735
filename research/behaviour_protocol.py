"""Play a speed-commanded behaviour agent through the GMT evaluation protocol: the ceiling of a GMT imitating it.

A GMT learns its transitions from the behaviour data, so if the commanded agent itself cannot change speed
within a multi-switch segment's settle-in, no GMT trained on its episodes will. This drives the agent with its
own commands on the evaluation protocol (docs/architecture.md) (15 seeds, holds, switches at 500, cycles every 300 / 200 / 100) and
judges it against the goal means of its collected data, with the GMT protocol's tolerance and settle-in.

Usage:
    python -m research.behaviour_protocol --env Hopper-v5 --levels DIR/slow DIR/fast --goals 0.898 2.026
    python -m research.behaviour_protocol --env Hopper-v5 --levels WORK/step_01200000 --commands 1.0 2.2  # goals: own holds

Governed levels (`python -m research.governor levels`) are played with their governor, the commands being its targets.
"""

from __future__ import annotations

import argparse
import warnings
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import torch

from gmt.common.segments import achieved, held_windows, measured_spans, tolerance, within
from gmt.datagen.behaviour import load_behaviour
from gmt.model.evaluate import protocol


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", required=True, help="Gymnasium id, e.g. Hopper-v5.")
    ap.add_argument(
        "--levels", nargs="+", required=True, help="Commanded snapshots, slowest first (no suffix)."
    )
    ap.add_argument(
        "--commands", nargs="+", type=float, help="Speeds to command one snapshot with, slowest first."
    )
    ap.add_argument(
        "--goals",
        nargs="+",
        type=float,
        help="The data's goal means, same order (default: each level's own mean speed held over [100, 1000) in "
        "episodes seeded after the protocol's, which is what its collected episodes' goal mean will be near).",
    )
    ap.add_argument("--seeds", type=int, default=15, help="Episodes per condition.")
    ap.add_argument("--noise-scale", type=float, default=1.0, help="Action-noise multiplier (collection's).")
    args = ap.parse_args()
    if args.goals is not None and len(args.commands or args.levels) != len(args.goals):
        ap.error("one goal mean per level (or per command)")
    torch.set_num_threads(1)
    env = gym.make(args.env)
    levels = [load_behaviour(p, env.action_space) for p in args.levels]
    if any(p.command is None for p in levels):
        ap.error("every level must be a commanded snapshot (metadata extra.command)")
    policy, commands = levels[0], args.commands or [p.target for p in levels]  # levels differ in the command
    policy.noise_scale = args.noise_scale
    means = args.goals or [hold_mean(env, policy, c, range(args.seeds, 2 * args.seeds)) for c in commands]
    goals = [SimpleNamespace(id=i, name=str(i), mean=m) for i, m in enumerate(means)]
    print(
        f"goal means {[round(g.mean, 3) for g in goals]}"
        + ("" if args.goals else " (held, seeds after the protocol's)")
    )
    for cond in protocol(len(goals)):
        per_step = np.zeros(1000, dtype=int)
        for step, g in cond.schedule:
            per_step[step:] = g
        ok = falls = 0
        means, runs = [], []
        for seed in range(args.seeds):
            obs, _ = env.reset(seed=seed)
            rng = np.random.default_rng(seed)
            policy.start_episode()
            v = np.full(1000, np.nan)
            for t in range(1000):
                policy.target = commands[per_step[t]]
                obs, _, terminated, truncated, info = env.step(policy.act(obs, rng))
                v[t] = info["x_velocity"]
                if terminated or truncated:
                    break
            falls += bool(terminated)
            runs.append(v)
            means.append([achieved(v, a, b) for _, a, b in measured_spans(per_step)])
            ok += not terminated and all(
                within(achieved(v, a, b), goals[g].mean, tolerance(goals[g], goals))
                for g, a, b in measured_spans(per_step)
            )
        with warnings.catch_warnings():  # a segment no episode reached (all fell) is NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            seg = " ".join(f"{m:.2f}" for m in np.nanmean(np.asarray(means), axis=0))
        held = ""
        if cond.kind == "hold":
            g = goals[cond.schedule[0][1]]
            w = held_windows(np.asarray(runs))  # [windows, seeds]; a window reaching past a fall fails
            held = f"  held 150-step windows within {np.mean(within(w, g.mean, tolerance(g, goals))):.2f}"
        print(f"{cond.name:12s} {ok:2d}/{args.seeds}  fell {falls}  segment means {seg}{held}", flush=True)


def hold_mean(env, policy, command: float, seeds: range) -> float:
    """Mean x-velocity over the hold span [100, 1000) of episodes `seeds` commanded `command` (falls left out)."""
    speeds = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        policy.start_episode()
        v = []
        for _ in range(1000):
            policy.target = command
            obs, _, terminated, truncated, info = env.step(policy.act(obs, rng))
            v.append(info["x_velocity"])
            if terminated or truncated:
                break
        if not terminated:
            speeds.append(np.mean(v[100:]))
    return float(np.mean(speeds)) if speeds else float("nan")


if __name__ == "__main__":
    main()
