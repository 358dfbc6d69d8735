"""Refinement: the PPO trainer (`gmt.datagen.ppo`) configured to fine-tune one behaviour level so that it reaches
its target speed from other levels' states.

The PPO snapshots of `train_behaviour` are taken from a run that maximises speed; the slow one is simply an
early, half-trained runner. Started from a state of the fast level (a sprint) it often brakes by pitching
nose-down and stays stuck there, and no trajectory in the data shows anything better. Refinement fine-tunes
a level's actor with:

- a target-speed reward instead of "as fast as possible": `-|x_velocity - target| - ctrl_cost` for tasks that
  never terminate (HalfCheetah), else `SpeedTent` (healthy reward kept, so falling stays the worst outcome);
- half of the training episodes starting from states visited by the other levels (`start_states`);
- the level's own observation normalisation, kept fixed, and its actor as the starting point; the new critic
  is fitted alone for `critic_warmup` steps before the actor may change.

Snapshots are measured from rest and from pool states, and the most consistent one replaces the level's file.
Needs the optional `train` extra (stable-baselines3).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from gmt.datagen.behaviour import (
    BEHAVIOUR_DIR,
    BehaviourPolicy,
    RandomPolicy,
    env_slug,
    list_snapshots,
    load_behaviour,
    save_behaviour,
)
from gmt.datagen.collect import DEFAULT_NOISE_SCALE
from gmt.datagen.ppo import (
    PRESETS,
    PPOPreset,
    actor_state,
    copy_actor,
    keep_record,
    level_state,
    make_ppo,
    run_ppo,
    snapshot_path,
)
from gmt.datagen.rollout import rollout
from gmt.datagen.start_states import PoolStart, StatePool, build_pool
from gmt.datagen.train_behaviour import SpeedTent

NEVER_TERMINATES = {"halfcheetah", "swimmer"}  # tasks without a healthy-state termination


@dataclass
class RefineConfig:
    """One refinement run.

    Attributes:
        env_id: Gymnasium id.
        level: Level to refine (its snapshot is the starting actor and is replaced by the result).
        target_speed: Target mean x-velocity (m/s) of the reward.
        timesteps: PPO environment steps.
        learning_rate: PPO learning rate.
        critic_warmup: Steps during which only the critic is trained.
        pool_fraction: Share of training episodes that start from a pool state.
        pool_episodes: Episodes per other level rolled out to build the pool.
        noise_scale: Action-noise multiplier of the pool rollouts and of the measurements (None: the scale
            `gmt data collect` uses for this env).
        reward: `absolute` (`-|x_velocity - target| - ctrl_cost`) or `tent` (`SpeedTent`: the env's reward with
            the forward term capped at the target); None: `absolute` for tasks that never terminate, else
            `tent` (a reward that is negative everywhere would teach a Hopper to fall early).
        eval_every: Steps between snapshot measurements.
        eval_episodes: Episodes from rest and from pool states per measurement.
        seed: Seed of PPO, the pool and the measurements.
        behaviour_dir: Folder with <env>/<level>.safetensors.
        out_dir: Where the refined <level> snapshot goes (default: over the original, behaviour_dir/<env>/).
        work_dir: Where snapshots and measurements of this run go.
        preset: PPO hyperparameters (learning rate overridden).
    """

    env_id: str
    level: str = "slow"
    target_speed: float = 1.2
    timesteps: int = 200_000
    learning_rate: float = 3e-5
    critic_warmup: int = 20_000
    pool_fraction: float = 0.5
    pool_episodes: int = 10
    noise_scale: float | None = None
    reward: str | None = None
    eval_every: int = 10_000
    eval_episodes: int = 8
    seed: int = 0
    behaviour_dir: Path | None = None
    out_dir: Path | None = None
    work_dir: Path | None = None
    preset: PPOPreset | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        slug = env_slug(self.env_id)
        self.behaviour_dir = Path(self.behaviour_dir or BEHAVIOUR_DIR)
        self.out_dir = Path(self.out_dir or self.behaviour_dir / slug)
        self.work_dir = Path(
            self.work_dir or Path("runs") / "refine" / slug / f"{self.level}-seed{self.seed}"
        )
        self.preset = self.preset or PRESETS.get(slug, PPOPreset())
        if self.noise_scale is None:
            self.noise_scale = DEFAULT_NOISE_SCALE.get(slug, 1.0)
        if self.reward is None:
            self.reward = "absolute" if slug in NEVER_TERMINATES else "tent"
        if self.reward not in ("absolute", "tent"):
            raise ValueError(f"reward must be 'absolute' or 'tent', got {self.reward!r}")
        if not 0.0 <= self.pool_fraction <= 1.0:
            raise ValueError(f"pool_fraction must be in [0, 1], got {self.pool_fraction}")
        if self.timesteps <= self.critic_warmup:
            raise ValueError(f"timesteps ({self.timesteps}) must exceed critic_warmup ({self.critic_warmup})")


class TargetSpeedReward(gym.Wrapper):
    """Reward `-|x_velocity - target|` minus the environment's control cost."""

    def __init__(self, env, target: float):
        super().__init__(env)
        self.target = target

    def step(self, action):
        obs, _, terminated, truncated, info = self.env.step(action)
        reward = -abs(float(info["x_velocity"]) - self.target) + float(info.get("reward_ctrl", 0.0))
        return obs, reward, terminated, truncated, info


