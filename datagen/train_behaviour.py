"""Behaviour levels: the PPO trainer (`gmt.datagen.ppo`) configured to export snapshots at several measured speeds.

During training the current actor is exported every `eval_every` steps and rolled out with its stochastic
policy; its per-episode mean x-velocity is recorded. Afterwards, for every target speed the snapshot closest
to it with the most consistent speed is chosen, re-measured on more episodes, and written to
`behaviour/<env>/<level>.safetensors` plus its JSON sidecar. Needs the optional `train` extra.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from gmt.common.tables import markdown_table
from gmt.datagen.behaviour import BEHAVIOUR_DIR, env_slug, load_behaviour, save_behaviour
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
from gmt.datagen.rollout import measure, stuck_step
from gmt.datagen.start_states import PoolStart, build_pool

FASTEST = "max"


# Target mean x-velocities (m/s) per level; "max" keeps the fastest consistent snapshot.
DEFAULT_TARGETS: dict[str, dict[str, float | str]] = {
    "halfcheetah": {"slow": 1.0, "medium": 2.75, "fast": FASTEST},
    "hopper": {"slow": 1.0, "fast": FASTEST},
    # Walker2d's fastest snapshots fall in some episodes, which splits their speeds in two; 2.4 m/s stays unimodal.
    "walker2d": {"slow": 1.0, "fast": 2.4},
    # Ant's PPO snapshots beyond ~0.9 m/s end early (flip or jump) in some episodes and spread widely.
    "ant": {"slow": 0.0, "fast": 0.9},
}


@dataclass
class BehaviourTrainConfig:
    """One behaviour-training run.

    Attributes:
        env_id: Gymnasium environment id.
        total_timesteps: PPO environment steps.
        eval_every: Steps between snapshot measurements.
        dense_steps: During the first `dense_steps`, measure four times as often (skill changes fast early).
        eval_episodes: Stochastic episodes per measurement.
        final_episodes: Episodes per snapshot in the final measurement that chooses the levels.
        targets: Level name -> target mean x-velocity, or "max".
        seed: Seed of PPO, of its environment and of the measurements.
        out_dir: Where the chosen snapshots go (behaviour/<env>/).
        work_dir: Where every measured snapshot is kept during training.
        preset: PPO hyperparameters.
        track: Train one PPO run per level, rewarded for tracking the level's target speed (`SpeedTent`)
            instead of for speed, and keep each level's snapshot from its own run. Targets must be numbers.
        pool_start: With `track`, the share of training episodes that start from a state visited by the other
            levels' current snapshots in `out_dir` (rolled out with `gmt data collect`'s noise), so the level
            learns to reach its speed from theirs, as a switch asks of it.
        pool_episodes: Episodes per other level rolled out for that pool.
    """

    env_id: str
    total_timesteps: int = 1_000_000
    eval_every: int = 20_000
    dense_steps: int = 200_000
    eval_episodes: int = 3
    final_episodes: int = 30
    targets: dict[str, float | str] | None = None
    seed: int = 0
    out_dir: Path | None = None
    work_dir: Path | None = None
    preset: PPOPreset | None = None
    track: bool = False
    pool_start: float = 0.0
    pool_episodes: int = 10

    def __post_init__(self) -> None:
        slug = env_slug(self.env_id)
        self.targets = self.targets or DEFAULT_TARGETS.get(slug, {"slow": 1.0, "fast": FASTEST})
        self.out_dir = Path(self.out_dir or BEHAVIOUR_DIR / slug)
        self.work_dir = Path(self.work_dir or Path("runs") / "behaviour" / slug)
        self.preset = self.preset or PRESETS.get(slug, PPOPreset())
        if self.track and any(t == FASTEST for t in self.targets.values()):
            raise ValueError(f"tracking needs a numeric target speed for every level, got {self.targets}")
        if not 0.0 <= self.pool_start <= 1.0:
            raise ValueError(f"pool_start must be in [0, 1], got {self.pool_start}")
        if self.pool_start > 0 and not self.track:
            raise ValueError("pool_start needs track (each level's own run starts from the others' states)")

    def level_work_dir(self, level: str) -> Path:
        """Where one level's tracking run keeps its snapshots (`work_dir` itself without tracking)."""
        if not self.track:
            return self.work_dir
        return self.work_dir / (f"track-{level}" + (f"-pool{self.pool_start:g}" if self.pool_start else ""))


