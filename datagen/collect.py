"""Collect a mixed offline dataset: every behaviour snapshot (stochastic) plus a uniform-random policy.

Needs only torch, gymnasium and the exported snapshots in behaviour/<env>/. Seeded: the same config writes
the same arrays.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from gmt.common.statistics import canonical
from gmt.datagen.behaviour import RandomPolicy, env_slug, list_snapshots, load_behaviour
from gmt.datagen.plan import PlanConfig, PlannedPolicy
from gmt.datagen.rollout import rollout, stuck_step
from gmt.datagen.start_states import CheckpointPolicy, StatePool, build_pool
from gmt.datagen.user_policy import level_policies
from gmt.model.data.minari_io import Episode, check_dataset_id, write_dataset

RANDOM = "random"
# Episodes per level by default: HalfCheetah feeds the model (~150k transitions per goal); the others are
# sized to keep `make data` to minutes (their agents also fall, so episodes can be short).
DEFAULT_EPISODES = {"halfcheetah": 150, "hopper": 150, "walker2d": 100, "ant": 150}
# Behaviour-noise multipliers. HalfCheetah's PPO snapshots with their full noise (std ~0.13) run ~20% slower than
# their mean action and stall in ~7% of episodes; a policy that imitates the mean then overshoots every goal. At
# 0.35 x their noise they stay diverse (per-episode speed std 0.03-0.07 m/s) and none stalled in 36 test episodes.
DEFAULT_NOISE_SCALE = {"halfcheetah": 0.35}
# Share of a level's episodes that start from a state another level visited (see `start_states`). HalfCheetah's
# slow level is refined (`gmt data refine`) to brake from a sprint and to get going after random flailing; half of
# its episodes show that, the other half start at rest. Hopper's two levels each start half their episodes from
# the other's states (slow braking from a sprint, fast speeding up from a walk); falls are replaced (`drop_falls`).
# The same for Walker2d, whose commanded agent brakes from a sprint in ~74% of its tries (falls are replaced), and
# for Ant's scripted gait levels (`gmt.datagen.gait`), which pick up the stride where the other level left it.
DEFAULT_POOL_START = {
    "halfcheetah": {"slow": 0.5},
    "hopper": {"slow": 0.5, "fast": 0.5},
    "walker2d": {"slow": 0.5, "fast": 0.5},
    "ant": {"slow": 0.5, "fast": 0.5},
}
POOL_EPISODES = 10  # episodes per other level rolled out to build a level's start-state pool


def default_dataset_id(env_id: str) -> str:
    """gmt/<env-lower-without-version>/mixed-v0."""
    return f"gmt/{env_slug(env_id)}/mixed-v0"


@dataclass
class CollectConfig:
    """One collection run.

    Attributes:
        env_id: Gymnasium id, e.g. "HalfCheetah-v5".
        episodes_per_level: Episodes for every snapshot and for the random policy (None: per-env default).
        seed: Root seed of reset seeds and action noise.
        dataset_id: Minari id to write (None: gmt/<env>/mixed-v0).
        data_dir: Datasets root (None: $GMT_DATA_DIR, else data/minari).
        behaviour_dir: Folder holding <env>/<level>.safetensors (None: the repository's behaviour/).
        max_steps: Optional cap on episode length (tests use a tiny one).
        noise_scale: Multiplier of the snapshots' Gaussian action-noise std (None: per-env default, else 1).
        include_random: Add the uniform-random policy as a level.
        drop_stuck: Replace snapshot episodes in which the agent, after running, came to a standstill
            (`rollout.stuck_step` over `stuck_window` steps): the behaviour changed mid-episode, which would
            blur the level's speed. Also replaces pool-started episodes that end standing still (a start
            pose the level cannot leave). Counted per level; the random policy is never filtered. None: on
            for the shipped locomotion tasks (HalfCheetah, Hopper, Walker2d, Ant: its thresholds are in their
            m/s), off for any other environment; turned on elsewhere, its thresholds are relative to each
            episode's own speed (`stuck_step(relative=True)`).
        stuck_window: Steps averaged by the standstill test.
        drop_falls: Replace snapshot episodes that end in a fall (termination). A level's policy that falls
            shows a failure, not its goal (a level started from another's states may fall while changing
            speed), and such episodes would teach the model that braking means falling. Counted per level;
            the random policy is never filtered. None: on for the shipped locomotion tasks, off elsewhere
            (where a termination is how an episode ends, e.g. CartPole's pole falling).
        max_attempts: Episodes tried per level at most, as a multiple of `episodes_per_level`.
        pool_start: Level -> share of its episodes that start from a state visited by the other policies
            (None: per-env default; {} for none).
        pool_checkpoint: A GMT checkpoint whose own rollouts give the start-state pools instead of the other
            levels' policies: for each pool-started level, the model holds the goal nearest each other level's
            measured speed (`start_states.CheckpointPolicy`). None: the other levels' policies.
        pool_cycle: With `pool_checkpoint`: its rollouts cycle through all its goals every this many steps
            (from goal 0) instead of holding goals, so the pools hold the states of a quickly switched model.
        plan: Level -> how that level plans the start of its pool-started episodes, and of its episodes from
            rest where the plan says `from_rest` (`plan.PlannedPolicy`: the commanded level picks, in the
            simulator, the continuation that reaches its speed soonest); None or {} for no planning.
        overwrite: Replace an existing dataset with the same id.
        policy: A user's policy function "module:function" (`gmt.datagen.user_policy`) collected at `levels`,
            instead of the behaviour snapshots.
        levels: The level names passed to `policy`, one level (and its episodes) each; "NAME=FILE.zip" makes
            a level of a Stable-Baselines3 model instead (no `policy` needed).
    """

    env_id: str
    episodes_per_level: int | None = None
    seed: int = 0
    dataset_id: str | None = None
    data_dir: Path | None = None
    behaviour_dir: Path | None = None
    max_steps: int | None = None
    noise_scale: float | None = None
    include_random: bool = True
    drop_stuck: bool | None = None
    stuck_window: int = 100
    drop_falls: bool | None = None
    max_attempts: int = 3
    pool_start: dict[str, float] | None = None
    pool_checkpoint: Path | None = None
    pool_cycle: int | None = None
    plan: dict[str, PlanConfig] | None = None
    overwrite: bool = True
    policy: str | None = None
    levels: list[str] | None = None

    def __post_init__(self) -> None:
        slug = env_slug(self.env_id)
        locomotion = slug in DEFAULT_EPISODES  # the shipped locomotion tasks: the m/s thresholds fit them
        if self.drop_stuck is None:
            self.drop_stuck = locomotion
        if self.drop_falls is None:
            self.drop_falls = locomotion
        if self.policy is not None and not self.levels:
            raise ValueError("a --policy is collected at named levels: give --level NAME at least twice")
        if self.levels and self.policy is None and not all("=" in lv for lv in self.levels):
            raise ValueError("--level NAME names a level of a --policy module:function (or NAME=FILE.zip)")
        names = [lv.partition("=")[0] for lv in self.levels or []]
        if len(set(names)) != len(names) or RANDOM in names:
            raise ValueError(f"levels must be distinct and not {RANDOM!r}, got {names}")
        self.episodes_per_level = self.episodes_per_level or DEFAULT_EPISODES.get(slug, 50)
        self.dataset_id = self.dataset_id or default_dataset_id(self.env_id)
        check_dataset_id(self.dataset_id)  # before minutes of collection, not after
        if self.noise_scale is None:
            self.noise_scale = DEFAULT_NOISE_SCALE.get(slug, 1.0)
        if not self.noise_scale >= 0:
            raise ValueError(f"noise_scale must be >= 0, got {self.noise_scale}")
        if self.pool_start is None:
            self.pool_start = dict(DEFAULT_POOL_START.get(slug, {}))
        for level, share in self.pool_start.items():
            if not 0.0 <= share <= 1.0:
                raise ValueError(f"pool_start[{level!r}] must be in [0, 1], got {share}")
        if self.pool_cycle is not None and (self.pool_checkpoint is None or self.pool_cycle < 1):
            raise ValueError(f"pool_cycle must be >= 1 and needs a pool_checkpoint, got {self.pool_cycle}")
        self.plan = dict(self.plan or {})
        unplanned = sorted(
            level
            for level, p in self.plan.items()
            if not p.from_rest and not self.pool_start.get(level, 0.0) > 0
        )
        if unplanned:
            raise ValueError(
                f"plan names levels without pool starts {unplanned}: without from_rest only pool-started "
                "episodes are planned"
            )


@dataclass
class CollectResult:
    """What a collection wrote."""

    dataset_id: str
    path: Path
    levels: dict[str, dict]
    episodes: int
    transitions: int
    seconds: float
    bytes: int = 0  # size on disk, where the collector measured it


def collect_level(
    env,
    name: str,
    policy,
    cfg: CollectConfig,
    seeds: np.random.SeedSequence,
    first_id: int,
    bar=None,
    pool: StatePool | None = None,
) -> tuple[list[Episode], list[dict], dict]:
    """`cfg.episodes_per_level` episodes of one policy, replacing stuck ones (never for the random policy).

    With a `pool`, episode i starts from a pool state when i is below `pool_start[name]` x the episode count
    (the first share of episodes), else at the reset pose. With a plan for the level, a pool-started episode's
    first steps are planned (`plan.PlannedPolicy`), and an episode from rest's too where the plan says
    `from_rest`.

    Returns:
        The episodes, their Minari episode metadata, and a summary (counts, speed mean and std).
    """
    n = cfg.episodes_per_level
    reset_seeds = iter(seeds.generate_state(n * cfg.max_attempts, dtype=np.uint32))
    rng = np.random.default_rng(seeds)
    filtered = cfg.drop_stuck and name != RANDOM
    n_pool = round(cfg.pool_start.get(name, 0.0) * n) if pool is not None else 0
    plan = cfg.plan.get(name)
    planned = PlannedPolicy(policy, env, plan) if plan is not None and n_pool else None
    rested = PlannedPolicy(policy, env, plan.for_rest()) if plan is not None and plan.from_rest else None
    episodes, metadata, dropped, fell, n_planned = [], [], 0, 0, 0
    while len(episodes) < n:
        reset_seed = next(reset_seeds, None)
        if reset_seed is None:
            raise RuntimeError(
                f"{name}: {dropped} of {len(episodes) + dropped + fell} episodes got stuck and {fell} fell; "
                "giving up (raise max_attempts or improve the level's policy)"
            )
        start, meta = None, {}
        if len(episodes) < n_pool:
            i = pool.sample(rng)
            start = (pool.qpos[i], pool.qvel[i])
            meta = {"start_from": str(pool.source[i]), "start_step": int(pool.step[i])}
        actor = (planned if start is not None else rested) or policy
        if actor is not policy:
            meta["planned_steps"] = actor.cfg.steps
        ep = rollout(env, actor, seed=int(reset_seed), rng=rng, max_steps=cfg.max_steps, start_state=start)
        v = ep.infos.get("x_velocity")
        # A pooled start may be a pose the level cannot get out of (on its back): standing still at the end.
        if (
            filtered
            and v is not None
            and (
                stuck_step(v, cfg.stuck_window, relative=env_slug(cfg.env_id) not in DEFAULT_EPISODES)
                is not None
                or (start is not None and abs(np.mean(v[-cfg.stuck_window :])) < 0.1)
            )
        ):
            dropped += 1
            continue
        if cfg.drop_falls and name != RANDOM and ep.terminated:
            fell += 1
            continue
        episodes.append(ep.to_episode(first_id + len(episodes)))
        n_planned += actor is not policy
        metadata.append({"policy": name, "reset_seed": int(reset_seed), **meta})
        if bar is not None:
            bar.update(1)
            bar.set_postfix(level=name, stuck=dropped, fell=fell)
    speeds = [float(e.infos["x_velocity"].mean()) for e in episodes if "x_velocity" in e.infos]
    summary = {
        "episodes": n,
        "pool_starts": n_pool,
        "planned": n_planned,
        "stuck_dropped": dropped,
        "falls_dropped": fell,
        "mean_speed": float(np.mean(speeds)) if speeds else None,
        "std_speed": float(np.std(speeds)) if speeds else None,
    }
    return episodes, metadata, summary


def checkpoint_sources(
    path: Path, policies: dict, cycle_every: int | None = None
) -> dict[str, dict[str, CheckpointPolicy]]:
    """Level -> {"gmt:<goal>": the checkpoint holding the goal nearest the level's measured speed}, or with
    `cycle_every` {"gmt:cycle<N>": the checkpoint cycling all its goals every N steps} for every level."""
    from gmt.model.checkpoint import load_checkpoint
    from gmt.model.engine import PolicyEngine

    ckpt = load_checkpoint(path)
    if canonical(ckpt.statistic) != canonical("mean_x_velocity"):
        raise ValueError(f"{path}: a pool checkpoint must have x-velocity goals, not {ckpt.statistic!r}")
    engine = PolicyEngine(ckpt)
    if cycle_every is not None:
        cycling = CheckpointPolicy(engine, 0, cycle_every=cycle_every)
        return {name: {f"gmt:cycle{cycle_every}": cycling} for name in policies}
    out = {}
    for name, policy in policies.items():
        speed = getattr(getattr(policy, "meta", None), "mean_speed", None)
        if speed is None:
            raise ValueError(f"level {name!r} has no measured speed to match with a goal of {path}")
        goal = min(ckpt.goals, key=lambda g: abs(g.mean - speed))
        out[name] = {f"gmt:{goal.name}": CheckpointPolicy(engine, goal.id)}
    return out


def collect(cfg: CollectConfig, progress: bool = True) -> CollectResult:
    """Roll out every level's policy `episodes_per_level` times and write one Minari dataset.

    Level order is random first, then the snapshots from slowest to fastest measured speed; each episode's
    policy name and reset seed are stored as Minari episode metadata.
    """
    from tqdm import tqdm

    torch.set_num_threads(1)
    start = time.time()
    env = gym.make(cfg.env_id)
    policies = {RANDOM: RandomPolicy(env.action_space)} if cfg.include_random else {}
    if cfg.levels:
        policies.update(level_policies(cfg.policy, cfg.levels, cfg.seed))
    else:
        for path in list_snapshots(cfg.env_id, cfg.behaviour_dir):
            policies[path.stem] = load_behaviour(path, env.action_space)
            policies[path.stem].noise_scale = cfg.noise_scale
    children = np.random.SeedSequence(cfg.seed).spawn(len(policies))
    unknown = sorted((set(cfg.pool_start) | set(cfg.plan)) - set(policies))
    if unknown:
        raise ValueError(
            f"pool_start or plan names unknown levels {unknown}; the levels are {list(policies)}"
        )
    steps = cfg.max_steps or env.spec.max_episode_steps or 1000
    sources = (
        {name: {name: p} for name, p in policies.items()}
        if cfg.pool_checkpoint is None
        else checkpoint_sources(cfg.pool_checkpoint, policies, cfg.pool_cycle)
    )
    pools = {
        name: build_pool(
            env,
            {k: p for other, src in sources.items() if other != name for k, p in src.items()},
            POOL_EPISODES,
            cfg.seed + 50_000,
            skip=min(20, steps // 2),
            every=max(1, min(10, steps // 10)),
            max_steps=steps,
        )
        for name in policies
        if cfg.pool_start.get(name, 0.0) > 0 and len(policies) > 1  # a lone policy has no one to start from
    }
    episodes, metadata, levels = [], [], {}
    with tqdm(total=cfg.episodes_per_level * len(policies), desc=f"collect {cfg.env_id}", unit="ep",
              disable=not progress) as bar:  # fmt: skip
        for (name, policy), seeds in zip(policies.items(), children, strict=True):
            eps, meta, levels[name] = collect_level(
                env, name, policy, cfg, seeds, len(episodes), bar, pools.get(name)
            )
            episodes += eps
            metadata += meta
    dropped = ", ".join(f"{k} {v['stuck_dropped']}" for k, v in levels.items())
    fell = ", ".join(f"{k} {v['falls_dropped']}" for k, v in levels.items())
    source = (
        f"behaviour snapshots rolled out with {cfg.noise_scale:g} x their Gaussian noise"
        if not cfg.levels
        else f"the user's policies at levels {', '.join(cfg.levels)}"
        + (f" ({cfg.policy})" if cfg.policy else "")
    )
    description = (
        f"Mixed-skill {cfg.env_id} data from policies {', '.join(policies)} ({source}"
        f"{', and a uniform-random policy' * cfg.include_random}), {cfg.episodes_per_level} "
        f"episodes each, seed {cfg.seed}. "
        + f"Snapshot episodes where a running agent came to a standstill were replaced ({dropped}). "
        * cfg.drop_stuck
        + f"Snapshot episodes that ended in a fall were replaced ({fell}). " * cfg.drop_falls
        + "".join(
            f"{round(share * cfg.episodes_per_level)} {name} episodes start from states "
            + (
                "the other policies"
                if cfg.pool_checkpoint is None
                else f"the GMT {cfg.pool_checkpoint} holding the other goals"
                if cfg.pool_cycle is None
                else f"the GMT {cfg.pool_checkpoint} cycling its goals every {cfg.pool_cycle} steps"
            )
            + " visited (episode metadata start_from / start_step). "
            for name, share in cfg.pool_start.items()
            if name in pools
        )
        + "".join(_plan_sentence(name, p) for name, p in cfg.plan.items() if name in pools or p.from_rest)
        + "Written by `gmt data collect`."
    )
    path = write_dataset(
        cfg.dataset_id,
        episodes,
        cfg.env_id,
        env.observation_space,
        env.action_space,
        cfg.data_dir,
        episode_metadata=metadata,
        description=description,
        algorithm_name="gmt-mixed-ppo-snapshots" if not cfg.levels else "gmt-user-policy",
        overwrite=cfg.overwrite,
    )
    return CollectResult(
        dataset_id=cfg.dataset_id,
        path=path,
        levels=levels,
        episodes=len(episodes),
        transitions=sum(len(e) for e in episodes),
        seconds=time.time() - start,
    )


def _plan_sentence(name: str, p) -> str:
    """The dataset description's sentence on how a level's episodes were planned."""
    episodes = f"{name}'s pool-started{' and from-rest' * p.from_rest} episodes"
    rest_parts = []
    if p.rest_target is not None:
        rest_parts.append(f"against {p.rest_target:g} m/s")
    if p.rest_commands is not None:
        rest_parts.append("with commands " + ", ".join(f"{c:g}" for c in p.rest_commands))
    rest = f" (from rest {' and '.join(rest_parts)})" if rest_parts else ""
    target = "the level's speed" if p.target is None else f"{p.target:g} m/s"
    commands = ", ".join(f"{c:g}" for c in p.commands)
    return (
        f"The first {p.steps} steps of {episodes} are planned{rest}: every {p.every} steps the best of "
        f"{p.candidates} simulated {p.horizon}-step continuations (commands {commands}) by closeness of its mean "
        f"x-velocity to {target} (episode metadata planned_steps). "
    )
