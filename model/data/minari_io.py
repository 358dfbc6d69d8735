"""Read and write offline datasets in Minari's format through one small contract (`Episode`, `OfflineDataset`).

Any Minari dataset on disk loads the same way: ours (`gmt/halfcheetah/mixed-v0`) or a D4RL port a user
downloaded (`mujoco/halfcheetah/medium-v0`). Minari stores T + 1 observations and, when infos are recorded,
T + 1 infos (the reset info first); the contract keeps the T observations at which actions were taken and the T
infos returned by `env.step`.

Data root: `$GMT_DATA_DIR` if set, else `data/minari` in the repository. It is Minari's datasets root
(`MINARI_DATASETS_PATH`), so `<root>/gmt/halfcheetah/mixed-v0/data/` holds one dataset.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

DEFAULT_DATA_DIR = Path(__file__).resolve().parents[2] / "data" / "minari"


@dataclass
class Episode:
    """One trajectory, aligned on actions.

    Attributes:
        observations: [T, *obs_shape], the observation each action was taken at.
        actions: [T, *act_shape], float32 for Box, int64 for Discrete.
        rewards: [T] float32.
        terminated: Whether the episode ended in a terminal state.
        truncated: Whether it was cut by a time limit.
        infos: Per-step arrays of length T, the info returned by env.step(action_t), e.g. "x_velocity".
        final_observation: The observation after the last action (None if the source lacks it).
        episode_id: Index of the episode in its dataset.
    """

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminated: bool
    truncated: bool
    infos: dict[str, np.ndarray]
    final_observation: np.ndarray | None
    episode_id: int

    def __len__(self) -> int:
        return len(self.actions)


@dataclass
class OfflineDataset:
    """A whole dataset in memory.

    Attributes:
        dataset_id: Minari id, e.g. "gmt/halfcheetah/mixed-v0".
        env_id: Gymnasium id of the environment, e.g. "HalfCheetah-v5".
        observation_space: The environment's observation space.
        action_space: The environment's action space.
        episodes: All episodes, in dataset order.
        fingerprint: sha256 hex of the observation, action and reward bytes (checkpoint provenance).
        preprocessing: The observation pipeline the collector declared in metadata.json (Atari frames), or None
            for raw environment observations.
        goal_labels: How the per-step goal labels of a dataset of served sessions were made (metadata.json
            `goal_labels`, `gmt.model.data.served`), or None: goals come from relabelling.
    """

    dataset_id: str
    env_id: str
    observation_space: gym.spaces.Space
    action_space: gym.spaces.Space
    episodes: list[Episode]
    fingerprint: str
    preprocessing: dict | None = None
    goal_labels: dict | None = None

    @property
    def n_transitions(self) -> int:
        """Total number of (observation, action) steps."""
        return sum(len(ep) for ep in self.episodes)

    @property
    def info_keys(self) -> set[str]:
        """Info keys present in every episode."""
        if not self.episodes:
            return set()
        return set.intersection(*(set(ep.infos) for ep in self.episodes))


def data_root(path: str | Path | None = None) -> Path:
    """The datasets root: `path` if given, else $GMT_DATA_DIR, else data/minari in the repository."""
    return Path(path or os.environ.get("GMT_DATA_DIR") or DEFAULT_DATA_DIR)


@contextmanager
def minari_root(root: Path) -> Iterator[None]:
    """Point MINARI_DATASETS_PATH at `root` for the duration of the block."""
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def fingerprint(episodes: list[Episode]) -> str:
    """sha256 hex over every episode's observations, actions and rewards, in order."""
    h = hashlib.sha256()
    for ep in episodes:
        for arr in (ep.observations, ep.actions, ep.rewards):
            a = np.ascontiguousarray(arr)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
    return h.hexdigest()


def _candidate_paths(dataset: str, root: str | Path | None) -> list[Path]:
    as_path = Path(dataset)
    paths = [as_path / "data", as_path]
    roots = [data_root(root)]
    if os.environ.get("MINARI_DATASETS_PATH"):
        roots.append(Path(os.environ["MINARI_DATASETS_PATH"]))
    roots.append(Path.home() / ".minari" / "datasets")
    paths += [r / dataset / "data" for r in roots]
    return paths


