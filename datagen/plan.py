"""A commanded level that plans its change of speed in the simulator: receding-horizon selection.

A commanded agent (`train_commanded`) started from another level's state brakes or speeds up at its own pace,
and how fast depends on where in its stride the start finds it: from the fast Hopper gait, the slow level's mean
x-velocity over steps [50, 200) ranges over 1.65-2.0 m/s by start state (std 0.09 across starts, 0.05 within
one start over the agent's own action noise). A GMT learns its transitions from these episodes, so a goal
switched every 200 steps inherits that spread. Filtering whole episodes (`settle`) mostly keeps the lucky
starts and leaves the hard ones unshown.

`PlannedPolicy` instead plans the first `steps` steps of an episode (a pool-started one; with `from_rest`, also
one that starts at the reset pose, where the agent speeds up from standing at its own pace): every `every` steps
it copies the MuJoCo state, simulates `candidates` continuations of `horizon` steps (the same actor, its command
cycled over `commands`, with its own action noise), keeps the one whose mean x-velocity is closest to the level's target
(one that falls ranks last), restores the state and plays that candidate's first `every` actions. Lower
commands than the level's own let it brake harder from a bad start; its own command keeps it steady once
there. After `steps` steps it is the plain level. It is a behaviour policy like any other: each episode still
has one goal, and the dataset records which episodes were planned.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class PlanConfig:
    """How a level plans the start of an episode.

    Attributes:
        commands: Commands (m/s) the candidates are given, cycled over them; include the level's own.
        candidates: Continuations simulated at each decision.
        every: Steps played from the chosen continuation before deciding again.
        horizon: Steps simulated per continuation (its mean x-velocity is what is scored).
        steps: Leading steps of an episode that are planned; later steps are the plain level.
        target: Speed (m/s) the continuations are scored against; None: the snapshot's measured mean speed.
        from_rest: Also plan the episodes that start at the reset pose (from rest), not only the pool-started
            ones: from rest the level reaches its speed at the pace the candidates allow, not its own.
        rest_target: Speed (m/s) the continuations of an episode from rest are scored against (None: as
            `target`). Above the level's speed it makes the start from standing urgent: the plan then keeps
            choosing the fastest continuation until the horizon's mean passes the level's speed.
        rest_commands: Commands of the candidates of an episode from rest (None: as `commands`), e.g. commands
            above the level's range for a sprint from standing, apart from the braking commands of the
            pool-started episodes.
    """

    commands: tuple[float, ...]
    candidates: int = 12
    every: int = 20
    horizon: int = 80
    steps: int = 200
    target: float | None = None
    from_rest: bool = False
    rest_target: float | None = None
    rest_commands: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("commands", "rest_commands"):
            value = getattr(self, name)
            if value is not None and not (value and all(np.isfinite(c) for c in value)):
                raise ValueError(f"{name} must be finite speeds, got {value}")
        for name in ("candidates", "every", "horizon", "steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.every > self.horizon:
            raise ValueError(f"every ({self.every}) must not exceed horizon ({self.horizon})")
        for name in ("target", "rest_target"):
            value = getattr(self, name)
            if value is not None and not np.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value}")
        if (self.rest_target is not None or self.rest_commands is not None) and not self.from_rest:
            raise ValueError("rest_target and rest_commands are for episodes from rest: they need from_rest")

    def for_rest(self) -> PlanConfig:
        """The plan of an episode from rest: scored against `rest_target` and given `rest_commands` where
        these are set."""
        return replace(
            self,
            target=self.target if self.rest_target is None else self.rest_target,
            commands=self.commands if self.rest_commands is None else self.rest_commands,
        )


def parse_plan(item: str) -> tuple[str, tuple[float, ...]]:
    """'LEVEL=C1,C2,...' -> (LEVEL, commands)."""
    name, sep, value = item.partition("=")
    try:
        commands = tuple(float(c) for c in value.split(","))
    except ValueError:
        commands = ()
    if not sep or not name or not commands:
        raise ValueError(f"expected LEVEL=COMMAND[,COMMAND...], got {item!r}")
    return name, commands


class PlannedPolicy:
    """A commanded behaviour policy whose first `cfg.steps` steps per episode are chosen in the simulator.

    Args:
        policy: A commanded `BehaviourPolicy` (not governed): its `command` is set per candidate.
        env: The environment the episode runs in; its `unwrapped` MuJoCo env is copied and restored.
        cfg: The plan.
    """

    def __init__(self, policy, env, cfg: PlanConfig):
        if getattr(policy, "command", None) is None or getattr(policy, "governor", None) is not None:
            raise ValueError("planning needs a commanded, ungoverned level (gmt data commanded)")
        self.target = cfg.target if cfg.target is not None else policy.meta.mean_speed
        if self.target is None:
            raise ValueError("the snapshot has no measured mean speed: give the plan a target")
        self.policy, self.env, self.cfg = policy, env, cfg
        self.t, self.queue = 0, []

    def start_episode(self) -> None:
        """Forget the previous episode's step count and chosen actions."""
        self.policy.start_episode()
        self.t, self.queue = 0, []

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """The next action: from the chosen continuation while planning, else the level's own."""
        planning = self.t < self.cfg.steps
        self.t += 1
        if not planning:
            return self.policy.act(obs, rng)
        if not self.queue:
            self.queue = self._plan(rng)
        return self.queue.pop(0)

    def _plan(self, rng: np.random.Generator | None) -> list[np.ndarray]:
        """Simulate the candidates from the current state; the chosen one's first `every` actions."""
        sim = self.env.unwrapped
        qpos, qvel = sim.data.qpos.copy(), sim.data.qvel.copy()
        own = self.policy.command
        best_key, best = None, None
        try:
            for n in range(self.cfg.candidates):
                sim.set_state(qpos, qvel)
                self.policy.command = self.cfg.commands[n % len(self.cfg.commands)]
                actions, speeds, fell = self._simulate(sim, rng)
                # Survivors first, then the longest survival among falls, then the closest mean speed.
                key = (fell, -len(actions), abs(float(np.mean(speeds)) - self.target))
                if best_key is None or key < best_key:
                    best_key, best = key, actions
        finally:
            self.policy.command = own
            sim.set_state(qpos, qvel)
        return best[: self.cfg.every]

    def _simulate(self, sim, rng) -> tuple[list[np.ndarray], list[float], bool]:
        """Step the bare MuJoCo env `horizon` steps with the policy; its actions, x-velocities and whether it fell."""
        obs = sim._get_obs()
        actions, speeds = [], []
        for _ in range(self.cfg.horizon):
            action = self.policy.act(obs, rng)
            obs, _, terminated, _, info = sim.step(action)
            actions.append(action)
            speeds.append(float(info["x_velocity"]))
            if terminated:
                return actions, speeds, True
        return actions, speeds, False
