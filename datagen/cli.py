"""`gmt data ...`: train behaviour agents, collect, describe and relabel offline datasets, import served sessions.

Heavy imports (torch, gymnasium, sklearn, matplotlib) stay inside the commands so `gmt --help` is fast. `collect`,
`describe`, `relabel` and `import-sessions` need the `data` extra, `behaviour` and `refine` the `train` extra;
`statistics` nothing.
"""

from __future__ import annotations

import math
from pathlib import Path

import typer

from gmt.common.cli_support import needs

app = typer.Typer(help="Offline datasets: behaviour agents, collection, statistics and goal relabelling.")


def parse_targets(targets: list[str] | None) -> dict[str, float | str] | None:
    """LEVEL=SPEED or LEVEL=max options (repeated) as a dict (None when none is given)."""
    if not targets:
        return None
    out: dict[str, float | str] = {}
    for item in targets:
        name, _, value = item.partition("=")
        if not value:
            raise typer.BadParameter(f"expected LEVEL=SPEED or LEVEL=max, got {item!r}")
        out[name] = value if value == "max" else float(value)
    return out


def _level_values(items: list[str] | None, value: str, hint: str) -> dict[str, float]:
    """LEVEL=NUMBER options (repeated) as a dict; a missing level name or a non-finite number is refused."""
    out: dict[str, float] = {}
    for item in items or []:
        name, _, text = item.partition("=")
        try:
            out[name] = float(text)
        except ValueError:
            raise typer.BadParameter(f"expected LEVEL={value}, got {item!r}", param_hint=hint) from None
        if not name or not math.isfinite(out[name]):
            raise typer.BadParameter(
                f"expected LEVEL={value} with a finite number, got {item!r}", param_hint=hint
            )
    return out


def parse_range(text: str | None) -> tuple[float, float] | None:
    """A LO:HI option in m/s as (lo, hi) (None when not given)."""
    if text is None:
        return None
    lo, sep, hi = text.partition(":")
    try:
        if not sep:
            raise ValueError
        return float(lo), float(hi)
    except ValueError:
        raise typer.BadParameter(f"expected LO:HI in m/s, e.g. 0.5:2.6, got {text!r}") from None


@app.command()
@needs("train", "gmt data behaviour")
def behaviour(
    env: str = typer.Option(..., help="Gymnasium id, e.g. HalfCheetah-v5."),
    timesteps: int = typer.Option(1_000_000, help="PPO environment steps."),
    eval_every: int = typer.Option(20_000, help="Steps between snapshot speed measurements."),
    dense_steps: int = typer.Option(200_000, help="Measure 4x as often during the first DENSE_STEPS."),
    eval_episodes: int = typer.Option(3, help="Stochastic episodes per measurement."),
    final_episodes: int = typer.Option(
        30, help="Episodes per snapshot in the measurement that picks levels."
    ),
    target: list[str] = typer.Option(None, help="LEVEL=SPEED (m/s) or LEVEL=max; repeat. Default per env."),
    seed: int = typer.Option(0, help="Seed of PPO and of the measurements."),
    out_dir: Path = typer.Option(None, help="Where snapshots go (default behaviour/<env>/)."),
    select_only: bool = typer.Option(
        False, help="Skip training; choose levels among the kept snapshots up to TIMESTEPS (runs/behaviour/)."
    ),
    track: bool = typer.Option(
        False,
        help="One PPO run per level, rewarded for holding its target speed; writes only the levels given "
        "(so separate processes can train separate levels).",
    ),
    pool_start: float = typer.Option(
        0.0,
        help="With --track: share of episodes starting from states of the other levels' current snapshots "
        "(so the level learns to reach its speed from theirs).",
    ),
) -> None:
    """Train a PPO behaviour agent and export snapshots at target speeds (needs the `train` extra)."""
    from gmt.datagen.train_behaviour import (
        BehaviourTrainConfig,
        remeasure_all,
        select_levels,
        train,
        write_provenance,
    )

    cfg = BehaviourTrainConfig(
        env_id=env,
        total_timesteps=timesteps,
        eval_every=eval_every,
        dense_steps=dense_steps,
        eval_episodes=eval_episodes,
        final_episodes=final_episodes,
        targets=parse_targets(target),
        seed=seed,
        out_dir=out_dir,
        track=track,
        pool_start=pool_start,
    )
    if select_only:
        coarse = {lv: remeasure_all(cfg, lv) for lv in cfg.targets} if track else remeasure_all(cfg)
        chosen = select_levels(cfg, coarse)
    else:
        chosen = train(cfg)
    typer.echo(f"wrote {write_provenance(cfg, chosen)}")


