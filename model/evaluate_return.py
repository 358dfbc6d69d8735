"""Return-goal evaluation for games (paper section 3.2 and A.2.2): hold every goal, and switch at one step
between a low, a middle and a high goal in both directions, against the return the paper expects.

Goals of a `return` checkpoint are clusters of episode returns, so a goal is judged by the return of whole
episodes (the environment's own ends, game over included, capped at `steps` agent steps), not per segment
against a tolerance:
- **hold g**: the mean return over the seeds; the holds should rise with the goal id.
- **switch a->b at step S**: expected return = w x R(a) + (1 - w) x R(b), with R the holds' mean returns and
  w the measured share of the switch episodes' steps taken before S (0.3 for 1000-step episodes switched at 300,
  more when games end early). Success: the mean return within 20% of the expected one.
- Reported beside it, not judged (`expected_per_step`): each part of the episode credited with the return its
  goal earns per step in the holds, i.e. for a switch episode of n steps min(n, S) x r(a) + max(n - S, 0) x r(b)
  with r(g) the hold's total return over its total steps, averaged over the seeds. For episodes that run to the
  cap both are 0.3 x R(a) + 0.7 x R(b). They part when games end early: the share formula credits a whole
  episode's return R(a) to part of an episode, the per-step one ignores that later bricks are worth more (an
  effect the paper notes in A.2.2).
- `alive_at_switch`: how many of a switch's episodes were still running at step S; a game already over there
  never switched (the low goal can lose its five lives before S), and the report says how many did.
The return of a segment is the sum of its rewards, so the two parts of a switch episode add up to its return
(the `return` statistic of `gmt.common.statistics` is the same sum over a whole trajectory).

JSON schema (`ReturnEvalResult.to_dict`): checkpoint, env_id, statistic, action_mode, seeds, episode_steps,
switch_at, wall_time_s, goals [{id, name, mean, std, ...}], holds [{goal, returns, lengths, mean, std, sem}],
switches [{first, second, returns, before, after, lengths, alive_at_switch, mean, share_first, expected, relative_error,
within_20pct, expected_per_step, relative_error_per_step, within_20pct_per_step}], summary {holds_rise,
high_minus_low, high_minus_low_z, switches_within_20pct, switches_within_20pct_per_step, switches}.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from gmt.common.envs import make_env
from gmt.common.statistics import signal_from_step
from gmt.common.tables import markdown_table
from gmt.model.checkpoint import Checkpoint, model_info
from gmt.model.engine import PolicyEngine
from gmt.model.evaluate import play_lockstep

SWITCH_AT = 300
TOLERANCE = 0.2  # a switch's mean return within 20% of the expected return


@dataclass(frozen=True)
class ReturnCondition:
    """Play `first` from the start, then `second` from step `switch_at` (a hold when `second` is None)."""

    first: int
    second: int | None = None
    switch_at: int = SWITCH_AT

    @property
    def name(self) -> str:
        """e.g. "hold 2" or "switch 0->2"."""
        return f"hold {self.first}" if self.second is None else f"switch {self.first}->{self.second}"

    def goal_at(self, step: int) -> int:
        """The goal played at `step`."""
        return self.first if self.second is None or step < self.switch_at else self.second


def switch_goals(n_goals: int) -> list[int]:
    """The low, middle and high goals (ids are ordered by mean return): fewer when there are fewer goals."""
    return sorted({0, n_goals // 2, n_goals - 1})


def return_protocol(n_goals: int, switch_at: int = SWITCH_AT) -> list[ReturnCondition]:
    """Every hold, then every ordered switch among the low, middle and high goals."""
    picks = switch_goals(n_goals)
    holds = [ReturnCondition(g) for g in range(n_goals)]
    return holds + [ReturnCondition(a, b, switch_at) for a in picks for b in picks if a != b]


def expected_return(hold_a: float, hold_b: float, share_first: float) -> float:
    """The paper's expected return of a switch: the holds' returns weighted by the share of steps under each."""
    return share_first * hold_a + (1.0 - share_first) * hold_b


def expected_return_per_step(lengths: np.ndarray, switch_at: int, rate_a: float, rate_b: float) -> float:
    """Expected return of switch episodes of these lengths: each step earns its goal's return per step."""
    n = np.asarray(lengths, dtype=np.float64)
    return float(np.mean(np.minimum(n, switch_at) * rate_a + np.maximum(n - switch_at, 0) * rate_b))