class SpeedTent(gym.Wrapper):
    """Training-only reward for a target speed: the forward reward becomes `target - |x_velocity - target|`.

    Below the target it equals the environment's own forward reward (x-velocity), so standing still earns no
    more than before; above it, every m/s of overshoot costs as much as a m/s short. The healthy reward and
    the control cost are the environment's.
    """

    def __init__(self, env, target: float):
        super().__init__(env)
        self.target = float(target)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        v = float(info["x_velocity"])
        reward = float(reward) - float(info["reward_forward"]) + self.target - abs(v - self.target)
        return obs, reward, terminated, truncated, info


class StuckTermination(gym.Wrapper):
    """Training-only shaping: end the episode with a penalty once a running agent has come to a standstill.

    PPO cheetahs occasionally fall into a pose where they stay still for the rest of the episode. The
    condition is `rollout.stuck_step`'s, checked online. (Measured on HalfCheetah: it did not lower the
    3-20% stuck rate of stochastic episodes; `gmt data collect` drops such episodes instead.)
    """

    def __init__(
        self, env, penalty: float, window: int = 20, run_speed: float = 1.0, stop_speed: float = 0.1
    ):
        super().__init__(env)
        self.penalty, self.window, self.run_speed, self.stop_speed = penalty, window, run_speed, stop_speed

    def reset(self, **kwargs):
        self._speeds: list[float] = []
        return self.env.reset(**kwargs)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._speeds.append(float(info["x_velocity"]))
        tail = self._speeds[-self.window :]
        if not terminated and len(tail) == self.window and abs(np.mean(tail)) < self.stop_speed:
            if stuck_step(self._speeds, self.window, self.run_speed, self.stop_speed) is not None:
                terminated, reward = True, reward - self.penalty
        return obs, reward, terminated, truncated, info


def make_train_env(
    env_id: str,
    preset: PPOPreset,
    track: float | None = None,
    pool=None,
    pool_start: float = 0.0,
    seed: int = 0,
):
    """The training environment: Monitor over the (optionally stuck-terminated, speed-tracking, pool-started)
    Gymnasium env."""
    from stable_baselines3.common.monitor import Monitor

    env = gym.make(env_id)
    if track is not None:
        env = SpeedTent(env, track)
    if pool is not None and pool_start > 0:
        env = PoolStart(env, pool, pool_start, seed)
    if preset.stuck_penalty > 0:
        env = StuckTermination(env, preset.stuck_penalty)
    return Monitor(env)


def level_score(record: dict, target: float | str, max_len: int) -> float:
    """Lower is better: distance to the target plus the speed spread; early falls are heavily penalised."""
    fell = record["min_length"] < max_len
    if target == FASTEST:
        return -(record["mean_speed"] - 2.0 * record["std_speed"]) + 100.0 * fell
    return abs(record["mean_speed"] - float(target)) + 2.0 * record["std_speed"] + 100.0 * fell


def measure_snapshot(cfg: BehaviourTrainConfig, step: int, env, work_dir: Path | None = None) -> dict:
    """The coarse measurement of the snapshot saved at `step` (deterministic: fixed seeds)."""
    policy = load_behaviour(snapshot_path(work_dir or cfg.work_dir, step), env.action_space)
    return {**measure(env, policy, cfg.eval_episodes, 10_000), "step": step}


def remeasure_all(cfg: BehaviourTrainConfig, level: str | None = None) -> list[dict]:
    """Coarse measurements of every snapshot kept in the (level's) work dir up to `cfg.total_timesteps`.

    Reuses records.json where it has a snapshot, else measures again (same seeds, same numbers).
    """
    work = cfg.level_work_dir(level) if level is not None else cfg.work_dir
    path = work / "records.json"
    known = {r["step"]: r for r in json.loads(path.read_text())} if path.exists() else {}
    env = gym.make(cfg.env_id)
    steps = sorted(int(f.stem.split("_")[1]) for f in work.glob("step_*.safetensors"))
    return [known.get(s) or measure_snapshot(cfg, s, env, work) for s in steps if s <= cfg.total_timesteps]


def train(cfg: BehaviourTrainConfig) -> list[dict]:
    """Train PPO, measure snapshots as it goes, then choose and export one snapshot per level.

    With `cfg.track`, one speed-tracking PPO run per level, each level chosen among its own run's snapshots.

    Returns:
        The chosen levels, each with its name, target, training step and measured speeds.
    """
    if not cfg.track:
        return select_levels(cfg, _train_run(cfg, cfg.work_dir, None))
    return select_levels(
        cfg, {level: _train_run(cfg, cfg.level_work_dir(level), t, level) for level, t in cfg.targets.items()}
    )


