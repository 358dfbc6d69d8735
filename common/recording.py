"""A served session's recording: the format on disk and over the wire, and how it splits into episodes.

NumPy only: the server writes it (`gmt.service.records`), `gmt data import-sessions` turns recordings into a
Minari dataset, `gmt replay` feeds them to another checkpoint.

Format `gmt-recording` v1, one row per step the session answered, in order:

`<name>.npz` (arrays; `np.load` reads it, no pickle), where `<name>` is the whole session id (`file_stem`: a
leading `.` and any character outside letters, digits and `._~-` percent-encoded) and, when a recording of a
re-created id is already there, `@2`, `@3`, ... after it (nothing overwrites an earlier session's recording):
    episode [N] int64: the session's episode (0, then +1 at each reset)
    t [N] int64: the step within its episode (0, 1, ...)
    time [N] float64: server clock (seconds since the epoch) when the step was answered
    observations [N, *obs_shape]: float32 (uint8 for images), as the model received them
    actions [N, A] float32 as answered ([N] int64 for discrete actions)
    goals [N] int64: the goal the session pursued at the step (the target of a running blend)
    goal_tokens [N] int64: the goal of the step's token (the faded-out goal while a blend runs)
    blend_w [N] float32: weight of `goals` in the token (0 outside a blend)
    reported [N] bool: the client reported the outcome of this step's action (with its next act)
    rewards [N] float64 (NaN where not reported); terminated [N] bool; truncated [N] bool
    info.<key> [N] float64 for every info key the client reported (NaN where not reported)
    meta [M] uint8: the metadata below as UTF-8 JSON, so that the .npz alone is complete
`<name>.json` (the same metadata, written after the .npz: its presence marks a complete recording):
    format, version, session_id, model, fingerprint (of the model's weights and gmt.json), env_id,
    observation_space, action_space, statistic, goals (the model's goal table), action_mode, seed,
    created_at, ended_at, ended_by (close, expiry or shutdown; null for a live session's snapshot), steps,
    max_steps, stopped (why the recording stopped before the session ended, or null), timeline: every goal the
    session had, [{step, episode, goal, given, blend_steps, by, at}] in order.

Episodes (`Recording.episodes`): the rows of one `episode` value. The client reports the outcome of action t
(reward, terminated, truncated, info) with the act of step t + 1, whose observation is the one the environment
returned. So an episode's transitions are its rows up to the first whose outcome says terminated or truncated,
and the observation of the next row is its final observation (the action answered for it belongs to no
transition); an episode without such a report ends with its last row's observation as the final one and counts
as truncated (the recording ended before the environment did).
"""

from __future__ import annotations

import io
import itertools
import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

FORMAT = "gmt-recording"
VERSION = 1
COLUMNS = (
    "episode",
    "t",
    "time",
    "observations",
    "actions",
    "goals",
    "goal_tokens",
    "blend_w",
    "reported",
    "rewards",
    "terminated",
    "truncated",
)
INFO_PREFIX = "info."


class RecordingError(ValueError):
    """A file or array set is not a readable recording."""


@dataclass
class RecordedEpisode:
    """One environment episode of a recording, aligned on actions (as `gmt.model.data.minari_io.Episode`).

    Attributes:
        episode: Its index in the session.
        observations: [T, *obs_shape] the observation each action was taken at.
        actions: [T, ...] the actions answered.
        goals: [T] the goal pursued at each step.
        rewards: [T] reported rewards (NaN where the client reported none).
        reported: [T] whether the outcome of each action was reported.
        infos: Per info key, [T] reported values (NaN where not reported).
        final_observation: The observation after the last action (None for an empty episode).
        terminated: The client reported a terminal state after the last action.
        truncated: The episode was cut (reported truncated, or the recording ended first).
        timeline: The timeline entries of this episode.
    """

    episode: int
    observations: np.ndarray
    actions: np.ndarray
    goals: np.ndarray
    rewards: np.ndarray
    reported: np.ndarray
    infos: dict[str, np.ndarray]
    final_observation: np.ndarray | None
    terminated: bool
    truncated: bool
    timeline: list[dict] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.actions)

    @property
    def switches(self) -> int:
        """How many times the goal label changes between consecutive steps."""
        return int(np.count_nonzero(np.diff(self.goals))) if len(self.goals) > 1 else 0


