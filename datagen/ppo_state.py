"""A PPO learner's whole state in safetensors, so a long behaviour run can stop and go on later.

Speed-commanded Ant needs millions of PPO steps, more than one working session or one lent machine's time.
`gmt data commanded` therefore keeps, beside each measured snapshot, the learner itself
(`learner_<step>.safetensors` + `.json`): every policy weight (actor, critic, log-std), Adam's moments and the
`VecNormalize` running statistics of observations and returns. `--resume-from STEP` loads it and PPO goes on from
that step; what is not kept is the rollout in progress (the run starts fresh episodes) and the random streams
(a resumed run is reseeded from its seed and step, so it does not replay the first run's noise).

A run from before learner files existed kept actor-only snapshots (`step_<step>`). Resuming from one warm-starts:
its actor, log-std and observation statistics are loaded; the critic, Adam and the return statistics start afresh.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from gmt.datagen.ppo import copy_actor

FORMAT = 1


def learner_path(work_dir: Path, step: int) -> Path:
    """Where the learner state of training step `step` is kept (without suffix)."""
    return Path(work_dir) / f"learner_{step:08d}"


def save_learner(path: Path, model, venv) -> None:
    """Write an SB3 PPO learner and its `VecNormalize` statistics to `path`.safetensors / .json."""
    tensors = {f"policy.{k}": v.detach().cpu().contiguous() for k, v in model.policy.state_dict().items()}
    optim = model.policy.optimizer.state_dict()
    for index, state in optim["state"].items():
        for name, value in state.items():
            tensors[f"optimizer.{index}.{name}"] = (
                torch.as_tensor(value).detach().cpu().reshape(-1).contiguous()
            )
    for name in ("obs_rms", "ret_rms"):
        rms = getattr(venv, name)
        tensors[f"{name}.mean"] = torch.from_numpy(np.array(rms.mean, dtype=np.float64).reshape(-1))
        tensors[f"{name}.var"] = torch.from_numpy(np.array(rms.var, dtype=np.float64).reshape(-1))
        tensors[f"{name}.count"] = torch.tensor([float(rms.count)], dtype=torch.float64)
    path = Path(path)
    save_file(tensors, path.with_suffix(".safetensors"))
    meta = {
        "format": FORMAT,
        "num_timesteps": int(model.num_timesteps),
        "param_groups": optim["param_groups"],
    }
    path.with_suffix(".json").write_text(json.dumps(meta, indent=1))


def load_learner(path: Path, model, venv) -> int:
    """Load a learner written by `save_learner` into `model` and `venv` (built alike); its training step.

    Raises:
        ValueError: The file is of another format or does not fit the learner (other sizes or layers).
    """
    path = Path(path)
    meta = json.loads(path.with_suffix(".json").read_text())
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path}: learner format {meta.get('format')!r}, expected {FORMAT}")
    tensors = load_file(path.with_suffix(".safetensors"))
    policy = {k.removeprefix("policy."): v for k, v in tensors.items() if k.startswith("policy.")}
    try:
        model.policy.load_state_dict(policy)
    except RuntimeError as e:
        raise ValueError(f"{path}: does not fit this learner: {e}") from None
    params = [p for group in model.policy.optimizer.param_groups for p in group["params"]]
    state: dict[int, dict[str, torch.Tensor]] = {}
    for key, value in tensors.items():
        if key.startswith("optimizer."):
            _, index, name = key.split(".", 2)
            # back to the shapes the optimizer keeps: Adam's step is a scalar, its moments shaped like the weight
            shape = () if name == "step" else params[int(index)].shape
            state.setdefault(int(index), {})[name] = value.reshape(shape)
    model.policy.optimizer.load_state_dict({"state": state, "param_groups": meta["param_groups"]})
    for name in ("obs_rms", "ret_rms"):
        rms = getattr(venv, name)
        rms.mean = tensors[f"{name}.mean"].numpy().reshape(np.shape(rms.mean)).copy()
        rms.var = tensors[f"{name}.var"].numpy().reshape(np.shape(rms.var)).copy()
        rms.count = float(tensors[f"{name}.count"][0])
    model.num_timesteps = int(meta["num_timesteps"])
    return model.num_timesteps


def warm_start_actor(snapshot: Path, model, venv, step: int) -> int:
    """Load an actor-only snapshot (`save_behaviour` format) into a fresh learner; the critic stays fresh.

    Args:
        snapshot: The snapshot without suffix (`step_<step>`).
        model: The SB3 PPO learner, built with the snapshot's layer sizes.
        venv: Its `VecNormalize` env; the observation statistics are set as if seen `step` times.
        step: The snapshot's training step; the learner goes on from there.

    Returns:
        `step`.
    """
    snapshot = Path(snapshot)
    state = load_file(snapshot.with_suffix(".safetensors"))
    meta = json.loads(snapshot.with_suffix(".json").read_text())
    copy_actor(model.policy, state, str(snapshot))
    rms = venv.obs_rms
    rms.mean = np.asarray(meta["obs_mean"], dtype=np.float64).reshape(np.shape(rms.mean))
    rms.var = np.asarray(meta["obs_var"], dtype=np.float64).reshape(np.shape(rms.var))
    rms.count = float(step)
    model.num_timesteps = int(step)
    return model.num_timesteps