def resolve(dataset: str, data_dir: str | Path | None = None) -> Path:
    """Find a dataset's `data/` folder (the one holding metadata.json) from an id or a path.

    Raises:
        FileNotFoundError: Naming every place that was searched.
    """
    candidates = _candidate_paths(dataset, data_dir)
    for path in candidates:
        if (path / "metadata.json").is_file():
            return path
    searched = "\n  ".join(str(p) for p in candidates)
    raise FileNotFoundError(
        f"dataset {dataset!r} not found; searched:\n  {searched}\n"
        "Collect one with `gmt data collect --env ENV`, or set GMT_DATA_DIR to the folder holding it."
    )


def _step_infos(infos: dict | None, n_steps: int) -> dict[str, np.ndarray]:
    """Per-step numeric info arrays of length T (drops Minari's leading reset info, skips nested dicts)."""
    out = {}
    for key, value in (infos or {}).items():
        if isinstance(value, dict):
            continue
        arr = np.asarray(value)
        if arr.dtype.kind not in "biuf" or arr.ndim == 0:
            continue
        if len(arr) == n_steps + 1:
            arr = arr[1:]
        if len(arr) == n_steps:
            out[key] = arr
    return out


# Where the root's x-velocity (qvel[0]) sits in each MuJoCo task's observation vector, for the v2-v5 layouts with
# the current x (and, for Ant, y) position excluded (Gymnasium's default): the positions qpos[1:] (qpos[2:] for
# Ant) come first, then the velocities. Keyed by the id's name before "-v"; with the positions included the
# index moves by the number of excluded coordinates. Used when a dataset has no `x_velocity` infos.
X_VELOCITY_OBS_INDEX = {"HalfCheetah": (8, 1), "Hopper": (5, 1), "Walker2d": (8, 1), "Ant": (13, 2)}


def x_velocity_obs_index(env_id: str, env_kwargs: dict | None = None) -> int | None:
    """Index of the x-velocity entry in `env_id`'s observation vector, or None for other tasks."""
    name = env_id.split("/")[-1].split("-v")[0]
    if name not in X_VELOCITY_OBS_INDEX:
        return None
    index, excluded = X_VELOCITY_OBS_INDEX[name]
    if (env_kwargs or {}).get("exclude_current_positions_from_observation", True) is False:
        index += excluded
    return index


def _actions_dtype(space: gym.spaces.Space) -> type:
    return np.int64 if isinstance(space, gym.spaces.Discrete) else np.float32


def load_dataset(dataset: str, data_dir: str | Path | None = None) -> OfflineDataset:
    """Load a Minari dataset into memory.

    Args:
        dataset: A dataset id ("gmt/halfcheetah/mixed-v0") or a path to a dataset folder (or its data/).
        data_dir: Datasets root to search first (default: $GMT_DATA_DIR, else data/minari); Minari's own
            roots ($MINARI_DATASETS_PATH, ~/.minari/datasets) are searched after it.

    Raises:
        FileNotFoundError: If no such dataset exists.
        ValueError: If its observations are not a single array (Dict/Tuple spaces are not supported).
    """
    from minari import MinariDataset

    ds = MinariDataset(resolve(dataset, data_dir))
    obs_space, act_space = ds.observation_space, ds.action_space
    if not isinstance(obs_space, gym.spaces.Box):
        raise ValueError(f"{dataset}: only Box observation spaces are supported, got {obs_space}")
    act_dtype = _actions_dtype(act_space)
    env_id = ds.env_spec.id if ds.env_spec is not None else "unknown"
    vx = x_velocity_obs_index(env_id, ds.env_spec.kwargs if ds.env_spec is not None else None)
    episodes = []
    for raw in ds.iterate_episodes():
        n = len(raw.rewards)
        obs = np.asarray(raw.observations)
        infos = _step_infos(raw.infos, n)
        if (
            "x_velocity" not in infos
            and vx is not None
            and obs.ndim == 2
            and obs.shape[1] > vx
            and len(obs) == n + 1
        ):
            # Recorded without infos (Minari's D4RL ports): the velocity after each step, read from the next
            # observation, stands in for env.step's finite-difference x_velocity (the same within a few %).
            infos["x_velocity"] = obs[1:, vx].astype(np.float64)
        episodes.append(
            Episode(
                observations=obs[:n],
                actions=np.asarray(raw.actions, dtype=act_dtype),
                rewards=np.asarray(raw.rewards, dtype=np.float32),
                terminated=bool(n and raw.terminations[-1]),
                truncated=bool(n and raw.truncations[-1]),
                infos=infos,
                final_observation=obs[n] if len(obs) > n else None,
                episode_id=int(raw.id),
            )
        )
    prep = ds.storage.metadata.get("preprocessing")
    labels = ds.storage.metadata.get("goal_labels")
    return OfflineDataset(ds.id, env_id, obs_space, act_space, episodes, fingerprint(episodes), prep, labels)


