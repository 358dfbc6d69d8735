"""Commanded agents: the PPO trainer (`gmt.datagen.ppo`) configured for one speed-commanded actor whose levels
differ only in the commanded speed, trained to switch between them.

Separately trained agents per level (`train_behaviour --track`) each know one gait; asked to start from another
level's states (a sprint, for a slow Hopper) they fall most of the time, so the data shows few transitions and a
GMT imitating it falls when its goal switches. Here one actor reads the observation with the commanded speed
appended, and during training the command changes at random steps within an episode (`SpeedCommand`), so the
agent learns every level and every change between them in one gait family. Each level is exported as the same
actor with its command fixed (`BehaviourMeta.extra["command"]`); `gmt data collect` rolls each level out like any
snapshot, so every collected episode still has one goal. Needs the optional `train` extra.

Snapshots are chosen by `command_score`: each level held from rest, and each ordered switch between levels
after `switch_at` steps, judged like the GMT protocol (speed of the level after the switch, no fall).
"""

from __future__ import annotations

import json
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from gmt.common.tables import markdown_table
from gmt.datagen.behaviour import BEHAVIOUR_DIR, BehaviourPolicy, env_slug, load_behaviour, save_behaviour
from gmt.datagen.ppo import (
    PRESETS,
    PPOPreset,
    export_actor,
    level_state,
    make_ppo,
    run_ppo,
    snapshot_path,
    trained_with,
)
from gmt.datagen.ppo_state import learner_path, load_learner, save_learner, warm_start_actor


class SpeedCommand(gym.Wrapper):
    """Training-only: a commanded speed appended to the observation, changed at random steps, and tracked.

    The reward is `SpeedTent`'s for the command in force: the environment's reward with its forward term
    replaced by `command - track_weight * |x_velocity - command|`. Keep the weight at 1 unless the task's healthy
    reward is large: above 1 a standing agent's reward turns negative and PPO learns to fall on purpose (Hopper,
    weight 3: every measurement episode fell through 800k steps). `overspeed_weight` adds
    `- overspeed_weight * max(0, x_velocity - command)`: it makes braking after a switch to a slower command
    urgent without touching a standing agent's reward. With `track_window` N > 1 the tracking (and overspeed)
    terms read the mean x-velocity of the last N steps instead of the step's own: a hop's speed swings around its
    mean within a stride, and what a goal is judged on is the mean over many strides, so the agent is then paid
    for a steady mean speed rather than for flattening every stride. The window is not cleared when the command
    changes (the first N - 1 steps after a change still weigh the old speed: braking late costs more), and it is
    not in the observation, so for N > 1 the reward depends on history the policy does not see.

    With `ceiling` Z and `ceiling_weight` W the reward also loses `W * max(0, torso height - Z)` (the torso body's z,
    metres): Ant-v5 ends an episode when its torso leaves the healthy z-range (0.2, 1.0), and its commanded runs'
    falls at 1 m/s were all bounces out of the top of that range, which a soft ceiling below it makes costly
    before they end the episode.

    With `command_range` (lo, hi) the command is drawn uniformly from that interval at every reset and change
    instead of from `commands`: the agent then tracks any speed in between, so that it can be commanded a
    speed other than the levels'.
    """

    def __init__(
        self,
        env,
        commands: list[float],
        switch_prob: float,
        seed: int,
        track_weight: float = 1.0,
        overspeed_weight: float = 0.0,
        track_window: int = 1,
        command_range: tuple[float, float] | None = None,
        ceiling: float | None = None,
        ceiling_weight: float = 0.0,
    ):
        super().__init__(env)
        if ceiling_weight < 0 or (ceiling_weight > 0 and ceiling is None):
            raise ValueError(
                f"ceiling_weight must be >= 0 and needs a ceiling, got {ceiling_weight} / {ceiling}"
            )
        self.ceiling, self.ceiling_weight = ceiling, float(ceiling_weight)
        if command_range is not None and not 0 <= command_range[0] < command_range[1]:
            raise ValueError(f"command_range must be (lo, hi) with 0 <= lo < hi, got {command_range}")
        self.command_range = (
            None if command_range is None else (float(command_range[0]), float(command_range[1]))
        )
        if track_window < 1:
            raise ValueError(f"track_window must be >= 1, got {track_window}")
        self.track_window = int(track_window)
        self.recent: deque[float] = deque(maxlen=self.track_window)
        self.track_weight = float(track_weight)
        self.overspeed_weight = float(overspeed_weight)
        self.commands = np.asarray(commands, dtype=np.float64)
        self.switch_prob = float(switch_prob)
        self.rng = np.random.default_rng(seed)
        box = env.observation_space
        lo, hi = self.command_range or (float(self.commands.min()), float(self.commands.max()))
        self.observation_space = gym.spaces.Box(
            np.append(box.low, lo).astype(box.dtype),
            np.append(box.high, hi).astype(box.dtype),
            dtype=box.dtype,
        )
        self.command = float(self.commands[0])

    def _obs(self, obs: np.ndarray) -> np.ndarray:
        return np.append(obs, self.command).astype(obs.dtype)

    def _draw(self) -> float:
        """A new command: uniform over `command_range`, else another of `commands` (any one at a reset)."""
        if self.command_range is not None:
            return float(self.rng.uniform(*self.command_range))
        return float(self.rng.choice(self.commands[self.commands != self.command]))

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.command = float(self.rng.choice(self.commands)) if self.command_range is None else self._draw()
        self.recent.clear()
        return self._obs(obs), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.recent.append(float(info["x_velocity"]))
        v = float(np.mean(self.recent))  # the step's own x-velocity when track_window is 1
        reward = (
            float(reward)
            - float(info["reward_forward"])
            + self.command
            - self.track_weight * abs(v - self.command)
            - self.overspeed_weight * max(0.0, v - self.command)
        )
        if self.ceiling_weight:
            height = float(self.env.unwrapped.data.body("torso").xpos[2])
            reward -= self.ceiling_weight * max(0.0, height - self.ceiling)
        if (len(self.commands) > 1 or self.command_range) and self.rng.random() < self.switch_prob:
            self.command = self._draw()  # from the next step on
        return self._obs(obs), reward, terminated, truncated, {**info, "command": self.command}


