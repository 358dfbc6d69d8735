"""Batched inference over many sessions: one forward pass answers a batch, with no loop over sessions.

Every session's state lives in one slot of a `SessionPool`: its goal state, its last `history_steps` steps in a
ring, and (for `window` models) its key/value cache. An act gathers the batch's slots, runs either

- the **incremental** path (`window` models): only the newest tokens of each session, the action taken at the
  previous step, the goal and the state, go through the network, attending over the key/value cache; or
- the **recompute** path (the reference, and the only exact path for `full` models): the whole history window
  through the network, heads at the last position only,

then samples actions for all rows at once and commits the rows that succeeded. Both paths give the same actions
(fp32, to rounding); `gmt serve --naive` uses the recompute path one request at a time as the exactness oracle.
"""

from __future__ import annotations

import ctypes
import functools
import math
import secrets
import threading

import numpy as np
import torch

from gmt.model import native as native_kernel
from gmt.model.checkpoint import Checkpoint
from gmt.model.context import Context, StoredContext
from gmt.model.kv_cache import KVCache
from gmt.model.runtime import InvalidObservation, PolicyRuntime, RuntimeInfo, StepFailed

__all__ = ["InvalidObservation", "PolicyEngine", "SessionPool", "StepFailed"]

# Discrete actions, default first: `expert` (paper A.1.3: sample among the logits above their 0.6 quantile).
ACTION_MODES = ("expert", "argmax", "sample")
CONTINUOUS_MODES = ("sample", "mean")  # continuous actions of a calibrated checkpoint, default first
MODES = ("argmax", "sample", "expert", "mean")  # index stored per slot
# Largest action-noise std (model space, actions in [-1, 1]) that `sample` adds. Trained behaviour levels explore
# with small noise (HalfCheetah: ~0.05) and sampling it reproduces their statistics; a uniform-random level's
# spread (~0.55) is the behaviour itself, and reproducing it tipped HalfCheetah into poses that no running data
# recovers from (6 of 15 switches out of the random goal failed uncapped; 0 of 15 capped at 0.1).
SAMPLE_STD_CAP = 0.1
EXPERT_QUANTILE = 0.6
TORCH_ROW_MULTIPLE = 8  # the torch step runs batches padded to a multiple of this many rows (exactness)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 arrays (wrapping arithmetic)."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def uniforms(seed: np.ndarray, step: np.ndarray, n: int, stream: int = 0) -> np.ndarray:
    """[B, n] uniforms in (0, 1), a pure function of (seed, step, stream): sampling needs no stored RNG state.

    Computed by the native library when it is available (one call instead of ~20 array operations; the same
    bits), else here.
    """
    out = native_kernel.uniforms(seed, step, n, stream)
    if out is not None:
        return out
    return numpy_uniforms(seed, step, n, stream)


def numpy_uniforms(seed: np.ndarray, step: np.ndarray, n: int, stream: int = 0) -> np.ndarray:
    """`uniforms` in numpy."""
    with np.errstate(over="ignore"):
        key = _mix(
            seed.astype(np.uint64) * _GOLDEN + _mix(step.astype(np.uint64) + np.uint64(stream) * _GOLDEN)
        )
        bits = _mix(key[:, None] + (np.arange(1, n + 1, dtype=np.uint64) * _GOLDEN)[None, :])
    return ((bits >> np.uint64(11)).astype(np.float64) + 0.5) / 2.0**53


def normals(seed: np.ndarray, step: np.ndarray, n: int) -> np.ndarray:
    """[B, n] standard normals from (seed, step) by Box-Muller (native when available, as `uniforms`)."""
    out = native_kernel.normals(seed, step, n)
    if out is not None:
        return out
    return numpy_normals(seed, step, n)


def numpy_normals(seed: np.ndarray, step: np.ndarray, n: int) -> np.ndarray:
    """`normals` in numpy."""
    u1, u2 = numpy_uniforms(seed, step, n, 1), numpy_uniforms(seed, step, n, 2)
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * math.pi * u2)


