"""Goal-switching evaluation (docs/architecture.md, "Evaluation protocol"; paper section 3.1 and A.2.3).

All episodes of every condition step in lockstep through the batched `PolicyEngine`, which is also what the
server uses. Conditions: hold every goal; every ordered switch pair at mid-episode; cycling through the goals
every N steps. Segments, their settle-in, the tolerance and success are `gmt.common.segments`' (the definition the
remote runner uses too): an episode succeeds when it never terminates early and every segment's mean statistic
after its settle-in of min(100, length // 4) steps lies within tolerance of its goal's dataset mean.

JSON schema (`EvalResult.to_dict`):
    checkpoint, env_id, statistic, action_mode, seeds (list), episode_steps, wall_time_s,
    goals: [{id, name, mean, std, min, max, count, tolerance}],
    conditions: [{
        name ("hold 0", "switch 0->2", "every 200"), kind ("hold" | "switch" | "multi_switch"),
        schedule: [[step, goal], ...],
        episodes, successes, terminated_early, never_switched (episodes that ended before a goal change: failures),
        segments: [{goal, start, end (the measured steps [start, end)), target, tolerance, achieved_mean,
                    achieved_std, within (count)}],
    }]
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
from tqdm import tqdm

from gmt.common.segments import achieved, measured_spans, tolerance, within
from gmt.common.statistics import get_statistic, signal_from_step
from gmt.common.tables import markdown_table
from gmt.model.checkpoint import Checkpoint, Goal
from gmt.model.engine import PolicyEngine

__all__ = ["Condition", "ConditionResult", "EvalResult", "evaluate", "judge", "protocol", "tolerance"]

MULTI_SWITCH_EVERY = (300, 200, 100)


@dataclass
class Condition:
    """One evaluation condition: a goal schedule and the segments it is judged on.

    Attributes:
        name: Human-readable name.
        kind: hold, switch or multi_switch.
        schedule: (step, goal) pairs; the goal applies from that step on.
        steps: Episode length.
    """

    name: str
    kind: str
    schedule: list[tuple[int, int]]
    steps: int

    @property
    def segments(self) -> list[tuple[int, int, int]]:
        """(goal, start, end) of the measured steps of each segment (`gmt.common.segments.measured_spans`)."""
        return measured_spans([self.goal_at(t) for t in range(self.steps)])

    def goal_at(self, step: int) -> int:
        """The scheduled goal at `step`."""
        g = self.schedule[0][1]
        for s, goal in self.schedule:
            if s <= step:
                g = goal
        return g


def protocol(
    n_goals: int, steps: int = 1000, multi_every: tuple[int, ...] = MULTI_SWITCH_EVERY
) -> list[Condition]:
    """The conditions of the evaluation protocol (docs/architecture.md) for `n_goals` goals and `steps`-step episodes.

    For 1000 steps, holds are measured over [100, 1000), switches at 500 over [100, 500) and [600, 1000), and
    cycles of N steps after their first N/4 steps (a shorter last cycle after a quarter of its own length).
    """
    half = steps // 2
    conds = [Condition(f"hold {g}", "hold", [(0, g)], steps) for g in range(n_goals)]
    for a in range(n_goals):
        for b in range(n_goals):
            if a != b:
                conds.append(Condition(f"switch {a}->{b}", "switch", [(0, a), (half, b)], steps))
    for n in multi_every:
        if n >= steps:
            continue
        sched = [(s, (s // n) % n_goals) for s in range(0, steps, n)]
        conds.append(Condition(f"every {n}", "multi_switch", sched, steps))
    return conds


@dataclass
class ConditionResult:
    """Outcome of one condition over all seeds."""

    condition: Condition
    signal: np.ndarray  # [E, steps] per-step statistic signal (NaN after an early termination)
    terminated: np.ndarray  # [E] bool
    segment_means: np.ndarray  # [E, S]
    success: np.ndarray  # [E] bool
    segments: list[dict] = field(default_factory=list)

    @property
    def never_switched(self) -> int:
        """Episodes that ended before one of the condition's goal changes: a switch that never happened (and a
        failure, as every early end is)."""
        changes = [s for s, _ in self.condition.schedule[1:] if s < self.signal.shape[1]]
        if not changes:
            return 0
        return int(np.isnan(self.signal[:, changes]).any(axis=1).sum())

    def to_dict(self) -> dict:
        """JSON-ready summary (without the per-step signal)."""
        c = self.condition
        return {
            "name": c.name,
            "kind": c.kind,
            "schedule": [list(x) for x in c.schedule],
            "episodes": int(len(self.success)),
            "successes": int(self.success.sum()),
            "terminated_early": int(self.terminated.sum()),
            "never_switched": self.never_switched,
            "segments": self.segments,
        }


@dataclass
class EvalResult:
    """All conditions of one evaluation run."""

    checkpoint: str
    env_id: str
    statistic: str
    action_mode: str
    seeds: list[int]
    episode_steps: int
    goals: list[Goal]
    results: list[ConditionResult]
    wall_time_s: float
    switch_relabel_steps: int = 0  # steps of context each goal change relabelled (`PolicyEngine.set_goal`)
    precision: str = "fp32"  # the engine's arithmetic (`PolicyEngine`'s `precision`)

    def to_dict(self) -> dict:
        """The documented JSON form."""
        return {
            "checkpoint": self.checkpoint,
            "env_id": self.env_id,
            "statistic": self.statistic,
            "action_mode": self.action_mode,
            "switch_relabel_steps": self.switch_relabel_steps,
            **({"precision": self.precision} if self.precision != "fp32" else {}),
            "seeds": self.seeds,
            "episode_steps": self.episode_steps,
            "wall_time_s": round(self.wall_time_s, 1),
            "goals": [{**asdict(g), "tolerance": tolerance(g, self.goals)} for g in self.goals],
            "conditions": [r.to_dict() for r in self.results],
        }

    def markdown(self) -> str:
        """A Markdown table: one row per condition."""
        n = len(self.seeds)
        rows = [
            (
                r.condition.name,
                f"{int(r.success.sum())}/{n}"
                + (f" ({r.never_switched} never switched)" if r.never_switched else ""),
                "; ".join(
                    f"{s['goal']}: {s['target']:.2f}±{s['tolerance']:.2f} -> {s['achieved_mean']:.2f} "
                    f"({s['achieved_std']:.2f})"
                    for s in r.segments
                ),
            )
            for r in self.results
        ]
        head = ("condition", "success", "segments: goal target ± tol -> achieved mean (std)")
        return (
            f"Evaluation of `{self.checkpoint}` on {self.env_id} ({self.statistic}), {n} seeds, "
            f"{self.episode_steps} steps, action mode {self.action_mode}"
            + (f", precision {self.precision}" if self.precision != "fp32" else "")
            + "\n\n"
            + markdown_table(head, rows)
        )


def play_lockstep(
    engine: PolicyEngine,
    envs: list,
    obs: list,
    ctxs: list,
    goal_at: list[Callable[[int], int]],
    steps: int,
    record: Callable[[int, int, float, dict, object, object], None],
    progress: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Step every episode together through one engine until each ends or `steps` steps are played.

    Args:
        engine: The engine acting for every context.
        envs: One environment per episode, already reset; `obs` holds their first observations.
        obs: Current observation per episode (updated in place).
        ctxs: One engine context per episode.
        goal_at: Per episode, the goal to pursue at a step (set before acting when it changes).
        steps: Most steps per episode.
        record: Called with (episode, step, reward, info, the observation acted on, the action) after every
            environment step.
        progress: Show a progress bar.

    Returns:
        [E] whether each episode terminated (the environment's own end), and [E] the steps each played.
    """
    n = len(envs)
    terminated = np.zeros(n, dtype=bool)
    lengths = np.full(n, steps)
    alive = np.ones(n, dtype=bool)
    for t in tqdm(range(steps), disable=not progress, desc="eval"):
        idx = np.flatnonzero(alive)
        if len(idx) == 0:
            break
        for i in idx:
            g = goal_at[i](t)
            if g != ctxs[i].goal:
                engine.set_goal(ctxs[i], g)
        actions = engine.act([ctxs[i] for i in idx], [obs[i] for i in idx])
        failed = [a for a in actions if isinstance(a, Exception)]
        if failed:
            raise failed[0]
        for i, a in zip(idx, actions, strict=True):
            before = obs[i]
            obs[i], r, term, trunc, info = envs[i].step(a)
            record(i, t, r, info, before, a)
            if term or trunc:
                terminated[i] = term
                alive[i], lengths[i] = False, t + 1
    return terminated, lengths