@dataclass
class Recording:
    """A recording's metadata and per-step arrays (see the module docstring)."""

    meta: dict
    arrays: dict[str, np.ndarray]

    @property
    def steps(self) -> int:
        """Rows (answered steps) recorded."""
        return len(self.arrays["t"])

    @property
    def info_keys(self) -> list[str]:
        """The info keys the client reported."""
        return sorted(k[len(INFO_PREFIX) :] for k in self.arrays if k.startswith(INFO_PREFIX))

    def rows_of(self, episode: int) -> np.ndarray:
        """Row indices of one episode, checked to be its steps 0, 1, ... exactly once.

        Raises:
            RecordingError: a step is missing or repeated.
        """
        rows = np.flatnonzero(self.arrays["episode"] == episode)
        t = self.arrays["t"][rows]
        if not np.array_equal(t, np.arange(len(rows))):
            raise RecordingError(
                f"recording {self.meta.get('session_id')!r}, episode {episode}: steps {t[:20].tolist()}... are "
                "not 0, 1, 2, ... exactly once"
            )
        return rows

    def episodes(self) -> list[RecordedEpisode]:
        """The environment episodes (see the module docstring for where each ends)."""
        a = self.arrays
        out = []
        for e in np.unique(a["episode"]):
            rows = self.rows_of(int(e))
            ends = np.flatnonzero(a["reported"][rows] & (a["terminated"][rows] | a["truncated"][rows]))
            if len(ends) and ends[0] + 1 < len(rows):
                n = int(ends[0]) + 1  # transitions 0..n-1; row n carries the final observation
                terminated, truncated = bool(a["terminated"][rows[n - 1]]), bool(a["truncated"][rows[n - 1]])
            else:
                n = max(len(rows) - 1, 0)
                terminated, truncated = False, True
            take = rows[:n]
            final = a["observations"][rows[n]] if len(rows) else None
            out.append(
                RecordedEpisode(
                    episode=int(e),
                    observations=a["observations"][take],
                    actions=a["actions"][take],
                    goals=a["goals"][take],
                    rewards=a["rewards"][take],
                    reported=a["reported"][take],
                    infos={k: a[INFO_PREFIX + k][take] for k in self.info_keys},
                    final_observation=final,
                    terminated=terminated,
                    truncated=truncated,
                    timeline=[x for x in self.meta.get("timeline", []) if x.get("episode", 0) == int(e)],
                )
            )
        return out

    # ----- files --------------------------------------------------------------------------------------------
    def npz_bytes(self) -> bytes:
        """The .npz of the recording (arrays plus the metadata as `meta`)."""
        buf = io.BytesIO()
        meta = np.frombuffer(json.dumps(self.meta, allow_nan=False).encode(), dtype=np.uint8)
        np.savez(buf, **self.arrays, meta=meta)
        return buf.getvalue()

    def write(self, directory: str | Path) -> Path:
        """Write `<name>.npz`, then `<name>.json` (see the module docstring), each a temporary file moved into
        place. A recording of the same session (same id and `created_at`: a retried close, a second replica's
        write) is replaced by this one, the same or longer; any other keeps its files, and this one takes the
        next free name (claimed by a hard link, which never replaces a file, so two writers never share one).

        Returns:
            The .json path (the recording is complete once it exists).
        """
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        stem = file_stem(str(self.meta["session_id"]))
        tmp = d / f".{stem}.{os.getpid()}.{id(self):x}.tmp"
        tmp.write_bytes(self.npz_bytes())
        try:
            for n in itertools.count(1):
                name = stem if n == 1 else f"{stem}@{n}"
                if (d / f"{name}.json").exists():
                    if not self._same_session(d / f"{name}.json"):
                        continue
                    tmp.replace(d / f"{name}.npz")
                    break
                try:
                    os.link(tmp, d / f"{name}.npz")
                    break
                except FileExistsError:  # another writer's, not complete yet
                    continue
        finally:
            tmp.unlink(missing_ok=True)
        text = json.dumps(self.meta, indent=1, allow_nan=False) + "\n"
        return _atomic_write(d / f"{name}.json", text.encode())

    def _same_session(self, path: Path) -> bool:
        """Whether the recording whose .json is `path` is of this recording's session (not an earlier one that
        had its id)."""
        try:
            other = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            return False
        key = ("session_id", "created_at")
        return isinstance(other, dict) and all(other.get(k) == self.meta.get(k) for k in key)

    @classmethod
    def from_npz(cls, data: bytes | str | Path) -> Recording:
        """A recording from an .npz (a file, or its bytes) that holds its `meta`.

        Raises:
            RecordingError: not a recording of this format.
        """
        where = "" if isinstance(data, bytes) else f" {data}"
        try:
            with np.load(io.BytesIO(data) if isinstance(data, bytes) else data, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile) as e:
            # np.load reads anything that is not an .npz archive as a pickle, which it refuses (allow_pickle=False)
            why = "not an .npz archive" if "pickle" in str(e) else str(e) or type(e).__name__
            raise RecordingError(f"not a recording .npz{where}: {why}") from None
        raw = arrays.pop("meta", None)
        if raw is None:
            raise RecordingError("the .npz holds no `meta`: not a gmt recording")
        return cls.of(json.loads(raw.tobytes().decode()), arrays)

    @classmethod
    def of(cls, meta: dict, arrays: dict[str, np.ndarray]) -> Recording:
        """A recording from its parts, checked.

        Raises:
            RecordingError: wrong format or version, a missing column, or columns of different lengths.
        """
        if meta.get("format") != FORMAT or meta.get("version") != VERSION:
            raise RecordingError(
                f"not a {FORMAT} v{VERSION} recording (format {meta.get('format')!r} v{meta.get('version')!r})"
            )
        missing = [c for c in COLUMNS if c not in arrays]
        if missing:
            raise RecordingError(f"recording {meta.get('session_id')!r} lacks the columns {missing}")
        n = {len(v) for v in arrays.values()}
        if len(n) != 1:
            raise RecordingError(f"recording {meta.get('session_id')!r} has columns of different lengths {n}")
        return cls(meta, arrays)


