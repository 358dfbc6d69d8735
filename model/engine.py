"""Batched inference over many sessions: one forward pass answers a batch, with no loop over sessions.

Every session's state lives in one slot of a `SessionPool` (`gmt.model.pool`): its goal state, its last
`history_steps` steps in a ring, and (for `window` models) its key/value cache. An act checks the observations,
gathers the batch's slots, runs the network over them (`gmt.model.predict`: the incremental path of `window`
models or the reference recompute), chooses every row's action at once (`gmt.model.sampling`) and commits the rows
that succeeded. `GMT_NAIVE=1 gmt serve` uses the recompute path one request at a time as the exactness oracle.

The engine owns the rules of what it is given: goal ids (`check_goal`), action modes (`check_mode`), blend lengths
(`check_blend_steps`) and observations (`prepare_observation`); the service calls these and maps their errors.
"""

from __future__ import annotations

import functools
import secrets
import threading
from dataclasses import dataclass

import numpy as np
import torch

from gmt.model import native as native_kernel
from gmt.model import sampling
from gmt.model.checkpoint import Checkpoint, CheckpointError
from gmt.model.context import Context, StoredContext
from gmt.model.pool import SessionPool
from gmt.model.predict import Predictor
from gmt.model.sampling import ACTION_MODES, CONTINUOUS_MODES, MODES

__all__ = [
    "MAX_BLEND_STEPS",
    "EngineInfo",
    "InvalidObservation",
    "PolicyEngine",
    "StepFailed",
    "check_blend_steps",
]

MAX_BLEND_STEPS = 100_000  # the longest gradual goal switch


class InvalidObservation(ValueError):
    """An observation has the wrong shape, dtype or non-finite values."""


class StepFailed(ArithmeticError):
    """A step produced non-finite values; the session was left as it was before the step."""


DEVICES = ("cpu", "cuda", "auto")


def resolve_device(device: str) -> str:
    """`cpu` or a torch CUDA device name for `device` (`cpu`, `cuda`, `cuda:N` or `auto`).

    Raises:
        ValueError: an unknown name, or `cuda` where torch sees no GPU.
    """
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device != "cpu" and device.split(":")[0] != "cuda":
        raise ValueError(f"device must be one of {', '.join(DEVICES)} (or cuda:N), got {device!r}")
    if device != "cpu" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: torch sees no CUDA GPU here (use --device cpu or auto)")
    return device


def check_blend_steps(blend_steps: object) -> int:
    """`blend_steps` if it can be a gradual switch's length: an integer in 0..MAX_BLEND_STEPS.

    Raises:
        ValueError: anything else.
    """
    if (
        isinstance(blend_steps, bool)
        or not isinstance(blend_steps, int | np.integer)
        or not 0 <= blend_steps <= MAX_BLEND_STEPS
    ):
        raise ValueError(f"blend_steps must be an integer in 0..{MAX_BLEND_STEPS}, got {blend_steps!r}")
    return int(blend_steps)


@dataclass(frozen=True)
class EngineInfo:
    """What an engine tells about itself.

    Attributes:
        action_modes: Modes a session may choose, the default first.
        history_steps: Steps of history that determine an action (and that a stored context keeps).
        path: `incremental` (key/value cache, newest tokens only) or `recompute` (the reference forward).
        kernel: What computes the incremental step: `native` (`model/native/gmt_step.c`) or `torch`.
        precision: The native step's block products: `fp32` or `bf16` (`PolicyEngine`'s `precision`).
    """

    action_modes: tuple[str, ...]
    history_steps: int
    path: str
    kernel: str = "torch"
    precision: str = "fp32"


