"""`gmt data import`: bring one's own episodes in as a Minari dataset, checked before anything is written.

A source is one of:
- a folder of `.npz` episode files (`gmt.common.episode_files`: the format, and a writer for Python collectors);
- a Minari dataset (an id or a folder): rewritten under the new id;
- a folder of served sessions' recordings (`gmt serve --record-dir`): `gmt.model.data.served.import_sessions`.

Spaces come from `--env` (its observation and action spaces, which the data must fit) or from the data: Box
observations (vectors or images; uint8 arrays become images in [0, 255]), Box actions bounded by the data's own
range, Discrete actions 0..max. A Dict observation (`observations.KEY` arrays) is flattened in sorted key order
(Gymnasium's `spaces.flatten` order), and the layout is recorded in the dataset's metadata.json
(`observation_layout`: key, shape, start, end). Anything else is refused naming what was found.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np

from gmt.model.data.minari_io import Episode, load_dataset, write_dataset

LAYOUT_KEY = "observation_layout"


class ImportProblem(ValueError):
    """The source cannot be imported; the message names the file and the field."""


@dataclass
class ImportReport:
    """What `import_data` wrote."""

    dataset_id: str
    path: Path
    kind: str  # "npz", "minari" or "sessions"
    episodes: int
    transitions: int
    observation_space: str
    action_space: str
    info_keys: list[str] = field(default_factory=list)
    env_id: str = ""


def source_kind(src: Path) -> str:
    """npz (a folder of episode files), minari (a dataset folder) or sessions (recordings: `gmt.common.recording`,
    whose .npz files hold a `meta` array)."""
    if (src / "metadata.json").is_file() or (src / "data" / "metadata.json").is_file():
        return "minari"
    if src.is_dir():
        for f in sorted(src.glob("*.npz"))[:1]:
            with np.load(f) as z:
                if "actions" in z.files and "meta" not in z.files:  # a recording's .npz holds its `meta`
                    return "npz"
        return "sessions"
    raise ImportProblem(f"{src}: not a folder of .npz episodes, a Minari dataset or a folder of recordings")


def _fail(name: str, what: str) -> ImportProblem:
    return ImportProblem(f"{name}: {what}")


def _observations(z, name: str) -> tuple[np.ndarray, list[dict] | None]:
    """[T or T+1, ...] observations, and the layout of a flattened Dict observation (else None)."""
    if "observations" in z.files:
        return np.asarray(z["observations"]), None
    keys = sorted(k[len("observations.") :] for k in z.files if k.startswith("observations."))
    if not keys:
        raise _fail(name, "no 'observations' array (nor 'observations.KEY' arrays of a Dict observation)")
    parts, layout, start = [], [], 0
    n = len(z[f"observations.{keys[0]}"])
    for k in keys:
        a = np.asarray(z[f"observations.{k}"])
        if len(a) != n:
            raise _fail(name, f"field 'observations.{k}' has {len(a)} steps, 'observations.{keys[0]}' {n}")
        size = int(np.prod(a.shape[1:], dtype=np.int64))
        layout.append({"key": k, "shape": list(a.shape[1:]), "start": start, "end": start + size})
        parts.append(a.reshape(n, size).astype(np.float32))
        start += size
    return np.concatenate(parts, axis=1), layout


def read_npz_episode(path: Path, index: int) -> tuple[Episode, list[dict] | None]:
    """One episode file, checked: lengths agree, numbers are finite, the arrays have the documented shapes."""
    name = path.name
    try:
        z = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise _fail(name, f"not a readable .npz file ({e})") from None
    with z:
        for required in ("actions", "rewards"):
            if required not in z.files:
                raise _fail(name, f"no '{required}' array (it has {sorted(z.files)})")
        obs, layout = _observations(z, name)
        actions, rewards = np.asarray(z["actions"]), np.asarray(z["rewards"])
        T = len(actions)
        if T == 0:
            raise _fail(name, "field 'actions' is empty: an episode needs at least one step")
        if rewards.shape != (T,):
            raise _fail(name, f"field 'rewards' has shape {rewards.shape}, expected ({T},) (one per action)")
        if len(obs) not in (T, T + 1):
            raise _fail(
                name, f"field 'observations' has {len(obs)} steps, expected {T} or {T + 1} ({T} actions)"
            )
        ends = {}
        for key in ("terminations", "truncations"):
            if key in z.files:
                a = np.asarray(z[key])
                if a.shape != (T,):
                    raise _fail(name, f"field '{key}' has shape {a.shape}, expected ({T},)")
                ends[key] = bool(a[-1])
        infos = {}
        for key in z.files:
            if key.startswith("info."):
                a = np.asarray(z[key])
                if a.shape != (T,) or a.dtype.kind not in "biuf":
                    raise _fail(
                        name, f"field '{key}' has shape {a.shape} ({a.dtype}), expected ({T},) numbers"
                    )
                infos[key[len("info.") :]] = a.astype(np.float64)
        for field_name, arr in (("observations", obs), ("actions", actions), ("rewards", rewards)):
            if arr.dtype.kind not in "biuf":
                raise _fail(name, f"field '{field_name}' holds {arr.dtype}, not numbers")
            if arr.dtype.kind == "f" and not np.isfinite(arr).all():
                bad = int(np.argwhere(~np.isfinite(arr.reshape(len(arr), -1)))[0, 0])
                raise _fail(name, f"field '{field_name}' has a NaN or infinity at step {bad}")
    ep = Episode(
        observations=obs[:T],
        actions=actions,
        rewards=rewards.astype(np.float32),
        terminated=ends.get("terminations", False),
        truncated=ends.get("truncations", not ends.get("terminations", False)),
        infos=infos,
        final_observation=obs[T] if len(obs) == T + 1 else None,
        episode_id=index,
    )
    return ep, layout


def _infer_spaces(episodes: list[Episode]) -> tuple[gym.spaces.Space, gym.spaces.Space]:
    obs = episodes[0].observations
    if obs.dtype == np.uint8:
        obs_space = gym.spaces.Box(0, 255, obs.shape[1:], np.uint8)
    else:
        obs_space = gym.spaces.Box(-np.inf, np.inf, obs.shape[1:], np.float32)
    acts = [ep.actions for ep in episodes]
    if acts[0].dtype.kind in "iub":
        if acts[0].ndim != 1:
            raise ImportProblem(
                f"integer actions of shape {acts[0].shape[1:]} per step: only Discrete (one integer per step) "
                "or Box (floats) actions are supported"
            )
        lo, hi = min(int(a.min()) for a in acts), max(int(a.max()) for a in acts)
        if lo < 0:
            raise ImportProblem(
                f"integer actions must be 0..n-1 (Discrete), found {lo}; pass --env for its space"
            )
        return obs_space, gym.spaces.Discrete(hi + 1)
    flat = np.concatenate([a.reshape(len(a), -1) for a in acts]).astype(np.float32)
    shape = acts[0].shape[1:]
    low, high = flat.min(axis=0).reshape(shape), flat.max(axis=0).reshape(shape)
    high = np.where(high > low, high, low + 1.0)  # a constant entry still spans a range
    return obs_space, gym.spaces.Box(low, high, shape, np.float32)


def _check_spaces(
    episodes: list[Episode], obs_space, act_space, env_id: str, names: list[str] | None = None
) -> None:
    if not isinstance(obs_space, gym.spaces.Box):
        raise ImportProblem(
            f"{env_id}: only Box observations (or Dict ones, flattened) are supported, got {obs_space}"
        )
    if not isinstance(act_space, gym.spaces.Box | gym.spaces.Discrete):
        raise ImportProblem(f"{env_id}: only Box and Discrete actions are supported, got {act_space}")
    for i, ep in enumerate(episodes):
        name = names[i] if names else f"episode {ep.episode_id}"
        if ep.observations.shape[1:] != obs_space.shape:
            raise _fail(
                name,
                f"field 'observations' has shape {ep.observations.shape[1:]} per step, {env_id} {obs_space.shape}",
            )
        if isinstance(act_space, gym.spaces.Discrete):
            a = ep.actions
            if a.ndim != 1 or a.dtype.kind not in "iub":
                raise _fail(
                    name,
                    f"field 'actions' must be one integer per step for {act_space}, got {a.dtype}{a.shape}",
                )
            if a.min() < act_space.start or a.max() >= act_space.start + act_space.n:
                raise _fail(name, f"field 'actions' has {int(a.min())}..{int(a.max())}, outside {act_space}")
        elif ep.actions.shape[1:] != act_space.shape:
            raise _fail(
                name, f"field 'actions' has shape {ep.actions.shape[1:]} per step, {env_id} {act_space.shape}"
            )


def _env_spaces(env_id: str, layout: list[dict] | None) -> tuple[gym.spaces.Space, gym.spaces.Space]:
    try:
        env = gym.make(env_id)
    except gym.error.Error as e:
        raise ImportProblem(f"--env {env_id}: {e}") from None
    obs_space, act_space = env.observation_space, env.action_space
    env.close()
    if isinstance(obs_space, gym.spaces.Dict):
        if layout is None:
            raise ImportProblem(f"{env_id} has Dict observations: write one 'observations.KEY' array per key")
        obs_space = gym.spaces.flatten_space(obs_space)
    return obs_space, act_space


def import_npz(
    src: Path, dataset_id: str, env_id: str | None, data_dir, overwrite: bool
) -> tuple[Path, list[Episode], gym.spaces.Space, gym.spaces.Space, str]:
    """Read, check and write a folder of episode files."""
    files = sorted(src.glob("*.npz"))
    if not files:
        raise ImportProblem(f"{src}: no .npz episode files")
    read = [read_npz_episode(f, i) for i, f in enumerate(files)]
    episodes = [ep for ep, _ in read]
    layouts = {json.dumps(layout) for _, layout in read}
    if len(layouts) > 1:
        raise ImportProblem(f"{src}: the episodes' Dict observations have different keys or shapes")
    layout = read[0][1]
    for f, ep in zip(files, episodes, strict=True):  # every file like the first
        first = episodes[0]
        for fld in ("observations", "actions"):
            a, b = getattr(ep, fld), getattr(first, fld)
            if a.shape[1:] != b.shape[1:] or (a.dtype.kind == "f") != (b.dtype.kind == "f"):
                raise _fail(f.name, f"field '{fld}' is {a.dtype}{list(a.shape[1:])} per step, {files[0].name} "
                            f"{b.dtype}{list(b.shape[1:])}")  # fmt: skip
    if env_id:
        obs_space, act_space = _env_spaces(env_id, layout)
    else:
        obs_space, act_space = _infer_spaces(episodes)
    _check_spaces(episodes, obs_space, act_space, env_id or "the data", [f.name for f in files])
    if isinstance(act_space, gym.spaces.Box):
        for ep in episodes:
            ep.actions = ep.actions.astype(np.float32)
    else:
        for ep in episodes:
            ep.actions = ep.actions.astype(np.int64)
    path = write_dataset(
        dataset_id,
        episodes,
        env_id or "unknown",
        obs_space,
        act_space,
        data_dir,
        description=f"Imported by `gmt data import` from {len(files)} episode files in {src}.",
        algorithm_name="gmt-data-import",
        overwrite=overwrite,
    )
    if layout is not None:
        meta_path = path / "metadata.json"
        meta = json.loads(meta_path.read_text())
        meta[LAYOUT_KEY] = layout
        meta_path.write_text(json.dumps(meta))
    return path, episodes, obs_space, act_space, env_id or "unknown"


def import_data(
    src: str | Path, dataset_id: str, env_id: str | None = None, data_dir=None, overwrite: bool = False
) -> ImportReport:
    """Import `src` (module docstring) as the Minari dataset `dataset_id`.

    Raises:
        ImportProblem: naming the file and field that cannot be imported (nothing is written then).
        FileExistsError: the dataset exists and `overwrite` is False.
    """
    from gmt.model.data.minari_io import check_dataset_id

    check_dataset_id(dataset_id)
    src = Path(src)
    kind = source_kind(src) if src.exists() else "minari"  # an id of a Minari dataset
    if kind == "sessions":
        from gmt.model.data.served import import_sessions

        res = import_sessions([src], dataset_id, data_dir, overwrite=overwrite)
        ds = load_dataset(str(res.path), data_dir)
        episodes, path = ds.episodes, res.path
        obs_space, act_space, env = ds.observation_space, ds.action_space, ds.env_id
    elif kind == "minari":
        ds = load_dataset(str(src), data_dir)
        env = env_id or ds.env_id
        obs_space, act_space = ds.observation_space, ds.action_space
        _check_spaces(ds.episodes, obs_space, act_space, env)
        episodes = ds.episodes
        path = write_dataset(dataset_id, episodes, env, obs_space, act_space, data_dir,
                             description=f"Imported by `gmt data import` from the Minari dataset {ds.dataset_id}.",
                             algorithm_name="gmt-data-import", overwrite=overwrite)  # fmt: skip
    else:
        path, episodes, obs_space, act_space, env = import_npz(src, dataset_id, env_id, data_dir, overwrite)
    keys = sorted(set.intersection(*(set(ep.infos) for ep in episodes))) if episodes else []
    return ImportReport(
        dataset_id,
        path,
        kind,
        len(episodes),
        sum(len(e) for e in episodes),
        str(obs_space),
        str(act_space),
        keys,
        env,
    )