def file_stem(session_id: str) -> str:
    """The file name (without suffix) of a session's recording: the whole id, a leading `.` and any character
    outside letters, digits and `._~-` percent-encoded (so a name is never hidden, never a path, and two ids
    never share one)."""
    stem = "".join(c if c in _NAME_CHARS else "".join(f"%{b:02X}" for b in c.encode()) for c in session_id)
    return "%2E" + stem[1:] if stem.startswith(".") else stem


_NAME_CHARS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._~-")


def read_recording(path: str | Path) -> Recording:
    """A recording from its `.json` (the .npz beside it) or from an .npz alone.

    Raises:
        RecordingError: unreadable, or not a recording.
        FileNotFoundError: the file (or the .npz beside a .json) does not exist.
    """
    p = Path(path)
    if p.suffix == ".json":
        try:
            meta = json.loads(p.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise RecordingError(f"{p} is not a recording's JSON: {e}") from None
        rec = Recording.from_npz(p.with_suffix(".npz"))
        return Recording.of(meta, rec.arrays)
    return Recording.from_npz(p)


def find_recordings(paths: list[str | Path]) -> list[Path]:
    """Recording files among `paths`: each file itself, and in each directory its `*.json` recordings (sorted).

    Raises:
        FileNotFoundError: a path does not exist, or a directory holds no recording.
    """
    out: list[Path] = []
    for raw in paths:
        p = Path(raw)
        if p.is_dir():
            found = sorted(q for q in p.glob("*.json") if q.with_suffix(".npz").is_file())
            if not found:
                raise FileNotFoundError(f"{p} holds no recording (<session id>.json beside its .npz)")
            out += found
        elif p.is_file():
            out.append(p)
        else:
            raise FileNotFoundError(f"no such recording: {p}")
    return out


def _atomic_write(path: Path, data: bytes) -> Path:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)
    return path
