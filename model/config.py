"""Typed configuration of the GMT network and of its training run."""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field
from typing import Literal

MaskingMode = Literal["token", "trajectory", "none"]
AttentionSpan = Literal["full", "window"]
Conditioning = Literal["goal", "return"]
ImageEncoderKind = Literal["nature", "fine"]
Device = Literal["auto", "cpu", "cuda"]


# Bounds of a model's sizes, far above any model here (the largest: n_embd 128, K 20, max_timestep 1024): a config
# past them is refused before anything is allocated (a checkpoint's gmt.json is read before its weights).
SIZE_BOUNDS = {
    "act_dim": 65_536,
    "n_goals": 4096,
    "context_length": 4096,
    "n_layer": 128,
    "n_head": 128,
    "n_embd": 16_384,
    "max_timestep": 10_000_000,
}
MAX_OBS_ELEMENTS = 1 << 24  # elements of one observation


@dataclass(frozen=True)
class GMTConfig:
    """Shape of one Goal-Masked Transformer; everything the network needs and nothing else.

    Attributes:
        obs_shape: Shape of one observation: (D,) for vectors, (C, H, W) for images (uint8 frames).
        act_dim: Action dimension for continuous actions, number of actions for discrete ones.
        discrete_actions: True for a Discrete action space (cross-entropy), False for Box (MSE, tanh head).
        n_goals: Number of goal labels; the embedding table has one more row, the learned [mask] token.
        context_length: K, the number of (goal, state, action) timesteps the model sees.
        n_layer: Number of transformer blocks.
        n_head: Attention heads per block.
        n_embd: Width of every token embedding.
        max_timestep: Size of the timestep embedding table; later timesteps are clamped to the last row (1: the
            model is blind to the episode's clock, as a locomotion policy may be).
        dropout: Dropout probability (0 by default: it costs a third of a CPU step for little gain here).
        attention: `full`: every token sees its whole K-step window (the paper's setting; serving recomputes
            the window every step). `window`: banded causal attention, each token sees the tokens of its own
            last K timesteps, so a per-layer key/value cache reproduces the reference forward exactly.
        conditioning: `goal`: the first token of each step is a goal id (GMT). `return`: it is the return-to-go,
            embedded linearly (Decision Transformer, the paper's baseline); such a model is evaluated by
            `gmt.model.evaluate_dt` and not served.
        return_scale: Returns-to-go are divided by this before their embedding (`return` conditioning only).
        image_encoder: Image models: `nature`, the Nature-DQN CNN (first layer 8 x 8 at stride 4); `fine`, two
            coordinate planes added to the frames (CoordConv) and four layers that start at stride 2, for a
            policy that depends on where a small object is to a pixel (about 3x the nature CNN's work).
    """

    obs_shape: tuple[int, ...]
    act_dim: int
    discrete_actions: bool
    n_goals: int
    context_length: int = 20
    n_layer: int = 3
    n_head: int = 1
    n_embd: int = 128
    max_timestep: int = 1024
    dropout: float = 0.0
    attention: AttentionSpan = "full"
    conditioning: Conditioning = "goal"
    return_scale: float = 1000.0
    image_encoder: ImageEncoderKind = "nature"

    def __post_init__(self) -> None:
        object.__setattr__(self, "obs_shape", tuple(int(s) for s in self.obs_shape))
        if len(self.obs_shape) not in (1, 3):
            raise ValueError(f"obs_shape must be (D,) or (C, H, W), got {self.obs_shape}")
        if self.act_dim < 1 or self.n_goals < 1 or self.context_length < 1 or self.max_timestep < 1:
            raise ValueError("act_dim, n_goals, context_length and max_timestep must be positive")
        if min(self.obs_shape) < 1 or math.prod(self.obs_shape) > MAX_OBS_ELEMENTS:
            raise ValueError(f"obs_shape must have 1 to {MAX_OBS_ELEMENTS} elements, got {self.obs_shape}")
        for name, most in SIZE_BOUNDS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not 1 <= value <= most:
                raise ValueError(f"{name} must be a whole number from 1 to {most}, got {value!r}")
        if self.n_embd % self.n_head != 0:
            raise ValueError(f"n_embd={self.n_embd} is not divisible by n_head={self.n_head}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        if self.attention not in ("full", "window"):
            raise ValueError(f"attention must be full or window, got {self.attention!r}")
        if self.conditioning not in ("goal", "return"):
            raise ValueError(f"conditioning must be goal or return, got {self.conditioning!r}")
        if not self.return_scale > 0:
            raise ValueError(f"return_scale must be positive, got {self.return_scale}")
        if self.image_encoder not in ("nature", "fine"):
            raise ValueError(f"image_encoder must be nature or fine, got {self.image_encoder!r}")

    @property
    def history_steps(self) -> int:
        """Steps of history that determine the action at a step (the reference forward's input).

        K for `full` attention; the receptive field n_layer * (K - 1) + 1 for `window` attention.
        """
        if self.attention == "full":
            return self.context_length
        return self.n_layer * (self.context_length - 1) + 1

    @property
    def is_image(self) -> bool:
        """Whether observations are images embedded by the CNN."""
        return len(self.obs_shape) == 3

    @property
    def mask_token(self) -> int:
        """Index of the learned [mask] row of the goal embedding table."""
        return self.n_goals

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        d = asdict(self)
        d["obs_shape"] = list(self.obs_shape)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> GMTConfig:
        """Inverse of `to_dict`; configs written before `attention` existed read as `full`."""
        return cls(**{"attention": "full", **d, "obs_shape": tuple(d["obs_shape"])})


@dataclass
class TrainConfig:
    """One training run.

    Attributes:
        steps: Optimiser steps.
        batch_size: Windows per batch.
        lr: Peak learning rate of AdamW.
        weight_decay: AdamW weight decay (not applied to embeddings, norms and biases).
        warmup_steps: Linear warmup steps before the cosine decay.
        min_lr_ratio: Final learning rate as a fraction of `lr`.
        grad_clip: Gradient-norm clip.
        masking: Goal masking mode: token (paper default), trajectory or none.
        mask_prob: Probability p of masking a goal token (or a window's goals in trajectory mode).
        alpha: Weight of the next-goal loss.
        seed: Seed of weights, window sampling and masks.
        threads: torch intra-op threads (0 = leave torch's default).
        log_every: Steps between TensorBoard scalars and progress-bar updates.
        save_every: Steps between resumable checkpoints.
        statistic: Per-trajectory statistic the goals cluster: an expression AGG(SOURCE) such as
            mean(info.x_velocity), sum(reward) or mean(abs(obs[2])), a name (mean_x_velocity, return), or a
            module:function plug-in (docs/your-own-data.md); default: inferred from the data and printed.
        k: Number of goals; None picks k by silhouette score.
        calibration_batches: Batches of windows scored after training to measure the per-goal action noise
            of continuous-action models (`gmt.model.calibrate`).
        bf16: Run matrix products under bfloat16 autocast (pays off only on CPUs with AMX).
        sequence_length: Timesteps per training sequence; 0 = K for `full` attention and 2K for `window`
            attention (a window model must learn from sequences longer than its span).
        device: Where to train: auto (a CUDA GPU when torch sees one, else the CPU), cpu or cuda. Under
            `torchrun`, every process trains on its share of each batch (`gmt.model.distributed`).
        augment_shift: Image models: largest random shift of each training sequence's frames, in pixels
            (`gmt.model.augment`; 0 = off).
        augment_degrees: Image models: largest random rotation of each training sequence's frames, in degrees
            (0 = off).
        default_action_mode: Action mode of sessions that name none, stored in the checkpoint (None: the
            engine's default, `expert` for discrete actions), e.g. `sample` when the goals differ in how often
            the data's agents acted at random.
        switch_relabel_steps: Inference setting stored in the checkpoint: on a goal change (without a blend),
            the last this-many steps of a session's context take the new goal token (0: none;
            `gmt.model.engine.PolicyEngine.set_goal`); at most the model's history.
        time_limit_s: Stop training after this many seconds of optimiser steps (0 = no limit), at whatever
            step is reached first of `steps` and the limit. The cosine decay follows the larger of the step
            share and the elapsed share of the limit, so a cut run still ends at the floor learning rate.
            Set `steps` past what the time allows to train "for as long as the limit".
        init_from: A checkpoint directory whose weights the model starts from instead of random ones
            (fine-tuning, e.g. a DAgger round on more data); its model configuration must equal this run's.
            The optimiser, the learning-rate schedule and the observation normalisation start afresh.
    """

    steps: int = 20000
    batch_size: int = 64
    lr: float = 6e-4
    weight_decay: float = 1e-4
    warmup_steps: int = 1000
    min_lr_ratio: float = 0.1
    grad_clip: float = 0.25
    masking: MaskingMode = "token"
    mask_prob: float = 0.5
    alpha: float = 1.0
    seed: int = 0
    threads: int = 0
    log_every: int = 100
    save_every: int = 2000
    statistic: str | None = None
    k: int | None = None
    calibration_batches: int = 200
    bf16: bool = False
    sequence_length: int = 0
    device: Device = "auto"
    augment_shift: float = 0.0
    augment_degrees: float = 0.0
    default_action_mode: str | None = None
    switch_relabel_steps: int = 0
    time_limit_s: float = 0.0
    init_from: str | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.masking not in ("token", "trajectory", "none"):
            raise ValueError(f"masking must be token, trajectory or none, got {self.masking!r}")
        if not 0.0 <= self.mask_prob <= 1.0:
            raise ValueError(f"mask_prob must be in [0, 1], got {self.mask_prob}")
        if self.steps < 1 or self.batch_size < 1:
            raise ValueError("steps and batch_size must be positive")
        if self.calibration_batches < 1:
            raise ValueError(f"calibration_batches must be >= 1, got {self.calibration_batches}")
        if self.switch_relabel_steps < 0:
            raise ValueError(f"switch_relabel_steps must be >= 0, got {self.switch_relabel_steps}")
        if self.sequence_length < 0:
            raise ValueError(f"sequence_length must be >= 0, got {self.sequence_length}")
        if self.augment_shift < 0 or self.augment_degrees < 0:
            raise ValueError("augment_shift and augment_degrees must be >= 0")
        if self.default_action_mode not in (None, "expert", "argmax", "sample", "mean"):
            raise ValueError(
                "default_action_mode must be expert, argmax or sample (discrete) or sample or mean "
                f"(continuous), got {self.default_action_mode!r}"
            )
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be auto, cpu or cuda, got {self.device!r}")
        if self.time_limit_s < 0:
            raise ValueError(f"time_limit_s must be >= 0, got {self.time_limit_s}")
        if self.warmup_steps < 0 or self.lr <= 0:
            raise ValueError("warmup_steps must be >= 0 and lr > 0")

    def sequence_steps(self, cfg: GMTConfig) -> int:
        """Timesteps per training sequence for the model `cfg`."""
        if self.sequence_length:
            if cfg.attention == "full" and self.sequence_length != cfg.context_length:
                raise ValueError("a full-attention model trains on sequences of exactly K steps")
            return self.sequence_length
        return cfg.context_length if cfg.attention == "full" else 2 * cfg.context_length