@dataclass
class CommandedConfig:
    """One commanded-agent training run.

    Attributes:
        env_id: Gymnasium environment id (a MuJoCo task reporting `x_velocity` and `reward_forward`).
        targets: Level name -> commanded speed (m/s), slowest first.
        total_timesteps: PPO environment steps.
        eval_every: Steps between snapshots (each is measured by `command_score`).
        switch_every: Mean steps between command changes in training episodes.
        track_weight: Weight of the speed-tracking error in the training reward (`SpeedCommand`).
        overspeed_weight: Extra weight of the speed above the command in the training reward (`SpeedCommand`).
        track_window: Steps of x-velocity averaged before the tracking terms compare it with the command
            (`SpeedCommand`; 1: each step's own).
        ceiling: Torso height (m) above which the training reward is docked (`SpeedCommand`); None: no ceiling.
        ceiling_weight: Reward docked per metre of torso height above `ceiling` (`SpeedCommand`).
        command_range: Training commands drawn uniformly from (lo, hi) m/s instead of from the levels' speeds
            (`SpeedCommand`); None: the levels' speeds only.
        cycle_every: Snapshots are also measured cycling through the levels every this many steps (the GMT
            protocol's multi-switch), so fast changes of speed are chosen; None to measure holds and switches only.
        switch_at: Step of the command change in the measurement episodes.
        eval_seeds: Episodes per hold and per ordered switch in a coarse measurement.
        final_seeds: Episodes per hold and per switch when the best coarse snapshots are measured again.
        candidates: Coarse-best snapshots measured again.
        seed: Seed of PPO, its environment and the measurements.
        out_dir: Where the chosen levels go (behaviour/<env>/).
        work_dir: Where every snapshot is kept during training.
        preset: PPO hyperparameters (default: the environment's `train_behaviour` preset).
        ent_coef: Entropy bonus in place of the preset's (None: the preset's). Ant's preset has none, and its
            action std shrank from 0.37 to ~0.05 by 1M steps while its speed stayed ~0.5 m/s.
        resume_from: Go on from this training step of `work_dir` (`gmt.datagen.ppo_state`): from its learner
            file where one is kept, else warm-started from its actor-only snapshot; None: start afresh.
    """

    env_id: str
    targets: dict[str, float]
    total_timesteps: int = 2_000_000
    eval_every: int = 50_000
    switch_every: int = 300
    track_weight: float = 1.0
    overspeed_weight: float = 0.0
    track_window: int = 1
    command_range: tuple[float, float] | None = None
    ceiling: float | None = None
    ceiling_weight: float = 0.0
    cycle_every: int | None = None
    switch_at: int = 500
    eval_seeds: int = 2
    final_seeds: int = 8
    candidates: int = 4
    seed: int = 0
    out_dir: Path | None = None
    work_dir: Path | None = None
    preset: PPOPreset | None = None
    ent_coef: float | None = None
    resume_from: int | None = None

    def __post_init__(self) -> None:
        slug = env_slug(self.env_id)
        if len(self.targets) < 2:
            raise ValueError(f"a commanded agent needs at least two levels, got {self.targets}")
        if any(isinstance(v, str) for v in self.targets.values()):
            raise ValueError(f"commanded levels need numeric speeds, got {self.targets}")
        if self.switch_every < 1 or not 0 < self.switch_at < 1000:
            raise ValueError("switch_every must be >= 1 and switch_at within an episode (0, 1000)")
        if self.track_weight <= 0:
            raise ValueError(f"track_weight must be > 0, got {self.track_weight}")
        if self.overspeed_weight < 0:
            raise ValueError(f"overspeed_weight must be >= 0, got {self.overspeed_weight}")
        if self.track_window < 1:
            raise ValueError(f"track_window must be >= 1, got {self.track_window}")
        if self.ceiling_weight < 0 or (self.ceiling_weight > 0 and self.ceiling is None):
            raise ValueError(f"ceiling_weight must be >= 0 and needs a ceiling, got {self.ceiling_weight}")
        if self.command_range is not None:
            lo, hi = self.command_range
            if not 0 <= lo < hi:
                raise ValueError(
                    f"command_range must be (lo, hi) with 0 <= lo < hi, got {self.command_range}"
                )
            if not all(lo <= v <= hi for v in self.targets.values()):
                raise ValueError(f"every level's speed must lie in command_range {self.command_range}")
        if self.cycle_every is not None and not 4 <= self.cycle_every < 1000:
            raise ValueError(f"cycle_every must be within [4, 1000), got {self.cycle_every}")
        if self.resume_from is not None and not 0 < self.resume_from < self.total_timesteps:
            raise ValueError(
                f"resume_from must lie within (0, total_timesteps={self.total_timesteps}), got {self.resume_from}"
            )
        self.out_dir = Path(self.out_dir or BEHAVIOUR_DIR / slug)
        self.work_dir = Path(self.work_dir or Path("runs") / "behaviour" / slug / "commanded")
        self.preset = self.preset or PRESETS.get(slug, PPOPreset())
        if self.ent_coef is not None:
            if not self.ent_coef >= 0:
                raise ValueError(f"ent_coef must be >= 0, got {self.ent_coef}")
            self.preset = replace(self.preset, ent_coef=float(self.ent_coef))