@app.command()
@needs("train", "gmt data commanded")
def commanded(
    env: str = typer.Option(..., help="Gymnasium id, e.g. Hopper-v5."),
    target: list[str] = typer.Option(..., help="LEVEL=SPEED (m/s), slowest first; repeat."),
    timesteps: int = typer.Option(2_000_000, help="PPO environment steps."),
    eval_every: int = typer.Option(50_000, help="Steps between measured snapshots."),
    switch_every: int = typer.Option(300, help="Mean steps between command changes in training episodes."),
    track_weight: float = typer.Option(
        1.0,
        help="Weight of the speed-tracking error in the reward (above 1 a standing agent can prefer falling).",
    ),
    overspeed_weight: float = typer.Option(
        0.0, help="Extra reward weight of speed above the command (urges braking; standing is not penalised)."
    ),
    track_window: int = typer.Option(
        1,
        help="Steps of x-velocity averaged before the tracking terms compare it with the command (1: each step).",
    ),
    command_range: str = typer.Option(
        None,
        help="LO:HI (m/s): train on commands drawn uniformly from this range, not only the levels' speeds.",
    ),
    ent_coef: float = typer.Option(None, help="PPO entropy bonus in place of the environment preset's."),
    ceiling: float = typer.Option(
        None,
        help="Torso height (m) above which training reward is docked (Ant: bounces end episodes above 1.0).",
    ),
    ceiling_weight: float = typer.Option(
        0.0, help="Reward docked per metre of torso height above --ceiling."
    ),
    cycle_every: int = typer.Option(
        None, help="Also measure snapshots cycling through the levels every N steps (choose fast changes)."
    ),
    eval_seeds: int = typer.Option(2, help="Episodes per hold and per switch in a snapshot's measurement."),
    final_seeds: int = typer.Option(8, help="Episodes per hold and per switch when choosing among the best."),
    seed: int = typer.Option(0, help="Seed of PPO and of the measurements."),
    out_dir: Path = typer.Option(None, help="Where the levels go (default behaviour/<env>/)."),
    work_dir: Path = typer.Option(
        None, help="Where every snapshot is kept (default runs/behaviour/<env>/commanded)."
    ),
    select_only: bool = typer.Option(False, help="Skip training; choose among the kept snapshots."),
    snapshot: int = typer.Option(
        None,
        help="With --select-only: export this kept snapshot (its training step) instead of the best-scored one, "
        "e.g. one chosen by screening the kept snapshots (docs/data.md).",
    ),
    resume_from: int = typer.Option(
        None,
        help="Go on from this training step of --work-dir: from its learner file (kept with every snapshot), "
        "else warm-started from its actor-only snapshot (critic fresh); --timesteps stays the run's total.",
    ),
) -> None:
    """Train one speed-commanded PPO agent that switches between levels; export each level (`train` extra)."""
    import json
    import shlex
    import sys

    from gmt.datagen.train_commanded import (
        CommandedConfig,
        resume_source,
        select_commanded,
        train_commanded,
        write_commanded_provenance,
    )

    targets = parse_targets(target) or {}
    if any(v == "max" for v in targets.values()):
        raise typer.BadParameter("commanded levels need speeds in m/s, not max", param_hint="--target")
    try:
        cfg = CommandedConfig(
            env_id=env,
            targets=targets,
            total_timesteps=timesteps,
            eval_every=eval_every,
            switch_every=switch_every,
            track_weight=track_weight,
            overspeed_weight=overspeed_weight,
            track_window=track_window,
            command_range=parse_range(command_range),
            ent_coef=ent_coef,
            ceiling=ceiling,
            ceiling_weight=ceiling_weight,
            cycle_every=cycle_every,
            eval_seeds=eval_seeds,
            final_seeds=final_seeds,
            seed=seed,
            out_dir=out_dir,
            work_dir=work_dir,
            resume_from=resume_from,
        )
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None
    if resume_from is not None:
        if select_only:
            raise typer.BadParameter("--resume-from trains: drop --select-only", param_hint="--resume-from")
        if resume_source(cfg.work_dir, resume_from) is None:
            raise typer.BadParameter(
                f"no learner or snapshot at step {resume_from} in {cfg.work_dir}", param_hint="--resume-from"
            )
    if snapshot is not None and not select_only:
        raise typer.BadParameter(
            "--snapshot chooses among kept snapshots: add --select-only", param_hint="--snapshot"
        )
    if select_only:
        records = json.loads((cfg.work_dir / "records.json").read_text())
        if snapshot is not None:
            records = [r for r in records if r["step"] == snapshot]
            if not records:
                raise typer.BadParameter(
                    f"no snapshot at step {snapshot} in {cfg.work_dir}", param_hint="--snapshot"
                )
        best = select_commanded(cfg, records)
    else:
        best = train_commanded(cfg)
    command = "gmt data commanded " + " ".join(shlex.quote(a) for a in sys.argv[3:])
    typer.echo(f"wrote {write_commanded_provenance(cfg, best, command, snapshot is not None)}")