def _locked(method):
    """Run an engine method under the engine's lock: an act (in an executor thread, the native step outside the
    GIL) and a pool change (a new or adopted session growing the pool, a release shrinking it, on the event loop)
    must never overlap, or the step would write into arrays the change just replaced."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper


def _return_freed_memory() -> None:
    """Ask glibc to give freed heap pages back to the OS (a no-op elsewhere): the pool's arrays were freed in
    several malloc arenas (the event loop's and the inference threads'), which glibc otherwise keeps."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class SessionPool:
    """Arrays of every live session of one engine, indexed by slot; grows by doubling.

    Attributes:
        H: Steps of history kept per slot (a ring indexed by timestep mod H).
        modes: Names of the mode indices stored in `mode`.
        goal, step, blend_from, blend_steps, blend_done, mode, seed, version: [S] per-slot scalars.
        h_goal, h_blend_to: [S, H] goal tokens; h_blend_w: [S, H] blend weights.
        h_state: [S, H, *obs_shape] normalised states; h_action: [S, H, A] (or [S, H] ids) actions taken.
        cache: the key/value cache (incremental path only).
    """

    SCALARS = ("goal", "step", "blend_from", "blend_steps", "blend_done", "mode", "seed", "version")

    def __init__(self, engine: PolicyEngine, n_slots: int = 16) -> None:
        cfg = engine.cfg
        self.H = cfg.history_steps
        self.modes = MODES
        state_dtype = np.uint8 if cfg.is_image else np.float32
        act_shape, act_dtype = ((), np.int64) if cfg.discrete_actions else ((cfg.act_dim,), np.float32)
        self._layout = {
            **{name: ((), np.uint64 if name == "seed" else np.int64) for name in self.SCALARS},
            "h_goal": ((self.H,), np.int64),
            "h_blend_to": ((self.H,), np.int64),
            "h_blend_w": ((self.H,), np.float32),
            "h_state": ((self.H, *cfg.obs_shape), state_dtype),
            "h_action": ((self.H, *act_shape), act_dtype),
        }
        self._cfg, self._incremental, self._initial = cfg, engine.incremental, n_slots
        self.generation = 0  # changes whenever the arrays are replaced (native code holds their addresses)
        self._allocate_arrays(n_slots)
        self.keys: dict[str, int] = {}

    def _allocate_arrays(self, n_slots: int) -> None:
        for name, (shape, dtype) in self._layout.items():
            setattr(self, name, np.zeros((n_slots, *shape), dtype=dtype))
        self.cache = KVCache(self._cfg, n_slots) if self._incremental else None
        self.free = list(range(n_slots - 1, -1, -1))
        self.generation += 1

    @property
    def n_slots(self) -> int:
        """Slots allocated."""
        return len(self.step)

    @property
    def live(self) -> int:
        """Slots in use."""
        return self.n_slots - len(self.free)

    def allocate(self) -> int:
        """A free slot, growing the pool when none is left."""
        if not self.free:
            n = self.n_slots
            for name, (shape, dtype) in self._layout.items():
                setattr(self, name, np.concatenate([getattr(self, name), np.zeros((n, *shape), dtype)]))
            if self.cache is not None:
                self.cache.grow(2 * n)
            self.free = list(range(2 * n - 1, n - 1, -1))
            self.generation += 1
        return self.free.pop()

    def release(self, slot: int) -> None:
        """Return a slot to the free list; once no slot is in use, a grown pool shrinks back to its first size.

        (Slots in use are never moved, so a pool cannot shrink while any is live: after a crowd has gone,
        memory returns to the baseline.)
        """
        self.free.append(slot)
        if not self.live and self.n_slots > self._initial:
            self._allocate_arrays(self._initial)
            _return_freed_memory()