def evaluate(
    ckpt: Checkpoint,
    seeds: int | list[int] = 15,
    steps: int = 1000,
    conditions: list[Condition] | None = None,
    progress: bool = True,
    action_mode: str | None = None,
    switch_relabel_steps: int | None = None,
    precision: str = "fp32",
) -> EvalResult:
    """Run every condition for every seed, all episodes in lockstep through one engine.

    Args:
        ckpt: The checkpoint to evaluate.
        seeds: Number of seeds (0..n-1) or an explicit list.
        steps: Episode length (the environment's own time limit is raised to it).
        conditions: Defaults to `protocol(n_goals, steps)`.
        progress: Show a progress bar.
        action_mode: The engine's action mode (default: the model's default, as the server uses); episode i of
            a condition seeds its sampler with seed i.
        switch_relabel_steps: Steps of context a goal change relabels (default: the checkpoint's, as the
            server uses).
        precision: The engine's arithmetic (`PolicyEngine`'s `precision`: fp32 or bf16).
    """
    import gymnasium as gym

    get_statistic(ckpt.statistic)  # fail early on an unknown statistic
    seed_list = list(range(seeds)) if isinstance(seeds, int) else list(seeds)
    conds = conditions or protocol(len(ckpt.goals), steps)
    engine = PolicyEngine(ckpt, switch_relabel_steps=switch_relabel_steps, precision=precision)
    runs = [(c, s) for c in conds for s in seed_list]
    envs = [gym.make(ckpt.env_id, max_episode_steps=steps) for _ in runs]
    t0 = time.time()
    obs = [env.reset(seed=s)[0] for env, (_, s) in zip(envs, runs, strict=True)]
    mode = action_mode or engine.default_action_mode
    ctxs = [engine.new_context(c.goal_at(0), mode, seed=s) for c, s in runs]
    signal = np.full((len(runs), steps), np.nan)

    def record(i: int, t: int, reward: float, info: dict, ob: object, action: object) -> None:
        signal[i, t] = signal_from_step(ckpt.statistic, reward, info, ob, action)

    terminated, _ = play_lockstep(
        engine, envs, obs, ctxs, [c.goal_at for c, _ in runs], steps, record, progress
    )
    for env in envs:
        env.close()
    result = judge(ckpt, conds, seed_list, signal, terminated, mode, steps, time.time() - t0)
    result.switch_relabel_steps = engine.switch_relabel_steps
    result.precision = engine.precision
    return result