@app.command()
@needs("data", "gmt data gait")
def gait(
    params: Path = typer.Argument(
        ...,
        help="A gait's parameters (JSON): a bare GaitConfig or a parameter search's output (docs/data.md).",
    ),
    level: list[str] = typer.Option(
        None, help="LEVEL=HZ, one stride frequency per level; repeat (default: the search's slow and fast)."
    ),
    target: list[str] = typer.Option(
        None, help="LEVEL=SPEED (m/s): that level's speed loop holds SPEED by moving its frequency; repeat."
    ),
    noise: float = typer.Option(0.1, help="Std of the Gaussian action noise of every level."),
    episodes: int = typer.Option(10, help="Noisy episodes measured per level."),
    out_dir: Path = typer.Option(None, help="Where the levels go (default behaviour/ant/)."),
) -> None:
    """Write scripted Ant gait levels (datagen/gait.py), each measured, collected like any snapshot."""
    import json
    import shlex
    import sys

    from gmt.datagen.behaviour import BEHAVIOUR_DIR
    from gmt.datagen.gait import GaitConfig, write_levels

    try:
        data = json.loads(params.read_text())
    except (OSError, ValueError) as e:
        raise typer.BadParameter(f"cannot read {params}: {e}", param_hint="PARAMS") from None
    try:
        cfg = GaitConfig(**data.get("gait", data))
    except (TypeError, ValueError) as e:
        raise typer.BadParameter(f"{params} is not a gait: {e}", param_hint="PARAMS") from None
    if level:
        freqs = _level_values(level, "HZ", "--level")
        if min(freqs.values()) <= 0:
            raise typer.BadParameter(f"stride frequencies must be > 0 Hz, got {freqs}", param_hint="--level")
    elif "slow_freq" in data:
        freqs = {"slow": float(data["slow_freq"]), "fast": cfg.freq}
    else:
        raise typer.BadParameter("a bare GaitConfig names no levels: give --level", param_hint="--level")
    if not (math.isfinite(noise) and noise > 0) or episodes < 1:
        raise typer.BadParameter(f"need --noise > 0 and --episodes >= 1, got {noise}, {episodes}")
    targets = _level_values(target, "SPEED", "--target")
    if set(targets) - set(freqs):
        raise typer.BadParameter(
            f"{sorted(set(targets) - set(freqs))}: a target speed needs one of the levels {list(freqs)}",
            param_hint="--target",
        )
    command = "gmt data gait " + " ".join(shlex.quote(a) for a in sys.argv[3:])
    written = write_levels(cfg, freqs, noise, out_dir or BEHAVIOUR_DIR / "ant", command, episodes,
                           targets=targets)  # fmt: skip
    for path in written:
        if path.suffix == ".json":
            meta = json.loads(path.read_text())
            typer.echo(f"{meta['level']}: {meta['mean_speed']:.3f} +- {meta['std_speed']:.3f} m/s, "
                       f"{meta['extra']['falls']} falls in {episodes}")  # fmt: skip
    typer.echo(f"wrote {', '.join(str(p) for p in written)}")


