"""One DAgger round for a Breakout GMT: the model plays, the scripted level labels every state it reaches.

A Breakout imitator agrees with its teacher on the teacher's own games (~83%) far more than on its own (~66%;
docs/breakout.md): once it plays, it reaches states the data never showed, with no example of
what to do there. DAgger (Ross et al. 2011) closes that loop: play the trained model, record at every state the
action the teacher would have taken there, and train again on the old data plus these labelled states.

`collect` plays each commanded goal with the model (`--goals 4=lead4 3=lead4 ...`: goal id = level that labels
it) on `--seeds` fresh seeds and writes the episodes as a Minari dataset. The recorded action is the level's, the
one the game got is kept as `infos["executed_action"]` (the layout of DART data, `datagen/breakout.py`), and each
episode's metadata names its goal, level and the model that drove it.

`merge` writes a new dataset holding a base dataset's episodes and then those of one or more rollout datasets (the
HDF5 groups are copied as they are, compressed), and a goal table for `gmt train --labels`: the base episodes keep
the goals relabelling gives them (`--statistic`, `--k`, `--seed`, the same call `gmt train` makes), every rollout
episode gets the goal that was commanded, whatever it scored (it was played by the model, not by the level), and
an episode of a scripted dataset (no `goal` in its metadata: more data of the same levels, the control) gets the
goal whose centre is nearest its return, as k-means assigns.

    python -m gmt.datagen.breakout_dagger collect behaviour/breakout-dagger-gmt/round0-gmt \\
        --goals 4=lead4 0=lead170 1=lead152 --seeds 80 --out-id gmt/breakout/lead-dagger-a-v1
    python -m gmt.datagen.breakout_dagger merge gmt/breakout/lead-v1 gmt/breakout/lead-dagger-a-v1 \\
        --out-id gmt/breakout/lead-dagger-v1 --k 5 --labels data/labels/breakout-dagger-1.json

The Remake section of checkpoints/breakout-dagger-gmt/PROVENANCE.md runs the whole chain behind that checkpoint.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

SEED_BASE = 10_000  # rollout seeds start here: apart from the evaluation's seeds (0..) and the data's (drawn)


def parse_goals(items: list[str]) -> dict[int, str]:
    """["4=lead4", "0=lead170"] -> {4: "lead4", 0: "lead170"}, levels checked against `LEVELS`."""
    from gmt.datagen.breakout import LEVELS

    out = {}
    for item in items:
        goal, sep, level = item.partition("=")
        if not sep or not goal.strip().isdigit():
            raise ValueError(f"expected GOAL=LEVEL, e.g. 4=lead4, got {item!r}")
        if level not in LEVELS:
            raise ValueError(f"unknown level {level!r}; levels: {', '.join(LEVELS)}")
        out[int(goal)] = level
    return out


def rollout(engine, spec, goal: int, level: str, seed: int, mode: str, steps: int):
    """One episode of `goal` played by the engine and labelled by `level`; returns (Played, agreement)."""
    from gmt.common.envs import make_env
    from gmt.datagen.breakout import LEVELS, Played, TrackingAgent, read_ram

    env = make_env(spec, max_steps=steps)
    obs, info = env.reset(seed=seed)
    ctx = engine.new_context(goal, mode, seed=seed)
    teacher = TrackingAgent(LEVELS[level])
    rng = np.random.default_rng(seed)
    frames, labels, executed, rewards, lives = [obs], [], [], [], []
    state = read_ram(env)
    ball_y = [state.ball_y]
    terminated = truncated = False
    while not (terminated or truncated):
        label = teacher.decide(state, rng)
        (a,) = engine.act([ctx], [obs])
        if isinstance(a, Exception):
            raise a
        a = int(a)
        teacher.played(a)  # the paddle moved as the model moved it
        obs, r, terminated, truncated, info = env.step(a)
        state = read_ram(env)
        frames.append(obs)
        labels.append(label)
        executed.append(a)
        rewards.append(float(r))
        lives.append(info.get("lives", 0))
        ball_y.append(state.ball_y)
    env.close()
    played = Played.from_steps(frames, labels, rewards, lives, terminated, truncated, ball_y, executed)
    return played, float(np.mean(played.actions == played.executed))


def collect(
    checkpoint: str,
    goals: dict[int, str],
    seeds: int,
    out_id: str,
    action_mode: str | None = None,
    steps: int = 1000,
    seed_base: int = SEED_BASE,
    progress: bool = True,
) -> dict:
    """Play every goal of `goals` on `seeds` seeds and write the labelled episodes as dataset `out_id`."""
    from tqdm import tqdm

    from gmt.common.envs import make_env
    from gmt.datagen.breakout import ENV_ID, recompress, update_metadata
    from gmt.model.checkpoint import load_checkpoint, model_info
    from gmt.model.data.minari_io import write_dataset
    from gmt.model.engine import PolicyEngine

    start = time.time()
    if not 1 <= seeds <= 1000:
        raise ValueError(
            f"seeds must be 1-1000 (goal g's episodes start from seed base + 1000 g), got {seeds}"
        )
    ckpt = load_checkpoint(checkpoint)
    for g in goals:
        if not 0 <= g < len(ckpt.goals):
            raise ValueError(f"goal {g} is not one of the checkpoint's {len(ckpt.goals)} goals")
    engine = PolicyEngine(ckpt)
    spec = model_info(ckpt)
    mode = action_mode or engine.default_action_mode
    episodes, metadata, summary = [], [], {}
    with tqdm(total=len(goals) * seeds, desc="dagger", unit="ep", disable=not progress) as bar:
        for goal, level in goals.items():
            rets, agree = [], []
            for i in range(seeds):
                seed = seed_base + 1000 * goal + i
                ep, agreement = rollout(engine, spec, goal, level, seed, mode, steps)
                episodes.append(ep.to_episode(len(episodes)))
                metadata.append(
                    {
                        "policy": f"dagger:{level}",
                        "goal": goal,
                        "reset_seed": seed,
                        "return": ep.ret,
                        "agreement": agreement,
                        "driver": checkpoint,
                        "action_mode": mode,
                    }
                )
                rets.append(ep.ret)
                agree.append(agreement)
                bar.update(1)
                bar.set_postfix(goal=goal, ret=f"{np.mean(rets):.1f}", agree=f"{np.mean(agree):.2f}")
            summary[str(goal)] = {
                "level": level,
                "episodes": seeds,
                "mean_return": float(np.mean(rets)),
                "agreement": float(np.mean(agree)),
                "steps": int(sum(len(e.actions) for e in episodes[-seeds:])),
            }
    env = make_env(spec, max_steps=steps)  # the dataset's spaces: the game the checkpoint declares
    description = (
        f"DAgger rollouts of {checkpoint} ({mode} actions) on {ENV_ID}: goal=level "
        + ", ".join(f"{g}={lv}" for g, lv in goals.items())
        + f", {seeds} episodes each from seed {seed_base} + 1000 x goal, at most {steps} steps. Actions are the "
        "level's label at each state; infos executed_action holds the model's. Written by "
        "`python -m gmt.datagen.breakout_dagger collect`."
    )
    path = write_dataset(
        out_id,
        episodes,
        ENV_ID,
        env.observation_space,
        env.action_space,
        episode_metadata=metadata,
        description=description,
        algorithm_name="gmt-dagger-breakout",
        overwrite=True,
    )
    env.close()
    update_metadata(path, {"preprocessing": ckpt.preprocessing, "jpeg_encoding": False, "dagger": summary})
    recompress(path)
    return {"dataset": out_id, "path": str(path), "seconds": round(time.time() - start, 1), "goals": summary}


def merge(base: str, parts: list[str], out_id: str, statistic: str, k: int, seed: int, labels: str) -> dict:
    """Base episodes, then each part's, as dataset `out_id`; the goal table for `gmt train --labels`."""
    import h5py

    from gmt.model.data.minari_io import check_dataset_id, data_root, resolve
    from gmt.model.data.relabel import GoalTable, relabel

    check_dataset_id(out_id)
    if statistic != "return":
        raise ValueError(f"only the return statistic is supported here (Breakout's goals), got {statistic!r}")
    src = resolve(base)
    dst = data_root(None) / out_id / "data"
    if dst.parent.exists():
        shutil.rmtree(dst.parent)
    dst.mkdir(parents=True)
    shutil.copy(src / "main_data.hdf5", dst / "main_data.hdf5")
    meta = json.loads((src / "metadata.json").read_text())
    with h5py.File(dst / "main_data.hdf5", "r") as f:
        n_base = len(f.keys())
        values = [float(f[f"episode_{i}"]["rewards"][()].sum()) for i in range(n_base)]
        obs_shape = f["episode_0"]["observations"].shape[1:]
    table = relabel(np.asarray(values), statistic=statistic, k=k, seed=seed)
    goals_of = list(table.labels)
    means = np.asarray([g.mean for g in table.goals])

    def nearest(value: float) -> int:  # k-means' own assignment: the closest centre (1-D)
        return int(np.argmin(np.abs(means - value)))

    steps, n = int(meta.get("total_steps", 0)), n_base
    added = {}
    with h5py.File(dst / "main_data.hdf5", "a") as out:
        for part in parts:
            before, p = n, resolve(part)
            with h5py.File(p / "main_data.hdf5", "r") as f:
                for i in range(len(f.keys())):
                    g = f[f"episode_{i}"]
                    if g["observations"].shape[1:] != obs_shape:
                        raise ValueError(
                            f"{part}: observations {g['observations'].shape[1:]} != base {obs_shape}"
                        )
                    ret = float(g["rewards"][()].sum())
                    # a rollout episode has the goal it was commanded; a scripted one the nearest goal's
                    goal = int(g.attrs["goal"]) if "goal" in g.attrs else nearest(ret)
                    if not 0 <= goal < k:
                        raise ValueError(f"{part} episode {i}: goal {goal} outside 0..{k - 1}")
                    f.copy(g, out, name=f"episode_{n}")
                    out[f"episode_{n}"].attrs["id"] = n
                    goals_of.append(goal)
                    values.append(ret)
                    steps += int(g.attrs["total_steps"])
                    n += 1
            added[part] = added.get(part, 0) + n - before
    meta.update(
        {
            "dataset_id": out_id,
            "total_episodes": n,
            "total_steps": steps,
            "description": f"{base} ({n_base} episodes) followed by "
            + ", ".join(f"{p} ({m} episodes)" for p, m in added.items())
            + ", merged by `python -m gmt.datagen.breakout_dagger merge`.",
            "dagger_merge": {"base": base, "base_episodes": n_base, "parts": added},
        }
    )
    (dst / "metadata.json").write_text(json.dumps(meta))
    d = table.to_dict()
    d["labels"] = [int(x) for x in goals_of]
    d["values"] = values
    Path(labels).parent.mkdir(parents=True, exist_ok=True)
    GoalTable.from_dict(d).save(labels)
    counts = np.bincount(np.asarray(goals_of[n_base:], dtype=np.int64), minlength=k).tolist()
    return {"dataset": out_id, "episodes": n, "steps": steps, "rollout_episodes_per_goal": counts}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect", help="play goals with the model, label with levels, write a dataset")
    c.add_argument("checkpoint")
    c.add_argument("--goals", nargs="+", required=True, help="GOAL=LEVEL pairs, e.g. 4=lead4 0=lead170")
    c.add_argument("--seeds", type=int, default=40, help="episodes per goal")
    c.add_argument(
        "--seed-base", type=int, default=SEED_BASE, help="episode i of goal g: seed base + 1000 g + i"
    )
    c.add_argument("--steps", type=int, default=1000, help="agent steps per episode at most")
    c.add_argument("--action-mode", default=None, help="engine action mode (default: the checkpoint's)")
    c.add_argument("--threads", type=int, default=1, help="torch threads")
    c.add_argument("--out-id", required=True, help="dataset id to write, namespace/name-vN")
    m = sub.add_parser("merge", help="base dataset + rollout datasets -> one dataset and a goal table")
    m.add_argument("base")
    m.add_argument("parts", nargs="+")
    m.add_argument("--out-id", required=True)
    m.add_argument("--statistic", default="return")
    m.add_argument("--k", type=int, required=True, help="goals of the base dataset's relabelling")
    m.add_argument("--seed", type=int, default=0, help="relabelling seed (gmt train's --seed)")
    m.add_argument("--labels", required=True, help="goal table to write, for gmt train --labels")
    a = ap.parse_args(argv)
    if a.cmd == "collect":
        import torch

        torch.set_num_threads(a.threads)
        res = collect(
            a.checkpoint, parse_goals(a.goals), a.seeds, a.out_id, a.action_mode, a.steps, a.seed_base
        )
    else:
        res = merge(a.base, a.parts, a.out_id, a.statistic, a.k, a.seed, a.labels)
    print(json.dumps(res))


if __name__ == "__main__":
    main()