class PolicyEngine(PolicyRuntime):
    """Answers batches of (context, observation) with actions; owns one loaded checkpoint.

    Args:
        checkpoint: The loaded checkpoint.
        incremental: Use the key/value-cache path (None = whenever the model has `window` attention);
            False forces the reference recompute.
        n_slots: Initial pool size (it grows as sessions arrive).
        native: Compute the incremental step with the native kernel (`gmt.model.native`; None = whenever it is
            available and the model has vector observations); False keeps the torch step.
    """

    def __init__(
        self,
        checkpoint: Checkpoint,
        incremental: bool | None = None,
        n_slots: int = 16,
        native: bool | None = None,
    ) -> None:
        if checkpoint.config.conditioning != "goal":
            raise ValueError(
                "this checkpoint is a Decision Transformer (return-to-go conditioning): it is a baseline for "
                "`gmt eval`, which runs it with model.evaluate_dt; the engine serves goal-conditioned models"
            )
        self.ckpt = checkpoint
        self.model = checkpoint.model.eval()
        self.cfg = checkpoint.config
        self.K = self.cfg.context_length
        self.n_goals = self.cfg.n_goals
        self.obs_size = int(np.prod(self.cfg.obs_shape))
        self.discrete = self.cfg.discrete_actions
        window = self.cfg.attention == "window"
        if incremental and not window:
            raise ValueError("the incremental path is exact only for attention='window' models")
        self.incremental = window if incremental is None else incremental
        noise = None if self.discrete else checkpoint.action_noise  # [n_goals, A] std or None
        # [n_goals, A] variance of the capped noise `sample` adds (interpolated during a blend).
        self.noise_var = None if noise is None else np.minimum(noise, SAMPLE_STD_CAP).astype(np.float64) ** 2
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
                raise ValueError(
                    f"checkpoint default_action_mode {default!r} is not one of {self.action_modes}"
                )
            self.action_modes = (default, *(m for m in self.action_modes if m != default))
        self._lock = threading.RLock()
        self.pool = SessionPool(self, n_slots)
        self._arange_h = np.arange(self.pool.H)
        self._native = self._native_step(native) if self.incremental else None

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
        return native_kernel.NativeStep(self.model, lib)

    def describe(self) -> RuntimeInfo:
        return RuntimeInfo(
            action_modes=self.action_modes,
            history_steps=self.pool.H,
            path="incremental" if self.incremental else "recompute",
            kernel="native" if self._native is not None else "torch",
        )

    @property
    def default_action_mode(self) -> str:
        return self.action_modes[0]

    # ----- contexts -----------------------------------------------------------------------------------------
    def check_goal(self, goal: int) -> None:
        """Raise ValueError for a goal id outside the goal table."""
        if (
            isinstance(goal, bool)
            or not isinstance(goal, int | np.integer)
            or not 0 <= int(goal) < self.n_goals
        ):
            raise ValueError(f"goal {goal!r} is not a goal id of this model (0..{self.n_goals - 1})")

    def _check_mode(self, action_mode: str | None) -> str:
        action_mode = action_mode or self.default_action_mode
        if action_mode not in self.action_modes:
            raise ValueError(
                f"action_mode must be one of {self.action_modes} for this model, got {action_mode!r}"
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
        mode = self._check_mode(action_mode)
        if seed is None:
            seed = secrets.randbits(63)
        slot = self._slot_for(key)
        p = self.pool
        p.goal[slot] = p.blend_from[slot] = goal
        p.step[slot] = p.blend_steps[slot] = p.blend_done[slot] = p.version[slot] = 0
        p.mode[slot], p.seed[slot] = MODES.index(mode), int(seed)
        if p.cache is not None:
            p.cache.clear(torch.tensor([slot]))
        return Context(p, slot, key)

    @_locked
    def release(self, ctx: Context) -> None:
        p = self.pool
        if ctx.key is not None and p.keys.get(ctx.key) == ctx.slot:
            del p.keys[ctx.key]
        p.release(ctx.slot)

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

    @_locked
    def set_goal(self, ctx: Context, goal: int, blend_steps: int = 0) -> None:
        self.check_goal(goal)
        if blend_steps < 0:
            raise ValueError(f"blend_steps must be >= 0, got {blend_steps}")
        p, s = self.pool, ctx.slot
        if blend_steps > 0 and goal != p.goal[s]:
            if ctx.blend_remaining == 0:
                p.blend_from[s] = p.goal[s]
            p.blend_steps[s], p.blend_done[s] = blend_steps, 0
        else:
            p.blend_from[s], p.blend_steps[s], p.blend_done[s] = goal, 0, 0
        p.goal[s] = goal
        p.version[s] += 1

    @_locked
    def from_stored(self, stored: StoredContext, key: str | None = None) -> Context:
        p = self.pool
        if key is not None and key in p.keys and p.version[p.keys[key]] == stored.version:
            slot = p.keys[key]
            if p.step[slot] == stored.step:
                return Context(p, slot, key)
        self.check_goal(stored.goal)
        self.check_goal(stored.blend_from)
        mode = self._check_mode(stored.action_mode)
        n = stored.size
        if n != min(stored.step, p.H) or len(stored.states) != n or len(stored.actions) != n:
            raise ValueError(
                f"stored context holds {n} steps; step {stored.step} needs {min(stored.step, p.H)}"
            )
        self._check_stored_tokens(stored, n)
        slot = self._slot_for(key)
        for name in ("goal", "step", "blend_from", "blend_steps", "blend_done", "seed", "version"):
            getattr(p, name)[slot] = getattr(stored, name)
        p.mode[slot] = MODES.index(mode)
        pos = np.arange(stored.step - n, stored.step) % p.H
        p.h_goal[slot, pos] = stored.goals
        p.h_blend_to[slot, pos] = stored.blend_to
        p.h_blend_w[slot, pos] = stored.blend_w
        p.h_state[slot, pos] = stored.states.reshape(n, *self.cfg.obs_shape)
        p.h_action[slot, pos] = stored.actions
        if p.cache is not None:
            self._rebuild_cache(slot)
        return Context(p, slot, key)

    def _check_stored_tokens(self, stored: StoredContext, n: int) -> None:
        """Raise ValueError unless every stored id and weight is one the model can embed (a corrupt store record
        must fail cleanly, never index outside a table)."""
        goals, blend_to = np.asarray(stored.goals), np.asarray(stored.blend_to)
        w = np.asarray(stored.blend_w, dtype=np.float64)
        if goals.size != n or blend_to.size != n or w.size != n:
            raise ValueError(f"stored context must hold {n} goals, blend targets and blend weights")
        for name, ids in (("goals", goals), ("blend_to", blend_to)):
            if ids.size and (ids.dtype.kind not in "iu" or ids.min() < 0 or ids.max() >= self.n_goals):
                raise ValueError(f"stored {name} must be goal ids 0..{self.n_goals - 1}")
        if w.size and not (np.isfinite(w).all() and w.min() >= 0.0 and w.max() <= 1.0):
            raise ValueError("stored blend weights must be in [0, 1]")
        if not 0 <= stored.step < 2**40:
            raise ValueError(f"stored step {stored.step} is out of range")
        if self.discrete:
            a = np.asarray(stored.actions)
            if a.size and (a.dtype.kind not in "iu" or a.min() < 0 or a.max() >= self.cfg.act_dim):
                raise ValueError(f"stored actions must be action ids 0..{self.cfg.act_dim - 1}")
        elif not np.isfinite(np.asarray(stored.actions, dtype=np.float64)).all():
            raise ValueError("stored actions must be finite")

    @torch.inference_mode()
    def _rebuild_cache(self, slot: int) -> None:
        """Recompute a slot's key/value cache from its history (a session adopted from a store).

        With the native step the stored steps are replayed through it (the kernel that computed the cache in
        the first place, so the session continues bit for bit); else by one reference forward over them.
        """
        p, cache = self.pool, self.pool.cache
        sl = torch.tensor([slot])
        cache.clear(sl)
        t = int(p.step[slot])
        n = min(t, p.H)
        if n == 0:
            return
        if self._native is not None:
            self._replay_cache(slot, t, n)
            return
        pos = np.arange(t - n, t) % p.H
        kv: list = []
        self.model(
            torch.from_numpy(p.h_goal[slot, pos][None]),
            torch.from_numpy(p.h_state[slot, pos][None]),
            torch.from_numpy(p.h_action[slot, pos][None]),
            torch.arange(t - n, t)[None],
            torch.ones(1, n, dtype=torch.bool),
            torch.from_numpy(p.h_blend_to[slot, pos][None]),
            torch.from_numpy(p.h_blend_w[slot, pos][None]),
            last_only=True,
            kv_out=kv,
        )
        keep = min(n, self.K + 1) * 3  # tokens of the last K + 1 steps
        tok = torch.arange(3 * (t - n), 3 * t)[-keep:]  # [keep] token indices
        ring = tok % cache.width
        for layer, (k, v) in enumerate(kv):
            cache.write(layer, slot, ring, k[0, -keep:], v[0, -keep:])
        cache.tok[slot, ring] = tok

    def _replay_cache(self, slot: int, t: int, n: int) -> None:
        """Run the stored steps t - n .. t - 1 of `slot` through the native step, oldest first.

        The action before the oldest stored step is not stored: a zero stands in for it, which changes only
        keys that no later step attends to (the stored history spans the receptive field).
        """
        p = self.pool
        slots = np.array([slot])
        for s in range(t - n, t):
            pos = s % p.H
            prev = p.h_action[slot, (s - 1) % p.H][None] if s > t - n else np.zeros_like(p.h_action[slot, :1])
            w = p.h_blend_w[slot, pos : pos + 1]
            self._native(
                prev,
                p.h_goal[slot, pos : pos + 1],
                p.h_state[slot, pos : pos + 1],
                np.array([s]),
                p.cache,
                slots,
                p.h_blend_to[slot, pos : pos + 1],
                w,
            )

    # ----- observations -------------------------------------------------------------------------------------
    def prepare_observation(self, obs: np.ndarray | list) -> np.ndarray:
        """Validate one raw observation and return it normalised in the model's shape.

        Raises:
            InvalidObservation: wrong number of values, non-numeric or non-finite values (also after
                normalisation, which can overflow float32).
        """
        try:
            x = np.asarray(obs)
        except (ValueError, TypeError) as e:
            raise InvalidObservation(f"observation is not a rectangular numeric array: {e}") from e
        if x.dtype == bool:
            raise InvalidObservation("observation must hold numbers, got booleans")
        if x.dtype == object or not np.issubdtype(x.dtype, np.number):
            raise InvalidObservation(f"observation must be numeric, got dtype {x.dtype}")
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
        self, contexts: list[Context], observations: list, prepared: bool = False
    ) -> list[np.ndarray | int | Exception]:
        """One step for each context: predict from the history plus the observation, then commit.

        Args:
            contexts: The sessions' contexts (each at most once in a batch).
            observations: One observation per context: raw, or the output of `prepare_observation`.
            prepared: Whether `observations` are already prepared.

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
        slots = np.fromiter((c.slot for c in contexts), dtype=np.int64, count=len(contexts))
        if len(slots) > 1 and len(np.unique(slots)) != len(slots):
            raise ValueError("a context may appear once per batch")
        actions, ok = self._step(slots, np.stack(states))
        for j, i in enumerate(rows):
            out[i] = (
                actions[j]
                if ok[j]
                else StepFailed(
                    "the model produced a non-finite action for this observation; the session is unchanged"
                )
            )
        return out

    def _step(self, slots: np.ndarray, states: np.ndarray) -> tuple[list, np.ndarray]:
        p = self.pool
        if self._native is not None and not self.discrete:  # all of it in one native call
            taken, ok = self._native.act(p, slots, states, self.noise_var, MODES.index("sample"))
            return list(self.ckpt.action_codec.decode(taken)), ok
        t = p.step[slots]  # [B]
        blending = p.blend_steps[slots] > p.blend_done[slots]  # [B]
        goal = p.goal[slots]
        g = np.where(blending, p.blend_from[slots], goal)  # [B] goal token
        w = np.where(blending, (p.blend_done[slots] + 1) / np.maximum(p.blend_steps[slots], 1), 0.0).astype(
            np.float32
        )  # [B] weight of `goal` in the token
        if self._native is not None:
            pred = self._predict_native(slots, t, g, goal, w, states)
        else:
            with torch.inference_mode():
                if self.incremental:
                    pred = self._predict_incremental(slots, t, g, goal, w, states)
                else:
                    pred = self._predict_recompute(slots, t, g, goal, w, states)
                pred = pred.float().numpy()  # [B, A]
        ok = np.isfinite(pred).all(axis=1)  # [B]
        every = bool(ok.all())
        if not every:
            pred = np.where(ok[:, None], pred, 0.0)
        taken, env_actions = self._choose(pred, slots, t, g, goal, w)
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

    def _predict_native(self, slots, t, g, goal, w, states) -> np.ndarray:
        """The incremental step by the native kernel: batch invariant by construction, so no lone-row or
        slot-order handling. Returns [B, A] float32."""
        p = self.pool
        prev = p.h_action[slots, (t - 1) % p.H]  # [B, A] (junk where t == 0)
        prev[t == 0] = 0
        blend = bool((w > 0).any())
        return self._native(prev, g, states, t, p.cache, slots, goal if blend else None, w if blend else None)

    def _predict_incremental(self, slots, t, g, goal, w, states) -> torch.Tensor:
        n = len(slots)
        if n % TORCH_ROW_MULTIPLE:
            # The BLAS kernel behind a matrix product depends on its row count, and a row's last bit on the
            # kernel: one row takes a GEMV path, and on AVX-512 here the rows past a multiple of 4 take another
            # micro-kernel. Padding every batch to a multiple of 8 rows (repeats of the last row: same slot,
            # same values) keeps batched == unbatched exact.
            pad = np.concatenate([np.arange(n), np.full(-n % TORCH_ROW_MULTIPLE, n - 1)])
            return self._predict_incremental(*[x[pad] for x in (slots, t, g, goal, w, states)])[:n]
        if (
            np.diff(slots) < 0
        ).any():  # rows in slot order: consecutive slots are read from the cache as views
            order = np.argsort(slots, kind="stable")
            sorted_rows = [x[order] for x in (slots, t, g, goal, w, states)]
            out = self._predict_incremental(*sorted_rows)
            return out[torch.from_numpy(np.argsort(order))]
        p = self.pool
        prev = p.h_action[slots, (t - 1) % p.H]  # [B, A] (junk where t == 0)
        prev[t == 0] = 0
        blend = bool((w > 0).any())
        return self.model.step(
            torch.from_numpy(prev),
            torch.from_numpy(g),
            torch.from_numpy(states),
            torch.from_numpy(t),
            p.cache,
            torch.from_numpy(slots),
            torch.from_numpy(goal) if blend else None,
            torch.from_numpy(w) if blend else None,
        )

    def _predict_recompute(self, slots, t, g, goal, w, states) -> torch.Tensor:
        p, H = self.pool, self.pool.H
        idx = t[:, None] - H + 1 + self._arange_h[None, :]  # [B, H] timesteps of the window
        valid = idx >= 0  # [B, H]
        pos = idx % H
        rows = slots[:, None]
        goals, blend_to, blend_w = p.h_goal[rows, pos], p.h_blend_to[rows, pos], p.h_blend_w[rows, pos]
        st, ac = p.h_state[rows, pos], p.h_action[rows, pos]  # [B, H, *obs], [B, H, A]
        goals[:, -1], blend_to[:, -1], blend_w[:, -1], st[:, -1], ac[:, -1] = g, goal, w, states, 0
        pad = ~valid
        goals[pad], blend_to[pad], blend_w[pad], st[pad], ac[pad] = 0, 0, 0, 0, 0
        blend = bool((blend_w > 0).any())
        pred, _ = self.model(
            torch.from_numpy(goals),
            torch.from_numpy(st),
            torch.from_numpy(ac),
            torch.from_numpy(np.where(valid, idx, 0)),
            torch.from_numpy(valid),
            torch.from_numpy(blend_to) if blend else None,
            torch.from_numpy(blend_w) if blend else None,
            last_only=True,
        )
        return pred[:, 0]  # [B, A]

    def _choose(self, pred: np.ndarray, slots, t, g, goal, w) -> tuple[np.ndarray, list]:
        """Actions of every row at once: (model-space actions to store [B, A] or ids [B], env actions)."""
        p = self.pool
        mode = p.mode[slots]
        seed = p.seed[slots]
        if self.discrete:
            z = pred.astype(np.float64)  # [B, n] logits
            ids = z.argmax(axis=1)
            stoch = mode != MODES.index("argmax")
            if stoch.any():
                expert = (mode == MODES.index("expert"))[:, None]
                thr = np.quantile(z, EXPERT_QUANTILE, axis=1, keepdims=True)
                z = np.where(expert & (z < thr), -math.inf, z)
                prob = np.exp(z - z.max(axis=1, keepdims=True))
                cdf = np.cumsum(prob / prob.sum(axis=1, keepdims=True), axis=1)
                u = uniforms(seed, t, 1)  # [B, 1]
                drawn = np.minimum((cdf < u).sum(axis=1), z.shape[1] - 1)
                ids = np.where(stoch, drawn, ids)
            return ids, [int(a) for a in ids]
        a = pred
        sample = mode == MODES.index("sample")
        if sample.any():
            var = (1.0 - w[:, None]) * self.noise_var[g] + w[:, None] * self.noise_var[goal]  # [B, A]
            noise = np.sqrt(var) * normals(seed, t, a.shape[1])
            a = np.where(sample[:, None], a + noise, a)
        a = np.clip(a, -1.0, 1.0).astype(np.float32)  # [B, A]
        return a, list(self.ckpt.action_codec.decode(a))
