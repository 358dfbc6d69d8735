"""A planned sprint from standing: how close a commanded agent can come to every 100's first segment without falling.

`research.from_rest` holds one command from the reset pose: on Hopper the commands fast enough for every 100's
first segment (judged over [25, 100)) throw the hopper over later. Here a planner (`datagen.plan.PlannedPolicy`)
chooses every `--every` steps among continuations that hold a sprint command (`--sprint-commands`) for
`--hold` steps and then hand back to the level's own command for the rest of a long `--horizon`, so that a
sprint which falls later ranks last. Until `--settle-at` the continuations are scored against `--sprint-target`
(above the level's speed: urgent); from then on against the level's own speed, with `--settle-commands`. Prints,
per reset seed, the mean x-velocity over the spans every 100, every 200 and every 300 judge their first segment
on, and whether and when it fell.

Usage:
    python -m research.rest_sprint --env Hopper-v5 --level behaviour/hopper3-gmt/hopper/slow \
        --sprint-commands 5.0 4.6 4.2 3.8 --sprint-target 2.6 --settle-at 60 --seeds 3
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
import torch

from gmt.common.tables import markdown_table
from gmt.datagen.behaviour import load_behaviour
from gmt.datagen.plan import PlanConfig, PlannedPolicy

# Spans on which every 100 / 200 / 300 judge their first segment (settle-in of a quarter, gmt.common.segments).
SPANS = ((25, 100), (50, 200), (75, 300))


class SprintPlan(PlannedPolicy):
    """`PlannedPolicy` whose continuations hold their command for `hold` steps, then the level's own command, and
    whose plan turns from the sprint to the level's own speed at step `settle_at`.

    Args:
        policy: A commanded `BehaviourPolicy`.
        env: The environment the episode runs in.
        sprint: The plan until `settle_at` (its `target` is the sprint target, required).
        settle: The plan from `settle_at` on (its `target`; None: the level's measured speed, as `PlannedPolicy`).
        hold: Steps a continuation holds its command before the level's own command takes over.
        settle_at: Step from which `settle` plans.
    """

    def __init__(self, policy, env, sprint: PlanConfig, settle: PlanConfig, hold: int, settle_at: int):
        if sprint.target is None:
            raise ValueError("the sprint plan needs a target speed")
        super().__init__(policy, env, settle)  # resolves the level's speed where `settle.target` is None
        self.plans = ((sprint, sprint.target), (settle, self.target))
        self.own, self.hold, self.settle_at = policy.command, hold, settle_at

    def start_episode(self) -> None:
        super().start_episode()
        self.cfg, self.target = self.plans[0]

    def _plan(self, rng):
        if self.t - 1 >= self.settle_at:  # act() has counted the current step already
            self.cfg, self.target = self.plans[1]
        return super()._plan(rng)

    def _simulate(self, sim, rng):
        held, act, played = self.policy.command, self.policy.act, 0

        def hand_back(obs, rng=None):  # the level's own command once `hold` actions are played
            nonlocal played
            if played == self.hold:
                self.policy.command = self.own
            played += 1
            return act(obs, rng)

        self.policy.act = hand_back
        try:
            return super()._simulate(sim, rng)
        finally:
            self.policy.act, self.policy.command = act, held


def run(
    env_id: str,
    level: str,
    sprint: PlanConfig,
    settle: PlanConfig,
    hold: int,
    settle_at: int,
    seeds: int,
    steps: int,
) -> tuple[float, list[dict]]:
    """Play `seeds` episodes from rest with the sprint plan.

    Returns:
        The settling plan's target speed, and per episode the spans' mean speeds and the fall step.
    """
    env = gym.make(env_id, max_episode_steps=steps)
    policy = load_behaviour(level, env.action_space)
    if getattr(policy, "command", None) is None:
        raise ValueError(f"{level} is not a commanded snapshot")
    planner = SprintPlan(policy, env, sprint, settle, hold, settle_at)
    rows = []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        obs, _ = env.reset(seed=seed)
        planner.start_episode()
        speeds, fell = [], None
        for t in range(steps):
            obs, _, terminated, truncated, info = env.step(planner.act(obs, rng))
            speeds.append(float(info["x_velocity"]))
            if terminated:
                fell = t
                break
            if truncated:
                break
        v = np.asarray(speeds)
        spans = {f"[{a}, {b})": float(v[a:b].mean()) if len(v) >= b else float("nan") for a, b in SPANS}
        rows.append({"seed": seed, **spans, "fell at": fell})
    return planner.plans[1][1], rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", required=True, help="Gymnasium id, e.g. Hopper-v5.")
    ap.add_argument("--level", required=True, help="A commanded snapshot (no suffix).")
    ap.add_argument("--sprint-commands", nargs="+", type=float, required=True, help="Sprint commands (m/s).")
    ap.add_argument("--sprint-target", type=float, required=True, help="Speed the sprint is scored against.")
    ap.add_argument("--settle-commands", nargs="+", type=float, help="Commands after --settle-at (default: 2.0 "
                    "1.6 1.2 0.8 around a 1.6 level; give the level's own and lower ones).")  # fmt: skip
    ap.add_argument(
        "--settle-at", type=int, default=60, help="Step from which the plan aims at the level's speed."
    )
    ap.add_argument("--hold", type=int, default=20, help="Steps a continuation holds its sprint command.")
    ap.add_argument("--every", type=int, default=20, help="Steps played before deciding again.")
    ap.add_argument("--horizon", type=int, default=300, help="Steps simulated per sprint continuation.")
    ap.add_argument(
        "--settle-horizon", type=int, default=80, help="Steps simulated per settling continuation."
    )
    ap.add_argument("--per-command", type=int, default=4, help="Continuations per command at each decision.")
    ap.add_argument("--planned-steps", type=int, default=200, help="Leading steps planned.")
    ap.add_argument("--steps", type=int, default=600, help="Steps per episode; falls are counted over them.")
    ap.add_argument("--seeds", type=int, default=3, help="Episodes (reset seeds 0..).")
    args = ap.parse_args()
    if not 0 < args.hold <= args.horizon or args.settle_at < 0 or args.steps < SPANS[-1][1]:
        ap.error(f"need 0 < --hold <= --horizon, --settle-at >= 0 and --steps >= {SPANS[-1][1]}")
    torch.set_num_threads(1)
    settle_commands = tuple(args.settle_commands or (2.0, 1.6, 1.2, 0.8))
    sprint = PlanConfig(
        commands=tuple(args.sprint_commands),
        candidates=len(args.sprint_commands) * args.per_command,
        every=args.every,
        horizon=args.horizon,
        steps=args.planned_steps,
        target=args.sprint_target,
    )
    settle = PlanConfig(
        commands=settle_commands,
        candidates=len(settle_commands) * args.per_command,
        every=args.every,
        horizon=args.settle_horizon,
        steps=args.planned_steps,
    )
    speed, rows = run(args.env, args.level, sprint, settle, args.hold, args.settle_at, args.seeds, args.steps)
    print(
        f"{args.level} (level speed {speed:.3f} m/s): mean x-velocity over each first-segment span, from rest"
    )
    head = list(rows[0])
    print(
        markdown_table(
            head, [[f"{r[k]:.3f}" if isinstance(r[k], float) else r[k] for k in head] for r in rows]
        )
    )


if __name__ == "__main__":
    main()
