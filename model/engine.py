"""Batched inference over many rolling contexts: one forward pass answers a batch of sessions.

Evaluation and the server both use this engine. A `Context` is one episode's last K steps plus its goal state;
it holds only NumPy arrays and plain values, so a session store can persist it without pickle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from model.checkpoint import Checkpoint
from model.tokens import Windows, pad_left

ACTION_MODES = ("argmax", "sample", "expert")  # discrete actions, default first
CONTINUOUS_MODES = ("sample", "mean")  # continuous actions of a calibrated checkpoint, default first
DETERMINISTIC_MODES = ("argmax", "mean")
# Largest action-noise std (model space, actions in [-1, 1]) that `sample` adds. Trained behaviour levels explore
# with small noise (HalfCheetah: ~0.05) and sampling it reproduces their statistics; a uniform-random level's
# spread (~0.55) is the behaviour itself, and reproducing it tipped HalfCheetah into poses that no running data
# recovers from (6 of 15 switches out of the random goal failed uncapped; 0 of 15 capped at 0.1).
SAMPLE_STD_CAP = 0.1
EXPERT_QUANTILE = 0.6


class InvalidObservation(ValueError):
    """An observation has the wrong size, dtype or non-finite values."""


@dataclass
class Context:
    """One episode's rolling context and goal state.

    Attributes:
        goal: The goal the session is asked to pursue (reported with every action).
        step: Timestep of the next observation.
        blend_from: Goal being faded out during a gradual switch.
        blend_steps: Length of the current gradual switch (0 = none).
        blend_done: Steps of the gradual switch already taken.
        action_mode: Discrete actions: argmax, sample or expert; continuous: mean or sample.
        rng: Generator for sampled actions.
        goals: [n] goal token of each step (the faded-out goal during a blend).
        blend_to: [n] second goal of each step's token.
        blend_w: [n] weight of `blend_to` in each step's token (0 = plain goal).
        states: [n, *obs_shape] normalised states.
        actions: [n, A] model-space actions ([n] ids for discrete).
        timesteps: [n] timesteps.
    """

    goal: int
    step: int = 0
    blend_from: int = 0
    blend_steps: int = 0
    blend_done: int = 0
    action_mode: str = "argmax"
    rng: np.random.Generator = field(default_factory=np.random.default_rng)
    goals: np.ndarray | None = None
    blend_to: np.ndarray | None = None
    blend_w: np.ndarray | None = None
    states: np.ndarray | None = None
    actions: np.ndarray | None = None
    timesteps: np.ndarray | None = None

    @property
    def size(self) -> int:
        """Number of steps held (at most K)."""
        return 0 if self.goals is None else len(self.goals)

    @property
    def blend_remaining(self) -> int:
        """Steps left in the current gradual switch."""
        return max(self.blend_steps - self.blend_done, 0)


class PolicyEngine:
    """Answers batches of (context, observation) with actions; owns one loaded checkpoint."""

    def __init__(self, checkpoint: Checkpoint) -> None:
        self.ckpt = checkpoint
        self.model = checkpoint.model.eval()
        self.cfg = checkpoint.config
        self.K = self.cfg.context_length
        self.n_goals = self.cfg.n_goals
        self.obs_size = int(np.prod(self.cfg.obs_shape))
        self.discrete = self.cfg.discrete_actions
        noise = None if self.discrete else checkpoint.action_noise  # [n_goals, A] std or None
        # [n_goals, A] variance of the capped noise `sample` adds (interpolated during a blend).
        self.noise_var = None if noise is None else np.minimum(noise, SAMPLE_STD_CAP).astype(np.float64) ** 2
        # Default first: argmax for discrete actions; sample for calibrated continuous models (it reproduces
        # the goal statistics measured under the behaviour noise), else mean.
        if self.discrete:
            self.action_modes: tuple[str, ...] = ACTION_MODES
        else:
            self.action_modes = CONTINUOUS_MODES if self.noise_var is not None else ("mean",)

    @property
    def default_action_mode(self) -> str:
        """The mode of a session that does not choose one."""
        return self.action_modes[0]

    # ----- contexts -----------------------------------------------------------------------------------------
    def new_context(self, goal: int, action_mode: str | None = None, seed: int | None = None) -> Context:
        """An empty context for a new episode (`action_mode` None = the model's default)."""
        self.check_goal(goal)
        action_mode = action_mode or self.default_action_mode
        if action_mode not in self.action_modes:
            raise ValueError(
                f"action_mode must be one of {self.action_modes} for this model, got {action_mode!r}"
            )
        return Context(goal=goal, blend_from=goal, action_mode=action_mode, rng=np.random.default_rng(seed))

    def reset(self, ctx: Context, goal: int | None = None) -> None:
        """Forget the episode; keep (or replace) the goal."""
        if goal is not None:
            self.check_goal(goal)
            ctx.goal = goal
        ctx.step, ctx.blend_from, ctx.blend_steps, ctx.blend_done = 0, ctx.goal, 0, 0
        ctx.goals = ctx.blend_to = ctx.blend_w = ctx.states = ctx.actions = ctx.timesteps = None

    def set_goal(self, ctx: Context, goal: int, blend_steps: int = 0) -> None:
        """Condition tokens from the next step on `goal`; fade it in over `blend_steps` steps if > 0."""
        self.check_goal(goal)
        if blend_steps < 0:
            raise ValueError(f"blend_steps must be >= 0, got {blend_steps}")
        if blend_steps > 0 and goal != ctx.goal:
            ctx.blend_from = self._token_goal(ctx)[0] if ctx.blend_remaining == 0 else ctx.blend_from
            ctx.blend_steps, ctx.blend_done = blend_steps, 0
        else:
            ctx.blend_from, ctx.blend_steps, ctx.blend_done = goal, 0, 0
        ctx.goal = goal

    def check_goal(self, goal: int) -> None:
        """Raise ValueError for a goal id outside the goal table."""
        if not isinstance(goal, int | np.integer) or not 0 <= int(goal) < self.n_goals:
            raise ValueError(f"goal {goal!r} is not a goal id of this model (0..{self.n_goals - 1})")

    @staticmethod
    def _token_goal(ctx: Context) -> tuple[int, int, float]:
        """(goal, blend_to, weight) of the next step's goal token, without advancing the blend."""
        if ctx.blend_remaining == 0:
            return ctx.goal, ctx.goal, 0.0
        return ctx.blend_from, ctx.goal, (ctx.blend_done + 1) / ctx.blend_steps

    # ----- observations -------------------------------------------------------------------------------------
    def prepare_observation(self, obs: np.ndarray | list) -> np.ndarray:
        """Validate one raw observation and return it normalised in the model's shape.

        Raises:
            InvalidObservation: wrong number of values or non-finite values.
        """
        try:
            x = np.asarray(obs)
        except (ValueError, TypeError) as e:
            raise InvalidObservation(f"observation is not a rectangular numeric array: {e}") from e
        if x.dtype == object or not (np.issubdtype(x.dtype, np.number) or x.dtype == bool):
            raise InvalidObservation(f"observation must be numeric, got dtype {x.dtype}")
        if x.size != self.obs_size:
            raise InvalidObservation(
                f"observation has {x.size} values, expected {self.obs_size} (shape {list(self.cfg.obs_shape)})"
            )
        if np.issubdtype(x.dtype, np.floating) and not np.isfinite(x).all():
            bad = int(np.flatnonzero(~np.isfinite(x.ravel()))[0])
            raise InvalidObservation(f"observation has a non-finite value (NaN or Inf) at index {bad}")
        return self.ckpt.obs_norm(x.reshape(self.cfg.obs_shape))

    # ----- inference ----------------------------------------------------------------------------------------
    def _grown(self, ctx: Context, state: np.ndarray) -> tuple[np.ndarray, ...]:
        g, b, w = self._token_goal(ctx)
        zero_a = np.zeros(
            () if self.discrete else (self.cfg.act_dim,), dtype=np.int64 if self.discrete else np.float32
        )

        def push(arr: np.ndarray | None, item) -> np.ndarray:
            item = np.asarray(item)[None]
            return (
                item
                if arr is None
                else np.concatenate([arr[-(self.K - 1) :] if self.K > 1 else arr[:0], item])
            )

        return (
            push(ctx.goals, np.int64(g)),
            push(ctx.blend_to, np.int64(b)),
            push(ctx.blend_w, np.float32(w)),
            push(ctx.states, state),
            push(ctx.actions, zero_a),
            push(ctx.timesteps, np.int64(ctx.step)),
        )

    @torch.inference_mode()
    def forward(
        self, windows: Windows, blend_to: torch.Tensor | None = None, blend_w: torch.Tensor | None = None
    ):
        """Action predictions [B, K, A] of the network for a batch of windows (reference, fp32)."""
        pred, _ = self.model(*windows.model_inputs(), blend_to=blend_to, blend_w=blend_w)
        return pred

    def act(self, contexts: list[Context], observations: list) -> list[np.ndarray | int]:
        """One step for each context: append the observation, predict, append the action.

        Contexts are changed only when the whole batch succeeded.

        Args:
            contexts: The sessions' contexts (each at most once in a batch).
            observations: One raw observation per context.

        Returns:
            Environment actions: float32 arrays (continuous, clipped) or ints (discrete).
        """
        if len(contexts) != len(observations):
            raise ValueError("one observation per context is required")
        if not contexts:
            return []
        states = [self.prepare_observation(o) for o in observations]
        grown = [self._grown(c, s) for c, s in zip(contexts, states, strict=True)]
        windows = pad_left(
            [x[0] for x in grown], [x[3] for x in grown], [x[4] for x in grown], [x[5] for x in grown], self.K
        )
        blend = any(float(x[2][-1]) > 0.0 or (x[2] > 0).any() for x in grown)
        blend_to = blend_w = None
        if blend:
            bw = pad_left(
                [x[1] for x in grown],
                [x[2][:, None] for x in grown],
                [x[4] for x in grown],
                [x[5] for x in grown],
                self.K,
            )
            blend_to, blend_w = bw.goals, bw.states[..., 0]
        pred = self.forward(windows, blend_to, blend_w)[:, -1]  # [B, A]
        pred_np = pred.float().numpy()
        out: list[np.ndarray | int] = []
        for ctx, row, (g, b, w, s, a, t) in zip(contexts, pred_np, grown, strict=True):
            if self.discrete:
                act = self._choose(row, ctx)
                a[-1] = act
                out.append(int(act))
            else:
                if ctx.action_mode == "sample":
                    row = row + self._noise_std(g[-1], b[-1], w[-1]) * ctx.rng.standard_normal(row.shape)
                a[-1] = np.clip(row, -1.0, 1.0)
                out.append(self.ckpt.action_codec.decode(a[-1]))
            ctx.goals, ctx.blend_to, ctx.blend_w, ctx.states, ctx.actions, ctx.timesteps = g, b, w, s, a, t
            if ctx.blend_remaining > 0:
                ctx.blend_done += 1
                if ctx.blend_remaining == 0:
                    ctx.blend_from, ctx.blend_steps, ctx.blend_done = ctx.goal, 0, 0
            ctx.step += 1
        return out

    def _noise_std(self, goal: int, blend_to: int, weight: float) -> np.ndarray:
        """[A] action std (capped) of a step's goal token (variances interpolated during a blend)."""
        return np.sqrt((1.0 - weight) * self.noise_var[goal] + weight * self.noise_var[blend_to])

    @staticmethod
    def _choose(logits: np.ndarray, ctx: Context) -> int:
        if ctx.action_mode == "argmax":
            return int(np.argmax(logits))
        z = logits.astype(np.float64)
        if ctx.action_mode == "expert":
            z = np.where(z >= np.quantile(z, EXPERT_QUANTILE), z, -math.inf)
        p = np.exp(z - z.max())
        p /= p.sum()
        return int(ctx.rng.choice(len(p), p=p))