@app.command()
@needs("train", "gmt data refine")
def refine(
    env: str = typer.Option(..., help="Gymnasium id, e.g. HalfCheetah-v5."),
    level: str = typer.Option("slow", help="Level to refine; its snapshot is the starting actor."),
    target_speed: float = typer.Option(1.2, help="Target x-velocity (m/s) of the reward."),
    timesteps: int = typer.Option(200_000, help="PPO environment steps."),
    learning_rate: float = typer.Option(3e-5, help="PPO learning rate."),
    critic_warmup: int = typer.Option(20_000, help="Steps that train only the new critic."),
    pool_fraction: float = typer.Option(0.5, help="Share of episodes starting from other levels' states."),
    pool_episodes: int = typer.Option(10, help="Episodes per other level rolled out for the state pool."),
    noise_scale: float = typer.Option(
        None, help="Action-noise multiplier of pool rollouts and measurements (default: collect's, per env)."
    ),
    reward: str = typer.Option(
        None,
        help="absolute (-|v - target| - ctrl) or tent (SpeedTent); default: absolute if the task never ends.",
    ),
    eval_every: int = typer.Option(10_000, help="Steps between snapshot measurements."),
    eval_episodes: int = typer.Option(8, help="Episodes from rest and from pool states per measurement."),
    seed: int = typer.Option(0, help="Seed of PPO, the pool and the measurements."),
    out_dir: Path = typer.Option(None, help="Where the refined snapshot goes (default: over the original)."),
) -> None:
    """Fine-tune one level with a target-speed reward from other levels' states (needs the `train` extra)."""
    import time

    from gmt.datagen.refine_behaviour import RefineConfig, command_line, refine, write_provenance

    cfg = RefineConfig(
        env_id=env, level=level, target_speed=target_speed, timesteps=timesteps, learning_rate=learning_rate,
        critic_warmup=critic_warmup, pool_fraction=pool_fraction, pool_episodes=pool_episodes,
        noise_scale=noise_scale, reward=reward, eval_every=eval_every, eval_episodes=eval_episodes, seed=seed, out_dir=out_dir,
    )  # fmt: skip
    typer.echo(command_line(cfg))
    start = time.time()
    best = refine(cfg)
    typer.echo(f"wrote {write_provenance(cfg, best, time.time() - start)}")
    typer.echo(
        f"chose step {best['step']}: from rest {best['rest_mean']:.3f} +- {best['rest_std']:.3f}, from pool states "
        f"{best['pool_mean']:.3f} +- {best['pool_std']:.3f}, {best['fails']} failed episodes; "
        f"wrote {cfg.out_dir / cfg.level}.safetensors"
    )