def play(env, policy: BehaviourPolicy, commands: list[float], switch_at: int, seed: int, rng) -> dict:
    """One stochastic episode commanded `commands[0]`, then `commands[-1]` from step `switch_at`.

    Returns:
        Whether it fell, and the mean x-velocity of the last command's segment after a 100-step transient.
    """
    schedule = [(0, commands[0])] + ([(switch_at, commands[-1])] if len(commands) > 1 else [])
    out = play_schedule(env, policy, schedule, seed, rng)
    return {"fell": out["fell"], "speed": out["speeds"][-1]}


def play_schedule(env, policy: BehaviourPolicy, schedule: list[tuple[int, float]], seed: int, rng) -> dict:
    """One stochastic episode following `schedule` ([(step, command), ...], the first at step 0).

    Returns:
        Whether it fell, and per segment the mean x-velocity after its settle-in of min(100, length // 4) steps
        (the GMT protocol's), NaN for a segment the episode did not reach.
    """
    steps = env.spec.max_episode_steps or 1000
    bounds = [s for s, _ in schedule] + [steps]
    speeds, fell = [], False
    obs, _ = env.reset(seed=seed)
    if hasattr(policy, "start_episode"):
        policy.start_episode()
    for t in range(steps):
        policy.target = float([c for s, c in schedule if s <= t][-1])  # a commanded (or governed) actor
        obs, _, terminated, truncated, info = env.step(policy.act(obs, rng))
        speeds.append(float(info["x_velocity"]))
        if terminated or truncated:
            fell = bool(terminated)
            break
    means = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        seg = speeds[a + min(100, (b - a) // 4) : b]
        means.append(float(np.mean(seg)) if seg else float("nan"))
    return {"fell": fell, "speeds": means}


def cycle_schedule(commands: list[float], every: int, steps: int = 1000) -> list[tuple[int, float]]:
    """Cycle through `commands` every `every` steps, as the GMT protocol's multi-switch does."""
    return [(s, commands[(s // every) % len(commands)]) for s in range(0, steps, every)]


def command_score(
    env,
    policy: BehaviourPolicy,
    targets: dict[str, float],
    switch_at: int,
    seeds: int,
    cycle_every: int | None = None,
) -> dict:
    """Holds of every level, every ordered switch and (with `cycle_every`) a multi-switch cycle, `seeds` each.

    The score (lower is better) adds, over every episode, the mean distance of its segments' measured speeds
    from their commands (the last segment only for a switch, as there the first is a hold), plus 10 per episode
    that fell.
    """
    rng = np.random.default_rng(30_000)
    speeds = list(targets.values())
    cases = [[v] for v in speeds] + [[a, b] for a in speeds for b in speeds if a != b]
    records = []
    for case in cases:
        for s in range(seeds):
            r = play(env, policy, case, switch_at, 30_000 + s, rng)
            records.append({"commands": case, **r, "error": abs(r["speed"] - case[-1])})
    if cycle_every is not None:
        schedule = cycle_schedule(speeds, cycle_every)
        for s in range(seeds):
            r = play_schedule(env, policy, schedule, 30_000 + s, rng)
            err = float(np.mean([abs(v - c) for v, (_, c) in zip(r["speeds"], schedule, strict=True)]))
            records.append({"commands": [f"every {cycle_every}"], "fell": r["fell"], "error": err})
    falls = sum(r["fell"] for r in records)
    err = [r["error"] for r in records if not r["fell"]]
    return {
        "score": float(sum(err) + 10.0 * falls),
        "falls": int(falls),
        "episodes": len(records),
        "mean_error": float(np.mean(err)) if err else float("nan"),
        "episodes_detail": records,
    }


def resume_source(work_dir: Path, step: int) -> Path | None:
    """What resuming from `step` loads: its learner file, else its actor-only snapshot; None if neither is kept."""
    for path in (learner_path(work_dir, step), snapshot_path(work_dir, step)):
        if path.with_suffix(".safetensors").exists():
            return path
    return None


def resume(work_dir: Path, step: int, model, venv) -> str:
    """Load training step `step` of `work_dir` into a fresh learner (`resume_source`).

    Returns:
        What was loaded, in words.

    Raises:
        FileNotFoundError: Neither a learner file nor a snapshot is kept for that step.
    """
    source = resume_source(work_dir, step)
    if source is None:
        raise FileNotFoundError(f"no learner or snapshot at step {step} in {work_dir}")
    if source == learner_path(work_dir, step):
        load_learner(source, model, venv)
        return f"resumed PPO at step {step:,} from {source}"
    warm_start_actor(source, model, venv, step)
    return f"warm-started PPO at step {step:,} from the actor-only {source} (critic, Adam and return statistics fresh)"


def train_commanded(cfg: CommandedConfig) -> dict:
    """Train the commanded agent, keep a measured snapshot every `eval_every` steps, export the best.

    Returns:
        The chosen snapshot's record (step, fine measurement).
    """
    from stable_baselines3.common.monitor import Monitor

    torch.set_num_threads(1)
    p = cfg.preset
    cfg.work_dir.mkdir(parents=True, exist_ok=True)
    commands = list(cfg.targets.values())
    switch_prob = 1.0 / cfg.switch_every
    first = cfg.resume_from or 0
    seed = cfg.seed + first  # a resumed run does not replay the first run's noise and commands
    model, venv = make_ppo(
        lambda: Monitor(
            SpeedCommand(
                gym.make(cfg.env_id),
                commands,
                switch_prob,
                seed,
                cfg.track_weight,
                cfg.overspeed_weight,
                cfg.track_window,
                cfg.command_range,
                cfg.ceiling,
                cfg.ceiling_weight,
            )
        ),
        p,
        seed,
    )
    records: list[dict] = []
    if cfg.resume_from is not None:
        print(resume(cfg.work_dir, cfg.resume_from, model, venv), flush=True)
        kept = cfg.work_dir / "records.json"
        records = [r for r in json.loads(kept.read_text()) if r["step"] <= first] if kept.exists() else []
    eval_env = gym.make(cfg.env_id)
    start = time.time()

    def snapshot(step: int) -> dict:
        path = snapshot_path(cfg.work_dir, step)
        state, meta = export_actor(model, venv, cfg.env_id, "", p.hidden_sizes, p.activation)
        meta.extra = {"command": commands[0]}
        save_behaviour(path, state, meta)
        save_learner(learner_path(cfg.work_dir, step), model, venv)
        m = command_score(eval_env, load_behaviour(path, eval_env.action_space), cfg.targets, cfg.switch_at,
                          cfg.eval_seeds, cfg.cycle_every)  # fmt: skip
        print(
            f"step {step:>8d}  score {m['score']:7.2f}  falls {m['falls']}/{m['episodes']}  "
            f"speed error {m['mean_error']:.3f}  {(step - first) / (time.time() - start):5.0f} steps/s",
            flush=True,
        )
        return {"step": step, **{k: v for k, v in m.items() if k != "episodes_detail"}}

    run_ppo(
        model,
        cfg.total_timesteps - first,
        lambda _: cfg.eval_every,
        snapshot,
        records,
        cfg.work_dir,
        reset_num_timesteps=first == 0,
    )
    return select_commanded(cfg, records)


def select_commanded(cfg: CommandedConfig, records: list[dict]) -> dict:
    """Measure the `candidates` best coarse snapshots on `final_seeds` episodes per case; export the best."""
    env = gym.make(cfg.env_id)
    best = None
    for rec in sorted(records, key=lambda r: r["score"])[: cfg.candidates]:
        policy = load_behaviour(snapshot_path(cfg.work_dir, rec["step"]), env.action_space)
        fine = {
            "step": rec["step"],
            **command_score(env, policy, cfg.targets, cfg.switch_at, cfg.final_seeds, cfg.cycle_every),
        }
        print(
            f"step {rec['step']:>8d}: fine score {fine['score']:.2f}, falls {fine['falls']}/{fine['episodes']}"
        )
        if best is None or fine["score"] < best["score"]:
            best = fine
    if best is None:
        raise ValueError(f"no snapshots in {cfg.work_dir}")
    policy = load_behaviour(snapshot_path(cfg.work_dir, best["step"]), env.action_space)
    state = level_state(policy)
    for old in [*cfg.out_dir.glob("*.safetensors"), *cfg.out_dir.glob("*.json")]:
        old.unlink()  # a level no longer commanded must not be collected
    for level, speed in cfg.targets.items():
        holds = [r for r in best["episodes_detail"] if r["commands"] == [speed] and not r["fell"]]
        meta = policy.meta
        meta.level, meta.train_step = level, best["step"]
        meta.mean_speed = float(np.mean([r["speed"] for r in holds])) if holds else None
        meta.std_speed = float(np.std([r["speed"] for r in holds])) if holds else None
        meta.extra = {
            "command": speed,
            "target_speed": speed,
            "commanded": True,
            "fine_falls": best["falls"],
            "fine_episodes": best["episodes"],
        }
        save_behaviour(cfg.out_dir / level, state, meta)
    return best


def write_commanded_provenance(
    cfg: CommandedConfig, best: dict, command: str, chosen_by_hand: bool = False
) -> Path:
    """`<out_dir>/TRAINED_WITH.md`: the command, packages, hyperparameters and the chosen snapshot's cases.

    Args:
        cfg: The run's configuration.
        best: The kept snapshot's fine measurement (`select_commanded`).
        command: The command line that wrote the levels.
        chosen_by_hand: The snapshot was named (`--snapshot`), not picked by score.
    """
    rows = {}
    for r in best["episodes_detail"]:
        key = " -> ".join(c if isinstance(c, str) else f"{c:g}" for c in r["commands"])
        rows.setdefault(key, []).append(r)

    def measured(v: list[dict]) -> str:
        kept = [r for r in v if not r["fell"]]
        if "speed" in v[0]:
            return "speed {:.3f} +- {:.3f}".format(*_mean_std([r["speed"] for r in kept]))
        return "segment error {:.3f} +- {:.3f}".format(*_mean_std([r["error"] for r in kept]))

    table = markdown_table(
        ("commanded (m/s)", "episodes", "fell", "last command's speed, or a cycle's mean error per segment"),
        [(k, len(v), sum(r["fell"] for r in v), measured(v)) for k, v in rows.items()],
    )
    cycle = (
        "" if cfg.cycle_every is None else f" and cycling through the levels every {cfg.cycle_every} steps"
    )
    choice = (
        f"step {best['step']} was named by hand (`--snapshot`) and measured again on {cfg.final_seeds} episodes each"
        if chosen_by_hand
        else f"the {cfg.candidates} best were measured again on {cfg.final_seeds}\nepisodes each, and step "
        f"{best['step']} was kept"
    )
    title = f"Behaviour agent for {cfg.env_id}: one speed-commanded actor"
    text = (
        trained_with(title, command, cfg.preset)
        + f"""
One PPO actor reads the observation with a commanded speed appended; in training the command changes at random
(on average every {cfg.switch_every} steps) among {cfg.targets}, and the reward tracks the command in force with
weight {cfg.track_weight:g}, and speed above it with an extra weight {cfg.overspeed_weight:g}, both on the mean
x-velocity of the last {cfg.track_window} step(s) (`gmt.datagen.train_commanded.SpeedCommand`). Each level file is that actor with its command fixed. Every
{cfg.eval_every} steps the actor was measured on every hold and every ordered switch (at step {cfg.switch_at}){cycle},
{cfg.eval_seeds} stochastic episodes each; {choice}:

{table}

Speeds: mean x-velocity over the last command's steps after a 100-step transient; a cycle's segments are
measured after min(100, length // 4) steps, as the GMT protocol does.
"""
    )
    path = cfg.out_dir / "TRAINED_WITH.md"
    path.write_text(text)
    return path


def _mean_std(x: list[float]) -> tuple[float, float]:
    return (float(np.mean(x)), float(np.std(x))) if x else (float("nan"), float("nan"))