def check_dataset_id(dataset_id: str) -> str:
    """Return `dataset_id` if it has Minari's "namespace/name-vN" form, else raise ValueError saying so.

    Minari accepts an id without "-vN" until it writes, and then fails on the missing version.
    """
    if not re.fullmatch(r"([\w-]+/)*[\w-]+-v\d+", dataset_id):
        raise ValueError(f"dataset id must look like namespace/name-vN (Minari's format), got {dataset_id!r}")
    return dataset_id


def write_dataset(
    dataset_id: str,
    episodes: list[Episode],
    env_id: str,
    observation_space: gym.spaces.Space,
    action_space: gym.spaces.Space,
    data_dir: str | Path | None = None,
    *,
    episode_metadata: list[dict] | None = None,
    description: str | None = None,
    algorithm_name: str | None = None,
    overwrite: bool = False,
) -> Path:
    """Write episodes as a Minari dataset; `load_dataset` reads back identical arrays.

    Infos are stored Minari-style with T + 1 entries; the reset entry is NaN (MuJoCo v5 resets report no
    velocities).

    Args:
        dataset_id: Minari id, "namespace/name-vN".
        episodes: The trajectories; a missing final observation is written as a copy of the last one.
        env_id: Gymnasium id recorded as the dataset's environment ("unknown" for data of none).
        observation_space: Observation space recorded in the dataset.
        action_space: Action space recorded in the dataset.
        data_dir: Datasets root (default: $GMT_DATA_DIR, else data/minari).
        episode_metadata: Optional per-episode attributes, e.g. {"policy": "medium", "seed": 3}.
        description: Free text stored in the dataset metadata.
        algorithm_name: Name of the data-generating procedure.
        overwrite: Replace an existing dataset with the same id instead of failing.

    Returns:
        The dataset's data/ folder.
    """
    import minari
    from minari.data_collector import EpisodeBuffer

    check_dataset_id(dataset_id)
    root = data_root(data_dir)
    target = root / dataset_id
    if target.exists():
        if not overwrite:
            raise FileExistsError(f"{target} exists; replace it with --overwrite (overwrite=True in Python)")
        shutil.rmtree(target)
    buffers = []
    for i, ep in enumerate(episodes):
        final = ep.final_observation if ep.final_observation is not None else ep.observations[-1]
        n = len(ep)
        buffers.append(
            EpisodeBuffer(
                id=i,
                observations=np.concatenate([ep.observations, np.asarray(final)[None]]),
                actions=np.asarray(ep.actions),
                rewards=np.asarray(ep.rewards, dtype=np.float32),
                terminations=np.arange(n) == n - 1 if ep.terminated else np.zeros(n, dtype=bool),
                truncations=np.arange(n) == n - 1 if ep.truncated else np.zeros(n, dtype=bool),
                infos={
                    k: np.concatenate([[np.nan], np.asarray(v, dtype=np.float64)])
                    for k, v in ep.infos.items()
                },
            )
        )
    with minari_root(root), warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=UserWarning, module="minari")  # optional metadata nags
        ds = minari.create_dataset_from_buffers(
            dataset_id=dataset_id,
            buffer=buffers,
            env=None if env_id in (None, "unknown") else env_id,  # data of no Gymnasium environment
            eval_env=None if env_id in (None, "unknown") else env_id,
            author="gmt-service",
            observation_space=observation_space,
            action_space=action_space,
            algorithm_name=algorithm_name,
            description=description,
            data_format="hdf5",
        )
        if episode_metadata is not None:
            ds.storage.update_episode_metadata(episode_metadata, range(len(episodes)))
    return target / "data"