def judge(
    ckpt: Checkpoint,
    conds: list[Condition],
    seed_list: list[int],
    signal: np.ndarray,
    terminated: np.ndarray,
    action_mode: str,
    steps: int,
    wall_time_s: float,
) -> EvalResult:
    """Score played episodes: per condition, segment means, tolerance hits and successes.

    Args:
        ckpt: The evaluated checkpoint (goal table, names).
        conds: The conditions, in the order their episodes were played.
        seed_list: Seeds per condition; episode `ci * len(seed_list) + j` is condition ci with seed j.
        signal: [E, steps] per-step statistic (NaN after an early termination).
        terminated: [E] whether each episode ended early.
        action_mode: How actions were chosen (recorded).
        steps: Episode length.
        wall_time_s: Time the episodes took.
    """
    results = []
    for ci, c in enumerate(conds):
        rows = slice(ci * len(seed_list), (ci + 1) * len(seed_list))
        sig, term = signal[rows], terminated[rows]
        spans = c.segments
        seg_means = np.stack([achieved(sig, a, b, ckpt.statistic) for _, a, b in spans], axis=1)
        ok = ~term
        seg_info = []
        for si, (g, a, b) in enumerate(spans):
            goal = ckpt.goals[g]
            tol = tolerance(goal, ckpt.goals)
            hit = within(seg_means[:, si], goal.mean, tol)
            ok &= hit
            with warnings.catch_warnings():  # a segment no episode reached: NaN, reported as such
                warnings.simplefilter("ignore", RuntimeWarning)
                mean, std = float(np.nanmean(seg_means[:, si])), float(np.nanstd(seg_means[:, si]))
            seg_info.append(
                {
                    "goal": g,
                    "start": a,
                    "end": b,
                    "target": goal.mean,
                    "tolerance": tol,
                    "achieved_mean": mean,
                    "achieved_std": std,
                    "within": int(hit.sum()),
                }
            )
        results.append(ConditionResult(c, sig, term, seg_means, ok, seg_info))
    return EvalResult(
        checkpoint=ckpt.name,
        env_id=ckpt.env_id,
        statistic=ckpt.statistic,
        action_mode=action_mode,
        seeds=seed_list,
        episode_steps=steps,
        goals=ckpt.goals,
        results=results,
        wall_time_s=wall_time_s,
    )
