"""Training loop: seeded, resumable, CPU-efficient; writes a checkpoint directory (docs/architecture.md, "Checkpoints")."""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from gmt.common.spaces import space_to_dict
from gmt.common.statistics import default_statistic
from gmt.model.augment import augment_frames
from gmt.model.calibrate import action_noise, goal_spread, mode_for_goals
from gmt.model.checkpoint import Checkpoint, Goal, code_revision, save_checkpoint
from gmt.model.config import GMTConfig, TrainConfig
from gmt.model.distributed import Parallel
from gmt.model.gmt import GMT
from gmt.model.losses import gmt_loss, loss_counts
from gmt.model.masking import mask_goals
from gmt.model.sampling import ACTION_MODES, CONTINUOUS_MODES
from gmt.model.tokens import ActionCodec, ObsNormalizer, WindowSampler

RESUME_DIR = "_resume"


def model_config_for(dataset, n_goals: int, **overrides) -> GMTConfig:
    """A GMTConfig matching a dataset's spaces; `overrides` set context_length, n_layer, ... ."""
    import gymnasium as gym

    obs_shape = dataset.observation_space.shape
    if len(obs_shape) == 2:  # grayscale frames [H, W] -> one channel
        obs_shape = (1, *obs_shape)
    act = dataset.action_space
    discrete = isinstance(act, gym.spaces.Discrete)
    return GMTConfig(
        obs_shape=obs_shape,
        act_dim=int(act.n) if discrete else int(np.prod(act.shape)),
        discrete_actions=discrete,
        n_goals=n_goals,
        **overrides,
    )


def build_sampler(
    dataset, labels: list[int | np.ndarray], cfg: GMTConfig, sequence_steps: int | None = None
) -> tuple[WindowSampler, ObsNormalizer, ActionCodec]:
    """Normalise a dataset's episodes and wrap them in a sampler of `sequence_steps`-step sequences (default K).

    Images are not normalised, so the sampler's one array of frames is also the dataset's: each episode's
    observations become a view into it as it is filled, and the frames are held once, not twice.
    """
    import gymnasium as gym

    obs = [ep.observations.reshape(len(ep.observations), *cfg.obs_shape) for ep in dataset.episodes]
    images = bool(obs) and ObsNormalizer.is_image(obs[0])
    norm = ObsNormalizer() if images else ObsNormalizer.fit(np.concatenate(obs))
    act = dataset.action_space
    codec = (
        ActionCodec()
        if isinstance(act, gym.spaces.Discrete)
        else ActionCodec(act.low.astype(np.float32), act.high.astype(np.float32))
    )
    if images:
        del obs  # views of the loaded arrays: none may outlive the copy into the sampler's array
        states = _frames_held_once(dataset.episodes, cfg.obs_shape)
    else:
        states = [norm(o) for o in obs]
    actions = [codec.encode(ep.actions) for ep in dataset.episodes]
    rewards = [ep.rewards for ep in dataset.episodes] if cfg.conditioning == "return" else None
    sampler = WindowSampler(states, actions, labels, sequence_steps or cfg.context_length, rewards)
    return sampler, norm, codec


def _frames_held_once(episodes, obs_shape: tuple[int, ...]) -> np.ndarray:
    """All episodes' uint8 frames in one [N, *obs_shape] array; each episode's observations (and its final
    observation, copied out of the array it was read with) then point into it, so the arrays they were read
    into are freed one episode at a time."""
    frames = np.empty((sum(len(ep.observations) for ep in episodes), *obs_shape), dtype=np.uint8)
    i = 0
    for ep in episodes:
        n = len(ep.observations)
        frames[i : i + n] = ep.observations.reshape(n, *obs_shape)
        shape = ep.observations.shape
        if getattr(ep, "final_observation", None) is not None:
            ep.final_observation = np.array(ep.final_observation)  # its own copy: no view keeps the old array
        ep.observations = frames[i : i + n].reshape(shape)
        i += n
    return frames


def goal_returns(dataset, labels: list[int], n_goals: int) -> list[float]:
    """Per goal, the mean episode return of its trajectories: a Decision Transformer's target for that goal."""
    returns = np.array([float(np.sum(ep.rewards)) for ep in dataset.episodes])
    lab = np.asarray(labels)
    return [float(returns[lab == g].mean()) if (lab == g).any() else float("nan") for g in range(n_goals)]