def _locked(method):
    """Run an engine method under the engine's lock: an act (in an executor thread, the native step outside the
    GIL) and a pool change (a new or adopted session growing the pool, a release shrinking it, on the event loop)
    must never overlap, or the step would write into arrays the change just replaced."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper


class PolicyEngine:
    """Answers batches of (context, observation) with actions; owns one loaded checkpoint.

    Args:
        checkpoint: The loaded checkpoint.
        incremental: Use the key/value-cache path (None = whenever the model has `window` attention);
            False forces the reference recompute.
        n_slots: Initial pool size (it grows as sessions arrive).
        native: Compute the incremental step with the native kernel (`gmt.model.native`; None = whenever it is
            available and the model has vector observations); False keeps the torch step.
        switch_relabel_steps: Steps of context a goal change relabels (`set_goal`; None = the checkpoint's
            `switch_relabel_steps`).
        device: Where the network runs: `cpu` (the native step where it can, else torch), `cuda` (the torch step
            on the GPU, the key/value pool allocated there for `n_slots` sessions up front; the network is moved
            there) or `auto` (`cuda` when a GPU is visible, else `cpu`).
        precision: `fp32` (exact: the reference arithmetic) or `bf16`: the native step computes the blocks'
            matrix products in bfloat16 (AVX-512 BF16; faster batches, answers within the tolerance in
            docs/performance.md). `bf16` needs the native step.
    """

    def __init__(
        self,
        checkpoint: Checkpoint,
        incremental: bool | None = None,
        n_slots: int = 16,
        native: bool | None = None,
        switch_relabel_steps: int | None = None,
        device: str = "cpu",
        precision: str = "fp32",
    ) -> None:
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be 'fp32' or 'bf16', got {precision!r}")
        self.precision = precision
        if checkpoint.config.conditioning != "goal":
            raise ValueError(
                "this checkpoint is a Decision Transformer (return-to-go conditioning): it is a baseline for "
                "`gmt eval`, which runs it with gmt.model.evaluate_dt; the engine serves goal-conditioned models"
            )
        self.device = resolve_device(device)
        if self.device != "cpu":
            if native:
                raise ValueError(f"the native step runs on the CPU, not on {self.device!r}")
            native = False
        self.ckpt = checkpoint
        self.model = checkpoint.model.eval().to(self.device)
        self.cfg = checkpoint.config
        self.K = self.cfg.context_length
        self.n_goals = self.cfg.n_goals
        self.obs_size = int(np.prod(self.cfg.obs_shape))
        self._uint8 = checkpoint.observation_space.get("dtype") == "uint8"  # image values: integers in 0..255
        self.discrete = self.cfg.discrete_actions
        window = self.cfg.attention == "window"
        if incremental and not window:
            raise ValueError("the incremental path is exact only for attention='window' models")
        self.incremental = window if incremental is None else incremental
        # [n_goals, A] variance of the capped noise `sample` adds (interpolated during a blend), or None.
        self.noise_var = sampling.noise_variance(None if self.discrete else checkpoint.action_noise)
        # Default first: expert for discrete actions (paper A.1.3); sample for calibrated continuous models (it
        # reproduces the goal statistics measured under the behaviour noise), else mean. A checkpoint may name
        # its own default.
        if self.discrete:
            self.action_modes: tuple[str, ...] = ACTION_MODES
        else:
            self.action_modes = CONTINUOUS_MODES if self.noise_var is not None else ("mean",)
        default = checkpoint.default_action_mode
        if default is not None:  # the checkpoint's own default goes first
            if default not in self.action_modes:
                raise CheckpointError(
                    f"checkpoint {checkpoint.name}: default_action_mode {default!r} is not one of "
                    f"{self.action_modes}"
                )
            self.action_modes = (default, *(m for m in self.action_modes if m != default))
        self._lock = threading.RLock()
        self.pool = SessionPool(self.cfg, self.incremental, n_slots, self.device)
        self.switch_relabel_steps = (
            checkpoint.switch_relabel_steps if switch_relabel_steps is None else switch_relabel_steps
        )
        if not 0 <= self.switch_relabel_steps <= self.pool.H:
            raise ValueError(
                f"switch_relabel_steps must be 0 to {self.pool.H} (the history kept), got {self.switch_relabel_steps}"
            )
        self._native = self._native_step(native) if self.incremental else None
        if precision == "bf16" and self._native is None:
            raise ValueError(
                "precision 'bf16' runs in the native step, which this model does not use here (it needs a CPU "
                "device, a vector-observation window model and the native library)"
            )
        self._predict = Predictor(self.model, self.pool, self.incremental, self._native, self.device)
        # Slots adopted from a stored form whose key/value cache is rebuilt at their next step: the sessions a
        # call adopts together are replayed together (`Predictor.rebuild_caches`).
        self._stale: set[int] = set()

    def _native_step(self, native: bool | None):
        """The native step for this model, or None (torch step). Raises if `native` is True and it cannot run."""
        if native is False:
            return None
        if self.cfg.is_image:
            if native:
                raise ValueError("the native step serves vector observations only")
            return None
        lib = native_kernel.load()
        if lib is None:
            if native:
                raise RuntimeError("the native step is unavailable (no C compiler, or GMT_NATIVE=0)")
            return None
        return native_kernel.NativeStep(self.model, lib, bf16=self.precision == "bf16")

    def describe(self) -> EngineInfo:
        """Modes, history and compute path."""
        return EngineInfo(
            action_modes=self.action_modes,
            history_steps=self.pool.H,
            path="incremental" if self.incremental else "recompute",
            kernel="native" if self._native is not None else "torch",
            precision=self.precision,
        )

    @property
    def default_action_mode(self) -> str:
        """The mode of a session that does not choose one."""
        return self.action_modes[0]

    # ----- contexts -----------------------------------------------------------------------------------------
    def check_goal(self, goal: int) -> None:
        """Raise ValueError for anything but a goal id of the goal table (0 .. n_goals - 1)."""
        if isinstance(goal, bool) or not isinstance(goal, int | np.integer):
            shown = repr(goal)
        elif 0 <= goal < self.n_goals:
            return
        else:
            shown = str(int(goal))
        names = ", ".join(f"{g.id}={g.name}" for g in self.ckpt.goals)
        raise ValueError(f"goal {shown} is not a goal id of model {self.ckpt.name!r}; goals are {names}")

    def check_mode(self, action_mode: str | None) -> str:
        """The action mode a session gets (its own, else the default). Raises ValueError for one this model lacks."""
        action_mode = action_mode or self.default_action_mode
        if action_mode not in self.action_modes:
            kind = "discrete" if self.discrete else "continuous"
            raise ValueError(
                f"action_mode {action_mode!r} is not available for model {self.ckpt.name!r} ({kind} actions); "
                f"choose one of {', '.join(self.action_modes)}"
            )
        return action_mode

    def _slot_for(self, key: str | None) -> int:
        p = self.pool
        if key is not None and key in p.keys:
            return p.keys[key]
        slot = p.allocate()
        if key is not None:
            p.keys[key] = slot
        return slot

    @_locked
    def new_context(
        self, goal: int, action_mode: str | None = None, seed: int | None = None, key: str | None = None
    ) -> Context:
        self.check_goal(goal)
        mode = self.check_mode(action_mode)
        if seed is None:
            seed = secrets.randbits(63)
        slot = self._slot_for(key)
        p = self.pool
        p.goal[slot] = p.blend_from[slot] = goal
        p.step[slot] = p.blend_steps[slot] = p.blend_done[slot] = p.version[slot] = 0
        p.mode[slot], p.seed[slot] = MODES.index(mode), int(seed)
        if p.cache is not None:
            p.cache.clear(torch.tensor([slot]))
        self._stale.discard(slot)
        return Context(p, slot, key)

    def warm_up(self) -> None:
        """One act of a throwaway session, released at once: a device's lazy start (its context, its kernels'
        first launch: ~0.5 s on a GPU) is paid here rather than by the first session's first act."""
        ctx = self.new_context(0, seed=0)
        try:
            self.act([ctx], [np.zeros(self.cfg.obs_shape, np.float32)])
        finally:
            self.release(ctx)

    @_locked
    def release(self, ctx: Context) -> None:
        p = self.pool
        if ctx.key is not None and p.keys.get(ctx.key) == ctx.slot:
            del p.keys[ctx.key]
        p.release(ctx.slot)
        self._stale.discard(ctx.slot)

    def forget(self, key: str) -> None:
        """Release the slot registered under `key`, if any."""
        slot = self.pool.keys.get(key)
        if slot is not None:
            self.release(Context(self.pool, slot, key))

    def last_answer(self, ctx: Context) -> tuple[np.ndarray | int, int]:
        p, s = self.pool, ctx.slot
        if p.step[s] == 0:
            raise ValueError("the context has not acted yet")
        pos = (p.step[s] - 1) % p.H
        a = p.h_action[s, pos]
        action = int(a) if self.discrete else self.ckpt.action_codec.decode(a[None])[0]
        return action, int(p.h_blend_to[s, pos])

    def same_as_last(self, ctx: Context, state: np.ndarray) -> bool:
        """Whether `state` (a prepared observation) is the one the context's last step acted on."""
        p, s = self.pool, ctx.slot
        if p.step[s] == 0:
            return False
        last = p.h_state[s, (p.step[s] - 1) % p.H]
        return bool(np.array_equal(last, np.asarray(state, dtype=last.dtype).reshape(last.shape)))

    @_locked
    def reset(self, ctx: Context, goal: int | None = None) -> None:
        p, s = self.pool, ctx.slot
        if goal is not None:
            self.check_goal(goal)
            p.goal[s] = goal
        p.step[s] = p.blend_steps[s] = p.blend_done[s] = 0
        p.blend_from[s] = p.goal[s]
        p.version[s] += 1
        if p.cache is not None:
            p.cache.clear(torch.tensor([s]))
        self._stale.discard(s)

    @_locked
    def set_goal(self, ctx: Context, goal: int, blend_steps: int = 0) -> int:
        """Condition the context's next steps on `goal`, faded in over `blend_steps` steps (0: at once).

        A change at once to another goal also relabels the context: the goal tokens of its last
        `switch_relabel_steps` steps become `goal` (no blend), as if the new goal had been pursued all along, and the
        key/value cache is rebuilt from them. Without it a model trained with goal masking reads the old
        tokens as evidence of the old goal and follows the new one slowly (docs/results.md, "Relabelling
        the context on a switch"). A blend keeps the context as it was given.

        Returns:
            The number of past steps relabelled: the held steps `ctx.step - n` .. `ctx.step - 1` changed.
        """
        self.check_goal(goal)
        blend_steps = check_blend_steps(blend_steps)
        p, s = self.pool, ctx.slot
        changed = goal != p.goal[s]
        if blend_steps > 0 and changed:
            if ctx.blend_remaining == 0:
                p.blend_from[s] = p.goal[s]
            p.blend_steps[s], p.blend_done[s] = blend_steps, 0
        else:
            p.blend_from[s], p.blend_steps[s], p.blend_done[s] = goal, 0, 0
        p.goal[s] = goal
        p.version[s] += 1
        n = min(self.switch_relabel_steps, ctx.size) if changed and blend_steps == 0 else 0
        if n:
            t = int(p.step[s])
            pos = np.arange(t - n, t) % p.H  # [n] ring positions of the last n steps
            p.h_goal[s, pos] = goal
            p.h_blend_to[s, pos] = goal
            p.h_blend_w[s, pos] = 0.0
            if p.cache is not None:
                self._predict.rebuild_caches([s])
                self._stale.discard(s)
        return n

    @_locked
    def from_stored(self, stored: StoredContext, key: str | None = None) -> Context:
        p = self.pool
        if key is not None and key in p.keys and p.version[p.keys[key]] == stored.version:
            slot = p.keys[key]
            if p.step[slot] == stored.step:
                return Context(p, slot, key)
        self.check_goal(stored.goal)
        self.check_goal(stored.blend_from)
        mode = self.check_mode(stored.action_mode)
        p.check_stored(stored)
        slot = self._slot_for(key)
        p.load(slot, stored, mode)
        if p.cache is not None:
            self._stale.add(slot)  # rebuilt at its next step, with the others adopted meanwhile
        return Context(p, slot, key)

    # ----- observations -------------------------------------------------------------------------------------
    def prepare_observation(self, obs: np.ndarray | list) -> np.ndarray:
        """Validate one raw observation and return it normalised in the model's shape.

        Raises:
            InvalidObservation: wrong number of values, non-numeric or non-finite values (also after
                normalisation, which can overflow float32), or values an image (uint8) cannot hold.
        """
        try:
            x = np.asarray(obs)
        except (ValueError, TypeError) as e:
            raise InvalidObservation(f"observation is not a rectangular numeric array: {e}") from e
        if x.dtype == bool:
            raise InvalidObservation("observation must hold numbers, got booleans")
        if x.dtype == object or not np.issubdtype(x.dtype, np.number):
            raise InvalidObservation(f"observation must be numeric, got dtype {x.dtype}")
        if self._uint8 and x.dtype != np.uint8 and x.size:
            with np.errstate(invalid="ignore"):
                if not np.all((x >= 0) & (x <= 255) & (x == np.round(x))):
                    raise InvalidObservation("image observation values must be integers in 0..255")
        if x.size != self.obs_size:
            raise InvalidObservation(
                f"observation has {x.size} values, expected {self.obs_size} (shape {list(self.cfg.obs_shape)})"
            )
        shape = self.cfg.obs_shape
        if x.shape != shape and not (len(shape) == 3 and shape[0] == 1 and x.shape == shape[1:]):
            raise InvalidObservation(f"observation has shape {list(x.shape)}, expected {list(shape)}")
        if x.dtype.kind == "f" and not self.cfg.is_image:  # fast path: one check of the normalised values
            with np.errstate(over="ignore", invalid="ignore"):
                state = self.ckpt.obs_norm(x.reshape(shape))
            if np.isfinite(state).all():
                return state
        if np.issubdtype(x.dtype, np.floating) and not np.isfinite(x).all():
            bad = int(np.flatnonzero(~np.isfinite(x.ravel()))[0])
            raise InvalidObservation(f"observation has a non-finite value (NaN or Inf) at index {bad}")
        with np.errstate(over="ignore", invalid="ignore"):
            state = self.ckpt.obs_norm(x.reshape(self.cfg.obs_shape))
        if state.dtype.kind == "f" and not np.isfinite(state).all():
            bad = int(np.flatnonzero(~np.isfinite(state.ravel()))[0])
            raise InvalidObservation(
                f"observation value at index {bad} is too large: its normalised value overflows"
            )
        return state

    # ----- inference ----------------------------------------------------------------------------------------
    @_locked
    def act(
        self, contexts: list[Context], observations: list, prepared: bool = False, threads: int = 1
    ) -> list[np.ndarray | int | Exception]:
        """One step for each context: predict from the history plus the observation, then commit.

        Args:
            contexts: The sessions' contexts (each at most once in a batch).
            observations: One observation per context: raw, or the output of `prepare_observation`.
            prepared: Whether `observations` are already prepared.
            threads: Threads the native step may split the batch's rows between (the same answers; the torch
                and device steps use their own threads).

        Returns:
            Per context: a float32 action (continuous, clipped to the space), an int (discrete), or the
            exception (InvalidObservation, StepFailed) that failed that item alone, whose context is unchanged.
        """
        if len(contexts) != len(observations):
            raise ValueError("one observation per context is required")
        if not contexts:
            return []
        out: list = [None] * len(contexts)
        rows, states = [], []
        for i, o in enumerate(observations):
            if prepared:
                rows.append(i)
                states.append(o)
                continue
            try:
                states.append(self.prepare_observation(o))
                rows.append(i)
            except InvalidObservation as e:
                out[i] = e
        if not rows:
            return out
        if len(rows) < len(contexts):
            contexts = [contexts[i] for i in rows]
        pool = self.pool
        if any(c.pool is not pool for c in contexts):
            raise ValueError(
                "a context of another engine's pool (adopt it with from_stored(ctx.to_stored()))"
            )
        slots = np.fromiter((c.slot for c in contexts), dtype=np.int64, count=len(contexts))
        if len(slots) > 1 and len(np.unique(slots)) != len(slots):
            raise ValueError("a context may appear once per batch")
        actions, ok = self._step(slots, np.stack(states), threads)
        for j, i in enumerate(rows):
            out[i] = (
                actions[j]
                if ok[j]
                else StepFailed(
                    "the model produced a non-finite action for this observation; the session is unchanged"
                )
            )
        return out

    def _step(self, slots: np.ndarray, states: np.ndarray, threads: int = 1) -> tuple[list, np.ndarray]:
        p = self.pool
        if self._stale:
            due = [s for s in slots.tolist() if s in self._stale]
            if due:
                self._predict.rebuild_caches(due)
                self._stale.difference_update(due)
        if self._native is not None and not self.discrete:  # all of it in one native call
            taken, ok = self._native.act(p, slots, states, self.noise_var, MODES.index("sample"), threads)
            return list(self.ckpt.action_codec.decode(taken)), ok
        t = p.step[slots]  # [B]
        blending = p.blend_steps[slots] > p.blend_done[slots]  # [B]
        goal = p.goal[slots]
        g = np.where(blending, p.blend_from[slots], goal)  # [B] goal token
        w = np.where(blending, (p.blend_done[slots] + 1) / np.maximum(p.blend_steps[slots], 1), 0.0).astype(
            np.float32
        )  # [B] weight of `goal` in the token
        pred = self._predict(slots, t, g, goal, w, states)  # [B, A]
        ok = np.isfinite(pred).all(axis=1)  # [B]
        every = bool(ok.all())
        if not every:
            pred = np.where(ok[:, None], pred, 0.0)
        taken = sampling.choose(
            pred, p.mode[slots], p.seed[slots], t, g, goal, w, self.noise_var, self.discrete
        )
        env_actions = [int(a) for a in taken] if self.discrete else list(self.ckpt.action_codec.decode(taken))
        # Commit the rows that succeeded.
        if not every:
            slots, t, g, goal, w, states, taken, blending = (
                x[ok] for x in (slots, t, g, goal, w, states, taken, blending)
            )
        pos = t % p.H
        p.h_goal[slots, pos], p.h_blend_to[slots, pos], p.h_blend_w[slots, pos] = g, goal, w
        p.h_state[slots, pos], p.h_action[slots, pos] = states, taken
        p.step[slots] += 1
        p.version[slots] += 1
        if blending.any():
            p.blend_done[slots] += blending
            done = slots[blending & (p.blend_done[slots] >= p.blend_steps[slots])]
            p.blend_from[done], p.blend_steps[done], p.blend_done[done] = p.goal[done], 0, 0
        return env_actions, ok
