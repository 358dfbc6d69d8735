"""Search the parameters of the scripted Ant gait (`gmt.datagen.gait`) with a simple evolution strategy.

Two stages, each a (5, 16) evolution strategy with log-rank weights over a 14-number parameter vector:

1. **Speed**: from a trot-like guess, maximise the mean x-velocity over steps [100, 500) of two noisy episodes,
   docked for speed swings (std of its 50-step means), heading drift and any fall.
2. **Two levels**: from stage 1's best, the same stride at `freq` (fast) and `freq - slow_offset` (slow) must
   both be steady: the score is the fast speed minus 3 x the per-episode speed spread of each level, docked for
   speed swings, heading, torso height above 0.92 m (Ant-v5 ends an episode above 1.0 m) and falls.

Usage:
    python -m research.search_gait --seed 0 --out runs/gait/search-s0.json

The output is a `GaitConfig` (JSON, `freq` the fast level's) with the search's scores and command; `gmt data
gait` turns it into behaviour levels. Each evaluation plays whole Ant-v5 episodes, so a stage-1 generation takes
~8 s and a stage-2 one ~60 s on one core.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from dataclasses import asdict
from pathlib import Path

import gymnasium as gym
import numpy as np

from gmt.datagen.gait import GaitConfig, GaitPolicy, gait_meta, heading

DIM = 14
POP, ELITE = 16, 5


def unpack(x: np.ndarray) -> GaitConfig:
    """Parameter vector -> gait (frequency kept above 1 Hz, ankle centre near 0.8 rad, gain above 0.5)."""
    return GaitConfig(
        freq=1.0 + abs(float(x[0])),
        hip_amp=float(x[1]),
        ankle_amp=float(x[2]),
        hip_phase=[float(v) for v in x[3:7]],
        ankle_phase=[float(v) for v in x[7:11]],
        ankle_centre=0.8 + 0.3 * float(x[11]),
        yaw_gain=float(x[12]),
        kp=max(0.5, 2.0 + float(x[13])),
        kd=0.05,
    )


def play(env, cfg: GaitConfig, steps: int, seed: int, noise: float) -> dict:
    """One episode of the gait with Gaussian action noise: x-velocities, torso heights, headings, fall step."""
    policy = GaitPolicy(gait_meta("search", cfg), np.full(8, np.log(noise)), env.action_space.low,
                        env.action_space.high)  # fmt: skip
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    policy.start_episode()
    vx, z, yaw = [], [], []
    for t in range(steps):
        obs, _, terminated, _, info = env.step(policy.act(obs, rng))
        vx.append(info["x_velocity"])
        z.append(obs[0])
        yaw.append(heading(obs))
        if terminated:
            return {"fell": t, "vx": np.array(vx), "z": np.array(z), "yaw": np.array(yaw)}
    return {"fell": None, "vx": np.array(vx), "z": np.array(z), "yaw": np.array(yaw)}


def swings(v: np.ndarray) -> float:
    """Std of the 50-step running means of a speed trace."""
    return float(np.convolve(v, np.ones(50) / 50, "valid").std())


def speed_score(env, x: np.ndarray, noise: float) -> float:
    """Stage 1: fast and steady, two episodes of 500 steps."""
    cfg, total = unpack(x), 0.0
    for seed in (0, 1):
        r = play(env, cfg, 500, seed, noise)
        if r["fell"] is not None:
            total += -5 + r["fell"] / 500
            continue
        v = r["vx"][100:]
        total += v.mean() - swings(v) - 0.5 * abs(r["yaw"][-1]) - 2 * max(0.0, r["z"].max() - 0.9)
    return total / 2


def levels_score(env, x: np.ndarray, noise: float, slow_offset: float, seed: int) -> float:
    """Stage 2: both levels steady and apart, two episodes of 600 steps each."""
    cfg, total, speeds = unpack(x), 0.0, {0: [], 1: []}
    for level, offset in enumerate((-slow_offset, 0.0)):
        for s in (seed * 10, seed * 10 + 1):
            r = play(env, cfg.with_freq(cfg.freq + offset), 600, s, noise)
            if r["fell"] is not None:
                return -5 + r["fell"] / 600
            v = r["vx"][100:]
            speeds[level].append(v.mean())
            total -= 2 * swings(v) + 0.5 * np.abs(r["yaw"]).mean() + 5 * max(0.0, r["z"].max() - 0.92)
    slow, fast = np.array(speeds[0]), np.array(speeds[1])
    return total / 4 + fast.mean() - 3 * (slow.std() + fast.std())


def evolve(
    score, start: np.ndarray, sigma: float, gens: int, rng, freq_step: float = 1.0, label: str = ""
) -> tuple:
    """(ELITE, POP) evolution strategy; returns the best (score, vector) seen."""
    mean, best = start.copy(), (-np.inf, start.copy())
    weights = np.log(ELITE + 0.5) - np.log(np.arange(1, ELITE + 1))
    weights /= weights.sum()
    for gen in range(gens):
        eps = rng.standard_normal((POP, DIM))
        eps[:, 0] *= freq_step
        xs = mean + sigma * eps
        f = np.array([score(x) for x in xs])
        order = np.argsort(-f)
        if f[order[0]] > best[0]:
            best = (float(f[order[0]]), xs[order[0]].copy())
        mean = (weights[:, None] * xs[order[:ELITE]]).sum(0)
        sigma *= 0.97
        print(
            f"{label} gen {gen}: best {f[order[0]]:.3f} median {np.median(f):.3f} overall {best[0]:.3f}",
            flush=True,
        )
    return best


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--speed-gens", type=int, default=40, help="stage-1 generations")
    p.add_argument("--level-gens", type=int, default=15, help="stage-2 generations")
    p.add_argument("--slow-offset", type=float, default=0.5, help="Hz between the fast and the slow level")
    p.add_argument("--noise", type=float, default=0.1, help="action-noise std while searching")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    rng = np.random.default_rng(args.seed)
    env = gym.make("Ant-v5")
    start = np.zeros(DIM)
    start[0], start[1], start[2] = 0.5, 0.3, 0.2
    start[3:7] = [0.0, np.pi, 0.0, 0.0]  # hips: a trot-like guess
    start[7:11] = 3 * np.pi / 2
    s1, x1 = evolve(
        lambda x: speed_score(env, x, args.noise), start, 0.25, args.speed_gens, rng, label="speed"
    )
    s2, x2 = evolve(lambda x: levels_score(env, x, args.noise, args.slow_offset, args.seed), x1, 0.1,
                    args.level_gens, rng, freq_step=0.3, label="levels")  # fmt: skip
    out = {
        "gait": asdict(unpack(x2)),
        "slow_freq": unpack(x2).freq - args.slow_offset,
        "speed_score": s1,
        "levels_score": s2,
        "command": "python -m research.search_gait " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