def lr_at(step: int, tc: TrainConfig, time_share: float = 0.0) -> float:
    """Linear warmup then cosine decay to `min_lr_ratio * lr`.

    Args:
        step: Optimiser step.
        tc: The run's configuration.
        time_share: Elapsed share of `tc.time_limit_s` (0 without a limit); the decay follows it when it is
            ahead of the step share.
    """
    if step < tc.warmup_steps:
        return tc.lr * (step + 1) / tc.warmup_steps
    progress = min(max((step - tc.warmup_steps) / max(tc.steps - tc.warmup_steps, 1), time_share), 1.0)
    return tc.lr * (tc.min_lr_ratio + (1 - tc.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress)))


def make_optimizer(model: GMT, tc: TrainConfig) -> torch.optim.AdamW:
    """AdamW with weight decay on matrices only."""
    decay = [p for n, p in model.named_parameters() if p.dim() >= 2 and "emb" not in n]
    no_decay = [p for n, p in model.named_parameters() if not (p.dim() >= 2 and "emb" not in n)]
    groups = [{"params": decay, "weight_decay": tc.weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    return torch.optim.AdamW(groups, lr=tc.lr, betas=(0.9, 0.95), fused=True)


def _save_resume(d: Path, step: int, model: GMT, opt: torch.optim.Optimizer, gen: torch.Generator) -> None:
    d.mkdir(parents=True, exist_ok=True)
    tensors = {f"model.{k}": v.detach().clone().contiguous() for k, v in model.state_dict().items()}
    opt_state = opt.state_dict()
    for pid, st in opt_state["state"].items():
        for k, v in st.items():
            tensors[f"opt.{pid}.{k}"] = v.detach().clone().contiguous().reshape(v.shape)
    tensors["rng"] = gen.get_state()
    save_file(tensors, str(d / "state.safetensors"))
    (d / "state.json").write_text(json.dumps({"step": step, "param_groups": opt_state["param_groups"]}))


def _load_resume(d: Path, model: GMT, opt: torch.optim.Optimizer, gen: torch.Generator) -> int:
    tensors = load_file(str(d / "state.safetensors"))
    meta = json.loads((d / "state.json").read_text())
    model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
    state: dict[int, dict] = {}
    for k, v in tensors.items():
        if k.startswith("opt."):
            _, pid, name = k.split(".", 2)
            state.setdefault(int(pid), {})[name] = v
    opt.load_state_dict({"state": state, "param_groups": meta["param_groups"]})
    gen.set_state(tensors["rng"])
    return int(meta["step"])


def _init_from(model: GMT, path: str) -> dict:
    """Copy a checkpoint's weights into `model`; its configuration must be the same (CheckpointError names the
    fields that differ). Returns the checkpoint's path and fingerprint, for gmt.json."""
    from gmt.model.checkpoint import CheckpointError, load_checkpoint

    src = load_checkpoint(path)
    mine, theirs = model.cfg.to_dict(), src.model.cfg.to_dict()
    diff = {k: (theirs.get(k), v) for k, v in mine.items() if theirs.get(k) != v}
    if diff:
        raise CheckpointError(
            f"init_from {path}: its model differs from this run's in "
            + ", ".join(f"{k} ({a!r} there, {b!r} here)" for k, (a, b) in diff.items())
        )
    model.load_state_dict(src.model.state_dict())
    return {"path": str(path), "fingerprint": src.fingerprint}


def train(
    dataset,
    labels: list[int | np.ndarray],
    goals: list[Goal],
    out_dir: str | Path,
    tc: TrainConfig,
    model_overrides: dict | None = None,
    name: str | None = None,
    extra_meta: dict | None = None,
    resume: bool = True,
    progress: bool = True,
) -> Checkpoint | None:
    """Train a GMT on a relabelled dataset and write its checkpoint directory.

    Args:
        dataset: An `OfflineDataset` (`gmt.model.data.minari_io`).
        labels: Goal label per episode, or per step ([T] per episode: served sessions that switched goals).
        goals: Goal table.
        out_dir: Checkpoint directory (created); `_resume/` inside holds the resumable state.
        tc: Training configuration.
        model_overrides: GMTConfig fields to override (context_length, n_layer, ...).
        name: Model name (defaults to the directory name).
        extra_meta: More fields for gmt.json (relabelling details, commands).
        resume: Continue from `out_dir/_resume` when it exists.
        progress: Show a progress bar.

    Continuous-action checkpoints are calibrated at the end (`gmt.model.calibrate.action_noise`). A model with
    `return` conditioning is a Decision Transformer: returns-to-go replace the goal tokens, there is no masking
    and no next-goal loss, and gmt.json records each goal's mean episode return (its evaluation targets).

    Under `torchrun` every process calls this; each trains on its share of every batch (`gmt.model.distributed`)
    and only rank 0 writes the checkpoint, which the other processes get as None.
    """
    out = Path(out_dir)
    if tc.threads:
        torch.set_num_threads(tc.threads)
    par = Parallel.from_env(tc.device)
    if tc.time_limit_s and par.world > 1:  # each process would stop at its own step: DDP would wait forever
        raise ValueError("time_limit_s needs a single training process (not torchrun)")
    torch.manual_seed(tc.seed)
    cfg = model_config_for(dataset, len(goals), **(model_overrides or {}))
    augment = bool(tc.augment_shift or tc.augment_degrees)
    if augment and not cfg.is_image:
        raise ValueError("augment_shift / augment_degrees apply to image observations only")
    modes = ACTION_MODES if cfg.discrete_actions else CONTINUOUS_MODES
    if tc.default_action_mode is not None and tc.default_action_mode not in modes:
        raise ValueError(
            f"default_action_mode {tc.default_action_mode!r} is not one of {modes} for this model"
        )
    if tc.switch_relabel_steps > cfg.history_steps:
        raise ValueError(
            f"switch_relabel_steps {tc.switch_relabel_steps} exceeds the model's history of {cfg.history_steps} steps"
        )
    if cfg.conditioning == "return" and any(np.ndim(x) for x in labels):
        raise ValueError(
            "a Decision Transformer is conditioned on returns: it takes one goal label per episode"
        )
    sampler, norm, codec = build_sampler(dataset, labels, cfg, tc.sequence_steps(cfg))
    if par.device.type != "cpu":
        # fp32 matrix products on tensor cores (TF32), and cuDNN's fastest convolution for the fixed shapes
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
        torch.backends.cudnn.benchmark = True
        if not augment:  # the whole dataset on the accelerator: batches are gathered there, not copied over
            sampler.to(par.device)
    model = GMT(cfg)
    if tc.init_from:
        extra_meta = {**(extra_meta or {}), "init_from": _init_from(model, tc.init_from)}
    model = model.to(par.device)
    dt = cfg.conditioning == "return"
    rows = par.rows(tc.batch_size)
    net = par.wrap(model)
    opt = make_optimizer(model, tc)
    gen = torch.Generator().manual_seed(tc.seed)
    start = 0
    resume_dir = out / RESUME_DIR
    if resume and (resume_dir / "state.json").exists():
        start = _load_resume(resume_dir, model, opt, gen)
    writer = _summary_writer(out / "tb") if par.is_main else None
    model.train()
    t0, last, curve = time.time(), {}, []
    bar = tqdm(
        range(start, tc.steps),
        initial=start,
        total=tc.steps,
        disable=not (progress and par.is_main),
        desc="train",
    )
    done = start
    for step in bar:
        share = (time.time() - t0) / tc.time_limit_s if tc.time_limit_s else 0.0
        if share >= 1.0:
            break
        lr = lr_at(step, tc, share)
        for g in opt.param_groups:
            g["lr"] = lr
        # Every process draws the same global batch (same generator) and trains on its rows of it.
        w = sampler.sample(tc.batch_size, gen)
        if dt:  # Decision Transformer: returns-to-go in the goal slot, no masking
            goals_in = w.rtg
        else:  # masks drawn on the CPU from the run's generator, wherever the batch is: the same on any device
            goals_in = mask_goals(w.goals.cpu(), w.valid.cpu(), tc.masking, tc.mask_prob, cfg.mask_token, gen)
        if augment:  # before taking this process's rows: every process augments the same global batch
            w = replace(w, states=augment_frames(w.states, tc.augment_shift, tc.augment_degrees, gen))
        counts = loss_counts(w.actions, w.valid, cfg.discrete_actions) if par.world > 1 else None
        w, goals_in = w.select(rows).to(par.device), goals_in[rows].to(par.device)
        with torch.autocast(par.device.type, dtype=torch.bfloat16, enabled=tc.bf16):
            pred, goal_logits = net(goals_in, w.states, w.actions, w.timesteps, w.valid)
        parts = gmt_loss(
            pred,
            goal_logits,
            w.actions,
            w.goals,
            w.valid,
            cfg.discrete_actions,
            0.0 if dt else tc.alpha,
            counts,
        )
        opt.zero_grad(set_to_none=True)
        (parts.total * par.world).backward()  # DDP averages gradients over processes: this undoes it
        gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip)
        opt.step()
        done = step + 1
        if step % tc.log_every == 0 or step == tc.steps - 1:
            loss, a_loss, g_loss = par.sum([parts.total.item(), parts.action, parts.goal])
            last = {
                "loss": loss,
                "action_loss": a_loss,
                "goal_loss": g_loss,
                "goal_accuracy": parts.goal_accuracy,
                "grad_norm": float(gnorm),
                "lr": lr,
            }
            curve.append([step, round(loss, 6)])
            bar.set_postfix(loss=f"{loss:.4f}", act=f"{a_loss:.4f}", goal=f"{g_loss:.3f}")
            if writer is not None:
                for k, v in last.items():
                    writer.add_scalar(f"train/{k}", v, step)
        if (step + 1) % tc.save_every == 0 and step + 1 < tc.steps and par.is_main:
            _save_resume(resume_dir, step + 1, model, opt, gen)
    if writer is not None:
        writer.close()
    model.eval()
    elapsed = time.time() - t0
    if not par.is_main:
        par.close()
        return None
    model.cpu()
    sampler.to(torch.device("cpu"))  # calibration runs the CPU model over the sampler's windows
    noise = (
        None
        if cfg.discrete_actions or dt  # a Decision Transformer acts with its mean action
        else action_noise(model, sampler, len(goals), batches=tc.calibration_batches, seed=tc.seed)
    )
    default_mode, spread = tc.default_action_mode, None
    if cfg.discrete_actions and not dt:  # do the goals change the actions of the mode sessions get?
        spread = goal_spread(model, sampler, len(goals), seed=tc.seed)
        default_mode, note = mode_for_goals(spread, tc.default_action_mode)
        spread = {"total_variation": spread, "default_action_mode": default_mode, "note": note}
    meta = {
        **(extra_meta or {}),
        **(
            {"decision_transformer": {"goal_returns": goal_returns(dataset, labels, len(goals))}}
            if dt
            else {}
        ),
        **({"goal_spread": spread} if spread is not None else {}),
        "training": {
            **asdict(replace(tc)),
            "final": last,
            "wall_time_s": round(elapsed, 1),
            "steps_done": done,
            "steps_per_s": round((done - start) / max(elapsed, 1e-9), 2),
            "loss_curve": curve,
            "processes": par.world,
            "device": str(par.device.type),
        },
        "dataset": {
            "id": dataset.dataset_id,
            "fingerprint": dataset.fingerprint,
            "episodes": len(dataset.episodes),
            "transitions": int(sampler.n),
        },
        "code_revision": code_revision(),
    }
    ckpt = Checkpoint(
        name=name or out.name,
        model=model,
        env_id=dataset.env_id,
        observation_space=space_to_dict(dataset.observation_space),
        action_space=space_to_dict(dataset.action_space),
        obs_norm=norm,
        action_codec=codec,
        statistic=tc.statistic or default_statistic(set(getattr(dataset, "info_keys", ())))[0],
        goals=goals,
        meta=meta,
        action_noise=noise,
        preprocessing=dataset.preprocessing,
        default_action_mode=default_mode,
        switch_relabel_steps=tc.switch_relabel_steps,
    )
    save_checkpoint(ckpt, out)
    shutil.rmtree(resume_dir, ignore_errors=True)  # the run is complete: nothing is left to resume
    par.close()
    return ckpt


def _summary_writer(path: Path):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:  # tensorboard is in the optional `train` extra
        return None
    return SummaryWriter(str(path))
