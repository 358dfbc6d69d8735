"""From served sessions to a dataset: recordings (`gmt.common.recording`) become a Minari dataset.

Each recorded environment episode becomes a Minari episode (observations, actions, the rewards and the
terminated / truncated flags the client reported, and as infos the numbers it reported, e.g. `x_velocity`)
with a per-step goal label: the info `goal`, the goal the session pursued at that step according to its timeline
(checked against the goal the server recorded with each step). The dataset's metadata.json holds `goal_labels`
(where the labels come from, the models' fingerprints, the goal table), which `gmt train` uses instead of
relabelling by a per-trajectory statistic. Episodes of another dataset (`include`, e.g. the offline data the
served model was trained on) can be added, labelled by `gmt train`'s own relabelling, so that one dataset holds
both; their goal table must be the served model's.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gmt.common.recording import RecordedEpisode, Recording, find_recordings, read_recording
from gmt.common.spaces import space_from_dict
from gmt.model.data.minari_io import Episode, load_dataset, write_dataset

GOAL_INFO = "goal"  # the info key of per-step goal labels
LABELS_KEY = "goal_labels"  # the metadata.json key describing them


@dataclass
class ImportResult:
    """What `import_sessions` wrote."""

    dataset_id: str
    path: Path
    recordings: int
    episodes: int
    transitions: int
    switches: int
    included: int = 0
    skipped: list[str] = field(default_factory=list)


def timeline_labels(timeline: list[dict], steps: int) -> np.ndarray:
    """The goal pursued at each of `steps` steps of one episode, from its timeline entries (in order; the last
    entry at a step wins, as the server applied them)."""
    out = np.empty(steps, np.int64)
    entries = sorted(enumerate(timeline), key=lambda ie: (ie[1]["step"], ie[0]))
    if steps and (not entries or entries[0][1]["step"] != 0):
        raise ValueError("the timeline has no goal for step 0")
    for j, (_, e) in enumerate(entries):
        end = entries[j + 1][1]["step"] if j + 1 < len(entries) else steps
        out[min(e["step"], steps) : min(end, steps)] = e["goal"]
    return out


def _goal_table(rec: Recording) -> list[dict]:
    return [{k: g[k] for k in ("id", "name", "mean")} for g in rec.meta.get("goals") or []]


def _episode(rec: Recording, ep: RecordedEpisode, obs_dtype: np.dtype, index: int) -> Episode:
    labels = timeline_labels(ep.timeline, len(ep))
    bad = np.flatnonzero(labels != ep.goals)
    if len(bad):
        raise ValueError(
            f"recording {rec.meta['session_id']}, episode {ep.episode}: the timeline says goal {labels[bad[0]]} at "
            f"step {bad[0]}, the recorded step says {ep.goals[bad[0]]}"
        )
    infos = {k: v.astype(np.float64) for k, v in ep.infos.items()} | {GOAL_INFO: labels.astype(np.float64)}
    return Episode(
        observations=ep.observations.astype(obs_dtype),
        actions=ep.actions,
        rewards=np.nan_to_num(ep.rewards, nan=0.0).astype(np.float32),
        terminated=ep.terminated,
        truncated=ep.truncated,
        infos=infos,
        final_observation=None if ep.final_observation is None else ep.final_observation.astype(obs_dtype),
        episode_id=index,
    )


def import_sessions(
    paths: list[str | Path],
    dataset_id: str,
    data_dir: str | Path | None = None,
    *,
    include: str | None = None,
    min_steps: int = 1,
    overwrite: bool = False,
) -> ImportResult:
    """Write the recorded episodes under `paths` (recordings, or directories of them) as a Minari dataset.

    Args:
        paths: Recording files (`<session_id>.json` or `.npz`) or directories holding them.
        dataset_id: The new dataset's id, e.g. gmt/halfcheetah/served-v0.
        data_dir: Datasets root (default: $GMT_DATA_DIR, else data/minari).
        include: Also take every episode of this dataset, labelled by the served model's relabelling (the
            statistic, k and seed recorded in its checkpoint are not known here: the dataset is relabelled as
            `gmt train` would, and its goal table must match the recordings').
        min_steps: Leave out recorded episodes with fewer transitions.
        overwrite: Replace an existing dataset with that id.

    Raises:
        FileNotFoundError: no recording found.
        ValueError: recordings of different environments or goal tables, or an inconsistent recording.
    """
    files = find_recordings(paths)
    recs = [read_recording(p) for p in files]
    envs = {r.meta.get("env_id") for r in recs}
    if len(envs) != 1 or None in envs:
        raise ValueError(f"the recordings are of several environments (or none): {sorted(map(str, envs))}")
    tables = {json.dumps(_goal_table(r)) for r in recs}
    if len(tables) != 1:
        raise ValueError("the recordings come from models with different goal tables; import them separately")
    first = recs[0].meta
    env_id = first["env_id"]
    obs_space = space_from_dict(first["observation_space"])
    act_space = space_from_dict(first["action_space"])
    goals = first["goals"]
    episodes, meta, skipped = [], [], []
    for rec in recs:
        for ep in rec.episodes():
            if len(ep) < min_steps:
                skipped.append(f"{rec.meta['session_id']}#{ep.episode} ({len(ep)} steps)")
                continue
            episodes.append(_episode(rec, ep, obs_space.dtype, len(episodes)))
            meta.append(
                {
                    "source": "served",
                    "session_id": rec.meta["session_id"],
                    "session_episode": ep.episode,
                    "model": rec.meta["model"],
                    "fingerprint": rec.meta.get("fingerprint") or "",
                    "switches": ep.switches,
                    "rewards_reported": bool(ep.reported.all()),
                }
            )
    if not episodes:
        raise ValueError(f"no recorded episode has {min_steps} or more transitions")
    n_served = len(episodes)
    switches = sum(m["switches"] for m in meta)
    if include is not None:
        extra = _included(include, first, data_dir)
        for ep in extra:
            ep.episode_id = len(episodes)
            episodes.append(ep)
            meta.append({"source": include, "switches": 0})
    keys = sorted(set().union(*(ep.infos for ep in episodes)))
    for ep in episodes:  # Minari wants the same info keys in every episode: NaN where one was not reported
        ep.infos = {k: ep.infos.get(k, np.full(len(ep), np.nan)) for k in keys}
    description = (
        f"{n_served} episodes recorded by gmt serve ({len(recs)} sessions of {sorted({r.meta['model'] for r in recs})}"
        f" on {env_id}), with per-step goal labels from each session's timeline (info `{GOAL_INFO}`)"
        + (f", plus the {len(episodes) - n_served} episodes of {include}" if include else "")
        + ". Written by `gmt data import-sessions`."
    )
    path = write_dataset(
        dataset_id,
        episodes,
        env_id,
        obs_space,
        act_space,
        data_dir,
        episode_metadata=[{k: v for k, v in m.items()} for m in meta],
        description=description,
        algorithm_name="gmt-served-sessions",
        overwrite=overwrite,
    )
    labels = {
        "source": "timeline",
        "info": GOAL_INFO,
        "statistic": first.get("statistic"),
        "goals": goals,
        "models": sorted({f"{r.meta['model']}@{(r.meta.get('fingerprint') or '')[:12]}" for r in recs}),
        **({"included": include} if include else {}),
    }
    meta_path = path / "metadata.json"
    data = json.loads(meta_path.read_text())
    data[LABELS_KEY] = labels
    meta_path.write_text(json.dumps(data))
    return ImportResult(
        dataset_id,
        path,
        len(recs),
        len(episodes),
        sum(len(e) for e in episodes),
        switches,
        len(episodes) - n_served,
        skipped,
    )


def _included(dataset: str, served: dict, data_dir: str | Path | None = None) -> list[Episode]:
    """Every episode of `dataset`, with the per-step goal label of its trajectory (relabelled as `gmt train`
    does), after checking that its goal table is the served model's."""
    from gmt.model.data.relabel import relabel
    from gmt.model.data.statistics import per_trajectory

    ds = load_dataset(dataset, data_dir)
    if ds.env_id != served["env_id"]:
        raise ValueError(f"{dataset} is {ds.env_id}, the recordings are {served['env_id']}")
    goals = served["goals"]
    table = relabel(
        per_trajectory(served["statistic"], ds), statistic=served["statistic"], k=len(goals), seed=0
    )
    for g, s in zip(table.goals, goals, strict=True):
        if g.name != s["name"] or abs(g.mean - s["mean"]) > max(1e-3, 0.02 * abs(s["mean"])):
            raise ValueError(
                f"{dataset} relabels goal {g.id} as {g.name} (mean {g.mean:.3f}); the served model's goal {s['id']} "
                f"is {s['name']} (mean {s['mean']:.3f}): the labels would not mean the same goals"
            )
    out = []
    for ep, label in zip(ds.episodes, table.labels, strict=True):
        ep.infos = {**ep.infos, GOAL_INFO: np.full(len(ep), float(label))}
        out.append(ep)
    return out


def step_labels(dataset) -> tuple[list[np.ndarray], list[dict]] | None:
    """(per-episode [T] goal labels, goal table) of a dataset written by `import_sessions`, else None."""
    labels = getattr(dataset, "goal_labels", None)
    if not labels:
        return None
    key = labels.get("info", GOAL_INFO)
    missing = [ep.episode_id for ep in dataset.episodes if key not in ep.infos]
    if missing:
        raise ValueError(f"{dataset.dataset_id}: episodes {missing[:5]} lack the per-step goal info {key!r}")
    out = []
    for ep in dataset.episodes:
        v = ep.infos[key]
        if not np.isfinite(v).all():
            raise ValueError(f"{dataset.dataset_id}: episode {ep.episode_id} has steps without a goal label")
        out.append(v.astype(np.int64))
    return out, labels["goals"]


def switch_count(labels: list[np.ndarray]) -> tuple[int, int]:
    """(goal switches in all episodes, episodes with at least one)."""
    per = [int(np.count_nonzero(np.diff(lab))) for lab in labels]
    return sum(per), sum(1 for n in per if n)
