"""Checkpoint directories: `model.safetensors` (weights) + `gmt.json` (everything else). Never pickle."""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_tensors
from safetensors.torch import save_file

from gmt.common.spec import ModelInfo
from gmt.model.config import GMTConfig
from gmt.model.gmt import GMT
from gmt.model.goals import Goal
from gmt.model.tokens import ActionCodec, ObsNormalizer

FORMAT = "gmt-checkpoint"
FORMAT_VERSION = 1
WEIGHTS = "model.safetensors"
META = "gmt.json"
PICKLE_SUFFIXES = {".pt", ".pth", ".pkl", ".pickle", ".ckpt", ".bin"}
VERSION_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")  # a served version: one URL path segment


class CheckpointError(Exception):
    """A checkpoint is missing, malformed, or in a refused format."""


@dataclass
class Checkpoint:
    """A loaded checkpoint: the network plus everything needed to serve it.

    Attributes:
        name: Model name (the directory name by default).
        model: The network, in eval mode.
        env_id: Gymnasium environment id.
        observation_space: `gmt.common.spaces.space_to_dict` of the observation space.
        action_space: Same for the action space.
        obs_norm: State normalisation from the training dataset.
        action_codec: Action scaling to and from [-1, 1].
        statistic: Name of the per-trajectory statistic the goals cluster.
        goals: Goal table, goal 0 = lowest statistic.
        meta: The whole gmt.json (training config, dataset fingerprint, code revision, ...).
        action_noise: [n_goals, A] per-goal action std in model space for sampled continuous actions
            (`gmt.model.calibrate`), or None when not calibrated.
        preprocessing: The observation pipeline of the training data (Atari frames: wrappers and their
            arguments, from the dataset's metadata), or None for raw environment observations. Clients build
            their environment from it.
        default_action_mode: Action mode of sessions that name none (None: the engine's default), e.g.
            `sample` for a model whose goals differ in how often the data's agents acted at random.
        switch_relabel_steps: On a goal change (without a blend), the last this-many steps of a session's context take
            the new goal token, as if it had been pursued all along (0: the context keeps the goals it was
            given; `gmt.model.engine.PolicyEngine.set_goal`).
        fingerprint: sha256 hex of the weights and the metadata as loaded (`fingerprint`); empty for a
            checkpoint built in memory.
        version: The served version: gmt.json's `version`, else the fingerprint's first 12 hex digits.
    """

    name: str
    model: GMT
    env_id: str
    observation_space: dict
    action_space: dict
    obs_norm: ObsNormalizer
    action_codec: ActionCodec
    statistic: str
    goals: list[Goal]
    meta: dict = field(default_factory=dict)
    action_noise: np.ndarray | None = None
    preprocessing: dict | None = None
    default_action_mode: str | None = None
    switch_relabel_steps: int = 0
    fingerprint: str = ""
    version: str = ""

    @property
    def config(self) -> GMTConfig:
        """The network's config."""
        return self.model.cfg