def other_levels_pool(cfg: BehaviourTrainConfig, level: str):
    """States visited by the current snapshots in `cfg.out_dir` other than `level` (collect's noise)."""
    from gmt.datagen.collect import DEFAULT_NOISE_SCALE

    env = gym.make(cfg.env_id)
    others = {}
    for path in sorted(cfg.out_dir.glob("*.safetensors")):
        if path.stem != level:
            others[path.stem] = load_behaviour(path.with_suffix(""), env.action_space)
            others[path.stem].noise_scale = DEFAULT_NOISE_SCALE.get(env_slug(cfg.env_id), 1.0)
    if not others:
        raise ValueError(
            f"pool_start needs other levels' snapshots in {cfg.out_dir}, found none besides {level}"
        )
    return build_pool(env, others, cfg.pool_episodes, cfg.seed + 777)


def _train_run(
    cfg: BehaviourTrainConfig, work_dir: Path, track: float | None, level: str | None = None
) -> list[dict]:
    """One PPO run (rewarded for speed, or for tracking `track` m/s); its snapshots' coarse measurements."""
    torch.set_num_threads(1)
    p = cfg.preset
    work_dir.mkdir(parents=True, exist_ok=True)
    pool = other_levels_pool(cfg, level) if cfg.pool_start > 0 else None
    model, venv = make_ppo(
        lambda: make_train_env(cfg.env_id, p, track, pool, cfg.pool_start, cfg.seed), p, cfg.seed
    )
    eval_env = gym.make(cfg.env_id)
    start = time.time()

    def snapshot(step: int) -> dict:
        state, meta = export_actor(model, venv, cfg.env_id, "", p.hidden_sizes, p.activation)
        save_behaviour(snapshot_path(work_dir, step), state, meta)
        rec = measure_snapshot(cfg, step, eval_env, work_dir)
        print(
            f"step {rec['step']:>8d}  speed {rec['mean_speed']:6.2f} +- {rec['std_speed']:.2f}  "
            f"len {rec['mean_length']:6.1f}  return {rec['mean_return']:8.1f}  "
            f"{step / (time.time() - start):6.0f} steps/s",
            flush=True,
        )
        return rec

    def every(step: int) -> int:
        return cfg.eval_every // 4 if step <= cfg.dense_steps else cfg.eval_every

    return run_ppo(model, cfg.total_timesteps, every, snapshot, [], work_dir)


def _fine(cfg: BehaviourTrainConfig, work_dir: Path, records: list[dict], env) -> list[dict]:
    """`final_episodes`-episode measurements of the given snapshots, cached in the work dir."""
    cache_path = work_dir / f"fine_records_{cfg.final_episodes}.json"
    cache = {r["step"]: r for r in json.loads(cache_path.read_text())} if cache_path.exists() else {}
    fine = []
    for rec in records:
        if rec["step"] not in cache:
            policy = load_behaviour(snapshot_path(work_dir, rec["step"]), env.action_space)
            cache[rec["step"]] = {**measure(env, policy, cfg.final_episodes, 20_000), "step": rec["step"]}
            cache_path.write_text(json.dumps(sorted(cache.values(), key=lambda r: r["step"]), indent=1))
        fine.append(cache[rec["step"]])
    return fine


TRACK_CANDIDATES = 8  # per tracking run, the snapshots with the best coarse scores that are measured finely