@app.command()
@needs("data", "gmt data collect")
def collect(
    env: str = typer.Option(..., help="Gymnasium id, e.g. HalfCheetah-v5."),
    episodes_per_level: int = typer.Option(
        None, help="Episodes per snapshot and for random (default per env)."
    ),
    seed: int = typer.Option(0, help="Root seed of resets and action noise."),
    out_id: str = typer.Option(None, help="Dataset id (default gmt/<env>/mixed-v0)."),
    data_dir: Path = typer.Option(None, help="Datasets root (default $GMT_DATA_DIR, else data/minari)."),
    behaviour_dir: Path = typer.Option(
        None, help="Folder with <env>/<level>.safetensors (default behaviour/)."
    ),
    max_steps: int = typer.Option(None, help="Cap episode length (for quick checks)."),
    noise_scale: float = typer.Option(
        None,
        help="Multiplier of the snapshots' action-noise std (default per env: HalfCheetah 0.35, else 1).",
    ),
    no_random: bool = typer.Option(False, help="Leave out the uniform-random policy."),
    keep_stuck: bool = typer.Option(
        None,
        "--keep-stuck/--drop-stuck",
        help="Keep (or replace) episodes in which a running agent stopped for good; default: replaced on the "
        "shipped locomotion tasks, kept elsewhere.",
        show_default=False,
    ),
    keep_falls: bool = typer.Option(
        None,
        "--keep-falls/--drop-falls",
        help="Keep (or replace) episodes that end in a termination; default: replaced on the shipped locomotion "
        "tasks (a fall), kept elsewhere (how an episode ends).",
        show_default=False,
    ),
    policy: str = typer.Option(
        None,
        help="module:function, your policy: function(obs, level, rng) -> action, collected at each --level "
        "instead of the behaviour snapshots (docs/your-own-data.md).",
    ),
    level: list[str] = typer.Option(
        None,
        help="A level name passed to --policy, or NAME=FILE.zip: a level acted by a Stable-Baselines3 model "
        "(the train extra); repeat (two or more).",
    ),
    pool_start: list[str] = typer.Option(
        None,
        help="LEVEL=SHARE: that share of LEVEL's episodes starts from states the other policies visited; "
        "repeat. Default per env (HalfCheetah: slow=0.5). LEVEL=0 turns it off.",
    ),
    pool_checkpoint: Path = typer.Option(
        None,
        help="A GMT checkpoint whose own rollouts (holding the goal nearest each other level's speed) give the "
        "pool-started episodes their start states, instead of the other levels' policies.",
    ),
    pool_cycle: int = typer.Option(
        None,
        help="With --pool-checkpoint: its rollouts cycle through all its goals every N steps instead of holding "
        "goals, so the pools also hold the states between two speeds.",
    ),
    plan: list[str] = typer.Option(
        None,
        help="LEVEL=C1,C2,...: plan the start of LEVEL's pool-started episodes in the simulator, choosing among "
        "continuations of the commanded level at these commands (datagen/plan.py); repeat per level.",
    ),
    plan_candidates: int = typer.Option(12, help="Continuations simulated per planning decision."),
    plan_every: int = typer.Option(
        20, help="Steps played from a chosen continuation before the next decision."
    ),
    plan_horizon: int = typer.Option(80, help="Steps simulated per continuation."),
    plan_steps: int = typer.Option(200, help="Leading steps of a planned episode that are planned."),
    plan_from_rest: list[str] = typer.Option(
        None,
        help="LEVEL[=SPEED] (one of the --plan levels): also plan LEVEL's episodes that start from rest (the "
        "reset pose), so the level speeds up at the pace the plan finds; SPEED (m/s) scores those episodes' "
        "continuations instead of the level's own speed (above it: a more urgent start); repeat per level.",
    ),
    plan_rest_commands: list[str] = typer.Option(
        None,
        help="LEVEL=C1,C2,... (one of the --plan-from-rest levels): the commands of LEVEL's episodes from rest "
        "instead of its --plan commands, e.g. a sprint from standing above the level's own range; repeat per level.",
    ),
    plan_target: list[str] = typer.Option(
        None,
        help="LEVEL=SPEED (one of the --plan levels): score LEVEL's planned pool-started episodes against SPEED "
        "(m/s) instead of the level's measured speed, e.g. a little below it to brake harder after a switch down; "
        "repeat per level.",
    ),
) -> None:
    """Roll out every behaviour snapshot and a random policy into a Minari dataset.

    For ALE/Breakout-v5 the behaviour is scripted agents reading the game's RAM (`gmt.datagen.breakout`; more
    options: `python -m gmt.datagen.breakout --help`).
    """
    if env.startswith("ALE/Breakout"):
        from gmt.datagen.breakout import DEFAULT_RECIPE, RECIPES
        from gmt.datagen.breakout import main as collect_breakout

        argv = ["--seed", str(seed)]
        argv += ["--out-id", out_id] if out_id else []
        argv += ["--data-dir", str(data_dir)] if data_dir else []
        argv += ["--max-steps", str(max_steps)] if max_steps else []
        if episodes_per_level:
            levels = RECIPES[DEFAULT_RECIPE].episodes
            argv += ["--episodes", *(f"{level}={episodes_per_level}" for level in levels)]
        raise typer.Exit(collect_breakout(argv))
    from gmt.datagen.collect import CollectConfig, collect
    from gmt.datagen.plan import PlanConfig, parse_plan

    rest = {}
    for item in plan_from_rest or []:
        name, sep, value = item.partition("=")
        try:
            rest[name] = float(value) if sep else None
        except ValueError:
            raise typer.BadParameter(
                f"expected LEVEL or LEVEL=SPEED, got {item!r}", param_hint="--plan-from-rest"
            ) from None
    targets = {}
    for item in plan_target or []:
        name, sep, value = item.partition("=")
        try:
            speed = float(value)
        except ValueError:
            speed = math.nan
        if not (sep and name and math.isfinite(speed)):
            raise typer.BadParameter(f"expected LEVEL=SPEED, got {item!r}", param_hint="--plan-target")
        targets[name] = speed
    rest_commands = {}
    for item in plan_rest_commands or []:
        try:
            name, commands = parse_plan(item)
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--plan-rest-commands") from None
        if name not in rest:
            raise typer.BadParameter(
                f"{name!r} has no --plan-from-rest: rest commands are for its episodes from rest",
                param_hint="--plan-rest-commands",
            )
        rest_commands[name] = commands
    plans = {}
    for item in plan or []:
        try:
            name, commands = parse_plan(item)
            plans[name] = PlanConfig(
                commands, plan_candidates, plan_every, plan_horizon, plan_steps, target=targets.get(name),
                from_rest=name in rest, rest_target=rest.get(name), rest_commands=rest_commands.get(name),
            )  # fmt: skip
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--plan") from None
    for option, levels in (("--plan-from-rest", rest), ("--plan-target", targets)):
        unknown = sorted(set(levels) - set(plans))
        if unknown:
            raise typer.BadParameter(
                f"{unknown} have no --plan: give LEVEL=C1,C2,... for each", param_hint=option
            )
    shares = _level_values(pool_start, "SHARE", "--pool-start") if pool_start else None
    if policy is not None:
        from gmt.datagen.user_policy import load_policy_function

        try:
            load_policy_function(policy)  # a name that cannot be imported: said before the environment starts
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--policy") from None

    try:
        cfg = CollectConfig(
            env_id=env,
            episodes_per_level=episodes_per_level,
            seed=seed,
            dataset_id=out_id,
            data_dir=data_dir,
            behaviour_dir=behaviour_dir,
            max_steps=max_steps,
            noise_scale=noise_scale,
            include_random=not no_random,
            drop_stuck=None if keep_stuck is None else not keep_stuck,
            drop_falls=None if keep_falls is None else not keep_falls,
            policy=policy,
            levels=level or None,
            pool_start=shares,
            pool_checkpoint=pool_checkpoint,
            pool_cycle=pool_cycle,
            plan=plans,
        )
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None
    res = collect(cfg)
    typer.echo(f"wrote {res.dataset_id} to {res.path}")
    typer.echo(f"{res.episodes} episodes, {res.transitions} transitions in {res.seconds:.1f} s")
    for name, lv in res.levels.items():
        speed = (
            ""
            if lv["mean_speed"] is None
            else f"  mean x-velocity {lv['mean_speed']:.3f} +- {lv['std_speed']:.3f}"
        )
        typer.echo(
            f"  {name:<8} {lv['episodes']} episodes ({lv['pool_starts']} from pool states, {lv['planned']} planned, "
            f"{lv['stuck_dropped']} stuck and {lv['falls_dropped']} fallen ones replaced){speed}"
        )


