"""The one interface between the service core and an inference engine.

The core and the model registry only ever call these methods; which engine sits behind them (the exact
incremental engine of a `window` model, or the reference recompute) is decided once, by `load_runtime`.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gmt.model.checkpoint import Checkpoint
from gmt.model.context import Context, StoredContext


class InvalidObservation(ValueError):
    """An observation has the wrong shape, dtype or non-finite values."""


class StepFailed(ArithmeticError):
    """A step produced non-finite values; the session was left as it was before the step."""


@dataclass(frozen=True)
class RuntimeInfo:
    """What an engine tells about itself.

    Attributes:
        action_modes: Modes a session may choose, the default first.
        history_steps: Steps of history that determine an action (and that a stored context keeps).
        path: `incremental` (key/value cache, newest tokens only) or `recompute` (the reference forward).
        kernel: What computes the incremental step: `native` (`model/native/gmt_step.c`) or `torch`.
    """

    action_modes: tuple[str, ...]
    history_steps: int
    path: str
    kernel: str = "torch"


class PolicyRuntime(abc.ABC):
    """A loaded checkpoint that answers acts for many sessions (see `gmt.model.engine.PolicyEngine`)."""

    ckpt: Checkpoint

    @abc.abstractmethod
    def describe(self) -> RuntimeInfo:
        """Modes, history and compute path."""

    @property
    def default_action_mode(self) -> str:
        """The mode of a session that does not choose one."""
        return self.describe().action_modes[0]

    @abc.abstractmethod
    def new_context(
        self, goal: int, action_mode: str | None = None, seed: int | None = None, key: str | None = None
    ) -> Context:
        """A fresh episode pursuing `goal` (registered under `key` when given)."""

    @abc.abstractmethod
    def prepare_observation(self, obs: np.ndarray | list) -> np.ndarray:
        """Validate one raw observation and return it normalised (raises InvalidObservation)."""

    @abc.abstractmethod
    def act(
        self, contexts: list[Context], observations: list, prepared: bool = False
    ) -> list[np.ndarray | int | Exception]:
        """One step for each context; a failed item is an exception in its place and leaves its context as it was."""

    @abc.abstractmethod
    def last_answer(self, ctx: Context) -> tuple[np.ndarray | int, int]:
        """(action, goal) the context's last act answered, rebuilt from its history (for idempotent retries)."""

    @abc.abstractmethod
    def same_as_last(self, ctx: Context, state: np.ndarray) -> bool:
        """Whether a prepared observation is the one the context's last act answered (a retry must repeat it)."""

    @abc.abstractmethod
    def set_goal(self, ctx: Context, goal: int, blend_steps: int = 0) -> None:
        """Condition tokens from the next step on `goal`, faded in over `blend_steps` steps if > 0."""

    @abc.abstractmethod
    def reset(self, ctx: Context, goal: int | None = None) -> None:
        """Forget the episode; keep (or replace) the goal."""

    @abc.abstractmethod
    def release(self, ctx: Context) -> None:
        """Free the context's resources; the handle must not be used afterwards."""

    @abc.abstractmethod
    def forget(self, key: str) -> None:
        """Release the context registered under `key`, if this engine holds one."""

    @abc.abstractmethod
    def from_stored(self, stored: StoredContext, key: str | None = None) -> Context:
        """Adopt a stored context (reusing this engine's copy of `key` when it is at the same version)."""

    def to_stored(self, ctx: Context) -> StoredContext:
        """The context as plain data."""
        return ctx.to_stored()


def load_runtime(
    path: str | Path | Checkpoint, naive: bool = False, name: str | None = None
) -> PolicyRuntime:
    """The engine for a checkpoint: incremental for `window` models, recompute otherwise or when `naive`."""
    from gmt.model.checkpoint import load_checkpoint
    from gmt.model.engine import PolicyEngine

    ckpt = path if isinstance(path, Checkpoint) else load_checkpoint(path, name=name)
    return PolicyEngine(ckpt, incremental=None if not naive else False)