@dataclass
class ReturnEvalResult:
    """Every episode's rewards and what they say."""

    checkpoint: str
    env_id: str
    statistic: str
    action_mode: str
    seeds: list[int]
    episode_steps: int
    switch_at: int
    goals: list
    conditions: list[ReturnCondition]
    rewards: np.ndarray  # [C, E, steps] reward at each step (0 after the episode ended)
    lengths: np.ndarray  # [C, E] agent steps of each episode
    wall_time_s: float

    def returns(self, ci: int, start: int = 0, end: int | None = None) -> np.ndarray:
        """[E] sums of condition `ci`'s rewards over steps [start, end)."""
        return self.rewards[ci, :, start:end].sum(axis=1)

    def hold_means(self) -> dict[int, float]:
        """Mean return of each held goal."""
        return {
            c.first: float(self.returns(i).mean()) for i, c in enumerate(self.conditions) if c.second is None
        }

    def hold_rates(self) -> dict[int, float]:
        """Return per agent step of each held goal (total return over total steps of its episodes)."""
        return {
            c.first: float(self.returns(i).sum() / max(int(self.lengths[i].sum()), 1))
            for i, c in enumerate(self.conditions)
            if c.second is None
        }

    def to_dict(self) -> dict:
        """The documented JSON form."""
        holds, switches = [], []
        means = self.hold_means()
        rates = self.hold_rates()
        for i, c in enumerate(self.conditions):
            ret, n = self.returns(i), self.lengths[i]
            if c.second is None:
                holds.append(
                    {
                        "goal": c.first,
                        "returns": ret.tolist(),
                        "lengths": n.tolist(),
                        "mean": float(ret.mean()),
                        "std": float(ret.std()),
                        "sem": float(ret.std(ddof=1) / np.sqrt(len(ret))) if len(ret) > 1 else 0.0,
                    }
                )
                continue
            share = float(np.mean(np.minimum(n, c.switch_at) / np.maximum(n, 1)))
            exp = expected_return(means[c.first], means[c.second], share)
            err = abs(float(ret.mean()) - exp) / max(abs(exp), 1e-9)
            exp_step = expected_return_per_step(n, c.switch_at, rates[c.first], rates[c.second])
            err_step = abs(float(ret.mean()) - exp_step) / max(abs(exp_step), 1e-9)
            alive = int((n > c.switch_at).sum())
            switched = alive == len(n)  # an episode over before the switch never switched: not a pass
            switches.append(
                {
                    "first": c.first,
                    "second": c.second,
                    "returns": ret.tolist(),
                    "before": self.returns(i, 0, c.switch_at).tolist(),
                    "after": self.returns(i, c.switch_at).tolist(),
                    "lengths": n.tolist(),
                    "alive_at_switch": alive,
                    "mean": float(ret.mean()),
                    "share_first": share,
                    "expected": exp,
                    "relative_error": err,
                    "within_20pct": bool(switched and err <= TOLERANCE),
                    "expected_per_step": exp_step,
                    "relative_error_per_step": err_step,
                    "within_20pct_per_step": bool(switched and err_step <= TOLERANCE),
                }
            )
        ordered = [means[g] for g in sorted(means)]
        low, high = holds[0], holds[-1]
        diff = high["mean"] - low["mean"]
        z = diff / max(np.hypot(high["sem"], low["sem"]), 1e-9)
        return {
            "checkpoint": self.checkpoint,
            "env_id": self.env_id,
            "statistic": self.statistic,
            "action_mode": self.action_mode,
            "seeds": self.seeds,
            "episode_steps": self.episode_steps,
            "switch_at": self.switch_at,
            "wall_time_s": round(self.wall_time_s, 1),
            "goals": [asdict(g) if hasattr(g, "__dataclass_fields__") else dict(g) for g in self.goals],
            "holds": holds,
            "switches": switches,
            "summary": {
                "holds_rise": bool(all(b > a for a, b in zip(ordered, ordered[1:], strict=False))),
                "high_minus_low": diff,
                "high_minus_low_z": float(z),
                "switches_within_20pct": sum(s["within_20pct"] for s in switches),
                "switches_within_20pct_per_step": sum(s["within_20pct_per_step"] for s in switches),
                "switches": len(switches),
                "switches_unreached": sum(s["alive_at_switch"] < len(s["lengths"]) for s in switches),
            },
        }

    def markdown(self) -> str:
        """Tables of the holds and the switches."""
        d = self.to_dict()
        names = {g["id"]: g["name"] for g in d["goals"]}
        n = len(self.seeds)
        hold_rows = [
            (
                f"{h['goal']} {names.get(h['goal'], '')}",
                f"{self.goals[h['goal']].mean:.1f}",
                f"{h['mean']:.1f} ± {h['sem']:.1f}",
                f"{np.mean(h['lengths']):.0f}",
            )
            for h in d["holds"]
        ]
        switch_rows = [
            (
                f"{s['first']} -> {s['second']}",
                f"{s['alive_at_switch']}/{n}",
                f"{s['share_first']:.2f}",
                f"{s['mean']:.1f}",
                f"{s['expected']:.1f}",
                f"{100 * s['relative_error']:.0f}%",
                "yes" if s["within_20pct"] else "no",
                f"{s['expected_per_step']:.1f}",
                f"{100 * s['relative_error_per_step']:.0f}%",
            )
            for s in d["switches"]
        ]
        sm = d["summary"]
        return (
            f"Evaluation of `{self.checkpoint}` on {self.env_id} ({self.statistic}: per-episode goals), {n} seeds, episodes capped at "
            f"{self.episode_steps} agent steps, switch at step {self.switch_at}, action mode {self.action_mode}\n\n"
            + markdown_table(
                ("hold goal", "dataset mean return", "mean return ± s.e.", "mean length"), hold_rows
            )
            + "\n\n"
            + markdown_table(
                (
                    "switch",
                    "alive at switch",
                    "share before",
                    "mean return",
                    "expected",
                    "error",
                    "within 20%",
                    "expected per step",
                    "error per step",
                ),
                switch_rows,
            )
            + f"\n\nHolds rise with the goal: {'yes' if sm['holds_rise'] else 'no'}; highest minus lowest "
            f"{sm['high_minus_low']:.1f} (z = {sm['high_minus_low_z']:.1f}); switches within 20%: "
            f"{sm['switches_within_20pct']}/{sm['switches']} (of the per-step expectation: "
            f"{sm['switches_within_20pct_per_step']}/{sm['switches']})"
            + (
                f"; {sm['switches_unreached']} switches had episodes that ended before the switch (never "
                "switched), which are not passes"
                if sm["switches_unreached"]
                else ""
            )
            + ".\n"
        )