class FixedObsNorm(gym.ObservationWrapper):
    """The snapshot's own VecNormalize observation transform, frozen."""

    def __init__(self, env, policy: BehaviourPolicy):
        super().__init__(env)
        self.policy = policy

    def observation(self, observation):
        return self.policy.normalise(observation).numpy()


def measure_refined(env, policy, pool: StatePool, target: float, episodes: int, seed: int) -> dict:
    """Speeds from rest (1000-step episodes, mean over steps 100+) and from pool states (400 steps, mean over
    steps 100+). An episode fails when its mean is off the target by more than 0.4 m/s or when it ends early
    (a fall); a fall's speed is its mean over all its steps."""
    rng = np.random.default_rng(seed)
    out: dict[str, list[float]] = {"rest": [], "pool": []}
    fell: list[bool] = []
    for case, steps in (("rest", 1000), ("pool", 400)):
        for e in range(episodes):
            start = None
            if case == "pool":
                i = pool.sample(rng)
                start = (pool.qpos[i], pool.qvel[i])
            ep = rollout(env, policy, seed=seed + e, rng=rng, max_steps=steps, start_state=start)
            v = np.asarray(ep.infos["x_velocity"], dtype=float)
            fell.append(ep.terminated)
            out[case].append(float(np.nanmean(v if fell[-1] else v[100:])))
    speeds = np.asarray(out["rest"] + out["pool"])
    fails = int(((np.abs(speeds - target) > 0.4) | np.asarray(fell)).sum())
    return {
        "rest_mean": float(np.mean(out["rest"])),
        "rest_std": float(np.std(out["rest"])),
        "pool_mean": float(np.mean(out["pool"])),
        "pool_std": float(np.std(out["pool"])),
        "fails": fails,
        "falls": int(sum(fell)),
        "score": float(np.mean(np.abs(speeds - target)) + np.std(out["rest"]) + fails),
        "speeds": out,
    }


def _pool(cfg: RefineConfig, env, seed_offset: int) -> StatePool:
    """States of every other level (snapshots at `noise_scale`, and a uniform-random policy)."""
    # A random Hopper / Walker2d is falling by the time its states are kept: such starts teach nothing.
    random_states = env_slug(cfg.env_id) in NEVER_TERMINATES
    others: dict = {"random": RandomPolicy(env.action_space)} if random_states else {}
    for path in list_snapshots(cfg.env_id, cfg.behaviour_dir):
        if path.stem != cfg.level:
            others[path.stem] = load_behaviour(path, env.action_space)
            others[path.stem].noise_scale = cfg.noise_scale
    return build_pool(env, others, cfg.pool_episodes, cfg.seed + seed_offset)