STATISTIC_HELP = (
    "Per-trajectory statistic: AGG(SOURCE) (AGG mean, sum, min, max, first, last, std; SOURCE reward, info.KEY, "
    "obs[i], action[i], optionally abs(...)), a name (mean_x_velocity, return) or module:function; default: "
    "inferred from the data (mean_x_velocity where infos record x_velocity, else return) and printed."
)


def _relabel(dataset: str, statistic: str | None, k: int | None, seed: int, data_dir: Path | None, ds=None):
    from gmt.model.data.minari_io import load_dataset
    from gmt.model.data.relabel import relabel
    from gmt.model.data.statistics import MissingInfoError, chosen_statistic, per_trajectory

    ds = ds or load_dataset(dataset, data_dir)
    statistic = statistic or chosen_statistic(ds, typer.echo)
    try:
        values = per_trajectory(statistic, ds)
    except (MissingInfoError, KeyError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None
    return ds, relabel(values, statistic=statistic, k=k, seed=seed)


@app.command()
@needs("data", "gmt data describe")
def describe(
    dataset: str = typer.Argument(..., help="Dataset id or path."),
    statistic: str = typer.Option(None, help=STATISTIC_HELP),
    k: int = typer.Option(None, help="Fix the number of goals instead of sampling it."),
    seed: int = typer.Option(0, help="Seed of k-means and of the sampling of k."),
    data_dir: Path = typer.Option(None, help="Datasets root (default $GMT_DATA_DIR, else data/minari)."),
    plot: Path = typer.Option(None, help="Save a histogram of the statistic coloured by goal here."),
) -> None:
    """Print size, goal switches, silhouette scores, chosen k and the goal table of a dataset."""
    import numpy as np

    from gmt.model.data.minari_io import load_dataset
    from gmt.model.data.relabel import separation
    from gmt.model.data.served import step_labels, switch_count

    ds = load_dataset(dataset, data_dir)
    typer.echo(f"{ds.dataset_id} ({ds.env_id}): {len(ds.episodes)} episodes, {ds.n_transitions} transitions")
    typer.echo(f"fingerprint {ds.fingerprint}")
    served = step_labels(ds)
    if served is None:
        typer.echo("goal switches: 0 (one goal per trajectory, from relabelling)\n")
    else:
        per_step, goals = served
        n, eps = switch_count(per_step)
        counts = np.bincount(np.concatenate(per_step), minlength=len(goals))
        typer.echo(
            f"goal switches: {n} in {eps} of {len(per_step)} episodes (per-step labels from served sessions' "
            f"timelines, {ds.goal_labels.get('models')}); steps per goal: "
            + ", ".join(f"{g['id']}={g['name']}: {c}" for g, c in zip(goals, counts, strict=False))
            + "\n"
        )
    if served is not None:  # relabelling by the statistic is for comparison only: it may not apply
        from gmt.model.data.relabel import relabel
        from gmt.model.data.statistics import MissingInfoError, chosen_statistic, per_trajectory

        statistic = statistic or chosen_statistic(ds, typer.echo)
        try:
            table = relabel(per_trajectory(statistic, ds), statistic=statistic, k=k, seed=seed)
        except (MissingInfoError, ValueError) as e:
            typer.echo(f"(no relabelling by {statistic}: {e})")
            return
        typer.echo(f"for comparison, relabelled per trajectory by {statistic}:")
    else:
        ds, table = _relabel(dataset, statistic, k, seed, data_dir, ds)
        statistic = table.statistic
    typer.echo(table.format())
    seps = separation(table)
    if seps:
        pairs = ", ".join(f"{i}-{i + 1}: {s:.1f}" for i, s in enumerate(seps))
        typer.echo(f"\nneighbour separation (mean gap / larger std): {pairs}")
    if plot:
        from gmt.model.data.plots import plot_goals

        plot_goals(table, plot, title=f"{ds.dataset_id}: {statistic}")
        typer.echo(f"saved {plot}")


@app.command()
@needs("data", "gmt data relabel")
def relabel(
    dataset: str = typer.Argument(..., help="Dataset id or path."),
    out: Path = typer.Option(..., help="Where to write the goal table (JSON)."),
    statistic: str = typer.Option(None, help=STATISTIC_HELP),
    k: int = typer.Option(None, help="Fix the number of goals instead of sampling it."),
    seed: int = typer.Option(0, help="Seed of k-means and of the sampling of k."),
    data_dir: Path = typer.Option(None, help="Datasets root (default $GMT_DATA_DIR, else data/minari)."),
) -> None:
    """Cluster trajectories into goals and write the goal table and per-episode labels as JSON."""
    _, table = _relabel(dataset, statistic, k, seed, data_dir)
    table.save(out)
    typer.echo(table.format())
    typer.echo(f"\nwrote {out}")


@app.command("import")
@needs("data", "gmt data import")
def import_command(
    src: Path = typer.Argument(
        ...,
        help="A folder of .npz episode files (docs/your-own-data.md), a Minari dataset (id or folder), or a "
        "folder of served sessions' recordings.",
    ),
    dataset_id: str = typer.Option(..., "--id", help="The new dataset's id, namespace/name-vN."),
    env: str = typer.Option(
        None, help="Gymnasium id whose spaces the data must fit (default: spaces inferred from the data)."
    ),
    overwrite: bool = typer.Option(False, help="Replace an existing dataset with this id."),
    data_dir: Path = typer.Option(None, help="Datasets root (default $GMT_DATA_DIR, else data/minari)."),
) -> None:
    """Check your own episodes (lengths, shapes, NaN) and write them as a Minari dataset."""
    from gmt.common.recording import RecordingError
    from gmt.model.data.importer import import_data

    try:
        rep = import_data(src, dataset_id, env, data_dir, overwrite)
    except (FileNotFoundError, FileExistsError, RecordingError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None
    typer.echo(
        f"wrote {rep.path} ({rep.kind}): {rep.episodes} episodes, {rep.transitions} transitions; environment "
        f"{rep.env_id}, observations {rep.observation_space}, actions {rep.action_space}; per-step infos: "
        f"{', '.join(rep.info_keys) or 'none'}"
    )


@app.command("import-sessions")
@needs("data", "gmt data import-sessions")
def import_sessions(
    recordings: list[Path] = typer.Argument(
        ..., help="Recordings (<session_id>.json / .npz from gmt serve --record-dir) or directories of them."
    ),
    out_id: str = typer.Option(..., help="The new dataset's id, e.g. gmt/halfcheetah/served-v0."),
    include: str = typer.Option(
        None,
        help="Also take every episode of this dataset (e.g. the served model's training data), relabelled.",
    ),
    min_steps: int = typer.Option(1, min=1, help="Leave out recorded episodes with fewer transitions."),
    overwrite: bool = typer.Option(False, help="Replace an existing dataset with this id."),
    data_dir: Path = typer.Option(None, help="Datasets root (default $GMT_DATA_DIR, else data/minari)."),
) -> None:
    """Turn served sessions' recordings into a Minari dataset with per-step goal labels from their timelines
    (`gmt data import RECORDINGS --id ID` does the same without --include)."""
    from gmt.common.recording import RecordingError
    from gmt.model.data.served import import_sessions as run_import

    try:
        res = run_import(
            recordings, out_id, data_dir, include=include, min_steps=min_steps, overwrite=overwrite
        )
    except (FileNotFoundError, FileExistsError, RecordingError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None
    also = f"; {res.included} from {include}" if include else ""
    typer.echo(
        f"wrote {res.path}: {res.episodes} episodes ({res.episodes - res.included} recorded in {res.recordings} "
        f"sessions, {res.switches} goal switches{also}), {res.transitions} transitions"
    )
    if res.skipped:
        typer.echo(f"left out {len(res.skipped)} short episodes: {', '.join(res.skipped[:10])}")


@app.command()
def statistics() -> None:
    """List the registered per-trajectory statistics and how to write any other."""
    from gmt.common.statistics import AGGREGATIONS, canonical, get_statistic, list_statistics

    for name in list_statistics():
        s = get_statistic(name)
        needs = f" (needs info {sorted(s.requires)})" if s.requires else ""
        same = f" = {canonical(name)}" if canonical(name) != name else ""
        typer.echo(f"{name:<18} {s.description}{same}{needs}")
    typer.echo(
        f"any other: AGG(SOURCE), AGG one of {', '.join(AGGREGATIONS)}, SOURCE reward, info.KEY, obs[i] or "
        "action[i], optionally abs(...), e.g. mean(abs(obs[2])); or module:function (docs/your-own-data.md)"
    )