def evaluate_returns(
    ckpt: Checkpoint,
    seeds: int | list[int] = 15,
    steps: int = 1000,
    switch_at: int = SWITCH_AT,
    conditions: list[ReturnCondition] | None = None,
    progress: bool = True,
    action_mode: str | None = None,
) -> ReturnEvalResult:
    """Play every condition for every seed, all episodes in lockstep through one engine.

    Args:
        ckpt: A checkpoint whose goals are return clusters.
        seeds: Number of seeds (0..n-1) or an explicit list (the environment's reset seed and the sampler's).
        steps: Cap on agent steps per episode.
        switch_at: Step of every switch.
        conditions: Defaults to `return_protocol(n_goals, switch_at)`.
        progress: Show a progress bar.
        action_mode: The engine's action mode (default: the model's, `expert` for discrete actions).
    """
    seed_list = list(range(seeds)) if isinstance(seeds, int) else list(seeds)
    conds = conditions or return_protocol(len(ckpt.goals), switch_at)
    spec = model_info(ckpt)
    engine = PolicyEngine(ckpt)
    mode = action_mode or engine.default_action_mode
    runs = [(c, s) for c in conds for s in seed_list]
    envs = [make_env(spec, max_steps=steps) for _ in runs]
    t0 = time.time()
    obs = [env.reset(seed=s)[0] for env, (_, s) in zip(envs, runs, strict=True)]
    ctxs = [engine.new_context(c.goal_at(0), mode, seed=s) for c, s in runs]
    rewards = np.zeros((len(runs), steps))  # the statistic's per-step signal: the reward for `return`

    def record(i: int, t: int, reward: float, info: dict, ob: object, action: object) -> None:
        rewards[i, t] = signal_from_step(ckpt.statistic, reward, info, ob, action)

    _, lengths = play_lockstep(engine, envs, obs, ctxs, [c.goal_at for c, _ in runs], steps, record, progress)
    for env in envs:
        env.close()
    E = len(seed_list)
    return ReturnEvalResult(
        checkpoint=ckpt.name,
        env_id=ckpt.env_id,
        statistic=ckpt.statistic,
        action_mode=mode,
        seeds=seed_list,
        episode_steps=steps,
        switch_at=switch_at,
        goals=ckpt.goals,
        conditions=conds,
        rewards=rewards.reshape(len(conds), E, steps),
        lengths=lengths.reshape(len(conds), E),
        wall_time_s=time.time() - t0,
    )


def plot_returns(result: ReturnEvalResult, path) -> None:
    """Holds (mean return ± s.e. per goal, dataset mean marked) and switches (expected vs achieved), one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = result.to_dict()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    ids = [h["goal"] for h in d["holds"]]
    a1.bar(ids, [h["mean"] for h in d["holds"]], yerr=[h["sem"] for h in d["holds"]], color="tab:blue")
    a1.plot(ids, [result.goals[g].mean for g in ids], "k_", markersize=30, label="dataset mean")
    a1.set_xticks(ids, [f"{g} {result.goals[g].name}" for g in ids])
    a1.set_ylabel("episode return")
    a1.set_title(f"hold, {len(result.seeds)} seeds")
    a1.legend()
    x = np.arange(len(d["switches"]))
    a2.bar(x - 0.2, [s["expected"] for s in d["switches"]], 0.4, label="expected", color="tab:gray")
    a2.bar(x + 0.2, [s["mean"] for s in d["switches"]], 0.4, label="achieved", color="tab:orange")
    a2.set_xticks(x, [f"{s['first']}->{s['second']}" for s in d["switches"]])
    a2.set_title(f"switch at step {result.switch_at}")
    a2.legend()
    fig.suptitle(f"{result.checkpoint}: {result.env_id}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