def code_revision() -> str:
    """The git commit of this code (with '+dirty' for uncommitted changes), or 'unknown'.

    $GMT_CODE_REVISION, when set, is taken as it is: an install without the repository (a wheel built from a
    clean commit and carried to another machine) has no git to ask.
    """
    if os.environ.get("GMT_CODE_REVISION"):
        return os.environ["GMT_CODE_REVISION"]
    root = Path(__file__).resolve().parents[1]
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        return rev + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def save_checkpoint(ckpt: Checkpoint, directory: str | Path, extra_meta: dict | None = None) -> Path:
    """Write `model.safetensors` and `gmt.json` into `directory` (created if needed)."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().contiguous() for k, v in ckpt.model.state_dict().items()}
    save_file(tensors, str(d / WEIGHTS))
    meta = {
        **ckpt.meta,
        **(extra_meta or {}),
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "name": ckpt.name,
        "model": ckpt.config.to_dict(),
        "env": {
            "env_id": ckpt.env_id,
            "observation_space": ckpt.observation_space,
            "action_space": ckpt.action_space,
            **({"preprocessing": ckpt.preprocessing} if ckpt.preprocessing else {}),
        },
        "normalization": {"observation": ckpt.obs_norm.to_dict(), "action": ckpt.action_codec.to_dict()},
        "statistic": ckpt.statistic,
        "goals": [asdict(g) for g in ckpt.goals],
    }
    meta.pop("action_noise", None)
    meta.pop("default_action_mode", None)
    if ckpt.default_action_mode:
        meta["default_action_mode"] = ckpt.default_action_mode
    meta.pop("switch_relabel_steps", None)
    if ckpt.switch_relabel_steps:
        meta["switch_relabel_steps"] = ckpt.switch_relabel_steps
    if ckpt.action_noise is not None:
        meta["action_noise"] = {
            "std": np.asarray(ckpt.action_noise, dtype=np.float32).astype(np.float64).tolist(),
            "description": "[goal][action dim] RMS residual of the dataset actions around the prediction "
            "(model space); continuous `sample` mode adds std * N(0, 1)",
        }
    (d / META).write_text(json.dumps(meta, indent=2, allow_nan=False) + "\n")
    return d


def _refuse_pickle(path: Path) -> None:
    if path.suffix in PICKLE_SUFFIXES:
        raise CheckpointError(
            f"refusing to load {path}: pickle-based formats are not accepted; "
            f"a checkpoint is a directory with {WEIGHTS} and {META}"
        )
    with path.open("rb") as f:
        head = f.read(2)
    if len(head) == 2 and head[0] == 0x80 and head[1] <= 5:
        raise CheckpointError(f"refusing to load {path}: it is a pickle stream, not safetensors")


def fingerprint(weights: bytes, meta: dict) -> str:
    """A checkpoint's identity: sha256 hex over its weights' bytes and its metadata (canonical JSON, so that
    formatting does not count)."""
    h = hashlib.sha256(b"gmt-checkpoint-fingerprint-v1\0")
    h.update(hashlib.sha256(weights).digest())
    h.update(hashlib.sha256(json.dumps(meta, sort_keys=True, separators=(",", ":")).encode()).digest())
    return h.hexdigest()


def version_of(meta: dict, fp: str) -> str:
    """The served version: gmt.json's `version` when it names one, else the fingerprint's first 12 hex digits.

    Raises:
        CheckpointError: the named version is not 1 to 64 letters, digits, '.', '_' or '-'.
    """
    v = meta.get("version")
    if v is None:
        return fp[:12]
    if not isinstance(v, str) or not VERSION_PATTERN.fullmatch(v):
        raise CheckpointError(
            f"gmt.json names version {v!r}: a version is 1 to 64 letters, digits, '.', '_' or '-' "
            "(starting with a letter or digit)"
        )
    return v


def read_meta(directory: str | Path) -> dict:
    """A checkpoint directory's gmt.json.

    Raises:
        CheckpointError: it is missing, not JSON, or not a gmt checkpoint of this format.
    """
    meta_path = Path(directory) / META
    try:
        meta = json.loads(meta_path.read_text())
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {Path(directory)} has no {META}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{meta_path} is not valid JSON: {e}") from e
    except OSError as e:
        raise CheckpointError(f"{meta_path} cannot be read: {e.strerror}") from e
    if (
        not isinstance(meta, dict)
        or meta.get("format") != FORMAT
        or meta.get("format_version") != FORMAT_VERSION
    ):
        got = (meta.get("format"), meta.get("format_version")) if isinstance(meta, dict) else (None, None)
        raise CheckpointError(
            f"{meta_path}: expected format {FORMAT} v{FORMAT_VERSION}, got {got[0]} v{got[1]}"
        )
    return meta


def load_checkpoint(
    directory: str | Path, name: str | None = None, expect_fingerprint: str | None = None
) -> Checkpoint:
    """Load a checkpoint directory; only safetensors and JSON are ever read.

    The weights are read once: the fingerprint is of the very bytes loaded.

    Args:
        expect_fingerprint: Refuse the checkpoint unless its fingerprint starts with this (12 to 64 hex digits).

    Raises:
        CheckpointError: the directory, weights or metadata are missing or malformed, the weights do not fit the
            config, a pickle is given, or the fingerprint is not the expected one.
    """
    d = Path(directory)
    if d.is_file():
        _refuse_pickle(d)
        raise CheckpointError(f"{d} is a file; a checkpoint is a directory with {WEIGHTS} and {META}")
    if not d.exists():
        raise CheckpointError(f"checkpoint {d} does not exist")
    weights, meta_path = d / WEIGHTS, d / META
    for p in (weights, meta_path):
        if not p.is_file():
            raise CheckpointError(f"checkpoint {d} has no {p.name}")
    _refuse_pickle(weights)
    meta = read_meta(d)
    try:
        data = weights.read_bytes()
    except OSError as e:
        raise CheckpointError(f"{weights} cannot be read: {e.strerror}") from e
    fp = fingerprint(data, meta)
    if expect_fingerprint is not None and not fp.startswith(expect_fingerprint.lower()):
        raise CheckpointError(
            f"checkpoint {d} has fingerprint {fp}, not the expected {expect_fingerprint} (a different or changed "
            "checkpoint)"
        )
    try:
        cfg = GMTConfig.from_dict(meta["model"])
        env = meta["env"]
        obs_norm = ObsNormalizer.from_dict(meta["normalization"]["observation"])
        action_codec = ActionCodec.from_dict(meta["normalization"]["action"])
        goals = [Goal(**g) for g in meta["goals"]]
        env_id, observation_space, action_space = env["env_id"], env["observation_space"], env["action_space"]
        statistic = meta["statistic"]
    except KeyError as e:
        raise CheckpointError(f"{meta_path}: unreadable metadata: missing field {e}") from None
    except (TypeError, ValueError, AttributeError) as e:
        raise CheckpointError(f"{meta_path}: unreadable metadata: {e}") from None
    if len(goals) != cfg.n_goals:
        raise CheckpointError(f"{meta_path}: {len(goals)} goals listed for a model of {cfg.n_goals}")
    try:
        state = load_tensors(data)  # as large as the file, which is read already
    except (SafetensorError, ValueError, OSError) as e:  # safetensors raises its own error types
        raise CheckpointError(f"{weights} is not a readable safetensors file: {e}") from e
    _check_shapes(state, cfg, weights)
    model = GMT(cfg)  # only now: a config the tensors do not fill allocates nothing
    model.load_state_dict(state, strict=True)
    model.eval()
    return Checkpoint(
        name=name or meta.get("name") or d.name,
        model=model,
        env_id=env_id,
        observation_space=observation_space,
        action_space=action_space,
        obs_norm=obs_norm,
        action_codec=action_codec,
        statistic=statistic,
        goals=goals,
        meta=meta,
        action_noise=_action_noise(meta, cfg, meta_path),
        preprocessing=env.get("preprocessing"),
        default_action_mode=meta.get("default_action_mode"),
        switch_relabel_steps=_switch_relabel_steps(meta, cfg, meta_path),
        fingerprint=fp,
        version=version_of(meta, fp),
    )


def _check_shapes(state: dict[str, torch.Tensor], cfg: GMTConfig, weights: Path) -> None:
    """Compare the tensors with the ones `cfg` makes, built on the meta device (shapes only, no memory).

    Raises:
        CheckpointError: a tensor of another shape, a missing one or an unexpected one (five named at most).
    """
    with torch.device("meta"):
        expected = {k: tuple(v.shape) for k, v in GMT(cfg).state_dict().items()}
    wrong = [
        f"{k} {list(v.shape)} (config: {list(expected[k])})"
        for k, v in state.items()
        if k in expected and tuple(v.shape) != expected[k]
    ]
    if wrong:
        raise CheckpointError(
            f"{weights} does not match the config: wrong tensor shapes: {', '.join(wrong[:5])}"
        )
    missing, unexpected = sorted(expected.keys() - state.keys()), sorted(state.keys() - expected.keys())
    if missing or unexpected:
        raise CheckpointError(
            f"{weights} does not match the config: {len(missing)} tensors missing {missing[:5]}, "
            f"{len(unexpected)} unexpected {unexpected[:5]}"
        )


def _switch_relabel_steps(meta: dict, cfg: GMTConfig, meta_path: Path) -> int:
    n = meta.get("switch_relabel_steps", 0)
    if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= cfg.history_steps:
        raise CheckpointError(
            f"{meta_path}: switch_relabel_steps must be a whole number of steps from 0 to the model's history "
            f"({cfg.history_steps}), got {n!r}"
        )
    return n


def _action_noise(meta: dict, cfg: GMTConfig, meta_path: Path) -> np.ndarray | None:
    if "action_noise" not in meta:
        return None
    std = np.asarray(meta["action_noise"].get("std"), dtype=np.float32)
    if (
        cfg.discrete_actions
        or std.shape != (cfg.n_goals, cfg.act_dim)
        or not (np.isfinite(std) & (std >= 0)).all()
    ):
        raise CheckpointError(
            f"{meta_path}: action_noise.std must be [{cfg.n_goals}, {cfg.act_dim}] finite values >= 0 "
            f"for a continuous-action model, got shape {list(std.shape)}"
        )
    return std


def state_dicts_equal(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    """Whether two modules hold bit-identical parameters and buffers."""
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def model_info(ckpt: Checkpoint, **served) -> ModelInfo:
    """The checkpoint as a client sees it (`GET /models/{name}`): enough to build its environment.

    Args:
        served: Fields a server sets from its engine (`action_modes`, `switch_relabel_steps`, `name`).
    """
    return ModelInfo(
        **{
            "name": ckpt.name,
            "env_id": ckpt.env_id,
            "observation_space": ckpt.observation_space,
            "action_space": ckpt.action_space,
            "context_length": ckpt.config.context_length,
            "statistic": ckpt.statistic,
            "goals": list(ckpt.goals),  # a checkpoint's goals are the goal record (gmt.common.spec.GoalInfo)
            "preprocessing": ckpt.preprocessing,
            **served,
        }
    )
