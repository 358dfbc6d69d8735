"""The session pool: every live session of one engine as a slot of a few arrays (history ring, goal state,
key/value cache), so that one act over many sessions is a handful of array operations; and the checks that a
stored context fits those arrays before it is adopted into a slot.
"""

from __future__ import annotations

import ctypes

import numpy as np

from gmt.model.config import GMTConfig
from gmt.model.context import StoredContext
from gmt.model.kv_cache import KVCache
from gmt.model.sampling import MODES


def _return_freed_memory() -> None:
    """Ask glibc to give freed heap pages back to the OS (a no-op elsewhere): the pool's arrays were freed in
    several malloc arenas (the event loop's and the inference threads'), which glibc otherwise keeps."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class SessionPool:
    """Arrays of every live session of one engine, indexed by slot; grows by doubling, and reads a session's
    stored form into a slot (`check_stored`, `load`).

    Attributes:
        H: Steps of history kept per slot (a ring indexed by timestep mod H).
        modes: Names of the mode indices stored in `mode`.
        goal, step, blend_from, blend_steps, blend_done, mode, seed, version: [S] per-slot scalars.
        h_goal, h_blend_to: [S, H] goal tokens; h_blend_w: [S, H] blend weights.
        h_state: [S, H, *obs_shape] normalised states; h_action: [S, H, A] (or [S, H] ids) actions taken.
        cache: the key/value cache (incremental path only), on `device` (allocated there for `n_slots` sessions
            up front: size the pool for the sessions expected, so that it rarely grows).
    """

    SCALARS = ("goal", "step", "blend_from", "blend_steps", "blend_done", "mode", "seed", "version")

    def __init__(self, cfg: GMTConfig, incremental: bool, n_slots: int = 16, device: str = "cpu") -> None:
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
        self._cfg, self._incremental, self._initial, self._device = cfg, incremental, n_slots, device
        self.generation = 0  # changes whenever the arrays are replaced (native code holds their addresses)
        self._allocate_arrays(n_slots)
        self.keys: dict[str, int] = {}

    def _allocate_arrays(self, n_slots: int) -> None:
        for name, (shape, dtype) in self._layout.items():
            setattr(self, name, np.zeros((n_slots, *shape), dtype=dtype))
        self.cache = KVCache(self._cfg, n_slots, self._device) if self._incremental else None
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

    def check_stored(self, stored: StoredContext) -> None:
        """Raise ValueError unless `stored` fits this pool: as many steps as its step keeps, and every stored id and
        weight one the model can embed (a corrupt store record must fail cleanly, never index outside a table)."""
        cfg, n = self._cfg, stored.size
        if n != min(stored.step, self.H) or len(stored.states) != n or len(stored.actions) != n:
            raise ValueError(
                f"stored context holds {n} steps; step {stored.step} needs {min(stored.step, self.H)}"
            )
        goals, blend_to = np.asarray(stored.goals), np.asarray(stored.blend_to)
        w = np.asarray(stored.blend_w, dtype=np.float64)
        if goals.size != n or blend_to.size != n or w.size != n:
            raise ValueError(f"stored context must hold {n} goals, blend targets and blend weights")
        for name, ids in (("goals", goals), ("blend_to", blend_to)):
            if ids.size and (ids.dtype.kind not in "iu" or ids.min() < 0 or ids.max() >= cfg.n_goals):
                raise ValueError(f"stored {name} must be goal ids 0..{cfg.n_goals - 1}")
        if w.size and not (np.isfinite(w).all() and w.min() >= 0.0 and w.max() <= 1.0):
            raise ValueError("stored blend weights must be in [0, 1]")
        if not 0 <= stored.step < 2**40:
            raise ValueError(f"stored step {stored.step} is out of range")
        if cfg.discrete_actions:
            a = np.asarray(stored.actions)
            if a.size and (a.dtype.kind not in "iu" or a.min() < 0 or a.max() >= cfg.act_dim):
                raise ValueError(f"stored actions must be action ids 0..{cfg.act_dim - 1}")
        elif not np.isfinite(np.asarray(stored.actions, dtype=np.float64)).all():
            raise ValueError("stored actions must be finite")

    def load(self, slot: int, stored: StoredContext, mode: str) -> None:
        """Write a stored context (checked by `check_stored`) into `slot`, its action mode `mode`; the slot's
        key/value cache is left for the engine to rebuild."""
        n = stored.size
        for name in ("goal", "step", "blend_from", "blend_steps", "blend_done", "seed", "version"):
            getattr(self, name)[slot] = getattr(stored, name)
        self.mode[slot] = MODES.index(mode)
        pos = np.arange(stored.step - n, stored.step) % self.H
        self.h_goal[slot, pos] = stored.goals
        self.h_blend_to[slot, pos] = stored.blend_to
        self.h_blend_w[slot, pos] = stored.blend_w
        self.h_state[slot, pos] = stored.states.reshape(n, *self._cfg.obs_shape)
        self.h_action[slot, pos] = stored.actions
