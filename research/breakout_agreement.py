"""Where a Breakout imitator leaves its teacher: play a goal and ask the scripted level, at every state the model
reaches, what it would have done.

An imitator with a tiny training loss can still lose the ball: the loss is measured on the teacher's states, play
visits the imitator's own. This plays `--seeds` episodes of one goal through the engine and, at each step, asks
the scripted level (`gmt.datagen.breakout`, from the emulator's RAM) for its action on that same state, as
DAgger would label it. It reports how often the two agree: over all steps, and on the steps that decide a catch
(the ball descending in the lower half of the field), with the return and the balls lost.

    python -m research.breakout_agreement runs/gpu/breakout-gpu-b256 --goal 4 --level ace --seeds 10
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from gmt.common.envs import make_env
from gmt.datagen.breakout import LEVELS, TrackingAgent, read_ram
from gmt.model.checkpoint import load_checkpoint, model_info
from gmt.model.engine import PolicyEngine

LOW_HALF = 100  # RAM ball y below which (larger y) a descending ball is on its way to the paddle (at ~183)


def agreement(
    checkpoint: str,
    goal: int,
    level: str,
    seeds: list[int],
    steps: int = 1000,
    action_mode: str | None = None,
    teacher_drives: bool = False,
) -> dict:
    """Play `goal` from each seed and compare every action with `level`'s on the same state.

    With `teacher_drives` the level's actions are the ones played (the model is only asked): the agreement on
    the teacher's own states, the distribution the model was trained on. The model's context then holds its own
    answers as the previous actions, not the played ones.

    Returns:
        {"overall", "deciding"}: share of steps where the model's action equals the level's (all steps; steps
        with the ball descending below y 100), "steps", "deciding_steps", "return" and "lives_lost" (means over
        the episodes), and the per-seed figures under "episodes".
    """
    ckpt = load_checkpoint(checkpoint)
    engine = PolicyEngine(ckpt)
    spec = model_info(ckpt)
    mode = action_mode or engine.default_action_mode
    episodes = []
    for seed in seeds:
        env = make_env(spec, max_steps=steps)
        obs, info = env.reset(seed=seed)
        ctx = engine.new_context(goal, mode, seed=seed)
        teacher = TrackingAgent(LEVELS[level])
        same = deciding = deciding_same = n = 0
        ret, lives0, lives, before = 0.0, info.get("lives", 5), info.get("lives", 5), None
        for _ in range(steps):
            state = read_ram(env)
            label = teacher.decide(state, np.random.default_rng(0))
            (a,) = engine.act([ctx], [obs])
            if isinstance(a, Exception):
                raise a
            a = int(a)
            played = label if teacher_drives else a
            teacher.played(played)  # the paddle moves as it was moved
            critical = before is not None and state.ball_y > before.ball_y and state.ball_y > LOW_HALF
            same += a == label
            deciding += critical
            deciding_same += critical and a == label
            n += 1
            before = state
            obs, r, term, trunc, info = env.step(played)
            ret += float(r)
            lives = info.get("lives", lives)
            if term or trunc:
                break
        env.close()
        episodes.append(
            {
                "seed": seed,
                "steps": n,
                "overall": same / max(n, 1),
                "deciding": deciding_same / max(deciding, 1),
                "deciding_steps": deciding,
                "return": ret,
                "lives_lost": int(lives0 - lives),
            }
        )

    def mean(key: str) -> float:
        return float(np.mean([e[key] for e in episodes]))

    return {
        "checkpoint": checkpoint,
        "goal": goal,
        "level": level,
        "action_mode": mode,
        "driver": "teacher" if teacher_drives else "model",
        **{
            k: round(mean(k), 4)
            for k in ("overall", "deciding", "steps", "deciding_steps", "return", "lives_lost")
        },
        "episodes": episodes,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--goal", type=int, required=True, help="goal id to play")
    ap.add_argument("--level", required=True, help=f"scripted level to compare with ({', '.join(LEVELS)})")
    ap.add_argument("--seeds", type=int, default=10, help="episodes (seeds 0..n-1)")
    ap.add_argument("--steps", type=int, default=1000, help="agent steps per episode at most")
    ap.add_argument("--action-mode", default=None, help="engine action mode (default: the checkpoint's)")
    ap.add_argument(
        "--teacher-drives", action="store_true", help="play the level's actions, only asking the model"
    )
    ap.add_argument("--json", default=None, help="write the result here")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    res = agreement(
        a.checkpoint, a.goal, a.level, list(range(a.seeds)), a.steps, a.action_mode, a.teacher_drives
    )
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
    print(json.dumps({k: v for k, v in res.items() if k != "episodes"}))


if __name__ == "__main__":
    main()