def select_levels(cfg: BehaviourTrainConfig, records: list[dict] | dict[str, list[dict]]) -> list[dict]:
    """Re-measure snapshots on `final_episodes` episodes, then choose one per level and export it.

    A rare failure (e.g. a cheetah stuck on its head) shows up only over many episodes, so the choice uses
    the fine measurements: per level, in the order given, the unused snapshot with the best `level_score`.
    Without tracking every snapshot of the one run is re-measured and every old level file is replaced; with
    tracking, each level's run offers its `TRACK_CANDIDATES` best snapshots by the coarse score, and only the
    levels in `cfg.targets` are written (so levels can be trained by separate processes).

    Args:
        cfg: The training configuration (targets, work and output folders, episodes).
        records: Coarse measurements of the snapshots: one list for the single run, or, with tracking, a list
            per level.
    """
    torch.set_num_threads(1)
    env = gym.make(cfg.env_id)
    max_len = env.spec.max_episode_steps or 1000
    if cfg.track:
        assert isinstance(records, dict)
        fine = {}
        for level, target in cfg.targets.items():
            ranked = sorted(records[level], key=lambda r: level_score(r, target, max_len))
            fine[level] = _fine(cfg, cfg.level_work_dir(level), ranked[:TRACK_CANDIDATES], env)
        for level in cfg.targets:
            for old in cfg.out_dir.glob(f"{level}.*"):
                old.unlink()
    else:
        assert isinstance(records, list)
        shared = _fine(cfg, cfg.work_dir, records, env)
        fine = {level: shared for level in cfg.targets}
        for old in [*cfg.out_dir.glob("*.safetensors"), *cfg.out_dir.glob("*.json")]:
            old.unlink()  # a level no longer targeted must not be collected
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    chosen, used = [], set()
    for level, target in cfg.targets.items():
        best = min(
            (r for r in fine[level] if r["step"] not in used), key=lambda r: level_score(r, target, max_len)
        )
        if not cfg.track:
            used.add(best["step"])
        policy = load_behaviour(snapshot_path(cfg.level_work_dir(level), best["step"]), env.action_space)
        meta = policy.meta
        meta.level = level
        meta.mean_speed, meta.std_speed, meta.train_step = best["mean_speed"], best["std_speed"], best["step"]
        meta.extra = {
            "target_speed": target,
            "episodes": cfg.final_episodes,
            "mean_return": best["mean_return"],
            "mean_length": best["mean_length"],
            "min_length": best["min_length"],
            "speed_tracking": cfg.track,
        }
        save_behaviour(cfg.out_dir / level, level_state(policy), meta)
        chosen.append({"level": level, "target": target, **best})
        print(
            f"{level:>8s} (target {target}): step {best['step']}, speed {best['mean_speed']:.3f} "
            f"+- {best['std_speed']:.3f}, length {best['mean_length']:.0f} (min {best['min_length']})",
            flush=True,
        )
    return chosen


def command_line(cfg: BehaviourTrainConfig) -> str:
    """The `gmt data behaviour` invocation that reproduces `cfg`, every option explicit."""
    targets = " ".join(f"--target {k}={v}" for k, v in cfg.targets.items())
    return (
        f"gmt data behaviour --env {cfg.env_id} --timesteps {cfg.total_timesteps} --eval-every {cfg.eval_every} "
        f"--dense-steps {cfg.dense_steps} --eval-episodes {cfg.eval_episodes} "
        f"--final-episodes {cfg.final_episodes} {targets} --seed {cfg.seed}"
        + (" --track" if cfg.track else "")
        + (f" --pool-start {cfg.pool_start:g}" if cfg.pool_start else "")
    )


def write_provenance(cfg: BehaviourTrainConfig, chosen: list[dict]) -> Path:
    """Write `<out_dir>/TRAINED_WITH.md` (with tracking, `TRAINED_WITH-<levels>.md`): the command, package
    versions, hyperparameters and levels."""
    dense = f" (every {cfg.eval_every // 4} during the first {cfg.dense_steps})" if cfg.dense_steps else ""
    levels = markdown_table(
        ("level", "target", "PPO step", "mean speed", "std", "mean length", "mean return"),
        [
            (
                c["level"],
                c["target"],
                c["step"],
                f"{c['mean_speed']:.3f}",
                f"{c['std_speed']:.3f}",
                f"{c['mean_length']:.0f}",
                f"{c['mean_return']:.0f}",
            )
            for c in chosen
        ],
    )
    text = (
        trained_with(f"Behaviour agents for {cfg.env_id}", command_line(cfg), cfg.preset)
        + f"""
Every {cfg.eval_every} steps{dense} the actor was exported
and measured; afterwards every snapshot was measured again on {cfg.final_episodes} stochastic episodes (reset seeds
20000+) and, per level in order, the unused snapshot minimising |mean - target| + 2 std was kept (`max`: the
highest mean - 2 std; a snapshot with an episode that fell ranks last). Speeds are the mean and standard deviation
over episodes of the per-episode mean `x_velocity` (m/s). The PPO run's snapshots and measurements are kept
in `runs/behaviour/<env>/` (not committed); `--select-only` re-chooses from them.

{levels}

`gmt data collect --env {cfg.env_id}` rolls these out with their Gaussian noise and adds a uniform-random
policy; it replaces snapshot episodes in which a running agent came to a standstill for good (see its output).
"""
    )
    if cfg.track:
        text = text.replace(
            "Every ",
            "Each level is its own PPO run rewarded for holding its target speed (`SpeedTent`). Every ",
            1,
        )
    name = f"TRAINED_WITH-{'-'.join(cfg.targets)}.md" if cfg.track else "TRAINED_WITH.md"
    path = cfg.out_dir / name
    path.write_text(text)
    return path