def refine(cfg: RefineConfig) -> dict:
    """Run PPO from the level's snapshot, measure snapshots, and write the best one over the level's file.

    Returns:
        The chosen snapshot's measurement (with its step).
    """
    from stable_baselines3.common.monitor import Monitor

    torch.set_num_threads(1)
    p = cfg.preset
    slug = env_slug(cfg.env_id)
    level_path = cfg.behaviour_dir / slug / cfg.level
    env = gym.make(cfg.env_id)
    init = load_behaviour(level_path, env.action_space)
    if list(init.meta.hidden_sizes) != list(p.hidden_sizes) or init.meta.activation != p.activation:
        raise ValueError(
            f"{level_path}: network {init.meta.hidden_sizes}/{init.meta.activation} differs from the preset"
        )
    train_pool, eval_pool = _pool(cfg, env, 0), _pool(cfg, env, 10_000)
    cfg.work_dir.mkdir(parents=True, exist_ok=True)

    def make_env():
        e = gym.make(cfg.env_id)
        shaped = TargetSpeedReward if cfg.reward == "absolute" else SpeedTent
        e = PoolStart(shaped(e, cfg.target_speed), train_pool, cfg.pool_fraction, cfg.seed)
        return Monitor(FixedObsNorm(e, init))

    # The snapshot's own observation normalisation (FixedObsNorm) and its actor: PPO normalises rewards only.
    model, _ = make_ppo(make_env, replace(p, learning_rate=cfg.learning_rate), cfg.seed, norm_obs=False)
    policy = model.policy
    copy_actor(policy, init.state_dict(), str(level_path))
    actor_params = [
        *policy.mlp_extractor.policy_net.parameters(),
        *policy.action_net.parameters(),
        policy.log_std,
    ]
    for prm in actor_params:
        prm.requires_grad_(False)

    def export(step: int) -> BehaviourPolicy:
        state = actor_state(policy)
        meta = init.meta.__class__(**{**asdict(init.meta), "train_step": step})
        save_behaviour(snapshot_path(cfg.work_dir, step), state, meta)
        return load_behaviour(snapshot_path(cfg.work_dir, step), env.action_space)

    records: list[dict] = []
    start = time.time()

    def record(step: int) -> dict:
        snap = export(step)
        snap.noise_scale = cfg.noise_scale
        rec = {
            "step": step,
            **measure_refined(env, snap, eval_pool, cfg.target_speed, cfg.eval_episodes, 30_000),
        }
        print(
            f"step {step:>7d}  rest {rec['rest_mean']:5.2f} +- {rec['rest_std']:.2f}  pool {rec['pool_mean']:5.2f} "
            f"+- {rec['pool_std']:.2f}  fails {rec['fails']:2d} (falls {rec['falls']:2d})  score {rec['score']:.3f}  "
            f"{step / max(time.time() - start, 1e-9):5.0f} steps/s",
            flush=True,
        )
        return rec

    def unfreeze(step: int) -> None:
        if step == cfg.critic_warmup:
            for prm in actor_params:
                prm.requires_grad_(True)

    keep_record(records, record(0), cfg.work_dir)
    run_ppo(model, cfg.timesteps, lambda _: cfg.eval_every, record, records, cfg.work_dir, unfreeze)
    best = min(records, key=lambda r: r["score"])
    chosen = load_behaviour(snapshot_path(cfg.work_dir, best["step"]), env.action_space)
    meta = chosen.meta
    meta.train_step = (init.meta.train_step or 0) + best["step"]
    meta.mean_speed, meta.std_speed = best["rest_mean"], best["rest_std"]
    meta.extra = {
        **init.meta.extra,
        "refined": {
            "from_step": init.meta.train_step,
            "refine_step": best["step"],
            "target_speed": cfg.target_speed,
            "measured_with_noise_scale": cfg.noise_scale,
            "rest_mean": best["rest_mean"],
            "rest_std": best["rest_std"],
            "pool_mean": best["pool_mean"],
            "pool_std": best["pool_std"],
            "fails": best["fails"],
            "episodes": cfg.eval_episodes,
        },
    }
    save_behaviour(cfg.out_dir / cfg.level, level_state(chosen), meta)
    return best


def command_line(cfg: RefineConfig) -> str:
    """The `gmt data refine` invocation that reproduces `cfg`."""
    return (
        f"gmt data refine --env {cfg.env_id} --level {cfg.level} --target-speed {cfg.target_speed} "
        f"--timesteps {cfg.timesteps} --learning-rate {cfg.learning_rate} --critic-warmup {cfg.critic_warmup} "
        f"--pool-fraction {cfg.pool_fraction} --pool-episodes {cfg.pool_episodes} --noise-scale {cfg.noise_scale} "
        f"--reward {cfg.reward} --eval-every {cfg.eval_every} --eval-episodes {cfg.eval_episodes} --seed {cfg.seed}"
    )


def write_provenance(cfg: RefineConfig, best: dict, seconds: float) -> Path:
    """Add (or replace) this level's refinement section in `<out_dir>/TRAINED_WITH.md`."""
    path = cfg.out_dir / "TRAINED_WITH.md"
    begin, end = f"<!-- refine:{cfg.level} -->", f"<!-- /refine:{cfg.level} -->"
    text = path.read_text() if path.exists() else ""
    if begin in text and end in text:
        text = text[: text.index(begin)].rstrip() + "\n" + text[text.index(end) + len(end) :].lstrip("\n")
    reward_text = (
        f"`-|x_velocity - {cfg.target_speed}| - ctrl_cost`"
        if cfg.reward == "absolute"
        else f"`SpeedTent` (the env's reward, forward term `{cfg.target_speed} - |x_velocity - {cfg.target_speed}|`)"
    )
    section = f"""{begin}
## Refined level: {cfg.level}

`{cfg.level}` was then fine-tuned from the snapshot above ({seconds / 60:.1f} min, one thread) with:

```bash
{command_line(cfg)}
```

PPO (same preset, learning rate {cfg.learning_rate}) on the reward {reward_text},
with {cfg.pool_fraction:.0%} of the episodes starting from states that the other levels and a uniform-random policy
visited, the snapshot's observation normalisation frozen, and only the new critic trained for the first
{cfg.critic_warmup} steps. Every {cfg.eval_every} steps the actor was measured ({cfg.noise_scale} x noise,
{cfg.eval_episodes} episodes from rest and {cfg.eval_episodes} from other states); the best score was step
{best["step"]}: from rest {best["rest_mean"]:.3f} +- {best["rest_std"]:.3f} m/s, from other levels' states
{best["pool_mean"]:.3f} +- {best["pool_std"]:.3f} m/s, {best["fails"]} episodes off by more than 0.4 m/s.
Snapshots and measurements: `{cfg.work_dir}/` (not committed).
{end}
"""
    path.write_text(text.rstrip() + "\n\n" + section)
    return path
